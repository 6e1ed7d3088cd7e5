"""Scoring against the reference: trajectory errors of a fusion run, statistics of absolute
errors, structure points against the true scene points. The estimator never sees any of it.

Alignment: the fusion's world frame is its own start point (SPP-anchored), so every run is
aligned to the reference by ONE translation, the reference position at the fusion's origin
time. No rotation is fitted: a heading error shows as a growing position error. σ of a
horizontal error is ``sqrt(var_N + var_E)`` over the window (the thesis' "standard deviation
converted to the horizontal distance"; a constant offset is not in σ, it is in the max and in
the RMS printed beside it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from estimator.frames import wrap_angle

from .records import (
    BandStats,
    ErrorStats,
    PointScores,
    PointStats,
    QuayEdge,
    QuayStats,
    TrajectoryScores,
)
from .runs import FusionRun

BANDS_M = ((0.0, 10.0), (10.0, 30.0), (30.0, 60.0), (60.0, math.inf))  # range bands
MATCH_GATE_M = 1.0  # a structure point is matched to a true point within max(this, ...
MATCH_GATE_FRACTION = 0.05  # ... this fraction of its range from the camera)
MATCH_GATE = f"max({MATCH_GATE_M:g} m, {100 * MATCH_GATE_FRACTION:g} % of the range)"
QUAY_BAND_M = 3.0  # structure points this close (horizontally) to the quay edge are quay points
NEAR_M = 30.0  # "near" structure: within this range of the camera


def band_range(lo: float, hi: float) -> list[float | None]:
    """A band's [lo, hi] for the JSON (None: unbounded)."""
    return [lo, None if math.isinf(hi) else hi]


def error_stats(e: np.ndarray) -> ErrorStats:
    """Statistics of the absolute values of the finite errors ``e``."""
    e = np.asarray(e, float)
    e = e[np.isfinite(e)]
    if not len(e):
        return ErrorStats()
    a = np.abs(e)
    return ErrorStats(n=int(len(e)), median=float(np.median(a)),
                      p90=float(np.percentile(a, 90)), max=float(a.max()),
                      rms=float(np.sqrt(np.mean(e**2))))


# ------------------------------------------------------------------------ trajectories


def horizontal_std(e: np.ndarray) -> float:
    """σ converted to the horizontal distance: sqrt(var_N + var_E)."""
    return float(np.sqrt(np.var(e[:, 0]) + np.var(e[:, 1])))


@dataclass
class Errors:
    """Errors of a run against the reference at its frames."""

    time: np.ndarray  # all samples (s since the recording start)
    position: np.ndarray  # (N,3) aligned position error, NaN when unknown
    velocity: np.ndarray
    heading: np.ndarray  # rad
    window: np.ndarray  # (N,) bool: inside the window and scored


def run_errors(run: FusionRun, reference: object, start: float, t0: float) -> Errors | None:
    """Errors of a run against ``reference`` (``recordings.format.Reference``), aligned by the
    translation at its origin; the window starts at gpst ``t0``."""
    if run.origin_time is None:
        return None
    ref_pos, ref_vel, ref_eul = reference.interpolate(run.time)  # type: ignore[attr-defined]
    origin = reference.interpolate(run.origin_time)[0]  # type: ignore[attr-defined]
    e_pos = run.position - (ref_pos - origin)
    e_vel = run.velocity - ref_vel
    e_hdg = wrap_angle(run.euler[:, 2] - ref_eul[:, 2])
    ok = np.isfinite(e_pos).all(axis=1) & np.isfinite(e_hdg)
    return Errors(time=run.time - start, position=e_pos, velocity=e_vel, heading=e_hdg,
                  window=ok & (run.time >= t0 - 1e-6))


def trajectory_scores(err: Errors | None, n_window: int) -> TrajectoryScores:
    """Table 17's figures of a run over the window (``n_window`` frames in it)."""
    if err is None or not err.window.any():
        return TrajectoryScores()
    w = err.window
    e, v, h = err.position[w], err.velocity[w], err.heading[w]
    horiz = np.hypot(e[:, 0], e[:, 1])
    vok = np.isfinite(v).all(axis=1)
    return TrajectoryScores(
        horizontal_std_m=horizontal_std(e), horizontal_max_m=float(horiz.max()),
        horizontal_rms_m=float(np.sqrt(np.mean(horiz**2))),
        velocity_std_mps=horizontal_std(v[vok]) if vok.any() else None,
        heading_std_deg=float(np.degrees(np.std(h))),
        heading_rms_deg=float(np.degrees(np.sqrt(np.mean(h**2)))),
        heading_max_deg=float(np.degrees(np.abs(h).max())),
        coverage=float(w.sum() / max(n_window, 1)))


# --------------------------------------------------------------------------- structure


def point_scores(pts: np.ndarray, true: np.ndarray, cam: np.ndarray,
                 quay: np.ndarray | None) -> tuple[PointScores, np.ndarray]:
    """Nearest-true-point statistics by range band and the quay-edge distances; also the
    distance of every point to its nearest true point."""
    d, _ = cKDTree(true).query(pts)
    rng = np.linalg.norm(pts - cam, axis=1)
    matched = d <= np.maximum(MATCH_GATE_M, MATCH_GATE_FRACTION * rng)

    def stats(sel: np.ndarray) -> PointStats:
        m = sel & matched
        return PointStats(int(sel.sum()), int(m.sum()),
                          float(np.median(d[m])) if m.any() else None,
                          float(np.percentile(d[m], 90)) if m.any() else None)

    whole = stats(np.ones(len(pts), bool))
    bands = [BandStats(band_range(lo, hi), **vars(stats((rng >= lo) & (rng < hi))))
             for lo, hi in BANDS_M]
    edge = None
    if quay is not None:
        dq = distance_to_polyline(pts[:, :2], quay[:, :2])
        near = dq <= QUAY_BAND_M

        def qstats(sel: np.ndarray) -> QuayStats:
            return QuayStats(int(sel.sum()), float(np.median(dq[sel])) if sel.any() else None,
                             float(np.percentile(dq[sel], 90)) if sel.any() else None)

        edge = QuayEdge(QUAY_BAND_M, qstats(near), qstats(near & (rng < NEAR_M)))
    return PointScores(whole.points, whole.matched, whole.median_m, whole.p90_m,
                       stats(rng < NEAR_M), bands, edge), d


def quay_line(scene_points: np.ndarray | None, kinds: list[str] | None,
              origin: np.ndarray) -> np.ndarray | None:
    """The quay edge in the fusion's frame: the scene points of kind "quay" in order along
    their main direction (a straight or gently curved quay), None without them."""
    if scene_points is None or not kinds:
        return None
    q = np.asarray(scene_points, float)[np.array(kinds) == "quay"] - origin
    if len(q) < 2:
        return None
    d = q[:, :2] - q[:, :2].mean(axis=0)
    axis = np.linalg.svd(d, full_matrices=False)[2][0]
    return q[np.argsort(d @ axis)]


def distance_to_polyline(p: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Distance of 2-D points (N,2) to a polyline (M,2)."""
    a, b = line[:-1], line[1:]
    ab = b - a
    L2 = np.maximum(np.sum(ab**2, axis=1), 1e-12)
    t = np.clip(np.einsum("nmk,mk->nm", p[:, None, :] - a[None], ab) / L2, 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.min(np.linalg.norm(p[:, None, :] - closest, axis=2), axis=1)
