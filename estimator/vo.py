"""Visual odometry block (thesis 5.1.1, fig. 17; ``METHOD.md``).

Monocular, causal, frame by frame: ORB corners are detected at keyframes and followed by
pyramidal Lucas–Kanade with a forward–backward check, each result then aligned on the track's
template under an affine warp (no drift as the scene zooms; cuts tracks on the changing
water, ``align_affine``); the first map comes from the essential
matrix (5-point + RANSAC) between a reference frame and a later frame with enough parallax,
later frames are located by PnP + RANSAC on the map points, new points are triangulated at
keyframes and a local bundle adjustment refines the last keyframes and their points. RANSAC
(E, PnP) and the triangulation / BA residual checks drop points that do not move rigidly with
the port (water, other boats). There is no loop closure (a berthing path does not revisit).

Initialisation is the delicate part: a quay tens of metres ahead seen while moving towards it
gives little parallax, and the two-view problem then has several solutions of nearly equal
epipolar cost (rotation traded against sideways translation, the translation direction off by
tens of degrees) between which RANSAC picks at random, helped by water texture drifting along
the epipolar lines. Once the map is built on a wrong one, bundle adjustment stays in that
basin. Hence: tracks must be epipolar inliers over several frame pairs since the reference;
several two-view geometries are scored by how well their map explains every frame since the
reference (located by PnP); two consecutive attempts must agree; and the located frames in
between join the first bundle adjustment as keyframes.

Conventions (``estimator.frames``): camera C right-down-forward; the world frame W of a segment
is the camera frame of its first keyframe (C0), the reference frame the initialisation started
from (``VoOutput.world_time``, earlier than the segment's first pose). A pose maps
``x_C = C_world_to_camera @ x_W + t_C``. ``C_world_to_camera`` is the thesis' ``C_W^C``, from
which the fusion forms the VO relative attitude ``Θ: C_B0^L = Ĉ_B^L · C_C^B · C_W^C · C_B0^W``;
``t_C`` is its ``t^C`` and the camera centre in W, ``-C_W^C.T @ t^C = -C_C^W · t^C``, is the
bracket of the thesis' ``d``. Positions are scale-free: the first baseline (reference frame →
the frame at which the VO initialised, both keyframes) has length 1.

Image points are handled as undistorted normalised coordinates ``xy`` (``x/z, y/z`` in C); pixel
thresholds are converted with the mean focal length.

A camera wider than ``VoParams.max_working_width`` (the thesis' 1920×1200) is tracked on its
image averaged down by 2, 4, … until it fits: the VO is that of a smaller camera of the same
field of view (``working_camera``), its pixel thresholds those of the working image; only its
outputs' pixels are full-size. Tracking at 960×600 already beats the thesis' figures, and each
halving divides the per-frame image work by four.

When tracking is lost (too few PnP inliers) the map is dropped and a new world is initialised;
``segment`` then changes so the fusion can reset its VO states (attitude drift, scale, drift of
``d``) instead of reading a jump of the trajectory.
"""

from __future__ import annotations

import time as _time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import cv2
import numpy as np

from estimator.frames import rotvec_to_dcm, skew
from estimator.records import CameraCalibration, mean_focal
from estimator.workers import Pending, worker

STAGES = ("detect", "track", "pose", "triangulate", "ba")


def _timed_bundle_adjust(*args: object) -> tuple[tuple[np.ndarray, ...], float]:
    """``bundle_adjust`` and the seconds it took (in whichever thread it ran)."""
    t0 = _time.perf_counter()
    return bundle_adjust(*args), _time.perf_counter() - t0  # type: ignore[arg-type]


class _FrontEnd(NamedTuple):
    """A frame's tracks as the front end followed them (``VisualOdometry._front_end``): the
    found pixels, which are kept, and the rows whose template warp moved with their warps."""

    uv: np.ndarray
    ok: np.ndarray
    warp_rows: np.ndarray
    warps: np.ndarray


class _BaProblem(NamedTuple):
    """A local BA as ``_ba_problem`` posed it: the keyframes whose poses it refines (by
    ``bundle_adjust``'s camera index), the map ids of its points, whether it is the
    segment's early one (gauge reset), and ``bundle_adjust``'s arguments."""

    keyframes: list
    point_ids: np.ndarray
    early: bool
    args: tuple

    @property
    def point_index(self) -> np.ndarray:
        """Each observation's point (an index into ``point_ids``)."""
        return self.args[4]


@dataclass
class VoParams:
    """Tuning of the VO block. Pixel values refer to the working image (``working_camera``)."""

    max_working_width: int = 1280  # wider images are halved until they fit (px)
    n_features: int = 500  # live tracks wanted; ORB tops them up at keyframes
    orb_fast_threshold: int = 10  # FAST threshold of the ORB detector (grey levels)
    orb_levels: int = 3  # ORB pyramid levels (few: corners are only seeds for LK)
    min_feature_distance_px: float = 20.0  # one new corner per cell of this size, none near tracks
    lk_window: int = 21  # LK window side (px)
    lk_levels: int = 3  # LK pyramid levels above the full image
    fb_threshold_px: float = 0.7  # forward–backward LK disagreement that cuts a track
    template_check: bool = True  # align every track on its template (off: chained LK only)
    template_half_px: int = 10  # template side 2·half+1 (px), as the LK window
    template_iterations: int = 3  # Gauss–Newton steps of the affine alignment
    template_min_ncc: float = 0.9  # correlation with the template below this cuts the track
    template_max_shift_px: float = 2.0  # alignment moving the LK result farther cuts the track
    template_max_stretch: float = 1.3  # warp stretching beyond this (or 1/this): new template
    template_blur_px: float = 1.0  # Gaussian σ applied before sampling (aliasing, convergence)
    min_tracked: int = 30  # fewer PnP inliers than this: tracking lost
    init_min_parallax_px: float = 6.0  # median track displacement before E is tried
    init_min_angle_deg: float = 0.7  # median triangulation angle the first map must reach
    init_min_points: int = 60  # triangulated points the first map must have
    init_views: int = 4  # keyframes made at initialisation (reference, frames between, now)
    init_attempt_interval: int = 2  # frames between attempts (each tries several geometries)
    init_agreement_deg: float = 0.15  # consecutive attempts must agree (attitude; 10x for the
    # direction of travel) before the first map is accepted
    keyframe_parallax_px: float = 40.0  # median displacement of tracks since the last keyframe
    keyframe_baseline_ratio: float = 0.01  # baseline / median scene depth since the last keyframe
    keyframe_track_ratio: float = 0.7  # tracked map points below this share of the last keyframe
    keyframe_max_interval_s: float = 1.0  # at the latest: PnP poses drift between BAs when slow
    ransac_threshold_px: float = 1.0  # epipolar distance of the E RANSAC
    pnp_threshold_px: float = 1.5  # reprojection error of the PnP RANSAC
    min_triangulation_angle_deg: float = 0.5  # parallax a new point needs
    max_reprojection_px: float = 1.5  # reprojection error allowed for a new point
    ba_window: int = 6  # keyframes in the local BA (KF0, later the oldest two, held fixed)
    ba_huber_px: float = 1.0  # threshold of the (pseudo-)Huber BA loss
    ba_max_nfev: int = 10  # function evaluations of one BA
    ba_outlier_px: float = 2.0  # points with a larger BA residual are dropped
    # Frames a keyframe's BA (once the first keyframes are fixed) runs beside the tracking
    # before it lands, applied on that frame whatever the machine (0: at once, in line)
    ba_lag_frames: int = 3
    history_frames: int = 40  # recent frames kept to check new points against their whole track
    history_checks: int = 8  # at most this many of them checked per new point set


class WorkingImage(NamedTuple):
    """A frame as the VO reads it (``VisualOdometry.prepare``)."""

    gray: np.ndarray  # uint8, at the working level (``working_camera``)
    blurred: np.ndarray | None  # float32, for the templates (None without the template check)


@dataclass
class VoOutput:
    time: float
    status: str  # "initialising" | "tracking" | "lost"
    # Id of the world frame W of the pose. Starts at 0 and is incremented when tracking is
    # lost, so every (re)initialised W has its own id: poses of different segments are unrelated.
    segment: int
    C_world_to_camera: np.ndarray | None  # C_W^C (3x3), None unless tracking
    camera_position_world: np.ndarray | None  # camera centre in W, first baseline = 1
    n_tracked: int  # live LK tracks
    n_inliers: int  # PnP (or E at initialisation) inliers among the map points
    is_keyframe: bool
    points_world: np.ndarray  # (M,3) local map (points of the BA window and tracked), in W
    point_ids: np.ndarray  # (M,) stable ids (accumulate by id to keep points leaving the map)
    observations: tuple[np.ndarray, np.ndarray]  # (ids, (K,2) distorted pixel uv) in this frame
    # Time of the frame whose camera frame is W (the segment's reference frame). It precedes
    # the first pose of the segment by the initialisation time: the fusion takes B0 (body
    # attitude at W) at this time, not at the first "tracking" output.
    world_time: float | None = None
    # Why the frame was not used (``integrity.FrameCheck``: black, blinded, frozen), "" if it was.
    problem: str = ""
    # The id the VO gives its next new feature: a VO restarted in another world goes on from
    # it, so that no id of an earlier world is reused (``VisualOdometry.restart``).
    next_id: int = 0


# ---------------------------------------------------------------------------- geometry


