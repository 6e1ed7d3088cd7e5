"""The simulated GNSS observables obey the physics the compass relies on."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.ephemeris import (
    carrier_wavelength,
    klobuchar_delay,
    satellite_geometry,
    tropo_mapping,
    troposphere_delay,
)
from estimator.frames import SPEED_OF_LIGHT, ned_to_ecef, rot_z
from recordings.rinex import read_nav
from recordings.sim.gnss import GnssErrorModel, draw_world, simulate_gnss
from recordings.sim.gnss_errors import (
    niell_hydrostatic,
    niell_wet,
    pierce_point,
    saastamoinen_zenith_hydrostatic,
)
from recordings.sim.scenarios import LARGE_SHIP, SMALL_BOAT
from recordings.sim.simulate import NAV_FILE

START = SMALL_BOAT.start_gpst
ORIGIN = np.array([np.radians(SMALL_BOAT.origin_llh_deg[0]),
                   np.radians(SMALL_BOAT.origin_llh_deg[1]), SMALL_BOAT.origin_llh_deg[2]])
ANTENNAS = SMALL_BOAT.antennas_body()


@pytest.fixture(scope="module")
def nav():
    return read_nav(NAV_FILE)


def rotating_array(t: float, i: int) -> np.ndarray:
    """A platform turning at 5 deg/s while moving north at 1 m/s."""
    yaw = np.radians(30.0 + 5.0 * t)
    return np.array([-50.0 + 1.0 * t, -20.0, -1.0]) + rot_z(yaw) @ ANTENNAS[i]


def simulate(nav, errors: GnssErrorModel, duration: float = 10.0, seed: int = 3):
    return simulate_gnss(SMALL_BOAT, rotating_array, nav, START, duration, seed, errors=errors)


def true_ranges(nav, t_true: float, i: int, sats) -> dict[str, float]:
    rx = ned_to_ecef(rotating_array(t_true - START, i), ORIGIN)
    return {s: satellite_geometry(nav, s, t_true, rx).range for s in sats}


@pytest.mark.parametrize("noisy", [False, True])
def test_single_differences_are_geometry_plus_integers_and_delays(nav, noisy: bool) -> None:
    errors = GnssErrorModel(slip_rate_per_epoch=0.0) if noisy else GnssErrorModel.perfect()
    epochs, truth = simulate(nav, errors)
    tolerance_m = 0.02 if noisy else 1e-4
    checked = 0
    for e in range(len(epochs[0])):
        t_true = epochs[0][e].time - truth.clock_bias_s[e]
        sats = sorted(set.intersection(*(set(rx[e].satellites) for rx in epochs)))
        assert len(sats) >= 8
        ranges = [true_ranges(nav, t_true, i, sats) for i in range(4)]
        for i, j in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]:
            for s in sats:
                lam = carrier_wavelength(s, nav)
                sd_phase_m = lam * (epochs[i][e].satellites[s].carrier_phase
                                    - epochs[j][e].satellites[s].carrier_phase)
                geometric = ranges[i][s] - ranges[j][s]
                delay = truth.hardware_delay_m[i] - truth.hardware_delay_m[j]
                cycles = (sd_phase_m - geometric - delay) / lam
                # What remains is an integer number of cycles (the SD ambiguity) plus noise.
                assert abs(cycles - np.round(cycles)) * lam < tolerance_m
                # The baseline (10-14 cm) shows in the geometric difference, not absent.
                assert abs(geometric) < 0.15
                checked += 1
    assert checked > 1000


def test_atmosphere_and_clock_are_present_but_cancel(nav) -> None:
    epochs, truth = simulate(nav, GnssErrorModel.perfect(), duration=2.0)
    e = 1
    t_true = epochs[0][e].time - truth.clock_bias_s[e]
    rx = ned_to_ecef(rotating_array(t_true - START, 0), ORIGIN)
    for s, obs in epochs[0][e].satellites.items():
        geo = satellite_geometry(nav, s, t_true, rx)
        clock = SPEED_OF_LIGHT * (truth.clock_bias_s[e] - geo.sat_clock_bias)
        atmosphere = obs.pseudorange - geo.range - clock - truth.hardware_delay_m[0]
        assert 1.0 < atmosphere < 60.0  # ionosphere + troposphere, metres
        # Ionosphere advances the phase and delays the code: their difference is twice it.
        lam = carrier_wavelength(s, nav)
        assert obs.pseudorange - lam * obs.carrier_phase != pytest.approx(0.0, abs=1e3)


def test_doppler_matches_phase_rate(nav) -> None:
    epochs, _ = simulate(nav, GnssErrorModel.perfect(), duration=4.0)
    for e in range(1, len(epochs[0])):
        dt = epochs[0][e].time - epochs[0][e - 1].time
        for s, obs in epochs[0][e].satellites.items():
            prev = epochs[0][e - 1].satellites[s]
            phase_rate = (obs.carrier_phase - prev.carrier_phase) / dt
            mean_doppler = 0.5 * (obs.doppler + prev.doppler)
            # RINEX: Doppler is positive when approaching while the phase (range) decreases.
            assert mean_doppler == pytest.approx(-phase_rate, abs=0.05)


def test_cycle_slips_and_masks(nav) -> None:
    errors = GnssErrorModel(slip_rate_per_epoch=0.05)
    epochs, truth = simulate(nav, errors, duration=20.0)
    assert truth.slips, "slips were requested"
    flagged = [s for s in truth.slips if s[4]]
    unflagged = [s for s in truth.slips if not s[4]]
    assert flagged and unflagged
    for t, rx, sat, _cycles, _ in flagged:
        epoch = next(ep for ep in epochs[rx] if ep.time == t)
        assert epoch.satellites[sat].lli & 1
    # The large-ship scenario's cranes hide the low northern sky near the quay.
    epochs, _ = simulate_gnss(LARGE_SHIP, lambda t, i: np.array([-100.0, 0.0, -14.0]), nav,
                              LARGE_SHIP.start_gpst, 2.0, 1)
    open_sky, _ = simulate_gnss(SMALL_BOAT, lambda t, i: np.array([-100.0, 0.0, -14.0]), nav,
                                LARGE_SHIP.start_gpst, 2.0, 1)
    assert len(epochs[0][0].satellites) < len(open_sky[0][0].satellites)


def test_deterministic_for_a_seed(nav) -> None:
    a, _ = simulate(nav, GnssErrorModel(), duration=3.0, seed=7)
    b, _ = simulate(nav, GnssErrorModel(), duration=3.0, seed=7)
    c, _ = simulate(nav, GnssErrorModel(), duration=3.0, seed=8)
    assert a == b
    assert a != c


# ------------------------------------------------------------------ the world's error sources


def world(nav, seed: int, n_epochs: int = 61, errors: GnssErrorModel | None = None):
    sats = [s for s in nav.satellites() if s[0] in "GEJ"]
    return draw_world(errors or GnssErrorModel(), np.random.default_rng([seed, 1]), nav, sats,
                      ORIGIN, START, n_epochs, 1.0, SMALL_BOAT.start.timetuple().tm_yday)


def visible(nav, t: float):
    rx = ned_to_ecef(np.zeros(3), ORIGIN)
    geos = [satellite_geometry(nav, s, t, rx) for s in nav.satellites() if s[0] in "GEJ"]
    return [g for g in geos if g is not None and g.elevation > np.radians(10.0)]


def test_thin_shell_and_niell_mapping() -> None:
    lat, lon = ORIGIN[0], ORIGIN[1]
    assert pierce_point(lat, lon, np.pi / 2, 0.0) == pytest.approx((lat, lon, 1.0), abs=1e-9)
    lat_p, lon_p, obliquity = pierce_point(lat, lon, np.radians(10.0), 0.0)  # looking north
    assert obliquity == pytest.approx(2.79, abs=0.01)  # 1/sqrt(1 - (R cos E / (R + 350 km))^2)
    assert lat_p > lat + np.radians(8.0) and lon_p == pytest.approx(lon)
    for el in (90.0, 30.0, 10.0, 5.0):
        e = np.radians(el)
        mh, mw = niell_hydrostatic(e, lat, 37.0, 176), niell_wet(e, lat)
        if el == 90.0:
            assert mh == pytest.approx(1.0, abs=1e-3) and mw == pytest.approx(1.0, abs=1e-3)
        else:
            # Below the flat-Earth 1/sin(E), not far; different from the estimator's MOPS
            # mapping by more than a millimetre of a 2.4 m zenith delay.
            for m in (mh, mw):
                assert 0.85 / np.sin(e) < m < 1.0 / np.sin(e)
            assert abs(mh - tropo_mapping(e)) * 2.4 > 1e-3
    assert niell_hydrostatic(np.radians(5.0), lat, 0.0, 176) == pytest.approx(10.1, abs=0.1)
    assert saastamoinen_zenith_hydrostatic(1013.25, lat, 0.0) == pytest.approx(2.31, abs=0.01)


def iono_left(nav, w, g, t: float) -> float:
    """Simulated ionospheric delay minus the Klobuchar model's (m)."""
    lat, lon = ORIGIN[0], ORIGIN[1]
    return (w.ionosphere.slant(t, lat, lon, g.elevation, g.azimuth)
            - klobuchar_delay(nav.iono_alpha, nav.iono_beta, t, lat, lon, g.elevation, g.azimuth))


