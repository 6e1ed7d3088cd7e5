"""Overlay geometry, hull prediction and berth-line read-outs (pure functions, no server).

backend/geometry.py, backend/overlay.py, estimator/prediction.py.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from backend.geometry import berth_metrics, hue_color
from backend.overlay import OverlayConfig, build_overlay, polygon_distance
from engine.camera import Projector, camera_pose, water_plane_point
from estimator.frames import camera_to_body, euler_to_dcm
from estimator.prediction import predict_outlines, predict_poses
from estimator.records import CameraCalibration, Hull

K = np.array([[681.7, 0.0, 479.5], [0.0, 681.7, 299.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.05, 0.0005, -0.0003, 0.0])
CAMERA = CameraCalibration(960, 600, K, DIST, camera_to_body(0.0, np.radians(3.0)),
                           np.array([3.0, 0.0, -0.4]))
HULL = Hull(np.array([[3.5, 0.0], [1.75, 1.25], [-3.5, 1.25], [-3.5, -1.25], [1.75, -1.25]]),
            7.0, 2.5)
WATER = 0.6  # the water plane's down coordinate (body origin 0.6 m above the water at start)


def make_state(position=(0.0, 0.0, 0.0), euler=(0.0, 0.0, 0.0), velocity=(0.0, 0.0, 0.0),
               rate=0.0) -> SimpleNamespace:
    e = np.array(euler, dtype=float)
    return SimpleNamespace(time=100.0, position_ned=np.array(position, dtype=float),
                           llh_deg=np.zeros(3), velocity_ned=np.array(velocity, dtype=float),
                           euler=e, C_body_to_level=euler_to_dcm(*e), rate_of_turn=rate,
                           omega_body=np.zeros(3), position_cov=np.eye(3) * 1e-4,
                           attitude_cov=np.eye(3) * 1e-6, status=None)


# ------------------------------------------------------------------------------ prediction


def test_prediction_straight_line_keeps_body_frame_velocity():
    heading = np.radians(30.0)
    v_body = np.array([1.0, 0.2])  # forward, drifting to starboard
    R = np.array([[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]])
    state = make_state((5.0, -3.0, 0.0), (0.0, 0.0, heading), (*(R @ v_body), 0.0))
    outlines = predict_outlines(state, HULL, 3)
    assert len(outlines) == 3
    for k, outline in enumerate(outlines, start=1):
        expected = HULL.outline_body @ R.T + np.array([5.0, -3.0]) + k * (R @ v_body)
        np.testing.assert_allclose(outline, expected, atol=1e-9)
    assert predict_outlines(state, HULL, 0) == []


def test_prediction_constant_turn_matches_integration():
    heading, rate = np.radians(-20.0), np.radians(10.0)
    v_body = np.array([1.2, -0.3])
    R = np.array([[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]])
    positions, headings = predict_poses(np.zeros(2), heading, R @ v_body, rate, [1.0, 2.0, 5.0])
    # brute-force integration of the same model
    dt, p, h, out = 1e-4, np.zeros(2), heading, {}
    for i in range(1, 50001):
        c, s = np.cos(h + rate * dt / 2), np.sin(h + rate * dt / 2)
        p = p + dt * np.array([[c, -s], [s, c]]) @ v_body
        h += rate * dt
        if i in (10000, 20000, 50000):
            out[i] = p.copy()
    np.testing.assert_allclose(positions, np.array([out[10000], out[20000], out[50000]]),
                               atol=1e-6)
    np.testing.assert_allclose(headings, heading + rate * np.array([1.0, 2.0, 5.0]))


# -------------------------------------------------------------------------------- projection


@pytest.mark.parametrize("euler_deg", [(0, 0, 0), (4, -2, 35), (-6, 3, -120)])
def test_grid_nodes_reproject_to_the_water_plane(euler_deg):
    state = make_state((12.0, -7.0, 0.02), np.radians(euler_deg), (1.0, 0.3, 0.0), 0.1)
    projector = Projector(CAMERA)
    overlay = build_overlay(state, CAMERA, HULL, projector,
                            config=OverlayConfig(water_down_m=WATER))
    grid = overlay["video"]["grid"]
    nodes = np.array(grid["nodes"]["ned"])
    uv = np.array(grid["nodes"]["uv"])
    assert len(nodes) > 20 and grid["plane_down_m"] == WATER
    pose = camera_pose(state, CAMERA)
    for node, pixel in zip(nodes, uv, strict=True):
        hit = water_plane_point(pose.position_ned, projector.pixel_ray(pose, *pixel), WATER)
        assert hit is not None
        assert np.linalg.norm(hit - node) < 1e-3  # 1 mm, even 30 m away at a grazing angle
    assert len(grid["lines"]) > 10
    for line in grid["lines"]:  # clipped to the frustum: never folded far outside the image
        pts = np.array(line)
        assert (pts[:, 0] > -80).all() and (pts[:, 0] < 1040).all()
        assert (pts[:, 1] > -80).all() and (pts[:, 1] < 680).all()


def test_segments_behind_the_camera_are_clipped_at_the_near_plane():
    projector = Projector(CAMERA)
    pose = camera_pose(make_state(), CAMERA)
    # camera at (3, 0, -0.4) looking north: one segment crosses behind it, one is all behind
    a = np.array([[-20.0, 0.5, 0.6], [-30.0, 0.0, 0.6]])
    b = np.array([[40.0, 0.5, 0.6], [-5.0, 0.0, 0.6]])
    ca, cb, keep = projector.clip_segments(pose.to_camera(a), pose.to_camera(b))
    assert keep.tolist() == [True, False]
    for end in (ca[0], cb[0]):  # both ends inside the frustum (up to rounding)
        x, y = end[:2] / end[2]
        assert end[2] >= projector.near - 1e-9
        assert projector.x_min - 1e-9 <= x <= projector.x_max + 1e-9
        assert projector.y_min - 1e-9 <= y <= projector.y_max + 1e-9
    lines = projector.project_segments(pose, a, b)
    assert len(lines) == 1
    assert np.isfinite(lines[0]).all()
    # a point far outside the field of view must not fold back into the image
    visible, _uv = projector.project_points(pose, np.array([[3.5, 30.0, 0.6]]))
    assert not visible[0]


def test_points_colour_and_visibility():
    state = make_state()
    projector = Projector(CAMERA)
    pts = np.array([[13.0, 0.0, -1.0], [25.0, 2.0, -3.0], [-20.0, 0.0, 0.0]])  # ahead, behind
    sigma = np.array([0.2, 3.0, 0.2])  # the second one still converging (σ 14 % of range)
    overlay = build_overlay(state, CAMERA, HULL, projector, (pts, sigma, np.arange(3)),
                            config=OverlayConfig(water_down_m=WATER, color_range_m=40.0))
    points = overlay["video"]["points"]
    assert points["id"] == [0, 1]
    assert points["converged"] == [True, False]
    assert overlay["birdseye"]["points"]["converged"] == [True, True, False]  # nearest first
    assert points["distance_m"][0] == pytest.approx(np.linalg.norm(pts[0] - [3.0, 0, -0.4]),
                                                    abs=0.01)
    assert points["color"][0] == hue_color([10.0], 40.0)[0]
    assert hue_color([0.0, 40.0, 99.0], 40.0) == ["#ff0000", "#0000ff", "#0000ff"]
    assert len(overlay["birdseye"]["points"]["ne"]) == 3  # plan shows behind the camera too


# ------------------------------------------------------------------------------ berth line


def test_berth_metrics_bow_stern_distance_and_approach_speed():
    line = np.array([[0.0, -50.0], [0.0, 50.0]])  # an east-west quay edge at north = 0
    # heading east, 6 m south of the line, moving north (towards it) at 0.2 m/s, no turn
    state = make_state((-6.0, 0.0, 0.0), (0.0, 0.0, np.pi / 2), (0.2, 0.0, 0.0))
    m = berth_metrics(state, HULL, line)
    assert m["bow_distance_m"] == pytest.approx(6.0 - 1.25, abs=1e-6)  # port side faces it
    assert m["stern_distance_m"] == pytest.approx(6.0 - 1.25, abs=1e-6)
    assert m["bow_approach_mps"] == pytest.approx(0.2)
    assert m["stern_approach_mps"] == pytest.approx(0.2)
    # turning to port (negative rate) swings the bow towards the quay, the stern away
    state.rate_of_turn = -0.05
    m = berth_metrics(state, HULL, line)
    assert m["bow_approach_mps"] > 0.2 > m["stern_approach_mps"]


def test_polygon_distance_and_water_plane_point():
    square = np.array([[0.0, 0.0], [0.0, 2.0], [2.0, 2.0], [2.0, 0.0]])
    assert polygon_distance(np.array([1.0, 1.0]), square) == 0.0
    assert polygon_distance(np.array([5.0, 1.0]), square) == pytest.approx(3.0)
    hit = water_plane_point(np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 1.0]) / np.sqrt(2),
                            0.5)
    np.testing.assert_allclose(hit, [1.5, 0.0, 0.5])
    assert water_plane_point(np.zeros(3), np.array([1.0, 0.0, -0.1]), 0.5) is None  # looks up
