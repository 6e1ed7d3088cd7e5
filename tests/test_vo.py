"""Tests of the VO block (estimator/vo.py).

a) geometry on projected synthetic points (ORB needs texture, so the pipeline is fed point
   tracks through ``process_tracks``); b) the full image pipeline on a short rendered sequence
   of the small-boat scenario (skipped while the simulator's renderer is not available).
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from estimator.frames import camera_to_body, dcm_to_rotvec, euler_to_dcm, rotvec_to_dcm
from estimator.records import CameraCalibration
from estimator.vo import (
    VisualOdometry,
    VoParams,
    bundle_adjust,
    locate,
    relative_pose,
    to_full_pixels,
    triangulate,
    triangulation_quality,
    umeyama_alignment,
    working_camera,
    working_level,
)

K = np.array([[680.0, 0.0, 480.0], [0.0, 680.0, 300.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.05, 0.0005, -0.0003, 0.0])
CAMERA = CameraCalibration(960, 600, K, DIST, camera_to_body(0.0, np.radians(3.0)),
                           np.array([3.0, 0.0, -0.4]))


def angle_deg(C: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(dcm_to_rotvec(C))))


def direction_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


# ------------------------------------------------------------------------- synthetic world


def marina_points(rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    """Points (NED) on structures 10–80 m ahead of a camera starting near the origin."""
    return np.column_stack([rng.uniform(10.0, 80.0, n), rng.uniform(-45.0, 45.0, n),
                            rng.uniform(-8.0, 0.0, n)])


def camera_path(n: int, speed: float = 1.0, yaw_rate_deg: float = 0.0, dt: float = 0.1
                ) -> list[tuple[np.ndarray, np.ndarray]]:
    """(C_level_to_camera, camera position NED) of a boat going north with wave roll/pitch."""
    out = []
    for k in range(n):
        t = k * dt
        C_b_l = euler_to_dcm(np.radians(2.0) * np.sin(1.8 * t), np.radians(1.0) * np.sin(1.1 * t),
                             np.radians(yaw_rate_deg) * t)
        position = np.array([speed * t, 0.0, -1.0 + 0.03 * np.sin(1.8 * t)])
        out.append(((C_b_l @ CAMERA.C_camera_to_body).T, position))
    return out


def project(X: np.ndarray, C_l_c: np.ndarray, position: np.ndarray, noise_px: float,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Ids and distorted pixels of the points visible in the 960x600 image."""
    depth = (X - position) @ C_l_c[2]
    uv, _ = cv2.projectPoints(X, cv2.Rodrigues(C_l_c)[0], -C_l_c @ position, K, DIST)
    uv = uv.reshape(-1, 2) + rng.normal(0.0, noise_px, (len(X), 2))
    visible = (depth > 1.0) & (uv[:, 0] > 2) & (uv[:, 0] < 957) & (uv[:, 1] > 2) & (uv[:, 1] < 597)
    return np.flatnonzero(visible), uv[visible]


def run_tracks(vo: VisualOdometry, X: np.ndarray, path, noise_px: float, seed: int,
               moving: np.ndarray | None = None, blank: range = range(0)):
    rng = np.random.default_rng(seed)
    outs, truth = [], []
    for k, (C, position) in enumerate(path):
        Xk = X.copy()
        if moving is not None:  # "water": drift with the current (0.5 m/s) and the waves
            phase = 0.7 * k + moving
            Xk[moving] += np.column_stack([0.2 * np.sin(phase), 0.05 * k + 0.2 * np.cos(phase),
                                           0.1 * np.sin(1.3 * phase)])
        ids, uv = project(Xk, C, position, noise_px, rng)
        if k in blank:
            ids, uv = ids[:0], uv[:0]
        outs.append(vo.process_tracks(0.1 * k, ids, uv))
        truth.append((C, position))
    return outs, truth


def trajectory_residual(outs, truth, segment: int | None = None) -> tuple[float, float]:
    """Largest residual after a similarity alignment, as a share of the path length, and the
    path length (truth) of the tracked frames."""
    keep = [i for i, o in enumerate(outs)
            if o.status == "tracking" and (segment is None or o.segment == segment)]
    est = np.array([outs[i].camera_position_world for i in keep])
    tru = np.array([truth[i][1] for i in keep])
    s, R, t = umeyama_alignment(est, tru)
    residual = np.linalg.norm(tru - (s * est @ R.T + t), axis=1)
    length = float(np.sum(np.linalg.norm(np.diff(tru, axis=0), axis=1)))
    return float(residual.max() / length), length


# --------------------------------------------------------------------------- geometry


