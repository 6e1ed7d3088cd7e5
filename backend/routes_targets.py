"""Routes of a session's designated ``targets`` and its ``berth-line``."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Response, status
from pydantic import BaseModel, Field

from .deps import SessionDep, errors
from .models import (
    BerthLineRequest,
    BerthLineStatus,
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
             status_code=status.HTTP_201_CREATED, responses=errors(404, 409, 422),
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
    projects)."""
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


@router.put("/berth-line", response_model=BerthLineStatus, responses=errors(404, 409, 422),
            summary="Set the berth line")
def put_berth_line(body: BerthLineRequest, session: SessionDep) -> BerthLineStatus:
    """From two (north, east) points, or from two pixels on the quay's water line of a frame
    (their rays meet the water plane). Answers the bow and stern distance to the line and
    their approach speeds (positive closing) at the current pose."""
    if body.ned is not None:
        session.set_berth_line_ned(body.ned)
    else:
        frame_t = None if body.frame_time == "current" else float(body.frame_time)
        session.set_berth_line_image(frame_t, body.image_points)
    return _berth_status(session)


@router.get("/berth-line", response_model=BerthLineStatus, responses=errors(404),
            summary="Berth line with bow/stern distance and approach speed")
def get_berth_line(session: SessionDep) -> BerthLineStatus:
    return _berth_status(session)


@router.delete("/berth-line", status_code=status.HTTP_204_NO_CONTENT, responses=errors(404),
               summary="Remove the berth line")
def delete_berth_line(session: SessionDep) -> Response:
    session.clear_berth_line()
    return Response(status_code=status.HTTP_204_NO_CONTENT)

