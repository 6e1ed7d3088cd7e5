"""The integrity of a fusion run against the truth: for every frame of the scored window,
the true horizontal and heading errors against the protection levels the engine stated
(``estimator.integrity``), whether the state was trusted, and the engine's alerts."""

from __future__ import annotations

import numpy as np

from recordings.format import Recording

from .records import AlertRecord, IntegrityReport
from .runs import FusionRun
from .scoring import horizontal_std, run_errors


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
    err = None if rec.reference is None else run_errors(run, rec.reference, start, t0)
    if err is None:
        return out
    horizontal, heading = _horizontal_heading(err.position, err.heading)
    trusted_err, ratios = [], []
    for k, s in states:
        integ = s.status.integrity
        mode = "unassessed" if integ is None else integ.mode
        out.modes[mode] = out.modes.get(mode, 0) + 1
        if integ is None or not integ.trusted or not np.isfinite(run.position[k]).all():
            continue
        h, hdg = horizontal[k], heading[k]
        trusted_err.append(err.position[k])
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
    err = None if rec.reference is None else \
        run_errors(run, rec.reference, float(rec.manifest.start_gpst), t0)
    if err is None:
        return np.zeros(0), np.zeros(0), np.zeros(0, bool)
    horizontal, _ = _horizontal_heading(err.position, err.heading)
    err_m, pl, ok = [], [], []
    for k, s in enumerate(run.states):
        integ = None if s is None else s.status.integrity
        if integ is None or integ.hpl_m is None or run.time[k] < t0 - 1e-6 \
                or not np.isfinite(run.position[k]).all():
            continue
        err_m.append(float(horizontal[k]))
        pl.append(integ.hpl_m)
        ok.append(integ.trusted)
    return np.array(err_m), np.array(pl), np.array(ok, bool)


def _horizontal_heading(position: np.ndarray, heading: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal error (m) and absolute heading error (deg) per frame."""
    return np.hypot(position[:, 0], position[:, 1]), np.abs(np.degrees(heading))