def test_relative_pose_recovers_rotation_and_translation_direction():
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(-20, 20, 300), rng.uniform(-5, 5, 300),
                         rng.uniform(8, 60, 300)])
    R_true = rotvec_to_dcm(np.radians([1.0, 4.0, -0.5]))
    t_true = np.array([0.2, 0.05, -1.0])
    pts0 = X[:, :2] / X[:, 2:] * 680.0 + [480.0, 300.0]
    Xc1 = X @ R_true.T + t_true
    pts1 = Xc1[:, :2] / Xc1[:, 2:] * 680.0 + [480.0, 300.0]
    pts0 += rng.normal(0, 0.2, pts0.shape)
    pts1 += rng.normal(0, 0.2, pts1.shape)
    outliers = rng.choice(300, 30, replace=False)  # mismatches / moving water
    pts1[outliers] += rng.uniform(-30, 30, (30, 2))
    R, t, inliers = relative_pose(pts0, pts1, K)
    assert angle_deg(R @ R_true.T) < 0.1
    assert direction_error_deg(t, t_true) < 1.0
    assert abs(np.linalg.norm(t) - 1.0) < 1e-9
    assert inliers[outliers].mean() < 0.2
    assert inliers[np.setdiff1d(np.arange(300), outliers)].mean() > 0.9


def test_triangulation_and_cheirality():
    rng = np.random.default_rng(2)
    X = np.column_stack([rng.uniform(-5, 5, 50), rng.uniform(-2, 2, 50), rng.uniform(5, 30, 50)])
    C0, t0 = np.eye(3), np.zeros(3)
    C1 = rotvec_to_dcm(np.array([0.0, 0.05, 0.0]))
    t1 = -C1 @ np.array([1.0, 0.0, 0.2])  # centre of camera 1 at (1, 0, 0.2)

    def xy(C, t, P):
        Pc = P @ C.T + t
        return Pc[:, :2] / Pc[:, 2:]

    Xt = triangulate(C0, t0, C1, t1, xy(C0, t0, X), xy(C1, t1, X))
    assert np.allclose(Xt, X, atol=1e-6)
    front, err, angle = triangulation_quality(Xt, C0, t0, C1, t1, xy(C0, t0, X), xy(C1, t1, X))
    assert front.all() and err.max() < 1e-9
    rays0, rays1 = X, X - np.array([1.0, 0.0, 0.2])
    cos = np.sum(rays0 * rays1, 1) / np.linalg.norm(rays0, axis=1) / np.linalg.norm(rays1, axis=1)
    assert np.allclose(angle, np.arccos(cos), atol=1e-9)
    behind = -X  # same image points, but behind both cameras' centres
    front_b, _, _ = triangulation_quality(behind, C0, t0, C1, t1, xy(C0, t0, X), xy(C1, t1, X))
    assert not front_b.any()


def _skyline_frames(n_near: int, n_far: int, frames: int = 40):
    """Frames of a map with ``n_near`` quay points 10–50 units ahead of the camera and
    ``n_far`` skyline points the BA has pushed to 10⁴–10⁶ units (small boat 158 at 59 s),
    all in front of it: (X, xy, the last frame's pose, the true pose)."""
    rng = np.random.default_rng(n_near * 1000 + n_far)
    for k in range(frames):
        C = rotvec_to_dcm(np.array([0.01, 0.3 + 0.01 * k, 0.0]))
        t = np.array([-3.0, 0.3, -17.0])
        z = rng.uniform(10, 50, n_near)
        near = np.column_stack([rng.uniform(-0.6, 0.6, n_near) * z,
                                rng.uniform(-0.05, 0.2, n_near) * z, z])
        d = 10 ** rng.uniform(4, 6.2, n_far)
        az, el = rng.uniform(-0.5, 0.5, n_far), rng.uniform(-0.05, 0.15, n_far)
        far = np.column_stack([d * np.sin(az), -d * np.sin(el), d * np.cos(az)])
        X = (np.vstack([near, far]) - t) @ C  # camera → world
        xy = np.vstack([near, far])
        xy = xy[:, :2] / xy[:, 2:] + rng.normal(0.0, 0.3 / 800.0, (len(X), 2))
        # the last frame's pose: 0.1 s of the ship's motion earlier
        previous = (rotvec_to_dcm(np.array([0.0, -0.004, 0.0])) @ C, t + [0.02, 0.0, -0.08])
        yield X, xy, previous, (C, t)


# (the guard each map needs: a few far points break RANSAC's last fit, a majority wins it)
@pytest.mark.parametrize("n_near, n_far, guard, off", [
    (250, 6, "KEPT_INLIERS", 0.0), (250, 130, "KEPT_INLIERS", 0.0),
    (80, 300, "FAR_DEPTH", np.inf), (40, 300, "FAR_DEPTH", np.inf)])
def test_a_frame_is_located_on_a_map_with_a_skyline_near_infinity(monkeypatch, n_near, n_far,
                                                                  guard, off):
    """A few points near infinity break the last fit of OpenCV's RANSAC (158 lost its VO);
    a skyline majority wins the RANSAC with any translation. ``locate`` refines a broken fit
    from the last pose and samples only the points within ``FAR_DEPTH`` when the far ones
    are the majority: every frame is located to the truth, with the skyline among its
    inliers; without the guard the map needs, frames are lost or metres off."""
    thr = 1.5 / 800.0
    for k, (X, xy, previous, (C, t)) in enumerate(_skyline_frames(n_near, n_far)):
        located = locate(X, xy, thr, 30, previous)
        assert located is not None, k
        C_found, t_found, _Xc, good = located
        assert good.sum() >= 0.95 * len(X), k
        assert np.degrees(np.linalg.norm(dcm_to_rotvec(C_found @ C.T))) < 0.02, k
        np.testing.assert_allclose(t_found, t, atol=0.02)
    monkeypatch.setattr(f"estimator.vo.{guard}", off)
    failed = 0
    for X, xy, previous, (_C, t) in _skyline_frames(n_near, n_far):
        located = locate(X, xy, thr, 30, previous)
        failed += located is None or np.linalg.norm(located[1] - t) > 0.05
    assert failed >= 10


