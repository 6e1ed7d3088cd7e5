"""Berth lines clicked on the quay's water line, over many recordings: the bow distance the
berth panel shows against the true one, and whether its σ covers the error.

    .venv/bin/python benchmarks/berth_clicks.py RECORDING [RECORDING ...] [--every 10]
        [--json OUT.json]

For each recording (simulated: with a reference, its berth line in hull.json and its scene)
the session's engine runs once; every ``--every`` s from 20 s it stops, and the berth line is
set as the server sets it from two clicks on the true quay foot (``Berth.set_image``: the
quay-face fit, else the water plane), exact and slipped by (0, 3) and (3, -3) px. The clicks
are where the reference pose projects the foot, a fifth of its visible stretch in from either
end (``evaluation.truth.quay_foot_clicks``). Per recording: the lines set, the share fitted to
the quay face, the median and worst bow-distance error, the share within max(0.15 m, 1 %) and
within 2σ, and the lines **confidently wrong** (error beyond the tolerance and beyond 3σ).
"""

from __future__ import annotations

import argparse
import json
import os
import threading
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from backend.berth import Berth  # noqa: E402
from backend.errors import Unprocessable  # noqa: E402
from backend.models import FusionOptionsModel  # noqa: E402
from backend.sessions import engine_setup  # noqa: E402
from engine.camera import Projector  # noqa: E402
from engine.driver import create_engine, dispatch, frame_preparer  # noqa: E402
from engine.messages import sensor_messages  # noqa: E402
from engine.targets import Structure  # noqa: E402
from evaluation.truth import quay_foot_clicks  # noqa: E402
from recordings.format import load  # noqa: E402

SLIPS_PX = ((0.0, 0.0), (0.0, 3.0), (3.0, -3.0))
FIRST_S = 20.0


def evaluate_recording(path: Path, every_s: float) -> dict:
    """One recording's berth lines (module docstring)."""
    rec = load(path)
    water, make, _key = engine_setup(rec, create_engine, FusionOptionsModel().model_dump(),
                                     None, None)
    engine = make()
    start = float(rec.manifest.start_gpst)
    times = list(np.arange(FIRST_S, float(rec.manifest.duration_s) - 1.0, every_s))
    berth = Berth(rec, Projector(rec.calibration.camera),
                  water.down_m if water.known else None, lambda _s: np.zeros(3),
                  threading.RLock())
    lines = []
    state = None
    for msg in sensor_messages(rec, prepare=frame_preparer(engine)):
        s = dispatch(engine, msg)
        if s is None:
            continue
        state = s
        if not times or state.time - start < times[0] - 1e-6:
            continue
        t = times.pop(0)
        seen = quay_foot_clicks(rec, float(state.time))
        if seen is None:
            continue
        clicks, true_bow = seen
        structure = Structure.of(engine, state.time)
        for slip in SLIPS_PX:
            try:
                line = berth.set_image(state, clicks + np.asarray(slip), structure)
            except Unprocessable as exc:
                lines.append({"t": t, "slip": slip, "refused": str(exc)})
                continue
            m = berth.metrics(state)
            lines.append({"t": t, "slip": slip, "method": line.method, "true_m": true_bow,
                          "bow_m": m["bow_distance_m"], "sigma_m": m["bow_distance_sigma_m"]})
    return {"recording": path.name, "lines": lines}


def summarise(row: dict) -> dict:
    """Per-recording figures of ``evaluate_recording``'s lines."""
    set_ = [x for x in row["lines"] if "bow_m" in x]
    if not set_:
        return {"n": 0}
    err = np.array([x["bow_m"] - x["true_m"] for x in set_])
    sigma = np.array([x["sigma_m"] if x["sigma_m"] is not None else np.inf for x in set_])
    tol = np.maximum(0.15, 0.01 * np.array([x["true_m"] for x in set_]))
    return {"n": len(set_), "refused": len(row["lines"]) - len(set_),
            "quay_face": float(np.mean([x["method"] == "quay-face" for x in set_])),
            "median_m": float(np.median(np.abs(err))), "max_m": float(np.max(np.abs(err))),
            "within_tolerance": float(np.mean(np.abs(err) <= tol)),
            "within_2_sigma": float(np.mean(np.abs(err) <= 2 * sigma)),
            "confidently_wrong": int(np.sum((np.abs(err) > tol) & (np.abs(err) > 3 * sigma)))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recordings", nargs="+", type=Path)
    ap.add_argument("--every", type=float, default=10.0, help="s between berth lines")
    ap.add_argument("--json", type=Path, help="write the lines and the figures here")
    args = ap.parse_args()
    rows = []
    for path in tqdm(args.recordings, desc="recordings", unit="rec"):
        row = evaluate_recording(path, args.every)
        row["figures"] = summarise(row)
        rows.append(row)
    print(f"{'recording':<28} {'lines':>5} {'refd':>4} {'face':>5} {'median':>7} {'max':>7} "
          f"{'tol':>5} {'2σ':>5} {'wrong':>5}")
    for r in rows:
        f = r["figures"]
        if not f["n"]:
            print(f"{r['recording']:<28} no line (quay foot not in view)")
            continue
        print(f"{r['recording']:<28} {f['n']:>5d} {f['refused']:>4d} {f['quay_face']:>5.2f} "
              f"{f['median_m']:>7.3f} {f['max_m']:>7.3f} {f['within_tolerance']:>5.2f} "
              f"{f['within_2_sigma']:>5.2f} {f['confidently_wrong']:>5d}")
    scored = [r["figures"] for r in rows if r["figures"]["n"]]
    if scored:
        print(f"{'worst':<28} {'':>5} {'':>4} {min(f['quay_face'] for f in scored):>5.2f} "
              f"{max(f['median_m'] for f in scored):>7.3f} {max(f['max_m'] for f in scored):>7.3f}"
              f" {min(f['within_tolerance'] for f in scored):>5.2f} "
              f"{min(f['within_2_sigma'] for f in scored):>5.2f} "
              f"{sum(f['confidently_wrong'] for f in scored):>5d}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
