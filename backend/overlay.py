"""The berthing overlay of one video frame (thesis 5.3, figs. 32–33), as plain JSON-ready data.

Pure functions of a fused state, the calibration, the hull and what the session knows (port
structure, targets, berth line): the browser only draws what it gets. Everything drawn on the
video is already projected to distorted image pixels; the bird's-eye view gets the same
content in plan (north, east).

Numbers are rounded for the wire: pixels of lines and points to 0.1 px, plan coordinates to
1 cm; grid nodes keep full precision (they let a client check the projection exactly).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.camera import CameraPose, Projector, camera_pose
from estimator.frames import wrap_angle
from estimator.landmarks import converged
from estimator.prediction import predict_outlines
from estimator.records import CameraCalibration, Hull

from .geometry import (
    BAND_COLORS,
    DISTANCE_BANDS_M,
    berth_metrics,
    distance_band,
    hull_outline_ne,
    polygon_distances,
)

GRID_CELL_M = 2.0
MAX_OVERLAY_POINTS = 1500  # nearest visible structure points drawn on the video
MAX_PLAN_POINTS = 3000  # nearest structure points in the bird's-eye view
MAX_GRID_NODES = 400


@dataclass(frozen=True)
class OverlayConfig:
    prediction_seconds: int = 5
    grid_cell_m: float = GRID_CELL_M
    grid_radius_m: float | None = None  # None: from the camera height (see grid_radius)
    water_down_m: float = 0.0  # the water plane (down coordinate) in the engine's frame


@dataclass(frozen=True)
class TargetInput:
    id: str
    position_ned: np.ndarray
    label: str | None = None


PLAN_RANGE_FACTOR = 4.0  # plan points out to this many grid radii (small boat: 120 m)
NEAR_BERTH_M = 6.0  # points this near the berth line are "near the berth"
BEHIND_FACE_M = 3.0  # points farther behind the quay face (or berth line) are land
ABOVE_WATER_M = 0.15  # a point less than this above the water plane is no obstacle
QUAY_MAX_HEIGHT_M = 6.0  # points up to this above the water hide the water behind them
OCCLUSION_BIN_DEG = 1.0
FRONT_GAP_BINS = 8  # directions without structure between two with it: bridged up to this
GRID_PIECE_M = 0.5  # grid lines are cut where they pass behind the quay to this resolution


def grid_radius(camera_height_m: float) -> float:
    """Half-size of the water grid: far enough to reach the quay, not so far that 2 m cells
    shrink below a pixel at the horizon (small boat ~1 m → 30 m; large ship ~20 m → 200 m)."""
    return float(np.clip(30.0 * camera_height_m, 20.0, 200.0))


def _round(a: np.ndarray, digits: int) -> list:
    return np.round(np.asarray(a, dtype=float), digits).tolist()


# ----------------------------------------------------------------------------- pose, status


def pose_dict(state: Any, start_gpst: float) -> dict[str, Any]:
    """JSON form of a fused state (angles in degrees for display, times in both scales)."""
    euler = np.asarray(state.euler, dtype=float)
    v = np.asarray(state.velocity_ned, dtype=float)
    # against the world: the filter's and the drift it does not model
    pos_cov = np.asarray(state.position_cov, dtype=float) + np.asarray(
        state.position_drift_cov, dtype=float)
    att_cov = np.asarray(state.attitude_cov, dtype=float)
    vel_cov = np.asarray(state.velocity_cov, dtype=float)
    speed = float(np.hypot(v[0], v[1]))
    # the speed's σ along the track (at a standstill, the wider horizontal axis)
    along = v[:2] / speed if speed > 1e-3 else None
    speed_var = float(along @ vel_cov[:2, :2] @ along) if along is not None \
        else float(np.linalg.eigvalsh(vel_cov[:2, :2])[-1])
    # the course's: the velocity's σ across the track over the speed (at 0.07 m/s a user trial
    # saw the course 5° off with no σ shown)
    course_std = None
    if speed > 0.05 and along is not None:
        across = np.array([-along[1], along[0]])
        course_std = math.degrees(math.sqrt(max(float(across @ vel_cov[:2, :2] @ across), 0.0))
                                  / speed)
    return {
        "t": round(float(state.time) - start_gpst, 6),
        "gpst": float(state.time),
        "position_ned": _round(state.position_ned, 4),
        "llh_deg": [round(float(x), 9) for x in state.llh_deg[:2]] + [round(float(
            state.llh_deg[2]), 4)],
        "velocity_ned": _round(v, 4),
        "euler_deg": _round(np.degrees(euler), 6),
        "heading_deg": round(float(np.degrees(euler[2]) % 360.0), 4),
        "speed_mps": round(speed, 4),
        "speed_std_mps": round(math.sqrt(max(speed_var, 0.0)), 4),
        "heading_std_deg": round(math.degrees(math.sqrt(max(float(att_cov[2, 2]), 0.0))), 4),
        "course_deg": round(float(np.degrees(np.arctan2(v[1], v[0])) % 360.0), 3)
        if speed > 0.05 else None,
        "course_std_deg": None if course_std is None else round(course_std, 4),
        "rate_of_turn_dps": round(float(np.degrees(state.rate_of_turn)), 4),
        "rate_of_turn_std_dps": round(math.degrees(float(getattr(state, "rate_of_turn_sigma",
                                                                 0.0))), 4),
        "position_std_m": _round(np.sqrt(np.clip(np.diag(pos_cov), 0.0, None)), 4),
        "velocity_std_mps": _round(np.sqrt(np.clip(np.diag(vel_cov), 0.0, None)), 4),
        "attitude_std_deg": _round(np.degrees(np.sqrt(np.clip(np.diag(att_cov), 0.0, None))), 4),
    }


def status_dict(status: Any) -> dict[str, Any]:
    integrity = getattr(status, "integrity", None)
    return {
        "phase": str(status.phase),
        "compass_fixed": bool(status.compass_fixed),
        "satellites": int(status.satellites),
        "vo_status": str(status.vo_status),
        "scale": None if status.scale is None else float(status.scale),
        "scale_converged": bool(status.scale_converged),
        "message": str(status.message),
        "integrity": None if integrity is None else integrity_dict(integrity),
    }


def integrity_dict(integrity: Any) -> dict[str, Any]:
    """JSON form of ``estimator.integrity.Integrity``."""

    def level(x: float | None, digits: int) -> float | None:
        return None if x is None or not np.isfinite(x) else round(float(x), digits)

    # 4 digits: the page rounds them to 2, as the reasons' text does (3 then 2 put the chip's
    # ±0.54 m beside the banner's 0.53 m)
    return {"mode": integrity.mode, "trusted": bool(integrity.trusted),
            "reasons": [str(r) for r in integrity.reasons],
            "hpl_m": level(integrity.hpl_m, 4),
            "heading_pl_deg": level(integrity.heading_pl_deg, 4),
            "alert_limit_m": float(integrity.alert_limit_m),
            "heading_alert_limit_deg": float(integrity.heading_alert_limit_deg)}


# ----------------------------------------------------------------------------------- grid


def grid_lines(center_ne: np.ndarray, radius: float, cell: float, down: float = 0.0
               ) -> tuple[np.ndarray, np.ndarray]:
    """Water-plane grid segments (a, b) (N,3) of cell ``cell`` covering a square of
    half-size ``radius`` around ``center_ne``, aligned to multiples of ``cell``, at ``down``."""
    c = np.round(np.asarray(center_ne, dtype=float)[:2] / cell) * cell
    k = int(np.ceil(radius / cell))
    offsets = np.arange(-k, k + 1) * cell
    n_vals, e_vals = c[0] + offsets, c[1] + offsets
    lo_n, hi_n, lo_e, hi_e = n_vals[0], n_vals[-1], e_vals[0], e_vals[-1]
    zeros = np.full(len(offsets), float(down))
    # lines of constant north (running east) then lines of constant east (running north)
    a = np.concatenate([np.column_stack([n_vals, np.full(len(offsets), lo_e), zeros]),
                        np.column_stack([np.full(len(offsets), lo_n), e_vals, zeros])])
    b = np.concatenate([np.column_stack([n_vals, np.full(len(offsets), hi_e), zeros]),
                        np.column_stack([np.full(len(offsets), hi_n), e_vals, zeros])])
    return a, b


def grid_nodes(center_ne: np.ndarray, radius: float, cell: float, down: float = 0.0
               ) -> np.ndarray:
    c = np.round(np.asarray(center_ne, dtype=float)[:2] / cell) * cell
    k = int(np.ceil(radius / cell))
    offsets = np.arange(-k, k + 1) * cell
    nn, ee = np.meshgrid(c[0] + offsets, c[1] + offsets, indexing="ij")
    return np.column_stack([nn.ravel(), ee.ravel(), np.full(nn.size, float(down))])


def _grid(projector: Projector, pose: CameraPose, center_ne: np.ndarray, radius: float,
          cell: float, down: float, keep: Any = None) -> dict[str, Any]:
    """The water grid; ``keep`` (plan points (N,2) → mask) cuts it where the water is hidden
    (behind the quay face) — grid nodes are kept only where it is visible too."""
    a, b = grid_lines(center_ne, radius, cell, down)
    if keep is not None:
        a, b = clip_segments(a, b, keep)
    lines = projector.project_segments(pose, a, b)
    nodes = grid_nodes(center_ne, radius, cell, down)
    visible, uv = projector.project_points(pose, nodes)
    if keep is not None and len(nodes):
        visible &= keep(nodes[:, :2])
    idx = np.flatnonzero(visible)
    if len(idx) > MAX_GRID_NODES:  # keep the nearest: those matter for berthing
        d = np.linalg.norm(nodes[idx] - pose.position_ned, axis=1)
        idx = idx[np.argsort(d)[:MAX_GRID_NODES]]
    return {
        "cell_m": cell,
        "radius_m": radius,
        "plane_down_m": down,
        "lines": [_round(line, 1) for line in lines],
        "nodes": {"ned": nodes[idx].tolist(), "uv": uv[idx].tolist()},
    }


def _front_ranges(rel_ne: np.ndarray, bins: int) -> np.ndarray:
    """Per direction bin, the plan range of the nearest surface: the second-nearest point
    within a bin of it (one stray point does not make a surface), gaps of up to
    FRONT_GAP_BINS between surfaces bridged (the points of a quay face are sparse); inf where
    there is none."""
    front = np.full(bins, np.inf)
    if len(rel_ne) < 2:
        return front
    k0 = (np.degrees(np.arctan2(rel_ne[:, 1], rel_ne[:, 0])) // OCCLUSION_BIN_DEG).astype(int)
    r0 = np.linalg.norm(rel_ne, axis=1)
    k = np.concatenate([(k0 + j) % bins for j in (-1, 0, 1)])
    r = np.tile(r0, 3)
    order = np.lexsort((r, k))
    k, r = k[order], r[order]
    first = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    second = np.minimum(first + 1, len(k) - 1)
    has = (first + 1 < len(k)) & (k[second] == k[first])
    front[k[first[has]]] = r[second[has]]
    # bridge short gaps (on three turns, so that a gap across ±180° is bridged too)
    tiled = np.tile(front, 3)
    known = np.isfinite(tiled)
    if known.sum() >= 2:
        idx = np.arange(len(tiled))
        prev = np.maximum.accumulate(np.where(known, idx, -1))
        nxt = np.minimum.accumulate(np.where(known, idx, len(tiled))[::-1])[::-1]
        gap = (~known) & (prev >= 0) & (nxt < len(tiled)) & (nxt - prev <= FRONT_GAP_BINS + 1)
        tiled[gap] = np.interp(idx[gap], idx[known], tiled[known])
    return tiled[bins:2 * bins]


def clip_segments(a: np.ndarray, b: np.ndarray, keep: Any, piece: float = GRID_PIECE_M
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The parts of segments a→b (N,3) whose points ``keep`` (plan (M,2) → mask) accepts,
    to about ``piece`` metres (every segment cut into as many pieces as the longest needs)."""
    a = np.asarray(a, dtype=float).reshape(-1, 3)
    b = np.asarray(b, dtype=float).reshape(-1, 3)
    if not len(a):
        return a, b
    n = max(1, int(np.ceil(np.linalg.norm(b[:, :2] - a[:, :2], axis=1).max() / piece)))
    s = np.linspace(0.0, 1.0, n + 1)
    mids = a[:, None] + ((s[:-1] + s[1:]) / 2)[None, :, None] * (b - a)[:, None]  # (N,n,3)
    ok = keep(mids[..., :2].reshape(-1, 2)).reshape(len(a), n)
    padded = np.pad(ok, ((0, 0), (1, 1)))
    rows, starts = np.nonzero(~padded[:, :-1] & padded[:, 1:])
    _, ends = np.nonzero(padded[:, :-1] & ~padded[:, 1:])  # same rows, same order
    d = b - a
    return a[rows] + s[starts][:, None] * d[rows], a[rows] + s[ends][:, None] * d[rows]


