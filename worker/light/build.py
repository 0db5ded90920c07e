"""A frame's PhysicalLight from the spec and its generator: the water's one description, then every light term
derived from it, and which terms the frame needs."""

from __future__ import annotations

import numpy as np

from seasynth.service.spec.dataset import DatasetSpec
from seasynth.service.water import jerlov_absorption, jerlov_scattering
from seasynth.worker.light import Medium, PhysicalLight, Terms
from seasynth.worker.light.caustics import sample_caustics
from seasynth.worker.light.lamps import lamp_from_spec, spread_worthwhile
from seasynth.worker.light.solved import with_column
from seasynth.worker.light.sun import shadow_worthwhile, sun_in_water
from seasynth.worker.render import Lighting


def for_spec(light: PhysicalLight, solved_column: bool) -> PhysicalLight:
    """The light a frame renders with: the solved column on where the spec asks for it (water.solved_column) and the
    sun or the sky lights the frame (lamp-only frames have no column to solve)."""
    return with_column(light, solved_column and (light.terms.sun or light.terms.sky))


def sample_physical(
    spec: DatasetSpec, rng: np.random.Generator, lighting: Lighting, top_z: float,
    seabed: tuple[np.ndarray, float] | None = None,
) -> tuple[PhysicalLight, str | None]:
    """Draw the water (type, jitter, explicit a/b, g, depth) and lamp intensities, in that order, and derive the
    frame's light. top_z: world z of the highest point that receives light (shadow maps are skipped when the
    sun's unscattered beam is invisible there); seabed: its mean albedo (3,) and the world z of its mean plane (the
    solved column's seabed). Returns the light and the Jerlov type used (None if explicit)."""
    w = spec.water
    kind = w.jerlov[rng.integers(len(w.jerlov))] if w.jerlov else None
    jitter = rng.uniform(*w.beta_jitter)
    if w.absorption is not None:
        a = rng.uniform(np.asarray(w.absorption.min), np.asarray(w.absorption.max))
    else:
        a = jerlov_absorption(kind) * jitter
    if w.scattering is not None:
        b = rng.uniform(np.asarray(w.scattering.min), np.asarray(w.scattering.max))
    else:
        b = jerlov_scattering(kind) * jitter
    g = float(rng.uniform(*w.phase_g))
    depth = float(rng.uniform(*w.depth_m))
    intensities = [float(rng.uniform(*lp.intensity)) for lp in spec.lighting.lamps]

    medium = Medium(a=a, b=b, g=g, surface_z=depth)
    sun_dir, e0 = sun_in_water(lighting.sun_dir_world, lighting.sun_intensity)
    sky = np.full(3, lighting.ambient)
    lamps = tuple(lamp_from_spec(lp, i) for lp, i in zip(spec.lighting.lamps, intensities) if i > 0
                  and max(lp.colour) > 0)
    sun_on = bool(e0.max() > 0)
    beam_seen = sun_on and shadow_worthwhile(medium.c, depth - top_z, sun_dir[2])  # the unscattered beam matters
    caustics = None
    if spec.lighting.caustics.enabled and beam_seen:
        # Their own stream (a child of the frame's generator, which spawning does not advance): switching caustics
        # on changes no other draw.
        crng = rng.spawn(1)[0]
        cs = spec.lighting.caustics
        caustics = sample_caustics(crng, float(crng.uniform(*cs.wavelength_m)), float(crng.uniform(*cs.slope)))
    terms = Terms(
        sun=sun_on,
        sun_shadows=beam_seen and spec.lighting.shadows,
        caustics=caustics is not None,
        sky=bool(sky.max() > 0),
        scattering=bool(b.max() > 0),
        lamps=len(lamps),
        lamp_spread=bool(lamps) and spread_worthwhile(medium.c, medium.k),
    )
    light = PhysicalLight(medium=medium, sun_dir_world=sun_dir, sun_irradiance=e0, sky_irradiance=sky,
                          lamps=lamps, terms=terms, caustics=caustics,
                          **({} if seabed is None else {"seabed_albedo": np.asarray(seabed[0], np.float64),
                                                         "seabed_z": float(seabed[1])}))
    used = w.absorption is None or w.scattering is None
    return for_spec(light, w.solved_column), kind if used else None
