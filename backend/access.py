"""Access control for use on a ship's network.

On loopback the server is open, as a desktop tool. Bound to anything else it requires a
token on every ``/api`` request (``serve`` generates and prints the tokens, or takes them from
the environment): a *control* token may do everything, a *view* token may only read (GET,
HEAD, OPTIONS) and watch the stream — a second screen on the bridge, not a second officer.
The page itself (its static files, ``/docs``, ``/openapi.json``) needs none: it takes the token
from the URL fragment once (``/#token=…``, never sent to the server in a URL) and sends it as
``Authorization: Bearer …``; the WebSocket, which a browser cannot give headers, takes it as
``?token=…``.

Refused requests: 401 (no or unknown token, with ``WWW-Authenticate: Bearer``) and 403 (a
view token asking to change something), in the API's error schema; a stream without a valid
token is accepted and closed at once with code 4401 after an ``error`` message, so that the
page can tell it from a network failure.
"""

from __future__ import annotations

import ipaddress
import json
import os
import secrets
from collections.abc import Mapping
from dataclasses import dataclass
from urllib.parse import parse_qs

from starlette.types import ASGIApp, Receive, Scope, Send

from .errors import error_body

CONTROL_ENV = "BERTHING_AID_TOKEN"
VIEW_ENV = "BERTHING_AID_VIEW_TOKEN"
READ_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
MIN_TOKEN_CHARS = 16


@dataclass(frozen=True)
class Access:
    """The tokens the server requires (``control`` None: open, as on loopback)."""

    control: str | None = None
    view: str | None = None

    @property
    def required(self) -> bool:
        return self.control is not None

    def role(self, token: str | None) -> str | None:
        """"control", "view" or None (no or unknown token). Constant-time comparisons."""
        if token is None:
            return None
        given = token.encode()
        if self.control is not None and secrets.compare_digest(given, self.control.encode()):
            return "control"
        if self.view is not None and secrets.compare_digest(given, self.view.encode()):
            return "view"
        return None


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: it may resolve to anything


def access_for(host: str, env: Mapping[str, str] = os.environ) -> tuple[Access, bool]:
    """The access a server bound to ``host`` requires, and whether its tokens were generated
    (to be printed). Tokens from the environment (``BERTHING_AID_TOKEN``,
    ``BERTHING_AID_VIEW_TOKEN``) apply anywhere; off loopback without them both are
    generated."""
    control, view = env.get(CONTROL_ENV) or None, env.get(VIEW_ENV) or None
    for name, token in ((CONTROL_ENV, control), (VIEW_ENV, view)):
        if token is not None and len(token) < MIN_TOKEN_CHARS:
            raise ValueError(f"{name} is shorter than {MIN_TOKEN_CHARS} characters")
    if view is not None and control is None:
        raise ValueError(f"{VIEW_ENV} is set without {CONTROL_ENV}")
    if control is not None:
        if view == control:
            raise ValueError(f"{VIEW_ENV} equals {CONTROL_ENV}: a viewer could control")
        return Access(control, view), False
    if is_loopback(host):
        return Access(), False
    return Access(secrets.token_urlsafe(24), secrets.token_urlsafe(24)), True


def _bearer(scope: Scope) -> str | None:
    for name, value in scope.get("headers", ()):
        if name == b"authorization":
            scheme, _, token = value.decode("latin-1").partition(" ")
            if scheme.lower() == "bearer" and token.strip():
                return token.strip()
    return None


class TokenGate:
    """ASGI middleware enforcing ``Access`` on ``/api`` (HTTP and WebSocket)."""

    def __init__(self, app: ASGIApp, access: Access) -> None:
        self.app = app
        self.access = access

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (not self.access.required or scope["type"] not in ("http", "websocket")
                or not scope["path"].startswith("/api")):
            return await self.app(scope, receive, send)
        if scope["type"] == "websocket":
            query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
            token = (query.get("token") or [None])[0] or _bearer(scope)
            if self.access.role(token) is not None:  # either role may watch
                return await self.app(scope, receive, send)
            return await self._refuse_stream(receive, send)
        role = self.access.role(_bearer(scope))
        if role == "control" or (role == "view" and scope["method"] in READ_METHODS):
            return await self.app(scope, receive, send)
        if role is None:
            status, detail = 401, ("a token is required: send 'Authorization: Bearer <token>' "
                                   "(the server printed the tokens when it started)")
        else:
            status, detail = 403, ("this token is read-only: it may read and watch the "
                                   "stream, not create, control or delete")
        body = json.dumps(error_body(detail)).encode()
        headers = [(b"content-type", b"application/json"),
                   (b"content-length", str(len(body)).encode())]
        if status == 401:
            headers.append((b"www-authenticate", b'Bearer realm="berthing-aid"'))
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})

    @staticmethod
    async def _refuse_stream(receive: Receive, send: Send) -> None:
        message = await receive()
        if message["type"] != "websocket.connect":
            return
        await send({"type": "websocket.accept"})
        await send({"type": "websocket.send", "text": json.dumps(
            {"type": "error", "status": 401,
             "detail": "a token is required: connect with ?token=<token>"})})
        await send({"type": "websocket.close", "code": 4401, "reason": "token required"})