def test_umeyama_alignment_recovers_similarity():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(40, 3))
    R = rotvec_to_dcm(np.array([0.3, -1.0, 2.0]))
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 3.0])
    s, R_est, t = umeyama_alignment(src, dst)
    assert s == pytest.approx(2.5)
    assert np.allclose(R_est, R) and np.allclose(t, [1.0, -2.0, 3.0])


def test_bundle_adjust_converges_from_perturbed_poses_and_points():
    rng = np.random.default_rng(4)
    X = np.column_stack([rng.uniform(-10, 10, 200), rng.uniform(-3, 3, 200),
                         rng.uniform(10, 40, 200)])
    n_cam = 5
    C = np.array([rotvec_to_dcm(np.array([0.0, 0.03 * k, 0.01 * k])) for k in range(n_cam)])
    centres = np.array([[0.3 * k, 0.0, 1.0 * k] for k in range(n_cam)])
    t = -np.einsum("kij,kj->ki", C, centres)
    cam_idx, pt_idx, xy = [], [], []
    for k in range(n_cam):
        Xc = X @ C[k].T + t[k]
        cam_idx.append(np.full(len(X), k))
        pt_idx.append(np.arange(len(X)))
        xy.append(Xc[:, :2] / Xc[:, 2:])
    cam_idx, pt_idx, xy = map(np.concatenate, (cam_idx, pt_idx, xy))
    fixed = np.array([True, True, False, False, False])
    C_init = C.copy()
    for k in range(2, n_cam):
        C_init[k] = rotvec_to_dcm(rng.normal(0, 0.003, 3)) @ C[k]
    t_init = t + np.where(fixed[:, None], 0.0, rng.normal(0, 0.05, t.shape))
    X_init = X * rng.uniform(0.97, 1.03, (len(X), 1))
    C_ba, t_ba, X_ba, res = bundle_adjust(C_init, t_init, X_init, cam_idx, pt_idx, xy, fixed,
                                          680.0, 1.0, 30)
    for k in range(n_cam):
        assert angle_deg(C_ba[k] @ C[k].T) < 1e-5
        assert np.linalg.norm(-C_ba[k].T @ t_ba[k] - centres[k]) < 1e-5
    assert np.abs(X_ba - X).max() < 1e-4
    assert res.max() < 1e-4
    assert np.array_equal(C_ba[:2], C_init[:2])
    # A gross outlier (a mistracked point) keeps a large residual instead of spreading.
    xy[5] += 0.05
    *_, res = bundle_adjust(C_init, t_init, X_init, cam_idx, pt_idx, xy, fixed, 680.0, 1.0, 30)
    assert res[5] > 20.0 and np.median(res) < 0.05


# ---------------------------------------------------------------- pipeline on point tracks


def test_tracks_straight_path_scale_consistent():
    """Straight path: after initialisation 20 tracked frames lie on the true path up to one
    similarity (the scale of the first baseline is kept by the fixed keyframes)."""
    X = marina_points(np.random.default_rng(5))
    vo = VisualOdometry(CAMERA)
    path = camera_path(60)
    outs, truth = run_tracks(vo, X, path, 0.2, 5)
    first = next(i for i, o in enumerate(outs) if o.status == "tracking")
    assert first < 25
    outs, truth = outs[first:first + 20], truth[first:first + 20]
    assert all(o.status == "tracking" and o.segment == 0 for o in outs)
    share, _ = trajectory_residual(outs, truth)
    assert share < 0.01
    # Attitude relative to W (= camera at the reference frame) matches the truth.
    C_ref = path[0][0]  # the reference frame is the first one here
    for o, (C_true, _) in zip(outs, truth, strict=True):
        assert angle_deg(o.C_world_to_camera @ (C_true @ C_ref.T).T) < 0.2
    # Unit first baseline: the initialisation frame (a keyframe) lies at distance 1 from W.
    assert outs[0].is_keyframe
    assert np.linalg.norm(outs[0].camera_position_world) == pytest.approx(1.0, abs=1e-9)
    assert len(outs[-1].point_ids) == len(np.unique(outs[-1].point_ids)) > 100


