"""Carrier-phase processing: TDCP velocity, cycle slips, η (tight coupling), ζ and D_ij."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from estimator import cpp
from estimator.frames import SPEED_OF_LIGHT, C_ecef_to_level, euler_to_dcm, geodetic_to_ecef
from estimator.records import GnssEpoch, NavigationData
from estimator.spp import standalone_position
from recordings.rinex import l1_epochs, read_nav, read_obs
from recordings.sim.gnss import GnssErrorModel, simulate_gnss
from recordings.sim.scenarios import SMALL_BOAT
from recordings.sim.simulate import NAV_FILE

DATA = Path(__file__).parent / "data"
ANTENNAS = SMALL_BOAT.antennas_body()
LEVERS = ANTENNAS - ANTENNAS.mean(axis=0)
START = SMALL_BOAT.start_gpst
YAW_RATE = np.radians(6.0)


# ------------------------------------------------------------------------------ data


@pytest.fixture(scope="module")
def real():
    nav = read_nav(DATA / "static.nav")
    base = l1_epochs(read_obs(DATA / "static_base.obs"), systems="GEJ")
    rover = l1_epochs(read_obs(DATA / "static_rover.obs"), systems="GEJ")
    return nav, base, rover


@pytest.fixture(scope="module")
def sim_nav():
    return read_nav(NAV_FILE)


def turning_array(t: float, i: int) -> np.ndarray:
    """Array turning at 6 deg/s while accelerating north-west, small wave roll."""
    C = euler_to_dcm(0.03 * np.sin(2 * np.pi * t / 3.5), 0.0, np.radians(20.0) + YAW_RATE * t)
    return C @ ANTENNAS[i] + np.array([-1.0 * t + 0.05 * t * t, 0.3 * t, -1.0])


def centroid_velocity(t1: float, t2: float) -> np.ndarray:
    """True mean velocity of the antenna centroid over [t1, t2] (scenario seconds)."""
    p = [np.mean([turning_array(t, i) for i in range(4)], axis=0) for t in (t1, t2)]
    return (p[1] - p[0]) / (t2 - t1)


@pytest.fixture(scope="module")
def sim(sim_nav):
    obs, truth = simulate_gnss(SMALL_BOAT, turning_array, sim_nav, START, 20.0, seed=11,
                               errors=dataclasses.replace(GnssErrorModel(),
                                                          slip_rate_per_epoch=0.0))
    return obs, truth


def keep(ep: GnssEpoch | None, sats) -> GnssEpoch | None:
    if ep is None:
        return None
    return GnssEpoch(ep.time, {s: o for s, o in ep.satellites.items() if s in sats}, ep.flag)


def with_phase(ep: GnssEpoch, sat: str, add_cycles: float = 0.0, **fields) -> GnssEpoch:
    """Copy of ``ep`` with ``sat``'s phase shifted and other fields replaced."""
    ob = ep.satellites[sat]
    new = dataclasses.replace(ob, carrier_phase=ob.carrier_phase + add_cycles, **fields)
    return GnssEpoch(ep.time, {**ep.satellites, sat: new}, ep.flag)


def horizontal(v: np.ndarray) -> float:
    return float(np.hypot(v[0], v[1]))


# ----------------------------------------------------------------- real static data


def test_tdcp_velocity_of_static_real_receivers_is_zero(real):
    nav, base, rover = real
    for epochs in (base, rover):
        v = [cpp.tdcp_velocity(epochs[k - 1], epochs[k], nav, systems="GEJ")
             for k in range(1, 60)]
        assert all(x is not None for x in v)
        V = np.array([x.velocity_ned for x in v])
        h = np.hypot(V[:, 0], V[:, 1])
        assert np.sqrt(np.mean(h**2)) < 0.01  # target: <= 1 cm/s horizontal RMS
        assert h.max() < 0.02
        assert np.sqrt(np.mean(V[:, 2] ** 2)) < 0.02
        assert all(len(x.satellites) >= 10 for x in v)


