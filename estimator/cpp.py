"""Carrier-phase processing, the CPP block (thesis 5.1.1, fig. 18; ``METHOD.md``).

From the raw L1 observations of the compass receivers this module produces:

- cycle-slip flags per receiver and satellite (LLI bit, Doppler vs phase rate, and the residual
  test of the velocity solutions), so that a slip never reaches a velocity or an attitude;
- the time-differenced carrier phase (TDCP) of each satellite between consecutive epochs,
  corrected for the satellite's motion and clock drift;
- ``v``: loosely coupled velocity of each receiver (3 velocity + 1 clock drift, ≥ 4 satellites);
- ``η``: the tightly coupled line-of-sight velocities ``η_i^k = λ·φ̇_i^k + v^k − Ẑ`` with ONE
  clock drift Ẑ shared by the receivers driven by the common clock, and their joint solution;
- ``ζ``: single differences ``ζ_ij^k = λ·Φ_ij^k − D̂_ij − λ·N_ij^k`` on the six baselines and the
  estimate of the inter-receiver delay difference ``D_ij``.

Sign conventions (all SI, ECEF unless a name says ``ned``):
- ``e^k`` is the unit vector from the receiver towards satellite k (``Geometry.line_of_sight``).
- Baselines: ``b_ij = r_j − r_i`` (from antenna i to antenna j). With ``Φ_ij = Φ_i − Φ_j`` the
  single difference is ``λ·Φ_ij^k = e^k·b_ij + D_ij + λ·N_ij^k`` (common clock: no clock term).
- Velocity: ``φ̇`` is the phase rate ΔΦ/Δt (cycles/s, grows with the range), ``Ẑ = c·ḋt_r`` the
  receiver clock drift (m/s) and ``u^k = −e^k`` the direction from satellite k to the antenna.
  Then ``η_i^k = u^k·v_i`` (the antenna velocity along the line of sight) and
  ``v^k = −(Δρ_sat − c·Δdt^k)/Δt`` is the satellite's own contribution to the range rate
  (its motion along the line of sight and its clock drift), so the thesis' equation holds as
  written with natural signs. An ``EtaRow.measured`` holds ``λ·φ̇ + v^k = η + Ẑ``: Ẑ is left in
  because the EKF estimates it as a state.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from .ephemeris import (
    Geometry,
    carrier_wavelength,
    klobuchar_delay,
    rotate_earth,
    satellite_geometry,
    satellite_state,
    select_ephemeris,
    troposphere_delay,
)
from .frames import (
    OMEGA_EARTH,
    SPEED_OF_LIGHT,
    WAVELENGTH_L1,
    C_ecef_to_level,
    ecef_to_geodetic,
)
from .records import GlonassEphemeris, GnssEpoch, KeplerEphemeris, NavigationData
from .spp import standalone_position

# The six baselines of the four-antenna square (thesis fig. 10), antenna indices 0..3.
BASELINE_PAIRS: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
# Systems whose L1 signal shares the 1575.42 MHz carrier: their single/double differences of
# different satellites can be combined (GLONASS FDMA and BeiDou B1I cannot).
SAME_CARRIER_SYSTEMS = "GEJ"

DEFAULT_SLIP_THRESHOLD = 0.5  # cycles/s, Doppler vs phase rate (real data: 0.06 σ, 0.3 max)
DEFAULT_PHASE_SIGMA_M = 0.003  # m, undifferenced carrier phase at zenith (noise + multipath)
DEFAULT_MAX_INTERVAL_S = 5.0  # longest epoch interval over which phase is differenced
NORMALISED_RESIDUAL_LIMIT = 4.0
MIN_SIN_ELEVATION = 0.1

# ----------------------------------------------------------------------------- epochs


def align_epochs(receivers: Sequence[Sequence[GnssEpoch]],
                 tolerance_s: float = 1e-3) -> list[tuple[float, list[GnssEpoch | None]]]:
    """Group the epochs of several receivers by time tag: ``[(time, [epoch or None per rx])]``.

    A receiver that missed an epoch gets None there, so callers see the dropout instead of a
    silently shifted list.
    """
    keyed: dict[int, list[GnssEpoch | None]] = {}
    for i, epochs in enumerate(receivers):
        for ep in epochs:
            key = int(round(ep.time / tolerance_s))
            keyed.setdefault(key, [None] * len(receivers))[i] = ep
    return [(key * tolerance_s, row) for key, row in sorted(keyed.items())]


def _phase(ep: GnssEpoch | None, sat: str) -> float:
    if ep is None or sat not in ep.satellites:
        return math.nan
    return ep.satellites[sat].carrier_phase


# -------------------------------------------------------------------------- geometry


@dataclass
class EpochGeometry:
    """Satellite geometry of one epoch seen from an approximate receiver (or array) position.

    Antennas a few decimetres apart share it: the line of sight differs by < 1e-8 rad.
    """

    time: float  # receiver time tag (gpst s)
    receiver_ecef: np.ndarray  # approximate position the geometry was computed for
    clock_bias_s: float  # receiver clock bias used to get the true reception time
    C_ecef_to_level: np.ndarray  # local NED at the receiver
    satellites: dict[str, Geometry]
    wavelengths: dict[str, float]
    rejected: dict[str, str] = field(default_factory=dict)  # sat → why it has no geometry
    # The broadcast ephemeris issue each geometry was computed from: differences between
    # epochs must use ONE issue, or the jump between issues (dm) becomes a velocity spike.
    ephemerides: dict[str, KeplerEphemeris | GlonassEphemeris] = field(default_factory=dict)

    def los_ned(self, sat: str) -> np.ndarray:
        """Unit vector receiver → satellite in the local NED frame."""
        return self.C_ecef_to_level @ self.satellites[sat].line_of_sight


def epoch_geometry(
    nav: NavigationData,
    sats: Iterable[str],
    time_tag: float,
    receiver_ecef: np.ndarray,
    clock_bias_s: float = 0.0,
    elevation_mask_deg: float = 10.0,
) -> EpochGeometry:
    """Geometry of ``sats`` at the true reception time ``time_tag − clock_bias_s``.

    Satellites without a usable ephemeris or below the mask are listed in ``rejected`` with the
    reason rather than raising: one bad ephemeris must not stop the others.
    """
    rx = np.asarray(receiver_ecef, dtype=float)
    llh = ecef_to_geodetic(rx)
    out = EpochGeometry(time=time_tag, receiver_ecef=rx, clock_bias_s=clock_bias_s,
                        C_ecef_to_level=C_ecef_to_level(llh[0], llh[1]), satellites={},
                        wavelengths={})
    mask = math.radians(elevation_mask_deg)
    t_receive = time_tag - clock_bias_s
    for sat in sats:
        if sat in out.satellites or sat in out.rejected:
            continue
        try:
            lam = carrier_wavelength(sat, nav)
        except ValueError:
            out.rejected[sat] = "unknown carrier frequency"
            continue
        eph = select_ephemeris(nav, sat, t_receive)  # the one satellite_geometry will use
        geo = satellite_geometry(nav, sat, t_receive, rx) if eph is not None else None
        if geo is None:
            out.rejected[sat] = "no ephemeris"
            continue
        if geo.elevation < mask:
            out.rejected[sat] = "below elevation mask"
            continue
        out.satellites[sat] = geo
        out.wavelengths[sat] = lam
        out.ephemerides[sat] = eph
    return out


def range_with_ephemeris(eph: KeplerEphemeris | GlonassEphemeris, geo: Geometry,
                         t_receive: float, receiver_ecef: np.ndarray) -> tuple[float, float]:
    """(range m, satellite clock s) of the signal described by ``geo`` (received at true gpst
    ``t_receive``) recomputed with another ephemeris issue; same flight time (the issues
    differ by metres at most, i.e. nanoseconds of flight)."""
    st = satellite_state(eph, t_receive, -geo.flight_time)
    pos = rotate_earth(st.position, OMEGA_EARTH * geo.flight_time)
    return float(np.linalg.norm(pos - np.asarray(receiver_ecef))), st.clock_bias


def elevation_sigma(sigma_zenith: float, elevation: float) -> float:
    """σ of a carrier-phase observable at ``elevation`` (rad) from its zenith σ: noise and
    multipath grow as 1/sin(elevation), floored at ``MIN_SIN_ELEVATION``."""
    return sigma_zenith / max(math.sin(elevation), MIN_SIN_ELEVATION)


# ------------------------------------------------------------------------ cycle slips


def detect_cycle_slips(
    prev_epochs: Sequence[GnssEpoch | None],
    curr_epochs: Sequence[GnssEpoch | None],
    *,
    threshold_cycles_per_s: float = DEFAULT_SLIP_THRESHOLD,
    max_interval_s: float = DEFAULT_MAX_INTERVAL_S,
    common_clock: bool = True,
) -> dict[tuple[int, str], str]:
    """Receivers/satellites whose carrier phase does NOT continue from the previous epoch.

    Returns ``{(receiver, sat): reason}`` for every satellite with a phase at the current epoch
    that cannot be differenced with the previous one: not tracked before, LLI set, epoch flag,
    interval too long, or the phase rate ΔΦ/Δt disagreeing with the mean Doppler over the
    interval by more than ``threshold_cycles_per_s``. The receiver clock's high-frequency noise
    enters the phase rate and the Doppler differently and is common to all satellites of a
    clock, so the median disagreement is removed first (over all receivers when they share one
    clock) — that is also what keeps a receiver clock jump from being taken for slips.
    """
    broken: dict[tuple[int, str], str] = {}
    candidates: list[tuple[int, str, float]] = []  # receiver, sat, disagreement (cycles/s)
    groups: dict[int, list[float]] = {}
    for i, (prev, curr) in enumerate(zip(prev_epochs, curr_epochs, strict=True)):
        if curr is None:
            continue
        sats = [s for s, o in curr.satellites.items() if math.isfinite(o.carrier_phase)]
        if prev is None:
            for s in sats:
                broken[(i, s)] = "no previous epoch"
            continue
        dt = curr.time - prev.time
        for s in sats:
            ob = curr.satellites[s]
            p0 = _phase(prev, s)
            if curr.flag != 0:
                broken[(i, s)] = f"epoch flag {curr.flag}"
            elif not 0.0 < dt <= max_interval_s:
                broken[(i, s)] = f"interval {dt:.1f} s too long"
            elif not math.isfinite(p0):
                broken[(i, s)] = "not tracked at the previous epoch"
            elif ob.lli & 1:
                broken[(i, s)] = "loss of lock (LLI)"
            else:
                d0 = prev.satellites[s].doppler
                dops = [d for d in (d0, ob.doppler) if math.isfinite(d)]
                if dops:
                    # Doppler is −range rate / λ: the mean over the interval predicts −ΔΦ/Δt.
                    disagreement = (ob.carrier_phase - p0) / dt + sum(dops) / len(dops)
                    candidates.append((i, s, disagreement))
                    groups.setdefault(0 if common_clock else i, []).append(disagreement)
    common = {}
    for g, values in groups.items():
        # Fewer than 3 satellites cannot separate the clock from a slip: no removal, and a
        # doubled threshold below so that clock noise alone raises no alarm.
        common[g] = float(np.median(values)) if len(values) >= 3 else 0.0
    for i, s, disagreement in candidates:
        g = 0 if common_clock else i
        limit = threshold_cycles_per_s * (1.0 if len(groups[g]) >= 3 else 2.0)
        residual = disagreement - common[g]
        if abs(residual) > limit:
            broken[(i, s)] = f"Doppler/phase-rate mismatch {residual:+.2f} cycle/s"
    return broken


# ------------------------------------------------------------------ TDCP and η rows


@dataclass(frozen=True)
class EtaRow:
    """One line-of-sight velocity observation of antenna ``antenna`` towards satellite ``sat``.

    Model: ``measured = los·v_antenna + Ẑ`` (m/s), i.e. ``η = measured − Ẑ``; ``los`` is the unit
    vector from the satellite to the antenna. It is the mean over ``[time − interval, time]``.
    """

    antenna: int
    sat: str
    los_ecef: np.ndarray
    los_ned: np.ndarray
    measured: float  # λ·φ̇ + v^k, m/s
    sigma: float  # m/s
    elevation: float  # rad
    time: float  # end of the interval (time tag)
    interval: float  # s


@dataclass
class EtaSet:
    time: float
    rows: list[EtaRow]
    rejected: dict[tuple[int, str], str]  # (antenna, sat) → why no row

    def for_antenna(self, antenna: int) -> list[EtaRow]:
        return [r for r in self.rows if r.antenna == antenna]

    def satellites(self) -> list[str]:
        return sorted({r.sat for r in self.rows})


def eta_observations(
    prev_epochs: Sequence[GnssEpoch | None],
    curr_epochs: Sequence[GnssEpoch | None],
    prev_geometry: EpochGeometry | Sequence[EpochGeometry | None],
    curr_geometry: EpochGeometry | Sequence[EpochGeometry | None],
    *,
    slips: Mapping[tuple[int, str], str] | None = None,
    phase_sigma_m: float = DEFAULT_PHASE_SIGMA_M,
    slip_threshold_cycles_per_s: float = DEFAULT_SLIP_THRESHOLD,
    common_clock: bool = True,
) -> EtaSet:
    """Time-differenced carrier phase of every antenna and satellite as ``η`` rows.

    One geometry serves all antennas of the array (pass one ``EpochGeometry``), or one per
    receiver. The geometry of each epoch is computed at that epoch's approximate position r̃;
    the TDCP term ``y = λΔΦ − [ρ(r̃₂,t₂) − ρ(r̃₁,t₁)] − e₂·(r̃₂ − r̃₁) + cΔdt^k`` then equals
    ``u₂·Δr + cΔdt_r`` to second order in the position errors (< 1 µm for metre-level SPP).
    ``slips`` (from :func:`detect_cycle_slips`) is computed here when not given.
    """
    n = len(curr_epochs)
    prev_geos = _per_receiver(prev_geometry, n)
    curr_geos = _per_receiver(curr_geometry, n)
    if slips is None:
        slips = detect_cycle_slips(prev_epochs, curr_epochs, common_clock=common_clock,
                                   threshold_cycles_per_s=slip_threshold_cycles_per_s)
    rows: list[EtaRow] = []
    rejected: dict[tuple[int, str], str] = {}
    time = math.nan
    for i in range(n):
        prev, curr = prev_epochs[i], curr_epochs[i]
        g1, g2 = prev_geos[i], curr_geos[i]
        if curr is None:
            continue
        time = curr.time
        for sat, ob in curr.satellites.items():
            if not math.isfinite(ob.carrier_phase):
                continue
            key = (i, sat)
            if key in slips:
                rejected[key] = slips[key]
                continue
            if prev is None or g1 is None or g2 is None or abs(g1.time - prev.time) > 1e-6 \
                    or abs(g2.time - curr.time) > 1e-6:
                rejected[key] = "no geometry for the interval"
                continue
            if sat not in g2.satellites or sat not in g1.satellites:
                rejected[key] = g2.rejected.get(sat) or g1.rejected.get(sat) or "no geometry"
                continue
            a, b = g1.satellites[sat], g2.satellites[sat]
            range_a, clock_a = a.range, a.sat_clock_bias
            eph = g2.ephemerides.get(sat)
            if eph is not None and g1.ephemerides.get(sat) is not eph:
                # A new ephemeris issue between the epochs: redo the old end with the new one.
                range_a, clock_a = range_with_ephemeris(eph, a, g1.time - g1.clock_bias_s,
                                                        g1.receiver_ecef)
            lam = g2.wavelengths[sat]
            dt = curr.time - prev.time
            d_phase_m = lam * (ob.carrier_phase - prev.satellites[sat].carrier_phase)
            # Satellite motion (incl. Earth rotation) and clock, receiver displacement left in.
            sat_term = (b.range - range_a) + b.line_of_sight @ (g2.receiver_ecef - g1.receiver_ecef)
            sat_clock = SPEED_OF_LIGHT * (b.sat_clock_bias - clock_a)
            y = d_phase_m - sat_term + sat_clock
            u = -b.line_of_sight
            sigma = elevation_sigma(math.sqrt(2.0) * phase_sigma_m, b.elevation) / dt
            rows.append(EtaRow(antenna=i, sat=sat, los_ecef=u, los_ned=g2.C_ecef_to_level @ u,
                               measured=y / dt, sigma=sigma, elevation=b.elevation,
                               time=curr.time, interval=dt))
    return EtaSet(time=time, rows=rows, rejected=rejected)


# One receiver's ranges changing, from one epoch to the next, by more than this against the
# other receivers' (the same satellites; antennas 10 cm apart differ by centimetres): a step
# of its own clock or front end, not motion
RECEIVER_STEP_M = 1.0
RECEIVER_STEP_SPREAD = 0.05  # ... by the same on its satellites, to this fraction (a clock)


def receiver_steps(prev_epochs: Sequence[GnssEpoch | None],
                   curr_epochs: Sequence[GnssEpoch | None],
                   nav: NavigationData | None = None) -> dict[int, float]:
    """Receivers whose carrier-phase ranges all stepped since the previous epoch against the
    other receivers' on the same satellites (m, the median over their satellites):
    receiver → step. A common clock is the same for all, and the antennas 10 cm apart change
    by centimetres: one receiver's step is its own clock or front end. Needs three receivers
    on a satellite, so that the others outvote the one that is off, and the same step on its
    satellites (cycle slips move each its own way). (Every satellite of it is then a "slip"
    to ``detect_cycle_slips``: this says they are one fault.)"""
    by_sat: dict[str, dict[int, float]] = {}
    for i, (prev, curr) in enumerate(zip(prev_epochs, curr_epochs, strict=True)):
        if prev is None or curr is None:
            continue
        for sat, ob in curr.satellites.items():
            p0 = _phase(prev, sat)
            if math.isfinite(p0) and math.isfinite(ob.carrier_phase):
                by_sat.setdefault(sat, {})[i] = (ob.carrier_phase - p0) \
                    * carrier_wavelength(sat, nav)
    diffs: dict[int, list[float]] = {}
    for seen in by_sat.values():
        if len(seen) < 3:
            continue
        middle = float(np.median(list(seen.values())))  # a good receiver's, or between two
        for i, v in seen.items():
            diffs.setdefault(i, []).append(v - middle)
    out = {}
    for i, d in diffs.items():
        if len(d) < 4:
            continue
        step = float(np.median(d))
        # the same on every satellite: a clock; cycle slips (1–30 cycles each, unflagged)
        # move each satellite its own way (the campaign's cycle-slip fault was named a step)
        spread = float(np.median(np.abs(np.asarray(d) - step)))
        if abs(step) > RECEIVER_STEP_M and spread < RECEIVER_STEP_SPREAD * abs(step):
            out[i] = step
    return out


def velocity_map(rows: Sequence[EtaRow], C_ecef_to_level: np.ndarray, rate_sigma: float,
                 min_satellites: int = 4) -> tuple[list[str], np.ndarray] | None:
    """The satellites of ``rows`` and what an error of each one's range rate does to the
    rows' weighted least-squares velocity (NED, with the clock drift): 3 x n m/s per m/s.
    One row per satellite — its antennas, 10 cm apart, share the error (the atmosphere's,
    the signal's). None with fewer than ``min_satellites`` (4: the velocity and the clock
    drift)."""
    by_sat: dict[str, list[EtaRow]] = {}
    for r in rows:
        by_sat.setdefault(r.sat, []).append(r)
    if len(by_sat) < max(min_satellites, 4):
        return None
    sats = list(by_sat)
    H = np.array([np.append(C_ecef_to_level @ by_sat[s][0].los_ecef, 1.0) for s in sats])
    w = np.array([1.0 / (np.mean([r.sigma**2 for r in by_sat[s]]) / len(by_sat[s])
                         + rate_sigma**2) for s in sats])
    Hw = H * w[:, None]
    return sats, np.linalg.solve(H.T @ Hw, Hw.T)[:3]


def origin_sensitivity(rows: Sequence[EtaRow], prev: EpochGeometry, curr: EpochGeometry,
                       C_ecef_to_level: np.ndarray, rate_sigma: float) -> np.ndarray:
    """The velocity (NED, m/s) the rows' least-squares solution takes per metre (NED) of error
    of the point both geometries were computed at (3 x 3; zero without enough satellites).

    The satellite term of a row is the range change seen from that point: an error δ of it
    adds ``(e₂ − e₁)·δ / Δt`` to the row, e the unit vector towards the satellite at each end
    (its line of sight turns ~1.5·10⁻⁴ rad/s). A standalone fix metres off therefore drifts
    the carrier-phase trajectory by ~0.1 mm/s per metre — for as long as it is used."""
    kept = [r for r in rows if r.sat in prev.satellites and r.sat in curr.satellites]
    found = velocity_map(kept, C_ecef_to_level, rate_sigma, min_satellites=5)
    if found is None:
        return np.zeros((3, 3))
    sats, L = found
    interval = kept[0].interval
    D = np.array([C_ecef_to_level @ (curr.satellites[s].line_of_sight
                                     - prev.satellites[s].line_of_sight) / interval
                  for s in sats])
    return L @ D


@dataclass
class CorrelatedDrift:
    """The trajectory error that the satellites' correlated range-rate errors integrate to.

    The EKF takes each epoch's TDCP rate error as white, but the atmosphere's residual and
    the signal's fluctuation stay correlated over tens of seconds, and the carrier-phase
    trajectory integrates them: on the real static pair the drift grows about 5x from 30 s
    to 300 s, where white rate noise would grow it 3x. Model: each satellite's error a
    first-order Gauss–Markov process (``sigma_mps``, ``tau_s``) common to its antennas,
    through each epoch's least-squares velocity map (``velocity_map``); this keeps the
    covariance of the integrated error and its cross-covariance with each satellite's current
    error (a satellite that sets takes its correlation with it). ``sigma_mps`` and ``tau_s``:
    fitted to the real static pair (``benchmarks/calibration.py``, one receiver alone, the
    1-σ of its horizontal drift over windows of 30–180 s within 15 %) — a quiet day: on a
    more active one the errors are larger, and ``interval`` takes them scaled by the
    activity measured (``AtmosphereActivity``)."""

    sigma_mps: float = 0.0005
    tau_s: float = 30.0
    cov: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    _cross: dict[str, np.ndarray] = field(default_factory=dict)

    def interval(self, sats: Sequence[str], L: np.ndarray, dt: float,
                 scale: float = 1.0) -> None:
        """One interval of ``dt`` s whose velocity took the satellites' errors through
        ``L`` (3 x n, ``velocity_map``), their σ ``scale`` times the quiet day's."""
        rho = math.exp(-dt / self.tau_s)
        var = (scale * self.sigma_mps) ** 2
        cross = {s: rho * c for s, c in self._cross.items() if s in sats}
        for j, s in enumerate(sats):
            lever = L[:, j] * dt
            c = cross.get(s, np.zeros(3))
            self.cov += np.outer(lever, c) + np.outer(c, lever) + var * np.outer(lever, lever)
            cross[s] = c + var * lever
        self._cross = cross


