"""``berthing-aid replay RECORDING --report``: the thesis' experiments on a recording with a
reference trajectory (``docs/references.md``: thesis tables 17–21, fig. 14; seed 002 fig. 7;
seed 000 fig. 10), every fusion run through the server's own engine path (``runs``).

Table 17 (methods):
- INS+VO+CPP: ``FusionOptions()``.
- INS, INS+VO: the thesis' protocol — carrier phase (and compass) for the ``init_s`` of the
  initialisation, which estimates the biases, the attitude and the VO scale, then no satellite
  at all (``satellites_keep=[]``): the INS (with or without VO) alone over the window. The
  literal ``use_cpp=False`` runs (no carrier phase after the ~1 s start-up, so nothing is
  estimated) are reported too, under ``methods_without_cpp_after_startup``.
- VO: the VO trajectory alone, mapped into L ONCE at the window start with the INS+VO+CPP
  run's camera pose and VO scale there (``C_W^L = C_B^L·C_C^B·C_W^C`` and the scale then
  frozen); it ends when the VO loses its world (a new segment cannot be tied to the old one).

Tables 18–20: ``subsets`` chooses the satellites; each subset runs loosely (per-receiver TDCP
velocities) and tightly (η rows) coupled. Table 21: the best four satellites, each kept by ONE
receiver only (``per_receiver_sats``), one common clock-drift state vs one per receiver.
Fig. 14: ``heading``. Structure: ``structure``. Designated targets and landmarks: ``tracking``
and ``landmarks``. The scored window starts ``init_s`` after the first GNSS epoch and ends at
the last frame with a fused state; it is printed as scored.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from engine.driver import run_vo
from estimator.frames import dcm_to_euler
from estimator.pipeline import FusionOptions
from recordings.format import Recording, load

from .heading import OneSatelliteHeading
from .integrity import integrity_scores
from .landmarks import evaluate_landmarks
from .records import (
    ClockDrift,
    ClockFigures,
    ReplayReport,
    SubsetFigures,
    SubsetRow,
    TrajectoryScores,
    VoAloneScores,
    finite,
)
from .runs import Collect, FusionRun, RunSet
from .scoring import Errors, run_errors, trajectory_scores
from .structure import StructurePlot, structure_scores
from .subsets import choose_subsets
from .tracking import EVAL_METHODS, evaluate_tracking
from .truth import DEFAULT_CLICK_TIMES_S, default_clicks

INIT_S = 30.0  # thesis: 30 s of initialisation with carrier phase, then the window
SUBSET_SIZES = (5, 4, 3, 2, 1, 0)
CLICK_END_MARGIN_S = 5.0  # clicks at least this long before the end of the replay
MAIN = "INS+VO+CPP"
METHODS = ("INS", "VO", "INS+VO", MAIN)  # table 17


@dataclass
class ReportOptions:
    """What to run: ``end_s`` replays only the first seconds; ``methods`` (table 17's, the
    INS+VO+CPP run always), ``subset_sizes`` (tables 18–20), ``clock_drift`` (table 21),
    ``single_satellites`` (how many of the best five for fig. 14) and ``without_cpp`` (the
    literal ``use_cpp=False`` runs) trim the work for a quick run (the keys stay, empty);
    ``tracking`` adds the designated-target and landmark evaluations (``tracking_methods``:
    the image trackers followed, ``evaluation.tracking.EVAL_METHODS``); ``fusion``: the
    product's options (a campaign's parameter sweep)."""

    init_s: float = INIT_S
    end_s: float | None = None
    methods: Sequence[str] = METHODS
    subset_sizes: Sequence[int] = SUBSET_SIZES
    clock_drift: bool = True
    single_satellites: int = 5
    without_cpp: bool = True
    tracking: bool = True
    tracking_methods: Sequence[str] = EVAL_METHODS
    plots_dir: str | Path | None = None
    fusion: dict = field(default_factory=dict)


@dataclass
class Evaluated:
    """A report with what its plots draw."""

    report: ReplayReport
    runs: dict[str, FusionRun]
    errors: dict[str, Errors | None]
    structure_plot: StructurePlot | None
    rs: RunSet


def replay_report_for(rec: Recording, options: ReportOptions | None = None,
                      progress: Callable[[str], None] | None = None) -> ReplayReport:
    """The thesis' experiments on a loaded recording with a reference (module docstring)."""
    opt = options or ReportOptions()
    ev = evaluate(rec, opt, progress or (lambda _text: None))
    if opt.plots_dir is not None:
        from .plots import write_plots  # matplotlib only when plots are asked for

        ev.report.plots = write_plots(Path(opt.plots_dir), ev)
    return ev.report


