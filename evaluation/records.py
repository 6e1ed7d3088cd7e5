"""Typed results of the evaluation, one dataclass per group of figures of the replay report
(the thesis' tables 17–21, fig. 14, the port structure, seed 002's fig. 7 and seed 000's
fig. 10, the integrity). The JSON of ``berthing-aid replay --report --json`` is these records
(``to_json``), so its keys are these field names. The records of ``berthing-aid compass`` and
``baseline`` are in ``evaluation.gnss_records``."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# ------------------------------------------------------------------------ trajectories


@dataclass
class TrajectoryScores:
    """Errors of one fusion run over the scored window (table 17's columns)."""

    horizontal_std_m: float | None = None  # sqrt(var_N + var_E)
    horizontal_max_m: float | None = None
    horizontal_rms_m: float | None = None
    velocity_std_mps: float | None = None
    heading_std_deg: float | None = None
    heading_rms_deg: float | None = None
    heading_max_deg: float | None = None
    coverage: float = 0.0  # share of the window's frames scored


@dataclass
class VoAloneScores(TrajectoryScores):
    """The VO trajectory alone, mapped into L once at the window start."""

    anchored_at_s: float | None = None
    scale: float | None = None
    segment: int | None = None


@dataclass
class SubsetFigures:
    velocity_std_mps: float | None
    horizontal_std_m: float | None
    heading_std_deg: float | None
    horizontal_max_m: float | None
    heading_rms_deg: float | None
    # trusted states whose error was beyond their protection level (as ``IntegrityReport``):
    # few satellites must not make the fusion confident and wrong
    misleading_epochs: int | None = None


@dataclass
class SubsetRow:
    """Tables 18–20: the satellites kept after the initialisation, loosely and tightly."""

    n_satellites: int
    satellites: list[str]
    geometry_hdop: float | None
    loose: SubsetFigures
    tight: SubsetFigures


@dataclass
class ClockFigures:
    horizontal_std_m: float | None
    horizontal_max_m: float | None
    velocity_std_mps: float | None
    heading_std_deg: float | None
    heading_rms_deg: float | None


@dataclass
class ClockDrift:
    """Table 21: one satellite per receiver, one common clock-drift state vs one each."""

    satellite_per_receiver: dict[str, str]
    common: ClockFigures
    separate: ClockFigures


@dataclass
class SatelliteHeading:
    """Fig. 14, one satellite: heading σ per baseline configuration ("all six", "0-1", …)."""

    sat: str
    elevation_deg: float | None
    heading_std_deg: dict[str, float | None] = field(default_factory=dict)
    heading_max_deg: dict[str, float | None] = field(default_factory=dict)
    snapshot_std_deg: dict[str, float | None] = field(default_factory=dict)
    updates: dict[str, int] = field(default_factory=dict)
    pipeline_all_baselines_std_deg: float | None = None


@dataclass
class SingleSatelliteHeading:
    method: str
    satellites: list[SatelliteHeading] = field(default_factory=list)
    worst_single_baseline_heading_std_deg: float | None = None
    worst_all_six_heading_std_deg: float | None = None
    worst_single_baseline_snapshot_std_deg: float | None = None
    worst_all_six_snapshot_std_deg: float | None = None
    reason: str | None = None


# --------------------------------------------------------------------------- structure


@dataclass
class PointStats:
    points: int
    matched: int
    median_m: float | None
    p90_m: float | None


@dataclass
class BandStats:
    range_m: list[float | None]
    points: int
    matched: int
    median_m: float | None
    p90_m: float | None


@dataclass
class QuayStats:
    points: int
    median_m: float | None
    p90_m: float | None


@dataclass
class QuayEdge:
    band_m: float
    all: QuayStats
    within_30m: QuayStats


@dataclass
class PointScores:
    """Structure points against the true scene points (nearest within the gate)."""

    points: int
    matched: int
    median_m: float | None
    p90_m: float | None
    within_30m: PointStats
    bands: list[BandStats]
    quay_edge: QuayEdge | None


@dataclass
class UnrefinedScores:
    median_m: float | None
    p90_m: float | None
    within_30m: PointStats
    quay_edge: QuayEdge | None


@dataclass
class StructureScores:
    gate: str
    points: int = 0
    matched: int = 0
    median_m: float | None = None
    p90_m: float | None = None
    within_30m: PointStats | None = None
    bands: list[BandStats] = field(default_factory=list)
    quay_edge: QuayEdge | None = None
    camera_end_ned: list[float] | None = None
    unrefined: UnrefinedScores | None = None
    reason: str | None = None


# ------------------------------------------------------------------- designated targets


@dataclass
class ErrorStats:
    """Of absolute errors: count, median, p90, max and RMS."""

    n: int = 0
    median: float | None = None
    p90: float | None = None
    max: float | None = None
    rms: float | None = None


@dataclass
class DistanceBand(ErrorStats):
    range_m: list[float | None] = field(default_factory=list)
    within_tolerance: float | None = None
    relative_median: float | None = None


@dataclass
class DistanceScores(ErrorStats):
    within_tolerance: float | None = None
    bands: list[DistanceBand] = field(default_factory=list)


@dataclass
class MethodScores:
    """One tracking method over the clicks (seed 002 fig. 7)."""

    frames: int
    frames_in_view: int
    tracked_fraction: float | None
    pixel_error: ErrorStats
    pixel_error_every_frame: ErrorStats
    undetected_loss_frames: int
    lost_frames_in_view: int
    loss_events: int
    reacquisitions: int
    ms_per_frame: float
    distance_m: DistanceScores | None = None
    distance_m_after_5s: DistanceScores | None = None
    distance_m_all_frames: DistanceScores | None = None
    distance_within_2_sigma: float | None = None  # share of frames with |error| ≤ 2σ
    distance_error_median_m: float | None = None  # (per click)
    # tracked frames beyond 2σ by cause (``tracking.BEYOND_2_SIGMA_CAUSES``)
    beyond_2_sigma: dict[str, int] | None = None
    range_m: list[float] | None = None  # (per click)


@dataclass
class ClickResult:
    click: int
    label: str
    frame: int
    t_s: float
    uv: list[float]
    point: int | None = None
    method: str | None = None  # how the click was designated
    support_points: int | None = None
    true_point_ned: list[float] | None = None
    per_method: dict[str, MethodScores] = field(default_factory=dict)
    # The designated distance at the target's last solved view, triangulated from its views
    # as they are and with the truth put in for the pixels, the poses or both
    # (``tracking.error_sources``): what limits it. m, signed, and the true range;
    # None when never refined.
    error_sources: dict[str, float] | None = None
    # The designated point at the click frame, before any view: its distance − the true
    # one (m) and its σ as the officer reads it.
    designation_error_m: float | None = None
    designation_sigma_m: float | None = None
    skipped: str | None = None


@dataclass
class TrackingReport:
    clicks: list[ClickResult] = field(default_factory=list)
    methods: dict[str, MethodScores] = field(default_factory=dict)
    fixed_point_distance_m: DistanceScores | None = None
    loss_px: float | None = None
    distance_tolerance: str | None = None
    window_px: int | None = None
    wall_s: float | None = None
    reason: str | None = None


# ---------------------------------------------------------------------------- landmarks


@dataclass
class DepthStats:
    points: int
    depth_median_m: float | None
    depth_p90_m: float | None
    xyz_median_m: float | None


@dataclass
class DepthBand:
    range_m: list[float | None]
    points: int
    depth_median_m: float | None
    depth_p90_m: float | None
    xyz_median_m: float | None


@dataclass
class DepthScores:
    points: int
    depth_median_m: float | None
    depth_p90_m: float | None
    xyz_median_m: float | None
    within_30m: DepthStats
    bands_final_range: list[DepthBand]
    bands_last_view_depth: list[DepthBand]


@dataclass
class SigmaCover:
    """Does the structure's stated σ cover its depth error? The converged points within 30 m
    of the camera at the end whose last view has a rendered truth: the share within 2σ, how
    many beyond 3σ and the largest |error| / σ. A point on a depth edge (the corner of a
    near surface against a far one) is within when it is within 2σ of either surface."""

    points: int = 0
    within_2sigma: float | None = None
    beyond_3sigma: int = 0
    worst_ratio: float | None = None
    edge_points: int = 0
    edge_within_2sigma: float | None = None


@dataclass
class DepthTruth:
    raw: DepthScores
    refined: DepthScores
    raw_same_points: DepthScores
    raw_converged: DepthScores
    refined_converged: DepthScores
    truth_points: int
    sigma_cover: SigmaCover | None = None


@dataclass
class MatchStats:
    points: int
    matched: int | None = None
    median_m: float | None = None


@dataclass
class SceneMatch(MatchStats):
    within_30m: MatchStats | None = None


@dataclass
class ViewsRow:
    """Landmark error after ``views`` views (seed 000 fig. 10)."""

    views: int
    landmarks: int
    depth_median_m: float
    relative_depth_median: float
    xyz_median_m: float
    depth_p90_m: float | None = None


@dataclass
class LandmarkReport:
    timing_ms_per_frame: float | None = None
    points: int | None = None
    refined_points: int | None = None
    scene_point_match: dict[str, SceneMatch] = field(default_factory=dict)
    depth_truth: DepthTruth | None = None
    error_vs_views: list[ViewsRow] = field(default_factory=list)
    error_vs_views_same_landmarks: list[ViewsRow] = field(default_factory=list)
    reason: str | None = None


# ---------------------------------------------------------------------------- integrity


@dataclass
class AlertRecord:
    t: float  # s after the recording start
    kind: str
    message: str
    active: bool = True  # False: the fault cleared


@dataclass
class IntegrityReport:
    """The integrity of the INS+VO+CPP run over the scored window: misleading = the true
    error beyond the protection level while the state is trusted; hazardous = that, and
    beyond the alert limit."""

    alert_limit_m: float
    heading_alert_limit_deg: float
    epochs: int  # frames expected in the window
    available_fraction: float  # trusted frames / epochs
    misleading_epochs: int
    hazardous_epochs: int
    misleading_heading_epochs: int = 0
    modes: dict[str, int] = field(default_factory=dict)  # frames by declared mode
    trusted_horizontal_std_m: float | None = None  # accuracy over the trusted frames
    trusted_horizontal_max_m: float | None = None
    worst_error_to_protection: float | None = None  # max error/HPL over the trusted frames
    alerts: list[AlertRecord] = field(default_factory=list)


# ------------------------------------------------------------------------------ report


@dataclass
class ReplayReport:
    """``berthing-aid replay --report``: everything scored on one recording."""

    recording: str
    duration_s: float
    init_s: float
    window_s: list[float]  # the window actually scored (s after the recording start)
    origin_time_s: float
    alignment: str
    methods: dict[str, TrajectoryScores]
    methods_without_cpp_after_startup: dict[str, TrajectoryScores] = field(default_factory=dict)
    satellite_subsets: list[SubsetRow] = field(default_factory=list)
    satellites_tracked: dict[str, dict[str, float]] = field(default_factory=dict)
    clock_drift: ClockDrift | None = None
    single_satellite_heading: SingleSatelliteHeading | None = None
    structure: StructureScores | None = None
    tracking: TrackingReport | None = None
    landmarks: LandmarkReport | None = None
    integrity: IntegrityReport | None = None
    realtime_factor: float | None = None
    timing_ms: dict[str, float] = field(default_factory=dict)
    plots: list[str] = field(default_factory=list)


# -------------------------------------------------------------------------------- JSON


# Field metadata for ``to_json``: a key present only when the figure exists (None: the key is
# left out, not null), and a dict whose items are keys of the enclosing object.
OMIT_IF_NONE = {"json": "omit if None"}
INLINE = {"json": "inline"}


def omitted_if_none() -> Any:
    """A field defaulting to None that ``to_json`` leaves out while it is None."""
    return field(default=None, metadata=OMIT_IF_NONE)


def to_json(x: Any) -> Any:
    """Strict-JSON form of a result (dataclasses as objects, NaN/inf as null)."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        out: dict[str, Any] = {}
        for f in dataclasses.fields(x):
            value, how = getattr(x, f.name), f.metadata.get("json")
            if how == "inline":
                out.update(to_json(value))
            elif value is not None or how != "omit if None":
                out[f.name] = to_json(value)
        return out
    if isinstance(x, dict):
        return {str(k): to_json(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [to_json(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_json(x.tolist())
    if isinstance(x, float | np.floating):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer | np.bool_):
        return x.item()
    return x


def finite(x: float | None) -> float | None:
    """``x`` as a float, None when missing or not finite."""
    return float(x) if x is not None and math.isfinite(x) else None
