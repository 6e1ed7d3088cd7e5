"""The berth line from clicks on the quay face, typed in and nudged, and the berthing alarms of
the session's alarm book (backend/berth.py, backend/alarms.py; pure, no server).

A synthetic port: a quay face at north 15 m (points from the water line to the coping), a
building behind it, a boat moored in front of part of it and reflections below the water; the
camera 1 m above the water looking north at it."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from backend.alarms import AlarmBook, ApproachLimit
from backend.berth import Berth
from backend.errors import Unprocessable
from backend.geometry import berth_metrics
from engine.camera import Projector, camera_pose
from engine.targets import Structure
from tests.test_backend_overlay import CAMERA, HULL, WATER, make_state

QUAY_N = 15.0
COPING_M = 1.5  # quay top above the water


def _planes(*planes: tuple, seed: int = 0) -> Structure:
    """Structure points on vertical planes (north, east values, heights above the water, σ)."""
    rng = np.random.default_rng(seed)
    parts = []
    for n, e, h, sigma in planes:
        e, h = np.meshgrid(e, h)
        p = np.column_stack([np.full(e.size, n), e.ravel(), WATER - h.ravel()])
        p += rng.normal(0.0, sigma, p.shape) * [1, 0.2, 0.2]
        parts.append((p, np.full(len(p), sigma)))
    pts = np.concatenate([p for p, _ in parts])
    sigma = np.concatenate([s for _, s in parts])
    return Structure(0.0, pts, sigma, np.arange(len(pts)))


def _port(seed: int = 0) -> Structure:
    return _planes(
        (QUAY_N, np.arange(-25.0, 25.0, 1.3), np.array([0.3, 0.8, 1.3]), 0.05),  # the face
        (QUAY_N + 12.0, np.arange(-30.0, 30.0, 0.8), np.arange(2.0, 12.0, 1.5), 0.3),  # building
        (11.0, np.arange(6.0, 12.0, 0.7), np.array([0.3, 0.7]), 0.05),  # a moored boat
        (9.0, np.arange(-10.0, 10.0, 1.0), np.array([-0.4]), 0.05),  # reflections: under water
        seed=seed)


def _berth(structure_known: bool = True) -> Berth:
    rec = SimpleNamespace(hull=SimpleNamespace(outline_body=HULL.outline_body,
                                               berth_line_ned=None),
                          calibration=SimpleNamespace(camera=CAMERA))
    return Berth(rec, Projector(CAMERA), WATER if structure_known else None,
                 lambda s: np.zeros(3), threading.RLock())


def _pixel(state, ned) -> np.ndarray:
    projector = Projector(CAMERA)
    visible, uv = projector.project_points(camera_pose(state, CAMERA), np.atleast_2d(ned))
    assert visible.all(), ned
    return uv


TRUE_BOW = QUAY_N - 3.5  # the stem is 3.5 m ahead of the body origin at north 0


@pytest.mark.parametrize("height", [0.0, 0.7, COPING_M])  # water line, wall, coping
def test_clicks_on_the_quay_give_the_bow_distance_and_a_slip_hardly_moves_it(height):
    state = make_state()
    berth = _berth()
    clicks = _pixel(state, [[QUAY_N, -4.0, WATER - height], [QUAY_N, 5.0, WATER - height]])
    line = berth.set_image(state, clicks, _port())
    assert line.method == "quay-face" and line.support >= 20, line
    bow = berth.status(state, 0.0)["bow_distance_m"]
    assert bow == pytest.approx(TRUE_BOW, abs=max(0.15, 0.01 * TRUE_BOW))
    assert 0 < line.sigma_m < 0.1
    for du, dv in [(3, 0), (-3, 0), (0, 3), (0, -3), (3, -3)]:
        berth.set_image(state, clicks + [du, dv], _port())
        slipped = berth.status(state, 0.0)["bow_distance_m"]
        assert abs(slipped - bow) <= 0.3, (du, dv, slipped, bow)
        assert abs(slipped - TRUE_BOW) <= max(0.15, 0.01 * TRUE_BOW)


def test_the_moored_boat_in_front_is_not_the_quay_unless_clicked():
    state = make_state()
    berth = _berth()
    # both clicks on the quay, one of them beside the boat
    clicks = _pixel(state, [[QUAY_N, -6.0, WATER], [QUAY_N, 4.0, WATER - 0.5]])
    berth.set_image(state, clicks, _port())
    assert berth.status(state, 0.0)["bow_distance_m"] == pytest.approx(TRUE_BOW, abs=0.15)


def test_without_structure_the_line_falls_back_to_the_water_plane_and_says_so():
    state = make_state()
    berth = _berth()
    empty = Structure(None)
    foot = _pixel(state, [[QUAY_N, -4.0, WATER], [QUAY_N, 5.0, WATER]])
    line = berth.set_image(state, foot, empty)
    assert line.method == "water-plane" and "water plane" in line.note
    assert berth.status(state, 0.0)["bow_distance_m"] == pytest.approx(TRUE_BOW, abs=0.05)
    # a 3 px slip on the water plane moves it by metres: that is why the quay face is used;
    # its σ says so
    berth.set_image(state, foot + [0, -3], empty)
    slipped = berth.status(state, 0.0)
    assert slipped["bow_distance_m"] - TRUE_BOW > 0.5
    assert slipped["bow_distance_m"] - TRUE_BOW <= 2.0 * slipped["bow_distance_sigma_m"] < 4.0
    # the coping is above the horizon: no water plane there, and no structure
    coping = _pixel(state, [[QUAY_N, -4.0, WATER - COPING_M], [QUAY_N, 5.0, WATER - COPING_M]])
    with pytest.raises(Unprocessable, match="above the horizon"):
        berth.set_image(state, coping, empty)
    # the quay face is found from the coping once there is structure
    assert berth.set_image(state, coping, _port()).method == "quay-face"


@pytest.mark.parametrize("pitch_deg", [1.0, -1.0])
def test_a_water_plane_line_carries_the_fused_tilt_sigma(pitch_deg):
    """The water plane's range is height·cot(depression): a fused pitch off by a degree moves a
    line 15 m off by 4 m from 1 m up (a large ship's camera 20 m up, 110 m off: 11 m per
    degree). The line's σ carries the attitude's σ, so the error stays within 2σ."""
    truth = make_state()
    foot = _pixel(truth, [[QUAY_N, -4.0, WATER], [QUAY_N, 5.0, WATER]])
    fused = make_state(euler=(0.0, np.radians(pitch_deg), 0.0))  # its pitch 1° off ...
    fused.attitude_cov = np.eye(3) * np.radians(0.7) ** 2  # ... under a σ of 0.7°
    berth = _berth()
    line = berth.set_image(fused, foot, Structure(None))
    assert line.method == "water-plane"
    status = berth.status(fused, 0.0)
    error = status["bow_distance_m"] - TRUE_BOW
    assert abs(error) > 2.0, error  # the tilt moves it by metres
    assert abs(error) <= 2.0 * status["bow_distance_sigma_m"], (error, status)
    fused.attitude_cov = np.eye(3) * 1e-12  # a perfect tilt: the σ of a slipped click only
    berth.set_image(fused, foot, Structure(None))
    assert berth.status(fused, 0.0)["bow_distance_sigma_m"] < abs(error) / 2.0


def test_a_surface_behind_the_water_a_click_shows_is_not_the_quay():
    """The fault of 2026-11-27 on the bundled recording: the quay face has no points near the
    right click (a bare stretch of wall), a building behind the quay has, its wall receding
    from the left click's stretch of quay. The plane through the face's points under the left
    click and the wall's under the right one lies beyond where the right click's ray meets the
    water: that pixel shows the quay's water line, so the plane cannot be what it shows. The
    face's own points farther along are found instead."""
    state = make_state()
    berth = _berth()
    face_e = np.r_[np.arange(-25.0, 3.8, 1.2), np.arange(8.2, 25.0, 1.2)]  # none at 4..8 m
    wall = np.linspace(0.0, 1.2, 30)[:, None] * [11.0, 17.0] + [QUAY_N + 1.0, -5.0]
    port = _planes((QUAY_N, face_e, np.array([0.3, 0.8, 1.3]), 0.05))
    wall_pts = np.column_stack([np.repeat(wall, 4, axis=0),
                                WATER - np.tile([2.0, 4.0, 6.0, 8.0], len(wall))])
    port = Structure(0.0, np.vstack([port.points, wall_pts]),
                     np.r_[port.sigma, np.full(len(wall_pts), 0.05)],
                     np.arange(len(port.points) + len(wall_pts)))
    clicks = _pixel(state, [[QUAY_N, -4.0, WATER], [QUAY_N, 6.0, WATER]])
    line = berth.set_image(state, clicks, port)
    status = berth.status(state, 0.0)
    assert line.method == "quay-face", line
    assert status["bow_distance_m"] == pytest.approx(TRUE_BOW, abs=max(0.15, 0.01 * TRUE_BOW))
    np.testing.assert_allclose(line.line_ne[:, 0], QUAY_N, atol=0.1)


