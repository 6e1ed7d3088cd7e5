"""Integrity of the fusion: the berthing aid knows, and says, when not to trust it.

Three parts (the concepts of GNSS integrity, thesis-independent; ``docs/references.md``):

- **Fault detection on the inputs** (``IntegrityMonitor``): every IMU sample, GNSS epoch and
  frame is checked before the fusion uses it — time going backwards, non-finite or physically
  implausible IMU values (spikes, saturation), a frozen IMU, gaps, a silent stream (IMU,
  receivers, video), black / blinded / frozen frames, a burst of cycle slips, a receiver clock
  jump, an implausible standalone position. A sample that fails is not used; a fault is raised
  with its time and reason, and cleared when the input is healthy again. Faults found inside the
  fusion (single differences that no longer agree with the attitude, an inconsistent VO) are
  raised by the stage that finds them.
- **A declared mode** (``Integrity.mode``): ``fused`` (carrier phase drives the trajectory),
  ``coasting`` (INS, and VO when it tracks, without carrier phase), ``aligning`` (heading from the
  course over ground only), ``no position`` (initialising, or no IMU: nothing to trust).
- **Protection levels**: with every state, a horizontal protection level HPL (m) and a heading
  protection level (deg) that the true error exceeds with a probability below the integrity
  risk: ``k`` times the 1-σ (major axis of the horizontal covariance; the heading σ), ``k``
  from the χ² quantile of the integrity risk, plus the error a fault just below the detection
  thresholds could leave (``IntegrityConfig.undetected_*``) and, for the HPL, an overbound of
  the correlated carrier-phase drift the filter does not model (b·√t on a day like the real
  pair's, growing faster while the atmosphere is more active: ``cpp.AtmosphereActivity``).
  The horizontal covariance is the filter's plus what the world origin's error has driven:
  the carrier phase's satellite geometry is computed at the standalone fix, metres off, and
  that drifts the trajectory ~0.1 mm/s per metre for as long as it runs
  (``origin_drift_cov``). Between carrier-phase epochs the HPL also carries the VO
  sub-solution's separation from the fused position (``vo_coupling``): an INS failing there
  is bounded by it. The state is
  **trusted** when the mode is usable, no critical fault is active and both levels are within
  their alert limits (default 0.5 m, 1°).

Every raised fault is also an ``Alert`` (time, kind, message) in the monitor's history: the
report, the page and the bridge outputs read them.
"""

from __future__ import annotations

import functools
import math
import statistics
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.stats import chi2

from .compass import MIN_RECEIVERS
from .frames import vector_length
from .vo import VisualOdometry, VoOutput, WorkingImage

MODES = ("fused", "coasting", "aligning", "no position")
USABLE_MODES = ("fused", "coasting")

# Faults that make the output untrusted while they are active (the others are warnings: the
# fusion works around them, e.g. a receiver silent while three others track; an inconsistent
# VO is excluded and the attitude σ widened by what it may have pulled, so the protection
# levels say what is left). An implausible IMU sample is dropped and bridged like a gap; a
# run of them long enough to matter is "imu-silent" (a user trial: each spike of a burst
# flipped the trust for a frame while the position stayed 4 cm off).
CRITICAL = frozenset({"imu-silent", "imu-frozen", "time-backwards", "sd-inconsistent"})


