"""What each seed draws (recordings/sim/variety.py): deterministic, idempotent, varied over a set
of seeds, and plausible berthings on every seed (the manoeuvre the motion model makes of the
drawn keyframes, not the keyframes alone)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from backend.reports.tracking import CLICK_RANGE_M, DEFAULT_CLICK_TIMES_S

from recordings.sim import variety
from recordings.sim.motion import ShipMotion
from recordings.sim.scenarios import LARGE_SHIP, SMALL_BOAT
from recordings.sim.variety import look, seeded

SMALL_SEEDS = range(1, 25)
LARGE_SEEDS = range(1, 9)


def test_draws_are_deterministic_and_idempotent():
    a, b = seeded(SMALL_BOAT, 7), seeded(SMALL_BOAT, 7)
    assert a == b and seeded(a, 7) == a  # a recording's scenario gives its own seed back
    variety._CACHE.clear()
    assert seeded(SMALL_BOAT, 7) == a and look(SMALL_BOAT, 7) == look(a, 7)
    assert seeded(SMALL_BOAT, 8) != a
    # what a seed does not draw is the registered scenario's
    for f in dataclasses.fields(SMALL_BOAT):
        if f.name not in variety._SEEDED_FIELDS:
            assert getattr(a, f.name) == getattr(SMALL_BOAT, f.name), f.name
    # a caller's variant keeps its own path and camera (only the port varies)
    still = dataclasses.replace(SMALL_BOAT, name="static", duration_s=20.0,
                                path_keyframes=((0.0, -20.0, 5.0, 30.0), (20.0, -20.0, 5.0, 30.0)))
    s = seeded(still, 3)
    assert s.path_keyframes == still.path_keyframes
    assert s.camera_lever_arm == still.camera_lever_arm
    assert s.quay_height_m == look(still, 3).port.quay_height_m


def test_seeds_vary_what_real_ports_vary():
    """Over the small-boat set: every light, calm and choppy water, every quay material,
    low-rise and tall ports, moored and moving boats, the bow in view on some seeds only,
    camera heights and tilts and speeds spread over their ranges."""
    looks = [look(SMALL_BOAT, k) for k in SMALL_SEEDS]
    scs = [seeded(SMALL_BOAT, k) for k in SMALL_SEEDS]
    assert {lk.light.kind for lk in looks} == set(variety.LIGHT_KINDS)
    chop = np.array([lk.water.chop for lk in looks])
    assert chop.min() < 0.15 and chop.max() > 0.6
    assert {lk.port.quay_material for lk in looks} == set(variety.QUAY_MATERIALS)
    tallest = np.array([max(lk.port.heights_m) for lk in looks])
    assert tallest.min() <= 12.0 and tallest.max() >= 45.0
    assert any(b.surge_m > 0 for lk in looks for b in lk.port.boats)
    assert any(b.speed > 0 for lk in looks for b in lk.port.boats)
    assert any(not b.moves for lk in looks for b in lk.port.boats)
    fwd = np.array([sc.camera_lever_arm[0] for sc in scs])
    bow_in_view = fwd < 0.5 * SMALL_BOAT.hull_length_m - 1.0
    assert 0.1 < bow_in_view.mean() < 0.75  # some seeds, not all (p = 0.35 a seed)
    height = np.array([-sc.reference_point_down_m - sc.camera_lever_arm[2] for sc in scs])
    assert height.min() < 1.0 and height.max() > 1.9
    tilt = np.array([sc.camera_tilt_deg for sc in scs])
    assert tilt.min() < 2.0 and tilt.max() > 6.0
    az = np.array([lk.light.sun_az_deg for lk in looks])
    assert np.ptp(az) > 180.0
    large = [seeded(LARGE_SHIP, k) for k in LARGE_SEEDS]
    assert {np.sign(sc.camera_pan_deg) for sc in large} == {-1.0, 1.0}  # quay to port/starboard
    assert len({look(LARGE_SHIP, k).port.cranes for k in LARGE_SEEDS}) >= 3


def test_quay_span_matches_the_tracking_evaluation():
    """The span over which every small-boat seed keeps the quay in view is the one the
    tracking evaluation clicks in."""
    assert variety.QUAY_IN_VIEW_S == (min(DEFAULT_CLICK_TIMES_S), max(DEFAULT_CLICK_TIMES_S))
    lo, hi = variety.QUAY_IN_VIEW_RANGE_M
    assert CLICK_RANGE_M[0] <= lo < hi <= CLICK_RANGE_M[1]


def _kinematics(sc, seed, t):
    motion = ShipMotion(sc, seed)
    st = motion.state(t)
    centre = np.array([*sc.motion_centre_body, -sc.reference_point_down_m])
    speed = np.linalg.norm(motion.point_velocity_ned(t, centre)[:, :2], axis=1)
    yaw_rate = np.degrees(np.gradient(np.unwrap(st.euler[:, 2]), t))
    cam = motion.point_position_ned(t, np.array(sc.camera_lever_arm))
    axis = st.C_body_to_level @ (sc.C_camera_to_body @ np.array([0.0, 0.0, 1.0]))
    return motion, st, speed, yaw_rate, cam, np.arctan2(axis[:, 1], axis[:, 0])


def _quay_seen_m(sc, cam, azimuth, range_m):
    """Metres of quay face (every 0.5 m) in range and within the picture's width."""
    e = np.arange(sc.quay_east_range[0], sc.quay_east_range[1], 0.5)
    d = np.stack([np.broadcast_to(-cam[:, :1], (len(cam), len(e))), e[None] - cam[:, 1:2]], -1)
    dist = np.hypot(np.linalg.norm(d, axis=-1), cam[:, 2:3])
    off = np.abs(np.angle(np.exp(1j * (np.arctan2(d[..., 1], d[..., 0]) - azimuth[:, None]))))
    ok = (dist > range_m[0]) & (dist < range_m[1]) & (off < np.radians(sc.camera_hfov_deg / 2))
    return 0.5 * ok.sum(axis=1)


