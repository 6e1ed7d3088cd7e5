"""The replay report as the thesis' tables, in plain text."""

from __future__ import annotations

from typing import Any

from .records import (
    IntegrityReport,
    LandmarkReport,
    ReplayReport,
    StructureScores,
    TrackingReport,
    TrajectoryScores,
)
from .tracking import SETTLED_S, error_source_shares


def f(x: Any, spec: str = ".3f") -> str:
    """A figure, or "-" when there is none."""
    return "-" if x is None else format(x, spec)


def format_replay_report(report: ReplayReport) -> str:
    """The thesis' tables of a :class:`ReplayReport`."""
    w0, w1 = report.window_s
    lines = [f"{report.recording}: {report.duration_s:g} s, window {w0:g}-{w1:g} s after "
             f"a {report.init_s:g} s initialisation; {report.alignment}", ""]
    lines += _table17(report)
    lines += _tables18_20(report)
    lines += _table21(report)
    lines += _fig14(report)
    if report.integrity is not None:
        lines += _integrity(report.integrity)
    if report.structure is not None:
        lines += _structure(report.structure)
    t = report.timing_ms
    stages = ", ".join(f"{k} {v:.2f}" for k, v in t.items())
    lines += ["", f"realtime factor {f(report.realtime_factor, '.2f')} (VO + INS+VO+CPP "
                  f"fusion); ms per call/frame: {stages}"]
    if report.tracking is not None:
        lines += ["", format_tracking_report(report.tracking, report.landmarks)]
    if report.plots:
        lines.append("plots: " + ", ".join(report.plots))
    return "\n".join(lines)


def _row(name: str, m: TrajectoryScores) -> str:
    return (f"  {name:<27} {f(m.horizontal_std_m, '7.3f')}  {f(m.horizontal_max_m, '8.3f')}  "
            f"{f(m.horizontal_rms_m, '8.3f')}  {f(m.heading_std_deg, '6.3f')}/"
            f"{f(m.heading_rms_deg, '<6.3f')}  {100 * m.coverage:6.0f}%")


def _table17(report: ReplayReport) -> list[str]:
    lines = ["table 17  horizontal error     std (m)   max (m)   rms (m)  hdg std/rms (deg)"
             " coverage"]
    lines += [_row(name, m) for name, m in report.methods.items()]
    vo = report.methods.get("VO")
    if getattr(vo, "anchored_at_s", None) is not None:
        lines.append(f"  (VO alone: mapped at +{vo.anchored_at_s:.1f} s with the fused pose "
                     f"and scale {vo.scale:.4f} m/unit, segment {vo.segment})")
    if report.methods_without_cpp_after_startup:
        lines.append("  no carrier phase after the start-up (use_cpp=False):")
        lines += [_row(f"  {name}", m)
                  for name, m in report.methods_without_cpp_after_startup.items()]
    return lines


def _tables18_20(report: ReplayReport) -> list[str]:
    if not report.satellite_subsets:
        return []
    lines = ["", "tables 18-20  satellites kept after the initialisation "
                 "(loose | tight coupling of the velocity)",
             f"  {'n':>2} {'satellites':<24} {'HDOP':>6}  {'vel σ (m/s)':>15}  "
             f"{'traj σ (m)':>15}  {'traj max (m)':>15}  {'heading σ (deg)':>15}  "
             f"{'hdg rms (deg)':>15}  {'misleading':>11}"]
    for s in report.satellite_subsets:
        lo, ti = s.loose, s.tight
        lines.append(
            f"  {s.n_satellites:>2} {','.join(s.satellites) or '-':<24} "
            f"{f(s.geometry_hdop, '6.2f')}  "
            f"{f(lo.velocity_std_mps, '7.3f')}|{f(ti.velocity_std_mps, '<7.3f')}  "
            f"{f(lo.horizontal_std_m, '7.3f')}|{f(ti.horizontal_std_m, '<7.3f')}  "
            f"{f(lo.horizontal_max_m, '7.3f')}|{f(ti.horizontal_max_m, '<7.3f')}  "
            f"{f(lo.heading_std_deg, '7.3f')}|{f(ti.heading_std_deg, '<7.3f')}  "
            f"{f(lo.heading_rms_deg, '7.3f')}|{f(ti.heading_rms_deg, '<7.3f')}  "
            f"{f(lo.misleading_epochs, '5d')}|{f(ti.misleading_epochs, '<5d')}")
    return lines