def test_an_epochs_own_tdcp_fit_on_real_receivers(real):
    """``cpp.tdcp_fit`` on the real static receiver (its antenna still, its clock free): the
    satellites scatter ~1.7 mm/s about the fit, within the phase noise the rows state (no
    common rate error beyond it); a burst of 10 mm/s per satellite is read as one; a velocity
    the INS got wrong is the fit's correction (what the INS check weighs), not scatter."""
    nav, base, _ = real
    rng = np.random.default_rng(5)
    quiet, burst, moved = [], [], []
    wrong = np.array([0.05, -0.03, 0.02])
    for k in range(1, 40):
        eps = [base[k - 1], base[k]]
        geos = []
        for ep in eps:
            spp = standalone_position([ep], nav)
            geos.append(cpp.epoch_geometry(nav, sorted(ep.satellites), ep.time, spp.position,
                                           spp.clock_bias_m / SPEED_OF_LIGHT))
        rows = cpp.eta_observations([eps[0]], [eps[1]], geos[0], geos[1]).rows
        sats = [r.sat for r in rows]
        u = np.array([r.los_ned for r in rows])
        y = np.array([r.measured for r in rows])  # still: the velocity is zero
        sigma = np.array([r.sigma for r in rows])
        quiet.append(cpp.tdcp_fit(sats, y, u, sigma))
        kick = {s: rng.normal(0.0, 0.010) for s in sorted(set(sats))}  # (set order varies)
        burst.append(cpp.tdcp_fit(sats, y + [kick[s] for s in sats], u, sigma).scatter)
        moved.append(cpp.tdcp_fit(sats, y + u @ wrong, u, sigma))
    assert len(quiet) == 39 and all(f.satellites >= 10 for f in quiet)
    assert np.median([f.scatter for f in quiet]) < 0.001
    assert 0.005 < np.median(burst) < 0.013  # less the (generous) phase noise the rows state
    for q, m in zip(quiet, moved, strict=True):
        assert m.scatter == pytest.approx(q.scatter, abs=1e-9)
        np.testing.assert_allclose(m.correction[:3] - q.correction[:3], wrong, atol=1e-9)
        assert np.all(np.sqrt(np.diag(q.covariance)[:3]) < 0.01)  # mm/s-level agreement
    # Five satellites (a street of buildings): a plain fit, the scatter it cannot measure
    # taken as given, the correction still the INS's error; three: none
    few = cpp.tdcp_fit(sats[:5], (y + u @ wrong)[:5], u[:5], sigma[:5], unknown_scatter=5e-4)
    assert few.satellites == 5 and few.scatter == 5e-4
    np.testing.assert_allclose(few.correction[:3], wrong, atol=0.01)
    assert np.all(np.diag(few.covariance) > 5e-4**2)
    assert cpp.tdcp_fit(sats[:3], y[:3], u[:3], sigma[:3]) is None


def _per_satellite_velocity(rows, C_el: np.ndarray, rate_sigma: float) -> np.ndarray:
    """The η rows' velocity (NED) as ``cpp.origin_sensitivity`` weighs them."""
    sats = sorted({r.sat for r in rows})
    H, y, w = [], [], []
    for s in sats:
        rs = [r for r in rows if r.sat == s]
        H.append([*(C_el @ rs[0].los_ecef), 1.0])
        y.append(np.mean([r.measured for r in rs]))
        w.append(1.0 / (np.mean([r.sigma**2 for r in rs]) / len(rs) + rate_sigma**2))
    sw = np.sqrt(w)
    return np.linalg.lstsq(np.array(H) * sw[:, None], np.array(y) * sw, rcond=None)[0][:3]


