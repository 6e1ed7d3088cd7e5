"""Standalone (single-point) positioning from L1/E1/B1I pseudoranges (the CPP block's ``r``).

Iterated weighted least squares on position, one receiver clock per constellation (the first
present of G, E, J, C, R is the reference; the others are its inter-system biases), with the
satellite clock, Sagnac, Saastamoinen troposphere and Klobuchar ionosphere corrections and
an elevation-dependent weighting. Outliers are removed one at a time by the normalised residual
(w-) test while redundancy remains.

Several receivers driven by one clock (the GNSS compass) can be solved together by passing a
list of their epochs: one position (their mean antenna position) and one set of clocks; the
observation keys are then ``"<receiver index>:<sat>"``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .ephemeris import (
    SatelliteState,
    carrier_frequency,
    is_beidou_geo,
    klobuchar_delay,
    pierce_angle,
    rotate_earth,
    satellite_state,
    select_ephemeris,
    troposphere_delay,
)
from .frames import (
    FREQ_L1,
    OMEGA_EARTH,
    SPEED_OF_LIGHT,
    C_ecef_to_level,
    ecef_to_geodetic,
    vector_length,
)
from .records import GnssEpoch, NavigationData

SYSTEM_ORDER = "GEJCR"  # reference-clock preference

# 1-sigma signal-in-space range error (orbit + clock + group delay) per system (m); GLONASS
# also carries receiver inter-frequency biases, BeiDou GEO orbits are the weakest.
_SIS_SIGMA = {"G": 1.0, "J": 1.0, "E": 0.8, "C": 1.5, "R": 2.0}
_SIS_SIGMA_BEIDOU_GEO = 2.5
_CODE_SIGMA = 0.3  # m, zenith code noise + multipath; grows as 1/sin(elevation)
# Klobuchar leaves ~50 % of the delay, but that error is mostly common to all satellites
# (absorbed by clock and height); 20 % is the part that shows in the residuals ...
_IONO_MODEL_FRACTION = 0.2
# ... and the common part is what moves the position: a scale of every satellite's delay
# (mostly the height) and the residual's horizontal gradient (a north-south gradient of the
# day's TEC moves the position north). Both are carried in the position's covariance: the
# level off by half, the gradient by half the delay per 1000 km of pierce-point offset.
_IONO_COMMON_FRACTION = 0.5
_IONO_GRADIENT_PER_M = 0.5 / 1e6
_SEMICIRCLE_M = math.pi * 6.371e6  # half a great circle of the Earth's surface
_IONO_SIGMA_NO_MODEL = 5.0  # m at zenith when no Klobuchar coefficients are broadcast
_TROPO_SIGMA = 0.1  # m at zenith for the standard-atmosphere model

NORMALISED_RESIDUAL_LIMIT = 4.0
# Plausibility of a solution (a ship's receivers): a diverged or ill-conditioned solution is
# refused rather than returned (it would anchor the absolute position, or seed the next epoch).
HEIGHT_RANGE_M = (-500.0, 10_000.0)  # ellipsoidal height
MAX_RESIDUAL_RMS_M = 50.0
_MAX_ITERATIONS = 20
_CONVERGED_M = 1e-4


@dataclass
class StandalonePosition:
    time: float  # receiver time tag (gpst s) of the epoch
    position: np.ndarray  # ECEF m
    llh: np.ndarray  # lat, lon (rad), h (m)
    clock_bias_m: float  # receiver clock of the reference system times c (m)
    system_biases_m: dict[str, float]  # per used system, relative to the reference (which is 0)
    satellites: list[str]  # observation keys used
    residuals_m: dict[str, float]  # post-fit residuals of the used observations
    pdop: float
    # ECEF covariance of the position (m²): the weighted solution's plus the ionosphere's
    # common modes (Klobuchar's level and a horizontal gradient, which the clocks and the
    # residuals do not show).
    covariance: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    rejected: list[str] = field(default_factory=list)  # keys removed by the outlier test
    reference_system: str = "G"
    iterations: int = 0


@dataclass
class _Obs:
    key: str
    sat: str
    system: str
    pseudorange: float
    state: SatelliteState  # at the true transmit time
    iono_scale: float  # (f_L1 / f)^2
    sis_sigma: float


def _prepare(epochs: Sequence[GnssEpoch], nav: NavigationData) -> list[_Obs]:
    multi = len(epochs) > 1
    out = []
    for index, ep in enumerate(epochs):
        for sat, ob in ep.satellites.items():
            p = ob.pseudorange
            if not math.isfinite(p) or p <= 0.0 or sat[0] not in SYSTEM_ORDER:
                continue
            # The pseudorange itself gives the satellite-time transmit instant, including the
            # receiver clock offset, so no receiver-clock iteration is needed.
            flight = p / SPEED_OF_LIGHT  # kept apart from the large gpst for precision
            eph = select_ephemeris(nav, sat, ep.time - flight)
            if eph is None:
                continue
            try:
                freq = carrier_frequency(sat, nav)
            except ValueError:
                continue
            st = satellite_state(eph, ep.time, -flight)
            dts = st.clock_bias
            # Shift to true time t = t_sv - dts; |dts| < 1 ms so the linear step is exact to um.
            state = SatelliteState(
                st.position - st.velocity * dts, st.velocity,
                st.clock_bias - st.clock_drift * dts, st.clock_drift,
            )
            sis = _SIS_SIGMA_BEIDOU_GEO if is_beidou_geo(sat) else _SIS_SIGMA[sat[0]]
            out.append(_Obs(
                key=f"{index}:{sat}" if multi else sat, sat=sat, system=sat[0],
                pseudorange=p, state=state, iono_scale=(FREQ_L1 / freq) ** 2, sis_sigma=sis,
            ))
    return out


@dataclass
class _Linearised:
    obs: list[_Obs]
    systems: list[str]
    H: np.ndarray
    prefit: np.ndarray  # measured - modelled (m), receiver clocks not yet removed
    sigma: np.ndarray
    # Each row's share (m) of the three common ionosphere errors of σ 1: level, north and
    # east gradient (n x 3).
    iono_common: np.ndarray


def _linearise(
    obs: list[_Obs], pos: np.ndarray, nav: NavigationData, mask: float, t_tag: float
) -> _Linearised:
    near_surface = False
    llh = None
    C_el = None
    if vector_length(pos) > 1e6:
        llh = ecef_to_geodetic(pos)
        near_surface = abs(llh[2]) < 1e5
        C_el = C_ecef_to_level(llh[0], llh[1])
    rows, used = [], []
    for ob in obs:
        r_sat = ob.state.position
        rng = vector_length(r_sat - pos)
        for _ in range(2):  # Earth rotation during the flight (Sagnac)
            rotated = rotate_earth(r_sat, OMEGA_EARTH * rng / SPEED_OF_LIGHT)
            rng = vector_length(rotated - pos)
        los = (rotated - pos) / rng
        model = rng - SPEED_OF_LIGHT * ob.state.clock_bias
        if near_surface:
            ned = C_el @ los
            el = math.asin(max(-1.0, min(1.0, -ned[2])))
            if el < mask:
                continue
            az = math.atan2(ned[1], ned[0])
            tropo = troposphere_delay(el, llh[2])
            sin_el = max(math.sin(el), 0.05)
            if nav.iono_alpha is not None and nav.iono_beta is not None:
                iono = ob.iono_scale * klobuchar_delay(
                    nav.iono_alpha, nav.iono_beta, t_tag, llh[0], llh[1], el, az)
                iono_sigma = _IONO_MODEL_FRACTION * iono
                delay = iono
            else:
                iono = 0.0
                iono_sigma = delay = ob.iono_scale * _IONO_SIGMA_NO_MODEL / sin_el
            offset = pierce_angle(el) * _SEMICIRCLE_M * _IONO_GRADIENT_PER_M
            common = delay * np.array([_IONO_COMMON_FRACTION, offset * math.cos(az),
                                       offset * math.sin(az)])
            model += tropo + iono
            var = (
                _CODE_SIGMA**2 * (1.0 + 1.0 / sin_el**2) + ob.sis_sigma**2 + iono_sigma**2
                + (_TROPO_SIGMA / (sin_el + 0.1)) ** 2
            )
        else:
            # Far from the surface (first iterations from the Earth centre): no atmosphere,
            # no mask, equal weights.
            var, common = 1.0, np.zeros(3)
        rows.append((ob, los, model, var, common))
        used.append(ob)
    systems = [s for s in SYSTEM_ORDER if any(o.system == s for o in used)]
    # A system seen by a single satellite only determines its own clock: leave it out.
    sats_per_system = {s: {o.sat for o in used if o.system == s} for s in systems}
    systems = [s for s in systems if len(sats_per_system[s]) >= 2]
    rows = [r for r in rows if r[0].system in systems]
    n, m = len(rows), 3 + len(systems)
    H = np.zeros((n, m))
    prefit = np.zeros(n)
    sigma = np.zeros(n)
    common = np.zeros((n, 3))
    for i, (ob, los, model, var, c) in enumerate(rows):
        H[i, :3] = -los
        H[i, 3 + systems.index(ob.system)] = 1.0
        prefit[i] = ob.pseudorange - model
        sigma[i] = math.sqrt(var)
        common[i] = c
    return _Linearised([r[0] for r in rows], systems, H, prefit, sigma, common)


def _solve(lin: _Linearised, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted LS correction for the misclosures ``y`` and its cofactor matrix."""
    A = lin.H / lin.sigma[:, None]
    b = y / lin.sigma
    N = A.T @ A
    Q = np.linalg.inv(N)
    return Q @ (A.T @ b), Q