def normalise_points(pts: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Undistorted pixel coordinates (N,2) → normalised coordinates x/z, y/z."""
    h = np.column_stack([pts, np.ones(len(pts))]) @ np.linalg.inv(K).T
    return h[:, :2] / h[:, 2:]


def sampson_distance(E: np.ndarray, xy0: np.ndarray, xy1: np.ndarray) -> np.ndarray:
    """First-order geometric error of ``x1ᵀ E x0 = 0`` (normalised units, signed)."""
    h0 = np.column_stack([xy0, np.ones(len(xy0))])
    h1 = np.column_stack([xy1, np.ones(len(xy1))])
    Ex0 = h0 @ E.T
    Etx1 = h1 @ E
    num = np.sum(h1 * Ex0, axis=1)
    den = Ex0[:, 0] ** 2 + Ex0[:, 1] ** 2 + Etx1[:, 0] ** 2 + Etx1[:, 1] ** 2
    return num / np.sqrt(np.maximum(den, 1e-30))


KEPT_INLIERS = 0.9  # share of RANSAC's inliers its pose must keep, or the refit broke down
# The world's unit is its first baseline, taken at a median parallax of 0.7° or more (the
# scene within ~80 units), and no point is triangulated under 0.5°: a point farther than this
# is one the BA has pushed out along its ray (a skyline), and it fixes no translation.
FAR_DEPTH = 1000.0


def locate(X: np.ndarray, xy: np.ndarray, threshold: float, min_points: int,
           previous: tuple[np.ndarray, np.ndarray] | None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """A tracked frame's pose from the map points ``X`` and their normalised image points
    ``xy`` (PnP + RANSAC, then Levenberg–Marquardt on the inliers): (C_W^C, t^C), the points
    in the camera, and which lie in front within ``threshold`` (normalised units); None
    when fewer than ``min_points`` do. ``previous``: the last frame's pose (C, t), or None.

    Points near infinity (a skyline BA has pushed to 10⁶ baselines) break the RANSAC two
    ways. A few of them break its own last fit of the inliers (EPnP): small boat 158 lost
    its VO at 59 s with 379 inliers, none within the threshold of the pose returned. The
    inliers are right: when the pose returned keeps fewer than ``KEPT_INLIERS`` of them
    (≥ 0.97 in a sound frame), they are refined from the last frame's pose too, and the pose
    that keeps more points is taken. When they are most of the map, a sample of them alone
    wins with any translation (80 quay points under a skyline of 300: 35 of 40 frames metres
    off): then only the points within ``FAR_DEPTH`` are sampled, and the far ones join the
    inliers afterwards (they still fix the rotation in the refinement)."""
    near = _near(X, previous)
    sample = slice(None) if near is None else near
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X[sample], xy[sample], np.eye(3), None,
                                             iterationsCount=100, reprojectionError=threshold,
                                             confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
    if not ok or inl is None or len(inl) < min_points:
        return None
    inl = inl.ravel()
    if near is not None:  # RANSAC's inliers index the near points: take the far ones in too
        inl = np.flatnonzero(_reprojected(rvec, tvec, X, xy, threshold)[3])
        if len(inl) < min_points:
            return None
    rvec, tvec = cv2.solvePnPRefineLM(X[inl], xy[inl], np.eye(3), None, rvec, tvec)
    best = _reprojected(rvec, tvec, X, xy, threshold)
    if best[3].sum() < KEPT_INLIERS * len(inl) and previous is not None:
        rvec, tvec = cv2.solvePnPRefineLM(X[inl], xy[inl], np.eye(3), None,
                                          cv2.Rodrigues(previous[0])[0],
                                          np.asarray(previous[1], float).reshape(3, 1).copy())
        other = _reprojected(rvec, tvec, X, xy, threshold)
        if other[3].sum() > best[3].sum():
            best = other
    return best if best[3].sum() >= min_points else None


def _near(X: np.ndarray, previous: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray | None:
    """Indices of the map points within ``FAR_DEPTH`` of the last frame's camera when the
    farther ones are at least half the map and at least four are not; else None."""
    if previous is None:
        return None
    z = X @ np.asarray(previous[0])[2] + np.ravel(previous[1])[2]
    near = np.flatnonzero(z < FAR_DEPTH)
    return near if 4 <= len(near) <= len(X) // 2 else None


def _reprojected(rvec: np.ndarray, tvec: np.ndarray, X: np.ndarray, xy: np.ndarray,
                 threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A PnP pose as (C_W^C, t^C), the points in the camera and which of them lie in front
    and reproject within ``threshold`` (normalised units) of ``xy``."""
    C = cv2.Rodrigues(rvec)[0]
    t = tvec.ravel()
    Xc = X @ C.T + t
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(Xc[:, :2] / Xc[:, 2:] - xy, axis=1)
    return C, t, Xc, (Xc[:, 2] > 0) & (err < threshold)


def triangulate(C0: np.ndarray, t0: np.ndarray, C1: np.ndarray, t1: np.ndarray,
                xy0: np.ndarray, xy1: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of normalised points seen from poses (C_W^C, t^C)."""
    if len(xy0) == 0:
        return np.zeros((0, 3))
    P0 = np.hstack([C0, np.reshape(t0, (3, 1))])
    P1 = np.hstack([C1, np.reshape(t1, (3, 1))])
    Xh = cv2.triangulatePoints(P0, P1, np.ascontiguousarray(xy0.T, dtype=np.float64),
                               np.ascontiguousarray(xy1.T, dtype=np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        return (Xh[:3] / Xh[3]).T


def triangulation_quality(X: np.ndarray, C0: np.ndarray, t0: np.ndarray, C1: np.ndarray,
                          t1: np.ndarray, xy0: np.ndarray, xy1: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cheirality (in front of both cameras), largest reprojection error of the two views
    (normalised units) and parallax angle (rad) of triangulated points."""
    Xc0 = X @ C0.T + t0
    Xc1 = X @ C1.T + t1
    with np.errstate(divide="ignore", invalid="ignore"):
        front = np.isfinite(X).all(axis=1) & (Xc0[:, 2] > 0) & (Xc1[:, 2] > 0)
        e0 = np.linalg.norm(Xc0[:, :2] / Xc0[:, 2:] - xy0, axis=1)
        e1 = np.linalg.norm(Xc1[:, :2] / Xc1[:, 2:] - xy1, axis=1)
        r0 = X + C0.T @ t0  # ray from centre 0 = X - (-C0ᵀ t0)
        r1 = X + C1.T @ t1
        cos = np.sum(r0 * r1, axis=1) / (np.linalg.norm(r0, axis=1) * np.linalg.norm(r1, axis=1))
    err = np.where(front, np.maximum(e0, e1), np.inf)
    angle = np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1.0, 1.0))
    return front, err, angle


