"""``berthing-aid compass RECORDING``: GNSS compass and carrier-phase velocity vs the reference.

Over ``trials`` cold starts spread over the recording, both attitude methods of
``estimator.compass`` (the thesis' fast method and the conventional float-KF + LAMBDA) are run:
time to fix (fraction fixed within 1, 10 and 150 s, as thesis fig. 13 — a fix with the first
epoch counts as 1 s), wrong fixes (heading error > 3° at the fix), heading/pitch/roll errors of
the fixed epochs. Then one pass over the recording compares the velocity of the antenna array
loosely coupled (mean of the four receivers' TDCP velocities) and tightly coupled (η rows of
all receivers with one clock drift: snapshot and short filter) with the reference, with all
satellites and with only 4 (one per receiver, thesis table 21), 3 or 2 satellites kept after
the first ``reduced_after_s`` seconds.

``sky_mask_deg`` blocks the satellites whose azimuth lies within ±sky_mask/2 of
``sky_mask_centre_deg`` (north: the quay side of the simulated berths), e.g. 180 = the half sky
of the thesis' experiment (fig. 12). ``gps_only`` restricts both compass and velocity to GPS.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from estimator.compass import GnssCompass, tilt_from_specific_force
from estimator.cpp import (
    EpochGeometry,
    TightVelocityFilter,
    align_epochs,
    epoch_geometry,
    eta_observations,
    loose_velocity,
    tight_velocity,
)
from estimator.frames import SPEED_OF_LIGHT, euler_to_dcm, ned_to_ecef, wrap_angle
from estimator.records import GnssEpoch
from estimator.spp import standalone_position
from recordings.format import Recording, load

from .gnss_records import (
    ArrayVelocity,
    AttitudeErrors,
    CompassMethodScores,
    CompassReport,
    CompassTrial,
    VelocityErrorStats,
)

WRONG_FIX_DEG = 3.0
SWITCH_CONFIGS = ("4 satellites, one per receiver", "3 satellites", "2 satellites")


def _rms(values: list[float] | np.ndarray) -> float | None:
    a = np.asarray(values, dtype=float)
    return float(np.sqrt(np.mean(a**2))) if a.size else None


def _filter_epoch(ep: GnssEpoch | None, keep: set[str] | None, systems: str
                  ) -> GnssEpoch | None:
    if ep is None:
        return None
    return GnssEpoch(ep.time, {s: o for s, o in ep.satellites.items()
                               if s[0] in systems and (keep is None or s in keep)}, ep.flag)


class _Prepared:
    """Per-epoch inputs shared by the compass trials and the velocity pass."""

    def __init__(self, rec: Recording, systems: str, sky_mask_deg: float,
                 centre_deg: float) -> None:
        self.rec = rec
        self.nav = rec.nav
        self.antennas = np.asarray(rec.calibration.antennas_body, dtype=float)
        self.centroid = self.antennas.mean(axis=0)
        origin = np.asarray(rec.manifest.origin_llh, dtype=float)
        ref = rec.reference
        if ref is None:
            raise ValueError(f"{rec.manifest.name}: no reference trajectory to score against")
        rows = align_epochs(rec.gnss)
        self.times: list[float] = []
        self.epochs: list[list[Any]] = []
        self.tilt: list[tuple[float, float] | None] = []
        self.euler_ref: list[np.ndarray] = []
        self.masked: dict[str, int] = {}
        imu = rec.imu
        for t, eps in rows:
            pos, _, eul = ref.interpolate(t)
            if not np.all(np.isfinite(pos)):
                continue  # outside the reference: cannot be scored
            keep = None
            if sky_mask_deg > 0.0:
                # The environment blocks satellites: decided from the true antenna position.
                rx = ned_to_ecef(pos, origin)
                sats = sorted({s for e in eps if e is not None for s in e.satellites})
                geo = epoch_geometry(self.nav, sats, t, rx, 0.0, 0.0)
                keep = set()
                for s, g in geo.satellites.items():
                    off = (math.degrees(g.azimuth) - centre_deg + 180.0) % 360.0 - 180.0
                    if abs(off) > sky_mask_deg / 2.0:
                        keep.add(s)
                    else:
                        self.masked[s] = self.masked.get(s, 0) + 1
            self.times.append(t)
            self.epochs.append([_filter_epoch(e, keep, systems) for e in eps])
            self.euler_ref.append(np.asarray(eul))
            sel = (imu.time >= t - 0.5) & (imu.time <= t + 0.5)
            self.tilt.append(tilt_from_specific_force(imu.accel[sel].mean(axis=0))
                             if np.any(sel) else None)
        if len(self.times) < 2:
            raise ValueError(f"{rec.manifest.name}: fewer than 2 GNSS epochs inside the reference")
        self.interval = float(np.median(np.diff(self.times)))

    def gyro_mean(self, t1: float, t2: float) -> np.ndarray | None:
        imu = self.rec.imu
        sel = (imu.time >= t1) & (imu.time <= t2)
        return imu.gyro[sel].mean(axis=0) if np.any(sel) else None

    def centroid_velocity(self, t1: float, t2: float) -> np.ndarray:
        """True mean velocity of the antenna centroid over [t1, t2] (NED m/s)."""
        ends = []
        for t in (t1, t2):
            pos, _, eul = self.rec.reference.interpolate(t)
            ends.append(pos + euler_to_dcm(*eul) @ self.centroid)
        return (ends[1] - ends[0]) / (t2 - t1)


# ------------------------------------------------------------------------ attitude


def _cold_start(prep: _Prepared, method: str, s: int, systems: str, max_window_s: float,
                hold_window_s: float) -> tuple[CompassTrial, list[np.ndarray]]:
    """One cold start at epoch ``s``: the trial and the attitude errors (deg; roll, pitch,
    heading) of its fixed epochs, the first at the fix."""
    comp = GnssCompass(prep.nav, prep.antennas, method=method, systems=systems)
    t0 = prep.times[s]
    trial = CompassTrial(start_gpst=t0, time_to_fix_s=None,
                         window_s=min(max_window_s, prep.times[-1] - t0 + prep.interval))
    errors: list[np.ndarray] = []
    fix_time = None
    for k in range(s, len(prep.times)):
        t = prep.times[k]
        if t - t0 >= max_window_s or (fix_time is not None and t - fix_time > hold_window_s):
            break
        sol = comp.update(prep.epochs[k], prep.tilt[k])
        if not sol.fixed:
            continue
        err = np.degrees(wrap_angle(sol.euler - prep.euler_ref[k]))
        errors.append(err)
        if fix_time is None:
            fix_time = t
            trial = dataclasses.replace(
                trial, time_to_fix_s=t - t0 + prep.interval, satellites=sol.n_satellites,
                heading_error_deg=float(err[2]), wrong=bool(abs(err[2]) > WRONG_FIX_DEG))
    return trial, errors


def _run_trials(prep: _Prepared, method: str, starts: list[int], systems: str,
                max_window_s: float, hold_window_s: float, keep_trials: bool
                ) -> CompassMethodScores:
    """Cold starts of one method at the epochs ``starts``: fig. 13's fractions and the errors."""
    per_trial, errors, first_errors = [], [], []
    for s in starts:
        trial, errs = _cold_start(prep, method, s, systems, max_window_s, hold_window_s)
        per_trial.append(trial)
        errors += errs
        first_errors += errs[:1]
    ttf = [e.time_to_fix_s for e in per_trial]
    n = len(per_trial)

    def within(limit: float) -> float:
        return sum(1 for x in ttf if x is not None and x <= limit + 1e-6) / max(n, 1)

    fixed = [e for e in per_trial if e.time_to_fix_s is not None]
    E = np.array(errors).reshape(-1, 3)
    F = np.array(first_errors).reshape(-1, 3)
    return CompassMethodScores(
        trials=n,
        fixed_within_1s=within(1.0),
        fixed_within_10s=within(10.0),
        fixed_within_150s=within(150.0),
        median_time_to_fix_s=float(np.median([x for x in ttf if x is not None]))
        if fixed else None,
        wrong_fixes=sum(1 for e in fixed if e.wrong),
        wrong_fix_rate=(sum(1 for e in fixed if e.wrong) / len(fixed)) if fixed else None,
        first_fix_heading_rms_deg=_rms(F[:, 2]),
        attitude_error_deg=AttitudeErrors(
            epochs=int(len(E)),
            heading_rms=_rms(E[:, 2]), pitch_rms=_rms(E[:, 1]), roll_rms=_rms(E[:, 0]),
            heading_max=float(np.abs(E[:, 2]).max()) if len(E) else None),
        per_trial=per_trial if keep_trials else None,
    )