def test_a_plane_behind_points_right_at_a_click_is_not_the_clicked_surface():
    """Far off, the quay has only a few converged points (too few to stand as a face) and the
    buildings behind it many; with the water level unknown nothing bounds the range from the
    water. The quay's points right at the clicks are a nearer surface there: the buildings'
    plane is not what the clicks show, and no line is made up from it."""
    state = make_state()
    berth = _berth(structure_known=False)
    port = _planes((QUAY_N, np.array([-4.3, -3.7, 5.7, 6.3]), np.array([0.5]), 0.05),
                   (QUAY_N + 12.0, np.arange(-30.0, 30.0, 0.8), np.arange(2.0, 12.0, 1.5), 0.1))
    clicks = _pixel(state, [[QUAY_N, -4.0, WATER - 0.5], [QUAY_N, 6.0, WATER - 0.5]])
    with pytest.raises(Unprocessable, match="no converged port structure near the clicks"):
        berth.set_image(state, clicks, port)


def test_a_boat_moored_alongside_ending_beside_the_clicks_is_not_the_quay():
    """A boat moored alongside, 2.5 m in front of the quay, ends a metre short of each click
    (seed 9 of the small-boat scenario: its side was taken for the quay, bow 2.6 m short). Its
    side stands as the nearest plane with points right at both clicks, but it does not extend
    past where either click's ray meets it: not what the clicks are on. Whatever the line is
    then, it is not that side, and its σ covers its error."""
    state = make_state()
    berth = _berth()
    quay_e = np.r_[np.arange(-25.0, -3.0, 1.0), np.arange(5.5, 25.0, 1.0)]  # hidden behind it
    port = _planes((QUAY_N, quay_e, np.array([0.3, 0.8, 1.3]), 0.05),
                   (QUAY_N - 2.5, np.arange(-3.0, 4.5, 0.3), np.array([0.2, 0.6, 1.0]), 0.05))
    clicks = _pixel(state, [[QUAY_N, -4.0, WATER], [QUAY_N, 5.5, WATER]])
    line = berth.set_image(state, clicks, port)
    status = berth.status(state, 0.0)
    error = abs(status["bow_distance_m"] - TRUE_BOW)
    assert error < 1.0 or line.method == "water-plane", (line, status)
    assert error <= 2.0 * status["bow_distance_sigma_m"], (line, status)


