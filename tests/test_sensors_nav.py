"""DVL, pressure, IMU and the lawnmower trajectory: geometry, stated noise, derivatives, determinism, independence."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from local_datasets import tree

from seasynth.service.errors import SpecError
from seasynth.service.spec.dataset import load_spec, parse_spec
from seasynth.service.spec.sensors import DVL, SensorPose
from seasynth.worker.frame.function import to_render_mesh
from seasynth.worker.local.generate import generate, reproduce
from seasynth.worker.render import DrawItem
from seasynth.worker.scene.poses import look_at_pose
from seasynth.worker.scene.trajectory import GRAVITY, lawnmower_state
from seasynth.worker.sensors import vehicle_from_sensor
from seasynth.worker.sensors.nav import P_ATM, RHO, G, cast, dvl_record, imu_record, janus_directions, pressure_record

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"
SEABED = trimesh.Trimesh(vertices=[[-40, -40, 0], [40, -40, 0], [40, 40, 0], [-40, 40, 0]],
                         faces=[[0, 1, 2], [0, 2, 3]])


def seabed_items() -> list[DrawItem]:
    return [DrawItem(mesh=to_render_mesh("nav-seabed", SEABED), world_from_obj=np.eye(4),
                     albedo_scale=np.ones(3, np.float32), albedo_bias=np.zeros(3, np.float32), instance_id=0)]


def level_vehicle(z: float, pitch_deg: float = 0.0) -> np.ndarray:
    """world_from_vehicle: at (0, 0, z), looking along +y, pitched down by pitch_deg, x horizontal."""
    p = math.radians(pitch_deg)
    eye = np.array([0.0, 0.0, z])
    return look_at_pose(eye, eye + [0.0, math.cos(p), -math.sin(p)])


def spec_with(**sensors) -> SimpleNamespace:
    """The parts of a spec the nav records read."""
    return SimpleNamespace(sensors=SimpleNamespace(**sensors), seed=3)


def test_sensor_pose_pitch_tilts_forward_down_and_yaw_turns_to_starboard():
    R = vehicle_from_sensor(SensorPose(pitch_deg=90.0))[:3, :3]
    assert np.allclose(R @ [0, 0, 1], [0, 1, 0])  # forward now points down (+y)
    R = vehicle_from_sensor(SensorPose(yaw_deg=90.0))[:3, :3]
    assert np.allclose(R @ [0, 0, 1], [1, 0, 0])  # forward now points to starboard (+x)
    T = vehicle_from_sensor(SensorPose(offset_m=(0.1, 0.2, 0.3)))
    assert np.array_equal(T[:3, 3], [0.1, 0.2, 0.3])


def test_dvl_janus_ranges_on_a_flat_seabed_are_altitude_over_cos_beam_angle(renderer):
    # A level DVL (camera pitched 30 deg down, DVL pitched 30 deg up) 3 m above a flat seabed: every beam's slant
    # range is 3 / cos(30 deg) (float32 range: 1e-5 m); a DVL 60 m up (max range 50 m) has no bottom lock.
    dvl = DVL(enabled=True, pose=SensorPose(pitch_deg=-30.0), range_sigma_m=0.0, velocity_sigma_m_s=0.0)
    scene = SimpleNamespace(world_from_cam=level_vehicle(3.0, pitch_deg=30.0))
    rec = dvl_record(spec_with(dvl=dvl), scene, None, seabed_items(), renderer, np.random.default_rng(0))
    assert rec["beam_ranges_true_m"] == pytest.approx([3.0 / math.cos(math.radians(30))] * 4, abs=1e-5)
    assert rec["beam_ranges_m"] == rec["beam_ranges_true_m"] and rec["bottom_lock"]
    assert rec["velocity_dvl_m_s"] is None  # random poses: no velocity
    high = SimpleNamespace(world_from_cam=level_vehicle(60.0, pitch_deg=30.0))
    rec = dvl_record(spec_with(dvl=dvl), high, None, seabed_items(), renderer, np.random.default_rng(0))
    assert rec["beam_ranges_m"] == [None] * 4 and not rec["bottom_lock"]
    d = janus_directions(30.0)
    assert np.allclose(np.linalg.norm(d, axis=1), 1) and np.allclose(d[:, 1], math.cos(math.radians(30)))
    assert np.allclose(cast(renderer, seabed_items(), np.array([0, 0, 2.0]), np.array([[0, 0, -1.0]]), 10), 2.0)


def test_noisy_dvl_ranges_are_never_negative(renderer):
    # A level DVL 0.3 m above a flat seabed (slant ranges 0.346 m) with range_sigma_m 0.5: each measured range is
    # max(r + n, 0) for the record's own draws n, so ranges the noise took below 0 read exactly 0 (they were
    # negative before), and the others r + n.
    dvl = DVL(enabled=True, pose=SensorPose(pitch_deg=-30.0), range_sigma_m=0.5, velocity_sigma_m_s=0.0)
    scene = SimpleNamespace(world_from_cam=level_vehicle(0.3, pitch_deg=30.0))
    r = 0.3 / math.cos(math.radians(30))
    clipped = kept = 0
    for seed in range(8):
        rec = dvl_record(spec_with(dvl=dvl), scene, None, seabed_items(), renderer, np.random.default_rng(seed))
        n = np.random.default_rng(seed).normal(0.0, 0.5, 4)
        assert rec["beam_ranges_true_m"] == pytest.approx([r] * 4, abs=1e-5)
        assert rec["beam_ranges_m"] == pytest.approx(np.maximum(np.array(rec["beam_ranges_true_m"]) + n, 0.0), abs=0)
        clipped += int(np.sum(r + n < 0))
        kept += int(np.sum(r + n > 0))
    assert clipped >= 4 and kept >= 4


def test_pressure_is_hydrostatic_with_the_stated_noise():
    scene = SimpleNamespace(world_from_cam=level_vehicle(1.5))
    quiet = spec_with(pressure=SimpleNamespace(pose=SensorPose(offset_m=(0.0, 0.5, 0.0)), sigma_pa=0.0))
    rec = pressure_record(quiet, scene, 12.0, np.random.default_rng(0))
    depth = 12.0 - 1.0  # the sensor sits 0.5 m below the vehicle (+y is down when level)
    assert rec["depth_true_m"] == pytest.approx(depth, abs=1e-12)
    assert rec["pressure_pa"] == rec["pressure_true_pa"] == pytest.approx(P_ATM + RHO * G * depth, rel=1e-12)
    noisy = spec_with(pressure=SimpleNamespace(pose=SensorPose(), sigma_pa=100.0))
    rng = np.random.default_rng(1)
    err = np.array([(lambda r: r["pressure_pa"] - r["pressure_true_pa"])(pressure_record(noisy, scene, 12.0, rng))
                    for _ in range(4000)])
    assert err.mean() == pytest.approx(0.0, abs=4 * 100 / math.sqrt(4000))
    assert err.std() == pytest.approx(100.0, rel=4 / math.sqrt(2 * 4000))


def test_imu_noise_and_bias_are_as_stated():
    spec = parse_spec({"seed": 3, "sensors": {"imu": {"enabled": True, "gyro_sigma_rad_s": 0.01,
                                                      "accel_sigma_m_s2": 0.02}},
                       "trajectory": {"kind": "lawnmower"}})
    state = lawnmower_state(spec.trajectory, 0)
    scene = SimpleNamespace(world_from_cam=state.world_from_vehicle)
    rng = np.random.default_rng(5)
    recs = [imu_record(spec, scene, state, rng) for _ in range(3000)]
    assert all(r["bias"] == recs[0]["bias"] for r in recs)  # one bias per dataset
    for name, unit, bias, sigma in (("angular_rate", "rad_s", "gyro_rad_s", 0.01),
                                    ("specific_force", "m_s2", "accel_m_s2", 0.02)):
        err = np.array([np.subtract(r[f"{name}_{unit}"], r[f"{name}_true_{unit}"]) for r in recs])
        err -= recs[0]["bias"][bias]
        assert np.abs(err.mean(axis=0)).max() < 4 * sigma / math.sqrt(len(recs))
        assert err.std(axis=0) == pytest.approx([sigma] * 3, rel=4 / math.sqrt(2 * len(recs)))
    # Level flight, no heave: specific force is g upwards, |f| = 9.80665, angular rate 0.
    assert np.linalg.norm(recs[0]["specific_force_true_m_s2"]) == pytest.approx(-GRAVITY[2], rel=1e-12)
    assert recs[0]["angular_rate_true_rad_s"] == [0.0, 0.0, 0.0]


def test_trajectory_refuses_a_vehicle_above_the_surface():
    with pytest.raises(SpecError, match="trajectory.altitude_m"):
        parse_spec({"water": {"model": "physical", "depth_m": [3.0, 4.0]},
                    "trajectory": {"kind": "lawnmower", "altitude_m": 2.9, "heave_m": 0.2}})


# ---- end to end on a lawnmower survey --------------------------------------------------------------------------
SURVEY = {"camera.width": 32, "camera.height": 24, "frames": 8, "shard_size": 3, "trajectory.kind": "lawnmower",
          "trajectory.heave_m": 0.2, "trajectory.heave_period_s": 4.0, "trajectory.rate_hz": 4.0,
          "trajectory.leg_length_m": 6.0, "sensors.dvl.enabled": True, "sensors.dvl.pose.pitch_deg": -30.0,
          "sensors.dvl.pose.offset_m": [0.0, 0.1, -0.2], "sensors.pressure.enabled": True,
          "sensors.imu.enabled": True}


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    spec = load_spec(EXAMPLE, SURVEY)
    out = tmp_path_factory.mktemp("survey")
    generate(spec, out, workers=1)
    navs = [json.loads((out / f"nav/{i:06d}.json").read_text()) for i in range(spec.frames)]
    return out, spec, navs


def test_dvl_velocity_and_imu_specific_force_equal_the_trajectory_derivatives(survey):
    _, spec, navs = survey
    tr = spec.trajectory
    dt = 1 / tr.rate_hz
    w = 2 * math.pi / tr.heave_period_s
    assert all(n["dvl"]["bottom_lock"] for n in navs)
    checked = 0
    for i in range(1, spec.frames - 1):
        legs = {lawnmower_state(tr, j).leg for j in (i - 1, i, i + 1)}
        if len(legs) > 1:
            continue
        pos = [np.array(navs[j]["dvl"]["pose_world_from_dvl"])[:3, 3] for j in (i - 1, i + 1)]
        R = np.array(navs[i]["dvl"]["pose_world_from_dvl"])[:3, :3]
        v_fd = (pos[1] - pos[0]) / (2 * dt)
        # Central differences err by dt^2/6 times the third derivative (heave: h w^3).
        assert R @ navs[i]["dvl"]["velocity_dvl_true_m_s"] == pytest.approx(v_fd, abs=dt**2 / 6 * tr.heave_m * w**3
                                                                             + 1e-9)
        vel = [np.array(navs[j]["velocity_world_m_s"]) for j in (i - 1, i + 1)]
        Ri = np.array(navs[i]["pose_world_from_vehicle"])[:3, :3]
        assert Ri @ navs[i]["velocity_vehicle_m_s"] == pytest.approx(navs[i]["velocity_world_m_s"], abs=1e-12)
        f_fd = Ri.T @ ((vel[1] - vel[0]) / (2 * dt) - GRAVITY)
        assert navs[i]["imu"]["specific_force_true_m_s2"] == pytest.approx(f_fd, abs=dt**2 / 6 * tr.heave_m * w**4
                                                                           + 1e-9)
        checked += 1
    assert checked >= 4


def test_survey_frames_share_one_world_and_are_deterministic(survey, tmp_path):
    out, spec, navs = survey
    metas = [json.loads((out / f"meta/{i:06d}.json").read_text()) for i in range(spec.frames)]
    seen = ("label_line", "visible_pixels", "pixels_alone")  # what the frame's view sees changes; the world does not
    world = [[{k: v for k, v in o.items() if k not in seen} for o in m["objects"]] for m in metas]
    assert all(w == world[0] for w in world) and world[0]
    assert all(m["terrain"] == metas[0]["terrain"] and m["water"] == metas[0]["water"] for m in metas)
    assert all(m["camera"]["pose_world_from_camera"] == n["pose_world_from_vehicle"] for m, n in zip(metas, navs))
    two = tmp_path / "two"
    generate(load_spec(EXAMPLE, {**SURVEY, "shard_size": 5}), two, workers=2)
    a, b = tree(two), tree(out)
    a.pop("seasynth.json"), b.pop("seasynth.json")
    assert a == b
    for rel in reproduce(spec, 5, tmp_path / "one"):
        assert (tmp_path / "one" / rel).read_bytes() == (out / rel).read_bytes(), rel


def test_each_nav_sensor_draws_from_its_own_stream(survey, tmp_path):
    out, spec, navs = survey
    generate(load_spec(EXAMPLE, {**SURVEY, "sensors.dvl.enabled": False, "sensors.imu.enabled": False}), tmp_path,
             workers=1)
    for i in range(spec.frames):
        alone = json.loads((tmp_path / f"nav/{i:06d}.json").read_text())
        assert set(alone) - set(navs[i]) == set() and "dvl" not in alone and "imu" not in alone
        assert alone["pressure"] == navs[i]["pressure"]
        for rel in (f"image_2/{i:06d}.png", f"label_2/{i:06d}.txt"):
            assert (tmp_path / rel).read_bytes() == (out / rel).read_bytes()


def test_a_surveys_frames_share_one_water_surface_and_random_frames_draw_their_own():
    """Under the paper model the surface depth is drawn from water.depth_m: once per world. A survey's frames share
    frame 0's world, so pressure follows the vehicle alone; independent random frames each draw their own."""
    from seasynth.worker.sensors.outputs import surface_z

    no_light = SimpleNamespace(light=None)
    survey = parse_spec({"water": {"depth_m": [5.0, 30.0]}, "trajectory": {"kind": "lawnmower"}})
    random = parse_spec({"water": {"depth_m": [5.0, 30.0]}})
    assert len({surface_z(survey, no_light, i) for i in range(6)}) == 1
    assert surface_z(survey, no_light, 0) == surface_z(random, no_light, 0)
    assert len({surface_z(random, no_light, i) for i in range(6)}) == 6
