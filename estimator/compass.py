"""GNSS compass attitude from four antennas on a 10 cm square (thesis ch. 4; ``METHOD.md``).

Attitude determination = integer ambiguity resolution of the carrier-phase differences on the
six short baselines ``b_ij = r_j − r_i`` (pairs ``BASELINE_PAIRS``). Two resolution methods:

- ``"conventional"`` (thesis 3.2.2, fig. 11a): double differences on the three independent
  baselines (0,1), (0,2), (0,3), one float Kalman filter per baseline (baseline + ambiguities),
  LAMBDA with the ratio test and the known baseline length (``estimator.baseline``), ≥ 5
  satellites. Needs several epochs for the float solution to converge.
- ``"fast"`` (thesis 4.1.1, fig. 11b): no float solution. The IMU tilt (roll, pitch) and trial
  headings every few degrees give candidate baselines, hence predicted double differences and
  candidate integer sets (nearest integers, plus the neighbour when the fraction is near ½).
  Each set is solved for the baselines by least squares and accepted only if all six
  baselines have their known lengths and every pair keeps the known inter-baseline angle
  computed from the dot product (acos) AND from the cross product (asin) within δψ. A rigid-body
  fit of the layout to the double differences, with the IMU tilt as a prior, closes the test
  (χ²); a fix is declared when exactly one distinct set survives, or when the best set's χ² is
  ``survivor_ratio`` times below the next one → attitude from ONE epoch, ≥ 4 satellites.

Roll, pitch, heading come from fitting the layout (body frame) to the resolved baselines: Wahba
by SVD for the start, then Gauss–Newton on the double differences themselves (the rigid-body
constraint uses all six baselines with their correct correlations).

With a receiver lost (or missing from a recording) the same runs on the three others: two
independent baselines, three in all, still the whole attitude (``GnssCompass.receivers``).

``GnssCompass`` keeps the integers across epochs, re-validates them every epoch (χ² of the
rigid fit, baseline lengths), drops a satellite on a cycle slip (``cpp.detect_cycle_slips``)
and resolves newly risen satellites from the known attitude. With the common clock the
inter-receiver delay differences ``D_0j`` are estimated once fixed, after which single
differences ``ζ`` keep the attitude with 2 satellites (``attitude_from_single_differences``).
One satellite gives only two independent constraints per epoch on three angles: it needs the
IMU tilt (passed here as a prior) or, properly, the tight coupling with the gyro in the EKF.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2 as chi2_dist

from .baseline import BaselineFix, DoubleDifferenceFilter, SdObservation
from .cpp import (
    DEFAULT_PHASE_SIGMA_M,
    SAME_CARRIER_SYSTEMS,
    EpochGeometry,
    detect_cycle_slips,
    elevation_sigma,
    epoch_geometry,
)
from .frames import SPEED_OF_LIGHT, dcm_to_euler, euler_to_dcm, rotvec_to_dcm, wrap_angle
from .records import GnssEpoch, NavigationData
from .spp import standalone_position

MIN_RECEIVERS = 3  # two independent baselines still give the whole attitude


def receiver_pairs(n: int) -> tuple[tuple[int, int], ...]:
    """The baselines of ``n`` receivers, ``(0, j)`` first: the independent ones (the others
    are their differences). Four receivers: ``cpp.BASELINE_PAIRS``."""
    return tuple(itertools.combinations(range(n), 2))


# --------------------------------------------------------------------------- results


@dataclass
class CompassSolution:
    time: float
    fixed: bool
    method: str  # "fast" | "conventional" (resolved now), "hold-dd" | "hold-sd" (kept), "none"
    C_body_to_level: np.ndarray | None = None
    euler: np.ndarray | None = None  # roll, pitch, yaw (rad)
    baselines_ned: np.ndarray | None = None  # (pairs, 3) b_ij of ``receivers``' pairs
    integers: dict[tuple[int, int], dict[str, int]] = field(default_factory=dict)
    n_satellites: int = 0
    residual_rms_m: float = math.nan
    ratio: float = math.nan
    reference: str | None = None
    delays_m: dict[tuple[int, int], float] | None = None  # D̂_ij once estimated
    # Covariance of the attitude error as a rotation vector in the level frame (rad²), from
    # the assumed phase noise: [2, 2] is the heading variance (for the EKF's R).
    attitude_covariance: np.ndarray | None = None
    message: str = ""
    receivers: tuple[int, ...] = ()  # those resolved with (three or four; the first: reference)


# ------------------------------------------------------------------------- geometry


def layout_baselines(antennas_body: np.ndarray) -> np.ndarray:
    """(pairs, 3) body-frame baselines ``a_j − a_i`` for ``receiver_pairs(len(antennas))``:
    six for four antennas (``BASELINE_PAIRS``), three for three."""
    a = np.asarray(antennas_body, dtype=float)
    return np.array([a[j] - a[i] for i, j in receiver_pairs(len(a))])


def _all_baselines(b0: np.ndarray) -> np.ndarray:
    """(..., pairs, 3) baselines from the (..., n − 1, 3) independent ones b_01 … b_0(n−1)."""
    full = np.concatenate([np.zeros_like(b0[..., :1, :]), b0], axis=-2)
    i, j = np.array(receiver_pairs(b0.shape[-2] + 1)).T
    return full[..., j, :] - full[..., i, :]


def baseline_angles(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angles of every pair of baselines from the dot product (acos) and the cross product
    (asin).

    ``b``: (..., m, 3). Returns two (..., m(m−1)/2) arrays in radians (15 for the six
    baselines of four antennas); the asin one lies in [0, π/2].
    """
    p, q = np.array(receiver_pairs(b.shape[-2])).T
    b1, b2 = b[..., p, :], b[..., q, :]
    norms = np.linalg.norm(b1, axis=-1) * np.linalg.norm(b2, axis=-1)
    norms = np.maximum(norms, 1e-12)
    cos_a = np.clip(np.sum(b1 * b2, axis=-1) / norms, -1.0, 1.0)
    sin_a = np.clip(np.linalg.norm(np.cross(b1, b2), axis=-1) / norms, 0.0, 1.0)
    return np.arccos(cos_a), np.arcsin(sin_a)


