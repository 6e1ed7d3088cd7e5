"""The VO inside the fusion and the port structure (thesis 5.1.1, figs. 16–17; the
EKF's output, ``METHOD.md``).

Each VO world (``VoOutput.segment``) is mapped into L once the camera has moved a little since
its first tracked frame (the first scale is the INS displacement over the VO one); from then on
every tracked frame updates the EKF (Θ, d) and the map points are carried into L with the
current scale and drift estimates (``structure``). While the single differences hold the
attitude, those updates leave it and the gyro bias alone (``ErrorStateEkf.update_vo``). A
lost segment's points are frozen in L.
Every tracked frame also feeds the landmark EKFs (``estimator.landmarks``, seed 000): each map
point seen is one EKF in L, seeded from its mapped VO point and updated with its pixel and the
fused camera pose and covariance; ``structure`` gives the refined point once it is reportable
(``structure(refined=False)``: the raw points).

Every tracked frame is first checked (``VoConsistency``): its rotation against the gyro's and
its direction of travel against the fused track. A VO that departs from them further than the
EKF's own model of its drift allows (a map built on a wrong two-view geometry, rotation traded
against sideways translation) would drag the fused heading with it. It is then excluded —
declared ("vo-inconsistent"), its segment dropped from the EKF, the attitude σ widened by what
it may have pulled — and mapped afresh once it has agreed again for the longest window. A VO
that still disagrees ``VO_RESTART_AFTER_S`` later with the carrier phase behind the fused track
is not going to agree: its world is wrong while its tracking is fine, so it would never
reinitialise by itself. It is restarted (``VoCoupling.restart``, taken by ``Fusion``) and its
new world checked from scratch.

Between two carrier-phase epochs the INS alone carries the position: an accelerometer step
there was 11 cm off under a 9 cm protection level for the second before the next epoch
declared it. The VO, which sees it, is loosely weighted in the EKF (its origin drifts), so
its updates hardly pull it back. Over that second the VO also dead-reckons a sub-solution
from the first frame after the epoch: that frame's camera position carried by the VO's own
displacement, mapped as the EKF held it then. Its horizontal separation from the fused
camera (``separation_m``) goes into the protection level (``IntegrityMonitor.assess``). This
is the solution separation of fault-detection practice: if the INS fails, the fused error is
at most the fault-free bound plus the separation. While both are right it is millimetres
once the VO's scale has settled, up to ~10 cm in a new world's first seconds.
"""

from __future__ import annotations

import math
import time as _time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from .ekf import EkfConfig, ErrorStateEkf, chi2_gate
from .frames import dcm_to_rotvec, vector_length
from .integrity import IntegrityMonitor
from .landmarks import (
    LandmarkMap,
    LandmarkParams,
    SolvedViews,
    camera_pose_covariance,
    sigma_along_ray,
)
from .records import CameraCalibration
from .vo import VoOutput

VO_START_BASELINE = 0.3  # VO units moved since the anchor frame before a segment is mapped
VO_START_METRES = 0.3  # ... and metres (a sensible first scale from the INS)
VO_START_SCALE_SIGMA = 0.3  # relative σ of that first scale
# The VO is compared with the gyro and the fused track over these spans: a fast runaway shows
# in the short one, a slow steady one in the long one. A gyro bias step of b is seen over a
# window T once b T passes the gate of the VO model's rotation drift (~0.12°/√s): T ≈ 0.3 s
# for 1°/s, which the 1 s window saw only after 0.6 s (the rate of turn wrong under a tight σ
# meanwhile); the YawStepCheck finds steps a hull cannot make at once.
VO_CHECK_WINDOWS_S = (0.3, 1.0, 2.0, 5.0)
MIN_TRAVEL_M = 1.0  # the direction of travel is checked over windows with this much of it
# A VO found inconsistent may have pulled the fused attitude by as much as it disagrees, but
# no more than this (a direction of travel tens of degrees off moves the heading degrees).
MAX_PULL_DEG = 3.0
# A VO still disagreeing this long after it was excluded has a wrong world (a marginal one
# agrees again sooner): it is restarted, if the fused track it disagrees with rests on the
# carrier phase (coasting on the INS, the fused track is the doubtful one).
VO_RESTART_AFTER_S = 15.0
# A frame's time is its exposure's to within the jitter of its stamps (a live camera stamps
# arrival: tens of ms): the scatter of the last frame intervals about their median measures
# it, and a turn at ω moves the VO's rotation by ω times it against the gyro's at the stamps.
FRAME_INTERVALS = 50


