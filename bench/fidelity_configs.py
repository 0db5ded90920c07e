"""The fidelity bench's configurations (seasynth.bench.fidelity): the near view's water x light table, the world's
(textures, the long view, the port, marine snow), and the lamps and views they use."""

LAMPS = [
    {"offset_m": [-0.35, 0.1, 0.0], "direction": [0.15, 0.35, 1.0], "beam_width_deg": 20, "cutoff_deg": 40,
     "intensity": [3.0, 3.0]},
    {"offset_m": [0.35, 0.1, 0.0], "direction": [-0.15, 0.35, 1.0], "beam_width_deg": 20, "cutoff_deg": 40,
     "intensity": [3.0, 3.0]},
]
CONFIGS: dict[str, str] = {
    "clear-ocean-sun": "I:sun@15",
    "ocean-sun": "II:sun@10",
    "coastal-sun": "1C:sun@6",
    "clear-lamps": "I:lamp@40",
    "turbid-lamps": "3C:lamp@40",
    "ocean-sun-lamp": "II:sun+lamp@10",
}
# The world the light falls on (textures and the far field), in configurations of their own: the near view with
# per-pixel textures, and the long view (`long`) out to where the water hides the seabed, clear and turbid, sun
# with and without lamps.
WORLD_CONFIGS: dict[str, str] = {
    "clear-ocean-sun-textured": "I:sun@15 textured",
    "ocean-sun-textured": "II:sun@10 textured",
    "coastal-sun-textured": "1C:sun@6 textured",
    "long-clear-sun": "I:sun@15 long textured",
    "long-clear-sun-lamp": "I:sun+lamp@15 long textured",
    "long-turbid-sun": "III:sun@20 long textured",
    "long-turbid-sun-lamp": "III:sun+lamp@20 long textured",
    # The near view of ocean-sun-textured through a flat port (camera.port's defaults: 10 mm acrylic 20 mm in front
    # of the lens): the path tracer traces the slab (seasynth.bench.pathtracer_port), seasynth resamples a wider
    # pinhole (seasynth.worker.optics.geometry).
    "ocean-sun-port": "II:sun@10 textured port",
    # Marine snow (water.particles at the type's default density): spheres in the path tracer, lit by the sun and
    # sky (beside coastal-sun-textured), and by the lamps near the camera.
    "coastal-sun-particles": "1C:sun@6 textured particles",
    "turbid-lamps-particles": "3C:lamp@40 textured particles",
    "clear-ocean-sun-dof": "I:sun@15 textured dof",
}
# Configurations whose references are still to be path traced (on a GPU host: bench/reference.py) and stored in
# bench/results/cpu/fidelity-references/; until then `seasynth bench fidelity --config NAME` renders one here.
# turbid-lamps-particles: its first reference (1,747 samples a half, no lamp housing) had a noise floor of 18.9 dB,
# below the row it would score; it needs the lamp housing and the samples turbid-lamps had.
REFERENCES_PENDING = frozenset({"turbid-lamps-particles"})
PRESET_NAMES = ("draft", "fast", "default", "high")
# The long view: the camera 1.2 m over the seabed looking at a point of it 7.7 m ahead (8.9 degrees down), so the
# frame holds seabed from ~2 m out to where the water hides it and open water above.
LONG_VIEW = {"workspaces.camera": {"min": [0.0, -1.7, 1.2], "max": [0.0, -1.7, 1.2]},
             "workspaces.look_at": {"min": [0.0, 6.0, 0.0], "max": [0.0, 6.0, 0.0]}, "camera.look_at_jitter_m": 0.0}


VIEWS = ("textured", "long", "port", "particles", "dof")
# Depth of field: a thin lens at f/1 focused at 1.5 m, the seabed of the near view 1.2-3.2 m away; the 100 mm
# sensor (a 65 mm lens at the table's 320 px) makes its circles of confusion up to ~2.5 px in radius.
DOF = {"camera.aperture_f": 1.0, "camera.focus_m": 1.5, "camera.sensor_width_mm": 100.0}
