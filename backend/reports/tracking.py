"""Evaluation of the supporting techniques (SPEC section 7) on a recording with a reference:
designated-target tracking (seed 002's fig. 7) and the port-structure refinement (seed 000's
fig. 10). Pure functions; the replay report (``backend/reports/replay.py``) calls them:

    clicks = default_clicks(rec)
    run = run_fusion(rec, vo_outputs=rp.vo, snapshot_frames=[c.frame for c in clicks],
                     snapshot_every=REANCHOR_FRAMES)
    report["tracking"] = evaluate_tracking(rec, run, clicks)
    report["landmarks"] = evaluate_landmarks(rec, run)

``run_fusion`` replays the recording through ``estimator.pipeline.Fusion`` exactly as the
replay report does (IMU before GNSS before the frame at equal time tags; cached VO outputs are
fed through ``process_vo``) and keeps what the evaluations need: the fused pose and its
covariance at every frame, the port structure and the structure window's solved views at the
click frames (a target is designated from the structure of ITS frame — causal) and once a
second after the first click (as the server refreshes them), the landmark estimates as
reported (the joint window's where it has one) when their view count reaches the
checkpoints, and the last view of every landmark.

Scoring (the estimator never sees any of this):

- Tracking. A click is the TRUE projection (reference pose + calibration) of a true scene
  point (``rec.scene_points``) at the click frame: by default quay points (quay edge,
  fenders, ladders, bollards) 5–30 m from the camera, several clicks spread over the replay.
  Each is tracked from its frame to the end by the full method (``DesignatedTarget``,
  exactly what the server runs: tracked back through the frames before the click, its 3-D
  point triangulated in the solved views once a second) and by the two ablations of seed
  002's fig. 7, ``template`` (adaptive template matching alone) and ``camshift_pf`` (the
  CAMSHIFT-guided particle filter alone). Pixel error = tracked point − true projection of
  the clicked scene point, over the frames where the method reports "tracking" and the point
  is in the image. An UNDETECTED loss is a frame reported "tracking" more than ``LOSS_PX``
  from the truth (or with the point out of the image). Distance error = the target's
  distance (fused camera → its 3-D point) − the true distance (true camera → the true scene
  point); tolerance ``max(10 cm, 1 % of the range)``. ``fixed_point`` is the distance of the
  point designated at the click without any image tracking afterwards (the server's
  behaviour before the tracker).
- Landmarks. Where the recording is a simulation whose scene can be rebuilt
  (``manifest.scenario`` / ``seed``, checked against ``scene_points``), the truth of a
  landmark is the rendered true depth at the pixel of its last view (rendered every
  ``TRUTH_STRIDE`` frames; pixels on a depth discontinuity are skipped): its error is the
  depth error along that ray (the monocular error, ``depth``) and the distance to the true
  surface point there (``xyz``). The fusion's world frame is aligned to the reference by the
  translation at its origin time, as in the replay report. The replay report's convention
  (nearest true scene point within ``max(1 m, 5 % of the range)``) is given as well; the scene
  points are sparse (about a metre apart), so it mostly measures that sparsity.
"""

from __future__ import annotations

import math
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from estimator.frames import euler_to_dcm
from estimator.landmarks import camera_pose_covariance
from estimator.tracking import (
    METHODS,
    DesignatedTarget,
    TargetParams,
    TargetTracker,
    point_on_ray,
    structure_point_at,
)

LOSS_PX = 10.0  # a "tracking" point farther than this from the truth is an undetected loss
# The structure is snapshot (and the targets refreshed on it) every this many frames after the
# first click: once a second, as the server refreshes it.
REANCHOR_FRAMES = 10
CLICK_KINDS = ("quay", "fender", "ladder")  # on the quay wall (bollards: see the report)
CLICK_RANGE_M = (5.0, 30.0)
CLICK_MARGIN_PX = 40.0  # clicked points at least this far inside the image
VIEW_CHECKPOINTS = (1, 2, 3, 5, 10, 20, 50, 100, 200, 400)
TRUTH_STRIDE = 5  # frames between rendered depth maps (landmark truth)
BANDS_M = ((0.0, 10.0), (10.0, 30.0), (30.0, 60.0), (60.0, math.inf))
MATCH_GATE_M = 1.0  # replay report's scene-point matching: max(1 m, 5 % of the range)
MATCH_GATE_FRACTION = 0.05
DISTANCE_TOL_M = 0.10
DISTANCE_TOL_FRACTION = 0.01
DESIGNATED = "designated"  # the server's pipeline: full tracker + 3-D point + re-acquisition
EVAL_METHODS = (DESIGNATED, *METHODS)
NCOL = 11  # columns of a target's per-frame series (see _method_scores)
FRAME_RATE_HZ = 10.0  # for "seconds since the click" (the recordings' frame rate)
SETTLED_S = 5.0  # distance figures also given from this long after the click


# -------------------------------------------------------------------------- fusion run


@dataclass
class Click:
    frame: int  # index of the clicked video frame
    uv: tuple[float, float]  # clicked pixel (distorted)
    point: int | None = None  # index into rec.scene_points; None: the one under the pixel
    label: str = ""