# ------------------------------------------------------------------------ velocity


class _VelocityErrors:
    """The array velocity errors of one satellite configuration over the pass."""

    def __init__(self) -> None:
        self.filter = TightVelocityFilter(vertical_sigma_mps=0.1)
        self.errors: dict[str, list[np.ndarray]] = {"loose": [], "tight": [], "tight filter": []}
        self.count = 0
        self.prev: list[GnssEpoch | None] | None = None

    def step(self, prep: _Prepared, cur: list[GnssEpoch | None], prev_geo: EpochGeometry | None,
             geo: EpochGeometry, C: np.ndarray | None, scored: bool) -> None:
        """One epoch: loose (mean of the receivers' TDCP), tight snapshot and tight filter."""
        if self.prev is not None and prev_geo is not None:
            t = geo.time
            eta = eta_observations(self.prev, cur, prev_geo, geo)
            truth = prep.centroid_velocity(prev_geo.time, t)
            self.count += int(scored)
            loose = [loose_velocity(eta.for_antenna(i), geo.C_ecef_to_level)
                     for i in range(len(cur))]
            lever = dict(lever_arms_body=prep.antennas - prep.centroid if C is not None else None,
                         C_body_to_level=C, omega_body=prep.gyro_mean(prev_geo.time, t))
            snap = tight_velocity(eta.rows, **lever)
            filt = self.filter.step(eta.rows, t, **lever)
            if scored and all(v is not None for v in loose):
                self.errors["loose"].append(np.mean([v.velocity_ned for v in loose], 0) - truth)
            if scored and snap is not None:
                self.errors["tight"].append(snap.velocity_ned - truth)
            if scored and filt is not None:
                self.errors["tight filter"].append(filt.velocity_ned - truth)
        self.prev = cur

    def summary(self) -> dict[str, VelocityErrorStats]:
        """Per estimator ("loose", "tight", "tight filter")."""
        out = {}
        for name, errs in self.errors.items():
            E = np.array(errs).reshape(-1, 3)
            out[name] = VelocityErrorStats(solved_fraction=len(E) / max(self.count, 1),
                                           horizontal_rms_mps=_rms(np.hypot(E[:, 0], E[:, 1])),
                                           vertical_rms_mps=_rms(E[:, 2]))
        return out


