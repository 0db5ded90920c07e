"""The sensor: what turns the light on each pixel into recorded values (spec `noise`), in this order:

1. exposure and gain: the linear image times 2^exposure_ev (or the automatic exposure's scale) times gain;
2. photon noise: at gain g a value of 1 is full_well_e / g electrons, drawn Poisson (variance value * g / full_well_e);
3. read noise: read_noise_e electrons RMS, Gaussian, amplified by the gain like the signal; then gaussian_sigma,
   additive in linear light (its own draw from the frame's noise stream, as before the sensor model);
4. white balance: per-channel multipliers, fixed or gray-world (the exposed image's channel means made equal);
5. clip to [0, 1]: a full well saturates, and no value is negative.

gaussian_sigma alone keeps its own record (meta's "noise") and is exactly what it was; the rest records under meta's
"optics" as "sensor" and draws from the frame's sensor stream. Automatic exposure meters the image as it will be
recorded without noise: the scale s that makes the mean over pixels and channels of clip(s * gain * wb * image, 0, 1)
equal to the target, solved exactly (the mean is piecewise linear in s).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from seasynth.service.seeds import STREAM_NOISE, STREAM_SENSOR, frame_rng
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.service.spec.lens import Noise
from seasynth.worker.optics.base import Plain, Shot
from seasynth.worker.render import RenderResult

SATURATE = 1.0 + 1e-6
# The most an exposure scales the light: times float32's largest value and the largest gain it is still finite in
# float64, so no exposed pixel is inf (which a zero pixel or white balance would make NaN).
MAX_SCALE = 1e200
POISSON_EXACT = 2.0**50  # electrons: sqrt(n) / n = 3e-8 there, under float32's 6e-8 steps


def gray_world(image: np.ndarray) -> np.ndarray:
    """(3,) float64 multipliers that make the channel means of image ((h, w, 3) linear) equal to their mean (a
    channel whose mean is 0 keeps 1)."""
    means = image.reshape(-1, 3).mean(axis=0, dtype=np.float64)
    target = means.mean()
    return np.where(means > 0, target / np.where(means > 0, means, 1.0), 1.0)


def metered_scale(values: np.ndarray, target: float) -> float:
    """The s >= 0 with mean(clip(s * values, 0, 1)) == target, values >= 0 (any shape); the mean is piecewise
    linear in s: with the k smallest values unclipped it is (s C_k + n - k) / n, C_k their sum. When the target is
    out of reach (at least as many values are 0 as the target leaves dark), s saturates every nonzero value (a
    margin over the smallest's reciprocal so that float32 products reach 1 too). At most MAX_SCALE: a value metered
    below 1 / MAX_SCALE (a white balance of 5e-324 on one channel) is left short of its target rather than the
    scale made inf."""
    # sorted in the values' own precision (float32 sorts much faster), then widened: the same numbers as float64's
    v = np.sort(np.maximum(values.reshape(-1), 0)).astype(np.float64)
    n = v.size
    c = np.cumsum(v)
    k = np.arange(1, n + 1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # c may be subnormal: s inf, never ok
        s = (n * target - (n - k)) / c
        above = np.append(v[1:], np.inf)  # the smallest clipped value for each k
        ok = (c > 0) & (s >= 0) & (s * v <= 1.0 + 1e-12) & (s * above >= 1.0 - 1e-12)
    if ok.any():
        return min(float(s[np.argmax(ok)]), MAX_SCALE)
    nonzero = v[v > 0]
    return min(SATURATE / float(nonzero.min()), MAX_SCALE) if nonzero.size else 1.0


def wb_multipliers(noise: Noise, image: np.ndarray) -> np.ndarray:
    """(3,) float64: the white balance's multipliers for this linear image."""
    if noise.white_balance is None:
        return np.ones(3)
    if noise.white_balance == "gray_world":
        return gray_world(image)
    return np.asarray(noise.white_balance, dtype=np.float64)


def photon_read_noise(signal: np.ndarray, full_well_e: float, read_noise_e: float, gain: float,
                      rng: np.random.Generator) -> np.ndarray:
    """(h, w, 3) float64: the exposed signal ((h, w, 3) linear, >= 0 expected) as the sensor counts it: Poisson
    electrons (full_well_e / gain per unit), plus Gaussian read noise in electrons, back in linear units.

    The electrons are counted from the signal before the gain (signal / gain * full_well_e), never through
    full_well_e / gain, which overflows to inf for a gain as small as 5e-324 (and 0 signal times inf is NaN). Past
    POISSON_EXACT electrons a pixel counts its mean: Poisson's relative spread there is below float32's resolution,
    and numpy refuses means past about 9.2e18 (a pixel 1e12 times its full well, as lighting at its caps gives)."""
    mean = np.maximum(signal.astype(np.float64), 0.0) / gain * full_well_e
    exact = mean > POISSON_EXACT
    electrons = rng.poisson(np.where(exact, 0.0, mean)).astype(np.float64)
    electrons[exact] = mean[exact]
    if read_noise_e > 0:
        electrons += rng.normal(0.0, read_noise_e, signal.shape)
    return electrons * gain / full_well_e


class Sensor(Plain):
    name = "noise"

    def on(self, spec: DatasetSpec) -> bool:
        return spec.noise.gaussian_sigma > 0 or spec.noise.sensor_on

    def prepare(self, shot: Shot) -> None:
        shot.float_image = True

    def develop(self, shot: Shot, result: RenderResult) -> RenderResult:
        noise = shot.spec.noise
        image = result.image
        if noise.sensor_on:
            wb = wb_multipliers(noise, image)
            scale = 2.0 ** noise.exposure_ev
            if noise.auto_exposure is not None:
                scale = metered_scale(image.astype(np.float64) * (wb * noise.gain), noise.auto_exposure)
            # float64 until the clip: an exposure that lifts a dark frame (auto_exposure over values near float32's
            # least, scale up to 1e45) or a bright one times the gain overflows float32 to inf, and inf times a
            # zero pixel or a white balance of 5e-324 (0 in float32) is NaN.
            image = image.astype(np.float64) * (scale * noise.gain)
            if noise.full_well_e is not None:
                image = photon_read_noise(image, noise.full_well_e, noise.read_noise_e, noise.gain,
                                          frame_rng(shot.spec.seed, shot.index, STREAM_SENSOR))
            shot.record["sensor"] = {
                "exposure_scale": scale, "exposure_ev": math.log2(scale) if scale > 0 else None,
                "auto_exposure_target": noise.auto_exposure, "gain": noise.gain, "full_well_e": noise.full_well_e,
                "read_noise_e": noise.read_noise_e, "white_balance": wb.tolist()}
        sigma = noise.gaussian_sigma
        if sigma > 0:
            rng = frame_rng(shot.spec.seed, shot.index, STREAM_NOISE)
            image = image + rng.normal(0.0, sigma, result.image.shape).astype(np.float32)
            shot.record[self.name] = {"gaussian_sigma_linear": sigma}
        if noise.sensor_on:
            with np.errstate(over="ignore"):  # a pixel past float64's range is past the full well: the clip's 1
                image = np.clip(image * wb, 0.0, 1.0).astype(np.float32)
        return dataclasses.replace(result, image=image)
