"""The berthing overlay of one video frame (thesis 5.3, figs. 32–33), as plain JSON-ready data.

Pure functions of a fused state, the calibration, the hull and what the session knows (port
structure, targets, berth line): the browser only draws what it gets. Everything drawn on the
video is already projected to distorted image pixels; the bird's-eye view gets the same
content in plan (north, east).

Numbers are rounded for the wire: pixels of lines and points to 0.1 px, plan coordinates to
1 cm; grid nodes keep full precision (they let a client check the projection exactly).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.camera import CameraPose, Projector, camera_pose
from estimator.frames import wrap_angle
from estimator.landmarks import converged
from estimator.prediction import predict_outlines
from estimator.records import CameraCalibration, Hull

from .geometry import berth_metrics, hue_color, hull_outline_ne

GRID_CELL_M = 2.0
MAX_OVERLAY_POINTS = 1500  # nearest visible structure points drawn on the video
MAX_PLAN_POINTS = 3000  # nearest structure points in the bird's-eye view
MAX_GRID_NODES = 400


@dataclass(frozen=True)
class OverlayConfig:
    prediction_seconds: int = 5
    grid_cell_m: float = GRID_CELL_M
    grid_radius_m: float | None = None  # None: from the camera height (see grid_radius)
    color_range_m: float | None = None  # distance shown blue; None: twice the grid radius
    water_down_m: float = 0.0  # the water plane (down coordinate) in the engine's frame


@dataclass(frozen=True)
class TargetInput:
    id: str
    position_ned: np.ndarray
    label: str | None = None


PLAN_RANGE_FACTOR = 4.0  # plan points out to this many grid radii (small boat: 120 m)


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
    pos_cov = np.asarray(state.position_cov, dtype=float)
    att_cov = np.asarray(state.attitude_cov, dtype=float)
    speed = float(np.hypot(v[0], v[1]))
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
        "course_deg": round(float(np.degrees(np.arctan2(v[1], v[0])) % 360.0), 3)
        if speed > 0.05 else None,
        "rate_of_turn_dps": round(float(np.degrees(state.rate_of_turn)), 4),
        "position_std_m": _round(np.sqrt(np.clip(np.diag(pos_cov), 0.0, None)), 4),
        "attitude_std_deg": _round(np.degrees(np.sqrt(np.clip(np.diag(att_cov), 0.0, None))), 4),
    }


def status_dict(status: Any) -> dict[str, Any]:
    return {
        "phase": str(status.phase),
        "compass_fixed": bool(status.compass_fixed),
        "satellites": int(status.satellites),
        "vo_status": str(status.vo_status),
        "scale": None if status.scale is None else float(status.scale),
        "scale_converged": bool(status.scale_converged),
        "message": str(status.message),
    }


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
          cell: float, down: float) -> dict[str, Any]:
    a, b = grid_lines(center_ne, radius, cell, down)
    lines = projector.project_segments(pose, a, b)
    nodes = grid_nodes(center_ne, radius, cell, down)
    visible, uv = projector.project_points(pose, nodes)
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
                  config: OverlayConfig | None = None) -> dict[str, Any]:
    """Overlay of one frame: ``video`` (image pixels), ``birdseye`` (plan) and ``targets`` /
    ``berth`` read-outs, all for the pose of ``state``."""
    config = config or OverlayConfig()
    pose = camera_pose(state, camera)
    ship_ne = np.asarray(state.position_ned, dtype=float)[:2]
    water = float(config.water_down_m)
    height = max(water - float(pose.position_ned[2]), 0.5)  # camera above the water
    radius = config.grid_radius_m or grid_radius(height)
    color_range = config.color_range_m or 2.0 * radius

    video: dict[str, Any] = {"grid": _grid(projector, pose, ship_ne, radius, config.grid_cell_m,
                                           water)}
    plan: dict[str, Any] = {
        "position": _round(ship_ne, 3),
        "heading_deg": round(float(np.degrees(wrap_angle(state.euler[2]))), 3),
        "ship": _round(hull_outline_ne(state, hull), 3),
        "frustum": _plan_frustum(projector, pose, radius),
        "radius_m": radius,
    }

    _structure_points(video, plan, projector, pose, structure, ship_ne, radius, color_range)
    _predictions(video, plan, projector, pose, state, hull, config.prediction_seconds, water)
    target_out = _targets(plan, projector, pose, state, hull, targets)
    berth = _berth(plan, projector, pose, state, hull, berth_line_ne, water)
    return {"video": video, "birdseye": plan, "targets": target_out, "berth": berth,
            "color_range_m": color_range}


def _structure_points(video: dict[str, Any], plan: dict[str, Any], projector: Projector,
                      pose: CameraPose,
                      structure: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
                      ship_ne: np.ndarray, radius: float, color_range: float) -> None:
    """Port structure: visible points on the video, nearby points in plan, same colours."""
    pts = np.zeros((0, 3))
    sigma = np.zeros(0)
    ids = np.zeros(0, dtype=int)
    if structure is not None and len(structure[0]):
        pts = np.asarray(structure[0], dtype=float).reshape(-1, 3)
        sigma = np.asarray(structure[1], dtype=float).reshape(-1)
        ids = np.asarray(structure[2])
        finite = np.isfinite(pts).all(axis=1)
        pts, sigma, ids = pts[finite], sigma[finite], ids[finite]
    dist = np.linalg.norm(pts - pose.position_ned, axis=1)
    # Points still converging (σ beyond a few % of the range) are drawn hollow: their
    # distance is not to be trusted yet.
    trusted = converged(sigma, dist)
    visible, uv = projector.project_points(pose, pts)
    vis = np.flatnonzero(visible)
    vis = vis[np.argsort(dist[vis])[:MAX_OVERLAY_POINTS]]
    video["points"] = {
        "uv": _round(uv[vis], 1),
        "distance_m": _round(dist[vis], 2),
        "color": hue_color(dist[vis], color_range),
        "converged": trusted[vis].tolist(),
        "id": ids[vis].tolist(),
    }
    # The plan reaches further than the water grid: the quay must show during the approach.
    horizontal = np.linalg.norm(pts[:, :2] - ship_ne, axis=1)
    near = np.flatnonzero(horizontal <= PLAN_RANGE_FACTOR * radius)
    near = near[np.argsort(horizontal[near])[:MAX_PLAN_POINTS]]
    plan["points"] = {"ne": _round(pts[near, :2], 2), "color": hue_color(dist[near],
                                                                         color_range),
                      "converged": trusted[near].tolist()}


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
           hull: Hull, berth_line_ne: np.ndarray | None, water: float
           ) -> dict[str, Any] | None:
    """Berth line drawn on the water plane, bow/stern distance and approach speed."""
    plan["berth_line"] = None
    if berth_line_ne is None:
        return None
    line = np.asarray(berth_line_ne, dtype=float).reshape(2, 2)
    line3 = np.column_stack([line, np.full(2, water)])
    berth: dict[str, Any] = {key: (None if val is None else round(val, 3))
                             for key, val in berth_metrics(state, hull, line).items()}
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
