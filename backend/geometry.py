"""Display geometry of the ship and the berth: distance colours, the hull outline in the
plan, the berth metrics. The camera geometry (pose, projection, rays, water plane) is
``engine.camera``."""

from __future__ import annotations

from typing import Any

import numpy as np

from estimator.records import Hull


def hue_color(distance: np.ndarray, max_distance: float) -> list[str]:
    """'#rrggbb' colours by distance: red (near) through yellow, green, cyan to blue (far)."""
    h6 = 4.0 * np.clip(np.asarray(distance, dtype=float) / max(max_distance, 1e-6), 0.0, 1.0)
    r = np.clip(2.0 - h6, 0.0, 1.0)  # hue 0..240 deg = h6 0..4 on the HSV hexagon
    g = np.clip(np.minimum(h6, 4.0 - h6), 0.0, 1.0)
    b = np.clip(h6 - 2.0, 0.0, 1.0)
    rgb = np.round(np.column_stack([r, g, b]) * 255).astype(int)
    return [f"#{c[0]:02x}{c[1]:02x}{c[2]:02x}" for c in rgb]


# ------------------------------------------------------------------------ the ship's plan


def heading_rotation(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


def hull_outline_ne(state: Any, hull: Hull) -> np.ndarray:
    """Current hull polygon (N,2) north/east."""
    R = heading_rotation(float(state.euler[2]))
    return np.asarray(hull.outline_body, dtype=float)[:, :2] @ R.T \
        + np.asarray(state.position_ned, dtype=float)[:2]


def densify(polygon: np.ndarray, step: float) -> np.ndarray:
    """Closed polygon (N,2) with extra points so that no edge is longer than ``step``."""
    out = []
    p = np.asarray(polygon, dtype=float)
    for a, b in zip(p, np.roll(p, -1, axis=0), strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + np.linspace(0.0, 1.0, n, endpoint=False)[:, None] * (b - a))
    return np.concatenate(out)


def berth_metrics(state: Any, hull: Hull, line_ne: np.ndarray) -> dict[str, float | None]:
    """Bow and stern distance to the berth line and their approach speeds (crews' terms).

    The bow (stern) distance is the smallest perpendicular distance from the fore (aft) half
    of the hull outline to the infinite berth line; its approach speed is the velocity of
    that hull point (ship velocity + rate of turn x lever) towards the line, positive closing.
    """
    line = np.asarray(line_ne, dtype=float).reshape(2, 2)
    direction = line[1] - line[0]
    length = float(np.linalg.norm(direction))
    if length < 1e-6:
        raise ValueError("the berth line's two points coincide")
    direction /= length
    normal = np.array([-direction[1], direction[0]])
    outline_body = densify(np.asarray(hull.outline_body, dtype=float)[:, :2], 0.25)
    R = heading_rotation(float(state.euler[2]))
    centre = np.asarray(state.position_ned, dtype=float)[:2]
    points = outline_body @ R.T + centre
    side = np.sign(float(np.dot(centre - line[0], normal))) or 1.0
    signed = (points - line[0]) @ normal * side  # > 0 on the ship's side of the line
    velocity = np.asarray(state.velocity_ned, dtype=float)[:2]
    r = float(state.rate_of_turn)
    out: dict[str, float | None] = {}
    for name, half in (("bow", outline_body[:, 0] >= 0.0), ("stern", outline_body[:, 0] < 0.0)):
        if not half.any():
            out[f"{name}_distance_m"] = out[f"{name}_approach_mps"] = None
            continue
        idx = np.flatnonzero(half)
        # of the (nearly) nearest points, the one nearest the bow (stern) end: a hull side
        # parallel to the line has many equally near points
        near = idx[signed[idx] <= signed[idx].min() + 0.01]
        i = near[np.argmax(np.abs(outline_body[near, 0]))]
        lever = points[i] - centre
        v_point = velocity + r * np.array([-lever[1], lever[0]])  # omega_down x lever in NE
        out[f"{name}_distance_m"] = float(signed[i])
        out[f"{name}_approach_mps"] = float(-np.dot(v_point, normal) * side)
    return out
