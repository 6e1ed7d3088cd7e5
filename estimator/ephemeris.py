"""Satellite orbits and clocks from broadcast ephemerides, and the atmosphere models of SPP.

Times are GPS seconds since the GPS epoch (``gpst``). ``KeplerEphemeris.toe``/``toc`` are
absolute gpst (BeiDou already converted from BDT by the reader), so ``t - toe`` needs no week
roll-over handling; only the right ascension term needs the time of week in the system's own
time scale (BDT = GPST - 14 s).

References: IS-GPS-200 (20.3.3.3, 20.3.3.5.2), Galileo OS SIS ICD (5.1.1-5.1.5), BeiDou
ICD B1I (5.2.4.12, GEO case), IS-QZSS-PNT, GLONASS ICD 5.1 (appendix A.3.1.2).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .frames import (
    FREQ_GLONASS_L1_BASE,
    FREQ_GLONASS_L1_STEP,
    FREQ_L1,
    GM_BEIDOU,
    GM_GALILEO,
    GM_GPS,
    OMEGA_EARTH,
    SECONDS_PER_WEEK,
    SPEED_OF_LIGHT,
    elevation_azimuth,
    vector_length,
)
from .records import GlonassEphemeris, KeplerEphemeris, NavigationData

# Earth rotation rates used by each system's ephemeris definition (rad/s)
OMEGA_EARTH_BEIDOU = 7.2921150e-5  # CGCS2000
# GLONASS PZ-90 constants (ICD 2008, table 3.2)
GM_GLONASS = 3.986004418e14
A_GLONASS = 6378136.0
J2_GLONASS = 1.0826257e-3
OMEGA_EARTH_GLONASS = 7.292115e-5

FREQ_B1I = 1561.098e6
BDT_MINUS_GPST = -14.0  # s, BDT = GPST - 14 s

# BeiDou geostationary satellites (B1I ICD: PRN 1-5, BDS-3 GEO PRN 59-63); their broadcast
# orbit is defined in a frame tilted by -5 deg and needs the special rotation.
BEIDOU_GEO_PRNS = frozenset({1, 2, 3, 4, 5, 59, 60, 61, 62, 63})
_GEO_TILT = math.radians(-5.0)

# Largest |t - toe| accepted when selecting an ephemeris (s): half the GPS/QZSS 4 h fit
# interval, the Galileo nominal 4 h validity, BeiDou (hourly uploads) 2 h, GLONASS 15 min
# half-interval with a 15 min margin (30 min uploads).
MAX_EPHEMERIS_AGE = {"G": 7200.0, "J": 7200.0, "E": 14400.0, "C": 7200.0, "R": 1800.0}

_GLONASS_STEP = 30.0  # RK4 step (s): truncation error < 0.1 mm after 30 min

# Galileo data-source bits (RINEX 3.04): 8 = clock for E5a,E1 (F/NAV), 9 = E5b,E1 (I/NAV)
_GAL_CLOCK_E5A_E1 = 1 << 8


@dataclass(frozen=True)
class SatelliteState:
    """Satellite state at the (true, gpst) transmit time, in the ECEF frame of that time."""

    position: np.ndarray  # m
    velocity: np.ndarray  # m/s
    clock_bias: float  # s, incl. relativistic term, minus the L1/E1/B1I group delay
    clock_drift: float  # s/s


@dataclass(frozen=True)
class Geometry:
    """One satellite seen from one receiver at one (true gpst) reception time.

    ``sat_position``/``sat_velocity`` are the transmit-time state rotated into the ECEF frame of
    the reception time (Earth rotation during the signal flight, i.e. the Sagnac correction), so
    ``range == |sat_position - receiver|`` exactly.
    """

    sat: str
    range: float  # m, geometric
    line_of_sight: np.ndarray  # unit vector receiver -> satellite, ECEF
    sat_position: np.ndarray
    sat_velocity: np.ndarray
    sat_clock_bias: float  # s
    sat_clock_drift: float  # s/s
    elevation: float  # rad
    azimuth: float  # rad, from north towards east
    flight_time: float  # s, = range / c (transmit time = reception time - flight_time)

    def range_rate(self, receiver_velocity: np.ndarray | None = None) -> float:
        """Exact d(range)/d(reception time) (m/s) for a receiver moving at ``receiver_velocity``
        (ECEF m/s; default static).

        ``line_of_sight @ (sat_velocity - v_rx)`` misses the change of the flight time, an
        error of ~range_rate^2 / c (up to 1.5 mm/s for GPS). With p the position in the
        reception frame, A = sat_velocity and B = d p / d tau = -w z x p:
        rate = los.(A - v_rx) / (1 + los.(A - B) / c).
        """
        los = self.line_of_sight
        p = self.sat_position
        a = self.sat_velocity
        b = OMEGA_EARTH * np.array([p[1], -p[0], 0.0])
        v_rx = np.zeros(3) if receiver_velocity is None else np.asarray(receiver_velocity)
        return float(los @ (a - v_rx) / (1.0 + los @ (a - b) / SPEED_OF_LIGHT))


# ------------------------------------------------------------------------- selection


def _healthy(eph: KeplerEphemeris | GlonassEphemeris) -> bool:
    if eph.sat[0] == "J":
        # The QZSS LSB flags L6 (ex-LEX), irrelevant for L1 C/A users.
        return (eph.health & ~1) == 0
    return eph.health == 0


def select_ephemeris(
    nav: NavigationData, sat: str, t: float
) -> KeplerEphemeris | GlonassEphemeris | None:
    """Healthy ephemeris of ``sat`` with the toe nearest to ``t`` within its validity, or None.

    Galileo: among records with the same toe the F/NAV one (clock for E5a,E1) is preferred,
    because the stored group delay is BGD(E5a,E1), which is the one matching that clock.
    """
    candidates = nav.ephemerides.get(sat)
    if not candidates:
        return None
    max_age = MAX_EPHEMERIS_AGE.get(sat[0], 7200.0)
    best = None
    best_key = None
    for eph in candidates:
        age = abs(t - eph.toe)
        if age > max_age or not _healthy(eph):
            continue
        fnav = isinstance(eph, KeplerEphemeris) and bool(eph.data_source & _GAL_CLOCK_E5A_E1)
        key = (age, not fnav)
        if best_key is None or key < best_key:
            best, best_key = eph, key
    return best


# ------------------------------------------------------------------------ frequencies


def carrier_frequency(sat: str, nav: NavigationData | None = None) -> float:
    """L1 C/A, E1, B1I, or GLONASS L1OF carrier frequency (Hz) of a satellite."""
    system = sat[0]
    if system in "GEJS":
        return FREQ_L1
    if system == "C":
        return FREQ_B1I
    if system == "R":
        if nav is not None:
            for eph in nav.ephemerides.get(sat, []):
                if isinstance(eph, GlonassEphemeris):
                    return FREQ_GLONASS_L1_BASE + eph.frequency_number * FREQ_GLONASS_L1_STEP
        raise ValueError(f"{sat}: GLONASS frequency number unknown (no ephemeris in nav)")
    raise ValueError(f"{sat}: unsupported system {system!r}")


def carrier_wavelength(sat: str, nav: NavigationData | None = None) -> float:
    """Carrier wavelength (m) of the L1/E1/B1I signal (GLONASS from its frequency number)."""
    return SPEED_OF_LIGHT / carrier_frequency(sat, nav)


# ---------------------------------------------------------------------------- orbits


def _system_constants(sat: str) -> tuple[float, float]:
    """(GM, Earth rotation rate) of the system's ephemeris definition."""
    system = sat[0]
    if system == "E":
        return GM_GALILEO, OMEGA_EARTH
    if system == "C":
        return GM_BEIDOU, OMEGA_EARTH_BEIDOU
    return GM_GPS, OMEGA_EARTH  # GPS, QZSS