@dataclass
class IntegrityConfig:
    alert_limit_m: float = 0.5  # horizontal alert limit (berthing: 0.5 m)
    heading_alert_limit_deg: float = 1.0
    integrity_risk: float = 1e-7  # probability that the error exceeds the protection level
    # Errors a fault just below the detection thresholds may leave (added to k·σ).
    undetected_horizontal_m: float = 0.005
    undetected_heading_deg: float = 0.02
    # The filter takes the carrier-phase velocity errors as white; the real ones are correlated
    # (atmosphere residuals, multipath) and the trajectory drifts from where the fusion started
    # more than its σ grows. Overbound of that drift, added to the HPL: b·√(t − start). From
    # the real static pair (benchmarks/calibration.py, one receiver alone, the worst window):
    # 20 mm in 10 s, 32 in 30, 46 in 60, 58 in 120 → b = 6 mm/√s bounds every window. Its
    # variance grows with the square of the measured activity (``assess``'s ``drift_scale``):
    # on a seed whose atmosphere was 2.5x as active the trajectory drifted 0.16 m in 70 s against an
    # HPL of 0.18 m.
    # (The reported position σ holds that drift's 1-σ, ``cpp.CorrelatedDrift``; k times it
    # would be ~3x the worst window seen, so the HPL keeps this overbound instead.)
    drift_m_per_sqrt_s: float = 0.006
    # IMU checks (a ship: rates and specific forces far from a MEMS unit's range)
    imu_gap_s: float = 0.05  # samples further apart than this: a gap
    imu_silent_s: float = 0.3  # no IMU sample for this long while other inputs arrive
    max_rate_rad_s: float = 3.0  # |ω| beyond this is not a ship's motion
    max_specific_force: float = 40.0  # m/s²
    max_rate_step: float = 2.0  # rad/s between consecutive samples (a spike)
    max_force_step: float = 30.0  # m/s² between consecutive samples
    frozen_samples: int = 20  # the same raw sample this many times running: frozen
    # GNSS checks
    # epochs without a receiver before it is declared silent: the first (they come each
    # second, and a sensor that fails is said within a second; a user trial waited 3 s)
    receiver_silent_epochs: int = 1
    gnss_silent_s: float = 2.5  # no GNSS epoch at all for this long (they come each second)
    slip_burst_fraction: float = 0.5  # this share of the tracked signals slipping at once
    clock_jump_m: float = 3000.0  # common change of all ranges beyond the drift (1 µs ≈ 300 m)
    spp_max_speed_mps: float = 50.0  # standalone positions implying more than this
    # Video checks
    video_silent_s: float = 1.0  # no frame for this long while other inputs arrive
    dark_level: float = 8.0  # mean grey level below this: black frame
    bright_level: float = 245.0  # mean grey level above this: blinded frame
    saturated_fraction: float = 0.9  # ... or this share of pixels saturated
    # Mean grey-level change from the last frame below this: the same frame again (a re-encoded
    # repeat differs by ~0.001; a live camera's noise alone by ~1).
    frozen_level: float = 0.05
    # A feed found frozen stays so until this many frames running each differ from the one
    # before: an encoder refreshing a frozen picture (each keyframe, every 12 frames of a
    # re-encoded copy) changes it by up to ~1.6 for a frame or two, and the freeze must not
    # clear, the VO take a 5 s old picture and the page draw on it, at each refresh.
    frozen_clear_frames: int = 5
    # A protection level that went beyond its alert limit is back within it at this fraction
    # of it: hovering at the limit (a heading PL converging through 1.00°) flipped the trust,
    # the overlay's colours and an alarm every second (a user trial).
    pl_rearm_fraction: float = 0.95

    def k(self, dof: int) -> float:
        """Multiple of σ that the error exceeds with probability ``integrity_risk``."""
        return _sigma_multiple(self.integrity_risk, dof)


@functools.lru_cache(maxsize=16)
def _sigma_multiple(risk: float, dof: int) -> float:
    """√ of the χ² quantile (computed once: ``assess`` runs for every state)."""
    return float(math.sqrt(chi2.ppf(1.0 - risk, dof)))


@dataclass(frozen=True)
class Alert:
    t: float  # gpst the fault was raised (or cleared)
    kind: str
    message: str
    active: bool = True  # False: the fault cleared at t


@dataclass
class Integrity:
    """What the officer may trust in one state (``FusionStatus.integrity``)."""

    mode: str
    trusted: bool
    # why it is not trusted first (critical faults, protection levels beyond their limits),
    # then the faults the fusion works around
    reasons: list[str] = field(default_factory=list)
    hpl_m: float | None = None  # horizontal protection level
    heading_pl_deg: float | None = None
    alert_limit_m: float = 0.5
    heading_alert_limit_deg: float = 1.0


