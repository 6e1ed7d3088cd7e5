"""A session's berth line: fitted to the quay face under the officer's clicks, typed in from
the bow, set from two (north, east) points or given by the recording, and nudged; the berth
geometry (``geometry.berth_metrics``) against it.

Clicks in the video (coping, wall or water line: all on the quay's vertical face) give only
their *directions* in plan; the line's place comes from the converged port-structure points of
the quay face between them (``fit_quay_face``): a vertical plane fitted through them, with its
σ. A pixel's depth along the water plane is ill-conditioned from a camera a metre above the
water (a pixel is ~0.3 m at 15 m); the face's points are not. Only where there is no structure
near the clicks does the line fall back to the click rays' intersections with the water plane
(``method`` = ``water-plane``, with a note saying so, and a σ from a slipped click and the
camera's height over the water).

A wrong plane is worse than none: the fit is refused (the water plane then) when the plane
lies beyond where a click's ray meets the water, behind converged points right at a click,
or does not extend on both sides of where a click's ray meets it (a moored boat's side
ending beside a click).
``benchmarks/berth_clicks.py`` measures it over many recordings.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from engine.camera import CameraPose, Projector, camera_pose, water_plane_point
from engine.targets import Structure
from estimator.landmarks import converged, excess_disagreement
from recordings.format import Recording

from .errors import Unprocessable
from .geometry import berth_metrics, heading_rotation
from .models import MAX_PLAN_M

MIN_LENGTH_M = 0.1  # the two points of a berth line at least this far apart
# structure points "under" a click: these fractions of the image width (nearest first; the
# widest only reaches a face whose points lie beside the click, as on a bare wall)
CLICK_RADII = (0.05, 0.1, 0.2)
HYPOTHESIS_GATE_M = 0.25  # a point supports a hypothetical face this near it
REFIT_GATE_M = 0.5  # the chosen face is re-fitted to the points this near it
EXTEND_M = 30.0  # ... and to those this far beyond the clicks along it
FRONT_DEPTH_M = 1.0  # faces this close behind the nearest one are the same surface
FACE_GATE_M = 1.5  # a line clicked in plan: fitted to the points this near it
SECTOR_MARGIN_DEG = 2.0  # the face is fitted between the clicks' directions, widened by this
MIN_FACE_POINTS = 8  # fewer than this: no face fit (water plane)
MIN_HALF_POINTS = 3  # a half of a face's points with fewer is not fitted on its own
ABOVE_WATER_M = 0.1  # structure points at most this far above the water plane are not quay
MIN_INLIER_GATE_M = 0.15
CORRELATED_FRACTION = 0.002  # σ of the line shared by all its points, per metre of range
MIN_POINT_SIGMA_M = 0.02  # a structure point's σ taken as at least this in the fit
# Where a click's ray meets the water bounds the clicked surface's range (it hides what lies
# beyond), give or take a slipped click and the camera's height over the water (waves, squat).
CLICK_SLIP_PX = 2.0
CAMERA_HEIGHT_SIGMA_M = 0.1
OCCLUSION_SIGMAS = 3.0
MIN_BLOCKERS = 2  # converged points at a click in front of a plane that rule it out
# A recording's own berth line is placed through the fused absolute position (standalone GNSS:
# metre-level), not through what the camera sees.
RECORDING_LINE_SIGMA_M = 2.0
RECORDING_LINE_NOTE = ("the recording's berth line, placed through the standalone GNSS "
                       "position (metre-level): set it on the quay for centimetres")
WATER_PLANE_NOTE = ("no converged port structure near the clicks: the line is where the click "
                    "rays meet the water plane, to a few pixels' worth of metres (click the "
                    "quay's water line exactly, or wait for the quay's points to converge)")


@dataclass(frozen=True)
class BerthLine:
    line_ne: np.ndarray  # (2,2) north, east
    source: str  # "recording", "ned", "image", "typed"
    # "world": the engine's frame; "recording": the recording's local level (hull.json), mapped
    # to the world frame through the fused absolute position (SPP-anchored: metre-level)
    frame: str = "world"
    method: str | None = None  # "quay-face" | "water-plane" | None (as given)
    sigma_m: float | None = None  # 1-σ of the line across itself (at its middle)
    sigma_deg: float | None = None  # 1-σ of its direction
    support: int = 0  # structure points the face was fitted to
    note: str = ""
    # moved by the officer since it was set (m away from the ship, deg clockwise): the σ is
    # still the fit's, the nudge exact; the page says the line is no longer the fit alone
    nudged_m: float = 0.0
    nudged_deg: float = 0.0
    # the fused position's unmodelled drift (``FusedState.position_drift_cov``) when the line
    # was measured from the trajectory (clicked, snapped, typed from the bow); None for a line
    # fixed in the world: the ship's whole drift since the INS started is then against it
    drift_at_set: np.ndarray | None = None

    def drift_since(self, state: Any) -> np.ndarray:
        """The drift (3 x 3 m², NED) of the fused position against this line at ``state``."""
        drift = np.asarray(state.position_drift_cov, dtype=float)
        if self.drift_at_set is not None:
            drift = drift - self.drift_at_set
        # the drift only grows; keep what may not (the difference of two covariances)
        w, V = np.linalg.eigh(0.5 * (drift + drift.T))
        return (V * np.clip(w, 0.0, None)) @ V.T

    def describe(self) -> dict[str, Any]:
        """What the line is, as the API and the frames give it (besides where it is)."""
        return {"source": self.source, "method": self.method, "support_points": self.support,
                "note": self.note, "sigma_m": _r(self.sigma_m), "sigma_deg": _r(self.sigma_deg),
                "nudged_m": _r(self.nudged_m), "nudged_deg": _r(self.nudged_deg)}


@dataclass(frozen=True)
class FaceFit:
    """A vertical plane (a line in plan) fitted to quay-face points."""

    centre: np.ndarray  # (2,) north, east
    direction: np.ndarray  # (2,) unit
    sigma_m: float  # σ of the offset at the centre
    sigma_rad: float  # σ of the direction
    support: int
    scatter: float  # χ² per degree of freedom, at least 1: how far beyond their σ the points lie


def _weighted_line(p: np.ndarray, w: np.ndarray) -> FaceFit:
    """Weighted (``w`` = 1/σ²) total-least-squares line through plan points ``p``: its σ the
    weighted least-squares σ, scaled up by the scatter when the points lie farther from the
    line than their σ say."""
    centre = (w[:, None] * p).sum(axis=0) / w.sum()
    d = p - centre
    cov = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(axis=0) / w.sum()
    _, vecs = np.linalg.eigh(cov)
    direction, normal = vecs[:, 1], vecs[:, 0]
    residual = d @ normal
    factor = max(1.0, float((w * residual ** 2).sum()) / max(len(p) - 2, 1))
    along = d @ direction
    return FaceFit(centre, direction, float(np.sqrt(factor / w.sum())),
                   float(np.sqrt(factor / max(float((w * along ** 2).sum()), 1e-9))), len(p),
                   factor)


def _at_centre(half: FaceFit, fit: FaceFit) -> tuple[np.ndarray, np.ndarray]:
    """A half's line as (offset across ``fit`` at its centre, angle to it) with its 2x2
    covariance (its offset σ carried from its own centre along its direction σ)."""
    d = half.direction if half.direction @ fit.direction >= 0 else -half.direction
    normal = np.array([-fit.direction[1], fit.direction[0]])
    # where the half's line crosses the normal through the fit's centre
    t, s = np.linalg.solve(np.column_stack([d, -normal]), fit.centre - half.centre)
    angle = float(np.arctan2(fit.direction[0] * d[1] - fit.direction[1] * d[0],
                             fit.direction @ d))
    # the crossing lies t along the half's line from its centre: turned by δ, it moves t δ
    cov = np.array([[half.sigma_m ** 2 + (t * half.sigma_rad) ** 2, t * half.sigma_rad ** 2],
                    [t * half.sigma_rad ** 2, half.sigma_rad ** 2]])
    return np.array([s, angle]), cov


def fit_line(points_ne: np.ndarray, sigma: np.ndarray) -> FaceFit | None:
    """Weighted (1/σ²) total-least-squares line through plan points, re-fitted without the
    points beyond 3 of their σ (and the fit's scatter) from it; None with fewer than
    MIN_FACE_POINTS. Its σ: the weighted least-squares σ, scaled up by the scatter when the
    points lie farther from the line than their σ say, and widened by what the lines through
    either half of the points (along it) disagree beyond their σ (``excess_disagreement``).
    A straight line through two surfaces (the quay and a boat's side before it) or through
    points whose errors are alike along a stretch fits each half well and the halves not
    together: the line's σ then says how far it may be off (a yardstick seed's fit through
    two such surfaces was 0.5 m off at the bow under a σ of 4 cm)."""
    p = np.asarray(points_ne, dtype=float).reshape(-1, 2)
    sig = np.maximum(np.asarray(sigma, dtype=float), MIN_POINT_SIGMA_M)
    w = 1.0 / sig ** 2
    keep = np.ones(len(p), dtype=bool)
    fit = None
    for _ in range(5):
        if int(keep.sum()) < MIN_FACE_POINTS:
            return None
        fit = _weighted_line(p[keep], w[keep])
        residual = (p - fit.centre) @ np.array([-fit.direction[1], fit.direction[0]])
        new = np.abs(residual) <= np.maximum(3.0 * np.sqrt(sig ** 2 * fit.scatter),
                                             MIN_INLIER_GATE_M)
        if (new == keep).all():
            break
        keep = new
    assert fit is not None
    pk, wk = p[keep], w[keep]
    along = (pk - fit.centre) @ fit.direction
    first = along < float(np.median(along))
    if min(int(first.sum()), int((~first).sum())) < MIN_HALF_POINTS:
        return fit
    x_a, P_a = _at_centre(_weighted_line(pk[first], wk[first]), fit)
    x_b, P_b = _at_centre(_weighted_line(pk[~first], wk[~first]), fit)
    extra = excess_disagreement(x_a, P_a, x_b, P_b)
    return replace(fit, sigma_m=float(np.sqrt(fit.sigma_m ** 2 + extra[0, 0])),
                   sigma_rad=float(np.sqrt(fit.sigma_rad ** 2 + extra[1, 1])))


def _azimuth(v: np.ndarray) -> np.ndarray:
    return np.arctan2(v[..., 1], v[..., 0])


def _wrap(a: np.ndarray | float) -> np.ndarray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _ray_line(origin: np.ndarray, azimuth: float, centre: np.ndarray, direction: np.ndarray
              ) -> np.ndarray | None:
    """Where the plan ray from ``origin`` at ``azimuth`` meets the line (None: it does not)."""
    r = np.array([np.cos(azimuth), np.sin(azimuth)])
    A = np.column_stack([r, -direction])
    if abs(np.linalg.det(A)) < 1e-6:
        return None
    s, _ = np.linalg.solve(A, centre - origin)
    return None if s <= 0 else origin + s * r


def fit_quay_face(projector: Projector, pose: CameraPose, clicks_uv: np.ndarray,
                  structure: Structure, water_down_m: float | None,
                  attitude_cov: np.ndarray | None = None) -> BerthLine | None:
    """The berth line on the quay face between two clicks of the frame seen from ``pose``
    (module docstring); None when the structure does not support it.

    Hypotheses: the vertical planes through a point under the first click and one under the
    second (points projecting within ``CLICK_RADII`` of the image width, nearer first). A
    hypothesis stands when points of it lie under both clicks; of those standing, the clicked
    surface is the nearest (what a pixel shows is the first surface along its ray), and of the
    planes of that surface the best supported is fitted to all its points between the clicks
    and up to ``EXTEND_M`` beyond them. No plane may lie beyond where a click's ray meets the
    water (``water_bounds``: that pixel would show the water, not it), behind MIN_BLOCKERS
    converged points right at a click (the innermost radius: a nearer surface is there), nor
    end short of where a click's ray meets it (its points on one side only); the fitted line is
    held to the same."""
    pts = np.asarray(structure.points, dtype=float).reshape(-1, 3)
    if len(pts) < MIN_FACE_POINTS:
        return None
    sigma = np.asarray(structure.sigma, dtype=float).ravel()
    cam = pose.position_ned
    finite = np.isfinite(pts).all(axis=1)
    pts = np.where(finite[:, None], pts, 0.0)
    usable = finite & converged(sigma, np.linalg.norm(pts - cam, axis=1))
    if water_down_m is not None:  # at or below the water: reflections, not the quay
        usable &= pts[:, 2] < water_down_m - ABOVE_WATER_M
    _, uv = projector.project_points(pose, pts)
    clicks = np.asarray(clicks_uv, dtype=float).reshape(2, 2)
    rays = [projector.pixel_ray(pose, u, v) for u, v in clicks]
    click_az = [float(np.arctan2(r[1], r[0])) for r in rays]
    azimuths = _azimuth(pts[:, :2] - cam[:2])
    half = abs(float(_wrap(click_az[1] - click_az[0]))) / 2
    mid = float(_wrap(click_az[0] + _wrap(click_az[1] - click_az[0]) / 2))
    sector = usable & (np.abs(_wrap(azimuths - mid)) <= half + np.radians(SECTOR_MARGIN_DEG))
    bound = water_bounds(projector, cam, rays, water_down_m, attitude_cov)
    px = [np.nan_to_num(np.hypot(uv[:, 0] - u, uv[:, 1] - v), nan=np.inf) for u, v in clicks]
    at = usable & ((px[0] <= CLICK_RADII[0] * projector.width)  # right at a click
                   | (px[1] <= CLICK_RADII[0] * projector.width))
    blockers = (pts[at, :2], sigma[at])
    chosen = None
    for radius in CLICK_RADII:  # the nearest points under the clicks first
        under = [usable & (d <= radius * projector.width) for d in px]
        chosen = _front_face(pts, under, sector, rays, cam, bound, blockers)
        if chosen is not None:
            break
    if chosen is None:
        return None
    # the face goes on beyond the clicks: its points out there steady the line's direction
    centre, direction = chosen
    span = float(np.ptp(np.concatenate([(pts[m, :2] - centre) @ direction for m in under])))
    fit = None
    for _ in range(3):  # the chosen pair's plane, then the fitted one
        normal_c = np.array([-direction[1], direction[0]])
        along = (pts[:, :2] - centre) @ direction
        mid_along = float(np.mean(along[under[0] | under[1]]))
        near = np.abs((pts[:, :2] - centre) @ normal_c) <= REFIT_GATE_M
        beyond = np.abs(along - mid_along) <= span / 2 + EXTEND_M
        members = np.flatnonzero(usable & near & (sector | beyond))
        fit = fit_line(pts[members, :2], sigma[members])
        if fit is None:
            return None
        centre, direction = fit.centre, fit.direction
    ends = [_ray_line(cam[:2], az, fit.centre, fit.direction) for az in click_az]
    if any(e is None for e in ends) or np.linalg.norm(ends[1] - ends[0]) < MIN_LENGTH_M:
        return None
    shown, _ = _shown_at_clicks(fit.centre[None], fit.direction[None], pts[members, :2],
                                np.ones((1, len(members)), dtype=bool), rays, cam, bound,
                                blockers)
    if not shown[0]:
        return None  # the re-fit swung to where the clicks cannot be on it
    return _face_line(fit, np.array(ends), "image", cam)


@dataclass(frozen=True)
class WaterHit:
    """Where a click's ray meets the water, and how its plan range moves: by a slipped click
    (its own), by the camera's height over the water and by the camera's attitude (both
    shared by every click of one frame)."""

    point: np.ndarray  # NED (m)
    range_m: float  # in plan, from the camera
    slip_sigma_m: float  # a click slipped by CLICK_SLIP_PX
    # (4,) m of range per m of camera height and per rad of attitude error (rotation in L),
    # the errors of ``shared_covariance``
    per_shared: np.ndarray

    def sigma(self, attitude_cov: np.ndarray | None = None) -> float:
        """The range's σ: slip, height and attitude (``shared_covariance``)."""
        return math.sqrt(self.slip_sigma_m ** 2 + float(
            self.per_shared @ shared_covariance(attitude_cov) @ self.per_shared))


def shared_covariance(attitude_cov: np.ndarray | None) -> np.ndarray:
    """(4,4) covariance of the errors every click of a frame shares: the camera's height over
    the water (CAMERA_HEIGHT_SIGMA_M) and the fused attitude (rad², none when not given)."""
    S = np.zeros((4, 4))
    S[0, 0] = CAMERA_HEIGHT_SIGMA_M ** 2
    if attitude_cov is not None:
        S[1:, 1:] = np.asarray(attitude_cov, float)
    return S


def water_range(projector: Projector, cam: np.ndarray, ray: np.ndarray,
                water_down_m: float | None) -> WaterHit | None:
    """Where a click's ray meets the water; None where the ray misses the water or the level
    is unknown."""
    if water_down_m is None:
        return None
    hit = water_plane_point(cam, ray, water_down_m)
    if hit is None:
        return None
    height = water_down_m - float(cam[2])
    rng = float(np.linalg.norm(hit[:2] - cam[:2]))
    focal = float(max(projector.K[0, 0], projector.K[1, 1]))
    # range = height·cot(depression): its sensitivity to the depression and to the height
    per_rad = (height ** 2 + rng ** 2) / height
    # a turn δ of the camera moves the ray by δ × r: its depression by (δ × r)_down / |r_h|
    # (a large ship's camera 20 m up sees the quay 110 m off at 11 m per degree)
    r = np.asarray(ray, float) / np.linalg.norm(ray)
    g = np.array([r[1], -r[0], 0.0]) / max(float(np.hypot(r[0], r[1])), 1e-9)
    return WaterHit(hit, rng, per_rad / focal * CLICK_SLIP_PX,
                    np.concatenate([[rng / height], per_rad * g]))


def water_bounds(projector: Projector, cam: np.ndarray, rays: list[np.ndarray],
                 water_down_m: float | None, attitude_cov: np.ndarray | None = None
                 ) -> np.ndarray:
    """The farthest plan range each click's surface can lie at: where its ray meets the water,
    plus OCCLUSION_SIGMAS of that range's σ (``water_range``); inf where there is none."""
    bound = np.full(len(rays), np.inf)
    for i, r in enumerate(rays):
        hit = water_range(projector, cam, r, water_down_m)
        if hit is not None:
            bound[i] = hit.range_m + OCCLUSION_SIGMAS * hit.sigma(attitude_cov)
    return bound


def water_plane_line(projector: Projector, pose: CameraPose, clicks_uv: np.ndarray,
                     water_down_m: float | None, attitude_cov: np.ndarray | None = None
                     ) -> BerthLine:
    """The line through where the click rays meet the water, with the σ of those ranges
    (``water_range``) carried across the line (at its middle and in its direction);
    Unprocessable when a ray misses the water."""
    cam = pose.position_ned
    hits = []
    for u, v in np.asarray(clicks_uv, dtype=float).reshape(2, 2):
        hit = water_range(projector, cam, projector.pixel_ray(pose, u, v), water_down_m)
        if hit is None:
            raise Unprocessable(
                f"pixel ({u:g}, {v:g}): no converged port structure near the clicks and "
                "its ray does not meet the water plane (above the horizon, or the water "
                "level is unknown); click the quay where its points are shown, or type "
                "the line in from the bow")
        hits.append(hit)
    line = np.array([h.point[:2] for h in hits])
    length = float(np.linalg.norm(line[1] - line[0]))
    if length < MIN_LENGTH_M:
        raise Unprocessable(f"the clicks meet the water less than {MIN_LENGTH_M:g} m apart")
    d = (line[1] - line[0]) / length
    normal = np.array([-d[1], d[0]])
    # each end's range moves it along its ray; across the line by this much per metre
    a = [float((h.point[:2] - cam[:2]) @ normal) / h.range_m for h in hits]
    # the ends' covariance across the line: their own slips, and the camera's height and
    # attitude that move both at once (the line's middle takes all of those, not 1/√2)
    J = np.array([ai * h.per_shared for ai, h in zip(a, hits, strict=True)])
    C = J @ shared_covariance(attitude_cov) @ J.T \
        + np.diag([(ai * h.slip_sigma_m) ** 2 for ai, h in zip(a, hits, strict=True)])
    middle = 0.5 * math.sqrt(max(C[0, 0] + C[1, 1] + 2.0 * C[0, 1], 0.0))
    turn = math.sqrt(max(C[0, 0] + C[1, 1] - 2.0 * C[0, 1], 0.0)) / length
    return BerthLine(line, "image", method="water-plane", sigma_m=float(middle),
                     sigma_deg=float(np.degrees(turn)), note=WATER_PLANE_NOTE)


def _in_front(points_ne: np.ndarray, sigma: np.ndarray, on_plane: np.ndarray,
              normal: np.ndarray, cam: np.ndarray) -> np.ndarray:
    """Per plane (a point on it, its normal: (H, 2) each): whether MIN_BLOCKERS of the points
    lie between it and the camera, farther from it than FRONT_DEPTH_M and twice their σ (one
    stray point is no surface)."""
    if not len(points_ne):
        return np.zeros(len(on_plane), dtype=bool)
    towards = np.sign(np.einsum("hk,hk->h", cam[:2] - on_plane, normal))
    depth = np.einsum("hnk,hk->hn", points_ne[None] - on_plane[:, None], normal) * towards[:, None]
    return (depth > FRONT_DEPTH_M + 2.0 * sigma[None]).sum(axis=1) >= MIN_BLOCKERS


def _shown_at_clicks(on_plane: np.ndarray, direction: np.ndarray, points_ne: np.ndarray,
                     inlier: np.ndarray, rays: list[np.ndarray], cam: np.ndarray,
                     bound: np.ndarray, blockers: tuple[np.ndarray, np.ndarray]
                     ) -> tuple[np.ndarray, list[np.ndarray]]:
    """Per vertical plane (a point on it, its unit direction in plan: (H, 2) each; its points:
    ``inlier`` (H, N) of ``points_ne``): whether it can be what both clicks show, and the plan
    range along each click's ray to it. It cannot when a ray meets it behind the camera or
    beyond ``bound`` (the water that pixel shows), when MIN_BLOCKERS ``blockers`` (plan points
    right at a click, σ) lie in front of it, or when its points do not lie on both sides of
    where a ray meets it (a moored boat's side ending beside a click)."""
    normal = np.column_stack([-direction[:, 1], direction[:, 0]])
    along = np.einsum("hnk,hk->hn", points_ne[None] - on_plane[:, None], direction)
    shown = ~_in_front(*blockers, on_plane, normal, cam)
    ranges = []
    for r, b in zip(rays, bound, strict=True):
        norm = max(float(np.linalg.norm(r[:2])), 1e-9)
        with np.errstate(divide="ignore", invalid="ignore"):
            rng = np.einsum("hk,hk->h", on_plane - cam[:2], normal) / (normal @ r[:2]) * norm
            end = np.einsum("hk,hk->h", cam[:2] + rng[:, None] * r[:2] / norm - on_plane,
                            direction)
            offset = np.where(inlier, along - end[:, None], np.nan)
            shown &= np.isfinite(rng) & (rng > 0) & (rng <= b)
            shown &= (np.nanmin(offset, axis=1) < 0) & (np.nanmax(offset, axis=1) > 0)
        ranges.append(rng)
    return shown, ranges


def _front_face(pts: np.ndarray, under: list[np.ndarray], sector: np.ndarray,
                rays: list[np.ndarray], cam: np.ndarray, bound: np.ndarray,
                blockers: tuple[np.ndarray, np.ndarray]
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """(point, direction) of the nearest well-supported vertical plane through a point under
    each click (``fit_quay_face``) that can be what the clicks show (``_shown_at_clicks``),
    None when there is none."""
    if any(m.sum() < 1 for m in under):
        return None
    ia, ib = np.flatnonzero(under[0]), np.flatnonzero(under[1])
    pa = np.repeat(pts[ia, :2], len(ib), axis=0)
    d = np.tile(pts[ib, :2], (len(ia), 1)) - pa
    length = np.linalg.norm(d, axis=1)
    ok = length > 0.5
    if not ok.any():
        return None
    pa, d = pa[ok], d[ok] / length[ok, None]
    normal = np.column_stack([-d[:, 1], d[:, 0]])
    cand = np.flatnonzero(sector | under[0] | under[1])
    res = np.abs(np.einsum("hnk,hk->hn", pts[cand, :2][None] - pa[:, None], normal))
    inlier = res <= HYPOTHESIS_GATE_M  # (hypotheses, candidates)
    support_a = (inlier & under[0][cand][None]).sum(axis=1)
    support_b = (inlier & under[1][cand][None]).sum(axis=1)
    total = (inlier & sector[cand][None]).sum(axis=1)
    standing = (support_a >= 2) & (support_b >= 2) & (total >= MIN_FACE_POINTS)
    shown, ranges = _shown_at_clicks(pa, d, pts[cand, :2], inlier, rays, cam, bound, blockers)
    standing &= shown
    reach = np.maximum(ranges[0], ranges[1])
    if not standing.any():
        return None
    nearest = float(reach[standing].min())
    front = standing & (reach <= nearest + FRONT_DEPTH_M)
    best = int(np.argmax(np.where(front, total, -1)))
    return pa[best], d[best]


def snap_to_face(line_ne: np.ndarray, structure: Structure, water_down_m: float | None,
                 camera_ned: np.ndarray) -> BerthLine | None:
    """A line clicked in the plan, fitted to the converged above-water structure points within
    FACE_GATE_M of it (None when there are too few)."""
    pts = np.asarray(structure.points, dtype=float).reshape(-1, 3)
    if len(pts) < MIN_FACE_POINTS:
        return None
    sigma = np.asarray(structure.sigma, dtype=float).ravel()
    usable = np.isfinite(pts).all(axis=1) & converged(
        sigma, np.linalg.norm(pts - np.asarray(camera_ned, dtype=float), axis=1))
    if water_down_m is not None:
        usable &= pts[:, 2] < water_down_m - ABOVE_WATER_M
    a, b = np.asarray(line_ne, dtype=float).reshape(2, 2)
    length = float(np.linalg.norm(b - a))
    d = (b - a) / length
    n = np.array([-d[1], d[0]])
    along = (pts[:, :2] - a) @ d
    candidates = usable & (np.abs((pts[:, :2] - a) @ n) <= FACE_GATE_M) \
        & (along >= -0.1 * length) & (along <= 1.1 * length)
    fit = fit_line(pts[candidates, :2], sigma[candidates])
    if fit is None:
        return None
    ends = [fit.centre + float(np.dot(p - fit.centre, fit.direction)) * fit.direction
            for p in (a, b)]
    return _face_line(fit, np.array(ends), "ned", np.asarray(camera_ned, dtype=float))


def _face_line(fit: FaceFit, ends: np.ndarray, source: str, camera_ned: np.ndarray
               ) -> BerthLine:
    """The berth line between ``ends`` on a fitted face, with the σ of its offset at its
    middle (``BerthLine.sigma_m``; the fit's is at the points' centre, which may lie tens of
    metres along) and of its direction."""
    # the points' errors are not independent (one VO scale, the poses they were triangulated
    # from): a σ proportional to the range stands for what they share
    shared = CORRELATED_FRACTION * float(np.linalg.norm(fit.centre - camera_ned[:2]))
    along = float((ends.mean(axis=0) - fit.centre) @ fit.direction)
    return BerthLine(ends, source, method="quay-face",
                     sigma_m=float(np.sqrt(fit.sigma_m ** 2 + (fit.sigma_rad * along) ** 2
                                           + shared ** 2)),
                     sigma_deg=float(np.degrees(fit.sigma_rad)), support=fit.support)


def line_from_bow(state: Any, hull_outline_body: np.ndarray, distance_m: float,
                  bearing_deg: float, half_length_m: float = 50.0) -> np.ndarray:
    """A berth line typed in from the bow: ``distance_m`` from the hull's foremost point, in
    the direction ``bearing_deg`` relative to the ship's head (0 ahead, 90 starboard, -90
    port); the line runs across that direction."""
    outline = np.asarray(hull_outline_body, dtype=float)[:, :2]
    bow_body = outline[np.argmax(outline[:, 0])]
    yaw = float(state.euler[2])
    bow = np.asarray(state.position_ned, dtype=float)[:2] + heading_rotation(yaw) @ bow_body
    az = yaw + np.radians(bearing_deg)
    normal = np.array([np.cos(az), np.sin(az)])
    foot = bow + distance_m * normal
    along = np.array([-normal[1], normal[0]])
    return np.array([foot - half_length_m * along, foot + half_length_m * along])


class Berth:
    """The berth line of a session (``line`` may be None)."""

    def __init__(self, rec: Recording, projector: Projector, water_down_m: float | None,
                 origin_in_recording: Callable[[Any], np.ndarray], lock: threading.RLock
                 ) -> None:
        self.rec = rec
        self.projector = projector
        self.water_down_m = water_down_m  # None: the water level is unknown (no fallback)
        self._origin_in_recording = origin_in_recording
        self.lock = lock
        self.line: BerthLine | None = None
        if rec.hull.berth_line_ned is not None:
            self.line = BerthLine(np.asarray(rec.hull.berth_line_ned, float).reshape(2, 2),
                                  "recording", frame="recording", sigma_m=RECORDING_LINE_SIGMA_M,
                                  note=RECORDING_LINE_NOTE)

    @staticmethod
    def _check(line_ne: np.ndarray) -> np.ndarray:
        line = np.asarray(line_ne, dtype=float).reshape(2, 2)
        if not np.isfinite(line).all() or np.abs(line).max() > MAX_PLAN_M:
            raise Unprocessable(f"the berth line's points must lie within {MAX_PLAN_M:g} m of "
                                "the origin (north and east)")
        if np.linalg.norm(line[1] - line[0]) < MIN_LENGTH_M:
            raise Unprocessable(f"the berth line's two points are less than {MIN_LENGTH_M:g} m "
                                "apart")
        return line

    def _set(self, line: BerthLine, measured_at: Any | None = None) -> BerthLine:
        """Set ``line``; ``measured_at``: the fused state it was measured from (its drift)."""
        self._check(line.line_ne)
        if measured_at is not None:
            line = replace(line, drift_at_set=np.array(measured_at.position_drift_cov, float))
        with self.lock:
            self.line = line
            return line

    def set_ned(self, line_ne: np.ndarray, snap: bool = False, structure: Structure | None = None,
                state: Any | None = None) -> BerthLine:
        """Two plan points; with ``snap`` fitted to the quay face's points near them, seen from
        the fused ``state``, when the structure has enough (else as given, and the note says
        so)."""
        line = self._check(line_ne)
        if snap and structure is not None and state is not None:
            camera_ned = camera_pose(state, self.rec.calibration.camera).position_ned
            fitted = snap_to_face(line, structure, self.water_down_m, camera_ned)
            if fitted is not None:
                return self._set(fitted, state)
            return self._set(BerthLine(line, "ned", note="no converged port structure near "
                                       "the clicked line: kept as clicked"))
        return self._set(BerthLine(line, "ned"))

    def set_image(self, state: Any, points_uv: np.ndarray, structure: Structure) -> BerthLine:
        """Berth line from two clicks on the quay (coping, wall or water line) of the frame of
        ``state``: fitted to the quay face, else on the water plane (module docstring)."""
        pose = camera_pose(state, self.rec.calibration.camera)
        p = self.projector
        clicks = np.asarray(points_uv, dtype=float).reshape(2, 2)
        for u, v in clicks:
            if not (-0.5 <= u <= p.width - 0.5 and -0.5 <= v <= p.height - 0.5):
                raise Unprocessable(f"pixel ({u:g}, {v:g}) is outside the {p.width}x{p.height}"
                                    " image")
        attitude_cov = getattr(state, "attitude_cov", None)  # its σ tilts the click rays
        fitted = fit_quay_face(p, pose, clicks, structure, self.water_down_m, attitude_cov)
        if fitted is not None:
            return self._set(fitted, state)
        return self._set(water_plane_line(p, pose, clicks, self.water_down_m, attitude_cov),
                         state)

    def set_from_bow(self, state: Any, distance_m: float, bearing_deg: float) -> BerthLine:
        line = line_from_bow(state, self.rec.hull.outline_body, distance_m, bearing_deg)
        return self._set(BerthLine(line, "typed"), state)

    def nudge(self, state: Any | None, offset_m: float, rotate_deg: float) -> BerthLine:
        """Move the line ``offset_m`` away from the ship (negative: towards it) and turn it
        ``rotate_deg`` (clockwise seen from above) about its middle."""
        with self.lock:
            line = self.line
        if line is None:
            raise Unprocessable("there is no berth line to nudge: set one first")
        world = self.world(state)
        if world is None:
            raise Unprocessable("the recording's berth line is placed from the first fused "
                                "pose: nudge it once the fusion runs")
        centre = world.mean(axis=0)
        d = world[1] - world[0]
        normal = np.array([-d[1], d[0]]) / np.linalg.norm(d)
        if state is not None and np.dot(np.asarray(state.position_ned)[:2] - centre,
                                        normal) > 0:
            normal = -normal  # away from the ship
        R = heading_rotation(np.radians(rotate_deg))
        moved = (world - centre) @ R.T + centre + offset_m * normal
        return self._set(replace(line, line_ne=moved, frame="world",
                                 source=line.source if line.frame == "world" else "ned",
                                 nudged_m=line.nudged_m + offset_m,
                                 nudged_deg=line.nudged_deg + rotate_deg))

    def clear(self) -> None:
        with self.lock:
            self.line = None

    def world(self, state: Any | None) -> np.ndarray | None:
        """The line in the engine's world frame (None without a line, or for a recording's
        line before the first fused state)."""
        line = self.line
        if line is None:
            return None
        if line.frame == "world":
            return line.line_ne
        if state is None:
            return None
        return line.line_ne - self._origin_in_recording(state)[:2]

    def metrics(self, state: Any | None) -> dict[str, float | None] | None:
        """The berth geometry at ``state`` (None without a line or a state)."""
        line = self.line
        world = self.world(state)
        if line is None or world is None or state is None:
            return None
        return berth_metrics(state, self.rec.hull, world, line.sigma_m, line.sigma_deg,
                             line.drift_since(state))

    def status(self, state: Any | None, start_gpst: float, placed_by: Any | None = None
               ) -> dict[str, Any]:
        """The line with the berth geometry at ``state``; without one, the line alone, a
        recording's placed in the world by ``placed_by`` (any fused state: the origin)."""
        with self.lock:
            line = self.line
        out: dict[str, Any] = {"line_ne": None, "source": None, "method": None, "t": None,
                               "sigma_m": None, "sigma_deg": None, "support_points": 0,
                               "note": "", "nudged_m": 0.0, "nudged_deg": 0.0}
        out.update(dict.fromkeys(METRIC_KEYS))
        if line is None:
            return out
        out.update(line.describe())
        world = self.world(state if state is not None else placed_by)
        if world is not None:
            out["line_ne"] = world.round(3).tolist()
        metrics = self.metrics(state)
        if metrics is not None:
            out["t"] = float(state.time) - start_gpst
            out.update({k: _r(v) for k, v in metrics.items()})
        return out


METRIC_KEYS = ("bow_distance_m", "stern_distance_m", "bow_approach_mps", "stern_approach_mps",
               "bow_distance_sigma_m", "stern_distance_sigma_m", "bow_approach_sigma_mps",
               "stern_approach_sigma_mps", "along_berth_mps", "along_berth_sigma_mps", "angle_deg",
               "angle_sigma_deg", "time_to_contact_s", "time_to_contact_sigma_s",
               "nearest_distance_m")


def _r(x: float | None) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), 3)
