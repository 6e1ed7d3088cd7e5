"""Thesis fig. 14: the heading from the single differences of ONE satellite, on one baseline
(each of the six) or on all six.

The pipeline cannot restrict baselines, so the heading is computed here with
``estimator.compass.attitude_from_single_differences`` (the snapshot) in
``estimator.heading_filter.HeadingFilter`` driven by the calibrated gyro: integers and
inter-receiver delays from a ``GnssCompass`` run on all satellites up to the window start and
then frozen, roll/pitch and the initial heading/gyro bias from the INS+VO+CPP run (the
estimator's own values). A cycle slip of the satellite ends its updates. The pipeline's own
heading with that satellite alone (all baselines, EKF) is listed beside it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from estimator.compass import CompassSolution, GnssCompass, attitude_from_single_differences
from estimator.cpp import (
    BASELINE_PAIRS,
    DEFAULT_PHASE_SIGMA_M,
    EpochGeometry,
    detect_cycle_slips,
    elevation_sigma,
    epoch_geometry,
)
from estimator.frames import euler_to_dcm, wrap_angle
from estimator.heading_filter import HeadingFilter
from estimator.ins import calibration_matrices
from estimator.records import GnssEpoch

from .records import SatelliteHeading, SingleSatelliteHeading
from .runs import FusionRun, RunSet
from .scoring import run_errors, trajectory_scores

TILT_SIGMA = math.radians(0.2)  # roll/pitch prior of the snapshot (from the INS)
INITIAL_HEADING_SIGMA = math.radians(0.1)
INITIAL_BIAS_SIGMA = math.radians(0.01)
METHOD = ("single differences of one satellite (integers and inter-receiver delays of a "
          "GnssCompass on all satellites, frozen at the window start) + calibrated gyro in a "
          "[heading, gyro bias] Kalman filter (4σ gate); roll/pitch, initial heading and gyro "
          "bias from the INS+VO+CPP run. snapshot = the single-epoch heading from the single "
          "differences (tilt from the INS, started from the filter's prediction), no gyro")


class OneSatelliteHeading:
    """The fig. 14 experiment on one recording (module docstring)."""

    def __init__(self, rs: RunSet, main: FusionRun, t0: float) -> None:
        rec = rs.rec
        self.rs, self.main, self.t0 = rs, main, t0
        self.antennas = np.asarray(rec.calibration.antennas_body, float)
        self.ok = np.flatnonzero(np.isfinite(main.euler).all(axis=1))
        self.fix: CompassSolution | None = None
        self.reason = ""
        if not len(self.ok) or main.origin_time is None:
            self.reason = "the INS+VO+CPP run never started"
            return
        compass = self._frozen_compass()
        if self.fix is None or compass.position is None:
            self.reason = "the GNSS compass holds no fix with delays at the window start"
            return
        self._gyro_yaw_rate(main.origin_time)
        self.window = [m for m in rs.gnss if m.t > t0 + 1e-6]
        self.geos: dict[float, EpochGeometry] = {}
        self._compass = compass

    def _frozen_compass(self) -> GnssCompass:
        """A compass on ALL satellites until the window start (its integers then frozen)."""
        compass = GnssCompass(self.rs.rec.nav, self.antennas)
        for m in self.rs.gnss:
            if m.t > self.t0 + 1e-6:
                break
            sol = compass.update(list(m.epochs), self.tilt(m.t))
            self.fix = sol if sol.fixed and sol.delays_m is not None else None
        return compass

    def _gyro_yaw_rate(self, origin_time: float) -> None:
        """Yaw rate from the calibrated gyro (roll/pitch of the INS); its bias against the
        fused heading change over the second half of the initialisation (at most 20 s): the
        first seconds hold the convergence of the fused heading itself."""
        imu_t, gyro = self.rs.imu
        G, _ = calibration_matrices(self.rs.rec.calibration.imu)
        w = gyro @ G.T
        eul = self.attitudes(imu_t)
        self.yaw_rate = (w[:, 1] * np.sin(eul[:, 0]) + w[:, 2] * np.cos(eul[:, 0])) \
            / np.maximum(np.cos(eul[:, 1]), 1e-6)
        self.dt = np.diff(imu_t, prepend=imu_t[0])
        t0, main = self.t0, self.main
        t_a = max(0.5 * (origin_time + t0), t0 - 20.0)
        span = (imu_t > t_a) & (imu_t <= t0)
        yaw = np.unwrap(main.euler[self.ok, 2])
        turn = np.interp(t0, main.time[self.ok], yaw) - np.interp(t_a, main.time[self.ok], yaw)
        self.bias0 = float((np.sum(self.yaw_rate[span] * self.dt[span]) - turn)
                           / max(t0 - t_a, 1e-3))

    def attitudes(self, t: np.ndarray) -> np.ndarray:
        """Roll, pitch, yaw of the INS+VO+CPP run at times ``t`` (nearest sample)."""
        tt = self.main.time[self.ok]
        k = np.clip(np.searchsorted(tt, t), 1, len(tt) - 1)
        k -= (np.abs(tt[k - 1] - t) < np.abs(tt[k] - t)).astype(int)
        return self.main.euler[self.ok][k]

    def tilt(self, t: float) -> tuple[float, float]:
        e = self.attitudes(np.array([t]))[0]
        return float(e[0]), float(e[1])

    def _geometry(self, t: float, sats: Sequence[str]) -> EpochGeometry:
        if t not in self.geos:
            c = self._compass
            self.geos[t] = epoch_geometry(self.rs.rec.nav, list(sats), t, c.position,
                                          c.clock_bias_s, 0.0)
        return self.geos[t]

    def _snapshot(self, sat: str, eps: list[GnssEpoch | None], geo: EpochGeometry,
                  pairs: Sequence[tuple[int, int]], t: float, heading: float
                  ) -> tuple[float, float] | None:
        """The single-epoch heading and its variance from the satellite's single
        differences on ``pairs`` (ζ_ij = λΦ_ij − D_ij − λN_ij, ``estimator/METHOD.md``)."""
        fix = self.fix
        assert fix is not None and fix.delays_m is not None
        lam = geo.wavelengths[sat]
        zetas: dict[tuple[int, int], dict[str, float]] = {}
        for i, j in pairs:
            a, b = eps[i], eps[j]
            if a is None or b is None or sat not in a.satellites or sat not in b.satellites:
                continue
            sd = a.satellites[sat].carrier_phase - b.satellites[sat].carrier_phase
            zetas[(i, j)] = {sat: lam * sd - fix.delays_m[(i, j)]
                             - lam * fix.integers[(i, j)][sat]}
        if not zetas:
            return None
        roll, pitch = self.tilt(t)
        sigma = elevation_sigma(DEFAULT_PHASE_SIGMA_M, geo.satellites[sat].elevation)
        att = attitude_from_single_differences(
            zetas, {sat: geo.los_ned(sat)}, self.antennas, euler_to_dcm(roll, pitch, heading),
            tilt=(roll, pitch), tilt_sigma_rad=TILT_SIGMA, sigma_u={sat: sigma})
        if att is None or not math.isfinite(att.covariance[2, 2]):
            return None
        return float(att.euler[2]), float(att.covariance[2, 2])

    def run(self, sat: str, pairs: Sequence[tuple[int, int]], sats: Sequence[str]
            ) -> tuple[np.ndarray, np.ndarray, int]:
        """Filtered and snapshot heading errors (rad) over the window epochs, and the number of
        accepted updates. A slip of the satellite at a receiver in use ends the updates (the
        frozen integer is no longer valid)."""
        imu_t = self.rs.imu[0]
        filt = HeadingFilter(float(self.attitudes(np.array([self.t0]))[0][2]), self.bias0,
                             INITIAL_HEADING_SIGMA, INITIAL_BIAS_SIGMA)
        ref_yaw = self.rs.rec.reference.interpolate(  # type: ignore[union-attr]
            np.array([m.t for m in self.window]))[2][:, 2]
        receivers = {i for p in pairs for i in p}
        t_prev, prev, slipped, used = self.t0, None, False, 0
        filtered, snapshot = [], []
        for k, m in enumerate(self.window):
            sel = (imu_t > t_prev) & (imu_t <= m.t)
            filt.predict(self.yaw_rate[sel], self.dt[sel], m.t - t_prev)
            t_prev = m.t
            eps = [None if e is None else GnssEpoch(
                e.time, {s: o for s, o in e.satellites.items() if s == sat}, e.flag)
                for e in m.epochs]
            if prev is not None and any(i in receivers for i, _ in detect_cycle_slips(prev, eps)):
                slipped = True
            prev = eps
            geo = self._geometry(m.t, sats)
            snap = math.nan
            if not slipped and sat in geo.satellites:
                got = self._snapshot(sat, eps, geo, pairs, m.t, filt.heading)
                if got is not None:
                    snap = got[0]
                    used += int(filt.update(*got))
            filtered.append(filt.heading - ref_yaw[k])
            snapshot.append(snap - ref_yaw[k])
        return wrap_angle(np.array(filtered)), wrap_angle(np.array(snapshot)), used

    def report(self, sats: list[str], pipeline: dict[str, FusionRun]) -> SingleSatelliteHeading:
        out = SingleSatelliteHeading(method=METHOD)
        if self.fix is None:
            out.reason = self.reason
            return out
        configs = [("all six", BASELINE_PAIRS)] + [(f"{i}-{j}", ((i, j),))
                                                   for i, j in BASELINE_PAIRS]
        for sat in sats:
            g0 = self._geometry(self.window[0].t, sats).satellites.get(sat) \
                if self.window else None
            entry = SatelliteHeading(sat, None if g0 is None else math.degrees(g0.elevation))
            for name, pairs in configs:
                pairs = tuple(p for p in pairs if sat in self.fix.integers.get(p, {}))
                filt = snap = np.zeros(0)
                used = 0
                if pairs and self.window:
                    filt, snap, used = self.run(sat, pairs, sats)
                snap = snap[np.isfinite(snap)]
                entry.heading_std_deg[name] = float(np.degrees(np.std(filt))) \
                    if len(filt) else None
                entry.heading_max_deg[name] = float(np.degrees(np.abs(filt).max())) \
                    if len(filt) else None
                entry.snapshot_std_deg[name] = float(np.degrees(np.std(snap))) \
                    if len(snap) else None
                entry.updates[name] = used
            run = pipeline.get(sat)
            if run is not None:
                err = run_errors(run, self.rs.rec.reference, self.rs.start, self.t0)
                entry.pipeline_all_baselines_std_deg = trajectory_scores(err, 1).heading_std_deg
            out.satellites.append(entry)
        _worst(out)
        return out


def _worst(out: SingleSatelliteHeading) -> None:
    """The worst single baseline and the worst "all six" of the satellites."""
    for key in ("heading_std_deg", "snapshot_std_deg"):
        singles = [v for e in out.satellites for k, v in getattr(e, key).items()
                   if k != "all six" and v is not None]
        sixes = [getattr(e, key)["all six"] for e in out.satellites
                 if getattr(e, key).get("all six") is not None]
        setattr(out, f"worst_single_baseline_{key}", max(singles) if singles else None)
        setattr(out, f"worst_all_six_{key}", max(sixes) if sixes else None)