# The real static pair's rate error common to a satellite's antennas, beyond the phase noise:
# 0.7-2.5 mm/s per satellite (``benchmarks/calibration.py``), the day ``CorrelatedDrift`` was
# fitted on. More than this in the epochs' fits: a more active atmosphere.
QUIET_SCATTER_MPS = 0.0015


@dataclass
class AtmosphereActivity:
    """How active the atmosphere and the signals are against the quiet day the drift model
    was fitted on: the epochs' TDCP scatter (``TdcpFit.scatter``, what the satellites' common
    rate errors leave after the fit), its RMS over ``tau_s``, over ``QUIET_SCATTER_MPS``, not
    below 1. The fit cannot see the errors' slow part (it moves the trajectory), but in the
    simulated world and, by their physics, in the real one both come with the same
    irregularities: of nine small-boat seeds, the three whose trajectories drifted 4-13x
    their σ were the three whose scatter was 3.8-9.8 mm/s RMS, against 0.1-1.0 for the six
    others (``benchmarks/position_consistency.py``)."""

    tau_s: float = 30.0
    _mean_square: float | None = None

    def add(self, scatter_mps: float, dt: float) -> None:
        """One epoch's fit scatter, ``dt`` s after the last."""
        x = scatter_mps**2
        if self._mean_square is None:
            self._mean_square = x
        else:
            w = 1.0 - math.exp(-max(dt, 0.0) / self.tau_s)
            self._mean_square += w * (x - self._mean_square)

    @property
    def scale(self) -> float:
        """The errors' σ against the quiet day's (≥ 1)."""
        if self._mean_square is None:
            return 1.0
        return max(1.0, math.sqrt(self._mean_square) / QUIET_SCATTER_MPS)


