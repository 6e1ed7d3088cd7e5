"""Causal fusion engine: INS + CPP + GNSS compass + VO through the error-state EKF (thesis
fig. 16, SPEC section 4). The backend drives it live and for replay, the CLI report as fast as
the data allow.

Feed the sensor messages in time order (for equal times any order): ``process_imu`` for every
IMU sample, ``process_gnss`` with the four receivers' epochs of one time tag, ``process_frame``
for every video frame (or ``process_vo`` with an external VO's output). A GNSS epoch or a frame
that is ahead of the INS waits for the IMU sample that reaches its time; the INS is then
propagated exactly to the measurement time (the raw sample is interpolated) before the update.

Start-up (phases of ``FusionStatus``):

- ``initialising``: IMU samples are buffered, the GNSS compass (``compass.GnssCompass``) is fed
  every epoch with the accelerometer tilt until it fixes its integers;
- at the epoch after the first fix the INS starts at the PREVIOUS epoch from the compass
  attitude, the SPP position (the world origin: local level L at the body origin there, all
  positions relative to it) and the TDCP velocity, the buffered IMU samples are replayed and
  the carrier phase of the interval is applied — the trajectory is the integral of the
  carrier-phase velocity from the origin; the SPP position only anchors ``llh_deg`` (and the
  EKF, loosely, when no carrier-phase velocity has been usable for a while);
- without a compass fix after ``ALIGN_TIMEOUT_S`` (and moving), the INS starts from the
  accelerometer tilt and the course over ground (``aligning``) and the single differences are
  used once the EKF's attitude is good enough to round their integers;
- ``fused``: carrier-phase velocity accepted within the last few seconds; ``degraded``
  otherwise (INS, VO and whatever GNSS is left).

The single-difference integers are kept per (receiver, satellite) with an arbitrary offset per
satellite (N_ij = A_i − A_j); the integer part of the inter-receiver delays is absorbed in the
same way as in the compass. New or slipped satellites are re-resolved by rounding against the
EKF's prediction when its σ is far below a cycle. The TDCP is corrected for the modelled
change of the tropospheric and ionospheric delays over the interval (mm/s for a low satellite,
a few cm per minute of trajectory otherwise).

VO: each VO world (``VoOutput.segment``) is mapped into L once the camera has moved a little
since its first tracked frame (the first scale is the INS displacement over the VO one); from
then on every tracked frame updates the EKF (Θ, d) and the map points are carried into L with
the current scale and drift estimates (``structure``). A lost segment's points are frozen in L.
Every tracked frame also feeds the landmark EKFs (``estimator.landmarks``, seed 000): each map
point seen is one EKF in L, seeded from its mapped VO point and updated with its pixel and the
fused camera pose and covariance; ``structure`` gives the refined point once it has
``LandmarkParams.min_views`` views (``structure(refined=False)``: the raw points).

Performance: the matrices are small (≈ 40 states, ≈ 120 carrier-phase rows per epoch); a
multi-threaded BLAS costs more than it gains at these sizes, so run the process with
``OPENBLAS_NUM_THREADS=1`` (timings in the tests' report were taken so).
"""

from __future__ import annotations

import math
import time as _time
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from .compass import GnssCompass, tilt_from_specific_force
from .cpp import (
    SAME_CARRIER_SYSTEMS,
    EpochGeometry,
    EtaRow,
    detect_cycle_slips,
    epoch_geometry,
    eta_observations,
    loose_velocity,
    tight_velocity,
)
from .ekf import (
    EkfConfig,
    ErrorStateEkf,
    EtaInput,
    SdRow,
    VelocityInput,
)
from .ephemeris import klobuchar_delay, troposphere_delay
from .frames import (
    SPEED_OF_LIGHT,
    WAVELENGTH_L1,
    C_ecef_to_level,
    dcm_to_euler,
    ecef_to_geodetic,
    ecef_to_ned,
    euler_to_dcm,
    ned_to_ecef,
    rotvec_to_dcm,
)
from .ins import Ins, InsState, calibration_matrices
from .landmarks import LandmarkMap, LandmarkParams, SolvedViews, camera_pose_covariance
from .records import Calibration, GnssEpoch, NavigationData
from .spp import standalone_position
from .vo import VisualOdometry, VoOutput

ALIGN_TIMEOUT_S = 20.0  # without a compass fix, start from tilt + course after this long
IMU_BUFFER_S = 2.5  # raw IMU kept before the INS starts (replayed from the previous epoch)
GNSS_STALE_S = 3.0  # no carrier-phase velocity for this long: "degraded"
SPP_AIDING_AFTER_S = 5.0  # ... and for this long: the SPP position aids the EKF (loosely)
SPP_SIGMA_M = (5.0, 5.0, 8.0)  # 1-σ NED of the standalone position when it aids the EKF
ROUNDING_SIGMA_CYCLES = 0.12  # predicted single difference must be this sure to round N
ROUNDING_FRACTION = 0.3  # ... and the measured fraction this close to an integer
SCALE_CONVERGED = 0.01  # relative σ of the VO scale below which it is "converged"
VO_START_BASELINE = 0.3  # VO units moved since the anchor frame before a segment is mapped
VO_START_METRES = 0.3  # ... and metres (a sensible first scale from the INS)
_PAST = 1e-6


# --------------------------------------------------------------------------- interface