def water_visibility(camera_ned: np.ndarray, points: np.ndarray, water_down: float,
                     berth_line_ne: np.ndarray | None) -> Any:
    """Plan points (M,2) → mask of those whose water is visible (so: which are not land): on
    the ship's side of the berth line, and in front of the reconstructed quay: per direction
    from the camera
    (``_front_ranges``), the structure standing on the water (points up to QUAY_MAX_HEIGHT_M
    above it) hides the water behind it."""
    cam = np.asarray(camera_ned, dtype=float)[:2]
    height = water_down - np.asarray(points, dtype=float).reshape(-1, 3)[:, 2]
    wall = points[(height > ABOVE_WATER_M) & (height < QUAY_MAX_HEIGHT_M)] if len(points) \
        else np.zeros((0, 3))
    bins = int(round(360.0 / OCCLUSION_BIN_DEG))
    front = _front_ranges(wall[:, :2] - cam, bins)
    normal = side = None
    if berth_line_ne is not None:
        line = np.asarray(berth_line_ne, dtype=float).reshape(2, 2)
        d = line[1] - line[0]
        normal = np.array([-d[1], d[0]]) / max(float(np.linalg.norm(d)), 1e-9)
        side = np.sign(float(np.dot(cam - line[0], normal))) or 1.0

    def keep(ne: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(``margin`` > 0: points up to that far behind the quay face count too.)"""
        rel = np.asarray(ne, dtype=float).reshape(-1, 2) - cam
        k = (np.degrees(np.arctan2(rel[:, 1], rel[:, 0])) // OCCLUSION_BIN_DEG).astype(int) % bins
        ok = np.linalg.norm(rel, axis=1) < front[k] + margin
        if normal is not None:
            ok &= (rel + cam - line[0]) @ normal * side > -margin
        return ok

    return keep


# ------------------------------------------------------------------------------ overlay


def _plan_frustum(projector: Projector, pose: CameraPose, reach: float) -> list:
    """Camera footprint in plan: the camera and the two horizontal field-of-view edges."""
    out = [pose.position_ned[:2]]
    for x in (projector.x_min, projector.x_max):
        d = pose.ray_to_level(np.array([x, 0.0, 1.0]))
        h = np.hypot(d[0], d[1])
        out.append(pose.position_ned[:2] + reach * d[:2] / max(h, 1e-9))
    return _round(np.array(out), 2)


def build_overlay(state: Any, camera: CameraCalibration, hull: Hull, projector: Projector,
                  structure: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                  targets: Sequence[TargetInput] = (),
                  berth_line_ne: np.ndarray | None = None,
                  config: OverlayConfig | None = None,
                  berth_sigma: tuple[float | None, float | None] = (None, None),
                  berth_drift_cov: np.ndarray | None = None) -> dict[str, Any]:
    """Overlay of one frame: ``video`` (image pixels), ``birdseye`` (plan) and ``targets`` /
    ``berth`` read-outs, all for the pose of ``state``. ``berth_sigma``: the berth line's σ
    (m across it, deg of its direction); ``berth_drift_cov``: the position's drift against it
    (``berth.BerthLine.drift_since``)."""
    config = config or OverlayConfig()
    pose = camera_pose(state, camera)
    ship_ne = np.asarray(state.position_ned, dtype=float)[:2]
    water = float(config.water_down_m)
    height = max(water - float(pose.position_ned[2]), 0.5)  # camera above the water
    radius = config.grid_radius_m or grid_radius(height)
    pts, sigma, ids = _structure_arrays(structure)
    keep = water_visibility(pose.position_ned, pts[converged(sigma, np.linalg.norm(
        pts - pose.position_ned, axis=1))], water, berth_line_ne)
    hull_ne = hull_outline_ne(state, hull)
    video: dict[str, Any] = {
        "grid": _grid(projector, pose, ship_ne, radius, config.grid_cell_m, water, keep),
        "hull": [_round(line, 1) for line in projector.project_polygon(
            pose, np.column_stack([hull_ne, np.full(len(hull_ne), water)]))],
    }
    plan: dict[str, Any] = {
        "position": _round(ship_ne, 3),
        "heading_deg": round(float(np.degrees(wrap_angle(state.euler[2]))), 3),
        "ship": _round(hull_ne, 3),
        "frustum": _plan_frustum(projector, pose, radius),
        "radius_m": radius,
    }

    _structure_points(video, plan, projector, pose, (pts, sigma, ids), hull_ne, radius, water,
                      berth_line_ne, keep(pts[:, :2], BEHIND_FACE_M))
    _predictions(video, plan, projector, pose, state, hull, config.prediction_seconds, water)
    target_out = _targets(plan, projector, pose, state, hull, targets)
    berth = _berth(plan, projector, pose, state, hull, berth_line_ne, water, berth_sigma,
                   berth_drift_cov)
    return {"video": video, "birdseye": plan, "targets": target_out, "berth": berth,
            "distance_bands_m": list(DISTANCE_BANDS_M)}


def _structure_arrays(structure: tuple[np.ndarray, np.ndarray, np.ndarray] | None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (N,3), σ (N,), ids (N,)) with the non-finite points left out."""
    if structure is None or not len(structure[0]):
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=int)
    pts = np.asarray(structure[0], dtype=float).reshape(-1, 3)
    sigma = np.asarray(structure[1], dtype=float).reshape(-1)
    ids = np.asarray(structure[2])
    finite = np.isfinite(pts).all(axis=1) & np.isfinite(sigma)
    return pts[finite], sigma[finite], ids[finite]


