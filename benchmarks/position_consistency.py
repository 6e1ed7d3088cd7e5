"""Does the fused position's σ against the world cover its error? Per seed, INS + carrier
phase over simulated sensors (no video: a few seconds a seed), 90 s scored from 20 s, as the
server runs it: the horizontal NEES with the filter's covariance alone and with the drift it
does not model, the largest error, the σ at the end, the largest error over the HPL and the
atmosphere's activity (``evaluation.consistency``).

    .venv/bin/python benchmarks/position_consistency.py [--scenario small-boat] \
        [--seeds 101-120] [--json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run from anywhere without installing

from evaluation.consistency import position_consistency  # noqa: E402
from recordings.sim.scenarios import SCENARIOS  # noqa: E402

DURATION_S = 90.0
SCORED_AFTER_S = 20.0


def seed_figures(scenario: str, seed: int) -> dict[str, float]:
    """The figures of one seed (``evaluation.consistency``)."""
    return position_consistency(scenario, seed, DURATION_S, SCORED_AFTER_S)


def _seeds(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="small-boat", choices=sorted(SCENARIOS))
    parser.add_argument("--seeds", default="101-120", help="A-B (default %(default)s)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args(argv)
    out = {seed: seed_figures(args.scenario, seed)
           for seed in tqdm(_seeds(args.seeds), desc=args.scenario, file=sys.stderr)}
    summary = {k: {"median": float(np.median([r[k] for r in out.values()])),
                   "worst": float(max(r[k] for r in out.values()))}
               for k in ("nees_filter", "nees", "max_error_m", "max_error_to_hpl")}
    if args.json:
        print(json.dumps({"scenario": args.scenario, "seeds": out, "summary": summary}, indent=1))
        return 0
    print(f"{args.scenario}: horizontal position NEES per dof after {SCORED_AFTER_S:g} s "
          f"of {DURATION_S:g} s (INS + carrier phase)")
    print("seed  NEES filter  NEES with drift  max error (cm)  σ at the end (cm)  "
          "max error / HPL  activity")
    for seed, r in out.items():
        print(f"{seed:4d}  {r['nees_filter']:11.2f}  {r['nees']:15.2f}  "
              f"{100 * r['max_error_m']:14.2f}  {100 * r['sigma_end_m']:17.2f}  "
              f"{r['max_error_to_hpl']:15.2f}  {r['activity_end']:8.2f}")
    for k, v in summary.items():
        print(f"{k}: median {v['median']:.3g}, worst {v['worst']:.3g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