def test_a_keyframe_bundle_adjustment_lands_on_its_frame_whatever_the_worker():
    """The local BA (past the segment's first keyframes) runs in a worker thread beside the
    next frames and lands ``ba_lag_frames`` later: the outputs are the same on every run, a
    copy taken while a BA is under way (``backend.replay.snapshot``, as the server's scout
    takes them) goes on exactly like the original, and the lagged BA keeps the path as true
    as the in-line one."""
    import copy

    from backend.replay import snapshot

    X = marina_points(np.random.default_rng(5))
    path = camera_path(70)

    def run(vo: VisualOdometry, copy_at: int | None = None):
        rng = np.random.default_rng(5)
        outs, copied = [], None
        for k, (C, position) in enumerate(path):
            ids, uv = project(X, C, position, 0.2, rng)
            outs.append(vo.process_tracks(0.1 * k, ids, uv))
            if k == copy_at:
                assert vo._pending_ba is not None  # a BA under way
                copied = (snapshot(vo), copy.deepcopy(rng))
        return outs, copied

    lagged, _ = run(VisualOdometry(CAMERA))
    again, _ = run(VisualOdometry(CAMERA))
    keyframes = [k for k, o in enumerate(lagged) if o.is_keyframe]
    pending_at = next(k for k in keyframes[1:] if k > keyframes[0] + 10)
    _, (twin, twin_rng) = run(VisualOdometry(CAMERA), copy_at=pending_at)
    for k in range(pending_at + 1, len(path)):
        ids, uv = project(X, *path[k], 0.2, twin_rng)
        out = twin.process_tracks(0.1 * k, ids, uv)
        assert np.array_equal(out.camera_position_world, lagged[k].camera_position_world)
    for a, b in zip(lagged, again, strict=True):
        assert a.status == b.status
        if a.camera_position_world is not None:
            assert np.array_equal(a.camera_position_world, b.camera_position_world)
            assert np.array_equal(a.points_world, b.points_world)
    # the BA landed: the map of the frame after its lag differs from the one before
    lag = VisualOdometry(CAMERA).params.ba_lag_frames
    before, after = lagged[pending_at + lag - 1], lagged[pending_at + lag]
    common = np.intersect1d(before.point_ids, after.point_ids)
    moved = np.abs(after.points_world[np.searchsorted(after.point_ids, common)]
                   - before.points_world[np.searchsorted(before.point_ids, common)]).max()
    assert moved > 0.0
    in_line, _ = run(VisualOdometry(CAMERA, replace(VoParams(), ba_lag_frames=0)))
    first = next(i for i, o in enumerate(lagged) if o.status == "tracking")
    for outs in (lagged, in_line):
        share, _ = trajectory_residual(outs[first:], [(C, c) for C, c in path[first:]])
        assert share < 0.01


def test_tracks_turning_relative_rotation_and_direction():
    X = marina_points(np.random.default_rng(6))
    vo = VisualOdometry(CAMERA)
    outs, truth = run_tracks(vo, X, camera_path(60, yaw_rate_deg=8.0), 0.2, 6)
    tracked = [i for i, o in enumerate(outs) if o.status == "tracking"]
    assert len(tracked) > 35
    for i, j in zip(tracked[:-1], tracked[1:], strict=True):
        rel = outs[j].C_world_to_camera @ outs[i].C_world_to_camera.T
        rel_true = truth[j][0] @ truth[i][0].T
        assert angle_deg(rel @ rel_true.T) < 0.1
    share, _ = trajectory_residual(outs, truth)
    assert share < 0.02


