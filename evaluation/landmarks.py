"""The port-structure refinement on a recording with a reference (seed 000's fig. 10).

Where the recording is a simulation whose scene can be rebuilt (``truth.rebuild_scene``), the
truth of a landmark is the rendered true depth at the pixel of its last view (pixels on a depth
discontinuity are skipped): its error is the depth error along that ray (the monocular error,
``depth``) and the distance to the true surface point there (``xyz``). The fusion's world frame
is aligned to the reference by the translation at its origin time, as everywhere. The replay
report's convention (nearest true scene point within ``max(1 m, 5 % of the range)``) is given as
well; the scene points are sparse (about a metre apart), so it mostly measures that sparsity.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from recordings.format import Recording

from .records import (
    DepthBand,
    DepthScores,
    DepthStats,
    DepthTruth,
    LandmarkReport,
    MatchStats,
    SceneMatch,
    SigmaCover,
    ViewsRow,
)
from .runs import VIEW_CHECKPOINTS, FusionRun
from .scoring import BANDS_M, NEAR_M, band_range, point_scores
from .truth import Truth, rebuild_scene, scene_depth, true_cameras

LandmarkTruth = dict[int, tuple[int, float, np.ndarray]]  # id → (frame, depth, true point)
EdgeTruth = dict[int, tuple[int, float, float]]  # id → (frame, nearest, farthest depth)
SAME_SET_MIN = 200  # landmarks the "same landmarks all along" curve needs at its last count


def evaluate_landmarks(rec: Recording, run: FusionRun,
                       progress: Callable[[str], None] | None = None) -> LandmarkReport:
    """Seed 000 fig. 10 (landmark error vs number of views) and the port structure at the end
    with and without the refinement (module docstring)."""
    out = LandmarkReport(timing_ms_per_frame=run.timing_ms.get("landmarks"))
    if run.structure is None or run.structure_raw is None or run.origin_time is None:
        out.reason = "the fusion never started"
        return out
    if rec.reference is None:
        out.reason = "no reference trajectory"
        return out
    truth = true_cameras(rec, run.time, run.origin_time)
    ok = np.flatnonzero(np.isfinite(run.position).all(axis=1))
    cam_end = truth.position[int(ok[-1])] - truth.origin  # true camera at the end, fusion frame
    pts, sig, ids = run.structure
    raw, _rsig, raw_ids = run.structure_raw
    out.points, out.refined_points = int(len(raw_ids)), int(len(ids))
    out.scene_point_match = {"raw": _scene_match(rec, truth, raw, cam_end),
                             "refined": _scene_match(rec, truth, pts, cam_end)}
    truths = _landmark_truth(rec, run, truth, progress)
    if truths is None:
        out.reason = "no rendered truth (not a simulated recording whose scene can be rebuilt)"
        return out
    lt, edges = truths
    # The reported (refined) points are the landmarks that passed their checks: a subset of
    # the raw VO points. "raw_same_points" scores the raw points of that same subset.
    raw_row = {int(i): k for k, i in enumerate(raw_ids)}
    same = np.array([raw_row.get(int(i), -1) for i in ids], np.int64)
    # The converged landmarks alone (the others are shown as converging, with their σ).
    conv = np.isin(ids, run.converged_ids)
    conv_raw = np.isin(raw_ids, run.converged_ids)
    out.depth_truth = DepthTruth(
        raw=_depth_scores(lt, truth, raw_ids, raw, cam_end),
        refined=_depth_scores(lt, truth, ids, pts, cam_end),
        raw_same_points=_depth_scores(lt, truth, ids[same >= 0], raw[same[same >= 0]], cam_end),
        raw_converged=_depth_scores(lt, truth, raw_ids[conv_raw], raw[conv_raw], cam_end),
        refined_converged=_depth_scores(lt, truth, ids[conv], pts[conv], cam_end),
        truth_points=len(lt),
        sigma_cover=_sigma_cover(lt, edges, truth, ids[conv], pts[conv], sig[conv], cam_end))
    out.error_vs_views = _views_curve(lt, truth, run)
    out.error_vs_views_same_landmarks = _same_landmarks_curve(lt, truth, run)
    return out


def _views_curve(lt: LandmarkTruth, truth: Truth, run: FusionRun) -> list[ViewsRow]:
    """The landmarks' error as they reach each view count (the set changes with the count)."""
    curve = []
    for c in VIEW_CHECKPOINTS:
        if c not in run.view_history:
            continue
        e = _depth_errors(lt, truth, *run.view_history[c])
        if len(e):
            curve.append(ViewsRow(
                views=c, landmarks=int(len(e)), depth_median_m=float(np.median(np.abs(e[:, 0]))),
                depth_p90_m=float(np.percentile(np.abs(e[:, 0]), 90)),
                xyz_median_m=float(np.median(e[:, 1])),
                relative_depth_median=float(np.median(np.abs(e[:, 0]) / e[:, 2]))))
    return curve


