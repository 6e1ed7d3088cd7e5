"""Dependencies injected into the routes (the app's services live on ``app.state``)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, Path, Request

from .catalog import RecordingCatalog
from .models import ErrorResponse
from .sessions import Session, SessionManager


def get_catalog(request: Request) -> RecordingCatalog:
    return request.app.state.catalog


def get_manager(request: Request) -> SessionManager:
    return request.app.state.manager


def get_viewer(request: Request) -> Any | None:
    return request.app.state.viewer


CatalogDep = Annotated[RecordingCatalog, Depends(get_catalog)]
ManagerDep = Annotated[SessionManager, Depends(get_manager)]


def get_session(manager: ManagerDep,
                session_id: Annotated[str, Path(description="id from POST /api/sessions",
                                                max_length=64)]) -> Session:
    return manager.get(session_id)


SessionDep = Annotated[Session, Depends(get_session)]


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for the error statuses a route may answer."""
    return {code: {"model": ErrorResponse} for code in codes}
