"""Routes of a session's designated ``targets``, its ``berth-line`` and the approach-speed
limits of its berthing alarms."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Response, status
from pydantic import BaseModel, Field

from .alarms import ApproachLimit
from .deps import SessionDep, errors
from .errors import Unprocessable
from .models import (
    ApproachLimitRow,
    ApproachLimits,
    BerthLineRequest,
    BerthLineStatus,
    BerthNudge,
    TargetCreate,
    Vec2,
)
from .models import TargetOut as _TargetOutBase
from .models import TrackPoint as _TrackPointBase
from .sessions import Session
from .targets import Target

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["targets"])


# The target models with the image tracking (``estimator.tracking``) added (same names in
# the OpenAPI schema).
class TargetOut(_TargetOutBase):
    status: Literal["tracking", "lost"] = Field(
        description="tracking: the point is followed in the video in the current frame; lost: "
                    "it is not (occluded, out of the image, not found again) — the distance "
                    "is then that of its 3-D point, not of a point seen now")
    tracked_uv: Vec2 | None = Field(None, description="the tracked image point (distorted px)")
    score: float | None = Field(None, description="template correlation of the tracked point")
    reason: str = Field("", description="why the target is lost")
    distance_sigma_m: float | None = Field(
        None, description="1-σ of distance_m from the 3-D point's covariance")
    views: int = Field(0, description="tracked views (before and after the click) the 3-D "
                                      "point is triangulated from, in the attitudes the "
                                      "port-structure window solved; 0: not yet (the point "
                                      "is the click's)")


class TrackPoint(_TrackPointBase):
    status: Literal["tracking", "lost"] | None = None
    tracked_uv: Vec2 | None = None
    score: float | None = None
    reason: str = ""
    distance_sigma_m: float | None = None


class TargetDetail(TargetOut):
    track: list[TrackPoint]


class TargetList(BaseModel):
    targets: list[TargetOut]


def _target_out(session: Session, target: Target) -> dict:
    last = target.track[-1] if target.track else None
    return {
        "id": target.id,
        "label": target.label,
        "method": target.method,
        "position_ned": [round(float(x), 4) for x in target.position_ned],
        "frame_time": round(target.frame_gpst - session.start_gpst, 6),
        "designated_t": round(target.designated_gpst - session.start_gpst, 6),
        "uv": list(target.uv),
        "support_points": target.support,
        "distance_m": last["distance_m"] if last else None,
        "hull_distance_m": last["hull_distance_m"] if last else None,
        "visible": last["visible"] if last else None,
        "status": target.status,
        "tracked_uv": None if target.tracked_uv is None else [round(float(x), 2)
                                                              for x in target.tracked_uv],
        "score": None if target.score is None else round(float(target.score), 3),
        "reason": target.reason,
        "distance_sigma_m": None if target.distance_sigma_m is None else round(
            float(target.distance_sigma_m), 3),
        "views": target.views,
    }


@router.post("/targets", response_model=TargetOut,
             status_code=status.HTTP_201_CREATED, responses=errors(400, 404, 409),
             summary="Designate a point in the video")
def create_target(body: TargetCreate, session: SessionDep) -> TargetOut:
    """The 3-D point under pixel (u, v) of a frame (``frame_time``, or the current one): from
    the port-structure points projecting within 12 px of the pixel (24 px when fewer than two
    of them are on the nearest surface; that surface's median range along the ray; ``method``
    = ``structure``), else where the ray meets the water plane (``method`` = ``water-plane``);
    422 when neither exists. The point is then tracked in the video frame by frame (particle
    filter with template matching, ``estimator.tracking``); a structure point is also tracked
    back through the 20 s of video before the click, and its 3-D point triangulated from
    these views in the attitudes the port-structure window solved for them (``views``), at
    once and about once a second after. ``status`` says whether it is locked in the current
    frame (``lost`` when occluded, out of the image or not found again where its 3-D point
    projects). 409 while the replay seeks (the frame on screen is one it is leaving) and
    when a target already measures that pixel (within 3 px) of that frame."""
    frame_t = None if body.frame_time == "current" else float(body.frame_time)
    target = session.designate(frame_t, body.u, body.v, body.label)
    with session.lock:
        out = _target_out(session, target)
    return TargetOut(**out)


@router.get("/targets", response_model=TargetList, responses=errors(404),
            summary="Designated targets")
def list_targets(session: SessionDep) -> TargetList:
    with session.lock:
        outs = [_target_out(session, t) for t in session.targets.all()]
    return TargetList(targets=[TargetOut(**o) for o in outs])


@router.get("/targets/{target_id}", response_model=TargetDetail, responses=errors(404),
            summary="A target with its track over time")
def get_target(target_id: str, session: SessionDep) -> TargetDetail:
    target = session.targets.get(target_id)
    with session.lock:
        track = [TrackPoint(**p) for p in target.track]
        out = _target_out(session, target)
    return TargetDetail(**out, track=track)


@router.delete("/targets/{target_id}", status_code=status.HTTP_204_NO_CONTENT,
               responses=errors(404), summary="Forget a target")
def delete_target(target_id: str, session: SessionDep) -> Response:
    session.delete_target(target_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def _berth_status(session: Session) -> BerthLineStatus:
    return BerthLineStatus(**session.berth_status())


@router.put("/berth-line", response_model=BerthLineStatus, responses=errors(400, 404, 409),
            summary="Set the berth line")
def put_berth_line(body: BerthLineRequest, session: SessionDep) -> BerthLineStatus:
    """From two clicks on the quay in a frame (``image_points``: fitted to the quay face's
    converged port-structure points, else on the water plane — ``method`` and ``note`` say
    which), two (north, east) points (``ned``, fitted to the quay face near them with
    ``snap``), or typed in from the bow (``from_bow``). Answers the berth geometry at the
    current pose: bow and stern distance and approach speed (positive closing), speed along
    the berth, angle to it, time to contact, with σ."""
    if body.ned is not None:
        session.set_berth_line_ned(body.ned, snap=bool(body.snap))
    elif body.from_bow is not None:
        session.set_berth_line_from_bow(body.from_bow.distance_m, body.from_bow.bearing_deg)
    else:
        frame_t = None if body.frame_time == "current" else float(body.frame_time)
        session.set_berth_line_image(frame_t, body.image_points)
    return _berth_status(session)


@router.post("/berth-line/nudge", response_model=BerthLineStatus,
             responses=errors(400, 404, 409), summary="Nudge the berth line")
def nudge_berth_line(body: BerthNudge, session: SessionDep) -> BerthLineStatus:
    """Move the line ``offset_m`` away from the ship (negative: towards it) and turn it
    ``rotate_deg`` about its middle; 422 when there is no line."""
    session.nudge_berth_line(body.offset_m, body.rotate_deg)
    return _berth_status(session)


@router.get("/berth-line", response_model=BerthLineStatus, responses=errors(404),
            summary="Berth line with bow/stern distance and approach speed")
def get_berth_line(session: SessionDep) -> BerthLineStatus:
    """404 when the session has no berth line (none in the recording, none set, or deleted)."""
    return _berth_status(session)


@router.delete("/berth-line", status_code=status.HTTP_204_NO_CONTENT, responses=errors(404),
               summary="Remove the berth line (204 also when there is none)")
def delete_berth_line(session: SessionDep) -> Response:
    session.clear_berth_line()
    return Response(status_code=status.HTTP_204_NO_CONTENT)



def _limits(session: Session) -> ApproachLimits:
    return ApproachLimits(rows=[ApproachLimitRow(within_m=r.within_m, warning_cms=r.warning_cms,
                                                 alarm_cms=r.alarm_cms)
                                for r in session.alarms.approach_limits])


@router.get("/approach-limits", response_model=ApproachLimits, responses=errors(404),
            summary="Approach-speed alarm limits by distance")
def get_approach_limits(session: SessionDep) -> ApproachLimits:
    """The bow's and stern's closing speed raises an amber (``warning``) alarm above the
    row's ``warning_cms`` and a red sounding one (``alarm``) above its ``alarm_cms``; the row
    is the nearest whose ``within_m`` exceeds the distance to the berth line (none beyond the
    last row)."""
    return _limits(session)


@router.put("/approach-limits", response_model=ApproachLimits, responses=errors(400, 404),
            summary="Set the approach-speed alarm limits")
def put_approach_limits(body: ApproachLimits, session: SessionDep) -> ApproachLimits:
    """The whole table at once (an empty one: no approach alarms). 422 when a row's
    warning_cms exceeds its alarm_cms or two rows have the same within_m."""
    for r in body.rows:
        if r.warning_cms > r.alarm_cms:
            raise Unprocessable(f"the row within {r.within_m:g} m: warning_cms "
                                f"({r.warning_cms:g}) exceeds alarm_cms ({r.alarm_cms:g})")
    within = [r.within_m for r in body.rows]
    if len(set(within)) != len(within):
        raise Unprocessable("two rows have the same within_m")
    session.alarms.set_approach_limits([ApproachLimit(r.within_m, r.warning_cms, r.alarm_cms)
                                        for r in body.rows])
    session.redraw_if_paused()
    return _limits(session)
