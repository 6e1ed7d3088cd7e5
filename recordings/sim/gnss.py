"""GNSS observables of the four compass receivers (the sensors of thesis table 15 and fig. 10,
``docs/references.md``).

Physics per antenna i, satellite k, receiver time tag t (all four receivers share ONE clock):
    P = rho + c (dt_rx - dt_sat) + I + T + d_i + mp_code + noise              [m]
    L = (rho + c (dt_rx - dt_sat) - I + T + d_i + mp_phase + noise) / lambda + N_i^k   [cycles]
    D = -(d/dt)(rho + c (dt_rx - dt_sat)) / lambda + noise                   [Hz]
rho is evaluated at the true reception time t - dt_rx (light time and Earth rotation inside
``satellite_geometry``). I and T are the same physical delays for all antennas (they cancel in
single differences, as on a real 10 cm array); d_i is each receiver's fixed hardware delay, so the
inter-receiver delay difference D_ij = d_i - d_j survives single differences.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from estimator.ephemeris import (
    carrier_wavelength,
    klobuchar_delay,
    satellite_geometry,
    troposphere_delay,
)
from estimator.frames import SPEED_OF_LIGHT, ecef_to_geodetic, ned_to_ecef
from estimator.records import GnssEpoch, NavigationData, SatObservation

from .scenarios import Scenario


@dataclass
class GnssErrorModel:
    """Error magnitudes of a single-frequency receiver (1-sigma unless stated)."""

    code_noise_m: float = 0.30  # at zenith, grows as 1/sin(el)
    phase_noise_m: float = 0.0015
    doppler_noise_hz: float = 0.03
    code_multipath_m: float = 0.6  # amplitude at low elevation, decays with elevation
    phase_multipath_m: float = 0.004
    multipath_decay_deg: float = 15.0
    clock_bias_s: float = 2.0e-4  # initial receiver clock bias
    clock_drift_s_per_s: float = 1.5e-7  # initial drift (TCXO)
    clock_drift_random_walk: float = 5.0e-11  # s/s per sqrt(s)
    hardware_delay_m: float = 0.15  # spread of the receivers' delays d_i
    slip_rate_per_epoch: float = 1.0 / 2500.0  # per satellite and receiver
    unflagged_slip_fraction: float = 0.3
    iono_scale: float = 1.0  # Klobuchar model scaled, plus a slow random variation

    @classmethod
    def perfect(cls) -> GnssErrorModel:
        """No noise, multipath or slips (for checking the geometry)."""
        return cls(code_noise_m=0.0, phase_noise_m=0.0, doppler_noise_hz=0.0, code_multipath_m=0.0,
                   phase_multipath_m=0.0, slip_rate_per_epoch=0.0)


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
    """Slowly varying reflection error of one antenna and satellite, larger at low elevation."""

    def __init__(self, errors: GnssErrorModel, rng: np.random.Generator) -> None:
        self.phase = rng.uniform(0, 2 * np.pi, 2)
        self.period = rng.uniform(40.0, 160.0, 2)
        self.amplitude = np.array([errors.code_multipath_m, errors.phase_multipath_m])
        self.decay = np.radians(errors.multipath_decay_deg)

    def __call__(self, t: float, elevation: float) -> tuple[float, float]:
        """(code, carrier) multipath errors in metres."""
        envelope = np.exp(-elevation / self.decay)
        code, carrier = self.amplitude * envelope * np.sin(2 * np.pi * t / self.period + self.phase)
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

    # Per receiver and satellite: ambiguity, multipath phase offsets, lock state.
    ambiguity: list[dict[str, int]] = [{} for _ in range(n_rx)]
    multipath = {(i, s): Multipath(errors, rng) for i in range(n_rx) for s in sats}
    iono_factor = {s: errors.iono_scale * rng.uniform(0.8, 1.2) for s in sats}
    truth = GnssTruth(bias, drift, hardware_delay, ambiguity)
    out: list[list[GnssEpoch]] = [[] for _ in range(n_rx)]

    def geometry(sat: str, t_true: float, i: int):
        # The antenna is where it truly is at the true reception time, not at the time tag.
        ned = antenna_position_ned(t_true - start_gpst, i)
        return satellite_geometry(nav, sat, t_true, ned_to_ecef(ned, origin)), ned

    for e, t_tag in enumerate(epoch_times):
        t_rel = t_tag - start_gpst
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
                iono = iono_factor[sat] * klobuchar_delay(nav.iono_alpha, nav.iono_beta, t_true,
                                                          llh[0], llh[1], geo.elevation,
                                                          geo.azimuth)
                tropo = troposphere_delay(geo.elevation, llh[2])
                sin_el = max(np.sin(geo.elevation), 0.1)
                mp_code, mp_carrier = multipath[(i, sat)](t_rel, geo.elevation)
                clock_term = SPEED_OF_LIGHT * (dt_rx - geo.sat_clock_bias)
                common = geo.range + clock_term + tropo + hardware_delay[i]
                code = common + iono + mp_code + rng.normal(0, errors.code_noise_m / sin_el)
                phase_m = common - iono + mp_carrier + rng.normal(0, errors.phase_noise_m / sin_el)
                phase = phase_m / lam + ambiguity[i][sat]
                # Range rate from the same geometry a few ms apart (exact for the simulated motion).
                h = 0.01
                geo_a, _ = geometry(sat, t_true - h, i)
                geo_b, _ = geometry(sat, t_true + h, i)
                range_rate = (geo_b.range - geo_a.range) / (2 * h)
                rate = range_rate + SPEED_OF_LIGHT * (drift[e] - geo.sat_clock_drift)
                doppler = -rate / lam + rng.normal(0, errors.doppler_noise_hz)
                snr = 30.0 + 20.0 * np.sin(geo.elevation) + rng.normal(0, 1.0)
                observations[sat] = SatObservation(code, phase, doppler, float(snr), lli)
            out[i].append(GnssEpoch(float(t_tag), observations))
        if progress:
            progress(e + 1, n_epochs)
    return out, truth
