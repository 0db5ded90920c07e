"""The range fit's fast paths equal their plain forms bit for bit: the grid least squares solved only inside the
backscatter prior's band, and the per-bin group statistics built for every bin at once."""

from __future__ import annotations

import numpy as np
import pytest

from seasynth.service.calibration import fit
from seasynth.service.calibration.estimate import srgb8_to_linear_table
from tests.test_calibration import photo


def plain_range_data(work: fit.Work, idx: np.ndarray):
    """Group means (3, GROUPS, bins) and range histograms (3, GROUPS, bins, Z) bin by bin, channel by channel."""
    fin = idx[work.bin[idx] >= 0]
    ys, hs = [], []
    for k in range(fit.RANGE_BINS):
        sel = fin[work.bin[fin] == k]
        n = sel.size
        if n < fit.MIN_BIN_PIXELS:
            continue
        groups = np.arange(n) * fit.GROUPS // n
        counts = np.bincount(groups, minlength=fit.GROUPS)
        yk, hk = np.empty((3, fit.GROUPS)), np.empty((3, fit.GROUPS, fit.Z_NODES))
        for c in range(3):
            s = sel[np.argsort(work.rank[sel, c], kind="stable")]
            yk[c] = np.bincount(groups, weights=work.lin[s, c], minlength=fit.GROUPS) / counts
            at, f = groups * fit.Z_NODES + work.node[s], work.node_frac[s]
            size = fit.GROUPS * fit.Z_NODES
            hk[c] = (np.bincount(at, 1 - f, size) + np.bincount(at + 1, f, size + 1)[:-1]).reshape(
                fit.GROUPS, fit.Z_NODES) / counts[:, None]
        ys.append(yk)
        hs.append(hk)
    return np.stack(ys, axis=2), np.stack(hs, axis=2)


def restrict_ratio(sse: np.ndarray, bd: np.ndarray, bb: np.ndarray) -> np.ndarray:
    """The plain form of the prior's band: sse (nD, nB) with grid points outside BACKSCATTER_PRIOR set to +inf."""
    r = bb[None, :] / bd[:, None]
    return np.where((r >= fit.BACKSCATTER_PRIOR[0]) & (r <= fit.BACKSCATTER_PRIOR[1]), sse, np.inf)


@pytest.fixture(scope="module")
def work() -> fit.Work:
    img, z = photo(sigma=0.01)
    z = z.copy()
    z[:40, :60] = np.nan  # unknown range
    return fit.Work.build(img, z, srgb8_to_linear_table())


def test_group_statistics_of_every_bin_at_once_equal_the_bin_by_bin_ones_bit_for_bit(work):
    rng = np.random.default_rng(5)
    draws = [np.arange(work.lin.shape[0]), work.resample(rng), work.resample(rng),
             # every pixel of the nearer half of the bins, too few of each farther one (under MIN_BIN_PIXELS)
             np.concatenate([np.flatnonzero(work.bin == k)[: None if k < 8 else fit.MIN_BIN_PIXELS - 1]
                             for k in range(fit.RANGE_BINS)])]
    sparse_bins, kept_bins = 0, 0
    for idx in draws:
        got = work.range_data(idx)
        y, h = plain_range_data(work, idx)
        np.testing.assert_array_equal(got.y, y)
        np.testing.assert_array_equal(got.h, h)
        sparse_bins += fit.RANGE_BINS - got.bins
        kept_bins += got.bins
    assert sparse_bins == fit.RANGE_BINS // 2 and kept_bins == 3.5 * fit.RANGE_BINS


def test_the_grid_fit_inside_the_backscatter_band_equals_the_full_grid_restricted_bit_for_bit(work, monkeypatch):
    data = work.range_data()
    c = 1
    args = (data.y[c], data.h[c], data.z_nodes)
    grids = [(fit.BETA_GRID, fit.BETA_GRID), (np.geomspace(0.03, 0.05, 41), np.geomspace(0.01, 0.2, 41)),
             (np.geomspace(0.5, 0.6, 7), np.geomspace(0.001, 0.01, 9))]  # the last: no point inside the band
    for bd, bb in grids:
        band, B_band = fit.grid_sse(*args, bd, bb, 0.2, 32.0)
        with monkeypatch.context() as m:
            m.setattr(fit, "BACKSCATTER_PRIOR", None)
            full, B_full = fit.grid_sse(*args, bd, bb, 0.2, 32.0)
        np.testing.assert_array_equal(band, restrict_ratio(full, bd, bb))
        inside = np.isfinite(band)
        np.testing.assert_array_equal(B_band[inside], B_full[inside])
        assert (B_band[~inside] == 0).all()
    assert not np.isfinite(band).any()