def _configured(c: str, eps: list[GnssEpoch | None], kept: dict[str, list[str]]
                ) -> list[GnssEpoch | None]:
    """The epochs of one satellite configuration (all until the switch)."""
    if c == "all satellites" or not kept:
        return eps
    if c == SWITCH_CONFIGS[0]:
        # Thesis table 21: each receiver tracks a different single satellite.
        return [_filter_epoch(e, set(kept[c][i:i + 1]), "GEJRC") for i, e in enumerate(eps)]
    return [_filter_epoch(e, set(kept[c]), "GEJRC") for e in eps]


def _velocity_pass(prep: _Prepared, reduced_after_s: float) -> ArrayVelocity:
    compass = GnssCompass(prep.nav, prep.antennas, method="fast")
    t_switch = prep.times[0] + reduced_after_s
    configs = ("all satellites", *SWITCH_CONFIGS)
    passes = {c: _VelocityErrors() for c in configs}
    kept: dict[str, list[str]] = {}
    prev_geo = None
    position, clock = None, 0.0
    for k, (t, eps) in enumerate(zip(prep.times, prep.epochs, strict=True)):
        present = [e for e in eps if e is not None]
        spp = standalone_position(present, prep.nav, initial_ecef=position) if present else None
        if spp is not None:
            position, clock = spp.position, spp.clock_bias_m / SPEED_OF_LIGHT
        sol = compass.update(eps, prep.tilt[k])
        if position is None:
            continue
        sats = sorted({s for e in present for s in e.satellites})
        geo = epoch_geometry(prep.nav, sats, t, position, clock)
        if t >= t_switch and not kept:
            common = [s for s in geo.satellites
                      if all(e is not None and s in e.satellites for e in eps)]
            common.sort(key=lambda s: -geo.satellites[s].elevation)
            kept = {c: common[:n] for c, n in zip(SWITCH_CONFIGS, (4, 3, 2), strict=True)}
        C = sol.C_body_to_level if sol.fixed else None
        for c in configs:
            passes[c].step(prep, _configured(c, eps, kept), prev_geo, geo, C,
                           scored=c == "all satellites" or bool(kept))
        prev_geo = geo
    return ArrayVelocity(reduced_after_s=reduced_after_s,
                         kept_satellites={c: kept.get(c) for c in SWITCH_CONFIGS},
                         configurations={c: passes[c].summary() for c in configs})