def test_tracks_reject_moving_points():
    """A third of the points drift like water: RANSAC and the triangulation checks keep them
    out of the map and the trajectory stays on the truth."""
    rng = np.random.default_rng(7)
    X = marina_points(rng)
    moving = rng.choice(len(X), len(X) // 3, replace=False)
    vo = VisualOdometry(CAMERA)
    outs, truth = run_tracks(vo, X, camera_path(50), 0.2, 7, moving=moving)
    assert sum(o.status == "tracking" for o in outs) > 25
    ids = np.unique(np.concatenate([o.point_ids for o in outs]))
    assert np.isin(ids, moving).mean() < 0.03
    share, _ = trajectory_residual(outs, truth)
    assert share < 0.02


def test_tracks_gap_starts_new_segment():
    X = marina_points(np.random.default_rng(8))
    vo = VisualOdometry(CAMERA)
    outs, truth = run_tracks(vo, X, camera_path(90), 0.2, 8, blank=range(35, 40))
    status = [o.status for o in outs]
    assert status[34] == "tracking" and status[35] == "lost"
    assert outs[34].segment == 0
    assert all(o.C_world_to_camera is None for o in outs[35:40])
    after = [o for o in outs[40:] if o.status == "tracking"]
    assert len(after) > 20 and all(o.segment == 1 for o in after)
    assert after[-1].status == "tracking"
    for seg in (0, 1):
        share, _ = trajectory_residual(outs, truth, seg)
        assert share < 0.02


def test_a_full_resolution_camera_is_tracked_at_half_size():
    """The thesis' 1920x1200 camera: the VO works on the 960x600 block means (its pixel
    thresholds those of the smaller image) and answers in full-size pixels."""
    full = CameraCalibration(1920, 1200, np.array([[1360.0, 0, 960.5], [0, 1360.0, 600.5],
                                                   [0, 0, 1]]), DIST, CAMERA.C_camera_to_body,
                             CAMERA.lever_arm_body)
    assert working_level(1920, 1280) == 1 and working_level(960, 1280) == 0
    half = working_camera(full, 1)
    assert (half.width, half.height) == (960, 600)
    # A point projects where the block mean of its full-size pixel puts it.
    X = marina_points(np.random.default_rng(9), 50)
    C, position = camera_path(1)[0]
    args = (X, cv2.Rodrigues(C)[0], -C @ position)
    uv_full = cv2.projectPoints(*args, full.K, DIST)[0].reshape(-1, 2)
    uv_half = cv2.projectPoints(*args, half.K, DIST)[0].reshape(-1, 2)
    assert np.abs(to_full_pixels(uv_half, 1) - uv_full).max() < 1e-9

    vo = VisualOdometry(full)
    assert vo.level == 1 and vo.working_size == (960, 600)
    rng = np.random.default_rng(5)
    X = marina_points(rng)
    outs, truth = [], []
    for k, (C, position) in enumerate(camera_path(60)):
        depth = (X - position) @ C[2]
        uv = cv2.projectPoints(X, cv2.Rodrigues(C)[0], -C @ position, full.K, DIST
                               )[0].reshape(-1, 2) + rng.normal(0.0, 0.4, (len(X), 2))
        seen = np.flatnonzero((depth > 1) & (uv[:, 0] > 4) & (uv[:, 0] < 1915)
                              & (uv[:, 1] > 4) & (uv[:, 1] < 1195))
        outs.append(vo.process_tracks(0.1 * k, seen, uv[seen]))
        truth.append((C, position))
        ids, obs = outs[-1].observations
        row = {int(i): j for j, i in enumerate(seen)}
        assert np.abs(obs - uv[seen][[row[int(i)] for i in ids]]).max(initial=0.0) < 1e-3
    first = next(i for i, o in enumerate(outs) if o.status == "tracking")
    assert first < 25 and all(o.status == "tracking" for o in outs[first:first + 20])
    share, _ = trajectory_residual(outs[first:first + 20], truth[first:first + 20])
    assert share < 0.01


# ------------------------------------------------------------------ rendered small-boat run

RENDER_START_S = 45.0  # ~27 m from the quay at ~0.9 m/s: parallax for a prompt initialisation
N_CLEAN = 60  # clean frames, then a black gap, then the VO must start a new segment
GAP = range(60, 63)
N_RENDERED = 95


@pytest.fixture(scope="module")
def rendered_run():
    scene_mod = pytest.importorskip("recordings.sim.scene")
    motion_mod = pytest.importorskip("recordings.sim.motion")
    from recordings.sim.scenarios import SCENARIOS

    scenario = SCENARIOS["small-boat"]
    from recordings.sim.variety import reference_look

    # The VO's mechanics on the reference look (the simulator's former single look). On seed
    # 3's own look (its port mirrored in the water) it initialises at frame 31 (21 without the
    # reflections) and its attitude relative to the world frame is 1.6 deg off (1 deg
    # allowed): issue 17's robustness work, judged on the seeds, not here.
    scene = scene_mod.PortScene.build(scenario, 3, look=reference_look(scenario))
    motion = motion_mod.ShipMotion(scenario, 3)
    camera = scene_mod.camera_calibration(scenario)
    rng = np.random.default_rng(3)
    vo = VisualOdometry(camera)
    outs, truth, frames = [], [], {}
    for k in range(N_RENDERED):
        t = RENDER_START_S + 0.1 * k
        C_b_l = np.asarray(motion.state(t).C_body_to_level).reshape(-1, 3, 3)[0]
        position = np.asarray(motion.point_position_ned(t, camera.lever_arm_body)).reshape(3)
        C_l_c = (C_b_l @ camera.C_camera_to_body).T
        if k in GAP:
            image = np.zeros((camera.height, camera.width, 3), np.uint8)
        else:
            image = scene.render(C_l_c, position, t, camera, rng)
        if k == N_CLEAN - 1:
            frames["last_clean"] = image
        outs.append(vo.process(scenario.start_gpst + t, image))
        truth.append((C_l_c, position))
    return outs, truth, vo, frames


def test_the_next_frames_front_end_made_ahead_changes_nothing(monkeypatch):
    """Given the next frame as it ends a frame (``process(following=…)``, a recording's
    reader has it), the VO starts that frame's front end (LK, its check, the template
    alignment) in a worker thread: the outputs are the same bit for bit as without, the LK
    is no longer made on the caller's thread, and a frame the fusion skipped in between
    (the frame check) is tracked as usual."""
    import threading

    import estimator.vo as vo_module
    from recordings.sim.motion import ShipMotion
    from recordings.sim.scenarios import SCENARIOS
    from recordings.sim.scene import PortScene, camera_calibration

    scenario = SCENARIOS["small-boat"]
    scene, motion = PortScene.build(scenario, 5), ShipMotion(scenario, 5)
    camera = camera_calibration(scenario)
    rng = np.random.default_rng(5)
    images = []
    for k in range(45):
        t = RENDER_START_S + 0.1 * k
        C_b_l = np.asarray(motion.state(t).C_body_to_level).reshape(-1, 3, 3)[0]
        position = np.asarray(motion.point_position_ned(t, camera.lever_arm_body)).reshape(3)
        images.append(scene.render((C_b_l @ camera.C_camera_to_body).T, position, t, camera,
                                   rng))
    skipped = 30  # never given to the VO, though announced as the next frame
    forward_on = []
    lk_forward = vo_module._lk_forward

    def spy(*args):
        forward_on.append(threading.current_thread() is threading.main_thread())
        return lk_forward(*args)

    monkeypatch.setattr(vo_module, "_lk_forward", spy)
    runs = {}
    for ahead in (False, True):
        vo = VisualOdometry(camera)
        prepared = [vo.prepare(im) for im in images]
        forward_on.clear()
        outs = []
        for k, im in enumerate(images):
            if k == skipped:
                continue
            following = prepared[k + 1] if ahead and k + 1 < len(images) else None
            outs.append(vo.process(0.1 * k, im, prepared[k], following))
        runs[ahead] = (outs, list(forward_on))
    (plain, on_main), (made_ahead, on_main_ahead) = runs[False], runs[True]
    assert sum(o.status == "tracking" for o in plain) > 10
    assert all(on_main) and len(on_main) > 40
    # ahead: on the caller's thread only after the skipped frame (its LK into the frame
    # that never came is dropped)
    assert sum(on_main_ahead) == 1 and len(on_main_ahead) == len(on_main) + 1
    for a, b in zip(plain, made_ahead, strict=True):
        assert a.status == b.status and a.n_tracked == b.n_tracked
        assert np.array_equal(a.observations[1], b.observations[1])
        if a.camera_position_world is not None:
            assert np.array_equal(a.camera_position_world, b.camera_position_world)


def test_rendered_sequence_tracks_truth(rendered_run):
    outs, truth, vo, _ = rendered_run
    clean = outs[:N_CLEAN]
    tracked = [i for i, o in enumerate(clean) if o.status == "tracking"]
    assert tracked and tracked[0] < 30, [o.status for o in clean]
    # Once initialised, tracking is never lost on this clean sequence.
    assert tracked == list(range(tracked[0], N_CLEAN))
    assert all(o.segment == 0 for o in clean)
    for i, j in zip(tracked[:-1], tracked[1:], strict=True):
        rel = clean[j].C_world_to_camera @ clean[i].C_world_to_camera.T
        rel_true = truth[j][0] @ truth[i][0].T
        assert angle_deg(rel @ rel_true.T) < 0.3
    # W is the camera at the reference frame the initialisation started from (world_time).
    t0 = clean[0].time
    w = int(round((clean[-1].world_time - t0) / 0.1))
    assert 0 <= w < tracked[0] and clean[-1].world_time == pytest.approx(t0 + 0.1 * w)
    for k in tracked:
        assert angle_deg(clean[k].C_world_to_camera @ (truth[k][0] @ truth[w][0].T).T) < 1.0
    i, j = tracked[0], tracked[-1]
    moved = clean[i].C_world_to_camera @ (clean[j].camera_position_world
                                          - clean[i].camera_position_world)
    assert direction_error_deg(moved, truth[i][0] @ (truth[j][1] - truth[i][1])) < 3.0
    share, length = trajectory_residual(clean, truth[:N_CLEAN])
    # The largest residual is in the first frames after the initialisation, before the first
    # local BA; over this 3 m path it varies from 1.2 to 3.5 % with the front end's settings
    # (template size, blur, iterations). A broken VO is off by tens of %.
    assert length > 2.0 and share < 0.04
    # The API: the frame's observations are map points, in pixels inside the image.
    o = clean[-1]
    ids, uv = o.observations
    assert len(ids) >= vo.params.min_tracked and np.isin(ids, o.point_ids).all()
    assert (uv >= 0).all() and (uv[:, 0] < 960).all() and (uv[:, 1] < 600).all()
    assert o.points_world.shape == (len(o.point_ids), 3)


def test_rendered_blank_gap_starts_new_segment(rendered_run):
    outs, truth, _, _ = rendered_run
    assert outs[GAP[0]].status == "lost"
    assert all(outs[k].status != "tracking" and outs[k].C_world_to_camera is None for k in GAP)
    after = outs[GAP[-1] + 1:]
    resumed = [k for k, o in enumerate(after) if o.status == "tracking"]
    assert resumed, [o.status for o in after]
    assert resumed == list(range(resumed[0], len(after)))  # and keeps tracking
    assert all(after[k].segment == 1 for k in resumed)
    assert after[resumed[0]].world_time > outs[GAP[-1]].time
    for i, j in zip(resumed[:-1], resumed[1:], strict=True):
        rel = after[j].C_world_to_camera @ after[i].C_world_to_camera.T
        k0 = GAP[-1] + 1
        rel_true = truth[k0 + j][0] @ truth[k0 + i][0].T
        assert angle_deg(rel @ rel_true.T) < 0.3


def zoom_texture_frames(n: int, rate: float, seed: int) -> list[np.ndarray]:
    """A textured plane approached head-on: frame k is the texture scaled by 1 + rate·k about
    the image centre (as a quay wall ahead grows in the image)."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.normal(0.0, 1.0, (600, 960)), (0, 0), 2.0)
    tex = np.clip(128 + 45 * tex / tex.std(), 0, 255).astype(np.float32)
    frames = []
    for k in range(n):
        s = 1.0 + rate * k
        M = np.array([[s, 0.0, (1 - s) * 479.5], [0.0, s, (1 - s) * 299.5]])
        frames.append(cv2.warpAffine(tex, M, (960, 600), flags=cv2.INTER_CUBIC).astype(np.uint8))
    return frames


def test_align_affine_recovers_zoomed_patches():
    """Templates cut from one frame are found in a frame zoomed by 15 %: the affine alignment
    lands within a few hundredths of a pixel and recovers the scale; a translation-only LK
    window (what chained tracking does) is off by a good fraction of a pixel."""
    from estimator.vo import align_affine, take_templates

    f0, f1 = zoom_texture_frames(2, 0.15, 3)
    rng = np.random.default_rng(4)
    pts = rng.uniform([150, 120], [810, 480], (300, 2))
    truth = (pts - [479.5, 299.5]) * 1.15 + [479.5, 299.5]
    b0, b1 = (cv2.GaussianBlur(f.astype(np.float32), (0, 0), 1.0) for f in (f0, f1))
    eye = np.broadcast_to(np.eye(2), (len(pts), 2, 2)).copy()
    templates, h_inv = take_templates(b0, pts, 10)
    start = truth + rng.normal(0.0, 0.5, truth.shape)
    centre, warp, ncc = align_affine(b1, templates, h_inv, start, eye, 6)
    err = np.linalg.norm(centre - truth, axis=1)
    assert np.median(err) < 0.05 and np.percentile(err, 90) < 0.15
    assert np.median(ncc) > 0.98
    assert np.allclose(np.median(warp[:, [0, 1], [0, 1]], axis=0), 1.15, atol=0.01)
    assert np.allclose(np.median(warp[:, [0, 1], [1, 0]], axis=0), 0.0, atol=0.01)
    lk, st, _ = cv2.calcOpticalFlowPyrLK(f0, f1, pts.astype(np.float32).reshape(-1, 1, 2),
                                         start.astype(np.float32).reshape(-1, 1, 2),
                                         winSize=(21, 21), maxLevel=0,
                                         flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    lk_err = np.linalg.norm(lk.reshape(-1, 2) - truth, axis=1)[st.ravel() == 1]
    assert np.median(lk_err) > 5 * np.median(err)


def test_tracks_do_not_slide_as_the_scene_zooms():
    """A plane approached over 80 frames (scale 1 → 1.4): tracks found in the first frame
    stay on their texture point with the template alignment; chained LK slides off it."""
    frames = zoom_texture_frames(81, 0.005, 6)
    from estimator.vo import VoParams

    slide = {}
    for check in (True, False):
        vo = VisualOdometry(CAMERA, VoParams(template_check=check, n_features=300))
        vo.process(0.0, frames[0])
        ids0, uv0 = vo._tracks.id.copy(), vo._tracks.uv.astype(float).copy()
        for k in range(1, len(frames)):
            vo.process(0.1 * k, frames[k])
        alive = np.isin(ids0, vo._tracks.id)
        now = {int(i): u for i, u in zip(vo._tracks.id, vo._tracks.uv.astype(float),
                                         strict=True)}
        s = 1.0 + 0.005 * (len(frames) - 1)
        truth = (uv0[alive] - [479.5, 299.5]) * s + [479.5, 299.5]
        inside = ((truth > 30) & (truth < [930, 570])).all(axis=1)
        est = np.array([now[int(i)] for i in ids0[alive]])
        slide[check] = np.linalg.norm(est - truth, axis=1)[inside]
    assert len(slide[True]) > 50
    assert np.median(slide[True]) < 0.1
    assert np.median(slide[False]) > 3 * np.median(slide[True])


def test_template_check_cuts_tracks_on_changing_water():
    """Front end: the left half is a rigid textured quay panning slowly, the right half water
    made of two wave patterns drifting in opposite directions. Frame-to-frame LK (with its
    forward-backward check) follows blends of the water patterns for a long time; aligned on
    the track's template (its look when it was found) they are cut, while the quay's tracks
    live on."""
    rng = np.random.default_rng(5)

    def texture(sigma: float) -> np.ndarray:
        n = cv2.GaussianBlur(rng.normal(0.0, 1.0, (600, 1400)), (0, 0), sigma)
        return n / n.std()

    quay, wave_a, wave_b = texture(2.5), texture(2.5), texture(2.5)

    def frame(k: int) -> np.ndarray:
        img = np.empty((600, 960))
        img[:, :480] = quay[:, 200 + k // 2:680 + k // 2]
        sa, sb = 220 + k // 2, 220 - k // 2
        img[:, 480:] = 0.7 * wave_a[:, sa:sa + 480] + 0.7 * wave_b[:, sb:sb + 480]
        return np.clip(128 + 45 * img, 0, 255).astype(np.uint8)

    from estimator.vo import VoParams

    alive = {}
    for name, check in (("template", True), ("chained", False)):
        vo = VisualOdometry(CAMERA, VoParams(template_check=check))
        vo.process(0.0, frame(0))
        ids0 = vo._tracks.id.copy()
        water0 = np.isin(ids0, vo._tracks.id[vo._tracks.uv[:, 0] > 500])
        for k in range(1, 41):
            vo.process(0.1 * k, frame(k))
        live = np.isin(ids0, vo._tracks.id)
        alive[name] = (int((live & ~water0).sum()), int((live & water0).sum()),
                       int((~water0).sum()), int(water0.sum()))
    quay_a, water_a, n_quay, n_water = alive["template"]
    quay_c, water_c, _, _ = alive["chained"]
    assert n_quay > 50 and n_water > 50
    assert quay_a > 0.8 * n_quay  # the rigid texture keeps its tracks
    assert water_c > 0.2 * n_water  # chained LK keeps following the water ...
    assert water_a < 0.25 * water_c  # ... the template check does not


def _track_in_child(frames: list[np.ndarray], out) -> None:
    vo = VisualOdometry(CAMERA)
    for k, f in enumerate(frames):
        o = vo.process(0.1 * k, f)
    out.put(o.n_tracked)


def test_a_forked_process_tracks_with_its_own_worker_thread():
    """The forward–backward check runs in a worker thread made on first use. A process forked
    after the parent used it (a campaign's workers, the yardstick's jobs) has none of the
    parent's threads: it must make its own rather than wait on a dead one for ever."""
    import multiprocessing

    frames = zoom_texture_frames(4, 0.005, 6)
    parent = VisualOdometry(CAMERA)
    for k, f in enumerate(frames):
        parent.process(0.1 * k, f)
    ctx = multiprocessing.get_context("fork")
    out = ctx.Queue()
    child = ctx.Process(target=_track_in_child, args=(frames, out))
    child.start()
    child.join(60)
    if child.is_alive():
        child.kill()
        pytest.fail("the forked VO never finished a frame")
    assert child.exitcode == 0 and out.get(timeout=5) == parent._tracks.id.size


def _turning_frames(stamps: np.ndarray, exposures: np.ndarray, rate: float,
                    gyro_step: tuple[float, float] | None = None) -> list:
    """Frames of a camera (= body) turning about the vertical at ``rate``: the VO's attitude
    at each exposure, the gyro's (``Ins.C_gyro``) at each stamp, its rate off by
    ``gyro_step`` = (from s, rad/s) when given."""
    from estimator.vo_coupling import _Seen

    def yaw_of(t: float) -> float:
        off = 0.0 if gyro_step is None else gyro_step[1] * max(t - gyro_step[0], 0.0)
        return rate * t + off

    return [_Seen(float(s), 0, euler_to_dcm(0.0, 0.0, rate * e).T, np.zeros(3),
                  euler_to_dcm(0.0, 0.0, yaw_of(s)), np.eye(3), np.zeros(3), 1e-3, None)
            for s, e in zip(stamps, exposures, strict=True)]


def test_the_vo_rotation_check_allows_for_the_jitter_of_frame_stamps():
    """A live camera's frames are stamped on arrival, tens of ms after their exposure and not
    always as long: the gyro's rotation at the stamps and the VO's at the exposures differ by
    the turn rate times that jitter — 0.4° at 8°/s and 50 ms, beyond the 0.3 s window's gate
    (~0.3°). The jitter is measured from the intervals' scatter and joins the gate; exact
    stamps (a recording) keep it as tight as it was, and a gyro step is still seen within
    0.4 s."""
    from estimator.ekf import EkfConfig
    from estimator.vo_coupling import VoConsistency

    rate = np.radians(8.0)
    exposures = np.arange(0.0, 20.0, 0.1)
    rng = np.random.default_rng(7)
    stamps = exposures + 0.08 + rng.uniform(-0.04, 0.04, len(exposures))  # latency + jitter
    check = VoConsistency(EkfConfig(), np.eye(3))
    flagged = [f.t for f in _turning_frames(stamps, exposures, rate) if check.check(f)]
    assert not flagged, flagged
    assert 0.015 < check.time_sigma < 0.035  # uniform ±40 ms: σ 23 ms
    # exact stamps: no jitter, and a 1°/s gyro step at 10 s is flagged within 0.4 s
    check = VoConsistency(EkfConfig(), np.eye(3))
    frames = _turning_frames(exposures, exposures, rate, gyro_step=(10.0, np.radians(1.0)))
    flagged = [f.t for f in frames if check.check(f)]
    assert check.time_sigma == 0.0
    assert flagged and 10.0 < flagged[0] <= 10.4 + 1e-9, flagged[:3]


def test_the_couplings_raw_points_keep_the_last_world_of_each_id_in_first_seen_order():
    """``_RawPoints`` (the VO's map points by id, as arrays) against the dict it replaces:
    an id keeps its first place, takes its latest segment and point, and leaves with its
    segment."""
    from estimator.vo_coupling import _RawPoints

    rng = np.random.default_rng(3)
    raw, model = _RawPoints(), {}
    for step in range(200):
        segment = int(rng.integers(0, 3))
        if step % 23 == 22:
            raw.drop(segment)
            model = {k: v for k, v in model.items() if v[0] != segment}
            continue
        ids = rng.choice(60, size=int(rng.integers(0, 15)), replace=False)
        X = rng.normal(size=(len(ids), 3))
        raw.update(segment, ids, X)
        for pid, x in zip(ids.tolist(), X, strict=True):
            model[pid] = (segment, x)
        for s in range(3):
            ids_s, X_s = raw.of(s)
            want = [(k, v[1]) for k, v in model.items() if v[0] == s]
            assert ids_s.tolist() == [k for k, _ in want]
            assert np.array_equal(X_s.reshape(-1, 3), np.array([x for _, x in want]).reshape(-1, 3))
