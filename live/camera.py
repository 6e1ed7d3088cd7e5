"""Camera input: an RTSP or HTTP (MJPEG) URL, a V4L2 device or a video file → timed frames.

Read with OpenCV's FFmpeg backend (V4L2 devices with OpenCV's V4L2 backend), except HTTP
MJPEG (see below). Frame times:

    t = t_anchor + (pts - pts_anchor) - latency_s

``pts`` is the stream's own presentation time (``CAP_PROP_POS_MSEC``: RTP timestamps for
RTSP, the container's for files, the driver's buffer time for V4L2); the anchor pairs the
first frame's pts with the reception time given by ``clock()`` (gpst; the host clock by
default). ``latency_s`` is the camera's capture-to-reception delay, measured once per
installation (the config's latency offset). HTTP MJPEG carries no timestamps (FFmpeg's
demuxer numbers the parts at a nominal 25 fps), so for ``http(s)://`` URLs, and whenever
the pts is missing or does not increase, the reception time is the frame time
(``timestamps="arrival"``). HTTP MJPEG is read part by part here (``multipart/
x-mixed-replace``, each part's JPEG decoded by OpenCV) rather than through FFmpeg, whose
stream probing holds the first frames back (measured: the first frame 0.19 s, the second
0.13 s late, in a burst), which would mistime exactly the frames the VO starts from.

If the pts-based time drifts from the reception time by more than ``reanchor_s`` (a camera
clock running off, a stream restarted), the anchor is reset and counted in ``reanchors``
(live sources only: a file's frames are timed by its pts from the first frame's anchor).

A stream that cannot be opened raises :class:`CameraError`; one that stops delivering frames
raises :class:`CameraStalled` after ``read_timeout_s`` (FFmpeg's own I/O timeout): never a
hang. A file simply ends.
"""

from __future__ import annotations

import http.client
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from urllib.parse import urlsplit

import cv2
import numpy as np

from engine.messages import FrameMessage

__all__ = ["CameraError", "CameraStalled", "host_clock_gpst", "CameraSource"]

GPS_EPOCH_UNIX = 315964800.0  # 1980-01-06 00:00:00 UTC in Unix seconds


class CameraError(RuntimeError):
    """The camera cannot be opened."""


class CameraStalled(CameraError):
    """The camera stopped delivering frames."""


def host_clock_gpst(leap_seconds: int = 18) -> float:
    """The host's clock as gpst (GPS − UTC = ``leap_seconds``)."""
    return time.time() - GPS_EPOCH_UNIX + leap_seconds


def _is_network(url: str) -> bool:
    return url.split("://", 1)[0].lower() in ("rtsp", "rtsps", "http", "https", "rtmp", "udp",
                                               "tcp")