def replay_report(recording_path: str | Path, options: ReportOptions | None = None,
                  progress: Callable[[str], None] | None = None) -> ReplayReport:
    """Load a recording (``recordings.format.load``) and run :func:`replay_report_for`."""
    return replay_report_for(load(recording_path), options, progress)


def evaluate(rec: Recording, opt: ReportOptions, progress: Callable[[str], None]) -> Evaluated:
    if rec.reference is None:
        raise ValueError(f"{rec.manifest.name}: no reference trajectory to score against "
                         "(the report needs reference/trajectory.csv)")
    rs = run_set(rec, opt, progress)
    t0 = rs.gnss[0].t + opt.init_s
    if t0 >= rs.end - 1.0:
        raise ValueError(f"{rec.manifest.name}: {rs.duration:g} s replayed leaves no window "
                         f"after the {opt.init_s:g} s initialisation")
    full = FusionOptions(keep_after_s=opt.init_s,
                         body_origin_height_m=rec.hull.body_origin_height_m,
                         sea_surface=rec.hull.sea_surface, hull_length_m=rec.hull.length,
                         **opt.fusion)
    main = rs.fuse(MAIN, full)
    if main.origin_time is None:
        raise ValueError(f"{rec.manifest.name}: the fusion never started (no GNSS compass fix "
                         "and no course over ground)")
    # The window's frames as the recording lists them: a video that ends early, or states
    # that are not positions (no IMU), show as missing coverage, not as a shorter window.
    frame_t = np.asarray(rec.frame_times, float)
    n_window = int(np.sum((frame_t >= t0 - 1e-6) & (frame_t <= rs.end + 1e-9)))
    report = ReplayReport(recording=str(getattr(rec.manifest, "name", "?")),
                          duration_s=rs.duration, init_s=opt.init_s,
                          window_s=_scored_window(main, t0, rs),
                          origin_time_s=main.origin_time - rs.start,
                          alignment="translation only, by the reference position at the "
                                    "fusion's origin time", methods={})
    ev = Evaluated(report, {}, {}, None, rs)
    _table17(ev, opt, t0, n_window)
    _tables18_21(ev, opt, t0, n_window)
    report.integrity = integrity_scores(rec, main, t0, rs.end)
    report.structure, ev.structure_plot = structure_scores(rec, main)
    if opt.tracking:
        _targets_and_landmarks(ev, opt, full, progress)
    _timing(ev, main)
    return ev


def run_set(rec: Recording, opt: ReportOptions, progress: Callable[[str], None]) -> RunSet:
    """The span to replay and the VO run once over its video."""
    start = float(rec.manifest.start_gpst)
    end = start + (float(rec.manifest.duration_s) if opt.end_s is None else opt.end_s)
    vo = run_vo(rec, until=end + 1e-9)
    if not vo.outputs:
        raise ValueError(f"{rec.manifest.name}: no video frame to replay")
    rs = RunSet(rec, start, end, vo, progress)
    if len(rs.gnss) < 3:
        raise ValueError(f"{rec.manifest.name}: fewer than 3 GNSS epochs to replay")
    n = len(vo.outputs)
    tracking = sum(o.status == "tracking" for o in vo.outputs)
    progress(f"VO over {n} frames: {(vo.vo_ms + vo.decode_ms) * n / 1e3:.1f} s "
             f"({vo.vo_ms:.1f} ms/frame VO, {vo.decode_ms:.1f} ms decoding), tracking "
             f"{100 * tracking / n:.0f} %, {len({o.segment for o in vo.outputs})} segment(s)")
    return rs


def _scored_window(main: FusionRun, t0: float, rs: RunSet) -> list[float]:
    """[first, last] frame (s after the start) with a position in the window: the window
    actually scored (the nominal one when nothing was)."""
    scored = (main.time >= t0 - 1e-6) & np.isfinite(main.position).all(axis=1)
    if not scored.any():
        return [t0 - rs.start, rs.end - rs.start]
    return [float(main.time[scored][0] - rs.start), float(main.time[scored][-1] - rs.start)]


