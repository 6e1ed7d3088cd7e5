"""The integrity of a fusion run against the truth: for every frame of the scored window,
the true horizontal and heading errors against the protection levels the engine stated
(``estimator.integrity``), whether the state was trusted, and the engine's alerts."""

from __future__ import annotations

import numpy as np

from estimator.frames import wrap_angle
from recordings.format import Recording

from .records import AlertRecord, IntegrityReport
from .runs import FusionRun
from .scoring import horizontal_std


def integrity_scores(rec: Recording, run: FusionRun, t0: float, t1: float) -> IntegrityReport:
    """Over the frames of ``rec`` between gpst ``t0`` and ``t1`` (all the video should have
    had: a frame without a state counts as unavailable)."""
    start = float(rec.manifest.start_gpst)
    frame_t = np.asarray(rec.frame_times, float)
    epochs = int(np.sum((frame_t >= t0 - 1e-6) & (frame_t <= t1 + 1e-9)))
    states = [(k, s) for k, s in enumerate(run.states)
              if s is not None and run.time[k] >= t0 - 1e-6 and run.time[k] <= t1 + 1e-9]
    cfg = next((s.status.integrity for _k, s in states if s.status.integrity is not None), None)
    al = cfg.alert_limit_m if cfg is not None else float("nan")
    hal = cfg.heading_alert_limit_deg if cfg is not None else float("nan")
    out = IntegrityReport(alert_limit_m=al, heading_alert_limit_deg=hal, epochs=epochs,
                          available_fraction=0.0, misleading_epochs=0, hazardous_epochs=0)
    out.alerts = [AlertRecord(a.t - start, a.kind, a.message, a.active) for a in run.alerts]
    if rec.reference is None or run.origin_time is None:
        return out
    origin = rec.reference.interpolate(run.origin_time)[0]
    trusted_err, ratios = [], []
    for k, s in states:
        integ = s.status.integrity
        mode = "unassessed" if integ is None else integ.mode
        out.modes[mode] = out.modes.get(mode, 0) + 1
        if integ is None or not integ.trusted or not np.isfinite(run.position[k]).all():
            continue
        ref_pos, _v, ref_eul = rec.reference.interpolate(run.time[k])
        e = run.position[k] - (ref_pos - origin)
        h = float(np.hypot(e[0], e[1]))
        hdg = abs(float(np.degrees(wrap_angle(run.euler[k, 2] - ref_eul[2]))))
        trusted_err.append(e)
        ratios.append(h / integ.hpl_m)
        misled_h, misled_hdg = h > integ.hpl_m, hdg > integ.heading_pl_deg
        out.misleading_epochs += int(misled_h or misled_hdg)
        out.misleading_heading_epochs += int(misled_hdg)
        out.hazardous_epochs += int((misled_h and h > al) or (misled_hdg and hdg > hal))
    out.available_fraction = len(trusted_err) / max(epochs, 1)
    if trusted_err:
        E = np.array(trusted_err)
        out.trusted_horizontal_std_m = horizontal_std(E)
        out.trusted_horizontal_max_m = float(np.max(np.hypot(E[:, 0], E[:, 1])))
        out.worst_error_to_protection = float(max(ratios))
    return out


def stanford_points(rec: Recording, run: FusionRun, t0: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(true horizontal error, HPL, trusted) of every frame with a state in the window: the
    Stanford diagram's points."""
    if rec.reference is None or run.origin_time is None:
        return np.zeros(0), np.zeros(0), np.zeros(0, bool)
    origin = rec.reference.interpolate(run.origin_time)[0]
    err, pl, ok = [], [], []
    for k, s in enumerate(run.states):
        integ = None if s is None else s.status.integrity
        if integ is None or integ.hpl_m is None or run.time[k] < t0 - 1e-6 \
                or not np.isfinite(run.position[k]).all():
            continue
        e = run.position[k] - (rec.reference.interpolate(run.time[k])[0] - origin)
        err.append(float(np.hypot(e[0], e[1])))
        pl.append(integ.hpl_m)
        ok.append(integ.trusted)
    return np.array(err), np.array(pl), np.array(ok, bool)
