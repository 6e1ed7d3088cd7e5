"""``berthing-aid baseline BASE.obs ROVER.obs NAV``: two real receivers, separate clocks.

What it measures, on any pair of RINEX files with carrier phase:
- the fixed baseline (north, east, up), its length and azimuth at every epoch, from one
  continuous run of the double-difference filter (``estimator.baseline``);
- the time to first fix from a cold start at restarts every ``restart_every_s``;
- the TDCP velocity of each receiver (``estimator.cpp``) and its RMS — the receivers of a
  static test are at rest, so the RMS is the velocity error.
With surveyed positions (``--surveyed`` or ``<obs stem>_position.txt`` beside each file, one line
"lat lon h" in degrees and metres) the fixed baselines are scored and wrong fixes counted.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from estimator.baseline import RelativePositioning, same_carrier_epoch
from estimator.cpp import (
    SAME_CARRIER_SYSTEMS,
    align_epochs,
    epoch_geometry,
    eta_observations,
    loose_velocity,
)
from estimator.frames import SPEED_OF_LIGHT, ecef_to_ned, geodetic_to_ecef
from estimator.records import GnssEpoch, NavigationData
from estimator.spp import StandalonePosition, standalone_position
from recordings.rinex import l1_epochs, read_nav, read_obs

from .gnss_records import (
    BaselineEpoch,
    BaselineReport,
    BaselineRestart,
    FixedBaseline,
    ReceiverVelocity,
    SurveyedScores,
    TimeToFix,
    ValueStats,
)
from .records import finite

# A fixed baseline further than this from the surveyed one has wrong integers (the nearest
# wrong integer set moves it by a large fraction of the 19 cm wavelength).
WRONG_FIX_M = 0.05


def read_position(path: Path) -> np.ndarray:
    values = [float(v) for v in path.read_text().split()[:3]]
    if len(values) != 3:
        raise ValueError(f"{path}: expected 'lat lon height' (deg, deg, m)")
    return np.array(values)


def _auto_position(obs_path: Path) -> np.ndarray | None:
    candidate = obs_path.with_name(obs_path.stem + "_position.txt")
    return read_position(candidate) if candidate.is_file() else None


def _epochs(obs: Any) -> list:
    if isinstance(obs, str | Path):
        return l1_epochs(read_obs(obs))
    return list(obs)


def _stats(values: list[float]) -> ValueStats:
    if not values:
        return ValueStats(mean=None, std=None, min=None, max=None)
    a = np.asarray(values, dtype=float)
    return ValueStats(mean=float(a.mean()), std=float(a.std()), min=float(a.min()),
                      max=float(a.max()))


def _standalone(epochs: list, nav: NavigationData) -> list[StandalonePosition | None]:
    """Standalone solution (GPS/Galileo/QZSS) of every epoch of one receiver, or None."""
    out, position = [], None
    for ep in epochs:
        spp = standalone_position(same_carrier_epoch(ep), nav, initial_ecef=position)
        if spp is not None:
            position = spp.position
        out.append(spp)
    return out


def _velocity_of(epochs: list, spps: list, nav: Any) -> ReceiverVelocity:
    """TDCP velocity of one receiver at every epoch (its own position and clock)."""
    prev_epoch = prev_geo = None
    position, clock = None, 0.0
    v_ned, excluded = [], {}
    for ep, spp in zip(epochs, spps, strict=True):
        if spp is not None:
            position, clock = spp.position, spp.clock_bias_m / SPEED_OF_LIGHT
        if position is None:
            continue
        sats = [s for s in ep.satellites if s[0] in SAME_CARRIER_SYSTEMS]
        geo = epoch_geometry(nav, sats, ep.time, position, clock)
        if prev_geo is not None:
            eta = eta_observations([prev_epoch], [ep], prev_geo, geo, common_clock=False)
            v = loose_velocity(eta.rows, geo.C_ecef_to_level)
            if v is not None:
                v_ned.append(v.velocity_ned)
                for why in v.excluded.values():
                    excluded[why] = excluded.get(why, 0) + 1
                slips = sum(1 for why in eta.rejected.values() if why.startswith("Doppler"))
                key = "cycle slip (Doppler)"
                if slips:
                    excluded[key] = excluded.get(key, 0) + slips
        prev_epoch, prev_geo = ep, geo
    if not v_ned:
        return ReceiverVelocity(epochs=0)
    V = np.array(v_ned)
    horiz = np.hypot(V[:, 0], V[:, 1])
    return ReceiverVelocity(
        epochs=len(V),
        horizontal_rms_mps=float(np.sqrt(np.mean(horiz**2))),
        vertical_rms_mps=float(np.sqrt(np.mean(V[:, 2] ** 2))),
        max_horizontal_mps=float(horiz.max()),
        mean_ned_mps=V.mean(axis=0).tolist(),
        excluded={k: v for k, v in excluded.items() if k != "below elevation mask"},
    )


Rows = list[tuple[float, GnssEpoch, GnssEpoch]]  # common epochs: time, base, rover


def baseline_report(
    base_obs: str | Path | list,
    rover_obs: str | Path | list,
    nav: Any,
    as_json: bool = False,
    *,
    restart_every_s: float = 20.0,
    max_time_to_fix_s: float = 120.0,
    elevation_mask_deg: float = 15.0,
    base_position_llh_deg: np.ndarray | None = None,
    rover_position_llh_deg: np.ndarray | None = None,
) -> BaselineReport:
    """Baseline, time to fix and TDCP velocity of two receivers (see the module docstring).

    ``base_obs``/``rover_obs``: RINEX paths or lists of ``GnssEpoch``; ``nav``: a path or a
    ``NavigationData``. ``as_json`` adds the per-epoch series (``records.to_json`` gives the
    JSON).
    """
    if base_position_llh_deg is None and isinstance(base_obs, str | Path):
        base_position_llh_deg = _auto_position(Path(base_obs))
    if rover_position_llh_deg is None and isinstance(rover_obs, str | Path):
        rover_position_llh_deg = _auto_position(Path(rover_obs))
    nav_data = read_nav(nav) if isinstance(nav, str | Path) else nav
    rows = [(t, ea, eb) for t, (ea, eb) in align_epochs([_epochs(base_obs), _epochs(rover_obs)])
            if ea is not None and eb is not None]
    if len(rows) < 2:
        raise ValueError("the two files have fewer than 2 common epochs")
    if all(ea.satellites == eb.satellites for _t, ea, eb in rows):
        raise ValueError("the base and rover observations are the same, epoch for epoch (the "
                         "same file twice?): a baseline needs two receivers")
    interval = float(np.median(np.diff([r[0] for r in rows])))
    truth = _surveyed_baseline(base_position_llh_deg, rover_position_llh_deg)
    # Standalone solutions once per epoch and receiver, shared by every run below.
    spps = (_standalone([r[1] for r in rows], nav_data),
            _standalone([r[2] for r in rows], nav_data))
    per_epoch = _continuous(rows, spps, nav_data, elevation_mask_deg)
    fixed = [p for p in per_epoch if p.fixed]
    restarts = _restarts(rows, spps, nav_data, elevation_mask_deg, interval, restart_every_s,
                         max_time_to_fix_s, truth)
    ttf = [r.time_to_fix_s for r in restarts if r.time_to_fix_s is not None]
    stats = FixedBaseline(*(_stats([getattr(p, key) for p in fixed])
                            for key in ("north", "east", "up", "length", "azimuth_deg")))
    return BaselineReport(
        epochs=len(rows),
        interval_s=interval,
        fixed_fraction=len(fixed) / max(len(per_epoch), 1),
        fixed=stats,
        restarts=restarts,
        time_to_fix=TimeToFix(restarts=len(restarts), fixed=len(ttf),
                              max_s=max(ttf) if ttf else None,
                              median_s=float(np.median(ttf)) if ttf else None),
        velocity={"base": _velocity_of([r[1] for r in rows], spps[0], nav_data),
                  "rover": _velocity_of([r[2] for r in rows], spps[1], nav_data)},
        surveyed=_surveyed_scores(truth, fixed, restarts, stats) if truth is not None else None,
        per_epoch=per_epoch if as_json else None,
    )


def _surveyed_baseline(base_llh_deg: np.ndarray | None, rover_llh_deg: np.ndarray | None
                       ) -> np.ndarray | None:
    """The surveyed base → rover baseline (NED at the base), None without both positions."""
    if base_llh_deg is None or rover_llh_deg is None:
        return None
    bl = np.asarray(base_llh_deg, dtype=float)
    rl = np.asarray(rover_llh_deg, dtype=float)
    base_llh = np.array([math.radians(bl[0]), math.radians(bl[1]), bl[2]])
    rover_ecef = geodetic_to_ecef(math.radians(rl[0]), math.radians(rl[1]), rl[2])
    return ecef_to_ned(rover_ecef, base_llh)


def _continuous(rows: Rows, spps: tuple[list, list], nav: NavigationData,
                elevation_mask_deg: float) -> list[BaselineEpoch]:
    """One continuous run: the baseline at every epoch."""
    rp = RelativePositioning(nav, elevation_mask_deg=elevation_mask_deg)
    per_epoch = []
    for k, (t, ea, eb) in enumerate(rows):
        sol = rp.update(ea, eb, spps[0][k], spps[1][k])
        if sol is None:
            continue
        n, e, d = (float(x) for x in sol.baseline_ned)
        per_epoch.append(BaselineEpoch(
            time_gpst=t, fixed=sol.fixed, north=n, east=e, up=-d, length=sol.length,
            azimuth_deg=sol.azimuth_deg, ratio=finite(sol.ratio), satellites=sol.n_satellites))
    return per_epoch


def _restarts(rows: Rows, spps: tuple[list, list], nav: NavigationData,
              elevation_mask_deg: float, interval: float, restart_every_s: float,
              max_time_to_fix_s: float, truth: np.ndarray | None) -> list[BaselineRestart]:
    """Cold starts at regular restarts: time to fix and the fixed baseline."""
    restarts = []
    start, t_end = rows[0][0], rows[-1][0]
    while start <= t_end - 1e-6:
        rp = RelativePositioning(nav, elevation_mask_deg=elevation_mask_deg)
        entry = BaselineRestart(start_gpst=start, time_to_fix_s=None)
        for k, (t, ea, eb) in enumerate(rows):
            if t < start - 1e-6:
                continue
            if t - start > max_time_to_fix_s:
                break
            sol = rp.update(ea, eb, spps[0][k], spps[1][k])
            if sol is not None and sol.fixed:
                error = (float(np.linalg.norm(sol.baseline_ned - truth)) if truth is not None
                         else None)
                entry = BaselineRestart(start_gpst=start, time_to_fix_s=t - start + interval,
                                        length=sol.length, azimuth_deg=sol.azimuth_deg,
                                        error_m=error)
                break
        restarts.append(entry)
        start += restart_every_s
    return restarts


def _surveyed_scores(truth: np.ndarray, fixed: list[BaselineEpoch],
                     restarts: list[BaselineRestart], stats: FixedBaseline) -> SurveyedScores:
    """The fixed baselines against the surveyed one: errors and wrong fixes."""
    length = float(np.linalg.norm(truth))
    az = float(np.degrees(np.arctan2(truth[1], truth[0])) % 360.0)
    errors = [np.linalg.norm(np.array([p.north, p.east, -p.up]) - truth) for p in fixed]
    wrong = sum(1 for x in errors if x > WRONG_FIX_M)
    wrong += sum(1 for r in restarts if r.error_m is not None and r.error_m > WRONG_FIX_M)
    return SurveyedScores(
        north=float(truth[0]), east=float(truth[1]), up=float(-truth[2]),
        length=length, azimuth_deg=az,
        length_error_m=(stats.length.mean - length) if fixed else None,
        azimuth_error_deg=(float((stats.azimuth_deg.mean - az + 180.0) % 360.0 - 180.0)
                           if fixed else None),
        max_error_m=float(max(errors)) if errors else None,
        wrong_fixes=wrong,
    )


def _fmt(x: Any, spec: str = ".4f") -> str:
    return "-" if x is None else format(x, spec)


def format_baseline_report(report: BaselineReport) -> str:
    """Readable table of :func:`baseline_report`."""
    f = report.fixed
    lines = [
        f"epochs {report.epochs} at {report.interval_s:g} s, "
        f"fixed {100 * report.fixed_fraction:.1f} %",
        "",
        "fixed baseline (m)      mean        std",
    ]
    for key in ("north", "east", "up", "length"):
        stats = getattr(f, key)
        lines.append(f"  {key:<12} {_fmt(stats.mean):>12} {_fmt(stats.std):>10}")
    lines.append(f"  {'azimuth deg':<12} {_fmt(f.azimuth_deg.mean, '.3f'):>12} "
                 f"{_fmt(f.azimuth_deg.std, '.3f'):>10}")
    if report.surveyed is not None:
        s = report.surveyed
        lines += ["", f"surveyed: length {s.length:.4f} m, azimuth {s.azimuth_deg:.3f} deg"
                      f" -> errors {_fmt(s.length_error_m)} m, "
                      f"{_fmt(s.azimuth_error_deg, '.3f')} deg, max 3-D "
                      f"{_fmt(s.max_error_m)} m, wrong fixes {s.wrong_fixes}"]
    t = report.time_to_fix
    lines += ["", f"cold starts: {t.fixed}/{t.restarts} fixed, time to fix max "
                  f"{_fmt(t.max_s, 'g')} s, median {_fmt(t.median_s, 'g')} s"]
    for r in report.restarts:
        lines.append(f"  start +{r.start_gpst - report.restarts[0].start_gpst:5.0f} s: "
                     + (f"fix after {r.time_to_fix_s:g} s, length {r.length:.4f} m, "
                        f"azimuth {r.azimuth_deg:.2f} deg" if r.time_to_fix_s is not None
                        else "no fix"))
    lines += ["", "TDCP velocity (receivers at rest)   horiz RMS   vert RMS   max horiz  epochs"]
    for name, v in report.velocity.items():
        if v.epochs:
            lines.append(f"  {name:<33} {v.horizontal_rms_mps:8.4f}   "
                         f"{v.vertical_rms_mps:8.4f}   {v.max_horizontal_mps:8.4f}  "
                         f"{v.epochs:6d}  m/s")
        else:
            lines.append(f"  {name:<33} no solution")
    return "\n".join(lines)