def relative_pose_normalised(xy0: np.ndarray, xy1: np.ndarray, threshold: float,
                             confidence: float = 0.999
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Relative pose of view 1 w.r.t. view 0 from normalised points: ``x1 = R x0 + t``,
    |t| = 1, with the inlier mask (epipolar distance below ``threshold`` and in front of both
    cameras). None when no model is found.

    The 5-point RANSAC is OpenCV's USAC_ACCURATE variant: its local optimisation and final
    least-squares polish on all inliers matter here, where plain RANSAC returns the model of
    one minimal sample, off by degrees under a small parallax."""
    if len(xy0) < 8:
        return None
    xy0 = np.ascontiguousarray(xy0, dtype=np.float64)
    xy1 = np.ascontiguousarray(xy1, dtype=np.float64)
    E, mask = cv2.findEssentialMat(xy0, xy1, np.eye(3), method=cv2.USAC_ACCURATE, prob=confidence,
                                   threshold=threshold)
    if E is None or E.shape != (3, 3) or mask is None:
        return None
    inl = mask.ravel() > 0
    if inl.sum() < 8:
        return None
    # recoverPose picks the decomposition by cheirality (its mask also drops points farther than
    # 50 baselines, i.e. most of a distant quay, so it is not used for the inliers).
    _, R, t, _ = cv2.recoverPose(E, xy0, xy1, np.eye(3), mask=mask.copy())
    t = t.ravel() / np.linalg.norm(t)
    X = triangulate(np.eye(3), np.zeros(3), R, t, xy0, xy1)
    front, _, _ = triangulation_quality(X, np.eye(3), np.zeros(3), R, t, xy0, xy1)
    inl = (np.abs(sampson_distance(skew(t) @ R, xy0, xy1)) < threshold) & front
    return R, t, inl


def relative_pose(pts0: np.ndarray, pts1: np.ndarray, K: np.ndarray, threshold_px: float = 1.0,
                  confidence: float = 0.999
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``relative_pose_normalised`` for undistorted pixel points of a camera with intrinsics K:
    returns (C_0_to_1, unit t^C1, inlier mask) or None."""
    f = mean_focal(K)
    return relative_pose_normalised(normalise_points(pts0, K), normalise_points(pts1, K),
                                    threshold_px / f, confidence)


def umeyama_alignment(src: np.ndarray, dst: np.ndarray, with_scale: bool = True
                      ) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising ``Σ |dst - (s R src + t)|²`` (Umeyama 1991)."""
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    U, D, Vt = np.linalg.svd(xd.T @ xs / len(src))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / np.mean(np.sum(xs**2, axis=1))) if with_scale else 1.0
    return s, R, mu_d - s * R @ mu_s


# ------------------------------------------------------------------------ bundle adjustment

# A point's normal block has six distinct entries (a, b); _SYM puts them back into 3×3.
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_SYM = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])


def _inv3_sym(M: np.ndarray) -> np.ndarray:
    """Inverses of a stack (n,3,3) of symmetric positive definite blocks, by cofactors."""
    a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    d, e, f = M[:, 1, 1], M[:, 1, 2], M[:, 2, 2]
    cof = np.stack([d * f - e * e, c * e - b * f, b * e - c * d,
                    a * f - c * c, b * c - a * e, a * d - b * b], axis=1)
    det = a * cof[:, 0] + b * cof[:, 1] + c * cof[:, 2]
    return cof[:, _SYM] / det[:, None, None]


def bundle_adjust(C_world_to_camera: np.ndarray, t_camera: np.ndarray, points: np.ndarray,
                  camera_index: np.ndarray, point_index: np.ndarray, xy: np.ndarray,
                  fixed: np.ndarray, focal: float, huber_px: float = 1.0, max_nfev: int = 10,
                  ftol: float = 1e-8) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Minimise the reprojection error (pixels, pseudo-Huber loss of threshold ``huber_px``)
    over the free poses and all points.

    Poses (K,3,3)/(K,3) map W into each camera; observation o is point ``point_index[o]`` seen
    at normalised ``xy[o]`` by camera ``camera_index[o]``. A free pose is updated as
    ``C = exp([δ×]) C`` (no Rodrigues singularity whatever the attitude). Levenberg–Marquardt
    on the robust cost, its loss as iteratively reweighted least squares, each step solved
    by the Schur complement: the points' 3×3 blocks are eliminated in closed form and the
    few free poses (6 unknowns each) solved densely — the sparsity every local BA has, which
    a general sparse solver does not exploit. At most ``max_nfev`` cost evaluations; stops
    when a step lowers the cost by less than ``ftol`` of it. Returns the refined poses,
    points and the per-observation residual norm (px).
    """
    C = np.array(C_world_to_camera, float)
    t = np.array(t_camera, float)
    X = np.array(points, float)
    # Observations grouped by point: the points' sums are then contiguous (reduceat).
    order = np.argsort(np.asarray(point_index), kind="stable")
    ci, pi = np.asarray(camera_index)[order], np.asarray(point_index)[order]
    xy = np.asarray(xy, float)[order]
    free = np.flatnonzero(~np.asarray(fixed, bool))
    n_free, n_pt, n_cam = len(free), len(X), len(C)
    slot = np.full(n_cam, -1)
    slot[free] = np.arange(n_free)
    of = np.flatnonzero(slot[ci] >= 0)  # observations by free cameras
    so = slot[ci[of]]
    by_camera = [np.flatnonzero(so == k) for k in range(n_free)]
    seen = np.unique(pi)  # points without an observation keep their place
    starts = np.searchsorted(pi, seen)
    f2 = huber_px ** 2

    def project(C: np.ndarray, t: np.ndarray, X: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # every point in every camera (one product), then each observation's
        Y = (X @ C.transpose(2, 0, 1).reshape(3, 3 * n_cam)).reshape(n_pt, n_cam, 3)[pi, ci]
        Xc = Y + t[ci]
        r = focal * (Xc[:, :2] / np.maximum(Xc[:, 2:], 1e-9) - xy)
        return r, Y, Xc

    def cost(r: np.ndarray) -> float:
        return float(f2 * np.sum(np.sqrt(1.0 + r * r / f2) - 1.0))

    r, Y, Xc = project(C, t, X)
    c0, lam, nfev, done = cost(r), 1e-3, 1, False
    while nfev < max_nfev and not done:
        # Jacobians of the residuals, each row scaled by √(loss weight)
        sw = (1.0 + r * r / f2) ** -0.25
        z = np.maximum(Xc[:, 2], 1e-9)
        u, v = Xc[:, 0] / z, Xc[:, 1] / z
        A = np.zeros((len(r), 2, 3))  # d(residual)/d(Xc): rows (1, 0, −u), (0, 1, −v) · f/z
        A[:, 0, 0] = sw[:, 0] * focal / z
        A[:, 1, 1] = sw[:, 1] * focal / z
        A[:, 0, 2] = -A[:, 0, 0] * u
        A[:, 1, 2] = -A[:, 1, 1] * v
        rw = sw * r
        Cc = C[ci]
        J0 = A[:, 0, :1] * Cc[:, 0] + A[:, 0, 2:] * Cc[:, 2]  # d(residual x)/d(point)
        J1 = A[:, 1, 1:2] * Cc[:, 1] + A[:, 1, 2:] * Cc[:, 2]
        Ao = A[of]  # d Xc/dδ = −[Y×]: a row a of A gives Y × a
        Jc = np.concatenate([np.stack([np.cross(Y[of], Ao[:, 0]), np.cross(Y[of], Ao[:, 1])],
                                      axis=1), Ao], axis=2)  # (observations by free, 2, 6)
        V = np.zeros((n_pt, 6))
        V[seen] = np.add.reduceat(np.column_stack([J0[:, a] * J0[:, b] + J1[:, a] * J1[:, b]
                                                   for a, b in _PAIRS]), starts, axis=0)
        V = V[:, _SYM]
        gp = np.zeros((n_pt, 3))
        gp[seen] = np.add.reduceat(J0 * rw[:, :1] + J1 * rw[:, 1:], starts, axis=0)
        U = np.zeros((n_free, 6, 6))
        gc = np.zeros((n_free, 6))
        for k, rows in enumerate(by_camera):
            Jk = Jc[rows].reshape(-1, 6)
            U[k] = Jk.T @ Jk
            gc[k] = Jk.T @ rw[of[rows]].ravel()
        # pose-point coupling blocks, (point, 6·free, 3)
        W = np.zeros((n_pt, n_free, 6, 3))
        W[pi[of], so] = Jc[:, 0, :, None] * J0[of, None, :] + Jc[:, 1, :, None] * J1[of, None, :]
        W = W.reshape(n_pt, 6 * n_free, 3)
        dU = np.einsum("kii->ki", U)
        dV = np.einsum("pii->pi", V)
        while nfev < max_nfev:
            # Marquardt's damping, and a ridge for a depth no observation constrains
            Vi = _inv3_sym(V + (lam * dV + 1e-9 * dV.sum(1, keepdims=True) + 1e-12)[:, :, None]
                           * np.eye(3))
            WV = W @ Vi
            S = -(WV.transpose(1, 0, 2).reshape(6 * n_free, -1)
                  @ W.transpose(1, 0, 2).reshape(6 * n_free, -1).T)
            for k in range(n_free):
                S[6 * k:6 * k + 6, 6 * k:6 * k + 6] += U[k] + np.diag(lam * dU[k])
            b = (WV @ gp[:, :, None]).sum(axis=0)[:, 0] - gc.ravel()
            dc = np.linalg.lstsq(S, b, rcond=None)[0] if n_free else b
            dp = -(Vi @ (gp + W.transpose(0, 2, 1) @ dc)[:, :, None])[:, :, 0]
            Cn, tn = C.copy(), t.copy()
            for k, c in enumerate(free):
                Cn[c] = rotvec_to_dcm(dc[6 * k:6 * k + 3]) @ C[c]
                tn[c] = t[c] + dc[6 * k + 3:6 * k + 6]
            rn, Yn, Xcn = project(Cn, tn, X + dp)
            cn = cost(rn)
            nfev += 1
            if cn < c0:
                done = c0 - cn < ftol * c0
                C, t, X, r, Y, Xc, c0 = Cn, tn, X + dp, rn, Yn, Xcn, cn
                lam = max(lam / 3.0, 1e-7)
                break
            lam *= 5.0
    res = np.empty(len(r))
    res[order] = np.linalg.norm(r, axis=1)
    return C, t, X, res


def _same_pose_direction(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray],
                         p: VoParams) -> bool:
    """Two poses (C, t) relative to the same reference agree in attitude and in the direction
    of the camera centre (their scales are arbitrary)."""
    rot = np.degrees(np.linalg.norm(cv2.Rodrigues(a[0] @ b[0].T)[0]))
    ca, cb = -a[0].T @ a[1], -b[0].T @ b[1]
    cos = ca @ cb / (np.linalg.norm(ca) * np.linalg.norm(cb) + 1e-300)
    return bool(rot < p.init_agreement_deg and
                np.degrees(np.arccos(np.clip(cos, -1, 1))) < 10 * p.init_agreement_deg)


def working_level(width: int, max_width: int) -> int:
    """How many halvings bring an image ``width`` pixels wide to at most ``max_width``."""
    level = 0
    while width > max_width and width % 2 == 0:
        width //= 2
        level += 1
    return level


def working_camera(camera: CameraCalibration, level: int) -> CameraCalibration:
    """The camera whose image is ``camera``'s averaged over 2^level × 2^level pixel blocks:
    working pixel i covers full pixels s·i … s·i + s − 1, its centre at s·i + (s − 1)/2, so
    the focal length is divided by s = 2^level and the principal point moves by (s − 1)/2
    first. The distortion acts on normalised coordinates and stays."""
    if level == 0:
        return camera
    s = 2 ** level
    K = np.array(camera.K, float)
    K[:2, :2] /= s
    K[:2, 2] = (K[:2, 2] - (s - 1) / 2) / s
    return replace(camera, width=camera.width // s, height=camera.height // s, K=K)


def to_full_pixels(uv: np.ndarray, level: int) -> np.ndarray:
    """Working-image pixels (``working_camera``) to the full image's."""
    s = 2 ** level
    return s * np.asarray(uv, float) + (s - 1) / 2


def to_working_pixels(uv: np.ndarray, level: int) -> np.ndarray:
    """Full-image pixels to the working image's (``working_camera``)."""
    s = 2 ** level
    return (np.asarray(uv, float) - (s - 1) / 2) / s


# ------------------------------------------------------------------- template alignment


def sample_patches(image: np.ndarray, centres: np.ndarray, warps: np.ndarray, half: int
                   ) -> np.ndarray:
    """Patches (N, 2·half+1, 2·half+1) of ``image`` (bilinear): pixel (i, j) of patch n is the
    image at ``centres[n] + warps[n] @ (j - half, i - half)``."""
    side = 2 * half + 1
    x, y = np.meshgrid(np.arange(-half, half + 1, dtype=np.float32),
                       np.arange(-half, half + 1, dtype=np.float32))
    w = warps.reshape(-1, 4).astype(np.float32)[:, :, None, None]
    c = centres.astype(np.float32)[:, :, None, None]
    map_x = c[:, 0] + w[:, 0] * x + w[:, 1] * y
    map_y = c[:, 1] + w[:, 2] * x + w[:, 3] * y
    out = cv2.remap(image, map_x.reshape(-1, side), map_y.reshape(-1, side), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(len(centres), side, side, *image.shape[2:])


# The affine warp's parameters (centre x, y, warp 00, 01, 10, 11) each have a Jacobian of one
# gradient (x or y) times one monomial of the template pixel (1, x or y).
_GRAD_OF = np.array([0, 1, 0, 0, 1, 1])
_MONOMIAL_OF = np.array([0, 0, 1, 2, 1, 2])


def _template_grid(half: int) -> tuple[np.ndarray, np.ndarray]:
    """The template pixels' offsets (2, P) and their monomials (1, x, y) as (P, 3), float32."""
    x, y = (c.ravel() for c in np.meshgrid(np.arange(-half, half + 1, dtype=np.float32),
                                           np.arange(-half, half + 1, dtype=np.float32)))
    return np.stack([x, y]), np.stack([np.ones_like(x), x, y]).T


def template_gradients(templates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x and y gradients (N, P) of bordered templates (N, S+2, S+2) at their inner S x S
    pixels (central differences)."""
    n = len(templates)
    gx = 0.5 * (templates[:, 1:-1, 2:] - templates[:, 1:-1, :-2])
    gy = 0.5 * (templates[:, 2:, 1:-1] - templates[:, :-2, 1:-1])
    return gx.reshape(n, -1), gy.reshape(n, -1)


def take_templates(image: np.ndarray, centres: np.ndarray, half: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Templates of ``image`` (blurred, float32) around ``centres`` for ``align_affine``: the
    patches with a one-pixel border (N, S+2, S+2), normalised to zero mean and unit σ over
    their inner S x S pixels, and the inverse of each one's damped Gauss–Newton normal matrix
    (N, 6, 6). The alignment is inverse compositional (Baker & Matthews): its Jacobian is the
    template's, so the normal matrix is formed once here, not at every step of every frame."""
    n = len(centres)
    eye = np.broadcast_to(np.eye(2), (n, 2, 2))
    border = sample_patches(image, np.asarray(centres, float), eye, half + 1)
    inner = border[:, 1:-1, 1:-1]
    mean = inner.mean(axis=(1, 2), keepdims=True)
    std = np.maximum(inner.std(axis=(1, 2), keepdims=True), 1.0)
    templates = ((border - mean) / std).astype(np.float32)
    gx, gy = template_gradients(templates)
    _offsets, monomials = _template_grid(half)
    products = np.column_stack([monomials[:, i] * monomials[:, j]
                                for i in range(3) for j in range(3)])  # (P, 9)
    sums = (np.stack([gx * gx, gx * gy, gy * gy], axis=1).reshape(3 * n, -1)
            @ products).reshape(n, 3, 9)
    grad_pair = _GRAD_OF[:, None] + _GRAD_OF[None, :]  # 0: gx², 1: gx·gy, 2: gy²
    product_of = 3 * _MONOMIAL_OF[:, None] + _MONOMIAL_OF[None, :]
    H = sums[:, grad_pair, product_of].astype(float)
    # Levenberg damping, and a small pull of the warp to its start (a patch with one dominant
    # edge leaves part of it free).
    H += 0.1 * H * np.eye(6) + np.diag([1e-3, 1e-3, 1.0, 1.0, 1.0, 1.0])
    return templates, np.linalg.inv(H)


def stretches(warps: np.ndarray) -> np.ndarray:
    """Singular values (N, 2), largest first, of 2x2 ``warps`` (N, 2, 2), in closed form:
    LAPACK's batched SVD costs a tenth of a millisecond per frame for these."""
    a, b, c, d = (warps[:, i, j] for i in (0, 1) for j in (0, 1))
    # σ₁² + σ₂² = |W|²_F and σ₁ σ₂ = |det W|
    frobenius = a * a + b * b + c * c + d * d
    det = np.abs(a * d - b * c)
    spread = np.sqrt(np.maximum(frobenius * frobenius - 4.0 * det * det, 0.0))
    big = np.sqrt(0.5 * (frobenius + spread))
    small = np.sqrt(np.maximum(0.5 * (frobenius - spread), 0.0))
    return np.stack([big, small], axis=1)


def align_affine(image: np.ndarray, templates: np.ndarray, h_inv: np.ndarray,
                 centres: np.ndarray, warps: np.ndarray, iterations: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss–Newton alignment of ``templates`` (bordered and normalised, with their
    ``h_inv``: ``take_templates``) on ``image`` (float32, blurred as the templates' image was)
    under an affine warp (centre and 2x2 ``warps``, as in ``sample_patches``), started from the
    given ones; inverse compositional: each step is solved in the template's frame and the
    warp composed with its inverse. Returns the centres, the warps and the normalised
    correlation at the end."""
    n, side = len(templates), templates.shape[1] - 2
    n_px = side * side
    _offsets, monomials = _template_grid(side // 2)
    gx, gy = template_gradients(templates)
    target = templates[:, 1:-1, 1:-1].reshape(n, -1)
    # The step's right-hand side is Σ SD·r over the pixels, SD the steepest-descent images
    # (gradient x monomial) and r = (patch - mean) / std - target: Σ SD·(patch - mean) / std
    # minus the template's own share, fixed for the call.
    order = 3 * _GRAD_OF + _MONOMIAL_OF

    def sd_dot(values: np.ndarray) -> np.ndarray:
        return np.concatenate([(gx * values) @ monomials, (gy * values) @ monomials],
                              axis=1)[:, order].astype(float)

    sd_target = sd_dot(target)
    monomials_t = np.ascontiguousarray(monomials.T)
    centres, warps = centres.astype(float), warps.astype(float)
    coef = np.empty((2 * n, 3), np.float32)  # each map is a row of (centre, warp row) @ (1, x, y)
    for _ in range(max(iterations, 1)):
        coef[:n, 0], coef[n:, 0] = centres[:, 0], centres[:, 1]
        coef[:n, 1:], coef[n:, 1:] = warps[:, 0], warps[:, 1]
        maps = coef @ monomials_t
        patch = cv2.remap(image, maps[:n], maps[n:], cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)
        patch -= patch.mean(axis=1, keepdims=True)
        power = np.einsum("np,np->n", patch, patch) / n_px
        std = np.maximum(np.sqrt(power), 1.0)
        if iterations < 1:
            break
        g = sd_dot(patch) / std[:, None].astype(float) - sd_target
        step = np.einsum("nij,nj->ni", h_inv, g)
        # W(x) ← W(W_step⁻¹(x)), W_step(x) = step[:2] + (I + step[2:]) x
        a, b, c, d = 1.0 + step[:, 2], step[:, 3], step[:, 4], 1.0 + step[:, 5]
        step_inv = np.stack([d, -b, -c, a], axis=1).reshape(n, 2, 2) / (a * d - b * c)[:, None,
                                                                                        None]
        warps = warps @ step_inv
        centres = centres - (warps @ step[:, :2, None])[..., 0]
    # the mean squared residual at the last step's start: |p/σ|² - 2 p·t/σ + |t|² (p centred)
    mean_r2 = (power / std ** 2 - 2.0 * np.einsum("np,np->n", patch, target) / (n_px * std)
               + np.einsum("np,np->n", target, target) / n_px)
    ncc = 1.0 - 0.5 * mean_r2.astype(float)
    return centres, warps, ncc


def align_on_templates(image: np.ndarray, tracks: _Tracks, uv: np.ndarray, ok: np.ndarray,
                       p: VoParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Chained frame-to-frame LK drifts: each step's small error adds up, and a
    translation-only window slides across the texture as the scene zooms (the quay
    approaching), about 1 px per 100 frames — metres of depth for a distant point. So each
    LK result ``uv`` (kept where ``ok``) is refined by aligning the track's own template
    under an affine warp (scale, shear, rotation followed from frame to frame). This also
    cuts tracks whose look changed (the drifting wave patterns of the water, occlusions),
    which LK with its forward–backward check follows. Returns the refined pixels, which are
    kept, and the rows whose warp moved with their new warps (``tracks`` is not changed)."""
    rows = np.flatnonzero(ok & np.isfinite(tracks.warp[:, 0, 0]))
    if len(rows) == 0:
        return uv, ok, rows, np.zeros((0, 2, 2))
    uv, ok = uv.copy(), ok.copy()
    centre, warp, ncc = align_affine(image, tracks.template[rows], tracks.h_inv[rows],
                                     uv[rows].astype(float), tracks.warp[rows],
                                     p.template_iterations)
    stretch = stretches(warp)
    good = ((ncc >= p.template_min_ncc)
            & (np.linalg.norm(centre - uv[rows], axis=1) <= p.template_max_shift_px)
            & (stretch[:, 0] < 2.0) & (stretch[:, 1] > 0.5))  # a warp gone wild in a frame
    uv[rows[good]] = centre[good]
    ok[rows[~good]] = False
    return uv, ok, rows[good], warp[good]


# ------------------------------------------------------------------------------ LK


def _lk_forward(prev: np.ndarray, cur: np.ndarray, p0: np.ndarray, lk: dict
                ) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal LK of points ``p0`` (N,1,2) from ``prev`` to ``cur``: (p1, status)."""
    p1, status, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, None, **lk)
    return p1, status


def _lk_backward(cur: np.ndarray, prev: np.ndarray, p1: np.ndarray, p0: np.ndarray, lk: dict,
                 threshold_px: float) -> np.ndarray:
    """The forward–backward check: whether each point tracked back from ``p1`` returns
    within ``threshold_px`` of where it started. A mistrack (occlusion, water glint,
    texture-less patch such as a black frame) rarely does."""
    p0b, status, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, None, **lk)
    fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
    return (status.ravel() == 1) & (fb < threshold_px)


# ------------------------------------------------------------------------------ state


@dataclass
class _Tracks:
    """Live feature tracks (struct of arrays). A track's id is also the id of its map point."""

    id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))  # distorted px
    xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # normalised, now
    anchor_kf: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # first keyframe
    anchor_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # xy at anchor
    kf_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # xy at last keyframe
    # The track's template (grey values normalised to zero mean and unit σ, sampled around
    # the track when it got it, with a one-pixel border: ``take_templates``), its inverse
    # normal matrix, and the affine warp from template to image pixels now (NaN: no template
    # yet, or an external front end).
    template: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0), np.float32))
    h_inv: np.ndarray = field(default_factory=lambda: np.zeros((0, 6, 6)))
    warp: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))

    def __len__(self) -> int:
        return len(self.id)

    def _columns(self) -> tuple[np.ndarray, ...]:
        return (self.id, self.uv, self.xy, self.anchor_kf, self.anchor_xy, self.kf_xy,
                self.template, self.h_inv, self.warp)

    def select(self, index: np.ndarray) -> _Tracks:
        return _Tracks(*(a[index] for a in self._columns()))

    def extend(self, other: _Tracks) -> _Tracks:
        # An empty table's template column has no side yet: take the other's as it is.
        return _Tracks(*(np.concatenate([a, b]) if len(a) else b.copy() for a, b in zip(
            self._columns(), other._columns(), strict=True)))


