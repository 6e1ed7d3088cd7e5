"""The port structure at the end of the INS+VO+CPP run against the true scene points.

The structure (``Fusion.structure()``), shifted by the run's alignment translation, is matched
to the nearest true scene point within ``max(1 m, 5 % of the range)`` (the scene points are a
sparse set of strong corners; a feature elsewhere on a surface has no true counterpart): median
and 90th percentile of the matched distances by range band from the camera at the end. Because
the true points are sparse (about a metre apart along the quay), the quay is also scored as a
line: the horizontal distance of the points within ``QUAY_BAND_M`` of the quay edge (the
polyline through the scene points of kind "quay") to that edge — bollards and deck features
just behind the edge count as error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recordings.format import Recording

from .records import StructureScores, UnrefinedScores
from .runs import FusionRun
from .scoring import MATCH_GATE, point_scores, quay_line


@dataclass
class StructurePlot:
    """What the structure plot draws: the points, their distance to the nearest true point,
    the camera at the end, the quay edge."""

    points: np.ndarray
    distance: np.ndarray
    camera: np.ndarray
    quay: np.ndarray | None


def structure_scores(rec: Recording, main: FusionRun
                     ) -> tuple[StructureScores, StructurePlot | None]:
    out = StructureScores(gate=MATCH_GATE)
    true = rec.scene_points
    if main.structure is None or true is None or len(true) == 0 or main.origin_time is None \
            or rec.reference is None:
        out.reason = "no structure or no true scene points"
        return out, None
    pts = main.structure[0]
    ok = np.flatnonzero(np.isfinite(main.position).all(axis=1))
    if len(pts) == 0 or len(ok) == 0:
        out.reason = "no structure points"
        return out, None
    k = ok[-1]
    cam = main.position[k] + main.C[k] @ np.asarray(rec.calibration.camera.lever_arm_body)
    origin = rec.reference.interpolate(main.origin_time)[0]
    true_w = np.asarray(true, float) - origin  # the same translation as the trajectories
    quay = quay_line(rec.scene_points, rec.scene_point_kinds, origin)
    scores, d = point_scores(pts, true_w, cam, quay)
    out.points, out.matched, out.median_m, out.p90_m = (scores.points, scores.matched,
                                                        scores.median_m, scores.p90_m)
    out.within_30m, out.bands, out.quay_edge = scores.within_30m, scores.bands, scores.quay_edge
    out.camera_end_ned = cam.tolist()
    if main.structure_raw is not None and len(main.structure_raw[0]):
        # The same points before the pipeline's landmark refinement, for comparison.
        raw, _ = point_scores(main.structure_raw[0], true_w, cam, quay)
        out.unrefined = UnrefinedScores(raw.median_m, raw.p90_m, raw.within_30m, raw.quay_edge)
    return out, StructurePlot(pts, d, cam, quay)
