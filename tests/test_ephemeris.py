"""Broadcast orbits, clocks, geometry and atmosphere models (estimator.ephemeris)."""

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
    satellite_state,
    select_ephemeris,
    troposphere_delay,
)
from estimator.frames import (
    GM_BEIDOU,
    GM_GALILEO,
    GM_GPS,
    OMEGA_EARTH,
    SPEED_OF_LIGHT,
    ecef_to_geodetic,
    geodetic_to_ecef,
)
from estimator.records import KeplerEphemeris, NavigationData
from recordings.rinex import l1_epochs, read_nav, read_obs

DATA = Path(__file__).parent / "data"
WEEK = 2320 * 604800.0  # GPS week of the test data (2024-06-24)


def kepler(**kw) -> KeplerEphemeris:
    """A GPS-like ephemeris with every perturbation zero unless given."""
    base = dict(
        sat="G01", toc=WEEK + 86400.0, af0=0.0, af1=0.0, af2=0.0, toe=WEEK + 86400.0,
        sqrt_a=5153.6, e=0.0, i0=0.0, omega0=0.0, omega=0.0, m0=0.0, delta_n=0.0, idot=0.0,
        omega_dot=0.0, cuc=0.0, cus=0.0, crc=0.0, crs=0.0, cic=0.0, cis=0.0, iode=1, tgd=0.0,
        health=0,
    )
    base.update(kw)
    return KeplerEphemeris(**base)


@pytest.fixture(scope="module")
def nav() -> NavigationData:
    return read_nav(DATA / "static.nav")


@pytest.fixture(scope="module")
def base_llh() -> np.ndarray:
    lat, lon, h = np.loadtxt(DATA / "static_base_position.txt")
    return np.array([math.radians(lat), math.radians(lon), h])


# ----------------------------------------------------------------- constructed orbits


@pytest.mark.parametrize(
    "sat, gm, omega_e, bdt_offset",
    [("G01", GM_GPS, OMEGA_EARTH, 0.0), ("E01", GM_GALILEO, OMEGA_EARTH, 0.0),
     ("C30", GM_BEIDOU, 7.2921150e-5, 14.0)],
)
def test_circular_equatorial_orbit(sat: str, gm: float, omega_e: float, bdt_offset: float) -> None:
    a = 5153.6**2
    # BeiDou: toe is stored as gpst; 86400 s into the BDT week is 14 s later in GPST.
    toe = WEEK + 86400.0 + bdt_offset
    eph = kepler(sat=sat, omega0=1.0, omega=0.3, m0=0.2, toe=toe, toc=toe)
    tk = 1234.0
    st = satellite_state(eph, eph.toe + tk)
    n = math.sqrt(gm / a**3)
    # Angle from the ECEF x axis: node (which turns with the Earth since the start of the
    # week of the system's time scale, toe being 86400 s into it) + argument of latitude.
    angle = 1.0 - omega_e * (tk + 86400.0) + 0.3 + 0.2 + n * tk
    expected = a * np.array([math.cos(angle), math.sin(angle), 0.0])
    np.testing.assert_allclose(st.position, expected, atol=1e-3)
    # Inertial speed n*a along the orbit, minus the frame rotation omega x r
    v_inertial = n * a * np.array([-math.sin(angle), math.cos(angle), 0.0])
    v_expected = v_inertial - np.cross([0.0, 0.0, omega_e], expected)
    np.testing.assert_allclose(st.velocity, v_expected, atol=1e-6)


def test_inclined_orbit_node_and_apex() -> None:
    a, inc = 5153.6**2, math.radians(55.0)
    node = 2.0 - OMEGA_EARTH * 86400.0
    at_node = satellite_state(kepler(i0=inc, omega0=2.0), WEEK + 86400.0)
    np.testing.assert_allclose(at_node.position, a * np.array([math.cos(node), math.sin(node), 0]),
                               atol=1e-3)
    apex = satellite_state(kepler(i0=inc, omega0=2.0, m0=math.pi / 2), WEEK + 86400.0)
    assert apex.position[2] == pytest.approx(a * math.sin(inc), abs=1e-3)
    assert np.linalg.norm(apex.position) == pytest.approx(a, abs=1e-3)


