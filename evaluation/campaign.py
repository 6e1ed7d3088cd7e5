"""``berthing-aid campaign``: the replay evaluation over many berthings and injected faults, on
one machine or a Dask cluster.

Each task simulates one recording (or reuses it from the cache, keyed by scenario, seed,
duration and the simulator's version), injects a fault into a copy when asked
(``recordings.faults``), and runs the replay report on it (``evaluation.report`` — the same
code as ``berthing-aid replay --report``). Tasks run on Dask distributed: a local cluster
sized to the machine by default, or the scheduler at ``--scheduler`` (workers started with
``dask worker tcp://HOST:PORT`` elsewhere; the cache and the output directory must then be
a path every worker reaches, or the recordings are simulated on the workers). A task that
fails, or whose worker dies, is written with its error and the campaign goes on; a second run
with the same ``--out`` skips the tasks already done.

Output: ``tasks/<task>.json`` (the report's JSON with the task, or its error), and
``summary.json`` / ``summary.md``: per figure (``FIGURES``) the median, p90, worst and the
task of the worst over the tasks that have it. Timings are summarised apart (they are not
reproducible); everything else is the same for the same tasks wherever they ran.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import shutil
import tempfile
import time
import traceback
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from estimator.pipeline import FusionOptions
from recordings.faults import FAULTS, inject, parse_fault
from recordings.format import load
from recordings.sim.scenarios import SCENARIOS
from recordings.sim.simulate import simulate

from .integrity import stanford_points
from .records import to_json
from .report import ReportOptions, evaluate

TASK_DIR = "tasks"
MIN_INIT_S, INIT_FRACTION = 5.0, 0.35  # short recordings: initialisation a share of them


# -------------------------------------------------------------------------------- tasks


@dataclass(frozen=True)
class Task:
    scenario: str
    seed: int
    duration_s: float | None  # None: the scenario's
    fault: str | None  # None: the recording as simulated

    @property
    def key(self) -> str:
        d = "full" if self.duration_s is None else f"{self.duration_s:g}s"
        f = "clean" if self.fault is None else re.sub(r"[^A-Za-z0-9.-]", "_", self.fault)
        return f"{self.scenario}-seed{self.seed}-{d}-{f}"

    @property
    def recording_key(self) -> str:
        d = "full" if self.duration_s is None else f"{self.duration_s:g}s"
        return f"{self.scenario}-seed{self.seed}-{d}-sim{simulator_version()}"


@dataclass
class CampaignSpec:
    scenarios: list[str]
    seeds: list[int]
    duration_s: float | None = None
    faults: list[str | None] = field(default_factory=lambda: [None])
    fusion: dict[str, Any] = field(default_factory=dict)  # FusionOptions fields (a sweep)
    tracking: bool = True
    quick: bool = False  # table 17 and integrity only (no satellite subsets, fig. 14)

    def tasks(self) -> list[Task]:
        return [Task(sc, seed, self.duration_s, fault) for sc in self.scenarios
                for seed in self.seeds for fault in self.faults]


def parse_seeds(text: str) -> list[int]:
    """``"1-20"``, ``"3"`` or ``"1,4,7-9"`` → the seeds."""
    out: list[int] = []
    for part in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if not m:
            raise ValueError(f"--seeds {text!r}: expected numbers and ranges like 1-20,25")
        a, b = int(m.group(1)), int(m.group(2) or m.group(1))
        if b < a:
            raise ValueError(f"--seeds {text!r}: range {a}-{b} goes backwards")
        out.extend(range(a, b + 1))
    return sorted(set(out))


def parse_faults(text: str | None) -> list[str | None]:
    """``None`` → no fault; ``"all"`` → the clean recording and every fault kind (default
    parameters); else a comma-separated list (each ``KIND[:a:b]``, checked)."""
    if not text:
        return [None]
    if text.strip() == "all":
        return [None, *FAULTS]
    faults = [f.strip() for f in text.split(",") if f.strip()]
    for f in faults:
        if f != "clean":
            parse_fault(f)
    return [None if f == "clean" else f for f in faults]


def simulator_version() -> str:
    """A digest of the simulator's sources and data: a cached recording made by another
    simulator is not reused."""
    root = Path(__file__).resolve().parent.parent / "recordings"
    h = hashlib.sha256()
    for path in sorted([*(root / "sim").glob("*.py"), *(root / "data").glob("*")]):
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:10]


# ---------------------------------------------------------------------- on the workers


def make_recording(task: Task, cache: str) -> str:
    """The task's recording in the cache (simulated when missing); returns its path."""
    path = Path(cache) / task.recording_key
    if (path / "manifest.json").is_file():
        return str(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{task.recording_key}-", dir=cache))
    try:
        simulate(task.scenario, task.seed, tmp / "rec", duration_s=task.duration_s,
                 progress=False)
        try:
            (tmp / "rec").rename(path)  # atomic: another worker may have made it meanwhile
        except OSError:
            if not (path / "manifest.json").is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return str(path)


def run_task(task: Task, recording: str, out: str, spec: CampaignSpec) -> dict[str, Any]:
    """One evaluation; its JSON written to ``out/tasks``, its figures returned. Errors are
    written and returned too (the campaign goes on)."""
    tic = time.perf_counter()
    doc: dict[str, Any] = {"task": _task_dict(task), "recording": recording}
    work = Path(tempfile.mkdtemp(prefix="campaign-"))
    try:
        path = recording if task.fault is None else \
            str(inject(recording, task.fault, work / "damaged"))
        rec = load(path)
        init = min(30.0, max(MIN_INIT_S, INIT_FRACTION * float(rec.manifest.duration_s)))
        options = ReportOptions(init_s=init, tracking=spec.tracking, fusion=dict(spec.fusion))
        if spec.quick:
            options.subset_sizes, options.clock_drift = (), False
            options.single_satellites, options.without_cpp = 0, False
        ev = evaluate(rec, options, lambda _text: None)
        doc["report"] = to_json(ev.report)
        err, pl, trusted = stanford_points(rec, ev.runs["INS+VO+CPP"], ev.rs.start + init)
        doc["stanford"] = {"error_m": np.round(err, 4).tolist(),
                           "hpl_m": np.round(pl, 4).tolist(), "trusted": trusted.tolist()}
    except Exception as exc:  # the campaign records it and goes on
        doc["error"] = f"{type(exc).__name__}: {exc}"
        doc["traceback"] = traceback.format_exc()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    doc["wall_s"] = time.perf_counter() - tic
    doc["worker"] = os.environ.get("DASK_WORKER_NAME") or os.uname().nodename
    _write_json(Path(out) / TASK_DIR / f"{task.key}.json", doc)
    return {"key": task.key, "error": doc.get("error")}


def _task_dict(task: Task) -> dict[str, Any]:
    return {"key": task.key, "scenario": task.scenario, "seed": task.seed,
            "duration_s": task.duration_s, "fault": task.fault}


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1, allow_nan=False))
    tmp.replace(path)  # a reader never sees half a file


