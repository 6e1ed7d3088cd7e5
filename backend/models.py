"""Request and response models of the HTTP API, declared once and reused by the OpenAPI schema.

Times in the API are seconds since the recording start (``t``, ``time``, ``frame_time``) unless
named ``gpst``; positions are metres north/east/down in the local-level frame at the world
origin; angles are degrees.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Speed = Annotated[float, Field(gt=0.0, le=64.0)] | Literal["max"]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Vec2 = Annotated[list[float], Field(min_length=2, max_length=2)]
SatelliteId = Annotated[str, Field(pattern=r"^[GRECJSI]\d{2}$", examples=["G05"])]
FrameTime = Annotated[float, Field(ge=0.0)] | Literal["current"]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")  # a misspelt field is an error, not ignored


class ErrorResponse(BaseModel):
    detail: str = Field(description="what is wrong with the request")


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
    keep_after_s: float = Field(30.0, ge=0.0)
    sky_mask_deg: float | None = Field(None, ge=0.0, le=90.0,
                                       description="elevation mask (deg)")
    per_receiver_sats: dict[Annotated[int, Field(ge=0, le=3)], list[SatelliteId]] | None = Field(
        None, description="receiver index (0..3) → the only satellites it keeps after "
                          "keep_after_s (thesis table 21); receivers not listed keep theirs",
        examples=[{"0": ["G05"], "1": ["G13"], "2": ["E11"], "3": ["J02"]}])


class SessionCreate(Strict):
    recording: str = Field(description="a name from GET /api/recordings", examples=["default"])
    speed: Speed = Field(1.0, description="replay speed factor, or 'max' (as fast as possible)")
    options: FusionOptionsModel = Field(default_factory=FusionOptionsModel)
    paused: bool = False
    prediction_seconds: int = Field(5, ge=0, le=30,
                                    description="predicted hull outlines in the stream")
    body_height_m: float | None = Field(
        None, ge=-50.0, le=100.0,
        description="height of the body origin (IMU) above the water: places the water plane "
                    "(grid, predicted outlines, water-plane targets). Default: from the "
                    "recording (see water_level.source in the status)")


class ControlRequest(Strict):
    action: Literal["play", "pause", "seek", "speed"]
    time: float | None = Field(None, ge=0.0, description="seek target, s since the start")
    speed: Speed | None = None

    @model_validator(mode="after")
    def _needs(self) -> ControlRequest:
        if self.action == "seek" and self.time is None:
            raise ValueError("action 'seek' needs 'time' (seconds since the recording start)")
        if self.action == "speed" and self.speed is None:
            raise ValueError("action 'speed' needs 'speed' (a factor in (0, 64] or 'max')")
        return self


class FusionStatusModel(BaseModel):
    phase: str = Field(description="initialising | aligning | fused | degraded")
    compass_fixed: bool
    satellites: int
    vo_status: str
    scale: float | None
    scale_converged: bool
    message: str


class WaterLevelModel(BaseModel):
    down_m: float = Field(description="the water plane's down coordinate in the world frame")
    source: str = Field(description="request | manifest | reference | unknown…")


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
    frames_processed: int
    frames_total: int
    clients: int
    error: str | None
    fusion: FusionStatusModel | None
    timing_ms: dict[str, float] = Field(description="engine milliseconds per call by stage")
    checkpoints_s: list[float] = Field(description="cached engine copies for backward seeks")
    checkpoint_note: str | None
    prediction_seconds: int
    options: dict[str, Any]
    has_reference: bool
    water_level: WaterLevelModel
    created_at: float


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
    speed_mps: float
    course_deg: float | None
    rate_of_turn_dps: float
    position_std_m: Vec3
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
    u: float = Field(description="image column (distorted pixels)")
    v: float = Field(description="image row (distorted pixels)")
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


class BerthLineRequest(Strict):
    image_points: Annotated[list[Vec2], Field(min_length=2, max_length=2)] | None = Field(
        None, description="two pixels on the quay's water line")
    frame_time: FrameTime = "current"
    ned: Annotated[list[Vec2], Field(min_length=2, max_length=2)] | None = Field(
        None, description="two (north, east) points")

    @model_validator(mode="after")
    def _one(self) -> BerthLineRequest:
        if (self.image_points is None) == (self.ned is None):
            raise ValueError("give exactly one of 'image_points' and 'ned'")
        return self


class BerthLineStatus(BaseModel):
    line_ne: list[Vec2] | None
    source: str | None = Field(description="recording | ned | image")
    t: float | None
    bow_distance_m: float | None
    stern_distance_m: float | None
    bow_approach_mps: float | None = Field(description="positive when closing")
    stern_approach_mps: float | None


# --------------------------------------------------------------------------------- report


class ErrorStats(BaseModel):
    rms: float
    std: float
    mean: float
    max: float
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
                                            "at its first pose (it starts from its own origin)")
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
    session: str


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
    distance_m: list[float]
    color: list[str] = Field(description="'#rrggbb', hue by distance (red near, blue far)")
    id: list[int]


class VideoOutline(BaseModel):
    seconds: int
    polylines: list[list[Vec2]]


class VideoOverlay(BaseModel):
    grid: VideoGrid
    points: VideoPoints
    prediction: list[VideoOutline]


class PlanPoints(BaseModel):
    ne: list[Vec2]
    color: list[str]


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


class BerthReadout(BaseModel):
    bow_distance_m: float | None
    stern_distance_m: float | None
    bow_approach_mps: float | None
    stern_approach_mps: float | None
    polylines: list[list[Vec2]]
    source: Literal["recording", "ned", "image"] | None = Field(
        None, description="where the line came from")


class Overlay(BaseModel):
    video: VideoOverlay
    birdseye: BirdsEye
    targets: list[TargetReadout]
    berth: BerthReadout | None
    color_range_m: float = Field(description="distance drawn blue (red at 0)")


class ReplayBrief(BaseModel):
    state: str
    speed: float | None
    lag_s: float


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
