"""INS block (thesis 5.1.1, fig. 19; ``METHOD.md``): strapdown mechanization at the IMU rate.

Navigation frame
    ``L`` = the NED tangent frame at ``origin_llh`` (the local-level frame at the world origin
    in which the EKF keeps the trajectory), FIXED TO THE EARTH. Position is NED metres relative
    to the origin, velocity is relative to the Earth, attitude is ``C_body_to_level``. Because
    ``L`` does not follow the ship, there is no transport rate (Ω_en = 0) and the equations are
    the Earth-fixed (ECEF-like) ones written in constant NED axes:

        Ċ_B^L = C_B^L [ω_ib^B ×] − [ω_ie^L ×] C_B^L
        v̇^L   = C_B^L f^B + g^L(r) − 2 ω_ie^L × v^L
        ṙ^L   = v^L

    ``ω_ie^L`` is the (constant) Earth rate in the origin's NED axes and ``g^L(r)`` is normal
    gravity (Somigliana + free air, centrifugal included) at the current point along the local
    ellipsoid normal, expressed in ``L`` (it tilts by ~1.6e-5 rad per 100 m from the origin).
    Euler angles from ``C_B^L`` are relative to the origin's axes (< 0.001 deg from the local
    ones within a harbour).

IMU samples
    Raw gyro (rad/s) and accel (m/s²) in the sensor (body) axes, INSTANTANEOUS values at the
    sample times (``recordings.sim.imu`` obeys the same convention). Calibration (thesis
    fig. 19, ``ImuCalibration``: raw = M diag(1 + s) true + bias):
        ω̂ = G (ω̃ − b̂_ω),  â = A (ã − b̂_a),  G = (M_ω diag(1 + s_ω))⁻¹, A = (M_a diag(1 + s_a))⁻¹
    with the bias estimates ``b̂`` in the raw sensor axes.

Integration over one interval Δτ = t_k − t_{k−1} (second order exact for rates and specific
forces varying linearly over the interval):
    coning   ω'_k = ω̄_k + (Δτ/12) ω̂_{k−1} × ω̂_k,   rotation vector φ = ω'_k Δτ
    sculling a'_k = ā_k + (Δτ/2) ω̄_k × ā_k + (Δτ/12)(ω̂_{k−1} × â_k − ω̂_k × â_{k−1})
where ω̄, ā are the interval means of the two calibrated samples (the thesis' ω_k, a_k are the
interval averages a delta-angle/delta-velocity IMU delivers; the trapezoid mean gives them for
instantaneous samples). The last term is the classic sculling term for linear variation, the
(Δτ/2) term is the thesis' rotation correction.

Error state (for the EKF, ``error_state_matrix``): x = [x_r, x_v, x_e, x_ω, x_a] (15), every
component defined as INS estimate minus truth:
    x_r = r̂ − r,  x_v = v̂ − v,  Ĉ_B^L = (I + [x_e ×]) C_B^L (small angles in L),
    x_ω = b̂_ω − b_ω,  x_a = b̂_a − b_a (raw sensor axes).
``Ins.correct`` removes such estimated errors (feedback), e.g. r ← r̂ − x_r.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .frames import (
    C_ecef_to_level,
    dcm_to_euler,
    earth_rate_level,
    ecef_to_geodetic,
    geodetic_to_ecef,
    normal_gravity,
    orthonormalize,
    rotvec_to_dcm,
    skew,
)
from .records import ImuCalibration

# Default Gauss–Markov correlation times of the bias errors (s); the EKF may pass its own.
GYRO_BIAS_TAU_S = 300.0
ACCEL_BIAS_TAU_S = 300.0

_ORTHONORMALIZE_EVERY = 100  # steps; rotvec_to_dcm products drift only at rounding level
_GRAVITY_REFRESH_M = 1.0  # re-evaluate exact gravity after moving this far (linear in between)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # np.cross costs ~30 us on 3-vectors; this runs at every IMU sample several times.
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


# ----------------------------------------------------------------------------- gravity


def gravity_level(position_ned: np.ndarray, origin_llh: np.ndarray) -> np.ndarray:
    """Normal gravity vector (m/s², (3,) or (N,3)) at NED points relative to ``origin_llh``
    (rad, rad, m), expressed in the origin's NED axes."""
    p = np.asarray(position_ned, float)
    C_el = C_ecef_to_level(origin_llh[0], origin_llh[1])
    ecef = p @ C_el + geodetic_to_ecef(*origin_llh)
    lat, lon, h = ecef_to_geodetic(np.moveaxis(ecef, -1, 0))
    g = normal_gravity(lat, h)
    cl = np.cos(lat)
    down_ecef = -np.stack([cl * np.cos(lon), cl * np.sin(lon), np.sin(lat)], axis=-1)
    return (g[..., None] * down_ecef) @ C_el.T