@dataclass(frozen=True)
class VoDisagreement:
    """The worst window of a VO that disagrees with the gyro or the fused track."""

    what: str  # "rotation" | "direction of travel"
    angle_rad: float  # between the VO's and the gyro's rotation / the fused displacement
    window_s: float
    nis: float  # the disagreement² over the variance the EKF's VO model allows


@dataclass(frozen=True)
class _SubSolution:
    """The VO sub-solution's start (module docstring): its first tracked frame after the
    carrier-phase epoch at ``carrier_time``, in VO world ``segment``."""

    carrier_time: float
    segment: int
    camera_position_world: np.ndarray  # VO units
    camera_position_ned: np.ndarray  # fused
    C_world_to_level: np.ndarray  # the EKF's mapping then
    scale: float


@dataclass(frozen=True)
class _Seen:
    t: float
    segment: int
    C_world_to_camera: np.ndarray
    camera_position_world: np.ndarray  # VO units
    C_gyro: np.ndarray  # ``Ins.C_gyro``
    C_level_to_camera: np.ndarray  # fused
    camera_position_ned: np.ndarray  # fused
    attitude_sigma: float  # fused, rad (largest axis)
    # the fused velocity's covariance (3,3) in L, (m/s)², while the fused track is not on the
    # carrier phase (coasting); None while it is (its displacement then good to millimetres)
    coasting_velocity_cov: np.ndarray | None