def atmosphere_corrected(rows: Sequence[EtaRow], prev: EpochGeometry, curr: EpochGeometry,
                         nav: NavigationData, receiver_llh: np.ndarray) -> list[EtaRow]:
    """``rows`` with the modelled change of the tropospheric and ionospheric delays over the
    interval ``prev`` → ``curr`` removed (mm/s for a low satellite: the delays grow as it
    sets). The models are the broadcast Klobuchar ionosphere (when ``nav`` has its parameters)
    and the standard-atmosphere troposphere at ``receiver_llh`` (rad, rad, m)."""
    lat, lon, h = (float(x) for x in receiver_llh)
    cache: dict[str, float] = {}
    out = []
    for r in rows:
        if r.sat not in cache:
            a, b = prev.satellites[r.sat], curr.satellites[r.sat]
            d_tropo = troposphere_delay(b.elevation, h) - troposphere_delay(a.elevation, h)
            d_iono = 0.0
            if nav.iono_alpha is not None and nav.iono_beta is not None:
                scale = (curr.wavelengths[r.sat] / WAVELENGTH_L1) ** 2
                d_iono = scale * (
                    klobuchar_delay(nav.iono_alpha, nav.iono_beta, curr.time, lat, lon,
                                    b.elevation, b.azimuth)
                    - klobuchar_delay(nav.iono_alpha, nav.iono_beta, prev.time, lat, lon,
                                      a.elevation, a.azimuth))
            cache[r.sat] = (d_tropo - d_iono) / r.interval  # phase: +T, −I
        out.append(replace(r, measured=r.measured - cache[r.sat]))
    return out