def _beyond(what: str, level: float, unit: str, limit: float, within: float) -> str:
    """Why a protection level ``level`` is not trusted against ``limit``: beyond it, or
    not yet back under ``within`` of it."""
    sep = " " if unit == "m" else ""
    if level > limit:
        return f"{what} {level:.2f}{sep}{unit} above the {limit:g}{sep}{unit} alert limit"
    return (f"{what} {level:.3f}{sep}{unit} not yet back under {within * limit:.3f}{sep}{unit} "
            f"({100 * within:.0f} % of the {limit:g}{sep}{unit} alert limit)")


def _attitude_left(receivers: int) -> str:
    """What the carrier-phase attitude still has with ``receivers`` tracking."""
    if receivers >= MIN_RECEIVERS:
        return "the compass works with the other antennas"
    if receivers == 2:
        return "2 receivers left: no compass fix, one baseline for the attitude"
    return f"{receivers} receiver(s) left: no carrier-phase attitude"


class IntegrityMonitor:
    """Input checks and the fault register of one fusion engine."""

    def __init__(self, config: IntegrityConfig | None = None) -> None:
        self.cfg = config or IntegrityConfig()
        self.active: dict[str, Alert] = {}  # kind → the alert that raised it
        self.alerts: list[Alert] = []  # history, raised and cleared
        self.last_input = -math.inf  # gpst of the newest input of any kind
        self.anchored_at: float | None = None  # gpst of the first filter state (world anchor)
        # The carrier-phase drift's overbound (``IntegrityConfig.drift_m_per_sqrt_s``), its
        # variance accumulated since the anchor with the atmosphere's activity (``assess``)
        self._drift_var = 0.0
        self._drift_t: float | None = None
        self._pl_over = False  # a protection level went beyond its limit (``pl_rearm_fraction``)
        # The standalone fix the carrier phase's geometry is computed at (the world origin):
        # its error covariance (NED, m²) and the trajectory's accumulated sensitivity to it
        # (m of position per m of origin error, ``cpp.origin_sensitivity`` times the interval).
        self.origin_cov = np.zeros((3, 3))
        self.origin_drift = np.zeros((3, 3))
        self.last_imu = -math.inf
        self.last_frame = -math.inf
        self.frames_seen = 0
        self.last_gnss = -math.inf
        self._prev_raw: tuple[np.ndarray, np.ndarray] | None = None
        self._intervals: deque[float] = deque(maxlen=50)  # recent regular IMU intervals
        self._same = 0
        self._rx_missing: dict[int, int] = {}
        self._frame_sig: np.ndarray | None = None
        self._spp: tuple[float, np.ndarray] | None = None

    # ------------------------------------------------------------------------ register

    def raise_fault(self, kind: str, t: float, message: str, news: bool = False) -> None:
        """A fault (again): recorded once until it clears; its message kept current.
        ``news``: what the engine did about an active fault (a restart): recorded too."""
        alert = Alert(float(t), kind, message)
        if kind not in self.active or news:
            self.alerts.append(alert)
        self.active[kind] = alert if kind not in self.active else \
            Alert(self.active[kind].t, kind, message)

    def clear(self, kind: str, t: float, message: str = "") -> None:
        if kind in self.active:
            del self.active[kind]
            self.alerts.append(Alert(float(t), kind, message or f"{kind} cleared", False))

    def is_active(self, kind: str) -> bool:
        return kind in self.active

    def imu_bridged(self) -> bool:
        """Whether the IMU is silent or a gap is being bridged on its held mean rate: the
        gyro's rotation then measures nothing (``Ins.C_gyro`` turns on the held rate)."""
        return "imu-gap" in self.active or "imu-silent" in self.active

    def _input(self, t: float) -> None:
        self.last_input = max(self.last_input, t)

    def quiet_until(self, t: float) -> None:
        """Nothing arrived from any sensor until ``t`` (a live source gone quiet, on the
        receiver clock): the streams' silence counts up to it."""
        self._input(t)

    # ---------------------------------------------------------------------------- IMU

    def imu(self, t: float, gyro: np.ndarray, accel: np.ndarray) -> bool:
        """Whether an IMU sample may be used (False: dropped, the fault raised)."""
        cfg = self.cfg
        if t <= self.last_imu:  # declared at the stream's own time, not the bad tag's
            self.raise_fault("time-backwards", self.last_imu,
                             f"IMU time tag {self.last_imu - t:.2f} s before the last one: "
                             "sample dropped")
            return False
        self.clear("time-backwards", t, "time tags increase again")
        if not (np.isfinite(gyro).all() and np.isfinite(accel).all()):
            self.raise_fault("imu-implausible", t, "IMU sample not finite: dropped")
            return False
        prev = self._prev_raw
        self._prev_raw = (gyro, accel)
        if prev is not None and np.array_equal(prev[0], gyro) and np.array_equal(prev[1], accel):
            self._same += 1
        else:
            self._same = 0
        if self._same >= cfg.frozen_samples:
            self.raise_fault("imu-frozen", t, f"IMU repeats one sample ({self._same + 1} "
                             "times): its data are not used")
            return False
        self.clear("imu-frozen", t, "IMU samples vary again")
        rate, force = vector_length(gyro), vector_length(accel)
        spike = prev is not None and (
            vector_length(gyro - prev[0]) > cfg.max_rate_step
            or vector_length(accel - prev[1]) > cfg.max_force_step)
        if rate > cfg.max_rate_rad_s or force > cfg.max_specific_force or spike:
            self.raise_fault("imu-implausible", t, f"IMU sample implausible (|ω| {rate:.3g} "
                             f"rad/s, |f| {force:.3g} m/s²{', a spike' if spike else ''}): "
                             "dropped")
            if spike:  # compare the next sample with the last good one
                self._prev_raw = prev
            return False
        self.clear("imu-implausible", t, "IMU samples plausible again")
        gap = t - self.last_imu
        if math.isfinite(gap) and gap > cfg.imu_gap_s:
            self.raise_fault("imu-gap", t, f"IMU gap of {gap:.2f} s: bridged, "
                             "uncertainty inflated")
        else:
            self.clear("imu-gap", t, "IMU samples regular again")
            if math.isfinite(gap):
                self._intervals.append(gap)
        self.clear("imu-silent", t, "IMU samples again")
        self.last_imu = t
        self._input(t)
        return True

    @property
    def imu_interval(self) -> float:
        """The IMU's regular sample interval (s), from the recent samples."""
        # statistics.median: a tenth of np.median's cost on 50 floats, asked every sample
        return float(statistics.median(self._intervals)) if self._intervals else 0.01

    def imu_gap(self, t: float) -> float:
        """The time since the last used IMU sample (the gap a sample at ``t`` closes)."""
        return t - self.last_imu

    # --------------------------------------------------------------------------- GNSS

    def gnss(self, t: float, present: list[bool]) -> bool:
        """Whether a GNSS epoch may be used; ``present``: which receivers have an epoch."""
        if t <= self.last_gnss:
            self.raise_fault("time-backwards", self.last_gnss,
                             f"GNSS epoch {self.last_gnss - t:.2f} s before the last one: "
                             "dropped")
            return False
        self.last_gnss = t
        self._input(t)
        self.clear("gnss-silent", t, "GNSS epochs arrive again")
        left = sum(present)
        for i, here in enumerate(present):
            kind = f"receiver-{i + 1}-silent"
            if here:
                self._rx_missing[i] = 0
                self.clear(kind, t, f"receiver {i + 1} tracks again")
                continue
            self._rx_missing[i] = self._rx_missing.get(i, 0) + 1
            if self._rx_missing[i] >= self.cfg.receiver_silent_epochs:
                # the compass and the single differences take the first receiver they have
                # as the reference: three are enough for the whole attitude
                n = self._rx_missing[i]
                self.raise_fault(kind, t, f"receiver {i + 1} silent for {n} "
                                 f"epoch{'s' if n > 1 else ''}: {_attitude_left(left)}")
        self.check_streams(t)
        return True

    def slips(self, t: float, slipped: int, tracked: int) -> None:
        """A burst: most of the tracked signals slipping at one epoch."""
        if tracked >= 4 and slipped >= self.cfg.slip_burst_fraction * tracked:
            self.raise_fault("cycle-slips", t, f"burst of cycle slips: {slipped} of {tracked} "
                             "signals; their integers are re-resolved")
        else:
            self.clear("cycle-slips", t, "carrier phase continuous again")

    def clock_jump(self, t: float, common_m: float) -> bool:
        """Whether the common change of all carrier-phase ranges over the interval (beyond
        the estimated drift) is a receiver clock jump; raised as a fault when it is."""
        if abs(common_m) > self.cfg.clock_jump_m:
            self.raise_fault("clock-jump", t, f"receiver clock jump of {common_m / 299.792458:.1f}"
                             " µs: this interval's carrier-phase velocity is not used")
            return True
        self.clear("clock-jump", t, "receiver clock continuous")
        return False

    def spp(self, t: float, ecef: np.ndarray | None) -> bool:
        """Whether a standalone position is plausible against the previous one (speed)."""
        if ecef is None:
            return False
        prev = self._spp
        if prev is not None and t > prev[0]:
            speed = float(np.linalg.norm(ecef - prev[1])) / (t - prev[0])
            if speed > self.cfg.spp_max_speed_mps and t - prev[0] < 10.0:
                self.raise_fault("spp-implausible", t, f"standalone position jumps at "
                                 f"{speed:.0f} m/s: not used (absolute position held)")
                return False
        self.clear("spp-implausible", t, "standalone position plausible again")
        self._spp = (t, np.asarray(ecef, float))
        return True

    # -------------------------------------------------------------------------- video

    def vo_frame(self, t: float, problem: str) -> bool:
        """A frame's VO output arrived (``problem``: why the frame was unusable, "" if it was
        used); False when its time goes backwards."""
        if t <= self.last_frame:
            self.raise_fault("time-backwards", self.last_frame,
                             f"frame time {self.last_frame - t:.2f} s before the last one: "
                             "dropped")
            return False
        self.last_frame = t
        self.frames_seen += 1
        self._input(t)
        self.clear("video-silent", t, "frames arrive again")
        if problem:
            self.raise_fault("video", t, f"{problem}: the VO skips it")
        else:
            self.clear("video", t, "video usable again")
        return True

    # -------------------------------------------------------------------------- state

    def _drift_bound(self, t: float, scale: float) -> float:
        """The drift overbound at ``t``: b·√(t − anchor) on a quiet day, its variance
        growing with the square of the activity ``scale`` while it lasts."""
        assert self._drift_t is not None
        if t > self._drift_t:
            self._drift_var += (self.cfg.drift_m_per_sqrt_s * scale) ** 2 * (t - self._drift_t)
            self._drift_t = t
        return math.sqrt(self._drift_var)

    def origin_fix(self, covariance_ned: np.ndarray) -> None:
        """The world origin's standalone-fix covariance (NED, m²)."""
        self.origin_cov = np.asarray(covariance_ned, float)
        self.origin_drift = np.zeros((3, 3))

    def origin_interval(self, sensitivity: np.ndarray, interval: float) -> None:
        """One carrier-phase interval taken at the origin's geometry: velocity per metre of
        origin error (``cpp.origin_sensitivity``) over ``interval`` seconds."""
        self.origin_drift += np.asarray(sensitivity, float) * interval

    def origin_drift_cov(self) -> np.ndarray:
        """Covariance (m², NED 3 x 3) of the trajectory error the origin's error has driven so
        far; independent of the filter's own (which takes the origin as exact)."""
        A = self.origin_drift
        return A @ self.origin_cov @ A.T

    def check_streams(self, t: float) -> None:
        """Streams that fell silent while others go on (or until ``quiet_until``)."""
        if math.isfinite(self.last_imu) and t - self.last_imu > self.cfg.imu_silent_s:
            # (one message while it lasts: the alarm list keeps the first, the banner the last)
            self.raise_fault("imu-silent", t, f"no IMU sample for over "
                             f"{self.cfg.imu_silent_s:g} s: no position")
        if math.isfinite(self.last_gnss) and t - self.last_gnss > self.cfg.gnss_silent_s:
            self.raise_fault("gnss-silent", t, f"no GNSS epoch for over "
                             f"{self.cfg.gnss_silent_s:g} s: no satellites, no carrier phase")
        if self.frames_seen and t - self.last_frame > self.cfg.video_silent_s:
            self.raise_fault("video-silent", t, f"no video frame for over "
                             f"{self.cfg.video_silent_s:g} s: no VO")

    def assess(self, t: float, mode: str, position_cov: np.ndarray | None,
               heading_var: float | None, drift_scale: float = 1.0,
               separation_m: float = 0.0) -> Integrity:
        """The integrity of a state at ``t``: its mode, protection levels and trust.
        ``drift_scale``: the atmosphere's activity against the quiet day the drift's overbound
        was fitted on (``cpp.AtmosphereActivity``). ``separation_m``: how far the VO's
        sub-solution since the last carrier-phase epoch is from the fused position
        (``vo_coupling``): an INS failing since that epoch is off by no more than it beyond
        the fault-free bound."""
        cfg = self.cfg
        self.check_streams(max(t, self.last_input))
        if self.is_active("imu-silent"):
            mode = "no position"
        hpl = hdg = None
        if position_cov is not None and heading_var is not None and mode != "no position":
            if self.anchored_at is None:
                self.anchored_at = self._drift_t = t
            horizontal = np.asarray(position_cov, float)[:2, :2] + self.origin_drift_cov()[:2, :2]
            major = float(np.linalg.eigvalsh(horizontal)[-1])
            drift = self._drift_bound(t, drift_scale)
            hpl = cfg.k(2) * math.sqrt(max(major, 0.0)) + cfg.undetected_horizontal_m + drift \
                + (separation_m if math.isfinite(separation_m) else 0.0)
            hdg = cfg.k(1) * math.degrees(math.sqrt(max(heading_var, 0.0))) \
                + cfg.undetected_heading_deg
        critical = [a for k, a in self.active.items() if k in CRITICAL]
        within = cfg.pl_rearm_fraction if self._pl_over else 1.0
        hpl_ok = hpl is not None and hpl <= within * cfg.alert_limit_m
        hdg_ok = hdg is not None and hdg <= within * cfg.heading_alert_limit_deg
        if hpl is not None and hdg is not None:
            self._pl_over = not (hpl_ok and hdg_ok)
        trusted = mode in USABLE_MODES and not critical and hpl_ok and hdg_ok
        # why it is not trusted first (the page and the alarm show the first), then the
        # faults the fusion works around
        reasons = [a.message for a in critical]
        if hpl is not None and not hpl_ok:
            reasons.append(_beyond("protection level", hpl, "m", cfg.alert_limit_m, within))
        if hdg is not None and not hdg_ok:
            reasons.append(_beyond("heading protection level", hdg, "°",
                                   cfg.heading_alert_limit_deg, within))
        reasons += [a.message for k, a in self.active.items() if k not in CRITICAL]
        return Integrity(mode, bool(trusted), reasons, hpl, hdg, cfg.alert_limit_m,
                         cfg.heading_alert_limit_deg)