def test_a_boat_side_between_the_clicks_is_not_taken_for_the_quay():
    """Early in an approach (the quay 45 m off, none of its points converged yet) a boat's
    side 30 m off, between the clicks' rays but metres from either, stands as a plane with
    points within a fifth of the image of both clicks; it ends short of where either click's
    ray meets it, so it is not what they show. The line falls back to the water plane, whose σ
    covers its error (a 3 px slip included)."""
    state = make_state()
    berth = _berth()
    far, true_bow = 45.0, 45.0 - 3.5
    boat = _planes((30.0, np.arange(-4.0, 5.0, 0.25), np.array([0.2, 0.5, 0.8]), 0.05))
    for slip in ([0, 0], [0, 3], [3, -3]):
        clicks = _pixel(state, [[far, -15.0, WATER], [far, 15.0, WATER]]) + slip
        line = berth.set_image(state, clicks, boat)
        status = berth.status(state, 0.0)
        assert line.method == "water-plane", (slip, line)
        error = abs(status["bow_distance_m"] - true_bow)
        assert error <= 2.0 * status["bow_distance_sigma_m"], (slip, status)


def test_a_face_fitted_across_two_surfaces_says_how_far_off_it_may_be():
    """The quay (north = 0) on one side and a moored boat's side 2 m before it on the other,
    both in the fit's gate: one straight line through both is tilted and 1 m off at their
    middle, and the points (σ 0.2 m each, 40 of them) made its σ a few centimetres (yardstick
    seeds: 14 lines 0.2–1.1 m off under σ of 4–16 cm). The halves' lines disagree: the σ now
    covers where the quay is; on one straight face it stays the points' σ over their count."""
    from backend.berth import fit_line

    rng = np.random.default_rng(7)
    quay = np.column_stack([rng.normal(0.0, 0.05, 20), np.linspace(-20.0, -10.0, 20)])
    boat = np.column_stack([rng.normal(-2.0, 0.05, 20), np.linspace(-4.0, 6.0, 20)])
    both = fit_line(np.vstack([quay, boat]), np.full(40, 0.2))
    assert both is not None
    normal = np.array([-both.direction[1], both.direction[0]])
    for east in (-15.0, 0.0, 1.0):  # the berth line's middle, the bow beside the boat
        true_offset = abs(float((np.array([0.0, east]) - both.centre) @ normal))
        along = float((np.array([0.0, east]) - both.centre) @ both.direction)
        sigma = float(np.hypot(both.sigma_m, both.sigma_rad * along))
        assert true_offset <= 2.0 * sigma, (east, true_offset, sigma)
        if east > 0.0:  # beside the boat the line is the boat's, not the quay's
            assert true_offset > 1.0
    one = fit_line(np.vstack([quay, quay + [0.0, 12.0]]), np.full(40, 0.2))
    assert one is not None and one.sigma_m < 0.1 and np.degrees(one.sigma_rad) < 0.5