def _time_of_week(sat: str, t_gpst: float) -> float:
    """Seconds of week in the system's time scale (only BeiDou differs from GPST)."""
    if sat[0] == "C":
        t_gpst = t_gpst + BDT_MINUS_GPST
    return t_gpst - math.floor(t_gpst / SECONDS_PER_WEEK) * SECONDS_PER_WEEK


def is_beidou_geo(sat: str) -> bool:
    return sat[0] == "C" and int(sat[1:]) in BEIDOU_GEO_PRNS


def _kepler_state(eph: KeplerEphemeris, t: float, offset: float) -> SatelliteState:
    gm, omega_e = _system_constants(eph.sat)
    a = eph.sqrt_a * eph.sqrt_a
    e = eph.e
    tk = (t - eph.toe) + offset
    n = math.sqrt(gm / (a * a * a)) + eph.delta_n
    mk = eph.m0 + n * tk

    ek = mk
    for _ in range(30):  # Newton on Kepler's equation
        step = (ek - e * math.sin(ek) - mk) / (1.0 - e * math.cos(ek))
        ek -= step
        if abs(step) < 1e-15:
            break
    sin_e, cos_e = math.sin(ek), math.cos(ek)
    one_m_ecos = 1.0 - e * cos_e
    sq = math.sqrt(1.0 - e * e)
    nu = math.atan2(sq * sin_e, cos_e - e)
    phi = nu + eph.omega
    s2, c2 = math.sin(2.0 * phi), math.cos(2.0 * phi)
    u = phi + eph.cus * s2 + eph.cuc * c2
    r = a * one_m_ecos + eph.crs * s2 + eph.crc * c2
    inc = eph.i0 + eph.idot * tk + eph.cis * s2 + eph.cic * c2

    # Time derivatives (analytic, so velocity is exactly the derivative of position)
    e_dot = n / one_m_ecos
    nu_dot = e_dot * sq / one_m_ecos
    u_dot = nu_dot * (1.0 + 2.0 * (eph.cus * c2 - eph.cuc * s2))
    r_dot = a * e * sin_e * e_dot + 2.0 * nu_dot * (eph.crs * c2 - eph.crc * s2)
    inc_dot = eph.idot + 2.0 * nu_dot * (eph.cis * c2 - eph.cic * s2)

    cu, su = math.cos(u), math.sin(u)
    xp, yp = r * cu, r * su
    xp_dot = r_dot * cu - r * u_dot * su
    yp_dot = r_dot * su + r * u_dot * cu

    toe_sow = _time_of_week(eph.sat, eph.toe)
    geo = is_beidou_geo(eph.sat)
    if geo:
        # Node in the inertial-like GEO frame (no Earth rotation term); rotated below.
        big_omega = eph.omega0 + eph.omega_dot * tk - omega_e * toe_sow
        big_omega_dot = eph.omega_dot
    else:
        big_omega = eph.omega0 + (eph.omega_dot - omega_e) * tk - omega_e * toe_sow
        big_omega_dot = eph.omega_dot - omega_e

    co, so = math.cos(big_omega), math.sin(big_omega)
    ci, si = math.cos(inc), math.sin(inc)
    x = xp * co - yp * ci * so
    y = xp * so + yp * ci * co
    z = yp * si
    vx = xp_dot * co - yp_dot * ci * so + yp * si * inc_dot * so - y * big_omega_dot
    vy = xp_dot * so + yp_dot * ci * co - yp * si * inc_dot * co + x * big_omega_dot
    vz = yp_dot * si + yp * ci * inc_dot
    pos = np.array([x, y, z])
    vel = np.array([vx, vy, vz])

    if geo:
        # r = Rz(omega_e tk) Rx(-5 deg) r_GK with coordinate-rotation matrices (B1I ICD)
        ct, st = math.cos(_GEO_TILT), math.sin(_GEO_TILT)
        rx = np.array([[1.0, 0.0, 0.0], [0.0, ct, st], [0.0, -st, ct]])
        ang = omega_e * tk
        ca, sa = math.cos(ang), math.sin(ang)
        rz = np.array([[ca, sa, 0.0], [-sa, ca, 0.0], [0.0, 0.0, 1.0]])
        rz_dot = omega_e * np.array([[-sa, ca, 0.0], [-ca, -sa, 0.0], [0.0, 0.0, 0.0]])
        p_tilt, v_tilt = rx @ pos, rx @ vel
        pos = rz @ p_tilt
        vel = rz @ v_tilt + rz_dot @ p_tilt

    # Clock: polynomial + relativistic eccentricity term - group delay of the L1 user
    dt = (t - eph.toc) + offset
    f_rel = -2.0 * math.sqrt(gm) / SPEED_OF_LIGHT**2
    rel = f_rel * e * eph.sqrt_a * sin_e
    rel_dot = f_rel * e * eph.sqrt_a * cos_e * e_dot
    clock = eph.af0 + eph.af1 * dt + eph.af2 * dt * dt + rel - eph.tgd
    drift = eph.af1 + 2.0 * eph.af2 * dt + rel_dot
    return SatelliteState(pos, vel, clock, drift)