def plausible(height_m: float, pdop: float, residuals_m: np.ndarray) -> bool:
    """A standalone solution a ship's receiver can have: height within ``HEIGHT_RANGE_M``, a
    geometry that solves (finite PDOP; a minimal set may be in the hundreds and still right),
    post-fit residuals within ``MAX_RESIDUAL_RMS_M`` RMS."""
    rms = float(np.sqrt(np.mean(np.square(residuals_m)))) if len(residuals_m) else 0.0
    return (HEIGHT_RANGE_M[0] <= height_m <= HEIGHT_RANGE_M[1] and math.isfinite(pdop)
            and rms <= MAX_RESIDUAL_RMS_M)


def _distinct_sats(obs: list[_Obs]) -> int:
    return len({o.sat for o in obs})


def standalone_position(
    epoch: GnssEpoch | Sequence[GnssEpoch],
    nav: NavigationData,
    *,
    elevation_mask_deg: float = 10.0,
    initial_ecef: np.ndarray | None = None,
) -> StandalonePosition | None:
    """Standalone position of one epoch (or of several receivers sharing one clock).

    None when fewer than 3 + (number of systems) satellites are usable, the iteration does
    not converge or the solution is not ``plausible``.
    """
    epochs = [epoch] if isinstance(epoch, GnssEpoch) else list(epoch)
    if not epochs:
        return None
    t_tag = epochs[0].time
    all_obs = _prepare(epochs, nav)
    mask = math.radians(elevation_mask_deg)
    pos = np.zeros(3) if initial_ecef is None else np.asarray(initial_ecef, dtype=float).copy()
    clocks: dict[str, float] = {}
    rejected: list[str] = []
    iterations = 0

    while True:
        active = [o for o in all_obs if o.key not in rejected]
        converged = False
        for _ in range(_MAX_ITERATIONS):
            iterations += 1
            lin = _linearise(active, pos, nav, mask, t_tag)
            if not lin.systems or _distinct_sats(lin.obs) < 3 + len(lin.systems):
                return None
            # A system joining later (e.g. after the mask) starts from the reference clock.
            ref_clock = clocks.get(lin.systems[0], 0.0)
            for s in lin.systems:
                clocks.setdefault(s, ref_clock)
            y = lin.prefit - np.array([clocks[o.system] for o in lin.obs])
            try:
                dx, Q = _solve(lin, y)
            except np.linalg.LinAlgError:  # degenerate geometry
                return None
            pos = pos + dx[:3]
            for j, s in enumerate(lin.systems):
                clocks[s] += dx[3 + j]
            if vector_length(dx) < _CONVERGED_M:
                converged = True
                break
        if not converged:
            return None
        v = y - lin.H @ dx  # post-fit residuals (the last step was below 0.1 mm)
        dof = len(v) - lin.H.shape[1]
        if dof >= 2:
            # Normalised residuals w_i = v_i / sqrt(Qvv_ii) with Qvv = Sigma - H Q H^T
            qvv = np.diag(lin.sigma**2) - lin.H @ Q @ lin.H.T
            d = np.sqrt(np.maximum(np.diag(qvv), 1e-9))
            w = np.abs(v) / d
            worst = int(np.argmax(w))
            if w[worst] > NORMALISED_RESIDUAL_LIMIT:
                # Residuals perfectly correlated with the worst one (e.g. the two satellites of
                # a system seen by two only) cannot be told apart: reject them together.
                corr = np.abs(qvv[worst]) / (d[worst] * d)
                twins = np.flatnonzero((corr > 0.999) & (w > 0.999 * w[worst]))
                rejected.extend(lin.obs[i].key for i in twins)
                continue
        break

    ref = lin.systems[0]
    pdop = float(math.sqrt(np.trace(np.linalg.inv(lin.H.T @ lin.H)[:3, :3])))
    # The positions the common ionosphere errors move (what the clocks do not absorb).
    shift = (Q @ (lin.H.T @ (lin.iono_common / lin.sigma[:, None] ** 2)))[:3]
    llh = ecef_to_geodetic(pos)
    if not plausible(llh[2], pdop, v):
        return None
    return StandalonePosition(
        time=t_tag,
        position=pos,
        llh=llh,
        clock_bias_m=float(clocks[ref]),
        system_biases_m={s: float(clocks[s] - clocks[ref]) for s in lin.systems},
        satellites=[o.key for o in lin.obs],
        residuals_m={o.key: float(r) for o, r in zip(lin.obs, v, strict=True)},
        pdop=pdop,
        covariance=Q[:3, :3] + shift @ shift.T,
        rejected=rejected,
        reference_system=ref,
        iterations=iterations,
    )