# ----------------------------------------------------------------------- on the client


def done(out: Path, task: Task) -> bool:
    """The task has a result (not an error) in ``out``: a resumed campaign skips it."""
    path = out / TASK_DIR / f"{task.key}.json"
    if not path.is_file():
        return False
    try:
        return "error" not in json.loads(path.read_text())
    except (OSError, ValueError):
        return False


def run_campaign(spec: CampaignSpec, out: str | Path, cache: str | Path | None = None,
                 workers: int | None = None, scheduler: str | None = None,
                 memory_limit: str = "4GiB", show_progress: bool = True) -> dict[str, Any]:
    """Run (or resume) the campaign; write and return the summary."""
    from distributed import Client, LocalCluster  # the cluster's machinery: only when asked

    out = Path(out).resolve()
    cache = Path(cache).resolve() if cache else out / "recordings"
    out.mkdir(parents=True, exist_ok=True)
    cache.mkdir(parents=True, exist_ok=True)
    tasks = spec.tasks()
    todo = [t for t in tasks if not done(out, t)]
    if todo:
        if scheduler:
            client = Client(scheduler)
            cluster = None
        else:
            n = workers or max(1, (os.cpu_count() or 2))
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                   memory_limit=memory_limit, dashboard_address=None)
            client = Client(cluster)
        try:
            _submit(client, todo, spec, out, cache, show_progress)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    summary = summarise(out, tasks)
    write_summary(out, summary)
    return summary


