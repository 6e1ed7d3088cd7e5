"""Frames, rotations, geodesy and time (thesis table 5; ``METHOD.md``).

Conventions used everywhere in the project:
- local level L: north, east, down (NED), origin given as geodetic (lat, lon, h);
- body B: forward, right, down;  camera C: right, down, forward;  ECEF E;
- ``C_A_to_B`` (or ``C_A^B`` in the thesis) rotates A coordinates into B: ``x_B = C_A_to_B @ x_A``;
- Euler angles (roll, pitch, yaw) in radians, ZYX order:
  ``C_body_to_level = Rz(yaw) Ry(pitch) Rx(roll)``;
- time: GPS time in seconds since the GPS epoch 1980-01-06 00:00:00 (float64), called ``gpst``.
"""

from __future__ import annotations

import math
from datetime import datetime, timedelta

import numpy as np

# WGS84 and physical constants (IS-GPS-200)
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
OMEGA_EARTH = 7.2921151467e-5  # rad/s
SPEED_OF_LIGHT = 299792458.0  # m/s
GM_GPS = 3.986005e14
GM_GALILEO = 3.986004418e14
GM_BEIDOU = 3.986004418e14

# Carrier frequencies of the L1/E1 signals used by the compass (Hz)
FREQ_L1 = 1575.42e6
FREQ_GLONASS_L1_BASE = 1602.0e6
FREQ_GLONASS_L1_STEP = 0.5625e6
WAVELENGTH_L1 = SPEED_OF_LIGHT / FREQ_L1

GPS_EPOCH = datetime(1980, 1, 6)
SECONDS_PER_WEEK = 604800.0


# ----------------------------------------------------------------------------- time

def gpst_from_datetime(t: datetime) -> float:
    """GPS seconds since the GPS epoch for a naive datetime expressed in GPS time."""
    return (t - GPS_EPOCH).total_seconds()


def datetime_from_gpst(gpst: float) -> datetime:
    """Naive datetime (GPS time scale) for GPS seconds since the GPS epoch."""
    return GPS_EPOCH + timedelta(seconds=float(gpst))


def gpst_from_week_tow(week: int, tow: float) -> float:
    return week * SECONDS_PER_WEEK + tow