def check_baseline_geometry(
    baselines: np.ndarray,
    layout: np.ndarray,
    length_tolerance_m: float,
    angle_tolerance_rad: float,
) -> np.ndarray:
    """Thesis 4.1.1 test of resolved baselines against the known layout.

    ``baselines``: (..., 6, 3) candidate baselines (any frame), ``layout``: (6, 3) body ones.
    True where every length is within ``length_tolerance_m`` and, for every pair, both
    ``|acos(b1·b2/|b1||b2|) − Δ_OFFSET|`` and ``|asin(|b1×b2|/|b1||b2|) − asin(sin Δ_OFFSET)|``
    are below δψ. (asin only returns angles up to 90°, so an offset of e.g. 135° is compared
    with its supplement 45°.)
    """
    lengths = np.linalg.norm(baselines, axis=-1)
    ok = np.all(np.abs(lengths - np.linalg.norm(layout, axis=-1)) < length_tolerance_m, axis=-1)
    a_cos, a_sin = baseline_angles(baselines)
    offset_cos, offset_sin = baseline_angles(layout)
    ok &= np.all(np.abs(a_cos - offset_cos) < angle_tolerance_rad, axis=-1)
    ok &= np.all(np.abs(a_sin - offset_sin) < angle_tolerance_rad, axis=-1)
    return ok