def test_origin_sensitivity_is_what_a_wrong_geometry_point_does(real):
    """The rows computed at a point 10 m off (up, north, east) of the surveyed one move the
    velocity by ``origin_sensitivity`` times the offset — checked against the real rows
    recomputed at the moved point — and by the size measured over this file's 300 s (a point
    10 m up: ~1 mm/s horizontally, a trajectory 28 cm off in five minutes)."""
    nav, base, _ = real
    lat, lon, h = np.loadtxt(DATA / "static_base_position.txt")
    site = geodetic_to_ecef(np.radians(lat), np.radians(lon), h)
    C_el = C_ecef_to_level(np.radians(lat), np.radians(lon))
    up_drift = []
    for k in range(1, 30, 3):
        prev, curr = base[k - 1], base[k]
        clock = standalone_position([curr], nav).clock_bias_m / SPEED_OF_LIGHT

        def rows_at(point, prev=prev, curr=curr, clock=clock):
            g1 = cpp.epoch_geometry(nav, sorted(prev.satellites), prev.time, point, clock)
            g2 = cpp.epoch_geometry(nav, sorted(curr.satellites), curr.time, point, clock)
            return cpp.eta_observations([prev], [curr], g1, g2).rows, g1, g2

        rows, g1, g2 = rows_at(site)
        K = cpp.origin_sensitivity(rows, g1, g2, C_el, 0.0005)
        v0 = _per_satellite_velocity(rows, C_el, 0.0005)
        for delta_ned in ([0.0, 0.0, -10.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]):
            moved, _, _ = rows_at(site + C_el.T @ np.array(delta_ned))
            dv = _per_satellite_velocity(moved, C_el, 0.0005) - v0
            np.testing.assert_allclose(K @ delta_ned, dv, atol=1e-7)  # m/s (dv ~1 mm/s)
        up_drift.append(np.hypot(*(K @ [0.0, 0.0, -10.0])[:2]))
    assert 0.0005 < np.median(up_drift) < 0.0015, up_drift
    assert not cpp.origin_sensitivity(rows[:4], g1, g2, C_el, 0.0005).any()  # too few


def test_injected_slip_is_detected_and_does_not_spike_velocity(real):
    nav, base, _ = real
    k, sat = 40, "G13"
    clean = cpp.tdcp_velocity(base[k - 1], base[k], nav, systems="GEJ")
    # A 3-cycle slip without LLI: the Doppler/phase-rate test catches it.
    slipped = with_phase(base[k], sat, 3.0)
    flags = cpp.detect_cycle_slips([base[k - 1]], [slipped])
    assert flags[(0, sat)].startswith("Doppler/phase-rate mismatch")
    assert len(flags) == 1
    v = cpp.tdcp_velocity(base[k - 1], slipped, nav, systems="GEJ")
    assert sat not in v.satellites and sat in v.excluded
    assert np.linalg.norm(v.velocity_ned - clean.velocity_ned) < 0.005
    # With the LLI bit set the reason is the receiver's own flag.
    flagged = with_phase(base[k], sat, 3.0, lli=1)
    assert "LLI" in cpp.detect_cycle_slips([base[k - 1]], [flagged])[(0, sat)]
    # Without Doppler the slip reaches the velocity solution, whose residual test drops it.
    no_doppler = with_phase(base[k], sat, 2.0, doppler=float("nan"))
    prev = with_phase(base[k - 1], sat, 0.0, doppler=float("nan"))
    assert (0, sat) not in cpp.detect_cycle_slips([prev], [no_doppler])
    v = cpp.tdcp_velocity(prev, no_doppler, nav, systems="GEJ")
    assert v.excluded[sat] == "velocity residual test"
    assert np.linalg.norm(v.velocity_ned - clean.velocity_ned) < 0.005


def test_common_phase_jump_is_a_clock_jump_not_slips(real):
    nav, base, _ = real
    k = 30
    jumped = base[k]
    for sat in list(jumped.satellites):
        jumped = with_phase(jumped, sat, 1500.0)  # e.g. a receiver clock step
    assert cpp.detect_cycle_slips([base[k - 1]], [jumped]) == {}
    v = cpp.tdcp_velocity(base[k - 1], jumped, nav, systems="GEJ")
    assert horizontal(v.velocity_ned) < 0.01  # the step went into the clock drift