def test_the_halves_of_one_straight_face_disagree_as_their_sigma_say():
    """On points of one straight face (their σ 5–50 cm, as stated) the halves' lines differ
    by what their covariances say (χ² of 2 degrees of freedom): the widening is for faces
    that are not one line, not a tax on every fit. Their offsets are compared at one point,
    each carried there along its direction's σ (a sign slip there read 4.1 for 2)."""
    from backend.berth import _at_centre, _weighted_line

    rng = np.random.default_rng(3)
    chi2 = []
    for _ in range(500):
        east = np.sort(rng.uniform(-20.0, 30.0, 30))
        sig = rng.uniform(0.05, 0.5, 30)
        p = np.column_stack([rng.normal(0.0, sig), east])
        w = 1.0 / sig**2
        fit = _weighted_line(p, w)
        first = (p - fit.centre) @ fit.direction < np.median((p - fit.centre) @ fit.direction)
        x_a, P_a = _at_centre(_weighted_line(p[first], w[first]), fit)
        x_b, P_b = _at_centre(_weighted_line(p[~first], w[~first]), fit)
        d = x_a - x_b
        chi2.append(float(d @ np.linalg.solve(P_a + P_b, d)))
    assert 1.4 < np.mean(chi2) < 2.4 and np.mean(np.array(chi2) > 5.99) < 0.08