def _submit(client: Any, todo: list[Task], spec: CampaignSpec, out: Path, cache: Path,
            show_progress: bool) -> None:
    """Every task on the cluster: one simulation per recording, the evaluations after it."""
    from distributed import as_completed

    recordings: dict[str, Any] = {}
    futures = {}
    for t in todo:
        if t.recording_key not in recordings:
            recordings[t.recording_key] = client.submit(
                make_recording, t, str(cache), key=f"simulate-{t.recording_key}", pure=False)
        # evaluations before further simulations: results come in as early as they can
        futures[client.submit(run_task, t, recordings[t.recording_key], str(out), spec,
                              key=f"evaluate-{t.key}", pure=False, priority=1)] = t
    failed = 0
    with tqdm(total=len(futures), desc="campaign", unit="task", disable=not show_progress,
              dynamic_ncols=True) as bar:
        for fut in as_completed(list(futures)):
            t = futures[fut]
            try:
                result = fut.result()
                failed += result["error"] is not None
            except Exception as exc:  # the worker died or the simulation failed: record it
                failed += 1
                _write_json(out / TASK_DIR / f"{t.key}.json",
                            {"task": _task_dict(t), "error": f"{type(exc).__name__}: {exc}"})
            running = sum(1 for f in futures if f.status == "pending")
            bar.set_postfix(failed=failed, running=min(running, _n_workers(client)))
            bar.update(1)


def _n_workers(client: Any) -> int:
    try:
        return max(1, len(client.scheduler_info()["workers"]))
    except Exception:
        return 1


# --------------------------------------------------------------------------- summary


@dataclass(frozen=True)
class Figure:
    name: str  # the path in the report's JSON, dots between keys ([n]: list index)
    worse: str  # "high" or "low": which way is worse
    timing: bool = False  # not reproducible from run to run


def _figures() -> list[Figure]:
    out = []
    for m in ("INS", "VO", "INS+VO", "INS+VO+CPP"):
        out += [Figure(f"methods.{m}.horizontal_std_m", "high"),
                Figure(f"methods.{m}.horizontal_max_m", "high"),
                Figure(f"methods.{m}.heading_std_deg", "high")]
    for n in (5, 4, 3, 2, 1, 0):
        for mode in ("loose", "tight"):
            out += [Figure(f"satellite_subsets[n={n}].{mode}.horizontal_std_m", "high"),
                    Figure(f"satellite_subsets[n={n}].{mode}.heading_std_deg", "high"),
                    Figure(f"satellite_subsets[n={n}].{mode}.misleading_epochs", "high")]
    out += [Figure("clock_drift.common.horizontal_std_m", "high"),
            Figure("clock_drift.separate.horizontal_std_m", "high"),
            Figure("single_satellite_heading.worst_all_six_heading_std_deg", "high"),
            Figure("single_satellite_heading.worst_single_baseline_heading_std_deg", "high"),
            Figure("structure.within_30m.median_m", "high"),
            Figure("landmarks.depth_truth.refined_converged.within_30m.depth_median_m", "high"),
            Figure("tracking.methods.designated.distance_m.median", "high"),
            Figure("tracking.methods.designated.distance_m.within_tolerance", "low"),
            Figure("tracking.methods.designated.distance_within_2_sigma", "low"),
            Figure("integrity.misleading_epochs", "high"),
            Figure("integrity.hazardous_epochs", "high"),
            Figure("integrity.available_fraction", "low"),
            Figure("integrity.worst_error_to_protection", "high"),
            Figure("integrity.trusted_horizontal_max_m", "high"),
            Figure("realtime_factor", "low", timing=True)]
    return out


FIGURES = _figures()


def figure_value(report: dict[str, Any], name: str) -> float | None:
    """The value of figure ``name`` in a report's JSON (None when it has none)."""
    node: Any = report
    for part in name.split("."):
        m = re.fullmatch(r"(.+)\[n=(\d+)\]", part)
        if m:
            rows = node.get(m.group(1)) if isinstance(node, dict) else None
            node = next((r for r in rows or () if r.get("n_satellites") == int(m.group(2))),
                        None)
        else:
            node = node.get(part) if isinstance(node, dict) else None
        if node is None:
            return None
    return float(node) if isinstance(node, int | float) and math.isfinite(node) else None


