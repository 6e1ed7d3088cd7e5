"""Which satellites the blocking experiments keep (thesis tables 18–21).

The satellites tracked with carrier phase by all four receivers throughout (GPS first, as the
thesis; Galileo/QZSS fill up if fewer than 5 GPS) are ranked by geometry; the best 5, and for
4…1 the best subset of those 5, are kept after the initialisation, plus none. Geometry = the
horizontal DOP of the carrier-phase velocity with one common clock drift, rows weighted like
the EKF's (σ ∝ 1/sin elevation), the vertical velocity held by the INS (unit-weight prior) and a
weak prior on every unknown so that 1–2 satellites still rank, averaged over the window.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np

from engine.messages import GnssMessage
from estimator.cpp import MIN_SIN_ELEVATION, SAME_CARRIER_SYSTEMS, epoch_geometry
from estimator.frames import ned_to_ecef
from recordings.format import Recording

SatelliteInfo = dict[str, dict[str, float]]  # sat → elevation_deg, azimuth_deg
LineOfSight = dict[float, dict[str, np.ndarray]]  # epoch time → sat → NED line of sight


def tracked(gnss: Sequence[GnssMessage]) -> list[str]:
    """Satellites with carrier phase at all four receivers in every epoch replayed."""
    sats: set[str] | None = None
    for m in gnss:
        here = set()
        eps = list(m.epochs)
        if len(eps) < 4 or any(e is None for e in eps):
            continue
        for s in eps[0].satellites:
            if all(s in e.satellites and math.isfinite(e.satellites[s].carrier_phase)
                   for e in eps):
                here.add(s)
        sats = here if sats is None else sats & here
    return sorted(sats or ())


def geometry(rec: Recording, gnss: Sequence[GnssMessage], sats: list[str], t0: float
             ) -> tuple[SatelliteInfo, LineOfSight]:
    """Elevation/azimuth (deg, averaged) and line of sight (NED) at epochs of the window,
    seen from the site (the manifest origin: metres do not matter for the geometry)."""
    site = ned_to_ecef(np.zeros(3), rec.manifest.origin_llh)
    times = [m.t for m in gnss if m.t >= t0 - 1e-6] or [gnss[-1].t]
    times = times[:: max(1, len(times) // 6)]
    los: LineOfSight = {}
    elaz: dict[str, list[tuple[float, float]]] = {s: [] for s in sats}
    for t in times:
        geo = epoch_geometry(rec.nav, sats, t, site, 0.0, 10.0)
        los[t] = {s: geo.los_ned(s) for s in geo.satellites}
        for s, g in geo.satellites.items():
            elaz[s].append((math.degrees(g.elevation), math.degrees(g.azimuth)))
    info = {s: {"elevation_deg": float(np.mean([a[0] for a in v])),
                "azimuth_deg": float(v[0][1])} for s, v in elaz.items() if v}
    return info, los


def velocity_dop(los: LineOfSight, subset: Sequence[str]) -> float:
    """Horizontal DOP of the carrier-phase velocity (v, one clock drift), rows weighted as the
    EKF weighs them (σ ∝ 1/sin elevation), the vertical held by the INS (unit weight) and a
    weak prior (1e-3) on everything, averaged over the epochs."""
    values = []
    for per in los.values():
        if any(s not in per for s in subset):
            return math.inf
        N = np.diag([1e-3, 1e-3, 1.0 + 1e-3, 1e-3])
        for s in subset:
            h = np.append(-per[s], 1.0)
            # weight 1/σ² ∝ sin²(elevation) as ``elevation_sigma``; sin(elevation) = −e_down
            N += max(-per[s][2], MIN_SIN_ELEVATION) ** 2 * np.outer(h, h)
        Q = np.linalg.inv(N)
        values.append(math.sqrt(Q[0, 0] + Q[1, 1]))
    return float(np.mean(values)) if values else math.inf


def choose_subsets(rec: Recording, gnss: Sequence[GnssMessage], t0: float
                   ) -> tuple[dict[int, list[str]], SatelliteInfo, dict[int, float]]:
    """The best 5 satellites and, for 4…1, the best subsets of those 5 (and 0: none)."""
    same = [s for s in tracked(gnss) if s[0] in SAME_CARRIER_SYSTEMS]
    info, los = geometry(rec, gnss, same, t0)
    same = [s for s in same if s in info]
    gps = [s for s in same if s[0] == "G"]
    pool = gps if len(gps) >= 5 else gps + [s for s in same if s[0] != "G"]
    best5 = min(itertools.combinations(pool, min(5, len(pool))),
                key=lambda c: (velocity_dop(los, c), c), default=())
    chosen: dict[int, list[str]] = {}
    dops: dict[int, float] = {}
    for n in range(len(best5), -1, -1):
        if n == 0:
            chosen[0], dops[0] = [], math.inf
            continue
        # Ties (1–2 satellites barely observe the horizontal) go to the higher satellites.
        combo = min(itertools.combinations(best5, n),
                    key=lambda c: (round(velocity_dop(los, c), 6),
                                   -sum(info[s]["elevation_deg"] for s in c)))
        chosen[n] = sorted(combo)
        dops[n] = velocity_dop(los, combo)
    return chosen, info, dops