def _structure_points(video: dict[str, Any], plan: dict[str, Any], projector: Projector,
                      pose: CameraPose, structure: tuple[np.ndarray, np.ndarray, np.ndarray],
                      hull_ne: np.ndarray, radius: float, water: float,
                      berth_line_ne: np.ndarray | None, seaward: np.ndarray) -> None:
    """Port structure: visible points on the video, nearby points in plan, coloured by the
    fixed band of their distance from the hull. ``obstacle`` marks what is drawn by default:
    converged, above the water plane (at or below it: reflections and noise, not something to
    hit), near the ship or the berth line, and not on land well behind the quay face
    (``seaward``: buildings and trees are no obstacles)."""
    pts, sigma, ids = structure
    dist = np.linalg.norm(pts - pose.position_ned, axis=1)
    # Points still converging (σ beyond a few % of the range): their distance is not to be
    # trusted yet.
    trusted = converged(sigma, dist)
    hull_dist = polygon_distances(pts[:, :2], hull_ne) if len(pts) else np.zeros(0)
    near = hull_dist <= radius
    if berth_line_ne is not None and len(pts):
        near |= _segment_distance(pts[:, :2], berth_line_ne) <= NEAR_BERTH_M
    obstacle = trusted & (pts[:, 2] < water - ABOVE_WATER_M) & near & seaward
    band = distance_band(hull_dist)
    colors = np.array(BAND_COLORS)[band] if len(pts) else np.zeros(0, dtype=str)
    visible, uv = projector.project_points(pose, pts)
    vis = np.flatnonzero(visible)
    vis = vis[np.argsort(dist[vis])[:MAX_OVERLAY_POINTS]]
    video["points"] = {
        "uv": _round(uv[vis], 1),
        "distance_m": _round(dist[vis], 2),
        "hull_distance_m": _round(hull_dist[vis], 2),
        "band": band[vis].tolist(),
        "color": colors[vis].tolist(),
        "converged": trusted[vis].tolist(),
        "obstacle": obstacle[vis].tolist(),
        "id": ids[vis].tolist(),
    }
    # The plan reaches further than the water grid: the quay must show during the approach.
    horizontal = np.linalg.norm(pts[:, :2] - pose.position_ned[:2], axis=1)
    near_plan = np.flatnonzero(horizontal <= PLAN_RANGE_FACTOR * radius)
    near_plan = near_plan[np.argsort(horizontal[near_plan])[:MAX_PLAN_POINTS]]
    plan["points"] = {"ne": _round(pts[near_plan, :2], 2), "color": colors[near_plan].tolist(),
                      "band": band[near_plan].tolist(),
                      "converged": trusted[near_plan].tolist(),
                      "obstacle": obstacle[near_plan].tolist()}


