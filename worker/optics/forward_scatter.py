"""Forward-scatter blur: a surface's light that reaches the camera after small-angle scattering arrives from slightly
wrong directions, so it is spread by a point spread function whose width grows with range, b and the phase function.

The physical light model attenuates a surface's light on its way to the camera by the diffuse K (the light scattered
forwards stays in the beam); of that, `J exp(-c r)` is unscattered and stays sharp, and `J (exp(-K r) - exp(-c r))`
was scattered at least once and is spread here. A turn by theta at a uniform place along the path moves the light's
apparent direction by (1 - s/r) theta, so after n turns the apparent direction's variance per axis is n <theta^2> / 6
(Fermi's small-angle relation, the one the lamps' spread uses), n = b r / (1 - exp(-b r)) the mean number of turns of
light scattered at least once. Only the Henyey-Greenstein phase function's small-angle turns (within
SMALL_ANGLE_RAD: 87% of them at g = 0.92, mean square 0.035 rad^2 against 0.19 over all) spread the image; a wider
turn sends light out of the pencil it left by more than the frame, and K counts it replaced by what the surfaces
around send in (docs/optics.md: spreading it too lost fidelity). The spread is a Gaussian of that variance centred
on the pixel the light left, applied in linear light as a scatter (each pixel's light spreads with its own range's
width), so no light is made or lost; the frame's edges reflect what would leave it. The path radiance
(backscatter) is left alone: it is smooth in the image already.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
from scipy import fft

from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.frame.formation import transmission
from seasynth.worker.light import Medium
from seasynth.worker.optics.base import Plain, Shot
from seasynth.worker.render import RenderResult

LEVEL_RATIO = math.sqrt(2.0)  # widths of neighbouring Gaussian levels; a pixel's kernel mixes two, in variance
FINEST_LEVEL_PX = 0.5  # the narrowest level above none: narrower kernels mix it with the unblurred image
SMALL_ANGLE_RAD = 0.5  # turns within it spread the image (sin within 4% of the angle); wider ones leave it


@functools.lru_cache(maxsize=64)
def phase_split(g: float) -> tuple[float, float]:
    """The Henyey-Greenstein phase function's small-angle part: (the share of scatterings that turn by less than
    SMALL_ANGLE_RAD, their mean square turn in rad^2), by quadrature over the scattering angle."""
    theta = np.linspace(0.0, SMALL_ANGLE_RAD, 100001)
    # (1 - g^2) / (1 + g^2 - 2 g mu)^1.5 integrates to 2 over mu in [-1, 1].
    pdf = (1.0 - g * g) / (1.0 + g * g - 2.0 * g * np.cos(theta)) ** 1.5 * np.sin(theta) / 2.0
    share = float(np.trapezoid(pdf, theta))
    return share, float(np.trapezoid(pdf * theta**2, theta) / share)


def scatter_events(b: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """Mean number of scatterings of the light scattered at least once over a path: x / (1 - exp(-x)), x = b r (1 at
    x = 0, rising with x). b: (3,) 1/m; range_m: (h, w) metres, finite. -> (h, w, 3) float64."""
    x = np.asarray(range_m, np.float64)[..., None] * np.asarray(b, np.float64)
    safe = np.where(x > 0, x, 1.0)
    return np.where(x > 0, safe / -np.expm1(-safe), 1.0)


def angular_variance(b: np.ndarray, g: float, range_m: np.ndarray) -> np.ndarray:
    """Variance per image axis (rad^2) of the apparent direction of the light scattered forwards over `range_m`:
    n share <theta^2> / 6 (n turns, the small-angle share of them, their mean square turn; half of it per axis
    and a third for where along the path a turn happens). b: (3,) 1/m; range_m: (h, w) metres, finite.
    -> (h, w, 3) float64."""
    share, mean_square = phase_split(float(g))
    return scatter_events(b, range_m) * (share * mean_square / 6.0)


def forward_part(clean: np.ndarray, range_m: np.ndarray, medium: Medium) -> np.ndarray:
    """The surface light that arrives after forward scattering: J (exp(-K r) - exp(-c r)). clean: (h, w, 3) float32
    linear in-air radiance J; range_m: (h, w) metres, +inf where no surface (there: 0). -> (h, w, 3) float32."""
    scattered = transmission(medium.k, range_m) - transmission(medium.c, range_m)
    np.maximum(scattered, 0.0, out=scattered)  # K <= c; guards rounding
    return clean.astype(np.float32) * scattered


def levels_px(max_sigma_px: float) -> np.ndarray:
    """Widths (pixels) of the Gaussian levels a frame needs: 0 (none), then FINEST_LEVEL_PX growing by LEVEL_RATIO up
    to the first at or past max_sigma_px. -> (L,) float64, L >= 2."""
    out = [0.0, FINEST_LEVEL_PX]
    while out[-1] < max_sigma_px:
        out.append(out[-1] * LEVEL_RATIO)
    return np.asarray(out)


def spread(light: np.ndarray, variance_px: np.ndarray, aspect: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's light spread by a Gaussian of its own variance, conserving the total (reflecting edges).

    light: (h, w, 3) float32, linear. variance_px: (h, w, 3) variance along x, pixels^2 (along y: aspect^2 times it;
    aspect = fy / fx). Each pixel's light is split between the two levels whose variances bracket its own (weights
    that keep its variance), every level is blurred once in the cosine domain (DCT-II: reflecting edges, the sum kept
    exactly), and the levels are summed before one inverse transform.
    Returns ((h, w, 3) float32, the levels used in pixels).
    """
    h, w, _ = light.shape
    lit = light != 0
    if not lit.any():
        return light.copy(), np.zeros(0)
    var = np.where(lit, variance_px, 0.0)
    sigmas = levels_px(math.sqrt(float(var.max())))
    level_var = sigmas**2
    lo = np.clip(np.searchsorted(level_var, var, side="right") - 1, 0, len(sigmas) - 2).ravel()
    t = np.clip((var.ravel() - level_var[lo]) / (level_var[lo + 1] - level_var[lo]), 0.0, 1.0)
    upper = t.astype(np.float32).reshape(light.shape)  # the upper level's share; the lower one has the rest
    lower_light, upper_light = (light * (1.0 - upper)).ravel(), (light * upper).ravel()
    # the pixels and channels by lower level: those of level k are order[first[k]:first[k + 1]]
    lo = lo.astype(np.int16)  # levels_px's levels number far fewer than 2^15; a radix sort's small integers
    order = np.argsort(lo, kind="stable")
    first = np.searchsorted(lo[order], np.arange(len(sigmas) + 1))
    # the squared angular frequency's Gaussian, exp(-sigma^2 (aspect^2 wy^2 + wx^2) / 2), is separable
    wy = (np.pi * np.arange(h) / h) ** 2
    wx = (np.pi * np.arange(w) / w) ** 2
    total = None
    used = []
    for k in range(len(sigmas)):
        below, above = order[first[k]:first[k + 1]], order[first[k - 1]:first[k]] if k > 0 else order[:0]
        if below.size == 0 and above.size == 0:
            continue
        # this level's share of each pixel and channel's light: the lower share of those whose lower level is k,
        # the upper share of those whose upper level it is
        part = np.zeros(light.size, np.float32)
        part[below] = lower_light[below]
        part[above] = upper_light[above]
        part = part.reshape(light.shape)
        if not part.any():
            continue
        spectrum = fft.dctn(part, type=2, axes=(0, 1), norm="ortho")
        sigma = sigmas[k]
        if sigma > 0:
            gain = np.exp(-0.5 * sigma**2 * aspect**2 * wy)[:, None] * np.exp(-0.5 * sigma**2 * wx)[None, :]
            spectrum *= gain.astype(np.float32)[..., None]
        total = spectrum if total is None else total + spectrum
        used.append(float(sigma))
    out = fft.idctn(total, type=2, axes=(0, 1), norm="ortho")
    return out.astype(np.float32, copy=False), np.asarray(used)


