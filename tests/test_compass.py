"""GNSS compass attitude: the thesis' fast method, the conventional one, single differences,
and the conventional double-difference baseline on the real static pair."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from estimator import compass as cm
from estimator.baseline import RelativePositioning
from estimator.cpp import BASELINE_PAIRS, epoch_geometry
from estimator.frames import (
    SPEED_OF_LIGHT,
    dcm_to_euler,
    ecef_to_ned,
    euler_to_dcm,
    geodetic_to_ecef,
    wrap_angle,
)
from estimator.records import GnssEpoch
from estimator.spp import standalone_position
from recordings.rinex import l1_epochs, read_nav, read_obs
from recordings.sim.gnss import GnssErrorModel, simulate_gnss
from recordings.sim.scenarios import SMALL_BOAT
from recordings.sim.simulate import NAV_FILE

DATA = Path(__file__).parent / "data"
ANTENNAS = SMALL_BOAT.antennas_body()
LAYOUT = cm.layout_baselines(ANTENNAS)
START = SMALL_BOAT.start_gpst
NO_SLIPS = dataclasses.replace(GnssErrorModel(), slip_rate_per_epoch=0.0)


@pytest.fixture(scope="module")
def nav():
    return read_nav(NAV_FILE)


def attitude(t: float) -> np.ndarray:
    """Turning at 6 deg/s with wave roll and pitch (rad)."""
    return np.array([0.035 * np.sin(2 * np.pi * t / 3.5), 0.017 * np.sin(2 * np.pi * t / 5.0),
                     np.radians(20.0) + np.radians(6.0) * t])


def turning(t: float, i: int) -> np.ndarray:
    return euler_to_dcm(*attitude(t)) @ ANTENNAS[i] + np.array([-1.0 * t, 0.3 * t, -1.0])


def noisy_tilt(t: float, rng: np.random.Generator) -> tuple[float, float]:
    """Accelerometer tilt: the truth plus 1 deg of manoeuvre/bias error."""
    r, p, _ = attitude(t)
    return r + math.radians(rng.normal()), p + math.radians(rng.normal())


def keep(ep: GnssEpoch | None, sats) -> GnssEpoch | None:
    if ep is None:
        return None
    return GnssEpoch(ep.time, {s: o for s, o in ep.satellites.items() if s in sats}, ep.flag)


def epoch_dd(nav, eps, systems="GEJ", sats=None):
    spp = standalone_position([e for e in eps if e is not None], nav)
    names = [s for s in eps[0].satellites if s[0] in systems and (sats is None or s in sats)]
    geo = epoch_geometry(nav, names, eps[0].time, spp.position,
                         spp.clock_bias_m / SPEED_OF_LIGHT)
    tracked = [s for s in geo.satellites if all(s in e.satellites for e in eps)]
    return geo, cm.double_differences(eps, geo, tracked)


def true_integers(dd: cm.DoubleDifferences, C: np.ndarray) -> np.ndarray:
    pred = (C @ LAYOUT[:3].T).T @ dd.H.T / dd.wavelength
    return np.round(dd.dd - pred).astype(np.int64)


def heading_error_deg(C: np.ndarray, t: float) -> float:
    return float(np.degrees(wrap_angle(dcm_to_euler(C)[2] - attitude(t)[2])))


# -------------------------------------------------------------------- geometry test


def test_dot_and_cross_test_of_the_six_baselines():
    a_cos, a_sin = cm.baseline_angles(LAYOUT)
    # Square: sides at 90 deg, diagonals at 45 deg to the sides, parallel opposite sides.
    assert np.degrees(a_cos).round(6).tolist().count(90.0) >= 4
    assert np.all(np.degrees(a_sin) <= 90.0 + 1e-9)
    C = euler_to_dcm(0.05, -0.03, 2.0)
    ok = (C @ LAYOUT.T).T
    assert cm.check_baseline_geometry(ok, LAYOUT, 0.01, math.radians(5))
    # Lengths off by 2 cm fail.
    assert not cm.check_baseline_geometry(ok * 1.2, LAYOUT, 0.01, math.radians(5))
    # A pair at the supplementary angle (135 deg instead of 45) has the same |cross|: only the
    # dot product (acos) rejects it. Here b_03 is mirrored through b_01.
    b = np.array([[0.1, 0.0, 0.0], [0.1, 0.1, 0.0]])
    ref = np.array([[0.1, 0.0, 0.0], [-0.1, 0.1, 0.0]])
    cos_b, sin_b = cm.baseline_angles(np.vstack([b, np.zeros((4, 3)) + 1e-3]))
    cos_r, sin_r = cm.baseline_angles(np.vstack([ref, np.zeros((4, 3)) + 1e-3]))
    assert abs(sin_b[0] - sin_r[0]) < 1e-12 and abs(cos_b[0] - cos_r[0]) > math.radians(80)


def test_wrong_integers_are_rejected_by_the_layout_test(nav):
    obs, _ = simulate_gnss(SMALL_BOAT, turning, nav, START, 1.0, seed=5, errors=NO_SLIPS)
    eps = [o[0] for o in obs]
    geo, dd = epoch_dd(nav, eps, systems="G")
    dd5 = cm.double_differences(eps, geo, [dd.reference, *dd.sats[:4]])  # 5 satellites
    C = euler_to_dcm(*attitude(0.0))
    good = true_integers(dd5, C)
    b0, _ = cm._baseline_ls(dd5, good)
    assert cm.check_baseline_geometry(cm._all_baselines(b0), LAYOUT, 0.015, math.radians(8))
    wrong = []
    for j in range(3):
        for k in range(len(dd5.sats)):
            for step in (-1, 1):
                bad = good.copy()
                bad[j, k] += step
                wrong.append(bad)
    b0, _ = cm._baseline_ls(dd5, np.array(wrong))
    passed = cm.check_baseline_geometry(cm._all_baselines(b0), LAYOUT, 0.015, math.radians(8))
    assert not passed.any()


# ------------------------------------------------------------------ fast method


def test_fast_method_fixes_from_one_epoch(nav):
    rng = np.random.default_rng(1)
    obs, _ = simulate_gnss(SMALL_BOAT, turning, nav, START, 15.0, seed=2, errors=NO_SLIPS)
    heading = []
    for k in range(len(obs[0])):
        geo, dd = epoch_dd(nav, [o[k] for o in obs])
        res = cm.resolve_fast(dd, ANTENNAS, noisy_tilt(float(k), rng))
        assert res.fixed, res.message
        assert np.array_equal(res.integers, true_integers(dd, euler_to_dcm(*attitude(k))))
        heading.append(heading_error_deg(res.C_body_to_level, float(k)))
        assert res.n_candidates > res.n_survivors == 1
    assert np.sqrt(np.mean(np.square(heading))) < 1.0


def test_fast_method_with_four_gps_satellites(nav):
    rng = np.random.default_rng(2)
    obs, _ = simulate_gnss(SMALL_BOAT, turning, nav, START, 10.0, seed=3, errors=NO_SLIPS)
    geo0, dd0 = epoch_dd(nav, [o[0] for o in obs], systems="G")
    four = [dd0.reference, *sorted(dd0.sats, key=lambda s: -geo0.satellites[s].elevation)[:3]]
    fixed = 0
    for k in range(len(obs[0])):
        _, dd = epoch_dd(nav, [o[k] for o in obs], sats=set(four))
        assert dd.n_satellites == 4
        res = cm.resolve_fast(dd, ANTENNAS, noisy_tilt(float(k), rng))
        if res.fixed:
            fixed += 1
            assert np.array_equal(res.integers, true_integers(dd, euler_to_dcm(*attitude(k))))
            assert abs(heading_error_deg(res.C_body_to_level, float(k))) < 6.0
    assert fixed >= 8


def test_compass_keeps_the_fix_on_a_rotating_platform_through_slips(nav):
    rng = np.random.default_rng(3)
    slips = dataclasses.replace(GnssErrorModel(), slip_rate_per_epoch=1.0 / 150.0)
    obs, truth = simulate_gnss(SMALL_BOAT, turning, nav, START, 40.0, seed=4, errors=slips)
    assert truth.slips  # the simulation did slip
    comp = cm.GnssCompass(nav, ANTENNAS)
    errors, sigmas = [], []
    for k in range(len(obs[0])):
        sol = comp.update([o[k] for o in obs], noisy_tilt(float(k), rng))
        assert sol.fixed, (k, sol.message)
        assert sol.method == ("fast" if k == 0 else "hold-dd")
        errors.append(heading_error_deg(sol.C_body_to_level, float(k)))
        sigmas.append(math.degrees(math.sqrt(sol.attitude_covariance[2, 2])))
    rms = np.sqrt(np.mean(np.square(errors)))
    assert rms < 1.0 and np.max(np.abs(errors)) < 3.0
    # The heading σ handed to the EKF is honest: it covers the error, conservatively (3 mm
    # phase noise assumed; the simulated carrier noise follows C/N0, mostly below that).
    assert rms < np.mean(sigmas) < 6.0 * rms + 0.3
    # The integers held at the end are the true ones (N_0j = N_0 − N_j up to one offset).
    for j in (1, 2, 3):
        held = sol.integers[(0, j)]
        n_true = {s: truth.ambiguities[0][s] - truth.ambiguities[j][s] for s in held}
        offsets = {held[s] - n_true[s] for s in held}
        assert len(offsets) == 1
    assert sol.delays_m is not None and len(sol.delays_m) == 6
    # The six baselines come back with their lengths.
    assert np.allclose(np.linalg.norm(sol.baselines_ned, axis=1),
                       np.linalg.norm(LAYOUT, axis=1), atol=0.02)


# ------------------------------------------------------------------- conventional


def test_conventional_method_needs_five_satellites_and_fixes(nav):
    obs, _ = simulate_gnss(SMALL_BOAT, turning, nav, START, 30.0, seed=6, errors=NO_SLIPS)
    geo0, dd0 = epoch_dd(nav, [o[0] for o in obs], systems="G")
    by_el = [dd0.reference, *sorted(dd0.sats, key=lambda s: -geo0.satellites[s].elevation)]
    four = [[keep(e, set(by_el[:4])) for e in o] for o in obs]
    five = [[keep(e, set(by_el[:5])) for e in o] for o in obs]
    comp4 = cm.GnssCompass(nav, ANTENNAS, method="conventional", systems="G")
    comp5 = cm.GnssCompass(nav, ANTENNAS, method="conventional", systems="G")
    first = None
    for k in range(len(obs[0])):
        sol4 = comp4.update([o[k] for o in four])
        assert not sol4.fixed and "< 5" in sol4.message
        sol5 = comp5.update([o[k] for o in five])
        if sol5.fixed and first is None:
            first = k
            assert sol5.method == "conventional" and sol5.ratio >= 3.0
            assert abs(heading_error_deg(sol5.C_body_to_level, float(k))) < 4.0
    assert first is not None


# ------------------------------------------------------------- single differences


def test_attitude_from_two_satellites_single_differences(nav):
    obs, truth = simulate_gnss(SMALL_BOAT, turning, nav, START, 2.0, seed=7, errors=NO_SLIPS)
    k = 2  # the truth holds the ambiguities of the last epoch
    eps = [o[k] for o in obs]
    geo, _ = epoch_dd(nav, eps)
    # Two satellites far apart in azimuth at mid elevation.
    cands = [s for s, g in geo.satellites.items() if 0.4 < g.elevation < 1.1]
    pair = max(((a, b) for a in cands for b in cands if a < b),
               key=lambda p: abs(math.sin(geo.satellites[p[0]].azimuth
                                          - geo.satellites[p[1]].azimuth)))
    d = truth.hardware_delay_m
    zetas = {}
    for i, j in BASELINE_PAIRS:
        zetas[(i, j)] = {}
        for s in pair:
            lam = geo.wavelengths[s]
            sd = lam * (eps[i].satellites[s].carrier_phase - eps[j].satellites[s].carrier_phase)
            n_ij = truth.ambiguities[i][s] - truth.ambiguities[j][s]
            zetas[(i, j)][s] = sd - (d[i] - d[j]) - lam * n_ij
    los = {s: geo.los_ned(s) for s in pair}
    true = attitude(float(k))
    start = euler_to_dcm(true[0], true[1], true[2] + math.radians(10.0))
    att = cm.attitude_from_single_differences(zetas, los, ANTENNAS, start)
    assert att is not None and att.n_satellites == 2
    err = np.degrees(wrap_angle(att.euler - true))
    assert abs(err[2]) < 3.0 and att.residual_rms_m < 0.01
    # One satellite gives two equations for three angles: only with the IMU tilt.
    one = {pq: {pair[0]: z[pair[0]]} for pq, z in zetas.items()}
    assert cm.attitude_from_single_differences(one, los, ANTENNAS, start) is None
    att1 = cm.attitude_from_single_differences(one, los, ANTENNAS, start,
                                               tilt=(true[0], true[1]))
    assert att1 is not None and abs(np.degrees(wrap_angle(att1.euler[2] - true[2]))) < 5.0


def test_compass_holds_attitude_on_two_satellites_and_a_dropout(nav):
    rng = np.random.default_rng(8)
    obs, _ = simulate_gnss(SMALL_BOAT, turning, nav, START, 25.0, seed=9, errors=NO_SLIPS)
    comp = cm.GnssCompass(nav, ANTENNAS)
    kept = None
    for k in range(len(obs[0])):
        eps = [o[k] for o in obs]
        if k == 12:
            eps[3] = None  # receiver 4 misses an epoch: single differences carry on
        if k >= 15:
            if kept is None:
                geo, _ = epoch_dd(nav, eps)
                mid = [s for s, g in geo.satellites.items() if 0.4 < g.elevation < 1.2]
                kept = set(sorted(mid, key=lambda s: geo.satellites[s].azimuth)[::3][:2])
            eps = [keep(e, kept) for e in eps]
        sol = comp.update(eps, noisy_tilt(float(k), rng))
        assert sol.fixed, (k, sol.message)
        if k == 12 or k >= 15:
            assert sol.method == "hold-sd"
            assert abs(heading_error_deg(sol.C_body_to_level, float(k))) < 5.0
        if k == 12:
            assert abs(heading_error_deg(sol.C_body_to_level, float(k))) < 2.0


def test_three_antennas_fix_from_one_epoch(nav):
    """A receiver lost leaves three antennas: three baselines, two of them independent, and
    the layout test on three angles instead of fifteen. Still one epoch, the true integers,
    never a wrong set — with every satellite and with only four GPS ones."""
    rng = np.random.default_rng(8)
    obs, _ = simulate_gnss(SMALL_BOAT, turning, nav, START, 10.0, seed=9, errors=NO_SLIPS)
    fixed = 0
    for lost in (3, 0):  # the last receiver; the reference (resolve_fast takes any three)
        here = [i for i in range(4) if i != lost]
        layout = cm.layout_baselines(ANTENNAS[here])
        assert layout.shape == (3, 3)
        for k in range(len(obs[0])):
            eps = [obs[i][k] for i in here]
            geo, dd = epoch_dd(nav, eps, systems="G")
            four = [dd.reference, *sorted(dd.sats, key=lambda s: -geo.satellites[s].elevation)[:3]]
            for d in (dd, cm.double_differences(eps, geo, four)):
                assert d.n_baselines == 2
                res = cm.resolve_fast(d, ANTENNAS[here], noisy_tilt(float(k), rng))
                if not res.fixed:
                    continue
                fixed += 1
                C = euler_to_dcm(*attitude(k))
                truth = np.round(d.dd - (C @ layout[:2].T).T @ d.H.T / d.wavelength)
                assert np.array_equal(res.integers, truth), (lost, k, d.n_satellites)
                assert abs(heading_error_deg(res.C_body_to_level, float(k))) < 6.0
                assert res.baselines_ned.shape == (3, 3)
    assert fixed >= 0.9 * 4 * len(obs[0])


@pytest.mark.parametrize("lost", [3, 0])
def test_compass_fixes_and_holds_on_the_receivers_it_has(nav, lost):
    """One receiver never delivers (a cable cut, or missing from the recording; the last, or
    the first — the reference): the compass resolves on the other three from the first epoch
    and holds through slips, with the true integers and an honest heading σ. With two
    receivers gone it does not fix, and says which are missing."""
    rng = np.random.default_rng(3)
    slips = dataclasses.replace(GnssErrorModel(), slip_rate_per_epoch=1.0 / 150.0)
    obs, truth = simulate_gnss(SMALL_BOAT, turning, nav, START, 40.0, seed=4, errors=slips)
    here = tuple(i for i in range(4) if i != lost)
    comp = cm.GnssCompass(nav, ANTENNAS)
    errors, sigmas = [], []
    for k in range(len(obs[0])):
        sol = comp.update([None if i == lost else obs[i][k] for i in range(4)],
                          noisy_tilt(float(k), rng))
        assert sol.fixed, (k, sol.message)
        assert sol.method == ("fast" if k == 0 else "hold-dd") and sol.receivers == here
        errors.append(heading_error_deg(sol.C_body_to_level, float(k)))
        sigmas.append(math.degrees(math.sqrt(sol.attitude_covariance[2, 2])))
    rms = np.sqrt(np.mean(np.square(errors)))
    assert rms < 1.0 and np.max(np.abs(errors)) < 3.0
    assert rms < np.mean(sigmas) < 6.0 * rms + 0.3
    ref, others = here[0], here[1:]
    assert set(sol.integers) == {(i, j) for i in here for j in here if i < j}
    assert len(sol.delays_m) == 3
    for j in others:  # N_ref,j = N_ref − N_j up to one offset per baseline
        held = sol.integers[(ref, j)]
        assert len({held[s] - (truth.ambiguities[ref][s] - truth.ambiguities[j][s])
                    for s in held}) == 1
    for gone, named in (((2, 3), "receiver 3, 4 without"), ((0, 1), "receiver 1, 2 without")):
        comp = cm.GnssCompass(nav, ANTENNAS)
        for k in range(3):
            sol = comp.update([None if i in gone else obs[i][k] for i in range(4)])
            assert not sol.fixed
            assert named in sol.message and "a fix needs 3 receivers" in sol.message
    with pytest.raises(ValueError, match="at least 3 antennas"):
        cm.GnssCompass(nav, ANTENNAS[:2])


# --------------------------------------------------------- real static pair (DD KF)


def _surveyed(name: str) -> np.ndarray:
    lat, lon, h = (float(v) for v in (DATA / name).read_text().split()[:3])
    return np.array([math.radians(lat), math.radians(lon), h])


def test_real_static_pair_conventional_baseline():
    nav = read_nav(DATA / "static.nav")
    base = l1_epochs(read_obs(DATA / "static_base.obs"))
    rover = l1_epochs(read_obs(DATA / "static_rover.obs"))
    b_llh, r_llh = _surveyed("static_base_position.txt"), _surveyed("static_rover_position.txt")
    truth = ecef_to_ned(geodetic_to_ecef(*r_llh), b_llh)
    length = np.linalg.norm(truth)
    azimuth = math.degrees(math.atan2(truth[1], truth[0])) % 360.0
    assert length == pytest.approx(0.990, abs=0.001) and azimuth == pytest.approx(193.0, abs=0.2)
    for start in range(0, len(base) - 10, 20):  # cold starts every 20 s
        rp = RelativePositioning(nav)
        for k in range(start, min(start + 30, len(base))):
            sol = rp.update(base[k], rover[k])
            if sol.fixed:
                break
        assert sol.fixed, f"no fix within 30 s of {start}: {sol.message}"
        assert abs(sol.length - length) < 0.01
        assert abs(sol.azimuth_deg - azimuth) < 0.5
        assert np.linalg.norm(sol.baseline_ned - truth) < 0.02


def test_without_ephemerides_the_compass_says_it_waits_for_them(nav):
    """A live start knows no satellite's orbit until the receivers have sent its navigation
    message (~30 s): the compass says so, with how many it has, instead of a bare 'no
    standalone position yet' (a user trial: 25 s of 'initialising' and no reason)."""
    obs, _truth = simulate_gnss(SMALL_BOAT, turning, nav, START, 2.0, seed=4, errors=NO_SLIPS)
    sats = sorted({s for e in obs[0] for s in e.satellites})
    some = dataclasses.replace(nav, ephemerides={s: nav.ephemerides[s] for s in sats[:2]
                                                 if s in nav.ephemerides})
    sol = cm.GnssCompass(some, ANTENNAS).update([o[0] for o in obs], None)
    assert not sol.fixed
    assert "broadcast ephemerides of 2 of" in sol.message, sol.message
    assert "waiting for their navigation messages" in sol.message
