"""The MCAP export's sonar and navigation messages (seasynth.worker.export.mcap writes them): one frame's sensor files as ROS 2
messages, with the message definitions they need.

Topics, each only where the spec switches the sensor on (header.frame_id in brackets; every sensor frame has the
camera's axes, x right/starboard, y down, z forward, turned and placed by the sensor's spec pose: /tf_static's
camera -> sensor transform, seasynth.worker.export.mcap_tf):

  /fls/image        sensor_msgs/msg/Image  [fls]  "mono16": fls/N.png as it is (rows = range bins nearest first,
                                                   columns = beams port first)
  /fls/fan          sensor_msgs/msg/Image  [fls]  "mono16": fls_fan/N.png (apex at the bottom centre)
  /fls/sonar_image  marine_acoustic_msgs/msg/ProjectedSonarImage [fls]: the polar image with its geometry.
                    beam_directions: unit vectors (sin az, 0, cos az) at the beam centres az = -H/2 + (b + 1/2) H /
                    beams; ranges: bin centres r_min + (k + 1/2) dr (float32, m); ping_info: frequency (Hz),
                    sound_speed NOMINAL_SOUND_SPEED (the model's ranges are geometric: it converts no times),
                    tx_beamwidths = the vertical aperture, rx_beamwidths = the horizontal beam width, per beam (rad);
                    image: DTYPE_UINT16 little-endian, beam_count = beams, cells in the polar PNG's order (bin
                    major: data[k * beams + b])
  /sss/image        sensor_msgs/msg/Image  [sss]  "mono16": sss/N.png (1 row: port far..near, starboard near..far)
  /sss/sonar_image  marine_acoustic_msgs/msg/ProjectedSonarImage [sss]: two beams, port then starboard, directions
                    (-cos d, sin d, 0) and (cos d, sin d, 0) at depression d; ranges: slant-range bin centres
                    (k + 1/2) range_m / bins; tx = vertical, rx = horizontal beam width; data[k * 2 + side]
  /dvl/twist        geometry_msgs/msg/TwistWithCovarianceStamped [dvl]: nav's velocity_dvl_m_s; covariance
                    diag(sigma^2, sigma^2, sigma^2, -1, -1, -1): the angular rate is not measured. Only with
                    bottom lock (frames whose velocity is null have no message)
  /pressure         sensor_msgs/msg/FluidPressure [pressure]: pressure_pa (Pa, absolute), variance sigma_pa^2
  /imu              sensor_msgs/msg/Imu [imu]: angular_rate_rad_s, specific_force_m_s2, their white-noise
                    variances on the diagonals; no orientation (orientation_covariance[0] = -1, REP 145). Only where
                    the values are not null (trajectory: lawnmower)
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from seasynth.service.errors import ExportError
from seasynth.service.spec.sensors import FLS, SSS, Sensors

NOMINAL_SOUND_SPEED = 1500.0  # m/s, ping_info.sound_speed
_DTYPES = ("UINT8", "INT8", "UINT16", "INT16", "UINT32", "INT32", "UINT64", "INT64", "FLOAT32", "FLOAT64")
DTYPE_UINT16 = _DTYPES.index("UINT16")
_COV3 = "float64[9]"

SENSOR_DEFS = {
    "geometry_msgs/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n",
    "geometry_msgs/TwistWithCovariance": "geometry_msgs/Twist twist\nfloat64[36] covariance\n",
    "geometry_msgs/TwistWithCovarianceStamped": ("std_msgs/Header header\n"
                                                 "geometry_msgs/TwistWithCovariance twist\n"),
    "sensor_msgs/FluidPressure": "std_msgs/Header header\nfloat64 fluid_pressure\nfloat64 variance\n",
    "sensor_msgs/Imu": ("std_msgs/Header header\ngeometry_msgs/Quaternion orientation\n"
                        f"{_COV3} orientation_covariance\ngeometry_msgs/Vector3 angular_velocity\n"
                        f"{_COV3} angular_velocity_covariance\ngeometry_msgs/Vector3 linear_acceleration\n"
                        f"{_COV3} linear_acceleration_covariance\n"),
    "marine_acoustic_msgs/PingInfo": ("float32 frequency\nfloat32 sound_speed\nfloat32[] tx_beamwidths\n"
                                      "float32[] rx_beamwidths\n"),
    "marine_acoustic_msgs/SonarImageData": ("".join(f"uint32 DTYPE_{t}={i}\n" for i, t in enumerate(_DTYPES))
                                            + "bool is_bigendian\nuint32 dtype\nuint32 beam_count\nuint8[] data\n"),
    "marine_acoustic_msgs/ProjectedSonarImage": ("std_msgs/Header header\nmarine_acoustic_msgs/PingInfo ping_info\n"
                                                 "geometry_msgs/Vector3[] beam_directions\nfloat32[] ranges\n"
                                                 "marine_acoustic_msgs/SonarImageData image\n"),
}

FLS_IMAGE, FLS_FAN, FLS_SONAR, SSS_IMAGE, SSS_SONAR, DVL_TOPIC, PRESSURE_TOPIC, IMU_TOPIC = (
    "/fls/image", "/fls/fan", "/fls/sonar_image", "/sss/image", "/sss/sonar_image", "/dvl/twist", "/pressure",
    "/imu")
SENSOR_TOPICS = {
    FLS_IMAGE: "sensor_msgs/msg/Image",
    FLS_FAN: "sensor_msgs/msg/Image",
    FLS_SONAR: "marine_acoustic_msgs/msg/ProjectedSonarImage",
    SSS_IMAGE: "sensor_msgs/msg/Image",
    SSS_SONAR: "marine_acoustic_msgs/msg/ProjectedSonarImage",
    DVL_TOPIC: "geometry_msgs/msg/TwistWithCovarianceStamped",
    PRESSURE_TOPIC: "sensor_msgs/msg/FluidPressure",
    IMU_TOPIC: "sensor_msgs/msg/Imu",
}


def fls_beam_azimuths(fls: FLS) -> np.ndarray:
    """(beams,) float64, rad: beam centres, port (negative) first."""
    half = math.radians(fls.horizontal_aperture_deg) / 2
    return -half + (np.arange(fls.beams) + 0.5) * (2 * half / fls.beams)


def fls_range_centres(fls: FLS) -> np.ndarray:
    """(range_bins,) float64, metres: bin centres, nearest first."""
    lo, hi = fls.range_m
    return lo + (np.arange(fls.range_bins) + 0.5) * ((hi - lo) / fls.range_bins)


def sss_range_centres(sss: SSS) -> np.ndarray:
    """(range_bins,) float64, metres: slant-range bin centres of one side, nearest first."""
    return (np.arange(sss.range_bins) + 0.5) * (sss.range_m / sss.range_bins)


def read_png16(path: Path) -> np.ndarray:
    """(h, w) uint16 of a 16-bit grey PNG; ExportError naming the file otherwise."""
    import imagecodecs

    try:
        a = imagecodecs.png_decode(path.read_bytes())
    except (OSError, imagecodecs.PngError) as err:
        raise ExportError(f"{path}: unreadable as PNG ({err})") from None
    if a.dtype != np.uint16 or a.ndim != 2:
        raise ExportError(f"{path}: a 16-bit grey PNG was expected, got {a.shape} {a.dtype}")
    return a


def image_msg(header: dict, a: np.ndarray) -> dict:
    """sensor_msgs/Image "mono16" of (h, w) uint16, little-endian rows."""
    h, w = a.shape
    return {"header": header, "height": h, "width": w, "encoding": "mono16", "is_bigendian": 0, "step": 2 * w,
            "data": a.astype("<u2").tobytes()}


def _vec(v) -> dict:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def sonar_msg(header: dict, cells: np.ndarray, directions: np.ndarray, ranges: np.ndarray, frequency_khz: float,
              tx_rad: float, rx_rad: float) -> dict:
    """ProjectedSonarImage of cells (bins, beams) uint16, directions (beams, 3) unit vectors, ranges (bins,) m."""
    beams = cells.shape[1]
    return {
        "header": header,
        "ping_info": {"frequency": frequency_khz * 1000.0, "sound_speed": NOMINAL_SOUND_SPEED,
                      "tx_beamwidths": [tx_rad] * beams, "rx_beamwidths": [rx_rad] * beams},
        "beam_directions": [_vec(d) for d in directions],
        "ranges": [float(r) for r in ranges],
        "image": {"is_bigendian": False, "dtype": DTYPE_UINT16, "beam_count": beams,
                  "data": np.ascontiguousarray(cells).astype("<u2").tobytes()},
    }


def _diag(values, n: int) -> list[float]:
    out = [0.0] * (n * n)
    for i, v in enumerate(values):
        out[i * n + i] = float(v)
    return out


def sensor_messages(files: dict[str, Path], sensors: Sensors, header: Callable[[str], dict]) -> list[tuple[str, dict]]:
    """(topic, message) of one frame's sensor files (folder -> path, as seasynth.worker.export.dataset.Frame has them), in
    a fixed order. header(frame_id) gives the frame's std_msgs/Header."""
    out: list[tuple[str, dict]] = []
    if "fls" in files:
        fls, h = sensors.fls, header("fls")
        polar = read_png16(files["fls"])
        if polar.shape != (fls.range_bins, fls.beams):
            raise ExportError(f"{files['fls']}: shape {polar.shape}, the spec says {fls.range_bins} bins x "
                              f"{fls.beams} beams")
        az = fls_beam_azimuths(fls)
        dirs = np.stack([np.sin(az), np.zeros_like(az), np.cos(az)], axis=1)
        out += [(FLS_IMAGE, image_msg(h, polar)), (FLS_FAN, image_msg(h, read_png16(files["fls_fan"]))),
                (FLS_SONAR, sonar_msg(h, polar, dirs, fls_range_centres(fls), fls.frequency_khz,
                                      math.radians(fls.vertical_aperture_deg), math.radians(fls.beam_width_deg)))]
    if "sss" in files:
        sss, h = sensors.sss, header("sss")
        row = read_png16(files["sss"])
        n = sss.range_bins
        if row.shape != (1, 2 * n):
            raise ExportError(f"{files['sss']}: shape {row.shape}, the spec says (1, {2 * n})")
        cells = np.stack([row[0, :n][::-1], row[0, n:]], axis=1)  # (bins, 2): port, starboard, nearest first
        d = math.radians(sss.depression_deg)
        dirs = np.array([[-math.cos(d), math.sin(d), 0.0], [math.cos(d), math.sin(d), 0.0]])
        out += [(SSS_IMAGE, image_msg(h, row)),
                (SSS_SONAR, sonar_msg(h, cells, dirs, sss_range_centres(sss), sss.frequency_khz,
                                      math.radians(sss.vertical_beam_deg), math.radians(sss.horizontal_beam_deg)))]
    if "nav" in files:
        try:
            nav = json.loads(files["nav"].read_text())
        except (OSError, ValueError) as err:
            raise ExportError(f"{files['nav']}: unreadable nav record ({err})") from None
        out += _nav_messages(nav, sensors, header)
    return out


