"""The simulated world's GNSS error sources, physical and independent of the estimator's models.

The estimator corrects the carrier phase with the broadcast Klobuchar ionosphere and a standard
atmosphere troposphere through a simple mapping (``estimator.ephemeris``), and takes the
broadcast orbits and clocks as true. The simulated world departs from all of that the way the
real one does, so that the corrections are tested, not mirrored:

- ``Ionosphere``: a vertical delay field over a thin shell at 350 km (its own level, diurnal
  shape in local time, north-south gradient and travelling disturbances), slant delays through
  the shell's mapping; the Klobuchar model removes only about half of it.
- ``Troposphere``: Saastamoinen zenith delays from the day's pressure and a humid summer wet
  delay with a slow variation, the Niell (1996) mapping functions and a horizontal gradient.
- ``SatelliteErrors``: broadcast orbit error (radial/along/cross, once per revolution) and
  broadcast clock error (offset and rate) of each satellite, and a short-term range
  fluctuation common to nearby antennas (its rate a Gauss–Markov process).
- ``gauss_markov``: first-order Gauss–Markov sequences (also the multipath's).

Magnitudes are in ``gnss.GnssErrorModel``; each says where it comes from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from estimator.frames import WAVELENGTH_L1

EARTH_RADIUS_M = 6371e3
SHELL_HEIGHT_M = 350e3  # thin-shell height of the ionosphere (IGS/IONEX convention)
# Orbital periods (s) by system: the broadcast orbit error varies once per revolution.
ORBIT_PERIOD_S = {"G": 43082.0, "J": 86164.0, "E": 50680.0, "C": 46404.0, "R": 40544.0}

# Niell (1996) mapping function coefficients at latitudes 15, 30, 45, 60, 75 deg (table 3 of
# Niell, J. Geophys. Res. 101(B2), 3227-3246): hydrostatic average a, b, c; their seasonal
# amplitudes; the wet a, b, c; the hydrostatic height correction.
_NMF_LATITUDES = np.array([15.0, 30.0, 45.0, 60.0, 75.0])
_NMF_HYDRO_AVG = np.array([
    [1.2769934e-3, 1.2683230e-3, 1.2465397e-3, 1.2196049e-3, 1.2045996e-3],
    [2.9153695e-3, 2.9152299e-3, 2.9288445e-3, 2.9022565e-3, 2.9024912e-3],
    [62.610505e-3, 62.837393e-3, 63.721774e-3, 63.824265e-3, 64.258455e-3]])
_NMF_HYDRO_AMP = np.array([
    [0.0, 1.2709626e-5, 2.6523662e-5, 3.4000452e-5, 4.1202191e-5],
    [0.0, 2.1414979e-5, 3.0160779e-5, 7.2562722e-5, 11.723375e-5],
    [0.0, 9.0128400e-5, 4.3497037e-5, 84.795348e-5, 170.37206e-5]])
_NMF_WET = np.array([
    [5.8021897e-4, 5.6794847e-4, 5.8118019e-4, 5.9727542e-4, 6.1641693e-4],
    [1.4275268e-3, 1.5138625e-3, 1.4572752e-3, 1.5007428e-3, 1.7599082e-3],
    [4.3472961e-2, 4.6729510e-2, 4.3908931e-2, 4.4626982e-2, 5.4736038e-2]])
_NMF_HEIGHT = (2.53e-5, 5.49e-3, 1.14e-3)


def _continued_fraction(sin_el: float, a: float, b: float, c: float) -> float:
    """Marini's continued fraction, normalised to 1 at the zenith."""
    top = 1.0 + a / (1.0 + b / (1.0 + c))
    return top / (sin_el + a / (sin_el + b / (sin_el + c)))


def _nmf_coefficients(table: np.ndarray, lat_deg: float) -> np.ndarray:
    return np.array([np.interp(abs(lat_deg), _NMF_LATITUDES, row) for row in table])


def niell_hydrostatic(elevation: float, lat: float, height_m: float, day_of_year: float) -> float:
    """Niell hydrostatic mapping function (elevation, latitude in rad)."""
    phase = 2.0 * math.pi * (day_of_year - 28.0) / 365.25 + (math.pi if lat < 0 else 0.0)
    lat_deg = math.degrees(lat)
    a, b, c = (_nmf_coefficients(_NMF_HYDRO_AVG, lat_deg)
               - _nmf_coefficients(_NMF_HYDRO_AMP, lat_deg) * math.cos(phase))
    s = math.sin(max(elevation, math.radians(2.0)))
    height_term = (1.0 / s - _continued_fraction(s, *_NMF_HEIGHT)) * height_m / 1000.0
    return _continued_fraction(s, a, b, c) + height_term


