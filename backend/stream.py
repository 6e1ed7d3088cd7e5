"""The per-session WebSocket stream: one message pair per video frame.

Protocol (``/api/sessions/{id}/stream``), server → client:

* **text** ``{"type": "status", "session": {...}}`` when the replay state changes (playing,
  paused, seeking, ended…) and once on connect; ``session`` is the ``SessionStatus`` schema.
* **text** ``{"type": "frame", ...}`` header, immediately followed by **binary** = the JPEG of
  that frame (``jpeg_bytes`` long). The header carries ``frame``, ``t`` (s since the recording
  start), ``gpst``, ``width``/``height``, ``pose`` (``Pose`` schema), ``status`` (fusion
  status), ``overlay`` (``video`` in image pixels: grid lines and nodes, points, predicted
  outlines; ``birdseye`` in plan north/east; ``targets``; ``berth``) — see
  ``GET /api/stream/schema`` — plus ``seq`` (this client's frame number), ``processed_at``
  (server wall time when the engine returned the frame's state) and ``sent_at`` (server wall
  time of sending), both Unix seconds.
  ``pose``/``status``/``overlay`` are null until the engine has a solution.
* **text** ``{"type": "error" | "closed", "detail": ...}`` before the server closes the socket
  with code 4404 (unknown or deleted session: do not reconnect) or 4422 (a query parameter
  unknown or out of range, named in ``detail``).

Query: ``ack`` (1/true/yes/on or 0/false/no/off), ``window`` (1..16) and ``token``
(``backend.access``).

Binary JPEG + JSON header rather than base64-in-JSON: a third smaller, no encode/decode cost,
and the browser can hand the blob straight to an ``<img>``/``createImageBitmap``.

Flow control (recommended): connect with ``?ack=1`` (and optionally ``&window=w``, frames in
flight, default 2) and send ``{"type": "ack", "seq": n}`` after drawing the frame numbered
``seq`` (in its header). Each client has a latest-only slot; an acknowledging client never
has more than ``window`` frames in flight, so when it (or its network) is slower than the
video it skips frames and always gets the newest — never a growing lag. Without ``?ack=1``
frames are sent as fast as the connection accepts them, and TCP buffers can then hold seconds
of video for a slow client. A client that disconnects is dropped from the session at once,
and while nobody watches no JPEG or overlay is built.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import Mapping

from fastapi import WebSocket

from .errors import ApiError
from .sessions import Session, SessionManager


class LatestSlot:
    """Newest frame + newest status for one client; ``offer`` may be called from any thread.

    Flow control: TCP and the client library buffer megabytes, i.e. seconds of video, before
    a send blocks, so "newest frame only" needs the client's help: a client that acknowledges
    frames (``{"type": "ack", "seq": n}``, announced with ``?ack=1``) has at most ``window``
    unacknowledged frames in flight, and everything newer waits here, replaced by the next.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, window: int | None = None) -> None:
        self._loop = loop
        self.wake = asyncio.Event()
        self._frame: tuple[bytes, bytes] | None = None
        self._status: bytes | None = None
        self.ended: str | None = None
        self.window = window  # None: no flow control (the client does not acknowledge)
        self.acked = 0
        self.seq = 0  # sequence number of the last frame sent
        self.dropped = 0  # frames replaced before this client could take them

    # producer side (any thread)

    def offer(self, header: bytes, jpeg: bytes | None) -> None:
        with contextlib.suppress(RuntimeError):  # the loop is gone: the client is gone
            self._loop.call_soon_threadsafe(self._put, header, jpeg)

    def end(self, reason: str) -> None:
        with contextlib.suppress(RuntimeError):
            self._loop.call_soon_threadsafe(self._finish, reason)

    def _put(self, header: bytes, jpeg: bytes | None) -> None:
        if jpeg is None:
            self._status = header
        else:
            if self._frame is not None:
                self.dropped += 1
            self._frame = (header, jpeg)
        self.wake.set()

    def _finish(self, reason: str) -> None:
        self.ended = reason
        self.wake.set()

    # consumer side (the event loop)

    def ack(self, seq: int) -> None:
        if 0 <= seq <= self.seq:
            self.acked = max(seq, self.acked)
        self.wake.set()

    def take_status(self) -> bytes | None:
        status, self._status = self._status, None
        return status

    def take_frame(self) -> tuple[bytes, bytes] | None:
        """The newest frame if the flow-control window allows sending one now."""
        if self.window is not None and self.seq - self.acked >= self.window:
            return None
        frame, self._frame = self._frame, None
        return frame