def forward_scatter(image: np.ndarray, clean: np.ndarray, range_m: np.ndarray, medium: Medium,
                    fx: float, fy: float) -> tuple[np.ndarray, np.ndarray]:
    """The formed image with its surfaces' forward-scattered light spread: image - F + spread(F), F = forward_part.

    image, clean: (h, w, 3) float32 linear (formed and in-air); range_m: (h, w) metres, +inf where no surface;
    fx, fy: focal lengths in pixels. Where F is 0 everywhere (b = 0, zero range, K = c) the image is returned as
    is. Returns ((h, w, 3) float32, the Gaussian levels used in pixels).
    """
    part = forward_part(clean, range_m, medium)
    if not part.any():
        return image, np.zeros(0)
    finite = np.where(np.isfinite(range_m), range_m, 0.0)
    variance_px = angular_variance(medium.b, medium.g, finite) * fx**2
    spread_part, used = spread(part, variance_px, fy / fx)
    return image - part + spread_part, used


class ForwardScatter(Plain):
    name = "forward_scatter"

    def on(self, spec: DatasetSpec) -> bool:
        return spec.water.forward_scatter

    def prepare(self, shot: Shot) -> None:
        shot.float_image = True
        shot.needs |= {"clean", "range"}

    def develop(self, shot: Shot, result: RenderResult) -> RenderResult:
        medium = shot.scene.light.medium
        K = shot.render_view.K
        image, used = forward_scatter(result.image, result.clean, result.range_m, medium, K[0, 0], K[1, 1])
        g = float(medium.g)
        shot.record[self.name] = {
            "psf": "gaussian, small-angle multiple scattering",
            "variance_per_scattering_rad2": round(phase_split(g)[0] * phase_split(g)[1] / 6.0, 8),
            "levels_px": [round(s, 4) for s in used.tolist()],
        }
        return dataclasses.replace(result, image=image)