def summarise(out: Path, tasks: Iterable[Task]) -> dict[str, Any]:
    """Per figure: median, p90, worst and the task of the worst, over the tasks that have it;
    per fault kind the same for the integrity figures; the failed tasks with their errors."""
    docs = {}
    for t in tasks:
        path = out / TASK_DIR / f"{t.key}.json"
        docs[t.key] = json.loads(path.read_text()) if path.is_file() else \
            {"task": _task_dict(t), "error": "not run"}
    ok = {k: d for k, d in docs.items() if "error" not in d}
    figures = {f.name: _stats(f, ok) for f in FIGURES if not f.timing}
    timing = {f.name: _stats(f, ok) for f in FIGURES if f.timing}
    by_fault: dict[str, dict[str, Any]] = {}
    for fault in sorted({d["task"]["fault"] or "clean" for d in ok.values()}):
        sel = {k: d for k, d in ok.items() if (d["task"]["fault"] or "clean") == fault}
        by_fault[fault] = {f.name: _stats(f, sel) for f in FIGURES
                           if f.name.startswith("integrity.")
                           or f.name.startswith("methods.INS+VO+CPP")}
        by_fault[fault]["alerts_raised"] = sorted({a["kind"] for d in sel.values() for a in
                                                   (d["report"].get("integrity") or {})
                                                   .get("alerts", []) if a.get("active")})
    return {"tasks": len(docs), "succeeded": len(ok),
            "failed": {k: d["error"] for k, d in docs.items() if "error" in d},
            "figures": figures, "by_fault": by_fault, "timing": timing}


def _stats(fig: Figure, docs: dict[str, dict[str, Any]]) -> dict[str, Any]:
    vals = {k: v for k, d in docs.items()
            if (v := figure_value(d["report"], fig.name)) is not None}
    if not vals:
        return {"tasks": 0, "median": None, "p90": None, "worst": None, "worst_task": None}
    a = np.array(list(vals.values()))
    worst_key = (max if fig.worse == "high" else min)(vals, key=lambda k: (vals[k], k))
    p = 90 if fig.worse == "high" else 10
    return {"tasks": len(vals), "median": float(np.median(a)),
            "p90": float(np.percentile(a, p)), "worst": vals[worst_key],
            "worst_task": worst_key}


# Two processes may sum the same floats in another order (BLAS kernels, SIMD alignment): a
# cluster's figures agree with a local run's to ~1e-10 relative, not bit for bit.
SAME_FIGURE_REL_TOL = 1e-9


def summary_differences(a: dict[str, Any], b: dict[str, Any],
                        rel_tol: float = SAME_FIGURE_REL_TOL) -> list[str]:
    """Where two campaign summaries disagree (numbers beyond ``rel_tol``, anything else at
    all), one line each; the timing figures are left out (they differ from run to run), and of
    the failed tasks only which ones."""
    out: list[str] = []

    def walk(x: Any, y: Any, where: str) -> None:
        if isinstance(x, dict) and isinstance(y, dict):
            for k in sorted(set(x) | set(y)):
                if k not in x or k not in y:
                    side = "the second" if k not in x else "the first"
                    out.append(f"{where}.{k}: only in {side}")
                else:
                    walk(x[k], y[k], f"{where}.{k}" if where else k)
        elif isinstance(x, float | int) and isinstance(y, float | int) \
                and not isinstance(x, bool) and not isinstance(y, bool):
            if not math.isclose(x, y, rel_tol=rel_tol, abs_tol=1e-15):
                out.append(f"{where}: {x!r} != {y!r}")
        elif x != y:
            out.append(f"{where}: {x!r} != {y!r}")

    def comparable(summary: dict[str, Any]) -> dict[str, Any]:
        # A failed task's error may name a worker's paths: which tasks failed is what counts.
        return {k: sorted(v) if k == "failed" else v for k, v in summary.items()
                if k != "timing"}

    walk(comparable(a), comparable(b), "")
    return out


def write_summary(out: Path, summary: dict[str, Any]) -> None:
    _write_json(out / "summary.json", summary)
    (out / "summary.md").write_text(format_summary(summary))


def format_summary(summary: dict[str, Any]) -> str:
    def f(x: Any) -> str:
        return "–" if x is None else f"{x:.4g}"

    lines = [f"# Campaign summary: {summary['succeeded']} of {summary['tasks']} tasks", "",
             "p90 is the 90th percentile towards the worse side (the 10th for figures where "
             "low is worse).", "", "| figure | tasks | median | p90 | worst | worst task |",
             "| --- | ---: | ---: | ---: | ---: | --- |"]
    for name, s in {**summary["figures"], **summary["timing"]}.items():
        if s["tasks"]:
            lines.append(f"| {name} | {s['tasks']} | {f(s['median'])} | {f(s['p90'])} | "
                         f"{f(s['worst'])} | {s['worst_task']} |")
    if len(summary["by_fault"]) > 1 or "clean" not in summary["by_fault"]:
        lines += ["", "## By fault", "",
                  "| fault | tasks | misleading (worst) | hazardous (worst) | available "
                  "(worst) | INS+VO+CPP max (worst, m) | alerts raised |",
                  "| --- | ---: | ---: | ---: | ---: | ---: | --- |"]
        for fault, s in summary["by_fault"].items():
            lines.append(
                f"| {fault} | {s['integrity.misleading_epochs']['tasks']} | "
                f"{f(s['integrity.misleading_epochs']['worst'])} | "
                f"{f(s['integrity.hazardous_epochs']['worst'])} | "
                f"{f(s['integrity.available_fraction']['worst'])} | "
                f"{f(s['methods.INS+VO+CPP.horizontal_max_m']['worst'])} | "
                f"{', '.join(s['alerts_raised']) or '–'} |")
    if summary["failed"]:
        lines += ["", "## Failed tasks", ""]
        lines += [f"- `{k}`: {e}" for k, e in summary["failed"].items()]
    return "\n".join(lines) + "\n"