def test_atmosphere_departs_from_the_estimator_models(nav) -> None:
    """Klobuchar and the standard troposphere remove part, not all, of the simulated delays
    and of their change over a minute (what the TDCP correction is tested against)."""
    lat, lon, h = ORIGIN
    iono, tropo, rate = [], [], []
    for seed in range(1, 6):
        w = world(nav, seed)
        for t in (START, START + 60.0):
            for g in visible(nav, t):
                iono.append(iono_left(nav, w, g, t)
                            / w.ionosphere.slant(t, lat, lon, g.elevation, g.azimuth))
                tropo.append(w.troposphere.slant(t, g.elevation, g.azimuth)
                             - troposphere_delay(g.elevation, h))
        later = {g.sat: g for g in visible(nav, START + 60.0)}
        rate += [(iono_left(nav, w, later[g.sat], START + 60.0) - iono_left(nav, w, g, START))
                 / 60.0 for g in visible(nav, START) if g.sat in later]
    iono, tropo, rate = map(np.array, (iono, tropo, rate))
    assert 0.02 < np.sqrt(np.mean(iono**2)) < 0.6  # corrected in part, not mirrored
    assert 0.02 < np.sqrt(np.mean(tropo**2)) < 0.5  # m: wetter than the standard atmosphere
    assert 1e-5 < np.sqrt(np.mean(rate**2)) < 2e-3  # m/s left in the TDCP: ~0.1-1 mm/s


