"""Navigation sensors: DVL (velocity and four Janus beam ranges), pressure (depth) and IMU, one record per frame.

Models, stated so they can be checked:
- Truth comes from the trajectory (seasynth.worker.scene.trajectory): with `random` poses frames are independent, so velocity,
  angular rate and specific force are null (undefined) and only the DVL's ranges and the pressure are measured.
- DVL: beams k = 0..3 at beam_angle_deg from the sensor's +y axis (its boresight, "down" when mounted level),
  azimuths 45, 135, 225, 315 deg from its +z (forward) axis towards +x (Janus "X" layout). Each beam's slant range is
  the first hit of one ray cast on the GPU against the frame's geometry (terrain and objects), null past max_range_m;
  measured: max(r + Normal(0, range_sigma_m), 0), as a range is never negative (the clip biases ranges within a few
  sigma of 0 upwards). Velocity: the sensor's own velocity in its frame, v_s = R_ws^T (v + omega x lever),
  + Normal(0, velocity_sigma_m_s) per axis; null without bottom lock (fewer than 3 beams in range) or trajectory.
- Pressure: absolute p = P_ATM + RHO g d at the sensor's depth d below the surface (water.depth_m's draw: the
  physical model's, else the frame's nav stream), RHO = 1025 kg/m^3 constant, + Normal(0, sigma_pa).
- IMU: angular rate omega_s = R_ws^T omega + b_g + n_g, specific force f_s = R_ws^T (a - g) + b_a + n_a (a the
  sensor's acceleration: the vehicle's, as attitude is constant along a leg); biases b ~ Normal(0, bias sigma) per
  axis drawn once per dataset, white noise n per frame. No Earth rotation, no scale factor errors.
Each sensor draws from its own child of the frame's nav stream, so switching one on changes no other's numbers.
"""

from __future__ import annotations

import math

import numpy as np

from seasynth.service.seeds import STREAM_NAV, STREAM_NAV_BIAS, frame_rng
from seasynth.service.spec.dataset import DatasetSpec
from seasynth.worker.render import View
from seasynth.worker.scene.poses import look_at_pose, rigid_inverse
from seasynth.worker.scene.sample import Scene
from seasynth.worker.scene.trajectory import GRAVITY, VehicleState, vehicle_state
from seasynth.worker.sensors import vehicle_from_sensor, world_from_sensor

P_ATM = 101_325.0  # Pa
RHO = 1025.0  # kg/m^3, sea water
G = 9.80665  # m/s^2
JANUS_AZIMUTHS_DEG = (45.0, 135.0, 225.0, 315.0)


def janus_directions(beam_angle_deg: float) -> np.ndarray:
    """(4, 3) float64 unit beam directions in the DVL's frame (x right, y down = boresight, z forward)."""
    b = math.radians(beam_angle_deg)
    az = np.radians(JANUS_AZIMUTHS_DEG)
    return np.stack([math.sin(b) * np.sin(az), np.full(4, math.cos(b)), math.sin(b) * np.cos(az)], axis=1)


def ray_view(origin: np.ndarray, direction: np.ndarray, far: float) -> View:
    """A 1x1 view whose single pixel-centre ray starts at origin (3,) and runs along unit direction (3,), world."""
    T = look_at_pose(origin, origin + direction)
    return View(K=np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]), width=1, height=1,
                cam_from_world=rigid_inverse(T), near=1e-3, far=far)


def cast(renderer, items: list, origin: np.ndarray, directions: np.ndarray, far: float) -> np.ndarray:
    """(k,) float64 first-hit ranges (metres, +inf where nothing is hit within far) of rays from origin."""
    return np.array([float(renderer.geometry(ray_view(origin, d, far), items)[1][0, 0]) for d in directions])


def _vec(v: np.ndarray | None) -> list[float] | None:
    return None if v is None else [float(x) for x in v]


