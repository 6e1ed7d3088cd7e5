"""The web application: ``create_app(settings)`` builds the FastAPI app.

Routes are grouped by resource (``routes_recordings``, ``routes_sessions``, ``routes_targets``,
``routes_viewer``); the services they use (recording catalogue, session manager, 3-D viewer)
live on ``app.state`` and reach the routes as injected dependencies (``deps``).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fastapi import Depends, FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from engine.driver import EngineFactory, create_engine
from estimator.integrity import IntegrityConfig
from recordings import DEFAULT_RECORDING

from . import routes_recordings, routes_sessions, routes_targets, routes_viewer
from .access import Access, TokenGate
from .catalog import RecordingCatalog
from .errors import install_handlers
from .http_rules import MethodGate, reject_unknown_query
from .models import ErrorResponse, FusionOptionsModel, ServerInfo
from .sessions import Session, SessionManager

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
FRONTEND_DIR = ROOT / "frontend"
VERSION = "0.1.0"


@dataclass
class Settings:
    recordings_dir: Path | None = None  # sub-directories holding a manifest.json are listed
    default_recording: Path | None = DEFAULT_RECORDING
    frontend_dir: Path = FRONTEND_DIR
    viser_host: str = "127.0.0.1"
    viser_port: int | None = 8080  # None: no 3-D viewer; 0: any free port
    max_sessions: int = 4
    engine_factory: EngineFactory = create_engine
    checkpoint_interval_s: float | None = 10.0  # engine copies for backward seeks; None: off
    abandoned_after_s: float = 120.0  # at the session limit, reclaim one unwatched this long
    announce: bool = False  # print the 3-D viewer's URL once it listens (the CLI does)
    integrity: IntegrityConfig | None = None  # alert limits (None: the engine's defaults)
    access: Access = field(default_factory=Access)  # tokens required on /api (none: open)
    # Started with the server: a live session (``backend.live_session``) from this config
    live_config: Any = None  # live.config.LiveConfig
    bridge: Any = None  # live.config.BridgeConfig: NMEA from every replay session
    # start the default recording's look-ahead engine at once (the CLI does): the first
    # page's seeks are quick too
    warm_scout: bool = False


API_DESCRIPTION = (
    "Times are seconds since the recording start unless named `gpst`; "
    "positions are metres north/east/down in the local-level frame at the world "
    "origin; angles in degrees. Numbers are finite and within the documented "
    "ranges. Every error answers the `ErrorResponse` schema: "
    "`{\"detail\": \"what is wrong\", \"errors\": [{\"field\", "
    "\"message\", \"type\"}]}` (`errors` lists the wrong fields of a 422; "
    "a body that is not JSON is a 422 too, one that cannot be decoded a 400). "
    "Unknown body fields and unknown query parameters are 422. "
    "The per-frame stream is the WebSocket `/api/sessions/{id}/stream` "
    "(schema of its frame header: `GET /api/stream/schema`). "
    "Off loopback every `/api` request needs `Authorization: Bearer <token>` "
    "(the stream: `?token=`); a read-only token may only read and watch.")


def _warm(manager: SessionManager) -> None:
    """The default recording's look-ahead engine, with the options a page opens it with."""
    name = manager.catalog.default_name()
    if name is None:
        return
    try:
        manager.warm(name, FusionOptionsModel().model_dump())
    except Exception:  # a recording that does not load says so when a page opens it
        log.exception("warming the look-ahead engine of %s failed", name)