def _glonass_derivative(state: np.ndarray, acc_ls: np.ndarray) -> np.ndarray:
    """PZ-90 equations of motion in the rotating frame (GLONASS ICD A.3.1.2)."""
    x, y, z, vx, vy, vz = state
    r2 = x * x + y * y + z * z
    r = math.sqrt(r2)
    mu_r3 = GM_GLONASS / (r2 * r)
    j2_term = 1.5 * J2_GLONASS * GM_GLONASS * A_GLONASS**2 / (r2 * r2 * r)
    z2_r2 = 5.0 * z * z / r2
    w2 = OMEGA_EARTH_GLONASS**2
    ax = -mu_r3 * x - j2_term * x * (1.0 - z2_r2) + w2 * x + 2.0 * OMEGA_EARTH_GLONASS * vy
    ay = -mu_r3 * y - j2_term * y * (1.0 - z2_r2) + w2 * y - 2.0 * OMEGA_EARTH_GLONASS * vx
    az = -mu_r3 * z - j2_term * z * (3.0 - z2_r2)
    return np.array([vx, vy, vz, ax + acc_ls[0], ay + acc_ls[1], az + acc_ls[2]])


def _glonass_state(eph: GlonassEphemeris, t: float, offset: float) -> SatelliteState:
    dt_total = (t - eph.toe) + offset
    steps = max(1, math.ceil(abs(dt_total) / _GLONASS_STEP))
    h = dt_total / steps
    y = np.array([*eph.position, *eph.velocity], dtype=float)
    acc = np.asarray(eph.acceleration, dtype=float)
    if dt_total != 0.0:
        for _ in range(steps):
            k1 = _glonass_derivative(y, acc)
            k2 = _glonass_derivative(y + 0.5 * h * k1, acc)
            k3 = _glonass_derivative(y + 0.5 * h * k2, acc)
            k4 = _glonass_derivative(y + h * k3, acc)
            y = y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    # The broadcast clock already contains the relativistic effect (ICD 3.3.3).
    clock = eph.tau_n + eph.gamma_n * dt_total
    return SatelliteState(y[:3].copy(), y[3:].copy(), clock, eph.gamma_n)