def _table21(report: ReplayReport) -> list[str]:
    cd = report.clock_drift
    if cd is None:
        return []
    per = ", ".join(f"rx{int(i) + 1} {s}" for i, s in cd.satellite_per_receiver.items())
    lines = ["", f"table 21  one satellite per receiver ({per})",
             "  clock drift     std (m)   max (m)  vel σ (m/s)  hdg σ/rms (deg)"]
    for name in ("separate", "common"):
        m = getattr(cd, name)
        lines.append(f"  {name:<12} {f(m.horizontal_std_m, '8.3f')}  "
                     f"{f(m.horizontal_max_m, '8.3f')}  {f(m.velocity_std_mps, '11.3f')}  "
                     f"{f(m.heading_std_deg, '9.3f')}/{f(m.heading_rms_deg, '.3f')}")
    return lines


def _fig14(report: ReplayReport) -> list[str]:
    ss = report.single_satellite_heading
    if ss is None:
        return []
    if not ss.satellites:
        return ["", f"fig. 14: {ss.reason}"] if ss.reason else []
    names = list(ss.satellites[0].heading_std_deg)
    lines = ["", "fig. 14  heading σ (deg) from ONE satellite, each baseline vs all six: "
                 "SD + gyro filter / single-epoch snapshot; pipeline = the EKF with that "
                 "satellite alone",
             "  sat  elev  " + " ".join(f"{n:>13}" for n in names) + "  pipeline"]
    for e in ss.satellites:
        cells = [f"{f(e.heading_std_deg[n], '5.2f')}/{f(e.snapshot_std_deg[n], '<6.1f')}"
                 for n in names]
        lines.append(f"  {e.sat:<4} {f(e.elevation_deg, '4.0f')}  "
                     + " ".join(f"{c:>13}" for c in cells)
                     + f"  {f(e.pipeline_all_baselines_std_deg, '8.3f')}")
    return lines


def _integrity(ig: IntegrityReport) -> list[str]:
    modes = ", ".join(f"{m} {n}" for m, n in ig.modes.items())
    lines = ["", f"integrity (INS+VO+CPP; alert limits {ig.alert_limit_m:g} m, "
                 f"{ig.heading_alert_limit_deg:g}°): {ig.epochs} frames in the window, "
                 f"available (trusted) {100 * ig.available_fraction:.1f} %, misleading "
                 f"{ig.misleading_epochs} (heading {ig.misleading_heading_epochs}), hazardous "
                 f"{ig.hazardous_epochs}",
             f"  modes: {modes or '-'}; trusted frames: horizontal σ "
             f"{f(ig.trusted_horizontal_std_m, '.4f')} m, max "
             f"{f(ig.trusted_horizontal_max_m, '.4f')} m, worst error/HPL "
             f"{f(ig.worst_error_to_protection, '.2f')}"]
    raised = [a for a in ig.alerts if a.active]
    lines.append(f"  alerts: {len(raised)}" + ("" if raised else " (none)"))
    lines += [f"    {a.t:7.2f} s  {a.kind:<18} {a.message}" for a in raised[:20]]
    if len(raised) > 20:
        lines.append(f"    … {len(raised) - 20} more")
    return lines


def _structure(st: StructureScores) -> list[str]:
    lines = ["", f"structure: {st.points} points, {st.matched} matched to a true scene point "
                 f"within {st.gate} (the scene points sample outlines sparsely: a coarse check; "
                 "the 3-D error against the rendered surface is under the port-structure "
                 "refinement below)",
             "  range from the camera   points  matched  median (m)  p90 (m)"]
    for b in st.bands:
        lo, hi = b.range_m
        name = f"{lo:g}-{hi:g} m" if hi is not None else f">{lo:g} m"
        lines.append(f"  {name:<22} {b.points:7d}  {b.matched:7d}  {f(b.median_m, '10.3f')}  "
                     f"{f(b.p90_m, '7.3f')}")
    lines.append(f"  {'all':<22} {st.points:7d}  {st.matched:7d}  {f(st.median_m, '10.3f')}  "
                 f"{f(st.p90_m, '7.3f')}")
    raw = st.unrefined
    if raw is not None:
        rq = raw.quay_edge.within_30m.median_m if raw.quay_edge is not None else None
        lines.append(f"  before the landmark refinement: all median {f(raw.median_m)} m, "
                     f"p90 {f(raw.p90_m)} m; within 30 m median {f(raw.within_30m.median_m)} m;"
                     f" quay edge within 30 m median {f(rq)} m")
    q = st.quay_edge
    if q is not None:
        for name, b in (("within 30 m", q.within_30m), ("all", q.all)):
            lines.append(f"  quay edge, {name:<11} {b.points:7d} points within {q.band_m:g} m of"
                         f" the edge: median {f(b.median_m)} m, p90 {f(b.p90_m)} m")
    if st.reason:
        lines.append(f"  ({st.reason})")
    return lines


