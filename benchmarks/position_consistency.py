"""Does the fused position's σ against the world cover its error? INS + carrier phase (no VO)
over simulated sensors (no video: a few seconds a seed), every 0.1 s after the first 20 s of a
90 s run, per seed, with the recording's sea-surface height as the server and the report use
it (the origin's height; without it the origin's error drives a drift metres of standalone
height wide, which hides the atmosphere's):

- NEES per horizontal degree of freedom, ``eᵀ P⁻¹ e / 2``, with P the filter's position
  covariance alone (``FusedState.position_cov``) and with the drift it does not model added
  (``position_drift_cov``: the satellites' correlated rate errors, ``cpp.CorrelatedDrift``,
  and the world origin's error). Consistent is ~1; above 1 the σ is too small;
- the largest horizontal error and the σ (√ of the 2x2 trace) at the end;
- the largest horizontal error over the protection level (HPL), and the atmosphere's activity
  the fusion measured at the end (``cpp.AtmosphereActivity``: 1 on a day like the drift
  model's).

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

from estimator.pipeline import Fusion, FusionOptions  # noqa: E402
from recordings.sim.scenarios import SCENARIOS  # noqa: E402
from recordings.sim.simulate import (  # noqa: E402
    SEA_SURFACE_SIGMA_M,
    charted_sea_surface,
    simulate_sensors,
)
from recordings.sim.variety import seeded  # noqa: E402

DURATION_S = 90.0
SCORED_AFTER_S = 20.0


def seed_figures(scenario: str, seed: int) -> dict[str, float]:
    """The figures of one seed (module docstring)."""
    sc = seeded(SCENARIOS[scenario], seed)
    run = simulate_sensors(sc, seed, DURATION_S)
    sea = (charted_sea_surface(sc.origin_llh_deg[2], seed), SEA_SURFACE_SIGMA_M)
    fusion = Fusion(run.calibration, run.nav, FusionOptions(
        use_vo=False, landmarks=None, body_origin_height_m=-sc.reference_point_down_m,
        sea_surface=sea))
    p0 = None
    rows = []
    for k, _t in run.feed(fusion):
        if fusion.ekf is None or k % 10:
            continue
        if p0 is None:
            p0 = run.motion.state(fusion.origin_time - sc.start_gpst).position_ned[0]
        s = fusion.state()
        t = s.time - sc.start_gpst
        if t < SCORED_AFTER_S:
            continue
        e = (s.position_ned - (run.motion.state(t).position_ned[0] - p0))[:2]
        P = s.position_cov[:2, :2]
        W = P + s.position_drift_cov[:2, :2]
        rows.append((e @ np.linalg.solve(P, e) / 2, e @ np.linalg.solve(W, e) / 2,
                     float(np.hypot(*e)), float(np.sqrt(np.trace(W))),
                     float(np.hypot(*e)) / s.status.integrity.hpl_m))
    a = np.array(rows)
    activity = fusion.carrier.activity.scale if fusion.carrier is not None else float("nan")
    return {"nees_filter": float(a[:, 0].mean()), "nees": float(a[:, 1].mean()),
            "max_error_m": float(a[:, 2].max()), "sigma_end_m": float(a[-1, 3]),
            "max_error_to_hpl": float(a[:, 4].max()), "activity_end": float(activity)}


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
