"""Causal fusion engine: INS + CPP + GNSS compass + VO through the error-state EKF (thesis
fig. 16; the method is written up in ``estimator/METHOD.md``). The server drives it live and
for replay, the evaluation as fast as the data allow, both through ``engine.driver``.

Feed the sensor messages in time order (for equal times any order): ``process_imu`` for every
IMU sample, ``process_gnss`` with the four receivers' epochs of one time tag, ``process_frame``
for every video frame (or ``process_vo`` with the VO's output of a frame). A GNSS epoch or a
frame that is ahead of the INS waits for the IMU sample that reaches its time; the INS is then
propagated exactly to the measurement time (the raw sample is interpolated) before the update.

The engine is a facade over its stages, one module each:

- ``alignment``: before the INS runs (``initialising``): IMU buffer, GNSS compass, the INS
  start from the compass fix (or, without one, tilt + course over ground: ``aligning``);
- ``gnss_epochs``: every epoch's satellite selection, standalone position and geometry;
- ``carrier_phase``: once the INS runs, each epoch's η (or v) and ζ into the EKF with the
  single-difference integers and the inter-receiver delays; ``fused`` while carrier-phase
  velocity is accepted, ``degraded`` otherwise (INS, VO and whatever GNSS is left);
- ``vo_coupling``: each VO world mapped into L, its Θ and d into the EKF, the landmark
  refinement and the port structure.

The trajectory is the integral of the carrier-phase velocity from the world origin (local level
L at the body origin where the INS starts); the SPP position only anchors ``llh_deg`` (and the
EKF, loosely, when no carrier-phase velocity has been usable for a while).

Performance: the matrices are small (≈ 40 states, ≈ 120 carrier-phase rows per epoch); a
multi-threaded BLAS costs more than it gains at these sizes, so run the process with
``OPENBLAS_NUM_THREADS=1`` (timings in the tests' report were taken so).
"""

from __future__ import annotations

import math
import time as _time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .alignment import Alignment, InsStart
from .carrier_phase import CarrierPhaseCoupling
from .compass import GnssCompass
from .ekf import EkfConfig, ErrorStateEkf
from .frames import (
    C_ecef_to_level,
    dcm_to_euler,
    ecef_to_geodetic,
    ned_to_ecef,
    rotvec_to_dcm,
)
from .gnss_epochs import N_RECEIVERS, GnssFront
from .ins import Ins, InsState, RateSmoother, calibration_matrices
from .integrity import Alert, FrameCheck, IntegrityMonitor, YawStepCheck, checked_vo
from .landmarks import LandmarkMap, SolvedViews
from .options import FusedState, FusionOptions, FusionStatus, WorldOrigin
from .records import Calibration, GnssEpoch, NavigationData
from .spp import height_aided
from .vo import VisualOdometry, VoOutput, WorkingImage
from .vo_coupling import VoCoupling

__all__ = ["Fusion", "FusionOptions", "FusionStatus", "FusedState"]

SCALE_CONVERGED = 0.01  # relative σ of the VO scale below which it is "converged"
EXTRAPOLATE_S = 0.5  # a state is extrapolated to a frame time at most this far ahead
MAX_PENDING = 2000  # measurements waiting for the INS (a silent IMU must not grow it forever)
# An IMU gap: the motion in it is bounded by these (a ship's turn-rate and acceleration
# changes), and the INS error covariance widened by them over the gap's length.
GAP_RATE_SIGMA = 0.05  # rad/s
GAP_ACCEL_SIGMA = 0.4  # m/s²
GAP_MEAN_S = 3.0  # the INS coasts on the raw samples' mean over about this long (waves cancel)
_PAST = 1e-6
# The fusion's phase → the declared mode (``estimator.integrity``)
_MODE = {"initialising": "no position", "aligning": "aligning", "fused": "fused",
         "degraded": "coasting"}


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