def _per_receiver(geo: EpochGeometry | Sequence[EpochGeometry | None], n: int
                  ) -> list[EpochGeometry | None]:
    if isinstance(geo, EpochGeometry):
        return [geo] * n
    geos = list(geo)
    if len(geos) != n:
        raise ValueError(f"{len(geos)} geometries for {n} receivers")
    return geos


# ------------------------------------------------------------ weighted least squares


@dataclass
class _Fit:
    x: np.ndarray
    cov: np.ndarray
    residuals: np.ndarray  # of the kept observation rows (not of the priors)
    kept: list[int]
    dropped: list[int]


def _robust_wls(H: np.ndarray, y: np.ndarray, sigma: np.ndarray, n_prior: int,
                limit: float = NORMALISED_RESIDUAL_LIMIT) -> _Fit | None:
    """WLS with the w-test: drop the worst observation and re-solve while redundancy remains.

    The last ``n_prior`` rows are pseudo-observations (priors) that are never dropped. None when
    the kept rows (with the priors) do not determine every unknown.
    """
    m = H.shape[1]
    n_obs = len(y) - n_prior
    keep = list(range(n_obs))
    dropped: list[int] = []
    prior = list(range(n_obs, len(y)))
    while True:
        idx = keep + prior
        A = H[idx] / sigma[idx, None]
        b = y[idx] / sigma[idx]
        N = A.T @ A
        if len(idx) < m or np.linalg.cond(N) > 1e12:
            return None
        cov = np.linalg.inv(N)
        x = cov @ (A.T @ b)
        v = y[idx] - H[idx] @ x
        dof = len(idx) - m
        if dof >= 1 and keep:
            Hk = H[keep]
            qvv = sigma[keep] ** 2 - np.einsum("ij,jk,ik->i", Hk, cov, Hk)
            w = np.abs(v[: len(keep)]) / np.sqrt(np.maximum(qvv, 1e-12 * sigma[keep] ** 2))
            worst = int(np.argmax(w))
            if w[worst] > limit:
                dropped.append(keep.pop(worst))
                continue
        return _Fit(x=x, cov=cov, residuals=v[: len(keep)], kept=keep, dropped=dropped)


