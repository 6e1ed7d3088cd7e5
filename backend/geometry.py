"""Display geometry of the ship and the berth: distance colours, the hull outline in the
plan, the berth metrics. The camera geometry (pose, projection, rays, water plane) is
``engine.camera``."""

from __future__ import annotations

from typing import Any

import numpy as np

from estimator.records import Hull

# Fixed distance bands (m) of the structure points, the same on every frame and in the legend:
# a colour means the same distance all through the approach.
DISTANCE_BANDS_M = (2.0, 5.0, 10.0, 20.0, 50.0, 100.0)
# day colours of the bands, nearest first (the page has its night ones, css/base.css)
BAND_COLORS = ("#ff2a2a", "#ff8c1a", "#ffd21a", "#3cc85a", "#1ab4e6", "#3c64ff", "#8c8cb4")


def distance_band(distance: np.ndarray) -> np.ndarray:
    """Index into ``BAND_COLORS`` of each distance (0: under 2 m … 6: 100 m and more)."""
    return np.searchsorted(DISTANCE_BANDS_M, np.asarray(distance, dtype=float), side="right")


def polygon_distances(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Distances (m) from plan points (N,2) to a closed polygon (M,2), 0 inside it."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    a = np.asarray(polygon, dtype=float)
    ab = np.roll(a, -1, axis=0) - a
    rel = pts[:, None, :] - a[None]  # (N,M,2)
    s = np.clip(np.einsum("nmk,mk->nm", rel, ab) / np.maximum(np.einsum("mk,mk->m", ab, ab),
                                                               1e-12), 0.0, 1.0)
    d = np.linalg.norm(rel - s[..., None] * ab[None], axis=2).min(axis=1)
    # even-odd rule for inside
    x, y = pts[:, 0:1], pts[:, 1:2]
    (x1, y1), (x2, y2) = a.T[:, None, :], np.roll(a, -1, axis=0).T[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        crosses = ((y1 > y) != (y2 > y)) & (x < x1 + (y - y1) * (x2 - x1) / (y2 - y1))
    inside = crosses.sum(axis=1) % 2 == 1
    return np.where(inside, 0.0, d)


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


def berth_metrics(state: Any, hull: Hull, line_ne: np.ndarray,
                  line_sigma_m: float | None = None, line_sigma_deg: float | None = None,
                  drift_cov: np.ndarray | None = None) -> dict[str, float | None]:
    """The ship against the berth line as pilots' docking displays give it (crews' terms).

    - bow (stern) distance: from the hull's foremost (aftmost) point, perpendicular to the
      infinite berth line (of several equally far forward points, e.g. a transom's corners,
      the one nearest the line), positive on the ship's side;
    - bow (stern) approach speed: that point's velocity (ship velocity + rate of turn x lever)
      towards the line, positive closing;
    - along-berth speed: the ship's velocity along the line, positive in the direction the
      bow points along it;
    - angle to the berth: between the centreline and the line (deg, -90..90), positive when
      the bow points towards the line ("bow in"; comparing the bow's distance with the
      stern's would name it backwards below atan(half beam / length): 4.6° on a 200 m hull,
      the whole final approach);
    - time to contact: the first hull point to reach the line at its present closing speed
      (None when nothing closes);
    - σ of the bow and stern distance: the line's σ (offset at its middle, direction), the
      fused position's σ across the line and the heading's σ through the point's lever arm;
      σ of the approach speeds: the fused velocity's across the line (millimetres a second
      on the carrier phase; decimetres once an INS fault has been found and the velocity
      widened), the rate of turn's through the lever arm, and the line's direction's: a
      line turned by δ takes δ of the speed along it into the approach (a water-plane line
      known to 20° makes a third of a 1 m/s slide along the quay look like closing); σ of the
      along-berth speed: the velocity's along the line and the line's direction's; σ of the
      angle: the line's direction and the heading; σ of the time to contact: the first
      point's distance σ and closing-speed σ.
    """
    line = np.asarray(line_ne, dtype=float).reshape(2, 2)
    direction = line[1] - line[0]
    length = float(np.linalg.norm(direction))
    if length < 1e-6:
        raise ValueError("the berth line's two points coincide")
    direction /= length
    normal = np.array([-direction[1], direction[0]])
    middle = line.mean(axis=0)
    outline_body = np.asarray(hull.outline_body, dtype=float)[:, :2]
    yaw = float(state.euler[2])
    R = heading_rotation(yaw)
    centre = np.asarray(state.position_ned, dtype=float)[:2]
    side = np.sign(float(np.dot(centre - line[0], normal))) or 1.0
    normal = normal * side  # from the line towards the ship
    velocity = np.asarray(state.velocity_ned, dtype=float)[:2]
    r = float(state.rate_of_turn)
    # the filter's, and the drift it does not model since the line was set
    # (``BerthLine.drift_since``)
    pos_var = _plan_variance(getattr(state, "position_cov", None), normal) \
        + _plan_variance(drift_cov, normal)
    vel_cov = getattr(state, "velocity_cov", None)
    vel_var = _plan_variance(vel_cov, normal)
    yaw_var = _yaw_variance(state)
    rate_var = float(getattr(state, "rate_of_turn_sigma", 0.0) or 0.0) ** 2
    dir_var = np.radians(line_sigma_deg or 0.0) ** 2  # the line's direction, rad²

    def point(body_xy: np.ndarray) -> tuple[float, float, float, float]:
        """distance, closing speed and their σ of a hull point."""
        lever = R @ body_xy
        p = centre + lever
        v_point = velocity + r * np.array([-lever[1], lever[0]])  # omega_down x lever (NE)
        # the point's move across the line per radian of heading (and its speed per rad/s of
        # rate of turn): a large ship's bow is 160 m out
        d_dpsi = float(np.dot(normal, np.array([-lever[1], lever[0]])))
        var = pos_var + yaw_var * d_dpsi ** 2 + (line_sigma_m or 0.0) ** 2 \
            + dir_var * float(np.dot(p - middle, direction)) ** 2
        closing_var = vel_var + rate_var * d_dpsi ** 2 \
            + dir_var * float(np.dot(v_point, direction)) ** 2
        return float(np.dot(p - line[0], normal)), float(-np.dot(v_point, normal)), \
            float(np.sqrt(var)), float(np.sqrt(closing_var))

    out: dict[str, float | None] = {}
    x = outline_body[:, 0]
    for name, ends in (("bow", x >= x.max() - 0.01), ("stern", x <= x.min() + 0.01)):
        candidates = [point(b) for b in outline_body[ends]]
        d, closing, sigma, closing_sigma = min(candidates, key=lambda c: c[0])
        out[f"{name}_distance_m"] = d
        out[f"{name}_approach_mps"] = closing
        out[f"{name}_distance_sigma_m"] = sigma
        out[f"{name}_approach_sigma_mps"] = closing_sigma
    heading = R[:, 0]
    along = direction if np.dot(direction, heading) >= 0 else -direction
    out["along_berth_mps"] = float(np.dot(velocity, along))
    out["along_berth_sigma_mps"] = float(np.sqrt(
        _plan_variance(vel_cov, along)
        + dir_var * float(np.dot(velocity, normal)) ** 2))
    # the heading's part towards the line (``normal`` points from it to the ship)
    out["angle_deg"] = float(np.degrees(np.arcsin(np.clip(-np.dot(heading, normal), -1.0, 1.0))))
    out["angle_sigma_deg"] = float(np.degrees(np.sqrt(yaw_var + dir_var)))
    # time to contact: the whole outline (a shoulder or quarter may touch first)
    dense = densify(outline_body, 0.25)
    levers = dense @ R.T
    dist = (centre + levers - line[0]) @ normal
    closing = -(velocity + r * np.column_stack([-levers[:, 1], levers[:, 0]])) @ normal
    moving = np.flatnonzero(closing > MIN_CLOSING_MPS)
    out["time_to_contact_s"] = out["time_to_contact_sigma_s"] = None
    if len(moving):
        ttc = np.maximum(dist[moving], 0.0) / closing[moving]
        first = int(moving[np.argmin(ttc)])
        out["time_to_contact_s"] = float(ttc.min())
        # d / c: the first point's distance σ and its closing speed's, to first order
        _, c, d_sigma, c_sigma = point(dense[first])
        out["time_to_contact_sigma_s"] = float(np.hypot(d_sigma, out["time_to_contact_s"]
                                                        * c_sigma)) / c
    out["nearest_distance_m"] = float(dist.min())
    return out


MIN_CLOSING_MPS = 0.005  # slower than this is not closing (no time to contact)


def _plan_variance(cov: np.ndarray | None, normal: np.ndarray) -> float:
    """The variance along the horizontal ``normal`` of a 3x3 (position or velocity)
    covariance; 0 without one."""
    if cov is None:
        return 0.0
    P = np.asarray(cov, dtype=float)[:2, :2]
    v = float(normal @ P @ normal)
    return v if np.isfinite(v) and v > 0 else 0.0


def _yaw_variance(state: Any) -> float:
    cov = getattr(state, "attitude_cov", None)
    if cov is None:
        return 0.0
    v = float(np.asarray(cov, dtype=float)[2, 2])
    return v if np.isfinite(v) and v > 0 else 0.0
