"""The web application: ``create_app(settings)`` builds the FastAPI app.

Routes are grouped by resource (``routes_recordings``, ``routes_sessions``, ``routes_targets``,
``routes_viewer``); the services they use (recording catalogue, session manager, 3-D viewer)
live on ``app.state`` and reach the routes as injected dependencies (``deps``).
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles

from engine.driver import EngineFactory, create_engine
from recordings import DEFAULT_RECORDING

from . import routes_recordings, routes_sessions, routes_targets, routes_viewer
from .catalog import RecordingCatalog
from .errors import ApiError
from .models import ServerInfo
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


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    catalog = RecordingCatalog(settings.recordings_dir, settings.default_recording)
    manager = SessionManager(catalog, settings.engine_factory, settings.max_sessions,
                             settings.checkpoint_interval_s, settings.abandoned_after_s)

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
        try:
            yield
        finally:
            manager.close_all()
            if view is not None:
                view.stop()

    app = FastAPI(
        title="Berthing aid",
        version=VERSION,
        summary="Replays recorded berthings through the camera + GNSS compass + IMU fusion and "
                "streams the pose and the AR berthing overlay.",
        description="Times are seconds since the recording start unless named `gpst`; "
                    "positions are metres north/east/down in the local-level frame at the world "
                    "origin; angles in degrees. Errors answer `{\"detail\": \"what is wrong\"}`. "
                    "The per-frame stream is the WebSocket `/api/sessions/{id}/stream` "
                    "(schema of its frame header: `GET /api/stream/schema`).",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.catalog = catalog
    app.state.manager = manager
    app.state.viewer = None

    @app.exception_handler(ApiError)
    async def api_error(_request: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse({"detail": exc.message}, status_code=exc.status)

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