def test_harmonic_corrections_of_radius_and_inclination() -> None:
    a, phi = 5153.6**2, 0.4  # e = 0: argument of latitude phi = omega at tk = 0
    st = satellite_state(kepler(omega=phi, crs=120.0, crc=-80.0, i0=0.9, cis=1e-6,
                                cic=-2e-6), WEEK + 86400.0)
    r_expected = a + 120.0 * math.sin(2 * phi) - 80.0 * math.cos(2 * phi)
    assert np.linalg.norm(st.position) == pytest.approx(r_expected, abs=1e-3)
    inc = 0.9 + 1e-6 * math.sin(2 * phi) - 2e-6 * math.cos(2 * phi)
    assert st.position[2] == pytest.approx(r_expected * math.sin(phi) * math.sin(inc), abs=1e-3)


def test_clock_polynomial_relativity_and_group_delay() -> None:
    e, sqrt_a = 0.01, 5153.6
    # M chosen so that the eccentric anomaly is exactly pi/2 at toe: M = E - e sin E
    eph = kepler(e=e, sqrt_a=sqrt_a, m0=math.pi / 2 - e, af0=1e-4, af1=2e-11, af2=1e-18,
                 tgd=-5e-9)
    f_rel = -4.442807633e-10  # s/sqrt(m), IS-GPS-200 20.3.3.3.3.1
    dt = 300.0
    st_toe = satellite_state(eph, eph.toe)
    assert st_toe.clock_bias == pytest.approx(1e-4 + f_rel * e * sqrt_a + 5e-9, abs=1e-15)
    st = satellite_state(eph, eph.toe + dt)
    poly = 1e-4 + 2e-11 * dt + 1e-18 * dt * dt
    rel = st.clock_bias - poly - 5e-9
    assert abs(rel) <= abs(f_rel * e * sqrt_a) + 1e-15
    assert abs(rel - f_rel * e * sqrt_a) < 1e-10  # E moved by ~n*dt from pi/2
    no_tgd = satellite_state(dataclasses.replace(eph, tgd=0.0), eph.toe + dt)
    assert no_tgd.clock_bias - st.clock_bias == pytest.approx(-5e-9, abs=1e-16)


# ------------------------------------------------------------------ derivatives


@pytest.mark.parametrize("sat", ["G05", "E04", "J07", "C01", "C59", "C08", "R01", "R17"])
def test_velocity_and_drift_match_finite_differences(nav: NavigationData, sat: str) -> None:
    eph = nav.ephemerides[sat][0]
    t = eph.toe + 600.0
    h = 0.5
    s0, sp, sm = (satellite_state(eph, t + d) for d in (0.0, h, -h))
    fd_vel = (sp.position - sm.position) / (2 * h)
    np.testing.assert_allclose(s0.velocity, fd_vel, atol=1e-3)  # mm/s
    assert s0.clock_drift == pytest.approx((sp.clock_bias - sm.clock_bias) / (2 * h), abs=1e-15)


def test_beidou_geo_is_geostationary(nav: NavigationData) -> None:
    # Without the GEO rotation the broadcast elements (given in a frame tilted by 5 deg)
    # would swing the satellite through +-3.7 deg of latitude.
    eph = nav.ephemerides["C01"][0]
    lats, lons = [], []
    for dt in np.arange(0.0, 86400.0, 3600.0):
        st = satellite_state(eph, eph.toe + dt)
        lat, lon, _ = ecef_to_geodetic(st.position)
        lats.append(math.degrees(lat))
        lons.append(math.degrees(lon))
        assert np.linalg.norm(st.position) == pytest.approx(42164e3, abs=30e3)
        assert np.linalg.norm(st.velocity) < 150.0
    assert max(abs(x) for x in lats) < 2.5
    assert max(lons) - min(lons) < 0.2


# ------------------------------------------------------------- real ephemerides


def test_consecutive_ephemerides_agree_between_their_toes(nav: NavigationData) -> None:
    """Two independent uploads (different toe) evaluated half-way must agree."""
    checked = set()
    for sat, ephs in nav.ephemerides.items():
        healthy = [e for e in ephs if select_ephemeris(nav, sat, e.toe) is not None]
        for a, b in zip(healthy, healthy[1:], strict=False):
            if b.toe == a.toe or b.toe - a.toe > 3600.0:
                continue
            t_mid = 0.5 * (a.toe + b.toe)
            sa, sb = satellite_state(a, t_mid), satellite_state(b, t_mid)
            assert np.linalg.norm(sa.position - sb.position) < 3.0, sat
            assert np.linalg.norm(sa.velocity - sb.velocity) < 0.01, sat
            assert abs(sa.clock_bias - sb.clock_bias) * SPEED_OF_LIGHT < 1.0, sat
            checked.add(sat[0])
    assert checked == {"E", "R"}  # Galileo every 10 min, GLONASS every 30 min