def _same_landmarks_curve(lt: LandmarkTruth, truth: Truth, run: FusionRun) -> list[ViewsRow]:
    """The same landmarks all along (those that reached the highest count with at least
    ``SAME_SET_MIN`` of them): the plain curve mixes sets (landmarks seen often are the near,
    well-tracked ones)."""
    ref = next((c for c in sorted(run.view_history, reverse=True)
                if len(_depth_errors(lt, truth, *run.view_history[c])) >= SAME_SET_MIN), None)
    if ref is None:
        return []
    keep = set(int(i) for i in run.view_history[ref][0] if int(i) in lt)
    same = []
    for c in sorted(run.view_history):
        if c > ref:
            break
        h_ids, h_x = run.view_history[c]
        sel = np.array([int(i) in keep for i in h_ids], bool)
        e = _depth_errors(lt, truth, h_ids[sel], h_x[sel])
        if len(e):
            same.append(ViewsRow(
                views=c, landmarks=int(len(e)), depth_median_m=float(np.median(np.abs(e[:, 0]))),
                relative_depth_median=float(np.median(np.abs(e[:, 0]) / e[:, 2])),
                xyz_median_m=float(np.median(e[:, 1]))))
    return same


def _landmark_truth(rec: Recording, run: FusionRun, truth: Truth,
                    progress: Callable[[str], None] | None = None
                    ) -> tuple[LandmarkTruth, EdgeTruth] | None:
    """id → (frame, true depth, true surface point in the reference frame) at the pixel of
    the landmark's last view (rendered true depth; None for a real recording), and for the
    pixels on a depth edge id → (frame, nearest, farthest depth around it)."""
    scene = rebuild_scene(rec)
    if scene is None:
        return None
    cam = rec.calibration.camera
    K, dist = np.asarray(cam.K, float), np.asarray(cam.distortion, float)
    start = float(rec.manifest.start_gpst)
    by_frame: dict[int, list[tuple[int, np.ndarray]]] = {}
    for pid, (k, uv) in run.last_views.items():
        by_frame.setdefault(k, []).append((pid, uv))
    out: LandmarkTruth = {}
    edges: EdgeTruth = {}
    for n, k in enumerate(sorted(by_frame)):
        C, c = truth.C_level_to_camera[k], truth.position[k]
        depth = scene_depth(scene, truth, k, run.time[k] - start, cam)
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
                # A depth edge: the corner's truth is ambiguous, either surface around it.
                span = win[np.isfinite(win)]
                if len(span):
                    edges[int(pid)] = (k, float(span.min()), float(span.max()))
                continue
            out[int(pid)] = (k, z, C.T @ (np.array([x, y, 1.0]) * z) + c)
        if progress is not None and n % 50 == 0:
            progress(f"landmark truth: {n}/{len(by_frame)} frames rendered")
    return out, edges