def week_tow_from_gpst(gpst: float) -> tuple[int, float]:
    week = int(gpst // SECONDS_PER_WEEK)
    return week, gpst - week * SECONDS_PER_WEEK


# ------------------------------------------------------------------------- rotations

def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix: skew(a) @ b == np.cross(a, b)."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_to_dcm(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """C_body_to_level from roll, pitch, yaw (ZYX)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def dcm_to_euler(C_body_to_level: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) in radians from C_body_to_level; yaw in (-pi, pi]."""
    C = C_body_to_level
    roll = np.arctan2(C[2, 1], C[2, 2])
    pitch = -np.arcsin(np.clip(C[2, 0], -1.0, 1.0))
    yaw = np.arctan2(C[1, 0], C[0, 0])
    return np.array([roll, pitch, yaw])


def vector_length(v: np.ndarray) -> float:
    """Euclidean length of a short vector, in Python floats. ``np.linalg.norm`` of a 3-vector
    is a BLAS dot, which releases the GIL: the fusion's thread then waits to get it back
    while a worker thread runs Python (0.2–0.4 ms a call beside a busy thread, against
    3 µs; ``benchmarks/README.md``, stop 56). For the per-sample and per-satellite paths."""
    return math.hypot(*v)


def rotvec_to_dcm(phi: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrix exp([phi x]) = I + sin θ [k×] + (1 − cos θ) [k×]², in
    Python floats (it runs at every IMU sample: see ``vector_length``)."""
    x, y, z = np.asarray(phi, float).ravel().tolist()
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-12:
        return np.array([[1.0, -z, y], [z, 1.0, -x], [-y, x, 1.0]])
    s, c = math.sin(angle), 1.0 - math.cos(angle)
    x, y, z = x / angle, y / angle, z / angle
    return np.array([[1.0 - c * (y * y + z * z), c * x * y - s * z, c * x * z + s * y],
                     [c * x * y + s * z, 1.0 - c * (x * x + z * z), c * y * z - s * x],
                     [c * x * z - s * y, c * y * z + s * x, 1.0 - c * (x * x + y * y)]])


def dcm_to_rotvec(C: np.ndarray) -> np.ndarray:
    """Inverse of rotvec_to_dcm (angle below pi)."""
    cos_angle = np.clip((np.trace(C) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos_angle)
    w = np.array([C[2, 1] - C[1, 2], C[0, 2] - C[2, 0], C[1, 0] - C[0, 1]])
    if angle < 1e-8:
        return 0.5 * w
    return angle / (2.0 * np.sin(angle)) * w


def orthonormalize(C: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (removes numerical drift of integrated DCMs)."""
    u, _, vt = np.linalg.svd(C)
    R = u @ vt
    if np.linalg.det(R) < 0:
        u[:, -1] *= -1
        R = u @ vt
    return R


def wrap_angle(a):
    """Wrap radians into (-pi, pi]."""
    return np.angle(np.exp(1j * np.asarray(a)))


# Camera (right, down, forward) for a camera looking along the body x axis with no tilt:
# x_B = C_camera_to_body_forward @ x_C.
C_CAMERA_FORWARD_TO_BODY = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def camera_to_body(pan: float, tilt: float, roll: float = 0.0) -> np.ndarray:
    """C_camera_to_body for a camera mounted with a pan (about body z, to starboard positive),
    a tilt (downward positive) and a roll about its optical axis."""
    C_mount = rot_z(pan) @ rot_y(-tilt) @ rot_x(roll)
    return C_mount @ C_CAMERA_FORWARD_TO_BODY


# -------------------------------------------------------------------------- geodesy

def geodetic_to_ecef(lat: float, lon: float, h: float) -> np.ndarray:
    """ECEF position (m) of geodetic latitude, longitude (rad) and ellipsoidal height (m)."""
    s, c = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s * s)
    return np.array([
        (n + h) * c * np.cos(lon), (n + h) * c * np.sin(lon), (n * (1 - WGS84_E2) + h) * s
    ])


def ecef_to_geodetic(xyz: np.ndarray) -> np.ndarray:
    """(lat, lon, h) in rad, rad, m from ECEF (iterative, mm-exact in a few steps)."""
    x, y, z = xyz
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    lat = np.arctan2(z, p * (1.0 - WGS84_E2))
    h = 0.0
    for _ in range(6):
        s = np.sin(lat)
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s * s)
        h = p / np.cos(lat) - n
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n / (n + h)))
    return np.array([lat, lon, h])


def C_ecef_to_level(lat: float, lon: float) -> np.ndarray:
    """C_E^L: ECEF to local NED at (lat, lon)."""
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    return np.array([
        [-sl * co, -sl * so, cl],
        [-so, co, 0.0],
        [-cl * co, -cl * so, -sl],
    ])


def ecef_to_ned(xyz: np.ndarray, origin_llh: np.ndarray) -> np.ndarray:
    """NED coordinates (m) of ECEF points (..., 3) relative to a geodetic origin."""
    o = geodetic_to_ecef(*origin_llh)
    return (np.asarray(xyz) - o) @ C_ecef_to_level(origin_llh[0], origin_llh[1]).T


def ned_to_ecef(ned: np.ndarray, origin_llh: np.ndarray) -> np.ndarray:
    o = geodetic_to_ecef(*origin_llh)
    return np.asarray(ned) @ C_ecef_to_level(origin_llh[0], origin_llh[1]) + o


def normal_gravity(lat: float, h: float) -> float:
    """Somigliana normal gravity with a free-air height term (m/s^2, positive down)."""
    s2 = np.sin(lat) ** 2
    g0 = 9.7803253359 * (1 + 0.00193185265241 * s2) / np.sqrt(1 - WGS84_E2 * s2)
    return g0 - 3.087691e-6 * h + 4.3977e-14 * h * h


def earth_rate_level(lat: float) -> np.ndarray:
    """Earth rotation rate expressed in NED (rad/s)."""
    return OMEGA_EARTH * np.array([np.cos(lat), 0.0, -np.sin(lat)])


def elevation_azimuth(receiver_ecef: np.ndarray, sat_ecef: np.ndarray) -> tuple[float, float]:
    """Elevation and azimuth (rad) of a satellite seen from a receiver."""
    llh = ecef_to_geodetic(receiver_ecef)
    los = C_ecef_to_level(llh[0], llh[1]) @ (np.asarray(sat_ecef) - receiver_ecef)
    horiz = np.hypot(los[0], los[1])
    return float(np.arctan2(-los[2], horiz)), float(np.arctan2(los[1], los[0]) % (2 * np.pi))