# --------------------------------------------------------------- loosely coupled v


@dataclass
class ReceiverVelocity:
    """Loosely coupled TDCP velocity of one receiver (mean over the epoch interval)."""

    time: float  # end of the interval (time tag)
    interval_s: float
    antenna: int
    velocity_ecef: np.ndarray
    velocity_ned: np.ndarray
    clock_drift_mps: float  # Ẑ = c·(receiver clock drift)
    covariance_ned: np.ndarray  # 3x3, m²/s²
    satellites: list[str]
    excluded: dict[str, str]  # sat → why it was not used (slip, ephemeris, residual test)
    residual_rms_mps: float


MIN_FIT_SATELLITES = 6  # the fit's own outlier test and scatter need a few beyond its 4 unknowns
FIT_UNKNOWNS = 4  # velocity and clock drift


@dataclass(frozen=True)
class TdcpFit:
    """The satellites' agreement in one epoch's η innovations (measured − predicted, m/s):
    the common correction they ask for and their scatter about it (``tdcp_fit``)."""

    correction: np.ndarray  # (4,) velocity (3, L, m/s, the sign of the innovations) and clock
    covariance: np.ndarray  # (4,4) of ``correction``
    scatter: float  # m/s, rate error common to a satellite's antennas beyond the phase noise
    satellites: int


def robust_lsq(A: np.ndarray, y: np.ndarray, min_rows: int
               ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray] | None:
    """Least squares y ≈ A x, then again without the rows beyond 3 robust σ of the first fit
    (while ``min_rows`` remain): x, (AᵀA)⁻¹ of the rows kept, the residuals' robust σ
    (dof-corrected) and the mask of the rows kept; None with fewer than ``min_rows`` rows."""
    n_x = A.shape[1]
    if len(y) < max(min_rows, n_x + 1):
        return None
    keep = np.ones(len(y), bool)
    spread = 0.0
    for _ in range(2):
        x = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
        r = np.abs(y - A @ x)
        n = int(keep.sum())
        spread = 1.4826 * float(np.median(r[keep])) * math.sqrt(n / (n - n_x))
        again = r <= 3.0 * max(spread, 1e-9)
        if again.sum() < min_rows:
            break
        keep = again
    x = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
    return x, np.linalg.inv(A[keep].T @ A[keep]), spread, keep


