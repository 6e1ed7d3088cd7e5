"""The camera pipeline's yardstick (issue 17): VO, port structure and designated targets on a
set of simulated seeds chosen before looking.

    .venv/bin/python benchmarks/camera_yardstick.py [--small 101-120] [--large 201-205]
        [--cache DIR] [--end 90] [--jobs 2] [--json OUT.json] [--seeds small-boat:103 ...]
        [--recordings DIR ...] [--no-targets]

Each seed is simulated once into ``--cache`` (default ``~/.cache/berthing-aid/yardstick``,
outside the repository; reused when present) and evaluated with the replay report's own
functions (``evaluation.report.evaluate``), trimmed to what the issue's targets need:

- table 17's VO alone and INS+VO+CPP, and INS+VO — the thesis' protocol: carrier phase for
  the 30 s initialisation, then no satellite at all, tightly coupled (``satellites_keep=[]``;
  the "tight, 0 satellites" row of tables 18–19 is this same run);
- the port structure: depth error of the converged refined points within 30 m of the camera
  at the end (rendered true depth at each landmark's last view), and whether their stated σ
  covers it (``depth 2σ``: the share within 2σ; ``>3σ``: the points beyond 3σ);
- the designated targets on the server's path (``FollowedTarget``, no ablations): the share
  of tracked frames whose distance is within tolerance (max(0.1 m, 1 %)) and within 2σ; and
  what limits them (``evaluation.tracking.error_sources``): the share of refined clicks
  within tolerance at their last view triangulated from their views as they are (``src``),
  with the true pixels (``src px``) and with the true poses (``src pose``);
- the VO's cost per frame (ms), and how often the main fusion found it inconsistent with the
  gyro or the fused track and excluded it (``estimator.vo_coupling.VoConsistency``).

``--recordings`` evaluates recordings as they are instead (e.g. the campaign's, to compare two
versions of the code on the same videos); ``--no-targets`` leaves the designated targets out.

The replay is cut at ``--end`` s (default 90: the 30 s initialisation + the 60 s window of
the targets; the small-boat scenario lasts 90 s anyway, the large ship 120 s). Two seeds run
at a time (``--jobs``, at most 2 on the shared machine). Prints a table per seed and the
worst and median of each figure, and writes the whole as JSON (``--json``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

SIM_DIR = Path(__file__).resolve().parent.parent / "recordings" / "sim"
DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / \
    "berthing-aid" / "yardstick"

# (key, column title, better when: "low" | "high", target worst, target median, format)
FIGURES = (
    ("vo_sigma_m", "VO σ m", "low", 1.0, 0.4, "{:.2f}"),
    ("vo_max_m", "VO max", "low", None, None, "{:.2f}"),
    ("vo_coverage", "VO cov", "high", None, None, "{:.2f}"),
    ("zero_sat_sigma_m", "0sat σ m", "low", 1.0, 0.3, "{:.2f}"),
    ("zero_sat_max_m", "0sat max", "low", None, None, "{:.2f}"),
    ("main_sigma_cm", "CPP σ cm", "low", 1.0, None, "{:.2f}"),
    ("main_max_cm", "CPP max", "low", 5.0, None, "{:.2f}"),
    ("depth_median_m", "depth<30", "low", 0.15, None, "{:.3f}"),
    ("depth_points", "n<30", "high", None, None, "{:.0f}"),
    ("depth_within_2sigma", "depth 2σ", "high", 0.95, None, "{:.2f}"),
    ("depth_beyond_3sigma", ">3σ", "low", None, None, "{:.0f}"),
    ("target_within_tol", "tgt tol", "high", 0.9, None, "{:.2f}"),
    ("target_within_2sigma", "tgt 2σ", "high", 0.95, None, "{:.2f}"),
    ("target_median_m", "tgt med", "low", None, None, "{:.3f}"),
    ("target_frames", "tgt n", "high", None, None, "{:.0f}"),
    ("target_src_as_is", "src", "high", None, None, "{:.2f}"),
    ("target_src_true_px", "src px", "high", None, None, "{:.2f}"),
    ("target_src_true_poses", "src pose", "high", None, None, "{:.2f}"),
    ("vo_tracking", "VO trk", "high", None, None, "{:.2f}"),
    ("vo_segments", "segs", "low", None, None, "{:.0f}"),
    ("vo_exclusions", "VO excl", "low", None, None, "{:.0f}"),
    ("vo_ms", "VO ms", "low", None, None, "{:.1f}"),
)


def parse_range(text: str) -> list[int]:
    """``"101-120"`` or ``"101,105"`` → seeds."""
    out: list[int] = []
    for part in text.split(","):
        if not part:
            continue
        lo, _, hi = part.partition("-")
        out.extend(range(int(lo), int(hi or lo) + 1))
    return out


def sim_version() -> str:
    """Hash of the simulator's sources: a cached recording made by another simulator is
    re-made (the figures would not be comparable)."""
    h = hashlib.sha256()
    for p in sorted(SIM_DIR.glob("*.py")):
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def recording_dir(cache: Path, scenario: str, seed: int) -> Path:
    return cache / f"{scenario}-seed{seed}"


def ensure_recording(cache: Path, scenario: str, seed: int, version: str) -> Path:
    """The seed's recording in the cache, simulated when missing or made by another
    simulator version."""
    import shutil

    from recordings.sim.simulate import simulate

    out = recording_dir(cache, scenario, seed)
    stamp = out / ".sim-version"
    if stamp.exists() and stamp.read_text().strip() == version and (out / "manifest.json").exists():
        return out
    if out.exists():
        shutil.rmtree(out)
    tmp = out.with_name(out.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    simulate(scenario, seed, tmp, progress=False)
    (tmp / ".sim-version").write_text(version + "\n")
    tmp.rename(out)
    return out


def evaluate_seed(cache: str | None, scenario: str, seed: int | str, end_s: float,
                  version: str, targets: bool = True) -> dict:
    """Simulate (if needed) and evaluate one seed: the figures of ``FIGURES``. Without a
    ``cache``, ``seed`` is the directory of a recording to evaluate as it is."""
    from evaluation.records import to_json
    from evaluation.report import MAIN, ReportOptions, evaluate
    from evaluation.tracking import DESIGNATED, error_source_shares
    from recordings.format import load

    t_start = time.perf_counter()
    path = Path(str(seed)) if cache is None else \
        ensure_recording(Path(cache), scenario, int(seed), version)
    t_sim = time.perf_counter() - t_start
    rec = load(path)
    end = min(end_s, float(rec.manifest.duration_s))
    opt = ReportOptions(end_s=end, methods=("VO", "INS+VO", MAIN), subset_sizes=(),
                        clock_drift=False, single_satellites=0, without_cpp=False,
                        tracking=targets, tracking_methods=(DESIGNATED,))
    ev = evaluate(rec, opt, lambda _text: None)
    rep = ev.report
    row: dict = {"scenario": scenario, "seed": seed, "end_s": end,
                 "simulate_s": t_sim, "evaluate_s": time.perf_counter() - t_start - t_sim}
    vo = rep.methods.get("VO")
    row["vo_sigma_m"] = vo.horizontal_std_m if vo else None
    row["vo_max_m"] = vo.horizontal_max_m if vo else None
    row["vo_coverage"] = vo.coverage if vo else None
    z = rep.methods.get("INS+VO")
    row["zero_sat_sigma_m"] = z.horizontal_std_m if z else None
    row["zero_sat_max_m"] = z.horizontal_max_m if z else None
    m = rep.methods[MAIN]
    row["main_sigma_cm"] = None if m.horizontal_std_m is None else 100 * m.horizontal_std_m
    row["main_max_cm"] = None if m.horizontal_max_m is None else 100 * m.horizontal_max_m
    dt = rep.landmarks.depth_truth if rep.landmarks is not None else None
    near = dt.refined_converged.within_30m if dt is not None else None
    row["depth_median_m"] = near.depth_median_m if near is not None else None
    row["depth_points"] = near.points if near is not None else 0
    cover = dt.sigma_cover if dt is not None else None
    row["depth_within_2sigma"] = cover.within_2sigma if cover is not None else None
    row["depth_beyond_3sigma"] = cover.beyond_3sigma if cover is not None else None
    tr = rep.tracking.methods.get(DESIGNATED) if rep.tracking is not None else None
    dist = tr.distance_m if tr is not None else None
    row["target_within_tol"] = dist.within_tolerance if dist is not None else None
    row["target_within_2sigma"] = tr.distance_within_2_sigma if tr is not None else None
    # What limits the targets (``evaluation.tracking.error_sources``): the share of refined
    # clicks within tolerance at their last view, from their views as they are, with the true
    # pixels, with the true poses.
    shares = error_source_shares(rep.tracking.clicks) if rep.tracking is not None else None
    for key, name in (("as_is", "target_src_as_is"), ("true_pixels", "target_src_true_px"),
                      ("true_poses", "target_src_true_poses")):
        row[name] = shares[key] if shares is not None else None
    row["target_median_m"] = dist.median if dist is not None else None
    row["target_frames"] = dist.n if dist is not None else 0
    outs = ev.rs.vo.outputs
    row["vo_tracking"] = float(np.mean([o.status == "tracking" for o in outs]))
    row["vo_segments"] = len({o.segment for o in outs if o.status == "tracking"})
    # times the main fusion found the VO inconsistent and excluded it (VoConsistency)
    row["vo_exclusions"] = sum(a.kind == "vo-inconsistent" and a.active
                               for a in ev.runs[MAIN].alerts)
    row["vo_ms"] = rep.timing_ms.get("vo") if rep.timing_ms else None
    row["report"] = to_json(rep)
    return row


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def summary(rows: list[dict]) -> dict[str, dict]:
    """Worst and median of each figure over the seeds that have it."""
    out = {}
    for key, _title, better, t_worst, t_median, _fmt in FIGURES:
        vals = np.array([r[key] for r in rows if _is_number(r.get(key))], float)
        if not len(vals):
            out[key] = {"seeds": 0}
            continue
        worst = float(vals.max() if better == "low" else vals.min())
        med = float(np.median(vals))
        res = {"seeds": len(vals), "worst": worst, "median": med}
        if t_worst is not None:
            res["target_worst"] = t_worst
            res["worst_ok"] = bool(worst <= t_worst if better == "low" else worst >= t_worst)
        if t_median is not None:
            res["target_median"] = t_median
            res["median_ok"] = bool(med <= t_median if better == "low" else med >= t_median)
        out[key] = res
    return out


def format_table(rows: list[dict], summ: dict[str, dict]) -> str:
    cols = [(k, t, f) for k, t, _b, _w, _m, f in FIGURES]
    width = [max(len(t), 6) for _k, t, _f in cols]
    head = f"{'seed':<16}" + " ".join(f"{t:>{w}}" for (_k, t, _f), w in zip(cols, width,
                                                                           strict=True))
    lines = [head, "-" * len(head)]
    for r in rows:
        name = r["scenario"][:16] if isinstance(r["seed"], str) else \
            f"{r['scenario'][:5]} {r['seed']}"
        if "error" in r:
            lines.append(f"{name:<16} ERROR {r['error'].splitlines()[-1]}")
            continue
        cells = [(f.format(r[k]) if _is_number(r.get(k)) else "-") for k, _t, f in cols]
        lines.append(f"{name:<16}" + " ".join(f"{c:>{w}}" for c, w in zip(cells, width,
                                                                          strict=True)))
    lines.append("-" * len(head))
    for what in ("worst", "median"):
        cells = [(f.format(summ[k][what]) if what in summ[k] else "-") for k, _t, f in cols]
        lines.append(f"{what:<16}" + " ".join(f"{c:>{w}}" for c, w in zip(cells, width,
                                                                          strict=True)))
    lines.append("")
    for key, title, better, t_worst, t_median, _f in FIGURES:
        s = summ[key]
        checks = []
        if "worst_ok" in s:
            op = "<=" if better == "low" else ">="
            checks.append(f"worst {s['worst']:.3g} {op} {t_worst:g}: "
                          f"{'ok' if s['worst_ok'] else 'MISSED'}")
        if "median_ok" in s:
            checks.append(f"median {s['median']:.3g} <= {t_median:g}: "
                          f"{'ok' if s['median_ok'] else 'MISSED'}")
        if checks:
            lines.append(f"target {title:<9} ({s['seeds']} seeds): " + "; ".join(checks))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--small", default="101-120", help="small-boat seeds (e.g. 101-120)")
    ap.add_argument("--large", default="201-205", help="large-ship seeds (e.g. 201-205)")
    ap.add_argument("--seeds", nargs="*", default=None, metavar="SCENARIO:SEED",
                    help="explicit seeds instead (e.g. small-boat:103 large-ship:201)")
    ap.add_argument("--recordings", nargs="*", type=Path, default=None, metavar="DIR",
                    help="recordings to evaluate as they are, instead of simulated seeds")
    ap.add_argument("--no-targets", action="store_true",
                    help="leave out the designated targets (about half the time)")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE,
                    help=f"simulated recordings (default {DEFAULT_CACHE})")
    ap.add_argument("--end", type=float, default=90.0, help="replay the first S s (default 90)")
    ap.add_argument("--jobs", type=int, default=2, help="processes (at most 2)")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    args = ap.parse_args(argv)
    if args.recordings:
        jobs = [(p.name, str(p)) for p in args.recordings]
    elif args.seeds:
        jobs = [(s.split(":")[0], int(s.split(":")[1])) for s in args.seeds]
    else:
        jobs = [("small-boat", k) for k in parse_range(args.small)] + \
            [("large-ship", k) for k in parse_range(args.large)]
    args.cache.mkdir(parents=True, exist_ok=True)
    version = sim_version()
    rows: list[dict] = []
    with ProcessPoolExecutor(max_workers=max(1, min(args.jobs, 2))) as pool:
        cache = None if args.recordings else str(args.cache)
        futures = {pool.submit(evaluate_seed, cache, sc, seed, args.end, version,
                               not args.no_targets): (sc, seed) for sc, seed in jobs}
        bar = tqdm(as_completed(futures), total=len(futures), unit="seed", file=sys.stderr)
        for fut in bar:
            sc, seed = futures[fut]
            try:
                rows.append(fut.result())
            except Exception:  # noqa: BLE001 - one seed's failure is a result too
                rows.append({"scenario": sc, "seed": seed, "error": traceback.format_exc()})
            bar.set_postfix_str(f"{sc} {seed} done")
    rows.sort(key=lambda r: (r["scenario"] != "small-boat", str(r["seed"])))
    summ = summary([r for r in rows if "error" not in r])
    print(format_table(rows, summ))
    if args.json is not None:
        args.json.write_text(json.dumps({"end_s": args.end, "sim_version": version,
                                         "summary": summ, "seeds": rows}, indent=1,
                                        allow_nan=False, default=_json_default))
        print(f"wrote {args.json}")
    return 0


def _json_default(o: object) -> object:
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(type(o))


if __name__ == "__main__":
    sys.exit(main())
