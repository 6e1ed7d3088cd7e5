"""Rules every HTTP route follows, whatever it declares:

* HEAD is GET without the body;
* an unknown query parameter is an error (422), not silently ignored — ``pose?time=30``
  would otherwise answer the current pose instead of the one at 30 s;
* ``OPTIONS`` answers 204 with ``Allow`` listing exactly the documented methods of the path,
  and a method the path does not have answers 405 with that same ``Allow`` (Starlette lists
  only the methods of the first route matching the path, and the page's static files —
  mounted at ``/`` — would answer API paths without any ``Allow``).
"""

from __future__ import annotations

import json
import re
from typing import Any

from fastapi.exceptions import RequestValidationError
from starlette.requests import HTTPConnection
from starlette.routing import compile_path
from starlette.types import ASGIApp, Receive, Scope, Send

from .errors import error_body


def _query_names(dependant: Any) -> set[str]:
    names = {field.alias for field in dependant.query_params}
    for sub in dependant.dependencies:
        names |= _query_names(sub)
    return names


def reject_unknown_query(connection: HTTPConnection) -> None:
    """App-wide dependency: 422 naming any query parameter the route does not declare."""
    if connection.scope["type"] != "http":
        return
    route = connection.scope.get("route")
    dependant = getattr(route, "dependant", None)
    # the page's own address (``/?recording=…``, outside the API schema) is read by the page
    if dependant is None or not getattr(route, "include_in_schema", True):
        return
    known = _query_names(dependant)
    unknown = sorted(set(connection.query_params) - known)
    if unknown:
        takes = ", ".join(sorted(known)) or "none"
        raise RequestValidationError([
            {"type": "unknown_parameter", "loc": ("query", name),
             "msg": f"unknown query parameter (this route takes: {takes})", "input": None}
            for name in unknown])


class MethodGate:
    """ASGI middleware: exact ``Allow`` for OPTIONS and 405 (see the module docstring). The
    methods of a path are those the OpenAPI schema documents for it (HEAD with GET): the
    contract, whatever the framework's routing looks like inside."""

    HTTP_METHODS = frozenset({"get", "put", "post", "delete", "patch", "head", "options",
                              "trace"})

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self.paths: list[tuple[re.Pattern[str], set[str]]] | None = None  # on first use

    def _documented(self, app: Any) -> list[tuple[re.Pattern[str], set[str]]]:
        out = []
        for path, item in app.openapi().get("paths", {}).items():
            methods = {m.upper() for m in item if m in self.HTTP_METHODS}
            if "GET" in methods:
                methods.add("HEAD")
            out.append((compile_path(path)[0], methods))
        return out

    def allowed(self, scope: Scope) -> set[str]:
        """Documented methods of the path (empty: not an API path, e.g. a page file)."""
        if self.paths is None:
            self.paths = self._documented(scope["app"])
        methods: set[str] = set()
        for regex, documented in self.paths:
            if regex.match(scope["path"]):
                methods |= documented
        return methods

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        method = scope["method"]
        methods = self.allowed(scope)
        if not methods:  # not an API path: the page's files (or the API's own 404)
            if scope["path"].startswith("/api/"):
                return await self.app(scope, receive, send)
            methods = {"GET", "HEAD"}
        if method == "HEAD" and "GET" in methods:
            return await self.app({**scope, "method": "GET"}, receive, _without_body(send))
        if method in methods:
            return await self.app(scope, receive, send)
        allow = ", ".join(sorted(methods | {"OPTIONS"}))
        if method == "OPTIONS":
            await send({"type": "http.response.start", "status": 204,
                        "headers": [(b"allow", allow.encode())]})
            await send({"type": "http.response.body", "body": b""})
            return
        body = json.dumps(error_body(f"method {method} is not allowed here (allowed: {allow})"))
        await send({"type": "http.response.start", "status": 405,
                    "headers": [(b"allow", allow.encode()),
                                (b"content-type", b"application/json"),
                                (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body.encode()})


def _without_body(send: Send) -> Send:
    """HEAD is GET without the body (the API's routes declare GET only)."""

    async def head_send(message: dict[str, Any]) -> None:
        if message["type"] == "http.response.body":
            message = {**message, "body": b""}
        await send(message)

    return head_send