def tdcp_fit(sats: Sequence[str], innovation: np.ndarray, los: np.ndarray,
             sigma: np.ndarray, unknown_scatter: float = 0.0) -> TdcpFit | None:
    """Fit one epoch's η innovations (one per row: its satellite, ``los`` and phase-noise
    ``sigma``; averaged over a satellite's antennas) with a common velocity and clock
    correction. None with fewer satellites than the 4 unknowns.

    The correction is what the satellites, agreeing among themselves, say the INS's
    prediction is off by. The scatter is the rate error common to a satellite's antennas
    beyond the phase noise: the atmosphere and the signal (satellite clock, scintillation)
    change the range of antennas 10 cm apart alike and come in bursts — a fixed σ then
    weighs a burst's satellites four times over and lets them pull the velocity until the
    gate locks the rest out. With ``MIN_FIT_SATELLITES`` or more the fit is robust
    (``robust_lsq``: an outlier dropped, the scatter measured); with fewer (4–5: a street of
    buildings) it is plain, its scatter ``unknown_scatter`` (the filter's configured rate σ)
    and it cannot tell a bad satellite from a bad INS — still the INS must be checked, or
    its rows are gated out one by one while it runs away."""
    names = sorted(set(sats))
    if len(names) < FIT_UNKNOWNS:
        return None
    sats = np.asarray(sats)
    y = np.array([np.mean(innovation[sats == s]) for s in names])
    A = np.array([[*np.mean(los[sats == s], axis=0), 1.0] for s in names]).reshape(-1, 4)
    noise = float(np.mean([np.mean(sigma[sats == s] ** 2) / np.sum(sats == s) for s in names]))
    if len(names) < MIN_FIT_SATELLITES:
        x = np.linalg.lstsq(A, y, rcond=None)[0]
        var = noise + unknown_scatter**2
        return TdcpFit(x, np.linalg.pinv(A.T @ A) * var, unknown_scatter, len(names))
    fit = robust_lsq(A, y, MIN_FIT_SATELLITES)
    if fit is None:
        return None
    x, inv, spread, keep = fit
    return TdcpFit(x, inv * max(spread**2, noise), math.sqrt(max(spread**2 - noise, 0.0)),
                   int(keep.sum()))


def loose_velocity(rows: Sequence[EtaRow], C_ecef_to_level: np.ndarray | None = None,
                   excluded: Mapping[str, str] | None = None) -> ReceiverVelocity | None:
    """WLS of 3 velocity + 1 clock drift from one antenna's rows (≥ 4 satellites).

    A slip the Doppler test missed shows as one large residual: it is dropped and the solution
    re-computed (w-test), so it does not become a velocity spike. None with < 4 satellites.
    """
    rows = list(rows)
    excluded = dict(excluded or {})
    if len({r.antenna for r in rows}) > 1:
        raise ValueError("loose_velocity takes the rows of ONE antenna")
    if len(rows) < 4:
        return None
    H = np.array([[*r.los_ecef, 1.0] for r in rows])
    y = np.array([r.measured for r in rows])
    sigma = np.array([r.sigma for r in rows])
    fit = _robust_wls(H, y, sigma, n_prior=0)
    if fit is None:
        return None
    for k in fit.dropped:
        excluded[rows[k].sat] = "velocity residual test"
    if C_ecef_to_level is None:
        # The row's NED line of sight encodes the local frame: C = (los_ned) (los_ecef)^+.
        U = np.array([r.los_ecef for r in rows])
        V = np.array([r.los_ned for r in rows])
        C_ecef_to_level = np.linalg.lstsq(U, V, rcond=None)[0].T
    v_ecef = fit.x[:3]
    C = C_ecef_to_level
    return ReceiverVelocity(
        time=rows[0].time, interval_s=rows[0].interval, antenna=rows[0].antenna,
        velocity_ecef=v_ecef, velocity_ned=C @ v_ecef, clock_drift_mps=float(fit.x[3]),
        covariance_ned=C @ fit.cov[:3, :3] @ C.T,
        satellites=[rows[k].sat for k in fit.kept], excluded=excluded,
        residual_rms_mps=float(np.sqrt(np.mean(fit.residuals**2))) if len(fit.residuals) else 0.0,
    )


def tdcp_velocity(
    prev: GnssEpoch,
    curr: GnssEpoch,
    nav: NavigationData,
    *,
    receiver_ecef: np.ndarray | None = None,
    clock_bias_s: float | None = None,
    elevation_mask_deg: float = 10.0,
    systems: str = "GEJRC",
    phase_sigma_m: float = DEFAULT_PHASE_SIGMA_M,
) -> ReceiverVelocity | None:
    """Velocity of one receiver from two epochs (convenience wrapper of the steps above).

    Position and clock bias default to the standalone solution of ``curr`` (metre level is
    enough for the line of sight). Satellites skipped are in ``ReceiverVelocity.excluded``.
    """
    if receiver_ecef is None or clock_bias_s is None:
        spp = standalone_position(curr, nav, elevation_mask_deg=elevation_mask_deg)
        if spp is None:
            return None
        receiver_ecef = spp.position if receiver_ecef is None else receiver_ecef
        clock_bias_s = spp.clock_bias_m / SPEED_OF_LIGHT if clock_bias_s is None else clock_bias_s
    sats = [s for s in curr.satellites if s[0] in systems]
    g1 = epoch_geometry(nav, sats, prev.time, receiver_ecef, clock_bias_s, elevation_mask_deg)
    g2 = epoch_geometry(nav, sats, curr.time, receiver_ecef, clock_bias_s, elevation_mask_deg)
    eta = eta_observations([prev], [curr], g1, g2, phase_sigma_m=phase_sigma_m,
                           common_clock=False)
    excluded = {s: why for (_, s), why in eta.rejected.items() if s[0] in systems}
    return loose_velocity(eta.rows, g2.C_ecef_to_level, excluded)


