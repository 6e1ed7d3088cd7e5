"""Error-state EKF of the fusion (thesis 5.1 "EKF block", 5.2 tight coupling;
``METHOD.md``).

State (error = estimate − truth everywhere, as in ``estimator.ins``)::

    x = [x_r, x_v, x_e, x_ω, x_a | x_D, x_Z | x_θ, x_S, x_d | x_r⁻, x_e⁻]

- INS block (15): position, velocity, attitude (small angle in L, Ĉ = (I + [x_e×]) C), gyro and
  accel bias errors (raw sensor axes), time update of ``ins.error_state_transition`` (the
  bias errors as random walks: ``EkfConfig.gyro_bias_sigma``);
- CPP block: ``x_D`` (3) the errors of the inter-receiver delays δ_j = D_1j = d_1 − d_j of
  receivers 2..4 relative to receiver 1 (so D_ij = δ_j − δ_i, δ_1 ≡ 0), ``x_Z`` the clock drift
  (m/s) — ONE state for the common clock or one per receiver (``common_clock=False``);
- VO block: ``x_θ`` the error of the rotation C_W^L that carries the VO world into L (it
  absorbs the VO attitude drift), ``x_S`` the scale error (m per VO unit), ``x_d`` the error of
  the VO world origin in L (it absorbs the VO trajectory drift);
- a clone of x_r, x_e at the previous GNSS epoch (stochastic cloning): the carrier phase
  differenced over an epoch interval measures the DISPLACEMENT of each antenna, i.e. the
  integral of its velocity, so the TDCP rows see the position and attitude errors at both
  ends of the interval. The gyro-bias error enters through the attitude it has integrated
  between the two ends, the thesis' ``H_vω`` / ``H_ηω``.

All non-INS blocks are first-order Gauss–Markov, F_XX = (1 − Δt/T_X) I (thesis). After every
measurement update the estimated errors are fed back (closed loop) to every block: the INS
(``Ins.correct``), the delays and clock drift held here for the CPP block, the VO mapping
(C_W^L, scale, origin); the error state is then zero again.

Measurement models (y = measured − predicted = H x + u):

- y_r  standalone position of the array centre:  −x_r + [c×] x_e           (c = Ĉ l_centre)
- y_v  TDCP velocity of antenna i (loose):  −(x_r − [c×]x_e − x_r⁻ + [c⁻×]x_e⁻)/Δt
- y_η  line-of-sight displacement rate of antenna i to satellite k (tight): u·(same)/Δt − x_Z
- y_ζ  single difference ζ_ij^k − e^k·Ĉ(l_j − l_i):  (e × c_ij)·x_e − (x_δj − x_δi)
- y_Θ  VO attitude:  log(Ĉ_B^L C_C^B C_W^C · Ĉ_W^Lᵀ) = x_e − x_θ
- y_d  VO position:  ô + Ŝ Ĉ_W^L p_W − r̂_cam = x_d + x_S Ĉ_W^L p_W − Ŝ[Ĉ_W^L p_W ×] x_θ
                      − x_r + [Ĉ l_cam ×] x_e

The carrier phase of one epoch (η and ζ rows) is ONE update: both are linear in the
undifferenced phase noise of the epoch, and η also carries the previous epoch's noise. The
filter keeps the cross-covariance of its state with that previous noise, so consecutive TDCP
intervals telescope as they physically do (the integrated trajectory is as good as the phase at
its two ends) instead of random-walking; this is what keeps the position covariance honest.

The Kalman bookkeeping of the uncorrelated updates (Joseph form) is filterpy's
``KalmanFilter``; the correlated carrier-phase update and the time update (by blocks,
``flush``) are written out here. F, Q, H and R are built per step. Every measurement is
χ²-gated against the prior (row by row for η and ζ, as a vector for r, v, Θ, d); rejections
are counted in ``stats``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from filterpy.kalman import KalmanFilter
from scipy.stats import chi2

from .frames import dcm_to_rotvec, orthonormalize, rotvec_to_dcm, skew, vector_length
from .ins import IDX_A, IDX_E, IDX_R, IDX_V, IDX_W, Ins, error_state_transition
from .ins import gravity_gradient_level as _gravity_gradient

_DEG = math.pi / 180.0
_N_RX = 4


# ------------------------------------------------------------------------------ state layout


class StateIndex:
    """Named slices of the error state (KF-GINS style: ``P[ix.V, ix.E]`` reads like F_ve)."""

    def __init__(self, n_clocks: int) -> None:
        self.n_clocks = n_clocks
        self.R, self.V, self.E, self.BG, self.BA = IDX_R, IDX_V, IDX_E, IDX_W, IDX_A
        self.INS = slice(0, 15)
        self.D = slice(15, 18)  # δ_2, δ_3, δ_4 (receivers 2..4 vs receiver 1)
        self.Z = slice(18, 18 + n_clocks)
        k = 18 + n_clocks
        self.TH = slice(k, k + 3)
        self.S = slice(k + 3, k + 4)
        self.DV = slice(k + 4, k + 7)  # VO world origin ("trajectory drift")
        self.VO = slice(k, k + 7)
        self.R0 = slice(k + 7, k + 10)  # clones at the previous GNSS epoch
        self.E0 = slice(k + 10, k + 13)
        self.n = k + 13

    def clock(self, receiver: int) -> int:
        """State index of the clock drift seen by ``receiver`` (0..3)."""
        return self.Z.start + (receiver if self.n_clocks > 1 else 0)

    def delay(self, receiver: int) -> int | None:
        """State index of δ of ``receiver`` (None for receiver 0, the reference)."""
        return None if receiver == 0 else self.D.start + receiver - 1


# ------------------------------------------------------------------------------- tuning


@dataclass
class EkfConfig:
    """Noise densities, correlation times, initial uncertainties and gates (SI units).

    The INS figures default to a mid-range industrial MEMS unit; the simulated unit of
    ``recordings.sim.imu`` is within them."""

    gyro_arw: float = 0.2 * _DEG / 60.0  # rad/√s
    accel_vrw: float = 0.08 / 60.0  # m/s/√s
    # A MEMS bias is a turn-on constant (the init_* σ below) plus a slow Gauss–Markov
    # instability (σ, τ). The error of the constant does not fade by itself, so the bias
    # errors are random walks with the instability's density 2σ²/τ, not the thesis'
    # Gauss–Markov F = −1/τ: that let P forget the turn-on σ in a few τ without a measurement
    # (0.25 → 0.17 m/s² in 114 s), and the tilt tied to the accelerometer bias followed: a
    # large ship's pitch 0.5° off under σ 0.11° (seed 204, 4.6σ; 3.9σ as random walks).
    gyro_bias_sigma: float = 15.0 * _DEG / 3600.0  # rad/s, instability
    gyro_bias_tau: float = 300.0  # s
    accel_bias_sigma: float = 0.3e-3 * 9.80665  # m/s², instability
    accel_bias_tau: float = 300.0  # s
    delay_sigma: float = 0.005  # m, Gauss–Markov steady state of δ
    delay_tau: float = 3600.0
    clock_drift_psd: float = 0.08**2  # (m/s)²/s, random-walk density of Z
    clock_drift_tau: float = 1e4
    # VO drift grows with the distance travelled more than with time: each block has a time
    # density (rad²/s, 1/s, m²/s) plus a density per metre travelled (times the speed).
    # The attitude's time density is NOT small: a slow ship seeing a far scene sideways (large
    # ship, quay ~100 m abeam, 0.1 m/s) confuses lateral translation with yaw (bas-relief
    # ambiguity) and its VO yaw drifts ~0.03 deg/s (1.2 deg in 40 s on large-ship seed 5,
    # against < 0.1 deg in 80 s on the small boat). With (0.01 deg)²/s the 10 Hz Θ rows
    # (white 0.15 deg each, i.e. ~0.05 deg/√s together) outweighed the single differences
    # (~0.4 deg per epoch) and dragged the heading 0.7 deg off; at (0.1 deg)²/s the heading is
    # held by the single differences + gyro and the VO attitude only smooths it over seconds.
    vo_attitude_psd: float = (0.1 * _DEG) ** 2
    vo_attitude_per_m: float = (0.05 * _DEG) ** 2  # rad²/m
    vo_attitude_tau: float = 600.0
    vo_scale_psd: float = 0.001**2  # relative (times Ŝ²)
    vo_scale_per_m: float = 0.002**2  # relative²/m
    vo_scale_tau: float = 600.0
    vo_drift_psd: float = 0.005**2  # m²/s, drift of the VO origin
    vo_drift_per_m: float = 0.05**2  # m²/m
    vo_drift_tau: float = 600.0
    # initial 1-sigma
    init_velocity: float = 0.05  # m/s
    init_attitude: float = 2.0 * _DEG  # rad (GNSS compass single-epoch fix)
    init_gyro_bias: float = 0.1 * _DEG  # rad/s (turn-on bias of a MEMS gyro)
    init_accel_bias: float = 0.25  # m/s²
    init_delay: float = 0.02  # m, after the fractional-part estimate at the compass fix
    init_clock_drift: float = 300.0  # m/s (1 µs/s: unknown TCXO offset)
    # measurement noise
    phase_sigma_m: float = 0.0015  # undifferenced carrier phase at zenith (noise, multipath)
    # m/s, unmodelled rate of the TDCP (atmosphere, signal): one per satellite, common to its
    # antennas (the 1 mm/s it was for each antenna alone, averaged over four); an epoch's own
    # scatter replaces it when larger (a burst: ``cpp.tdcp_fit``)
    tdcp_rate_sigma: float = 0.0005
    vo_attitude_sigma: float = 0.15 * _DEG  # rad
    vo_position_sigma: float = 0.03  # m
    vo_position_relative: float = 0.005  # + this fraction of the VO distance from its origin
    # bookkeeping
    covariance_interval_s: float = 0.05  # P is propagated at this period (and before updates)
    gate_probability: float = 0.9999  # χ² quantile of the innovation gates


@lru_cache(maxsize=64)
def chi2_gate(dof: int, probability: float) -> float:
    return float(chi2.ppf(probability, dof))


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a × b of (m,3) arrays (``np.cross`` spends more on its axis handling than on
    the arithmetic for the few rows of a GNSS epoch)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


# ------------------------------------------------------------------------------ records


@dataclass(frozen=True)
class SdRow:
    """One single difference between receivers ``ref`` (i) and ``other`` (j) for ``sat``:
    ``value_m = λ·(Φ_i − Φ_j) − λ·N_ij`` (integers removed, delay NOT removed: the EKF owns D̂).
    ``los_ned`` is the unit vector receiver → satellite in L."""

    sat: str
    ref: int
    other: int
    los_ned: np.ndarray
    value_m: float
    sigma_m: float  # of one receiver's phase (the difference has √2 of it)


@dataclass(frozen=True)
class EtaInput:
    """One tightly coupled row: antenna (receiver) ``antenna`` to ``sat``, ``measured`` =
    λ·φ̇ + v^k (m/s) over ``interval`` s ending at the epoch, ``u_ned`` the unit vector
    satellite → antenna in L."""

    antenna: int
    sat: str
    u_ned: np.ndarray
    measured: float
    sigma: float
    interval: float


@dataclass(frozen=True)
class VelocityInput:
    """Loosely coupled TDCP velocity of one antenna (mean over ``interval``), L axes."""

    antenna: int
    velocity_ned: np.ndarray
    covariance: np.ndarray
    interval: float


@dataclass
class UpdateResult:
    kind: str
    rows: int
    accepted: int
    rejected: list[int] = field(default_factory=list)  # indices of the rows (or all, vector)
    nis: float = 0.0  # normalised innovation squared of the accepted rows
    dof: int = 0


@dataclass
class GateStats:
    updates: int = 0
    accepted: int = 0
    rejected: int = 0
    nis_sum: float = 0.0
    dof_sum: int = 0

    @property
    def mean_nis_per_dof(self) -> float:
        return self.nis_sum / self.dof_sum if self.dof_sum else math.nan


@dataclass
class VoMapping:
    """Nominal mapping of a VO segment into L: x_L = origin + scale · C_world_to_level @ x_W."""

    segment: int
    C_world_to_level: np.ndarray
    scale: float
    origin_ned: np.ndarray


@dataclass
class _CarrierEpoch:
    """What one carrier-phase epoch's satellites share while they are processed in turn:
    its η and ζ inputs and their rows (y, H at the nominal, η first), the state's
    cross-covariance with the previous epoch's phase noise (``M_prev``, columns ``prev``) and
    with this epoch's (``M_new``, the first ``n_new`` columns filled, keys ``new_keys``), and
    the results."""

    eta: list[EtaInput]
    sds: Sequence[SdRow]
    prev: dict[tuple[int, str], int]
    M_prev: np.ndarray
    results: tuple[UpdateResult, UpdateResult]
    rate_sigma: float
    y: np.ndarray = field(default_factory=lambda: np.zeros(0))
    H: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    M_new: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    n_new: int = 0
    new_keys: list[tuple[int, str]] = field(default_factory=list)


# --------------------------------------------------------------------------------- filter


class ErrorStateEkf:
    """Closed-loop error-state EKF around an ``Ins`` (which it propagates and corrects).

    ``antennas_body`` (4,3) and the camera lever arm are body-frame positions; they are used
    relative to the IMU (``ins.calibration.lever_arm_body``), the point the INS navigates.
    """

    def __init__(
        self,
        ins: Ins,
        antennas_body: np.ndarray,
        *,
        camera_to_body: np.ndarray | None = None,
        camera_lever_body: np.ndarray | None = None,
        common_clock: bool = True,
        config: EkfConfig | None = None,
        clock_drift: float = 0.0,
        initial_sigmas: dict[str, float] | None = None,
    ) -> None:
        self.ins = ins
        self.cfg = cfg = config or EkfConfig()
        imu_lever = np.asarray(ins.calibration.lever_arm_body, float)
        self.lever_antennas = np.asarray(antennas_body, float) - imu_lever  # (4,3)
        self.lever_centre = self.lever_antennas.mean(axis=0)
        self.C_camera_to_body = np.eye(3) if camera_to_body is None else np.asarray(
            camera_to_body, float)
        cam = np.zeros(3) if camera_lever_body is None else np.asarray(camera_lever_body, float)
        self.lever_camera = cam - imu_lever
        self.common_clock = common_clock
        self.ix = ix = StateIndex(1 if common_clock else _N_RX)
        self._gamma = _gravity_gradient(ins.origin_llh)

        # Nominal values of the non-INS blocks (fed back like the INS).
        self.delays = np.zeros(3)  # δ̂_2..4 (m)
        self.clock_drift = np.full(ix.n_clocks, float(clock_drift))  # Ẑ (m/s)
        self.vo: VoMapping | None = None
        self.clone_time: float | None = None
        self._clone_position = np.zeros(3)
        self._clone_attitude = np.eye(3)

        self.kf = KalmanFilter(dim_x=ix.n, dim_z=1)
        sig = dict(velocity=cfg.init_velocity, attitude=cfg.init_attitude,
                   gyro_bias=cfg.init_gyro_bias, accel_bias=cfg.init_accel_bias,
                   delay=cfg.init_delay, clock_drift=cfg.init_clock_drift)
        sig.update(initial_sigmas or {})
        P = np.zeros((ix.n, ix.n))
        P[ix.R, ix.R] = np.eye(3) * sig.get("position", 0.0) ** 2  # the world origin: exact
        P[ix.V, ix.V] = np.eye(3) * sig["velocity"] ** 2
        P[ix.E, ix.E] = np.eye(3) * sig["attitude"] ** 2
        P[ix.BG, ix.BG] = np.eye(3) * sig["gyro_bias"] ** 2
        P[ix.BA, ix.BA] = np.eye(3) * sig["accel_bias"] ** 2
        P[ix.D, ix.D] = np.eye(3) * sig["delay"] ** 2
        P[ix.Z, ix.Z] = np.eye(ix.n_clocks) * sig["clock_drift"] ** 2
        P[ix.VO, ix.VO] = np.eye(7)  # unused until a VO segment starts (then re-initialised)
        self.kf.P = P
        self.kf.x = np.zeros((ix.n, 1))
        self._acc_dt = 0.0
        self._acc_f = np.zeros(3)
        # Cross-covariance of the error state with the carrier-phase noise of the last epoch
        # (one column per (receiver, sat)): that noise is in the next interval's η again.
        self._noise_keys: list[tuple[int, str]] = []
        self._noise_M = np.zeros((ix.n, 0))
        self._noise_time: float | None = None
        self.stats: dict[str, GateStats] = {}
        self.nominal = ins.state  # INS solution snapshot (refreshed on propagate / feedback)
        self.clone(self.nominal.time)

    # ------------------------------------------------------------------------ accessors

    @property
    def P(self) -> np.ndarray:
        return self.kf.P

    @property
    def time(self) -> float:
        return self.nominal.time

    def covariance(self, block: slice) -> np.ndarray:
        self.flush()
        return self.kf.P[block, block].copy()

    # ---------------------------------------------------------------------- time update

    def propagate(self, t: float, gyro: np.ndarray, accel: np.ndarray) -> None:
        """INS mechanization to ``t`` with one raw IMU sample; the covariance follows every
        ``covariance_interval_s`` (and before any measurement)."""
        t_prev = self.nominal.time
        self.nominal = self.ins.propagate(t, gyro, accel)
        dt = self.nominal.time - t_prev
        if dt > 0.0:
            self._acc_dt += dt
            self._acc_f += self.ins.specific_force_level * dt
            if self._acc_dt >= self.cfg.covariance_interval_s:
                self.flush()

    def flush(self) -> None:
        """Propagate P over the accumulated interval (thesis P_{t+1/t} = F P Fᵀ + Q).

        By blocks: Φ is the INS block's transition and a diagonal elsewhere (the Gauss–Markov
        factors, 1 for the clones), and Q_c is diagonal. Done densely (filterpy's predict),
        every n × n allocation, product and sum released the GIL, and at each of them the
        fusion's thread waited for a busy worker thread to give it back (~0.5 ms a flush
        beside the VO's look-ahead); the blocks are small enough to keep it."""
        dt = self._acc_dt
        if dt <= 0.0:
            return
        f_mean = self._acc_f / dt
        self._acc_dt, self._acc_f = 0.0, np.zeros(3)
        cfg, ix, ins = self.cfg, self.ix, self.ins
        Phi = error_state_transition(
            dt, self.nominal.C_body_to_level, f_mean, ins.origin_llh, math.inf, math.inf,
            ins.gyro_correction, ins.accel_correction, self._gamma)  # random-walk biases
        q = np.zeros(ix.n)  # white-noise densities on the diagonal of Q_c
        q[ix.V] = cfg.accel_vrw**2
        q[ix.E] = cfg.gyro_arw**2
        q[ix.BG] = 2.0 * cfg.gyro_bias_sigma**2 / cfg.gyro_bias_tau
        q[ix.BA] = 2.0 * cfg.accel_bias_sigma**2 / cfg.accel_bias_tau
        phi_diag = np.ones(ix.n)  # Φ's diagonal outside the INS block
        speed = vector_length(self.nominal.velocity_ned)
        s2 = self.vo.scale**2 if self.vo is not None else 1.0
        # Gauss–Markov blocks: F_XX = (1 − Δt/T_X) I  (thesis)
        for block, tau, psd in (
            (ix.D, cfg.delay_tau, 2.0 * cfg.delay_sigma**2 / cfg.delay_tau),
            (ix.Z, cfg.clock_drift_tau, cfg.clock_drift_psd),
            (ix.TH, cfg.vo_attitude_tau, cfg.vo_attitude_psd + cfg.vo_attitude_per_m * speed),
            (ix.S, cfg.vo_scale_tau, (cfg.vo_scale_psd + cfg.vo_scale_per_m * speed) * s2),
            (ix.DV, cfg.vo_drift_tau, cfg.vo_drift_psd + cfg.vo_drift_per_m * speed),
        ):
            phi_diag[block] = 1.0 - dt / tau
            q[block] = psd
        I, O = ix.INS, slice(ix.INS.stop, ix.n)
        d, qI, qO = phi_diag[O], q[I], q[O]
        # Q_d = ½ (Φ Q_c Φᵀ + Q_c) Δt (trapezoid; gives the Q_rv, Q_rr of the thesis' Q).
        # P's blocks symmetrised first: the updates leave it asymmetric by rounding (1e-12),
        # and a cross block taken from one side only while the others keep theirs makes a P
        # that is no covariance (the no-carrier-phase INS+VO run went 1.7 -> 270 m so).
        P, P_new = self.kf.P, np.empty_like(self.kf.P)
        kI, kO = np.arange(I.stop - I.start), np.arange(O.stop - O.start)
        P_II = Phi @ (0.5 * (P[I, I] + P[I, I].T)) @ Phi.T + 0.5 * dt * ((Phi * qI) @ Phi.T)
        P_II[kI, kI] += 0.5 * dt * qI
        P_OO = 0.5 * (P[O, O] + P[O, O].T) * np.outer(d, d)
        P_OO[kO, kO] += 0.5 * dt * (d * d + 1.0) * qO
        P_new[I, I], P_new[O, O] = P_II, P_OO
        P_new[I, O] = (Phi @ (0.5 * (P[I, O] + P[O, I].T))) * d
        P_new[O, I] = P_new[I, O].T
        self.kf.P = P_new
        x = self.kf.x  # (zero between updates: the errors are fed back)
        x[I], x[O] = Phi @ x[I], d[:, None] * x[O]
        M = self._noise_M
        self._noise_M = np.vstack([Phi @ M[I], d[:, None] * M[O]])

    # ------------------------------------------------------------------- state surgery

    def _transform(self, T: np.ndarray, extra: np.ndarray | None = None) -> None:
        """x ← T x (+ independent noise of covariance ``extra``): resets, clones, augmentation."""
        P = T @ self.kf.P @ T.T
        if extra is not None:
            P = P + extra
        self.kf.P = 0.5 * (P + P.T)
        self._noise_M = T @ self._noise_M

    def clone(self, t: float) -> None:
        """Start a TDCP interval at ``t`` (the current INS time): x_r⁻ ← x_r, x_e⁻ ← x_e."""
        self.flush()
        ix = self.ix
        T = np.eye(ix.n)
        T[ix.R0, :] = 0.0
        T[ix.E0, :] = 0.0
        T[ix.R0, ix.R] = np.eye(3)
        T[ix.E0, ix.E] = np.eye(3)
        self._transform(T)
        s = self.nominal
        self.clone_time = float(t)
        self._clone_position = s.position_ned.copy()
        self._clone_attitude = s.C_body_to_level.copy()

    def inflate(self, position_m: float, velocity_mps: float, attitude_rad: float,
                accel_bias: float = 0.0, gyro_bias: float = 0.0) -> None:
        """Widen the INS error covariance by these 1-σ (per axis; biases in m/s² and rad/s):
        motion the IMU did not measure (a gap) or measured wrong, so that the next carrier
        phase is weighed against what is known."""
        self.flush()
        ix, P = self.ix, self.kf.P
        P[ix.R, ix.R] += np.eye(3) * position_m**2
        P[ix.V, ix.V] += np.eye(3) * velocity_mps**2
        P[ix.E, ix.E] += np.eye(3) * attitude_rad**2
        P[ix.BA, ix.BA] += np.eye(3) * accel_bias**2
        P[ix.BG, ix.BG] += np.eye(3) * gyro_bias**2

    def mean_velocity_covariance(self, interval: float) -> np.ndarray:
        """Covariance (m²/s²) of the predicted mean velocity of an antenna since the clone,
        what the η rows over ``interval`` s measure (the array's lever arms aside)."""
        self.flush()
        J = self._displacement_rows(0)[1]
        return J @ self.kf.P @ J.T / interval**2

    def reset_delays(self, delays: np.ndarray, sigma: float, reference: int = 0,
                     unknown: float = 0.0) -> None:
        """New δ̂ (e.g. from the fractional parts at the compass fix), uncorrelated, σ each.
        ``reference`` > 0: they were found against that receiver, receiver 1 not tracking:
        its δ̂ is exact relative to the others, and all of them are off by one common
        ``unknown`` (σ, m) against receiver 1 (pairs without it do not see that)."""
        self.flush()
        ix = self.ix
        self.delays = np.asarray(delays, float).copy()
        T = np.eye(ix.n)
        T[ix.D, ix.D] = 0.0
        cov = np.eye(3) * sigma**2
        if reference:
            cov[reference - 1, reference - 1] = 0.0
            cov += unknown**2
        extra = np.zeros((ix.n, ix.n))
        extra[ix.D, ix.D] = cov
        self._transform(T, extra)

    # ----------------------------------------------------------------------- the update

    def _update(self, kind: str, y: np.ndarray, H: np.ndarray, R: np.ndarray,
                per_row: bool, hold: Sequence[slice] = ()) -> UpdateResult:
        """χ²-gate and apply one measurement group, then feed the errors back. ``hold``:
        states the group must not correct (a Schmidt–Kalman update: their gain rows are
        zero, their covariance and correlations stay as the measurement leaves them)."""
        self.flush()
        st = self.stats.setdefault(kind, GateStats())
        m = len(y)
        res = UpdateResult(kind=kind, rows=m, accepted=0)
        if m == 0:
            return res
        P = self.kf.P
        S = H @ P @ H.T + R
        p = self.cfg.gate_probability
        if per_row:
            ok = y**2 / np.diag(S) <= chi2_gate(1, p)
            keep = np.flatnonzero(ok)
            res.rejected = [int(i) for i in np.flatnonzero(~ok)]
        else:
            d2 = float(y @ np.linalg.solve(S, y))
            keep = np.arange(m) if d2 <= chi2_gate(m, p) else np.zeros(0, int)
            res.rejected = [] if len(keep) else list(range(m))
        st.updates += 1
        st.rejected += len(res.rejected)
        if len(keep) == 0:
            return res
        yk, Hk, Rk = y[keep], H[keep], R[np.ix_(keep, keep)]
        Sk = S[np.ix_(keep, keep)]
        res.nis = float(yk @ np.linalg.solve(Sk, yk))
        res.dof = res.accepted = len(keep)
        st.accepted += len(keep)
        st.nis_sum += res.nis
        st.dof_sum += len(keep)
        if hold:
            self._schmidt_update(yk, Hk, Rk, Sk, hold)
        else:
            self.kf.update(yk.reshape(-1, 1), R=Rk, H=Hk)
        self._noise_M = self._noise_M - self.kf.K @ (Hk @ self._noise_M)
        self._feedback()
        return res

    def _schmidt_update(self, y: np.ndarray, H: np.ndarray, R: np.ndarray, S: np.ndarray,
                        hold: Sequence[slice]) -> None:
        """x = K y with the ``hold`` rows of K zeroed; P in Joseph form, which holds for any
        gain (the optimal one's short form does not)."""
        P = self.kf.P
        K = np.linalg.solve(S, H @ P).T  # P Hᵀ S⁻¹ (S, P symmetric)
        for block in hold:
            K[block] = 0.0
        IKH = -(K @ H)  # I − K H without a fresh identity (a 32×32 np.eye releases the GIL)
        IKH[np.diag_indices_from(IKH)] += 1.0
        P = IKH @ P @ IKH.T + K @ R @ K.T
        self.kf.P = 0.5 * (P + P.T)
        self.kf.x = K @ y.reshape(-1, 1)
        self.kf.K = K

    def _feedback(self) -> None:
        """Closed loop: remove the estimated errors from every block, zero the error state."""
        ix = self.ix
        x = self.kf.x.ravel()
        self.ins.correct(d_position=x[ix.R], d_velocity=x[ix.V], d_attitude=x[ix.E],
                         d_gyro_bias=x[ix.BG], d_accel_bias=x[ix.BA])
        self.delays = self.delays - x[ix.D]
        self.clock_drift = self.clock_drift - x[ix.Z]
        if self.vo is not None:
            vo = self.vo
            vo.C_world_to_level = orthonormalize(rotvec_to_dcm(-x[ix.TH]) @ vo.C_world_to_level)
            vo.scale = float(vo.scale - x[ix.S][0])
            vo.origin_ned = vo.origin_ned - x[ix.DV]
        self._clone_position = self._clone_position - x[ix.R0]
        self._clone_attitude = rotvec_to_dcm(-x[ix.E0]) @ self._clone_attitude
        self.kf.x = np.zeros((ix.n, 1))
        self.nominal = self.ins.state

    # ------------------------------------------------------------------ GNSS updates

    def antenna_position(self, antenna: int | None = None) -> np.ndarray:
        """Current nominal position of an antenna (None: the array centre) in L."""
        s = self.nominal
        lever = self.lever_centre if antenna is None else self.lever_antennas[antenna]
        return s.position_ned + s.C_body_to_level @ lever

    @property
    def since_clone(self) -> float | None:
        """Seconds from the clone (the previous GNSS epoch) to now; None before one."""
        return None if self.clone_time is None else self.time - self.clone_time

    def interval_ok(self, interval: float) -> bool:
        """Whether carrier-phase rows over ``interval`` s end now and start at the clone."""
        since = self.since_clone
        return since is not None and abs(since - interval) < 2e-3

    def eta_model(self, antenna: int, u_ned: np.ndarray, interval: float
                  ) -> tuple[float, np.ndarray]:
        """Predicted η row u·Δr̂_i/Δt + Ẑ and its H (y = measured − predicted = H x)."""
        pred, H = self.eta_rows([antenna], np.reshape(u_ned, (1, 3)), [interval])
        return float(pred[0]), H[0]

    def eta_rows(self, antennas: Sequence[int], u_ned: np.ndarray, intervals: Sequence[float]
                 ) -> tuple[np.ndarray, np.ndarray]:
        """``eta_model`` of m rows at once: antennas (m,), unit vectors (m,3), Δt (m,)."""
        ix = self.ix
        a = np.asarray(antennas, int)
        U = np.asarray(u_ned, float).reshape(-1, 3)
        dt = np.asarray(intervals, float)[:, None]
        c_now, c_then, disp = self._displacements(a)
        z = a if ix.n_clocks > 1 else np.zeros_like(a)
        # −u·(x_r − [c×]x_e − x_r⁻ + [c⁻×]x_e⁻)/Δt − x_Z, with u·[c×]x = (u × c)·x
        H = np.zeros((len(a), ix.n))
        H[:, ix.R] = -U / dt
        H[:, ix.E] = _cross_rows(U, c_now) / dt
        H[:, ix.R0] = U / dt
        H[:, ix.E0] = -_cross_rows(U, c_then) / dt
        H[np.arange(len(a)), ix.Z.start + z] = -1.0
        pred = np.einsum("ij,ij->i", U, disp) / dt[:, 0] + self.clock_drift[z]
        return pred, H

    def _displacements(self, antennas: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Antennas' lever arms in L now and at the clone (c, c⁻) and their predicted
        displacements since the clone, (m, 3) each."""
        s = self.nominal
        lever = self.lever_antennas[antennas]
        c_now = lever @ s.C_body_to_level.T
        c_then = lever @ self._clone_attitude.T
        return c_now, c_then, (s.position_ned + c_now) - (self._clone_position + c_then)

    def _displacement_rows(self, antenna: int) -> tuple[np.ndarray, np.ndarray]:
        """Predicted displacement of an antenna since the clone and ∂(it)/∂x (3 × n):
        error = x_r − [c×]x_e − x_r⁻ + [c⁻×]x_e⁻."""
        ix = self.ix
        (c_now,), (c_then,), (disp,) = self._displacements(np.array([antenna]))
        J = np.zeros((3, ix.n))
        J[:, ix.R] = np.eye(3)
        J[:, ix.E] = -skew(c_now)
        J[:, ix.R0] = -np.eye(3)
        J[:, ix.E0] = skew(c_then)
        return disp, J

    def update_velocity(self, velocities: Sequence[VelocityInput]) -> UpdateResult:
        """Loosely coupled TDCP velocity of each antenna (thesis 5.1 y_v), one gate each."""
        out = UpdateResult(kind="velocity", rows=0, accepted=0)
        for v in velocities:
            if not self.interval_ok(v.interval):
                continue
            y, J = self.velocity_innovation(v)
            r = self._update("velocity", y, -J / v.interval, np.asarray(v.covariance), False)
            out.rows += r.rows
            out.accepted += r.accepted
            out.rejected += [v.antenna] if r.rejected else []
            out.nis += r.nis
            out.dof += r.dof
        return out

    def velocity_innovation(self, v: VelocityInput) -> tuple[np.ndarray, np.ndarray]:
        """A loose TDCP velocity less the INS's mean velocity of its antenna over the
        interval (m/s), and the displacement's Jacobian (what ``update_velocity`` gates)."""
        disp, J = self._displacement_rows(v.antenna)
        return np.asarray(v.velocity_ned, float) - disp / v.interval, J

    def predict_single_difference(self, ref: int, other: int, los_ned: np.ndarray,
                                  sigma_m: float) -> tuple[float, float]:
        """Predicted ``λΦ_ij − λN_ij`` = e·Ĉ(l_j − l_i) + D̂_ij and its σ (m), for rounding N."""
        self.flush()
        pred, h = self.sd_model(ref, other, np.asarray(los_ned, float))
        var = h @ self.kf.P @ h + 2.0 * sigma_m**2
        return pred, math.sqrt(var)

    def sd_model(self, i: int, j: int, e: np.ndarray) -> tuple[float, np.ndarray]:
        """Predicted λΦ_ij − λN_ij = e·Ĉ(l_j − l_i) + D̂_ij and its H (y = H x)."""
        pred, H = self.sd_rows([i], [j], np.reshape(e, (1, 3)))
        return float(pred[0]), H[0]

    def sd_rows(self, refs: Sequence[int], others: Sequence[int], los_ned: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """``sd_model`` of m rows at once: receivers i (m,), j (m,), unit vectors e (m,3)."""
        ix = self.ix
        i, j = np.asarray(refs, int), np.asarray(others, int)
        E = np.asarray(los_ned, float).reshape(-1, 3)
        c = (self.lever_antennas[j] - self.lever_antennas[i]) @ self.nominal.C_body_to_level.T
        H = np.zeros((len(i), ix.n))
        H[:, ix.E] = _cross_rows(E, c)
        rows = np.arange(len(i))
        # D_ij = δ_j − δ_i (receiver 1, index 0, has no δ)
        H[rows[j > 0], ix.D.start + j[j > 0] - 1] -= 1.0
        H[rows[i > 0], ix.D.start + i[i > 0] - 1] += 1.0
        d = np.concatenate([[0.0], self.delays])
        return np.einsum("ij,ij->i", E, c) + d[j] - d[i], H

    def delay_difference(self, i: int, j: int) -> float:
        """D̂_ij = d_i − d_j = δ̂_j − δ̂_i (m)."""
        d = np.concatenate([[0.0], self.delays])
        return float(d[j] - d[i])

    def update_carrier_phase(self, eta: Sequence[EtaInput], sds: Sequence[SdRow],
                             rate_sigma: float | None = None
                             ) -> tuple[UpdateResult, UpdateResult]:
        """The carrier phase of one epoch k, satellite by satellite (rows gated one by one):

        - y_η = measured − (u·Δr̂_i/Δt + Ẑ) per antenna and satellite (thesis 5.2,
          η_i^k = λφ̇_i^k + v^k − Ẑ, one Ẑ for the common clock);
        - y_ζ = ζ_ij^k − e^k·Ĉ(l_j − l_i) with ζ = λΦ_ij − D̂_ij − λN_ij (thesis eq. of ζ).

        Both are linear in the undifferenced phase noise n of epochs k and k−1: η carries
        (n_k − n_{k−1})/Δt, ζ carries n_i,k − n_j,k. The filter keeps the cross-covariance of
        its state with n_{k−1} (from the previous epoch's gains), so the TDCP of consecutive
        intervals telescopes — the integrated trajectory has the phase noise of its two end
        epochs, not a random walk of it — and the ζ rows are correlated with the η rows and
        among themselves exactly. Different satellites' noises are independent, so the
        satellites are processed one after the other (exact for the linear update, and small
        matrices only). filterpy has no cross-covariance term, so this update is written out
        here (Joseph form with correlated noise). ``rate_sigma`` (m/s): the TDCP's unmodelled
        rate, common to a satellite's antennas (``EkfConfig.tdcp_rate_sigma`` when None)."""
        self.flush()
        eta = [r for r in eta if self.interval_ok(r.interval)]
        valid = self._noise_time is not None and self.clone_time is not None \
            and abs(self._noise_time - self.clone_time) < 2e-3
        ep = _CarrierEpoch(
            eta=eta, sds=sds,
            prev={k: c for c, k in enumerate(self._noise_keys)} if valid else {},
            M_prev=self._noise_M if valid else np.zeros((self.ix.n, 0)),
            results=(UpdateResult(kind="eta", rows=len(eta), accepted=0),
                     UpdateResult(kind="zeta", rows=len(sds), accepted=0)),
            rate_sigma=self.cfg.tdcp_rate_sigma if rate_sigma is None else rate_sigma)
        # Every row is linearised at the same nominal (fed back once, after the epoch).
        pe, He = self.eta_rows([r.antenna for r in eta], [r.u_ned for r in eta],
                               [r.interval for r in eta])
        ps, Hs = self.sd_rows([r.ref for r in sds], [r.other for r in sds],
                              [r.los_ned for r in sds])
        ep.y = np.concatenate([[r.measured for r in eta] - pe, [r.value_m for r in sds] - ps])
        ep.H = np.vstack([He, Hs])
        groups: dict[str, tuple[list[int], list[int]]] = {}
        for k, r in enumerate(eta):
            groups.setdefault(r.sat, ([], []))[0].append(k)
        for q, r in enumerate(sds):
            groups.setdefault(r.sat, ([], []))[1].append(q)
        ep.M_new = np.zeros((self.ix.n, _N_RX * len(groups)))  # at most, trimmed below
        for sat, (e_idx, s_idx) in groups.items():
            self._carrier_satellite(ep, sat, e_idx, s_idx)
        self._feedback()
        for res in ep.results:
            st = self.stats.setdefault(res.kind, GateStats())
            st.updates += 1 if res.accepted else 0
            st.accepted += res.accepted
            st.rejected += len(res.rejected)
            st.nis_sum += res.nis
            st.dof_sum += res.dof
        self._noise_keys = ep.new_keys
        self._noise_M = ep.M_new[:, :ep.n_new]
        self._noise_time = self.time
        return ep.results

    def _carrier_satellite(self, ep: _CarrierEpoch, sat: str, e_idx: list[int],
                           s_idx: list[int]) -> None:
        """One satellite's η and ζ rows (indices ``e_idx`` into the epoch's η, ``s_idx`` into
        its ζ): y = H x + A n_k + (own noise), cov(x, v) = Cxv."""
        ix = self.ix
        e_rows, s_rows = [ep.eta[k] for k in e_idx], [ep.sds[q] for q in s_idx]
        rx = sorted({r.antenna for r in e_rows} | {r.ref for r in s_rows}
                    | {r.other for r in s_rows})
        col = {a: c for c, a in enumerate(rx)}
        n_eta = len(e_rows)
        m = n_eta + len(s_rows)
        rows = np.array(e_idx + [len(ep.eta) + q for q in s_idx], int)
        y, H = ep.y[rows], ep.H[rows]
        sig = np.zeros(len(rx))
        A = np.zeros((m, len(rx)))
        R_own = np.zeros(m)  # noise not shared with other rows: n_{k−1} of η, TDCP rate
        Cxv = np.zeros((ix.n, m))
        for k, r in enumerate(e_rows):
            s_phase = r.sigma * r.interval / math.sqrt(2.0)
            sig[col[r.antenna]] = s_phase
            A[k, col[r.antenna]] = 1.0 / r.interval
            R_own[k] = (s_phase / r.interval) ** 2
            c = ep.prev.get((r.antenna, sat))
            if c is not None:
                Cxv[:, k] = -ep.M_prev[:, c] / r.interval
        for q, r in enumerate(s_rows):
            k = n_eta + q
            sig[col[r.ref]] = sig[col[r.ref]] or r.sigma_m
            sig[col[r.other]] = sig[col[r.other]] or r.sigma_m
            A[k, col[r.ref]] = 1.0
            A[k, col[r.other]] = -1.0
        Sig = sig**2
        R = (A * Sig) @ A.T + np.diag(R_own)
        # The TDCP's unmodelled rate (the atmosphere's change, multipath) is the satellite's:
        # one for the four antennas 10 cm apart, not four independent ones.
        R[:n_eta, :n_eta] += ep.rate_sigma**2
        y = y - H @ self.kf.x[:, 0]  # errors estimated from the satellites done so far
        P = self.kf.P
        PHt = P @ H.T + Cxv
        S = H @ PHt + Cxv.T @ H.T + R
        ok = y**2 / np.diag(S) <= chi2_gate(1, self.cfg.gate_probability)
        keep = np.flatnonzero(ok)
        is_sd = np.arange(m) >= n_eta
        ep.results[0].rejected.extend(e_idx[k] for k in np.flatnonzero(~ok & ~is_sd))
        ep.results[1].rejected.extend(s_idx[k - n_eta] for k in np.flatnonzero(~ok & is_sd))
        cols = slice(ep.n_new, ep.n_new + len(rx))
        ep.n_new = cols.stop
        ep.new_keys += [(a, sat) for a in rx]
        if len(keep) == 0:
            return
        S_kk = S[np.ix_(keep, keep)]
        for kind in (0, 1):
            kk = np.flatnonzero(is_sd[keep] == bool(kind))
            if len(kk):
                res = ep.results[kind]
                res.accepted += len(kk)
                res.dof += len(kk)
                res.nis += float(y[keep[kk]] @ np.linalg.solve(S_kk[np.ix_(kk, kk)],
                                                               y[keep[kk]]))
        Hk, Ck, Ak = H[keep], Cxv[:, keep], A[keep]
        K = np.linalg.solve(S_kk, PHt[:, keep].T).T
        self.kf.x = self.kf.x + K @ y[keep].reshape(-1, 1)
        IKH = np.eye(ix.n) - K @ Hk
        cross = IKH @ Ck @ K.T
        P = IKH @ P @ IKH.T + K @ R[np.ix_(keep, keep)] @ K.T - cross - cross.T
        self.kf.P = 0.5 * (P + P.T)
        # The state's cross-covariance with the other noises: n_{k−1} and this epoch's noise
        # of the satellites done so far (both independent of this satellite's v).
        ep.M_prev = IKH @ ep.M_prev
        ep.M_new[:, :cols.start] = IKH @ ep.M_new[:, :cols.start]
        ep.M_new[:, cols] = -(K @ Ak) * Sig

    def update_position(self, centre_ned: np.ndarray, covariance: np.ndarray) -> UpdateResult:
        """Standalone position of the array centre in L (loose, thesis y_r)."""
        ix = self.ix
        c = self.nominal.C_body_to_level @ self.lever_centre
        H = np.zeros((3, ix.n))
        H[:, ix.R] = -np.eye(3)
        H[:, ix.E] = skew(c)
        y = np.asarray(centre_ned, float) - self.antenna_position(None)
        return self._update("position", y, H, np.asarray(covariance, float), per_row=False)

    # --------------------------------------------------------------------- VO updates

    def camera_position(self) -> np.ndarray:
        s = self.nominal
        return s.position_ned + s.C_body_to_level @ self.lever_camera

    def camera_attitude(self) -> np.ndarray:
        """C_L^C of the nominal state: level frame → camera frame."""
        return (self.nominal.C_body_to_level @ self.C_camera_to_body).T

    def measured_world_to_level(self, C_world_to_camera: np.ndarray) -> np.ndarray:
        """Ĉ_B^L C_C^B C_W^C: where the INS attitude and the VO put the VO world (thesis Θ)."""
        C = self.nominal.C_body_to_level
        return C @ self.C_camera_to_body @ np.asarray(C_world_to_camera, float)

    def start_vo_segment(self, segment: int, C_world_to_camera: np.ndarray,
                         camera_position_world: np.ndarray, scale: float,
                         scale_sigma: float) -> None:
        """New VO world: C_W^L from the current INS attitude, origin so that the VO position
        matches the INS camera position now. The VO error states are augmented as functions of
        the INS errors (x_θ = x_e, x_d = x_r − [c×]x_e + Ŝ[u×]x_e − u x_S) plus the unknown
        scale, so their correlations are exact."""
        self.flush()
        ix = self.ix
        Cw = orthonormalize(self.measured_world_to_level(C_world_to_camera))
        p = np.asarray(camera_position_world, float)
        u = Cw @ p
        c = self.nominal.C_body_to_level @ self.lever_camera
        self.vo = VoMapping(segment=segment, C_world_to_level=Cw, scale=float(scale),
                            origin_ned=self.camera_position() - scale * u)
        T = np.eye(ix.n)
        T[ix.VO, :] = 0.0
        T[ix.TH, ix.E] = np.eye(3)
        T[ix.DV, ix.R] = np.eye(3)
        T[ix.DV, ix.E] = scale * skew(u) - skew(c)
        B = np.zeros((ix.n, 1))
        B[ix.S.start] = 1.0
        B[ix.DV, 0] = -u
        extra = B @ B.T * scale_sigma**2
        extra[ix.TH, ix.TH] += np.eye(3) * self.cfg.vo_attitude_sigma**2
        self._transform(T, extra)

    def vo_innovation(self, C_world_to_camera: np.ndarray, camera_position_world: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """y_Θ, H_Θ, y_d, H_d of a VO output (for the update and for tests)."""
        ix, vo = self.ix, self.vo
        assert vo is not None
        C_meas = self.measured_world_to_level(C_world_to_camera)
        y_th = dcm_to_rotvec(C_meas @ vo.C_world_to_level.T)
        H_th = np.zeros((3, ix.n))
        H_th[:, ix.E] = np.eye(3)
        H_th[:, ix.TH] = -np.eye(3)
        u = vo.C_world_to_level @ np.asarray(camera_position_world, float)
        c = self.nominal.C_body_to_level @ self.lever_camera
        y_d = vo.origin_ned + vo.scale * u - self.camera_position()
        H_d = np.zeros((3, ix.n))
        H_d[:, ix.DV] = np.eye(3)
        H_d[:, ix.S.start] = u
        H_d[:, ix.TH] = -vo.scale * skew(u)
        H_d[:, ix.R] = -np.eye(3)
        H_d[:, ix.E] = skew(c)
        return y_th, H_th, y_d, H_d

    def update_vo(self, C_world_to_camera: np.ndarray, camera_position_world: np.ndarray,
                  attitude: bool = True, position: bool = True,
                  hold_attitude: bool = False) -> list[UpdateResult]:
        """VO relative attitude Θ and scaled relative position d (thesis y_Θ, y_d).
        ``hold_attitude``: the VO corrects neither the attitude nor the gyro bias (nor the
        clone's attitude) — while the single differences hold the heading, a VO whose
        rotation drifts within its model would otherwise pull it (``_schmidt_update``)."""
        if self.vo is None:
            return []
        out = []
        cfg, ix = self.cfg, self.ix
        hold = (ix.E, ix.BG, ix.E0) if hold_attitude else ()
        if attitude:
            y, H, _, _ = self.vo_innovation(C_world_to_camera, camera_position_world)
            out.append(self._update("vo_attitude", y, H,
                                    np.eye(3) * cfg.vo_attitude_sigma**2, per_row=False,
                                    hold=hold))
        if position:
            _, _, y, H = self.vo_innovation(C_world_to_camera, camera_position_world)
            dist = self.vo.scale * float(np.linalg.norm(camera_position_world))
            sig = cfg.vo_position_sigma + cfg.vo_position_relative * dist
            out.append(self._update("vo_position", y, H, np.eye(3) * sig**2, per_row=False,
                                    hold=hold))
        return out

    def vo_to_level(self, points_world: np.ndarray) -> np.ndarray:
        """VO-world points (N,3) → L with the current (scaled, drift-corrected) mapping."""
        vo = self.vo
        assert vo is not None
        return vo.origin_ned + vo.scale * np.asarray(points_world, float) @ vo.C_world_to_level.T

    def vo_point_sigma(self, points_world: np.ndarray) -> np.ndarray:
        """1-σ (m, RMS per axis) of mapped points from the mapping's covariance (origin, scale,
        rotation); the VO's own triangulation error is not included."""
        self.flush()
        vo, ix, P = self.vo, self.ix, self.kf.P
        assert vo is not None
        u = np.asarray(points_world, float) @ vo.C_world_to_level.T
        var = (np.trace(P[ix.DV, ix.DV]) / 3.0 + np.sum(u**2, axis=1) * P[ix.S, ix.S][0, 0] / 3.0
               + vo.scale**2 * np.sum(u**2, axis=1) * np.trace(P[ix.TH, ix.TH]) / 3.0 * 2.0 / 3.0)
        return np.sqrt(np.maximum(var, 0.0))