def _sigma_cover(lt: LandmarkTruth, edges: EdgeTruth, truth: Truth, ids: np.ndarray,
                 X: np.ndarray, sigma: np.ndarray, cam_end: np.ndarray) -> SigmaCover:
    """``SigmaCover`` of the points ``X`` (fusion frame) with their stated 1-σ ``sigma``."""
    # id → (frame, the true depths a point there may take)
    surfaces = {pid: (k, (near, far)) for pid, (k, near, far) in edges.items()}
    surfaces.update({pid: (k, (z,)) for pid, (k, z, _T) in lt.items()})
    ratios, on_edge = [], []
    X = np.asarray(X, float).reshape(-1, 3)
    near = np.linalg.norm(X - cam_end, axis=1) < NEAR_M
    for pid, x, s in zip(np.asarray(ids)[near], X[near], np.asarray(sigma, float)[near],
                         strict=True):
        if int(pid) not in surfaces:
            continue
        k, depths = surfaces[int(pid)]
        z = float(truth.C_level_to_camera[k][2] @ (x + truth.origin - truth.position[k]))
        ratios.append(min(abs(z - d) for d in depths) / max(float(s), 1e-9))
        on_edge.append(len(depths) == 2)
    if not ratios:
        return SigmaCover()
    r, e = np.array(ratios), np.array(on_edge, bool)
    return SigmaCover(points=len(r), within_2sigma=float(np.mean(r <= 2.0)),
                      beyond_3sigma=int(np.sum(r > 3.0)), worst_ratio=float(r.max()),
                      edge_points=int(e.sum()),
                      edge_within_2sigma=float(np.mean(r[e] <= 2.0)) if e.any() else None)


def _depth_errors(lt: LandmarkTruth, truth: Truth, ids: np.ndarray, X: np.ndarray
                  ) -> np.ndarray:
    """Rows (signed depth error, 3-D error, true depth) of the estimates X (fusion frame) of
    landmarks ``ids`` with a truth."""
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


def _depth_scores(lt: LandmarkTruth, truth: Truth, ids: np.ndarray, X: np.ndarray,
                  cam_end: np.ndarray) -> DepthScores:
    sel = np.array([int(i) in lt for i in ids], bool)
    e = _depth_errors(lt, truth, ids[sel], X[sel])
    rng = np.linalg.norm(np.asarray(X, float)[sel] - cam_end, axis=1)

    def block(s: np.ndarray) -> DepthStats:
        if not s.any():
            return DepthStats(0, None, None, None)
        return DepthStats(int(s.sum()), float(np.median(np.abs(e[s, 0]))),
                          float(np.percentile(np.abs(e[s, 0]), 90)),
                          float(np.median(e[s, 1])))

    whole = block(np.ones(len(e), bool))
    return DepthScores(
        whole.points, whole.depth_median_m, whole.depth_p90_m, whole.xyz_median_m,
        within_30m=block(rng < NEAR_M),
        bands_final_range=[DepthBand(band_range(lo, hi), **vars(block((rng >= lo) & (rng < hi))))
                           for lo, hi in BANDS_M],
        bands_last_view_depth=[DepthBand(band_range(lo, hi),
                                         **vars(block((e[:, 2] >= lo) & (e[:, 2] < hi))))
                               for lo, hi in BANDS_M])


def _scene_match(rec: Recording, truth: Truth, pts: np.ndarray, cam_end: np.ndarray
                 ) -> SceneMatch:
    """The replay report's structure score: nearest true scene point within the gate."""
    true = np.asarray(rec.scene_points, float) - truth.origin
    if not len(pts) or not len(true):
        return SceneMatch(points=0)
    sc, _d = point_scores(pts, true, cam_end, None)
    near = sc.within_30m
    return SceneMatch(sc.points, sc.matched, sc.median_m,
                      within_30m=MatchStats(near.points, near.matched, near.median_m))