def format_tracking_report(tracking: TrackingReport, landmarks: LandmarkReport | None = None
                           ) -> str:
    """Seed 002 fig. 7 (designated targets) and seed 000 fig. 10 (landmarks)."""
    lines = ["Designated-target tracking (seed 002 fig. 7)"]
    if not tracking.methods:
        lines.append(f"  not evaluated: {tracking.reason or 'no click could be scored'}")
    for m, s in tracking.methods.items():
        pe, dm = s.pixel_error, s.distance_m
        lines.append(
            f"  {m:12s} px median {f(pe.median, '.2f')} p90 {f(pe.p90, '.2f')} max "
            f"{f(pe.max, '.1f')} | tracked {f(s.tracked_fraction, '.0%')} undetected-loss "
            f"frames {s.undetected_loss_frames} | distance median "
            f"{f(dm.median if dm else None, '.3f')} m, within tol "
            f"{f(dm.within_tolerance if dm else None, '.0%')} | {s.ms_per_frame:.1f} ms/frame")
    fx = tracking.fixed_point_distance_m
    if fx is not None:
        lines.append(f"  {'fixed point':12s} distance median {f(fx.median, '.3f')} m, "
                     f"within tol {f(fx.within_tolerance, '.0%')} (no image tracking)")
    d = tracking.methods.get("designated")
    late = d.distance_m_after_5s if d is not None else None
    if late is not None:
        lines.append(f"  designated, {SETTLED_S:g} s after the click: distance median "
                     f"{f(late.median, '.3f')} m p90 {f(late.p90, '.2f')} m, within tol "
                     f"{f(late.within_tolerance, '.0%')}; |error| ≤ 2σ in "
                     f"{f(d.distance_within_2_sigma, '.0%')} of the frames")
    beyond = d.beyond_2_sigma if d is not None else None
    if beyond is not None and sum(beyond.values()):
        lines.append(f"  designated, frames beyond 2σ ({sum(beyond.values())}) by cause: "
                     + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in beyond.items()))
    shares = error_source_shares(tracking.clicks)
    if shares is not None:
        lines.append(f"  what limits it ({shares['clicks']:.0f} refined clicks within tol at "
                     f"their last view, views triangulated): as tracked "
                     f"{shares['as_is']:.0%}, with the true pixels {shares['true_pixels']:.0%},"
                     f" with the true poses {shares['true_poses']:.0%}")
    if landmarks is not None:
        lines += _landmarks(landmarks)
    return "\n".join(lines)


def _landmarks(landmarks: LandmarkReport) -> list[str]:
    lines = ["Port-structure refinement (seed 000 fig. 10)"]
    dt = landmarks.depth_truth
    if dt is not None:
        for name, label in (("raw", "all raw VO points"),
                            ("raw_same_points", "raw, reported ones"),
                            ("refined", "refined, reported"),
                            ("raw_converged", "raw, converged ones"),
                            ("refined_converged", "refined, converged")):
            scores = getattr(dt, name)
            w = scores.within_30m
            b = scores.bands_last_view_depth[1]  # last seen at 10–30 m
            lines.append(f"  {label:20s} within 30 m: depth error median "
                         f"{f(w.depth_median_m, '.3f')} m p90 {f(w.depth_p90_m, '.2f')} m, "
                         f"3-D error median {f(w.xyz_median_m, '.3f')} m ({w.points} points); "
                         f"last seen at 10–30 m: {f(b.xyz_median_m, '.3f')} m ({b.points})")
        sc = dt.sigma_cover
        if sc is not None and sc.points:
            lines.append(f"  refined, converged within 30 m: depth error within 2σ "
                         f"{f(sc.within_2sigma, '.3f')}, beyond 3σ {sc.beyond_3sigma} of "
                         f"{sc.points}, worst {f(sc.worst_ratio, '.1f')}σ; on a depth edge "
                         f"{sc.edge_points} (within 2σ of a surface "
                         f"{f(sc.edge_within_2sigma, '.2f')})")
    elif landmarks.reason:
        lines.append(f"  {landmarks.reason}")
    if landmarks.error_vs_views_same_landmarks:
        lines.append("  reported position (the joint window's where it has one) as the views "
                     "accumulate:")
    for row in landmarks.error_vs_views_same_landmarks:
        lines.append(f"  after {row.views:4d} views: depth error median "
                     f"{row.depth_median_m:.3f} m, {100 * row.relative_depth_median:.1f} % of "
                     f"the range ({row.landmarks} landmarks, the same throughout)")
    lines.append(f"  {f(landmarks.timing_ms_per_frame, '.2f')} ms per frame")
    return lines