def receiver_velocities(
    epochs: Sequence[GnssEpoch],
    nav: NavigationData,
    *,
    systems: str = SAME_CARRIER_SYSTEMS,
    elevation_mask_deg: float = 10.0,
    correct_atmosphere: bool = True,
) -> list[ReceiverVelocity]:
    """TDCP velocity of ONE receiver over its consecutive epochs (its own position and clock).

    Each epoch's geometry is computed at its standalone position and clock bias (chained from
    the previous fix); with ``correct_atmosphere`` the rows are corrected as in the fusion
    (:func:`atmosphere_corrected`). An epoch without a standalone fix or without a velocity
    solution is skipped (the next interval starts after it).
    """
    out: list[ReceiverVelocity] = []
    prev = prev_geo = position = None
    for epoch in epochs:
        epoch = GnssEpoch(epoch.time, {s: o for s, o in epoch.satellites.items()
                                       if s[0] in systems}, epoch.flag)
        spp = standalone_position(epoch, nav, elevation_mask_deg=elevation_mask_deg,
                                  initial_ecef=position)
        if spp is None:
            prev = prev_geo = None
            continue
        position = spp.position
        geo = epoch_geometry(nav, list(epoch.satellites), epoch.time, position,
                             spp.clock_bias_m / SPEED_OF_LIGHT, elevation_mask_deg)
        if prev_geo is not None:
            rows = eta_observations([prev], [epoch], prev_geo, geo, common_clock=False).rows
            if correct_atmosphere:
                rows = atmosphere_corrected(rows, prev_geo, geo, nav, ecef_to_geodetic(position))
            v = loose_velocity(rows, geo.C_ecef_to_level)
            if v is not None:
                out.append(v)
        prev, prev_geo = epoch, geo
    return out


# --------------------------------------------------------------- tightly coupled η


@dataclass
class ArrayVelocity:
    """Velocity of the array reference point and the common clock drift from all η rows."""

    time: float
    velocity_ned: np.ndarray
    clock_drift_mps: float  # Ẑ, shared by the receivers
    covariance: np.ndarray  # 4x4 over (v_n, v_e, v_d, Ẑ)
    satellites: list[str]
    antennas: list[int]
    n_rows: int
    excluded: dict[tuple[int, str], str]
    residual_rms_mps: float


def _lever_velocity_ned(rows: Sequence[EtaRow], lever_arms_body: np.ndarray | None,
                        C_body_to_level: np.ndarray | None, omega_body: np.ndarray | None
                        ) -> np.ndarray:
    """u·(C (ω × l_i)) per row: the part of η due to the rotation of the array."""
    if lever_arms_body is None or omega_body is None:
        return np.zeros(len(rows))
    C = np.eye(3) if C_body_to_level is None else np.asarray(C_body_to_level)
    levers = np.asarray(lever_arms_body, dtype=float)
    v_rot = (C @ np.cross(np.asarray(omega_body, dtype=float), levers).T).T  # (n_ant, 3)
    return np.array([r.los_ned @ v_rot[r.antenna] for r in rows])


def tight_velocity(
    rows: Sequence[EtaRow],
    *,
    lever_arms_body: np.ndarray | None = None,
    C_body_to_level: np.ndarray | None = None,
    omega_body: np.ndarray | None = None,
    clock_drift_prior: tuple[float, float] | None = None,
    velocity_prior_ned: tuple[np.ndarray, np.ndarray] | None = None,
) -> ArrayVelocity | None:
    """Joint WLS of the array velocity (NED) and ONE clock drift Ẑ from all antennas' η.

    Antenna i moves at ``v + C_body_to_level (ω × l_i)`` with ``l_i`` its lever arm from the
    array reference point (``lever_arms_body``, rows by antenna index) and ``ω`` the body rate,
    e.g. from the gyro. Because Ẑ is common, satellites seen by different receivers add up
    (thesis table 21): 4 satellites in total suffice even if each receiver tracks only one.
    With fewer, priors make the problem solvable: ``clock_drift_prior = (Ẑ, σ)`` from a short
    filter, ``velocity_prior_ned = (v, σ per axis)`` (σ = inf for an unconstrained axis).
    The w-test drops one row at a time while redundancy remains: a slip of one receiver on one
    satellite disagrees with the three other antennas' rows and is caught.
    """
    rows = list(rows)
    if not rows:
        return None
    rot = _lever_velocity_ned(rows, lever_arms_body, C_body_to_level, omega_body)
    H = [[*r.los_ned, 1.0] for r in rows]
    y = [r.measured - rot[k] for k, r in enumerate(rows)]
    sigma = [r.sigma for r in rows]
    n_prior = 0
    if clock_drift_prior is not None:
        H.append([0.0, 0.0, 0.0, 1.0])
        y.append(float(clock_drift_prior[0]))
        sigma.append(float(clock_drift_prior[1]))
        n_prior += 1
    if velocity_prior_ned is not None:
        v0, s0 = (np.asarray(a, dtype=float) for a in velocity_prior_ned)
        for axis in range(3):
            if math.isfinite(s0[axis]):
                row = [0.0, 0.0, 0.0, 0.0]
                row[axis] = 1.0
                H.append(row)
                y.append(float(v0[axis]))
                sigma.append(float(s0[axis]))
                n_prior += 1
    fit = _robust_wls(np.array(H), np.array(y), np.array(sigma), n_prior)
    if fit is None:
        return None
    excluded = {(rows[k].antenna, rows[k].sat): "velocity residual test" for k in fit.dropped}
    kept = [rows[k] for k in fit.kept]
    res = fit.residuals
    return ArrayVelocity(
        time=rows[0].time, velocity_ned=fit.x[:3].copy(), clock_drift_mps=float(fit.x[3]),
        covariance=fit.cov, satellites=sorted({r.sat for r in kept}),
        antennas=sorted({r.antenna for r in kept}), n_rows=len(kept), excluded=excluded,
        residual_rms_mps=float(np.sqrt(np.mean(res**2))) if len(res) else 0.0,
    )


