"""Designated-target tracking (estimator/tracking.py) and its evaluation (evaluation/
tracking.py).

The tracker runs on short sequences rendered by the simulator (recordings.sim.scene) from the
small-boat scenario's true motion, where the true target path is the projection of a true
scene point; plus the particle-filter pieces, loss detection and re-acquisition, and a smoke
run of the evaluation on the simulated test recording.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from estimator.frames import rot_z
from estimator.landmarks import SolvedViews
from estimator.records import CameraCalibration, CameraView
from estimator.tracking import (
    DesignatedTarget,
    TargetParams,
    TargetTracker,
    nearest_surface,
    resample_indexes,
    structure_point_at,
)
from recordings.sim.motion import ShipMotion
from recordings.sim.scenarios import SMALL_BOAT
from recordings.sim.scene import PortScene, camera_calibration, project_points
from recordings.sim.variety import reference_look

SEED = 1
T0 = 62.0  # s: the boat is 15–25 m from the quay wall
N_FRAMES = 30
WALL_KINDS = ("quay", "fender", "ladder")


class Sequence:
    """Rendered frames with the true camera poses and a quay-wall point to track."""

    def __init__(self, scene: PortScene, cam: CameraCalibration,
                 poses: list[tuple[np.ndarray, np.ndarray]], times: list[float]) -> None:
        rng = np.random.default_rng(5)
        self.cam = cam
        self.poses = poses
        self.images = [scene.render(C, p, t, cam, rng) for (C, p), t in zip(poses, times,
                                                                             strict=True)]

    def truth(self, point: np.ndarray) -> np.ndarray:
        """(N,2) true pixel path of a NED point (NaN behind the camera)."""
        return np.array([project_points(point[None], C, p, self.cam)[0][0]
                         for C, p in self.poses])


@pytest.fixture(scope="module")
def world() -> tuple[PortScene, CameraCalibration, ShipMotion]:
    # The tracker's mechanics on the reference look (the simulator's former single look). On
    # seed 1's own look (overcast: no hue for CAMSHIFT, stone wall, its port mirrored in the
    # water) the particle cloud strays and a point leaving the image slips 36 px first:
    # issue 17's robustness work, judged on the seeds, not here.
    return PortScene.build(SMALL_BOAT, SEED, look=reference_look(SMALL_BOAT)), \
        camera_calibration(SMALL_BOAT), ShipMotion(SMALL_BOAT, SEED)


def true_pose(motion: ShipMotion, cam: CameraCalibration, t: float
              ) -> tuple[np.ndarray, np.ndarray]:
    st = motion.state(t)
    C_l_c = (st.C_body_to_level[0] @ cam.C_camera_to_body).T
    return C_l_c, motion.point_position_ned(t, cam.lever_arm_body).reshape(3)


def wall_point(scene: PortScene, cam: CameraCalibration, poses: list, margin: float = 150.0,
               min_motion_px: float = 20.0) -> np.ndarray:
    """A quay-wall scene point well inside the image at the first pose, nearest the image
    centre among those that move ``min_motion_px`` over the poses (the parallax the
    triangulation tests need: a point near the focus of expansion has none)."""
    pts, kinds = scene.scene_points()
    sel = np.isin(kinds, WALL_KINDS)
    uv, depth = project_points(pts[sel], *poses[0], cam)
    uv_end, _ = project_points(pts[sel], *poses[-1], cam)
    ok = (depth > 5.0) & (depth < 30.0) & (uv[:, 0] > margin) & \
        (uv[:, 0] < cam.width - margin) & (uv[:, 1] > 60) & (uv[:, 1] < cam.height - 60) & \
        (np.linalg.norm(np.nan_to_num(uv_end - uv), axis=1) > min_motion_px)
    assert ok.any(), "no quay-wall point in view"
    centre = np.array([cam.width / 2, cam.height / 2])
    k = np.flatnonzero(ok)[np.argmin(np.linalg.norm(uv[ok] - centre, axis=1))]
    return pts[sel][k]


@pytest.fixture(scope="module")
def along_path(world) -> tuple[Sequence, np.ndarray]:
    """~3 s of the true berthing motion (wave roll/pitch, forward speed, turning)."""
    scene, cam, motion = world
    times = [T0 + 0.1 * k for k in range(N_FRAMES)]
    poses = [true_pose(motion, cam, t) for t in times]
    seq = Sequence(scene, cam, poses, times)
    return seq, wall_point(scene, cam, poses)


@pytest.fixture(scope="module")
def panning(world) -> tuple[Sequence, np.ndarray]:
    """A camera panning to starboard 2.5°/frame from a fixed point: the target crosses the
    image and leaves it on the left."""
    scene, cam, motion = world
    C0, p0 = true_pose(motion, cam, T0)
    poses = [(C0 @ rot_z(-np.radians(2.5 * k)).T, p0) for k in range(N_FRAMES)]
    seq = Sequence(scene, cam, poses, [T0] * N_FRAMES)
    pts, kinds = scene.scene_points()
    sel = np.isin(kinds, WALL_KINDS)
    uv, depth = project_points(pts[sel], C0, p0, cam)
    # the wall point right of the centre, so that it leaves the image after ~20 frames
    ok = (depth > 5) & (depth < 30) & (uv[:, 0] > 480) & (uv[:, 0] < 650) & (uv[:, 1] > 60)
    assert ok.any()
    return seq, pts[sel][np.flatnonzero(ok)[0]]


# ------------------------------------------------------------------------ the tracker


def run(seq: Sequence, tracker: TargetTracker, start_uv: np.ndarray, images=None):
    images = seq.images if images is None else images
    tracker.init(images[0], start_uv)
    return [tracker.update(img) for img in images[1:]]


def test_tracks_a_quay_point_along_the_berthing_path(along_path):
    seq, point = along_path
    truth = seq.truth(point)
    assert np.linalg.norm(truth[-1] - truth[0]) > 10.0  # the point does move in the image
    results = run(seq, TargetTracker(seed=0), truth[0])
    assert all(r.status == "tracking" for r in results)
    err = np.array([np.linalg.norm(r.uv - t) for r, t in zip(results, truth[1:], strict=True)])
    assert np.median(err) < 1.0 and err.max() < 3.0, err
    assert all(r.score > 0.8 for r in results)
    # the particle cloud stays on the target (resampled, moved with the flow and the snap)
    assert all(np.linalg.norm(r.particles.mean(axis=0) - r.uv) < 15.0 for r in results)
    # the ablations of seed 002 fig. 7 run on the same frames
    tmpl = run(seq, TargetTracker(method="template", seed=0), truth[0])
    assert np.median([np.linalg.norm(r.uv - t) for r, t in zip(tmpl, truth[1:], strict=True)
                      if r.uv is not None]) < 3.0
    camshift = run(seq, TargetTracker(method="camshift_pf", seed=0), truth[0])
    assert len(camshift) == N_FRAMES - 1 and all(len(r.particles) == 20 for r in camshift)


def test_target_leaving_the_image_is_declared_lost_never_misplaced(panning):
    seq, point = panning
    truth = seq.truth(point)
    half = 31 / 2
    inside = (truth[:, 0] > half + 2) & (truth[:, 0] < seq.cam.width - half - 3)
    assert inside[0] and not inside[-1]  # it does leave
    results = run(seq, TargetTracker(seed=0), truth[0])
    for r, t, ok in zip(results, truth[1:], inside[1:], strict=True):
        if r.status == "tracking":
            assert ok and np.linalg.norm(r.uv - t) < 3.0, (r.uv, t)
        else:
            assert r.uv is None and r.reason
    first_out = int(np.argmin(inside))
    assert all(r.status == "tracking" for r in results[:first_out - 2])
    assert all(r.status == "lost" for r in results[first_out:])


def test_loss_on_a_blank_or_occluded_frame_and_reacquisition(along_path):
    seq, point = along_path
    truth = seq.truth(point)
    tr = TargetTracker(seed=0)
    tr.init(seq.images[0], truth[0])
    for img in seq.images[1:5]:
        assert tr.update(img).status == "tracking"
    blank = np.full_like(seq.images[5], 128)
    lost = tr.update(blank)
    assert lost.status == "lost" and lost.uv is None and lost.score < 0.55
    back = tr.update(seq.images[6])  # the target is visible again near where it was
    assert back.status == "tracking" and np.linalg.norm(back.uv - truth[6]) < 2.0
    # an occluder pasted over the target
    occluded = seq.images[7].copy()
    u, v = np.round(truth[7]).astype(int)
    occluded[v - 25:v + 26, u - 25:u + 26] = (40, 60, 70)
    assert tr.update(occluded).status == "lost"
    # re-acquisition from a predicted position (its 3-D point projected with the pose)
    found = tr.reacquire(seq.images[9], truth[9] + np.array([6.0, -4.0]))
    assert found.status == "tracking" and np.linalg.norm(found.uv - truth[9]) < 2.0
    far = TargetTracker(seed=0)
    far.init(seq.images[0], truth[0])
    assert far.reacquire(seq.images[9], truth[9] + np.array([200.0, 0.0])).status == "lost"


def test_systematic_resampling_counts():
    w = np.array([0.5, 0.25, 0.25, 0.0])
    rng = np.random.default_rng(3)
    idx = resample_indexes(w, rng)
    np.testing.assert_array_equal(np.bincount(idx, minlength=4), [2, 1, 1, 0])
    for _ in range(20):
        w = rng.random(20) ** 3
        counts = np.bincount(resample_indexes(w, rng), minlength=20)
        expected = 20 * w / w.sum()
        # systematic resampling: every count is the floor or the ceiling of N w
        assert counts.sum() == 20 and np.all(np.abs(counts - expected) < 1.0 + 1e-9)
    # unnormalised weights are normalised; a weight of zero is never drawn
    idx = resample_indexes(np.array([0.0, 3.0, 1.0]), rng)
    assert 0 not in idx and np.bincount(idx, minlength=3)[1] >= 2
    # the tracker's generator alone decides: the same seed, the same draw
    draws = [resample_indexes(rng.random(20), np.random.default_rng(7)) for rng in
             (np.random.default_rng(1), np.random.default_rng(1))]
    np.testing.assert_array_equal(draws[0], draws[1])


def test_init_outside_the_image_is_refused(along_path):
    seq, _ = along_path
    with pytest.raises(ValueError, match="not inside"):
        TargetTracker().init(seq.images[0], (-5.0, 10.0))
    # inside, but too near the edge for the template: said so, not "outside" (a user trial)
    with pytest.raises(ValueError, match=r"within \d+ px of the .* edge: no room"):
        TargetTracker().init(seq.images[0], (4.2, 236.8))
    with pytest.raises(ValueError, match="unknown tracking method"):
        TargetTracker(method="kalman")


# ---------------------------------------------------------------- the designated target


def test_designated_target_locks_its_distance_and_reacquires(along_path):
    """The clicked point from a structure point 15 % too far along its ray: the tracked views
    (true poses) bring the distance to the truth; a blank frame makes it lost and it is found
    again in the next frame; after a jump (a seek) it is re-acquired where its 3-D point
    projects."""
    seq, point = along_path
    truth = seq.truth(point)
    C0, p0 = seq.poses[0]
    ray = point - p0
    start = p0 + 1.15 * ray
    pose_cov = np.diag([1e-4] * 3 + [np.radians(0.02) ** 2] * 3)
    tgt = DesignatedTarget(seq.cam, seq.images[0], truth[0], start, None,
                           CameraView(math.nan, C0, p0, pose_cov), params=TargetParams(), seed=0)
    d0 = abs(np.linalg.norm(start - p0) - np.linalg.norm(point - p0))
    states = []
    for k in range(1, N_FRAMES):
        img = seq.images[k] if k != 12 else np.zeros_like(seq.images[k])
        states.append(tgt.update(img, CameraView(T0 + 0.1 * k, *seq.poses[k], pose_cov)))
    assert states[11].status == "lost" and states[11].uv is None  # the blank frame
    assert states[12].status == "tracking"
    tracked = [s for s in states if s.status == "tracking"]
    assert len(tracked) == N_FRAMES - 2
    C, p = seq.poses[-1]
    err_end = abs(states[-1].distance_m - np.linalg.norm(point - p))
    assert err_end < 0.5 * d0, (err_end, d0)
    assert states[-1].distance_sigma_m < 0.5 * np.linalg.norm(point - p)
    assert states[-1].views == len(tracked)
    # a seek back to frame 5: resumed from the projection of the 3-D point
    back = tgt.resume(seq.images[5], CameraView(T0 + 0.5, *seq.poses[5], pose_cov))
    assert back.status == "tracking" and back.reacquired
    assert np.linalg.norm(back.uv - truth[5]) < 2.0


def test_a_find_away_from_its_3d_point_does_not_take_the_target_back(panning):
    """Once its point has left the image, a look-alike of the target where the image tracker
    dead-reckons it (seed 18's fender: the tracker found the quay's dark band again, 90–350 px
    from the point, and said "tracking" two frames in three) is not the target: it stays
    lost, and says why."""
    seq, point = panning
    truth = seq.truth(point)
    C0, p0 = seq.poses[0]
    pose_cov = np.diag([1e-4] * 3 + [np.radians(0.02) ** 2] * 3)
    tgt = DesignatedTarget(seq.cam, seq.images[0], truth[0], point, None,
                           CameraView(math.nan, C0, p0, pose_cov), params=TargetParams(),
                           seed=0)
    u0, v0 = np.round(truth[0]).astype(int)
    look_alike = seq.images[0][v0 - 20:v0 + 21, u0 - 20:u0 + 21]
    w, h = seq.cam.width, seq.cam.height
    pasted = 0
    for k in range(1, N_FRAMES):
        image = seq.images[k].copy()
        out = not 0 <= truth[k, 0] <= w - 1
        guess = tgt.tracker.uv
        if out and guess is not None:
            u, v = np.clip(np.round(guess).astype(int), 25, [w - 26, h - 26])
            image[v - 20:v + 21, u - 20:u + 21] = look_alike  # where the tracker looks
            pasted += 1
        state = tgt.update(image, CameraView(T0 + 0.1 * k, *seq.poses[k], pose_cov))
        if out:
            assert state.status == "lost" and state.uv is None, (k, state.uv)
        elif state.status == "tracking":
            assert np.linalg.norm(state.uv - truth[k]) < 3.0
    assert pasted >= 3


def test_a_point_too_uncertain_to_predict_takes_nothing_back_at_its_projection(along_path):
    """A click the structure did not place: its point where the ray meets the water plane,
    tens of metres deep along the ray (σ 40 m), 60 m beyond the true one. After a seek the
    point's projection says little — the ray's image spans hundreds of pixels once the ship
    has moved — and a look-alike of the target sits there: the target is not taken back at
    it (dev seed 308: a fender "re-acquired" on another thing, whose track then triangulated
    110 m off with a σ of 7.5 m). Placed well, the same seek takes it back (the test above)."""
    seq, point = along_path
    truth = seq.truth(point)
    C0, p0 = seq.poses[0]
    ray = (point - p0) / np.linalg.norm(point - p0)
    wrong = point + 60.0 * ray
    cov = 40.0 ** 2 * np.outer(ray, ray) + 0.3 ** 2 * np.eye(3)
    pose_cov = np.diag([1e-4] * 3 + [np.radians(0.02) ** 2] * 3)
    tgt = DesignatedTarget(seq.cam, seq.images[0], truth[0], wrong, cov,
                           CameraView(math.nan, C0, p0, pose_cov), params=TargetParams(),
                           seed=0)
    # a seek 30 s on: the ship 6 m to the side of the click's ray
    k = N_FRAMES - 1
    side = np.cross(ray, [0.0, 0.0, 1.0])
    view = CameraView(T0 + 30.0, seq.poses[k][0], seq.poses[k][1] + 6.0 * side / np.linalg.norm(
        side), pose_cov)
    pred = tgt.project(view.C_level_to_camera, view.position_ned)
    true_uv = tgt.project(view.C_level_to_camera, view.position_ned, point)
    assert pred is not None and np.linalg.norm(pred - true_uv) > 100.0  # it projects elsewhere
    u0, v0 = np.round(truth[0]).astype(int)
    image = seq.images[k].copy()
    u, v = np.round(pred).astype(int)
    image[v - 20:v + 21, u - 20:u + 21] = seq.images[0][v0 - 20:v0 + 21, u0 - 20:u0 + 21]
    back = tgt.resume(image, view)
    assert back.status == "lost" and not back.reacquired, back
    assert "too uncertain" in back.reason


def test_designated_target_reanchors_on_converged_structure(along_path):
    """A target whose 3-D point came 15 % too far along its ray takes its point again from
    the structure around the pixel it tracks — only once the points there have converged
    (σ within a few % of their range)."""
    seq, point = along_path
    truth = seq.truth(point)
    C0, p0 = seq.poses[0]
    start = p0 + 1.15 * (point - p0)
    rng = np.random.default_rng(2)
    # structure points on the wall around the true point (a few cm of error), and their pixels
    around = point + rng.normal(0.0, 0.03, (6, 3))
    results = {}
    for name, sigma in (("converged", 0.05), ("converging", 3.0)):
        tgt = DesignatedTarget(seq.cam, seq.images[0], truth[0], start, None,
                               CameraView(math.nan, C0, p0), params=TargetParams(), seed=0)
        C, p = seq.poses[1]
        tgt.update(seq.images[1], CameraView(T0 + 0.1, C, p))
        uv = project_points(around, C, p, seq.cam)[0]
        done = tgt.reanchor(around, np.full(len(around), sigma), uv, CameraView(T0 + 0.1, C, p))
        results[name] = (done, np.linalg.norm(tgt.position_ned - point))
    d0 = np.linalg.norm(start - point)
    assert results["converged"][0] and results["converged"][1] < 0.1 < 0.5 * d0
    assert not results["converging"][0] and results["converging"][1] > 0.5 * d0


def solved_views(seq: Sequence, times: np.ndarray, rotation_sigma: float = 1e-5
                 ) -> SolvedViews:
    """The sequence's true poses as the structure window's solved views."""
    return SolvedViews(np.asarray(times, float), np.array([C for C, _ in seq.poses]),
                       np.array([p for _, p in seq.poses]),
                       np.full(len(times), rotation_sigma**2))


def test_target_tracked_back_and_triangulated_in_the_solved_views(along_path):
    """Clicked on the last frame with its 3-D point 15 % too far along the ray: the click's
    template, tracked back through the earlier frames, gives their views (on the true pixel
    path); triangulated in the solved attitudes they bring the distance to the truth at
    once. Without earlier frames there is nothing to triangulate from yet."""
    seq, point = along_path
    times = T0 + 0.1 * np.arange(N_FRAMES)
    truth = seq.truth(point)
    C, p = seq.poses[-1]
    start = p + 1.15 * (point - p)
    d_true = np.linalg.norm(point - p)
    tgt = DesignatedTarget(seq.cam, seq.images[-1], truth[-1], start, None,
                           CameraView(times[-1], C, p), params=TargetParams(), seed=0,
                           earlier_frames=list(zip(times[:-1], seq.images[:-1], strict=True)))
    assert len(tgt.seen) == N_FRAMES  # every earlier frame tracked back, and the click
    np.testing.assert_allclose(tgt.seen.t, times)
    K, dist = np.asarray(seq.cam.K, float), np.asarray(seq.cam.distortion, float)
    xy_true = cv2.undistortPoints(truth.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    assert np.max(np.linalg.norm(tgt.seen.xy - xy_true, axis=1)) * K[0, 0] < 1.0  # px
    views = solved_views(seq, times)
    assert tgt.refine(views) == N_FRAMES and tgt.refined
    # 1.7 m of baseline, mostly along the line of sight, at 18 m: σ along the ray ~1 m
    err = abs(np.linalg.norm(tgt.position_ned - p) - d_true)
    state = tgt.update(seq.images[-1], CameraView(times[-1] + 0.1, C, p))
    assert err < 0.3 * 0.15 * d_true and err < 2 * state.distance_sigma_m, err
    lone = DesignatedTarget(seq.cam, seq.images[-1], truth[-1], start, None,
                            CameraView(times[-1], C, p), params=TargetParams(), seed=0)
    assert lone.refine(views) == 0 and not lone.refined
    np.testing.assert_allclose(lone.position_ned, start)


def test_refined_target_ignores_the_fused_heading_wander(along_path):
    """The fused heading drifts by 0.1° over the 3 s (between two corrections of the GNSS
    compass); the window's solved attitudes do not. The target's landmark EKF on the fused
    views reads the drift as parallax (1 m off at 18 m); triangulated in the solved views
    (about once a second) the point is several times closer, and the fused views between
    two refinements only check it."""
    seq, point = along_path
    times = T0 + 0.1 * np.arange(N_FRAMES)
    truth = seq.truth(point)
    C0, p0 = seq.poses[0]
    start = p0 + 1.15 * (point - p0)
    pose_cov = np.diag([1e-6] * 3 + [np.radians(0.05) ** 2] * 3)
    drift = np.radians(0.1) * np.arange(N_FRAMES) / N_FRAMES
    fused = [(C @ rot_z(a), p) for (C, p), a in zip(seq.poses, drift, strict=True)]
    # the tracker's pixel noise on these renderings (0.1 px measured), with a margin
    params = TargetParams(landmark=replace(TargetParams().landmark, pixel_sigma_px=0.3))
    ekf_only, refined = (DesignatedTarget(seq.cam, seq.images[0], truth[0], start, None,
                                          CameraView(times[0], *fused[0], pose_cov),
                                          params=params, seed=0) for _ in range(2))
    views = solved_views(seq, times)
    for k in range(1, N_FRAMES):
        for tgt in (ekf_only, refined):
            tgt.update(seq.images[k], CameraView(times[k], *fused[k], pose_cov))
        if k == 10:
            assert refined.refine(views) == 11
            kept = refined.position_ned
        if k == N_FRAMES - 1:
            np.testing.assert_allclose(refined.position_ned, kept)  # checked, not moved
            assert refined.refine(views) == N_FRAMES
    p = seq.poses[-1][1]
    d_true = np.linalg.norm(point - p)
    err = {name: abs(np.linalg.norm(t.position_ned - p) - d_true)
           for name, t in (("ekf", ekf_only), ("refined", refined))}
    assert err["refined"] < 0.25 * err["ekf"] and err["refined"] < 0.15, err


def test_triangulation_drops_a_slipped_track():
    """A point seen from 40 views along a 10 m baseline: exact rays give it back; when the
    last quarter of the track slipped onto a feature 0.5 m aside, those rays are dropped
    and the point stays; a view time with no solved view is not used."""
    rng = np.random.default_rng(4)
    X = np.array([20.0, 5.0, -2.0])
    centres = np.column_stack([np.linspace(0, 10, 40), np.zeros(40), np.zeros(40)])
    C = np.array([rot_z(rng.normal(0, 0.01)).T for _ in range(40)])  # camera = level axes

    def pixels(point: np.ndarray) -> np.ndarray:
        xc = np.einsum("nij,nj->ni", C, point - centres)
        return xc[:, :2] / xc[:, 2:]

    # a camera looking along +down would see nothing; these look along +z (down): fine for
    # the geometry, the rays only need a positive depth
    X = np.array([3.0, 4.0, 20.0])
    xy = pixels(X)
    var = np.full(40, (1.0 / 800) ** 2)
    prior_x, prior_info = X + np.array([0.0, 0.0, 3.0]), np.eye(3) / 25.0
    from estimator.landmarks import triangulate_point
    est, info, used = triangulate_point(C, centres, xy, var, prior_x, prior_info)
    assert used.all() and np.linalg.norm(est - X) < 1e-3
    slipped = xy.copy()
    slipped[30:] = pixels(X + np.array([0.5, 0.0, 0.0]))[30:]
    est, _info, used = triangulate_point(C, centres, slipped, var, prior_x, prior_info)
    assert not used[30:].any() and used[:30].all() and np.linalg.norm(est - X) < 1e-2
    views = SolvedViews(np.arange(4.0), C[:4], centres[:4], np.array([1e-8, np.inf, 1e-8, 1e-8]))
    np.testing.assert_array_equal(views.at(np.array([0.0005, 1.0, 2.5, 3.0, -7.0])),
                                  [0, -1, -1, 3, -1])


def test_triangulation_gates_its_first_views_against_the_prior():
    """Seed 9's fender: the track back from the click jumped to a look-alike 6° aside within
    the first ten views. Taken ungated, rays that diverge from nearby cameras "meet" at the
    cameras, with a 2 cm σ 21 m short; gated against the click's point they are left out."""
    from estimator.landmarks import triangulate_point
    n = 10
    X = np.array([2.0, 0.0, 21.0])  # the camera looks along +z
    centres = np.column_stack([np.zeros(n), np.zeros(n), -0.3 * np.arange(n)])
    C = np.repeat(np.eye(3)[None], n, axis=0)
    xy = (X[:2] - centres[:, :2]) / (X[2] - centres[:, 2:])
    look_alike = X + np.array([2.2, 0.0, 0.0])  # 6° aside at 21 m
    xy[6:] = ((look_alike[:2] - centres[:, :2]) / (look_alike[2] - centres[:, 2:]))[6:]
    var = np.full(n, (1.5 / 800) ** 2)
    P0 = np.diag([0.05, 0.05, 0.7]) ** 2  # tight across the click's ray, 0.7 m along it
    est, info, used = triangulate_point(C, centres, xy, var, X + [0.0, 0.0, 0.25],
                                        np.linalg.inv(P0))
    assert used[:6].all() and not used[6:].any()
    sigma = np.sqrt(np.diag(np.linalg.inv(info)))
    assert abs(est[2] - X[2]) <= 2 * sigma[2] and np.linalg.norm(est - X) < 0.5