class Fusion:
    """The fusion engine (see the module docstring)."""

    def __init__(self, calibration: Calibration, nav: NavigationData,
                 options: FusionOptions | None = None) -> None:
        self.calibration = calibration
        self.nav = nav
        self.options = opt = options or FusionOptions()
        self.cfg = opt.ekf or EkfConfig()
        self.antennas = _four_antennas(np.asarray(calibration.antennas_body, float))
        self.monitor = IntegrityMonitor(opt.integrity)
        self.frame_check = FrameCheck(opt.integrity)
        self.compass = GnssCompass(nav, self.antennas, elevation_mask_deg=opt.elevation_mask_deg)
        self.vo = VisualOdometry(calibration.camera) if opt.use_vo else None
        self.last_vo: VoOutput | None = None  # the last VO output given (process_vo)
        self.ins: Ins | None = None
        self.ekf: ErrorStateEkf | None = None
        self.origin: WorldOrigin | None = None
        self._G, A = calibration_matrices(calibration.imu)
        self._last_raw: tuple[float, np.ndarray, np.ndarray] | None = None
        self._raw_mean: tuple[np.ndarray, np.ndarray] | None = None  # (gyro, accel) over ~3 s
        self._rate = RateSmoother(self.cfg.gyro_arw)  # the outputs' angular rate
        self._yaw_step = YawStepCheck(opt.hull_length_m) if opt.hull_length_m else None
        self._pending: deque[_Pending] = deque()
        self._timer = _Timer()
        self.front = GnssFront(nav, opt, self.monitor)
        self.alignment = Alignment(self.compass, self.antennas, self._G, A, self.cfg.phase_sigma_m,
                                   opt.common_clock)
        self.carrier: CarrierPhaseCoupling | None = None  # once the INS runs
        self.coupling = VoCoupling(calibration.camera, opt.landmarks if opt.use_vo else None,
                                   opt.body_origin_height_m, self.monitor)
        if self.vo is None:
            self.coupling.status = "off"

    # ------------------------------------------------------------------ public inputs

    def tick(self, t: float) -> None:
        """No sensor message has arrived until gpst ``t`` (a live feed gone quiet): the
        silence of every stream is declared from the time, not only when another speaks."""
        self.monitor.quiet_until(float(t))

    def process_imu(self, t: float, gyro: np.ndarray, accel: np.ndarray) -> None:
        """One raw IMU sample (gpst, rad/s, m/s², body axes): INS + covariance propagation
        (and the waiting GNSS / VO updates at their exact times on the way)."""
        t0 = _time.perf_counter()
        t = float(t)
        gyro = np.asarray(gyro, float)
        accel = np.asarray(accel, float)
        gap = self.monitor.imu_gap(t)
        if not self.monitor.imu(t, gyro, accel):
            return  # dropped (the monitor says why)
        if self.ekf is None:
            self.alignment.buffer_imu(t, gyro, accel)
        else:
            if gap > self.options.integrity.imu_gap_s:
                self._bridge_gap(t, gap)
            self._advance(t, gyro, accel)
            assert self.ins is not None
            self._rate.update(self.ins.omega_body, t - self._last_raw[0]
                              if self._last_raw is not None else 0.0)
            if self._yaw_step is not None:
                self._check_yaw_step(t, gyro)
        self._last_raw = (t, gyro, accel)
        self._average(gyro, accel)
        self._timer.add("imu", _time.perf_counter() - t0)

    def process_gnss(self, t: float, epochs: list[GnssEpoch | None]) -> None:
        """The four receivers' epochs of time tag ``t`` (None for a receiver without one)."""
        t0 = _time.perf_counter()
        t = float(t)
        epochs = list(epochs) + [None] * (N_RECEIVERS - len(epochs))
        if not self.monitor.gnss(t, [e is not None and bool(e.satellites) for e in epochs]):
            return
        epochs = self.front.select(t, epochs,
                                   carrier_off=not self.options.use_cpp and self.ekf is not None)
        if self.ekf is None:
            start = self.alignment.step(t, epochs, self.front, self._timer.add)
            if start is not None:
                self._start_ins(start)
                # The epoch itself is applied once the INS has reached it.
                self._schedule(_Pending(t, "gnss", epochs))
        else:
            self._schedule(_Pending(t, "gnss", epochs))
        self._timer.add("gnss", _time.perf_counter() - t0)

    @property
    def vo_restart_due(self) -> bool:
        """Whether the VO is restarted before its next frame (its world was found wrong):
        outputs of a VO run apart are no longer this engine's from that frame on."""
        return self.coupling.restart is not None

    def prepare_frame(self, image: np.ndarray) -> WorkingImage | None:
        """What ``process_frame`` will need of ``image`` and may be made ahead, in a frame
        reader's thread (the VO's ``prepare``: pure, no state touched); None without a VO."""
        return None if self.vo is None else self.vo.prepare(image)

    def process_frame(self, t: float, image: np.ndarray,
                      prepared: WorkingImage | None = None,
                      following: WorkingImage | None = None) -> FusedState | None:
        """One video frame: VO, then the fused state at the frame time (for the overlay).
        ``prepared``: the image's ``prepare_frame``, when it was made ahead; ``following``:
        the next frame's, when it is known already (the VO starts tracking into it)."""
        t0 = _time.perf_counter()
        if self.vo is not None:
            t1 = _time.perf_counter()
            if self.coupling.restart is not None:  # its world was found wrong (vo_restart_due)
                self.vo.restart(*self.coupling.restart)
                self.coupling.restart = None
            out = checked_vo(self.vo, self.frame_check, float(t), image, prepared, following)
            self._timer.add("vo", _time.perf_counter() - t1)
            self.process_vo(out)
        state = self.state(at=float(t))
        self._timer.add("frame", _time.perf_counter() - t0)
        return state

    def process_vo(self, out: VoOutput) -> None:
        """Use one VO output (from ``process_frame`` or the VO run apart) at its time."""
        self.last_vo = out
        use_vo = self.options.use_vo
        if not self.monitor.vo_frame(float(out.time), out.problem if use_vo else ""):
            return  # its time goes backwards (the monitor says so)
        if not use_vo or out.status == "skipped":
            return  # an unusable frame (the monitor raised why): the VO keeps its state
        self.coupling.status = out.status
        if self.ekf is None:
            return
        self._schedule(_Pending(float(out.time), "vo", out))

    # ----------------------------------------------------------------- public outputs

    @property
    def origin_time(self) -> float | None:
        """gpst of the world origin (where the INS started), None before."""
        return None if self.origin is None else self.origin.time

    @property
    def landmarks(self) -> LandmarkMap | None:
        return self.coupling.landmarks

    def position_drift_cov(self) -> np.ndarray:
        """What the filter's position covariance does not hold (NED, m²): the drift that the
        satellites' correlated rate errors integrate to (``cpp.CorrelatedDrift``) and the one
        the world origin's error drives (``IntegrityMonitor.origin_drift_cov``)."""
        drift = np.zeros((3, 3)) if self.carrier is None else self.carrier.drift.cov
        return drift + self.monitor.origin_drift_cov()

    def turn_rates(self, gyro: np.ndarray) -> np.ndarray | None:
        """Raw gyro samples' (n, 3) rates of turn (rad/s about the level down axis, the bias
        the EKF has learned removed): to carry the heading over samples not yet processed."""
        if self.ins is None:
            return None
        return (np.asarray(self.ins.level_yaw_rate(np.reshape(gyro, (-1, 3))))
                - self.ins.bias_yaw_rate - float(self.ins.omega_ie[2]))

    def state(self, at: float | None = None) -> FusedState | None:
        """Current fused state (extrapolated to ``at`` when the INS is slightly behind)."""
        if self.ekf is None or self.ins is None or self.origin is None:
            return None
        ekf, ins = self.ekf, self.ins
        s = ekf.nominal
        omega_ib = self._rate.out
        omega_lb = omega_ib - s.C_body_to_level.T @ ins.omega_ie
        C, r, v = s.C_body_to_level, s.position_ned, s.velocity_ned
        dt = 0.0 if at is None else float(at) - s.time
        if 0.0 < dt < EXTRAPOLATE_S:
            r = r + v * dt
            C = C @ rotvec_to_dcm(omega_lb * dt)
        lever = np.asarray(ins.calibration.lever_arm_body, float)
        position = r - C @ lever
        velocity = v - C @ np.cross(omega_lb, lever)
        euler = dcm_to_euler(C)
        roll, pitch = euler[0], euler[1]
        yaw_rate = (omega_lb[1] * math.sin(roll) + omega_lb[2] * math.cos(roll)) / max(
            math.cos(pitch), 1e-6)
        ecef = ned_to_ecef(position + self.origin.offset_ned, self.origin.llh)
        llh = ecef_to_geodetic(ecef)
        ekf.flush()
        ix, P = ekf.ix, ekf.P
        return FusedState(
            time=float(at) if 0.0 < dt < EXTRAPOLATE_S else s.time,
            position_ned=position, llh_deg=np.array([math.degrees(llh[0]),
                                                     math.degrees(llh[1]), llh[2]]),
            velocity_ned=velocity, euler=euler, C_body_to_level=C,
            rate_of_turn=float(yaw_rate), omega_body=omega_lb,
            # the smoothed rate's noise and lag, and the gyro bias' σ (about the body's down
            # axis)
            rate_of_turn_sigma=math.hypot(self._rate.sigma,
                                          math.sqrt(max(float(P[ix.BG, ix.BG][2, 2]), 0.0))),
            position_cov=P[ix.R, ix.R].copy(), position_drift_cov=self.position_drift_cov(),
            velocity_cov=P[ix.V, ix.V].copy(),
            attitude_cov=P[ix.E, ix.E].copy(),
            status=self.status())

    def status(self) -> FusionStatus:
        ekf, carrier = self.ekf, self.carrier
        self.monitor.check_streams(self.monitor.last_input)  # a silent IMU decides the phase
        if ekf is None or carrier is None:
            phase = "initialising"
        elif carrier.aligning and not len(carrier.integers):
            phase = "aligning"
        elif carrier.carrier_fresh(ekf.time) and not self.monitor.is_active("imu-silent"):
            phase = "fused"  # (the EKF's time stands still without the IMU)
        else:
            phase = "degraded"
        vo_status = self.coupling.status
        if vo_status == "tracking" and self.coupling.excluded:
            vo_status = "excluded"  # tracking, but off the gyro or the fused track
        if self.monitor.is_active("video-silent"):
            vo_status = "lost"  # its last output is no longer what the camera sees
        elif self.monitor.is_active("video") and self.options.use_vo:
            vo_status = "skipped"  # the frames are unusable (black, blinded, frozen)
        scale = None
        converged = False
        if ekf is not None and ekf.vo is not None and vo_status == "tracking":
            scale = ekf.vo.scale
            s_sigma = math.sqrt(max(ekf.P[ekf.ix.S, ekf.ix.S][0, 0], 0.0))
            converged = s_sigma < SCALE_CONVERGED * abs(scale)
        gnss = carrier is not None and not self.monitor.is_active("gnss-silent")
        # The compass attitude: its own fix before the INS runs, then the EKF's single
        # differences with fixed integers (False while the heading rests on the gyro alone,
        # as when the receivers have gone silent: not "fixed" beside 0 satellites)
        fixed = self.compass.fixed if carrier is None else gnss and carrier.n_sd_sats > 0
        message = carrier.message if carrier is not None and carrier.message \
            else self.alignment.message
        integrity = self.monitor.assess(
            self.monitor.last_input, _MODE[phase],
            None if ekf is None else ekf.P[ekf.ix.R, ekf.ix.R],
            None if ekf is None else float(ekf.P[ekf.ix.E, ekf.ix.E][2, 2]),
            1.0 if carrier is None else carrier.activity.scale,
            self.coupling.separation_m if ekf is not None and ekf.vo is not None else 0.0)
        return FusionStatus(phase=phase, compass_fixed=fixed,
                            satellites=carrier.n_sats if gnss else 0,
                            vo_status=vo_status, scale=scale, scale_converged=converged,
                            message=message, integrity=integrity,
                            picture_since=self.frame_check.still_since)

    def alerts(self) -> list[Alert]:
        """Every fault raised (and cleared) so far, in time order (``estimator.integrity``)."""
        return list(self.monitor.alerts)

    def active_alerts(self) -> list[Alert]:
        """The faults active now, each with its current message (the history keeps the words
        it was raised with: "silent for 1 epoch" of a receiver silent for ten)."""
        return list(self.monitor.active.values())

    def solved_views(self) -> SolvedViews | None:
        """The landmark window's views with their solved attitudes (``SolvedViews``), for
        the designated targets; None without the joint refinement."""
        return self.coupling.solved_views()

    def structure(self, refined: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Port-structure points in L, their 1-σ (m), ids. Without ``refined``: the VO points
        (scaled, drift-corrected). With it (and the landmark refinement on): a reportable
        landmark (``LandmarkMap.classify``: enough views and parallax, views that agree,
        above the water) gives its refined position, its σ its covariance's along the viewing
        ray from the camera that last saw it (a monocular point errs along its ray);
        a rejected one (water patterns, reflections, mistracks) is left out; one still
        converging keeps the VO point with the larger of the two σ, and is left out when that
        σ exceeds its range."""
        return self.coupling.structure(self.ekf, refined)

    def converged_ids(self, ids: np.ndarray) -> np.ndarray:
        """Those of the structure's ``ids`` whose landmark has converged (reportable)."""
        return self.coupling.converged_ids(ids)

    def landmark_views(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids, accepted views) of every landmark seeded so far (0 views: dropped)."""
        return self.coupling.landmark_views()

    def landmark_positions(self, ids: np.ndarray) -> np.ndarray:
        """Reported positions of landmarks ``ids`` (the joint window's where it has one)."""
        return self.coupling.landmark_positions(ids)

    def timing(self) -> dict[str, float]:
        """Milliseconds per call by stage ('imu', 'gnss', 'frame', 'vo', 'compass',
        'gnss_update', 'vo_update' (which includes 'landmarks'), 'landmarks')."""
        return self._timer.report()

    # ------------------------------------------------------------------ scheduling

    def _schedule(self, item: _Pending) -> None:
        assert self.ins is not None
        if self.ekf is not None and item.time <= self.ekf.time + _PAST:
            self._handle(item)  # the INS is there already (or a late message: use it now)
        else:
            self._pending.append(item)
            while len(self._pending) > MAX_PENDING:  # the IMU is silent (a fault is raised)
                self._pending.popleft()

    def _bridge_gap(self, t: float, gap: float) -> None:
        """An IMU gap ending at ``t``: the INS coasts through it on the raw samples' mean of
        the last seconds (a ship's motion is smooth, the waves cancel), the waiting
        measurements applied at their times, its covariance widened by what the gap left
        unmeasured."""
        ekf = self.ekf
        assert ekf is not None and self._last_raw is not None and self._raw_mean is not None
        t_last = self._last_raw[0]
        g0, a0 = self._raw_mean
        if self._yaw_step is not None:
            self._yaw_step.reset()  # the rate over the gap was not measured
        step = self.monitor.imu_interval  # at the IMU's own rate: one long step would not do
        for k in range(1, int(gap / step)):
            # The error of a held rate (acceleration) grows linearly in the attitude (velocity)
            # and quadratically in the position: the variance added over this step.
            a, b = (k - 1) * step, k * step
            ekf.inflate(position_m=0.5 * GAP_ACCEL_SIGMA * math.sqrt(b**4 - a**4),
                        velocity_mps=GAP_ACCEL_SIGMA * math.sqrt(b**2 - a**2),
                        attitude_rad=GAP_RATE_SIGMA * math.sqrt(b**2 - a**2))
            self._advance(t_last + b, g0, a0)

    def _check_yaw_step(self, t: float, gyro: np.ndarray) -> None:
        """The gyro's rate of turn against the hull's (``YawStepCheck``): a step beyond it is
        declared ("gyro") and the gyro's bias σ widened to it as it is measured, so that the
        rate of turn and the approach speeds say how far off they may be while the VO and the
        single differences teach the EKF the new bias; the carrier-phase heading's check then
        judges the gyro afresh (and clears the fault once they agree)."""
        ins, ekf, check = self.ins, self.ekf, self._yaw_step
        assert ins is not None and ekf is not None and check is not None
        # the raw gyro (bias and all): the EKF's bias corrections are no steps of the ship
        found = check.update(t, ins.level_yaw_rate(gyro), self.monitor.imu_interval,
                             ins.horizontal_speed)
        if found is None:
            return
        if found.widen > 0.0:
            ekf.inflate(0.0, 0.0, 0.0, gyro_bias=found.widen)
        if found.settled:  # declared once measured (a tenth of a second), widened already
            if self.carrier is not None:
                self.carrier.gyro.restart()
            self.monitor.raise_fault(
                "gyro", t, f"gyro's rate of turn stepped {math.degrees(found.step):+.2f}°/s, "
                f"more than a {check.length_m:.0f} m hull turns in "
                f"{check.RECENT_S + check.BEFORE_S:.1f} s ({math.degrees(found.bound):.2f}°/s):"
                " its bias re-learned")

    def _average(self, gyro: np.ndarray, accel: np.ndarray) -> None:
        """The raw samples' running mean (time constant ``GAP_MEAN_S``): what a gap coasts on."""
        if self._raw_mean is None:
            self._raw_mean = (gyro, accel)
            return
        w = min(1.0, self.monitor.imu_interval / GAP_MEAN_S)
        g, a = self._raw_mean
        self._raw_mean = (g + w * (gyro - g), a + w * (accel - a))

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
        assert self.ekf is not None and self.carrier is not None and self.origin is not None
        if item.kind == "gnss":
            self.carrier.update(item.time, item.payload, self.ekf,  # type: ignore[arg-type]
                                self.origin, self.front)
            self._timer.add("gnss_update", _time.perf_counter() - t0)
        else:
            self.coupling.update(item.payload, self.ekf,  # type: ignore[arg-type]
                                 self._timer.add, self.carrier.velocity_held(self.ekf.time),
                                 self.carrier.last_velocity_time
                                 if self.carrier.carrier_fresh(self.ekf.time) else None,
                                 self.carrier.attitude_held(self.ekf.time))
            self._timer.add("vo_update", _time.perf_counter() - t0)

    # -------------------------------------------------------------------- INS start

    def _sea_surface_aided(self, start: InsStart) -> tuple[np.ndarray, np.ndarray]:
        """The start's standalone fix (antenna-array centre) and its covariance, corrected
        with the antennas' height above the sea surface when it is known."""
        opt = self.options
        if opt.sea_surface is None or opt.body_origin_height_m is None:
            return start.spp_ecef, start.spp_covariance
        sea, sigma = opt.sea_surface
        centre_down = float((start.C_body_to_level @ self.antennas.mean(axis=0))[2])
        aided = height_aided(start.spp_ecef, start.spp_covariance,
                             sea + opt.body_origin_height_m - centre_down, sigma)
        if not aided.used:
            self.monitor.raise_fault(
                "sea-surface", start.time,
                f"sea-surface height {sea:g} m puts the antennas {aided.innovation_m:+.1f} m "
                f"from the standalone fix (σ {aided.innovation_sigma_m:.1f} m): not used, the "
                "origin's height taken as that uncertain — is the height above the "
                "ellipsoid, or the ionosphere far from its model?")
        return aided.position, aided.covariance

    def _start_ins(self, start: InsStart) -> None:
        """INS at the previous epoch (the world origin): compass attitude (or tilt + course),
        SPP position, TDCP velocity and clock drift of the interval; then the buffered IMU
        samples are replayed up to now."""
        C = start.C_body_to_level
        spp, spp_cov = self._sea_surface_aided(start)
        llh = ecef_to_geodetic(spp)
        C_el = C_ecef_to_level(llh[0], llh[1])
        lever_centre = self.antennas.mean(axis=0) - self.calibration.imu.lever_arm_body
        imu_ecef = spp - C_el.T @ (C @ lever_centre)
        origin_llh = ecef_to_geodetic(imu_ecef)
        self.origin = WorldOrigin(origin_llh, C_ecef_to_level(origin_llh[0], origin_llh[1]),
                                  start.time)
        C_el0 = self.origin.C_ecef_to_level
        self.monitor.origin_fix(C_el0 @ spp_cov @ C_el0.T)
        samples = self.alignment.samples_from(start.time, _PAST)
        omega = self._G @ samples[0][1] if samples else np.zeros(3)
        v0 = start.velocity_centre_ned - C @ np.cross(omega, lever_centre)
        state = InsState(time=start.time, position_ned=np.zeros(3), velocity_ned=v0,
                         C_body_to_level=C)
        self.ins = Ins(origin_llh, self.calibration.imu, state)
        # The interval's mean velocity stands for the velocity at its start (± ½ a Δt); the
        # delays are unknown until their fractions are found with the attitude.
        sig = {"velocity": 0.2, "clock_drift": 1.0, "delay": 0.2}
        if start.attitude_sigma is not None:
            sig["attitude"] = start.attitude_sigma
        self.ekf = ErrorStateEkf(
            self.ins, self.antennas, camera_to_body=self.calibration.camera.C_camera_to_body,
            camera_lever_body=self.calibration.camera.lever_arm_body,
            common_clock=self.options.common_clock, config=self.cfg,
            clock_drift=start.clock_drift_mps, initial_sigmas=sig)
        for ts, g, a in samples:
            self.ekf.propagate(ts, g, a)
        self.alignment.imu.clear()
        self.carrier = CarrierPhaseCoupling(self.nav, self.options, self.cfg, self.monitor,
                                            aligning=start.attitude_sigma is not None)


def _four_antennas(antennas: np.ndarray) -> np.ndarray:
    """The compass's four antennas; a receiver missing from the recording (three antennas
    given) stands at the centroid of the others, so the array centre stays where it is, and
    never observes anything (its epochs are all missing: the compass resolves on the three
    others, the carrier phase's single differences take the pairs that have epochs)."""
    if len(antennas) >= N_RECEIVERS:
        return antennas[:N_RECEIVERS]
    if len(antennas) < 2:
        raise ValueError(f"the GNSS compass needs at least 2 antennas, the calibration has "
                         f"{len(antennas)}")
    fill = np.repeat(antennas.mean(axis=0)[None], N_RECEIVERS - len(antennas), axis=0)
    return np.vstack([antennas, fill])