def dvl_record(spec: DatasetSpec, scene: Scene, state: VehicleState | None, items: list, renderer,
               rng: np.random.Generator) -> dict:
    d = spec.sensors.dvl
    T = world_from_sensor(scene.world_from_cam, d.pose)
    beams_world = janus_directions(d.beam_angle_deg) @ T[:3, :3].T
    ranges = cast(renderer, items, T[:3, 3], beams_world, d.max_range_m)
    ranges = np.where(ranges <= d.max_range_m, ranges, np.inf)
    range_noise = rng.normal(0.0, d.range_sigma_m, 4)
    vel_noise = rng.normal(0.0, d.velocity_sigma_m_s, 3)
    lock = int(np.isfinite(ranges).sum()) >= 3
    true_v = None
    if state is not None:
        lever = T[:3, 3] - state.world_from_vehicle[:3, 3]
        true_v = T[:3, :3].T @ (state.velocity_world + np.cross(state.angular_rate_world, lever))
    measured_v = true_v + vel_noise if (true_v is not None and lock) else None
    return {
        "pose_world_from_dvl": T.tolist(),
        "beam_directions_dvl": janus_directions(d.beam_angle_deg).tolist(),
        "beam_ranges_true_m": [float(r) if math.isfinite(r) else None for r in ranges],
        "beam_ranges_m": [max(float(r + n), 0.0) if math.isfinite(r) else None for r, n in zip(ranges, range_noise)],
        "bottom_lock": lock,
        "velocity_dvl_true_m_s": _vec(true_v),
        "velocity_dvl_m_s": _vec(measured_v),
        "noise": {"range_sigma_m": d.range_sigma_m, "velocity_sigma_m_s": d.velocity_sigma_m_s},
    }


def pressure_record(spec: DatasetSpec, scene: Scene, surface_z: float, rng: np.random.Generator) -> dict:
    p = spec.sensors.pressure
    z = float(world_from_sensor(scene.world_from_cam, p.pose)[2, 3])
    depth = surface_z - z
    true = P_ATM + RHO * G * depth
    measured = true + float(rng.normal(0.0, p.sigma_pa))
    return {"depth_true_m": depth, "pressure_true_pa": true, "pressure_pa": measured,
            "pressure_gauge_dbar": (measured - P_ATM) / 1e4, "surface_z_world_m": surface_z,
            "model": "p = 101325 Pa + 1025 kg/m^3 * 9.80665 m/s^2 * depth + Normal(0, sigma_pa)",
            "noise": {"sigma_pa": p.sigma_pa}}


def imu_biases(spec: DatasetSpec) -> tuple[np.ndarray, np.ndarray]:
    """(gyro bias (3,) rad/s, accel bias (3,) m/s^2): one draw per dataset, the same in every frame and shard."""
    imu = spec.sensors.imu
    rng = frame_rng(spec.seed, 0, STREAM_NAV_BIAS)
    return rng.normal(0.0, imu.gyro_bias_sigma_rad_s, 3), rng.normal(0.0, imu.accel_bias_sigma_m_s2, 3)


def imu_record(spec: DatasetSpec, scene: Scene, state: VehicleState | None, rng: np.random.Generator) -> dict:
    imu = spec.sensors.imu
    R = (scene.world_from_cam @ vehicle_from_sensor(imu.pose))[:3, :3]
    n_g, n_a = rng.normal(0.0, imu.gyro_sigma_rad_s, 3), rng.normal(0.0, imu.accel_sigma_m_s2, 3)
    b_g, b_a = imu_biases(spec)
    omega = f = None
    if state is not None:
        omega = R.T @ state.angular_rate_world
        f = R.T @ (state.acceleration_world - GRAVITY)
    return {
        "angular_rate_true_rad_s": _vec(omega),
        "specific_force_true_m_s2": _vec(f),
        "angular_rate_rad_s": _vec(None if omega is None else omega + b_g + n_g),
        "specific_force_m_s2": _vec(None if f is None else f + b_a + n_a),
        "bias": {"gyro_rad_s": _vec(b_g), "accel_m_s2": _vec(b_a)},
        "noise": {"gyro_sigma_rad_s": imu.gyro_sigma_rad_s, "accel_sigma_m_s2": imu.accel_sigma_m_s2},
    }


def nav_record(spec: DatasetSpec, index: int, scene: Scene, items: list, renderer, surface_z: float) -> dict:
    """nav/{frame}.json: the vehicle's true state and each enabled navigation sensor's reading."""
    s = spec.sensors
    state = vehicle_state(spec.trajectory, index)
    dvl_rng, pressure_rng, imu_rng = frame_rng(spec.seed, index, STREAM_NAV).spawn(3)
    record: dict = {
        "trajectory": spec.trajectory.kind,
        "time_s": None if state is None else state.t_s,
        "pose_world_from_vehicle": scene.world_from_cam.tolist(),
        "velocity_world_m_s": None if state is None else _vec(state.velocity_world),
        "velocity_vehicle_m_s": None if state is None else _vec(scene.world_from_cam[:3, :3].T @ state.velocity_world),
        "acceleration_world_m_s2": None if state is None else _vec(state.acceleration_world),
    }
    if s.dvl.enabled:
        record["dvl"] = dvl_record(spec, scene, state, items, renderer, dvl_rng)
    if s.pressure.enabled:
        record["pressure"] = pressure_record(spec, scene, surface_z, pressure_rng)
    if s.imu.enabled:
        record["imu"] = imu_record(spec, scene, state, imu_rng)
    return record