def test_plan_clicks_snap_to_the_quay_face():
    state = make_state()
    berth = _berth()
    line = berth.set_ned(np.array([[QUAY_N - 1.0, -8.0], [QUAY_N + 0.8, 8.0]]), snap=True,
                         structure=_port(), state=state)
    assert line.method == "quay-face"
    np.testing.assert_allclose(line.line_ne[:, 0], QUAY_N, atol=0.1)
    # nothing there: kept as clicked, with a note
    line = berth.set_ned(np.array([[40.0, -8.0], [40.0, 8.0]]), snap=True,
                         structure=_port(), state=make_state())
    assert line.method is None and "as clicked" in line.note


def test_typed_in_from_the_bow_and_nudged():
    psi = np.radians(30.0)
    state = make_state((5.0, -2.0, 0.0), (0.0, 0.0, psi), (0.1, 0.0, 0.0))
    berth = _berth()
    berth.set_from_bow(state, 12.0, -90.0)  # 12 m on the port beam of the bow
    st = berth.status(state, 0.0)
    assert st["source"] == "typed"
    assert st["bow_distance_m"] == pytest.approx(12.0, abs=1e-6)
    assert st["angle_deg"] == pytest.approx(0.0, abs=1e-6)  # parallel to the centreline
    berth.nudge(state, 0.5, 0.0)  # half a metre away from the ship
    assert berth.status(state, 0.0)["bow_distance_m"] == pytest.approx(12.5, abs=1e-6)
    berth.nudge(state, -1.0, 0.0)
    assert berth.status(state, 0.0)["bow_distance_m"] == pytest.approx(11.5, abs=1e-6)
    berth.nudge(state, 0.0, 5.0)
    assert abs(berth.status(state, 0.0)["angle_deg"]) == pytest.approx(5.0, abs=1e-6)
    berth.set_from_bow(state, 20.0, 0.0)  # dead ahead, across the bow
    st = berth.status(state, 0.0)
    assert st["bow_distance_m"] == pytest.approx(20.0, abs=1e-6)
    assert st["angle_deg"] == pytest.approx(90.0, abs=1e-6)


def test_the_distance_sigma_holds_the_drift_since_the_line_was_set():
    """The fused position drifts against the world more than the filter's covariance says
    (``FusedState.position_drift_cov``). A line measured from the trajectory drifts with it
    until it is set, so only the drift since counts; a line fixed in the world takes it all."""
    psi = np.radians(30.0)
    at_set = make_state((5.0, -2.0, 0.0), (0.0, 0.0, psi), drift_m=0.30)
    later = make_state((5.0, -2.0, 0.0), (0.0, 0.0, psi), drift_m=0.50)
    berth = _berth()
    berth.set_from_bow(at_set, 12.0, -90.0)
    own = berth.status(at_set, 0.0)["bow_distance_sigma_m"]  # the filter's position, heading
    assert own < 0.02
    since = np.sqrt(0.50**2 - 0.30**2)
    assert berth.status(later, 0.0)["bow_distance_sigma_m"] == pytest.approx(
        np.hypot(own, since), abs=2e-3)
    berth.nudge(later, 0.5, 0.0)  # moved by hand: still measured when it was set
    assert berth.status(later, 0.0)["bow_distance_sigma_m"] == pytest.approx(
        np.hypot(own, since), abs=2e-3)
    world = berth.world(later)
    berth.set_ned(world)  # the same line typed in world coordinates: the whole drift
    assert berth.status(later, 0.0)["bow_distance_sigma_m"] == pytest.approx(
        np.hypot(own, 0.50), abs=2e-3)


# -------------------------------------------------------------------------------- alarms


