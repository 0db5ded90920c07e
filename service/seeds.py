"""Seeds: every random draw of frame i comes from one generator derived from (dataset seed, i)."""

import numpy as np

# Distinct streams derived from one frame's entropy; appended to the SeedSequence key so they never collide.
STREAM_SCENE = 0
STREAM_NOISE = 1
# Sensors' own streams (ASCII tags, like seasynth.worker.export's STREAM_SPLIT): switching a sensor on changes no other draw.
STREAM_FLS = 0x666C73  # "fls": forward-looking sonar speckle and noise
STREAM_SSS = 0x737373  # "sss": side-scan sonar speckle and noise
STREAM_NAV = 0x6E6176  # "nav": DVL, pressure and IMU noise, and the seabed depth when the water model draws none
STREAM_NAV_BIAS = 0x62696173  # "bias": IMU biases, drawn once per dataset (frame index 0 of this stream)
# Optical effects' own streams (seasynth.worker.optics): switching one on changes no other draw.
STREAM_SNOW = 0x736E6F77  # "snow": marine snow, the particle field of water.particles
STREAM_MOTION = 0x6D6F7469  # "moti": a random frame's velocity and turn rate over the exposure (motion blur)
STREAM_SENSOR = 0x73656E73  # "sens": photon and read noise (gaussian_sigma keeps STREAM_NOISE)


def frame_rng(dataset_seed: int, frame_index: int, stream: int = STREAM_SCENE) -> np.random.Generator:
    """The generator of one frame: a pure function of (dataset_seed, frame_index, stream)."""
    if dataset_seed < 0 or frame_index < 0:
        raise ValueError(f"seed and frame index must be >= 0, got {dataset_seed}, {frame_index}")
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([dataset_seed, frame_index, stream])))