# Nomoto's first-order steering model, T·ṙ + r = K·δ with K = K'·U/L and T = T'·L/U, puts a
# hull's largest yaw acceleration (full rudder from a steady course) at K'/T'·δ·(U/L)².
NOMOTO_GAIN_RATIO = 2.0  # K'/T': near 1 for ships (K', T' both ~1.5–3); an upper value
MAX_RUDDER_RAD = math.radians(35.0)
# Below this Froude number U/√(gL) the bound stays at its value there: at berthing speeds
# thrusters, tugs and waves turn a hull more than its rudder does.
MIN_FROUDE = 0.4
GRAVITY_MPS2 = 9.81


def max_yaw_acceleration(length_m: float, speed_mps: float) -> float:
    """The largest yaw acceleration (rad/s²) of a hull ``length_m`` long at ``speed_mps``:
    K'/T'·δ_max·g·Fn²/L (Nomoto, above), Fn at least ``MIN_FROUDE``. A 200 m ship: 0.55°/s²;
    a 7 m boat: 16°/s² (the simulated ones reach 0.01 and 7)."""
    froude2 = max(speed_mps**2 / (GRAVITY_MPS2 * length_m), MIN_FROUDE**2)
    return NOMOTO_GAIN_RATIO * MAX_RUDDER_RAD * GRAVITY_MPS2 * froude2 / length_m