HEIGHT_GATE_SIGMA = 4.0  # a height further than this many σ from the fix's is a blunder


@dataclass(frozen=True)
class HeightAided:
    position: np.ndarray  # ECEF m
    covariance: np.ndarray  # ECEF m²
    innovation_m: float  # known height − the fix's
    innovation_sigma_m: float
    # False: the height disagreed beyond ``HEIGHT_GATE_SIGMA``: the position is the fix's,
    # its height uncertain by the whole disagreement
    used: bool


def height_aided(position_ecef: np.ndarray, covariance_ecef: np.ndarray, height_m: float,
                 sigma_m: float) -> HeightAided:
    """A fix and its covariance updated with a known ellipsoidal height (the antennas of a
    ship stand a known height above the sea surface): one Kalman update along the vertical.
    The ionosphere's level error moves the fix mostly up or down, correlated with its
    horizontal error, so the height also takes some of that back.

    Beyond the gate one of the two is wrong (a height above mean sea level instead of the
    ellipsoid, or an ionosphere far from its model): neither corrects the other, and the
    fix's vertical variance is raised to the disagreement squared."""
    position = np.asarray(position_ecef, float)
    P = np.asarray(covariance_ecef, float)
    llh = ecef_to_geodetic(position)
    up = -C_ecef_to_level(llh[0], llh[1])[2]
    innovation = float(height_m - llh[2])
    Pu = P @ up
    s = float(math.sqrt(up @ Pu + sigma_m**2))
    if abs(innovation) > HEIGHT_GATE_SIGMA * s:
        excess = max(innovation**2 - float(up @ Pu), 0.0)
        return HeightAided(position, P + excess * np.outer(up, up), innovation, s, used=False)
    gain = Pu / s**2
    return HeightAided(position + gain * innovation, P - np.outer(gain, Pu), innovation, s,
                       used=True)