def niell_wet(elevation: float, lat: float) -> float:
    """Niell wet mapping function (elevation, latitude in rad)."""
    a, b, c = _nmf_coefficients(_NMF_WET, math.degrees(lat))
    return _continued_fraction(math.sin(max(elevation, math.radians(2.0))), a, b, c)


def saastamoinen_zenith_hydrostatic(pressure_hpa: float, lat: float, height_m: float) -> float:
    """Zenith hydrostatic delay (m) from the surface pressure (Saastamoinen / Davis et al.)."""
    return 0.0022768 * pressure_hpa / (1.0 - 0.00266 * math.cos(2.0 * lat)
                                       - 0.00028 * height_m / 1000.0)


# ----------------------------------------------------------------------------- ionosphere


def pierce_point(lat: float, lon: float, elevation: float, azimuth: float
                 ) -> tuple[float, float, float]:
    """(latitude, longitude, obliquity) of the line of sight's crossing of the thin shell."""
    ratio = EARTH_RADIUS_M / (EARTH_RADIUS_M + SHELL_HEIGHT_M)
    cos_zenith_shell = math.sqrt(1.0 - (ratio * math.cos(elevation)) ** 2)
    psi = math.pi / 2.0 - elevation - math.asin(ratio * math.cos(elevation))
    lat_p = math.asin(math.sin(lat) * math.cos(psi)
                      + math.cos(lat) * math.sin(psi) * math.cos(azimuth))
    lon_p = lon + math.asin(math.sin(psi) * math.sin(azimuth) / math.cos(lat_p))
    return lat_p, lon_p, 1.0 / cos_zenith_shell


@dataclass
class TravellingDisturbance:
    """A plane wave of vertical delay moving over the shell (medium-scale TID)."""

    amplitude_m: float
    wavelength_m: float
    azimuth: float  # direction of travel, rad from north
    period_s: float
    phase: float


def local_time_s(lon: float, t_gpst: float) -> float:
    """Local solar time (s of day) at longitude ``lon`` (rad) at GPS time ``t_gpst``."""
    return (t_gpst + lon / (2.0 * math.pi) * 86400.0) % 86400.0


@dataclass
class Ionosphere:
    """Vertical L1 group delay over the thin shell: a diurnal bulge in local time at the pierce
    point (so the evening decay shows both as a trend and as an east-west gradient), a
    north-south gradient and travelling disturbances."""

    lat0: float  # the site (reference of the gradient and of the disturbances' positions)
    lon0: float
    peak_m: float  # vertical delay at the diurnal peak, at the site's latitude
    night_fraction: float  # night-time floor as a fraction of the peak
    peak_local_time_s: float
    width_s: float  # standard deviation of the bulge in local time
    gradient_north_per_m: float  # relative change of the level per metre north
    disturbances: list[TravellingDisturbance]
    t0: float  # the disturbances' time origin

    def vertical(self, lat: float, lon: float, t: float) -> float:
        hours_from_peak = (local_time_s(lon, t) - self.peak_local_time_s + 43200.0) % 86400.0
        hours_from_peak -= 43200.0
        bulge = math.exp(-0.5 * (hours_from_peak / self.width_s) ** 2)
        shape = self.night_fraction + (1.0 - self.night_fraction) * bulge
        north = (lat - self.lat0) * EARTH_RADIUS_M
        east = (lon - self.lon0) * EARTH_RADIUS_M * math.cos(self.lat0)
        v = self.peak_m * shape * (1.0 + self.gradient_north_per_m * north)
        dt = t - self.t0
        for d in self.disturbances:
            along = north * math.cos(d.azimuth) + east * math.sin(d.azimuth)
            v += d.amplitude_m * math.sin(2.0 * math.pi * (along / d.wavelength_m
                                                           - dt / d.period_s) + d.phase)
        return max(v, 0.0)

    def slant(self, t: float, lat: float, lon: float, elevation: float, azimuth: float,
              wavelength_m: float = WAVELENGTH_L1) -> float:
        """Slant group delay (m) of the carrier of ``wavelength_m`` (phase: the same, advanced)."""
        lat_p, lon_p, obliquity = pierce_point(lat, lon, elevation, azimuth)
        return (wavelength_m / WAVELENGTH_L1) ** 2 * obliquity * self.vertical(lat_p, lon_p, t)