@dataclass
class YawStep:
    """A step of the gyro's rate of turn (``YawStepCheck.update``), rad/s."""

    step: float  # measured so far: the recent mean still holds samples before the step
    bound: float  # what the hull could have turned by
    widen: float  # σ to add to the gyro bias now (with what was added before, it covers |step|)
    settled: bool  # the recent mean lies after the step: ``step`` is the whole of it


class YawStepCheck:
    """The gyro's rate of turn against what the hull can do: its mean over the last 0.1 s
    against that over the 0.5 s before, apart by more than the hull's largest yaw
    acceleration (``max_yaw_acceleration``) makes of the 0.3 s between them plus five σ of the
    two means' noise, is a step of the gyro (its bias), not a turn of the ship.

    On a 200 m hull that is ~0.2°/s, found within a tenth of a second. The carrier-phase
    heading (``carrier_phase.GyroCheck``) needs seconds and the VO's rotation a second, and
    meanwhile the rate of turn and the bow's and stern's approach speeds on the hull's lever
    are wrong under a tight σ (a user trial: after a 0.5°/s step the bow showed opening at
    1.1 m/s while it closed at 0.26, trusted for 0.9 s). On a small boat the bound is ~5°/s:
    only gross steps are found there. The rate is the raw gyro's (its bias in it, constant):
    the EKF's bias corrections would be steps of their own.

    Found, the step is measured on for 0.1 s against the mean before it (the first sample
    beyond the bound holds only part of it), then the check starts afresh on the new level."""

    RECENT_S = 0.1
    BEFORE_S = 0.5
    NOISE_S = 2.0  # time constant of the samples' noise estimate (and the settling it needs)
    K_NOISE = 5.0

    def __init__(self, length_m: float) -> None:
        self.length_m = float(length_m)
        self.reset()

    def reset(self) -> None:
        """Start afresh (after a gap, or a step measured: the new level is the ship's)."""
        self._recent: deque[float] = deque()
        self._before: deque[float] = deque()
        self._since: float | None = None
        self._last: float | None = None
        self._abs_diff = 0.0  # running mean of |successive difference| (the noise)
        # a step found: the mean before it, the bound it passed, the σ added to the bias so
        # far (root-sum-square), and the samples until the recent mean lies after it
        self._found_before: float | None = None
        self._found_bound = 0.0
        self._widened = 0.0
        self._found_left = 0

    def update(self, t: float, rate: float, interval: float, speed_mps: float
               ) -> YawStep | None:
        """One sample's rate of turn (rad/s, about the level down axis) at ``t``, the IMU's
        regular ``interval`` (s) and the speed over ground: the step while one is found and
        measured, else None."""
        if self._last is not None:
            w = min(interval / self.NOISE_S, 1.0)
            self._abs_diff += w * (abs(rate - self._last) - self._abs_diff)
        self._last = rate
        if self._since is None:
            self._since = t
        n1 = max(3, round(self.RECENT_S / interval))
        n0 = max(10, round(self.BEFORE_S / interval))
        self._recent.append(rate)
        while len(self._recent) > n1:
            self._before.append(self._recent.popleft())
        while len(self._before) > n0:
            self._before.popleft()
        if self._found_before is not None:
            return self._measure()
        if len(self._before) < n0 or t - self._since < self.NOISE_S:
            return None
        before = sum(self._before) / n0
        step = sum(self._recent) / n1 - before
        # |Δ| of two samples' white noise has the mean 2σ/√π
        sigma = self._abs_diff * math.sqrt(math.pi) / 2.0
        bound = (max_yaw_acceleration(self.length_m, speed_mps)
                 * 0.5 * (n0 + n1) * interval
                 + self.K_NOISE * sigma * math.sqrt(1.0 / n1 + 1.0 / n0))
        if abs(step) <= bound:
            return None
        self._found_before, self._found_bound, self._found_left = before, bound, n1 - 1
        self._widened = abs(step)
        return YawStep(step, bound, abs(step), False)

    def _measure(self) -> YawStep:
        assert self._found_before is not None
        step = sum(self._recent) / len(self._recent) - self._found_before
        widen = math.sqrt(max(step**2 - self._widened**2, 0.0))  # what covers |step| now
        self._widened = max(self._widened, abs(step))
        self._found_left -= 1
        out = YawStep(step, self._found_bound, widen, self._found_left <= 0)
        if out.settled:
            self.reset()
        return out