def _closing(distance: float, speed: float, trusted: bool = True) -> tuple:
    """A state with its bow ``distance`` m from a berth line (heading along it, the stern
    1.25 m nearer), closing at ``speed``."""
    line = np.array([[0.0, -50.0], [0.0, 50.0]])
    state = make_state((-distance, 0.0, 0.0), (0.0, 0.0, np.pi / 2),
                       (speed, 0.0, 0.0))
    state.status = SimpleNamespace(integrity=SimpleNamespace(trusted=trusted, reasons=[],
                                                             mode="fused"))
    return state, berth_metrics(state, HULL, line)


def _approach(book: AlarmBook) -> dict[str, dict]:
    return {a["kind"]: a for a in book.active() if a["kind"].startswith("approach")}


def test_approach_alarms_depend_on_the_distance_amber_then_red():
    book = AlarmBook(0.0)
    book.set_approach_limits([ApproachLimit(10.0, 20.0, 30.0), ApproachLimit(50.0, 80.0, 120.0)])
    # 0.5 m/s at 60 m: beyond the table, nothing; at 40 m: within the 80 cm/s row, nothing
    for d in (60.0, 40.0):
        book.update(*_closing(d, 0.5)[:1], [], _closing(d, 0.5)[1])
        assert _approach(book) == {}
    # at 9 m the same speed is above the 30 cm/s alarm speed: red for bow and stern
    state, m = _closing(9.0, 0.5)
    book.update(state, [], m)
    alarms = _approach(book)
    assert alarms.keys() == {"approach-bow", "approach-stern"}
    assert alarms["approach-bow"]["severity"] == "alarm"
    assert "50 cm/s" in alarms["approach-bow"]["message"]
    assert "9.0 m" in alarms["approach-bow"]["message"]
    # slowing to 25 cm/s: amber, the same alarm eased (its acknowledgement kept)
    book.acknowledge(alarms["approach-bow"]["id"])
    state, m = _closing(8.5, 0.25)
    book.update(state, [], m)
    eased = _approach(book)["approach-bow"]
    assert eased["severity"] == "warning" and eased["acknowledged"]
    # ... and the run's list keeps the red it was, with what it said then (a user trial:
    # every red alarm of a replay was listed afterwards as the amber it had eased to)
    listed = next(a for a in book.all() if a["id"] == eased["id"])
    assert listed["peak_severity"] == "alarm" and "50 cm/s" in listed["peak_message"]
    assert "25 cm/s" in listed["message"]
    # speeding up again: a new red alarm, sounding (not acknowledged)
    state, m = _closing(8.0, 0.35)
    book.update(state, [], m)
    again = _approach(book)["approach-bow"]
    assert again["severity"] == "alarm" and not again["acknowledged"]
    assert again["id"] != eased["id"]
    # hysteresis: just under the limit it holds (and says so), well under it clears
    state, m = _closing(7.9, 0.19)
    book.update(state, [], m)
    held = _approach(book)["approach-bow"]
    assert held["severity"] == "warning"
    assert "19 cm/s" in held["message"] and "held until below 18" in held["message"]
    state, m = _closing(7.8, 0.10)
    book.update(state, [], m)
    assert _approach(book) == {}
    # the history keeps every alarm of the run, the replaced and cleared ones too
    bow = [a for a in book.all() if a["kind"] == "approach-bow"]
    assert [a["id"] for a in bow] == [alarms["approach-bow"]["id"], again["id"]]
    assert [a["severity"] for a in bow] == ["warning", "warning"]  # each at its last level
    assert not any(a["active"] for a in bow) and "50 cm/s" not in bow[1]["message"]
    # closing too fast again, at once: a new alarm (approach alarms are news each time)
    state, m = _closing(7.7, 0.25)
    book.update(state, [], m)
    fresh = _approach(book)["approach-bow"]
    assert fresh["id"] not in (alarms["approach-bow"]["id"], again["id"])
    assert not fresh["acknowledged"] and fresh["repeats"] == 0
    state, m = _closing(7.6, 0.10)
    book.update(state, [], m)
    # no berth line, or an untrusted pose: no approach alarm
    state, m = _closing(5.0, 0.6)
    book.update(state, [], None)
    assert _approach(book) == {}
    state, m = _closing(5.0, 0.6, trusted=False)
    book.update(state, [], m)
    assert _approach(book) == {}