class VoConsistency:
    """The VO against what it cannot outvote, over ``VO_CHECK_WINDOWS_S``:

    - its rotation against the gyro's (``Ins.C_gyro``: integrated without the EKF's
      corrections, so without what the VO itself fed in);
    - its direction of travel (in the camera frame at the window's start) against the fused
      displacement (carrier phase: millimetres) seen through the fused attitude. A map built
      on a wrong two-view geometry (rotation traded against sideways translation) keeps the
      gyro's rotation and travels tens of degrees off; mapped into L, it drags the heading.

    A window disagrees beyond the χ² gate of the variance the EKF's VO model allows over it:
    the VO world's rotation drift (``vo_attitude_psd`` per second, ``vo_attitude_per_m`` per
    metre), its origin's drift and position noise across the travel, and the fused
    attitude's σ — and, when the fused track is not on the carrier phase, the fused
    displacement's own error: its velocity σ over the window. With the carrier phase that is
    millimetres; without it (satellites blocked) the fused track is the INS coasting, whose
    velocity error soon turns its direction of travel by degrees, and a right VO judged by it
    as if it were the carrier phase would be excluded again and again."""

    def __init__(self, cfg: EkfConfig, C_camera_to_body: np.ndarray) -> None:
        self.cfg = cfg
        self.C_cb = np.asarray(C_camera_to_body, float)
        self.gates = {"rotation": chi2_gate(3, cfg.gate_probability),
                      "direction of travel": chi2_gate(2, cfg.gate_probability)}
        self._seen: deque[_Seen] = deque()
        # the last frame up to which the gyro's rotation was no measurement: no window holding
        # it judges the VO's rotation
        self._unmeasured_at = -math.inf
        self._intervals: deque[float] = deque(maxlen=FRAME_INTERVALS)
        self.time_sigma = 0.0  # s, the stamps' jitter (FRAME_INTERVALS module comment)

    def check(self, now: _Seen, gyro_measured: bool = True) -> VoDisagreement | None:
        """Add a tracked frame; the worst disagreeing window ending at it, None if none.
        ``gyro_measured`` False: ``C_gyro`` up to this frame turned on an IMU gap's held mean
        rate, or the gyro is declared off (``carrier_phase.GyroCheck``)."""
        seen = self._seen
        if seen and 0.0 < now.t - seen[-1].t < 1.0:  # (a gap or a seek is no jitter)
            self._intervals.append(now.t - seen[-1].t)
            dt = np.asarray(self._intervals)
            # one interval's scatter is two stamps' jitter: /√2
            self.time_sigma = 1.4826 * float(np.median(np.abs(dt - np.median(dt)))) / math.sqrt(2)
        if seen and (seen[-1].segment != now.segment or now.t < seen[-1].t):
            seen.clear()  # another VO world (or time went back): nothing to compare with
            self._unmeasured_at = -math.inf
        seen.append(now)
        if not gyro_measured:
            self._unmeasured_at = now.t
        longest = max(VO_CHECK_WINDOWS_S)
        while len(seen) > 1 and now.t - seen[1].t >= longest:
            seen.popleft()
        worst = None
        for window in VO_CHECK_WINDOWS_S:
            old = next((e for e in reversed(seen) if now.t - e.t >= window - 1e-6), None)
            if old is None:
                continue
            rotation = self._rotation(old, now) if old.t > self._unmeasured_at else None
            for found in (rotation, self._direction(old, now)):
                if found is not None and found.nis > self.gates[found.what] and \
                        (worst is None or found.nis > worst.nis):
                    worst = found
        return worst

    def _rotation(self, old: _Seen, now: _Seen) -> VoDisagreement:
        cfg = self.cfg
        # camera at the start → camera now: by the VO, and by the gyro through the mounting
        R_vo = now.C_world_to_camera @ old.C_world_to_camera.T
        R_gyro = self.C_cb.T @ now.C_gyro.T @ old.C_gyro @ self.C_cb
        angle = vector_length(dcm_to_rotvec(R_vo @ R_gyro.T))
        travel = vector_length(now.camera_position_ned - old.camera_position_ned)
        rate = vector_length(dcm_to_rotvec(R_gyro)) / max(now.t - old.t, 1e-6)
        var = (cfg.vo_attitude_psd * (now.t - old.t) + cfg.vo_attitude_per_m * travel
               + 2.0 * (rate * self.time_sigma) ** 2)  # both ends' stamps
        return VoDisagreement("rotation", angle, now.t - old.t, angle**2 / var)

    def _direction(self, old: _Seen, now: _Seen) -> VoDisagreement | None:
        cfg = self.cfg
        fused = old.C_level_to_camera @ (now.camera_position_ned - old.camera_position_ned)
        travel = vector_length(fused)
        vo = old.C_world_to_camera @ (now.camera_position_world - old.camera_position_world)
        if travel < MIN_TRAVEL_M or not vector_length(vo) > 0.0:
            return None
        u = vo / vector_length(vo)
        across = vector_length(fused - (fused @ u) * u)  # m, off the VO's direction
        # the fused displacement's error across u (per axis of the 2 across it): its velocity
        # error held over the window, the larger of the two ends'
        Q = np.eye(3) - np.outer(u, u)
        C = old.C_level_to_camera
        fused_var = max((float(np.trace(Q @ C @ e.coasting_velocity_cov @ C.T @ Q))
                         for e in (old, now) if e.coasting_velocity_cov is not None), default=0.0)
        var = (cfg.vo_drift_psd * (now.t - old.t) + cfg.vo_drift_per_m * travel
               + 2.0 * cfg.vo_position_sigma**2 + (cfg.vo_position_relative * travel) ** 2
               + (old.attitude_sigma * travel) ** 2 + 0.5 * fused_var * (now.t - old.t) ** 2)
        return VoDisagreement("direction of travel", math.asin(min(1.0, across / travel)),
                              now.t - old.t, across**2 / var)

    def consistent_for(self, t: float) -> float:
        """How long (s) the checked frames of this segment span up to ``t``."""
        return t - self._seen[0].t if self._seen else 0.0



