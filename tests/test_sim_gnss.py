"""The simulated GNSS observables obey the physics the compass relies on."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.ephemeris import carrier_wavelength, satellite_geometry
from estimator.frames import SPEED_OF_LIGHT, ned_to_ecef, rot_z
from recordings.rinex import read_nav
from recordings.sim.gnss import GnssErrorModel, simulate_gnss
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