def lean_options(opt: ReportOptions, init_s: float, **kw: object) -> FusionOptions:
    """Options of a run scored on the trajectory only: without the port-structure refinement
    (a consumer of the fused poses, not an input of the EKF: ~1 ms per frame)."""
    return FusionOptions(keep_after_s=init_s, landmarks=None, **{**opt.fusion, **kw})


def _score(ev: Evaluated, name: str, run: FusionRun, t0: float, n_window: int
           ) -> TrajectoryScores:
    err = run_errors(run, ev.rs.rec.reference, ev.rs.start, t0)
    ev.errors[name] = err
    return trajectory_scores(err, n_window)


def _table17(ev: Evaluated, opt: ReportOptions, t0: float, n_window: int) -> None:
    rs, report = ev.rs, ev.report
    main = rs.runs[MAIN]
    runs: dict[str, FusionRun] = {MAIN: main}
    if "INS" in opt.methods:
        runs["INS"] = rs.fuse("INS", lean_options(opt, opt.init_s, use_vo=False,
                                                  satellites_keep=[]))
    if "INS+VO" in opt.methods:
        runs["INS+VO"] = rs.fuse("INS+VO", lean_options(opt, opt.init_s, satellites_keep=[]))
    vo_scores: dict[str, object] = {}
    if "VO" in opt.methods:
        runs["VO"], vo_scores = vo_alone(rs, main, t0)
    ev.runs = runs = {n: runs[n] for n in METHODS if n in runs}
    for name in METHODS:
        if name in runs:
            report.methods[name] = _score(ev, name, runs[name], t0, n_window)
    if "VO" in runs:
        report.methods["VO"] = VoAloneScores(**vars(report.methods["VO"]), **vo_scores)
    if opt.without_cpp:
        lean = {"landmarks": None, **opt.fusion}
        lit = {"INS": rs.fuse("INS (use_cpp=False)",
                              FusionOptions(**{**lean, "use_vo": False, "use_cpp": False})),
               "INS+VO": rs.fuse("INS+VO (use_cpp=False)",
                                 FusionOptions(**{**lean, "use_cpp": False}))}
        report.methods_without_cpp_after_startup = {
            k: _score(ev, f"{k} (no CPP after start-up)", r, t0, n_window)
            for k, r in lit.items()}


def _tables18_21(ev: Evaluated, opt: ReportOptions, t0: float, n_window: int) -> None:
    rs, report = ev.rs, ev.report
    chosen, info, dops = choose_subsets(rs.rec, rs.gnss, t0)
    for n in opt.subset_sizes:
        if n not in chosen:
            continue
        sats = chosen[n]
        figures = {}
        for mode, tight in (("loose", False), ("tight", True)):
            run = rs.fuse(f"{n} sat {mode} {','.join(sats)}",
                          lean_options(opt, opt.init_s, satellites_keep=sats,
                                       tightly_coupled=tight))
            sc = trajectory_scores(run_errors(run, rs.rec.reference, rs.start, t0), n_window)
            ig = integrity_scores(rs.rec, run, t0, rs.end)
            figures[mode] = SubsetFigures(sc.velocity_std_mps, sc.horizontal_std_m,
                                          sc.heading_std_deg, sc.horizontal_max_m,
                                          sc.heading_rms_deg, ig.misleading_epochs)
        report.satellite_subsets.append(SubsetRow(n, sats, finite(dops[n]), **figures))
    report.satellites_tracked = {s: info[s] for s in sorted(info)}
    four = chosen.get(4)
    if opt.clock_drift and four:
        sats = sorted(four, key=lambda s: -info[s]["elevation_deg"])
        per = {i: [s] for i, s in enumerate(sats)}
        figures = {}
        for name, common in (("common", True), ("separate", False)):
            run = rs.fuse(f"one satellite per receiver, {name} clock drift",
                          lean_options(opt, opt.init_s, per_receiver_sats=per,
                                       common_clock=common))
            sc = _score(ev, f"per-receiver sats, {name} clock", run, t0, n_window)
            figures[name] = ClockFigures(sc.horizontal_std_m, sc.horizontal_max_m,
                                         sc.velocity_std_mps, sc.heading_std_deg,
                                         sc.heading_rms_deg)
        report.clock_drift = ClockDrift({str(i): s for i, s in enumerate(sats)}, **figures)
    five = chosen[max(chosen)][:max(opt.single_satellites, 0)]
    if five:
        pipeline = {s: rs.fuse(f"1 sat tight {s}",
                               lean_options(opt, opt.init_s, satellites_keep=[s]))
                    for s in five}
        report.single_satellite_heading = OneSatelliteHeading(
            rs, rs.runs[MAIN], t0).report(five, pipeline)