def _segment_distance(points: np.ndarray, segment: np.ndarray) -> np.ndarray:
    a, b = np.asarray(segment, dtype=float).reshape(2, 2)
    ab = b - a
    s = np.clip((points - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(points - (a + s[:, None] * ab), axis=1)


def _predictions(video: dict[str, Any], plan: dict[str, Any], projector: Projector,
                 pose: CameraPose, state: Any, hull: Hull, seconds: int, water: float) -> None:
    """Predicted hull outlines at the water line, 1..N s ahead."""
    video["prediction"] = []
    plan["prediction"] = []
    for k, ne in enumerate(predict_outlines(state, hull, seconds), start=1):
        polygon = np.column_stack([ne, np.full(len(ne), water)])
        video["prediction"].append({"seconds": k, "polylines": [
            _round(line, 1) for line in projector.project_polygon(pose, polygon)]})
        plan["prediction"].append({"seconds": k, "ne": _round(ne, 3)})


def _targets(plan: dict[str, Any], projector: Projector, pose: CameraPose, state: Any,
             hull: Hull, targets: Sequence[TargetInput]) -> list[dict[str, Any]]:
    """The designated targets' readouts (and their places in plan)."""
    target_out = []
    plan["targets"] = []
    if targets:
        positions = np.array([t.position_ned for t in targets], dtype=float)
        t_visible, t_uv = projector.project_points(pose, positions)
        ship = hull_outline_ne(state, hull)
        for i, target in enumerate(targets):
            entry = target_readout(target.position_ned, pose, ship)
            entry.update(id=target.id, label=target.label, visible=bool(t_visible[i]),
                         uv=_round(t_uv[i], 1) if t_visible[i] else None)
            target_out.append(entry)
            plan["targets"].append({"id": target.id, "ne": _round(target.position_ned[:2], 3)})
    return target_out


def _berth(plan: dict[str, Any], projector: Projector, pose: CameraPose, state: Any,
           hull: Hull, berth_line_ne: np.ndarray | None, water: float,
           sigma: tuple[float | None, float | None], drift_cov: np.ndarray | None
           ) -> dict[str, Any] | None:
    """Berth line drawn at the foot of the quay (on the water plane) and the berth
    geometry."""
    plan["berth_line"] = None
    if berth_line_ne is None:
        return None
    line = np.asarray(berth_line_ne, dtype=float).reshape(2, 2)
    line3 = np.column_stack([line, np.full(2, water)])
    berth: dict[str, Any] = {key: (None if val is None else round(val, 3))
                             for key, val in berth_metrics(state, hull, line, *sigma,
                                                           drift_cov).items()}
    berth["polylines"] = [_round(p, 1) for p in projector.project_segments(
        pose, line3[:1], line3[1:])]
    plan["berth_line"] = _round(line, 3)
    return berth


def target_readout(position_ned: np.ndarray, pose: CameraPose, ship_outline_ne: np.ndarray
                   ) -> dict[str, float]:
    """Distances to a designated point: from the camera (3-D) and from the hull (plan)."""
    p = np.asarray(position_ned, dtype=float)
    return {
        "distance_m": round(float(np.linalg.norm(p - pose.position_ned)), 3),
        "hull_distance_m": round(polygon_distance(p[:2], ship_outline_ne), 3),
    }


def polygon_distance(point: np.ndarray, polygon: np.ndarray) -> float:
    """Distance (m) from a plan point to a closed polygon, 0 inside it."""
    p = np.asarray(polygon, dtype=float)
    a, b = p, np.roll(p, -1, axis=0)
    ab = b - a
    s = np.clip(np.einsum("ij,ij->i", point - a, ab) / np.maximum(
        np.einsum("ij,ij->i", ab, ab), 1e-12), 0.0, 1.0)
    d = float(np.min(np.linalg.norm(a + s[:, None] * ab - point, axis=1)))
    # even-odd rule for inside
    x, y = point
    inside = False
    for (x1, y1), (x2, y2) in zip(a, b, strict=True):
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return 0.0 if inside else d