def test_receiver_dropout_and_gap(real):
    nav, base, rover = real
    rows = cpp.align_epochs([base[:30], rover[:10] + rover[11:30]])
    assert rows[10][1][1] is None and rows[10][1][0] is not None
    # Across the gap the rover's phase is differenced over 2 s: still a good velocity.
    v = cpp.tdcp_velocity(rover[9], rover[11], nav, systems="GEJ")
    assert v is not None and v.interval_s == pytest.approx(2.0)
    assert horizontal(v.velocity_ned) < 0.01
    # A missing receiver yields no rows for it and does not stop the others.
    spp = standalone_position(base[9], nav)
    g1 = cpp.epoch_geometry(nav, list(base[9].satellites), base[9].time, spp.position)
    g2 = cpp.epoch_geometry(nav, list(base[10].satellites), base[10].time, spp.position)
    eta = cpp.eta_observations([base[9], rover[9]], [base[10], None], g1, g2,
                               common_clock=False)
    assert {r.antenna for r in eta.rows} == {0}
    assert cpp.loose_velocity(eta.for_antenna(0), g2.C_ecef_to_level) is not None
    # An epoch flag (power failure) breaks every satellite's continuity.
    flagged = GnssEpoch(base[11].time, base[11].satellites, flag=1)
    flags = cpp.detect_cycle_slips([base[10]], [flagged])
    assert len(flags) == len(base[11].satellites)


def test_missing_ephemeris_skips_that_satellite_with_a_record(real):
    nav, base, _ = real
    sat = "G13"
    partial = NavigationData({s: e for s, e in nav.ephemerides.items() if s != sat},
                             nav.iono_alpha, nav.iono_beta, nav.leap_seconds)
    v = cpp.tdcp_velocity(base[20], base[21], partial, systems="GEJ")
    assert v is not None
    assert v.excluded[sat] == "no ephemeris"
    assert horizontal(v.velocity_ned) < 0.01
    geo = cpp.epoch_geometry(partial, [sat, "G05"], base[21].time, np.array(
        [-3817679.3, 3562837.4, 3650160.7]))
    assert geo.rejected == {sat: "no ephemeris"} and "G05" in geo.satellites


# --------------------------------------------------------------------- tight vs loose


def _geometries(sim_nav, obs):
    geos = []
    for k in range(len(obs[0])):
        eps = [o[k] for o in obs]
        spp = standalone_position(eps, sim_nav)
        geos.append(cpp.epoch_geometry(sim_nav, sorted(eps[0].satellites), eps[0].time,
                                       spp.position, spp.clock_bias_m / SPEED_OF_LIGHT))
    return geos


def _lever(t: float) -> dict:
    C = euler_to_dcm(0.0, 0.0, np.radians(20.0) + YAW_RATE * t)
    return dict(lever_arms_body=LEVERS, C_body_to_level=C, omega_body=np.array([0, 0, YAW_RATE]))


def test_tight_and_loose_agree_with_all_satellites(sim, sim_nav):
    obs, _ = sim
    geos = _geometries(sim_nav, obs)
    for k in (3, 9, 15):
        prev, cur = [o[k - 1] for o in obs], [o[k] for o in obs]
        eta = cpp.eta_observations(prev, cur, geos[k - 1], geos[k])
        truth = centroid_velocity(k - 1.0, float(k))
        loose = [cpp.loose_velocity(eta.for_antenna(i), geos[k].C_ecef_to_level)
                 for i in range(4)]
        v_loose = np.mean([v.velocity_ned for v in loose], axis=0)
        tight = cpp.tight_velocity(eta.rows, **_lever(k - 0.5))
        assert np.linalg.norm(v_loose - truth) < 0.01
        assert np.linalg.norm(tight.velocity_ned - truth) < 0.01
        # One clock for four receivers: the loose clock drifts agree, and with the tight one.
        drifts = [v.clock_drift_mps for v in loose]
        assert np.ptp(drifts) < 0.02 and abs(tight.clock_drift_mps - np.mean(drifts)) < 0.01
        # η rows for the EKF: one per antenna and satellite, unit LOS, σ at mm/s level.
        row = eta.rows[0]
        assert np.linalg.norm(row.los_ned) == pytest.approx(1.0)
        assert 0.0 < row.sigma < 0.05