def test_triangulation_leaves_out_a_stretch_that_slid_and_came_back():
    """Seed 1's quay point: tracked back past a moored boat, the template slid up to 15 px
    with the boat's edge over 10 s, then came back onto the wall. One chunk at a time, the
    slow slide's first rays pass the gate and pull the point along the click's ray; the
    consensus along that ray leaves the whole stretch out."""
    from estimator.landmarks import triangulate_point
    m = 120
    centres = np.column_stack([np.linspace(0, -12, m), np.linspace(0, -3, m), np.zeros(m)])
    C = np.repeat(np.eye(3)[None], m, axis=0)
    X = np.array([4.0, 1.0, 20.0])
    xy = (X[:2] - centres[:, :2]) / (X[2] - centres[:, 2:])
    slide = np.interp(np.arange(m), [20, 60, 100], [0.0, 15.0, 0.0]) / 800  # px → rad
    xy[:, 0] += slide
    var = np.full(m, (1.5 / 800) ** 2)
    u = X / np.linalg.norm(X)
    P0 = 0.05**2 * np.eye(3) + (1.5**2 - 0.05**2) * np.outer(u, u)  # the click: 1.5 m along
    est, info, used = triangulate_point(C, centres, xy, var, X + 0.4 * u, np.linalg.inv(P0))
    assert not used[35:85].any() and used[:20].all() and used[100:].all()
    sigma_along = float(np.sqrt(u @ np.linalg.inv(info) @ u))
    assert abs((est - X) @ u) < max(0.05, 2 * sigma_along), (est - X, sigma_along)


