"""The CPP block inside the fusion, once the INS runs (thesis 5.1.1, fig. 18, and 5.2.1;
``METHOD.md``): per GNSS epoch the time-differenced carrier phase (η rows, or the loose
per-receiver velocities ``v``) and the single differences ζ with their integers, applied to the
EKF; the standalone position only anchors the absolute output and aids the EKF when nothing
else does.

The single-difference integers are kept per (receiver, satellite) with an arbitrary offset per
satellite (N_ij = A_i − A_j); the integer part of the inter-receiver delays is absorbed in the
same way as in the compass. New or slipped satellites are re-resolved by rounding against the
EKF's prediction when its σ is far below a cycle. The TDCP is corrected for the modelled
change of the tropospheric and ionospheric delays over the interval (mm/s for a low satellite,
a few cm per minute of trajectory otherwise).
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from .cpp import (
    FIT_UNKNOWNS,
    MIN_FIT_SATELLITES,
    SAME_CARRIER_SYSTEMS,
    AtmosphereActivity,
    CorrelatedDrift,
    EpochGeometry,
    EtaRow,
    TdcpFit,
    atmosphere_corrected,
    detect_cycle_slips,
    elevation_sigma,
    eta_observations,
    loose_velocity,
    origin_sensitivity,
    receiver_steps,
    robust_lsq,
    tdcp_fit,
    velocity_map,
)
from .ekf import EkfConfig, ErrorStateEkf, EtaInput, SdRow, VelocityInput, chi2_gate
from .frames import SPEED_OF_LIGHT, dcm_to_rotvec, ecef_to_ned, ned_to_ecef, rotvec_to_dcm
from .gnss_epochs import N_RECEIVERS, GnssFront
from .integrity import IntegrityMonitor
from .options import FusionOptions, WorldOrigin
from .records import GnssEpoch, NavigationData

GNSS_STALE_S = 3.0  # no carrier-phase velocity for this long: "degraded"
SPP_AIDING_AFTER_S = 5.0  # ... and for this long: the SPP position aids the EKF (loosely)
SPP_SIGMA_M = (5.0, 5.0, 8.0)  # 1-σ NED of the standalone position when it aids the EKF
ROUNDING_SIGMA_CYCLES = 0.12  # predicted single difference must be this sure to round N
ROUNDING_FRACTION = 0.3  # ... and the measured fraction this close to an integer
DELAY_SEED_ATTITUDE = math.radians(8.0)  # attitude σ below which the delays' fractions are found
DELAY_SEED_COHERENCE = 0.8  # |mean phasor| of the fractions below this: they disagree
DELAY_UNKNOWN_M = 0.1  # σ of a delay against a receiver never tracked: any fraction of a cycle
SD_INCONSISTENT_FRACTION = 0.5  # this share of the single differences rejected: a fault
MIN_ATTITUDE_ROWS = 8  # single differences for the attitude check (3 unknowns, a few over)
ATTITUDE_MIN_SPREAD = 0.3  # the least scatter of their stated σ the attitude check assumes
ATTITUDE_DELAY_SIGMA_M = 0.005  # rows whose delay is less sure than this do not judge it
# The gyro's turn is compared with the single differences' heading over these spans: a bias
# step of half a degree per second shows in a second or two, where one epoch's attitude check
# (its σ a few tenths of a degree) sees nothing.
GYRO_CHECK_WINDOWS_S = (3.0, 6.0)
GYRO_CHECK_LONGEST_S = max(GYRO_CHECK_WINDOWS_S) - 1e-6  # (a float's margin)
# The single differences' heading scatter (``GyroCheck.scatter``): over this many epochs
# (30 left a scatter 15 % low often enough to trip the gate: 1.7x the stated σ, 20 draws of
# 300 epochs, a perfect gyro: 154 alarms judged by the stated σ, 11 by the scatter over 60
# epochs), used from this many on
GYRO_SCATTER_EPOCHS = 60
GYRO_SCATTER_MIN = 10
# ... and before: the most it was seen to scatter on clean recordings (large ship 205 ~1.6x,
# 191 with half the sky blocked 1.7x). Taken as 1 meanwhile, a 1.7x scatter raised "gyro" on
# a perfect gyro in the first 12 epochs of 187 draws in 1000 (campaign seed 191's half-sky:
# "gyro turned 2.7° off" at 9 s, the SD heading's own error 2.4° in 3 s).
GYRO_SCATTER_PRIOR = 1.7


class SdIntegers:
    """Integers of the single differences, A[(receiver, sat)] with N_ij = A_i − A_j."""

    def __init__(self) -> None:
        self.A: dict[tuple[int, str], int] = {}
        self._strikes: dict[tuple[int, str], int] = {}

    def __len__(self) -> int:
        return len(self.A)

    def drop(self, keys: Iterable[tuple[int, str]]) -> None:
        for key in keys:
            self.A.pop(key, None)
            self._strikes.pop(key, None)

    def rows(self, epochs: Sequence[GnssEpoch | None], geo: EpochGeometry, C_el: np.ndarray,
             ekf: ErrorStateEkf, phase_sigma: float, receivers: Collection[int]) -> list[SdRow]:
        """Rows of the satellites with known integers; new ones are rounded first. Only the
        ``receivers`` whose delays are known take part (rounding needs D̂)."""
        out: list[SdRow] = []
        for sat, g in geo.satellites.items():
            if sat[0] not in SAME_CARRIER_SYSTEMS:
                continue
            lam = geo.wavelengths[sat]
            phase = {i: e.satellites[sat].carrier_phase for i, e in enumerate(epochs)
                     if i in receivers and e is not None and sat in e.satellites
                     and math.isfinite(e.satellites[sat].carrier_phase)}
            if len(phase) < 2:
                continue
            for i in list(self.A):
                if i[1] == sat and i[0] not in phase:
                    self.drop([i])
            e = C_el @ g.line_of_sight
            sigma = elevation_sigma(phase_sigma, g.elevation)
            self._resolve(sat, phase, lam, e, sigma, ekf)
            known = sorted(i for i in phase if (i, sat) in self.A)
            if len(known) < 2:
                continue
            ref = known[0]
            for j in known[1:]:
                n_ij = self.A[(ref, sat)] - self.A[(j, sat)]
                out.append(SdRow(sat=sat, ref=ref, other=j, los_ned=e,
                                 value_m=lam * (phase[ref] - phase[j] - n_ij), sigma_m=sigma))
        return out

    def _resolve(self, sat: str, phase: dict[int, float], lam: float, e: np.ndarray,
                 sigma: float, ekf: ErrorStateEkf) -> None:
        known = sorted(i for i in phase if (i, sat) in self.A)
        unknown = [i for i in sorted(phase) if (i, sat) not in self.A]
        if not unknown:
            return
        if not known:
            ref = unknown.pop(0)
            candidate = {ref: 0}
        else:
            ref = known[0]
            candidate = {}
        for j in unknown:
            pred, s = ekf.predict_single_difference(ref, j, e, sigma)
            n = (lam * (phase[ref] - phase[j]) - pred) / lam
            N = round(n)
            if s < ROUNDING_SIGMA_CYCLES * lam and abs(n - N) < ROUNDING_FRACTION:
                base = candidate.get(ref, self.A.get((ref, sat), 0))
                candidate[j] = base - int(N)
        if len(candidate) >= 2 or known:
            for i, a in candidate.items():
                self.A[(i, sat)] = a

    def strike(self, rows: Sequence[SdRow], rejected: Sequence[int]) -> None:
        """A row failing the gate twice running loses the integer of its non-reference
        receiver; when every row of a satellite fails, the reference is the suspect and the
        satellite starts again."""
        bad = set(rejected)
        for k, r in enumerate(rows):
            if k not in bad:
                self._strikes.pop((r.other, r.sat), None)
        by_sat: dict[str, list[SdRow]] = {}
        for k in bad:
            by_sat.setdefault(rows[k].sat, []).append(rows[k])
        for sat, failed in by_sat.items():
            whole = len(failed) >= 2 and len(failed) == sum(1 for r in rows if r.sat == sat)
            for r in failed:
                key = (r.other, r.sat)
                self._strikes[key] = self._strikes.get(key, 0) + 1
                if self._strikes[key] >= 2:
                    self.drop([k for k in list(self.A) if k[1] == sat] if whole else [key])


@dataclass(frozen=True)
class _HeadingEpoch:
    """One epoch of ``GyroCheck``."""

    t: float
    C_sd: np.ndarray  # body to level, by the single differences alone
    heading_var_sd: float  # its heading's variance (rad²)
    C_gyro: np.ndarray  # ``Ins.C_gyro`` then
    bias_var: float  # the EKF's gyro bias variance then ((rad/s)², largest axis)
    bias_turn: float = 0.0  # ``Ins.bias_turn`` then (rad)
    bias_yaw_rate: float = 0.0  # ``Ins.bias_yaw_rate`` then (rad/s)


def _heading_off(old: _HeadingEpoch, new: _HeadingEpoch) -> float:
    """The rotation from ``old`` to ``new`` by the single differences less the gyro's, in
    level axes at the start (where the attitudes' errors are stated): its down component.
    The gyro's with its bias held at ``old``'s estimate: the EKF's estimates since (of a bias
    step it is learning) are given back. Without that, the faster the VO's check had the EKF
    learn a 1°/s step, the less of it this check saw: it never named the gyro."""
    learned = new.bias_turn - old.bias_turn - old.bias_yaw_rate * (new.t - old.t)
    return float((old.C_sd @ dcm_to_rotvec((old.C_sd.T @ new.C_sd)
                                           @ (old.C_gyro.T @ new.C_gyro).T))[2]) - learned


class GyroCheck:
    """The gyro's turn over a few seconds (``Ins.C_gyro``: integrated from the calibrated
    gyro, never corrected by the EKF) against that of the heading the single differences give
    at each epoch on their own (``CarrierPhaseCoupling._check_attitude``'s fit): the arbiter
    when the VO and the gyro disagree (``vo_coupling.VoConsistency``), which alone cannot say
    which of the two is off. A bias step of the gyro turns both the VO's check and the
    heading; declared as the gyro's, the VO's rotation is not judged by it meanwhile.

    The heading (about the level down axis) only: the tilt axes, on simulated small boats
    rolling in a swell, disagree beyond the gate on clean recordings (their χ² up to 30
    against 10 for the heading over 25 seeds), and the tilt has gravity to hold it."""

    def __init__(self, cfg: EkfConfig) -> None:
        self.cfg = cfg
        self.gate = chi2_gate(1, cfg.gate_probability)
        self._seen: deque[_HeadingEpoch] = deque()
        # the last epoch up to which the gyro did not measure the rotation (an IMU gap
        # bridged on the held mean rate): no window holding it is judged
        self._unmeasured_at = -math.inf
        # Consecutive epochs' disagreements over their stated σ: their spread is what the
        # single differences' heading scatters by. On large ship 205 it was 1.5x the fit's
        # σ (multipath), and two epochs 2.9σ apart raised "gyro" on a clean recording. A
        # bias step adds the same to each, which their spread about the median ignores.
        self._normalised: deque[float] = deque(maxlen=GYRO_SCATTER_EPOCHS)

    def check(self, epoch: _HeadingEpoch, measured: bool = True
              ) -> tuple[float, float] | None:
        """Add an epoch; the worst disagreeing window ending at it as (angle rad, window s),
        None if none. A window's gyro may be off by its start's bias σ (a widening since, by
        the VO's check, must not hide the step). ``measured`` False: an IMU gap was bridged
        up to this epoch."""
        seen, t = self._seen, epoch.t
        if seen and t <= seen[-1].t:
            seen.clear()  # time went back (a seek): nothing to compare with
            self._unmeasured_at = -math.inf
        seen.append(epoch)
        if not measured:
            self._unmeasured_at = t
        while len(seen) > 1 and t - seen[1].t >= GYRO_CHECK_LONGEST_S:
            seen.popleft()
        if len(seen) > 1 and seen[-2].t > self._unmeasured_at:
            last = seen[-2]
            self._normalised.append(_heading_off(last, epoch) / math.sqrt(
                last.heading_var_sd + epoch.heading_var_sd))
        scatter2 = self.scatter() ** 2
        worst, worst_nis = None, self.gate
        for window in GYRO_CHECK_WINDOWS_S:
            old = next((e for e in reversed(seen) if t - e.t >= window - 1e-6), None)
            if old is None or old.t <= self._unmeasured_at:
                continue
            span = t - old.t
            # rotation from then to now, by the single differences and by the gyro, in level
            # axes at the start (where the attitudes' errors are stated): its down component
            off = _heading_off(old, epoch)
            S = (old.heading_var_sd + epoch.heading_var_sd) * scatter2 \
                + self.cfg.gyro_arw**2 * span + old.bias_var * span**2
            if off**2 / S > worst_nis:
                worst, worst_nis = (abs(off), span), off**2 / S
        return worst

    def scatter(self) -> float:
        """How many times its stated σ the single differences' heading scatters by (at
        least 1; ``GYRO_SCATTER_PRIOR`` until ``GYRO_SCATTER_MIN`` epochs are known): 1.4826
        times the median absolute deviation of the consecutive epochs' normalised
        disagreements."""
        z = self._normalised
        if len(z) < GYRO_SCATTER_MIN:
            return GYRO_SCATTER_PRIOR
        med = statistics.median(z)
        return max(1.0, 1.4826 * statistics.median(abs(v - med) for v in z))

    def restart(self) -> None:
        """Forget the epochs so far (the gyro's bias was widened: judged afresh)."""
        self._seen.clear()

    def spans(self, t: float) -> float:
        """How long (s) the epochs kept span up to ``t``."""
        return t - self._seen[0].t if self._seen else 0.0


class CarrierPhaseCoupling:
    """One GNSS epoch into the running EKF: η (or v), ζ, the delays, the SPP aiding."""

    def __init__(self, nav: NavigationData, options: FusionOptions, config: EkfConfig,
                 monitor: IntegrityMonitor, aligning: bool) -> None:
        self.nav = nav
        self.monitor = monitor
        self.options = options
        self.cfg = config
        self.integers = SdIntegers()
        self.delays_known: set[int] = set()  # receivers whose δ̂ shares one reference
        self.last_velocity_time = -math.inf
        self.n_sats = 0  # satellites that served the last velocity update
        self.n_sd_sats = 0  # ... and the last single-difference update
        # Started from tilt + course (no compass fix): until the single differences agree.
        self.aligning = aligning
        self.message = ""
        # the trajectory error the satellites' correlated rate errors have integrated to
        # since the INS started (the EKF takes them as white)
        self.drift = CorrelatedDrift()
        self.activity = AtmosphereActivity()  # scales the drift and its overbound (the HPL's)
        self.gyro = GyroCheck(config)
        self._stepped: set[int] = set()  # receivers whose ranges stepped at the last epoch

    def update(self, t: float, epochs: list[GnssEpoch | None], ekf: ErrorStateEkf,
               origin: WorldOrigin, front: GnssFront) -> None:
        opt, cfg = self.options, self.cfg
        front.standalone(epochs, joint=False)
        geo = front.geometry(t, epochs, ned_to_ecef(ekf.antenna_position(None), origin.llh))
        stepped = self._receiver_steps(t, front.prev, epochs) if opt.common_clock else set()
        slips = detect_cycle_slips(front.prev, epochs, common_clock=opt.common_clock)
        self.monitor.slips(t, sum(1 for i, _s in slips if i not in stepped),
                           sum(len(e.satellites) for i, e in enumerate(epochs)
                               if e is not None and i not in stepped))
        prev_ok = front.prev_geo is not None and ekf.clone_time is not None \
            and abs(front.prev_geo.time - ekf.clone_time) < 1e-3
        rows: list[EtaRow] = []
        if prev_ok and opt.use_cpp:
            rows = eta_observations(front.prev, epochs, front.prev_geo, geo, slips=slips,
                                    phase_sigma_m=cfg.phase_sigma_m,
                                    common_clock=opt.common_clock).rows
            rows = atmosphere_corrected(rows, front.prev_geo, geo, self.nav, origin.llh)
            if rows and self.monitor.clock_jump(t, self._common_range_change(rows, ekf)):
                rows = []
            if rows:
                self.monitor.origin_interval(
                    origin_sensitivity(rows, front.prev_geo, geo, origin.C_ecef_to_level,
                                       cfg.tdcp_rate_sigma), rows[0].interval)
                found = velocity_map(rows, origin.C_ecef_to_level, cfg.tdcp_rate_sigma)
                if found is not None:
                    self.drift.interval(*found, rows[0].interval, self.activity.scale)
        # Single differences: integers re-resolved after slips, rows for the attitude.
        self.integers.drop([key for key in slips if key in self.integers.A])
        sd_rows: list[SdRow] = []
        if opt.use_cpp:
            self._seed_delays(epochs, geo, ekf, origin)
            sd_rows = self.integers.rows(epochs, geo, origin.C_ecef_to_level, ekf,
                                         cfg.phase_sigma_m, self.delays_known)
        self.n_sats = len(self._apply(rows, sd_rows, ekf, origin))
        if front.spp_ecef is not None:
            self._spp_aiding(front.spp_ecef, ekf, origin)
        ekf.clone(t)
        front.advance(epochs, geo)
        active = self.activity.scale
        self.message = (f"{self.n_sats} sats in the velocity, {self.n_sd_sats} in the single "
                        f"differences; gate rejections {_gate_text(ekf)}"
                        + (f"; atmosphere {active:.1f}x as active as a quiet day's: the drift "
                           "bound widened" if active > 1.05 else ""))

    def _apply(self, rows: Sequence[EtaRow], sd_rows: Sequence[SdRow], ekf: ErrorStateEkf,
               origin: WorldOrigin) -> set[str]:
        """η (or the loose per-receiver velocities) and ζ of one epoch; returns the satellites
        that served the velocity."""
        C_el = origin.C_ecef_to_level
        used: set[str] = set()
        eta: list[EtaInput] = []
        # In a burst of cycle slips the few rows left may have slipped unseen: a fit of them
        # that the robust one does not check (under MIN_FIT_SATELLITES), or the gate, would
        # blame the INS for them (a campaign task: 154 cm/s "off" 2 of 2 satellites, the
        # INS widened, unavailable for the rest of the run). The gate keeps them out.
        suspect = self.monitor.is_active("cycle-slips")
        if self.options.tightly_coupled:
            eta = [EtaInput(antenna=r.antenna, sat=r.sat, u_ned=C_el @ r.los_ecef,
                            measured=r.measured, sigma=r.sigma, interval=r.interval)
                   for r in rows]
        else:
            vels = []
            for i in range(N_RECEIVERS):
                lv = loose_velocity([r for r in rows if r.antenna == i], C_el)
                if lv is not None:
                    vels.append(VelocityInput(antenna=i, velocity_ned=lv.velocity_ned,
                                              covariance=lv.covariance_ned,
                                              interval=lv.interval_s))
                    used |= set(lv.satellites)
            vels = [v for v in vels if ekf.interval_ok(v.interval)]
            offs = [float(np.linalg.norm(ekf.velocity_innovation(v)[0])) for v in vels]
            res = ekf.update_velocity(vels)
            if vels and not suspect:
                turned = [k for k, v in enumerate(vels) if v.antenna in res.rejected]
                self._check_gated(len(turned), len(vels), max((offs[k] for k in turned),
                                  default=0.0), "receivers' velocities", ekf)
            if res.accepted:
                self.last_velocity_time = ekf.time
            else:
                used = set()
        taken, innovation = self._innovations(eta, ekf)
        fit = self._fit(taken, innovation, ekf)
        if fit is not None and fit.satellites >= MIN_FIT_SATELLITES and taken:
            self.activity.add(fit.scatter, taken[0].interval)  # (robust: its scatter measured)
        if fit is not None and not (suspect and fit.satellites < MIN_FIT_SATELLITES):
            self._check_velocity(fit, ekf)
        self._check_attitude(sd_rows, ekf)
        rate_sigma = max(self.cfg.tdcp_rate_sigma, fit.scatter if fit is not None else 0.0)
        res_eta, res_sd = ekf.update_carrier_phase(eta, sd_rows, rate_sigma)
        if taken and fit is None and not suspect:
            turned = set(res_eta.rejected)
            self._check_gated(len({taken[k].sat for k in turned}), len({r.sat for r in taken}),
                              max((abs(innovation[k]) for k in turned), default=0.0),
                              "satellites (too few to fit a velocity)", ekf)
        if eta:
            bad = set(res_eta.rejected)
            used = {r.sat for k, r in enumerate(rows) if k not in bad}
            if res_eta.accepted:
                self.last_velocity_time = ekf.time
        bad_sd = set(res_sd.rejected)
        self.n_sd_sats = len({r.sat for k, r in enumerate(sd_rows) if k not in bad_sd})
        if len(sd_rows) >= 4 and len(bad_sd) >= SD_INCONSISTENT_FRACTION * len(sd_rows):
            self.monitor.raise_fault("sd-inconsistent", ekf.time, f"{len(bad_sd)} of "
                                     f"{len(sd_rows)} single differences disagree with the "
                                     "attitude: integers re-resolved, heading not trusted")
        elif sd_rows and res_sd.accepted:
            self.monitor.clear("sd-inconsistent", ekf.time, "single differences agree again")
        if sd_rows:
            self.integers.strike(sd_rows, res_sd.rejected)
            if res_sd.accepted:
                self.aligning = False
        return used

    @staticmethod
    def _innovations(eta: Sequence[EtaInput], ekf: ErrorStateEkf
                     ) -> tuple[list[EtaInput], np.ndarray]:
        """The η rows the update takes (over the interval since the EKF's clone), in its
        order, and their innovations against the INS's prediction (m/s)."""
        taken = [r for r in eta if ekf.interval_ok(r.interval)]
        pred = ekf.eta_rows([r.antenna for r in taken], [r.u_ned for r in taken],
                            [r.interval for r in taken])[0]
        return taken, np.array([r.measured for r in taken]) - pred

    @staticmethod
    def _fit(taken: Sequence[EtaInput], innovation: np.ndarray, ekf: ErrorStateEkf
             ) -> TdcpFit | None:
        """The epoch's η innovations fitted with a common correction (``cpp.tdcp_fit``)."""
        if not taken:
            return None
        return tdcp_fit([r.sat for r in taken], innovation, np.array([r.u_ned for r in taken]),
                        np.array([r.sigma for r in taken]), ekf.cfg.tdcp_rate_sigma)

    def _check_gated(self, turned: int, of: int, speed: float, what: str,
                     ekf: ErrorStateEkf) -> None:
        """Where the velocity check cannot run (1–3 satellites; the loose receivers'
        velocities), its stand-in: when the gate turned away ``turned`` of ``of`` (half or
        more), the INS and the carrier phase disagree and nothing can say which is right —
        left alone, the INS runs away while a satellite or two along the way keep the state
        "fused". Declared, and the INS widened by the largest disagreement turned away
        (``speed``, m/s), so that the next epoch takes it back (the directions it does not
        see stay wide: the protection level says so)."""
        if not turned or 2 * turned < of:
            if self.monitor.is_active("ins-velocity"):
                self.monitor.clear("ins-velocity", ekf.time,
                                   "INS velocity agrees with the carrier phase again")
            return
        interval = ekf.since_clone
        assert interval is not None  # (rows were taken: they span it)
        ekf.inflate(position_m=speed * interval, velocity_mps=speed, attitude_rad=0.0,
                    accel_bias=speed / interval)
        self.monitor.raise_fault(
            "ins-velocity", ekf.time, f"INS velocity up to {100 * speed:.0f} cm/s off the "
            f"carrier phase of {turned} of {of} {what}: INS widened")

    def _check_velocity(self, fit: TdcpFit, ekf: ErrorStateEkf) -> None:
        """The satellites, agreeing among themselves, against the INS's predicted velocity:
        beyond the χ² gate of both covariances the INS is off (an accelerometer bias step, a
        shock): every row would be gated out one by one and the INS would drift on unseen,
        trusted. Declared, and the INS widened by the disagreement (velocity, its change
        over the interval as an accelerometer bias, the position it may have moved) so this
        epoch's carrier phase takes it back; the widened σ sets the protection level until
        the bias is known again (not a critical fault: a slight disagreement need not cost
        the trust)."""
        interval = ekf.since_clone
        assert interval is not None  # (a fit exists: its rows span it)
        off = fit.correction[:3]
        S = ekf.mean_velocity_covariance(interval) + fit.covariance[:3, :3]
        if self._agrees("ins-velocity", off, S, ekf.time,
                        "INS velocity agrees with the carrier phase again"):
            return
        speed = float(np.linalg.norm(off))
        ekf.inflate(position_m=speed * interval, velocity_mps=speed, attitude_rad=0.0,
                    accel_bias=speed / interval)
        self.monitor.raise_fault(
            "ins-velocity", ekf.time,
            f"INS velocity {100 * speed:.0f} cm/s off the carrier phase of {fit.satellites} "
            + ("satellites that agree" if fit.satellites >= MIN_FIT_SATELLITES else
               "satellites (too few to check each other)") + ": INS taken back to it")

    def _check_attitude(self, sd_rows: Sequence[SdRow], ekf: ErrorStateEkf) -> None:
        """The single differences, agreeing among themselves, against the INS's attitude (the
        velocity check's twin for the gyro): their innovations fitted with a common rotation
        (``cpp.robust_lsq``), beyond the χ² gate of it and the attitude covariance the INS is
        off (a gyro bias step): the rows would pull it back a little each epoch while it runs
        away, and the heading stays degrees off under a protection level of tenths. Declared,
        and the attitude and gyro bias σ widened by the disagreement. Rows whose delay is not
        known yet (just found for a receiver that came back: centimetres, common to its pairs,
        which would read as a tilt) wait for the update that finds it."""
        interval = ekf.since_clone
        if len(sd_rows) < MIN_ATTITUDE_ROWS or not interval:
            return
        ix = ekf.ix
        P_D = ekf.covariance(ix.D)
        pred, H = ekf.sd_rows([r.ref for r in sd_rows], [r.other for r in sd_rows],
                              [r.los_ned for r in sd_rows])
        known = np.einsum("ij,jk,ik->i", H[:, ix.D], P_D, H[:, ix.D]) \
            <= ATTITUDE_DELAY_SIGMA_M ** 2
        s = math.sqrt(2.0) * np.array([r.sigma_m for r in sd_rows])  # two receivers' phases
        A = (H[:, ix.E] / s[:, None])[known]
        y = ((np.array([r.value_m for r in sd_rows]) - pred) / s)[known]
        if len(A) < MIN_ATTITUDE_ROWS or np.linalg.matrix_rank(A, tol=1e-6) < 3:
            return  # one baseline (two receivers left) cannot tell a turn about itself
        fit = robust_lsq(A, y, MIN_ATTITUDE_ROWS)
        if fit is None or np.linalg.matrix_rank(A[fit[3]], tol=1e-6) < 3:
            return
        off, inv, spread, _keep = fit
        # their own scatter (in units of the σ they state, which is generous: ~0.3), not
        # less than ATTITUDE_MIN_SPREAD of it
        P_sd = inv * max(spread, ATTITUDE_MIN_SPREAD) ** 2
        self._check_gyro(rotvec_to_dcm(-off) @ ekf.nominal.C_body_to_level, P_sd, ekf)
        S = ekf.covariance(ix.E) + P_sd
        if self._agrees("ins-attitude", off, S, ekf.time,
                        "INS attitude agrees with the single differences again"):
            return
        angle = float(np.linalg.norm(off))
        ekf.inflate(position_m=0.0, velocity_mps=0.0, attitude_rad=angle,
                    gyro_bias=angle / interval)
        self.monitor.raise_fault(
            "ins-attitude", ekf.time,
            f"INS attitude {math.degrees(angle):.1f}° off the single differences of "
            f"{len(sd_rows)} satellite pairs that agree: INS taken back to them")

    def _check_gyro(self, C_sd: np.ndarray, P_sd: np.ndarray, ekf: ErrorStateEkf) -> None:
        """The gyro against the single differences' attitude ``C_sd`` (covariance ``P_sd``)
        over seconds (``GyroCheck``): beyond the gate, declared ("gyro") and its bias σ
        widened to the rate it is off by, so that the VO and the single differences teach
        the EKF the new bias within seconds; cleared once the longest window agrees."""
        bias_var = float(np.linalg.eigvalsh(ekf.covariance(ekf.ix.BG))[-1])
        found = self.gyro.check(_HeadingEpoch(ekf.time, C_sd, float(P_sd[2, 2]),
                                              ekf.ins.C_gyro.copy(), bias_var,
                                              ekf.ins.bias_turn, ekf.ins.bias_yaw_rate),
                                measured=not self.monitor.imu_bridged())
        if found is None:
            if self.monitor.is_active("gyro") \
                    and self.gyro.spans(ekf.time) >= GYRO_CHECK_LONGEST_S:
                self.monitor.clear("gyro", ekf.time,
                                   "gyro agrees with the carrier-phase heading again")
            return
        angle, span = found
        rate = angle / span
        ekf.inflate(0.0, 0.0, 0.0, gyro_bias=math.sqrt(max(rate**2 - bias_var, 0.0)))
        self.gyro.restart()
        self.monitor.raise_fault(
            "gyro", ekf.time, f"gyro turned {math.degrees(angle):.1f}° off the carrier-phase "
            f"heading in {span:.0f} s: its bias re-learned from the carrier phase")

    def _agrees(self, kind: str, off: np.ndarray, S: np.ndarray, t: float,
                cleared: str) -> bool:
        """Whether the INS is within the χ² gate of the carrier phase's correction ``off``
        (covariance ``S``); if so, a ``kind`` fault still raised is cleared."""
        if float(off @ np.linalg.solve(S, off)) > chi2_gate(len(off), self.cfg.gate_probability):
            return False
        if self.monitor.is_active(kind):
            self.monitor.clear(kind, t, cleared)
        return True

    def _seed_delays(self, epochs: Sequence[GnssEpoch | None], geo: EpochGeometry,
                     ekf: ErrorStateEkf, origin: WorldOrigin) -> None:
        """The delays of receivers that have none yet: D̂_rj from the fractional parts of
        λΦ_rj − e·Ĉb_rj over all satellites (common clock: the same for every satellite),
        given the compass/INS attitude, against a receiver ``r`` already known — at the first
        epoch receiver 1, or the first one tracking when it is silent. A receiver silent
        until then is seeded when it comes (its δ̂ was never known: rounding its integers
        against a guess would fix them a fraction of a cycle off)."""
        present = [i for i, e in enumerate(epochs) if e is not None and e.satellites]
        waiting = [j for j in present if j not in self.delays_known]
        if not waiting or len(present) < 2 \
                or max(np.linalg.eigvalsh(ekf.covariance(ekf.ix.E))) > DELAY_SEED_ATTITUDE ** 2:
            return  # a fraction needs the baselines to ~1 cm
        known = [i for i in present if i in self.delays_known]
        ref = known[0] if known else present[0]
        # d_j − d_i = D̂_ij, d_0 ≡ 0; the first seed: ``ref``'s delay is the others' reference
        d = np.concatenate([[0.0], ekf.delays]) if known else np.zeros(len(ekf.delays) + 1)
        found = {j: self._delay_fraction(epochs, geo, ekf, origin, ref, j)
                 for j in waiting if j != ref}
        found = {j: d[ref] + f for j, f in found.items() if f is not None}
        if not found:
            return
        d[list(found)] = list(found.values())
        self.delays_known |= {ref, *found}
        if 0 in self.delays_known:
            d -= d[0]  # receiver 1's δ̂ is 0 by definition: a shift of all (pairs only differ)
            ekf.reset_delays(d[1:], self.cfg.init_delay)
        else:  # found against ``ref``: against receiver 1 they are a fraction of a cycle off
            ekf.reset_delays(d[1:], self.cfg.init_delay, reference=ref,
                             unknown=DELAY_UNKNOWN_M)

    def _delay_fraction(self, epochs: Sequence[GnssEpoch | None], geo: EpochGeometry,
                        ekf: ErrorStateEkf, origin: WorldOrigin, i: int, j: int
                        ) -> float | None:
        """D̂_ij modulo one wavelength (m), None when too few satellites or they disagree."""
        C = ekf.nominal.C_body_to_level
        b = C @ (ekf.lever_antennas[j] - ekf.lever_antennas[i])
        ei, ej = epochs[i], epochs[j]
        assert ei is not None and ej is not None
        phasors, lam = [], 0.0
        for sat, g in geo.satellites.items():
            if sat[0] not in SAME_CARRIER_SYSTEMS or sat not in ei.satellites \
                    or sat not in ej.satellites:
                continue
            sd = ei.satellites[sat].carrier_phase - ej.satellites[sat].carrier_phase
            if not math.isfinite(sd):
                continue
            lam = geo.wavelengths[sat]
            e = origin.C_ecef_to_level @ g.line_of_sight
            phasors.append(np.exp(2j * math.pi * (sd - e @ b / lam)))
        if len(phasors) < 3:
            return None
        mean = np.mean(phasors)
        if abs(mean) < DELAY_SEED_COHERENCE:
            return None  # the fractions disagree: the attitude is not good enough
        return float(lam * np.angle(mean) / (2 * math.pi))  # L1 only: one wavelength

    def _spp_aiding(self, spp_ecef: np.ndarray, ekf: ErrorStateEkf,
                    origin: WorldOrigin) -> None:
        """SPP: refine the absolute origin (llh output); aid the EKF when nothing else does."""
        spp_ned = ecef_to_ned(spp_ecef, origin.llh)
        if ekf.time - self.last_velocity_time <= GNSS_STALE_S:
            # Only while the trajectory is carrier-phase driven: not an INS drift estimate.
            offset = spp_ned - ekf.antenna_position(None)
            origin.offset_weight += 1.0
            origin.offset_ned += (offset - origin.offset_ned) / origin.offset_weight
        elif ekf.time - self.last_velocity_time > SPP_AIDING_AFTER_S:
            R = np.diag(np.square(SPP_SIGMA_M))
            ekf.update_position(spp_ned - origin.offset_ned, R)

    def _receiver_steps(self, t: float, prev: Sequence[GnssEpoch | None],
                        epochs: Sequence[GnssEpoch | None]) -> set[int]:
        """Receivers whose ranges all stepped against the others' (``cpp.receiver_steps``: its
        own clock or front end). Their satellites all "slip" (no velocity rows this epoch);
        here their single-difference delay and integers are dropped to be found afresh this
        epoch, and the fault is declared by name: a user trial's 10 µs step of receiver 2 was
        blamed on the INS, the gyro and the VO, the integers rounded against the old delay,
        and the heading left 0.4–0.9° off for 30 s."""
        steps = receiver_steps(prev, epochs, self.nav)
        for j in [j for j in self._stepped if j not in steps]:
            self.monitor.clear(f"receiver-{j + 1}-step", t,
                               f"receiver {j + 1}'s ranges continuous with the others' again")
        self._stepped = set(steps)
        for j, step in steps.items():
            self.delays_known.discard(j)
            self.integers.drop([key for key in self.integers.A if key[0] == j])
            self.monitor.raise_fault(
                f"receiver-{j + 1}-step", t,
                f"receiver {j + 1}'s ranges all jumped {step:+.1f} m against the other "
                f"receivers' ({step / SPEED_OF_LIGHT * 1e6:+.2f} µs of its clock): its carrier "
                "phase taken afresh")
        return self._stepped

    @staticmethod
    def _common_range_change(rows: Sequence[EtaRow], ekf: ErrorStateEkf) -> float:
        """The change of all ranges common to the satellites over the interval beyond the
        estimated clock drift (m): a ship moves metres, a receiver clock jump kilometres."""
        common = float(np.median([r.measured for r in rows])) - float(np.median(
            ekf.clock_drift))
        return common * float(np.median([r.interval for r in rows]))

    def carrier_fresh(self, t: float) -> bool:
        """Carrier-phase velocity accepted within the last ``GNSS_STALE_S``."""
        return t - self.last_velocity_time <= GNSS_STALE_S

    def velocity_held(self, t: float) -> bool:
        """The carrier phase holds the whole velocity: fresh, and from at least as many
        satellites as it has unknowns. With one to three, the directions they do not see
        are the INS's alone — a track to weigh by its own σ, not millimetres."""
        return self.carrier_fresh(t) and self.n_sats >= FIT_UNKNOWNS

    def attitude_held(self, t: float) -> bool:
        """The single differences hold the attitude: fresh, from as many satellites as the
        velocity needs, and neither the gyro nor the INS attitude declared off (the VO then
        must not pull it: ``ErrorStateEkf.update_vo``; once they are, it helps re-learn
        them)."""
        return (self.carrier_fresh(t) and self.n_sd_sats >= FIT_UNKNOWNS
                and not self.monitor.is_active("gyro")
                and not self.monitor.is_active("ins-attitude"))


def _gate_text(ekf: ErrorStateEkf) -> str:
    return ", ".join(f"{k} {v.rejected}/{v.accepted + v.rejected}"
                     for k, v in ekf.stats.items())
