"""Standalone positioning (estimator.spp) on real and on exactly simulated pseudoranges."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from estimator.ephemeris import (
    carrier_wavelength,
    klobuchar_delay,
    satellite_geometry,
    troposphere_delay,
)
from estimator.frames import (
    SPEED_OF_LIGHT,
    C_ecef_to_level,
    ecef_to_geodetic,
    ecef_to_ned,
    elevation_azimuth,
    geodetic_to_ecef,
)
from estimator.records import GnssEpoch, NavigationData, SatObservation
from estimator.spp import height_aided, standalone_position
from recordings.rinex import l1_epochs, read_nav, read_obs

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def nav() -> NavigationData:
    return read_nav(DATA / "static.nav")


@pytest.fixture(scope="module")
def epochs() -> list[GnssEpoch]:
    return l1_epochs(read_obs(DATA / "static_base.obs"))


@pytest.fixture(scope="module")
def base_llh() -> np.ndarray:
    lat, lon, h = np.loadtxt(DATA / "static_base_position.txt")
    return np.array([math.radians(lat), math.radians(lon), h])


def horizontal_vertical(sol, llh) -> tuple[float, float]:
    ned = ecef_to_ned(sol.position, llh)
    return float(np.hypot(ned[0], ned[1])), float(abs(ned[2]))


def keep(ep: GnssEpoch, sats) -> GnssEpoch:
    return GnssEpoch(ep.time, {s: ep.satellites[s] for s in sats})


# ------------------------------------------------------------------------ real data


def test_every_epoch_near_surveyed_position(nav, epochs, base_llh) -> None:
    errors = []
    for ep in epochs:
        sol = standalone_position(ep, nav)
        assert sol is not None
        errors.append(horizontal_vertical(sol, base_llh))
        assert sol.reference_system == "G" and set(sol.system_biases_m) == set("GEJR")
        assert sol.system_biases_m["G"] == 0.0
        assert 1.0 < sol.pdop < 3.0
        assert sol.rejected == []
    errors = np.array(errors)
    # Measured on this excerpt: horizontal 2.8 m RMS / 3.1 m max (a 2.8 m northward bias of
    # the ionosphere, which the iono-free L1/L2 solution does not show), vertical 2.6 m max.
    assert errors[:, 0].max() < 5.0
    assert errors[:, 1].max() < 10.0


def test_covariance_covers_the_real_error(nav, epochs, base_llh) -> None:
    """The stated covariance must cover the real fix's error, a bias of the ionosphere the
    same at every epoch (2.5 m north, 2.2 m down here). The weighted solution's own cofactor
    (σ 1.2 m north: the residuals' scatter) puts it at a 3-D Mahalanobis distance of 2.6;
    with the common ionosphere modes — Klobuchar's level off by half and a horizontal
    gradient, which move every satellite alike and so never show in the residuals — 0.9."""
    C = C_ecef_to_level(base_llh[0], base_llh[1])
    d, north_sigma = [], []
    for ep in epochs[::10]:
        sol = standalone_position(ep, nav)
        e = ecef_to_ned(sol.position, base_llh)
        P = C @ sol.covariance @ C.T
        d.append(math.sqrt(float(e @ np.linalg.solve(P, e))))
        north_sigma.append(math.sqrt(P[0, 0]))
    assert max(d) < 1.5, max(d)
    assert 2.0 < np.median(north_sigma) < 6.0  # the gradient's share, not the cofactor's


def test_a_known_height_corrects_the_fix(nav, epochs, base_llh) -> None:
    """The surveyed height given with 0.5 m: the fix moves to it (its vertical error 2.2 m →
    within the 0.5 m), its covariance says so, and the correction stays inside what the
    covariance allowed; a height 37 m off (above mean sea level instead of the ellipsoid)
    is refused."""
    sol = standalone_position(epochs[0], nav)
    C = C_ecef_to_level(base_llh[0], base_llh[1])
    aided = height_aided(sol.position, sol.covariance, float(base_llh[2]), 0.5)
    assert aided.used
    before, after = ecef_to_ned(sol.position, base_llh), ecef_to_ned(aided.position, base_llh)
    assert abs(before[2]) > 1.5 and abs(after[2]) < 0.5
    P = C @ aided.covariance @ C.T
    assert 0.3 < math.sqrt(P[2, 2]) < 0.5
    assert float(after @ np.linalg.solve(P, after)) < 3.0**2
    np.testing.assert_allclose(aided.covariance, aided.covariance.T, atol=1e-9)
    blunder = height_aided(sol.position, sol.covariance, float(base_llh[2]) - 37.0, 1.0)
    assert not blunder.used and blunder.innovation_m < -30.0
    np.testing.assert_array_equal(blunder.position, sol.position)


def test_clock_and_residuals_are_consistent(nav, epochs, base_llh) -> None:
    sol = standalone_position(epochs[0], nav)
    # The receiver clock runs ~ -0.2 ppm free: -73 km at the first epoch
    assert sol.clock_bias_m == pytest.approx(-73337.0, abs=15.0)
    assert sol.time == epochs[0].time
    assert set(sol.residuals_m) == set(sol.satellites)
    assert max(abs(v) for v in sol.residuals_m.values()) < 8.0
    later = standalone_position(epochs[100], nav)
    drift = (later.clock_bias_m - sol.clock_bias_m) / (epochs[100].time - epochs[0].time)
    assert drift == pytest.approx(-61.5, abs=0.5)  # m/s


@pytest.mark.parametrize("k, system", [(0, "G"), (30, "E"), (60, "R"), (119, "G")])
def test_outlier_is_rejected(nav, epochs, base_llh, k: int, system: str) -> None:
    ep = epochs[k]
    clean = standalone_position(ep, nav)
    # The used satellite of that system with the highest elevation (the hardest to spot:
    # it has the most influence on the solution)
    candidates = [s for s in clean.satellites if s[0] == system]
    bad = max(candidates, key=lambda s: elevation_azimuth(
        clean.position, satellite_geometry(nav, s, ep.time, clean.position).sat_position)[0])
    sats = dict(ep.satellites)
    sats[bad] = dataclasses.replace(sats[bad], pseudorange=sats[bad].pseudorange + 100.0)
    sol = standalone_position(GnssEpoch(ep.time, sats), nav)
    assert sol.rejected == [bad]
    assert bad not in sol.satellites and bad not in sol.residuals_m
    h, v = horizontal_vertical(sol, base_llh)
    assert h < 5.0 and v < 10.0
    np.testing.assert_allclose(sol.position, clean.position, atol=0.5)


def test_two_satellite_system_outlier_cannot_be_told_apart(nav, epochs) -> None:
    """With a system seen by two satellites only, their residuals are fully correlated: both go."""
    ep = epochs[10]
    assert {s for s in ep.satellites if s[0] == "J"} == {"J03", "J07"}
    sats = dict(ep.satellites)
    sats["J07"] = dataclasses.replace(sats["J07"], pseudorange=sats["J07"].pseudorange + 100.0)
    sol = standalone_position(GnssEpoch(ep.time, sats), nav)
    assert sorted(sol.rejected) == ["J03", "J07"]
    assert "J" not in sol.system_biases_m


def test_too_few_satellites(nav, epochs, base_llh) -> None:
    ep = epochs[0]
    sol = standalone_position(ep, nav)
    gps = [s for s in sol.satellites if s[0] == "G"][:4]
    gal = [s for s in sol.satellites if s[0] == "E"][:2]
    assert standalone_position(keep(ep, gps[:3]), nav) is None
    assert standalone_position(keep(ep, gps), nav) is not None
    # A lone satellite of a second system only determines its own clock
    assert standalone_position(keep(ep, gps[:3] + gal[:1]), nav) is None
    five = standalone_position(keep(ep, gps[:3] + gal), nav)
    assert five is not None and set(five.system_biases_m) == {"G", "E"}
    assert standalone_position(GnssEpoch(ep.time, {}), nav) is None
    assert standalone_position(ep, NavigationData()) is None


def test_elevation_mask_and_initial_position(nav, epochs, base_llh) -> None:
    ep = epochs[50]
    default = standalone_position(ep, nav)
    high = standalone_position(ep, nav, elevation_mask_deg=30.0)
    assert 4 < len(high.satellites) < len(default.satellites)
    for s in high.satellites:
        g = satellite_geometry(nav, s, ep.time, high.position)
        assert g.elevation >= math.radians(30.0) - 1e-6
    warm = standalone_position(ep, nav, initial_ecef=default.position + 50.0)
    np.testing.assert_allclose(warm.position, default.position, atol=1e-3)
    assert warm.iterations < default.iterations


# ------------------------------------------------------------------- simulated data


def simulate(nav: NavigationData, antennas: np.ndarray, t_tag: float, clock_s: float,
             biases: dict[str, float]) -> list[GnssEpoch]:
    """Noise-free pseudoranges with the same models the estimator removes."""
    centre = antennas.mean(axis=0)
    llh = ecef_to_geodetic(centre)
    epochs = []
    for rx in antennas:
        sats = {}
        for sat in nav.satellites():
            if sat[0] not in "GEJR":
                continue
            g = satellite_geometry(nav, sat, t_tag - clock_s, rx)
            if g is None or g.elevation < math.radians(12.0):
                continue
            scale = (carrier_wavelength(sat, nav) / carrier_wavelength("G01")) ** 2
            iono = scale * klobuchar_delay(nav.iono_alpha, nav.iono_beta, t_tag, llh[0],
                                           llh[1], g.elevation, g.azimuth)
            p = (g.range + SPEED_OF_LIGHT * (clock_s - g.sat_clock_bias) + biases[sat[0]]
                 + troposphere_delay(g.elevation, llh[2]) + iono)
            sats[sat] = SatObservation(p, math.nan, math.nan, 45.0)
        epochs.append(GnssEpoch(t_tag, sats))
    return epochs


def test_exact_recovery_from_simulated_pseudoranges(nav, base_llh) -> None:
    truth = geodetic_to_ecef(*base_llh)
    t_tag = nav.ephemerides["G05"][0].toe - 6000.0
    biases = {"G": 0.0, "E": 4.0, "J": -2.0, "R": 11.0}
    clock = 1.2e-3  # 360 km: the satellites move ~5 m meanwhile, which must be accounted for
    (ep,) = simulate(nav, truth[None, :], t_tag, clock, biases)
    sol = standalone_position(ep, nav)
    np.testing.assert_allclose(sol.position, truth, atol=2e-3)
    assert sol.clock_bias_m == pytest.approx(SPEED_OF_LIGHT * clock, abs=2e-3)
    for s, b in biases.items():
        assert sol.system_biases_m[s] == pytest.approx(b, abs=2e-3)
    assert max(abs(v) for v in sol.residuals_m.values()) < 2e-3


def test_receivers_sharing_one_clock(nav, base_llh) -> None:
    centre = geodetic_to_ecef(*base_llh)
    square = np.array([[0.05, -0.05, 0.0], [0.05, 0.05, 0.0], [-0.05, 0.05, 0.0],
                       [-0.05, -0.05, 0.0]])  # NED, 10 cm square
    antennas = centre + square @ C_ecef_to_level(base_llh[0], base_llh[1])
    t_tag = nav.ephemerides["G05"][0].toe - 6000.0
    eps = simulate(nav, antennas, t_tag, -2e-4, {"G": 0.0, "E": 1.0, "J": 0.5, "R": -3.0})
    sol = standalone_position(eps, nav)
    np.testing.assert_allclose(sol.position, centre, atol=5e-3)
    assert sol.clock_bias_m == pytest.approx(SPEED_OF_LIGHT * -2e-4, abs=5e-3)
    assert all(k.split(":")[0] in "0123" for k in sol.satellites)
    assert len(sol.satellites) == sum(len(e.satellites) for e in eps)
    # The array-centre solution leaves each antenna's offset (<= 7 cm) in the residuals
    assert max(abs(v) for v in sol.residuals_m.values()) < 0.08