@pytest.mark.parametrize("seed", SMALL_SEEDS)
def test_small_boat_berthing_is_plausible(seed):
    sc, lk = seeded(SMALL_BOAT, seed), look(SMALL_BOAT, seed)
    t = np.linspace(0.0, sc.duration_s, 901)
    motion, st, speed, yaw_rate, cam, azimuth = _kinematics(sc, seed, t)
    assert 0.75 <= speed.max() <= 1.5  # the thesis' boat: ~1 m/s
    assert 5.0 <= np.abs(yaw_rate).max() <= 12.5  # ~10 deg/s turns
    assert speed[-1] < 0.3  # nearly stopped
    assert np.abs(motion.surge_sway(t)[1]).max() <= variety.MAX_SWAY_MS + 1e-9
    assert 5.0 <= -cam[-1, 0] <= 17.0  # the quay 7-15 m ahead of the camera at the end
    # the hull (a circle round its centre) never touches the quay or what is moored
    centre = st.position_ned[:, :2]
    r = 0.5 * sc.hull_length_m
    assert centre[:, 0].max() < -r
    if lk.port.pontoon is not None:
        pe, pl, pw = lk.port.pontoon
        dn = np.maximum(np.maximum(-pl - centre[:, 0], centre[:, 0]), 0.0)
        de = np.maximum(np.maximum(pe - centre[:, 1], centre[:, 1] - pe - pw), 0.0)
        assert np.hypot(dn, de).min() > r
    for b in lk.port.boats:  # moored or passing, at every time
        gap = np.linalg.norm(b.position(t) - centre, axis=1).min()
        assert gap > r + 0.5 * b.length, (b, gap)
    # the quay in view within the evaluation's click range while it clicks
    click = (t >= variety.QUAY_IN_VIEW_S[0]) & (t <= variety.QUAY_IN_VIEW_S[1])
    seen = _quay_seen_m(sc, cam[click], azimuth[click], CLICK_RANGE_M)
    assert seen.min() >= 5.0, seen.min()


@pytest.mark.parametrize("seed", LARGE_SEEDS)
def test_large_ship_berthing_is_plausible(seed):
    sc = seeded(LARGE_SHIP, seed)
    t = np.linspace(0.0, sc.duration_s, 601)
    motion, st, speed, yaw_rate, cam, azimuth = _kinematics(sc, seed, t)
    assert speed.max() <= 0.2 and np.abs(yaw_rate).max() <= 1.5
    assert np.all((-cam[:, 0] > 60.0) & (-cam[:, 0] < 135.0))  # quay ~100 m away
    assert 15.5 < -cam[:, 2].mean() < 28.5
    antenna = motion.point_position_ned(t, sc.antennas_body().mean(axis=0))
    assert np.all(-antenna[:, 0] < sc.mask_range_m)  # the cranes mask satellites
    assert _quay_seen_m(sc, cam, azimuth, (0.0, 300.0)).min() > 50.0