def satellite_state(
    eph: KeplerEphemeris | GlonassEphemeris, t_transmit: float, offset: float = 0.0
) -> SatelliteState:
    """Position, velocity (ECEF of the transmit time) and L1 clock at true gpst
    ``t_transmit + offset``.

    A float64 gpst near 1.4e9 s resolves only 0.24 us; passing the small part (e.g. minus the
    signal flight time) as ``offset`` keeps the time exact to ~1e-15 s.
    """
    if isinstance(eph, GlonassEphemeris):
        return _glonass_state(eph, t_transmit, offset)
    return _kepler_state(eph, t_transmit, offset)


def rotate_earth(vec: np.ndarray, angle: float) -> np.ndarray:
    """Coordinates, in a frame rotated by ``angle`` about z (Earth rotation), of ``vec``."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * vec[0] + s * vec[1], -s * vec[0] + c * vec[1], vec[2]])


def satellite_geometry(
    nav: NavigationData, sat: str, t_receive: float, receiver_ecef: np.ndarray
) -> Geometry | None:
    """Geometry of ``sat`` for a receiver at ``receiver_ecef`` at true gpst ``t_receive``.

    Solves the light-time equation |R(w tau) r_sat(t - tau) - r_rx| = c tau to far below a
    millimetre. None without a usable ephemeris.
    """
    eph = select_ephemeris(nav, sat, t_receive)
    if eph is None:
        return None
    rx = np.asarray(receiver_ecef, dtype=float)
    # Evaluate the orbit exactly at tau_eval and solve the light-time equation on its linear
    # extrapolation; re-evaluate until the solution stays within 1e-11 s of tau_eval, where
    # the extrapolation is exact (usually two orbit evaluations: GLONASS integration is slow).
    tau_eval = tau = 0.075
    state = satellite_state(eph, t_receive, -tau_eval)
    for _ in range(10):
        for _ in range(10):  # contraction factor ~ v_sat / c
            p = state.position + state.velocity * (tau_eval - tau)
            new_tau = vector_length(rotate_earth(p, OMEGA_EARTH * tau) - rx)
            new_tau /= SPEED_OF_LIGHT
            done = abs(new_tau - tau) < 1e-15
            tau = new_tau
            if done:
                break
        if abs(tau - tau_eval) < 1e-11:
            break
        tau_eval = tau
        state = satellite_state(eph, t_receive, -tau_eval)
    dt = tau_eval - tau
    pos = rotate_earth(state.position + state.velocity * dt, OMEGA_EARTH * tau)
    vel = rotate_earth(state.velocity, OMEGA_EARTH * tau)
    clock = state.clock_bias + state.clock_drift * dt
    diff = pos - rx
    rng = vector_length(diff)
    el, az = elevation_azimuth(rx, pos)
    return Geometry(
        sat=sat,
        range=rng,
        line_of_sight=diff / rng,
        sat_position=pos,
        sat_velocity=vel,
        sat_clock_bias=clock,
        sat_clock_drift=state.clock_drift,
        elevation=el,
        azimuth=az,
        flight_time=tau,
    )


# ------------------------------------------------------------------------ atmosphere


def tropo_mapping(elevation: float) -> float:
    """Simple elevation mapping (RTCA MOPS form), finite at the horizon."""
    s = math.sin(max(elevation, 0.0))
    return 1.001 / math.sqrt(0.002001 + s * s)


def troposphere_zenith(height_m: float) -> tuple[float, float]:
    """(hydrostatic, wet) zenith delays (m): Saastamoinen with a standard atmosphere,
    50 % relative humidity, at latitude 45 deg (the latitude term is below 1 cm)."""
    h = min(max(height_m, -500.0), 11000.0)
    pressure = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568  # hPa
    temp_k = 288.15 - 0.0065 * h
    temp_c = temp_k - 273.15
    e_sat = 6.112 * math.exp(17.62 * temp_c / (243.12 + temp_c))  # Magnus, hPa
    e = 0.5 * e_sat
    zhd = 0.0022768 * pressure / (1.0 - 0.00028 * h * 1e-3)
    zwd = 0.002277 * (1255.0 / temp_k + 0.05) * e
    return zhd, zwd


def troposphere_delay(elevation: float, height_m: float) -> float:
    """Slant tropospheric delay (m) at ``elevation`` (rad) for a receiver ``height_m`` above the
    sea (ellipsoidal height is fine: a 40 m geoid difference changes the delay by ~1 cm)."""
    zhd, zwd = troposphere_zenith(height_m)
    return (zhd + zwd) * tropo_mapping(elevation)


def pierce_angle(elevation: float) -> float:
    """Earth-centred angle (semicircles) from the receiver to the ionospheric pierce point
    of a satellite at ``elevation`` (rad): the Klobuchar model's approximation."""
    return 0.0137 / (max(elevation, 0.0) / math.pi + 0.11) - 0.022