def wahba(level: np.ndarray, body: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """C_body_to_level minimising Σ w |level_k − C body_k|² (SVD solution of Wahba's problem)."""
    w = np.ones(len(level)) if weights is None else np.asarray(weights, dtype=float)
    B = (np.asarray(level) * w[:, None]).T @ np.asarray(body)
    U, _, Vt = np.linalg.svd(B)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0
    return U @ np.diag([1.0, 1.0, d]) @ Vt


def tilt_from_specific_force(f_body: np.ndarray) -> tuple[float, float]:
    """(roll, pitch) in rad from the mean accelerometer specific force (body frd, m/s²).

    At rest the accelerometer measures −g expressed in the body frame (i.e. "up"), so
    ``f = [g sinθ, −g sinφ cosθ, −g cosφ cosθ]``.
    """
    fx, fy, fz = np.asarray(f_body, dtype=float)
    return float(math.atan2(-fy, -fz)), float(math.atan2(fx, math.hypot(fy, fz)))


# ------------------------------------------------------------- difference covariance


def _difference_covariance(rows: Sequence[tuple[Sequence[tuple[int, str, float]]]],
                           sigma_u: Mapping[str, float]) -> np.ndarray:
    """Covariance of linear combinations of undifferenced phases.

    Each row is a list of (receiver, satellite, coefficient); undifferenced phase noise is
    independent with σ = ``sigma_u[sat]`` (m) for every receiver.
    """
    keys: dict[tuple[int, str], int] = {}
    for row in rows:
        for i, s, _ in row:
            keys.setdefault((i, s), len(keys))
    M = np.zeros((len(rows), len(keys)))
    for r, row in enumerate(rows):
        for i, s, c in row:
            M[r, keys[(i, s)]] += c
    var = np.array([sigma_u[s] ** 2 for (_, s) in keys])
    return (M * var) @ M.T


def _whitener(cov: np.ndarray) -> np.ndarray:
    """W such that Wᵀ W = cov⁺ (pseudo-inverse square root; cov may be rank deficient)."""
    try:
        # Full rank (double differences): the inverse Cholesky factor is the cheap answer.
        L = np.linalg.cholesky(cov)
        return np.linalg.solve(L, np.eye(len(cov)))
    except np.linalg.LinAlgError:
        pass
    vals, vecs = np.linalg.eigh(cov)
    keep = vals > 1e-9 * max(vals.max(), 1e-30)
    return (vecs[:, keep] / np.sqrt(vals[keep])).T


# --------------------------------------------------------------- double differences


@dataclass
class DoubleDifferences:
    """Double differences of one epoch on the independent baselines (0,1) … (0,n−1).

    ``dd[j-1, k] = Φ_0j^{s_k} − Φ_0j^{ref}`` (cycles) with ``λ·dd = H[k]·b_0j + λ·N``; ``H`` rows
    are ``(e^k − e^ref)`` in NED.
    """

    time: float
    reference: str
    sats: list[str]  # the non-reference satellites, order of the columns
    H: np.ndarray  # (n, 3)
    dd: np.ndarray  # (receivers − 1, n) cycles
    wavelength: float
    cov: np.ndarray  # (m·n, m·n) m², baseline-major order (m independent baselines)
    sigma_u: dict[str, float]
    _whitener: np.ndarray | None = field(default=None, repr=False)

    @property
    def whitener(self) -> np.ndarray:
        """W with Wᵀ W = cov⁻¹ (cached: every candidate of an epoch shares it)."""
        if self._whitener is None:
            self._whitener = _whitener(self.cov)
        return self._whitener

    @property
    def n_satellites(self) -> int:
        return len(self.sats) + 1

    @property
    def n_baselines(self) -> int:
        """Independent baselines (0, j)."""
        return len(self.dd)


def double_differences(
    epochs: Sequence[GnssEpoch | None],
    geometry: EpochGeometry,
    sats: Sequence[str],
    phase_sigma_m: float = DEFAULT_PHASE_SIGMA_M,
    reference: str | None = None,
) -> DoubleDifferences | None:
    """Double differences of ``sats`` (tracked by every receiver of ``epochs``, same carrier).

    The reference satellite is the highest one unless given. None with < 2 satellites.
    """
    sats = [s for s in sats if s in geometry.satellites]
    if len(sats) < 2:
        return None
    ref = reference if reference in sats else max(
        sats, key=lambda s: geometry.satellites[s].elevation)
    others = [s for s in sats if s != ref]
    lam = geometry.wavelengths[ref]
    e_ref = geometry.los_ned(ref)
    H = np.array([geometry.los_ned(s) - e_ref for s in others])
    independent = range(1, len(epochs))
    dd = np.zeros((len(independent), len(others)))
    for j in independent:
        for k, s in enumerate(others):
            dd[j - 1, k] = (_sd(epochs, 0, j, s) - _sd(epochs, 0, j, ref))
    sigma_u = {s: elevation_sigma(phase_sigma_m, geometry.satellites[s].elevation) for s in sats}
    rows = [[(0, s, 1.0), (j, s, -1.0), (0, ref, -1.0), (j, ref, 1.0)]
            for j in independent for s in others]
    return DoubleDifferences(time=geometry.time, reference=ref, sats=others, H=H, dd=dd,
                             wavelength=lam, cov=_difference_covariance(rows, sigma_u),
                             sigma_u=sigma_u)


def _sd(epochs: Sequence[GnssEpoch | None], i: int, j: int, sat: str) -> float:
    """Φ_i − Φ_j (cycles), NaN when either is missing."""
    a, b = epochs[i], epochs[j]
    if a is None or b is None or sat not in a.satellites or sat not in b.satellites:
        return math.nan
    return a.satellites[sat].carrier_phase - b.satellites[sat].carrier_phase


def _baseline_ls(dd: DoubleDifferences, integers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unconstrained baselines (…, m, 3) and whitened residual χ² (…) for integer sets (…, m, n)
    of the ``m`` independent baselines.

    Each baseline is solved with its own block of the DD covariance (the cross-baseline
    correlation only matters for the rigid fit).
    """
    n = len(dd.sats)
    block = dd.cov[:n, :n]
    Wb = np.linalg.inv(block)
    G = np.linalg.solve(dd.H.T @ Wb @ dd.H, dd.H.T @ Wb)  # (3, n)
    y = dd.wavelength * (dd.dd - integers)  # (…, 3, n) metres
    b = y @ G.T  # (…, 3, 3)
    r = y - b @ dd.H.T
    chi2 = np.einsum("...jk,kl,...jl->...", r, Wb, r)
    return b, chi2


# ---------------------------------------------------------------------- rigid fits


def _gauss_newton_attitude(residual_fn, C0: np.ndarray, tilt: tuple[float, float] | None,
                           tilt_sigma: float, iterations: int = 8
                           ) -> tuple[np.ndarray, float, np.ndarray]:
    """Minimise |r(C)|² (+ tilt prior) over rotations C = exp(δθ×) C.

    ``residual_fn`` returns whitened residuals. Returns (C, cost without the prior, covariance
    of δθ — the rotation vector in the level frame, rad²).
    """
    def full(C: np.ndarray) -> np.ndarray:
        r = residual_fn(C)
        if tilt is None:
            return r
        eul = dcm_to_euler(C)
        return np.concatenate([r, [(eul[0] - tilt[0]) / tilt_sigma,
                                   (eul[1] - tilt[1]) / tilt_sigma]])

    C = C0.copy()
    eps = 1e-7
    J = np.eye(3)
    for _ in range(iterations):
        r0 = full(C)
        J = np.zeros((len(r0), 3))
        for a in range(3):
            d = np.zeros(3)
            d[a] = eps
            J[:, a] = (full(rotvec_to_dcm(d) @ C) - r0) / eps
        step, *_ = np.linalg.lstsq(J, -r0, rcond=None)
        C = rotvec_to_dcm(step) @ C
        if np.linalg.norm(step) < 1e-9:
            break
    r = residual_fn(C)
    cov = np.linalg.pinv(J.T @ J)
    return C, float(r @ r), cov


@dataclass
class AttitudeFit:
    """Rigid fit of the antenna layout to fixed double differences."""

    C_body_to_level: np.ndarray
    chi2: float  # of the double differences (σ = the assumed phase noise)
    residual_rms_m: float
    covariance: np.ndarray  # 3x3 of the rotation vector in the level frame (rad²)


def rigid_fit(dd: DoubleDifferences, integers: np.ndarray, layout: np.ndarray,
              C0: np.ndarray | None = None, tilt: tuple[float, float] | None = None,
              tilt_sigma_rad: float = math.radians(2.0)) -> AttitudeFit:
    """Attitude from fixed double differences (integers (m, n) for ``dd.sats``).

    Start from Wahba's solution on the resolved baselines (or ``C0``), then Gauss–Newton on
    the double differences of all the independent baselines with their full covariance.
    An IMU ``tilt`` (roll, pitch) enters as a prior: with few satellites on one side of the sky
    the heading is correlated with the poorly determined tilt, and the prior decorrelates it.
    χ² is that of the double differences alone.
    """
    if C0 is None:
        b0, _ = _baseline_ls(dd, integers)
        C0 = wahba(_all_baselines(b0), layout)
    y = (dd.wavelength * (dd.dd - integers)).reshape(-1)
    Wt = dd.whitener
    a0 = layout[:dd.n_baselines]  # body a_01, a_02, …

    def residual(C: np.ndarray) -> np.ndarray:
        pred = ((C @ a0.T).T @ dd.H.T).reshape(-1)  # (3n,) H·C a_0j, baseline-major
        return Wt @ (y - pred)

    C, chi2, cov = _gauss_newton_attitude(residual, C0, tilt, tilt_sigma_rad)
    raw = y - ((C @ a0.T).T @ dd.H.T).reshape(-1)
    return AttitudeFit(C, chi2, float(np.sqrt(np.mean(raw**2))), cov)


@dataclass
class SdAttitude:
    C_body_to_level: np.ndarray
    euler: np.ndarray
    residual_rms_m: float
    n_satellites: int
    n_observations: int
    covariance: np.ndarray  # 3x3 of the rotation vector in the level frame (rad²)


def attitude_from_single_differences(
    zetas: Mapping[tuple[int, int], Mapping[str, float]],
    los_ned: Mapping[str, np.ndarray],
    antennas_body: np.ndarray,
    C_initial: np.ndarray,
    *,
    tilt: tuple[float, float] | None = None,
    tilt_sigma_rad: float = math.radians(1.0),
    sigma_u: Mapping[str, float] | None = None,
) -> SdAttitude | None:
    """Attitude from single differences ``ζ_ij^k = e^k·C·(a_j − a_i)`` (common clock, D known).

    ``zetas[(i, j)][sat]`` in metres for any of the six pairs, ``los_ned[sat]`` the unit vector
    antenna → satellite. One satellite yields two independent constraints on the three angles
    (the square is planar), two satellites four: standalone it needs ≥ 2 satellites; with
    ``tilt`` = IMU (roll, pitch) one satellite is enough (the EKF does it properly with the gyro).
    The covariance of the six differences of four receivers' phases is rank 3 per satellite:
    its pseudo-inverse weights them correctly whatever pairs are given.
    """
    a = np.asarray(antennas_body, dtype=float)
    obs = [((i, j), s, z) for (i, j), per in zetas.items() for s, z in per.items()
           if s in los_ned and math.isfinite(z)]
    sats = sorted({s for _, s, _ in obs})
    if not sats or (len(sats) < 2 and tilt is None):
        return None
    sig = dict(sigma_u or {})
    for s in sats:
        sig.setdefault(s, DEFAULT_PHASE_SIGMA_M)
    cov = _difference_covariance([[(i, s, 1.0), (j, s, -1.0)] for (i, j), s, _ in obs], sig)
    Wt = _whitener(cov)
    y = np.array([z for _, _, z in obs])
    E = np.array([los_ned[s] for _, s, _ in obs])
    A = np.array([a[j] - a[i] for (i, j), _, _ in obs])

    def residual(C: np.ndarray) -> np.ndarray:
        return Wt @ (y - np.einsum("ki,ki->k", E, A @ C.T))

    C, _, cov = _gauss_newton_attitude(residual, np.asarray(C_initial, dtype=float), tilt,
                                       tilt_sigma_rad)
    raw = y - np.einsum("ki,ki->k", E, A @ C.T)
    return SdAttitude(C_body_to_level=C, euler=dcm_to_euler(C),
                      residual_rms_m=float(np.sqrt(np.mean(raw**2))), n_satellites=len(sats),
                      n_observations=len(obs), covariance=cov)


# --------------------------------------------------------------------- fast method


@dataclass
class FastResolution:
    """Outcome of the thesis' fast integer resolution at one epoch."""

    fixed: bool
    integers: np.ndarray | None  # (m, n) DD integers of baselines (0,j) for ``dd.sats``
    C_body_to_level: np.ndarray | None
    baselines_ned: np.ndarray | None  # (pairs, 3) resolved (least-squares) baselines
    chi2: float
    residual_rms_m: float
    ratio: float  # second-best / best rigid χ² among the geometric survivors (inf if one)
    n_candidates: int  # distinct integer sets tested
    n_geometry_pass: int  # sets passing the lengths and dot/cross angle test
    n_survivors: int  # sets passing every test
    message: str = ""
    covariance: np.ndarray | None = None  # of the attitude (rotation vector, level, rad²)


def _heading_candidates(dd: DoubleDifferences, layout: np.ndarray, tilt: tuple[float, float],
                        heading_step_deg: float, neighbour_margin: float,
                        max_ambiguous: int) -> np.ndarray:
    """Distinct integer sets (sets, baselines, n) predicted from the tilt and trial headings."""
    headings = np.radians(np.arange(0.0, 360.0, heading_step_deg))
    a0 = layout[:dd.n_baselines]
    sets = []
    for psi in headings:
        C = euler_to_dcm(tilt[0], tilt[1], psi)
        pred = (C @ a0.T).T @ dd.H.T / dd.wavelength  # (baselines, n) cycles
        f = dd.dd - pred
        base = np.round(f)
        frac = f - base
        ambiguous = np.argwhere(np.abs(frac) > 0.5 - neighbour_margin)
        sets.append(base)
        if 0 < len(ambiguous) <= max_ambiguous:
            # Every combination of the nearest and the other neighbouring integer.
            for mask in range(1, 2 ** len(ambiguous)):
                alt = base.copy()
                for bit, (j, k) in enumerate(ambiguous):
                    if mask >> bit & 1:
                        alt[j, k] += np.sign(frac[j, k])
                sets.append(alt)
    arr = np.array(sets)
    flat = np.unique(arr.reshape(len(arr), -1), axis=0)
    return flat.reshape(len(flat), dd.n_baselines, -1)


def _layout_tolerances(dd: DoubleDifferences, layout: np.ndarray,
                       length_tolerance_m: float | None, angle_tolerance_deg: float | None
                       ) -> tuple[float, float]:
    """(length m, angle rad) tolerances of the layout test from the baseline covariance of
    this epoch (the same for every candidate): 4 σ of the worst direction, at least 1 cm
    and 6°, unless given."""
    n = len(dd.sats)
    block = dd.cov[:n, :n]
    Cb = np.linalg.inv(dd.H.T @ np.linalg.solve(block, dd.H))
    sigma_b = math.sqrt(float(np.linalg.eigvalsh(Cb).max()))
    L = float(np.linalg.norm(layout, axis=1).min())
    dl = length_tolerance_m if length_tolerance_m is not None else max(0.01, 4.0 * sigma_b)
    dpsi = (math.radians(angle_tolerance_deg) if angle_tolerance_deg is not None
            else max(math.radians(6.0), 4.0 * math.sqrt(2.0) * sigma_b / L))
    return dl, dpsi


def _rigid_fits(dd: DoubleDifferences, cands: np.ndarray, idx: np.ndarray,
                layout: np.ndarray, level: tuple[float, float] | None, sig: float,
                chi2_quantile: float) -> list[tuple[float, int, AttitudeFit, bool]]:
    """Rigid fit of the layout to the double differences of each candidate ``idx``, with the
    IMU tilt ``level`` as a prior of σ ``sig``: its misfit joins the χ² (2 more degrees of
    freedom). A wrong set that only fits with a strongly tilted (e.g. mirrored) array fails
    here, while the right one with a weak vertical geometry (few satellites on one side) is
    held level by the prior. Returns (χ², candidate, fit, passes) sorted by χ²."""
    dof = dd.n_baselines * len(dd.sats) - 3 + (2 if level is not None else 0)
    limit = chi2_dist.ppf(chi2_quantile, dof)
    fits = []
    for k in idx:
        fit = rigid_fit(dd, cands[k], layout, tilt=level, tilt_sigma_rad=sig)
        chi2 = fit.chi2
        if level is not None:
            eul = dcm_to_euler(fit.C_body_to_level)
            chi2 += float(wrap_angle(eul[0] - level[0]) ** 2 + wrap_angle(eul[1] - level[1]) ** 2
                          ) / sig**2
        fits.append((chi2, k, fit, chi2 < limit))
    fits.sort(key=lambda f: f[0])
    return fits


def resolve_fast(
    dd: DoubleDifferences,
    antennas_body: np.ndarray,
    tilt: tuple[float, float] | None,
    *,
    heading_step_deg: float = 3.0,
    length_tolerance_m: float | None = None,
    angle_tolerance_deg: float | None = None,
    tilt_sigma_deg: float = 2.0,
    chi2_quantile: float = 0.9999,
    neighbour_margin: float = 0.12,
    max_ambiguous: int = 4,
    survivor_ratio: float | None = None,
) -> FastResolution:
    """Thesis 4.1.1: integers from IMU tilt + trial headings and the layout test of all the
    baselines (six with four antennas, three with three).

    Tolerances default to the noise of the epoch's least-squares baselines (4 σ of the worst
    direction, at least 1 cm and 6°), so the test is as tight as the geometry allows.
    A fix needs exactly one surviving set, or, with ``survivor_ratio``, a best set whose rigid
    χ² is that many times below the second one.
    """
    layout = layout_baselines(antennas_body)
    n = len(dd.sats)
    none = FastResolution(False, None, None, None, math.nan, math.nan, math.nan, 0, 0, 0)
    if n < 3:
        none.message = f"{n + 1} satellites < 4"
        return none
    level = (0.0, 0.0) if tilt is None else (float(tilt[0]), float(tilt[1]))
    cands = _heading_candidates(dd, layout, level, heading_step_deg, neighbour_margin,
                                max_ambiguous)
    b0, chi2_ls = _baseline_ls(dd, cands)
    b6 = _all_baselines(b0)

    dl, dpsi = _layout_tolerances(dd, layout, length_tolerance_m, angle_tolerance_deg)
    geo_ok = check_baseline_geometry(b6, layout, dl, dpsi)
    dof_ls = dd.n_baselines * (n - 3)
    if dof_ls > 0:
        geo_ok &= chi2_ls < chi2_dist.ppf(chi2_quantile, dof_ls)
    idx = np.flatnonzero(geo_ok)
    result = FastResolution(False, None, None, None, math.nan, math.nan, math.nan,
                            len(cands), len(idx), 0)
    if len(idx) == 0:
        result.message = "no candidate passes the baseline length/angle test"
        return result

    fits = _rigid_fits(dd, cands, idx, layout, None if tilt is None else level,
                       math.radians(tilt_sigma_deg), chi2_quantile)
    survivors = [f for f in fits if f[3]]
    result.n_survivors = len(survivors)
    result.ratio = fits[1][0] / max(fits[0][0], 1e-12) if len(fits) > 1 else math.inf
    if not survivors:
        result.message = "no candidate passes the rigid-fit χ² (with the IMU tilt)"
        return result
    best = survivors[0]
    if len(survivors) > 1:
        ratio = survivors[1][0] / max(best[0], 1e-12)
        if survivor_ratio is None or ratio < survivor_ratio:
            result.message = f"{len(survivors)} integer sets survive"
            return result
    chi2, k, fit, _ = best
    result.fixed = True
    result.integers = cands[k].astype(np.int64)
    result.C_body_to_level = fit.C_body_to_level
    result.covariance = fit.covariance
    result.baselines_ned = b6[k]
    result.chi2 = chi2
    result.residual_rms_m = fit.residual_rms_m
    return result


# -------------------------------------------------------------------------- compass


class GnssCompass:
    """Attitude of the four-antenna compass, epoch by epoch, with ambiguities kept.

    ``antennas_body``: (n,3) antenna phase centres in the body frame (calibration). The
    integers are resolved on the receivers that have an epoch, at least three, the first of
    them the reference: a receiver lost or missing from the recording leaves two independent
    baselines, which still give the whole attitude. ``method``:
    ``"fast"`` (thesis) or ``"conventional"``. ``systems``: constellations used for attitude
    (only those sharing the L1 carrier: G, E, J). The integers are stored per independent
    baseline (0,j) as single-difference integers with an arbitrary offset per baseline, which
    the estimated delay D̂_0j absorbs; N_ij of the other pairs is N_0j − N_0i.
    """

    def __init__(
        self,
        nav: NavigationData,
        antennas_body: np.ndarray,
        *,
        method: str = "fast",
        systems: str = SAME_CARRIER_SYSTEMS,
        elevation_mask_deg: float = 10.0,
        phase_sigma_m: float = DEFAULT_PHASE_SIGMA_M,
        heading_step_deg: float = 3.0,
        chi2_quantile: float = 0.9999,
        survivor_ratio: float | None = 3.0,
        conventional_ratio: float = 3.0,
        conventional_process_noise_m: float = 0.03,
        conventional_prior_m: float = 10.0,
        delay_smoothing: float = 0.2,
    ) -> None:
        if method not in ("fast", "conventional"):
            raise ValueError(f"unknown compass method {method!r} (fast or conventional)")
        if any(s not in SAME_CARRIER_SYSTEMS for s in systems):
            raise ValueError(f"systems {systems!r}: only {SAME_CARRIER_SYSTEMS} share the carrier")
        self.nav = nav
        self.antennas = np.asarray(antennas_body, dtype=float)
        if self.antennas.ndim != 2 or len(self.antennas) < MIN_RECEIVERS:
            raise ValueError(f"the GNSS compass needs at least {MIN_RECEIVERS} antennas, got "
                             f"{len(self.antennas)}")
        self.method = method
        self.systems = systems
        self.mask = elevation_mask_deg
        self.phase_sigma = phase_sigma_m
        self.heading_step = heading_step_deg
        self.chi2_quantile = chi2_quantile
        self.survivor_ratio = survivor_ratio
        self.delay_smoothing = delay_smoothing
        self._filters = {  # baselines (0, j) of the whole array
            j: DoubleDifferenceFilter(
                baseline_sigma_m=conventional_prior_m,
                process_noise_m=conventional_process_noise_m, phase_sigma_m=phase_sigma_m,
                ratio_threshold=conventional_ratio,
                known_length_m=float(np.linalg.norm(self.antennas[j] - self.antennas[0])),
                length_tolerance_m=0.02, min_satellites=5, hold=False)
            for j in range(1, len(self.antennas))
        }
        self.reset()

    def reset(self) -> None:
        """Forget everything (cold start)."""
        self.position: np.ndarray | None = None
        self.clock_bias_s = 0.0
        self.prev: list[GnssEpoch | None] = [None] * len(self.antennas)
        self._use(tuple(range(len(self.antennas))))
        self.integers: dict[int, dict[str, int]] | None = None
        self.delays: dict[int, float] | None = None
        self.C: np.ndarray | None = None
        self._last_fix: dict[int, BaselineFix] = {}
        for f in self._filters.values():
            f.reset()

    def _use(self, receivers: tuple[int, ...]) -> None:
        """Resolve and hold on these receivers (the first is the reference): from here on,
        indices are the sub-array's, and the output maps them back (``_solution``)."""
        self.receivers = receivers
        self.sub_antennas = self.antennas[list(receivers)]
        self.layout = layout_baselines(self.sub_antennas)
        self._pairs = receiver_pairs(len(receivers))
        self._independent = range(1, len(receivers))

    def _resolvable(self, epochs: Sequence[GnssEpoch | None]) -> tuple[int, ...]:
        """Every receiver with an epoch, if at least three have one (the first of them is the
        reference); else all of them (the resolution then finds nothing in common, and says
        why)."""
        here = tuple(i for i, e in enumerate(epochs) if e is not None and e.satellites)
        return here if len(here) >= MIN_RECEIVERS else tuple(range(len(epochs)))

    @property
    def fixed(self) -> bool:
        return self.integers is not None

    # ------------------------------------------------------------------ epoch

    def _no_position_why(self, present: Sequence[GnssEpoch]) -> str:
        """Why there is no standalone position: a live start waits for the satellites'
        broadcast ephemerides (~30 s of navigation messages; a user trial saw 25 s of
        "initialising" and no reason)."""
        sats = {s for e in present for s in e.satellites if s[0] in self.systems}
        known = sum(1 for s in sats if self.nav.ephemerides.get(s))
        if known < 4:
            return (f"no standalone position yet: broadcast ephemerides of {known} of "
                    f"{len(sats)} satellites (waiting for their navigation messages)")
        return "no standalone position yet"

    def update(self, epochs: Sequence[GnssEpoch | None],
               imu_tilt: tuple[float, float] | None = None) -> CompassSolution:
        """Process one epoch of every receiver (None for a receiver that has no epoch).

        ``imu_tilt`` = (roll, pitch) in rad from the accelerometer (``tilt_from_specific_force``).
        """
        epochs = list(epochs)
        if len(epochs) != len(self.antennas):
            raise ValueError(f"the compass takes {len(self.antennas)} receivers' epochs, got "
                             f"{len(epochs)}")
        present = [e for e in epochs if e is not None]
        if not present:
            return CompassSolution(time=math.nan, fixed=False, method="none",
                                   message="no receiver epoch")
        time = present[0].time
        spp = standalone_position(present, self.nav, elevation_mask_deg=self.mask,
                                  initial_ecef=self.position)
        if spp is not None:
            self.position = spp.position
            self.clock_bias_s = spp.clock_bias_m / SPEED_OF_LIGHT
        slips = detect_cycle_slips(self.prev, epochs, common_clock=True)
        for i, e in enumerate(epochs):
            if e is not None:
                self.prev[i] = e
        if self.position is None:
            return CompassSolution(time=time, fixed=False, method="none",
                                   message=self._no_position_why(present))
        sats = sorted({s for e in present for s in e.satellites if s[0] in self.systems})
        geo = epoch_geometry(self.nav, sats, time, self.position, self.clock_bias_s, self.mask)
        broken = {s for (_, s) in slips}
        lost = ""
        if self.integers is not None:
            sub = [epochs[i] for i in self.receivers]
            sol = self._hold(time, sub, geo, _tracked(sub, geo), broken, imu_tilt)
            if sol.fixed:
                return sol
            lost = sol.message
        if self.method == "conventional":
            # The float filters run only while there is no fix (they restart after a loss).
            self._feed_filters(time, epochs, geo, broken)
        self._use(self._resolvable(epochs))
        sub = [epochs[i] for i in self.receivers]
        sol = self._resolve(time, sub, geo, _tracked(sub, geo), imu_tilt)
        if lost and not sol.fixed:
            sol.message = f"{lost}; {sol.message}"
        return sol

    # --------------------------------------------------------------- resolve

    def _resolve(self, time: float, epochs, geo: EpochGeometry, tracked: list[str],
                 imu_tilt) -> CompassSolution:
        dd = double_differences(epochs, geo, tracked, self.phase_sigma)
        if dd is None or dd.n_satellites < 4:
            n = 0 if dd is None else dd.n_satellites
            silent = [str(self.receivers[i] + 1) for i, e in enumerate(epochs) if e is None]
            why = f"{n} common satellites < 4"
            if silent:  # the integers are resolved on the baselines from one receiver
                why += (f": receiver {', '.join(silent)} without an epoch (a fix needs "
                        f"{MIN_RECEIVERS} receivers)")
            return CompassSolution(time=time, fixed=False, method="none", n_satellites=n,
                                   message=why)
        if self.method == "fast":
            res = resolve_fast(dd, self.sub_antennas, imu_tilt,
                               heading_step_deg=self.heading_step,
                               chi2_quantile=self.chi2_quantile,
                               survivor_ratio=self.survivor_ratio)
            if not res.fixed:
                return CompassSolution(time=time, fixed=False, method="none",
                                       n_satellites=dd.n_satellites, ratio=res.ratio,
                                       message=res.message)
            integers, ratio = res.integers, res.ratio
            C, rms, cov = res.C_body_to_level, res.residual_rms_m, res.covariance
        else:
            got = self._conventional_integers(dd)
            if isinstance(got, str):
                return CompassSolution(time=time, fixed=False, method="none",
                                       n_satellites=dd.n_satellites, message=got)
            integers, ratio = got
            # The per-baseline fixes must also fit ONE rigid array.
            fit = rigid_fit(dd, integers, self.layout)
            if fit.chi2 > chi2_dist.ppf(self.chi2_quantile,
                                        dd.n_baselines * len(dd.sats) - 3):
                return CompassSolution(time=time, fixed=False, method="none",
                                       n_satellites=dd.n_satellites, message="fixed set fails "
                                       f"the rigid-fit χ² ({fit.chi2:.1f})")
            if imu_tilt is not None:
                fit = rigid_fit(dd, integers, self.layout, C0=fit.C_body_to_level, tilt=imu_tilt)
            C, rms, cov = fit.C_body_to_level, fit.residual_rms_m, fit.covariance
        self._store_integers(dd, integers, C, geo, epochs)
        self.C = C
        b0, _ = _baseline_ls(dd, integers)
        for f in self._filters.values():
            f.reset()  # the compass holds the integers itself from now on
        return self._solution(time, self.method, C, _all_baselines(b0), dd.n_satellites, rms,
                              ratio, dd.reference, cov)

    def _feed_filters(self, time: float, epochs, geo: EpochGeometry, broken: set[str]) -> None:
        for j, f in self._filters.items():
            sds = []
            for s, g in geo.satellites.items():
                o0, oj = epochs[0], epochs[j]
                if o0 is None or oj is None or s not in o0.satellites or s not in oj.satellites:
                    continue
                a, b = o0.satellites[s], oj.satellites[s]
                if not (math.isfinite(a.carrier_phase) and math.isfinite(b.carrier_phase)):
                    continue
                lam = geo.wavelengths[s]
                sds.append(SdObservation(
                    sat=s, phase_m=lam * (a.carrier_phase - b.carrier_phase),
                    code_m=a.pseudorange - b.pseudorange, los_ned=geo.los_ned(s),
                    elevation=g.elevation, wavelength=lam, continuous=s not in broken))
            self._last_fix[j] = f.update(time, sds)

    def _conventional_integers(self, dd: DoubleDifferences) -> tuple[np.ndarray, float] | str:
        """DD integers of the independent baselines from the float filters (all must be
        fixed)."""
        fixes = self._last_fix
        integers = np.zeros((dd.n_baselines, len(dd.sats)), dtype=np.int64)
        ratios = []
        for k in self._independent:
            j = self.receivers[k]
            fix = fixes.get(j)
            if fix is None or not fix.fixed:
                why = "no float solution" if fix is None else fix.message
                return f"baseline (0,{j}) not fixed: {why}"
            # The filter's reference may differ from dd.reference: N^{k,r} = N^{k,f} − N^{r,f}.
            sd = {fix.reference: 0, **fix.integers}
            if dd.reference not in sd or any(s not in sd for s in dd.sats):
                return f"baseline (0,{j}) fixed on other satellites"
            integers[k - 1] = [sd[s] - sd[dd.reference] for s in dd.sats]
            ratios.append(fix.ratio)
        return integers, float(min(ratios))

    def _store_integers(self, dd: DoubleDifferences, integers: np.ndarray, C: np.ndarray,
                        geo: EpochGeometry, epochs) -> None:
        """Keep SD-level integers; the reference's is chosen so that |D̂_0j| ≤ λ/2."""
        self.integers = {}
        lam = dd.wavelength
        e_ref = geo.satellites[dd.reference].line_of_sight
        C_le = geo.C_ecef_to_level.T
        for j in self._independent:
            b_ecef = C_le @ (C @ self.layout[j - 1])
            n_ref = int(round(_sd(epochs, 0, j, dd.reference) - e_ref @ b_ecef / lam))
            per = {dd.reference: n_ref}
            for k, s in enumerate(dd.sats):
                per[s] = n_ref + int(integers[j - 1, k])
            self.integers[j] = per
        self.delays = None
        self._update_delays(epochs, geo, C, first=True)

    # ------------------------------------------------------------------ hold

    def _hold(self, time: float, epochs, geo: EpochGeometry, tracked: list[str],
              broken: set[str], imu_tilt) -> CompassSolution:
        assert self.integers is not None and self.C is not None
        for per in self.integers.values():
            for s in list(per):
                if s in broken or s not in geo.satellites:
                    del per[s]
        # ``tracked`` holds only satellites of all the receivers: a receiver missing this
        # epoch leaves the double differences empty and the single differences take over.
        ind = self._independent
        fixed_sats = [s for s in tracked if all(s in self.integers[j] for j in ind)]
        sd_sats = [s for s in geo.satellites if any(s in self.integers[j] for j in ind)]
        C_prev = self.C
        if len(fixed_sats) >= 3:
            dd = double_differences(epochs, geo, fixed_sats, self.phase_sigma)
            ref = dd.reference
            ints = np.array([[self.integers[j][s] - self.integers[j][ref] for s in dd.sats]
                             for j in self._independent])
            fit = rigid_fit(dd, ints, self.layout, C0=C_prev)
            chi2 = fit.chi2
            if imu_tilt is not None:
                fit = rigid_fit(dd, ints, self.layout, C0=fit.C_body_to_level, tilt=imu_tilt)
            C, rms, cov = fit.C_body_to_level, fit.residual_rms_m, fit.covariance
            limit = chi2_dist.ppf(self.chi2_quantile, dd.n_baselines * len(dd.sats) - 3)
            b6 = None
            if len(dd.sats) >= 3:
                b0, _ = _baseline_ls(dd, ints)
                b6 = _all_baselines(b0)
            if chi2 > limit:
                return self._lose(time, f"held integers fail the χ² test ({chi2:.1f})")
            if b6 is not None and len(dd.sats) >= 4:
                lengths = np.linalg.norm(b6, axis=1)
                ref_l = np.linalg.norm(self.layout, axis=1)
                # Loose: a 4-5 satellite geometry gives cm-level single baselines.
                if np.any(np.abs(lengths - ref_l) > 0.05):
                    return self._lose(time, "held integers give wrong baseline lengths")
            method, n_sat, reference = "hold-dd", dd.n_satellites, ref
        elif self.delays is not None and sd_sats:
            zetas = self._zetas(epochs, geo, sd_sats)
            los = {s: geo.los_ned(s) for s in sd_sats}
            sig = {s: elevation_sigma(self.phase_sigma, geo.satellites[s].elevation)
                   for s in sd_sats}
            att = attitude_from_single_differences(zetas, los, self.sub_antennas, C_prev,
                                                   tilt=imu_tilt, sigma_u=sig)
            if att is None:
                return self._lose(time, f"{len(sd_sats)} satellite(s) with fixed integers")
            if att.residual_rms_m > 4.0 * self.phase_sigma:
                return self._lose(time, "single-difference attitude rejected")
            C, rms, method, n_sat, reference = att.C_body_to_level, att.residual_rms_m, \
                "hold-sd", att.n_satellites, None
            cov = att.covariance
            b6 = None
        else:
            return self._lose(time, f"{len(fixed_sats)} satellites with fixed integers")
        self.C = C
        self._add_new_satellites(epochs, geo, tracked, C)
        if method == "hold-dd" and n_sat >= 4:
            # With fewer satellites D̂ and the attitude are not separable: D̂ would soak up
            # the attitude error, so it is frozen (a constant hardware delay, thesis x_D).
            self._update_delays(epochs, geo, C)
        if b6 is None:
            b6 = (C @ self.layout.T).T
        return self._solution(time, method, C, b6, n_sat, rms, math.nan, reference, cov)

    def _lose(self, time: float, why: str) -> CompassSolution:
        self.integers = None
        self.delays = None
        return CompassSolution(time=time, fixed=False, method="none", message=why)

    def _zetas(self, epochs, geo: EpochGeometry, sats: list[str]
               ) -> dict[tuple[int, int], dict[str, float]]:
        out: dict[tuple[int, int], dict[str, float]] = {}
        assert self.integers is not None and self.delays is not None
        n = {0: {s: 0 for s in sats}, **self.integers}
        d = {0: 0.0, **self.delays}
        for i, j in self._pairs:
            per = {}
            for s in sats:
                sd = _sd(epochs, i, j, s)
                if not math.isfinite(sd) or s not in n[i] or s not in n[j]:
                    continue
                lam = geo.wavelengths[s]
                # N_ij = N_0j − N_0i and D_ij = D_0j − D_0i
                per[s] = lam * sd - (d[j] - d[i]) - lam * (n[j][s] - n[i][s])
            out[(i, j)] = per
        return out

    def _add_new_satellites(self, epochs, geo: EpochGeometry, tracked: list[str],
                            C: np.ndarray) -> None:
        """Integers of satellites without one, from the known attitude (and D̂ or a DD)."""
        assert self.integers is not None
        C_le = geo.C_ecef_to_level.T
        fixed = [s for s in tracked if all(s in self.integers[j] for j in self._independent)]
        ref = max(fixed, key=lambda s: geo.satellites[s].elevation) if fixed else None
        for s in tracked:
            if all(s in self.integers[j] for j in self._independent):
                continue
            lam = geo.wavelengths[s]
            values = {}
            for j in self._independent:
                b = C_le @ (C @ self.layout[j - 1])
                e = geo.satellites[s].line_of_sight
                if ref is not None:
                    e_r = geo.satellites[ref].line_of_sight
                    f = (_sd(epochs, 0, j, s) - _sd(epochs, 0, j, ref) - (e - e_r) @ b / lam
                         + self.integers[j][ref])
                elif self.delays is not None:
                    f = _sd(epochs, 0, j, s) - (e @ b + self.delays[j]) / lam
                else:
                    return
                values[j] = f
            if all(abs(f - round(f)) < 0.15 for f in values.values()):
                for j, f in values.items():
                    self.integers[j][s] = int(round(f))

    def _update_delays(self, epochs, geo: EpochGeometry, C: np.ndarray,
                       first: bool = False) -> None:
        """D̂_0j from the fixed single differences (common clock: no clock term)."""
        assert self.integers is not None
        C_le = geo.C_ecef_to_level.T
        new = {}
        for j in self._independent:
            b = C_le @ (C @ self.layout[j - 1])
            vals = []
            for s, n in self.integers[j].items():
                sd = _sd(epochs, 0, j, s)
                if s in geo.satellites and math.isfinite(sd):
                    lam = geo.wavelengths[s]
                    vals.append(lam * sd - lam * n - geo.satellites[s].line_of_sight @ b)
            if vals:
                new[j] = float(np.median(vals))
        if len(new) < len(self._independent):
            return
        if first or self.delays is None:
            self.delays = new
        else:
            a = self.delay_smoothing
            self.delays = {j: self.delays[j] + a * (new[j] - self.delays[j])
                           for j in self._independent}

    # -------------------------------------------------------------- output

    def _solution(self, time: float, method: str, C: np.ndarray, b6: np.ndarray, n_sat: int,
                  rms: float, ratio: float, reference: str | None,
                  covariance: np.ndarray | None) -> CompassSolution:
        assert self.integers is not None
        rx = self.receivers  # the sub-array's indices back to the receivers'
        ints = {(rx[0], rx[j]): dict(self.integers[j]) for j in self._independent}
        for i, j in self._pairs[len(self._independent):]:
            common = set(self.integers[i]) & set(self.integers[j])
            ints[(rx[i], rx[j])] = {s: self.integers[j][s] - self.integers[i][s]
                                    for s in sorted(common)}
        delays = None
        if self.delays is not None:
            d = {0: 0.0, **self.delays}
            delays = {(rx[i], rx[j]): d[j] - d[i] for i, j in self._pairs}
        return CompassSolution(time=time, fixed=True, method=method, C_body_to_level=C,
                               euler=dcm_to_euler(C), baselines_ned=b6, integers=ints,
                               n_satellites=n_sat, residual_rms_m=rms, ratio=ratio,
                               reference=reference, delays_m=delays,
                               attitude_covariance=covariance, receivers=rx)


def _tracked(epochs: Sequence[GnssEpoch | None], geo: EpochGeometry) -> list[str]:
    """The satellites with a carrier phase at every one of ``epochs``."""
    return [s for s in geo.satellites
            if all(e is not None and math.isfinite(_phase_of(e, s)) for e in epochs)]


def _phase_of(epoch: GnssEpoch, sat: str) -> float:
    ob = epoch.satellites.get(sat)
    return math.nan if ob is None else ob.carrier_phase