def test_track_back_follows_the_image_flow_not_a_look_alike():
    """A row of identical fenders on a plain band of a textured wall moving 9 px a frame: the
    template search alone (±34 px) finds the same best score on the neighbour it reaches
    first; the flow of the wall's texture around the point puts the search on the right
    one."""
    rng = np.random.default_rng(5)
    wall = cv2.GaussianBlur(rng.integers(0, 255, (400, 1400), dtype=np.uint8), (5, 5), 0)
    wall = (0.35 * wall + 80).astype(np.uint8)
    wall[175:222] = 120  # a plain band (painted concrete) ...
    for x in range(60, 1400, 24):  # ... with fenders 24 px apart: 12×16 px dark boards
        wall[190:206, x - 6:x + 6] = 20
    frames = [wall[100:300, 400 - 9 * k:1040 - 9 * k].copy() for k in range(12)]
    start = np.array([316.0, 98.0])  # a fender's centre in frame 0 (x = 716 on the wall)
    plain, guided = TargetTracker(method="template"), TargetTracker(method="template")
    for tr in (plain, guided):
        tr.init(frames[0], start, 31)
    for k in range(1, len(frames)):
        truth = start + [9.0 * k, 0.0]
        r = guided.follow_flow(frames[k])
        assert r.status == "tracking" and np.linalg.norm(r.uv - truth) < 1.0, (k, r.uv, truth)
        plain.update(frames[k])
    assert np.linalg.norm(plain.uv - (start + [9.0 * 11, 0.0])) > 10.0  # the plain one slipped


