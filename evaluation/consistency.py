"""Does the fused position's σ against the world cover its error? INS + carrier phase (no VO)
over a seed's simulated sensors (no video: seconds a seed), as the server runs it (with the
recording's sea-surface height), scored every 0.1 s after the first ``scored_after_s``:

- NEES per horizontal degree of freedom, ``eᵀ P⁻¹ e / 2``, with P the filter's position
  covariance alone (``FusedState.position_cov``) and with the drift it does not model added
  (``position_drift_cov``); consistent is ~1, above 1 the σ is too small;
- the largest horizontal error, the σ (√ of the 2x2 trace) at the end, the largest error over
  the protection level (HPL), and the atmosphere's activity the fusion measured
  (``cpp.AtmosphereActivity``).

``benchmarks/position_consistency.py`` prints them over many seeds.
"""

from __future__ import annotations

import numpy as np

from estimator.pipeline import Fusion, FusionOptions
from recordings.sim.scenarios import SCENARIOS
from recordings.sim.simulate import SEA_SURFACE_SIGMA_M, charted_sea_surface, simulate_sensors
from recordings.sim.variety import seeded


def position_consistency(scenario: str, seed: int, duration_s: float = 90.0,
                         scored_after_s: float = 20.0) -> dict[str, float]:
    """The figures of one seed (module docstring)."""
    sc = seeded(SCENARIOS[scenario], seed)
    run = simulate_sensors(sc, seed, duration_s)
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
        if t < scored_after_s:
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
