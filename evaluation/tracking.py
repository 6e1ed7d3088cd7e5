"""Designated-target tracking on a recording with a reference (seed 002's fig. 7), through the
server's own path (``engine.targets``).

A click is the TRUE projection (reference pose + calibration) of a true scene point at the
click frame (``truth.default_clicks``: quay points 5–30 m from the camera, several clicks
spread over the replay). Each is designated from the port structure of ITS frame
(``engine.targets.designate``, causal) and followed to the end as the server follows it
(``FollowedTarget``: tracked back through the frames before the click, refreshed on the
structure at most once a second), beside the two ablations of seed 002's fig. 7,
``template`` (adaptive template matching alone) and ``camshift_pf`` (the CAMSHIFT-guided
particle filter alone), and the image tracker ``full`` without its 3-D point.

Scores: pixel error = tracked point − true projection of the clicked scene point, over the
frames where the method reports "tracking" and the point is in the image. An UNDETECTED loss
is a frame reported "tracking" more than ``LOSS_PX`` from the truth (or with the point out of
the image). Distance error = the target's distance (fused camera → its 3-D point) − the true
distance (true camera → the true scene point); tolerance ``max(10 cm, 1 % of the range)``.
``fixed_point`` is the distance of the point designated at the click without any image
tracking afterwards.

A tracked frame whose distance is beyond 2σ is put down to the first cause that applies
(``BEYOND_2_SIGMA_CAUSES``): ``track_lost`` — the image track is an undetected loss there;
``designation`` — the click's point was already beyond 2σ of its own σ at the click, before
any view (the structure points under it, or the water plane); ``click_views`` — the target's
first tracked frame was beyond 2σ (the point its template tracked back gave at the click);
``later_views`` — the rest, the views since.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from engine.camera import Projector
from engine.targets import (
    DesignationError,
    FollowedTarget,
    camera_view,
    designate,
    target_window,
)
from estimator.landmarks import triangulate_point
from estimator.tracking import (
    METHODS,
    DesignatedTarget,
    TargetParams,
    TargetTracker,
    range_with_sigma,
    with_edge_span,
)
from recordings.format import Recording

from .records import ClickResult, DistanceBand, DistanceScores, MethodScores, TrackingReport
from .runs import FusionRun
from .scoring import error_stats
from .truth import CLICK_RANGE_M, Click, Truth, clicked_point, project, true_cameras

LOSS_PX = 10.0  # a "tracking" point farther than this from the truth is an undetected loss
DISTANCE_TOL_M = 0.10
DISTANCE_TOL_FRACTION = 0.01
DISTANCE_TOLERANCE = f"max({DISTANCE_TOL_M:g} m, {100 * DISTANCE_TOL_FRACTION:g} % of the range)"
DISTANCE_BANDS_M = ((5.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, math.inf))
DESIGNATED = "designated"  # the server's path: FollowedTarget (tracker + 3-D point)
EVAL_METHODS = (DESIGNATED, *METHODS)
FRAME_RATE_HZ = 10.0  # for "seconds since the click" (the recordings' frame rate)
SETTLED_S = 5.0  # distance figures also given from this long after the click
BEYOND_2_SIGMA_CAUSES = ("track_lost", "designation", "click_views", "later_views")


@dataclass
class _Row:
    """One frame of one method on one click."""

    frame: int
    tracking: bool
    in_view: bool
    px_error: float  # reported point − truth (NaN when not reported)
    distance_error: float  # NaN for the image-only methods
    true_range: float
    fixed_error: float  # the click's point, never tracked
    reacquired: bool
    guess_px_error: float  # the method's position whatever its status
    since_click_s: float
    distance_sigma: float


@dataclass
class _Followed:
    """A scored click while the frames go by."""

    result: ClickResult
    point: int
    designation: object
    rows: dict[str, list[_Row]] = field(default_factory=dict)
    trackers: dict[str, object] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)


def evaluate_tracking(rec: Recording, run: FusionRun, clicks: list[Click],
                      progress: Callable[[str], None] | None = None,
                      methods: Sequence[str] = EVAL_METHODS) -> TrackingReport:
    """Seed 002 fig. 7 on a recording (module docstring). ``run`` has the structure after
    every frame from the first click on (``runs.Collect(structures_from=...)``); ``methods``
    (of ``EVAL_METHODS``) trims the ablations."""
    methods = tuple(m for m in EVAL_METHODS if m in methods)
    if rec.reference is None or rec.scene_points is None:
        return TrackingReport(reason="no reference trajectory or no scene points to score "
                                     "against")
    if not clicks:
        return TrackingReport(reason=f"no quay point {CLICK_RANGE_M[0]:g}–{CLICK_RANGE_M[1]:g}"
                                     " m from the camera in view at the click times")
    truth = true_cameras(rec, run.time, run.origin_time)
    projector = Projector(rec.calibration.camera)
    followed = [_designated(rec, run, truth, projector, i, c, methods)
                for i, c in enumerate(clicks)]
    active = [f for f in followed if f.result.skipped is None]
    if not active:
        return TrackingReport(clicks=[f.result for f in followed],
                              reason="no click could be scored")
    wall = _follow(rec, run, truth, projector, active, progress)
    designation_off = [_designation_beyond_2_sigma(f.result) for f in active]
    scores = {m: _method_scores([f.rows[m] for f in active], sum(f.seconds[m] for f in active),
                                designation_off=designation_off)
              for m in methods}
    for f, off in zip(active, designation_off, strict=True):
        f.result.per_method = {m: _method_scores([f.rows[m]], f.seconds[m], brief=True,
                                                 designation_off=[off])
                               for m in methods}
        target = f.trackers.get(DESIGNATED)
        if target is not None:
            f.result.error_sources = error_sources(
                rec, target.tracker, np.asarray(rec.scene_points[f.point], float))  # type: ignore[attr-defined]
    fixed = [r for f in active for r in f.rows[methods[0]]] if methods else []
    return TrackingReport(
        clicks=[f.result for f in followed], methods=scores,
        fixed_point_distance_m=_distance_scores(np.array([r.fixed_error for r in fixed]),
                                                np.array([r.true_range for r in fixed])),
        loss_px=LOSS_PX, distance_tolerance=DISTANCE_TOLERANCE,
        window_px=target_window(projector.width), wall_s=wall)


def _designated(rec: Recording, run: FusionRun, truth: Truth, projector: Projector, i: int,
                click: Click, methods: Sequence[str]) -> _Followed:
    """The click designated as the server designates it, at its frame."""
    start = float(rec.manifest.start_gpst)
    k = click.frame
    result = ClickResult(click=i, label=click.label, frame=k,
                         t_s=float(run.time[k] - start) if k < len(run.time) else math.nan,
                         uv=[float(click.uv[0]), float(click.uv[1])])
    j = clicked_point(rec, truth, click)
    state = run.states[k] if k < len(run.states) else None
    if j is None:
        result.skipped = "no scene point under the click"
    elif state is None or k not in run.structures:
        result.skipped = "no fused pose or no port structure at the click frame"
    if result.skipped is not None:
        return _Followed(result, -1, None)
    view = camera_view(state, rec.calibration.camera)
    try:
        des = designate(projector, view, click.uv[0], click.uv[1], run.structures[k],
                        rec.hull.body_origin_height_m)
    except DesignationError as exc:
        result.skipped = str(exc)
        return _Followed(result, -1, None)
    result.point, result.method, result.support_points = j, des.method, len(des.anchor_ids)
    Xt = np.asarray(rec.scene_points[j], float)
    d, sigma = range_with_sigma(des.position_ned, with_edge_span(
        des.position_ned, des.covariance, view.position_ned, des.edge_span_m),
        view.position_ned)
    result.designation_error_m = d - float(np.linalg.norm(Xt - truth.position[k]))
    result.designation_sigma_m = sigma
    result.true_point_ned = Xt.tolist()
    return _Followed(result, j, des, rows={m: [] for m in methods},
                     seconds={m: 0.0 for m in methods})


def _follow(rec: Recording, run: FusionRun, truth: Truth, projector: Projector,
            active: list[_Followed], progress: Callable[[str], None] | None) -> float:
    """Every frame from the first click on: each method one step on each click."""
    first = min(f.result.frame for f in active)
    # The frames a click's template is tracked back through (as the server reads them).
    n_back = int(np.searchsorted(run.time, run.time[first] - TargetParams.track_back_s))
    earlier: deque[tuple[float, np.ndarray]] = deque(
        maxlen=int(math.ceil(TargetParams.track_back_s * FRAME_RATE_HZ)) + 1)
    cam = rec.calibration.camera
    tic = time.perf_counter()
    for k, t_k, image in rec.frames(n_back):
        if k >= len(run.time):
            break
        state = run.states[k]
        if k >= first and state is not None:
            view = camera_view(state, cam)
            for f in active:
                if k == f.result.frame:
                    _start(f, projector, image, view, k, list(earlier), run)
                elif k > f.result.frame:
                    _step(f, rec, run, truth, image, view, k)
        earlier.append((float(t_k), cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)))
        if progress is not None and k % 100 == 0:
            progress(f"tracking evaluation: frame {k}/{len(run.time)}")
    return time.perf_counter() - tic


def _start(f: _Followed, projector: Projector, image: np.ndarray, view: object, k: int,
           earlier: list[tuple[float, np.ndarray]], run: FusionRun) -> None:
    uv = tuple(f.result.uv)
    for m in f.rows:
        t0 = time.perf_counter()
        if m == DESIGNATED:
            f.trackers[m] = FollowedTarget(projector, f.designation, image, uv,  # type: ignore
                                           view, k, earlier, run.structures[k].views)
        else:
            f.trackers[m] = TargetTracker(method=m, seed=k)
            f.trackers[m].init(image, np.asarray(uv),  # type: ignore[attr-defined]
                               target_window(projector.width))
        f.seconds[m] += time.perf_counter() - t0


def _step(f: _Followed, rec: Recording, run: FusionRun, truth: Truth, image: np.ndarray,
          view: object, k: int) -> None:
    """One frame of every method on one click, scored against the truth."""
    cam = rec.calibration.camera
    W, H = int(cam.width), int(cam.height)
    half = 0.5 * target_window(W)
    Xt = np.asarray(rec.scene_points[f.point], float)
    uv_t = project(cam, truth.C_level_to_camera[k], truth.position[k], Xt)[0][0]
    ok_t = bool(np.isfinite(uv_t).all())
    in_view = ok_t and half <= uv_t[0] <= W - 1 - half and half <= uv_t[1] <= H - 1 - half
    d_true = float(np.linalg.norm(Xt - truth.position[k]))
    d_fixed = float(np.linalg.norm(f.designation.position_ned  # type: ignore[attr-defined]
                                   - view.position_ned))  # type: ignore[attr-defined]
    for m in f.rows:
        obj = f.trackers.get(m)
        if obj is None:
            continue
        t0 = time.perf_counter()
        if m == DESIGNATED:
            st = obj.follow(k, image, view, run.structures[k])  # type: ignore[attr-defined]
            uv_est, tracking, reacq = st.uv, st.status == "tracking", st.reacquired
            d_err, d_sig = st.distance_m - d_true, st.distance_sigma_m
            guess = obj.tracker.tracker.uv  # type: ignore[attr-defined]
        else:
            r = obj.update(image)  # type: ignore[attr-defined]
            uv_est, tracking, reacq = r.uv, r.status == "tracking", False
            d_err = d_sig = math.nan
            guess = obj.uv  # type: ignore[attr-defined]
        f.seconds[m] += time.perf_counter() - t0
        err = float(np.linalg.norm(uv_est - uv_t)) if uv_est is not None and ok_t else math.nan
        err_any = float(np.linalg.norm(guess - uv_t)) if guess is not None and ok_t \
            else math.nan
        f.rows[m].append(_Row(k, tracking, in_view, err, d_err, d_true, d_fixed - d_true, reacq,
                              err_any, (k - f.result.frame) / FRAME_RATE_HZ, d_sig))


def error_sources(rec: Recording, target: DesignatedTarget, true_point: np.ndarray
                  ) -> dict[str, float] | None:
    """The target's distance error at its last solved view, its views (``DesignatedTarget.
    seen``: tracked pixels, solved attitudes, fused centres) triangulated as they are and with
    the truth put in for the pixels (the true point's projections), the poses (true attitudes
    and camera centres), or both: which of them limits the distance on this recording. A weak
    prior, the same for all, so that only the views speak (``as_is`` is then not the target's
    own distance, which starts from the click's point); ``true_range`` the true distance.
    None before the first refine."""
    seen = target.seen
    rows = target.solved_rows()
    if len(rows) < target.params.min_refine_views or not target.refined:
        return None
    true = true_cameras(rec, seen.t[rows], None)  # reference frame
    xc = np.einsum("nij,nj->ni", true.C_level_to_camera, true_point - true.position)
    true_xy = xc[:, :2] / xc[:, 2:3]
    var = target.ray_variance()[rows]
    last = int(np.argmax(seen.t[rows]))
    d_true = float(np.linalg.norm(true_point - true.position[last]))
    X0, P0 = target.click_point
    out = {"true_range": d_true}
    weak = np.linalg.inv(P0) * 1e-6
    for name, C, centre, xy in (
            ("as_is", seen.C[rows], seen.centre[rows], seen.xy[rows]),
            ("true_pixels", seen.C[rows], seen.centre[rows], true_xy),
            ("true_poses", true.C_level_to_camera, true.position, seen.xy[rows]),
            ("true_both", true.C_level_to_camera, true.position, true_xy)):
        X = X0 + centre[0] - seen.centre[rows[0]]  # the click's point in these centres' frame
        # twice, the second from the first's estimate: with little parallax even the weak
        # prior pulls a point tens of metres off by centimetres along its ray (a click 150 m
        # away, triangulated with the true views: 8 cm after one pass, 2 mm after two)
        for _ in range(2):
            X = triangulate_point(C, centre, xy, var, X, weak)[0]
        out[name] = float(np.linalg.norm(X - centre[last])) - d_true
    return out


def error_source_shares(clicks: Sequence[ClickResult]) -> dict[str, float] | None:
    """The share of the refined clicks within tolerance at their last view for each way of
    triangulating them (``error_sources``: ``as_is``, ``true_pixels``, ``true_poses``,
    ``true_both``) and their number (``clicks``); None when no click was refined."""
    sources = [c.error_sources for c in clicks if c.error_sources is not None]
    if not sources:
        return None
    tol = np.array([max(DISTANCE_TOL_M, DISTANCE_TOL_FRACTION * s["true_range"])
                    for s in sources])
    out = {k: float(np.mean(np.abs([s[k] for s in sources]) <= tol))
           for k in ("as_is", "true_pixels", "true_poses", "true_both")}
    return {**out, "clicks": float(len(sources))}


# ------------------------------------------------------------------------------ scores


def _distance_scores(err: np.ndarray, rng: np.ndarray) -> DistanceScores:
    ok = np.isfinite(err) & np.isfinite(rng)
    err, rng = err[ok], rng[ok]
    out = DistanceScores(**vars(error_stats(err)))
    tol = np.maximum(DISTANCE_TOL_M, DISTANCE_TOL_FRACTION * rng)
    out.within_tolerance = float(np.mean(np.abs(err) <= tol)) if len(err) else None
    for lo, hi in DISTANCE_BANDS_M:
        s = (rng >= lo) & (rng < hi)
        if s.any():
            out.bands.append(DistanceBand(
                **vars(error_stats(err[s])), range_m=[lo, None if math.isinf(hi) else hi],
                within_tolerance=float(np.mean(np.abs(err[s]) <= tol[s])),
                relative_median=float(np.median(np.abs(err[s]) / rng[s]))))
    return out


def _designation_beyond_2_sigma(click: ClickResult) -> bool:
    e, s = click.designation_error_m, click.designation_sigma_m
    return e is not None and s is not None and abs(e) > 2.0 * s


def _undetected(tracking: np.ndarray, in_view: np.ndarray, px_error: np.ndarray
                ) -> np.ndarray:
    """Mask of the undetected losses: said "tracking" with the point out of the image or
    more than ``LOSS_PX`` from the truth (NaN: no truth to follow)."""
    return tracking & (~in_view | (np.nan_to_num(px_error, nan=np.inf) > LOSS_PX))


def _beyond_2_sigma(rows: list[list[_Row]], designation_off: Sequence[bool]) -> dict[str, int]:
    """Tracked frames beyond 2σ by cause (module docstring), over the clicks' ``rows``;
    ``designation_off``: whether each click's designation was beyond its own 2σ."""
    out = dict.fromkeys(BEYOND_2_SIGMA_CAUSES, 0)
    for rs, designation in zip(rows, designation_off, strict=True):
        err, sig = (np.array([getattr(r, a) for r in rs], float)
                    for a in ("distance_error", "distance_sigma"))
        tracking = np.array([r.tracking for r in rs], bool)
        scored = np.flatnonzero(tracking & np.isfinite(err) & np.isfinite(sig) & (sig > 0))
        if not len(scored):
            continue
        beyond = scored[np.abs(err[scored]) > 2.0 * sig[scored]]
        lost = _undetected(tracking, np.array([r.in_view for r in rs], bool),
                           np.array([r.px_error for r in rs], float))[beyond]
        out["track_lost"] += int(lost.sum())
        # the rest: the click's designation, else its first views, else the later ones
        rest = "designation" if designation else \
            "click_views" if beyond[:1].tolist() == scored[:1].tolist() else "later_views"
        out[rest] += int((~lost).sum())
    return out


def _method_scores(rows: list[list[_Row]], seconds: float, brief: bool = False,
                   designation_off: Sequence[bool] | None = None) -> MethodScores:
    flat = [r for rs in rows for r in rs]
    tracking = np.array([r.tracking for r in flat], bool)
    in_view = np.array([r.in_view for r in flat], bool)
    err = np.array([r.px_error for r in flat], float)
    scored = tracking & in_view & np.isfinite(err)
    undetected = _undetected(tracking, in_view, err)
    losses = sum(int(np.sum(tr[:-1] & ~tr[1:])) for tr in
                 (np.array([r.tracking for r in rs], bool) for rs in rows) if len(tr) > 1)
    out = MethodScores(
        frames=len(flat), frames_in_view=int(in_view.sum()),
        tracked_fraction=float(np.mean(tracking[in_view])) if in_view.any() else None,
        pixel_error=error_stats(err[scored]),
        pixel_error_every_frame=error_stats(np.array([r.guess_px_error for r in flat])[in_view]),
        undetected_loss_frames=int(undetected.sum()),
        lost_frames_in_view=int((in_view & ~tracking).sum()), loss_events=losses,
        reacquisitions=sum(r.reacquired for r in flat),
        ms_per_frame=1e3 * seconds / max(len(flat), 1))
    d = np.array([r.distance_error for r in flat], float)
    rng = np.array([r.true_range for r in flat], float)
    if not np.isfinite(d).any():
        return out
    if designation_off is not None:
        out.beyond_2_sigma = _beyond_2_sigma(rows, designation_off)
    if brief:
        out.distance_error_median_m = float(np.median(np.abs(d[tracking]))) \
            if tracking.any() else None
        out.range_m = [float(np.nanmin(rng)), float(np.nanmax(rng))]
        return out
    out.distance_m = _distance_scores(d[tracking], rng[tracking])
    settled = tracking & (np.array([r.since_click_s for r in flat]) >= SETTLED_S)
    out.distance_m_after_5s = _distance_scores(d[settled], rng[settled])
    out.distance_m_all_frames = _distance_scores(d, rng)
    sig = np.array([r.distance_sigma for r in flat], float)
    ok = tracking & np.isfinite(sig) & (sig > 0)
    # calibration of the reported σ: share of frames whose error is within 2σ (≈ 95 %)
    out.distance_within_2_sigma = float(np.mean(np.abs(d[ok]) <= 2 * sig[ok])) \
        if ok.any() else None
    return out
