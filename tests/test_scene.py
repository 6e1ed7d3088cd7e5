"""Textured port renderer of the simulator (recordings/sim/scene.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimator.frames import camera_to_body, euler_to_dcm
from recordings.sim.scenarios import LARGE_SHIP, SMALL_BOAT, Scenario
from recordings.sim.scene import PortScene, camera_calibration, project_points


def _pose(sc: Scenario, t: float, yaw_deg: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """C_level_to_camera and camera position of the scenario's ship at time t (no waves)."""
    kf = np.array(sc.path_keyframes)
    n, e = np.interp(t, kf[:, 0], kf[:, 1]), np.interp(t, kf[:, 0], kf[:, 2])
    yaw = np.interp(t, kf[:, 0], kf[:, 3]) if yaw_deg is None else yaw_deg
    C_body_to_level = euler_to_dcm(0.0, 0.0, np.radians(yaw))
    ref = np.array([n, e, sc.reference_point_down_m])  # the centre of motion, raised
    lever = np.array(sc.camera_lever_arm) - np.array([*sc.motion_centre_body, 0.0])
    position = ref + C_body_to_level @ lever
    return (C_body_to_level @ sc.C_camera_to_body).T, position


def _pixels_ned(uv: np.ndarray, depth: np.ndarray, C: np.ndarray, p: np.ndarray,
                camera) -> np.ndarray:
    """NED points seen at distorted pixels ``uv`` (N,2) with camera depths ``depth`` (N,)."""
    norm = cv2.undistortPoints(uv.reshape(-1, 1, 2).astype(np.float64), camera.K,
                               camera.distortion).reshape(-1, 2)
    cam = np.column_stack([norm, np.ones(len(norm))]) * depth[:, None]
    return cam @ C + p


@pytest.fixture(scope="module")
def marina() -> PortScene:
    return PortScene.build(SMALL_BOAT, seed=11)


@pytest.fixture(scope="module")
def terminal() -> PortScene:
    return PortScene.build(LARGE_SHIP, seed=11)


def test_camera_calibration_and_projection():
    cam = camera_calibration(SMALL_BOAT)
    w, h = SMALL_BOAT.camera_size
    assert (cam.width, cam.height) == (w, h)
    assert cam.K[0, 0] == pytest.approx(w / 2 / np.tan(np.radians(SMALL_BOAT.camera_hfov_deg) / 2))
    assert cam.K[0, 2] == pytest.approx((w - 1) / 2)
    np.testing.assert_allclose(cam.distortion, SMALL_BOAT.camera_distortion)
    np.testing.assert_allclose(cam.C_camera_to_body, SMALL_BOAT.C_camera_to_body)
    np.testing.assert_allclose(cam.lever_arm_body, SMALL_BOAT.camera_lever_arm)
    # camera looking north, level: a point 10 m north, 1 m east, 0.5 m down
    C = camera_to_body(0.0, 0.0).T  # level-to-camera for a body aligned with NED
    p = np.array([0.0, 0.0, -1.0])
    pts = np.array([[10.0, 1.0, -0.5], [-5.0, 0.0, -1.0]])
    uv, depth = project_points(pts, C, p, cam)
    np.testing.assert_allclose(depth, [10.0, -5.0])
    assert np.all(np.isnan(uv[1]))
    cam0 = camera_calibration(SMALL_BOAT)
    cam0.distortion = np.zeros(5)
    uv0, _ = project_points(pts[:1], C, p, cam0)
    np.testing.assert_allclose(uv0[0], [cam.K[0, 2] + cam.K[0, 0] * 0.1,
                                        cam.K[1, 2] + cam.K[1, 1] * 0.05], atol=1e-9)