# -------------------------------------------------------------------------- report


def compass_report_for(
    rec: Any,
    trials: int = 20,
    gps_only: bool = False,
    sky_mask_deg: float = 0.0,
    as_json: bool = False,
    *,
    sky_mask_centre_deg: float = 0.0,
    max_window_s: float = 150.0,
    hold_window_s: float = 20.0,
    reduced_after_s: float = 10.0,
    velocity: bool = True,
) -> CompassReport:
    """The report on an already loaded recording (anything with ``gnss``, ``nav``,
    ``calibration.antennas_body``, ``imu``, ``reference`` and ``manifest``). ``as_json`` keeps
    the per-trial results (``records.to_json`` gives the JSON)."""
    systems = "G" if gps_only else "GEJ"
    prep = _Prepared(rec, systems, sky_mask_deg, sky_mask_centre_deg)
    n = len(prep.times)
    last_start = max(n - min(10, n // 2), 1)
    starts = sorted(set(np.linspace(0, last_start - 1, max(trials, 1)).round().astype(int)))
    return CompassReport(
        recording=getattr(rec.manifest, "name", "?"),
        epochs=n,
        interval_s=prep.interval,
        systems=systems,
        sky_mask_deg=sky_mask_deg,
        sky_mask_centre_deg=sky_mask_centre_deg,
        masked_satellites=sorted(prep.masked),
        trials=len(starts),
        methods={m: _run_trials(prep, m, starts, systems, max_window_s, hold_window_s,
                                keep_trials=as_json)
                 for m in ("fast", "conventional")},
        velocity_error=_velocity_pass(prep, reduced_after_s) if velocity else None,
    )


def compass_report(recording_path: str | Path, trials: int = 20, gps_only: bool = False,
                   sky_mask_deg: float = 0.0, as_json: bool = False, **options: Any
                   ) -> CompassReport:
    """Load a recording (``recordings.format.load``) and run :func:`compass_report_for`."""
    return compass_report_for(load(recording_path), trials=trials, gps_only=gps_only,
                              sky_mask_deg=sky_mask_deg, as_json=as_json, **options)


def _f(x: Any, spec: str = ".3f") -> str:
    return "-" if x is None else format(x, spec)


def format_compass_report(report: CompassReport) -> str:
    """Readable tables of :func:`compass_report`."""
    lines = [
        f"{report.recording}: {report.epochs} epochs, systems {report.systems}, "
        f"sky mask {report.sky_mask_deg:g} deg around azimuth "
        f"{report.sky_mask_centre_deg:g}, {report.trials} cold starts",
        "",
        "attitude fix     <=1 s   <=10 s  <=150 s  median  wrong  1st-fix hdg RMS  "
        "hdg RMS  pitch RMS  roll RMS (deg)",
    ]
    for name, m in report.methods.items():
        a = m.attitude_error_deg
        lines.append(
            f"  {name:<13} {100 * m.fixed_within_1s:5.0f}%  {100 * m.fixed_within_10s:5.0f}%"
            f"  {100 * m.fixed_within_150s:5.0f}%  {_f(m.median_time_to_fix_s, '5.0f')} s"
            f"  {m.wrong_fixes:5d}  {_f(m.first_fix_heading_rms_deg):>15}"
            f"  {_f(a.heading_rms):>7}  {_f(a.pitch_rms):>9}  {_f(a.roll_rms):>8}")
    v = report.velocity_error
    if v is not None:
        lines += ["", f"velocity error of the array (m/s); reduced sets after "
                      f"{v.reduced_after_s:g} s: {v.kept_satellites}",
                  f"  {'satellites':<32} {'estimator':<13} solved  horiz RMS  vert RMS"]
        for c, per in v.configurations.items():
            for name, e in per.items():
                lines.append(f"  {c:<32} {name:<13} {100 * e.solved_fraction:5.0f}%  "
                             f"{_f(e.horizontal_rms_mps, '9.4f')}  "
                             f"{_f(e.vertical_rms_mps, '8.4f')}")
    return "\n".join(lines)