class TightVelocityFilter:
    """Short Kalman filter on (array velocity NED, common clock drift Ẑ) fed with η rows.

    It carries Ẑ (and the velocity) through epochs with too few satellites for a snapshot
    solution: with 3 satellites the predicted clock drift is the missing equation, with 2 a
    vertical-velocity constraint (a ship on the water) is added when ``vertical_sigma_mps`` is
    set. Velocity and Ẑ are random walks with the given densities. Rows whose innovation
    exceeds 5 σ are rejected (a missed slip).
    """

    def __init__(self, acceleration_sigma: float = 0.5, clock_drift_sigma: float = 0.06,
                 vertical_sigma_mps: float | None = None, initial_sigma: float = 30.0) -> None:
        self.q = np.array([acceleration_sigma**2] * 3 + [clock_drift_sigma**2])
        self.vertical_sigma = vertical_sigma_mps
        self.initial_sigma = initial_sigma
        self.x: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.time: float | None = None

    def reset(self) -> None:
        self.x = self.P = self.time = None

    def step(
        self,
        rows: Sequence[EtaRow],
        time: float,
        *,
        lever_arms_body: np.ndarray | None = None,
        C_body_to_level: np.ndarray | None = None,
        omega_body: np.ndarray | None = None,
    ) -> ArrayVelocity | None:
        """Predict to ``time`` and update with ``rows``; None until the state is determined."""
        rows = list(rows)
        if self.x is None:
            # Start from the snapshot solution when there is one, else from nothing.
            snap = tight_velocity(rows, lever_arms_body=lever_arms_body,
                                  C_body_to_level=C_body_to_level, omega_body=omega_body)
            if snap is None:
                return None
            self.x = np.array([*snap.velocity_ned, snap.clock_drift_mps])
            self.P = snap.covariance.copy()
            self.time = time
            return snap
        dt = max(time - (self.time or time), 0.0)
        self.time = time
        self.P = self.P + np.diag(self.q * max(dt, 1e-3))
        rot = _lever_velocity_ned(rows, lever_arms_body, C_body_to_level, omega_body)
        used: list[int] = []
        excluded: dict[tuple[int, str], str] = {}
        obs = [(np.array([*r.los_ned, 1.0]), r.measured - rot[k], r.sigma, k)
               for k, r in enumerate(rows)]
        if self.vertical_sigma is not None:
            obs.append((np.array([0.0, 0.0, 1.0, 0.0]), 0.0, self.vertical_sigma, -1))
        # Gate against the prediction first, then update with every accepted row at once.
        keep = []
        for h, y, s, k in obs:
            innov = y - h @ self.x
            S = h @ self.P @ h + s * s
            if k >= 0 and abs(innov) > 5.0 * math.sqrt(S) and math.sqrt(S) < 1.0:
                excluded[(rows[k].antenna, rows[k].sat)] = "innovation test"
                continue
            keep.append((h, y, s))
            if k >= 0:
                used.append(k)
        if keep:
            Hm = np.array([k[0] for k in keep])
            ym = np.array([k[1] for k in keep])
            R = np.diag([k[2] ** 2 for k in keep])
            S = Hm @ self.P @ Hm.T + R
            K = np.linalg.solve(S, Hm @ self.P).T
            self.x = self.x + K @ (ym - Hm @ self.x)
            I_KH = np.eye(4) - K @ Hm
            self.P = I_KH @ self.P @ I_KH.T + K @ R @ K.T
        res = np.array([rows[k].measured - rot[k] - np.array([*rows[k].los_ned, 1.0]) @ self.x
                        for k in used])
        kept = [rows[k] for k in used]
        return ArrayVelocity(
            time=time, velocity_ned=self.x[:3].copy(), clock_drift_mps=float(self.x[3]),
            covariance=self.P.copy(), satellites=sorted({r.sat for r in kept}),
            antennas=sorted({r.antenna for r in kept}), n_rows=len(kept), excluded=excluded,
            residual_rms_mps=float(np.sqrt(np.mean(res**2))) if len(res) else 0.0,
        )


# ---------------------------------------------------------------- single differences


def single_differences(epoch_i: GnssEpoch | None, epoch_j: GnssEpoch | None,
                       wavelengths: Mapping[str, float]) -> dict[str, float]:
    """Raw single differences ``λ·(Φ_i − Φ_j)`` (m) of the satellites both receivers track.

    Only satellites with a wavelength in ``wavelengths`` (e.g. ``EpochGeometry.wavelengths``)
    are differenced.
    """
    if epoch_i is None or epoch_j is None:
        return {}
    out = {}
    for sat, lam in wavelengths.items():
        a, b = _phase(epoch_i, sat), _phase(epoch_j, sat)
        if math.isfinite(a) and math.isfinite(b):
            out[sat] = lam * (a - b)
    return out


def sd_sigma(elevation: float, phase_sigma_m: float = DEFAULT_PHASE_SIGMA_M) -> float:
    """σ (m) of a single difference at ``elevation`` (two independent receivers)."""
    return elevation_sigma(math.sqrt(2.0) * phase_sigma_m, elevation)


def estimate_inter_receiver_delay(
    sd_m: Mapping[str, float],
    integers: Mapping[str, int],
    los_ecef: Mapping[str, np.ndarray],
    baseline_ecef: np.ndarray,
    wavelengths: Mapping[str, float],
    sigmas: Mapping[str, float] | None = None,
) -> tuple[float, float, int] | None:
    """D̂_ij (m), its σ and the number of satellites, given fixed N_ij and a known baseline.

    With the common clock ``λ·Φ_ij^k − λ·N_ij^k − e^k·b_ij = D_ij + noise`` for every satellite,
    so D_ij is their weighted mean (no clock term to separate). ``baseline_ecef`` is b_ij.
    """
    values, weights = [], []
    b = np.asarray(baseline_ecef, dtype=float)
    for sat, sd in sd_m.items():
        if sat not in integers or sat not in los_ecef:
            continue
        values.append(sd - wavelengths[sat] * integers[sat] - los_ecef[sat] @ b)
        s = sigmas.get(sat, DEFAULT_PHASE_SIGMA_M) if sigmas else DEFAULT_PHASE_SIGMA_M
        weights.append(1.0 / s**2)
    if not values:
        return None
    w = np.array(weights)
    d = float(np.sum(w * np.array(values)) / np.sum(w))
    return d, float(1.0 / math.sqrt(np.sum(w))), len(values)


def zeta(sd_m: Mapping[str, float], integers: Mapping[str, int],
         wavelengths: Mapping[str, float], delay_m: float) -> dict[str, float]:
    """``ζ_ij^k = λ·Φ_ij^k − D̂_ij − λ·N_ij^k`` (m) = ``e^k·b_ij`` + noise, per satellite."""
    return {sat: sd - delay_m - wavelengths[sat] * integers[sat]
            for sat, sd in sd_m.items() if sat in integers}
