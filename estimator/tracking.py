"""Designated-target tracking in the video: particle filter of seed 002
(``docs/references.md``).

The officer clicks a point of the quay; its image position must stay locked on it frame by
frame while the ship moves, and a lost lock must be SAID, never replaced by a wrong point.
Seed 002 (Nishida et al., CAMSHIFT-guided particle filter with adaptive template matching and
optical-flow camera-motion compensation) does exactly this for a target seen by a moving
underwater camera. Its state is the window ``x_k = (p_k, s_k)`` (centre, size; the size is
kept at the initial ``s_0``), represented by M weighted particles. Per frame (its fig. 5):

- Step 1, sampling (eq. 13–15): every particle is moved by the mean optical flow ``ō`` of the
  scene — good features to track (Shi–Tomasi) followed by pyramidal Lucas–Kanade between the
  previous and the current frame — plus Gaussian spread ``N(0, σ_D² I)``; then refined by
  CAMSHIFT (mean shift with the window size frozen at ``s_0``, its appendix) on the
  back-projection ``B_k`` of the current hue image with the initial region's hue histogram
  ``H_0``.
- Step 2, weighting (eq. 19): ``π = exp(−‖p̂ − p‖ / σ_o²)`` with ``p̂`` the best normalised
  correlation (``TM_CCOEFF_NORMED``) match of the current template ``T_k``; σ_o = 10, σ_D = 5 px,
  20 particles as in the paper.
- Step 3, resampling (eq. 20, systematic), the MAP particle as the estimate (eq. 22–23), and
  template adaptation at the estimate (eq. 9).
- Loss of track from the correlation score (its section 3.5: "judge the reliability from
  N_k(x, y) and stop when the target is lost").

Adaptations to a quay point tracked for minutes from a ship (documented deviations):

- The flow is taken from features AROUND the target (a window a few templates wide), robust
  mean (inliers within a few MADs of the median, forward–backward checked): the camera
  translates, so the flow of the distant scene or of the water is not the target's.
- A click is a point, not an object: the colour window CAMSHIFT converges to is not centred on
  it (a click on the corner of a blue board converges on the board). The particles carry the
  point; their colour windows sit at the offset the clicked window converged to at ``init``.
- ``σ_o²`` in eq. 19 makes the likelihood very flat (all particles within a few pixels weigh
  alike); the MAP particle is then simply the particle nearest ``p̂``. The reported point is
  ``p̂`` (sub-pixel) when the MAP particle confirms it (within ``snap_px`` or twice the
  cloud's RMS spread); away from it the MAP particle is kept only when its own correlation is
  within ``ambiguity_margin`` of p̂'s (two similar places: continuity decides, the paper's
  case), else p̂ if it correlates at least ``reacquire_score`` (the cloud drifted), else the
  target is lost (a jump to a weak match: an occlusion). The resampled cloud moves with that
  snap (part of the proposal) so that it does not random-walk off the target.
- Template adaptation (eq. 9) every frame re-cuts the template around an estimate that has
  pixel-level noise, and the template then random-walks off the clicked point. The template
  is adapted only when the correlation is high enough to be the same point and low enough
  to show a change of appearance (``adapt_min_score ≤ N < adapt_max_score``), and the
  estimate is first drift-corrected: the central part of the FIRST template (``anchor_size``:
  less of the background, which moves differently from a quay-edge target) is aligned to the
  frame by an affine ECC warp, accepted when good and within ``anchor_max_shift_px``.
- Loss: ``N`` below ``lost_score``, or the estimate leaving the image. When lost, ``update``
  keeps dead-reckoning the point with the flow and only reports ``tracking`` again when the
  template is found again with ``reacquire_score``; ``reacquire(image, uv_pred)`` searches
  around a predicted position (the target's 3-D point projected with the fused pose). A
  find after a loss has no continuity to decide between look-alikes (a row of fenders): it
  is taken only when no other place in the search window scores within
  ``ambiguity_margin`` of it (``_refind``); else the target stays lost.

``method`` selects the full method or the two ablations of the paper's fig. 7: ``template``
(adaptive template matching alone, searched around the previous position) and
``camshift_pf`` (the CAMSHIFT-guided particle filter alone: no flow, particles weighted by
the Bhattacharyya similarity of their hue histogram to ``H_0``).

Images are BGR (or grey) uint8, coordinates are distorted pixels (x right, y down; the centre
of the top-left pixel is (0, 0)).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from .landmarks import (
    LandmarkMap,
    LandmarkParams,
    SolvedViews,
    common_drift_jacobian,
    common_rotation_jacobian,
    converged,
    ray_prior,
    split_disagreement,
    triangulate_point,
)
from .records import CameraCalibration, CameraView

METHODS = ("full", "template", "camshift_pf")


@dataclass
class TrackerParams:
    n_particles: int = 20  # M (seed 002: no gain beyond 20)
    sigma_d_px: float = 5.0  # σ_D, spread of the sampling (eq. 13)
    sigma_o: float = 10.0  # σ_o of the likelihood exp(−‖p̂ − p‖/σ_o²) (eq. 19)
    n_features: int = 200  # good features to track for the mean flow
    flow_region: float = 5.0  # features within this many window sizes around the target
    flow_min_features: int = 8  # fewer inliers: the whole image's features are used
    flow_margin_px: int = 48  # image around the features' region the flow is computed on
    search_px: int = 24  # template search margin around the predicted position
    lost_search_px: int = 48  # ... while lost (dead-reckoned position)
    # ``follow_flow`` (a track that must not jump): template searched this close to where
    # the mean flow puts the point. A row of fenders or a repeated facade puts look-alikes
    # within ``search_px``; one frame's motion is rarely this far from the mean flow.
    flow_search_px: int = 8
    flow_search_features: int = 40  # ... the mean flow of this many features (a fifth the cost)
    lost_score: float = 0.55  # N below this: target lost
    reacquire_score: float = 0.75  # N needed to take a lost target back
    adapt_min_score: float = 0.8  # template adapted only above this (same point) ...
    adapt_max_score: float = 0.95  # ... and below this (its appearance has changed)
    snap_px: float = 8.0  # MAP particle snapped onto p̂ when closer than this ...
    snap_spread: float = 2.0  # ... or than this many RMS spreads of the particle cloud
    ambiguity_margin: float = 0.1  # MAP particle kept over a far p̂ scoring at most this more
    hue_bins: int = 16  # H_0 histogram bins
    min_saturation: int = 40  # pixels with less saturation / value carry no hue
    min_value: int = 30
    camshift_iterations: int = 10
    camshift_min_mass: float = 0.05  # mean back-projection (0..1) a window needs to move
    edge_margin_px: float = 2.0  # estimate within this of the border: out of the image
    bhattacharyya_sigma: float = 0.2  # camshift_pf likelihood exp(−(1 − ρ)/σ)
    # Drift correction: the estimate is refined by aligning the FIRST template T_0 (affine,
    # ECC) to the frame; accepted when the alignment is this good and this close.
    anchor_first_template: bool = True
    anchor_min_ecc: float = 0.8
    anchor_max_shift_px: float = 3.0
    anchor_size: float = 0.6  # part of the window (centred) aligned: less background


@dataclass
class TrackResult:
    uv: np.ndarray | None  # (2,) estimated image point, None when lost
    score: float  # normalised correlation N of the template at the estimate (−1..1)
    status: str  # "tracking" | "lost"
    particles: np.ndarray  # (M,2) particle centres after resampling
    uv_match: np.ndarray | None = None  # p̂, the best template match
    flow: np.ndarray | None = None  # ō, mean optical flow used for the sampling
    reason: str = ""  # why lost


class TargetTracker:
    """Tracks one designated image point (see the module docstring)."""

    def __init__(self, params: TrackerParams | None = None, method: str = "full",
                 seed: int | None = None) -> None:
        if method not in METHODS:
            raise ValueError(f"unknown tracking method {method!r}; one of {METHODS}")
        self.params = params or TrackerParams()
        self.method = method
        self.rng = np.random.default_rng(seed)
        self.window: tuple[int, int] = (31, 31)
        self.status = "lost"
        self.uv: np.ndarray | None = None  # last estimate (or dead-reckoned point when lost)
        self.particles = np.zeros((0, 2))
        self.template: np.ndarray | None = None
        self.template0: np.ndarray | None = None  # T_0 (float32) for the drift correction
        self._warp0 = np.zeros((2, 3), np.float32)  # T_0 coordinates → image
        self.anchored = 0  # frames whose estimate the T_0 alignment refined
        self.hist: np.ndarray | None = None
        self._ms_offset = np.zeros(2)  # CAMSHIFT window centre − target point
        self._prev_gray: np.ndarray | None = None
        self.frames = 0
        self.adaptations = 0

    # ------------------------------------------------------------------ public interface

    def init(self, image: np.ndarray, uv: tuple[float, float] | np.ndarray,
             window: int | tuple[int, int] = 31) -> TrackResult:
        """Start on ``uv`` of ``image`` with a ``window`` (odd side, or (w, h)) template."""
        w, h = (window, window) if isinstance(window, int | np.integer) else window
        self.window = (int(w) | 1, int(h) | 1)  # odd, so the centre is a pixel (seed 002)
        gray = _gray(image)
        size = np.array(gray.shape[::-1], float)
        p = np.asarray(uv, float).reshape(2)
        if not self._inside(p, size):
            where = f"{int(size[0])}x{int(size[1])} image"
            if np.all(p >= -0.5) and np.all(p <= size - 0.5):
                m = self.params.edge_margin_px + 0.5 * max(self.window)
                raise ValueError(f"point ({p[0]:.1f}, {p[1]:.1f}) is within {m:.0f} px of the "
                                 f"{where}'s edge: no room for its template there")
            raise ValueError(f"point ({p[0]:.1f}, {p[1]:.1f}) is not inside the {where}")
        self.template = _crop(gray, p, self.window)
        aw = int(round(self.params.anchor_size * self.window[0])) | 1
        ah = int(round(self.params.anchor_size * self.window[1])) | 1
        self.template0 = _crop(gray, p, (aw, ah)).astype(np.float32)
        c0 = 0.5 * (np.array([aw, ah], float) - 1.0)
        self._warp0 = np.array([[1.0, 0.0, p[0] - c0[0]], [0.0, 1.0, p[1] - c0[1]]], np.float32)
        self.hist = self._hue_histogram(image, p)
        # The colour window CAMSHIFT converges to is not centred on the clicked point (a
        # corner of a blue board converges to the board): the particles carry the point, the
        # windows are offset from it by where mean shift puts the clicked window now.
        self._ms_offset = np.zeros(2)
        self._ms_offset = self._camshift(image, p[None])[0] - p
        self.particles = np.repeat(p[None], self.params.n_particles, axis=0)
        self.uv = p.copy()
        self.status = "tracking"
        self._prev_gray = gray
        self.frames = 0
        return TrackResult(uv=p.copy(), score=1.0, status="tracking",
                           particles=self.particles.copy(), uv_match=p.copy(),
                           flow=np.zeros(2))

    def update(self, image: np.ndarray) -> TrackResult:
        """One new frame (the next one after the last ``init``/``update``)."""
        if self.template is None or self._prev_gray is None or self.uv is None:
            raise RuntimeError("TargetTracker.update before init")
        gray = _gray(image)
        self.frames += 1
        if self.method == "template":
            res = self._update_template(gray)
        elif self.method == "camshift_pf":
            res = self._update_camshift_pf(image, gray)
        else:
            res = self._update_full(image, gray)
        self._prev_gray = gray
        return res

    def reacquire(self, image: np.ndarray, uv_pred: np.ndarray | tuple[float, float],
                  radius_px: float = 30.0, min_score: float | None = None) -> TrackResult:
        """Look for the target's last good template within ``radius_px`` of ``uv_pred`` (its
        3-D point projected with the fused pose) in ``image`` — the frame of the last
        ``update`` (or a newer one: the flow state is reset to it). Takes the target back
        when the correlation reaches ``min_score`` (default ``reacquire_score``); otherwise
        it stays lost."""
        if self.template is None:
            raise RuntimeError("TargetTracker.reacquire before init")
        gray = _gray(image)
        self._prev_gray = gray
        need = self.params.reacquire_score if min_score is None else float(min_score)
        pred = np.asarray(uv_pred, float).reshape(2)
        back, score, seen_at, look_alikes = self._find_again(gray, pred,
                                                             int(math.ceil(radius_px)), need)
        if back is not None:
            return back
        self.status = "lost"
        if self._inside(pred, np.array(gray.shape[::-1], float)):
            self.uv = pred.copy()
        return TrackResult(uv=None, score=score, status="lost", particles=self.particles.copy(),
                           uv_match=seen_at, reason=_LOOK_ALIKES if look_alikes else
                           "not found near the predicted position")

    def follow_flow(self, image: np.ndarray) -> TrackResult:
        """One frame, the template matched only within ``flow_search_px`` of where the mean
        LK flow around the point moves it (no particles, no colour): a track that loses the
        point rather than jump to a look-alike. ``DesignatedTarget`` tracks the click back
        with it, where nothing else checks the track (the forward one is checked by its 3-D
        point)."""
        if self.template is None or self._prev_gray is None or self.uv is None:
            raise RuntimeError("TargetTracker.follow_flow before init")
        p = self.params
        gray = _gray(image)
        self.frames += 1
        predicted = self.uv + self._mean_flow(self._prev_gray, gray, self.uv,
                                              p.flow_search_features)
        self._prev_gray = gray
        return self._update_template(gray, predicted, p.flow_search_px)

    def hold(self, image: np.ndarray, reason: str = "lost") -> TrackResult:
        """Mark the target lost on ``image`` (the next ``update`` follows from it)."""
        self._prev_gray = _gray(image)
        self.status = "lost"
        return TrackResult(uv=None, score=-1.0, status="lost", particles=self.particles.copy(),
                           reason=reason)

    # --------------------------------------------------------------------- full method

    def _update_full(self, image: np.ndarray, gray: np.ndarray) -> TrackResult:
        p = self.params
        size = np.array(gray.shape[::-1], float)
        flow = self._mean_flow(self._prev_gray, gray, self.uv)
        # Step 1: sampling — camera motion from the flow, spread σ_D, CAMSHIFT on B_k.
        cloud = self.particles + flow + self.rng.normal(0.0, p.sigma_d_px, self.particles.shape)
        cloud = self._camshift(image, cloud)
        predicted = self.uv + flow
        if self.status == "lost":
            return self._lost_step(gray, predicted, cloud, flow)
        # Step 2: weights from the best normalised-correlation match p̂ (eq. 19).
        match = _match(gray, self.template, predicted, p.search_px + int(2 * p.sigma_d_px))
        if match is None:
            return self._declare_lost(predicted, cloud, flow, size, -1.0, "no match window")
        p_hat, score = match
        if np.linalg.norm(p_hat - predicted) > p.flow_search_px:
            # Two similar places (a facade's next window, a row of fenders): continuity
            # decides — the best match where the flow puts the point, when it is nearly as good
            near = _match(gray, self.template, predicted, p.flow_search_px)
            if near is not None and near[1] >= score - p.ambiguity_margin:
                p_hat, score = near
        d = np.linalg.norm(cloud - p_hat, axis=1)
        weights = np.exp(-d / p.sigma_o**2)
        weights /= weights.sum()
        # MAP particle (eq. 22–23), before the weights are equalised by the resampling.
        p_map = cloud[int(np.argmax(weights))]
        self.particles = cloud[resample_indexes(weights, self.rng)]
        # p̂ is taken when the MAP hypothesis confirms it (within the cloud's own spread); away
        # from it, the MAP particle only when its own correlation is nearly as good — two
        # similar-looking places (seed 002's case), where continuity decides — not when the
        # cloud has merely drifted off a clearly better match.
        spread = float(np.sqrt(np.mean(np.sum((cloud - cloud.mean(axis=0)) ** 2, axis=1))))
        gate = max(p.snap_px, p.snap_spread * spread)
        est = p_hat
        if np.linalg.norm(p_hat - p_map) > gate:
            n_map = _score_at(gray, self.template, p_map) if self._inside(p_map, size) \
                else -1.0
            if n_map >= score - p.ambiguity_margin:
                est = p_map
            elif score < p.reacquire_score:  # a jump to a weak match: an occlusion, say
                return self._declare_lost(predicted, self.particles, flow, size, score,
                                          "the best match jumped away with a weak correlation")
        # The snap is part of the proposal: the posterior cloud moves with it, so the MAP
        # hypothesis stays on the target instead of the cloud random-walking off it.
        self.particles = self.particles + (est - p_map)
        if not self._inside(est, size):
            return self._declare_lost(est, self.particles, flow, size, score,
                                      "left the image")
        n_est = score if est is p_hat else _score_at(gray, self.template, est)
        if n_est >= p.lost_score:
            est = self._anchor(gray, est)
        if n_est < p.lost_score:
            return self._declare_lost(predicted, self.particles, flow, size, n_est,
                                      "correlation below the loss threshold")
        self._adapt(gray, est, n_est)
        self.uv = est.copy()
        return TrackResult(uv=est.copy(), score=float(n_est), status="tracking",
                           particles=self.particles.copy(), uv_match=p_hat.copy(), flow=flow)

    def _lost_step(self, gray: np.ndarray, predicted: np.ndarray, cloud: np.ndarray,
                   flow: np.ndarray) -> TrackResult:
        """While lost: dead-reckon with the flow; come back only on a confident match."""
        p = self.params
        self.particles = cloud
        back, score, seen_at, look_alikes = self._find_again(gray, predicted, p.lost_search_px,
                                                             p.reacquire_score, flow)
        if back is not None:
            return back
        self.uv = predicted
        return TrackResult(uv=None, score=score, status="lost", particles=self.particles.copy(),
                           uv_match=seen_at, flow=flow, reason=_LOOK_ALIKES if look_alikes
                           else "waiting for the template to reappear")

    def _find_again(self, gray: np.ndarray, centre: np.ndarray, radius: int, need: float,
                    flow: np.ndarray | None = None
                    ) -> tuple[TrackResult | None, float, np.ndarray | None, bool]:
        """After a loss: the template's best match within ``radius`` of ``centre``. Taken back
        — the target tracking again there, its result returned first — when it correlates
        at least ``need``, lies inside the image and no look-alike is in reach
        (``_refind``). Otherwise (None, its score or −1, where it was, whether look-alikes
        alone kept it from being taken)."""
        p = self.params
        match = _refind(gray, self.template, centre, radius, p.ambiguity_margin)
        if match is None:
            return None, -1.0, None, False
        q, score, ambiguous = match
        if score < need or not self._inside(q, np.array(gray.shape[::-1], float)):
            return None, score, q, False
        if ambiguous:
            return None, score, q, True
        self.particles = q + self.rng.normal(0.0, 0.5 * p.sigma_d_px, (p.n_particles, 2))
        self.uv = q.copy()
        self.status = "tracking"
        return TrackResult(uv=q.copy(), score=score, status="tracking",
                           particles=self.particles.copy(), uv_match=q.copy(), flow=flow), \
            score, q, False

    def _declare_lost(self, where: np.ndarray, particles: np.ndarray, flow: np.ndarray,
                      size: np.ndarray, score: float, reason: str) -> TrackResult:
        self.status = "lost"
        self.particles = particles
        self.uv = np.asarray(where, float).copy()
        return TrackResult(uv=None, score=float(score), status="lost",
                           particles=particles.copy(), uv_match=None, flow=flow, reason=reason)

    # ---------------------------------------------------------------------- ablations

    def _update_template(self, gray: np.ndarray, centre: np.ndarray | None = None,
                         radius: int | None = None) -> TrackResult:
        """Adaptive template matching alone (seed 002 fig. 7 "適応パターンマッチングのみ"):
        searched around the last estimate (or ``centre``) within the tracking or lost search
        radius (or ``radius``)."""
        p = self.params
        size = np.array(gray.shape[::-1], float)
        if centre is None:
            centre = self.uv
        if radius is None:
            radius = (p.search_px if self.status == "tracking" else p.lost_search_px) \
                + int(2 * p.sigma_d_px)
        match = _match(gray, self.template, centre, radius)
        empty = np.zeros((0, 2))
        if match is None:
            return self._declare_lost(centre, empty, np.zeros(2), size, -1.0, "no match window")
        q, score = match
        need = p.lost_score if self.status == "tracking" else p.reacquire_score
        if score < need or not self._inside(q, size):
            return self._declare_lost(centre, empty, np.zeros(2), size, score,
                                      "correlation below the loss threshold")
        self.status = "tracking"
        q = self._anchor(gray, q)
        self._adapt(gray, q, score)
        self.uv = q.copy()
        return TrackResult(uv=q.copy(), score=score, status="tracking", particles=empty,
                           uv_match=q.copy())

    def _update_camshift_pf(self, image: np.ndarray, gray: np.ndarray) -> TrackResult:
        """The CAMSHIFT-guided particle filter alone (CAMSGPF, seed 002 fig. 7): spread and
        CAMSHIFT sampling, weights from the hue-histogram similarity to H_0, MAP particle; the
        correlation with the (initial) template only reports the score and the loss."""
        p = self.params
        size = np.array(gray.shape[::-1], float)
        cloud = self.particles + self.rng.normal(0.0, p.sigma_d_px, self.particles.shape)
        cloud = self._camshift(image, cloud)
        rho = np.array([self._bhattacharyya(image, c) for c in cloud])
        weights = np.exp(-(1.0 - rho) / p.bhattacharyya_sigma)
        weights = weights / weights.sum() if weights.sum() > 0 else np.full(len(cloud),
                                                                            1.0 / len(cloud))
        est = cloud[int(np.argmax(weights))].copy()
        self.particles = cloud[resample_indexes(weights, self.rng)]
        score = _score_at(gray, self.template, est) if self._inside(est, size) else -1.0
        self.uv = est
        if not self._inside(est, size) or score < p.lost_score:
            self.status = "lost"
            return TrackResult(uv=None, score=float(score), status="lost",
                               particles=self.particles.copy(),
                               reason="correlation below the loss threshold")
        self.status = "tracking"
        return TrackResult(uv=est.copy(), score=float(score), status="tracking",
                           particles=self.particles.copy())

    # ------------------------------------------------------------------------ pieces

    def _inside(self, q: np.ndarray, size: np.ndarray) -> bool:
        m = self.params.edge_margin_px + 0.5 * np.array(self.window, float)
        return bool(np.all(q >= m - 0.5) and np.all(q <= size - 0.5 - m))

    def _anchor(self, gray: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Drift correction of the adaptive template: align T_0 to the frame (affine ECC,
        started at the last alignment moved onto ``q``) and return the point it puts the
        clicked pixel at, when the alignment is good and near ``q``; ``q`` otherwise."""
        p = self.params
        if not p.anchor_first_template or self.template0 is None:
            return q
        th, tw = self.template0.shape
        c0 = 0.5 * (np.array([tw, th], float) - 1.0)
        A = self._warp0[:, :2].astype(float)
        t = q - A @ c0
        corners = np.array([[0.0, 0.0], [tw - 1.0, 0.0], [0.0, th - 1.0],
                            [tw - 1.0, th - 1.0]]) @ A.T + t
        margin = 2.0 * p.anchor_max_shift_px + 4.0
        x0, y0 = np.floor(corners.min(axis=0) - margin).astype(int)
        x1, y1 = np.ceil(corners.max(axis=0) + margin).astype(int)
        H, W = gray.shape
        if x0 < 0 or y0 < 0 or x1 >= W or y1 >= H:
            return q
        roi = gray[y0:y1 + 1, x0:x1 + 1].astype(np.float32)
        warp = np.hstack([A, (t - np.array([x0, y0], float))[:, None]]).astype(np.float32)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 1e-3)
        try:
            ecc, warp = cv2.findTransformECC(self.template0, roi, warp, cv2.MOTION_AFFINE, crit,
                                             None, 1)
        except cv2.error:  # did not converge (texture-less, occluded)
            return q
        A2 = warp[:, :2].astype(float)
        sv = np.linalg.svd(A2, compute_uv=False)
        centre = A2 @ c0 + warp[:, 2].astype(float) + np.array([x0, y0], float)
        if ecc < p.anchor_min_ecc or np.linalg.norm(centre - q) > p.anchor_max_shift_px \
                or sv.min() < 0.3 or sv.max() > 4.0:
            return q
        self._warp0 = np.hstack([A2, (centre - A2 @ c0)[:, None]]).astype(np.float32)
        self.anchored += 1
        return centre

    def _adapt(self, gray: np.ndarray, q: np.ndarray, score: float) -> None:
        """Template adaptation (eq. 9, size kept at s_0) when the match is the same point
        with a changed appearance."""
        p = self.params
        if p.adapt_min_score <= score < p.adapt_max_score:
            self.template = _crop(gray, q, self.window)
            self.adaptations += 1

    def _mean_flow(self, prev: np.ndarray, cur: np.ndarray, around: np.ndarray,
                   n_features: int | None = None) -> np.ndarray:
        """ō: robust mean LK flow of good features around ``around`` (whole image if few)."""
        p = self.params
        h, w = prev.shape
        half = 0.5 * p.flow_region * np.array(self.window, float)
        for region in (half, None):
            if region is None:
                x0, y0, x1, y1 = 0, 0, w, h
            else:
                x0 = int(max(0, around[0] - region[0]))
                y0 = int(max(0, around[1] - region[1]))
                x1 = int(min(w, around[0] + region[0] + 1))
                y1 = int(min(h, around[1] + region[1] + 1))
                if x1 - x0 < 16 or y1 - y0 < 16:
                    continue
            pts = cv2.goodFeaturesToTrack(prev[y0:y1, x0:x1], n_features or p.n_features,
                                          0.01, 5)
            if pts is None or len(pts) < p.flow_min_features:
                continue
            # LK on the region and a margin, not the whole frame: its pyramids are most of
            # its cost.
            m = p.flow_margin_px
            X0, Y0, X1, Y1 = max(0, x0 - m), max(0, y0 - m), min(w, x1 + m), min(h, y1 + m)
            pts = pts.reshape(-1, 2) + np.array([x0 - X0, y0 - Y0], np.float32)
            flow = _lk_flow(prev[Y0:Y1, X0:X1], cur[Y0:Y1, X0:X1], pts)
            if len(flow) >= p.flow_min_features:
                return _robust_mean(flow)
        return np.zeros(2)

    def _hue(self, image: np.ndarray, box: tuple[int, int, int, int]
             ) -> tuple[np.ndarray, np.ndarray] | None:
        """Hue and validity mask of the box (x0, y0, x1, y1) of a BGR image."""
        if image.ndim != 3:
            return None
        x0, y0, x1, y1 = box
        hsv = cv2.cvtColor(np.ascontiguousarray(image[y0:y1, x0:x1]), cv2.COLOR_BGR2HSV)
        mask = cv2.inRange(hsv, (0, self.params.min_saturation, self.params.min_value),
                           (180, 255, 255))
        return hsv[..., 0], mask

    def _hue_histogram(self, image: np.ndarray, q: np.ndarray) -> np.ndarray | None:
        """H_0: normalised hue histogram of the window at ``q`` (None without colour)."""
        box = _box(q, self.window, image.shape[1], image.shape[0])
        hue = self._hue(image, box)
        if hue is None:
            return None
        hist = cv2.calcHist([hue[0]], [0], hue[1], [self.params.hue_bins], [0, 180])
        total = float(hist.sum())
        if total < 0.05 * self.window[0] * self.window[1]:
            return None  # a grey target: no hue to follow (CAMSHIFT then leaves particles)
        return (hist / total).astype(np.float32)

    def _camshift(self, image: np.ndarray, cloud: np.ndarray) -> np.ndarray:
        """Each particle's colour window (size s_0, at the point + the CAMSHIFT offset) moved
        to the mode of B_k = BackProject(H_0); a move over half a window is another blob."""
        if self.hist is None or image.ndim != 3 or len(cloud) == 0:
            return cloud
        p = self.params
        H, W = image.shape[:2]
        ww, wh = self.window
        windows = cloud + self._ms_offset
        lo = np.floor(windows.min(axis=0) - np.array([ww, wh])).astype(int)
        hi = np.ceil(windows.max(axis=0) + np.array([ww, wh])).astype(int)
        x0, y0 = max(0, lo[0]), max(0, lo[1])
        x1, y1 = min(W, hi[0] + 1), min(H, hi[1] + 1)
        if x1 - x0 < ww or y1 - y0 < wh:
            return cloud
        hue, mask = self._hue(image, (x0, y0, x1, y1))
        scale = self.hist * (255.0 / max(float(self.hist.max()), 1e-9))
        back = cv2.calcBackProject([hue], [0], scale, [0, 180], 1)
        back = cv2.bitwise_and(back, back, mask=mask)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, p.camshift_iterations, 0.5)
        out = cloud.copy()
        min_mass = p.camshift_min_mass * 255.0 * ww * wh
        limit = 0.5 * min(ww, wh)
        for k, c in enumerate(windows):
            bx = int(round(c[0] - x0 - ww // 2))
            by = int(round(c[1] - y0 - wh // 2))
            bx = min(max(bx, 0), back.shape[1] - ww)
            by = min(max(by, 0), back.shape[0] - wh)
            roi = back[by:by + wh, bx:bx + ww]
            if float(roi.sum()) < min_mass:
                continue  # no target colour under the window: the particle stays
            _, (nx, ny, _, _) = cv2.meanShift(back, (bx, by, ww, wh), crit)
            shift = np.array([nx - bx, ny - by], float)
            if np.linalg.norm(shift) <= limit:
                out[k] = cloud[k] + shift
        return out

    def _bhattacharyya(self, image: np.ndarray, q: np.ndarray) -> float:
        if self.hist is None:
            return 0.0
        h = self._hue_histogram(image, q)
        if h is None:
            return 0.0
        return float(np.sum(np.sqrt(np.maximum(h, 0) * np.maximum(self.hist, 0))))


# ------------------------------------------------------------------ designated target


@dataclass
class TargetState:
    """A designated target after one frame."""

    status: str  # "tracking" | "lost"
    uv: np.ndarray | None  # tracked image point (distorted pixels), None when lost
    predicted_uv: np.ndarray | None  # its 3-D point projected with the pose (None: not in view)
    position_ned: np.ndarray  # 3-D point (L, m)
    covariance: np.ndarray  # (3,3) m²
    distance_m: float  # from the camera centre to the 3-D point
    distance_sigma_m: float
    score: float  # template correlation (−1 when not matched)
    views: int  # tracked views the 3-D point has used
    reason: str = ""  # why lost / what happened
    reacquired: bool = False  # taken back this frame from the projected 3-D point


@dataclass
class TargetParams:
    window: int = 31  # template side (px)
    reacquire_radius_px: float = 30.0  # search radius around the projected 3-D point
    max_disagreement: int = 3  # tracked views gated by the 3-D point running: declared lost
    min_refine_views: int = 3  # solved views ``refine`` needs
    # The click's template is tracked back through the frames before it (``earlier_frames``)
    # this far: views from before the click give its 3-D point the parallax the approach
    # along the line of sight does not. Further back a template can slip to a neighbouring
    # feature unnoticed (default recording: the first slips 25 and 33 s back).
    track_back_s: float = 20.0
    # Slow errors the views share, 1-σ rates of a drift common to them (``refine``: no
    # number of views averages it out). Every view: the fused camera centre's error moves
    # by a few cm over tens of seconds (m/s, per axis). While the track is unanchored (its
    # first template not aligned): the template slides as the target grows or shrinks, by
    # a few pixels over tens of seconds (px/s at 960 px of image width).
    position_drift_mps: float = 0.002
    unanchored_drift_px_per_s: float = 0.25
    # The target's landmark EKF: the tracker's pixel noise, never dropped (the tracker is
    # declared lost instead), the click's ray prior from the structure points' spread.
    landmark: LandmarkParams = field(default_factory=lambda: LandmarkParams(
        pixel_sigma_px=1.5, min_views=1, max_strikes=2**31 - 1, ray_sigma_fraction=0.1,
        joint=None))


def nearest_surface(ranges: np.ndarray, pixel_distance: np.ndarray,
                    surface_fraction: float = 0.15, min_support: int = 2,
                    on_point_px: float = 1.0) -> np.ndarray:
    """Mask of the anchors on the nearest surface: ranges grouped where consecutive sorted
    ranges are within ``surface_fraction`` of each other; the nearest group with
    ``min_support`` anchors, else the group of the anchor nearest the click in pixels.
    Foreground first: around a quay edge the background shows next to it in the image, and
    a distance too short errs on the safe side for a berthing aid. A click ON a drawn
    structure point (within ``on_point_px``) takes that point's group."""
    r = np.asarray(ranges, float)
    order = np.argsort(r)
    group = np.zeros(len(r), int)
    g = 0
    for a, b in zip(order[:-1], order[1:], strict=True):
        if r[b] - r[a] > surface_fraction * max(abs(r[a]), 1e-6):
            g += 1
        group[b] = g
    sizes = np.bincount(group)
    big = np.flatnonzero(sizes >= min(min_support, len(r)))
    closest = int(np.argmin(pixel_distance))
    if pixel_distance[closest] <= on_point_px or not len(big):
        chosen = int(group[closest])
    else:
        chosen = int(big[0])
    return group == chosen


def point_on_ray(points_ned: np.ndarray, sigma_m: np.ndarray | None,
                 camera_position_ned: np.ndarray, ray: np.ndarray, focal_px: float,
                 pixel_distance: np.ndarray | None = None, ray_sigma_fraction: float = 0.1,
                 lateral_sigma_px: float = 2.0, surface_fraction: float = 0.15
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The 3-D point of a clicked pixel from the port-structure points near its ray (the
    anchors): on the ray at their range, with a covariance that is tight across the ray (the
    click) and along it as uncertain as the anchors disagree (their range spread, their own σ
    and ``ray_sigma_fraction`` of the range: monocular points err along their ray).

    Anchors near a pixel often mix surfaces (the quay edge and the buildings behind it): with
    ``pixel_distance`` (px from the click) only the nearest surface is kept
    (``nearest_surface``)."""
    c = np.asarray(camera_position_ned, float)
    u = np.asarray(ray, float) / np.linalg.norm(ray)
    along = (np.asarray(points_ned, float).reshape(-1, 3) - c) @ u
    sig = None if sigma_m is None else np.asarray(sigma_m, float).reshape(-1)
    ambiguity = 0.0
    if pixel_distance is not None and len(along) > 1:
        keep = nearest_surface(along, np.asarray(pixel_distance, float), surface_fraction)
        if not keep.all():
            # Other surfaces near the click: a weakly supported choice keeps them in reach.
            other = along[~keep]
            gap = float(np.min(np.abs(other - np.median(along[keep]))))
            ambiguity = gap / (1.0 + keep.sum())
        along = along[keep]
        sig = None if sig is None else sig[keep]
    r = float(np.median(along))
    spread = 1.4826 * float(np.median(np.abs(along - r))) if len(along) > 1 else 0.0
    s_pts = 0.0 if sig is None or len(sig) == 0 else float(np.median(sig))
    s_ray = math.sqrt(spread**2 + s_pts**2 + (ray_sigma_fraction * r) ** 2 + ambiguity**2)
    s_lat = max(lateral_sigma_px / focal_px * r, 0.01)
    P = s_lat**2 * np.eye(3) + (s_ray**2 - s_lat**2) * np.outer(u, u)
    return c + r * u, P


# Structure points this close to a clicked pixel anchor it (widened to twice this when fewer
# than two of them are on the nearest surface).
DESIGNATION_RADIUS_PX = 12.0


def structure_point_at(points_ned: np.ndarray, sigma_m: np.ndarray, uv_points: np.ndarray,
                       click_uv: np.ndarray, camera_position_ned: np.ndarray, ray: np.ndarray,
                       focal_px: float, radius_px: float = DESIGNATION_RADIUS_PX,
                       max_radius_px: float = 2 * DESIGNATION_RADIUS_PX,
                       converged_sigma_fraction: float = 0.02
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The clicked point from the port structure: the points projecting (``uv_points``, NaN
    when not in view) within ``radius_px`` of the click — widened to ``max_radius_px`` when
    fewer than two of them are on the nearest surface — through ``point_on_ray``. Returns
    (point, covariance, indexes of the anchors on the chosen surface) or None.

    Anchored on converged points, the point's σ along the ray has a floor of
    ``converged_sigma_fraction`` of the range instead of ``point_on_ray``'s 10 %: such
    points are solved jointly with the views' attitudes (``estimator.landmarks.ViewWindow``).
    It is the prior of a designated target's own triangulation (``DesignatedTarget.refine``),
    which decides where the target's views have parallax."""
    pts = np.asarray(points_ned, float).reshape(-1, 3)
    sig = np.asarray(sigma_m, float).reshape(-1)
    d = np.linalg.norm(np.asarray(uv_points, float).reshape(-1, 2)
                       - np.asarray(click_uv, float).reshape(2), axis=1)
    d = np.nan_to_num(d, nan=np.inf)
    c = np.asarray(camera_position_ned, float)
    u = np.asarray(ray, float) / np.linalg.norm(ray)
    # Converged points (σ within the landmarks' reporting fraction of their range) anchor the
    # click when there are any near it: a point still converging may be metres off along its
    # ray.
    trusted = converged(sig, np.linalg.norm(pts - c, axis=1))
    for radius in (radius_px, max_radius_px):
        near = np.flatnonzero(d <= radius)
        if not len(near):
            continue
        floor = {}
        if trusted[near].any():
            near = near[trusted[near]]
            floor = {"ray_sigma_fraction": converged_sigma_fraction}
        keep = nearest_surface((pts[near] - c) @ u, d[near])
        if keep.sum() >= 2 or radius >= max_radius_px:
            X, P = point_on_ray(pts[near], sig[near], c, u, focal_px, pixel_distance=d[near],
                                **floor)
            return X, P, near[keep]
    return None


# A click whose template holds structure points this many times farther than its nearest
# ones straddles a depth edge (the quay's coping against the buildings behind it): its
# template is tracked, and triangulated, somewhere between the two surfaces.
EDGE_RANGE_RATIO = 1.5
EDGE_POINT_SIGMA_FRACTION = 0.25  # structure points this uncertain (σ / range) say nothing


def _click_offsets(uv_points: np.ndarray, click_uv: np.ndarray) -> np.ndarray:
    """(N,2) pixel offsets of ``uv_points`` from the click, +inf where a point is not in
    view (NaN)."""
    off = np.asarray(uv_points, float).reshape(-1, 2) - np.asarray(click_uv, float).reshape(2)
    return np.nan_to_num(off, nan=np.inf)


def in_template(uv_points: np.ndarray, click_uv: np.ndarray, half_window_px: float
                ) -> np.ndarray:
    """Mask of the points (pixels ``uv_points``, NaN when not in view) inside a clicked
    template: within ``half_window_px`` of the click each way."""
    return np.all(np.abs(_click_offsets(uv_points, click_uv)) <= half_window_px, axis=1)


def near_click(uv_points: np.ndarray, click_uv: np.ndarray, radius_px: float) -> np.ndarray:
    """Mask of the points (pixels ``uv_points``, NaN when not in view) within ``radius_px``
    of the click. With half a template's side this leaves out the template's corners, where
    its square reaches past the click's own surface: on 30 small-boat yardstick seeds,
    designations whose nearest anchor lay 15-21 px from the click (half side 15) were
    beyond 2σ for 4 of 27, those nearer for 7 of 420."""
    return np.hypot(*_click_offsets(uv_points, click_uv).T) <= radius_px


def shows_surface(uv_anchors: np.ndarray, click_uv: np.ndarray, radius_px: float,
                  on_point_px: float = 1.0) -> bool:
    """Whether the anchors of a click (pixels) show the surface under it: one of them ON the
    click (within ``on_point_px``), or at least two within ``radius_px`` (``near_click``).
    A single point beside the click has no extent to carry the click onto its surface: it
    may be a nearer object's silhouette with the click on what lies behind (the 12 s test
    recording: a building corner 150 m off anchored on one point 14 px away at 105 m,
    read as 105 m ± 3 m)."""
    d = np.hypot(*_click_offsets(uv_anchors, click_uv).T)
    return bool((d <= on_point_px).any() or (d <= radius_px).sum() >= 2)


def depth_edge(points_ned: np.ndarray, sigma_m: np.ndarray, uv_points: np.ndarray,
               click_uv: np.ndarray, camera_position_ned: np.ndarray, half_window_px: float
               ) -> tuple[float, float] | None:
    """(nearest, farthest) range (m) of the structure points inside a clicked template
    (``half_window_px`` each way) when they span a depth edge (``EDGE_RANGE_RATIO``), else
    None. On an edge the tracked views agree with each other (the template slides as one)
    yet not with either surface — found on an unseen seed: coping clicks 21 m away read
    38-73 m at +-1.2-2.4 m — so the distance the officer reads carries the span as its
    uncertainty (``DesignatedTarget.edge_span_m``)."""
    pts = np.asarray(points_ned, float).reshape(-1, 3)
    ranges = np.linalg.norm(pts - np.asarray(camera_position_ned, float), axis=1)
    inside = in_template(uv_points, click_uv, half_window_px) \
        & (np.asarray(sigma_m, float).reshape(-1) <= EDGE_POINT_SIGMA_FRACTION * ranges)
    if inside.sum() < 2:
        return None
    near, far = float(ranges[inside].min()), float(ranges[inside].max())
    return (near, far) if far > EDGE_RANGE_RATIO * near else None


def under_water(X: np.ndarray, P: np.ndarray, water_down_m: float | None) -> bool:
    """Whether the point ``X`` (covariance ``P``) lies under the water plane (its down,
    None: unknown) by more than 3σ: nothing the ship can run into is there — a mirror
    image on calm water, or a ray that missed what it was meant to hit."""
    return water_down_m is not None and \
        float(X[2]) - water_down_m > 3.0 * math.sqrt(max(float(P[2, 2]), 0.0))


class _SeenViews:
    """A designated target's tracked views, in time order: time, undistorted normalised
    pixel, the seconds the track had gone unanchored by then (``DesignatedTarget.unanchored_s``)
    and — once the structure's joint window has solved the view of that time — its
    attitude, camera centre and rotation variance (NaN before)."""

    def __init__(self) -> None:
        self.t = np.zeros(0)
        self.xy = np.zeros((0, 2))
        self.unanchored_s = np.zeros(0)
        self.C = np.zeros((0, 3, 3))
        self.centre = np.zeros((0, 3))
        self.rotation_var = np.zeros(0)

    def __len__(self) -> int:
        return len(self.t)

    def add(self, t: np.ndarray, xy: np.ndarray, unanchored_s: np.ndarray) -> None:
        """Views at times ``t`` (increasing); those at or after ``t[0]`` are dropped first
        (a seek back replays them)."""
        t = np.asarray(t, float).reshape(-1)
        if not len(t):
            return
        self.keep(self.t < t[0])
        n = len(t)
        self.t = np.concatenate([self.t, t])
        self.xy = np.concatenate([self.xy, np.asarray(xy, float).reshape(n, 2)])
        self.unanchored_s = np.concatenate([self.unanchored_s,
                                            np.asarray(unanchored_s, float).reshape(n)])
        self.C = np.concatenate([self.C, np.full((n, 3, 3), np.nan)])
        self.centre = np.concatenate([self.centre, np.full((n, 3), np.nan)])
        self.rotation_var = np.concatenate([self.rotation_var, np.full(n, np.nan)])

    def keep(self, mask: np.ndarray) -> None:
        self.t, self.xy, self.C = self.t[mask], self.xy[mask], self.C[mask]
        self.unanchored_s = self.unanchored_s[mask]
        self.centre, self.rotation_var = self.centre[mask], self.rotation_var[mask]

    def take(self, views: SolvedViews) -> np.ndarray:
        """Take the solved attitudes of ``views`` for the views at their times; forget the
        views older than them never solved (they never will be). Returns the mask of the
        views with a solved attitude."""
        idx = views.at(self.t)
        hit = idx >= 0
        self.C[hit] = views.C_level_to_camera[idx[hit]]
        self.centre[hit] = views.camera_position_ned[idx[hit]]
        self.rotation_var[hit] = views.rotation_var[idx[hit]]
        if len(views):
            self.keep(np.isfinite(self.rotation_var) | (self.t >= views.time[0]))
        return np.isfinite(self.rotation_var)


def range_with_sigma(point_ned: np.ndarray, covariance: np.ndarray, camera_ned: np.ndarray
                     ) -> tuple[float, float]:
    """Distance (m) from a camera centre to a 3-D point, and its 1-σ from the point's
    covariance along the line of sight."""
    rel = np.asarray(point_ned, float) - np.asarray(camera_ned, float)
    d = float(np.linalg.norm(rel))
    u = rel / max(d, 1e-9)
    return d, float(np.sqrt(max(float(u @ np.asarray(covariance, float) @ u), 0.0)))


def with_edge_span(point_ned: np.ndarray, covariance: np.ndarray, camera_ned: np.ndarray,
                   edge_span_m: tuple[float, float] | None) -> np.ndarray:
    """A clicked point's covariance as the officer reads it: on a depth edge (``depth_edge``:
    (nearest, farthest) range) with half the edge's span added along the line of sight from
    ``camera_ned`` (either surface within 2σ)."""
    P = np.asarray(covariance, float)
    if edge_span_m is None:
        return P
    u = np.asarray(point_ned, float) - np.asarray(camera_ned, float)
    u = u / max(float(np.linalg.norm(u)), 1e-9)
    near, far = edge_span_m
    return P + (0.5 * (far - near)) ** 2 * np.outer(u, u)


class DesignatedTarget:
    """A clicked point: its image track (``TargetTracker``) and its 3-D point, one landmark
    EKF (``estimator.landmarks``) fed with every tracked view and the fused camera pose. The
    3-D point keeps improving as the ship moves, by two means called as the port structure
    is refreshed (``refresh``, about once a second):

    - ``reanchor`` (until ``refine`` has done it once): the converged structure points
      around the tracked pixel give it again;
    - ``refine``: the target's own tracked views — those after the click and those before
      it (``earlier_frames``: the click's template tracked back) — taken in the attitudes
      the structure's joint window solved for them (``estimator.landmarks.SolvedViews``),
      triangulate it on top of the click's point. The fused attitude would read its
      heading's wander as parallax; the solved one does not. Once refined, the point is
      the triangulation's: a frame's view with the fused attitude only checks it.

    The image track and the 3-D point check each other: a track the 3-D point's χ² gate
    rejects ``max_disagreement`` times running is declared lost, and a lost track is
    searched for around the 3-D point's projection (re-acquisition). While lost the 3-D
    point and its distance are still given (from the views so far) with ``status`` "lost" —
    never a silently wrong distance.

    ``position_ned``/``covariance``: the point under the click (port-structure points near it,
    or the water plane) in the frame ``image`` (time ``t``) with the camera pose of that
    frame. ``earlier_frames``: (time, image) of the frames before it, oldest first (gray
    images will do); those within ``TargetParams.track_back_s`` are used. ``views``: the
    structure window's solved views as of the click (refined at once). ``water_down_m``:
    the water plane's down when known — a triangulation below it is refused (the track
    followed a mirror image). A click the structure did not place (its ray met the water
    plane) is refined like any other: what stands on the water, a fender or a hull, is
    placed by its own views."""

    def __init__(self, camera: CameraCalibration, image: np.ndarray, uv: np.ndarray,
                 position_ned: np.ndarray, covariance: np.ndarray | None, view: CameraView,
                 params: TargetParams | None = None, method: str = "full",
                 tracker_params: TrackerParams | None = None, seed: int | None = None,
                 earlier_frames: Sequence[tuple[float, np.ndarray]] = (),
                 views: SolvedViews | None = None, water_down_m: float | None = None,
                 edge_span_m: tuple[float, float] | None = None) -> None:
        self.camera = camera
        # the click straddles a depth edge (``depth_edge``): what the officer reads carries
        # the span (the track and its point are left as they are)
        self.edge_span_m = edge_span_m
        self.water_down_m = water_down_m  # a point triangulated below it is a reflection's
        self.params = params or TargetParams()
        self._K = np.asarray(camera.K, float)
        self._dist = np.asarray(camera.distortion, float).ravel()
        self._focal = f = camera.focal_px
        self.tracker = TargetTracker(tracker_params, method=method, seed=seed)
        self.tracker.init(image, uv, self.params.window)
        self.map = LandmarkMap(f, self.params.landmark)
        X = np.asarray(position_ned, float).reshape(3)
        P = ray_prior(X, view.position_ned, f, self.params.landmark)[0] if covariance is None \
            else np.asarray(covariance, float).reshape(3, 3)
        if self.map.seed(np.array([0]), X[None], P[None]) != 1:
            raise ValueError("the designated point or its covariance is not finite")
        self.click_point = (X.copy(), P.copy())  # the prior ``refine`` starts from
        t = float(view.t)
        self.click_time = t  # views nearest it are trusted first (``refine``)
        self.refined_views = 0  # views of the last ``refine`` (0: the point is not refined)
        # the fused attitude's covariance at the last view: its error is common to the views
        # ``refine`` triangulates in (``common_rotation_jacobian``)
        self.attitude_cov: np.ndarray | None = None
        self.seen = _SeenViews()
        # Seconds the forward track has gone without its first template's alignment
        # (``TargetTracker._anchor``) since the click: how far it may have drifted.
        self.unanchored_s = 0.0
        self._last_view_t = t
        if math.isfinite(t):
            self._track_back(image, np.asarray(uv, float), t, earlier_frames)
        self._view(np.asarray(uv, float), view, anchored=True)
        self.map.views[:] = 0  # the click is not a tracked view (for the EKF's count)
        self.disagreements = 0
        self.status = "tracking"
        self.reacquisitions = 0
        self.refine(views)

    @property
    def refined(self) -> bool:
        return self.refined_views > 0

    @property
    def position_ned(self) -> np.ndarray:
        return self.map.x[0].copy()

    @property
    def covariance(self) -> np.ndarray:
        return self.map.P[0] + self.map.floor[0]

    def reported_covariance(self, view: CameraView) -> np.ndarray:
        """The covariance the officer reads: ``with_edge_span`` of the point's."""
        return with_edge_span(self.position_ned, self.covariance, view.position_ned,
                              self.edge_span_m)

    def distance(self, view: CameraView, reported: np.ndarray | None = None
                 ) -> tuple[float, float]:
        """Distance (m) from the camera of ``view`` to the 3-D point, and its 1-σ (from
        ``reported``, the ``reported_covariance`` at ``view`` when already formed)."""
        P = self.reported_covariance(view) if reported is None else reported
        return range_with_sigma(self.position_ned, P, view.position_ned)

    def project(self, C_level_to_camera: np.ndarray, camera_position_ned: np.ndarray,
                point: np.ndarray | None = None) -> np.ndarray | None:
        """The 3-D point (or ``point``) in the image (distorted pixels), None behind the
        camera."""
        X = self.map.x[0] if point is None else point
        xc = np.asarray(C_level_to_camera, float) @ (X - np.asarray(camera_position_ned, float))
        if xc[2] <= 0.2:
            return None
        uv, _ = cv2.projectPoints(xc[None], np.zeros(3), np.zeros(3), self._K, self._dist)
        return uv.reshape(2)

    def _projected_cov(self, pred: np.ndarray, view: CameraView) -> np.ndarray | None:
        """(2,2) px²: the 3-D point's covariance projected at ``pred`` with the tracker's
        pixel noise; None at the camera (nothing to judge by)."""
        X, step = self.map.x[0], 0.01  # m: the projection's Jacobian by differences
        J = np.empty((2, 3))
        for i in range(3):
            q = self.project(view.C_level_to_camera, view.position_ned,
                             X + step * np.eye(3)[i])
            if q is None:
                return None
            J[:, i] = (q - pred) / step
        return J @ self.covariance @ J.T + self.params.landmark.pixel_sigma_px ** 2 * np.eye(2)

    def _beyond_reach(self, uv: np.ndarray, pred: np.ndarray, view: CameraView) -> bool:
        """Whether an image find at ``uv`` is farther from the 3-D point's projection
        ``pred`` than both the re-acquisition radius and the point's own uncertainty (its
        covariance projected, with the tracker's pixel noise, at the landmark EKF's own χ²
        gate of a view) allow."""
        d = np.asarray(uv, float) - pred
        if np.linalg.norm(d) <= self.params.reacquire_radius_px:
            return False
        S = self._projected_cov(pred, view)
        return S is not None and float(d @ np.linalg.solve(S, d)) > self.map.gate

    def _predicts(self, pred: np.ndarray, view: CameraView) -> bool:
        """Whether the 3-D point's projection ``pred`` is sure enough to take the target back
        at: its uncertainty's χ² gate within the re-acquisition radius. A point placed on the
        water plane, tens of metres deep along its ray, projects anywhere along the ray's
        image once the ship has moved: what its radius holds is some other thing."""
        S = self._projected_cov(pred, view)
        return S is not None and \
            self.map.gate * float(np.linalg.eigvalsh(S)[-1]) <= self.params.reacquire_radius_px ** 2

    def update(self, image: np.ndarray, view: CameraView) -> TargetState:
        """One frame and the fused camera pose at its time."""
        p = self.params
        pred = self.project(view.C_level_to_camera, view.position_ned)
        h, w = image.shape[:2]
        in_view = pred is not None and -0.5 <= pred[0] <= w - 0.5 and -0.5 <= pred[1] <= h - 0.5
        anchored = self.tracker.anchored
        res = self.tracker.update(image)
        reason, reacquired = res.reason, False
        if (res.status == "tracking" and self.status == "lost" and pred is not None
                and not in_view and res.uv is not None
                and self._beyond_reach(res.uv, pred, view)):
            # Lost, its 3-D point out of the image, the image tracker finds its template
            # again inside it, farther than the point's own uncertainty allows: the
            # look-alike it slid to, not the target. (With the point in view a find away
            # from it stays possible: it is the point that may be off, and the χ² gate of
            # the views judges.)
            self.tracker.status = "lost"
            res = replace(res, uv=None, status="lost",
                          reason="found again away from its 3-D point")
        if res.status != "tracking" and in_view and self._predicts(pred, view):
            res = self.tracker.reacquire(image, pred, p.reacquire_radius_px)
            reacquired = res.status == "tracking"
            self.reacquisitions += int(reacquired)
            reason = res.reason if not reacquired else "re-acquired at the projected 3-D point"
        return self._state(res, reason, reacquired, pred if in_view else None, view,
                           self.tracker.anchored > anchored)

    def resume(self, image: np.ndarray, view: CameraView) -> TargetState:
        """Continue on a frame that does not follow the last one (a seek, skipped frames):
        the image track is taken back only where the 3-D point projects (re-acquisition)."""
        pred = self.project(view.C_level_to_camera, view.position_ned)
        h, w = image.shape[:2]
        in_view = pred is not None and -0.5 <= pred[0] <= w - 0.5 and -0.5 <= pred[1] <= h - 0.5
        self.tracker.status = "lost"
        if in_view and self._predicts(pred, view):
            res = self.tracker.reacquire(image, pred, self.params.reacquire_radius_px)
        elif in_view:
            res = self.tracker.hold(image, "its 3-D point is too uncertain to look for it")
        else:
            res = self.tracker.hold(image, "its 3-D point is out of the image")
        reacquired = res.status == "tracking"
        self.reacquisitions += int(reacquired)
        reason = "re-acquired at the projected 3-D point" if reacquired else res.reason
        return self._state(res, reason, reacquired, pred if in_view else None, view, False)

    def _state(self, res: TrackResult, reason: str, reacquired: bool, pred: np.ndarray | None,
               view: CameraView, anchored: bool) -> TargetState:
        """Feed a tracked view to the 3-D point (χ²-checked) and form the target's state;
        ``anchored``: the tracker aligned its first template on this frame."""
        p = self.params
        uv = None
        if res.status == "tracking" and res.uv is not None:
            ok = self._view(res.uv, view, anchored)
            self.disagreements = 0 if ok else self.disagreements + 1
            if self.disagreements >= p.max_disagreement:
                self.tracker.status = "lost"
                self.disagreements = 0
                reason = "image track disagrees with the 3-D point"
            else:
                uv = res.uv
        self.status = "tracking" if uv is not None else "lost"
        P = self.reported_covariance(view)
        d, d_sigma = self.distance(view, P)
        return TargetState(status=self.status, uv=None if uv is None else np.asarray(uv).copy(),
                           predicted_uv=pred, position_ned=self.position_ned,
                           covariance=P, distance_m=d, distance_sigma_m=d_sigma,
                           score=float(res.score), views=int(self.map.views[0]),
                           reason=reason if uv is None or reacquired else "",
                           reacquired=reacquired)

    def refresh(self, points_ned: np.ndarray, sigma_m: np.ndarray, uv_points: np.ndarray,
                view: CameraView, views: SolvedViews | None) -> None:
        """The port structure was refreshed (points, σ, their pixels in this frame; the
        window's solved views): ``reanchor`` on it, then ``refine`` in its views."""
        if len(points_ned):
            self.reanchor(points_ned, sigma_m, uv_points, view)
        self.refine(views)

    def reanchor(self, points_ned: np.ndarray, sigma_m: np.ndarray, uv_points: np.ndarray,
                 view: CameraView) -> bool:
        """Take the 3-D point again from the port structure (points, σ, their pixels in this
        frame) around the pixel tracked now, when the points there have converged and the
        point has not been refined (``refine`` does better: it cannot take the wall behind a
        ladder for the ladder); True if it did. Call it as the structure is refreshed (about
        once a second) — it matters where the solved views are missing (no joint window)."""
        uv = self.tracker.uv
        if self.refined or self.status != "tracking" or uv is None:
            return False
        C = np.asarray(view.C_level_to_camera, float)
        c = np.asarray(view.position_ned, float)
        xy = cv2.undistortPoints(np.asarray(uv, np.float64).reshape(1, 1, 2), self._K,
                                 self._dist).reshape(2)
        ray = C.T @ np.array([xy[0], xy[1], 1.0])
        pts = np.asarray(points_ned, float).reshape(-1, 3)
        sig = np.asarray(sigma_m, float).reshape(-1)
        found = structure_point_at(pts, sig, uv_points, np.asarray(uv, float), c,
                                   ray / np.linalg.norm(ray), self._focal)
        if found is None:
            return False
        X, P, near = found
        if not len(near) or not converged(sig[near], np.linalg.norm(pts[near] - c, axis=1)).all():
            return False
        self.map.x[0], self.map.P[0] = X, P
        return True

    def refine(self, views: SolvedViews | None) -> int:
        """Triangulate the 3-D point from its tracked views with the attitudes the
        structure's joint window solved for them (``views``, ``Fusion.solved_views``), on
        top of the click's point. A view keeps the last solved attitude it had once the
        window has moved past it: the early views carry the parallax. Returns the views
        used (0: nothing done — fewer than ``TargetParams.min_refine_views``)."""
        if views is None:
            return 0
        seen = self.seen
        solved = seen.take(views)
        if solved.sum() < self.params.min_refine_views:
            return 0
        X0, P0 = self.click_point
        info0 = np.linalg.inv(P0)
        ray_var = self.ray_variance()
        rows = self.solved_rows()
        X, info, used = triangulate_point(seen.C[rows], seen.centre[rows], seen.xy[rows],
                                          ray_var[rows], X0, info0)
        n = int(used.sum())
        if n < self.params.min_refine_views or not np.isfinite(X).all():
            return 0
        P = np.linalg.inv(info)
        u = rows[used]
        common = (seen.C[u], seen.centre[u], seen.xy[u], ray_var[u], X, X0, info0)
        if self.attitude_cov is not None:
            J = common_rotation_jacobian(*common)
            P = P + J @ self.attitude_cov @ J.T
        if under_water(X, P, self.water_down_m):
            return 0  # the track followed a mirror image (the drifts unspent)
        # The views' slow common drifts: their camera centres' from the click
        # (``TargetParams.position_drift_mps``), the track's while it is unanchored
        # (``unanchored_drift_px_per_s``).
        J = common_drift_jacobian(*common, seen.t[u] - self.click_time, on="centres")
        P = P + self.params.position_drift_mps ** 2 * (J @ J.T)
        px = float(self.camera.width) / 960.0 / self.map.focal  # normalised units of 1 px
        J = common_drift_jacobian(*common, seen.unanchored_s[u])
        P = P + (self.params.unanchored_drift_px_per_s * px) ** 2 * (J @ J.T)
        P = P + self._halves_disagreement(rows, ray_var, X0, info0)
        self.map.x[0], self.map.P[0] = X, P
        self.refined_views = n
        return n

    def ray_variance(self) -> np.ndarray:
        """(len(seen),): each view's angular variance (normalised units²) — the tracker's
        pixel noise and what is left of its solved attitude's uncertainty (NaN before the
        view is solved)."""
        return (self.params.landmark.pixel_sigma_px / self.map.focal) ** 2 \
            + self.seen.rotation_var

    def solved_rows(self) -> np.ndarray:
        """Indexes of the views with a solved attitude, nearest the click first: the order
        ``refine`` trusts them in."""
        seen = self.seen
        rows = np.flatnonzero(np.isfinite(seen.rotation_var))
        return rows[np.argsort(np.abs(seen.t[rows] - self.click_time), kind="stable")]

    def _halves_disagreement(self, rows: np.ndarray, ray_var: np.ndarray, X0: np.ndarray,
                             info0: np.ndarray) -> np.ndarray:
        """(3,3): how far the points of two halves of the views disagree beyond their own
        covariances (``excess_disagreement``), the largest of three splits: the views before
        the click (its template tracked back) against those after it (the forward track),
        the forward track's older half against its newer one, and the track back's newer
        half against its older one (until the forward track has views of its own the point
        rests on the track back alone, which slides as a forward track does). A template
        that slid — along an edge, say, which near the horizon is the direction a depth
        change moves a point — moves the point of the views after the slide and not that
        of those before it, by an error no view's noise explains. A split needs
        ``min_refine_views`` on each side. ``rows``: the solved views, nearest the click
        first — all of them: those the triangulation's gates left out are a half's evidence
        too; ``ray_var``: every view's (``ray_variance``)."""
        seen = self.seen
        after = rows[seen.t[rows] > self.click_time]  # nearest the click first: oldest first
        before = rows[seen.t[rows] < self.click_time]  # nearest the click first: newest first
        n_after, n_before = len(after) // 2, len(before) // 2
        splits = ((before, after), (after[:n_after], after[n_after:]),
                  (before[:n_before], before[n_before:]))
        excess = np.zeros((3, 3))
        for a, b in splits:
            E = split_disagreement(seen.C, seen.centre, seen.xy, ray_var, X0, info0, a, b,
                                   self.params.min_refine_views)
            if np.trace(E) > np.trace(excess):
                excess = E
        return excess

    def _track_back(self, image: np.ndarray, uv: np.ndarray, t: float,
                    earlier_frames: Sequence[tuple[float, np.ndarray]]) -> None:
        """The click's template tracked back through the frames before it (newest first),
        following the image flow (``TargetTracker.follow_flow``: no jump to a look-alike)
        until it is lost or ``track_back_s`` is reached; its pixels kept as views."""
        back = TargetTracker(method="template")
        back.init(_gray(image), uv, self.params.window)
        seen = []
        unanchored_s, t_prev = 0.0, t  # unanchored seconds, counted back from the click (< 0)
        for t_k, img in reversed(earlier_frames):
            if not t - self.params.track_back_s <= t_k < t:
                continue
            anchored = back.anchored
            res = back.follow_flow(img)
            if res.status != "tracking" or res.uv is None:
                break
            unanchored_s = 0.0 if back.anchored > anchored else \
                unanchored_s - (t_prev - float(t_k))
            t_prev = float(t_k)
            seen.append((t_prev, res.uv, unanchored_s))
        if seen:
            times, uvs, unanchored = (np.array(column, np.float64)
                                      for column in zip(*reversed(seen), strict=True))
            self.seen.add(times, cv2.undistortPoints(uvs.reshape(-1, 1, 2), self._K,
                                                     self._dist).reshape(-1, 2), unanchored)

    def _view(self, uv: np.ndarray, view: CameraView, anchored: bool) -> bool:
        """One tracked view of the 3-D point (kept for ``refine``); False when its χ² gate
        rejects it. ``anchored``: on the first template's alignment (no drift)."""
        C, c, pose_cov, t = view.C_level_to_camera, view.position_ned, view.pose_cov, view.t
        if math.isfinite(t):
            step = t - self._last_view_t if math.isfinite(self._last_view_t) else 0.0
            self.unanchored_s = 0.0 if anchored else self.unanchored_s + max(step, 0.0)
            self._last_view_t = t
        if pose_cov is not None:
            self.attitude_cov = np.asarray(pose_cov, float)[3:, 3:]
        xy = cv2.undistortPoints(np.asarray(uv, np.float64).reshape(1, 1, 2), self._K,
                                 self._dist).reshape(1, 2)
        kept = self.map.x[0].copy(), self.map.P[0].copy()
        out = self.map.update(0.0, C, c, pose_cov, np.array([0]), xy)
        if self.refined:  # the fused attitude only checks a refined point (class docstring)
            self.map.x[0], self.map.P[0] = kept
        elif under_water(self.map.x[0], self.map.P[0], self.water_down_m):
            # a mirror image, or something the ship carries along: refused, as ``refine``
            # refuses it (the views disagreeing with the point, the track is given up)
            self.map.x[0], self.map.P[0] = kept
            return False
        ok = out.gated == 0
        if ok and math.isfinite(t):
            self.seen.add(np.array([t]), xy, np.array([self.unanchored_s]))
        return ok


# ---------------------------------------------------------------------------- helpers


def _gray(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def _box(q: np.ndarray, window: tuple[int, int], width: int, height: int
         ) -> tuple[int, int, int, int]:
    x0 = int(round(q[0])) - window[0] // 2
    y0 = int(round(q[1])) - window[1] // 2
    x0 = min(max(x0, 0), max(width - window[0], 0))
    y0 = min(max(y0, 0), max(height - window[1], 0))
    return x0, y0, x0 + window[0], y0 + window[1]


def _crop(gray: np.ndarray, q: np.ndarray, window: tuple[int, int]) -> np.ndarray:
    """Template of size ``window`` centred (sub-pixel) at ``q``."""
    return cv2.getRectSubPix(gray, window, (float(q[0]), float(q[1])))


_LOOK_ALIKES = "look-alikes in reach: not taken back"


def _correlation(gray: np.ndarray, template: np.ndarray, centre: np.ndarray, radius: int
                 ) -> tuple[np.ndarray, int, int] | None:
    """TM_CCOEFF_NORMED of ``template`` at every centre within ``radius`` of ``centre``, and
    the image position of the map's origin; None when the search window is off the image."""
    th, tw = template.shape
    H, W = gray.shape
    cx, cy = int(round(centre[0])), int(round(centre[1]))
    x0 = max(0, cx - radius - tw // 2)
    y0 = max(0, cy - radius - th // 2)
    x1 = min(W, cx + radius + tw // 2 + 1)
    y1 = min(H, cy + radius + th // 2 + 1)
    if x1 - x0 < tw or y1 - y0 < th:
        return None
    return cv2.matchTemplate(gray[y0:y1, x0:x1], template, cv2.TM_CCOEFF_NORMED), x0, y0


def _peak(res: np.ndarray, x0: int, y0: int, template: np.ndarray
          ) -> tuple[np.ndarray, float, int, int]:
    """(sub-pixel centre in the image, score, column, row in the map) of the map's best."""
    th, tw = template.shape
    _, score, _, (mx, my) = cv2.minMaxLoc(res)
    dx = _parabola(res, mx, my, axis=1)
    dy = _parabola(res, mx, my, axis=0)
    return np.array([x0 + mx + tw // 2 + dx, y0 + my + th // 2 + dy], float), float(score), \
        mx, my


def _match(gray: np.ndarray, template: np.ndarray, centre: np.ndarray, radius: int
           ) -> tuple[np.ndarray, float] | None:
    """Best TM_CCOEFF_NORMED match of ``template`` whose centre is within ``radius`` of
    ``centre``: (sub-pixel centre, score), None when the search window is off the image."""
    found = _correlation(gray, template, centre, radius)
    if found is None:
        return None
    q, score, _, _ = _peak(*found, template)
    return q, score


def _refind(gray: np.ndarray, template: np.ndarray, centre: np.ndarray, radius: int,
            margin: float) -> tuple[np.ndarray, float, bool] | None:
    """``_match`` and whether it is ambiguous: another local maximum of the correlation, more
    than half a template from the best, scores within ``margin`` of it (a look-alike)."""
    found = _correlation(gray, template, centre, radius)
    if found is None:
        return None
    res = found[0]
    q, score, mx, my = _peak(*found, template)
    rows, cols = np.indices(res.shape)
    far = (cols - mx) ** 2 + (rows - my) ** 2 > (0.5 * template.shape[1]) ** 2
    local_max = res >= cv2.dilate(res, np.ones((3, 3), np.uint8))
    others = res[far & local_max]
    return q, score, bool(len(others) and float(others.max()) >= score - margin)


def _parabola(res: np.ndarray, x: int, y: int, axis: int) -> float:
    """Sub-pixel offset of a peak from a parabola through it and its two neighbours."""
    if axis == 1:
        if x <= 0 or x >= res.shape[1] - 1:
            return 0.0
        a, b, c = res[y, x - 1], res[y, x], res[y, x + 1]
    else:
        if y <= 0 or y >= res.shape[0] - 1:
            return 0.0
        a, b, c = res[y - 1, x], res[y, x], res[y + 1, x]
    den = a - 2.0 * b + c
    if den >= 0.0:
        return 0.0
    return float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))


def _score_at(gray: np.ndarray, template: np.ndarray, q: np.ndarray) -> float:
    """Normalised correlation of the template with the window centred at ``q``."""
    patch = _crop(gray, q, template.shape[::-1])
    res = cv2.matchTemplate(patch, template, cv2.TM_CCOEFF_NORMED)
    return float(res[0, 0])


def _lk_flow(prev: np.ndarray, cur: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Flow vectors (K,2) of the points tracked forward and back consistently."""
    lk = dict(winSize=(21, 21), maxLevel=3,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03))
    p0 = pts.reshape(-1, 1, 2).astype(np.float32)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, None, **lk)
    if p1 is None:
        return np.zeros((0, 2))
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, None, **lk)
    fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < 1.0)
    return (p1 - p0).reshape(-1, 2)[ok].astype(float)


def _robust_mean(v: np.ndarray) -> np.ndarray:
    """Mean of the vectors within 3 MADs of the median (water, other boats move)."""
    med = np.median(v, axis=0)
    r = np.linalg.norm(v - med, axis=1)
    mad = max(float(np.median(r)), 0.3)
    keep = r <= 3.0 * mad
    return v[keep].mean(axis=0) if keep.any() else med


def resample_indexes(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling (seed 002 eq. 20) of weights (normalised here) → particle
    indexes, from the tracker's own generator (filterpy's ``systematic_resample`` draws from
    numpy's global one: a track would not repeat from one run to the next)."""
    w = np.asarray(weights, float)
    c = np.cumsum(w / w.sum())
    c[-1] = 1.0  # a cumulative sum a hair below 1 would leave the last position unmatched
    positions = (rng.random() + np.arange(len(w))) / len(w)
    return np.searchsorted(c, positions, side="right").astype(int)