def write_plots(out: Path, tasks: Sequence[Task]) -> list[str]:
    """A box plot per figure and the error-against-protection-level scatter of all tasks."""
    import matplotlib  # only when plots are asked for

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    docs = [json.loads(p.read_text()) for t in tasks
            if (p := out / TASK_DIR / f"{t.key}.json").is_file()]
    docs = [d for d in docs if "error" not in d]
    plots = out / "plots"
    plots.mkdir(exist_ok=True)
    written = []
    names = [f for f in FIGURES if any(figure_value(d["report"], f.name) is not None
                                       for d in docs)]
    cols = 4
    rows = max(1, math.ceil(len(names) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.6 * rows), squeeze=False)
    for ax, fg in zip(axes.ravel(), names, strict=False):
        vals = [v for d in docs if (v := figure_value(d["report"], fg.name)) is not None]
        ax.boxplot(vals, vert=False)
        ax.set_title(fg.name, fontsize=7)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(plots / "figures.png", dpi=80)
    plt.close(fig)
    written.append(str(plots / "figures.png"))
    fig, ax = plt.subplots(figsize=(7, 6.5))
    for d in docs:
        st = d.get("stanford") or {}
        e, p = np.array(st.get("error_m", [])), np.array(st.get("hpl_m", []))
        ok = np.array(st.get("trusted", []), bool)
        if len(e):
            ax.scatter(np.maximum(p[ok], 1e-3), np.maximum(e[ok], 1e-3), s=2, c="tab:green")
            ax.scatter(np.maximum(p[~ok], 1e-3), np.maximum(e[~ok], 1e-3), s=2,
                       c="tab:orange")
    ax.plot([1e-3, 1e3], [1e-3, 1e3], "k-", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("horizontal protection level (m)")
    ax.set_ylabel("true horizontal error (m)")
    ax.set_title(f"all tasks ({len(docs)}): green trusted, orange not")
    ax.grid(alpha=0.3, which="both")
    fig.savefig(plots / "stanford_all.png", dpi=90)
    plt.close(fig)
    written.append(str(plots / "stanford_all.png"))
    return written


def spec_from_args(scenarios: str, seeds: str, duration: float | None, faults: str | None,
                   options: str | None, tracking: bool, quick: bool = False) -> CampaignSpec:
    """The campaign of the command's arguments, checked."""
    names = [s.strip() for s in scenarios.split(",") if s.strip()]
    unknown = [s for s in names if s not in SCENARIOS]
    if not names or unknown:
        raise ValueError(f"--scenario: unknown {', '.join(unknown) or '(none given)'}; one or "
                         f"more of {', '.join(sorted(SCENARIOS))}")
    fusion: dict[str, Any] = {}
    if options:
        try:
            fusion = json.loads(options)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--options is not JSON: {exc}") from None
        if not isinstance(fusion, dict):
            raise ValueError("--options must be a JSON object of FusionOptions fields")
        _check_fusion_options(fusion)
    if duration is not None and not (1.0 <= duration <= 3600.0):
        raise ValueError(f"--duration {duration:g}: must be between 1 and 3600 s")
    return CampaignSpec(names, parse_seeds(seeds), duration, parse_faults(faults), fusion,
                        tracking, quick)


def _check_fusion_options(fusion: dict[str, Any]) -> None:
    known = {f.name for f in fields(FusionOptions)}
    bad = sorted(set(fusion) - known)
    if bad:
        raise ValueError(f"--options: unknown FusionOptions field(s) {', '.join(bad)}; "
                         f"known: {', '.join(sorted(known))}")