async def _send(websocket: WebSocket, slot: LatestSlot) -> None:
    while True:
        await slot.wake.wait()
        slot.wake.clear()
        status = slot.take_status()
        if status is not None:
            await websocket.send_text(status.decode())
        frame = slot.take_frame()
        if frame is not None:
            header, jpeg = frame
            slot.seq += 1
            # the header is sent without its closing brace: number it, stamp the send time
            await websocket.send_text(header.decode() + f',"seq":{slot.seq},'
                                                        f'"sent_at":{time.time():.6f}}}')
            await websocket.send_bytes(jpeg)
        if slot.ended is not None:
            await websocket.send_text(json.dumps({"type": "closed", "detail": slot.ended}))
            await websocket.close(code=4404, reason="session deleted")  # as for an unknown id
            return


async def _receive(websocket: WebSocket, slot: LatestSlot) -> None:
    """Read acknowledgements; return when the client goes away. Anything else is ignored
    (control goes through the HTTP API)."""
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
        text = message.get("text")
        if not text:
            continue
        try:
            data = json.loads(text)
            if data.get("type") == "ack":
                slot.ack(int(data["seq"]))
        except (ValueError, TypeError, KeyError, AttributeError, OverflowError):
            continue  # a malformed message (seq 1e400: int(inf)) must not end the stream


_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")
WINDOW_MAX = 16


def stream_query(query: Mapping[str, str]) -> int | None:
    """The stream's query: frames in flight for an acknowledging client (None: the client
    does not acknowledge). ValueError naming the parameter when it is unknown or bad."""
    unknown = sorted(set(query) - {"ack", "window", "token"})
    if unknown:
        raise ValueError(f"unknown query parameter {unknown[0]!r} (the stream takes: ack, "
                         "token, window)")
    ack = query.get("ack", "0").lower()
    if ack not in _TRUE + _FALSE:
        raise ValueError(f"ack: {query['ack']!r} is not a boolean (1, true, yes, on or 0, "
                         "false, no, off)")
    text = query.get("window", "2")
    if not (text.isascii() and text.isdigit()) or not 1 <= int(text) <= WINDOW_MAX:
        raise ValueError(f"window: {text!r} is not a whole number of frames in 1..{WINDOW_MAX}")
    return int(text) if ack in _TRUE else None


async def _refuse(websocket: WebSocket, status: int, detail: str, code: int, reason: str
                  ) -> None:
    await websocket.send_text(json.dumps({"type": "error", "status": status, "detail": detail}))
    await websocket.close(code=code, reason=reason)


async def serve_stream(websocket: WebSocket, manager: SessionManager, session_id: str) -> None:
    """Serve one client (its query: ``stream_query``)."""
    await websocket.accept()
    try:
        window = stream_query(websocket.query_params)
    except ValueError as exc:
        await _refuse(websocket, 422, str(exc), 4422, "bad query")
        return
    try:
        session: Session = manager.get(session_id)
    except ApiError as exc:
        await _refuse(websocket, exc.status, exc.message, 4404, "unknown session")
        return
    slot = LatestSlot(asyncio.get_running_loop(), window)
    session.subscribe(slot)
    tasks = [asyncio.create_task(_send(websocket, slot)),
             asyncio.create_task(_receive(websocket, slot))]
    try:  # the sender ends on a deleted session, the receiver when the client goes
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        session.unsubscribe(slot)
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):  # already reported
                await task