@dataclass
class _Keyframe:
    serial: int  # index in the segment's keyframe list
    time: float
    C: np.ndarray  # C_W^C
    t: np.ndarray  # t^C
    obs_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    obs_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def centre(self) -> np.ndarray:
        return -self.C.T @ self.t

    def add(self, ids: np.ndarray, xy: np.ndarray) -> None:
        self.obs_ids = np.concatenate([self.obs_ids, ids])
        self.obs_xy = np.concatenate([self.obs_xy, xy])


@dataclass
class _Frame:
    """A recent frame: its tracks (sorted by id) and its pose once known."""

    time: float
    ids: np.ndarray
    xy: np.ndarray
    C: np.ndarray | None = None
    t: np.ndarray | None = None


class _Map:
    """Map points of the current segment, sorted by id for vectorised look-ups."""

    def __init__(self) -> None:
        self.ids = np.zeros(0, np.int64)
        self.xyz = np.zeros((0, 3))

    def __len__(self) -> int:
        return len(self.ids)

    def lookup(self, ids: np.ndarray) -> np.ndarray:
        """Row of each id, -1 when absent."""
        if len(self.ids) == 0:
            return np.full(len(ids), -1)
        pos = np.clip(np.searchsorted(self.ids, ids), 0, len(self.ids) - 1)
        return np.where(self.ids[pos] == ids, pos, -1)

    def add(self, ids: np.ndarray, xyz: np.ndarray) -> None:
        ids_all = np.concatenate([self.ids, ids])
        order = np.argsort(ids_all, kind="stable")
        self.ids, self.xyz = ids_all[order], np.concatenate([self.xyz, xyz])[order]

    def keep(self, mask: np.ndarray) -> None:
        self.ids, self.xyz = self.ids[mask], self.xyz[mask]