def test_select_ephemeris(nav: NavigationData) -> None:
    ephs = nav.ephemerides["R01"]
    mid = 0.5 * (ephs[0].toe + ephs[1].toe)
    assert select_ephemeris(nav, "R01", mid - 10.0) is ephs[0]
    assert select_ephemeris(nav, "R01", mid + 10.0) is ephs[1]
    assert select_ephemeris(nav, "R01", ephs[1].toe + 4000.0) is None  # beyond 30 min
    assert select_ephemeris(nav, "G99", mid) is None
    # Galileo: same toe from I/NAV and F/NAV -> F/NAV (its clock matches the stored BGD E5a/E1)
    e04 = select_ephemeris(nav, "E04", nav.ephemerides["E04"][0].toe)
    assert e04.data_source & (1 << 8)
    # QZSS broadcasts health 1 (L6 flag) on usable L1 C/A satellites
    assert select_ephemeris(nav, "J03", nav.ephemerides["J03"][0].toe) is not None
    # Unhealthy GPS satellite is never selected
    g05 = nav.ephemerides["G05"][0]
    sick = NavigationData(ephemerides={"G05": [dataclasses.replace(g05, health=1)]})
    assert select_ephemeris(sick, "G05", g05.toe) is None
    # Nearest toe wins among several
    two = NavigationData(ephemerides={"G05": [g05, dataclasses.replace(g05, toe=g05.toe + 7200)]})
    assert select_ephemeris(two, "G05", g05.toe + 3000.0) is g05
    assert select_ephemeris(two, "G05", g05.toe + 4000.0).toe == g05.toe + 7200


def test_carrier_wavelength(nav: NavigationData) -> None:
    assert carrier_wavelength("G05") == pytest.approx(0.190293673, abs=1e-9)
    assert carrier_wavelength("E11") == carrier_wavelength("J03") == carrier_wavelength("G05")
    assert carrier_wavelength("C08") == pytest.approx(SPEED_OF_LIGHT / 1561.098e6)
    k = nav.ephemerides["R03"][0].frequency_number  # +5 in this file
    assert carrier_wavelength("R03", nav) == pytest.approx(
        SPEED_OF_LIGHT / (1602e6 + k * 0.5625e6))
    with pytest.raises(ValueError):
        carrier_wavelength("R03")


# --------------------------------------------------------------------- geometry


def test_geometry_light_time_and_earth_rotation(nav: NavigationData, base_llh) -> None:
    rx = geodetic_to_ecef(*base_llh)
    t_r = nav.ephemerides["G05"][0].toe - 5000.0
    g = satellite_geometry(nav, "G05", t_r, rx)
    eph = select_ephemeris(nav, "G05", t_r)
    tau = g.range / SPEED_OF_LIGHT
    assert g.flight_time == pytest.approx(tau, abs=1e-16)
    # Independent first-order form: range in the transmit frame plus the Sagnac term
    st = satellite_state(eph, t_r, -tau)
    sagnac = OMEGA_EARTH * (st.position[0] * rx[1] - st.position[1] * rx[0]) / SPEED_OF_LIGHT
    assert g.range == pytest.approx(np.linalg.norm(st.position - rx) + sagnac, abs=5e-3)
    assert abs(sagnac) > 1.0  # the test would notice a missing correction
    np.testing.assert_allclose(np.linalg.norm(g.line_of_sight), 1.0)
    assert g.sat_clock_bias == pytest.approx(st.clock_bias, abs=1e-15)
    assert math.radians(10) < g.elevation < math.pi / 2 and 0 <= g.azimuth < 2 * math.pi
    assert satellite_geometry(nav, "G99", t_r, rx) is None


@pytest.mark.parametrize("sat", ["G18", "E04", "R01", "C01"])
def test_range_rate_is_the_derivative_of_range(nav: NavigationData, base_llh, sat: str) -> None:
    rx = geodetic_to_ecef(*base_llh)
    v_rx = np.array([4.0, -3.0, 1.5])  # a moving receiver
    t = nav.ephemerides["G05"][0].toe - 6000.0
    h = 0.5
    g = satellite_geometry(nav, sat, t, rx)
    plus = satellite_geometry(nav, sat, t + h, rx + v_rx * h)
    minus = satellite_geometry(nav, sat, t - h, rx - v_rx * h)
    fd = (plus.range - minus.range) / (2 * h)
    assert g.range_rate(v_rx) == pytest.approx(fd, abs=1e-5)
    static = (satellite_geometry(nav, sat, t + h, rx).range
              - satellite_geometry(nav, sat, t - h, rx).range) / (2 * h)
    assert g.range_rate() == pytest.approx(static, abs=1e-5)
    if sat == "G18":  # fast (-545 m/s): the plain projection is off by ~rate^2 / c
        assert abs(g.line_of_sight @ g.sat_velocity - static) > 5e-4


