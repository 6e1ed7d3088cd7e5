"""Errors the API reports as they are: an HTTP status and a message saying what is wrong.

Every error of every route has the one body ``models.ErrorResponse``: ``{"detail": "what is
wrong", "errors": [{"field", "message", "type"}, ...]}`` — ``errors`` lists the wrong fields of
a validation error (422) and is empty otherwise. The handlers installed by
``install_handlers`` make FastAPI's and Starlette's own errors (validation, malformed JSON,
unknown path, method not allowed) answer in it too. Error bodies never echo the input (a NaN
in it could not even be serialised) and never name other sessions.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger(__name__)


class ApiError(Exception):
    """An error the API reports as-is: HTTP status and a message saying what is wrong."""

    status = 400

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class BadRequest(ApiError):
    status = 400


class NotFound(ApiError):
    status = 404


class Conflict(ApiError):
    status = 409


class Unprocessable(ApiError):
    status = 422


class TooMany(ApiError):
    status = 429


def error_body(detail: str, errors: Sequence[dict[str, str]] = ()) -> dict[str, Any]:
    """The ``ErrorResponse`` body."""
    return {"detail": detail, "errors": list(errors)}


def field_errors(raw: Sequence[Any]) -> list[dict[str, str]]:
    """pydantic / FastAPI validation errors as ``FieldError``s (no input echoed)."""
    out = []
    for e in raw:
        loc = [str(part) for part in e.get("loc", ())]
        kind = str(e.get("type", "invalid"))
        message = str(e.get("msg", "invalid"))
        if kind == "json_invalid":
            loc = loc[:1]
            reason = (e.get("ctx") or {}).get("error")
            message = "the body is not valid JSON" + (f": {reason}" if reason else "")
        elif loc == ["body"] and kind == "missing":
            message = "a JSON body is required"
        elif kind == "value_error" and message.startswith("Value error, "):
            message = message.removeprefix("Value error, ")
        out.append({"field": ".".join(loc) or "request", "message": message, "type": kind})
    return out


def install_handlers(app: FastAPI) -> None:
    """Answer every error in the one documented schema."""

    @app.exception_handler(ApiError)
    async def api_error(_request: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse(error_body(exc.message), status_code=exc.status)

    @app.exception_handler(RequestValidationError)
    async def invalid(_request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = field_errors(exc.errors())
        detail = "; ".join(f"{e['field']}: {e['message']}" for e in errors)
        return JSONResponse(error_body(detail or "invalid request", errors), status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_request: Request, exc: StarletteHTTPException) -> Response:
        headers = getattr(exc, "headers", None)
        if exc.status_code in (204, 304) or exc.status_code < 200:
            return Response(status_code=exc.status_code, headers=headers)
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        if exc.status_code == 400 and "parsing the body" in detail:
            detail = "the request body cannot be read (not UTF-8 JSON?)"
        return JSONResponse(error_body(detail), status_code=exc.status_code, headers=headers)

    @app.exception_handler(Exception)
    async def crashed(request: Request, exc: Exception) -> JSONResponse:
        log.error("unhandled error on %s %s", request.method, request.url.path,
                  exc_info=(type(exc), exc, exc.__traceback__))
        return JSONResponse(error_body("internal server error (logged on the server)"),
                            status_code=500)
