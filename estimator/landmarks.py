"""Port-structure refinement: one EKF per landmark fed with every view (seed 000).

Seed 000 estimates the joint state ``X = [x_c, x_l(1:n)]`` (sensor pose and n landmarks, full
covariance ``P = [[P_c, P_cl], [P_lc, P_l]]``) with an EKF: prediction from odometry, update
from each view of the landmarks, unknown components initialised from the first view and refined
as views accumulate (its fig. 10: landmark error falls with the number of views). Here the
sensor pose is already estimated — the fused camera pose of the error-state EKF with its
covariance — so the joint filter decouples into one small EKF per landmark:

- state: the landmark position ``x_l`` in L (NED, m) with its full 3x3 covariance ``P_l``;
- prediction: none (the port does not move);
- measurement (thesis camera model, seed 000's eq. 9–10 with a camera instead of a sonar):
  ``x' = C_L^C (x_l − p_cam)``, ``z = (x'_x / x'_z, x'_y / x'_z)`` — undistorted normalised
  image coordinates (the lens distortion is removed before, ``cv2.undistortPoints``);
- noise: the tracker's pixel noise ``(σ_px / f)² I`` plus the fused pose uncertainty carried
  through the measurement model, ``J_pose Σ_pose J_poseᵀ`` — seed 000's ``P_cl`` coupling,
  approximated per view (the pose errors are not re-estimated here);
- update: iterated EKF (Gauss–Newton on the prior and the view, a couple of iterations) in
  Joseph form, χ²-gated against the prior; a landmark rejected ``max_strikes`` views running
  is dropped (it is re-seeded from the VO's current point the next time it is seen).

Initialisation: from the VO point (triangulated by the VO, carried into L with the fusion's
scale and drift estimates) with an anisotropic prior — a monocular point is far less certain
along its viewing ray than across it (the thesis notes large errors along the viewing
direction), so ``P_l`` starts as ``σ_ray`` along the ray and ``σ_lat`` across it. Views from a
moving camera then pin the depth down by triangulation with the metric fused poses, which is
what "refined as the views accumulate" means here.

The pose error of the fusion is slowly varying, not white: treating it as independent per view
would let ``P_l`` shrink below what the camera positions themselves are known to. ``points``
therefore reports ``P_l`` plus the camera-position covariance of the landmark's last view (a
floor). The views of one landmark are views of one tracked corner, whose error they share (the
same template aligned again and again, a little off each time): however many views, ``P_l``
is never taken below what two views, the first and the last, of a corner ``corner_bias_px``
off would leave along the ray (``corner_bias``; in ``best`` and in the reporting test). On
the camera yardstick's seeds the converged points with the most views were the ones beyond
2σ without it: 1.5-2.5 % of the range off under σ of 0.4 %.

The decoupled EKFs cannot see that the fused attitude's error is common to all landmarks of a
view and wanders over seconds (the GNSS compass' heading corrections). ``ViewWindow`` restores
that coupling over the last ~45 s: the views' attitudes and the landmarks are solved jointly
(camera centres held at the fused positions). Where it has a landmark, its position is the
one reported (``best``); the EKF still decides whether a landmark is reportable.

Reporting (``classify``, ``points``): a landmark is reported once it has the views, the
parallax (σ along its last ray within a fraction of the range) and views that agree (mean NIS),
and lies above the water plane when that is known; one that fails the agreement or the water
test is rejected (water patterns, reflections, mistracks); the rest are still converging.

Everything is vectorised over the landmarks of a frame (a few hundred: well under a
millisecond).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from .frames import skew
from .workers import Pending, worker


@dataclass
class LandmarkParams:
    # View noise of the decoupled EKFs (full-size px): the corner noise and some of the pose
    # error they cannot model (``JointParams.pixel_sigma_px`` is the corner noise alone).
    pixel_sigma_px: float = 2.0
    min_views: int = 5  # views before a refined landmark replaces the raw point
    gate_probability: float = 0.999  # χ² gate (2 dof) of a view against the prior
    max_strikes: int = 3  # gated views running before the landmark is dropped (re-seeded)
    ray_sigma_fraction: float = 0.25  # prior σ along the viewing ray, fraction of the range
    # A tracked corner's error that all its views share (the same template, aligned again
    # and again): it does not average away with the number of views, so a landmark is never
    # surer along its ray than two views (its first and last) of a corner this far off, px.
    # The template-aligned front end's corner noise (``JointParams.pixel_sigma_px``).
    corner_bias_px: float = 1.0
    lateral_sigma_px: float = 2.0  # prior σ across the ray, pixels at the landmark's range
    min_sigma_m: float = 0.05  # floor of both prior σ
    iterations: int = 1  # Gauss–Newton iterations (1: the plain EKF of seed 000; more
    # iterations — an iterated EKF — were less consistent on the constructed cases)
    min_depth_m: float = 0.3  # a landmark closer than this in front of the camera is not updated
    # ... nor one farther than this: there the fused attitude's noise (a few hundredths of a
    # degree, varying over seconds) is a fake parallax larger than the true one, and the VO's
    # own triangulation (its relative poses) does better. None: no limit.
    max_depth_m: float | None = 60.0
    # Reported (``classify``, ``points``) only when the σ along the last viewing ray is below
    # this fraction of the range (the views had enough parallax) ...
    max_relative_sigma: float = 0.05
    # ... the views agree with the estimate (mean normalised innovation² of the accepted
    # views below this: a water pattern drifting with the waves, a corner made by two
    # surfaces at different depths or a track sliding along an edge do not) ...
    max_mean_nis: float = 3.0
    # ... and the point is above the water plane (NED down of the water surface in L; None:
    # unknown) by at least this much: reflections and water patterns lie on or below it.
    water_down_m: float | None = None
    water_margin_m: float = 0.05
    # Joint refinement over the last views (``ViewWindow``; None: off). Reported positions
    # of reportable landmarks come from it once it has them.
    joint: JointParams | None = field(default_factory=lambda: JointParams())


@dataclass
class JointParams:
    """The sliding window of ``ViewWindow``."""

    span_s: float = 45.0  # views kept (a landmark's life near the quay is 10–40 s)
    view_interval_s: float = 0.5  # a view kept at most this often
    solve_interval_s: float = 1.0  # a solve at most this often
    pixel_sigma_px: float = 1.0  # tracked corner noise (the template-aligned front end)
    iterations: int = 3  # alternations (points | rotations) per solve, warm-started
    land_after_calls: int = 3  # a solve posed at one frame lands this many frames later
    min_views: int = 5  # views a landmark needs in the window
    huber_px: float = 3.0  # residuals beyond this are down-weighted in the rotations
    min_view_landmarks: int = 20  # a view with fewer keeps its fused attitude


@dataclass
class LandmarkUpdate:
    """What one ``update`` did (counts over the observed ids)."""

    observed: int  # ids given
    unknown: int  # ids without a landmark (not seeded)
    updated: int  # views accepted
    gated: int  # views rejected by the χ² gate
    dropped: int  # landmarks dropped after max_strikes gated views running


def converged(sigma_m: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """Mask of the structure points whose σ is within the reporting fraction of their range
    (``LandmarkParams.max_relative_sigma``): trusted; the others are still converging."""
    return np.asarray(sigma_m, float) <= LandmarkParams.max_relative_sigma * np.asarray(
        range_m, float)


def sigma_along_ray(x: np.ndarray, P: np.ndarray, camera_position_ned: np.ndarray
                    ) -> np.ndarray:
    """(N,) σ (m) of points ``x`` (N,3) with covariances ``P`` (N,3,3) along their viewing
    rays from ``camera_position_ned`` (N,3): where a monocular point errs, and what a
    distance along the ray reads. NaN where the camera is not known."""
    d = np.asarray(x, float).reshape(-1, 3) - np.asarray(camera_position_ned, float)
    u = d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
    return np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", u, P, u), 0.0))


def camera_pose_covariance(position_cov: np.ndarray, attitude_cov: np.ndarray,
                           lever_level: np.ndarray,
                           cross_cov: np.ndarray | None = None) -> np.ndarray:
    """6x6 covariance of (camera position, attitude small angles in L) from the body-origin
    position and attitude covariances of the fused state.

    The camera sits at ``r + C l`` (``lever_level = C l``); with the EKF's convention
    ``Ĉ = (I + [e×]) C`` its position error is ``δr − [c×] e``. ``cross_cov`` is the 3x3
    position–attitude block ``E[δr eᵀ]`` when known (the EKF has it, ``FusedState`` not)."""
    Pr = np.asarray(position_cov, float)
    Pe = np.asarray(attitude_cov, float)
    Pre = np.zeros((3, 3)) if cross_cov is None else np.asarray(cross_cov, float)
    A = -skew(np.asarray(lever_level, float))
    pos = Pr + A @ Pre.T + Pre @ A.T + A @ Pe @ A.T
    pe = Pre + A @ Pe
    out = np.zeros((6, 6))
    out[:3, :3] = 0.5 * (pos + pos.T)
    out[:3, 3:] = pe
    out[3:, :3] = pe.T
    out[3:, 3:] = Pe
    return out


def ray_prior(xyz: np.ndarray, camera_position_ned: np.ndarray, focal_px: float,
              params: LandmarkParams, sigma_m: np.ndarray | None = None) -> np.ndarray:
    """(N,3,3) anisotropic prior covariance of points seen from ``camera_position_ned``:
    ``σ_ray`` along the viewing ray, ``σ_lat`` across it (``sigma_m``, an isotropic σ of the
    point such as the VO mapping's, is added in quadrature to both)."""
    d = np.asarray(xyz, float).reshape(-1, 3) - np.asarray(camera_position_ned, float)
    rng = np.maximum(np.linalg.norm(d, axis=1), 1e-6)
    u = d / rng[:, None]
    extra = np.zeros(len(d)) if sigma_m is None else np.asarray(sigma_m, float).reshape(-1)
    s_ray = np.maximum(params.ray_sigma_fraction * rng, params.min_sigma_m)
    s_lat = np.maximum(params.lateral_sigma_px / focal_px * rng, params.min_sigma_m)
    v_ray = s_ray**2 + extra**2
    v_lat = s_lat**2 + extra**2
    uu = u[:, :, None] * u[:, None, :]
    return v_lat[:, None, None] * np.eye(3) + (v_ray - v_lat)[:, None, None] * uu


@dataclass
class _View:
    time: float
    C_level_to_camera: np.ndarray  # the fused attitude (the prior)
    C_solved: np.ndarray  # the joint solution's so far (the next solve starts from it)
    attitude_info: np.ndarray  # inverse covariance of the fused attitude, camera axes
    camera_position_ned: np.ndarray
    ids: np.ndarray
    xy: np.ndarray  # undistorted normalised
    rotation_var: float = math.inf  # variance per axis of C_solved (rad², unsolved: none)


@dataclass(frozen=True)
class SolvedViews:
    """The views of a ``ViewWindow`` as of its last solve (a copy): what a point that is
    not a landmark but was seen in the same frames needs to be triangulated with the solved
    attitudes — a designated target, tracked on its own (``estimator.tracking``)."""

    time: np.ndarray  # (N,) view times
    C_level_to_camera: np.ndarray  # (N,3,3) the solved attitudes
    camera_position_ned: np.ndarray  # (N,3)
    rotation_var: np.ndarray  # (N,) what is left of each attitude's uncertainty (rad²)

    def __len__(self) -> int:
        return len(self.time)

    def at(self, times: np.ndarray) -> np.ndarray:
        """Index of the view at each of ``times`` (within 1 ms), -1 where there is none or
        it has not been solved yet."""
        times = np.asarray(times, float).reshape(-1)
        if not len(self.time):
            return np.full(len(times), -1, np.int64)
        k = np.searchsorted(self.time, times)
        lo, hi = np.clip(k - 1, 0, len(self.time) - 1), np.clip(k, 0, len(self.time) - 1)
        k = np.where(np.abs(self.time[lo] - times) <= np.abs(self.time[hi] - times), lo, hi)
        ok = (np.abs(self.time[k] - times) < 1e-3) & np.isfinite(self.rotation_var[k])
        return np.where(ok, k, -1)


def triangulate_point(C_level_to_camera: np.ndarray, camera_position_ned: np.ndarray,
                      xy: np.ndarray, ray_var: np.ndarray, x_prior: np.ndarray,
                      info_prior: np.ndarray, iterations: int = 3, gate: float = 13.8,
                      chunk: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One point from its views — attitudes (M,3,3), camera centres (M,3), undistorted
    normalised ``xy`` (M,2), each ray's angular variance ``ray_var`` (M,) — in the order
    they are trusted (a tracked point's: nearest the click first), and a prior
    (``x_prior``, inverse covariance ``info_prior``).

    Only the rays that agree on a point along the prior's long axis are taken, and the prior
    is widened to that point when it disagrees (``_consensus_on_prior_axis``). They are
    taken ``chunk`` at a time, each gated against the point so far (the prior for the first
    chunk): its distance from the ray against the ray's noise and the point's covariance
    (χ², 2 dof, 99.9 %). A track that slipped onto another feature at its far end would pull
    the point if taken at once; here its rays are left out, and so is everything after a
    chunk mostly rejected (the track is not trusted past where it disagrees). Returns
    (position, inverse covariance, mask of the rays used)."""
    C = np.asarray(C_level_to_camera, float).reshape(-1, 3, 3)
    o = np.asarray(camera_position_ned, float).reshape(-1, 3)
    xy = np.asarray(xy, float).reshape(-1, 2)
    ray_var = np.asarray(ray_var, float).reshape(-1)
    x0 = np.asarray(x_prior, float).reshape(1, 3)
    info0 = np.asarray(info_prior, float).reshape(1, 3, 3)
    valid = np.isfinite(xy).all(axis=1) & np.isfinite(ray_var) & np.isfinite(C).all(axis=(1, 2))
    rays = np.einsum("nji,nj->ni", np.nan_to_num(C), np.column_stack([np.nan_to_num(xy),
                                                                      np.ones(len(xy))]))
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    agree, consensus, prior_agrees = _consensus_on_prior_axis(x0[0], info0[0], rays, o,
                                                              ray_var, valid)
    valid &= agree
    if not prior_agrees:  # the prior widened to take in the point its views agree on
        gap = consensus - x0[0]
        info0 = np.linalg.inv(np.linalg.inv(info0[0]) + np.outer(gap, gap))[None]
    used = np.zeros(len(xy), bool)
    X, A = x0, info0
    for start in range(0, len(xy), chunk):
        idx = np.arange(start, min(start + chunk, len(xy)))
        idx = idx[valid[idx]]
        if not len(idx):
            continue
        # The first chunk is gated against the prior: rays that cross near their cameras
        # (a track that jumped between look-alikes) would otherwise "triangulate" there.
        ok = _ray_chi2(X[0], np.linalg.inv(A[0]), rays[idx], o[idx], ray_var[idx]) <= gate
        if 2 * ok.sum() < len(idx):
            break
        idx = idx[ok]
        used[idx] = True
        n = int(used.sum())
        point_of = np.zeros(n, np.int64)
        for _ in range(iterations):  # the rays' range weights follow the estimate
            X, A = _triangulate_rays(C[used], o[used], np.arange(n), point_of,
                                     _Groups(point_of, 1), xy[used], X, 1.0 / ray_var[used],
                                     x0, info0)
    return X[0], A[0], used


def common_rotation_jacobian(C_level_to_camera: np.ndarray, camera_position_ned: np.ndarray,
                             xy: np.ndarray, ray_var: np.ndarray, X: np.ndarray,
                             x_prior: np.ndarray, info_prior: np.ndarray, step: float = 1e-3
                             ) -> np.ndarray:
    """d(point)/d(e): how the point triangulated from these views (``triangulate_point``'s
    used ones) moves when all their attitudes share a small-angle error ``e`` (in L,
    ``Ĉ = (I + [e×]) C`` as the EKF has it). The structure window keeps the fused common
    rotation, so the fused attitude's error is common to every view: no number of views
    averages it out, and ``J P_e Jᵀ`` belongs in the point's covariance."""
    C = np.asarray(C_level_to_camera, float).reshape(-1, 3, 3)
    J = np.zeros((3, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = step
        J[:, k] = (_retriangulated(C @ (np.eye(3) - skew(e)), camera_position_ned, xy, ray_var,
                                   X, x_prior, info_prior) - X) / step
    return J


def common_drift_jacobian(C_level_to_camera: np.ndarray, camera_position_ned: np.ndarray,
                          xy: np.ndarray, ray_var: np.ndarray, X: np.ndarray,
                          x_prior: np.ndarray, info_prior: np.ndarray, dt: np.ndarray,
                          on: str = "pixels", step: float = 1e-4) -> np.ndarray:
    """d(point)/d(w): how the point triangulated from one tracked pixel's views moves when
    their errors drift at a common rate ``w`` from a reference view: view k off by
    ``w dt[k]``, on its ``"pixels"`` (normalised image units per second, (3,2): an image
    tracker's template sliding as the target grows or shrinks) or on its camera
    ``"centres"`` (m/s, (3,3): the fused position's slow error). Such errors grow with the
    views' distance in time from the reference, where the parallax is: no number of views
    averages them out, and ``J Q Jᵀ`` (Q: the rate's covariance) belongs in the point's
    covariance."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    centres = np.asarray(camera_position_ned, float).reshape(-1, 3)
    dt = np.asarray(dt, float).reshape(-1, 1)
    dims = {"pixels": 2, "centres": 3}[on]
    J = np.zeros((3, dims))
    for k in range(dims):
        w = np.zeros(dims)
        w[k] = step
        moved_xy, moved_c = (xy + dt * w, centres) if on == "pixels" else (xy, centres + dt * w)
        J[:, k] = (_retriangulated(C_level_to_camera, moved_c, moved_xy, ray_var, X, x_prior,
                                   info_prior) - X) / step
    return J


def excess_disagreement(x_a: np.ndarray, P_a: np.ndarray, x_b: np.ndarray, P_b: np.ndarray
                        ) -> np.ndarray:
    """(n,n): the part of two estimates' disagreement their covariances do not explain,
    along the line between them — ``max(0, |d|² − uᵀ(P_a + P_b)u) u uᵀ`` with ``d = x_a −
    x_b``, ``u = d/|d|`` (a method-of-moments estimate of the error neither covariance
    knows). Zero when they agree within their σ. Two halves of one track's views that
    disagree so show an error common to each half's views: a slid template."""
    d = np.asarray(x_a, float).reshape(-1) - np.asarray(x_b, float).reshape(-1)
    n = float(np.linalg.norm(d))
    if not np.isfinite(n) or n == 0.0:
        return np.zeros((len(d), len(d)))
    u = d / n
    extra = n * n - float(u @ (np.asarray(P_a, float) + np.asarray(P_b, float)) @ u)
    return max(extra, 0.0) * np.outer(u, u)


def split_disagreement(C_level_to_camera: np.ndarray, camera_position_ned: np.ndarray,
                       xy: np.ndarray, ray_var: np.ndarray, x_prior: np.ndarray,
                       info_prior: np.ndarray, a: np.ndarray, b: np.ndarray,
                       min_views: int = 3) -> np.ndarray:
    """(3,3): ``excess_disagreement`` of one point triangulated (``triangulate_point``)
    from the views ``a`` and from the views ``b`` (indexes, each in the order trusted);
    zero unless each side gives ``min_views``."""
    halves = []
    for r in (np.asarray(a, int), np.asarray(b, int)):
        if len(r) < min_views:
            return np.zeros((3, 3))
        X, info, used = triangulate_point(C_level_to_camera[r], camera_position_ned[r], xy[r],
                                          ray_var[r], x_prior, info_prior)
        if used.sum() < min_views or not np.isfinite(X).all():
            return np.zeros((3, 3))
        halves.append((X, np.linalg.inv(info)))
    return excess_disagreement(*halves[0], *halves[1])


def _retriangulated(C_level_to_camera: np.ndarray, camera_position_ned: np.ndarray,
                    xy: np.ndarray, ray_var: np.ndarray, X: np.ndarray, x_prior: np.ndarray,
                    info_prior: np.ndarray, iterations: int = 3) -> np.ndarray:
    """The point of these views (all used) from ``X`` on: the common-error Jacobians'
    perturbed solve."""
    C = np.asarray(C_level_to_camera, float).reshape(-1, 3, 3)
    n = len(C)
    point_of = np.zeros(n, np.int64)
    x0 = np.asarray(x_prior, float).reshape(1, 3)
    info0 = np.asarray(info_prior, float).reshape(1, 3, 3)
    Xk = np.asarray(X, float).reshape(1, 3)
    for _ in range(iterations):
        Xk, _ = _triangulate_rays(C, camera_position_ned, np.arange(n), point_of,
                                  _Groups(point_of, 1), xy, Xk, 1.0 / ray_var, x0, info0)
    return Xk[0]


def _consensus_on_prior_axis(x0: np.ndarray, info0: np.ndarray, rays: np.ndarray,
                             centres: np.ndarray, ray_var: np.ndarray, valid: np.ndarray,
                             steps: int = 241, limit: float = 4.0
                             ) -> tuple[np.ndarray, np.ndarray, bool]:
    """The rays that agree on one point of the prior's long axis (a click's ray). Points of
    that axis from a fifth to four times the prior's range are tried; the one where the
    rays' squared angular residuals over their variance — and the prior's own, counted as
    one more view — capped at ``limit`` sum least is the consensus (MSAC); a ray agrees when
    its residual there is within the cap. Returns (mask of the agreeing rays, the consensus
    point, whether the prior agrees with it).

    A stretch of a track that slid over a moored boat's edge and back disagrees with the
    views before and after it, however gradually it slid (gated one chunk at a time, in
    trust order, its first rays would pull the point instead); a click's point taken from
    the facade behind a ladder disagrees with the ladder's views."""
    P0 = np.linalg.inv(info0)
    lam, vec = np.linalg.eigh(P0)
    u, sigma = vec[:, -1], float(np.sqrt(max(lam[-1], 1e-12)))
    first = centres[int(np.argmax(valid))] if valid.any() else x0 - u
    if (x0 - first) @ u < 0.0:
        u = -u  # away from the cameras
    r0 = float(np.linalg.norm(x0 - first))
    s = r0 * (np.unique(np.append(np.geomspace(0.2, 4.0, steps), 1.0)) - 1.0)
    X = x0 + s[:, None] * u  # (G,3) candidate points
    d = X[:, None, :] - centres[None]  # (G,n,3)
    along = np.einsum("gni,ni->gn", d, rays)
    cos2 = along**2 / np.maximum(np.sum(d**2, axis=2), 1e-12)
    chi2 = np.where(along > 0.0, (1.0 - cos2) / ray_var, np.inf)
    prior = (s / sigma) ** 2
    cost = np.where(valid, np.minimum(chi2, limit), 0.0).sum(axis=1) + np.minimum(prior, limit)
    best = int(np.argmin(cost))
    return chi2[best] <= limit, X[best], bool(prior[best] <= limit)


def _ray_chi2(X: np.ndarray, P: np.ndarray, rays: np.ndarray, centres: np.ndarray,
              ray_var: np.ndarray) -> np.ndarray:
    """Squared normalised distance of point ``X`` (covariance ``P``) from each ray (unit
    ``rays`` from ``centres``, angular variance ``ray_var``): the offset across the ray
    against the ray's noise at that range plus the point's covariance across it."""
    d = X - centres
    helper = np.where(np.abs(rays[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(rays, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    E = np.stack([e1, np.cross(rays, e1)], axis=1)  # (n,2,3): the plane across the ray
    r = np.einsum("nij,nj->ni", E, d)
    S = np.einsum("nij,jk,nlk->nil", E, P, E) \
        + (ray_var * np.sum(d**2, axis=1))[:, None, None] * np.eye(2)
    return np.einsum("ni,nij,nj->n", r, _inv2(S), r)


class ViewWindow:
    """Joint refinement of the last views' attitudes and the landmarks they see.

    Seed 000 estimates the sensor pose and the landmarks in one filter, so the landmarks
    correct the pose as much as the pose places them. The per-landmark EKFs of ``LandmarkMap``
    drop that coupling, and they meet a hard limit. The fused heading wanders by a few
    hundredths of a degree over seconds, since the GNSS compass corrects it once per epoch.
    Between two views of a landmark this is a fake parallax, which puts quay points 20–30 m
    away off by decimetres. The window restores the coupling over its span:

    - the camera centres are held at the fused positions (millimetres);
    - each view's attitude may move about its fused value (prior: the fused covariance);
    - the landmarks are free.

    Many landmarks seen from each view then fix the views' relative attitudes. The fused
    priors hold their common rotation, so nothing drifts from window to window.

    The solve alternates two steps, each small and vectorised:
    - each landmark is triangulated from its rays (least squares on the ray distances,
      weighted by 1/range², i.e. angular errors);
    - each view's rotation is solved from its landmarks and its prior (Gauss–Newton on the
      reprojection, Huber-weighted)."""

    def __init__(self, focal_px: float, params: JointParams) -> None:
        self.focal = float(focal_px)
        self.params = params
        self.views: list[_View] = []
        self._last_solve = -math.inf
        self._job: Pending | None = None  # the solve under way in the worker (``step``)
        self._calls = 0  # ``step`` calls since it started

    def add(self, t: float, C_level_to_camera: np.ndarray, camera_position_ned: np.ndarray,
            attitude_cov: np.ndarray | None, ids: np.ndarray, xy: np.ndarray) -> None:
        """Keep this view if the last kept one is ``view_interval_s`` old; forget views older
        than ``span_s``. ``attitude_cov``: the fused attitude's covariance (small angles in L;
        None: exact), the prior of the view's rotation."""
        p = self.params
        if self.views and t - self.views[-1].time < p.view_interval_s:
            return
        if self.views and t < self.views[-1].time:
            self.views = []  # time went back (a new replay): start again
        C = np.asarray(C_level_to_camera, float)
        if attitude_cov is None:
            info = np.eye(3) * 1e16  # an exact attitude stays
        else:
            info = np.linalg.inv(C @ np.asarray(attitude_cov, float) @ C.T
                                 + np.eye(3) * 1e-16)
        self.views.append(_View(float(t), C.copy(), C.copy(), info,
                                np.asarray(camera_position_ned, float).copy(),
                                np.asarray(ids, np.int64).copy(),
                                np.asarray(xy, float).reshape(-1, 2).copy()))
        self.views = [v for v in self.views if t - v.time <= p.span_s]

    def solved(self) -> SolvedViews:
        """The views as of the last solve (``SolvedViews``; a view added since has no
        rotation variance yet and is not used)."""
        v = self.views
        return SolvedViews(np.array([x.time for x in v], float).reshape(-1),
                           np.array([x.C_solved for x in v], float).reshape(-1, 3, 3),
                           np.array([x.camera_position_ned for x in v], float).reshape(-1, 3),
                           np.array([x.rotation_var for x in v], float).reshape(-1))

    def due(self, t: float) -> bool:
        return t - self._last_solve >= self.params.solve_interval_s and len(self.views) >= 3

    def step(self, t: float, priors: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """One frame's turn: a solve is posed when one is due and runs in a worker thread
        (``estimator.workers``) beside the next frames, so that no frame carries it (a live
        frame has 100 ms). Returns the solution (``_JointSolve.result``) at the
        ``JointParams.land_after_calls``-th call after it was posed, None otherwise.
        The solve works on the views as they were when it was posed; the result is always
        the same for a given recording, whatever the machine."""
        if self._job is not None:
            self._calls += 1
            if self._calls < self.params.land_after_calls:
                return None
            solved = self._job.result().apply()
            self._job = None
            return solved
        if not self.due(t):
            return None
        self._last_solve = float(t)
        job = _JointSolve.start(list(self.views), priors, self.params, self.focal)
        if job is None:  # nothing to solve for
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))
        self._job = Pending(worker("landmark-window").submit(job.solve, self.params.iterations))
        self._calls = 0
        return None


@dataclass
class _JointSolve:
    """A joint solve (``ViewWindow.step``): posed from the views, then solved on its own
    plain arrays (``solve``, in a worker thread) and applied to the views when it lands. An
    engine copied in the middle of one (a replay's checkpoint) goes on exactly like the
    original.

    Warm start: the alternation converges slowly along the coupled directions (a rotation of
    the views against a shift of the points), so each solve goes on from the last one's
    rotations."""

    views: list[_View]  # as they were at the start: views come and go while it runs
    ids: np.ndarray  # the landmarks with ``min_views`` views in the window
    view_of: np.ndarray  # per observation
    point_of: np.ndarray
    xy: np.ndarray
    by_point: _Groups
    by_view: _Groups
    centre: np.ndarray  # per view
    prior: np.ndarray
    prior_info: np.ndarray
    few: np.ndarray  # views seeing too few landmarks: they keep their fused attitude
    x_prior: np.ndarray  # per landmark (``priors``)
    info_prior: np.ndarray
    sigma: float  # pixel σ, normalised
    focal: float  # px
    huber_px: float
    C: np.ndarray  # the views' rotations so far
    X: np.ndarray  # the landmarks so far
    H: np.ndarray  # the rotations' normal matrices
    done: int = 0  # alternations made
    rotation_var: np.ndarray | None = None  # per view, once solved
    result: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # ids, X, P once solved

    @staticmethod
    def start(views: list[_View], priors: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
              p: JointParams, focal: float) -> _JointSolve | None:
        """The solve of ``views``; None when no landmark has ``min_views`` views.
        ``priors(ids)``: each landmark's prior (position, inverse covariance; zero where
        none) — the same the landmark EKF started from, so a point with little parallax in
        the window stays near it."""
        if len(views) < 3:
            return None
        view_of = np.concatenate([np.full(len(v.ids), k) for k, v in enumerate(views)])
        ids_all = np.concatenate([v.ids for v in views])
        xy = np.concatenate([v.xy for v in views])
        ids, point_of, counts = np.unique(ids_all, return_inverse=True, return_counts=True)
        keep = counts[point_of] >= p.min_views
        if not keep.any():
            return None
        ids, point_of = np.unique(ids_all[keep], return_inverse=True)
        view_of, xy = view_of[keep], xy[keep]
        x_prior, info_prior = priors(ids)
        C = np.array([v.C_solved for v in views])
        return _JointSolve(
            views, ids, view_of, point_of, xy, _Groups(point_of, len(ids)),
            _Groups(view_of, len(views)), np.array([v.camera_position_ned for v in views]),
            np.array([v.C_level_to_camera for v in views]),
            np.array([v.attitude_info for v in views]),
            # A view's rotation is only as good as the landmarks it sees.
            np.bincount(view_of, minlength=len(views)) < p.min_view_landmarks,
            x_prior, info_prior, p.pixel_sigma_px / focal, focal, p.huber_px, C, x_prior,
            np.zeros((len(C), 3, 3)))

    def alternate(self) -> None:
        """One alternation: the landmarks from the rotations, then the rotations."""
        self.X, _A = _triangulate_rays(self.C, self.centre, self.view_of, self.point_of,
                                       self.by_point, self.xy, self.X, 1.0 / self.sigma**2,
                                       self.x_prior, self.info_prior)
        self.C, self.H = _solve_rotations(self.C, self.prior, self.prior_info, self.centre,
                                          self.X, self.view_of, self.point_of, self.by_view,
                                          self.xy, self.sigma, self.focal, self.huber_px)
        self.C[self.few] = self.prior[self.few]
        self.H[self.few] = self.prior_info[self.few]
        self.done += 1

    def solve(self, iterations: int) -> _JointSolve:
        """The alternations and the landmarks' final triangulation (``result``), on the
        job's own arrays alone: it may run in a worker while the views change."""
        for _ in range(iterations):
            self.alternate()
        # Each ray's angular variance: the pixel noise plus what is left of its view's
        # rotation uncertainty (small with many landmarks, the fused one with few).
        self.rotation_var = np.trace(np.linalg.inv(self.H), axis1=1, axis2=2) / 3.0
        X, A = _triangulate_rays(self.C, self.centre, self.view_of, self.point_of,
                                 self.by_point, self.xy, self.X,
                                 1.0 / (self.sigma**2 + self.rotation_var[self.view_of]),
                                 self.x_prior, self.info_prior)
        self.result = (self.ids, X, np.linalg.inv(A + 1e-9 * np.eye(3)))
        return self

    def apply(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The views take their solved rotations and rotation variances; returns (ids,
        positions (N,3), covariances (N,3,3)) of the landmarks (``solve`` done)."""
        for v, c, var in zip(self.views, self.C, self.rotation_var, strict=True):
            v.C_solved, v.rotation_var = c, float(var)
        return self.result


class _Groups:
    """Sums of per-observation values by group (landmark or view)."""

    def __init__(self, group: np.ndarray, n: int) -> None:
        self.group = np.asarray(group, np.intp)
        self.n = int(n)

    def sum(self, values: np.ndarray) -> np.ndarray:
        # One bincount per component: a single pass each, no sorting or copying of the rows.
        values = np.asarray(values, float)
        flat = values.reshape(len(values), int(np.prod(values.shape[1:])))
        out = np.empty((self.n, flat.shape[1]))
        for k in range(flat.shape[1]):
            out[:, k] = np.bincount(self.group, weights=flat[:, k], minlength=self.n)
        return out.reshape(self.n, *values.shape[1:])


def _triangulate_rays(C: np.ndarray, centre: np.ndarray, view_of: np.ndarray,
                      point_of: np.ndarray, by_point: _Groups, xy: np.ndarray, X: np.ndarray,
                      ray_info: np.ndarray | float, x_prior: np.ndarray,
                      info_prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points from their rays and their priors (``x_prior``, inverse covariances
    ``info_prior``): least squares on the ray distances, each ray weighted by ``ray_info``
    (its inverse angular variance) / range² at the estimate ``X`` (the distance across a ray
    is the angle times the range). Returns the points and their inverse covariances
    Σ w (I − u uᵀ) + prior."""
    rays = np.einsum("nji,nj->ni", C[view_of], np.column_stack([xy, np.ones(len(xy))]))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    o = centre[view_of]
    w = ray_info / np.maximum(np.linalg.norm(X[point_of] - o, axis=1), 1.0) ** 2
    # Σ w (I − u uᵀ) and Σ w (I − u uᵀ) o by point: Σ w, the six of Σ w u uᵀ and three more
    wu = w[:, None] * rays
    sums = by_point.sum(np.column_stack([
        w, *(wu[:, i] * rays[:, j] for i, j in _PAIRS),
        w[:, None] * o - wu * np.einsum("ni,ni->n", rays, o)[:, None]]))
    A = sums[:, 0, None, None] * np.eye(3) - sums[:, 1:7][:, _SYMMETRIC] + info_prior
    b = sums[:, 7:] + (info_prior @ x_prior[..., None])[..., 0]
    return np.linalg.solve(A + 1e-9 * np.eye(3), b[..., None])[..., 0], A


# A symmetric 3x3 matrix from its six distinct entries (``_PAIRS``): sums of outer products
# by group need only those.
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_SYMMETRIC = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])


def _solve_rotations(C: np.ndarray, prior: np.ndarray, prior_info: np.ndarray,
                     centre: np.ndarray, X: np.ndarray, view_of: np.ndarray,
                     point_of: np.ndarray, by_view: _Groups, xy: np.ndarray, sigma: float,
                     focal: float, huber_px: float) -> tuple[np.ndarray, np.ndarray]:
    """One Gauss–Newton step of every view's rotation (``C' = exp([φ×]) C``, φ in camera
    axes, small) on the reprojection of its landmarks and its prior (the fused attitude,
    inverse covariance ``prior_info``). Returns the rotations and their normal matrices."""
    xc = np.einsum("nij,nj->ni", C[view_of], X[point_of] - centre[view_of])
    z = np.maximum(xc[:, 2], 1e-6)
    h = xc[:, :2] / z[:, None]
    r = (xy - h) / sigma
    # The projection's Jacobian Jc (rows (1/z, 0, −h_x/z), (0, 1/z, −h_y/z)) times −[xc×]:
    # row k is xc × Jc_k.
    zero, inv_z = np.zeros_like(z), 1.0 / z
    J0 = np.cross(xc, np.column_stack([inv_z, zero, -h[:, 0] * inv_z])) / sigma
    J1 = np.cross(xc, np.column_stack([zero, inv_z, -h[:, 1] * inv_z])) / sigma
    w = 1.0 / np.maximum(1.0, np.linalg.norm(r, axis=1) * sigma * focal / huber_px)
    w[xc[:, 2] <= 0.3] = 0.0
    w0, w1 = w[:, None] * J0, w[:, None] * J1
    sums = by_view.sum(np.column_stack([*(w0[:, i] * J0[:, j] + w1[:, i] * J1[:, j]
                                          for i, j in _PAIRS),
                                        w0 * r[:, :1] + w1 * r[:, 1:]]))
    H, g = sums[:, :6][:, _SYMMETRIC], sums[:, 6:]  # Σ w (J0 J0ᵀ + J1 J1ᵀ), Σ w Jᵀ r
    # The prior pulls φ towards the (small) rotation from C to its fused value.
    D = prior @ C.transpose(0, 2, 1)
    to_prior = 0.5 * np.stack([D[:, 2, 1] - D[:, 1, 2], D[:, 0, 2] - D[:, 2, 0],
                               D[:, 1, 0] - D[:, 0, 1]], axis=1)
    H += prior_info
    g += (prior_info @ to_prior[..., None])[..., 0]
    S = _skew_batch(np.linalg.solve(H, g[..., None])[..., 0])
    return (np.eye(3) + S + 0.5 * S @ S) @ C, H  # exp([φ×]) to 2nd order (φ ≲ 1e-3)


class LandmarkMap:
    """The landmark EKFs of the port structure, kept by the VO's stable point ids."""

    def __init__(self, focal_px: float, params: LandmarkParams | None = None) -> None:
        self.focal = float(focal_px)
        self.params = params or LandmarkParams()
        self.gate = float(chi2.ppf(self.params.gate_probability, 2))  # χ² of a view, 2 dof
        self.ids = np.zeros(0, np.int64)  # row → id
        self.x = np.zeros((0, 3))
        self.P = np.zeros((0, 3, 3))
        self.views = np.zeros(0, np.int64)  # accepted views
        self.strikes = np.zeros(0, np.int64)  # gated views running
        self.alive = np.zeros(0, bool)
        self.last_time = np.zeros(0)
        self.floor = np.zeros((0, 3, 3))  # camera-position covariance of the last view
        self.last_camera = np.zeros((0, 3))  # camera centre of the last accepted view
        self.first_camera = np.zeros((0, 3))  # and of the first
        self.nis = np.zeros(0)  # sum of the normalised innovations² of the accepted views
        # The joint refinement's estimate (NaN until the window has solved for it).
        self.x_joint = np.zeros((0, 3))
        self.P_joint = np.zeros((0, 3, 3))
        self.x_seed = np.zeros((0, 3))  # the prior each landmark started from
        self.info_seed = np.zeros((0, 3, 3))
        self.window = None if self.params.joint is None else ViewWindow(self.focal,
                                                                        self.params.joint)
        self._sorted = np.zeros(0, np.int64)  # ids sorted, and their rows, for look-ups
        self._sorted_rows = np.zeros(0, np.int64)
        self.stats = {"updated": 0, "gated": 0, "dropped": 0, "seeded": 0}

    def __len__(self) -> int:
        return int(self.alive.sum())

    # ------------------------------------------------------------------------ look-ups

    def lookup(self, ids: np.ndarray) -> np.ndarray:
        """Row of each id (alive or not), -1 when the id was never seeded."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        if len(self._sorted) == 0 or len(ids) == 0:
            return np.full(len(ids), -1, np.int64)
        pos = np.clip(np.searchsorted(self._sorted, ids), 0, len(self._sorted) - 1)
        return np.where(self._sorted[pos] == ids, self._sorted_rows[pos], -1)

    def view_counts(self, ids: np.ndarray) -> np.ndarray:
        """Accepted views of each id (0 when unknown or dropped)."""
        rows = self.lookup(ids)
        ok = rows >= 0
        out = np.zeros(len(rows), np.int64)
        out[ok] = np.where(self.alive[rows[ok]], self.views[rows[ok]], 0)
        return out

    def known(self, ids: np.ndarray) -> np.ndarray:
        """Mask of the ids with a live landmark."""
        rows = self.lookup(ids)
        ok = rows >= 0
        out = np.zeros(len(rows), bool)
        out[ok] = self.alive[rows[ok]]
        return out

    # ----------------------------------------------------------------------- seeding

    def seed(self, ids: np.ndarray, xyz: np.ndarray, cov: np.ndarray, time: float = 0.0) -> int:
        """Start landmarks ``ids`` at ``xyz`` (N,3) with covariance ``cov`` (N,3,3); ids with
        a live landmark are left alone, dropped ones start again. Returns how many started."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        if len(ids) == 0:
            return 0
        xyz = np.asarray(xyz, float).reshape(-1, 3)
        cov = np.asarray(cov, float).reshape(-1, 3, 3)
        ids, first = np.unique(ids, return_index=True)
        xyz, cov = xyz[first], cov[first]
        rows = self.lookup(ids)
        ok = np.isfinite(xyz).all(axis=1) & np.isfinite(cov).all(axis=(1, 2))
        revive = ok & (rows >= 0)
        revive[revive] = ~self.alive[rows[revive]]
        new = ok & (rows < 0)
        r = rows[revive]
        self.x[r], self.P[r] = xyz[revive], cov[revive]
        self.x_seed[r], self.info_seed[r] = xyz[revive], np.linalg.inv(cov[revive])
        self.views[r] = 0
        self.strikes[r] = 0
        self.alive[r] = True
        self.last_time[r] = time
        self.floor[r] = 0.0
        self.last_camera[r] = np.nan
        self.first_camera[r] = np.nan
        self.nis[r] = 0.0
        self.x_joint[r] = np.nan
        n_new = int(new.sum())
        if n_new:
            self.ids = np.concatenate([self.ids, ids[new]])
            self.x = np.concatenate([self.x, xyz[new]])
            self.P = np.concatenate([self.P, cov[new]])
            self.x_seed = np.concatenate([self.x_seed, xyz[new]])
            self.info_seed = np.concatenate([self.info_seed, np.linalg.inv(cov[new])])
            self.views = np.concatenate([self.views, np.zeros(n_new, np.int64)])
            self.strikes = np.concatenate([self.strikes, np.zeros(n_new, np.int64)])
            self.alive = np.concatenate([self.alive, np.ones(n_new, bool)])
            self.last_time = np.concatenate([self.last_time, np.full(n_new, float(time))])
            self.floor = np.concatenate([self.floor, np.zeros((n_new, 3, 3))])
            self.last_camera = np.concatenate([self.last_camera, np.full((n_new, 3), np.nan)])
            self.first_camera = np.concatenate([self.first_camera, np.full((n_new, 3), np.nan)])
            self.nis = np.concatenate([self.nis, np.zeros(n_new)])
            self.x_joint = np.concatenate([self.x_joint, np.full((n_new, 3), np.nan)])
            self.P_joint = np.concatenate([self.P_joint, np.zeros((n_new, 3, 3))])
            order = np.argsort(self.ids, kind="stable")
            self._sorted, self._sorted_rows = self.ids[order], order.astype(np.int64)
        n = int(revive.sum()) + n_new
        self.stats["seeded"] += n
        return n

    def seed_from_view(self, ids: np.ndarray, xyz: np.ndarray, camera_position_ned: np.ndarray,
                       sigma_m: np.ndarray | None = None, time: float = 0.0) -> int:
        """``seed`` with the anisotropic ray prior (``ray_prior``) of points seen from
        ``camera_position_ned`` — the VO's points, uncertain mostly along their ray."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        if len(ids) == 0:
            return 0
        cov = ray_prior(xyz, camera_position_ned, self.focal, self.params, sigma_m)
        return self.seed(ids, xyz, cov, time)

    # ------------------------------------------------------------------------ update

    def update(self, t: float, C_level_to_camera: np.ndarray, camera_position_ned: np.ndarray,
               pose_cov: np.ndarray | None, ids: np.ndarray, xy: np.ndarray,
               busy: bool = False) -> LandmarkUpdate:
        """One view: landmarks ``ids`` seen at undistorted normalised image coordinates ``xy``
        (N,2) by the camera at ``camera_position_ned`` with attitude ``C_level_to_camera``.
        ``pose_cov``: 6x6 covariance of (camera position, attitude small angles in L)
        (``camera_pose_covariance``), None for an exactly known pose. ``busy``: this frame
        already carries a heavy step (the VO's keyframe bundle adjustment): the joint
        window's solve waits for the next one."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        xy = np.asarray(xy, float).reshape(-1, 2)
        rows = self.lookup(ids)
        ok = rows >= 0
        ok[ok] = self.alive[rows[ok]]
        ok &= np.isfinite(xy).all(axis=1)
        out = LandmarkUpdate(observed=len(ids), unknown=int((~ok).sum()), updated=0, gated=0,
                             dropped=0)  # (views outside the depth limits: neither)
        if not ok.any():
            return out
        rows, z_meas = rows[ok], xy[ok]
        # One view per landmark and frame (a duplicated id keeps its first).
        rows, first = np.unique(rows, return_index=True)
        z_meas = z_meas[first]
        C = np.asarray(C_level_to_camera, float)
        p = np.asarray(camera_position_ned, float)
        x, P_new, d2, front = self._filter(rows, z_meas, C, p, pose_cov)
        accept = front & (d2 <= self.gate)
        gated = front & ~accept
        a = rows[accept]
        self.first_camera[a[self.views[a] == 0]] = p
        self.x[a] = x[accept]
        self.P[a] = P_new[accept]
        self.views[a] += 1
        self.nis[a] += d2[accept]
        self.strikes[a] = 0
        self.last_time[a] = float(t)
        self.last_camera[a] = p
        if pose_cov is not None:
            self.floor[a] = np.asarray(pose_cov, float)[:3, :3]
        g = rows[gated]
        self.strikes[g] += 1
        drop = g[self.strikes[g] >= self.params.max_strikes]
        self.alive[drop] = False
        out.updated, out.gated, out.dropped = int(accept.sum()), int(gated.sum()), len(drop)
        self.stats["updated"] += out.updated
        self.stats["gated"] += out.gated
        self.stats["dropped"] += out.dropped
        if self.window is not None:
            self._to_window(t, C, p, pose_cov, rows, z_meas, busy)
        return out

    def _filter(self, rows: np.ndarray, z_meas: np.ndarray, C: np.ndarray, p: np.ndarray,
                pose_cov: np.ndarray | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The (iterated) EKF update of landmark ``rows`` with one view each: (positions,
        Joseph-form covariances, normalised innovation², in front within the depth limits)."""
        X0, P0 = self.x[rows], self.P[rows]
        n = len(rows)
        R_pix = (self.params.pixel_sigma_px / self.focal) ** 2 * np.eye(2)
        x = X0.copy()
        R = K = H = None
        front = np.ones(n, bool)
        d2 = np.zeros(n)
        for it in range(max(1, self.params.iterations)):
            d = x - p
            xc = d @ C.T
            zc = xc[:, 2]
            if it == 0:
                front = zc > self.params.min_depth_m
                if self.params.max_depth_m is not None:
                    front &= zc < self.params.max_depth_m
            zc = np.where(zc > 1e-6, zc, 1e-6)
            h = xc[:, :2] / zc[:, None]
            Jc = np.zeros((n, 2, 3))  # d z / d x' (camera coordinates)
            Jc[:, 0, 0] = Jc[:, 1, 1] = 1.0 / zc
            Jc[:, :, 2] = -h / zc[:, None]
            H = Jc @ C  # d z / d x_l
            if it == 0:
                R = np.broadcast_to(R_pix, (n, 2, 2)).copy()
                if pose_cov is not None:
                    # x' = C (I − [e×]) (x_l − p − δp) ≈ x' − C δp + C [d×] e
                    Jp = np.concatenate([-H, Jc @ (C @ _skew_batch(d))], axis=2)  # (n,2,6)
                    R += Jp @ np.asarray(pose_cov, float) @ Jp.transpose(0, 2, 1)
            PHt = P0 @ H.transpose(0, 2, 1)
            S = H @ PHt + R
            Si = _inv2(S)
            K = PHt @ Si
            # Iterated EKF: linearised about x, the innovation carries the prior's offset.
            r = z_meas - h - np.einsum("nij,nj->ni", H, X0 - x)
            if it == 0:
                nu = z_meas - h
                d2 = np.einsum("ni,nij,nj->n", nu, Si, nu)
                front &= np.isfinite(d2)
            x = X0 + np.einsum("nij,nj->ni", K, r)
        IKH = np.eye(3) - K @ H
        P_new = IKH @ P0 @ IKH.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)
        return x, 0.5 * (P_new + P_new.transpose(0, 2, 1)), d2, front

    def _to_window(self, t: float, C: np.ndarray, p: np.ndarray, pose_cov: np.ndarray | None,
                   rows: np.ndarray, z_meas: np.ndarray, busy: bool) -> None:
        """The view (of the landmarks still alive) into the joint window; its solution, when
        one is due, becomes the landmarks' joint estimates."""
        live = self.alive[rows]
        att = None if pose_cov is None else np.asarray(pose_cov, float)[3:, 3:]
        self.window.add(t, C, p, att, self.ids[rows[live]], z_meas[live])
        solved = None if busy else self.window.step(t, self._seed_prior)
        if solved is not None:
            j_ids, X, P = solved
            j_rows = self.lookup(j_ids)
            have = j_rows >= 0
            self.x_joint[j_rows[have]] = X[have]
            self.P_joint[j_rows[have]] = P[have]

    def _seed_prior(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The prior each of landmarks ``ids`` was seeded with (position, inverse covariance;
        zero for an id without a landmark — the window only holds ids the map gave it)."""
        rows = self.lookup(ids)
        have = rows >= 0
        x = np.zeros((len(ids), 3))
        info = np.zeros((len(ids), 3, 3))
        x[have], info[have] = self.x_seed[rows[have]], self.info_seed[rows[have]]
        return x, info

    def best(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions and covariances of landmark rows: the joint refinement's where it has
        one, else the landmark EKF's (its covariance with the camera-position floor)."""
        rows = np.asarray(rows, np.int64).reshape(-1)
        x, P = self.x[rows].copy(), self.P[rows] + self.floor[rows]
        joint = np.isfinite(self.x_joint[rows]).all(axis=1)
        x[joint] = self.x_joint[rows[joint]]
        P[joint] = self.P_joint[rows[joint]] + self.floor[rows[joint]]
        return x, P + self.corner_bias(rows, x)

    def corner_bias(self, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(N,3,3) covariance along the last viewing ray of landmarks ``rows`` at ``x`` from
        a corner error their views share (``LandmarkParams.corner_bias_px``): what two views,
        the first and the last, of a corner that far off would leave, whatever the views in
        between. Zero before a landmark has two viewpoints."""
        rows = np.asarray(rows, np.int64).reshape(-1)
        x = np.asarray(x, float).reshape(-1, 3)
        a, b = x - self.first_camera[rows], x - self.last_camera[rows]
        ra, rb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
        out = np.zeros((len(rows), 3, 3))
        ok = np.isfinite(ra) & np.isfinite(rb) & (ra > 0) & (rb > 0)
        if not ok.any():
            return out
        u = b[ok] / rb[ok, None]
        sin = np.linalg.norm(np.cross(a[ok] / ra[ok, None], u), axis=1)
        s = rb[ok] * math.sqrt(2.0) * self.params.corner_bias_px / self.focal \
            / np.maximum(sin, 1e-3)
        out[ok] = (s**2)[:, None, None] * np.einsum("ni,nj->nij", u, u)
        return out

    # ------------------------------------------------------------------------ output

    def _verdicts(self, rows: np.ndarray, min_views: int | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """(reportable, rejected) masks of landmark rows. Reportable: alive with
        ``min_views`` views (default ``params.min_views``), views that agree (mean NIS at
        most ``max_mean_nis``), above the water plane when it is known, σ along the last
        viewing ray at most ``max_relative_sigma`` of the range. Rejected: dropped, or with
        the views but disagreeing or below the water. Neither: still converging."""
        prm = self.params
        m = prm.min_views if min_views is None else int(min_views)
        rows = np.asarray(rows, np.int64).reshape(-1)
        views = self.views[rows]
        settled = self.alive[rows] & (views >= m)
        agree = self.nis[rows] / (2.0 * np.maximum(views, 1)) <= prm.max_mean_nis
        if prm.water_down_m is not None:
            agree &= self.x[rows, 2] <= prm.water_down_m - prm.water_margin_m
        x, cam = self.x[rows], self.last_camera[rows]
        s_ray = sigma_along_ray(x, self.P[rows] + self.corner_bias(rows, x), cam)
        rng = np.maximum(np.linalg.norm(x - cam, axis=1), 1e-9)
        parallax = ~np.isfinite(cam).all(axis=1) | (s_ray <= prm.max_relative_sigma * rng)
        return settled & agree & parallax, ~self.alive[rows] | (settled & ~agree)

    def classify(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows (-1: no landmark), reportable, rejected) of the ids (``_verdicts``)."""
        rows = self.lookup(ids)
        good = np.zeros(len(rows), bool)
        bad = np.zeros(len(rows), bool)
        have = rows >= 0
        good[have], bad[have] = self._verdicts(rows[have])
        return rows, good, bad

    def points(self, min_views: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, positions (N,3), covariances (N,3,3)) of the reportable landmarks
        (``_verdicts``); the covariance includes the camera-position floor (see the module
        docstring)."""
        sel = np.flatnonzero(self.alive)
        sel = sel[self._verdicts(sel, min_views)[0]]
        return self.ids[sel].copy(), *self.best(sel)


def _skew_batch(v: np.ndarray) -> np.ndarray:
    """(N,3,3) cross-product matrices of the rows of ``v``."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def _inv2(S: np.ndarray) -> np.ndarray:
    """Inverses of (N,2,2) matrices (NaN where singular)."""
    a, b, c, d = S[:, 0, 0], S[:, 0, 1], S[:, 1, 0], S[:, 1, 1]
    det = a * d - b * c
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.stack([np.stack([d, -b], axis=1), np.stack([-c, a], axis=1)], axis=1)
        return inv / det[:, None, None]


def triangulate_rays(origins: np.ndarray, directions: np.ndarray
                     ) -> tuple[np.ndarray, float]:
    """Least-squares point closest to rays (origins (M,3), unit directions (M,3)) and the
    largest angle (rad) between the rays (the parallax that constrains its depth)."""
    o = np.asarray(origins, float).reshape(-1, 3)
    u = np.asarray(directions, float).reshape(-1, 3)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for oi, ui in zip(o, u, strict=True):
        M = np.eye(3) - np.outer(ui, ui)
        A += M
        b += M @ oi
    X = np.linalg.lstsq(A, b, rcond=None)[0]
    cosines = np.clip(u @ u.T, -1.0, 1.0)
    return X, float(math.acos(float(cosines.min())))