class _RawPoints:
    """The VO's map points as last output, by id (ids are unique across segments): the
    segment and the point in its world W. Kept in the order the ids first came, as arrays,
    so that a frame's ~500 points are taken in a few array operations."""

    def __init__(self) -> None:
        self.ids = np.zeros(0, np.int64)
        self.segment = np.zeros(0, np.int64)
        self.X = np.zeros((0, 3))
        self._order = np.zeros(0, np.int64)  # argsort of ids, for look-ups

    def update(self, segment: int, ids: np.ndarray, X: np.ndarray) -> None:
        """The points ``ids`` (unique) of world ``segment`` at ``X``; new ids go last."""
        ids = np.asarray(ids, np.int64)
        X = np.asarray(X, float).reshape(-1, 3)
        row = np.full(len(ids), -1)
        if len(self.ids):
            sorted_ids = self.ids[self._order]
            pos = np.clip(np.searchsorted(sorted_ids, ids), 0, len(sorted_ids) - 1)
            found = sorted_ids[pos] == ids
            row[found] = self._order[pos[found]]
        old = row >= 0
        self.X[row[old]] = X[old]
        self.segment[row[old]] = segment
        if not old.all():
            self.ids = np.concatenate([self.ids, ids[~old]])
            self.segment = np.concatenate([self.segment, np.full((~old).sum(), segment)])
            self.X = np.concatenate([self.X, X[~old]])
            self._order = np.argsort(self.ids, kind="stable")

    def of(self, segment: int) -> tuple[np.ndarray, np.ndarray]:
        """(ids, points in W) of a segment, in the order they came."""
        mine = self.segment == segment
        return self.ids[mine], self.X[mine]

    def drop(self, segment: int) -> None:
        keep = self.segment != segment
        self.ids, self.segment, self.X = self.ids[keep], self.segment[keep], self.X[keep]
        self._order = np.argsort(self.ids, kind="stable")