def test_satellite_errors_are_realistic_and_prefix_consistent(nav) -> None:
    short, long = world(nav, 3, n_epochs=40), world(nav, 3, n_epochs=120)
    assert short.ionosphere == long.ionosphere and short.troposphere == long.troposphere
    orbit, clock_rate, rates = [], [], []
    for sat, err in long.satellites.items():
        # The same draws whatever the run's length: a shorter run is a prefix of a longer one.
        np.testing.assert_array_equal(short.satellites[sat].fluctuation_m, err.fluctuation_m[:40])
        orbit.append(np.hypot.reduce(err.orbit_mean_m + err.orbit_amplitude_m))
        clock_rate.append(err.clock_rate_mps)
        rates.append(np.diff(err.fluctuation_m))
    assert 0.2 < np.sqrt(np.mean(np.square(orbit))) < 3.0  # m, broadcast orbit error
    assert 1e-5 < np.sqrt(np.mean(np.square(clock_rate))) < 1e-3  # m/s
    assert 0.3e-3 < np.sqrt(np.mean(np.square(rates))) < 5e-3  # m/s, 1 s changes
    geo = visible(nav, START)[0]
    err = long.satellites[geo.sat]
    a = err.range_error(START, 0, geo.line_of_sight, geo.sat_position, geo.sat_velocity)
    b = err.range_error(START + 1.0, 0, geo.line_of_sight, geo.sat_position, geo.sat_velocity)
    assert 0.0 < abs(b - a) < 1e-3  # orbit and clock errors change slowly
    # The perfect model keeps the smooth world but drops the noise.
    quiet = world(nav, 3, errors=GnssErrorModel.perfect())
    assert quiet.ionosphere == world(nav, 3).ionosphere
    assert not np.any(quiet.satellites[geo.sat].fluctuation_m)
