"""Relative positioning of two receivers by double differences (thesis 3.2.2).

The conventional carrier-phase method: a float Kalman filter over epochs whose states are the
baseline ``b = r_B − r_A`` (local NED) and one float single-difference ambiguity per satellite,
then LAMBDA on the double-difference ambiguities with the ratio test (and, when the baseline
length is known, a length check of every candidate). Receivers with SEPARATE clocks are
handled: each receiver's observations are referred to its own true reception time
(``time tag − clock bias``), so the satellite's motion between the two reception instants
(``ρ̇·Δdt``, 0.4 m for the 0.5 ms offset of two real receivers) does not leak into the double
differences; the remaining clock difference is common to all satellites and cancels.

Double differences use one reference satellite (highest elevation) for the systems that share
the 1575.42 MHz carrier (GPS, Galileo, QZSS). GLONASS (FDMA: inter-frequency biases between
receivers) and BeiDou (B1I, another carrier) are not used here; they still serve the velocity.

Keeping the SINGLE-difference ambiguities as states (RTKLIB style) makes a change of reference
satellite trivial: the double differences are formed from the states at each update.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .ambiguity import lambda_resolve
from .cpp import (
    DEFAULT_PHASE_SIGMA_M,
    SAME_CARRIER_SYSTEMS,
    EpochGeometry,
    detect_cycle_slips,
    epoch_geometry,
    sd_sigma,
)
from .frames import SPEED_OF_LIGHT
from .records import GnssEpoch, NavigationData
from .spp import StandalonePosition, standalone_position

DEFAULT_CODE_SIGMA_M = 0.3  # undifferenced code at zenith (noise + multipath)
_AMBIGUITY_PROCESS = 1e-8  # cycles²/s: ambiguities are constants between slips
_HOLD_SIGMA_CYCLES = 0.01


@dataclass(frozen=True)
class SdObservation:
    """Single difference of one satellite between receivers A and B (B minus A baseline).

    ``phase_m = λ·(Φ_A − Φ_B)`` and ``code_m = P_A − P_B``, both already freed of the
    satellite's motion between the two receivers' reception instants; model
    ``phase_m = e·b + (clock/delay term common to all satellites) + λ·N_AB``.
    """

    sat: str
    phase_m: float
    code_m: float  # NaN if either pseudorange is missing
    los_ned: np.ndarray  # unit vector receiver → satellite, NED
    elevation: float  # rad
    wavelength: float  # m
    continuous: bool  # phase continuous in both receivers since the previous epoch


@dataclass
class BaselineFix:
    """Output of one filter update."""

    time: float
    fixed: bool
    baseline_ned: np.ndarray  # fixed when ``fixed``, else the float estimate
    float_baseline_ned: np.ndarray
    covariance_ned: np.ndarray  # of the float baseline
    ratio: float
    n_satellites: int
    reference: str | None
    integers: dict[str, int] = field(default_factory=dict)  # DD N^{k,ref}, by satellite k
    message: str = ""

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.baseline_ned))


class DoubleDifferenceFilter:
    """Float KF (baseline + SD ambiguities) with LAMBDA fixing, for one pair of receivers.

    ``process_noise_m`` is the baseline random walk (m/√s): large for a moving rover
    (kinematic), the rotation speed of the baseline for a compass. ``known_length_m`` turns on
    the length check of the LAMBDA candidates (compass); ``hold`` feeds a validated fix back
    as tight constraints (fix-and-hold) so the following epochs stay fixed cheaply.
    """

    def __init__(
        self,
        *,
        baseline_sigma_m: float = 30.0,
        process_noise_m: float = 1.0,
        phase_sigma_m: float = DEFAULT_PHASE_SIGMA_M,
        code_sigma_m: float = DEFAULT_CODE_SIGMA_M,
        ratio_threshold: float = 3.0,
        known_length_m: float | None = None,
        length_tolerance_m: float = 0.02,
        min_satellites: int = 5,
        hold: bool = True,
        n_candidates: int = 2,
    ) -> None:
        self.baseline_sigma = baseline_sigma_m
        self.process_noise = process_noise_m
        self.phase_sigma = phase_sigma_m
        self.code_sigma = code_sigma_m
        self.ratio_threshold = ratio_threshold
        self.known_length = known_length_m
        self.length_tolerance = length_tolerance_m
        self.min_satellites = min_satellites
        self.hold = hold
        # The length check needs candidates beyond the best two to choose from.
        self.n_candidates = max(30 if known_length_m is not None else 2, n_candidates)
        self.reset()

    def reset(self) -> None:
        self.sats: list[str] = []
        self.x = np.zeros(3)
        self.P = np.eye(3) * self.baseline_sigma**2
        self.time: float | None = None
        self.held: dict[str, int] = {}  # SD-level integers of the last fix (ref offset 0)

    # ------------------------------------------------------------------ states

    def _remove(self, sat: str) -> None:
        k = 3 + self.sats.index(sat)
        self.x = np.delete(self.x, k)
        self.P = np.delete(np.delete(self.P, k, 0), k, 1)
        self.sats.remove(sat)
        self.held.pop(sat, None)

    def _add(self, sd: SdObservation) -> None:
        # Phase minus code: clocks and geometry cancel, the ambiguity (± code noise) remains.
        if math.isfinite(sd.code_m):
            a0 = (sd.phase_m - sd.code_m) / sd.wavelength
            var = (3.0 * sd_sigma(sd.elevation, self.code_sigma) / sd.wavelength) ** 2
        else:
            a0 = (sd.phase_m - sd.los_ned @ self.x[:3]) / sd.wavelength
            var = (self.baseline_sigma * 2.0 / sd.wavelength) ** 2
        self.sats.append(sd.sat)
        self.x = np.append(self.x, a0)
        n = len(self.x)
        P = np.zeros((n, n))
        P[: n - 1, : n - 1] = self.P
        P[n - 1, n - 1] = var
        self.P = P

    def _predict(self, time: float) -> None:
        dt = 1.0 if self.time is None else max(time - self.time, 0.0)
        self.time = time
        q = np.full(len(self.x), _AMBIGUITY_PROCESS * dt)
        q[:3] = self.process_noise**2 * dt
        self.P = self.P + np.diag(q)

    def _kf_update(self, H: np.ndarray, y: np.ndarray, R: np.ndarray) -> None:
        S = H @ self.P @ H.T + R
        K = np.linalg.solve(S, H @ self.P).T
        self.x = self.x + K @ (y - H @ self.x)
        I_KH = np.eye(len(self.x)) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ R @ K.T
        self.P = 0.5 * (self.P + self.P.T)

    # ------------------------------------------------------------------ update

    def update(self, time: float, sds: Sequence[SdObservation]) -> BaselineFix:
        """Predict to ``time``, update with the single differences, try to fix."""
        self._predict(time)
        by_sat = {s.sat: s for s in sds if math.isfinite(s.phase_m)}
        for sat in list(self.sats):
            if sat not in by_sat or not by_sat[sat].continuous:
                self._remove(sat)  # lost or slipped: a new ambiguity when it comes back
        for sat, sd in by_sat.items():
            if sat not in self.sats:
                self._add(sd)
        if len(self.sats) < 2:
            return self._float_only(time, None, "fewer than 2 satellites")
        ref = max(self.sats, key=lambda s: by_sat[s].elevation)
        others = [s for s in self.sats if s != ref]
        n, m = len(others), len(self.x)
        r = by_sat[ref]
        idx = {s: 3 + i for i, s in enumerate(self.sats)}

        # Double differences k − ref of phase (and code), with the ref-correlated covariance.
        D = np.zeros((n, len(self.sats)))
        for i, s in enumerate(others):
            D[i, idx[s] - 3] = 1.0
            D[i, idx[ref] - 3] = -1.0
        order = self.sats
        var_phase = np.array([sd_sigma(by_sat[s].elevation, self.phase_sigma) ** 2 for s in order])
        var_code = np.array([sd_sigma(by_sat[s].elevation, self.code_sigma) ** 2 for s in order])
        H_phase = np.zeros((n, m))
        y_phase = np.zeros(n)
        for i, s in enumerate(others):
            o = by_sat[s]
            H_phase[i, :3] = o.los_ned - r.los_ned
            H_phase[i, idx[s]] = o.wavelength
            H_phase[i, idx[ref]] = -r.wavelength
            y_phase[i] = o.phase_m - r.phase_m
        R_phase = D @ np.diag(var_phase) @ D.T
        code_ok = [i for i, s in enumerate(others)
                   if math.isfinite(by_sat[s].code_m) and math.isfinite(r.code_m)]
        H_list, y_list, R_blocks = [H_phase], [y_phase], [R_phase]
        if code_ok:
            Dc = D[code_ok]
            H_code = np.zeros((len(code_ok), m))
            H_code[:, :3] = H_phase[code_ok, :3]
            y_code = np.array([by_sat[others[i]].code_m - r.code_m for i in code_ok])
            H_list.append(H_code)
            y_list.append(y_code)
            R_blocks.append(Dc @ np.diag(var_code) @ Dc.T)
        H = np.vstack(H_list)
        y = np.concatenate(y_list)
        R = np.zeros((len(y), len(y)))
        o = 0
        for B in R_blocks:
            R[o:o + len(B), o:o + len(B)] = B
            o += len(B)
        self._kf_update(H, y, R)
        if self.held and ref in self.held:
            self._apply_hold(ref, others, idx)
        return self._try_fix(time, ref, others, idx)

    def _apply_hold(self, ref: str, others: list[str], idx: dict[str, int]) -> None:
        held = [s for s in others if s in self.held]
        if not held:
            return
        H = np.zeros((len(held), len(self.x)))
        y = np.zeros(len(held))
        for i, s in enumerate(held):
            H[i, idx[s]] = 1.0
            H[i, idx[ref]] = -1.0
            y[i] = self.held[s] - self.held[ref]
        self._kf_update(H, y, np.eye(len(held)) * _HOLD_SIGMA_CYCLES**2)

    def _float_only(self, time: float, ref: str | None, message: str) -> BaselineFix:
        return BaselineFix(time=time, fixed=False, baseline_ned=self.x[:3].copy(),
                           float_baseline_ned=self.x[:3].copy(),
                           covariance_ned=self.P[:3, :3].copy(), ratio=0.0,
                           n_satellites=len(self.sats), reference=ref, message=message)

    def _try_fix(self, time: float, ref: str, others: list[str], idx: dict[str, int]
                 ) -> BaselineFix:
        if len(self.sats) < self.min_satellites:
            return self._float_only(time, ref, f"{len(self.sats)} satellites < "
                                               f"{self.min_satellites} for a fix")
        n = len(others)
        T = np.zeros((n, len(self.x)))
        for i, s in enumerate(others):
            T[i, idx[s]] = 1.0
            T[i, idx[ref]] = -1.0
        a = T @ self.x
        Q = T @ self.P @ T.T
        Q = 0.5 * (Q + Q.T)
        P_ba = self.P[:3] @ T.T
        try:
            sol = lambda_resolve(a, Q, n_candidates=min(self.n_candidates, 10_000))
        except ValueError as exc:
            return self._float_only(time, ref, f"LAMBDA failed: {exc}")
        gain = P_ba @ np.linalg.inv(Q)
        cands, norms = sol.candidates, sol.candidate_norms
        baselines = [self.x[:3] - gain @ (a - c) for c in cands]
        if self.known_length is not None:
            ok = [i for i, b in enumerate(baselines)
                  if abs(np.linalg.norm(b) - self.known_length) < self.length_tolerance]
        else:
            ok = list(range(len(cands)))
        if not ok:
            return self._float_only(time, ref, "no candidate passes the length check")
        best = ok[0]
        # Ratio among the candidates that pass; if only one passes, the worst one searched
        # bounds the second best from below.
        second = norms[ok[1]] if len(ok) > 1 else norms[-1]
        ratio = float(second / norms[best]) if norms[best] > 0 else math.inf
        integers = {s: int(cands[best][i]) for i, s in enumerate(others)}
        if ratio < self.ratio_threshold:
            fix = self._float_only(time, ref, f"ratio {ratio:.2f} < {self.ratio_threshold}")
            fix.ratio = ratio
            return fix
        if self.hold:
            self.held = {ref: 0, **integers}
        return BaselineFix(time=time, fixed=True, baseline_ned=baselines[best],
                           float_baseline_ned=self.x[:3].copy(),
                           covariance_ned=self.P[:3, :3].copy(), ratio=ratio,
                           n_satellites=len(self.sats), reference=ref, integers=integers)


# ------------------------------------------------------------- two real receivers


def aligned_single_differences(
    epoch_a: GnssEpoch,
    epoch_b: GnssEpoch,
    geometry: EpochGeometry,
    reception_offset_s: float,
    continuity: dict[str, bool],
) -> list[SdObservation]:
    """Single differences A − B with each receiver at its own reception time.

    ``geometry`` is that of receiver A (its time tag and clock bias); ``reception_offset_s`` is
    ``t_B − t_A`` of the true reception instants (≈ the clock-bias difference, < 1 ms). The
    satellite moves ``ρ̇·(t_B − t_A)`` in between (≈ 0.4 m at 0.5 ms): the second-order term is
    far below a micrometre, and using one geometry (one ephemeris issue) avoids a jump when
    the two instants straddle an ephemeris change. Then
    ``λΦ_A − λΦ_B + (ρ̇ − c·ḋt^k)·(t_B − t_A) = e·b + c(dt_A − dt_B) + λN``.
    """
    out = []
    C = geometry.C_ecef_to_level
    for sat, g in geometry.satellites.items():
        if sat[0] not in SAME_CARRIER_SYSTEMS:
            continue
        oa, ob = epoch_a.satellites.get(sat), epoch_b.satellites.get(sat)
        if oa is None or ob is None:
            continue
        if not (math.isfinite(oa.carrier_phase) and math.isfinite(ob.carrier_phase)):
            continue
        lam = geometry.wavelengths[sat]
        # Range rate of a receiver fixed to the Earth (its own motion over < 1 ms is < 1 mm).
        rate = g.range_rate() - SPEED_OF_LIGHT * g.sat_clock_drift
        motion = -rate * reception_offset_s  # ρ(t_A) − ρ(t_B) − c(dt^k(t_A) − dt^k(t_B))
        phase = lam * (oa.carrier_phase - ob.carrier_phase) - motion
        code = oa.pseudorange - ob.pseudorange - motion
        out.append(SdObservation(sat=sat, phase_m=phase, code_m=code,
                                 los_ned=C @ g.line_of_sight, elevation=g.elevation,
                                 wavelength=lam, continuous=continuity.get(sat, False)))
    return out


def same_carrier_epoch(epoch: GnssEpoch) -> GnssEpoch:
    """The epoch restricted to GPS, Galileo and QZSS (what the double differences use; also
    a faster standalone solution than with the GLONASS orbit integration)."""
    return GnssEpoch(epoch.time, {s: o for s, o in epoch.satellites.items()
                                  if s[0] in SAME_CARRIER_SYSTEMS}, epoch.flag)


@dataclass
class BaselineSolution:
    """Relative position of receiver B from receiver A at one epoch."""

    time: float
    fixed: bool
    baseline_ned: np.ndarray  # r_B − r_A in the local NED at A (m)
    sigma_ned: np.ndarray  # float σ per axis
    ratio: float
    n_satellites: int
    reference: str | None
    message: str = ""

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.baseline_ned))

    @property
    def azimuth_deg(self) -> float:
        """Direction of B seen from A, degrees clockwise from north in [0, 360)."""
        return float(np.degrees(np.arctan2(self.baseline_ned[1], self.baseline_ned[0])) % 360.0)


class RelativePositioning:
    """Two receivers with separate clocks → baseline per epoch (``berthing-aid baseline``).

    Each update runs the standalone solution of both receivers (position of A for the geometry,
    each receiver's clock bias for its reception time), the cycle-slip detector of each
    receiver, and the double-difference filter.
    """

    def __init__(self, nav: NavigationData, *, elevation_mask_deg: float = 15.0,
                 process_noise_m: float = 1.0, ratio_threshold: float = 3.0,
                 base_ecef: np.ndarray | None = None, **filter_options) -> None:
        self.nav = nav
        self.mask = elevation_mask_deg
        self.base_ecef = None if base_ecef is None else np.asarray(base_ecef, dtype=float)
        self.filter = DoubleDifferenceFilter(process_noise_m=process_noise_m,
                                             ratio_threshold=ratio_threshold, **filter_options)
        self._prev: tuple[GnssEpoch, GnssEpoch] | None = None
        self._position: np.ndarray | None = self.base_ecef
        self._clock = [0.0, 0.0]

    def reset(self) -> None:
        self.filter.reset()
        self._prev = None

    def update(self, epoch_a: GnssEpoch, epoch_b: GnssEpoch,
               spp_a: StandalonePosition | None = None,
               spp_b: StandalonePosition | None = None) -> BaselineSolution | None:
        """One epoch of both receivers. Their standalone solutions may be passed in when the
        caller already has them (they are computed here otherwise)."""
        given = (spp_a, spp_b)
        for k, ep in enumerate((epoch_a, epoch_b)):
            spp = given[k] or standalone_position(
                same_carrier_epoch(ep), self.nav, elevation_mask_deg=self.mask,
                initial_ecef=self._position)
            if spp is not None:
                self._clock[k] = spp.clock_bias_m / SPEED_OF_LIGHT
                if k == 0 and self.base_ecef is None:
                    self._position = spp.position
        if self._position is None:
            return None
        sats = [s for s in epoch_a.satellites if s[0] in SAME_CARRIER_SYSTEMS]
        geo = epoch_geometry(self.nav, sats, epoch_a.time, self._position, self._clock[0],
                             self.mask)
        offset = (epoch_b.time - self._clock[1]) - (epoch_a.time - self._clock[0])
        prev = self._prev or (None, None)
        slips = detect_cycle_slips(list(prev), [epoch_a, epoch_b], common_clock=False)
        continuity = {s: (0, s) not in slips and (1, s) not in slips for s in sats}
        self._prev = (epoch_a, epoch_b)
        sds = aligned_single_differences(epoch_a, epoch_b, geo, offset, continuity)
        fix = self.filter.update(epoch_a.time, sds)
        return BaselineSolution(time=epoch_a.time, fixed=fix.fixed,
                                baseline_ned=fix.baseline_ned,
                                sigma_ned=np.sqrt(np.diag(fix.covariance_ned)),
                                ratio=fix.ratio, n_satellites=fix.n_satellites,
                                reference=fix.reference, message=fix.message)
