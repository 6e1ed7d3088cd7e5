"""An HTTP MJPEG camera for the emulator: a recording's video frames served at real time.

``GET /stream.mjpg`` answers ``multipart/x-mixed-replace`` with one JPEG part per frame, as
network cameras do; each part also carries ``X-Timestamp: <gpst>`` (the recording's frame
time; clients such as OpenCV ignore it). Playback is a live camera's: one clock for all
clients, frame i sent when ``frame_times[i] - frame_times[0]`` has elapsed since ``start``;
a client that connects late sees the current frames, not the first ones.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np

from recordings.format import Recording

__all__ = ["MjpegServer"]

BOUNDARY = "berthingaidframe"


class MjpegServer:
    """Serves frames ``(gpst, BGR image)`` from ``frames()`` at real time on ``host:port``."""

    def __init__(self, frames: Callable[[], Iterator[tuple[float, np.ndarray]]], *,
                 host: str = "127.0.0.1", port: int = 0, quality: int = 90,
                 speed: float = 1.0):
        self._frames = frames
        self.quality = quality
        self.speed = speed
        self._cond = threading.Condition()
        self._latest: tuple[int, float, bytes] | None = None  # (index, gpst, jpeg)
        self._done = False
        self._stop = threading.Event()
        self.frames_sent = 0
        # (gpst, Unix time) of each frame when it became the camera's newest: what a latency
        # benchmark measures from (the last hour's at 10 fps)
        self.published: deque[tuple[float, float]] = deque(maxlen=36_000)
        self.clients = 0  # connections to the stream so far
        # A shared playback clock (the emulator's): frame time t is due at
        # clock_start + (t - clock_t0) / speed (monotonic s). None: from the first frame.
        self.clock_start: float | None = None
        self.clock_t0: float | None = None
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: object) -> None:  # quiet
                pass

            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                if self.path.split("?")[0] != "/stream.mjpg":
                    self.send_error(404, "only /stream.mjpg here")
                    return
                server.clients += 1
                self.send_response(200)
                self.send_header("Content-Type",
                                 f"multipart/x-mixed-replace; boundary={BOUNDARY}")
                self.send_header("Cache-Control", "no-cache")
                self.end_headers()
                last = -1
                try:
                    while True:
                        item = server._next_frame(last)
                        if item is None:
                            return
                        last, t, jpeg = item
                        self.wfile.write(
                            f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                            f"Content-Length: {len(jpeg)}\r\nX-Timestamp: {t:.6f}\r\n\r\n"
                            .encode("ascii") + jpeg + b"\r\n")
                        self.wfile.flush()
                        server.frames_sent += 1
                except (BrokenPipeError, ConnectionResetError):
                    return

        self._httpd = ThreadingHTTPServer((host, port), Handler)
        self._httpd.daemon_threads = True
        self.address = self._httpd.server_address[:2]
        self.url = f"http://{self.address[0]}:{self.address[1]}/stream.mjpg"
        self._threads: list[threading.Thread] = []

    @classmethod
    def for_recording(cls, rec: Recording, start: int = 0, *, host: str = "127.0.0.1",
                      port: int = 0, quality: int = 90, speed: float = 1.0) -> MjpegServer:
        """A server of a recording's video from frame ``start``."""
        def frames() -> Iterator[tuple[float, np.ndarray]]:
            return ((t, image) for _, t, image in rec.frames(start))
        return cls(frames, host=host, port=port, quality=quality, speed=speed)

    def _next_frame(self, last: int) -> tuple[int, float, bytes] | None:
        with self._cond:
            if self._done and last == -1:
                return None  # switched off: a client connecting now gets no stale frame
            while not self._stop.is_set() and not self._done and (
                    self._latest is None or self._latest[0] == last):
                self._cond.wait(0.2)
            if self._stop.is_set() or (self._done and (self._latest is None
                                                       or self._latest[0] == last)):
                return None
            return self._latest

    def _play(self) -> None:
        start = self.clock_start
        t0: float | None = None
        for index, (t, image) in enumerate(self._frames()):
            if t0 is None:
                t0 = self.clock_t0 if self.clock_t0 is not None else t
            # encoded before its time comes: a camera sends a frame as it is captured
            ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
            if not ok:
                raise RuntimeError(f"cannot JPEG-encode frame {index}")
            if start is None:  # the clock starts with the first frame ready to go
                start = time.monotonic()
            wait = start + (t - t0) / self.speed - time.monotonic()
            if self._stop.wait(max(0.0, wait)):
                return
            with self._cond:
                self._latest = (index, t, jpeg.tobytes())
                self.published.append((t, time.time()))
                self._cond.notify_all()
        with self._cond:
            self._done = True
            self._cond.notify_all()

    def start(self) -> MjpegServer:
        for target, name in ((self._httpd.serve_forever, "mjpeg-http"),
                             (self._play, "mjpeg-play")):
            th = threading.Thread(target=target, name=name, daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def stop(self) -> None:
        """Stop serving: open connections are closed, as a camera that is switched off."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._httpd.shutdown()
        self._httpd.server_close()
        for th in self._threads:
            th.join(timeout=2)

    def __enter__(self) -> MjpegServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
