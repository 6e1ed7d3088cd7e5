"""Routes of the ``sessions`` resource: create, control and read a replay session, and its
stream (WebSocket)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Path, Query, Response, WebSocket, status
from fastapi.concurrency import run_in_threadpool

from .deps import ManagerDep, SessionDep, errors
from .errors import NotFound
from .geometry import hull_outline_ne
from .models import (
    MAX_TIME_S,
    Alarm,
    AlarmList,
    ControlRequest,
    Outline,
    PoseResponse,
    Prediction,
    Report,
    SessionCreate,
    SessionList,
    SessionStatus,
    StreamFrameHeader,
    Structure,
    Trajectory,
)
from .overlay import pose_dict, status_dict
from .sessions import Session
from .stream import serve_stream

router = APIRouter(prefix="/api/sessions", tags=["sessions"])


def _status(session: Session) -> SessionStatus:
    return SessionStatus(**session.status_brief())


@router.get("", response_model=SessionList, summary="List the open sessions")
def list_sessions(manager: ManagerDep) -> SessionList:
    return SessionList(sessions=[_status(s) for s in manager.all()])


@router.post("", response_model=SessionStatus, status_code=status.HTTP_201_CREATED,
             responses=errors(400, 404, 429), summary="Start replaying a recording")
async def create_session(body: SessionCreate, manager: ManagerDep) -> SessionStatus:
    """Replays ``recording`` through the fusion engine at ``speed`` (or paused), with the
    scenario ``options`` (satellite subsets, sky mask…). Loading a recording the first time
    takes a few seconds."""
    manager.catalog.resolve(body.recording)  # a bad name is rejected before any work
    session = await run_in_threadpool(
        manager.create, body.recording, None if body.speed == "max" else float(body.speed),
        body.options.model_dump(), body.paused, body.prediction_seconds, body.body_height_m)
    return _status(session)


@router.get("/{session_id}", response_model=SessionStatus, responses=errors(404),
            summary="Session status")
def get_session_status(session: SessionDep) -> SessionStatus:
    return _status(session)


@router.delete("/{session_id}", status_code=status.HTTP_204_NO_CONTENT,
               responses={**errors(404), 202: {"description": "deleted once unwatched"}},
               summary="Stop and delete a session")
def delete_session(session: SessionDep, manager: ManagerDep,
                   when_unwatched: Annotated[bool, Query(
                       description="only once no client watches it (202 while one does): "
                                   "what a closing page asks, so that a session another "
                                   "tab joined, and its locked targets, stay")] = False
                   ) -> Response:
    if not when_unwatched:
        manager.delete(session.id)
    elif not manager.delete_when_unwatched(session.id):
        return Response(status_code=status.HTTP_202_ACCEPTED)  # once its last watcher goes
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.post("/{session_id}/control", response_model=SessionStatus,
             responses=errors(400, 404, 409), summary="Play, pause, seek or change speed")
def control_session(body: ControlRequest, session: SessionDep) -> SessionStatus:
    """``seek`` restarts the engine from the nearest cached checkpoint before ``time`` (or from
    the start) and runs it as fast as possible up to ``time`` without sending frames; a seek
    forward fast-forwards from the current position, or jumps to a copy the look-ahead engine
    left on its way (``scouted_s`` says how far it got: up to there a seek fast-forwards at
    most 2 s of recording). The state is ``seeking`` meanwhile.
    ``play`` at the end of the recording is 409: nothing is thrown away unless the client
    seeks back (the history after the seek target is then recomputed). ``play`` after an
    error (state ``error``, the message in ``error``) restarts the engine from the newest
    checkpoint before the replay position, or from the start, and recomputes up to it."""
    session.control(body.action, body.time, body.speed)
    return _status(session)


@router.get("/{session_id}/pose", response_model=PoseResponse, responses=errors(404, 409),
            summary="Current pose, or the pose at a past time")
def get_pose(session: SessionDep,
             t: Annotated[float | None, Query(
                 ge=0.0, le=MAX_TIME_S, allow_inf_nan=False,
                 description="s since the recording start; omitted: the current pose. The "
                             "stored pose of the last frame at or before t.")] = None
             ) -> PoseResponse:
    state = session.current_state() if t is None else session.history.state_at(t)
    return PoseResponse(**pose_dict(state, session.start_gpst),
                        status=status_dict(state.status))


@router.get("/{session_id}/trajectory", response_model=Trajectory,
            responses={**errors(404), 200: {"content": {"text/csv": {}}}},
            summary="Fused trajectory so far (JSON columns or CSV)")
def get_trajectory(session: SessionDep,
                   format: Annotated[Literal["json", "csv"], Query()] = "json"
                   ) -> Trajectory | Response:
    if format == "csv":
        return Response(session.history.trajectory_csv(), media_type="text/csv",
                        headers={"Content-Disposition":
                                 f'attachment; filename="{session.name}-{session.id}.csv"'})
    return Trajectory(session=session.id, **session.history.trajectory())


@router.get("/{session_id}/structure", response_model=Structure, responses=errors(404),
            summary="Port-structure points (3-D feature points)")
def get_structure(session: SessionDep,
                  max_sigma: Annotated[float | None, Query(
                      gt=0.0, le=1e6, allow_inf_nan=False,
                      description="only points with sigma <= this (m)")] = None
                  ) -> Structure:
    s = session.structure()
    pts, sigma, ids, t = s.points, s.sigma, s.ids, s.t
    if max_sigma is not None and len(sigma) == len(pts):
        keep = sigma <= max_sigma
        pts, sigma, ids = pts[keep], sigma[keep], ids[keep]
    return Structure(t=None if t is None else t - session.start_gpst, count=len(pts),
                     points_ned=pts.round(4).tolist(), sigma_m=sigma.round(4).tolist(),
                     ids=[int(i) for i in ids])


@router.get("/{session_id}/prediction", response_model=Prediction,
            responses=errors(404, 409), summary="Predicted hull outlines")
def get_prediction(session: SessionDep,
                   seconds: Annotated[int, Query(ge=0, le=60, description="N: outlines at "
                                                 "1, 2, … N s ahead")] = 5) -> Prediction:
    """Constant rate of turn and constant body-frame velocity from the current state."""
    state, outlines = session.prediction(seconds)
    return Prediction(t=float(state.time) - session.start_gpst, seconds=seconds,
                      current=hull_outline_ne(state, session.rec.hull).round(3).tolist(),
                      outlines=[Outline(seconds=k, ne=o.round(3).tolist())
                                for k, o in enumerate(outlines, start=1)])


@router.get("/{session_id}/report", response_model=Report, responses=errors(404, 409),
            summary="Accuracy against the reference trajectory so far")
def get_report(session: SessionDep,
               after: Annotated[float, Query(ge=0.0, le=MAX_TIME_S, allow_inf_nan=False,
                                             description="ignore the first `after` s "
                                             "(initialisation; the thesis uses 30 s)")] = 0.0
               ) -> Report:
    """Horizontal error (RMS, std, mean, max), vertical and heading error of the fused poses
    so far against the recording's reference, the trajectory matched to the reference at its
    first pose (the engine integrates from its own origin); also the unaligned error of the
    fused latitude/longitude. 404 when the recording has no reference."""
    return Report(**session.report(after))


@router.get("/{session_id}/alarms", response_model=AlarmList, responses=errors(404),
            summary="Alarms: integrity and faults (active and cleared)")
def get_alarms(session: SessionDep,
               active: Annotated[bool, Query(description="only the active ones")] = False
               ) -> AlarmList:
    alarms = session.alarms.active() if active else session.alarms.all()
    return AlarmList(alarms=[Alarm(**a) for a in alarms])


@router.post("/{session_id}/alarms/{alarm_id}/acknowledge", response_model=Alarm,
             responses=errors(404), summary="Acknowledge an alarm (it stops sounding)")
def acknowledge_alarm(session: SessionDep,
                      alarm_id: Annotated[str, Path(max_length=16)]) -> Alarm:
    alarm = session.alarms.acknowledge(alarm_id)
    if alarm is None:
        raise NotFound(f"no alarm {alarm_id!r} in this session")
    session.redraw_if_paused()
    return Alarm(**alarm)


@router.websocket("/{session_id}/stream")
async def stream(websocket: WebSocket, session_id: str) -> None:
    """One JSON header (text) + one JPEG (binary) per video frame; see ``backend.stream``
    (its query, read there: a bad one is told by name, not refused bare at the handshake)."""
    await serve_stream(websocket, websocket.app.state.manager, session_id)


stream_router = APIRouter(prefix="/api/stream", tags=["sessions"])


@stream_router.get("/schema", summary="JSON schema of the stream's frame header")
def stream_schema() -> dict:
    """The WebSocket stream is not part of OpenAPI; this is the schema of its frame header
    (text message sent before each binary JPEG)."""
    return StreamFrameHeader.model_json_schema()
