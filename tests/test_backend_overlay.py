"""Overlay geometry, hull prediction and berth-line read-outs (pure functions, no server).

backend/geometry.py, backend/overlay.py, estimator/prediction.py.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from backend.geometry import BAND_COLORS, berth_metrics, distance_band, polygon_distances
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
               rate=0.0, drift_m=0.0) -> SimpleNamespace:
    e = np.array(euler, dtype=float)
    return SimpleNamespace(time=100.0, position_ned=np.array(position, dtype=float),
                           llh_deg=np.zeros(3), velocity_ned=np.array(velocity, dtype=float),
                           euler=e, C_body_to_level=euler_to_dcm(*e), rate_of_turn=rate,
                           omega_body=np.zeros(3), position_cov=np.eye(3) * 1e-4,
                           position_drift_cov=np.eye(3) * drift_m**2,
                           attitude_cov=np.eye(3) * 1e-6, velocity_cov=np.zeros((3, 3)),
                           status=None)


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
    # ahead (converged), ahead (still converging: σ 14 % of range), behind, ahead on the water
    pts = np.array([[13.0, 0.0, -1.0], [25.0, 2.0, -3.0], [-20.0, 0.0, 0.0], [9.0, 1.0, 0.62]])
    sigma = np.array([0.2, 3.0, 0.2, 0.1])
    overlay = build_overlay(state, CAMERA, HULL, projector, (pts, sigma, np.arange(4)),
                            config=OverlayConfig(water_down_m=WATER, grid_radius_m=20.0))
    points = overlay["video"]["points"]
    assert points["id"] == [3, 0, 1]  # visible, nearest first
    assert points["converged"] == [True, True, False]
    # drawn by default: converged, above the water and near the ship (within 20 m here)
    assert points["obstacle"] == [False, True, False]
    # plan, nearest the camera first: water, ahead, converging, behind (16.5 m from the stern)
    assert overlay["birdseye"]["points"]["obstacle"] == [False, True, False, True]
    assert points["distance_m"][1] == pytest.approx(np.linalg.norm(pts[0] - [3.0, 0, -0.4]),
                                                    abs=0.01)
    # coloured by the fixed band of the distance from the hull (bow at 3.5 m: 9.5 m → 5-10 m)
    assert points["hull_distance_m"][1] == pytest.approx(9.5, abs=0.01)
    assert points["band"][1] == 2 and points["color"][1] == BAND_COLORS[2]
    assert overlay["distance_bands_m"] == [2.0, 5.0, 10.0, 20.0, 50.0, 100.0]
    assert distance_band([0.0, 1.99, 2.0, 49.0, 100.0, 1e4]).tolist() == [0, 0, 1, 4, 6, 6]
    assert len(overlay["birdseye"]["points"]["ne"]) == 4  # plan shows behind the camera too
    assert overlay["video"]["hull"] == []  # the bow is below the field of view here
    # from a camera at the stern the current hull outline shows at the water line
    aft = CameraCalibration(960, 600, K, DIST, CAMERA.C_camera_to_body, np.array([-3.4, 0, -0.4]))
    hull = build_overlay(state, aft, HULL, Projector(aft),
                         config=OverlayConfig(water_down_m=WATER))["video"]["hull"]
    bow = Projector(aft).project_points(camera_pose(state, aft), np.array([[3.5, 0.0, WATER]]))
    assert bow[0][0] and min(np.hypot(*(np.array(p) - bow[1][0])) for line in hull
                             for p in line) < 1.0


def test_polygon_distances_match_the_single_point_form():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-8, 8, (200, 2))
    got = polygon_distances(pts, HULL.outline_body)
    want = [polygon_distance(p, HULL.outline_body) for p in pts]
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert (got == 0).sum() > 5  # some inside


def _quay_wall(north: float, east: np.ndarray, heights: np.ndarray) -> np.ndarray:
    """Points on a vertical quay face at ``north`` (down = WATER - height)."""
    e, h = np.meshgrid(east, heights)
    return np.column_stack([np.full(e.size, north), e.ravel(), WATER - h.ravel()])


def test_water_grid_stops_at_the_quay_face():
    state = make_state()  # camera at north 3 m, looking north
    projector = Projector(CAMERA)
    wall = _quay_wall(15.0, np.arange(-20.0, 20.1, 0.5), np.array([0.3, 0.8, 1.3]))
    tree = np.array([[22.0, 1.0, WATER - 4.0], [22.5, -1.0, WATER - 5.0]])  # on land
    pts = np.vstack([wall, tree])
    overlay = build_overlay(state, CAMERA, HULL, projector,
                            (pts, np.full(len(pts), 0.05), np.arange(len(pts))),
                            config=OverlayConfig(water_down_m=WATER, grid_radius_m=30.0))
    # the quay face is an obstacle, the tree 7 m behind it (as near the ship) is not
    points = overlay["video"]["points"]
    kind = dict(zip(points["id"], points["obstacle"], strict=True))
    assert kind[len(wall)] is False and kind[len(wall) + 1] is False
    assert np.mean([kind[i] for i in range(len(wall)) if i in kind]) > 0.9
    nodes = np.array(overlay["video"]["grid"]["nodes"]["ned"])
    assert len(nodes) > 20 and nodes[:, 0].max() < 15.0  # no node behind the wall
    pose = camera_pose(state, CAMERA)
    for line in overlay["video"]["grid"]["lines"]:
        for u, v in line:  # every drawn grid pixel is water in front of the wall
            hit = water_plane_point(pose.position_ned, projector.pixel_ray(pose, u, v), WATER)
            assert hit is not None and hit[0] < 15.0 + 0.6, (u, v, hit)
    # without the wall the grid runs on beyond it
    bare = build_overlay(state, CAMERA, HULL, projector, config=OverlayConfig(water_down_m=WATER))
    assert np.array(bare["video"]["grid"]["nodes"]["ned"])[:, 0].max() > 20.0
    # a berth line cuts it too
    line = np.array([[10.0, -30.0], [10.0, 30.0]])
    cut = build_overlay(state, CAMERA, HULL, projector, berth_line_ne=line,
                        config=OverlayConfig(water_down_m=WATER))
    assert np.array(cut["video"]["grid"]["nodes"]["ned"])[:, 0].max() < 10.0


# ------------------------------------------------------------------------------ berth line


def test_berth_metrics_bow_stern_distance_and_approach_speed():
    line = np.array([[0.0, -50.0], [0.0, 50.0]])  # an east-west quay edge at north = 0
    # heading east, 6 m south of the line, moving north (towards it) at 0.2 m/s, no turn
    state = make_state((-6.0, 0.0, 0.0), (0.0, 0.0, np.pi / 2), (0.2, 0.0, 0.0))
    m = berth_metrics(state, HULL, line)
    # from the foremost point (the stem, on the centreline) and the aftmost one (the transom's
    # port corner faces the quay)
    assert m["bow_distance_m"] == pytest.approx(6.0, abs=1e-9)
    assert m["stern_distance_m"] == pytest.approx(6.0 - 1.25, abs=1e-9)
    assert m["nearest_distance_m"] == pytest.approx(6.0 - 1.25, abs=1e-9)
    assert m["bow_approach_mps"] == pytest.approx(0.2)
    assert m["stern_approach_mps"] == pytest.approx(0.2)
    assert m["along_berth_mps"] == pytest.approx(0.0, abs=1e-12)
    assert m["angle_deg"] == pytest.approx(0.0, abs=1e-9)
    assert m["time_to_contact_s"] == pytest.approx((6.0 - 1.25) / 0.2)
    # σ: the position's across the line (1 cm), the heading's (1 mrad) through the stem's
    # 3.5 m lever, and the line's own
    assert m["bow_distance_sigma_m"] == pytest.approx(np.hypot(0.01, 0.0035), abs=1e-6)
    m = berth_metrics(state, HULL, line, line_sigma_m=0.05)
    assert m["bow_distance_sigma_m"] == pytest.approx(np.sqrt(0.01**2 + 0.0035**2 + 0.05**2),
                                                      abs=1e-6)
    # the angle's σ: the heading's (1 mrad), and the line's direction; the time to contact's:
    # the first point's distance σ (a side point: lever across the line ≤ 3.5 m) over 0.2 m/s
    assert m["angle_sigma_deg"] == pytest.approx(np.degrees(0.001), rel=1e-6)
    assert np.hypot(0.01, 0.05) / 0.2 <= m["time_to_contact_sigma_s"] \
        <= np.sqrt(0.01**2 + 0.0035**2 + 0.05**2) / 0.2 + 1e-9
    m = berth_metrics(state, HULL, line, line_sigma_deg=2.0)
    assert m["angle_sigma_deg"] == pytest.approx(np.hypot(2.0, np.degrees(0.001)), rel=1e-6)
    # turning to port (negative rate) swings the bow towards the quay, the stern away
    state.rate_of_turn = -0.05
    m = berth_metrics(state, HULL, line)
    assert m["bow_approach_mps"] > 0.2 > m["stern_approach_mps"]
    # the approach speeds' σ: the velocity's across the line (an INS fault found: 5 cm/s
    # north, 1 cm/s east); it carries into the time to contact, ttc · σ_v / v
    state.rate_of_turn = 0.0
    state.velocity_cov = np.diag([0.05**2, 0.01**2, 0.0])
    m = berth_metrics(state, HULL, line)
    assert m["bow_approach_sigma_mps"] == pytest.approx(0.05)
    assert m["stern_approach_sigma_mps"] == pytest.approx(0.05)
    ttc = m["time_to_contact_s"]
    assert m["time_to_contact_sigma_s"] == pytest.approx(
        np.hypot(0.01, ttc * 0.05) / 0.2, rel=0.05)
    # ... and the rate of turn's through the lever: the stem 3.5 m out, 1 mrad/s → 3.5 mm/s
    state.velocity_cov = np.zeros((3, 3))
    state.rate_of_turn_sigma = 0.001
    m = berth_metrics(state, HULL, line)
    assert m["bow_approach_sigma_mps"] == pytest.approx(0.0035)


def test_berth_metrics_at_an_angle_take_the_ends_not_midships():
    line = np.array([[0.0, -50.0], [0.0, 50.0]])
    # bow 30 deg in towards the quay (heading 60 deg), sliding east at 0.3 m/s, opening
    psi = np.radians(60.0)
    state = make_state((-10.0, 0.0, 0.0), (0.0, 0.0, psi), (-0.05, 0.3, 0.0))
    m = berth_metrics(state, HULL, line)
    assert m["bow_distance_m"] == pytest.approx(10.0 - 3.5 * np.cos(psi), abs=1e-9)
    # aftmost corners (-3.5, ±1.25): the port one is nearer the quay
    R = np.array([[np.cos(psi), -np.sin(psi)], [np.sin(psi), np.cos(psi)]])
    corners = np.array([[-3.5, 1.25], [-3.5, -1.25]]) @ R.T + [-10.0, 0.0]
    assert m["stern_distance_m"] == pytest.approx(-corners[:, 0].max(), abs=1e-9)
    assert m["angle_deg"] == pytest.approx(30.0, abs=1e-9)  # positive: bow in
    assert m["along_berth_mps"] == pytest.approx(0.3)
    assert m["bow_approach_mps"] == pytest.approx(-0.05)
    assert m["time_to_contact_s"] is None  # opening: no contact
    assert m["time_to_contact_sigma_s"] is None


def test_berth_angle_names_where_the_bow_points_even_nearly_parallel():
    """A user trial: a 200 m ship with her bow turned 4.5–5.2° towards the quay read
    "stern in" — the sign compared the bow's distance with the nearer stern corner's, which
    for angles below atan(half beam / length) is nearer whichever way the bow points."""
    line = np.array([[0.0, -50.0], [0.0, 50.0]])  # the quay along north = 0, ship south of it
    for deg in (1.0, 3.0, 8.0, 30.0):
        # heading east (90°), turned towards the quay (north) by deg: heading 90 - deg
        toward = make_state((-10.0, 0.0, 0.0), (0.0, 0.0, np.radians(90.0 - deg)), (0, 0, 0))
        away = make_state((-10.0, 0.0, 0.0), (0.0, 0.0, np.radians(90.0 + deg)), (0, 0, 0))
        assert berth_metrics(toward, HULL, line)["angle_deg"] == pytest.approx(deg, abs=1e-9)
        assert berth_metrics(away, HULL, line)["angle_deg"] == pytest.approx(-deg, abs=1e-9)
    # going astern with the bow towards the quay is still bow in
    astern = make_state((-10.0, 0.0, 0.0), (0.0, 0.0, np.radians(85.0)), (0.0, -0.5, 0.0))
    assert berth_metrics(astern, HULL, line)["angle_deg"] == pytest.approx(5.0, abs=1e-9)


def test_berth_speeds_carry_the_lines_direction_sigma():
    """A user trial: a berth line on the water plane (direction σ 12–26°) with the boat sliding
    along it read "▼71 cm/s CLOSING" with no ± (σ 0.2 cm/s) while she closed at 109: a line
    turned by δ takes δ of the speed along it into the approach. The along-berth speed had no
    σ at all."""
    line = np.array([[0.0, -50.0], [0.0, 50.0]])
    # heading east along the quay at 1 m/s, closing at 0.2 m/s
    state = make_state((-10.0, 0.0, 0.0), (0.0, 0.0, np.pi / 2), (0.2, 1.0, 0.0))
    exact = berth_metrics(state, HULL, line)
    assert exact["bow_approach_sigma_mps"] == pytest.approx(0.0, abs=1e-12)
    assert exact["along_berth_sigma_mps"] == pytest.approx(0.0, abs=1e-12)
    m = berth_metrics(state, HULL, line, line_sigma_deg=20.0)
    sd = np.radians(20.0)
    assert m["bow_approach_sigma_mps"] == pytest.approx(1.0 * sd, rel=1e-6)
    assert m["along_berth_sigma_mps"] == pytest.approx(0.2 * sd, rel=1e-6)
    # and it covers what the line's turn does: the true line 15° off the stated one
    turned = np.array([[0.0, 0.0], [np.sin(np.radians(15.0)), np.cos(np.radians(15.0))]]) * 50
    t = berth_metrics(state, HULL, turned)
    assert abs(t["bow_approach_mps"] - m["bow_approach_mps"]) < 2 * m["bow_approach_sigma_mps"]
    assert abs(t["along_berth_mps"] - m["along_berth_mps"]) < 2 * m["along_berth_sigma_mps"]
    # the velocity's own σ along the line
    state.velocity_cov = np.diag([0.0, 0.03**2, 0.0])
    assert berth_metrics(state, HULL, line)["along_berth_sigma_mps"] == pytest.approx(0.03)


def test_polygon_distance_and_water_plane_point():
    square = np.array([[0.0, 0.0], [0.0, 2.0], [2.0, 2.0], [2.0, 0.0]])
    assert polygon_distance(np.array([1.0, 1.0]), square) == 0.0
    assert polygon_distance(np.array([5.0, 1.0]), square) == pytest.approx(3.0)
    hit = water_plane_point(np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 1.0]) / np.sqrt(2),
                            0.5)
    np.testing.assert_allclose(hit, [1.5, 0.0, 0.5])
    assert water_plane_point(np.zeros(3), np.array([1.0, 0.0, -0.1]), 0.5) is None  # looks up
