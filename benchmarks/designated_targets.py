"""Designated-target distances over many recordings (issue 17): the share of tracked frames
whose distance is within tolerance (max(0.1 m, 1 %)) and within 2σ, per recording and their
worst and median, with each click's median error; and the image track's honesty: the share
of in-view frames tracked and the frames said "tracking" while the target is more than 10 px
away or out of the image (undetected losses). The frames beyond 2σ are put down to their
cause (``evaluation.tracking.BEYOND_2_SIGMA_CAUSES``: the track lost unnoticed, the click's
designation already beyond its 2σ, the point its track back gave at the click, the views
since), summed over the recordings, and the clicks with most of them are listed.

    .venv/bin/python benchmarks/designated_targets.py RECORDING [RECORDING ...]
        [--json OUT.json]

Each recording (with a reference and scene points: a simulated one, e.g. the campaign's
cache ``DIR/small-boat-seed7-60s-sim…``) goes through the replay report itself
(``evaluation.report.evaluate``) trimmed to its main fusion and the designated targets: the
server's path for each of the report's clicks (quay points at 45, 52, … s), no ablations.
About a minute per 60 s recording.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from evaluation.report import MAIN, ReportOptions, evaluate  # noqa: E402
from evaluation.tracking import BEYOND_2_SIGMA_CAUSES, DESIGNATED  # noqa: E402
from recordings.format import load  # noqa: E402

# The replay report trimmed to the designated targets: its main fusion (needed for the
# window), then its own tracking run and evaluation, without the ablations.
OPTIONS = ReportOptions(methods=(MAIN,), subset_sizes=(), clock_drift=False,
                        single_satellites=0, without_cpp=False, tracking=True,
                        tracking_methods=(DESIGNATED,))


def evaluate_recording(path: Path) -> dict:
    """One recording's designated-target figures (clicks as in ``replay --report``)."""
    report = evaluate(load(path), OPTIONS, lambda _text: None).report.tracking
    scores = report.methods.get(DESIGNATED) if report is not None else None
    if scores is None or scores.distance_m is None:
        return {"recording": path.name, "clicks": 0,
                "reason": report.reason if report is not None else "no tracking report"}
    return {"recording": path.name, "clicks": len(report.clicks),
            "frames": scores.distance_m.n,
            "within_tolerance": scores.distance_m.within_tolerance,
            "within_2_sigma": scores.distance_within_2_sigma,
            "median_m": scores.distance_m.median,
            "tracked_fraction": scores.tracked_fraction,
            "undetected_loss_frames": scores.undetected_loss_frames,
            "beyond_2_sigma": scores.beyond_2_sigma,
            "per_click_median_m": [
                (c.label, c.per_method[DESIGNATED].distance_error_median_m)
                for c in report.clicks if c.per_method],
            "per_click_beyond_2_sigma": [
                {"click": c.click, "t_s": c.t_s, "method": c.method,
                 "designation_error_m": c.designation_error_m,
                 "designation_sigma_m": c.designation_sigma_m,
                 **(c.per_method[DESIGNATED].beyond_2_sigma or {})}
                for c in report.clicks if c.per_method]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recordings", nargs="+", type=Path)
    ap.add_argument("--json", type=Path, help="write the rows and the summary here")
    args = ap.parse_args()
    rows = []
    for path in tqdm(args.recordings, desc="recordings", unit="rec"):
        try:
            rows.append(evaluate_recording(path))
        except Exception as exc:  # noqa: BLE001 — one bad recording does not stop the rest
            rows.append({"recording": path.name, "error": f"{type(exc).__name__}: {exc}"})
    print(f"{'recording':<40} {'tol':>5} {'2σ':>5} {'median':>7} {'trk':>5} {'undet':>5}  "
          "per-click median error (m)")
    for r in rows:
        if "error" in r or not r.get("clicks"):
            print(f"{r['recording']:<40} {r.get('error') or r.get('reason') or 'no click'}")
            continue
        clicks = " ".join(f"{e:.2f}" for _label, e in r["per_click_median_m"] if e is not None)
        print(f"{r['recording']:<40} {r['within_tolerance']:>5.2f} {r['within_2_sigma']:>5.2f} "
              f"{r['median_m']:>7.3f} {r['tracked_fraction'] or 0:>5.2f} "
              f"{r['undetected_loss_frames']:>5d}  {clicks}")
    scored = [r for r in rows if r.get("clicks") and "error" not in r]
    summary = {}
    for key in ("within_tolerance", "within_2_sigma", "tracked_fraction"):
        have = [r for r in scored if r.get(key) is not None]
        if have:
            vals = np.array([r[key] for r in have], float)
            worst = have[int(np.argmin(vals))]["recording"]
            summary[key] = {"worst": float(vals.min()), "median": float(np.median(vals)),
                            "worst_recording": worst}
            print(f"{key}: worst {vals.min():.2f} ({worst}), median {np.median(vals):.2f} "
                  f"over {len(vals)} recordings")
    if scored:
        undetected = [r["undetected_loss_frames"] for r in scored]
        worst = scored[int(np.argmax(undetected))]["recording"]
        summary["undetected_loss_frames"] = {"total": int(sum(undetected)),
                                             "worst": int(max(undetected)),
                                             "worst_recording": worst}
        print(f"undetected_loss_frames: {sum(undetected)} in all, worst {max(undetected)} "
              f"({worst})")
    causes = {k: sum((r.get("beyond_2_sigma") or {}).get(k, 0) for r in scored)
              for k in BEYOND_2_SIGMA_CAUSES}
    summary["beyond_2_sigma"] = causes
    print(f"frames beyond 2σ: {sum(causes.values())} in all, by cause: "
          + ", ".join(f"{k} {v}" for k, v in causes.items()))
    worst_clicks = sorted(((sum(c.get(k, 0) for k in BEYOND_2_SIGMA_CAUSES), r["recording"], c)
                           for r in scored for c in r["per_click_beyond_2_sigma"]),
                          key=lambda x: -x[0])
    for n, rec, c in [w for w in worst_clicks if w[0]][:8]:
        cause = max(BEYOND_2_SIGMA_CAUSES, key=lambda k: c.get(k, 0))
        line = f"  {rec} click {c['click']} at {c['t_s']:.0f} s ({c['method']}): {n} frames, " \
               f"mostly {cause}"
        if c["designation_error_m"] is not None:
            line += f"; designated {c['designation_error_m']:+.2f} m " \
                    f"±{c['designation_sigma_m']:.2f}"
        print(line)
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "summary": summary}, indent=1))


if __name__ == "__main__":
    main()