@dataclass
class FusionOptions:
    use_vo: bool = True
    use_cpp: bool = True  # carrier phase (η/v, ζ); False: INS (+ VO) after the start-up
    tightly_coupled: bool = True  # η rows (True) or per-receiver loose velocity (False)
    common_clock: bool = True  # one clock-drift state (True) or one per receiver
    satellites_keep: list[str] | None = None  # only these after keep_after_s (tables 18–20)
    keep_after_s: float = 30.0  # s after the first GNSS epoch
    sky_mask_deg: float | None = None  # elevation mask (deg) applied to every epoch
    # Table 21: receiver index (0..3) → the only satellites it keeps after keep_after_s
    # (receivers not listed keep theirs).
    per_receiver_sats: dict[int, list[str]] | None = None
    ekf: EkfConfig | None = None  # tuning of the EKF (defaults when None)
    # Port-structure refinement (``estimator.landmarks``): a landmark EKF per VO point, fed
    # with every view and the fused camera pose; refined points replace the raw ones in
    # ``structure`` once they have ``landmarks.min_views`` views. None: raw points only.
    landmarks: LandmarkParams | None = field(default_factory=LandmarkParams)
    # Height of the body origin above the waterline (hull.json ``body_origin_height_m``, an
    # installation constant): the water plane lies that far below the world origin, and
    # structure points on or below it (reflections, water patterns) are not reported.
    body_origin_height_m: float | None = None


@dataclass
class FusionStatus:
    phase: str  # 'initialising' | 'aligning' | 'fused' | 'degraded'
    compass_fixed: bool
    satellites: int  # distinct satellites in the last carrier-phase velocity update
    vo_status: str  # VO status ('off' without VO)
    scale: float | None
    scale_converged: bool
    message: str


@dataclass
class FusedState:
    time: float
    position_ned: np.ndarray  # body origin, L at the world origin (start point), m
    llh_deg: np.ndarray  # lat, lon (deg), h (m) of the body origin (SPP-anchored)
    velocity_ned: np.ndarray
    euler: np.ndarray  # roll, pitch, yaw (rad)
    C_body_to_level: np.ndarray
    rate_of_turn: float  # yaw rate, rad/s
    omega_body: np.ndarray  # body rate w.r.t. L, body axes, rad/s
    position_cov: np.ndarray  # (3,3) m²
    attitude_cov: np.ndarray  # (3,3) rad² (small angles in L)
    status: FusionStatus


@dataclass
class _Pending:
    time: float
    kind: str  # "gnss" | "vo"
    payload: object


@dataclass
class _Timer:
    total: dict[str, float] = field(default_factory=dict)
    calls: dict[str, int] = field(default_factory=dict)

    def add(self, stage: str, seconds: float) -> None:
        self.total[stage] = self.total.get(stage, 0.0) + seconds
        self.calls[stage] = self.calls.get(stage, 0) + 1

    def report(self) -> dict[str, float]:
        return {k: 1e3 * v / max(self.calls[k], 1) for k, v in self.total.items()}


# ------------------------------------------------------------- single-difference integers


class _Integers:
    """Integers of the single differences, A[(receiver, sat)] with N_ij = A_i − A_j."""

    def __init__(self) -> None:
        self.A: dict[tuple[int, str], int] = {}
        self._strikes: dict[tuple[int, str], int] = {}

    def __len__(self) -> int:
        return len(self.A)

    def drop(self, keys: Iterable[tuple[int, str]]) -> None:
        for key in keys:
            self.A.pop(key, None)
            self._strikes.pop(key, None)

    def rows(self, epochs: Sequence[GnssEpoch | None], geo: EpochGeometry, C_el: np.ndarray,
             ekf: ErrorStateEkf, phase_sigma: float, resolve: bool = True) -> list[SdRow]:
        """Rows of the satellites with known integers; new ones are rounded first."""
        out: list[SdRow] = []
        for sat, g in geo.satellites.items():
            if sat[0] not in SAME_CARRIER_SYSTEMS:
                continue
            lam = geo.wavelengths[sat]
            phase = {i: e.satellites[sat].carrier_phase for i, e in enumerate(epochs)
                     if e is not None and sat in e.satellites
                     and math.isfinite(e.satellites[sat].carrier_phase)}
            if len(phase) < 2:
                continue
            for i in list(self.A):
                if i[1] == sat and i[0] not in phase:
                    self.drop([i])
            e = C_el @ g.line_of_sight
            sigma = phase_sigma / max(math.sin(g.elevation), 0.1)
            if resolve:
                self._resolve(sat, phase, lam, e, sigma, ekf)
            known = sorted(i for i in phase if (i, sat) in self.A)
            if len(known) < 2:
                continue
            ref = known[0]
            for j in known[1:]:
                n_ij = self.A[(ref, sat)] - self.A[(j, sat)]
                out.append(SdRow(sat=sat, ref=ref, other=j, los_ned=e,
                                 value_m=lam * (phase[ref] - phase[j] - n_ij), sigma_m=sigma))
        return out

    def _resolve(self, sat: str, phase: dict[int, float], lam: float, e: np.ndarray,
                 sigma: float, ekf: ErrorStateEkf) -> None:
        known = sorted(i for i in phase if (i, sat) in self.A)
        unknown = [i for i in sorted(phase) if (i, sat) not in self.A]
        if not unknown:
            return
        if not known:
            ref = unknown.pop(0)
            candidate = {ref: 0}
        else:
            ref = known[0]
            candidate = {}
        for j in unknown:
            pred, s = ekf.predict_single_difference(ref, j, e, sigma)
            n = (lam * (phase[ref] - phase[j]) - pred) / lam
            N = round(n)
            if s < ROUNDING_SIGMA_CYCLES * lam and abs(n - N) < ROUNDING_FRACTION:
                base = candidate.get(ref, self.A.get((ref, sat), 0))
                candidate[j] = base - int(N)
        if len(candidate) >= 2 or known:
            for i, a in candidate.items():
                self.A[(i, sat)] = a

    def strike(self, rows: Sequence[SdRow], rejected: Sequence[int]) -> None:
        """A row failing the gate twice running loses the integer of its non-reference
        receiver; when every row of a satellite fails, the reference is the suspect and the
        satellite starts again."""
        bad = set(rejected)
        for k, r in enumerate(rows):
            if k not in bad:
                self._strikes.pop((r.other, r.sat), None)
        by_sat: dict[str, list[SdRow]] = {}
        for k in bad:
            by_sat.setdefault(rows[k].sat, []).append(rows[k])
        for sat, failed in by_sat.items():
            whole = len(failed) >= 2 and len(failed) == sum(1 for r in rows if r.sat == sat)
            for r in failed:
                key = (r.other, r.sat)
                self._strikes[key] = self._strikes.get(key, 0) + 1
                if self._strikes[key] >= 2:
                    self.drop([k for k in list(self.A) if k[1] == sat] if whole else [key])