def gravity_gradient_level(origin_llh: np.ndarray, position_ned: np.ndarray | None = None,
                           step_m: float = 10.0) -> np.ndarray:
    """∂g^L/∂r (3x3, 1/s²) of ``gravity_level``: ≈ (g/R) diag(−1, −1, 2) (central differences)."""
    r0 = np.zeros(3) if position_ned is None else np.asarray(position_ned, float)
    pts = r0 + step_m * np.vstack([np.eye(3), -np.eye(3)])
    g = gravity_level(pts, origin_llh)
    return ((g[:3] - g[3:]) / (2 * step_m)).T


# ----------------------------------------------------------------------------- state


@dataclass
class InsState:
    """INS solution at ``time`` (gpst s). Biases in raw sensor axes (rad/s, m/s²)."""

    time: float
    position_ned: np.ndarray  # m, relative to the INS origin
    velocity_ned: np.ndarray  # m/s w.r.t. the Earth
    C_body_to_level: np.ndarray  # 3x3
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def euler(self) -> np.ndarray:
        """(roll, pitch, yaw) rad of C_body_to_level (relative to the origin's NED axes)."""
        return dcm_to_euler(self.C_body_to_level)

    def copy(self) -> InsState:
        return replace(
            self,
            position_ned=np.array(self.position_ned, float),
            velocity_ned=np.array(self.velocity_ned, float),
            C_body_to_level=np.array(self.C_body_to_level, float),
            gyro_bias=np.array(self.gyro_bias, float),
            accel_bias=np.array(self.accel_bias, float),
        )


def calibration_matrices(calibration: ImuCalibration) -> tuple[np.ndarray, np.ndarray]:
    """Thesis' G and A (scale factor + misalignment correction): true = G (raw − bias)."""
    G = np.linalg.inv(calibration.gyro_misalignment @ np.diag(1.0 + calibration.gyro_scale_factor))
    A = np.linalg.inv(
        calibration.accel_misalignment @ np.diag(1.0 + calibration.accel_scale_factor))
    return G, A