def klobuchar_delay(
    nav_alpha: Sequence[float],
    nav_beta: Sequence[float],
    t_gpst: float,
    lat: float,
    lon: float,
    elevation: float,
    azimuth: float,
) -> float:
    """GPS L1 ionospheric group delay (m), IS-GPS-200 20.3.3.5.2.5.

    ``lat``, ``lon``, ``elevation``, ``azimuth`` in radians; the ICD works in semicircles.
    Scale by (f_L1 / f)^2 for other frequencies.
    """
    el_sc = max(elevation, 0.0) / math.pi
    psi = pierce_angle(elevation)
    phi_i = lat / math.pi + psi * math.cos(azimuth)
    phi_i = min(max(phi_i, -0.416), 0.416)
    lam_i = lon / math.pi + psi * math.sin(azimuth) / math.cos(phi_i * math.pi)
    phi_m = phi_i + 0.064 * math.cos((lam_i - 1.617) * math.pi)  # geomagnetic latitude
    tod = 4.32e4 * lam_i + t_gpst
    tod -= math.floor(tod / 86400.0) * 86400.0  # local time at the pierce point
    slant = 1.0 + 16.0 * (0.53 - el_sc) ** 3
    amp = sum(a * phi_m**k for k, a in enumerate(nav_alpha))
    per = sum(b * phi_m**k for k, b in enumerate(nav_beta))
    amp = max(amp, 0.0)
    per = max(per, 72000.0)
    x = 2.0 * math.pi * (tod - 50400.0) / per
    if abs(x) < 1.57:
        delay = slant * (5e-9 + amp * (1.0 - x * x / 2.0 + x**4 / 24.0))
    else:
        delay = slant * 5e-9
    return SPEED_OF_LIGHT * delay