class FrameCheck:
    """Is a frame fit for the VO? Black, blinded (saturated) and frozen (the very frame again)
    frames are not (``IntegrityConfig`` levels). Stateful: it remembers the last frame, and a
    frozen feed until it moves again (``frozen_clear_frames``)."""

    def __init__(self, config: IntegrityConfig | None = None) -> None:
        self.cfg = config or IntegrityConfig()
        self._last: np.ndarray | None = None
        self._last_t = math.nan
        self._moving = 0  # frames running that differed from the one before
        # time of the picture a frozen feed keeps repeating (None: not frozen)
        self.still_since: float | None = None

    def problem(self, image: np.ndarray, t: float = math.nan) -> str:
        """Why the frame (at time ``t``) is unusable, "" when it is fine."""
        cfg = self.cfg
        small = np.ascontiguousarray(np.asarray(image)[::8, ::8])
        grey = small.astype(np.float32)
        if grey.ndim == 3:  # the channels' mean (OpenCV's per-pixel transform: numpy's is slow)
            grey = cv2.transform(grey, np.full((1, grey.shape[2]), 1.0 / grey.shape[2]))
        last, self._last = self._last, small
        last_t, self._last_t = self._last_t, float(t)
        level = float(grey.mean())
        problem = ""
        if level < cfg.dark_level:
            problem = f"video black (mean level {level:.0f})"
        elif level > cfg.bright_level or np.mean(grey >= 250) > cfg.saturated_fraction:
            problem = f"video blinded (mean level {level:.0f})"
        if problem:  # (black frames are alike, not a picture frozen)
            self.still_since, self._moving = None, 0
            return problem
        if last is not None and last.shape == small.shape:
            if cv2.norm(small, last, cv2.NORM_L1) / small.size < cfg.frozen_level:
                self._moving = 0
                if self.still_since is None:
                    self.still_since = last_t
            else:
                self._moving += 1
                if self._moving >= cfg.frozen_clear_frames:
                    self.still_since = None
        if self.still_since is not None:
            age = float(t) - self.still_since
            return "video frozen (the same picture" + \
                (f" for {age:.1f} s)" if math.isfinite(age) else " again)")
        return ""


def checked_vo(vo: VisualOdometry, check: FrameCheck, t: float, image: np.ndarray,
               prepared: WorkingImage | None = None,
               following: WorkingImage | None = None) -> VoOutput:
    """The VO's output of a frame, or, for a frame unfit for it, an output that says why
    (status "skipped"; the VO's state untouched). The engine and the evaluation's VO pass
    both go through here. ``prepared``: the VO's ``prepare`` of the image, made ahead;
    ``following``: the next frame's, when known (``VisualOdometry.process``)."""
    problem = check.problem(image, t)
    if not problem:
        return vo.process(t, image, prepared, following)
    return VoOutput(time=float(t), status="skipped", segment=-1, C_world_to_camera=None,
                    camera_position_world=None, n_tracked=0, n_inliers=0, is_keyframe=False,
                    points_world=np.zeros((0, 3)), point_ids=np.zeros(0, np.int64),
                    observations=(np.zeros(0, np.int64), np.zeros((0, 2))), problem=problem)