def _targets_and_landmarks(ev: Evaluated, opt: ReportOptions, full: FusionOptions,
                           progress: Callable[[str], None]) -> None:
    """Seed 002 fig. 7 and seed 000 fig. 10 on a run of the full pipeline that keeps the
    structure after every frame from the first click on."""
    rs, rec = ev.rs, ev.rs.rec
    # The default click times (45-78 s) when the replay reaches them, else three times spread
    # over the scored window.
    times = [t for t in DEFAULT_CLICK_TIMES_S if t < rs.duration - CLICK_END_MARGIN_S]
    times = times or list(np.linspace(opt.init_s, rs.duration - CLICK_END_MARGIN_S, 3))
    clicks = [c for c in default_clicks(rec, times_s=times) if c.frame < len(rs.vo.outputs)]
    progress("tracking and landmark evaluation")
    first = min((c.frame for c in clicks), default=None)
    run = rs.fuse(f"{MAIN} (targets, landmarks)", full,
                  Collect(structures_from=first, landmarks=True))
    ev.report.tracking = evaluate_tracking(rec, run, clicks, methods=opt.tracking_methods)
    ev.report.landmarks = evaluate_landmarks(rec, run)


def _timing(ev: Evaluated, main: FusionRun) -> None:
    vo = ev.rs.vo
    n = len(vo.outputs)
    vo_s = (vo.vo_ms + vo.decode_ms) * n / 1e3
    ev.report.realtime_factor = ev.rs.duration / max(main.wall_s + vo_s, 1e-9)
    timing = {k: float(v) for k, v in main.timing_ms.items()}
    timing["vo"] = vo.vo_ms
    timing["decode"] = vo.decode_ms
    timing["fusion_per_frame"] = 1e3 * main.wall_s / n
    ev.report.timing_ms = timing


# ------------------------------------------------------------------------------ VO alone


def vo_alone(rs: RunSet, main: FusionRun, t0: float) -> tuple[FusionRun, dict[str, object]]:
    """The VO trajectory mapped into L once at the window start (pose and scale of the
    INS+VO+CPP run there), then left alone. The VO is the one that run had: the VO pass, or
    from a restart on the run's own (a scale belongs to its world)."""
    cam = rs.rec.calibration.camera
    C_cb, lever = np.asarray(cam.C_camera_to_body, float), np.asarray(cam.lever_arm_body, float)
    outs = main.vo_outputs or rs.vo.outputs
    n = len(main.time)
    run = FusionRun("VO", main.time, [None] * n, main.origin_time, 0.0, {})
    k0 = next((k for k in range(n) if main.time[k] >= t0 - 1e-6 and outs[k].status == "tracking"
               and np.isfinite(main.scale[k]) and np.isfinite(main.position[k]).all()), None)
    info: dict[str, object] = {"anchored_at_s": None, "scale": None, "segment": None}
    if k0 is None:
        return run, info
    o0 = outs[k0]
    s = float(main.scale[k0])
    C_wl = main.C[k0] @ C_cb @ o0.C_world_to_camera  # C_W^L = C_B^L·C_C^B·C_W^C
    p_cam0 = main.position[k0] + main.C[k0] @ lever
    p_w0 = np.asarray(o0.camera_position_world, float)
    for k in range(k0, n):
        o = outs[k]
        if o.segment != o0.segment:
            break  # a new VO world: VO alone cannot tie it to the old one
        if o.status != "tracking":
            continue
        C_bl = C_wl @ o.C_world_to_camera.T @ C_cb.T  # C_B^L = C_W^L·C_C^W·C_B^C
        p_cam = p_cam0 + s * C_wl @ (np.asarray(o.camera_position_world, float) - p_w0)
        run.position[k] = p_cam - C_bl @ lever
        run.euler[k] = dcm_to_euler(C_bl)
    info = {"anchored_at_s": float(main.time[k0] - rs.start), "scale": s,
            "segment": int(o0.segment)}
    return run, info