@dataclass
class FusionRun:
    """A fusion replay sampled at the frame times (NaN before the INS starts)."""

    time: np.ndarray  # (N,) gpst of the frames
    position_ned: np.ndarray  # (N,3) body origin in the fusion's world frame
    C_body_to_level: np.ndarray  # (N,3,3)
    position_cov: np.ndarray  # (N,3,3)
    attitude_cov: np.ndarray  # (N,3,3)
    origin_time: float | None
    lever_camera: np.ndarray  # camera centre in the body frame relative to the body origin
    C_camera_to_body: np.ndarray
    structure_at: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(
        default_factory=dict)  # frame → Fusion.structure() after that frame
    views_at: dict[int, Any] = field(default_factory=dict)  # frame → Fusion.solved_views()
    structure: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # final, refined
    structure_raw: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # final, raw
    # ids of the final structure whose landmark has converged (reportable, not converging)
    converged_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    # checkpoint → (ids, positions as reported: the joint window's where it has one) of the
    # landmarks reaching that many views
    view_history: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    last_views: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)
    timing_ms: dict[str, float] = field(default_factory=dict)
    wall_s: float = 0.0
    vo_ms: float | None = None

    def camera(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(C_level_to_camera, camera centre, 6x6 pose covariance) at frame k, None before
        the fusion started."""
        p = self.position_ned[k]
        if not np.isfinite(p).all():
            return None
        C = self.C_body_to_level[k]
        lever = C @ self.lever_camera
        cov = camera_pose_covariance(self.position_cov[k], self.attitude_cov[k], lever)
        return (C @ self.C_camera_to_body).T, p + lever, cov


def run_fusion(rec: Any, vo_outputs: Sequence[Any] | None = None,
               snapshot_frames: Iterable[int] = (), snapshot_every: int = 0,
               options: Any = None,
               end_s: float | None = None,
               progress: Callable[[str], None] | None = None) -> FusionRun:
    """Replay ``rec`` through the fusion (``options``: ``FusionOptions``, default ones) and
    keep what the evaluations need (module docstring). ``vo_outputs``: the VO's outputs per
    frame when already computed (the replay report's ``rp.vo``), else the VO runs here."""
    from engine.messages import group_gnss
    from estimator.pipeline import Fusion, FusionOptions
    from estimator.vo import VisualOdometry

    start = float(rec.manifest.start_gpst)
    end = start + (float(rec.manifest.duration_s) if end_s is None else float(end_s))
    vo_ms = None
    if vo_outputs is None:
        vo = VisualOdometry(rec.calibration.camera)
        outs = []
        tic = time.perf_counter()
        for _, t, image in rec.frames():
            if t > end + 1e-9:
                break
            outs.append(vo.process(t, image))
        vo_ms = 1e3 * (time.perf_counter() - tic) / max(len(outs), 1)
        vo_outputs = outs
    vo_outputs = [o for o in vo_outputs if o.time <= end + 1e-9]
    n = len(vo_outputs)
    imu = rec.imu
    gnss = [m for m in group_gnss(rec) if m.t <= end + 1e-9]
    events = [(float(t), 0, i) for i, t in enumerate(imu.time) if t <= end + 1e-9]
    events += [(m.t, 1, i) for i, m in enumerate(gnss)]
    events += [(float(o.time), 2, i) for i, o in enumerate(vo_outputs)]
    events.sort()
    f = Fusion(rec.calibration, rec.nav, options or FusionOptions())
    cam = rec.calibration.camera
    run = FusionRun(
        time=np.array([o.time for o in vo_outputs], float),
        position_ned=np.full((n, 3), np.nan), C_body_to_level=np.full((n, 3, 3), np.nan),
        position_cov=np.full((n, 3, 3), np.nan), attitude_cov=np.full((n, 3, 3), np.nan),
        origin_time=None,
        lever_camera=np.asarray(cam.lever_arm_body, float)
        - np.asarray(rec.calibration.imu.lever_arm_body, float),
        C_camera_to_body=np.asarray(cam.C_camera_to_body, float), vo_ms=vo_ms)
    snaps = set(int(k) for k in snapshot_frames)
    if snapshot_every > 0 and snaps:  # and every ``snapshot_every`` frames after the first
        snaps |= set(range(min(snaps), n, snapshot_every))
    history: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {c: [] for c in VIEW_CHECKPOINTS}
    prev_views = np.zeros(0, np.int64)
    tic = time.perf_counter()
    for t, kind, i in events:
        if kind == 0:
            f.process_imu(t, imu.gyro[i], imu.accel[i])
            continue
        if kind == 1:
            f.process_gnss(t, list(gnss[i].epochs))
            continue
        out = vo_outputs[i]
        f.process_vo(out)
        s = f.state(at=t)
        if s is not None:
            run.position_ned[i], run.C_body_to_level[i] = s.position_ned, s.C_body_to_level
            run.position_cov[i], run.attitude_cov[i] = s.position_cov, s.attitude_cov
        if i in snaps:
            run.structure_at[i] = f.structure()
            run.views_at[i] = f.solved_views()
        lm = f.landmarks
        if lm is not None and len(lm.views):
            views = np.where(lm.alive, lm.views, 0)
            prev = np.zeros(len(views), np.int64)
            prev[:len(prev_views)] = prev_views[:len(views)]
            for c in VIEW_CHECKPOINTS:
                hit = np.flatnonzero((prev < c) & (views >= c))
                if len(hit):
                    history[c].append((lm.ids[hit].copy(), lm.best(hit)[0]))
            prev_views = views
        if i % TRUTH_STRIDE == 0:
            for pid, uv in zip(*out.observations, strict=True):
                run.last_views[int(pid)] = (i, np.asarray(uv, float))
    run.wall_s = time.perf_counter() - tic
    run.origin_time = f.origin_time
    if f.ekf is not None:
        run.structure = f.structure()
        run.structure_raw = f.structure(refined=False)
        if f.landmarks is not None:
            ids = run.structure[2]
            run.converged_ids = ids[f.landmarks.classify(ids)[1]]
    for c, parts in history.items():
        if parts:
            run.view_history[c] = (np.concatenate([p[0] for p in parts]),
                                   np.concatenate([p[1] for p in parts]))
    run.timing_ms = {k: float(v) for k, v in f.timing().items()}
    if progress is not None:
        progress(f"fusion for the tracking/landmark evaluation: {run.wall_s:.1f} s")
    return run


# ------------------------------------------------------------------------------ truth


@dataclass
class _Truth:
    """True camera poses at the frame times, in the reference frame."""

    C_level_to_camera: np.ndarray  # (N,3,3)
    position: np.ndarray  # (N,3) camera centre
    origin: np.ndarray  # reference position of the fusion's world origin


def _truth(rec: Any, run: FusionRun) -> _Truth:
    ref = rec.reference
    pos, _vel, eul = ref.interpolate(run.time)
    cam = rec.calibration.camera
    Cs = np.array([euler_to_dcm(*e) for e in eul])
    lever = np.asarray(cam.lever_arm_body, float)
    cpos = pos + np.einsum("nij,j->ni", Cs, lever)
    C_lc = np.einsum("nij,jk->nki", Cs, np.asarray(cam.C_camera_to_body, float))
    origin = ref.interpolate(run.origin_time)[0] if run.origin_time is not None else \
        np.full(3, np.nan)
    return _Truth(C_lc, cpos, origin)


def _project(camera: Any, C: np.ndarray, p: np.ndarray, X: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels (N,2) and depths (N,) of points X (N,3); NaN pixels behind."""
    X = np.asarray(X, float).reshape(-1, 3)
    xc = (X - p) @ C.T
    uv = np.full((len(X), 2), np.nan)
    front = xc[:, 2] > 0.2
    if front.any():
        proj, _ = cv2.projectPoints(xc[front], np.zeros(3), np.zeros(3),
                                    np.asarray(camera.K, float),
                                    np.asarray(camera.distortion, float))
        uv[front] = proj.reshape(-1, 2)
    return uv, xc[:, 2]


def _rebuild_scene(rec: Any) -> Any | None:
    """The simulator's scene of a simulated recording (None for a real one or a mismatch)."""
    try:
        from recordings.sim.scenarios import SCENARIOS
        from recordings.sim.scene import PortScene
    except ImportError:
        return None
    m = rec.manifest
    if getattr(m, "scenario", None) not in SCENARIOS or getattr(m, "seed", None) is None:
        return None
    scene = PortScene.build(SCENARIOS[m.scenario], int(m.seed))
    pts = rec.scene_points
    if pts is None or len(pts) != len(scene.points) or \
            np.max(np.abs(np.asarray(pts, float) - scene.points)) > 1e-3:
        return None
    return scene


DEFAULT_CLICK_TIMES_S = (45.0, 52.0, 60.0, 66.0, 72.0, 78.0)  # s after the start


def default_clicks(rec: Any, times_s: Sequence[float] = DEFAULT_CLICK_TIMES_S,
                   per_time: int = 3, kinds: Sequence[str] = CLICK_KINDS,
                   range_m: tuple[float, float] = CLICK_RANGE_M, seed: int = 0) -> list[Click]:
    """Designated quay points for the evaluation: at each of ``times_s`` (s after the
    start) up to ``per_time`` true scene points of ``kinds`` at ``range_m`` from the camera,
    in view (and, for a simulated recording, not hidden behind anything), spread across the
    image; the click is their true projection."""
    if rec.reference is None or rec.scene_points is None:
        return []
    frame_t = np.asarray(rec.frame_times, float)
    start = float(rec.manifest.start_gpst)
    kinds_all = np.array(rec.scene_point_kinds or [""] * len(rec.scene_points))
    pts = np.asarray(rec.scene_points, float)
    pick = np.flatnonzero(np.isin(kinds_all, list(kinds)))
    cam = rec.calibration.camera
    scene = _rebuild_scene(rec)
    rng = np.random.default_rng(seed)
    out: list[Click] = []
    for ts in times_s:
        k = int(np.argmin(np.abs(frame_t - (start + ts))))
        pos, _v, e = rec.reference.interpolate(frame_t[k])
        if not np.isfinite(pos).all():
            continue
        C_bl = euler_to_dcm(*e)
        C = (C_bl @ cam.C_camera_to_body).T
        c = pos + C_bl @ np.asarray(cam.lever_arm_body, float)
        uv, z = _project(cam, C, c, pts[pick])
        rng_m = np.linalg.norm(pts[pick] - c, axis=1)
        m = CLICK_MARGIN_PX
        ok = (np.isfinite(uv).all(axis=1) & (uv[:, 0] > m) & (uv[:, 0] < cam.width - 1 - m)
              & (uv[:, 1] > m) & (uv[:, 1] < cam.height - 1 - m)
              & (rng_m >= range_m[0]) & (rng_m <= range_m[1]))
        cand = np.flatnonzero(ok)
        if scene is not None and len(cand):
            _img, depth = scene.render(C, c, frame_t[k] - start, cam, np.random.default_rng(0),
                                       return_depth=True)
            vis = []
            for j in cand:
                u, v = int(round(uv[j, 0])), int(round(uv[j, 1]))
                dz = depth[v - 1:v + 2, u - 1:u + 2]
                vis.append(bool(np.isfinite(dz).all() and np.min(np.abs(dz - z[j]))
                                < 0.03 * z[j]))
            cand = cand[np.array(vis, bool)]
        chosen: list[int] = []
        for j in rng.permutation(cand):
            if all(np.linalg.norm(uv[j] - uv[i]) > 120.0 for i in chosen):
                chosen.append(int(j))
            if len(chosen) >= per_time:
                break
        for j in chosen:
            out.append(Click(frame=k, uv=(float(uv[j, 0]), float(uv[j, 1])),
                             point=int(pick[j]), label=f"{kinds_all[pick[j]]}@{ts:g}s"))
    return out


def _clicked_point(rec: Any, truth: _Truth, click: Click) -> int | None:
    """The scene point under the click: the given one, else the nearest true projection
    within 3 px (the nearest to the camera when several)."""
    if click.point is not None:
        return int(click.point)
    k = click.frame
    uv, z = _project(rec.calibration.camera, truth.C_level_to_camera[k], truth.position[k],
                     rec.scene_points)
    d = np.linalg.norm(uv - np.asarray(click.uv, float), axis=1)
    near = np.flatnonzero(np.nan_to_num(d, nan=np.inf) < 3.0)
    if not len(near):
        return None
    return int(near[np.argmin(z[near])])


def _designate(rec: Any, run: FusionRun, click: Click
               ) -> tuple[np.ndarray, np.ndarray, str, int] | None:
    """The server's designation at the click frame: the structure points projecting within
    ``estimator.tracking.DESIGNATION_RADIUS_PX`` of the click (``point_on_ray``), else the
    water plane."""
    pose = run.camera(click.frame)
    if pose is None:
        return None
    C, c, _cov = pose
    cam = rec.calibration.camera
    f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
    xy = cv2.undistortPoints(np.array([[click.uv]], np.float64), np.asarray(cam.K, float),
                             np.asarray(cam.distortion, float)).reshape(2)
    ray = C.T @ np.array([xy[0], xy[1], 1.0])
    ray /= np.linalg.norm(ray)
    pts, sigma, _ids = run.structure_at.get(click.frame, (np.zeros((0, 3)), np.zeros(0), None))
    if len(pts):
        uv, _z = _project(cam, C, c, pts)
        found = structure_point_at(pts, sigma, uv, np.asarray(click.uv, float), c, ray, f)
        if found is not None:
            return found[0], found[1], "structure", len(found[2])
    h = rec.hull.body_origin_height_m
    if h is None or ray[2] <= 1e-6:
        return None
    s = (float(h) - c[2]) / ray[2]
    X, P = point_on_ray(c[None] + s * ray[None], None, c, ray, f)
    return X, P, "water-plane", 0


# --------------------------------------------------------------------------- tracking


def _stats(e: np.ndarray) -> dict[str, Any]:
    e = np.asarray(e, float)
    e = e[np.isfinite(e)]
    if not len(e):
        return {"n": 0, "median": None, "p90": None, "max": None, "rms": None}
    a = np.abs(e)
    return {"n": int(len(e)), "median": float(np.median(a)), "p90": float(np.percentile(a, 90)),
            "max": float(a.max()), "rms": float(np.sqrt(np.mean(e**2)))}


def evaluate_tracking(rec: Any, run: FusionRun, clicks: Sequence[Click] | None = None,
                      methods: Sequence[str] = EVAL_METHODS, window: int = 31,
                      end_s: float | None = None, seed: int = 0,
                      progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Seed 002 fig. 7 on a recording: pixel error of each tracking method against the true
    projection of the clicked scene point, loss detection, and the distance error of the
    designated target (module docstring). ``run`` from ``run_fusion`` (with the click frames
    in ``snapshot_frames``); ``clicks`` default to ``default_clicks(rec)``."""
    if rec.reference is None or rec.scene_points is None:
        return {"reason": "no reference trajectory or no scene points to score against"}
    if clicks is None:
        clicks = default_clicks(rec)
    if not clicks:
        return {"clicks": [], "methods": {},
                "reason": f"no quay point {CLICK_RANGE_M[0]:g}–{CLICK_RANGE_M[1]:g} m from the "
                          "camera in view at the click times"}
    truth = _truth(rec, run)
    cam = rec.calibration.camera
    W, H = int(cam.width), int(cam.height)
    half = 0.5 * window
    start = float(rec.manifest.start_gpst)
    n_frames = len(run.time)
    if end_s is not None:
        n_frames = int(np.searchsorted(run.time, start + end_s + 1e-9))
    targets: list[dict[str, Any]] = []
    for ci, click in enumerate(clicks):
        entry: dict[str, Any] = {"click": ci, "label": click.label, "frame": click.frame,
                                 "t_s": float(run.time[click.frame] - start),
                                 "uv": [float(click.uv[0]), float(click.uv[1])]}
        j = _clicked_point(rec, truth, click)
        if click.frame not in run.structure_at:
            entry["skipped"] = ("no structure snapshot at the click frame: pass the click "
                                "frames to run_fusion(snapshot_frames=...)")
            targets.append(entry)
            continue
        des = _designate(rec, run, click) if j is not None else None
        if j is None or des is None or click.frame >= n_frames:
            entry["skipped"] = "no scene point under the click" if j is None else \
                "no fused pose at the click frame, or nothing under the click"
            targets.append(entry)
            continue
        X, P, how, support = des
        entry.update(point=j, method=how, support_points=support,
                     true_point_ned=np.asarray(rec.scene_points[j], float).tolist(),
                     _X0=X.copy(), _P0=P, _series={m: [] for m in methods}, _objs={},
                     _ms={m: 0.0 for m in methods})
        targets.append(entry)
    active = [t for t in targets if "skipped" not in t]
    if not active:
        return {"clicks": _public(targets), "methods": {}, "reason": "no click could be scored"}
    first = min(t["frame"] for t in active)
    # The frames a click's template is tracked back through (as the server reads them).
    n_back = int(np.searchsorted(run.time, run.time[first] - TargetParams.track_back_s))
    earlier: deque[tuple[float, np.ndarray]] = deque(
        maxlen=int(math.ceil(TargetParams.track_back_s * FRAME_RATE_HZ)) + 1)
    tic = time.perf_counter()
    for k, t_k, image in rec.frames(n_back):
        if k >= n_frames:
            break
        if k < first:
            earlier.append((float(t_k), cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)))
            continue
        pose = run.camera(k)
        C_t, c_t = truth.C_level_to_camera[k], truth.position[k]
        for tg in active:
            if k < tg["frame"]:
                continue
            Xt = np.asarray(rec.scene_points[tg["point"]], float)
            uv_t, _z = _project(cam, C_t, c_t, Xt)
            uv_t = uv_t[0]
            in_view = bool(np.isfinite(uv_t).all() and half <= uv_t[0] <= W - 1 - half
                           and half <= uv_t[1] <= H - 1 - half)
            d_true = float(np.linalg.norm(Xt - c_t))
            for m in methods:
                if k == tg["frame"]:
                    if pose is None:
                        continue
                    C, c, cov = pose
                    t0 = time.perf_counter()
                    if m == DESIGNATED:
                        tg["_objs"][m] = DesignatedTarget(
                            cam, image, np.asarray(tg["uv"]), tg["_X0"], tg["_P0"], C, c, cov,
                            params=TargetParams(window=window), method="full", seed=seed + k,
                            t=float(run.time[k]), earlier_frames=list(earlier),
                            views=run.views_at.get(k))
                    else:
                        tg["_objs"][m] = TargetTracker(method=m, seed=seed + k)
                        tg["_objs"][m].init(image, np.asarray(tg["uv"]), window)
                    tg["_ms"][m] += time.perf_counter() - t0
                    continue
                obj = tg["_objs"].get(m)
                if obj is None or pose is None:
                    continue
                C, c, cov = pose
                t0 = time.perf_counter()
                if m == DESIGNATED:
                    st = obj.update(float(run.time[k]), image, C, c, cov)
                    if k in run.structure_at:  # the structure refreshed
                        pts, sig, _ids = run.structure_at[k]
                        obj.refresh(pts, sig, _project(cam, C, c, pts)[0], C, c,
                                    run.views_at.get(k))
                    uv_est, tracking, reacq = st.uv, st.status == "tracking", st.reacquired
                    d_err, d_sig = st.distance_m - d_true, st.distance_sigma_m
                    guess = obj.tracker.uv
                else:
                    r = obj.update(image)
                    uv_est, tracking, reacq = r.uv, r.status == "tracking", False
                    d_err = d_sig = math.nan
                    guess = obj.uv
                tg["_ms"][m] += time.perf_counter() - t0
                ok_t = bool(np.isfinite(uv_t).all())
                err = float(np.linalg.norm(uv_est - uv_t)) if uv_est is not None and ok_t \
                    else math.nan
                err_any = float(np.linalg.norm(guess - uv_t)) if guess is not None and ok_t \
                    else math.nan
                d_fixed = float(np.linalg.norm(tg["_X0"] - c))
                tg["_series"][m].append((k, tracking, in_view, err, d_err, d_true,
                                         d_fixed - d_true, reacq, err_any,
                                         (k - tg["frame"]) / FRAME_RATE_HZ, d_sig))
        earlier.append((float(t_k), cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)))
        if progress is not None and k % 100 == 0:
            progress(f"tracking evaluation: frame {k}/{n_frames}")
    wall = time.perf_counter() - tic
    out_methods: dict[str, Any] = {}
    for m in methods:
        rows = [np.array(t["_series"][m], float).reshape(-1, NCOL) for t in active]
        out_methods[m] = _method_scores(rows, sum(t["_ms"][m] for t in active))
    fixed_rows = [np.array(t["_series"][DESIGNATED], float).reshape(-1, NCOL) for t in active
                  if DESIGNATED in t["_series"]]
    fixed = np.concatenate([r[:, [4, 5, 6]] for r in fixed_rows]) if fixed_rows else \
        np.zeros((0, 3))
    for t in active:
        t["per_method"] = {m: _method_scores([np.array(t["_series"][m], float).reshape(-1, NCOL)],
                                             t["_ms"][m], brief=True) for m in methods}
    return {
        "clicks": _public(targets),
        "methods": out_methods,
        "fixed_point_distance_m": _distance_scores(fixed[:, 2], fixed[:, 1]),
        "loss_px": LOSS_PX,
        "distance_tolerance": f"max({DISTANCE_TOL_M:g} m, {100 * DISTANCE_TOL_FRACTION:g} % of "
                              "the range)",
        "window_px": window,
        "wall_s": wall,
    }


def _public(targets: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in t.items() if not k.startswith("_")} for t in targets]


def _distance_scores(err: np.ndarray, rng: np.ndarray) -> dict[str, Any]:
    ok = np.isfinite(err) & np.isfinite(rng)
    err, rng = err[ok], rng[ok]
    out = _stats(err)
    tol = np.maximum(DISTANCE_TOL_M, DISTANCE_TOL_FRACTION * rng)
    out["within_tolerance"] = float(np.mean(np.abs(err) <= tol)) if len(err) else None
    out["bands"] = []
    for lo, hi in ((5.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, math.inf)):
        s = (rng >= lo) & (rng < hi)
        if s.any():
            b = _stats(err[s])
            b["range_m"] = [lo, None if math.isinf(hi) else hi]
            b["within_tolerance"] = float(np.mean(np.abs(err[s]) <= tol[s]))
            b["relative_median"] = float(np.median(np.abs(err[s]) / rng[s]))
            out["bands"].append(b)
    return out


def _method_scores(rows: list[np.ndarray], seconds: float, brief: bool = False
                   ) -> dict[str, Any]:
    """Columns: frame, tracking, in view, px error, distance error, true range, fixed-point
    distance error, re-acquired, px error of the method's position guess whatever its status,
    seconds since the click, distance σ."""
    a = np.concatenate(rows) if rows else np.zeros((0, NCOL))
    tracking, in_view = a[:, 1] > 0, a[:, 2] > 0
    err = a[:, 3]
    scored = tracking & in_view & np.isfinite(err)
    undetected = tracking & (~in_view | (np.nan_to_num(err, nan=np.inf) > LOSS_PX))
    losses = 0
    for r in rows:
        tr = r[:, 1] > 0
        losses += int(np.sum(tr[:-1] & ~tr[1:])) if len(tr) > 1 else 0
    out: dict[str, Any] = {
        "frames": int(len(a)),
        "frames_in_view": int(in_view.sum()),
        "tracked_fraction": float(np.mean(tracking[in_view])) if in_view.any() else None,
        "pixel_error": _stats(err[scored]),
        # the method's position whatever it reports (seed 002 fig. 7 plots it every frame)
        "pixel_error_every_frame": _stats(a[in_view, 8]),
        "undetected_loss_frames": int(undetected.sum()),
        "lost_frames_in_view": int((in_view & ~tracking).sum()),
        "loss_events": losses,
        "reacquisitions": int(np.sum(a[:, 7] > 0)),
        "ms_per_frame": 1e3 * seconds / max(len(a), 1),
    }
    if not np.isfinite(a[:, 4]).any():
        return out
    if not brief:
        out["distance_m"] = _distance_scores(a[tracking, 4], a[tracking, 5])
        settled = tracking & (a[:, 9] >= SETTLED_S)
        out[f"distance_m_after_{SETTLED_S:g}s"] = _distance_scores(a[settled, 4], a[settled, 5])
        out["distance_m_all_frames"] = _distance_scores(a[:, 4], a[:, 5])
        ok = tracking & np.isfinite(a[:, 10]) & (a[:, 10] > 0)
        # calibration of the reported σ: share of frames whose error is within 2σ (≈ 95 %)
        out["distance_within_2_sigma"] = float(np.mean(np.abs(a[ok, 4]) <= 2 * a[ok, 10])) \
            if ok.any() else None
    else:
        d = a[tracking, 4]
        out["distance_error_median_m"] = float(np.median(np.abs(d))) if len(d) else None
        out["range_m"] = [float(np.nanmin(a[:, 5])), float(np.nanmax(a[:, 5]))] if len(a) \
            else None
    return out


# -------------------------------------------------------------------------- landmarks


def _landmark_truth(rec: Any, run: FusionRun, truth: _Truth,
                    progress: Callable[[str], None] | None = None
                    ) -> dict[int, tuple[int, float, np.ndarray]] | None:
    """id → (frame, true depth, true surface point in the reference frame) at the pixel of
    the landmark's last view (rendered true depth; None for a real recording)."""
    scene = _rebuild_scene(rec)
    if scene is None:
        return None
    cam = rec.calibration.camera
    K, dist = np.asarray(cam.K, float), np.asarray(cam.distortion, float)
    start = float(rec.manifest.start_gpst)
    by_frame: dict[int, list[tuple[int, np.ndarray]]] = {}
    for pid, (k, uv) in run.last_views.items():
        by_frame.setdefault(k, []).append((pid, uv))
    out: dict[int, tuple[int, float, np.ndarray]] = {}
    rng = np.random.default_rng(0)
    for n, k in enumerate(sorted(by_frame)):
        C, c = truth.C_level_to_camera[k], truth.position[k]
        _img, depth = scene.render(C, c, run.time[k] - start, cam, rng, return_depth=True)
        ids = np.array([q[0] for q in by_frame[k]])
        uv = np.array([q[1] for q in by_frame[k]], float)
        xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
        for pid, (u, v), (x, y) in zip(ids, uv, xy, strict=True):
            iu, iv = int(round(u)), int(round(v))
            if not (1 <= iu < cam.width - 1 and 1 <= iv < cam.height - 1):
                continue
            win = depth[iv - 1:iv + 2, iu - 1:iu + 2]
            z = float(depth[iv, iu])
            if not np.isfinite(win).all() or float(win.max() - win.min()) > 0.05 * z:
                continue  # a depth edge: the corner's truth is ambiguous
            out[int(pid)] = (k, z, C.T @ (np.array([x, y, 1.0]) * z) + c)
        if progress is not None and n % 50 == 0:
            progress(f"landmark truth: {n}/{len(by_frame)} frames rendered")
    return out


def evaluate_landmarks(rec: Any, run: FusionRun,
                       progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Seed 000 fig. 10 on a recording (landmark error vs number of views) and the port
    structure at the end with and without the refinement (module docstring)."""
    out: dict[str, Any] = {"timing_ms_per_frame": run.timing_ms.get("landmarks")}
    if run.structure is None or run.structure_raw is None or run.origin_time is None:
        out["reason"] = "the fusion never started"
        return out
    if rec.reference is None:
        out["reason"] = "no reference trajectory"
        return out
    truth = _truth(rec, run)
    ok = np.flatnonzero(np.isfinite(run.position_ned).all(axis=1))
    k_end = int(ok[-1])
    cam_end = truth.position[k_end] - truth.origin  # true camera at the end, fusion frame
    pts, _sig, ids = run.structure
    raw, _rsig, raw_ids = run.structure_raw
    # The reported (refined) points are the landmarks that passed their checks: a subset of
    # the raw VO points. "raw_same_points" scores the raw points of that same subset.
    raw_row = {int(i): k for k, i in enumerate(raw_ids)}
    same = np.array([raw_row.get(int(i), -1) for i in ids], np.int64)
    raw_same = raw[same[same >= 0]]
    raw_same_ids = ids[same >= 0]
    out["points"] = int(len(raw_ids))
    out["refined_points"] = int(len(ids))
    out["scene_point_match"] = {"raw": _scene_match(rec, truth, raw, cam_end),
                                "refined": _scene_match(rec, truth, pts, cam_end)}
    lt = _landmark_truth(rec, run, truth, progress)
    if lt is None:
        out["depth_truth"] = None
        out["reason"] = "no rendered truth (not a simulated recording whose scene can be rebuilt)"
        return out
    # The converged landmarks alone (the others are shown as converging, with their σ).
    conv = np.isin(ids, run.converged_ids)
    conv_raw = np.isin(raw_ids, run.converged_ids)
    out["depth_truth"] = {
        "raw": _depth_scores(lt, truth, raw_ids, raw, cam_end),
        "refined": _depth_scores(lt, truth, ids, pts, cam_end),
        "raw_same_points": _depth_scores(lt, truth, raw_same_ids, raw_same, cam_end),
        "raw_converged": _depth_scores(lt, truth, raw_ids[conv_raw], raw[conv_raw], cam_end),
        "refined_converged": _depth_scores(lt, truth, ids[conv], pts[conv], cam_end),
        "truth_points": len(lt),
    }
    curve = []
    for c in VIEW_CHECKPOINTS:
        if c not in run.view_history:
            continue
        h_ids, h_x = run.view_history[c]
        e = _depth_errors(lt, truth, h_ids, h_x)
        if not len(e):
            continue
        curve.append({"views": c, "landmarks": int(len(e)),
                      "depth_median_m": float(np.median(np.abs(e[:, 0]))),
                      "depth_p90_m": float(np.percentile(np.abs(e[:, 0]), 90)),
                      "xyz_median_m": float(np.median(e[:, 1])),
                      "relative_depth_median": float(np.median(np.abs(e[:, 0]) / e[:, 2]))})
    out["error_vs_views"] = curve
    # The same landmarks all along (those that reached ``ref`` views): the curve above mixes
    # sets (landmarks seen often are the near, well-tracked ones).
    same: list[dict[str, Any]] = []
    ref = next((c for c in sorted(run.view_history, reverse=True)
                if len(_depth_errors(lt, truth, *run.view_history[c])) >= 200), None)
    if ref is not None:
        keep = set(int(i) for i in run.view_history[ref][0] if int(i) in lt)
        for c in sorted(run.view_history):
            if c > ref:
                break
            h_ids, h_x = run.view_history[c]
            sel = np.array([int(i) in keep for i in h_ids], bool)
            e = _depth_errors(lt, truth, h_ids[sel], h_x[sel])
            if len(e):
                same.append({"views": c, "landmarks": int(len(e)),
                             "depth_median_m": float(np.median(np.abs(e[:, 0]))),
                             "relative_depth_median": float(np.median(np.abs(e[:, 0]) / e[:, 2])),
                             "xyz_median_m": float(np.median(e[:, 1]))})
    out["error_vs_views_same_landmarks"] = same
    return out


def _depth_errors(lt: dict[int, tuple[int, float, np.ndarray]], truth: _Truth,
                  ids: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Rows (signed depth error, 3-D error, true depth, range from the final camera is not
    here) of the estimates X (fusion frame) of landmarks ``ids`` with a truth."""
    rows = []
    for pid, x in zip(np.asarray(ids).ravel(), np.asarray(X, float).reshape(-1, 3), strict=True):
        t = lt.get(int(pid))
        if t is None:
            continue
        k, z, T = t
        xr = x + truth.origin
        dz = float(truth.C_level_to_camera[k][2] @ (xr - truth.position[k])) - z
        rows.append((dz, float(np.linalg.norm(xr - T)), z))
    return np.array(rows, float).reshape(-1, 3)


def _depth_scores(lt: dict[int, tuple[int, float, np.ndarray]], truth: _Truth,
                  ids: np.ndarray, X: np.ndarray, cam_end: np.ndarray) -> dict[str, Any]:
    sel = np.array([int(i) in lt for i in ids], bool)
    e = _depth_errors(lt, truth, ids[sel], X[sel])
    rng = np.linalg.norm(np.asarray(X, float)[sel] - cam_end, axis=1)

    def block(s: np.ndarray) -> dict[str, Any]:
        if not s.any():
            return {"points": 0, "depth_median_m": None, "depth_p90_m": None,
                    "xyz_median_m": None}
        return {"points": int(s.sum()), "depth_median_m": float(np.median(np.abs(e[s, 0]))),
                "depth_p90_m": float(np.percentile(np.abs(e[s, 0]), 90)),
                "xyz_median_m": float(np.median(e[s, 1]))}

    out = block(np.ones(len(e), bool))
    out["within_30m"] = block(rng < 30.0)
    out["bands_final_range"] = [{"range_m": [lo, None if math.isinf(hi) else hi],
                                 **block((rng >= lo) & (rng < hi))} for lo, hi in BANDS_M]
    out["bands_last_view_depth"] = [{"range_m": [lo, None if math.isinf(hi) else hi],
                                     **block((e[:, 2] >= lo) & (e[:, 2] < hi))}
                                    for lo, hi in BANDS_M]
    return out


def _scene_match(rec: Any, truth: _Truth, pts: np.ndarray, cam_end: np.ndarray
                 ) -> dict[str, Any]:
    """The replay report's structure score: nearest true scene point within the gate."""
    from scipy.spatial import cKDTree

    true = np.asarray(rec.scene_points, float) - truth.origin
    if not len(pts) or not len(true):
        return {"points": 0}
    d, _ = cKDTree(true).query(pts)
    rng = np.linalg.norm(pts - cam_end, axis=1)
    matched = d <= np.maximum(MATCH_GATE_M, MATCH_GATE_FRACTION * rng)

    def stats(s: np.ndarray) -> dict[str, Any]:
        m = s & matched
        return {"points": int(s.sum()), "matched": int(m.sum()),
                "median_m": float(np.median(d[m])) if m.any() else None}

    return {**stats(np.ones(len(pts), bool)), "within_30m": stats(rng < 30.0)}


# ----------------------------------------------------------------------------- text


def format_tracking_report(tracking: dict[str, Any], landmarks: dict[str, Any] | None = None
                           ) -> str:
    """Plain-text summary of ``evaluate_tracking`` (and ``evaluate_landmarks``)."""
    lines = ["Designated-target tracking (seed 002 fig. 7)"]

    def f(x: Any, spec: str = ".2f") -> str:
        return "–" if x is None else format(x, spec)

    if not tracking.get("methods"):
        lines.append(f"  not evaluated: {tracking.get('reason') or 'no click could be scored'}")

    for m, s in tracking.get("methods", {}).items():
        pe = s["pixel_error"]
        dm = s.get("distance_m", {})
        lines.append(
            f"  {m:12s} px median {f(pe['median'])} p90 {f(pe['p90'])} max {f(pe['max'], '.1f')}"
            f" | tracked {f(s['tracked_fraction'], '.0%')} undetected-loss frames "
            f"{s['undetected_loss_frames']} | distance median {f(dm.get('median'), '.3f')} m, "
            f"within tol {f(dm.get('within_tolerance'), '.0%')} | "
            f"{s['ms_per_frame']:.1f} ms/frame")
    fx = tracking.get("fixed_point_distance_m")
    if fx:
        lines.append(f"  {'fixed point':12s} distance median {f(fx['median'], '.3f')} m, "
                     f"within tol {f(fx['within_tolerance'], '.0%')} (no image tracking)")
    d = tracking.get("methods", {}).get(DESIGNATED, {})
    late = d.get(f"distance_m_after_{SETTLED_S:g}s")
    if late:
        lines.append(f"  designated, {SETTLED_S:g} s after the click: distance median "
                     f"{f(late['median'], '.3f')} m p90 {f(late['p90'], '.2f')} m, within tol "
                     f"{f(late['within_tolerance'], '.0%')}; |error| ≤ 2σ in "
                     f"{f(d.get('distance_within_2_sigma'), '.0%')} of the frames")
    if landmarks:
        lines.append("Port-structure refinement (seed 000 fig. 10)")
        dt = landmarks.get("depth_truth")
        if dt:
            for name, label in (("raw", "all raw VO points"),
                                ("raw_same_points", "raw, reported ones"),
                                ("refined", "refined, reported"),
                                ("raw_converged", "raw, converged ones"),
                                ("refined_converged", "refined, converged")):
                if name not in dt:
                    continue
                w = dt[name]["within_30m"]
                b = dt[name]["bands_last_view_depth"][1]  # last seen at 10–30 m
                lines.append(f"  {label:20s} within 30 m: depth error median "
                             f"{f(w['depth_median_m'], '.3f')} m p90 "
                             f"{f(w['depth_p90_m'], '.2f')} m, 3-D error median "
                             f"{f(w['xyz_median_m'], '.3f')} m ({w['points']} points); "
                             f"last seen at 10–30 m: {f(b['xyz_median_m'], '.3f')} m "
                             f"({b['points']})")
        if landmarks.get("error_vs_views_same_landmarks"):
            lines.append("  reported position (the joint window's where it has one) as the "
                         "views accumulate:")
        for row in landmarks.get("error_vs_views_same_landmarks", []):
            lines.append(f"  after {row['views']:4d} views: depth error median "
                         f"{row['depth_median_m']:.3f} m, {100 * row['relative_depth_median']:.1f}"
                         f" % of the range ({row['landmarks']} landmarks, the same throughout)")
        lines.append(f"  {f(landmarks.get('timing_ms_per_frame'), '.2f')} ms per frame")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m backend.reports.tracking [RECORDING] [--end S]``: both evaluations."""
    import argparse
    import json

    from recordings.format import load

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", nargs="?", default="recordings/default")
    ap.add_argument("--end", type=float, default=None, help="replay only the first S seconds")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    rec = load(args.recording)

    def show(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    clicks = default_clicks(rec)
    run = run_fusion(rec, snapshot_frames=[c.frame for c in clicks],
                     snapshot_every=REANCHOR_FRAMES, end_s=args.end,
                     progress=show)
    tr = evaluate_tracking(rec, run, clicks, end_s=args.end, progress=show)
    lm = evaluate_landmarks(rec, run, progress=show)
    if args.json:
        print(json.dumps({"tracking": tr, "landmarks": lm}, indent=1, default=float))
    else:
        print(format_tracking_report(tr, lm))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
