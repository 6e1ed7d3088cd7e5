"""Routes of the ``viewer`` resource: the viser 3-D view run by the same process."""

from __future__ import annotations

from fastapi import APIRouter, Request

from .deps import ManagerDep, errors, get_viewer
from .errors import Conflict
from .models import Viewer, ViewerFollow, ViewerTheme

router = APIRouter(prefix="/api/viewer", tags=["viewer"])


def _viewer(request: Request) -> Viewer:
    view = get_viewer(request)
    if view is None:
        return Viewer(available=False, url=None, session=None,
                      note="the 3-D viewer is disabled (serve --viser-port 0 … or not started)")
    # the host the browser used for the API reaches the viewer too (loopback or not)
    host = request.url.hostname or view.host
    return Viewer(available=True, url=view.url(host), session=view.session_id,
                  note="trajectory red, port structure blue, reference grey")


@router.get("", response_model=Viewer, summary="URL of the 3-D viewer")
def get_viewer_info(request: Request) -> Viewer:
    return _viewer(request)


@router.put("", response_model=Viewer, responses=errors(400, 404, 409),
            summary="Choose the session the 3-D viewer shows")
def follow_session(body: ViewerFollow, request: Request, manager: ManagerDep) -> Viewer:
    view = get_viewer(request)
    session = manager.get(body.session)
    if view is None:
        raise Conflict("the 3-D viewer is disabled")
    view.follow(session)
    return _viewer(request)


@router.put("/theme", response_model=Viewer, responses=errors(400, 409),
            summary="Day or night colours in the 3-D view (the page's theme)")
def set_theme(body: ViewerTheme, request: Request) -> Viewer:
    view = get_viewer(request)
    if view is None:
        raise Conflict("the 3-D viewer is disabled")
    view.set_theme(body.theme)
    return _viewer(request)
