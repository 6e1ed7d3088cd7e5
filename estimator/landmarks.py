"""Port-structure refinement: one EKF per landmark fed with every view (seed 000, SPEC section 7).

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
floor).

Reporting (``classify``, ``points``): a landmark is reported once it has the views, the
parallax (σ along its last ray within a fraction of the range) and views that agree (mean NIS),
and lies above the water plane when that is known; one that fails the agreement or the water
test is rejected (water patterns, reflections, mistracks); the rest are still converging.

Everything is vectorised over the landmarks of a frame (a few hundred: well under a
millisecond).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from .frames import skew


@dataclass
class LandmarkParams:
    pixel_sigma_px: float = 2.0  # tracked corner noise (LK: jitter and slow slide), full-size px
    min_views: int = 5  # views before a refined landmark replaces the raw point
    gate_probability: float = 0.999  # χ² gate (2 dof) of a view against the prior
    max_strikes: int = 3  # gated views running before the landmark is dropped (re-seeded)
    ray_sigma_fraction: float = 0.25  # prior σ along the viewing ray, fraction of the range
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


@dataclass
class LandmarkUpdate:
    """What one ``update`` did (counts over the observed ids)."""

    observed: int  # ids given
    unknown: int  # ids without a landmark (not seeded)
    updated: int  # views accepted
    gated: int  # views rejected by the χ² gate
    dropped: int  # landmarks dropped after max_strikes gated views running


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


class LandmarkMap:
    """The landmark EKFs of the port structure, kept by the VO's stable point ids."""

    def __init__(self, focal_px: float, params: LandmarkParams | None = None) -> None:
        self.focal = float(focal_px)
        self.params = params or LandmarkParams()
        self._gate = float(chi2.ppf(self.params.gate_probability, 2))
        self.ids = np.zeros(0, np.int64)  # row → id
        self.x = np.zeros((0, 3))
        self.P = np.zeros((0, 3, 3))
        self.views = np.zeros(0, np.int64)  # accepted views
        self.strikes = np.zeros(0, np.int64)  # gated views running
        self.alive = np.zeros(0, bool)
        self.last_time = np.zeros(0)
        self.floor = np.zeros((0, 3, 3))  # camera-position covariance of the last view
        self.last_camera = np.zeros((0, 3))  # camera centre of the last accepted view
        self.nis = np.zeros(0)  # sum of the normalised innovations² of the accepted views
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
        self.views[r] = 0
        self.strikes[r] = 0
        self.alive[r] = True
        self.last_time[r] = time
        self.floor[r] = 0.0
        self.last_camera[r] = np.nan
        self.nis[r] = 0.0
        n_new = int(new.sum())
        if n_new:
            self.ids = np.concatenate([self.ids, ids[new]])
            self.x = np.concatenate([self.x, xyz[new]])
            self.P = np.concatenate([self.P, cov[new]])
            self.views = np.concatenate([self.views, np.zeros(n_new, np.int64)])
            self.strikes = np.concatenate([self.strikes, np.zeros(n_new, np.int64)])
            self.alive = np.concatenate([self.alive, np.ones(n_new, bool)])
            self.last_time = np.concatenate([self.last_time, np.full(n_new, float(time))])
            self.floor = np.concatenate([self.floor, np.zeros((n_new, 3, 3))])
            self.last_camera = np.concatenate([self.last_camera, np.full((n_new, 3), np.nan)])
            self.nis = np.concatenate([self.nis, np.zeros(n_new)])
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
               pose_cov: np.ndarray | None, ids: np.ndarray, xy: np.ndarray) -> LandmarkUpdate:
        """One view: landmarks ``ids`` seen at undistorted normalised image coordinates ``xy``
        (N,2) by the camera at ``camera_position_ned`` with attitude ``C_level_to_camera``.
        ``pose_cov``: 6x6 covariance of (camera position, attitude small angles in L)
        (``camera_pose_covariance``), None for an exactly known pose."""
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
        X0, P0 = self.x[rows], self.P[rows]
        n = len(rows)
        eye2 = np.eye(2)
        R_pix = (self.params.pixel_sigma_px / self.focal) ** 2 * eye2

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
        accept = front & (d2 <= self._gate)
        gated = front & ~accept
        IKH = np.eye(3) - K @ H
        P_new = IKH @ P0 @ IKH.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)
        P_new = 0.5 * (P_new + P_new.transpose(0, 2, 1))
        a = rows[accept]
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
        cam = self.last_camera[rows]
        seen = np.isfinite(cam).all(axis=1)
        d = self.x[rows] - np.where(seen[:, None], cam, 0.0)
        rng = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        u = d / rng[:, None]
        s_ray = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", u, self.P[rows], u), 0.0))
        parallax = ~seen | (s_ray <= prm.max_relative_sigma * rng)
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
        return self.ids[sel].copy(), self.x[sel].copy(), self.P[sel] + self.floor[sel]


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