def test_tight_coupling_works_where_loose_cannot(sim, sim_nav):
    obs, _ = sim
    geos = _geometries(sim_nav, obs)
    k0 = 10
    common = sorted(geos[k0].satellites, key=lambda s: -geos[k0].satellites[s].elevation)
    # (a) Thesis table 21: four satellites, each tracked by a different receiver only.
    one_each = [[keep(o[k], {common[i]}) for k in range(len(o))] for i, o in enumerate(obs)]
    # (b) Three satellites common to all receivers after 10 s.
    three = [[o[k] if k < k0 else keep(o[k], set(common[:3])) for k in range(len(o))]
             for o in obs]
    filt = cpp.TightVelocityFilter(vertical_sigma_mps=0.1)
    errors_a, errors_b = [], []
    for k in range(1, len(obs[0])):
        truth = centroid_velocity(k - 1.0, float(k))
        eta = cpp.eta_observations([o[k - 1] for o in one_each], [o[k] for o in one_each],
                                   geos[k - 1], geos[k])
        assert all(cpp.loose_velocity(eta.for_antenna(i)) is None for i in range(4))
        tight = cpp.tight_velocity(eta.rows, **_lever(k - 0.5))
        assert tight is not None and tight.satellites == sorted(common[:4])
        errors_a.append(horizontal(tight.velocity_ned - truth))

        eta = cpp.eta_observations([o[k - 1] for o in three], [o[k] for o in three],
                                   geos[k - 1], geos[k])
        fv = filt.step(eta.rows, geos[k].time, **_lever(k - 0.5))
        if k > k0:
            assert all(cpp.loose_velocity(eta.for_antenna(i)) is None for i in range(4))
            assert cpp.tight_velocity(eta.rows, **_lever(k - 0.5)) is None  # 3 eqs, 4 unknowns
            errors_b.append(horizontal(fv.velocity_ned - truth))
    assert np.sqrt(np.mean(np.square(errors_a))) < 0.03
    assert np.sqrt(np.mean(np.square(errors_b))) < 0.05  # clock drift carried by the filter


def test_tight_solution_drops_one_slipped_receiver(sim, sim_nav):
    obs, _ = sim
    geos = _geometries(sim_nav, obs)
    k = 8
    prev, cur = [o[k - 1] for o in obs], [o[k] for o in obs]
    sat = sorted(cur[2].satellites)[0]
    cur[2] = with_phase(cur[2], sat, 2.0, doppler=float("nan"))  # unseen by the Doppler test
    prev[2] = with_phase(prev[2], sat, 0.0, doppler=float("nan"))
    eta = cpp.eta_observations(prev, cur, geos[k - 1], geos[k])
    tight = cpp.tight_velocity(eta.rows, **_lever(k - 0.5))
    assert (2, sat) in tight.excluded
    assert np.linalg.norm(tight.velocity_ned - centroid_velocity(k - 1.0, k)) < 0.01


# ------------------------------------------------------------- single differences ζ


def test_single_differences_delay_and_zeta(sim, sim_nav):
    obs, truth = sim
    geos = _geometries(sim_nav, obs)
    k = len(obs[0]) - 1  # the truth holds the ambiguities of the last epoch
    geo = geos[k]
    t = geo.time - START
    C_le = geo.C_ecef_to_level.T
    los = {s: g.line_of_sight for s, g in geo.satellites.items()}
    sig = {s: cpp.sd_sigma(g.elevation) for s, g in geo.satellites.items()}
    for i, j in cpp.BASELINE_PAIRS:
        sd = cpp.single_differences(obs[i][k], obs[j][k], geo.wavelengths)
        assert len(sd) >= 8
        b_ecef = C_le @ (turning_array(t, j) - turning_array(t, i))
        n_ij = {s: truth.ambiguities[i][s] - truth.ambiguities[j][s] for s in sd}
        d_hat, d_sigma, n = cpp.estimate_inter_receiver_delay(sd, n_ij, los, b_ecef,
                                                              geo.wavelengths, sig)
        d_true = truth.hardware_delay_m[i] - truth.hardware_delay_m[j]
        assert abs(d_hat - d_true) < 0.004 and n == len(sd) and d_sigma < 0.003
        z = cpp.zeta(sd, n_ij, geo.wavelengths, d_hat)
        geometric = np.array([los[s] @ b_ecef for s in z])  # ρ_i − ρ_j = e·b_ij
        assert np.sqrt(np.mean((np.array(list(z.values())) - geometric) ** 2)) < 0.005