# ---------------------------------------------------------------------------- troposphere


@dataclass
class Troposphere:
    """Zenith hydrostatic + wet delays through the Niell mapping functions, with a gradient."""

    lat: float
    height_m: float
    day_of_year: float
    t0: float
    zenith_hydrostatic_m: float
    zenith_wet_m: float
    wet_waves: list[tuple[float, float, float]]  # (amplitude m, period s, phase)
    gradient_m: tuple[float, float]  # north, east (Chen & Herring)

    def zenith_wet(self, t: float) -> float:
        dt = t - self.t0
        return self.zenith_wet_m + sum(a * math.sin(2.0 * math.pi * dt / p + ph)
                                       for a, p, ph in self.wet_waves)

    def slant(self, t: float, elevation: float, azimuth: float) -> float:
        el = max(elevation, math.radians(2.0))
        gradient_map = 1.0 / (math.sin(el) * math.tan(el) + 0.0032)
        gradient = self.gradient_m[0] * math.cos(azimuth) + self.gradient_m[1] * math.sin(azimuth)
        return (self.zenith_hydrostatic_m * niell_hydrostatic(elevation, self.lat, self.height_m,
                                                              self.day_of_year)
                + self.zenith_wet(t) * niell_wet(elevation, self.lat)
                + gradient_map * gradient)


# ------------------------------------------------------------------------------ satellites


@dataclass
class SatelliteErrors:
    """Broadcast orbit and clock errors of one satellite, and its random-walk range error."""

    t0: float
    period_s: float
    orbit_mean_m: np.ndarray  # (radial, along, cross)
    orbit_amplitude_m: np.ndarray
    orbit_phase: np.ndarray
    clock_offset_m: float  # c * (true - broadcast satellite clock) at t0
    clock_rate_mps: float
    fluctuation_m: np.ndarray  # short-term range fluctuation, per epoch index

    def orbit_error_ecef(self, t: float, sat_position: np.ndarray,
                         sat_velocity: np.ndarray) -> np.ndarray:
        """True minus broadcast satellite position (m, ECEF)."""
        radial = sat_position / np.linalg.norm(sat_position)
        cross = np.cross(sat_position, sat_velocity)
        cross /= np.linalg.norm(cross)
        along = np.cross(cross, radial)
        rac = self.orbit_mean_m + self.orbit_amplitude_m * np.sin(
            2.0 * math.pi * (t - self.t0) / self.period_s + self.orbit_phase)
        return rac[0] * radial + rac[1] * along + rac[2] * cross

    def range_error(self, t: float, epoch: int, line_of_sight: np.ndarray,
                    sat_position: np.ndarray, sat_velocity: np.ndarray) -> float:
        """What the true range and satellite clock add to the broadcast-computed range (m)."""
        orbit = float(line_of_sight @ self.orbit_error_ecef(t, sat_position, sat_velocity))
        # The true satellite clock is ahead of the broadcast one by clock/c: the signal left
        # earlier, so the measured range is shorter.
        clock = self.clock_offset_m + self.clock_rate_mps * (t - self.t0)
        return orbit - clock + float(self.fluctuation_m[epoch])


def gauss_markov(rng: np.random.Generator, n: int, sigma: float, tau_s: float, dt: float
                 ) -> np.ndarray:
    """First-order Gauss–Markov sequence (stationary, standard deviation ``sigma``, correlation
    time ``tau_s``) sampled every ``dt`` seconds."""
    phi = math.exp(-dt / tau_s) if tau_s > 0 else 0.0
    drive = rng.normal(0.0, sigma, n)
    drive[1:] *= math.sqrt(1.0 - phi * phi)
    return lfilter([1.0], [1.0, -phi], drive)


def integrated_gauss_markov(rng: np.random.Generator, n: int, sigma_rate: float, tau_s: float,
                            dt: float, envelope: np.ndarray | None = None) -> np.ndarray:
    """A range error (m, 0 at the start) whose rate is Gauss–Markov (``sigma_rate`` m/s),
    optionally modulated by ``envelope`` (one factor per sample)."""
    rate = gauss_markov(rng, n, sigma_rate, tau_s, dt)
    if envelope is not None:
        rate = rate * envelope
    return np.concatenate([[0.0], np.cumsum(rate[1:] * dt)])