# ------------------------------------------------------------------------------ engine


class Fusion:
    """The fusion engine (see the module docstring)."""

    def __init__(self, calibration: Calibration, nav: NavigationData,
                 options: FusionOptions | None = None) -> None:
        self.calibration = calibration
        self.nav = nav
        self.options = opt = options or FusionOptions()
        self.cfg = opt.ekf or EkfConfig()
        self.antennas = np.asarray(calibration.antennas_body, float)
        self.compass = GnssCompass(nav, self.antennas, elevation_mask_deg=self._mask())
        self.vo = VisualOdometry(calibration.camera) if opt.use_vo else None
        self.ins: Ins | None = None
        self.ekf: ErrorStateEkf | None = None
        self._G, self._A = calibration_matrices(calibration.imu)
        self._imu: deque[tuple[float, np.ndarray, np.ndarray]] = deque()
        self._last_raw: tuple[float, np.ndarray, np.ndarray] | None = None
        self._pending: deque[_Pending] = deque()
        self._timer = _Timer()
        # GNSS
        self._t_first_gnss: float | None = None
        self._prev: list[GnssEpoch | None] = [None] * 4
        self._prev_geo: EpochGeometry | None = None
        self._prev_fix: np.ndarray | None = None  # compass attitude at the last epoch
        self._spp_ecef: np.ndarray | None = None
        self._clock_bias_s = 0.0
        self._integers = _Integers()
        self._last_velocity_time = -math.inf
        self._n_sats = 0
        self._n_sd_sats = 0
        self._origin_llh: np.ndarray | None = None
        self.origin_time: float | None = None  # gpst of the world origin (INS start)
        self._C_el: np.ndarray | None = None
        self._origin_offset = np.zeros(3)  # SPP-averaged correction of the origin (m, NED)
        self._origin_weight = 0.0
        self._message = "waiting for GNSS"
        self._phase_aligning = False
        self._prev_spp: np.ndarray | None = None
        self._delays_known = False
        # VO
        self._vo_status = "off" if self.vo is None else "initialising"
        self._vo_anchor: tuple[int, np.ndarray, np.ndarray] | None = None  # segment, p_W, r_cam
        self._points: dict[int, tuple[int, np.ndarray]] = {}  # id → (segment, X_W)
        self._frozen: dict[int, np.ndarray] = {}  # id → L point of ended segments
        self._frozen_sigma: dict[int, float] = {}
        cam = calibration.camera
        self.landmarks: LandmarkMap | None = None
        if self.vo is not None and opt.landmarks is not None:
            lp = opt.landmarks
            if opt.body_origin_height_m is not None and lp.water_down_m is None:
                lp = replace(lp, water_down_m=float(opt.body_origin_height_m))
            self.landmarks = LandmarkMap(0.5 * (cam.K[0, 0] + cam.K[1, 1]), lp)
        self._K = np.asarray(cam.K, float)
        self._dist = np.asarray(cam.distortion, float).ravel()

    # ------------------------------------------------------------------ public inputs

    def process_imu(self, t: float, gyro: np.ndarray, accel: np.ndarray) -> None:
        """One raw IMU sample (gpst, rad/s, m/s², body axes): INS + covariance propagation
        (and the waiting GNSS / VO updates at their exact times on the way)."""
        t0 = _time.perf_counter()
        t = float(t)
        gyro = np.asarray(gyro, float)
        accel = np.asarray(accel, float)
        if self.ekf is None:
            self._imu.append((t, gyro, accel))
            while self._imu and self._imu[0][0] < t - IMU_BUFFER_S:
                self._imu.popleft()
        else:
            self._advance(t, gyro, accel)
        self._last_raw = (t, gyro, accel)
        self._timer.add("imu", _time.perf_counter() - t0)

    def process_gnss(self, t: float, epochs: list[GnssEpoch | None]) -> None:
        """The four receivers' epochs of time tag ``t`` (None for a receiver without one)."""
        t0 = _time.perf_counter()
        epochs = self._filter_epochs(float(t), list(epochs) + [None] * (4 - len(epochs)))
        if self.ekf is None:
            self._start_up(float(t), epochs)
        else:
            self._schedule(_Pending(float(t), "gnss", epochs))
        self._timer.add("gnss", _time.perf_counter() - t0)

    def process_frame(self, t: float, image: np.ndarray) -> FusedState | None:
        """One video frame: VO, then the fused state at the frame time (for the overlay)."""
        t0 = _time.perf_counter()
        if self.vo is not None:
            t1 = _time.perf_counter()
            out = self.vo.process(float(t), image)
            self._timer.add("vo", _time.perf_counter() - t1)
            self.process_vo(out)
        state = self.state(at=float(t))
        self._timer.add("frame", _time.perf_counter() - t0)
        return state

    def process_vo(self, out: VoOutput) -> None:
        """Use one VO output (from ``process_frame`` or an external VO) at its time."""
        if not self.options.use_vo:
            return
        self._vo_status = out.status
        if self.ekf is None:
            return
        self._schedule(_Pending(float(out.time), "vo", out))

    # ----------------------------------------------------------------- public outputs

    def state(self, at: float | None = None) -> FusedState | None:
        """Current fused state (extrapolated to ``at`` when the INS is slightly behind)."""
        if self.ekf is None or self.ins is None or self._origin_llh is None:
            return None
        ekf, ins = self.ekf, self.ins
        s = ekf.nominal
        omega_ib = ins.omega_body
        omega_lb = omega_ib - s.C_body_to_level.T @ ins.omega_ie
        C, r, v = s.C_body_to_level, s.position_ned, s.velocity_ned
        dt = 0.0 if at is None else float(at) - s.time
        if 0.0 < dt < 0.5:
            r = r + v * dt
            C = C @ rotvec_to_dcm(omega_lb * dt)
        lever = np.asarray(ins.calibration.lever_arm_body, float)
        position = r - C @ lever
        velocity = v - C @ np.cross(omega_lb, lever)
        euler = dcm_to_euler(C)
        roll, pitch = euler[0], euler[1]
        yaw_rate = (omega_lb[1] * math.sin(roll) + omega_lb[2] * math.cos(roll)) / max(
            math.cos(pitch), 1e-6)
        ecef = ned_to_ecef(position + self._origin_offset, self._origin_llh)
        llh = ecef_to_geodetic(ecef)
        ekf.flush()
        ix, P = ekf.ix, ekf.P
        return FusedState(
            time=float(at) if 0.0 < dt < 0.5 else s.time,
            position_ned=position, llh_deg=np.array([math.degrees(llh[0]),
                                                     math.degrees(llh[1]), llh[2]]),
            velocity_ned=velocity, euler=euler, C_body_to_level=C,
            rate_of_turn=float(yaw_rate), omega_body=omega_lb,
            position_cov=P[ix.R, ix.R].copy(), attitude_cov=P[ix.E, ix.E].copy(),
            status=self.status())

    def status(self) -> FusionStatus:
        ekf = self.ekf
        if ekf is None:
            phase = "initialising"
        elif self._phase_aligning and not len(self._integers):
            phase = "aligning"
        elif ekf.time - self._last_velocity_time <= GNSS_STALE_S:
            phase = "fused"
        else:
            phase = "degraded"
        scale = None
        converged = False
        if ekf is not None and ekf.vo is not None and self._vo_status == "tracking":
            scale = ekf.vo.scale
            s_sigma = math.sqrt(max(ekf.P[ekf.ix.S, ekf.ix.S][0, 0], 0.0))
            converged = s_sigma < SCALE_CONVERGED * abs(scale)
        # The compass attitude: its own fix before the INS runs, then the EKF's single
        # differences with fixed integers (False while the heading rests on the gyro alone).
        fixed = self.compass.fixed if ekf is None else self._n_sd_sats > 0
        return FusionStatus(phase=phase, compass_fixed=fixed,
                            satellites=self._n_sats, vo_status=self._vo_status, scale=scale,
                            scale_converged=converged, message=self._message)

    def solved_views(self) -> SolvedViews | None:
        """The landmark window's views with their solved attitudes (``SolvedViews``), for
        the designated targets; None without the joint refinement."""
        lm = self.landmarks
        return None if lm is None or lm.window is None else lm.window.solved()

    def structure(self, refined: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Port-structure points in L, their 1-σ (m), ids. Without ``refined``: the VO points
        (scaled, drift-corrected). With it (and the landmark refinement on): a reportable
        landmark (``LandmarkMap.classify``: enough views and parallax, views that agree,
        above the water) gives its refined position, its σ the RMS per axis of its covariance;
        a rejected one (water patterns, reflections, mistracks) is
        left out; one still converging keeps the VO point with the larger of the two σ, and is
        left out when that σ exceeds its range."""
        ids, pts, sig = [], [], []
        for pid, p in self._frozen.items():
            ids.append(pid)
            pts.append(p)
            sig.append(self._frozen_sigma[pid])
        ekf = self.ekf
        if ekf is not None and ekf.vo is not None:
            seg = ekf.vo.segment
            cur = [(pid, X) for pid, (s, X) in self._points.items() if s == seg]
            if cur:
                X = np.array([c[1] for c in cur])
                pts.extend(ekf.vo_to_level(X))
                sig.extend(ekf.vo_point_sigma(X))
                ids.extend(c[0] for c in cur)
        if not ids:
            return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
        pts_a, sig_a, ids_a = np.array(pts), np.array(sig), np.array(ids, np.int64)
        if refined and self.landmarks is not None:
            lm = self.landmarks
            rows, ok, rejected = lm.classify(ids_a)
            have = rows >= 0
            x_lm, P_lm = lm.best(rows[have])
            sig_lm = np.sqrt(np.trace(P_lm, axis1=1, axis2=2) / 3.0)
            pts_a[ok] = x_lm[ok[have]]
            # Reportable: the landmark's σ; still converging: the larger of the two.
            sig_a[have] = np.where(ok[have], sig_lm, np.maximum(sig_a[have], sig_lm))
            # A point whose σ exceeds its range (from the camera that last saw it, else the
            # current one) says nothing of where it is (a far VO point re-triangulated near, a
            # reflection): left out.
            seen_from = lm.last_camera[rows[have]]
            unseen = ~np.isfinite(seen_from).all(axis=1)
            if ekf is not None:
                seen_from[unseen] = ekf.camera_position()
            vague = np.zeros(len(ids_a), bool)
            with np.errstate(invalid="ignore"):  # no camera at all: NaN, kept
                vague[have] = sig_a[have] > np.linalg.norm(pts_a[have] - seen_from, axis=1)
            keep = ~rejected & ~vague
            return pts_a[keep], sig_a[keep], ids_a[keep]
        return pts_a, sig_a, ids_a

    def timing(self) -> dict[str, float]:
        """Milliseconds per call by stage ('imu', 'gnss', 'frame', 'vo', 'compass',
        'gnss_update', 'vo_update' (which includes 'landmarks'), 'landmarks', 'start')."""
        return self._timer.report()

    # ------------------------------------------------------------------ scheduling

    def _schedule(self, item: _Pending) -> None:
        assert self.ins is not None
        if self.ekf is not None and item.time <= self.ekf.time + _PAST:
            self._handle(item)  # the INS is there already (or a late message: use it now)
        else:
            self._pending.append(item)

    def _advance(self, t: float, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Propagate to ``t``, stopping exactly at the pending measurements on the way."""
        ekf = self.ekf
        assert ekf is not None
        while self._pending and self._pending[0].time <= t + _PAST:
            item = self._pending.popleft()
            tm = item.time
            if tm > ekf.time + _PAST and tm < t - _PAST and self._last_raw is not None:
                t0, g0, a0 = self._last_raw
                w = (tm - t0) / (t - t0) if t > t0 else 1.0
                ekf.propagate(tm, g0 + w * (gyro - g0), a0 + w * (accel - a0))
            elif tm > ekf.time + _PAST:
                ekf.propagate(t, gyro, accel)
            self._handle(item)
        if t > ekf.time + _PAST:
            ekf.propagate(t, gyro, accel)

    def _handle(self, item: _Pending) -> None:
        t0 = _time.perf_counter()
        if item.kind == "gnss":
            self._gnss_update(item.time, item.payload)  # type: ignore[arg-type]
            self._timer.add("gnss_update", _time.perf_counter() - t0)
        else:
            self._vo_update(item.payload)  # type: ignore[arg-type]
            self._timer.add("vo_update", _time.perf_counter() - t0)

    # ---------------------------------------------------------------------- GNSS

    def _filter_epochs(self, t: float, epochs: list[GnssEpoch | None]) -> list[GnssEpoch | None]:
        """Satellite-blocking scenarios of the thesis (tables 18–21) and the sky mask."""
        opt = self.options
        if self._t_first_gnss is None:
            self._t_first_gnss = t
        late = t - self._t_first_gnss >= opt.keep_after_s
        out: list[GnssEpoch | None] = []
        for i, ep in enumerate(epochs[:4]):
            if ep is None:
                out.append(None)
                continue
            keep = set(ep.satellites)
            if late and opt.satellites_keep is not None:
                keep &= set(opt.satellites_keep)
            if late and opt.per_receiver_sats is not None and i in opt.per_receiver_sats:
                keep &= set(opt.per_receiver_sats[i])
            if not opt.use_cpp and self.ekf is not None:
                keep = set()
            if keep != set(ep.satellites):
                ep = GnssEpoch(ep.time, {s: o for s, o in ep.satellites.items() if s in keep},
                               ep.flag)
            out.append(ep)
        return out

    def _mask(self) -> float:
        return 10.0 if self.options.sky_mask_deg is None else float(self.options.sky_mask_deg)

    def _geometry(self, t: float, epochs: Sequence[GnssEpoch | None],
                  receiver_ecef: np.ndarray) -> EpochGeometry:
        sats = sorted({s for e in epochs if e is not None for s in e.satellites})
        return epoch_geometry(self.nav, sats, t, receiver_ecef, self._clock_bias_s, self._mask())

    def _spp(self, epochs: Sequence[GnssEpoch | None]) -> None:
        """Standalone position (joint over the receivers before the INS runs; afterwards one
        receiver is enough: it only anchors llh and gives the receiver clock bias)."""
        present = [e for e in epochs if e is not None and e.satellites]
        if not present:
            self._spp_ecef = None
            return
        if self.ekf is not None:
            present = present[:1]
        spp = standalone_position(present, self.nav, elevation_mask_deg=self._mask(),
                                  initial_ecef=self._spp_ecef)
        if spp is not None:
            self._spp_ecef = spp.position
            self._clock_bias_s = spp.clock_bias_m / SPEED_OF_LIGHT
        else:
            self._spp_ecef = None

    def _tilt(self) -> tuple[float, float] | None:
        if self.ins is not None:
            e = self.ekf.nominal.euler if self.ekf is not None else self.ins.state.euler
            return float(e[0]), float(e[1])
        if not self._imu:
            return None
        f = np.mean([s[2] for s in list(self._imu)[-100:]], axis=0)
        return tilt_from_specific_force(self._A @ f)

    def _start_up(self, t: float, epochs: list[GnssEpoch | None]) -> None:
        """Before the INS runs: compass, SPP and TDCP velocity until the INS can start."""
        self._spp(epochs)
        t0 = _time.perf_counter()
        sol = self.compass.update(epochs, self._tilt())
        self._timer.add("compass", _time.perf_counter() - t0)
        centre = self._spp_ecef
        geo = self._geometry(t, epochs, centre) if centre is not None else None
        v_interval = None
        if geo is not None and self._prev_geo is not None:
            rows = eta_observations(self._prev, epochs, self._prev_geo, geo,
                                    phase_sigma_m=self.cfg.phase_sigma_m,
                                    common_clock=self.options.common_clock).rows
            C = sol.C_body_to_level if sol.fixed else None
            levers = self.antennas - self.antennas.mean(axis=0)
            omega = self._G @ self._imu[-1][1] if self._imu else None
            tv = tight_velocity(rows, lever_arms_body=levers, C_body_to_level=C,
                                omega_body=omega if C is not None else None)
            if tv is not None:
                v_interval = (tv.velocity_ned, tv.clock_drift_mps)
        ready = v_interval is not None and self._prev_geo is not None \
            and self._prev_spp is not None
        started = False
        if ready and sol.fixed and self._prev_fix is not None:
            self._start_ins(self._prev_geo.time, self._prev_fix, v_interval, attitude_sigma=None)
            self._message = "INS started from the GNSS compass fix"
            started = True
        elif ready and t - (self._t_first_gnss or t) > ALIGN_TIMEOUT_S \
                and np.hypot(*v_interval[0][:2]) > 0.5:
            tilt = self._tilt() or (0.0, 0.0)
            yaw = math.atan2(v_interval[0][1], v_interval[0][0])
            self._start_ins(self._prev_geo.time, euler_to_dcm(tilt[0], tilt[1], yaw),
                            v_interval, attitude_sigma=math.radians(10.0))
            self._phase_aligning = True
            self._message = "no compass fix: INS started from tilt and course over ground"
            started = True
        if sol.fixed:
            self._prev_fix = sol.C_body_to_level
        else:
            self._prev_fix = None
            if not started:
                self._message = f"compass: {sol.message or 'not fixed'}"
        self._prev_spp = self._spp_ecef
        if started:
            # The epoch itself is applied once the INS has reached it.
            self._schedule(_Pending(t, "gnss", epochs))
            return
        self._prev, self._prev_geo = epochs, geo

    def _start_ins(self, t_start: float, C: np.ndarray, v_interval: tuple[np.ndarray, float],
                   attitude_sigma: float | None) -> None:
        """INS at the previous epoch (the world origin): compass attitude (or tilt + course,
        ``attitude_sigma``), SPP position, TDCP velocity and clock drift of the interval; then
        the buffered IMU samples are replayed up to now."""
        spp = self._prev_spp
        assert spp is not None
        llh = ecef_to_geodetic(spp)
        C_el = C_ecef_to_level(llh[0], llh[1])
        lever_centre = self.antennas.mean(axis=0) - self.calibration.imu.lever_arm_body
        imu_ecef = spp - C_el.T @ (C @ lever_centre)
        self._origin_llh = ecef_to_geodetic(imu_ecef)
        self._C_el = C_ecef_to_level(self._origin_llh[0], self._origin_llh[1])
        self.origin_time = t_start
        samples = [s for s in self._imu if s[0] >= t_start - _PAST]
        v_centre, drift = v_interval
        omega = self._G @ samples[0][1] if samples else np.zeros(3)
        v0 = v_centre - C @ np.cross(omega, lever_centre)
        state = InsState(time=t_start, position_ned=np.zeros(3), velocity_ned=v0,
                         C_body_to_level=C)
        self.ins = Ins(self._origin_llh, self.calibration.imu, state)
        # The interval's mean velocity stands for the velocity at its start (± ½ a Δt); the
        # delays are unknown until their fractions are found with the attitude.
        sig = {"velocity": 0.2, "clock_drift": 1.0, "delay": 0.2}
        if attitude_sigma is not None:
            sig["attitude"] = attitude_sigma
        self.ekf = ErrorStateEkf(
            self.ins, self.antennas, camera_to_body=self.calibration.camera.C_camera_to_body,
            camera_lever_body=self.calibration.camera.lever_arm_body,
            common_clock=self.options.common_clock, config=self.cfg, clock_drift=drift,
            initial_sigmas=sig)
        for ts, g, a in samples:
            self.ekf.propagate(ts, g, a)
        self._imu.clear()

    def _array_ecef(self) -> np.ndarray:
        assert self.ekf is not None and self._origin_llh is not None
        return ned_to_ecef(self.ekf.antenna_position(None), self._origin_llh)

    def _gnss_update(self, t: float, epochs: list[GnssEpoch | None]) -> None:
        ekf, opt, cfg = self.ekf, self.options, self.cfg
        assert ekf is not None and self._C_el is not None
        self._spp(epochs)
        geo = self._geometry(t, epochs, self._array_ecef())
        slips = detect_cycle_slips(self._prev, epochs, common_clock=opt.common_clock)
        prev_ok = self._prev_geo is not None and ekf.clone_time is not None \
            and abs(self._prev_geo.time - ekf.clone_time) < 1e-3
        rows: list[EtaRow] = []
        if prev_ok and opt.use_cpp:
            rows = eta_observations(self._prev, epochs, self._prev_geo, geo, slips=slips,
                                    phase_sigma_m=cfg.phase_sigma_m,
                                    common_clock=opt.common_clock).rows
            rows = self._atmosphere_corrected(rows, geo)
        # Single differences: integers re-resolved after slips, rows for the attitude.
        self._integers.drop([key for key in slips if key in self._integers.A])
        sd_rows: list[SdRow] = []
        if opt.use_cpp:
            if not self._delays_known:
                self._seed_delays(epochs, geo)
            sd_rows = self._integers.rows(epochs, geo, self._C_el, ekf, cfg.phase_sigma_m,
                                          resolve=self._delays_known)
        used = self._carrier_update(rows, sd_rows)
        self._n_sats = len(used)
        if self._spp_ecef is not None:
            self._spp_aiding()
        ekf.clone(t)
        self._prev, self._prev_geo = epochs, geo
        self._message = self._summary()

    def _atmosphere_corrected(self, rows: Sequence[EtaRow], geo: EpochGeometry
                              ) -> list[EtaRow]:
        """Remove the modelled change of the tropospheric and ionospheric delays over the
        interval from the TDCP (mm/s for a low satellite: the delays grow as it sets)."""
        prev = self._prev_geo
        assert prev is not None and self._origin_llh is not None
        lat, lon, h = self._origin_llh
        nav = self.nav
        cache: dict[str, float] = {}
        out = []
        for r in rows:
            if r.sat not in cache:
                a, b = prev.satellites[r.sat], geo.satellites[r.sat]
                d_tropo = troposphere_delay(b.elevation, h) - troposphere_delay(a.elevation, h)
                d_iono = 0.0
                if nav.iono_alpha is not None and nav.iono_beta is not None:
                    scale = (geo.wavelengths[r.sat] / WAVELENGTH_L1) ** 2
                    d_iono = scale * (
                        klobuchar_delay(nav.iono_alpha, nav.iono_beta, geo.time, lat, lon,
                                        b.elevation, b.azimuth)
                        - klobuchar_delay(nav.iono_alpha, nav.iono_beta, prev.time, lat, lon,
                                          a.elevation, a.azimuth))
                cache[r.sat] = (d_tropo - d_iono) / r.interval  # phase: +T, −I
            out.append(replace(r, measured=r.measured - cache[r.sat]))
        return out

    def _carrier_update(self, rows: Sequence[EtaRow], sd_rows: Sequence[SdRow]) -> set[str]:
        """η (or the loose per-receiver velocities) and ζ of one epoch; returns the satellites
        that served the velocity."""
        ekf = self.ekf
        assert ekf is not None and self._C_el is not None
        C_el = self._C_el
        used: set[str] = set()
        eta: list[EtaInput] = []
        if self.options.tightly_coupled:
            eta = [EtaInput(antenna=r.antenna, sat=r.sat, u_ned=C_el @ r.los_ecef,
                            measured=r.measured, sigma=r.sigma, interval=r.interval)
                   for r in rows]
        else:
            vels = []
            for i in range(4):
                lv = loose_velocity([r for r in rows if r.antenna == i], C_el)
                if lv is not None:
                    vels.append(VelocityInput(antenna=i, velocity_ned=lv.velocity_ned,
                                              covariance=lv.covariance_ned,
                                              interval=lv.interval_s))
                    used |= set(lv.satellites)
            res = ekf.update_velocity(vels)
            if res.accepted:
                self._last_velocity_time = ekf.time
            else:
                used = set()
        res_eta, res_sd = ekf.update_carrier_phase(eta, sd_rows)
        if eta:
            bad = set(res_eta.rejected)
            used = {r.sat for k, r in enumerate(rows) if k not in bad}
            if res_eta.accepted:
                self._last_velocity_time = ekf.time
        bad_sd = set(res_sd.rejected)
        self._n_sd_sats = len({r.sat for k, r in enumerate(sd_rows) if k not in bad_sd})
        if sd_rows:
            self._integers.strike(sd_rows, res_sd.rejected)
            if res_sd.accepted:
                self._phase_aligning = False
        return used

    def _seed_delays(self, epochs: Sequence[GnssEpoch | None], geo: EpochGeometry) -> None:
        """D̂_1j from the fractional parts of λΦ_1j − e·Ĉb_1j over all satellites (common
        clock: the same for every satellite), given the compass/INS attitude."""
        ekf = self.ekf
        assert ekf is not None and self._C_el is not None
        ix = ekf.ix
        if max(np.linalg.eigvalsh(ekf.covariance(ix.E))) > math.radians(8.0) ** 2:
            return  # a fraction needs the baselines to ~1 cm
        C = ekf.nominal.C_body_to_level
        delays = np.zeros(3)
        lam = 0.0
        for j in (1, 2, 3):
            phasors = []
            for sat, g in geo.satellites.items():
                if sat[0] not in SAME_CARRIER_SYSTEMS:
                    continue
                e0, ej = epochs[0], epochs[j]
                if e0 is None or ej is None or sat not in e0.satellites \
                        or sat not in ej.satellites:
                    continue
                sd = e0.satellites[sat].carrier_phase - ej.satellites[sat].carrier_phase
                if not math.isfinite(sd):
                    continue
                lam = geo.wavelengths[sat]
                e = self._C_el @ g.line_of_sight
                b = C @ (ekf.lever_antennas[j] - ekf.lever_antennas[0])
                phasors.append(np.exp(2j * math.pi * (sd - e @ b / lam)))
            if len(phasors) < 3:
                return
            mean = np.mean(phasors)
            if abs(mean) < 0.8:  # fractions disagree: the attitude is not good enough
                self._message = "single differences inconsistent with the attitude"
                return
            delays[j - 1] = lam * np.angle(mean) / (2 * math.pi)  # L1 only: one wavelength
        ekf.reset_delays(delays, self.cfg.init_delay)
        self._delays_known = True

    def _spp_aiding(self) -> None:
        """SPP: refine the absolute origin (llh output); aid the EKF when nothing else does."""
        ekf = self.ekf
        assert ekf is not None and self._origin_llh is not None and self._spp_ecef is not None
        spp_ned = ecef_to_ned(self._spp_ecef, self._origin_llh)
        if ekf.time - self._last_velocity_time <= GNSS_STALE_S:
            # Only while the trajectory is carrier-phase driven: not an INS drift estimate.
            offset = spp_ned - ekf.antenna_position(None)
            self._origin_weight += 1.0
            self._origin_offset += (offset - self._origin_offset) / self._origin_weight
        elif ekf.time - self._last_velocity_time > SPP_AIDING_AFTER_S:
            R = np.diag(np.square(SPP_SIGMA_M))
            ekf.update_position(spp_ned - self._origin_offset, R)

    def _summary(self) -> str:
        return (f"{self._n_sats} sats in the velocity, {self._n_sd_sats} in the single "
                f"differences; gate rejections {self._gate_text()}")

    def _gate_text(self) -> str:
        ekf = self.ekf
        assert ekf is not None
        return ", ".join(f"{k} {v.rejected}/{v.accepted + v.rejected}"
                         for k, v in ekf.stats.items())

    # ------------------------------------------------------------------------- VO

    def _vo_update(self, out: VoOutput) -> None:
        ekf = self.ekf
        assert ekf is not None
        if out.status != "tracking" or out.C_world_to_camera is None \
                or out.camera_position_world is None:
            if out.status == "lost":
                self._freeze_segment()
                self._vo_anchor = None
            return
        for pid, X in zip(out.point_ids, out.points_world, strict=True):
            self._points[int(pid)] = (out.segment, np.asarray(X, float))
        p = np.asarray(out.camera_position_world, float)
        if ekf.vo is None or ekf.vo.segment != out.segment:
            if ekf.vo is not None:
                self._freeze_segment()
            anchor = self._vo_anchor
            if anchor is None or anchor[0] != out.segment:
                self._vo_anchor = (out.segment, p, ekf.camera_position())
                return
            dp = np.linalg.norm(p - anchor[1])
            dr = np.linalg.norm(ekf.camera_position() - anchor[2])
            if dp < VO_START_BASELINE or dr < VO_START_METRES:
                return
            scale = dr / dp
            ekf.start_vo_segment(out.segment, out.C_world_to_camera, p, scale, 0.3 * scale)
            self._vo_anchor = None
            return
        ekf.update_vo(out.C_world_to_camera, p)
        if self.landmarks is not None:
            t0 = _time.perf_counter()
            self._refine_landmarks(out)
            self._timer.add("landmarks", _time.perf_counter() - t0)

    def _refine_landmarks(self, out: VoOutput) -> None:
        """One view of the landmark EKFs (``estimator.landmarks``): the map points seen in this
        frame (new ones seeded from the VO point mapped into L) with the fused camera pose and
        its covariance at the frame time."""
        ekf, lm = self.ekf, self.landmarks
        assert ekf is not None and ekf.vo is not None and lm is not None
        ids, uv = out.observations
        ids = np.asarray(ids, np.int64)
        if len(ids) == 0:
            return
        ekf.flush()
        ix, P = ekf.ix, ekf.P
        C_bl = ekf.nominal.C_body_to_level
        C_lc = (C_bl @ ekf.C_camera_to_body).T
        p_cam = ekf.camera_position()
        pose_cov = camera_pose_covariance(P[ix.R, ix.R], P[ix.E, ix.E], C_bl @ ekf.lever_camera,
                                          P[ix.R, ix.E])
        new = np.flatnonzero(~lm.known(ids))
        if len(new):
            # out.point_ids is sorted (the VO's map is kept sorted by id).
            pid = np.asarray(out.point_ids, np.int64)
            pos = np.clip(np.searchsorted(pid, ids[new]), 0, max(len(pid) - 1, 0))
            have = (pos < len(pid)) & (pid[pos] == ids[new]) if len(pid) else \
                np.zeros(len(new), bool)
            if have.any():
                Xw = np.asarray(out.points_world, float)[pos[have]]
                lm.seed_from_view(ids[new[have]], ekf.vo_to_level(Xw), p_cam,
                                  ekf.vo_point_sigma(Xw), time=out.time)
        pts = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        xy = cv2.undistortPoints(pts, self._K, self._dist).reshape(-1, 2)
        lm.update(out.time, C_lc, p_cam, pose_cov, ids, xy)

    def _freeze_segment(self) -> None:
        """Keep the points of an ended VO segment in L as they were last mapped."""
        ekf = self.ekf
        if ekf is None or ekf.vo is None:
            return
        seg = ekf.vo.segment
        cur = [(pid, X) for pid, (s, X) in self._points.items() if s == seg]
        if cur:
            X = np.array([c[1] for c in cur])
            for (pid, _), q, s in zip(cur, ekf.vo_to_level(X), ekf.vo_point_sigma(X),
                                      strict=True):
                self._frozen[pid] = q
                self._frozen_sigma[pid] = float(s)
        self._points = {k: v for k, v in self._points.items() if v[0] != seg}
        ekf.vo = None