# ------------------------------------------------------------------------------- VO


class VisualOdometry:
    """Causal monocular VO: call ``process`` once per frame in time order."""

    def __init__(self, camera: CameraCalibration, params: VoParams | None = None) -> None:
        self.camera = camera
        self.params = params or VoParams()
        p = self.params
        self.level = working_level(int(camera.width), p.max_working_width)
        camera = working_camera(camera, self.level)
        self._K = np.asarray(camera.K, float)
        self._dist = np.asarray(camera.distortion, float).ravel()
        self._focal = camera.focal_px
        self._size = (int(camera.width), int(camera.height))
        self._orb = cv2.ORB_create(nfeatures=4 * p.n_features, scaleFactor=1.2,
                                   nlevels=p.orb_levels, edgeThreshold=16, patchSize=16,
                                   fastThreshold=p.orb_fast_threshold)
        self._lk = dict(winSize=(p.lk_window, p.lk_window), maxLevel=p.lk_levels,
                        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        self._segment = 0
        self._next_id = 0
        self._prev_gray: np.ndarray | None = None
        self._elapsed = dict.fromkeys((*STAGES, "total", "ba_solve"), 0.0)
        self._n_frames = self._n_keyframes = self._n_ba = 0
        self._new_world()

    # ---------------------------------------------------------------- public interface

    def prepare(self, image_bgr: np.ndarray) -> WorkingImage:
        """The frame as the VO reads it. Depends on the image and the parameters alone, so a
        frame reader may call it in its own thread, ahead of ``process``."""
        gray = image_bgr if image_bgr.ndim == 2 else cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY)
        if self.level:
            gray = cv2.resize(gray, self._size, interpolation=cv2.INTER_AREA)  # block means
        blurred = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), self.params.template_blur_px
                                   ) if self.params.template_check else None
        return WorkingImage(gray, blurred)

    def process(self, time: float, image_bgr: np.ndarray,
                prepared: WorkingImage | None = None,
                following: WorkingImage | None = None) -> VoOutput:
        """Track the frame taken at ``time`` and return the VO output for it (``prepared``:
        the frame's ``prepare`` when it was made ahead). ``following``: the next frame's
        ``prepare`` when it is known already (a recording): the tracks' front end into it
        (``_front_end``: LK, its check, the template alignment) starts in a worker thread as
        this frame ends, beside what the fusion does before the next frame, and is taken if
        that frame comes to ``process`` next with nothing changed in between; the outcome is
        the same either way."""
        t_start = _time.perf_counter()
        gray, blurred = prepared if prepared is not None else self.prepare(image_bgr)
        ahead, self._ahead = self._ahead, None
        if len(self._tracks) and self._prev_gray is not None:
            if ahead is not None and ahead.prev is self._prev_gray and ahead.cur is gray \
                    and ahead.tracks is self._tracks:
                front = ahead.result()
            else:
                front = self._front_end(self._prev_gray, gray, blurred, self._tracks)
            self._tracks.warp[front.warp_rows] = front.warps
            self._set_tracks(np.flatnonzero(front.ok), front.uv[front.ok])
        else:
            self._set_tracks(np.zeros(0, np.int64), np.zeros((0, 2), np.float32))
        self._prev_gray = gray
        self._elapsed["track"] += _time.perf_counter() - t_start
        out = self._step(time, lambda n: self._detect(gray, n))
        self._renew_templates(blurred)
        if following is not None and len(self._tracks):
            self._ahead = Pending(
                worker("vo-ahead").submit(self._front_end, gray, following.gray,
                                          following.blurred, self._tracks, False),
                prev=gray, cur=following.gray, tracks=self._tracks)
        self._elapsed["total"] += _time.perf_counter() - t_start
        return out

    def process_tracks(self, time: float, track_ids: np.ndarray, uv: np.ndarray) -> VoOutput:
        """Same as ``process`` with an external front end: ``uv`` (distorted pixels) of feature
        ``track_ids`` in this frame. Ids not yet known are taken as new features when the VO
        wants some (reference frame, keyframes); known ids missing from the list are lost."""
        t_start = _time.perf_counter()
        track_ids = np.asarray(track_ids, np.int64)
        uv = to_working_pixels(np.reshape(uv, (-1, 2)), self.level).astype(np.float32)
        row = {int(i): k for k, i in enumerate(self._tracks.id)}
        known = np.array([int(i) in row for i in track_ids], bool)
        self._set_tracks(np.array([row[int(i)] for i in track_ids[known]], np.int64), uv[known])
        new_ids, new_uv = track_ids[~known], uv[~known]

        def detect(n: int) -> tuple[np.ndarray, np.ndarray]:
            return new_ids[:n], new_uv[:n]

        out = self._step(time, detect)
        self._elapsed["total"] += _time.perf_counter() - t_start
        return out

    def restart(self, segment: int, next_id: int) -> None:
        """Drop the world and the tracks (the fusion found them inconsistent, ``VoCoupling``):
        the next frame is the reference of world ``segment``, its features numbered from
        ``next_id`` on. A VO made afresh and restarted so goes on exactly like the one that
        produced the outputs (the evaluation runs its VO apart, then restarts a fresh one)."""
        self._segment = int(segment)
        self._next_id = max(self._next_id, int(next_id))
        self._new_world()
        self._prev_gray = None

    @property
    def working_size(self) -> tuple[int, int]:
        """(width, height) of the image the VO tracks on (``working_camera``)."""
        return self._size

    def stats(self) -> dict:
        """Average milliseconds per frame of each stage (and of the whole ``process``) in the
        caller's thread, the average of one local BA's solve (wherever it ran), and frame /
        keyframe / BA counts."""
        n = max(self._n_frames, 1)
        out = {f"{s}_ms": 1e3 * self._elapsed[s] / n for s in (*STAGES, "total")}
        out["ba_ms_per_call"] = 1e3 * self._elapsed["ba_solve"] / max(self._n_ba, 1)
        out.update(frames=self._n_frames, keyframes=self._n_keyframes, ba_calls=self._n_ba)
        return out

    # ------------------------------------------------------------------------ front end

    def _undistort(self, uv: np.ndarray) -> np.ndarray:
        if len(uv) == 0:
            return np.zeros((0, 2))
        pts = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        return cv2.undistortPoints(pts, self._K, self._dist).reshape(-1, 2)

    def _front_end(self, prev: np.ndarray, cur: np.ndarray, blurred: np.ndarray | None,
                   tracks: _Tracks, overlap: bool = True) -> _FrontEnd:
        """The tracks followed from ``prev`` into ``cur``: pyramidal LK, its forward–backward
        check (``_lk_backward``) and the template alignment (``align_on_templates``, on
        ``blurred``). Reads ``tracks`` and changes nothing: the caller applies the result.
        ``overlap``: the check runs in a worker thread beside the alignment (OpenCV releases
        the GIL; the alignment takes the rows the check will cut too and every row is
        computed on its own, so the outcome does not depend on the overlap); without it (the
        next frame's front end made ahead in a worker, ``process``) one after the other."""
        p = self.params
        p0 = tracks.uv.reshape(-1, 1, 2).astype(np.float32)
        p1, status = _lk_forward(prev, cur, p0, self._lk)
        check = worker("vo-lk").submit(_lk_backward, cur, prev, p1, p0, self._lk,
                                       p.fb_threshold_px) if overlap else None
        uv = p1.reshape(-1, 2)
        w, h = self._size
        ok = (status.ravel() == 1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) \
            & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        rows, warps = np.zeros(0, np.int64), np.zeros((0, 2, 2))
        if p.template_check and blurred is not None:
            uv, ok, rows, warps = align_on_templates(blurred, tracks, uv, ok, p)
        back = check.result() if check is not None else \
            _lk_backward(cur, prev, p1, p0, self._lk, p.fb_threshold_px)
        return _FrontEnd(uv, ok & back, rows, warps)

    def _renew_templates(self, image: np.ndarray | None) -> None:
        """New tracks, and those whose warp stretched the template beyond
        ``template_max_stretch``, take a template from this image (blurred)."""
        tr, p = self._tracks, self.params
        if not len(tr) or not p.template_check:
            return
        stretch = stretches(np.nan_to_num(tr.warp, nan=0.0))
        renew = ((stretch[:, 0] > p.template_max_stretch)
                 | (stretch[:, 1] < 1.0 / p.template_max_stretch))
        if renew.any():
            tr.template[renew], tr.h_inv[renew] = take_templates(
                image, tr.uv[renew].astype(float), p.template_half_px)
            tr.warp[renew] = np.eye(2)

    def _detect(self, gray: np.ndarray, n_wanted: int) -> tuple[np.ndarray, np.ndarray]:
        """New ORB corners, the strongest per cell of ``min_feature_distance_px``, none in a cell
        already holding a track: spreads features over the image."""
        t0 = _time.perf_counter()
        keypoints = self._orb.detect(gray, None)
        if not keypoints or n_wanted <= 0:
            self._elapsed["detect"] += _time.perf_counter() - t0
            return np.zeros(0, np.int64), np.zeros((0, 2), np.float32)
        pts = cv2.KeyPoint_convert(keypoints).reshape(-1, 2)
        response = np.array([k.response for k in keypoints])
        cell = self.params.min_feature_distance_px
        n_cols = int(np.ceil(self._size[0] / cell)) + 1

        def cell_of(uv: np.ndarray) -> np.ndarray:
            c = np.floor(uv / cell).astype(np.int64)
            return c[:, 1] * n_cols + c[:, 0]

        order = np.argsort(-response)
        pts, cells = pts[order], cell_of(pts[order])
        free = ~np.isin(cells, cell_of(self._tracks.uv))
        pts, cells = pts[free], cells[free]
        _, first = np.unique(cells, return_index=True)  # strongest corner of each cell
        pts = pts[np.sort(first)][:n_wanted]
        ids = np.arange(self._next_id, self._next_id + len(pts), dtype=np.int64)
        self._next_id += len(pts)
        self._elapsed["detect"] += _time.perf_counter() - t0
        return ids, pts.astype(np.float32)

    def _set_tracks(self, rows: np.ndarray, uv: np.ndarray) -> None:
        """Keep the given rows of the track table with their new positions."""
        tracks = self._tracks.select(rows)
        tracks.uv = np.asarray(uv, np.float32).reshape(-1, 2)
        tracks.xy = self._undistort(tracks.uv)
        self._tracks = tracks

    def _add_tracks(self, detect: Callable, anchor_kf: int, max_new: int) -> None:
        ids, uv = detect(max_new)
        if len(ids) == 0:
            return
        xy = self._undistort(uv)
        side = 2 * self.params.template_half_px + 3  # with the border
        self._tracks = self._tracks.extend(_Tracks(
            np.asarray(ids, np.int64), np.asarray(uv, np.float32).reshape(-1, 2), xy,
            np.full(len(ids), anchor_kf, np.int64), xy.copy(), xy.copy(),
            np.zeros((len(ids), side, side), np.float32), np.zeros((len(ids), 6, 6)),
            np.full((len(ids), 2, 2), np.nan)))

    # ------------------------------------------------------------------------- back end

    def _new_world(self) -> None:
        self._tracks = _Tracks()
        self._keyframes: list[_Keyframe] = []
        self._map = _Map()
        self._reference_time: float | None = None
        self._reference_count = 0
        self._pose: tuple[np.ndarray, np.ndarray] | None = None
        self._kf_inliers = 0
        self._history: list[_Frame] = []
        self._init_previous: tuple[float, np.ndarray, np.ndarray] | None = None
        self._init_count = 0
        self._gauge = 1  # keyframe at unit distance from KF0 (the initialisation frame)
        self._pending_ba: Pending | None = None  # a BA of this world (dropped with it)
        self._ahead: Pending | None = None  # the next frame's front end, made ahead

    def _output(self, time: float, status: str, n_inliers: int = 0, is_keyframe: bool = False,
                obs_rows: np.ndarray | None = None) -> VoOutput:
        C = position = None
        if status == "tracking" and self._pose is not None:
            C = self._pose[0].copy()
            position = -C.T @ self._pose[1]
        rows = np.zeros(0, np.int64) if obs_rows is None else obs_rows
        return VoOutput(
            time=float(time), status=status, segment=self._segment, C_world_to_camera=C,
            camera_position_world=position, n_tracked=len(self._tracks), n_inliers=int(n_inliers),
            is_keyframe=is_keyframe, points_world=self._map.xyz.copy(),
            point_ids=self._map.ids.copy(),
            observations=(self._tracks.id[rows].copy(),
                          to_full_pixels(self._tracks.uv[rows], self.level)),
            world_time=self._keyframes[0].time if self._keyframes else None,
            next_id=self._next_id)

    def _step(self, time: float, detect: Callable) -> VoOutput:
        self._n_frames += 1
        self._land_ba(now=False)
        if not self._keyframes:
            out = self._initialise(time, detect)
        else:
            out = self._track(time, detect)
        self._remember(time, out.status == "tracking")
        return out

    def _remember(self, time: float, with_pose: bool) -> None:
        order = np.argsort(self._tracks.id)
        frame = _Frame(time, self._tracks.id[order], self._tracks.xy[order])
        if with_pose and self._pose is not None:
            frame.C, frame.t = self._pose
        self._history.append(frame)
        del self._history[:-self.params.history_frames]

    def _frames_between(self, t_from: float, t_to: float) -> list[_Frame]:
        """Up to ``history_checks`` remembered frames strictly between two times, spread."""
        frames = [f for f in self._history if t_from < f.time < t_to]
        n = self.params.history_checks
        if len(frames) > n:
            frames = [frames[i] for i in np.linspace(0, len(frames) - 1, n).round().astype(int)]
        return frames

    def _track_consistent(self, ids: np.ndarray, X: np.ndarray, frames: list[_Frame]
                          ) -> np.ndarray:
        """Whether points X (W) reproject onto their tracks in every given frame with a pose:
        water and boats can move along the epipolar line of two views, not of many."""
        worst = np.zeros(len(ids))
        for f in frames:
            if f.C is None or len(f.ids) == 0:
                continue
            pos = np.clip(np.searchsorted(f.ids, ids), 0, len(f.ids) - 1)
            hit = f.ids[pos] == ids
            Xc = X[hit] @ f.C.T + f.t
            with np.errstate(divide="ignore", invalid="ignore"):
                err = np.linalg.norm(Xc[:, :2] / Xc[:, 2:] - f.xy[pos[hit]], axis=1)
            err[~(Xc[:, 2] > 0)] = np.inf
            worst[hit] = np.maximum(worst[hit], err)
        return worst < 1.5 * self.params.max_reprojection_px / self._focal

    def _rigid_between(self, time: float, threshold: float) -> np.ndarray:
        """Tracks (since the reference) that are epipolar inliers of the pairs reference→m and
        m→now for frames m at a third and two thirds of the way. Water drifting along the
        epipolar lines of one pair rarely does for all, and such tracks would otherwise bend
        the weakly conditioned first two-view geometry."""
        tr = self._tracks
        keep = np.ones(len(tr), bool)
        frames = [f for f in self._history if self._reference_time < f.time < time]
        if len(frames) < 3:
            return keep
        for f in (frames[len(frames) // 3], frames[2 * len(frames) // 3]):
            pos = np.clip(np.searchsorted(f.ids, tr.id), 0, len(f.ids) - 1)
            seen = f.ids[pos] == tr.id
            xy_m = np.where(seen[:, None], f.xy[pos], np.nan)
            for a, b in ((tr.anchor_xy, xy_m), (xy_m, tr.xy)):
                m = keep & seen
                if m.sum() < self.params.init_min_points:
                    return np.zeros(len(tr), bool)
                E, mask = cv2.findEssentialMat(a[m], b[m], np.eye(3), method=cv2.USAC_ACCURATE,
                                               prob=0.999, threshold=threshold)
                if E is None or mask is None:
                    return np.zeros(len(tr), bool)
                keep[np.flatnonzero(m)[mask.ravel() == 0]] = False
            keep &= seen
        return keep

    @staticmethod
    def _lookup(frame: _Frame, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of ``ids`` in a frame's sorted ids and whether each is there."""
        if len(frame.ids) == 0:
            return np.zeros(len(ids), np.int64), np.zeros(len(ids), bool)
        pos = np.clip(np.searchsorted(frame.ids, ids), 0, len(frame.ids) - 1)
        return pos, frame.ids[pos] == ids

    def _pnp(self, X: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Pose (C_W^C, t^C) from map points and their normalised image points, or None."""
        if len(X) < self.params.min_tracked:
            return None
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X, xy, np.eye(3), None, iterationsCount=100,
            reprojectionError=self.params.pnp_threshold_px / self._focal, confidence=0.999,
            flags=cv2.SOLVEPNP_AP3P)
        if not ok or inl is None or len(inl) < self.params.min_tracked:
            return None
        inl = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(X[inl], xy[inl], np.eye(3), None, rvec, tvec)
        return cv2.Rodrigues(rvec)[0], tvec.ravel()

    def _best_first_map(self, rigid: np.ndarray, between: list[_Frame], now: _Frame,
                        threshold: float) -> tuple[dict, np.ndarray, np.ndarray] | None:
        """Choose the first two-view geometry among several (reference → a frame half-way,
        two thirds of the way, this frame) by how well its map explains ALL the frames since
        the reference (each located by PnP): truncated squared reprojection error summed over
        the rigid tracks (MSAC over time). A distant quay under small parallax leaves several
        two-view solutions of nearly equal epipolar cost; the wrong ones (translation off by
        tens of degrees) do not fit the frames in between. Returns the poses of the frames
        (by ``id``) and this frame's pose, or None."""
        p = self.params
        tr = self._tracks
        frames = [*between, now]
        tau = p.max_reprojection_px / self._focal
        candidates = [now]
        if len(between) >= 4:
            candidates += [between[len(between) // 2], between[2 * len(between) // 3]]
        rows = np.flatnonzero(rigid)
        ids = tr.id[rows]
        looks = [self._lookup(f, ids) for f in frames]
        best, best_cost = None, np.inf
        I3, z3 = np.eye(3), np.zeros(3)
        for cand in candidates:
            pos, seen = self._lookup(cand, ids)
            model = relative_pose_normalised(tr.anchor_xy[rows[seen]], cand.xy[pos[seen]],
                                             threshold)
            if model is None:
                continue
            R, t, inl = model
            sel = np.flatnonzero(seen)[inl]
            X = triangulate(I3, z3, R, t, tr.anchor_xy[rows[sel]], cand.xy[pos[sel]])
            front, err, _ = triangulation_quality(X, I3, z3, R, t, tr.anchor_xy[rows[sel]],
                                                  cand.xy[pos[sel]])
            ok = front & (err < tau)
            sel, X = sel[ok], X[ok]
            if len(sel) < p.init_min_points:
                continue
            cost, poses = 0.0, {}
            for f, (fpos, fseen) in zip(frames, looks, strict=True):
                in_map = np.zeros(len(ids), bool)
                in_map[sel] = True
                use = in_map & fseen
                pose = self._pnp(X[np.searchsorted(sel, np.flatnonzero(use))],
                                 f.xy[fpos[use]])
                if pose is None:
                    cost = np.inf
                    break
                poses[id(f)] = pose
                e = np.full(len(ids), np.inf)
                Xc = X[np.searchsorted(sel, np.flatnonzero(use))] @ pose[0].T + pose[1]
                with np.errstate(divide="ignore", invalid="ignore"):
                    e[use] = np.linalg.norm(Xc[:, :2] / Xc[:, 2:] - f.xy[fpos[use]], axis=1)
                e[use & ~(np.isfinite(e))] = np.inf
                cost += float(np.sum(np.minimum(e[fseen], tau) ** 2))
            if cost < best_cost:
                best, best_cost = (poses, *poses[id(now)]), cost
        return best

    def _lose(self, time: float, detect: Callable) -> VoOutput:
        """Tracking lost: drop the world; this frame may already serve as the new reference."""
        self._segment += 1
        self._new_world()
        self._start_reference(time, detect)
        return self._output(time, "lost")

    def _start_reference(self, time: float, detect: Callable) -> bool:
        self._tracks = _Tracks()
        self._history = []
        self._init_previous = None
        self._init_count = 0
        self._add_tracks(detect, 0, self.params.n_features)
        if len(self._tracks) < self.params.init_min_points:
            self._tracks = _Tracks()
            self._reference_time = None
            return False
        self._reference_time = time
        self._reference_count = len(self._tracks)
        return True

    def _initialise(self, time: float, detect: Callable) -> VoOutput:
        p = self.params
        tr = self._tracks
        if self._reference_time is None or len(tr) < max(p.init_min_points,
                                                         0.5 * self._reference_count):
            # No reference yet, or too many of its corners gone (turning): start again here.
            ok = self._start_reference(time, detect)
            return self._output(time, "initialising" if ok else "lost")
        t0 = _time.perf_counter()
        if np.median(np.linalg.norm(tr.xy - tr.anchor_xy, axis=1)) * self._focal < \
                p.init_min_parallax_px:
            return self._output(time, "initialising")
        self._init_count += 1
        if self._init_count % p.init_attempt_interval:
            return self._output(time, "initialising")
        thr = p.ransac_threshold_px / self._focal
        rigid = self._rigid_between(time, thr)
        if rigid.sum() < p.init_min_points:
            return self._output(time, "initialising")
        order = np.argsort(tr.id)
        now = _Frame(time, tr.id[order], tr.xy[order])
        between = self._frames_between(self._reference_time, time)
        prev = self._init_previous
        f_prev = next((f for f in self._history if prev is not None and f.time == prev[0]), None)
        if f_prev is not None and all(f is not f_prev for f in between):
            between = sorted([*between, f_prev], key=lambda f: f.time)
        best = self._best_first_map(rigid, between, now, thr)
        self._elapsed["pose"] += _time.perf_counter() - t0
        if best is None:
            self._init_previous = None
            return self._output(time, "initialising")
        poses, R, t = best
        # Accept only a geometry that the previous attempt found too (same pose of the previous
        # frame up to scale): the wrong two-view solutions come and go from frame to frame, and
        # their sideways translation even inflates the parallax that gates the initialisation.
        self._init_previous = (time, R, t)
        if f_prev is None or id(f_prev) not in poses or \
                not _same_pose_direction(poses[id(f_prev)], prev[1:], p):
            return self._output(time, "initialising")
        t1 = _time.perf_counter()
        I3, z3 = np.eye(3), np.zeros(3)
        X = triangulate(I3, z3, R, t, tr.anchor_xy, tr.xy)
        _, err, angle = triangulation_quality(X, I3, z3, R, t, tr.anchor_xy, tr.xy)
        good = rigid & (err < p.max_reprojection_px / self._focal) & \
            (angle > np.radians(p.min_triangulation_angle_deg))
        if good.sum() < p.init_min_points or \
                np.degrees(np.median(angle[good])) < p.init_min_angle_deg:
            self._elapsed["triangulate"] += _time.perf_counter() - t1
            return self._output(time, "initialising")
        # Points must follow their tracks in the frames in between too.
        for f in between:
            f.C, f.t = poses.get(id(f), (None, None))
        good[good] = self._track_consistent(tr.id[good], X[good], between)
        self._elapsed["triangulate"] += _time.perf_counter() - t1
        if good.sum() < p.init_min_points:
            for f in between:
                f.C = f.t = None
            return self._output(time, "initialising")
        return self._first_world(time, detect, R, t, X, good, rigid, between)

    def _first_world(self, time: float, detect: Callable, R: np.ndarray, t: np.ndarray,
                     X: np.ndarray, good: np.ndarray, rigid: np.ndarray,
                     between: list[_Frame]) -> VoOutput:
        """The world: reference = KF0 = W; a few located frames in between and this frame
        become keyframes too, so the first BA sees the map from several views, not two."""
        p, tr = self.params, self._tracks
        I3, z3 = np.eye(3), np.zeros(3)
        for f in self._history:
            if f.time == self._reference_time:
                f.C, f.t = I3.copy(), z3.copy()
        kf0 = _Keyframe(0, self._reference_time, I3.copy(), z3.copy())
        kf0.add(tr.id[good], tr.anchor_xy[good])
        self._keyframes = [kf0]
        located = [f for f in between if f.C is not None]
        n_mid = min(p.init_views - 2, len(located))
        for i in np.linspace(0, len(located) - 1, n_mid + 2)[1:-1].round().astype(int):
            f = located[i]
            kf = _Keyframe(len(self._keyframes), f.time, f.C, f.t)
            pos, seen = self._lookup(f, tr.id[good])
            kf.add(tr.id[good][seen], f.xy[pos[seen]])
            self._keyframes.append(kf)
        kf1 = _Keyframe(len(self._keyframes), time, R, t)
        kf1.add(tr.id[good], tr.xy[good])
        self._keyframes.append(kf1)
        self._gauge = kf1.serial
        self._n_keyframes += len(self._keyframes)
        self._map.add(tr.id[good], X[good])
        self._tracks = tr.select(np.flatnonzero(rigid))  # the others do not move with the port
        self._pose = (R, t)
        self._local_ba()
        self._pose = (kf1.C, kf1.t)
        rows = np.flatnonzero(self._map.lookup(self._tracks.id) >= 0)
        self._kf_inliers = len(rows)
        self._finish_keyframe(detect, kf1.serial)
        return self._output(time, "tracking", len(rows), True, rows)

    def _track(self, time: float, detect: Callable) -> VoOutput:
        p = self.params
        t0 = _time.perf_counter()
        tr = self._tracks
        row = self._map.lookup(tr.id)
        mapped = np.flatnonzero(row >= 0)
        if len(mapped) < p.min_tracked:
            return self._lose(time, detect)
        obj = self._map.xyz[row[mapped]]
        img = tr.xy[mapped]
        thr = p.pnp_threshold_px / self._focal
        located = locate(obj, img, thr, p.min_tracked, self._pose)
        if located is None:
            return self._lose(time, detect)
        C, t, Xc, good = located
        # Map points off their reprojection move with the water / a boat, or were mistracked.
        keep = np.ones(len(tr), bool)
        keep[mapped[~good]] = False
        self._pose = (C, t)
        self._elapsed["pose"] += _time.perf_counter() - t0

        n_inliers = int(good.sum())
        kf = self._keyframes[-1]
        depth = float(np.median(Xc[good, 2]))
        baseline = np.linalg.norm(-C.T @ t - kf.centre)
        parallax = np.median(np.linalg.norm(tr.xy - tr.kf_xy, axis=1)) * self._focal
        is_kf = (baseline > p.keyframe_baseline_ratio * depth
                 or parallax > p.keyframe_parallax_px
                 or n_inliers < p.keyframe_track_ratio * self._kf_inliers
                 or len(tr) < 0.5 * p.n_features
                 or time - kf.time > p.keyframe_max_interval_s)
        self._tracks = tr.select(np.flatnonzero(keep))
        if is_kf:
            self._make_keyframe(time, depth, detect)
        rows = np.flatnonzero(self._map.lookup(self._tracks.id) >= 0)
        if is_kf:
            self._kf_inliers = len(rows)
        return self._output(time, "tracking", n_inliers if not is_kf else len(rows), is_kf, rows)

    def _make_keyframe(self, time: float, depth: float, detect: Callable) -> None:
        p = self.params
        C, t = self._pose
        serial = len(self._keyframes)
        kf = _Keyframe(serial, time, C, t)
        tr = self._tracks
        row = self._map.lookup(tr.id)
        mapped = row >= 0
        kf.add(tr.id[mapped], tr.xy[mapped])
        self._keyframes.append(kf)
        self._n_keyframes += 1

        # New points: candidates triangulated between their first keyframe and this one.
        t0 = _time.perf_counter()
        drop = np.zeros(len(tr), bool)
        max_err = p.max_reprojection_px / self._focal
        min_angle = np.radians(p.min_triangulation_angle_deg)
        for a in np.unique(tr.anchor_kf[~mapped]):
            idx = np.flatnonzero(~mapped & (tr.anchor_kf == a))
            anchor = self._keyframes[a]
            X = triangulate(anchor.C, anchor.t, C, t, tr.anchor_xy[idx], tr.xy[idx])
            front, err, angle = triangulation_quality(X, anchor.C, anchor.t, C, t,
                                                      tr.anchor_xy[idx], tr.xy[idx])
            good = front & (err < max_err) & (angle > min_angle)
            if good.any():
                moving = ~self._track_consistent(tr.id[idx[good]], X[good],
                                                 self._frames_between(anchor.time, time))
                drop[idx[good][moving]] = True
                good[good] = ~moving
            # With a real baseline a track off its epipolar geometry is not on the rigid port.
            if np.linalg.norm(anchor.centre - kf.centre) > 0.5 * p.keyframe_baseline_ratio * depth:
                drop[idx[err > 2.0 * max_err]] = True
            if good.any():
                anchor.add(tr.id[idx[good]], tr.anchor_xy[idx[good]])
                kf.add(tr.id[idx[good]], tr.xy[idx[good]])
                self._map.add(tr.id[idx[good]], X[good])
        self._tracks = tr.select(np.flatnonzero(~drop))
        self._elapsed["triangulate"] += _time.perf_counter() - t0

        self._local_ba()
        kf = self._keyframes[-1]
        self._pose = (kf.C, kf.t)
        # The local map: points seen by the BA window or still tracked.
        seen = np.concatenate([k.obs_ids for k in self._keyframes[-p.ba_window:]]
                              + [self._tracks.id])
        self._map.keep(np.isin(self._map.ids, seen))
        self._finish_keyframe(detect, serial)

    def _finish_keyframe(self, detect: Callable, serial: int) -> None:
        """Top the tracks up with new corners anchored at this keyframe."""
        self._tracks.kf_xy = self._tracks.xy.copy()
        missing = self.params.n_features - len(self._tracks)
        if missing > 0.1 * self.params.n_features:
            self._add_tracks(detect, serial, missing)

    def _local_ba(self) -> None:
        """Bundle adjustment of the last ``ba_window`` keyframes and of the points they see.

        While the window still holds KF0 only KF0 is fixed (it is W) and the scale is reset to
        a unit first baseline afterwards: the initial two-view geometry of a distant quay seen
        under a small parallax is ill-conditioned (translation direction off by several degrees
        at equal epipolar cost), and the next keyframes resolve it. Later the oldest two
        keyframes of the window are fixed, which holds the gauge and the scale; that BA runs
        in a worker thread (``ba_lag_frames``) and lands ``_land_ba``."""
        p = self.params
        t0 = _time.perf_counter()
        self._land_ba()  # one BA at a time, in keyframe order
        problem = self._ba_problem()
        if problem is None:
            return
        if problem.early or p.ba_lag_frames <= 0:
            self._apply_ba(problem, _timed_bundle_adjust(*problem.args))
        else:
            self._pending_ba = Pending(
                worker("vo-ba").submit(_timed_bundle_adjust, *problem.args), problem=problem,
                frame=self._n_frames + p.ba_lag_frames)
        self._elapsed["ba"] += _time.perf_counter() - t0

    def _ba_problem(self) -> _BaProblem | None:
        """The local BA's unknowns and observations as of now (``_local_ba``)."""
        p = self.params
        kfs = self._keyframes
        window = kfs[-p.ba_window:]
        early = window[0].serial == 0
        free = window[1:] if early else window[2:]
        free_serials = {k.serial for k in free}
        point_ids = np.unique(np.concatenate([k.obs_ids for k in free]))
        point_ids = point_ids[self._map.lookup(point_ids) >= 0]
        if len(point_ids) == 0:
            return None
        used = kfs[-3 * p.ba_window:]
        cam_idx, pt_idx, xy = [], [], []
        for j, k in enumerate(used):
            pos = np.clip(np.searchsorted(point_ids, k.obs_ids), 0, len(point_ids) - 1)
            hit = point_ids[pos] == k.obs_ids
            cam_idx.append(np.full(hit.sum(), j))
            pt_idx.append(pos[hit])
            xy.append(k.obs_xy[hit])
        args = (np.array([k.C for k in used]), np.array([k.t for k in used]),
                self._map.xyz[self._map.lookup(point_ids)], np.concatenate(cam_idx),
                np.concatenate(pt_idx), np.concatenate(xy),
                np.array([k.serial not in free_serials for k in used]), self._focal,
                p.ba_huber_px, p.ba_max_nfev)
        return _BaProblem(used, point_ids, early, args)

    def _land_ba(self, now: bool = True) -> None:
        """Apply the BA running in the worker, if any, when its frame has come (``now``:
        whatever the frame — a new keyframe or BA needs the map refined first)."""
        pending = self._pending_ba
        if pending is None or not (now or self._n_frames >= pending.frame):
            return
        self._pending_ba = None
        t0 = _time.perf_counter()
        self._apply_ba(pending.problem, pending.result())
        self._elapsed["ba"] += _time.perf_counter() - t0

    def _apply_ba(self, problem: _BaProblem,
                  solved: tuple[tuple[np.ndarray, ...], float]) -> None:
        """The refined poses and points (``_timed_bundle_adjust``) into the keyframes and the
        map; points the BA leaves beyond ``ba_outlier_px`` dropped. Points dropped from the
        map since the BA began stay dropped."""
        (C, t, X, res), seconds = solved
        self._elapsed["ba_solve"] += seconds
        for j, k in enumerate(problem.keyframes):
            k.C, k.t = C[j], t[j]
        rows = self._map.lookup(problem.point_ids)
        self._map.xyz[rows[rows >= 0]] = X[rows >= 0]
        if problem.early:  # the segment's gauge: reference → initialisation frame = 1
            kfs = self._keyframes
            s = 1.0 / np.linalg.norm(kfs[self._gauge].centre)
            for k in kfs:
                k.t = k.t * s
            for f in self._history:
                if f.t is not None:
                    f.t = f.t * s
            self._map.xyz = self._map.xyz * s
        # A point behind a camera gets a huge residual (depth clamped), so this also culls it.
        bad_pt = np.unique(problem.point_index[res > self.params.ba_outlier_px])
        if len(bad_pt):
            bad_ids = problem.point_ids[bad_pt]
            self._map.keep(~np.isin(self._map.ids, bad_ids))
            self._tracks = self._tracks.select(np.flatnonzero(~np.isin(self._tracks.id, bad_ids)))
        self._n_ba += 1