def test_pseudorange_residuals_at_surveyed_position(nav: NavigationData, base_llh) -> None:
    epochs = l1_epochs(read_obs(DATA / "static_base.obs"))
    rx = geodetic_to_ecef(*base_llh)
    per_system: dict[str, list[float]] = {}
    for ep in epochs[::20]:
        # Receiver clock from GPS first (its -73 km offset shifts the satellites' positions)
        clock = 0.0
        for _ in range(2):
            res: dict[str, float] = {}
            t_true = ep.time - clock / SPEED_OF_LIGHT
            for sat, ob in ep.satellites.items():
                g = satellite_geometry(nav, sat, t_true, rx)
                if g is None or g.elevation < math.radians(10) or not math.isfinite(
                        ob.pseudorange):
                    continue
                scale = (carrier_wavelength(sat, nav) / carrier_wavelength("G01")) ** 2
                iono = scale * klobuchar_delay(nav.iono_alpha, nav.iono_beta, t_true,
                                               base_llh[0], base_llh[1], g.elevation, g.azimuth)
                model = g.range - SPEED_OF_LIGHT * g.sat_clock_bias + iono + troposphere_delay(
                    g.elevation, base_llh[2])
                res[sat] = ob.pseudorange - model
            clock = float(np.mean([v for s, v in res.items() if s[0] == "G"]))
        for system in "GERJ":
            vals = np.array([v for s, v in res.items() if s[0] == system])
            per_system.setdefault(system, []).extend(vals - vals.mean())
    rms = {s: float(np.sqrt(np.mean(np.square(v)))) for s, v in per_system.items()}
    assert len(per_system["G"]) >= 9 * 6
    # Measured: G 1.4, E 1.1, J 0.3, R 2.8 m (GLONASS carries inter-frequency code biases).
    assert rms["G"] < 2.5
    assert rms["E"] < 2.5
    assert rms["J"] < 2.5
    assert rms["R"] < 5.0


# ------------------------------------------------------------------- atmosphere


def test_troposphere_delay() -> None:
    zenith = troposphere_delay(math.pi / 2, 0.0)
    assert 2.3 < zenith < 2.5  # ~2.31 m hydrostatic + ~0.09 m wet at sea level
    assert troposphere_delay(math.pi / 2, 2000.0) < 0.82 * zenith  # pressure falls ~21 %
    low = troposphere_delay(math.radians(5.0), 0.0)
    assert 9.5 < low / zenith < 11.0
    assert troposphere_delay(math.radians(30.0), 0.0) == pytest.approx(2.0 * zenith, rel=0.01)
    assert math.isfinite(troposphere_delay(0.0, 0.0))


def test_klobuchar_night_and_day_at_zenith() -> None:
    slant = 1.0 + 16.0 * (0.53 - 0.5) ** 3  # obliquity factor at zenith
    alpha, beta = (2e-8, 0.0, 0.0, 0.0), (1e5, 0.0, 0.0, 0.0)
    # User on the equator at longitude 0: local time = GPS time of day; 14:00 is the peak.
    peak = klobuchar_delay(alpha, beta, WEEK + 50400.0, 0.0, 0.0, math.pi / 2, 0.0)
    assert peak == pytest.approx(SPEED_OF_LIGHT * slant * (5e-9 + 2e-8), rel=1e-9)
    night = klobuchar_delay(alpha, beta, WEEK + 7200.0, 0.0, 0.0, math.pi / 2, 0.0)
    assert night == pytest.approx(SPEED_OF_LIGHT * slant * 5e-9, rel=1e-9)
    # 90 deg east the local peak comes 6 h earlier in GPS time
    east = klobuchar_delay(alpha, beta, WEEK + 50400.0 - 21600.0, 0.0, math.pi / 2,
                           math.pi / 2, 0.0)
    assert east == pytest.approx(peak, rel=1e-9)
    # Low elevation: longer path through the layer (factor ~3)
    low = klobuchar_delay(alpha, beta, WEEK + 7200.0, 0.0, 0.0, math.radians(5.0), 0.0)
    assert 2.5 < low / night < 3.5
