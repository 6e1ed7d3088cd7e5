"""MEMS IMU simulator (100 Hz gyro + accelerometer) driven by the true ship motion.

Ideal measurements, from the mechanization equations of ``estimator.ins`` (Earth-fixed NED
frame at the scenario origin, no transport rate; ω_lb is the body rate w.r.t. that frame):

    ω_ib^B = ω_lb^B + C_L^B ω_ie^L
    f^B    = C_L^B (a^L − g^L(r) + 2 ω_ie^L × v^L)

Samples are the INSTANTANEOUS rate and specific force at the sample times t_k = k / rate_hz
(not averages over the interval); the INS integrates them with the same convention.

Error model, per axis, in the sensor axes (``ImuCalibration``):

    raw = M diag(1 + s) true + b_turn_on + b_gm(t) + white noise

M = I + small off-diagonal misalignment/non-orthogonality. The calibration written to the
recording holds the "known" M and s (a factory calibration); the true ones differ by a small
unknown residual. The bias (turn-on + Gauss–Markov instability) is NOT in the calibration: the
EKF estimates it. Defaults are a mid-range industrial MEMS unit (ADIS1646x / BMI088 class).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from estimator.frames import earth_rate_level
from estimator.ins import gravity_level
from estimator.records import ImuCalibration, ImuData

from .motion import ShipMotion
from .scenarios import Scenario

G0 = 9.80665  # m/s² per g (for mg figures)
_DEG = np.pi / 180.0


@dataclass(frozen=True)
class ImuErrorModel:
    """1-sigma MEMS error magnitudes (SI units; the comments give them in datasheet units)."""

    gyro_bias_turn_on: float = 0.07 * _DEG  # rad/s    (0.07 deg/s = 250 deg/h per axis)
    gyro_bias_instability: float = 10.0 * _DEG / 3600.0  # rad/s (10 deg/h, Gauss–Markov)
    gyro_bias_tau: float = 300.0  # s, correlation time of the instability
    gyro_arw: float = 0.15 * _DEG / 60.0  # rad/√s  (0.15 deg/√h angle random walk)
    gyro_scale_factor: float = 2e-3  # (0.2 %) known, written into the calibration
    gyro_misalignment: float = 0.1 * _DEG  # rad (0.1 deg off-diagonal terms), known
    gyro_scale_factor_residual: float = 2e-4  # (0.02 %) unknown after calibration
    gyro_misalignment_residual: float = 0.01 * _DEG  # rad, unknown after calibration
    accel_bias_turn_on: float = 20e-3 * G0  # m/s²  (20 mg)
    accel_bias_instability: float = 0.1e-3 * G0  # m/s² (0.1 mg, Gauss–Markov)
    accel_bias_tau: float = 300.0  # s
    accel_vrw: float = 0.05 / 60.0  # m/s/√s  (0.05 m/s/√h velocity random walk)
    accel_scale_factor: float = 2e-3  # (0.2 %) known
    accel_misalignment: float = 0.1 * _DEG  # rad, known
    accel_scale_factor_residual: float = 2e-4  # unknown
    accel_misalignment_residual: float = 0.01 * _DEG  # rad, unknown

    @classmethod
    def none(cls) -> ImuErrorModel:
        """A perfect IMU (and an identity calibration)."""
        return cls(**{f.name: (1.0 if f.name.endswith("_tau") else 0.0) for f in fields(cls)})


def _misalignment(rng: np.random.Generator, sigma: float) -> np.ndarray:
    M = np.eye(3)
    off = ~np.eye(3, dtype=bool)
    M[off] = rng.normal(0.0, sigma, 6)
    return M


def _gauss_markov(rng: np.random.Generator, n: int, dt: float, sigma: float,
                  tau: float) -> np.ndarray:
    """(n,3) stationary first-order Gauss–Markov sequence, exact discretisation."""
    out = np.zeros((n, 3))
    if sigma <= 0.0 or n == 0:
        return out
    phi = np.exp(-dt / tau)
    drive = rng.normal(0.0, sigma * np.sqrt(1.0 - phi**2), (n, 3))
    out[0] = rng.normal(0.0, sigma, 3)
    for k in range(1, n):
        out[k] = phi * out[k - 1] + drive[k]
    return out


def ideal_imu(motion: ShipMotion, scenario: Scenario, t: np.ndarray) -> tuple[np.ndarray, ...]:
    """Error-free ω_ib^B and f^B (N,3) at scenario times ``t`` (s since start)."""
    lat, lon, h = scenario.origin_llh_deg
    origin = np.array([np.radians(lat), np.radians(lon), h])
    st = motion.state(t)
    w_ie = earth_rate_level(origin[0])
    g = gravity_level(st.position_ned, origin)
    f_level = st.accel_ned - g + 2.0 * np.cross(w_ie, st.velocity_ned)
    C_lb = np.transpose(st.C_body_to_level, (0, 2, 1))
    gyro = st.omega_body + C_lb @ w_ie
    accel = np.einsum("nij,nj->ni", C_lb, f_level)
    return gyro, accel


def simulate_imu(
    motion: ShipMotion,
    scenario: Scenario,
    seed: int,
    start_gpst: float,
    rate_hz: float = 100.0,
    errors: ImuErrorModel | None = None,
) -> tuple[ImuData, ImuCalibration, dict]:
    """IMU samples over the scenario, the calibration file's content, and the truth.

    Samples at t_k = k / rate_hz, k = 0 .. floor(duration · rate_hz) (instantaneous values, see
    the module docstring), time-tagged ``start_gpst + t_k``. Deterministic for a seed.

    The truth dict (scoring/tests only) holds ``time`` (gpst), ``gyro_bias`` / ``accel_bias``
    (N,3 total bias histories), their ``*_turn_on`` parts, the TRUE ``*_scale_factor`` and
    ``*_misalignment``, and the error-free ``gyro_true`` / ``accel_true``."""
    errors = ImuErrorModel() if errors is None else errors
    rng = np.random.default_rng([seed, 0x1A0])  # independent of the motion's wave phases
    n = int(np.floor(scenario.duration_s * rate_hz + 1e-9)) + 1
    dt = 1.0 / rate_hz
    t = np.arange(n) * dt
    gyro_true, accel_true = ideal_imu(motion, scenario, t)

    e = errors
    known = {
        "gyro_scale_factor": rng.normal(0.0, e.gyro_scale_factor, 3),
        "gyro_misalignment": _misalignment(rng, e.gyro_misalignment),
        "accel_scale_factor": rng.normal(0.0, e.accel_scale_factor, 3),
        "accel_misalignment": _misalignment(rng, e.accel_misalignment),
    }
    true = {
        "gyro_scale_factor": known["gyro_scale_factor"]
        + rng.normal(0.0, e.gyro_scale_factor_residual, 3),
        "gyro_misalignment": known["gyro_misalignment"]
        + _misalignment(rng, e.gyro_misalignment_residual) - np.eye(3),
        "accel_scale_factor": known["accel_scale_factor"]
        + rng.normal(0.0, e.accel_scale_factor_residual, 3),
        "accel_misalignment": known["accel_misalignment"]
        + _misalignment(rng, e.accel_misalignment_residual) - np.eye(3),
    }
    gyro_on = rng.normal(0.0, e.gyro_bias_turn_on, 3)
    accel_on = rng.normal(0.0, e.accel_bias_turn_on, 3)
    gyro_bias = gyro_on + _gauss_markov(rng, n, dt, e.gyro_bias_instability, e.gyro_bias_tau)
    accel_bias = accel_on + _gauss_markov(rng, n, dt, e.accel_bias_instability, e.accel_bias_tau)
    # White noise per sample: density × sqrt(bandwidth = sample rate).
    gyro_noise = rng.normal(0.0, e.gyro_arw * np.sqrt(rate_hz), (n, 3))
    accel_noise = rng.normal(0.0, e.accel_vrw * np.sqrt(rate_hz), (n, 3))

    Tg = true["gyro_misalignment"] @ np.diag(1.0 + true["gyro_scale_factor"])
    Ta = true["accel_misalignment"] @ np.diag(1.0 + true["accel_scale_factor"])
    gyro = gyro_true @ Tg.T + gyro_bias + gyro_noise
    accel = accel_true @ Ta.T + accel_bias + accel_noise

    time = start_gpst + t
    calibration = ImuCalibration(
        gyro_scale_factor=known["gyro_scale_factor"],
        gyro_misalignment=known["gyro_misalignment"],
        accel_scale_factor=known["accel_scale_factor"],
        accel_misalignment=known["accel_misalignment"],
        lever_arm_body=np.zeros(3),  # the body origin is the IMU
    )
    truth = {
        "time": time,
        "gyro_bias": gyro_bias,
        "accel_bias": accel_bias,
        "gyro_bias_turn_on": gyro_on,
        "accel_bias_turn_on": accel_on,
        **true,
        "gyro_true": gyro_true,
        "accel_true": accel_true,
    }
    return ImuData(time=time, gyro=gyro, accel=accel), calibration, truth