def test_an_alarm_back_within_seconds_is_the_same_alarm_again():
    """A heading protection level hovering at its limit flips the trust every second, and
    IMU spikes raise and clear a critical fault every half second: each was a new sounding
    alarm (a user trial counted twelve in 3 s for one cause). Back within ``REARM_S`` of
    clearing, no higher than it was, it is the same alarm again, counted, its acknowledgement
    kept and its first words (the cause) kept; back later it is a new one."""
    from backend.alarms import REARM_S
    from estimator.integrity import Alert

    def state(t: float, trusted: bool, reason: str = "") -> SimpleNamespace:
        return SimpleNamespace(time=t, status=SimpleNamespace(integrity=SimpleNamespace(
            trusted=trusted, reasons=[reason] if reason else [], mode="fused")))

    book = AlarmBook(0.0)
    book.update(state(1.0, True), [])
    book.update(state(2.0, False, "heading protection level 1.04° above the 1° alert limit"),
                [])
    first = book.active()[0]
    book.acknowledge(first["id"])
    for k in range(6):  # hovering: trusted, then not, every half second
        book.update(state(2.5 + k, True), [])
        assert not book.active()
        book.update(state(3.0 + k, False, "heading protection level 1.02° above the 1° "
                                          "alert limit"), [])
    listed = book.all()
    assert len(listed) == 1 and listed[0]["id"] == first["id"], listed
    assert listed[0]["active"] and listed[0]["acknowledged"] and listed[0]["repeats"] == 6
    assert "heading protection level" in listed[0]["message"]
    assert listed[0]["first_message"] == ("Integrity lost: heading protection level 1.04° "
                                          "above the 1° alert limit")
    # another cause within seconds: a new alarm, sounding (an IMU gap 4 s after a PL)
    book.update(state(8.5, True), [])
    book.update(state(8.7, False, "no IMU sample for over 0.3 s"), [])
    other = book.active()[0]
    assert other["id"] != first["id"] and not other["acknowledged"] and other["since_s"] == 8.7
    book.acknowledge(other["id"])
    # trusted for longer than REARM_S, then lost: a new alarm, sounding
    book.update(state(9.0, True), [])
    book.update(state(9.0 + REARM_S + 0.5, False, "no IMU sample for over 0.3 s"), [])
    assert [a["id"] not in (first["id"], other["id"]) and not a["acknowledged"]
            for a in book.active()] == [True]
    # a critical engine fault raised and cleared by every spike: one alarm, counted
    alerts = []
    for k in range(6):
        alerts += [Alert(20.0 + 0.5 * k, "imu-implausible", "IMU sample implausible: dropped"),
                   Alert(20.1 + 0.5 * k, "imu-implausible", "IMU samples plausible", False)]
        book.update(state(20.2 + 0.5 * k, True), alerts)
    spikes = [a for a in book.all() if a["kind"] == "imu-implausible"]
    assert len(spikes) == 1 and spikes[0]["repeats"] == 5 and not spikes[0]["active"]
    # an active fault's words go on (its count): the alarm says them, its first words kept
    alerts.append(Alert(30.0, "receiver-2-silent", "receiver 2 silent for 1 epoch"))
    book.update(state(30.0, True), alerts)
    later = Alert(30.0, "receiver-2-silent", "receiver 2 silent for 10 epochs")
    book.update(state(39.0, True), alerts, None, [later])
    rx = next(a for a in book.active() if a["kind"] == "receiver-2-silent")
    assert rx["message"] == later.message and rx["first_message"].endswith("1 epoch")