def test_deterministic_and_plausible_picture(marina):
    again = PortScene.build(SMALL_BOAT, seed=11)
    p1, k1 = marina.scene_points()
    p2, k2 = again.scene_points()
    np.testing.assert_array_equal(p1, p2)
    assert k1 == k2

    cam = camera_calibration(SMALL_BOAT)
    C, p = _pose(SMALL_BOAT, 30.0)
    a = marina.render(C, p, 30.0, cam, np.random.default_rng(3))
    b = again.render(C, p, 30.0, cam, np.random.default_rng(3))
    assert a.shape == (cam.height, cam.width, 3) and a.dtype == np.uint8
    np.testing.assert_array_equal(a, b)
    assert a.std() > 25.0  # not flat
    top = a[: cam.height // 12].reshape(-1, 3).mean(axis=0)  # B, G, R
    assert top[0] > top[2] + 15 and top.mean() > 120  # bright blue sky at the top
    bottom = a[-cam.height // 12:].reshape(-1, 3).mean(axis=0)
    assert bottom.mean() < top.mean()  # darker water at the bottom


@pytest.mark.parametrize("which", ["marina", "terminal"])
def test_scene_points_land_on_rendered_structure(which, request):
    scene: PortScene = request.getfixturevalue(which)
    sc = scene.scenario
    cam = camera_calibration(sc)
    t = 0.5 * sc.path_keyframes[-1][0]
    C, p = _pose(sc, t)
    img, depth = scene.render(C, p, t, cam, np.random.default_rng(0), return_depth=True)
    assert depth.shape == img.shape[:2]
    points, kinds = scene.scene_points()
    assert points.shape == (len(kinds), 3)
    uv, d = project_points(points, C, p, cam)
    # surfaces seen at less than 15 deg are too oblique for a point to be well defined
    view = (p - points) / np.linalg.norm(p - points, axis=1)[:, None]
    facing = np.einsum("ij,ij->i", view, scene.point_normals) > np.sin(np.radians(15.0))
    inside = facing & (d > 1.0) & np.all(uv >= 2, axis=1) & (uv[:, 0] < cam.width - 2) & \
        (uv[:, 1] < cam.height - 2)
    ij = np.rint(uv[inside]).astype(int)
    d_in = d[inside]
    # rendered depth in the 3x3 neighbourhood (a point may sit within a pixel of a silhouette)
    nb = np.stack([depth[ij[:, 1] + dy, ij[:, 0] + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    ratio = nb / d_in
    on_surface = np.any(np.abs(ratio - 1.0) < 0.03, axis=0)
    occluded = ~on_surface & np.all(ratio < 0.97, axis=0)
    missing = ~on_surface & ~occluded  # structure that should be there is not rendered
    assert on_surface.sum() > 300
    assert missing.mean() < 0.01, np.array(kinds)[inside][missing][:20]
    # a corner detector finds most of the visible points
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    corners = cv2.goodFeaturesToTrack(gray, 20000, 0.005, 2).reshape(-1, 2)
    vis_uv = uv[inside][on_surface]
    near = np.array([np.min(np.sum((corners - q) ** 2, axis=1)) for q in vis_uv]) <= 9.0
    assert near.mean() > 0.7
    assert {"quay", "bollard", "building"} <= set(np.array(kinds)[inside][on_surface])


def test_water_moves_structure_does_not(marina):
    cam = camera_calibration(SMALL_BOAT)
    C, p = _pose(SMALL_BOAT, 75.0)
    a, depth = marina.render(C, p, 75.0, cam, np.random.default_rng(4), return_depth=True)
    b = marina.render(C, p, 75.1, cam, np.random.default_rng(4))
    gy, gx = np.mgrid[0:cam.height:2, 0:cam.width:2]
    z = depth[gy, gx].ravel()
    finite = np.isfinite(z)
    uv = np.column_stack([gx.ravel(), gy.ravel()])[finite]
    ned = _pixels_ned(uv, z[finite], C, p, cam)
    diff = np.abs(a.astype(float) - b.astype(float)).sum(axis=2)[gy, gx].ravel()[finite]
    water = (np.abs(ned[:, 2]) < 0.02) & (ned[:, 0] < -0.5)
    structure = ned[:, 2] < -0.3
    assert water.sum() > 20000 and structure.sum() > 5000
    assert diff[water].mean() > 6.0
    assert diff[structure].mean() < 0.25 * diff[water].mean()
    assert diff[structure].mean() < 2.0


def test_orb_finds_many_keypoints_on_structure(marina):
    cam = camera_calibration(SMALL_BOAT)
    t = 60.0
    C, p = _pose(SMALL_BOAT, t)
    img, depth = marina.render(C, p, t, cam, np.random.default_rng(5), return_depth=True)
    kps = cv2.ORB_create(nfeatures=1500).detect(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), None)
    assert len(kps) > 300
    uv = np.array([k.pt for k in kps])
    ij = np.rint(uv).astype(int)
    z = depth[ij[:, 1], ij[:, 0]]
    finite = np.isfinite(z)
    ned = _pixels_ned(uv[finite], z[finite], C, p, cam)
    above_water = np.count_nonzero(ned[:, 2] < -0.05)
    assert above_water > 0.6 * len(kps)


def test_lens_distortion_bends_the_quay_edge(marina):
    """The yellow band along the top of the quay face is straight in the world; near the top
    of the picture the lens bends it, exactly as cv2.projectPoints predicts."""
    cam = camera_calibration(SMALL_BOAT)
    # 10 m off the quay looking north, pitched down so the band runs near the top of the image
    C_body_to_level = euler_to_dcm(0.0, np.radians(-13.0), 0.0)
    C = (C_body_to_level @ camera_to_body(0.0, 0.0)).T
    p = np.array([-10.0, -2.0, -1.0])
    img = marina.render(C, p, 0.0, cam, np.random.default_rng(6))
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    yellow = (hsv[..., 0] > 18) & (hsv[..., 0] < 35) & (hsv[..., 1] > 120) & (hsv[..., 2] > 120)
    qh = SMALL_BOAT.quay_height_m
    east = np.linspace(-20.0, 16.0, 2000)
    line = np.column_stack([np.zeros_like(east), east, np.full_like(east, -qh + 0.06)])
    uv, _ = project_points(line, C, p, cam)
    cols = np.arange(20, cam.width - 20, 4)
    v_pred = np.interp(cols, uv[:, 0], uv[:, 1])
    # a straight line through the ends: the distorted prediction bows away from it
    chord = np.interp(cols, [cols[0], cols[-1]], [v_pred[0], v_pred[-1]])
    assert np.max(np.abs(v_pred - chord)) > 8.0
    err = []
    for c, v in zip(cols, v_pred, strict=True):
        rows = np.nonzero(yellow[int(v) - 15:int(v) + 16, c])[0]
        if 3 <= len(rows) <= 14:  # band only (no ladder rail or occluder in this column)
            err.append(rows.mean() + int(v) - 15 - v)
    err = np.array(err)
    assert len(err) > 0.6 * len(cols)
    assert np.median(np.abs(err)) < 1.0
    # and the detected band is indeed curved, not straight
    assert np.percentile(np.abs(err), 90) < 0.2 * np.max(np.abs(v_pred - chord))


def test_quay_outline_and_point_kinds(marina, terminal):
    for scene in (marina, terminal):
        sc = scene.scenario
        q = scene.quay_outline_ne()
        assert q.ndim == 2 and q.shape[1] == 2
        assert q[0, 1] == pytest.approx(sc.quay_east_range[0])
        assert q[-1, 1] == pytest.approx(sc.quay_east_range[1])
        assert np.all(q[:, 0] <= 0.0)
        pts, kinds = scene.scene_points()
        assert np.all(np.isfinite(pts))
    assert {"quay", "fender", "bollard", "building", "ladder", "boat"} <= set(
        marina.scene_points()[1])
    assert {"quay", "fender", "bollard", "building", "crane", "container", "ship"} <= set(
        terminal.scene_points()[1])