def test_the_full_tracker_stays_on_its_window_of_a_repeated_facade():
    """A far facade: identical windows 19 px apart on a plain wall, drifting 2 px a frame, each
    frame with its own sensor noise. Every window within the ±34 px search scores alike, so
    the best match is often a neighbour; continuity decides (the best match where the flow
    puts the point, when it is nearly as good), and the track stays on the clicked window.
    (Found on the 12 s page recording: a click on a building slid one window up in 0.4 s.)"""
    rng = np.random.default_rng(7)
    wall = np.full((500, 900), 150, np.uint8)
    for y in range(20, 480, 19):
        for x in range(20, 880, 16):
            wall[y:y + 9, x:x + 7] = 60  # a window
    wall = cv2.GaussianBlur(wall, (3, 3), 0)
    start = np.array([320.0 + 3.0, 200.0 + 4.0])  # a window's centre in frame 0
    frames = []
    for k in range(40):
        img = wall[150 - k:550 - k, 100 - 2 * k:740 - 2 * k].astype(float)
        img = img + rng.normal(0.0, 6.0, img.shape)
        frames.append(cv2.cvtColor(np.clip(img, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR))
    tracker = TargetTracker(seed=3)
    tracker.init(frames[0], start, 31)
    for k in range(1, len(frames)):
        r = tracker.update(frames[k])
        truth = start + [2.0 * k, 1.0 * k]
        assert r.status == "tracking" and np.linalg.norm(r.uv - truth) < 3.0, (k, r.uv, truth)


def fender_row(shift: float, rng: np.random.Generator) -> np.ndarray:
    """A quay wall with a row of identical dark fenders 40 px apart, moved ``shift`` px to
    the right, with its own sensor noise (BGR)."""
    wall = np.full((300, 700), 150.0)
    x0 = 100 + shift
    for k in range(12):
        x = int(round(x0 + 40 * k))
        wall[135:155, x:x + 14] = 50.0
    wall = cv2.GaussianBlur(wall, (5, 5), 0) + rng.normal(0.0, 4.0, wall.shape)
    return cv2.cvtColor(np.clip(wall, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)


def test_a_lost_target_is_not_taken_back_among_look_alikes():
    """A fender in a row of identical ones, lost on a blank frame; the picture comes back
    moved half a fender spacing (the camera pitched): the two fenders either side of where
    the tracker looks score alike, and nothing tells which one was clicked. It stays lost and
    says why — taken back, it would be on a neighbour as often as not (dev seed 308: a fender
    re-found 28 px off, then triangulated 4.7 m off with a σ of 0.4 m). Where only one
    fender is in reach it is taken back."""
    rng = np.random.default_rng(5)
    start = np.array([100.0 + 40 * 6 + 7, 145.0])  # the seventh fender's centre
    tracker = TargetTracker(seed=1)
    tracker.init(fender_row(0.0, rng), start, 31)
    for k in range(1, 4):
        r = tracker.update(fender_row(2.0 * k, rng))
        assert r.status == "tracking" and np.linalg.norm(r.uv - start - [2.0 * k, 0]) < 1.5
    blank = np.full_like(fender_row(0.0, rng), 128)
    assert tracker.update(blank).status == "lost"
    for _ in range(3):  # every frame from now on: the clicked fender 20 px right
        r = tracker.update(fender_row(6.0 + 20.0, rng))
        assert r.status == "lost" and r.uv is None and "look-alikes" in r.reason, r
    # ... nor at a predicted position with a neighbour as near
    r = tracker.reacquire(fender_row(26.0, rng), start + [6.0, 0.0], 30.0)
    assert r.status == "lost" and "look-alikes" in r.reason, r
    # a single fender in reach is found again
    lone = fender_row(26.0, rng)
    lone[:, :int(start[0]) + 6] = lone[:, int(start[0]) + 6:int(start[0]) + 7]
    lone[:, int(start[0]) + 46:] = lone[:, int(start[0]) + 45:int(start[0]) + 46]
    r = tracker.reacquire(lone, start + [20.0, 0.0], 30.0)
    assert r.status == "tracking" and np.linalg.norm(r.uv - start - [26.0, 0]) < 1.5, r


def test_nearest_surface_prefers_the_foreground_unless_a_point_is_clicked():
    ranges = np.array([61.0, 20.5, 63.0, 21.0, 45.0])
    pixels = np.array([2.5, 9.0, 6.0, 11.0, 7.0])
    np.testing.assert_array_equal(nearest_surface(ranges, pixels),
                                  [False, True, False, True, False])
    # clicked on the drawn point (2.5 px away at most): its surface
    np.testing.assert_array_equal(nearest_surface(ranges, pixels, on_point_px=3.0),
                                  [True, False, True, False, False])
    cam = camera_calibration(SMALL_BOAT)
    C = np.eye(3)
    pts = np.array([[0.0, 0.0, 20.0], [0.2, 0.0, 20.5], [0.1, 0.1, 60.0], [0.0, 0.2, 61.0]])
    uv = project_points(pts, C, np.zeros(3), cam)[0]
    click = uv[0] + np.array([4.0, 4.0])
    X, P, idx = structure_point_at(pts, np.full(4, 0.2), uv, click, np.zeros(3),
                                   np.array([0.0, 0.0, 1.0]), cam.K[0, 0])
    assert set(idx) == {0, 1} and X[2] == pytest.approx(20.25, abs=0.3)
    s_ray, s_lat = np.sqrt(P[2, 2]), np.sqrt(P[0, 0])
    assert s_ray > 5 * s_lat  # uncertain along the ray, not across
    # On one surface, converged anchors (σ 1 % of the range) are trusted along the ray to a
    # few %; anchors still converging (σ 3 m) leave the point 10 % uncertain, for its views
    # to settle.
    sig_ray = {}
    for s in (0.2, 3.0):
        _X, P1, _ = structure_point_at(pts[:2], np.full(2, s), uv[:2], click, np.zeros(3),
                                       np.array([0.0, 0.0, 1.0]), cam.K[0, 0])
        sig_ray[s] = np.sqrt(P1[2, 2])
    assert sig_ray[0.2] < 0.05 * 20.25 < 0.1 * 20.25 < sig_ray[3.0]
    assert structure_point_at(pts, np.full(4, 0.2), uv, uv[0] + 100.0, np.zeros(3),
                              np.array([0.0, 0.0, 1.0]), cam.K[0, 0]) is None


# -------------------------------------------------------------------------- evaluation


def test_evaluation_smoke_on_the_simulated_recording(sim_recording):
    """The evaluation end to end on the 12 s test recording (quay far away: a click on a
    building corner), through the engine path; figures are checked for shape and sanity."""
    from engine.driver import run_vo
    from estimator.frames import euler_to_dcm
    from estimator.pipeline import FusionOptions
    from evaluation.landmarks import evaluate_landmarks
    from evaluation.records import to_json
    from evaluation.runs import Collect, fuse
    from evaluation.text import format_tracking_report
    from evaluation.tracking import BEYOND_2_SIGMA_CAUSES, error_source_shares, evaluate_tracking
    from evaluation.truth import Click
    from recordings.format import load

    rec = load(sim_recording)
    k = 100  # the structure has converged points by then (10 s into the recording)
    pos, _v, e = rec.reference.interpolate(rec.frame_times[k])
    C_bl = euler_to_dcm(*e)
    cam = rec.calibration.camera
    C = (C_bl @ cam.C_camera_to_body).T
    c = pos + C_bl @ cam.lever_arm_body
    uv, depth = project_points(rec.scene_points, C, c, cam)
    ok = np.flatnonzero((depth > 0) & (uv[:, 0] > 200) & (uv[:, 0] < 760) & (uv[:, 1] > 100)
                        & (uv[:, 1] < 500))
    run_ = fuse(rec, run_vo(rec), FusionOptions(), "full", np.inf,
                Collect(structures_from=k, landmarks=True))
    assert run_.origin_time is not None and k in run_.structures
    # Click the scene point nearest (in the image) to a reported structure point: only
    # converged landmarks are reported, 10 s into the recording only a few.
    pts = run_.structures[k].points + rec.reference.interpolate(run_.origin_time)[0]
    assert len(pts) > 0
    uv_s, _ = project_points(pts, C, c, cam)
    gap = np.nanmin(np.linalg.norm(uv[ok, None, :] - uv_s[None], axis=2), axis=1)
    j = int(ok[np.argmin(gap)])
    clicks = [Click(frame=k, uv=(float(uv[j, 0]), float(uv[j, 1])), point=j, label="near")]
    typed = evaluate_tracking(rec, run_, clicks)
    tr = to_json(typed)
    assert set(tr["methods"]) == {"designated", "full", "template", "camshift_pf"}
    d = tr["methods"]["designated"]
    assert d["frames"] == len(rec.frame_times) - k - 1
    assert d["pixel_error"]["n"] > 0 and d["pixel_error"]["median"] < 3.0
    assert d["undetected_loss_frames"] == 0
    # what limits the distance: the true pixels and the true poses give the true point (a
    # wrong frame or a wrong projection in the decomposition would not)
    src = typed.clicks[0].error_sources
    assert src is not None and set(src) == {"as_is", "true_pixels", "true_poses", "true_both",
                                               "true_range"}
    assert abs(src["true_both"]) < 0.005, src
    assert all(np.isfinite(v) for v in src.values()), src
    shares = error_source_shares(typed.clicks)
    assert shares is not None and shares["true_both"] == 1.0 and shares["clicks"] == 1.0
    # the designation as the officer read it at the click, scored against the truth: on a
    # converged structure point, within its 2σ; the frames beyond 2σ all have a cause, as
    # many as the share within 2σ leaves
    c0 = typed.clicks[0]
    assert c0.designation_sigma_m is not None and c0.designation_sigma_m > 0
    assert abs(c0.designation_error_m) <= 2 * c0.designation_sigma_m
    beyond = typed.methods["designated"].beyond_2_sigma
    n_sigma = typed.methods["designated"].distance_m.n
    assert beyond is not None and set(beyond) == set(BEYOND_2_SIGMA_CAUSES)
    assert sum(beyond.values()) == round(
        (1 - typed.methods["designated"].distance_within_2_sigma) * n_sigma)
    assert c0.per_method["designated"].beyond_2_sigma == beyond  # the one click's
    lm_typed = evaluate_landmarks(rec, run_)
    lm = to_json(lm_typed)
    assert lm["points"] > 0 and lm["scene_point_match"]["raw"]["points"] > 0
    assert lm["depth_truth"] is not None and lm["error_vs_views"]
    views = [row["views"] for row in lm["error_vs_views"]]
    assert views == sorted(views)
    text = format_tracking_report(typed, lm_typed)
    assert "Designated-target tracking" in text and "with the true pixels" in text


def test_frames_beyond_two_sigma_are_put_down_to_their_cause():
    """Four clicks of hand-made frames, each beyond 2σ for its own reason: an undetected
    loss (12 px off while "tracking") counts as the track lost whatever else holds; a click
    designated beyond its own 2σ as the designation; a target beyond 2σ from its first
    tracked frame (its track back) as the click's views; one that goes beyond 2σ later as
    the later views. Frames within 2σ, lost or without a σ count nowhere."""
    from evaluation.tracking import _beyond_2_sigma, _Row

    def row(err_m: float, px: float = 0.5, tracking: bool = True, sigma: float = 0.1) -> _Row:
        return _Row(frame=0, tracking=tracking, in_view=True, px_error=px,
                    distance_error=err_m, true_range=10.0, fixed_error=0.0, reacquired=False,
                    guess_px_error=px, since_click_s=0.0, distance_sigma=sigma)

    clicks = [
        [row(0.05), row(0.5, px=12.0), row(0.05)],  # a slide nobody noticed
        [row(0.5), row(0.5), row(0.5, tracking=False)],  # designated 5σ off
        [row(0.3), row(0.3), row(0.05), row(0.3, sigma=math.nan)],  # off from its first view
        [row(0.05), row(0.05), row(0.4), row(0.4)],  # slid off later, unnoticed by its σ
    ]
    out = _beyond_2_sigma(clicks, [False, True, False, False])
    assert out == {"track_lost": 1, "designation": 2, "click_views": 2, "later_views": 2}
    # the same frames with every designation within its σ: the second click's first frame
    # is beyond 2σ, so its frames are the click's views'
    out = _beyond_2_sigma(clicks, [False] * 4)
    assert out == {"track_lost": 1, "designation": 0, "click_views": 4, "later_views": 2}


def test_a_common_attitude_error_moves_the_triangulated_point():
    """Views along a 10 m baseline whose attitudes share a 0.1° error: the point they
    triangulate moves as ``common_rotation_jacobian`` says (against a re-triangulation), by
    centimetres at 20 m — which is why it is added to a refined target's covariance."""
    from estimator.landmarks import common_rotation_jacobian, triangulate_point
    m = 40
    centres = np.column_stack([np.linspace(0, 10, m), np.zeros(m), np.zeros(m)])
    C = np.repeat(np.eye(3)[None], m, axis=0)
    X = np.array([3.0, 4.0, 20.0])
    xy = (X[:2] - centres[:, :2]) / (X[2] - centres[:, 2:])
    var = np.full(m, (1.0 / 800) ** 2)
    prior = (X + [0.0, 0.0, 1.0], np.eye(3) / 25.0)
    est, _, used = triangulate_point(C, centres, xy, var, *prior)
    J = common_rotation_jacobian(C, centres, xy, var, est, *prior)
    from estimator.frames import skew
    e = np.radians([0.1, 0.0, 0.0])  # about an axis across the line of sight
    turned = C @ (np.eye(3) - skew(e))
    moved, _, _ = triangulate_point(turned, centres, xy, var, *prior)
    assert used.all() and np.linalg.norm(moved - est) > 0.02
    np.testing.assert_allclose(J @ e, moved - est, atol=0.1 * np.linalg.norm(moved - est))


def test_water_plane_designation_reaches_what_stands_on_the_water():
    """A click the port structure does not place falls back to where its ray meets the water.
    What the officer clicked may stand on the water (a fender, the quay face, a moored hull)
    up to ``WATER_PLANE_STANDING_M`` above it, nearer along the ray: the distance's 2σ reaches
    that far (seeds 112 and 113 had fenders designated 7–23 m beyond them with 2σ of 3–5 m)."""
    from engine.camera import CameraPose, Projector
    from engine.targets import WATER_PLANE_STANDING_M, Structure, designate

    cam = camera_calibration(SMALL_BOAT)
    projector = Projector(cam)
    C_level_to_camera = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # north
    for height in (2.0, 12.0):  # camera above the water: a small boat, a large ship's bridge
        view = CameraView(0.0, C_level_to_camera, np.array([0.0, 0.0, -height]), None)
        u, v = 0.5 * cam.width, 0.5 * cam.height + 60.0  # below the horizon
        des = designate(projector, view, u, v, Structure(None), 0.0)
        assert des.method == "water-plane"
        ray = projector.pixel_ray(CameraPose(C_level_to_camera, view.position_ned), u, v)
        ray = ray / np.linalg.norm(ray)
        r_water = float(np.linalg.norm(des.position_ned - view.position_ned))
        assert des.position_ned[2] == pytest.approx(0.0, abs=1e-9)
        sigma = math.sqrt(ray @ des.covariance @ ray)
        standing = min(WATER_PLANE_STANDING_M, height)
        r_standing = r_water * (1.0 - standing / height)  # on the ray, that high above water
        assert r_water - 2.0 * sigma <= r_standing + 1e-6, (height, r_water, sigma)
        assert sigma >= 0.1 * r_water - 1e-9


def test_a_click_anchored_beside_its_template_reaches_the_water_in_its_sigma():
    """A click whose structure points all lie outside its template (the widened radius):
    here a moored hull's, 20 px beside a click on the quay behind it, 30 % nearer. Nothing
    the target's tracker follows ties the click to the hull, so its σ reaches the quay,
    anything up to where the ray meets the water (on the yardstick's seeds such clicks were
    within 2σ for 19 of 26, 3-4σ short on hulls and fenders). So do anchors in the
    template's corners, farther than half its side (a quay click on an unseen seed read
    2.9 m short under σ 1.0 m from a hull 16-19 px away), and a single anchor beside the
    click, which has no extent to carry the click onto its surface (the 12 s test recording:
    a building corner 150 m off read 105 m ± 3 m from one point 14 px away). Two anchors
    near the click, or one on it, keep the tight σ of converged points."""
    from engine.camera import CameraPose, Projector, water_plane_point
    from engine.targets import Structure, designate, target_window

    cam = camera_calibration(SMALL_BOAT)
    projector = Projector(cam)
    C_level_to_camera = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # north
    view = CameraView(0.0, C_level_to_camera, np.array([0.0, 0.0, -2.0]), None)
    pose = CameraPose(C_level_to_camera, view.position_ned)
    u, v = 0.5 * cam.width, 0.5 * cam.height + 60.0  # below the horizon
    ray = projector.pixel_ray(pose, u, v)
    ray = ray / np.linalg.norm(ray)
    r_water = float(np.linalg.norm(water_plane_point(view.position_ned, ray) - view.position_ned))
    r_quay, r_hull = 0.85 * r_water, 0.6 * r_water
    assert target_window(cam.width) // 2 < 20
    half = target_window(cam.width) // 2
    for offsets, covered in ((((20.0, 2.0), (22.0, -3.0)), True),
                             # in the template's square, in its corner: 17-18 px off
                             (((half - 2.0, half - 3.0), (half - 3.0, half - 2.0)), True),
                             (((8.0, 2.0),), True),  # one point beside the click
                             (((0.5, -0.5),), False),  # one point on it
                             (((8.0, 2.0), (10.0, -3.0)), False)):
        pts = []
        for du, dv in offsets:
            d = projector.pixel_ray(pose, u + du, v + dv)
            pts.append(view.position_ned + r_hull * d / np.linalg.norm(d))
        pts = np.array(pts)
        structure = Structure(0.0, pts, 0.01 * r_hull * np.ones(len(pts)),
                              np.arange(len(pts)))
        des = designate(projector, view, u, v, structure, 0.0)
        assert des.method == "structure" and len(des.anchor_ids) == len(pts)
        r = float(np.linalg.norm(des.position_ned - view.position_ned))
        sigma = math.sqrt(ray @ des.covariance @ ray)
        assert r == pytest.approx(r_hull, rel=0.01)
        assert (abs(r_quay - r) <= 2.0 * sigma) == covered, (offsets, r, sigma, r_quay)
        assert (abs(r_water - r) <= 2.0 * sigma + 1e-6) == covered
        if not covered:
            assert sigma < 0.05 * r


def test_no_water_plane_distance_where_a_pixel_moves_it_by_metres():
    """Near the horizon one pixel moves where a ray meets the water by tens of metres: a user
    trial read "796 m ±398" for a quay corner 37 m off (no structure there yet) and "4662 m"
    for a fender at 104 m. Beyond a tenth of focal length x camera height the click is
    refused with the reason; nearer, the water plane gives the distance as before."""
    from engine.camera import CameraPose, Projector
    from engine.targets import (
        WATER_PLANE_MAX_PIXEL_FRACTION,
        DesignationError,
        Structure,
        designate,
    )

    cam = camera_calibration(SMALL_BOAT)
    projector = Projector(cam)
    C_level_to_camera = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # north
    height = 2.0
    view = CameraView(0.0, C_level_to_camera, np.array([0.0, 0.0, -height]), None)
    pose = CameraPose(C_level_to_camera, view.position_ned)
    limit = WATER_PLANE_MAX_PIXEL_FRACTION * cam.focal_px * height
    for below_px, refused in ((1.5, True), (8.0, True), (60.0, False)):
        u, v = 0.5 * cam.width, cam.K[1][2] + below_px  # this far below the horizon
        ray = projector.pixel_ray(pose, u, v)
        reach = height / ray[2] * float(np.linalg.norm(ray[:2]))
        assert (reach > limit) == refused, (below_px, reach, limit)
        if refused:
            with pytest.raises(DesignationError, match="one pixel moves it"):
                designate(projector, view, u, v, Structure(None), 0.0)
            # one pixel there does move it by more than the fraction
            lower = projector.pixel_ray(pose, u, v + 1.0)
            assert reach - height / lower[2] * float(np.linalg.norm(lower[:2])) \
                > WATER_PLANE_MAX_PIXEL_FRACTION * 0.5 * reach
        else:
            assert designate(projector, view, u, v, Structure(None), 0.0).method == "water-plane"


def test_a_click_on_a_reflection_is_placed_on_the_water():
    """Calm water mirrors the buildings: their reflections are structure points metres under
    the water (an unseen seed's click there read 94.8 ±17.9 m, 8.4 m under the water, for
    the water 17 m away). Nothing the ship can run into is there; the pixel shows the water,
    which its plane places."""
    from engine.camera import CameraPose, Projector
    from engine.targets import Structure, designate

    cam = camera_calibration(SMALL_BOAT)
    projector = Projector(cam)
    C_level_to_camera = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # north
    view = CameraView(0.0, C_level_to_camera, np.array([0.0, 0.0, -2.0]), None)
    pose = CameraPose(C_level_to_camera, view.position_ned)
    u, v = 0.5 * cam.width, 0.5 * cam.height + 30.0
    ray = projector.pixel_ray(pose, u, v)
    ray = ray / np.linalg.norm(ray)
    r_water = 2.0 / ray[2]
    # a building 60 m off mirrored: its points on this pixel's ray, 3-4 times beyond the water
    mirrored = np.array([view.position_ned + k * r_water * ray for k in (3.0, 3.2, 3.5)])
    assert (mirrored[:, 2] > 3.0).all()  # metres under the water (down 0)
    structure = Structure(0.0, mirrored, np.full(3, 0.3), np.arange(3))
    des = designate(projector, view, u, v, structure, 0.0)
    assert des.method == "water-plane"
    assert np.linalg.norm(des.position_ned - view.position_ned) == pytest.approx(r_water)
    # without the water level nothing says they are under it: the structure places the click
    assert designate(projector, view, u, v, structure, None).method == "structure"


def baseline_views(m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``m`` views along a 10 m baseline, each looking down L's third axis, of a point 20 m
    away: attitudes, camera centres, the point and its normalised pixels."""
    centres = np.column_stack([np.linspace(0, 10, m), np.zeros(m), np.zeros(m)])
    C = np.repeat(np.eye(3)[None], m, axis=0)
    X = np.array([3.0, 4.0, 20.0])
    return C, centres, X, (X[:2] - centres[:, :2]) / (X[2] - centres[:, 2:])


def test_a_common_track_drift_moves_the_triangulated_point():
    """Views along a 10 m baseline, 20 s of them, whose pixels slide at a common rate (a
    template drifting as the target grows): 0.25 px/s moves the point they triangulate as
    ``common_drift_jacobian`` says (against a re-triangulation), by decimetres at 20 m — far
    more than their independent 1-px noise says, which is why a refined target's covariance
    carries it. So does a drift of the camera centres."""
    from estimator.landmarks import common_drift_jacobian, triangulate_point
    m, f = 40, 800.0
    C, centres, X, xy = baseline_views(m)
    var = np.full(m, (1.0 / f) ** 2)
    prior = (X + [0.0, 0.0, 1.0], np.eye(3) / 25.0)
    dt = np.linspace(-20.0, 0.0, m)  # tracked back from the click (the last view)
    est, info, used = triangulate_point(C, centres, xy, var, *prior)
    J = common_drift_jacobian(C, centres, xy, var, est, *prior, dt)
    w = np.array([0.25, 0.0]) / f  # along the baseline: where it reads as depth
    moved, _, _ = triangulate_point(C, centres, xy + dt[:, None] * w, var, *prior)
    shift = np.linalg.norm(moved - est)
    assert used.all() and shift > 0.1
    assert shift > 5 * math.sqrt(np.linalg.inv(info)[2, 2])  # beyond the independent noise
    np.testing.assert_allclose(J @ w, moved - est, atol=0.1 * shift)
    # no time from the reference view, no drift (but the re-triangulation's rounding over its
    # finite step: 1.1e-9 on one machine, against entries of ~1e3)
    assert np.abs(common_drift_jacobian(C, centres, xy, var, est, *prior, 0 * dt)).max() < 1e-6
    # the camera centres' slow error (the fused position's), 5 mm/s along the baseline
    Jc = common_drift_jacobian(C, centres, xy, var, est, *prior, dt, on="centres")
    v = np.array([0.005, 0.0, 0.0])
    moved, _, _ = triangulate_point(C, centres + dt[:, None] * v, xy, var, *prior)
    shift = np.linalg.norm(moved - est)
    assert Jc.shape == (3, 3) and shift > 0.1
    np.testing.assert_allclose(Jc @ v, moved - est, atol=0.1 * shift)


def test_a_target_whose_views_meet_below_the_water_is_not_refined(along_path):
    """A track that followed a mirror image triangulates below the water plane: refused,
    the click's point kept. The same views with the water below them are taken."""
    seq, point = along_path
    times = T0 + 0.1 * np.arange(N_FRAMES)
    truth = seq.truth(point)
    C, p = seq.poses[-1]
    start = p + 1.15 * (point - p)
    earlier = list(zip(times[:-1], seq.images[:-1], strict=True))
    views = solved_views(seq, times)
    for water_down, refined in ((point[2] + 5.0, True), (point[2] - 0.5, False)):
        tgt = DesignatedTarget(seq.cam, seq.images[-1], truth[-1], start, None,
                               CameraView(times[-1], C, p), params=TargetParams(), seed=0,
                               earlier_frames=earlier, views=views, water_down_m=water_down)
        assert tgt.refined is refined, water_down
        moved = np.linalg.norm(tgt.position_ned - start)
        assert (moved > 0.5) if refined else (moved < 1e-9), (water_down, moved)


def test_a_click_the_structure_does_not_place_is_placed_by_its_own_views(along_path):
    """A click on the quay with no port-structure point near it falls back to where its ray
    meets the water, metres beyond what was clicked (a fender, the quay face: seeds 112 and
    113 had them 7–17 m off). Tracked back through the frames before the click and
    triangulated in the solved views like any target, it lands on what was clicked."""
    from engine.camera import Projector
    from engine.targets import FollowedTarget, Structure, designate

    seq, point = along_path
    times = T0 + 0.1 * np.arange(N_FRAMES)
    truth = seq.truth(point)
    C, p = seq.poses[-1]
    assert point[2] > p[2]  # the clicked point is below the camera: its ray goes down
    projector = Projector(seq.cam)
    view = CameraView(times[-1], C, p)
    d_true = float(np.linalg.norm(point - p))
    des = designate(projector, view, *truth[-1], Structure(None), float(point[2]) + 0.5)
    assert des.method == "water-plane"
    assert np.linalg.norm(des.position_ned - p) - d_true > 2.0
    tgt = FollowedTarget(projector, des, seq.images[-1], tuple(truth[-1]), view, N_FRAMES - 1,
                         list(zip(times[:-1], seq.images[:-1], strict=True)),
                         solved_views(seq, times))
    state = tgt.follow(N_FRAMES, seq.images[-1], CameraView(times[-1] + 0.1, C, p),
                       Structure(None))
    err = abs(state.distance_m - d_true)
    assert tgt.tracker.refined and err < 0.1 * d_true and err < 2 * state.distance_sigma_m, \
        (err, state.distance_sigma_m)


def test_a_click_on_a_depth_edge_reads_the_edge_in_its_sigma(along_path):
    """A click on the quay's coping, buildings 2.5 times as far just above it: the template
    straddles the edge and its track slides as one, between the two surfaces, agreeing with
    itself (an unseen seed's coping clicks 21 m away read 38–73 m at ±1.2–2.4 m). The
    distance the officer reads carries the edge: either surface within 2σ. A click with one
    surface in its template is left as it was."""
    from engine.camera import CameraPose, Projector
    from engine.targets import FollowedTarget, Structure, designate

    seq, point = along_path
    times = T0 + 0.1 * np.arange(N_FRAMES)
    truth = seq.truth(point)
    C, p = seq.poses[-1]
    projector = Projector(seq.cam)
    view = CameraView(times[-1], C, p)
    pose = CameraPose(C, p)
    u, v = truth[-1]
    d_true = float(np.linalg.norm(point - p))

    def at(du: float, dv: float, r: float) -> np.ndarray:
        ray = projector.pixel_ray(pose, u + du, v + dv)
        return p + r * ray / np.linalg.norm(ray)

    quay = [at(-6, 3, d_true), at(5, 4, d_true * 1.02), at(2, -3, d_true * 0.99)]
    behind = [at(-4, -9, 2.5 * d_true), at(7, -11, 2.6 * d_true)]
    for pts, edge in ((quay, False), (quay + behind, True)):
        pts = np.array(pts)
        structure = Structure(times[-1], pts, 0.01 * np.linalg.norm(pts - p, axis=1),
                              np.arange(len(pts)))
        des = designate(projector, view, u, v, structure, None)
        assert des.method == "structure" and (des.edge_span_m is not None) == edge
        tgt = FollowedTarget(projector, des, seq.images[-1], (u, v), view, N_FRAMES - 1,
                             [], None)
        d, sigma = tgt.tracker.distance(view)
        if edge:
            near, far = des.edge_span_m
            assert near == pytest.approx(0.99 * d_true, rel=1e-6)
            assert far == pytest.approx(2.6 * d_true, rel=1e-6)
            assert sigma >= 0.5 * (far - near) and abs(far - d) <= 2.0 * sigma
        else:
            assert sigma < 0.1 * d_true and abs(d - d_true) < 2.0 * sigma


def test_excess_disagreement_is_what_the_covariances_do_not_explain():
    """Two estimates of one point: agreeing within their σ, nothing; 1 m apart with 10 cm
    σ each, the excess (1 − 2·0.01 m²) along the line between them, none across it."""
    from estimator.landmarks import excess_disagreement
    P = 0.01 * np.eye(3)
    assert np.all(excess_disagreement([0, 0, 10], P, [0.05, 0, 10.1], P) == 0.0)
    E = excess_disagreement([0, 0, 10], P, [0, 0, 11], P)
    np.testing.assert_allclose(E, np.diag([0.0, 0.0, 0.98]), atol=1e-12)
    assert np.all(excess_disagreement([1, 2, 3], P, [1, 2, 3], P) == 0.0)


def test_a_track_that_slides_after_the_click_widens_its_sigma(along_path):
    """Clicked mid-way: the views before the click are its template tracked back, those after
    it the forward track. Forward frames shifted 0.3 px more each (a template sliding along
    the quay while its first template still aligns: the track follows the shift, the solved
    poses do not) pull the point metres off; the two sides then disagree, and the point's σ
    covers its error (it claimed 1.6 m for a 4.9 m error before). Without the slide the σ
    stays as the views make it."""
    seq, point = along_path
    times = T0 + 0.1 * np.arange(N_FRAMES)
    truth = seq.truth(point)
    k = N_FRAMES // 2
    views = solved_views(seq, times)
    errors, sigmas = {}, {}
    for slide in (0.0, 0.3):
        C, p = seq.poses[k]
        tgt = DesignatedTarget(seq.cam, seq.images[k], truth[k], p + 1.15 * (point - p), None,
                               CameraView(times[k], C, p), params=TargetParams(), seed=0,
                               earlier_frames=list(zip(times[:k], seq.images[:k], strict=True)))
        for j in range(k + 1, N_FRAMES):
            shift = np.float32([[1, 0, slide * (j - k)], [0, 1, 0]])
            img = cv2.warpAffine(seq.images[j], shift, seq.images[j].shape[1::-1],
                                 borderMode=cv2.BORDER_REPLICATE)
            tgt.update(img, CameraView(times[j], *seq.poses[j]))
        assert tgt.refine(views) >= k + 3, slide  # views on both sides of the click
        C, p = seq.poses[-1]
        d, sigma = tgt.distance(CameraView(times[-1], C, p))
        errors[slide], sigmas[slide] = abs(d - np.linalg.norm(point - p)), sigma
    assert errors[0.3] > 3 * errors[0.0] and errors[0.3] > 1.0, errors
    assert errors[0.3] <= 2 * sigmas[0.3], (errors, sigmas)
    assert errors[0.0] <= 2 * sigmas[0.0] and sigmas[0.0] < 0.5 * sigmas[0.3], sigmas


def test_a_track_back_that_slid_widens_the_sigma_at_the_click(along_path):
    """Clicked with no forward view yet: its point rests on its template tracked back alone,
    here 20 s of views along a 10 m baseline whose older half slid along it at 0.5 px/s
    (the template tracked back slipping along the quay in the dark). The track back's newer
    and older halves disagree, and the σ grows to cover the error (seed 113's quay click
    read 34.1 m ±0.9 for a true 28.6 m while only the forward track's halves were compared;
    here the σ stayed at 0.10 m for a 0.16 m error). Without the slide nothing is added."""
    seq, point = along_path
    m, f = 40, 800.0
    C, centres, X, xy = baseline_views(m)
    t = np.linspace(-20.0, -0.5, m)  # s, before the click at 0
    sigmas = {}
    for rate in (0.0, 0.5):
        tgt = DesignatedTarget(seq.cam, seq.images[-1], seq.truth(point)[-1], point, None,
                               CameraView(T0, *seq.poses[-1]), params=TargetParams(), seed=0)
        tgt.map.focal = f
        slid = xy + np.column_stack([rate / f * np.maximum(-10.0 - t, 0.0), np.zeros(m)])
        tgt.seen = type(tgt.seen)()
        tgt.seen.add(t, slid, np.zeros(m))
        tgt.click_time = 0.0
        tgt.click_point = (X + [0.0, 0.0, 2.0], np.diag([1.0, 1.0, 25.0]))
        assert tgt.refine(SolvedViews(t, C, centres, np.full(m, 1e-12))) >= m // 2
        error = float(np.linalg.norm(tgt.position_ned - X))
        u = (tgt.position_ned - X) / max(error, 1e-12)
        sigmas[rate] = math.sqrt(u @ tgt.covariance @ u)
        if rate == 0.0:
            assert error < 0.01 and error <= 2 * sigmas[rate], (error, sigmas)
        else:
            assert error > 0.1, error
            assert error <= sigmas[rate] and sigmas[rate] > 3 * sigmas[0.0], (error, sigmas)


def test_a_forward_track_sliding_late_shows_in_its_halves_disagreement():
    """Views along a 10 m baseline over 20 s; from the middle on the pixels slide along the
    baseline at 0.5 px/s (a template slipping along the quay). The point of all the views is
    pulled 0.24 m off with a σ of 5 cm; the older and the newer half of the views
    disagree beyond their own covariances, and that excess (``split_disagreement``) covers
    the error. Without the slide the halves agree: nothing is added."""
    from estimator.landmarks import split_disagreement, triangulate_point
    m, f = 40, 800.0
    C, centres, X, xy = baseline_views(m)
    var = np.full(m, (1.5 / f) ** 2)
    prior = (X + [0.0, 0.0, 2.0], np.diag([1.0, 1.0, 1 / 25.0]))
    t = np.linspace(0.0, 20.0, m)
    older, newer = np.arange(m // 2), np.arange(m // 2, m)
    for rate in (0.0, 0.5):
        slid = xy + np.column_stack([rate / f * np.maximum(t - 10.0, 0.0), np.zeros(m)])
        est, info, _ = triangulate_point(C, centres, slid, var, *prior)
        E = split_disagreement(C, centres, slid, var, *prior, older, newer)
        error = np.linalg.norm(est - X)
        u = (est - X) / max(error, 1e-12)
        sigma, widened = math.sqrt(u @ np.linalg.inv(info) @ u), math.sqrt(
            u @ (np.linalg.inv(info) + E) @ u)
        if rate == 0.0:
            assert np.all(E == 0.0) and error < 0.01
        else:
            assert error > 0.2 and error > 3 * sigma, (error, sigma)
            assert error <= 2 * widened, (error, widened)


def test_views_that_pull_a_target_under_the_water_are_refused(along_path):
    """Before its first refinement each tracked view updates the target's 3-D point. Views
    that would put it under the water plane (a track on a mirror image, or on something the
    ship carries along) are refused as ``refine`` refuses such a triangulation: the point
    never sinks more than 3σ under the water, and the track is given up. With the water
    below the point the same views are taken."""
    seq, point = along_path
    times = T0 + 0.1 * np.arange(N_FRAMES)
    truth = seq.truth(point)
    C0, p0 = seq.poses[0]
    dz = point[2] - p0[2]
    assert dz > 0.1  # the wall point is below the camera: its ray goes down
    start = p0 + 0.4 * (point - p0)  # the click's point on its ray, short of the wall
    for water_down, sinks in ((point[2] + 5.0, False), (p0[2] + 0.6 * dz, True)):
        tgt = DesignatedTarget(seq.cam, seq.images[0], truth[0], start, None,
                               CameraView(times[0], C0, p0), params=TargetParams(), seed=0,
                               water_down_m=water_down)
        lowest, states = -np.inf, []
        for k in range(1, N_FRAMES):
            states.append(tgt.update(seq.images[k], CameraView(times[k], *seq.poses[k])))
            X, P = tgt.position_ned, tgt.covariance
            lowest = max(lowest, (X[2] - water_down) / np.sqrt(P[2, 2]))
        err = np.linalg.norm(tgt.position_ned - point)
        if sinks:
            assert lowest <= 3.0, lowest
            assert any(st.status == "lost" and "disagrees" in st.reason for st in states)
        else:
            assert err < 0.5 * np.linalg.norm(start - point), err  # the views pulled it in