def _nav_messages(nav: dict, sensors: Sensors, header: Callable[[str], dict]) -> list[tuple[str, dict]]:
    out: list[tuple[str, dict]] = []
    dvl = nav.get("dvl")
    if dvl is not None and dvl.get("velocity_dvl_m_s") is not None:
        s2 = sensors.dvl.velocity_sigma_m_s ** 2
        out.append((DVL_TOPIC, {"header": header("dvl"), "twist": {
            "twist": {"linear": _vec(dvl["velocity_dvl_m_s"]), "angular": _vec((0.0, 0.0, 0.0))},
            "covariance": _diag((s2, s2, s2, -1.0, -1.0, -1.0), 6)}}))
    p = nav.get("pressure")
    if p is not None:
        out.append((PRESSURE_TOPIC, {"header": header("pressure"), "fluid_pressure": float(p["pressure_pa"]),
                                     "variance": sensors.pressure.sigma_pa ** 2}))
    imu = nav.get("imu")
    if imu is not None and imu.get("angular_rate_rad_s") is not None:
        g2, a2 = sensors.imu.gyro_sigma_rad_s ** 2, sensors.imu.accel_sigma_m_s2 ** 2
        out.append((IMU_TOPIC, {
            "header": header("imu"), "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            "orientation_covariance": [-1.0] + [0.0] * 8,
            "angular_velocity": _vec(imu["angular_rate_rad_s"]), "angular_velocity_covariance": _diag([g2] * 3, 3),
            "linear_acceleration": _vec(imu["specific_force_m_s2"]),
            "linear_acceleration_covariance": _diag([a2] * 3, 3)}))
    return out
