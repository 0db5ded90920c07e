"""The fits behind seasynth.service.calibration.estimate: per-range-bin group means, the (beta_D, beta_B) grid fit, and tile statistics
for photos without range. Free functions and small frozen records on numpy arrays."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RANGE_BINS = 16  # equal-count bins over the finite ranges
GROUPS = 2  # equal-count groups per bin and channel, ranked by the 8-neighbour mean (2: darker and brighter half)
MIN_BIN_PIXELS = 40  # a bin (or the open water) with fewer pixels is left out
MIN_BINS = 4
TILES = 16  # the image is cut into TILES x TILES tiles: the bootstrap's unit and the no-range statistics' regions
BETA_GRID = np.geomspace(0.002, 10.0, 121)  # 1/m; a profile interval reaching either end is not identified
FINE_POINTS = 41
Z_NODES = 64  # log-spaced range nodes of the groups' range histograms
FLAT_CONTRAST = 0.02  # linear: a tile flatter than this (sqrt of summed variances) can be open water
WATER_TILE_SHARE = 0.05  # the flattest 5% of tiles (at least 3) give B_inf without range
DARK_SHARE = 0.10  # a tile's darkest 10% of pixels (by 8-neighbour luminance) are its dark pixels
MIN_DARK_TILES = 5
BACKSCATTER_PRIOR: tuple[float, float] | None = (0.5, 2.0)  # beta_B / beta_D allowed in the range fit
EDGE_RATIO = 1.1  # a pixel whose neighbours' range differs by more than 10% is left out of the range fit
FLAT_SPREAD = 1e-5  # linear: group means spanning less than this carry no attenuation


def range_edges(z: np.ndarray) -> np.ndarray:
    """(h, w) bool: pixels whose 8 neighbours' ranges differ from theirs by more than EDGE_RATIO (a NaN or an
    infinite neighbour beside a finite range counts): such pixels mix surfaces (or a surface and open water) and
    their range does not describe their colour. z: (h, w) float64 metres, +inf open water, NaN unknown."""
    p = np.pad(z, 1, mode="edge")
    h, w = z.shape
    edge = np.zeros(z.shape, bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        for i in range(3):
            for j in range(3):
                n = p[i:i + h, j:j + w]
                same_inf = np.isinf(n) & np.isinf(z)
                ratio = np.abs(np.log(n / z))
                edge |= ~same_inf & ~(ratio <= np.log(EDGE_RATIO))
    return edge


def neighbour_mean(x: np.ndarray) -> np.ndarray:
    """Mean of each pixel's 8 neighbours (edges replicated). x: (h, w, 3) float64 -> (h, w, 3) float64.

    Ranking pixels by it instead of their own value keeps a pixel's own noise out of the group it falls in, so
    group means of the raw values stay unbiased under zero-mean noise."""
    p = np.pad(x, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = x.shape[:2]
    total = sum(p[i:i + h, j:j + w] for i in range(3) for j in range(3))
    return (total - x) / 8.0


@dataclass(frozen=True)
class RangeData:
    """Group means for the range fit. y: (3, GROUPS, bins) float64, mean linear value of each channel's groups per
    bin; h: (3, GROUPS, bins, Z) float64, each group's share of pixels at range node z_nodes (Z,) metres (linear
    interpolation in log range), so a group's mean transmission is h @ exp(-beta z_nodes) with no bin-width error.
    open_mean: (3,) linear mean of the open-water pixels (zeros when none). drift: None, or (Z,) float64, a factor on
    J at each range node that the fits assume (the drift sensitivity's stated change of J with range)."""

    y: np.ndarray
    h: np.ndarray
    z_nodes: np.ndarray
    open_mean: np.ndarray
    open_pixels: int
    finite_pixels: int
    z_lo: float
    z_hi: float
    drift: np.ndarray | None = None

    @property
    def bins(self) -> int:
        return self.y.shape[2]

    def keep_bins(self, keep: np.ndarray) -> RangeData:
        """The same data restricted to the range bins `keep` ((bins,) bool); open water and spans unchanged."""
        return RangeData(self.y[:, :, keep], self.h[:, :, keep], self.z_nodes, self.open_mean, self.open_pixels,
                         self.finite_pixels, self.z_lo, self.z_hi, self.drift)

    def with_drift(self, log_factor: float) -> RangeData:
        """The same data, fitted as if J's mean were e^log_factor times larger at the far end of the range than at
        the near end (log-linear in ln z between them)."""
        s = np.linspace(-0.5, 0.5, self.z_nodes.size)
        return RangeData(self.y, self.h, self.z_nodes, self.open_mean, self.open_pixels, self.finite_pixels,
                         self.z_lo, self.z_hi, np.exp(log_factor * s))

    def direct(self, beta: np.ndarray) -> np.ndarray:
        """(n, Z): exp(-beta z) at the nodes for each beta (n,) 1/m, times the assumed drift of J (if any)."""
        t = np.exp(-np.outer(beta, self.z_nodes))
        return t if self.drift is None else t * self.drift


@dataclass(frozen=True)
class RangeFit:
    """(3,) float64 each: beta_D, beta_B (1/m), B_inf (linear); *_sigma: (3,) the fit's own 1-sigma (half the log
    width of the profile interval where SSE <= min + 4 residual variances, times the value); *_inside: (3,) bool,
    that interval inside the grid and the data not flat (B_inf_inside: open water seen, or beta_B inside)."""

    beta_D: np.ndarray
    beta_B: np.ndarray
    B_inf: np.ndarray
    beta_D_sigma: np.ndarray
    beta_B_sigma: np.ndarray
    beta_D_inside: np.ndarray
    beta_B_inside: np.ndarray
    B_inf_inside: np.ndarray


@dataclass(frozen=True)
class TileStats:
    """Per tile (n tiles): mean (n, 3) linear, contrast (n,) linear (sqrt of the summed per-channel variances of the
    8-neighbour means), dark (n, 3) mean linear of the darkest pixels, pixels (n,) int."""

    mean: np.ndarray
    contrast: np.ndarray
    dark: np.ndarray
    pixels: np.ndarray


@dataclass(frozen=True)
class NoRangeFit:
    """B_inf (3,) linear; water_flat: its tiles are flat; beta_B_ratio (3,) to green, NaN where unknown."""

    B_inf: np.ndarray
    water_flat: bool
    beta_B_ratio: np.ndarray
    dark_tiles: int
    pixels: int


@dataclass(frozen=True)
class Work:
    """The photo as flat pixel arrays (n pixels, saturated ones left out): lin, rank (n, 3) float64 linear value and
    8-neighbour mean; z (n,) metres (+inf open water, NaN unknown or on a range edge) or None; tile (n,) int; bin (n,)
    int (-1: no finite range); edges (RANGE_BINS + 1,) metres; z_nodes (Z_NODES,) metres; node (n,) int and
    node_frac (n,) float64: each pixel's range node and its weight on the next node; tile_pixels: pixel indices of
    each tile."""

    lin: np.ndarray
    rank: np.ndarray
    z: np.ndarray | None
    tile: np.ndarray
    bin: np.ndarray
    edges: np.ndarray
    z_nodes: np.ndarray
    node: np.ndarray
    node_frac: np.ndarray
    tile_pixels: tuple[np.ndarray, ...]
    saturated_share: float = 0.0  # of the pixels with a finite range, those with a channel at 255 (left out)

    @staticmethod
    def build(img: np.ndarray, z: np.ndarray | None, lut: np.ndarray) -> Work:
        """img: (h, w, 3) uint8 sRGB; z: (h, w) float64 as calibration._check_range gives; lut: (256,) decode."""
        h, w = img.shape[:2]
        lin = lut[img]
        rank = neighbour_mean(lin)
        rows = np.minimum(np.arange(h) * TILES // h, TILES - 1)
        cols = np.minimum(np.arange(w) * TILES // w, TILES - 1)
        tile = (rows[:, None] * TILES + cols[None, :]).reshape(-1)
        saturated = (img == 255).any(axis=2).reshape(-1)
        keep = ~saturated
        ranged = np.zeros(0, bool) if z is None else np.isfinite(z).reshape(-1)
        share = float(saturated[ranged].mean()) if ranged.any() else 0.0
        lin, rank, tile = lin.reshape(-1, 3)[keep], rank.reshape(-1, 3)[keep], tile[keep]
        # Pixels on range edges (mixed surfaces) take no part in the range fit: their range is set unknown.
        zf = None if z is None else np.where(range_edges(z), np.nan, z).reshape(-1)[keep]
        edges, nodes = np.zeros(0), np.ones(Z_NODES)
        bins = np.full(lin.shape[0], -1)
        node, frac = np.zeros(lin.shape[0], np.int64), np.zeros(lin.shape[0])
        if zf is not None:
            finite = np.isfinite(zf)
            if finite.sum() >= MIN_BINS * MIN_BIN_PIXELS:
                zfin = zf[finite]
                edges = np.quantile(zfin, np.linspace(0, 1, RANGE_BINS + 1))
                bins[finite] = np.clip(np.searchsorted(edges[1:-1], zfin, side="right"), 0, RANGE_BINS - 1)
                lo, hi = np.log(edges[0]), np.log(max(edges[-1], edges[0] * 1.001))
                nodes = np.exp(np.linspace(lo, hi, Z_NODES))
                pos = np.clip((np.log(zfin) - lo) / (hi - lo) * (Z_NODES - 1), 0, Z_NODES - 1 - 1e-9)
                node[finite] = np.floor(pos).astype(np.int64)
                frac[finite] = pos - node[finite]
        order = np.argsort(tile, kind="stable")
        splits = np.searchsorted(tile[order], np.arange(1, TILES * TILES))
        return Work(lin, rank, zf, tile, bins, edges, nodes, node, frac, tuple(np.split(order, splits)), share)

    def resample(self, rng: np.random.Generator) -> np.ndarray:
        """Pixel indices of TILES^2 tiles drawn with replacement (a tile bootstrap). -> (m,) int."""
        return np.concatenate([self.tile_pixels[t] for t in self.resample_tiles(rng)])

    def resample_tiles(self, rng: np.random.Generator) -> np.ndarray:
        return rng.integers(0, len(self.tile_pixels), len(self.tile_pixels))

    def range_data(self, idx: np.ndarray | None = None) -> RangeData:
        """Group means over the pixels `idx` (all when None)."""
        if idx is None:
            idx = np.arange(self.lin.shape[0])
        z = self.z[idx]
        open_ = idx[np.isinf(z) & (z > 0)]
        fin = idx[self.bin[idx] >= 0]
        # Every bin at once: per channel, the pixels sorted by bin and, within a bin, by their neighbours' mean
        # (stable: ties keep their order in idx), each bin cut into GROUPS equal-count groups ("cells").
        b = self.bin[fin]
        size = np.bincount(b, minlength=RANGE_BINS)
        keep = size >= MIN_BIN_PIXELS
        start = np.cumsum(size) - size
        cells = RANGE_BINS * GROUPS
        y = np.empty((3, RANGE_BINS, GROUPS))
        hh = np.empty((3, RANGE_BINS, GROUPS, Z_NODES))
        by_bin = np.split(fin[np.argsort(b, kind="stable")], np.cumsum(size)[:-1])
        bs = np.repeat(np.arange(RANGE_BINS), size)
        for c in range(3):
            s = np.concatenate([p[np.argsort(self.rank[p, c], kind="stable")] for p in by_bin])
            cell = bs * GROUPS + (np.arange(s.size) - start[bs]) * GROUPS // size[bs]
            counts = np.maximum(np.bincount(cell, minlength=cells), 1)
            y[c] = (np.bincount(cell, weights=self.lin[s, c], minlength=cells) / counts).reshape(RANGE_BINS, GROUPS)
            at, f = cell * Z_NODES + self.node[s], self.node_frac[s]
            hist = np.bincount(at, 1 - f, cells * Z_NODES) + np.bincount(at + 1, f, cells * Z_NODES + 1)[:-1]
            hh[c] = (hist.reshape(cells, Z_NODES) / counts[:, None]).reshape(RANGE_BINS, GROUPS, Z_NODES)
        y = y[:, keep].transpose(0, 2, 1)  # (3, GROUPS, bins)
        hh = hh[:, keep].transpose(0, 2, 1, 3)  # (3, GROUPS, bins, Z)
        ok = open_.size >= MIN_BIN_PIXELS
        zfin = self.z[fin]
        return RangeData(
            y=y, h=hh, z_nodes=self.z_nodes,
            open_mean=self.lin[open_].mean(axis=0) if ok else np.zeros(3),
            open_pixels=int(open_.size) if ok else 0,
            finite_pixels=int(fin.size),
            z_lo=float(zfin.min()) if fin.size else 0.0,
            z_hi=float(zfin.max()) if fin.size else 0.0,
        )

    def tile_data(self) -> TileStats:
        """Per-tile mean colour, contrast (of the 8-neighbour means) and darkest pixels' mean colour."""
        n = TILES * TILES
        count = np.bincount(self.tile, minlength=n).astype(np.float64)
        safe = np.maximum(count, 1)
        mean = np.stack([np.bincount(self.tile, self.lin[:, c], n) for c in range(3)], axis=1) / safe[:, None]
        rmean = np.stack([np.bincount(self.tile, self.rank[:, c], n) for c in range(3)], axis=1) / safe[:, None]
        rsq = np.stack([np.bincount(self.tile, self.rank[:, c] ** 2, n) for c in range(3)], axis=1) / safe[:, None]
        var = np.maximum(rsq - rmean**2, 0).sum(axis=1)
        contrast = np.sqrt(var)
        lum = self.rank.sum(axis=1)
        order = np.lexsort((lum, self.tile))
        t_sorted = self.tile[order]
        first = np.searchsorted(t_sorted, np.arange(n))
        pos = np.arange(order.size) - first[t_sorted]
        dark_px = order[pos < np.maximum(1, np.ceil(DARK_SHARE * count[t_sorted]))]
        td = self.tile[dark_px]
        dcount = np.maximum(np.bincount(td, minlength=n), 1).astype(np.float64)
        dark = np.stack([np.bincount(td, self.lin[dark_px, c], n) for c in range(3)], axis=1) / dcount[:, None]
        return TileStats(mean=mean, contrast=contrast, dark=dark, pixels=count.astype(np.int64))


def grid_sse(y, h, nodes, bd, bb, y_inf: float, w2: float, drift: np.ndarray | None = None):
    """Least squares of y_g = m_g <d exp(-bd z)>_g + B <1 - exp(-bb z)>_g (+ w2-weighted B = y_inf) over grids bd, bb,
    <.>_g the mean over group g's ranges (h: (G, K, Z) shares at nodes (Z,) metres), d the drift (Z,) (None: 1).

    y: (G, K). bd: (nD,), bb: (nB,) 1/m. The per-group m_g and B are solved in closed form (m_g eliminated by
    projection, B clipped to [0, 1]). Returns sse (nD, nB) and B (nD, nB); with BACKSCATTER_PRIOR, only the grid
    points inside it are solved (sse +inf and B 0 elsewhere): on log grids that is a band of a few columns a row."""
    direct = np.exp(-bd[:, None] * nodes[None])
    g, k, z = h.shape
    hz = h.reshape(g * k, z).T  # contractions as matrix products (BLAS): einsum's loops took 2/3 of an estimate
    t = ((direct if drift is None else direct * drift) @ hz).reshape(-1, g, k)  # (nD, G, K)
    u = (-np.expm1(-bb[:, None] * nodes[None]) @ hz).reshape(-1, g, k)  # (nB, G, K)
    stt = np.maximum((t * t).sum(-1), 1e-300)  # (nD, G)
    sty = (t * y).sum(-1)
    syy = (y * y).sum(-1)  # (G,)
    stu = (t.transpose(1, 0, 2) @ u.transpose(1, 2, 0)).transpose(1, 2, 0)  # (nD, nB, G)
    suu = (u * u).sum(-1)  # (nB, G)
    suy = (u * y).sum(-1)
    a = sty / stt  # (nD, G)
    yy = (syy[None] - sty * a).sum(-1)  # (nD,)
    rows, cols, inside = ratio_band(bd, bb)  # (nD, W) each: the grid points solved
    stu = stu[rows, cols]  # (nD, W, G)
    uy = (suy[cols] - stu * a[:, None, :]).sum(-1)  # (nD, W)
    uu = (suu[cols] - stu**2 / stt[:, None, :]).sum(-1)
    den = uu + w2
    Bw = np.clip(np.divide(uy + w2 * y_inf, den, out=np.zeros_like(den), where=den > 1e-300), 0.0, 1.0)
    ssew = np.maximum(yy[:, None] - 2 * Bw * uy + Bw**2 * uu + w2 * (y_inf - Bw) ** 2, 0.0)
    sse, B = np.full((bd.size, bb.size), np.inf), np.zeros((bd.size, bb.size))
    sse[rows[inside], cols[inside]] = ssew[inside]
    B[rows[inside], cols[inside]] = Bw[inside]
    return sse, B


def ratio_band(bd: np.ndarray, bb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (beta_D, beta_B) grid points a fit solves: per row of bd, the columns of bb (ascending) inside
    BACKSCATTER_PRIOR, as (rows, cols, inside) index arrays (nD, W), W the widest row's count (inside: False where a
    narrower row's columns are padding). No prior: every column."""
    n, m = bd.size, bb.size
    if BACKSCATTER_PRIOR is None:
        return np.repeat(np.arange(n)[:, None], m, 1), np.tile(np.arange(m), (n, 1)), np.ones((n, m), bool)
    r = bb[None, :] / bd[:, None]
    ok = (r >= BACKSCATTER_PRIOR[0]) & (r <= BACKSCATTER_PRIOR[1])  # (nD, nB): one run of columns a row
    first = np.argmax(ok, axis=1)
    count = ok.sum(axis=1)
    width = max(int(count.max()), 1)
    cols = np.minimum(first[:, None] + np.arange(width)[None, :], m - 1)
    inside = np.arange(width)[None, :] < count[:, None]
    return np.repeat(np.arange(n)[:, None], width, 1), cols, inside


def profile_width(prof: np.ndarray, grid: np.ndarray, threshold: float) -> tuple[float, bool]:
    """(1-sigma relative width, inside) of a profile over a log grid: the grid points whose profile is <= threshold
    span [lo, hi]; sigma = ln(hi / lo) / 4; inside: neither end of the grid is in the span."""
    ok = np.flatnonzero(prof <= threshold)
    return float(np.log(grid[ok[-1]] / grid[ok[0]]) / 4), bool(ok[0] > 0 and ok[-1] < grid.size - 1)


def residual_variance(sse: float, rows: int, y: np.ndarray) -> float:
    """A fit's residual variance per row (GROUPS + 3 parameters), floored at 8-bit quantisation's scale of y so a
    perfect fit still has a width."""
    return max(sse / max(rows - GROUPS - 3, 1), (1e-3 * max(float(np.abs(y).max()), 1e-3)) ** 2)


def fit_range(data: RangeData) -> RangeFit:
    """Per channel: coarse grid argmin, then a fine grid between the argmin's neighbours; profile widths from the
    coarse grid."""
    n = BETA_GRID.size
    out = {k: np.zeros(3) for k in ("bd", "bb", "B", "sd", "sb")}
    inside = {k: np.zeros(3, bool) for k in ("bd", "bb", "B")}
    has_open = data.open_pixels >= MIN_BIN_PIXELS
    rows = data.y[0].size
    w2 = float(rows) if has_open else 0.0
    for c in range(3):
        y, h = data.y[c], data.h[c]
        if y.shape[1] == 0:
            out["B"][c] = data.open_mean[c]
            inside["B"][c] = has_open
            continue
        y_inf = float(data.open_mean[c])
        sse, _ = grid_sse(y, h, data.z_nodes, BETA_GRID, BETA_GRID, y_inf, w2, data.drift)
        i, j = np.unravel_index(np.argmin(sse), sse.shape)
        fd = np.geomspace(BETA_GRID[max(i - 1, 0)], BETA_GRID[min(i + 1, n - 1)], FINE_POINTS)
        fb = np.geomspace(BETA_GRID[max(j - 1, 0)], BETA_GRID[min(j + 1, n - 1)], FINE_POINTS)
        sse2, B2 = grid_sse(y, h, data.z_nodes, fd, fb, y_inf, w2, data.drift)
        k, m = np.unravel_index(np.argmin(sse2), sse2.shape)
        flat = np.ptp(y) < FLAT_SPREAD
        var = residual_variance(float(sse2[k, m]), rows, y)
        threshold = max(float(sse2[k, m]), float(sse.min())) + 4 * var
        out["sd"][c], in_d = profile_width(sse.min(axis=1), BETA_GRID, threshold)
        out["sb"][c], in_b = profile_width(sse.min(axis=0), BETA_GRID, threshold)
        out["bd"][c], out["bb"][c], out["B"][c] = fd[k], fb[m], B2[k, m]
        out["sd"][c] *= fd[k]
        out["sb"][c] *= fb[m]
        inside["bd"][c] = in_d and not flat
        inside["bb"][c] = in_b and not flat
        inside["B"][c] = has_open or bool(inside["bb"][c])
    return RangeFit(out["bd"], out["bb"], out["B"], out["sd"], out["sb"], inside["bd"], inside["bb"], inside["B"])


def fit_no_range(stats: TileStats, tiles: np.ndarray | None = None) -> NoRangeFit:
    """B_inf from the flattest tiles, beta_B ratios from the other tiles' dark pixels. tiles: (m,) tile indices
    (a bootstrap draw, repeats allowed); None: every tile."""
    if tiles is None:
        tiles = np.arange(stats.pixels.size)
    full = stats.pixels.max()
    tiles = tiles[stats.pixels[tiles] >= max(1, full // 2)]  # tiles mostly unsaturated
    if tiles.size < 3:
        return NoRangeFit(np.zeros(3), False, np.full(3, np.nan), 0, 0)
    contrast = stats.contrast[tiles]
    k = max(3, int(np.ceil(WATER_TILE_SHARE * tiles.size)))
    water = tiles[np.argsort(contrast, kind="stable")[:k]]
    B = np.median(stats.mean[water], axis=0)
    flat = bool(np.median(stats.contrast[water]) <= FLAT_CONTRAST)
    rest = np.setdiff1d(tiles, water, assume_unique=False)
    rest = tiles[np.isin(tiles, rest)]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = stats.dark[rest] / B[None, :]
        ok = (frac > 0.02) & (frac < 0.98)  # (m, 3): dark pixels below the water's colour, and not black
        x = -np.log1p(-np.clip(frac, 0.0, 0.98))  # (m, 3): beta_B_c * z of each tile
        ratio = np.full(3, np.nan)
        for c in range(3):
            both = ok[:, c] & ok[:, 1]
            if both.sum() >= MIN_DARK_TILES:
                ratio[c] = np.median(x[both, c] / x[both, 1])
    return NoRangeFit(B, flat, ratio, int(ok[:, 1].sum()), int(stats.pixels[tiles].sum()))

