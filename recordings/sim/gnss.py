"""GNSS observables of the four compass receivers (the sensors of thesis table 15 and fig. 10,
``docs/references.md``).

Physics per antenna i, satellite k, receiver time tag t (all four receivers share ONE clock):
    P = rho + c (dt_rx - dt_sat) + S + I + T + d_i + mp_code + noise              [m]
    L = (rho + c (dt_rx - dt_sat) + S - I + T + d_i + mp_phase + noise) / lambda + N_i^k   [cycles]
    D = -(d/dt)(rho + c (dt_rx - dt_sat)) / lambda + noise                   [Hz]
rho is evaluated at the true reception time t - dt_rx (light time and Earth rotation inside
``satellite_geometry``) from the broadcast orbit, dt_sat is the broadcast clock; S is what the
true orbit and clock add to that (``gnss_errors.SatelliteErrors``). I and T are the simulated
world's ionosphere and troposphere (``gnss_errors``), NOT the estimator's models. S, I and T are
the same physical delays for all antennas (they cancel in single differences, as on a real 10 cm
array); d_i is each receiver's fixed hardware delay, so the inter-receiver delay difference
D_ij = d_i - d_j survives single differences. The delay rates (< 1 mm/s, 0.005 Hz) are left out
of the Doppler, far below its noise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from estimator.ephemeris import carrier_wavelength, klobuchar_delay, satellite_geometry
from estimator.frames import SPEED_OF_LIGHT, ecef_to_geodetic, ned_to_ecef
from estimator.records import GnssEpoch, NavigationData, SatObservation

from .gnss_errors import (
    ORBIT_PERIOD_S,
    Ionosphere,
    SatelliteErrors,
    TravellingDisturbance,
    Troposphere,
    gauss_markov,
    integrated_gauss_markov,
    saastamoinen_zenith_hydrostatic,
)
from .scenarios import Scenario


@dataclass
class GnssErrorModel:
    """Error magnitudes of the simulated receivers and world (1-sigma unless stated).

    Tuned with ``benchmarks/calibration.py`` so that one simulated static receiver's TDCP
    velocity and its integrated drift match those of a real static receiver (Septentrio
    mosaic-X5, ``/work/shared/data/real-static-short-baseline``) within a factor 1.5.
    """

    # --- receiver
    code_noise_m: float = 0.30  # at zenith, grows as 1/sin(el)
    # Carrier tracking jitter lambda/2pi sqrt(B_L / (C/N0)) (PLL thermal noise) at the simulated
    # C/N0: B_L fitted to the real pair's receiver-only scatter (0.5 mm at 47, 1.2-1.5 at 38 dB-Hz).
    pll_bandwidth_hz: float = 12.0
    doppler_noise_hz: float = 0.03
    # Multipath: Gauss-Markov with a correlation time (the reflection geometry of an antenna
    # changes over minutes), amplitude decaying with elevation; carrier mm, code dm (typical).
    code_multipath_m: float = 0.6  # amplitude at low elevation, decays with elevation
    phase_multipath_m: float = 0.003
    multipath_decay_deg: float = 15.0
    multipath_correlation_s: float = 60.0
    clock_bias_s: float = 2.0e-4  # initial receiver clock bias
    clock_drift_s_per_s: float = 1.5e-7  # initial drift (TCXO)
    clock_drift_random_walk: float = 5.0e-11  # s/s per sqrt(s)
    hardware_delay_m: float = 0.15  # spread of the receivers' delays d_i
    slip_rate_per_epoch: float = 1.0 / 2500.0  # per satellite and receiver
    unflagged_slip_fraction: float = 0.3
    # --- ionosphere (thin shell)
    # Fraction of the true vertical delay at the site and start that the Klobuchar model's level
    # misses (under- or over-estimates with equal odds). Klobuchar corrects ~50 % RMS worldwide,
    # but on the real static pair (same day and hour) the code-minus-carrier rates of the
    # satellites follow Klobuchar's to 0-15 % (fitted ratio 0.86 and 1.00 on the receivers), and
    # a level 20 % off alone drifts a static receiver ~0.5 mm/s: the rest of the departure is
    # the diurnal shape, gradient, disturbances and mapping below.
    iono_klobuchar_residual: tuple[float, float] = (0.0, 0.1)
    # Diurnal bulge in local time (peak ~14 h, night floor 15-30 % of the peak: TEC climatology)
    iono_peak_hour: tuple[float, float] = (13.0, 15.0)
    iono_width_h: tuple[float, float] = (3.5, 5.0)
    iono_night_fraction: tuple[float, float] = (0.15, 0.3)
    iono_gradient_per_1000km: float = 0.25  # relative north-south gradient, ~1.5 mm/km of 6 m
    tid_amplitude_m: float = 0.05  # medium-scale travelling disturbances, ~0.3 TECU (0.16 m/TECU)
    tid_wavelength_km: tuple[float, float] = (100.0, 300.0)
    tid_period_s: tuple[float, float] = (900.0, 3600.0)
    # --- troposphere
    pressure_hpa: tuple[float, float] = (1000.0, 1020.0)  # surface pressure of the day
    zenith_wet_m: tuple[float, float] = (0.10, 0.30)  # humid summer (the estimator assumes 0.09)
    wet_variation_m: float = 0.005  # slow wet-delay variation (periods 20-120 min)
    tropo_gradient_m: float = 0.0007  # horizontal gradient parameters, typically 0.5-1 mm
    # --- satellites (broadcast ephemeris and clock)
    # Broadcast orbit error radial/along/cross RMS (~1 m 3-D: Montenbruck et al. 2015, GPS),
    # half as a constant and half varying once per revolution.
    orbit_error_m: tuple[float, float, float] = (0.2, 0.8, 0.5)
    clock_error_m: float = 0.3  # broadcast clock offset (signal-in-space range error ~0.5 m)
    clock_rate_error_mps: float = 1.0e-4  # broadcast clock rate error (~0.5 m over a 2 h fit)
    # Short-term range fluctuation of each satellite common to nearby antennas (satellite clock
    # and signal noise, small-scale ionospheric/tropospheric irregularities): a white part and
    # a part whose rate is Gauss-Markov; sigmas and correlation time log-uniform per satellite.
    # Source: the real pair's common-mode TDCP scatter, 0.7-2.5 mm/s per satellite with lag-1
    # correlation -0.46..+0.68 (mostly white, a few satellites correlated over seconds).
    sis_phase_sigma_m: tuple[float, float] = (0.3e-3, 1.2e-3)
    sis_rate_sigma_mps: tuple[float, float] = (0.8e-3, 4.0e-3)
    sis_rate_correlation_s: tuple[float, float] = (0.5, 4.0)
    sis_activity_log_sigma: float = 0.8  # bursts: the real pair's drift has heavy tails
    sis_activity_correlation_s: float = 60.0

    @classmethod
    def perfect(cls) -> GnssErrorModel:
        """No noise, multipath or slips (for checking the geometry): the smooth orbit, clock
        and atmosphere errors stay."""
        return cls(code_noise_m=0.0, pll_bandwidth_hz=0.0, doppler_noise_hz=0.0,
                   code_multipath_m=0.0, phase_multipath_m=0.0, slip_rate_per_epoch=0.0,
                   sis_phase_sigma_m=(0.0, 0.0), sis_rate_sigma_mps=(0.0, 0.0))


@dataclass
class GnssWorld:
    """The error sources of the simulated world common to all antennas."""

    ionosphere: Ionosphere
    troposphere: Troposphere
    satellites: dict[str, SatelliteErrors]


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    u = rng.uniform()  # drawn even when the range is empty: the same draws for every model
    return lo * (hi / lo) ** u if lo > 0 else 0.0


def draw_world(errors: GnssErrorModel, rng: np.random.Generator, nav: NavigationData,
               sats: list[str], origin: np.ndarray, start_gpst: float, n_epochs: int,
               dt: float, day_of_year: float) -> GnssWorld:
    """Draw the ionosphere, troposphere and satellite errors of one simulated run (the same
    draws whatever the magnitudes in ``errors`` and the run's length)."""
    lat, lon, h = (float(x) for x in origin)
    klobuchar = 3.0  # m, a quiet-day vertical delay when the file has no Klobuchar parameters
    if nav.iono_alpha is not None and nav.iono_beta is not None:
        klobuchar = klobuchar_delay(nav.iono_alpha, nav.iono_beta, start_gpst, lat, lon,
                                    np.pi / 2, 0.0)
    tids = [TravellingDisturbance(
        amplitude_m=abs(rng.normal(0.0, errors.tid_amplitude_m)),
        wavelength_m=1000.0 * rng.uniform(*errors.tid_wavelength_km),
        azimuth=rng.uniform(0.0, 2 * np.pi), period_s=rng.uniform(*errors.tid_period_s),
        phase=rng.uniform(0.0, 2 * np.pi)) for _ in range(2)]
    ionosphere = Ionosphere(
        lat0=lat, lon0=lon, peak_m=1.0, night_fraction=rng.uniform(*errors.iono_night_fraction),
        peak_local_time_s=3600.0 * rng.uniform(*errors.iono_peak_hour),
        width_s=3600.0 * rng.uniform(*errors.iono_width_h),
        gradient_north_per_m=rng.normal(0.0, errors.iono_gradient_per_1000km) / 1e6,
        disturbances=[], t0=start_gpst)
    # Scale the peak to the drawn level at the site's zenith at the start.
    residual = rng.uniform(*errors.iono_klobuchar_residual)
    level = 1.0 / (1.0 - residual) if rng.random() < 0.5 else 1.0 / (1.0 + residual)
    ionosphere.peak_m = klobuchar * level / ionosphere.vertical(lat, lon, start_gpst)
    ionosphere.disturbances = tids
    waves = [(rng.normal(0.0, errors.wet_variation_m), rng.uniform(1200.0, 7200.0),
              rng.uniform(0.0, 2 * np.pi)) for _ in range(2)]
    tropo_gradient = rng.normal(0.0, errors.tropo_gradient_m, 2)
    troposphere = Troposphere(
        lat, h, day_of_year, start_gpst,
        saastamoinen_zenith_hydrostatic(rng.uniform(*errors.pressure_hpa), lat, h),
        rng.uniform(*errors.zenith_wet_m), waves,
        (float(tropo_gradient[0]), float(tropo_gradient[1])))
    orbit_sigma = np.array(errors.orbit_error_m) / np.sqrt(2.0)
    # Own generators for the sequences: a shorter run is a prefix of a longer one.
    activity_rng, *sat_rngs = rng.spawn(len(sats) + 1)
    # Irregularity activity over the sky comes in bursts: a log-normal envelope (mean square 1)
    # of the fluctuation rates, slowly varying.
    s_log = errors.sis_activity_log_sigma
    activity = np.exp(s_log * gauss_markov(activity_rng, n_epochs, 1.0,
                                           errors.sis_activity_correlation_s, dt) - s_log**2)
    satellites = {}
    for sat, own_rng in zip(sats, sat_rngs, strict=True):
        white = _log_uniform(rng, *errors.sis_phase_sigma_m)
        sigma, tau = (_log_uniform(rng, *errors.sis_rate_sigma_mps),
                      _log_uniform(rng, *errors.sis_rate_correlation_s))
        rate_rng, white_rng = own_rng.spawn(2)
        satellites[sat] = SatelliteErrors(
            t0=start_gpst, period_s=ORBIT_PERIOD_S.get(sat[0], 43082.0),
            orbit_mean_m=rng.normal(0.0, orbit_sigma),
            orbit_amplitude_m=rng.normal(0.0, orbit_sigma),
            orbit_phase=rng.uniform(0.0, 2 * np.pi, 3),
            clock_offset_m=float(rng.normal(0.0, errors.clock_error_m)),
            clock_rate_mps=float(rng.normal(0.0, errors.clock_rate_error_mps)),
            fluctuation_m=(integrated_gauss_markov(rate_rng, n_epochs, sigma, tau, dt, activity)
                           + white_rng.normal(0.0, white, n_epochs)))
    return GnssWorld(ionosphere, troposphere, satellites)


@dataclass
class GnssTruth:
    """What the simulator knows and the estimator must not: used only for scoring and tests."""

    clock_bias_s: np.ndarray  # per epoch
    clock_drift_s_per_s: np.ndarray
    hardware_delay_m: np.ndarray  # (4,)
    ambiguities: list[dict[str, int]] = field(default_factory=list)  # per receiver, latest N_i^k
    # (time tag, receiver, satellite, cycles, flagged by LLI)
    slips: list[tuple[float, int, str, int, bool]] = field(default_factory=list)


class Multipath:
    """Reflection error of one antenna and satellite over the run: unit Gauss-Markov sequences
    (code, carrier) scaled by an amplitude that grows towards the horizon."""

    def __init__(self, errors: GnssErrorModel, rng: np.random.Generator, n_epochs: int,
                 dt: float) -> None:
        tau = errors.multipath_correlation_s
        self.sequence = np.array([gauss_markov(rng, n_epochs, 1.0, tau, dt) for _ in range(2)])
        self.amplitude = np.array([errors.code_multipath_m, errors.phase_multipath_m])
        self.decay = np.radians(errors.multipath_decay_deg)

    def __call__(self, epoch: int, elevation: float) -> tuple[float, float]:
        """(code, carrier) multipath errors in metres."""
        envelope = np.exp(-elevation / self.decay)
        code, carrier = self.amplitude * envelope * self.sequence[:, epoch]
        return float(code), float(carrier)


def is_masked(scenario: Scenario, antenna_ned: np.ndarray, elevation: float,
              azimuth: float) -> bool:
    """Receiver elevation mask plus scenario obstructions (cranes, buildings) near the quay."""
    el, az = np.degrees(elevation), np.degrees(azimuth)
    if el < scenario.elevation_mask_deg:
        return True
    near_quay = -antenna_ned[0] < scenario.mask_range_m
    if near_quay:
        for az_from, az_to, el_max in scenario.obstructions:
            if az_from <= az < az_to and el < el_max:
                return True
    return False


def simulate_gnss(
    scenario: Scenario,
    antenna_position_ned: Callable[[float, int], np.ndarray],
    nav: NavigationData,
    start_gpst: float,
    duration_s: float,
    seed: int,
    errors: GnssErrorModel | None = None,
    rate_hz: float = 1.0,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[list[list[GnssEpoch]], GnssTruth]:
    """Observations of the four receivers at ``rate_hz``.

    ``antenna_position_ned(t_rel, i)`` gives the true position of antenna i (0..3) in the
    scenario's local-level frame at ``t_rel`` seconds after the start.
    """
    errors = errors or GnssErrorModel()
    rng = np.random.default_rng(seed)
    lat, lon, h = scenario.origin_llh_deg
    origin = np.array([np.radians(lat), np.radians(lon), h])
    systems = scenario.constellations
    sats = [s for s in nav.satellites() if s[0] in systems]
    n_rx = 4
    n_epochs = int(round(duration_s * rate_hz)) + 1
    epoch_times = start_gpst + np.arange(n_epochs) / rate_hz

    # One receiver clock for the four receivers: bias integrates a random-walk drift.
    drift_steps = rng.normal(0, errors.clock_drift_random_walk, n_epochs - 1) / np.sqrt(rate_hz)
    drift = errors.clock_drift_s_per_s + np.concatenate([[0.0], np.cumsum(drift_steps)])
    bias_steps = 0.5 * (drift[1:] + drift[:-1]) / rate_hz
    bias = errors.clock_bias_s + np.concatenate([[0.0], np.cumsum(bias_steps)])
    hardware_delay = rng.normal(0.0, errors.hardware_delay_m, n_rx)

    # Per receiver and satellite: ambiguity, multipath, lock state; the world's errors.
    ambiguity: list[dict[str, int]] = [{} for _ in range(n_rx)]
    multipath = {(i, s): Multipath(errors, rng, n_epochs, 1.0 / rate_hz)
                 for i in range(n_rx) for s in sats}
    world = draw_world(errors, np.random.default_rng([seed, 1]), nav, sats, origin, start_gpst,
                       n_epochs, 1.0 / rate_hz,
                       scenario.start.timetuple().tm_yday)
    truth = GnssTruth(bias, drift, hardware_delay, ambiguity)
    out: list[list[GnssEpoch]] = [[] for _ in range(n_rx)]

    def geometry(sat: str, t_true: float, i: int):
        # The antenna is where it truly is at the true reception time, not at the time tag.
        ned = antenna_position_ned(t_true - start_gpst, i)
        return satellite_geometry(nav, sat, t_true, ned_to_ecef(ned, origin)), ned

    for e, t_tag in enumerate(epoch_times):
        dt_rx = bias[e]
        t_true = t_tag - dt_rx
        for i in range(n_rx):
            observations: dict[str, SatObservation] = {}
            for sat in sats:
                geo, ned = geometry(sat, t_true, i)
                if geo is None or is_masked(scenario, ned, geo.elevation, geo.azimuth):
                    ambiguity[i].pop(sat, None)  # loss of lock: a new ambiguity when it returns
                    continue
                lam = carrier_wavelength(sat, nav)
                lli = 0
                if sat not in ambiguity[i]:
                    ambiguity[i][sat] = int(rng.integers(-2_000_000, 2_000_000))
                    if e > 0:
                        lli = 1  # reacquired after loss of lock
                elif rng.random() < errors.slip_rate_per_epoch:
                    jump = int(rng.choice([-1, 1]) * rng.integers(1, 30))
                    ambiguity[i][sat] += jump
                    flagged = rng.random() >= errors.unflagged_slip_fraction
                    lli = 1 if flagged else 0
                    truth.slips.append((float(t_tag), i, sat, jump, flagged))
                llh = ecef_to_geodetic(ned_to_ecef(ned, origin))
                iono = world.ionosphere.slant(t_true, llh[0], llh[1], geo.elevation, geo.azimuth,
                                              lam)
                tropo = world.troposphere.slant(t_true, geo.elevation, geo.azimuth)
                sis = world.satellites[sat].range_error(t_true, e, geo.line_of_sight,
                                                        geo.sat_position, geo.sat_velocity)
                sin_el = max(np.sin(geo.elevation), 0.1)
                mp_code, mp_carrier = multipath[(i, sat)](e, geo.elevation)
                cn0 = 30.0 + 20.0 * np.sin(geo.elevation)  # dB-Hz
                phase_sigma = lam / (2 * np.pi) * np.sqrt(errors.pll_bandwidth_hz / 10**(cn0 / 10))
                clock_term = SPEED_OF_LIGHT * (dt_rx - geo.sat_clock_bias)
                common = geo.range + clock_term + sis + tropo + hardware_delay[i]
                code = common + iono + mp_code + rng.normal(0, errors.code_noise_m / sin_el)
                phase_m = common - iono + mp_carrier + rng.normal(0, phase_sigma)
                phase = phase_m / lam + ambiguity[i][sat]
                # Range rate from the same geometry a few ms apart (exact for the simulated motion).
                h = 0.01
                geo_a, _ = geometry(sat, t_true - h, i)
                geo_b, _ = geometry(sat, t_true + h, i)
                range_rate = (geo_b.range - geo_a.range) / (2 * h)
                rate = range_rate + SPEED_OF_LIGHT * (drift[e] - geo.sat_clock_drift)
                doppler = -rate / lam + rng.normal(0, errors.doppler_noise_hz)
                snr = cn0 + rng.normal(0, 1.0)
                observations[sat] = SatObservation(code, phase, doppler, float(snr), lli)
            out[i].append(GnssEpoch(float(t_tag), observations))
        if progress:
            progress(e + 1, n_epochs)
    return out, truth