class CameraSource:
    """Frames of one camera as :class:`engine.messages.FrameMessage` (gpst, index, BGR)."""

    def __init__(self, url: str | int, *, latency_s: float = 0.0,
                 clock: Callable[[], float] = host_clock_gpst,
                 open_timeout_s: float = 5.0, read_timeout_s: float = 2.0,
                 reanchor_s: float = 0.5, timestamps: str | None = None):
        self.url = url
        if timestamps is None:
            timestamps = "arrival" if str(url).lower().startswith("http") else "stream"
        if timestamps not in ("stream", "arrival"):
            raise ValueError(f"timestamps {timestamps!r} is neither 'stream' nor 'arrival'")
        self.timestamps = timestamps
        self.latency_s = latency_s
        self.clock = clock
        self.open_timeout_s = open_timeout_s
        self.read_timeout_s = read_timeout_s
        self.reanchor_s = reanchor_s
        self.reanchors = 0
        self.frames_read = 0
        self.status = "closed"
        self._anchor: tuple[float, float] | None = None  # (pts s, gpst)
        self._last_pts: float | None = None
        self._live = True

    def _open(self) -> cv2.VideoCapture:
        url = self.url
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(self.open_timeout_s * 1000),
                  cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(self.read_timeout_s * 1000)]
        if isinstance(url, int) or str(url).startswith("/dev/video"):
            cap = cv2.VideoCapture(url, cv2.CAP_V4L2)
        else:
            if not _is_network(str(url)) and not Path(str(url)).exists():
                raise CameraError(f"{url}: no such file")
            cap = cv2.VideoCapture(str(url), cv2.CAP_FFMPEG, params)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"{url}: cannot open the stream (within {self.open_timeout_s:g} s)")
        return cap

    def _time(self, pts: float | None) -> float:
        now = self.clock() - self.latency_s
        if pts is None or (self._last_pts is not None and pts <= self._last_pts):
            self._last_pts = None
            self._anchor = None
            return now
        self._last_pts = pts
        if self._anchor is None:
            self._anchor = (pts, now)
            return now
        t = self._anchor[1] + (pts - self._anchor[0])
        if self._live and abs(t - now) > self.reanchor_s:
            self.reanchors += 1
            self._anchor = (pts, now)
            return now
        return t

    def __iter__(self) -> Iterator[FrameMessage]:
        if self.timestamps == "arrival" and str(self.url).lower().startswith("http"):
            yield from self._iter_http_mjpeg()
            return
        cap = self._open()
        self.status = "streaming"
        network = isinstance(self.url, int) or _is_network(str(self.url)) \
            or str(self.url).startswith("/dev/")
        self._live = network  # a file is not real time: its pts alone make the times
        release = True
        try:
            index = 0
            while True:
                started = time.monotonic()
                finished, ok, image = _read_with_deadline(cap, self.read_timeout_s + 1.0)
                # a read still running in its thread must not see the capture released
                release = finished
                if not ok:
                    waited = time.monotonic() - started
                    if network:
                        self.status = (f"stalled: no frame for {waited:.1f} s"
                                       if waited >= self.read_timeout_s
                                       else "stalled: the stream ended")
                        raise CameraStalled(f"{self.url}: {self.status}")
                    self.status = "ended"
                    return
                pts_ms = cap.get(cv2.CAP_PROP_POS_MSEC)
                pts = pts_ms / 1000.0 if self.timestamps == "stream" and pts_ms >= 0 else None
                yield FrameMessage(self._time(pts), index, image)
                index += 1
                self.frames_read = index
        finally:
            if release:
                cap.release()


    def _iter_http_mjpeg(self) -> Iterator[FrameMessage]:
        """Frames of an HTTP MJPEG camera, each timed when its last byte arrived."""
        parts = urlsplit(str(self.url))
        conn_class = (http.client.HTTPSConnection if parts.scheme.lower() == "https"
                      else http.client.HTTPConnection)
        conn = conn_class(parts.hostname or "127.0.0.1", parts.port,
                          timeout=self.open_timeout_s)
        try:
            try:
                conn.request("GET", (parts.path or "/") + (f"?{parts.query}" if parts.query
                                                           else ""))
                resp = conn.getresponse()
            except OSError as exc:
                raise CameraError(f"{self.url}: cannot open the stream ({exc})") from exc
            kind = resp.getheader("Content-Type", "")
            if resp.status != 200 or "multipart" not in kind:
                raise CameraError(f"{self.url}: cannot open the stream (HTTP {resp.status}, "
                                  f"{kind or 'no content type'}; an MJPEG camera answers "
                                  "multipart/x-mixed-replace)")
            if conn.sock is not None:
                conn.sock.settimeout(self.read_timeout_s)
            self.status = "streaming"
            index = 0
            while True:
                try:
                    jpeg = _next_part(resp)
                except TimeoutError:
                    self.status = f"stalled: no frame for {self.read_timeout_s:.1f} s"
                    raise CameraStalled(f"{self.url}: {self.status}") from None
                except (OSError, http.client.HTTPException, ValueError) as exc:
                    self.status = f"stalled: the stream broke ({exc})"
                    raise CameraStalled(f"{self.url}: {self.status}") from exc
                if jpeg is None:
                    self.status = "stalled: the stream ended"
                    raise CameraStalled(f"{self.url}: {self.status}")
                t = self.clock() - self.latency_s
                image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
                if image is None:
                    continue  # a corrupt part: skipped (the integrity layer sees the gap)
                yield FrameMessage(t, index, image, jpeg)
                index += 1
                self.frames_read = index
        finally:
            conn.close()


def _next_part(resp: http.client.HTTPResponse) -> bytes | None:
    """The body of the next part of a multipart stream (None at its end): the part headers
    up to a blank line, then Content-Length bytes (or, without it, up to the next boundary
    line)."""
    length = None
    seen_header = False
    while True:
        line = resp.readline(8192)
        if not line:
            return None
        text = line.strip()
        if not text:
            if seen_header:
                break
            continue
        if text.startswith(b"--"):
            continue  # the boundary
        seen_header = True
        name, _, value = text.partition(b":")
        if name.strip().lower() == b"content-length":
            length = int(value.strip())
    if length is not None:
        data = resp.read(length)
        return data if len(data) == length else None
    body = bytearray()  # no length: JPEG up to its end-of-image marker
    while not body.endswith(b"\xff\xd9"):
        chunk = resp.read(1)
        if not chunk:
            return None
        body += chunk
    return bytes(body)


def _read_with_deadline(cap: cv2.VideoCapture, deadline_s: float):
    """(finished, ok, image) of ``cap.read()``, giving up after ``deadline_s`` even if the
    backend does not.

    FFmpeg's I/O timeout normally ends a stalled read first; this guard covers backends and
    protocols where it does not (the reading thread is then abandoned with the capture).
    """
    result: list = []
    th = threading.Thread(target=lambda: result.append(cap.read()), daemon=True)
    th.start()
    th.join(deadline_s)
    if not result:
        return False, False, None
    ok, image = result[0]
    return True, ok, image