def _lifespan(settings: Settings, manager: SessionManager
              ) -> Callable[[FastAPI], AbstractAsyncContextManager[None]]:
    """The app's start and end: the 3-D viewer (when asked) follows the newest session; at
    the end every session is closed."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        view = None
        if settings.viser_port is not None:
            from .viser_view import ViserView  # viser starts a server thread: only when asked

            view = ViserView(settings.viser_host, settings.viser_port)
            manager.created_listeners.append(view.follow)  # the newest session is shown

            def closed(session: Session) -> None:  # then the newest one still open
                if view.session_id == session.id:
                    view.forget(session)
                    remaining = manager.all()
                    if remaining:
                        view.follow(max(remaining, key=lambda s: s.created))

            manager.closed_listeners.append(closed)
            if settings.announce:
                print(f"3-D viewer: {view.url()}", flush=True)
        app.state.viewer = view
        if settings.bridge is not None:
            from .live_session import BridgeFeed

            def follow(session: Session) -> None:  # every replay tells the bridge, as simulated
                if not session.live:
                    feed = BridgeFeed(settings.bridge, simulated=True)
                    session.frame_listeners.append(feed)
                    session.closers.append(feed.close)

            manager.created_listeners.append(follow)
        app.state.live_session = None
        if settings.live_config is not None:
            from .live_session import start_live_session

            app.state.live_session = start_live_session(manager, settings.live_config,
                                                        integrity=settings.integrity)
            if settings.announce:
                print(f"live session {app.state.live_session.id} "
                      f"({settings.live_config.path})", flush=True)
        if settings.warm_scout and settings.live_config is None:
            threading.Thread(target=_warm, args=(manager,), name="warm-scout",
                             daemon=True).start()
        try:
            yield
        finally:
            manager.close_all()
            if view is not None:
                view.stop()

    return lifespan


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    catalog = RecordingCatalog(settings.recordings_dir, settings.default_recording)
    manager = SessionManager(catalog, settings.engine_factory, settings.max_sessions,
                             settings.checkpoint_interval_s, settings.abandoned_after_s,
                             settings.integrity)

    lifespan = _lifespan(settings, manager)

    # Every route may answer 422 (a wrong field or an unknown query parameter), in the one
    # error schema; with access control also 401 and 403.
    responses: dict[int | str, dict[str, Any]] = {
        422: {"model": ErrorResponse, "description": "a field or parameter is wrong: `errors` "
                                                     "names each one"}}
    if settings.access.required:
        responses[401] = {"model": ErrorResponse, "description": "no or unknown token"}
        responses[403] = {"model": ErrorResponse, "description": "read-only token"}
    app = FastAPI(
        title="Berthing aid",
        version=VERSION,
        summary="Replays recorded berthings through the camera + GNSS compass + IMU fusion and "
                "streams the pose and the AR berthing overlay.",
        description=API_DESCRIPTION,
        lifespan=lifespan,
        responses=responses,
        dependencies=[Depends(reject_unknown_query)],
    )
    app.state.settings = settings
    app.state.catalog = catalog
    app.state.manager = manager
    app.state.viewer = None
    install_handlers(app)
    app.add_middleware(MethodGate)
    app.add_middleware(TokenGate, access=settings.access)
    if settings.access.required:
        _document_bearer(app)

    app.include_router(routes_recordings.router)
    app.include_router(routes_sessions.router)
    app.include_router(routes_sessions.stream_router)
    app.include_router(routes_targets.router)
    app.include_router(routes_viewer.router)

    index = settings.frontend_dir / "index.html"

    @app.get("/", include_in_schema=False, response_model=None)
    def root() -> FileResponse | ServerInfo:
        if index.is_file():
            return FileResponse(index)
        view = app.state.viewer
        return ServerInfo(name="berthing-aid", version=VERSION, frontend=False,
                          docs="/docs", recordings="/api/recordings",
                          viewer=None if view is None else "/api/viewer")

    if settings.frontend_dir.is_dir():
        # after the API routes: the page's own files (scripts, styles) at the root
        app.mount("/", StaticFiles(directory=settings.frontend_dir), name="frontend")
    return app


def _document_bearer(app: FastAPI) -> None:
    """Declare the bearer token in OpenAPI (only when it is required: a schema that declares
    it on an open server would be wrong)."""
    plain = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = plain()
            schema.setdefault("components", {})["securitySchemes"] = {
                "token": {"type": "http", "scheme": "bearer",
                          "description": "control or read-only token printed by serve"}}
            schema["security"] = [{"token": []}]
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
