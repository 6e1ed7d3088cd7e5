"""Hull outline prediction (thesis 5.3).

The officer sees where the hull will be in 1, 2, … N seconds if nothing changes: the current
rate of turn is kept constant and the velocity is kept constant *in the body frame* (so a boat
that is drifting sideways keeps drifting sideways relative to its heading while it turns, which
is what wind, current and a steady helm do over a few seconds).

Everything is horizontal: positions are (north, east) in the local-level frame, the hull polygon
is (forward, right) in the body frame, heading is the yaw of the ZYX Euler angles.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# Below this |rate of turn| (rad/s) the straight-line limit is used: sin(r t)/r loses digits.
_STRAIGHT_RATE = 1e-9


def rotation_2d(heading: float) -> np.ndarray:
    """2x2 rotation taking (forward, right) body coordinates to (north, east) at a heading."""
    c, s = np.cos(heading), np.sin(heading)
    return np.array([[c, -s], [s, c]])


def _turn_integral(rate: float, tau: float) -> np.ndarray:
    """∫_0^tau rotation_2d(rate * s) ds: maps a body-frame velocity to the displacement
    accumulated while turning at a constant rate (closed form of the constant-turn model)."""
    if abs(rate) < _STRAIGHT_RATE:
        return tau * np.eye(2)
    a = rate * tau
    return np.array([[np.sin(a), -(1.0 - np.cos(a))], [1.0 - np.cos(a), np.sin(a)]]) / rate


def predict_poses(position_ne: np.ndarray, heading: float, velocity_ne: np.ndarray,
                  rate_of_turn: float, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (T,2) north/east and headings (T,) at ``times`` (s ahead, each >= 0) under
    the constant turn-rate, constant body-frame velocity model."""
    p0 = np.asarray(position_ne, dtype=float)[:2]
    v_body = rotation_2d(heading).T @ np.asarray(velocity_ne, dtype=float)[:2]
    R0 = rotation_2d(heading)
    times = np.atleast_1d(np.asarray(times, dtype=float))
    positions = np.array([p0 + R0 @ _turn_integral(rate_of_turn, t) @ v_body for t in times])
    headings = heading + rate_of_turn * times
    return positions.reshape(-1, 2), headings


def outline_at(outline_body: np.ndarray, position_ne: np.ndarray, heading: float) -> np.ndarray:
    """Hull polygon (N,2) in north/east for the body origin at ``position_ne`` and a heading."""
    outline = np.asarray(outline_body, dtype=float)[:, :2]
    return outline @ rotation_2d(heading).T + np.asarray(position_ne, dtype=float)[:2]


def predict_outlines(state: Any, hull: Any, seconds: float, step: float = 1.0
                     ) -> list[np.ndarray]:
    """Predicted hull outlines, (N_pts,2) north/east polygons, at step, 2 step, … <= seconds.

    ``state`` is a fused state (``position_ned``, ``velocity_ned``, ``euler``,
    ``rate_of_turn``) and ``hull`` a ``records.Hull``; ``seconds`` <= 0 gives no outline.
    """
    if step <= 0:
        raise ValueError(f"step must be positive, got {step}")
    count = int(np.floor(seconds / step + 1e-9)) if seconds > 0 else 0
    if count == 0:
        return []
    times = step * np.arange(1, count + 1)
    positions, headings = predict_poses(np.asarray(state.position_ned)[:2],
                                        float(state.euler[2]),
                                        np.asarray(state.velocity_ned)[:2],
                                        float(state.rate_of_turn), times)
    return [outline_at(hull.outline_body, p, h) for p, h in zip(positions, headings, strict=True)]
