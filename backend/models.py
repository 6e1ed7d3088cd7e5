"""Request and response models of the HTTP API, declared once and reused by the OpenAPI schema.

Times in the API are seconds since the recording start (``t``, ``time``, ``frame_time``) unless
named ``gpst``; positions are metres north/east/down in the local-level frame at the world
origin; angles are degrees.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    ValidatorFunctionWrapHandler,
    WrapValidator,
    model_validator,
)
from pydantic_core import PydanticCustomError

# Documented ranges. Every number a client sends is finite and inside one of these (NaN,
# ±inf and absurd magnitudes are 422 naming the field); times are checked against the
# recording itself once it is known (422 "outside the recording").
SPEED_MIN, SPEED_MAX = 0.01, 100.0  # replay speed factor
MAX_TIME_S = 1.0e6  # any time in the API, s since the recording start (recordings are shorter)
MAX_PLAN_M = 10_000.0  # |north|, |east| of a berth line point, m
MAX_PIXEL = 100_000.0  # |u|, |v| of a pixel (the image size is checked after)
MAX_BERTH_DISTANCE_M = 5_000.0  # a typed-in berth line, an approach-limit row
MAX_NUDGE_M, MAX_NUDGE_DEG = 50.0, 45.0


def _one_error(kind: str, message: str) -> WrapValidator:
    """One clear message for a union (pydantic would give one per member)."""

    def validate(value: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        try:
            return handler(value)
        except ValidationError:
            raise PydanticCustomError(kind, message) from None

    return WrapValidator(validate)


Speed = Annotated[Annotated[float, Field(ge=SPEED_MIN, le=SPEED_MAX, allow_inf_nan=False)]
                  | Literal["max"],
                  _one_error("speed", f"speed must be a number in [{SPEED_MIN:g}, "
                                      f"{SPEED_MAX:g}] or 'max'")]
Seconds = Annotated[float, Field(ge=0.0, le=MAX_TIME_S, allow_inf_nan=False)]
Pixel = Annotated[float, Field(ge=-MAX_PIXEL, le=MAX_PIXEL, allow_inf_nan=False)]
PlanMetres = Annotated[float, Field(ge=-MAX_PLAN_M, le=MAX_PLAN_M, allow_inf_nan=False)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Vec2 = Annotated[list[float], Field(min_length=2, max_length=2)]
PixelPoint = Annotated[list[Pixel], Field(min_length=2, max_length=2)]
PlanPoint = Annotated[list[PlanMetres], Field(min_length=2, max_length=2)]
# a recording's directory name: no path separator, no leading dot (catalog.RecordingCatalog)
RECORDING_NAME = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$"
RecordingName = Annotated[str, Field(pattern=RECORDING_NAME, examples=["default"]),
                          _one_error("recording_name", "a recording name from GET "
                                     "/api/recordings: letters, digits, '.', '_', '-' (not "
                                     "first), at most 128 characters")]
SatelliteId = Annotated[str, Field(pattern=r"^[GRECJSI]\d{2}$", examples=["G05"])]
FrameTime = Annotated[Seconds | Literal["current"],
                      _one_error("frame_time", f"a time in [0, {MAX_TIME_S:g}] s since the "
                                               "recording start, or 'current'")]


def _integral(value: Any) -> Any:
    """A JSON number with no fraction is an integer (JSON Schema's ``integer``: 26.0 is one)."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


class Strict(BaseModel):
    """A request body: a misspelt field is an error, not ignored; types are exact (``false``
    is not a number, ``"1"`` is not a number); numbers are finite."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


class FieldError(BaseModel):
    field: str = Field(description="where: body.<field>, query.<name>, path.<name>",
                       examples=["body.speed"])
    message: str
    type: str = Field(description="machine-readable kind (pydantic's error type, "
                                  "unknown_parameter, json_invalid…)")


class ErrorResponse(BaseModel):
    """The one error body of every route and status (400, 401, 403, 404, 405, 409, 422,
    429, 500)."""

    detail: str = Field(description="what is wrong with the request, for a person")
    errors: list[FieldError] = Field(
        default_factory=list,
        description="one entry per field that breaks the schema (422); empty otherwise — a "
                    "422 without entries is a request the schema allows that this session "
                    "cannot serve (a time beyond the recording, a pixel above the horizon), "
                    "said in `detail`")


# ---------------------------------------------------------------------------- recordings


class RecordingInfo(BaseModel):
    name: str
    default: bool = Field(description="the recording the server was started with")
    scenario: str | None = None
    seed: int | None = None
    start_gpst: float | None = None
    duration_s: float | None = None
    has_reference: bool = False
    problem: str | None = Field(None, description="why the manifest cannot be read, if so")


class RecordingList(BaseModel):
    recordings: list[RecordingInfo]
    default: str | None


class RecordingSummary(BaseModel):
    """``berthing-aid info --json`` of one recording (the server's paths left out)."""

    model_config = ConfigDict(extra="allow")
    name: str
    scenario: str | None
    seed: int | None
    start: dict[str, Any]
    duration_s: float
    origin_llh_deg: list[float]
    video: dict[str, Any]
    imu: dict[str, Any]
    gnss: dict[str, Any]
    nav: dict[str, Any]
    reference: dict[str, Any]
    scene_points: int | None
    warnings: list[str]


# ------------------------------------------------------------------------------- sessions


class FusionOptionsModel(Strict):
    """Scenario settings: the fields of ``estimator.pipeline.FusionOptions``."""

    use_vo: bool = True
    use_cpp: bool = True
    tightly_coupled: bool = True
    common_clock: bool = True
    satellites_keep: list[SatelliteId] | None = Field(
        None, description="keep only these satellites after keep_after_s (thesis tables 18-20)")
    keep_after_s: Seconds = 30.0
    sky_mask_deg: Annotated[float, Field(ge=0.0, le=90.0)] | None = Field(
        None, description="elevation mask (deg)")
    # JSON object keys are strings: the receiver index is parsed from one ("0".."3")
    per_receiver_sats: dict[Annotated[int, Field(ge=0, le=3, strict=False)],
                            list[SatelliteId]] | None = Field(
        None, description="receiver index (0..3) → the only satellites it keeps after "
                          "keep_after_s (thesis table 21); receivers not listed keep theirs",
        examples=[{"0": ["G05"], "1": ["G13"], "2": ["E11"], "3": ["J02"]}],
        json_schema_extra={"propertyNames": {"pattern": "^[0-3]$"}})


class SessionCreate(Strict):
    recording: RecordingName = Field(description="a name from GET /api/recordings")
    speed: Speed = Field(1.0, description=f"replay speed factor in [{SPEED_MIN:g}, "
                                          f"{SPEED_MAX:g}], or 'max' (as fast as possible)")
    options: FusionOptionsModel = Field(default_factory=FusionOptionsModel)
    paused: bool = False
    prediction_seconds: Annotated[int, BeforeValidator(_integral)] = Field(
        5, ge=0, le=30, description="predicted hull outlines in the stream")
    body_height_m: Annotated[float, Field(ge=-50.0, le=100.0)] | None = Field(
        None,
        description="height of the body origin (IMU) above the water: places the water plane "
                    "(grid, predicted outlines, water-plane targets). Default: from the "
                    "recording (see water_level.source in the status)")


class ControlRequest(Strict):
    """``time`` goes with ``seek`` only and ``speed`` with ``speed`` only (the schema's
    ``oneOf``)."""

    model_config = ConfigDict(json_schema_extra={"oneOf": [
        {"properties": {"action": {"enum": ["play", "pause"]}},
         "not": {"anyOf": [{"required": ["time"]}, {"required": ["speed"]}]}},
        {"properties": {"action": {"const": "seek"}}, "required": ["time"],
         "not": {"required": ["speed"]}},
        {"properties": {"action": {"const": "speed"}}, "required": ["speed"],
         "not": {"required": ["time"]}}]})

    action: Literal["play", "pause", "seek", "speed"] = Field(
        description="play: at the end of the recording answers 409 (seek first, e.g. to 0: "
                    "the history after the seek target is then recomputed); after an error "
                    "restarts the engine and recomputes up to where it stopped. seek: to "
                    "`time`. speed: to `speed`.")
    # not nullable: absent means absent (defaults are not validated)
    time: Seconds = Field(None, description="seek target, s since the recording start "
                                            "(within the recording; 422 beyond it)")
    speed: Speed = Field(None, description=f"[{SPEED_MIN:g}, {SPEED_MAX:g}] or 'max'")

    @model_validator(mode="after")
    def _needs(self) -> ControlRequest:
        wanted = {"seek": "time", "speed": "speed"}.get(self.action)
        for name in ("time", "speed"):
            given = getattr(self, name) is not None
            if name == wanted and not given:
                raise ValueError(f"action {self.action!r} needs {name!r}")
            if name != wanted and given:
                raise ValueError(f"{name!r} goes with action "
                                 f"{'seek' if name == 'time' else 'speed'!r} only")
        return self


class IntegrityModel(BaseModel):
    mode: Literal["fused", "coasting", "aligning", "no position"] = Field(
        description="fused: carrier phase drives the trajectory; coasting: INS (+VO) without "
                    "it; aligning: heading from the course only; no position: nothing to trust")
    trusted: bool = Field(description="the mode is usable, no critical fault is active and both "
                                      "protection levels are within their alert limits")
    reasons: list[str] = Field(description="active faults and exceeded limits, most severe first")
    hpl_m: float | None = Field(description="horizontal protection level (m)")
    heading_pl_deg: float | None = Field(description="heading protection level (deg)")
    alert_limit_m: float
    heading_alert_limit_deg: float


class FusionStatusModel(BaseModel):
    phase: str = Field(description="initialising | aligning | fused | degraded")
    compass_fixed: bool
    satellites: int
    vo_status: str = Field(description="tracking | initialising | lost | excluded (off the "
                                       "gyro or the fused track) | skipped (unusable frames: "
                                       "black, blinded, frozen) | off")
    scale: float | None
    scale_converged: bool
    message: str
    integrity: IntegrityModel | None = None


class Alarm(BaseModel):
    id: str
    kind: str = Field(description="integrity, or a fault kind (imu-gap, receiver-4-silent, …)")
    severity: Literal["alarm", "warning", "caution"] = Field(
        description="alarm: sounds until acknowledged; warning: shown; caution: listed")
    message: str
    since_s: float = Field(description="s since the recording start")
    active: bool
    acknowledged: bool
    peak_severity: Literal["alarm", "warning", "caution"] = Field(
        description="the worst it reached (an alarm that eased to a warning: alarm)")
    peak_message: str = Field(description="what it said at its worst, the last time")
    peak_s: float = Field(description="when, s since the recording start")
    first_message: str = Field(description="what it said when raised: its cause")
    repeats: int = Field(description="times it came back within 5 s of clearing (the same "
                                     "alarm again, not a new one sounding)")


class AlarmList(BaseModel):
    alarms: list[Alarm]


class WaterLevelModel(BaseModel):
    down_m: float = Field(description="the water plane's down coordinate in the world frame")
    source: str = Field(description="request | manifest | reference | unknown…")


class LiveInput(BaseModel):
    name: str = Field(description="imu, camera, rx1 … rx4")
    state: str = Field(description="connecting | streaming | lagging | stopped")
    received: int
    late: int = Field(description="messages dropped: they came after the merge passed them")
    ahead: int = Field(0, description="messages dropped: their time tag was ahead of the "
                                      "receivers' clock by more than half a second")
    rejected: int = Field(0, description="messages or lines the decoder rejected (bad "
                                         "checksum, unparsable, out of range)")
    last_rejection: str | None = Field(None, description="why the last one was rejected")
    last_gpst: float | None
    error: str | None


class LiveRecordingStatus(BaseModel):
    directory: str
    recording: bool
    frames: int
    imu_samples: int
    epochs: list[int] = Field(description="observation epochs written per receiver")
    duration_s: float


class LiveStatus(BaseModel):
    """A live session's inputs and the recording it writes."""

    inputs: list[LiveInput]
    recording: LiveRecordingStatus | None = Field(description="None: not recording")
    skipped_frames: int = Field(0, ge=0, description="video frames the engine skipped to keep "
                                                     "up with the sensors (it was behind)")
    recording_error: str | None = Field(None, description="why the recording stopped, if it did")


class LiveBrief(BaseModel):
    recording: bool = Field(description="the record indicator")
    record_s: float | None = Field(description="seconds recorded")
    inputs_down: list[str] = Field(description="inputs not streaming")


class SessionStatus(BaseModel):
    id: str
    recording: str
    state: str = Field(description="starting | playing | paused | seeking | ended | error")
    time_s: float = Field(description="replay position, s since the recording start")
    duration_s: float
    speed: float | Literal["max"]
    playing: bool
    seek_target_s: float | None
    lag_s: float = Field(description="how late the last message was on the replay clock")
    behind_s: float = Field(description="recording seconds the replay fell behind real time "
                                        "since it last started playing (engine too slow)")
    achieved_speed: float | None = Field(
        None, description="recording seconds per wall second since the replay clock last "
                          "started (play, seek, speed): below `speed` when the engine cannot "
                          "keep up; null while paused, seeking or flat out")
    frames_processed: int
    frames_total: int
    clients: int
    error: str | None
    fusion: FusionStatusModel | None
    timing_ms: dict[str, float] = Field(description="engine milliseconds per call by stage")
    checkpoints_s: list[float] = Field(description="cached engine copies for backward seeks")
    checkpoint_note: str | None
    scouted_s: float | None = Field(
        default=None, description="how far the look-ahead engine has run (s since the start): "
                                  "a seek up to here fast-forwards at most 2 s of recording; "
                                  "None without one (live, checkpoints off)")
    prediction_seconds: int
    options: dict[str, Any]
    has_reference: bool
    water_level: WaterLevelModel
    created_at: float
    live: LiveStatus | None = Field(default=None, description="live session: its inputs and "
                                                              "recording; None for a replay")


class SessionList(BaseModel):
    sessions: list[SessionStatus]


class Pose(BaseModel):
    t: float
    gpst: float
    position_ned: Vec3
    llh_deg: Vec3
    velocity_ned: Vec3
    euler_deg: Vec3 = Field(description="roll, pitch, yaw")
    heading_deg: float
    heading_std_deg: float = Field(description="1-σ of the heading (the attitude's about down)")
    speed_mps: float
    speed_std_mps: float = Field(description="1-σ of the speed over ground")
    course_deg: float | None = Field(description="course over ground; None below 0.05 m/s")
    course_std_deg: float | None = Field(
        description="1-σ of the course: the velocity's across the track over the speed")
    rate_of_turn_dps: float
    rate_of_turn_std_dps: float = Field(description="1-σ: the smoothed gyro noise and its bias")
    position_std_m: Vec3 = Field(description="1-σ against the world origin (NED): the filter's "
                                 "and the drift it does not model (correlated carrier-phase "
                                 "errors, the origin's standalone fix), which grows with time")
    velocity_std_mps: Vec3
    attitude_std_deg: Vec3


class PoseResponse(Pose):
    status: FusionStatusModel


class Trajectory(BaseModel):
    session: str
    count: int
    t: list[float]
    position_ned: list[Vec3]
    llh_deg: list[Vec3]
    velocity_ned: list[Vec3]
    euler_deg: list[Vec3]
    position_std_m: list[Vec3]
    phase: list[str]


class Structure(BaseModel):
    t: float | None = Field(description="replay time of the snapshot")
    count: int
    points_ned: list[Vec3]
    sigma_m: list[float]
    ids: list[int]


class Outline(BaseModel):
    seconds: float
    ne: list[Vec2]


class Prediction(BaseModel):
    t: float
    seconds: int
    current: list[Vec2]
    outlines: list[Outline]


# -------------------------------------------------------------------------------- targets


class TargetCreate(Strict):
    frame_time: FrameTime = Field("current", description="the frame the pixel belongs to")
    u: Pixel = Field(description="image column (distorted pixels)")
    v: Pixel = Field(description="image row (distorted pixels)")
    label: str | None = Field(None, max_length=64)


class TrackPoint(BaseModel):
    t: float
    gpst: float
    position_ned: Vec3
    visible: bool
    uv: Vec2 | None
    distance_m: float
    hull_distance_m: float


class TargetOut(BaseModel):
    id: str
    label: str | None
    method: Literal["structure", "water-plane"] = Field(
        description="3-D point from port-structure points near the ray, or the ray's "
                    "intersection with the water plane")
    position_ned: Vec3
    frame_time: float
    designated_t: float
    uv: Vec2
    support_points: int
    distance_m: float | None
    hull_distance_m: float | None
    visible: bool | None


class TargetDetail(TargetOut):
    track: list[TrackPoint]


class TargetList(BaseModel):
    targets: list[TargetOut]


class BerthFromBow(Strict):
    distance_m: Annotated[float, Field(ge=0.0, le=MAX_BERTH_DISTANCE_M)] = Field(
        description="from the hull's foremost point to the line, perpendicular to it")
    bearing_deg: Annotated[float, Field(ge=-180.0, le=180.0)] = Field(
        description="direction of the line from the bow, relative to the ship's head: 0 "
                    "ahead, 90 starboard, -90 port; the line runs across it")


class BerthLineRequest(Strict):
    """Exactly one of ``image_points``, ``ned`` and ``from_bow`` (the schema's ``oneOf``)."""

    model_config = ConfigDict(json_schema_extra={"oneOf": [
        {"required": ["image_points"], "not": {"anyOf": [
            {"required": ["ned"]}, {"required": ["from_bow"]}, {"required": ["snap"]}]}},
        {"required": ["ned"], "not": {"anyOf": [
            {"required": ["image_points"]}, {"required": ["from_bow"]},
            {"required": ["frame_time"]}]}},
        {"required": ["from_bow"], "not": {"anyOf": [
            {"required": ["image_points"]}, {"required": ["ned"]}, {"required": ["snap"]},
            {"required": ["frame_time"]}]}}]})

    # not nullable: absent means absent (defaults are not validated)
    image_points: Annotated[list[PixelPoint], Field(min_length=2, max_length=2)] = Field(
        None, description="two clicks on the quay (coping, wall or water line) of the frame at "
                          "`frame_time`: the line is fitted to the quay face's port-structure "
                          "points between them (`method` quay-face), or where there are none, "
                          "where the clicks' rays meet the water plane (`method` water-plane)")
    frame_time: FrameTime = "current"
    ned: Annotated[list[PlanPoint], Field(min_length=2, max_length=2)] = Field(
        None, description=f"two (north, east) points, |north|, |east| <= {MAX_PLAN_M:g} m")
    snap: bool = Field(None, description="with `ned`: fit the line to the quay face's points "
                                         "near it (as clicked when there are none)")
    from_bow: BerthFromBow = Field(None, description="typed in: distance and direction from "
                                                     "the bow at the current pose")

    @model_validator(mode="after")
    def _one(self) -> BerthLineRequest:
        given = [name for name in ("image_points", "ned", "from_bow")
                 if getattr(self, name) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of 'image_points', 'ned' and 'from_bow'")
        if self.snap is not None and self.ned is None:
            raise ValueError("'snap' goes with 'ned' only")
        if "frame_time" in self.model_fields_set and self.image_points is None:
            raise ValueError("'frame_time' goes with 'image_points' only (the pixels' frame)")
        return self


class BerthNudge(Strict):
    offset_m: Annotated[float, Field(ge=-MAX_NUDGE_M, le=MAX_NUDGE_M)] = Field(
        0.0, description="move the line this far away from the ship (negative: towards it)")
    rotate_deg: Annotated[float, Field(ge=-MAX_NUDGE_DEG, le=MAX_NUDGE_DEG)] = Field(
        0.0, description="turn it about its middle, clockwise seen from above")


class BerthGeometry(BaseModel):
    """The ship against the berth line (``backend.geometry.berth_metrics``)."""

    bow_distance_m: float | None = Field(
        None, description="from the hull's foremost point, perpendicular to the line")
    stern_distance_m: float | None = Field(None, description="from the hull's aftmost point")
    bow_approach_mps: float | None = Field(None, description="positive when closing")
    stern_approach_mps: float | None = None
    bow_distance_sigma_m: float | None = Field(
        None, description="1-σ: the line's, the position's and the heading's")
    stern_distance_sigma_m: float | None = None
    bow_approach_sigma_mps: float | None = Field(
        None, description="1-σ: the fused velocity's across the line, the rate of turn's "
        "through the lever and the line's direction's")
    stern_approach_sigma_mps: float | None = None
    along_berth_mps: float | None = Field(
        None, description="speed along the line, positive the way the bow points along it")
    along_berth_sigma_mps: float | None = Field(
        None, description="1-σ: the fused velocity's along the line and the line's direction's")
    angle_deg: float | None = Field(
        None, description="between the centreline and the line, positive when the bow points "
        "towards it (bow in)")
    angle_sigma_deg: float | None = Field(
        None, description="1-σ: the line's direction and the heading's")
    time_to_contact_s: float | None = Field(
        None, description="until the first hull point reaches the line at the present closing "
                          "speeds; null when nothing closes")
    time_to_contact_sigma_s: float | None = Field(
        None, description="1-σ: that point's distance σ and closing-speed σ")
    nearest_distance_m: float | None = Field(None, description="of the whole hull outline")


BerthSource = Literal["recording", "ned", "image", "typed"]
BerthMethod = Literal["quay-face", "water-plane"]


class BerthLineStatus(BerthGeometry):
    line_ne: list[Vec2] | None
    source: BerthSource | None = Field(description="recording | ned | image | typed")
    method: BerthMethod | None = Field(
        None, description="quay-face: fitted to the port structure; water-plane: click rays "
                          "on the water plane (no structure near the clicks); null: as given")
    sigma_m: float | None = Field(None, description="1-σ of the line across itself")
    sigma_deg: float | None = Field(None, description="1-σ of its direction")
    support_points: int = Field(0, description="structure points the line is fitted to")
    note: str = Field("", description="what the officer should know about the line")
    nudged_m: float = Field(0.0, description="moved away from the ship by the officer since "
                                             "it was set (m; negative: towards it)")
    nudged_deg: float = Field(0.0, description="turned by the officer since it was set (deg, "
                                               "clockwise)")
    t: float | None


class ApproachLimitRow(Strict):
    within_m: Annotated[float, Field(gt=0.0, le=MAX_BERTH_DISTANCE_M)] = Field(
        description="the row applies at distances below this (the nearest row that does)")
    warning_cms: Annotated[float, Field(gt=0.0, le=500.0)] = Field(
        description="amber above this closing speed (cm/s)")
    alarm_cms: Annotated[float, Field(gt=0.0, le=500.0)] = Field(
        description="red, sounding, above this closing speed (cm/s); not below warning_cms "
                    "(422 otherwise, as for two rows with the same within_m)")


class ApproachLimits(Strict):
    """Approach-speed limits of the bow and stern by distance to the berth line."""

    rows: Annotated[list[ApproachLimitRow], Field(min_length=0, max_length=12)]


# --------------------------------------------------------------------------------- report


class ErrorStats(BaseModel):
    rms: float
    std: float = Field(description="horizontal errors: sqrt(var_N + var_E) of the 2-D error, "
                                   "as `berthing-aid replay --report` (table 17); others: the "
                                   "signed error's")
    mean: float = Field(description="horizontal errors: of the distance; others: signed")
    max: float = Field(description="of the absolute error")
    max_at_s: float


class Report(BaseModel):
    session: str
    recording: str
    after_s: float
    from_s: float
    to_s: float
    samples: int
    phases: dict[str, int]
    aligned_at_s: float = Field(description="the fused trajectory is matched to the reference "
                                            "at its first pose (it starts from its own origin); "
                                            "`replay --report` matches it at the origin's time, "
                                            "up to a second earlier, so its figures differ by "
                                            "the fused error over that second")
    horizontal_error_m: ErrorStats
    absolute_horizontal_error_m: ErrorStats = Field(
        description="from the fused latitude/longitude (SPP-anchored origin), not aligned")
    vertical_error_m: ErrorStats
    heading_error_deg: ErrorStats


class Viewer(BaseModel):
    available: bool
    url: str | None
    session: str | None = Field(description="the session the 3-D view shows")
    note: str | None = None


class ViewerFollow(Strict):
    session: str = Field(max_length=64)


class ViewerTheme(Strict):
    theme: Literal["day", "night"] = Field(description="the 3-D view's colours (one view for "
                                                       "every page: the last switch sets it)")


class ServerInfo(BaseModel):
    name: str
    version: str
    frontend: bool
    docs: str
    recordings: str
    viewer: str | None


# ------------------------------------------------------------------ stream (documentation)


class GridNodes(BaseModel):
    ned: list[Vec3]
    uv: list[Vec2]


class VideoGrid(BaseModel):
    cell_m: float
    radius_m: float
    plane_down_m: float = Field(description="the water plane's down coordinate")
    lines: list[list[Vec2]] = Field(description="polylines in distorted pixels")
    nodes: GridNodes = Field(description="visible grid intersections, full precision")


class VideoPoints(BaseModel):
    uv: list[Vec2]
    distance_m: list[float] = Field(description="from the camera")
    hull_distance_m: list[float] = Field(description="from the hull outline, in plan")
    band: list[int] = Field(description="index of the distance band (distance_bands_m) of "
                                        "hull_distance_m")
    color: list[str] = Field(description="'#rrggbb', the band's day colour")
    converged: list[bool]
    obstacle: list[bool] = Field(description="converged, above the water plane, near the ship "
                                             "or the berth line: drawn by default")
    id: list[int]


class VideoOutline(BaseModel):
    seconds: int
    polylines: list[list[Vec2]]


class VideoOverlay(BaseModel):
    hull: list[list[Vec2]] = Field(description="the current hull outline at the water line")
    grid: VideoGrid
    points: VideoPoints
    prediction: list[VideoOutline]


class PlanPoints(BaseModel):
    ne: list[Vec2]
    color: list[str]
    band: list[int]
    converged: list[bool]
    obstacle: list[bool]


class PlanTarget(BaseModel):
    id: str
    ne: Vec2


class BirdsEye(BaseModel):
    position: Vec2
    heading_deg: float
    ship: list[Vec2]
    frustum: list[Vec2] = Field(description="camera, left and right field-of-view edges")
    radius_m: float
    points: PlanPoints
    prediction: list[Outline]
    targets: list[PlanTarget]
    berth_line: list[Vec2] | None


class TargetReadout(BaseModel):
    id: str
    label: str | None
    visible: bool
    uv: Vec2 | None
    distance_m: float
    hull_distance_m: float


class BerthReadout(BerthGeometry):
    polylines: list[list[Vec2]]
    source: BerthSource | None = Field(None, description="where the line came from")
    method: BerthMethod | None = None
    sigma_m: float | None = None
    support_points: int = 0
    note: str = ""


class Overlay(BaseModel):
    video: VideoOverlay
    birdseye: BirdsEye
    targets: list[TargetReadout]
    berth: BerthReadout | None
    distance_bands_m: list[float] = Field(
        description="upper ends of the fixed distance bands of the points (the last band is "
                    "beyond the last of these)")


class ReplayBrief(BaseModel):
    state: str
    speed: float | None
    lag_s: float
    behind_s: float = Field(0.0, description="recording seconds the replay fell behind real "
                                             "time since it last started playing")
    achieved_speed: float | None = Field(None, description="recording seconds per wall "
                                                           "second since the clock started")
    scouted_s: float | None = Field(None, description="how far the look-ahead engine has run: "
                                                      "seeks up to here are quick")


class StreamFrameHeader(BaseModel):
    """The text message sent before each JPEG on ``/api/sessions/{id}/stream``."""

    type: Literal["frame"]
    session: str
    frame: int
    t: float
    gpst: float
    width: int
    height: int
    jpeg_bytes: int
    replay: ReplayBrief
    processed_at: float
    seq: int = Field(description="this client's frame number, to acknowledge")
    sent_at: float
    pose: Pose | None
    status: FusionStatusModel | None
    overlay: Overlay | None
    alarms: list[Alarm] = Field(default_factory=list, description="active alarms")
    live: LiveBrief | None = Field(default=None, description="live session: record indicator "
                                                             "and inputs down; None in replay")
    picture_t: float | None = Field(
        default=None, description="s since the start of the picture when it is older than "
                                  "`t` (a live camera silent while the other sensors go on, "
                                  "or frozen on an old picture): the state is `t`'s, nothing "
                                  "is drawn on the picture")