class VoCoupling:
    """VO segments mapped into L, their EKF updates, and the port structure."""

    def __init__(self, camera: CameraCalibration, landmarks: LandmarkParams | None,
                 water_down_m: float | None, monitor: IntegrityMonitor | None = None) -> None:
        self.status = "initialising"  # the VO's last status
        self.monitor = monitor
        self.consistency: VoConsistency | None = None  # made with the EKF (its VO model)
        self.excluded_since: float | None = None  # gpst of the last disagreement while excluded
        self._disagreeing_since: float | None = None  # gpst of the exclusion (this world's)
        self._excluded_by: set[str] = set()  # what it disagreed in while excluded
        # (segment, next_id) the VO must restart with before its next frame, None if not
        # (``VisualOdometry.restart``; the fusion does it and clears this)
        self.restart: tuple[int, int] | None = None
        self._anchor: tuple[int, np.ndarray, np.ndarray] | None = None  # segment, p_W, r_cam
        self._points = _RawPoints()
        self.frozen: dict[int, np.ndarray] = {}  # id → L point of ended segments
        self.frozen_sigma: dict[int, float] = {}
        self.landmarks: LandmarkMap | None = None
        if landmarks is not None:
            if water_down_m is not None and landmarks.water_down_m is None:
                landmarks = replace(landmarks, water_down_m=float(water_down_m))
            self.landmarks = LandmarkMap(camera.focal_px, landmarks)
        self._K = np.asarray(camera.K, float)
        self._dist = np.asarray(camera.distortion, float).ravel()
        self._since_carrier: _SubSolution | None = None
        self.separation_m = 0.0  # its horizontal separation from the fused camera (m)

    # ---------------------------------------------------------------------------- input

    def update(self, out: VoOutput, ekf: ErrorStateEkf,
               timed: Callable[[str, float], None], carrier_fresh: bool = True,
               carrier_time: float | None = None, attitude_held: bool = False) -> None:
        """One VO output at its time (the INS is there): map a new segment, or update the
        EKF with Θ and d and the landmarks with the views. ``carrier_fresh``: the fused track
        rests on the carrier phase now (a wrong VO world may then be restarted; else the
        check weighs the coasting track's own velocity σ). ``carrier_time``: gpst of the
        last carrier-phase velocity update, where the VO sub-solution starts afresh; None
        while the carrier phase is stale (coasting, the INS and the VO are weighed by their
        covariance: no sub-solution). ``attitude_held``: the single differences hold the
        attitude now; the VO updates leave it and the gyro bias alone."""
        if out.status != "tracking" or out.C_world_to_camera is None \
                or out.camera_position_world is None:
            if out.status == "lost":
                self.freeze_segment(ekf)
                self._anchor = None
            return
        if not self._consistent(out, ekf, carrier_fresh):
            return
        self._points.update(out.segment, out.point_ids, out.points_world)
        p = np.asarray(out.camera_position_world, float)
        if ekf.vo is None or ekf.vo.segment != out.segment:
            self._start_segment(out, p, ekf)
            return
        self._separate(out.segment, p, ekf, carrier_time)
        ekf.update_vo(out.C_world_to_camera, p, hold_attitude=attitude_held)
        if self.landmarks is not None:
            t0 = _time.perf_counter()
            self._refine_landmarks(out, ekf)
            timed("landmarks", _time.perf_counter() - t0)

    def _separate(self, segment: int, p_world: np.ndarray, ekf: ErrorStateEkf,
                  carrier_time: float | None) -> None:
        """Carry the VO sub-solution to this frame (before its update), or start it at the
        first frame after a carrier-phase epoch or in a new VO world."""
        vo = ekf.vo
        assert vo is not None
        if carrier_time is None:
            self._since_carrier, self.separation_m = None, 0.0
            return
        cam = ekf.camera_position()
        ref = self._since_carrier
        if ref is None or ref.carrier_time != carrier_time or ref.segment != segment:
            self._since_carrier = _SubSolution(carrier_time, segment, p_world.copy(), cam,
                                               vo.C_world_to_level.copy(), vo.scale)
            self.separation_m = 0.0
            return
        carried = ref.camera_position_ned + ref.scale * (
            ref.C_world_to_level @ (p_world - ref.camera_position_world))
        self.separation_m = float(np.hypot(*(carried - cam)[:2]))

    @property
    def excluded(self) -> bool:
        return self.excluded_since is not None

    def _consistent(self, out: VoOutput, ekf: ErrorStateEkf, carrier_fresh: bool) -> bool:
        """Check the VO against the gyro and the fused track (module docstring): False while
        it is excluded."""
        if self.consistency is None:
            self.consistency = VoConsistency(ekf.cfg, ekf.C_camera_to_body)
        t = float(out.time)
        ekf.flush()
        bad = self.consistency.check(_Seen(
            t, out.segment, np.asarray(out.C_world_to_camera, float),
            np.asarray(out.camera_position_world, float), ekf.ins.C_gyro.copy(),
            ekf.camera_attitude(), ekf.camera_position(),
            math.sqrt(max(float(np.linalg.eigvalsh(ekf.P[ekf.ix.E, ekf.ix.E])[-1]), 0.0)),
            None if carrier_fresh else ekf.P[ekf.ix.V, ekf.ix.V].copy()),
            gyro_measured=self.monitor is None or not (self.monitor.imu_bridged()
                                                       or self.monitor.is_active("gyro")))
        if bad is not None:
            judge = "the gyro" if bad.what == "rotation" else "the fused track"
            off = (f"VO {bad.what} {math.degrees(bad.angle_rad):.1f}° off {judge} over "
                   f"{bad.window_s:.1g} s")
            if not self.excluded:
                # What it may have pulled the attitude by: widen the attitude σ so much. A
                # rotation the gyro disagrees with may be the gyro's fault (a bias step) as
                # well as the VO's: its bias σ is widened too, so the single differences can
                # take the heading back if it is.
                pull = min(bad.angle_rad, math.radians(MAX_PULL_DEG))
                ekf.inflate(0.0, 0.0, pull, gyro_bias=pull / bad.window_s
                            if bad.what == "rotation" else 0.0)
                self._drop_segment(ekf)
                if self.monitor is not None:
                    self.monitor.raise_fault("vo-inconsistent", t, f"{off}: VO excluded")
            self._excluded_by.add(bad.what)
            if self._disagreeing_since is None:
                self._disagreeing_since = t
            elif t - self._disagreeing_since >= VO_RESTART_AFTER_S and carrier_fresh:
                self.restart = (out.segment + 1, out.next_id)  # this world is wrong
                self._disagreeing_since = None
                if self.monitor is not None:
                    self.monitor.raise_fault(
                        "vo-inconsistent", t, f"{off}, {VO_RESTART_AFTER_S:.0f} s after it was "
                        "excluded: VO restarted", news=True)
            self.excluded_since = t
            return False
        if not self.excluded:
            return True
        self.excluded_since = min(self.excluded_since, t)  # (time went back: from now)
        # Excluded for its rotation alone, by a gyro since found off the carrier-phase heading
        # (``carrier_phase.GyroCheck``): it was the gyro's fault, and the VO, which holds the
        # heading while the gyro's bias is learned again, is taken back at once.
        gyro_blamed = self._excluded_by == {"rotation"} and self.monitor is not None \
            and self.monitor.is_active("gyro")
        if not gyro_blamed and (self.consistency.consistent_for(t) < max(VO_CHECK_WINDOWS_S)
                                or t - self.excluded_since < max(VO_CHECK_WINDOWS_S)):
            return False
        self.excluded_since = self._disagreeing_since = None
        self._excluded_by = set()
        if self.monitor is not None:
            self.monitor.clear("vo-inconsistent", t,
                               "the gyro was off, not the VO: mapped afresh" if gyro_blamed
                               else "VO agrees with the gyro and the fused track again: mapped "
                               "afresh")
        return True

    def _drop_segment(self, ekf: ErrorStateEkf) -> None:
        """Forget the current VO segment's mapping and raw points (not frozen: its geometry
        is wrong); the landmarks, refined from the fused poses, stay."""
        if ekf.vo is not None:
            self._points.drop(ekf.vo.segment)
            ekf.vo = None
        self._anchor = None

    def _start_segment(self, out: VoOutput, p: np.ndarray, ekf: ErrorStateEkf) -> None:
        """A new VO world: anchored at its first tracked frame, mapped into L once the camera
        has moved enough for a first scale."""
        if ekf.vo is not None:
            self.freeze_segment(ekf)
        anchor = self._anchor
        if anchor is None or anchor[0] != out.segment:
            self._anchor = (out.segment, p, ekf.camera_position())
            return
        dp = np.linalg.norm(p - anchor[1])
        dr = np.linalg.norm(ekf.camera_position() - anchor[2])
        if dp < VO_START_BASELINE or dr < VO_START_METRES:
            return
        scale = dr / dp
        ekf.start_vo_segment(out.segment, out.C_world_to_camera, p, scale,
                             VO_START_SCALE_SIGMA * scale)
        self._anchor = None

    def _refine_landmarks(self, out: VoOutput, ekf: ErrorStateEkf) -> None:
        """One view of the landmark EKFs (``estimator.landmarks``): the map points seen in this
        frame (new ones seeded from the VO point mapped into L) with the fused camera pose and
        its covariance at the frame time."""
        lm = self.landmarks
        assert ekf.vo is not None and lm is not None
        ids, uv = out.observations
        ids = np.asarray(ids, np.int64)
        if len(ids) == 0:
            return
        ekf.flush()
        ix, P = ekf.ix, ekf.P
        C_bl = ekf.nominal.C_body_to_level
        C_lc = ekf.camera_attitude()
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
        lm.update(out.time, C_lc, p_cam, pose_cov, ids, xy, busy=out.is_keyframe)

    def freeze_segment(self, ekf: ErrorStateEkf | None) -> None:
        """Keep the points of an ended VO segment in L as they were last mapped."""
        if ekf is None or ekf.vo is None:
            return
        seg = ekf.vo.segment
        cur, X = self._points.of(seg)
        if len(cur):
            for pid, q, s in zip(cur.tolist(), ekf.vo_to_level(X), ekf.vo_point_sigma(X),
                                 strict=True):
                self.frozen[pid] = q
                self.frozen_sigma[pid] = float(s)
        self._points.drop(seg)
        ekf.vo = None

    # --------------------------------------------------------------------------- output

    def solved_views(self) -> SolvedViews | None:
        """The landmark window's views with their solved attitudes (``SolvedViews``); None
        without the joint refinement."""
        lm = self.landmarks
        return None if lm is None or lm.window is None else lm.window.solved()

    def _mapped(self, ekf: ErrorStateEkf | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points in L, σ, ids) of the frozen segments and the current one (raw VO)."""
        ids, pts, sig = [], [], []
        for pid, p in self.frozen.items():
            ids.append(pid)
            pts.append(p)
            sig.append(self.frozen_sigma[pid])
        if ekf is not None and ekf.vo is not None:
            cur, X = self._points.of(ekf.vo.segment)
            if len(cur):
                pts.extend(ekf.vo_to_level(X))
                sig.extend(ekf.vo_point_sigma(X))
                ids.extend(cur.tolist())
        if not ids:
            return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
        return np.array(pts), np.array(sig), np.array(ids, np.int64)

    def structure(self, ekf: ErrorStateEkf | None, refined: bool = True
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Port-structure points in L, their 1-σ (m), ids (``Fusion.structure``)."""
        pts_a, sig_a, ids_a = self._mapped(ekf)
        if not refined or self.landmarks is None or not len(ids_a):
            return pts_a, sig_a, ids_a
        lm = self.landmarks
        rows, ok, rejected = lm.classify(ids_a)
        have = rows >= 0
        x_lm, P_lm = lm.best(rows[have])
        pts_a[ok] = x_lm[ok[have]]
        seen_from = lm.last_camera[rows[have]]
        unseen = ~np.isfinite(seen_from).all(axis=1)
        if ekf is not None:
            seen_from[unseen] = ekf.camera_position()
        # A monocular point errs along its viewing ray: its σ is the covariance's along the
        # ray from the camera that last saw it (else the current one), what a click or a
        # distance along that ray reads and what the map's own convergence test uses — not
        # the RMS of the three axes, which understated it by up to √3.
        sig_lm = sigma_along_ray(x_lm, P_lm, seen_from)
        nowhere = ~np.isfinite(sig_lm)  # no camera at all: the RMS over the axes
        sig_lm[nowhere] = np.sqrt(np.trace(P_lm[nowhere], axis1=1, axis2=2) / 3.0)
        # Reportable: the landmark's σ; still converging: the larger of the two.
        sig_a[have] = np.where(ok[have], sig_lm, np.maximum(sig_a[have], sig_lm))
        # A point whose σ exceeds its range (from the camera that last saw it, else the
        # current one) says nothing of where it is (a far VO point re-triangulated near, a
        # reflection): left out.
        vague = np.zeros(len(ids_a), bool)
        with np.errstate(invalid="ignore"):  # no camera at all: NaN, kept
            vague[have] = sig_a[have] > np.linalg.norm(pts_a[have] - seen_from, axis=1)
        keep = ~rejected & ~vague
        return pts_a[keep], sig_a[keep], ids_a[keep]

    def converged_ids(self, ids: np.ndarray) -> np.ndarray:
        """Those of ``ids`` whose landmark is reportable (converged), in their order."""
        ids = np.asarray(ids, np.int64)
        if self.landmarks is None:
            return ids[:0]
        return ids[self.landmarks.classify(ids)[1]]

    def landmark_views(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids, accepted views; 0 for a dropped one) of every landmark seeded so far."""
        lm = self.landmarks
        if lm is None:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return lm.ids.copy(), np.where(lm.alive, lm.views, 0)

    def landmark_positions(self, ids: np.ndarray) -> np.ndarray:
        """Reported positions (the joint window's where it has one) of landmarks ``ids``."""
        assert self.landmarks is not None
        return self.landmarks.best(self.landmarks.lookup(ids))[0]