class Ins:
    """Strapdown INS in the Earth-fixed NED frame at ``origin_llh`` (rad, rad, m)."""

    def __init__(self, origin_llh: np.ndarray, calibration: ImuCalibration,
                 initial: InsState) -> None:
        self.origin_llh = np.asarray(origin_llh, float)
        self.calibration = calibration
        self.gyro_correction, self.accel_correction = calibration_matrices(calibration)
        self.omega_ie = earth_rate_level(self.origin_llh[0])
        self._gravity_at = np.full(3, np.inf)
        self._gravity0 = np.zeros(3)
        self._gravity_gradient = gravity_gradient_level(self.origin_llh)
        self._earth_dt = -1.0
        self._earth_dcm = np.eye(3)
        self.reset(initial)

    # -- state -----------------------------------------------------------------------------

    def reset(self, state: InsState) -> None:
        """(Re)initialise, e.g. from CPP position/velocity and GNSS compass attitude."""
        self._state = state.copy()
        self._state.C_body_to_level = orthonormalize(self._state.C_body_to_level)
        self._raw: tuple[np.ndarray, np.ndarray] | None = None  # previous raw sample
        self._omega = np.zeros(3)  # previous calibrated sample
        self._f = np.zeros(3)
        self._steps = 0
        # The attitude integrated from the calibrated gyro alone, never corrected by the EKF:
        # its rotations over seconds check the VO's (``vo_coupling.VoConsistency``) without
        # the corrections the VO itself feeds in.
        self.C_gyro = self._state.C_body_to_level.copy()
        # The turn about the level down axis the EKF's gyro bias estimates took out of it (rad):
        # with it a window's rotation is had with the bias held as it was at its start, which
        # the EKF learning a bias step (from the VO, the single differences) must not hide
        # (``carrier_phase.GyroCheck``).
        self.bias_turn = 0.0

    @property
    def state(self) -> InsState:
        return self._state.copy()

    def level_yaw_rate(self, gyro: np.ndarray) -> float | np.ndarray:
        """Raw gyro samples' rate about the level down axis (rad/s; one sample (3,) or
        several (n, 3)), their bias not removed (scale factor and misalignment are)."""
        return (self.gyro_correction @ np.asarray(gyro, float).T).T @ self._state.C_body_to_level[2]

    @property
    def bias_yaw_rate(self) -> float:
        """The EKF's gyro bias estimate about the level down axis (rad/s), as it is taken out
        of the samples (``calibrate``)."""
        s = self._state
        return float(s.C_body_to_level[2] @ (self.gyro_correction @ s.gyro_bias))

    @property
    def horizontal_speed(self) -> float:
        """Speed over ground (m/s)."""
        return math.hypot(*self._state.velocity_ned[:2])

    @property
    def omega_body(self) -> np.ndarray:
        """Last calibrated angular rate ω_ib^B (rad/s)."""
        return self._omega.copy()

    @property
    def specific_force_level(self) -> np.ndarray:
        """Last calibrated specific force in L, C_B^L f^B (for the EKF's F_ve)."""
        return self._state.C_body_to_level @ self._f

    def gravity(self, position_ned: np.ndarray) -> np.ndarray:
        """Gravity at a point: exact at a reference point refreshed every metre, linear in
        between (the neglected curvature term is ~1e-12 m/s²)."""
        d = position_ned - self._gravity_at
        if not np.all(np.abs(d) < _GRAVITY_REFRESH_M):
            self._gravity_at = np.array(position_ned, float)
            self._gravity0 = gravity_level(self._gravity_at, self.origin_llh)
            d = np.zeros(3)
        return self._gravity0 + self._gravity_gradient @ d

    def _earth_rotation(self, dt: float) -> np.ndarray:
        # Rotation of L (with the Earth) over dt, cached: the IMU interval hardly ever changes.
        if dt != self._earth_dt:
            self._earth_dt = dt
            self._earth_dcm = rotvec_to_dcm(-self.omega_ie * dt)
        return self._earth_dcm

    def calibrate(self, gyro: np.ndarray, accel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Thesis' pre-processing: scale factor, misalignment and EKF bias estimates removed."""
        s = self._state
        return (self.gyro_correction @ (np.asarray(gyro, float) - s.gyro_bias),
                self.accel_correction @ (np.asarray(accel, float) - s.accel_bias))

    # -- mechanization ---------------------------------------------------------------------

    def propagate(self, t: float, gyro: np.ndarray, accel: np.ndarray) -> InsState:
        """Take one raw IMU sample at gpst ``t`` and integrate from the previous sample.

        The first sample after (re)initialisation only primes the two-sample formulas when
        ``t`` equals the state time; later than that it is held over the gap."""
        omega, f = self.calibrate(gyro, accel)
        s = self._state
        dt = float(t) - s.time
        if dt < -1e-9:
            raise ValueError(f"IMU sample at {t} precedes the INS time {s.time}")
        if self._raw is None:
            self._omega, self._f = omega, f  # no previous sample: hold this one
        self._raw = (np.array(gyro, float), np.array(accel, float))
        if dt <= 1e-9:
            self._omega, self._f = omega, f
            return self.state
        w0, f0 = self._omega, self._f
        w_mean, f_mean = 0.5 * (w0 + omega), 0.5 * (f0 + f)
        w_coning = w_mean + dt / 12.0 * _cross(w0, omega)
        f_sculling = (f_mean + 0.5 * dt * _cross(w_mean, f_mean)
                      + dt / 12.0 * (_cross(w0, f) - _cross(omega, f0)))

        C0, v0, r0 = s.C_body_to_level, s.velocity_ned, s.position_ned
        earth = self.omega_ie * dt
        # Velocity increment from the specific force, carried into L at the interval start and
        # corrected for the rotation of L (with the Earth) during the interval.
        dv_f = C0 @ f_sculling * dt
        dv_f = dv_f - 0.5 * _cross(earth, dv_f)
        g = self.gravity(r0 + 0.5 * dt * v0)
        v_mid = v0 + 0.5 * (dv_f + g * dt)
        v1 = v0 + dv_f + (g - 2.0 * _cross(self.omega_ie, v_mid)) * dt
        s.position_ned = r0 + 0.5 * dt * (v0 + v1)
        s.velocity_ned = v1
        earth_dcm, dC = self._earth_rotation(dt), rotvec_to_dcm(w_coning * dt)
        C1 = earth_dcm @ C0 @ dC
        self.C_gyro = earth_dcm @ self.C_gyro @ dC
        self.bias_turn += self.bias_yaw_rate * dt
        self._steps += 1
        if self._steps % _ORTHONORMALIZE_EVERY == 0:
            C1 = orthonormalize(C1)
            self.C_gyro = orthonormalize(self.C_gyro)
        s.C_body_to_level = C1
        s.time = float(t)
        self._omega, self._f = omega, f
        return self.state

    def correct(
        self,
        d_position: np.ndarray | None = None,
        d_velocity: np.ndarray | None = None,
        d_attitude: np.ndarray | None = None,
        d_gyro_bias: np.ndarray | None = None,
        d_accel_bias: np.ndarray | None = None,
    ) -> None:
        """EKF feedback: remove estimated errors (INS minus truth, see the module docstring).

        ``d_attitude`` is x_e, the small rotation (rad, level axes) with Ĉ = (I + [x_e×]) C, so
        the corrected attitude is exp(−[x_e×]) Ĉ. Bias corrections apply from the current
        sample on (the held previous sample is recalibrated)."""
        s = self._state
        if d_position is not None:
            s.position_ned = s.position_ned - np.asarray(d_position, float)
        if d_velocity is not None:
            s.velocity_ned = s.velocity_ned - np.asarray(d_velocity, float)
        if d_attitude is not None:
            s.C_body_to_level = orthonormalize(
                rotvec_to_dcm(-np.asarray(d_attitude, float)) @ s.C_body_to_level)
        if d_gyro_bias is not None:
            s.gyro_bias = s.gyro_bias - np.asarray(d_gyro_bias, float)
        if d_accel_bias is not None:
            s.accel_bias = s.accel_bias - np.asarray(d_accel_bias, float)
        if self._raw is not None and (d_gyro_bias is not None or d_accel_bias is not None):
            self._omega, self._f = self.calibrate(*self._raw)


# ----------------------------------------------------------------------------- error model

ERROR_STATE_SIZE = 15
IDX_R, IDX_V, IDX_E, IDX_W, IDX_A = (slice(3 * i, 3 * i + 3) for i in range(5))
_ZERO_15 = np.zeros((ERROR_STATE_SIZE, ERROR_STATE_SIZE))
_EYE_15 = np.eye(ERROR_STATE_SIZE)


def error_state_matrix(
    C_body_to_level: np.ndarray,
    specific_force_level: np.ndarray,
    origin_llh: np.ndarray,
    gyro_bias_tau: float = GYRO_BIAS_TAU_S,
    accel_bias_tau: float = ACCEL_BIAS_TAU_S,
    gyro_correction: np.ndarray | None = None,
    accel_correction: np.ndarray | None = None,
    gravity_gradient: np.ndarray | None = None,
) -> np.ndarray:
    """Continuous-time F (15x15) of ẋ = F x for x = [x_r, x_v, x_e, x_ω, x_a] (conventions in
    the module docstring), linearised about the INS solution:

        ẋ_r = x_v
        ẋ_v = Γ x_r − 2[ω_ie×] x_v − [f^L×] x_e − C_B^L A x_a
        ẋ_e = −[ω_ie×] x_e − C_B^L G x_ω
        ẋ_ω = −x_ω / T_ω,  ẋ_a = −x_a / T_a       (first-order Gauss–Markov)

    Γ is the gravity gradient; there are no transport-rate terms (Earth-fixed L)."""
    C = np.asarray(C_body_to_level, float)
    G = np.eye(3) if gyro_correction is None else gyro_correction
    A = np.eye(3) if accel_correction is None else accel_correction
    Gam = gravity_gradient_level(origin_llh) if gravity_gradient is None else gravity_gradient
    W = skew(earth_rate_level(origin_llh[0]))
    F = _ZERO_15.copy()  # (np.zeros of this size releases the GIL: ekf.flush)
    F[IDX_R, IDX_V] = np.eye(3)
    F[IDX_V, IDX_R] = Gam
    F[IDX_V, IDX_V] = -2.0 * W
    F[IDX_V, IDX_E] = -skew(specific_force_level)
    F[IDX_V, IDX_A] = -C @ A
    F[IDX_E, IDX_E] = -W
    F[IDX_E, IDX_W] = -C @ G
    F[IDX_W, IDX_W] = -np.eye(3) / gyro_bias_tau
    F[IDX_A, IDX_A] = -np.eye(3) / accel_bias_tau
    return F


def error_state_transition(
    dt: float,
    C_body_to_level: np.ndarray,
    specific_force_level: np.ndarray,
    origin_llh: np.ndarray,
    gyro_bias_tau: float = GYRO_BIAS_TAU_S,
    accel_bias_tau: float = ACCEL_BIAS_TAU_S,
    gyro_correction: np.ndarray | None = None,
    accel_correction: np.ndarray | None = None,
    gravity_gradient: np.ndarray | None = None,
) -> np.ndarray:
    """Discrete transition Φ = I + F dt + (F dt)²/2 over ``dt`` (F of ``error_state_matrix``,
    held over the interval). The bias blocks are the thesis' F_XX ≈ (1 − dt/T_X) I."""
    Fdt = dt * error_state_matrix(
        C_body_to_level, specific_force_level, origin_llh, gyro_bias_tau, accel_bias_tau,
        gyro_correction, accel_correction, gravity_gradient)
    return _EYE_15 + Fdt + 0.5 * Fdt @ Fdt


class RateSmoother:
    """The outputs' angular rate (the rate of turn shown, a hull point's speed on its lever):
    the calibrated gyro samples smoothed as much as the motion allows.

    One MEMS gyro sample's noise (~0.03°/s at 100 Hz) on a large ship's 160 m lever is 9 cm/s
    at the bow; smoothed over half a second, 1 cm/s. But a small boat in a chop yaws at
    ~2°/s², and half a second would put its rate 0.4°/s behind. Two running means measure
    the motion: their difference beyond the fast one's noise is the slow one's lag, a·τ_slow,
    which gives the rate's acceleration a; the output's time constant τ minimises the noise
    and the lag together, arw²/(2τ) + (aτ)² per axis: τ³ = 3·arw²/(4a²) over the three axes.
    The mechanisation itself integrates every sample as it comes."""

    FAST_S = 0.02  # the running means' time constants (s)
    SLOW_S = 0.5
    MEASURE_S = 2.0  # ... and the one their difference is averaged over

    def __init__(self, noise_density: float) -> None:
        self.arw2 = float(noise_density) ** 2  # (rad/s)²·s: an average over T has arw²/(2T)
        # what the two means' difference holds of the gyro noise alone (three axes)
        self._noise2 = 3.0 * self.arw2 * (1.0 / (2.0 * self.FAST_S) + 1.0 / (2.0 * self.SLOW_S))
        self.fast = self.slow = self.out = np.zeros(3)
        self.accel2 = 0.0  # the rate's squared acceleration, (rad/s²)², three axes
        self.tau = self.SLOW_S
        self._diff2: float | None = None

    def update(self, omega: np.ndarray, dt: float) -> None:
        """One calibrated sample ``omega`` (rad/s), ``dt`` after the previous one."""
        omega = np.asarray(omega, float)
        if self._diff2 is None:
            self.fast = self.slow = self.out = omega.copy()
            self._diff2 = 0.0
            return
        if dt <= 0.0:
            return
        self.fast = self.fast + min(dt / self.FAST_S, 1.0) * (omega - self.fast)
        self.slow = self.slow + min(dt / self.SLOW_S, 1.0) * (omega - self.slow)
        d = self.fast - self.slow
        self._diff2 += min(dt / self.MEASURE_S, 1.0) * (float(d @ d) - self._diff2)
        # the slow mean's lag beyond the noise, a·τ_slow
        self.accel2 = max(self._diff2 - self._noise2, 0.0) / self.SLOW_S**2
        self.tau = self.SLOW_S if self.accel2 <= 0.0 else min(max(
            (3.0 * self.arw2 / (4.0 * self.accel2)) ** (1.0 / 3.0), dt), self.SLOW_S)
        self.out = self.out + min(dt / self.tau, 1.0) * (omega - self.out)

    @property
    def sigma(self) -> float:
        """1-σ of one axis of ``out`` (rad/s): its noise and its lag (without the bias)."""
        return math.sqrt(self.arw2 / (2.0 * self.tau) + self.accel2 * self.tau**2 / 3.0)
