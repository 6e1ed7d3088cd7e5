"""Camera input: an RTSP or HTTP (MJPEG) URL, a V4L2 device or a video file → timed frames.

Read with OpenCV's FFmpeg backend (V4L2 devices with OpenCV's V4L2 backend). Frame times:

    t = t_anchor + (pts - pts_anchor) - latency_s

``pts`` is the stream's own presentation time (``CAP_PROP_POS_MSEC``: RTP timestamps for
RTSP, the container's for files, the driver's buffer time for V4L2); the anchor pairs the
first frame's pts with the reception time given by ``clock()`` (gpst; the host clock by
default). ``latency_s`` is the camera's capture-to-reception delay, measured once per
installation (the config's latency offset). HTTP MJPEG carries no timestamps (FFmpeg's
demuxer numbers the parts at a nominal 25 fps), so for ``http(s)://`` URLs, and whenever
the pts is missing or does not increase, the reception time is the frame time
(``timestamps="arrival"``). If the pts-based time drifts from the reception time by more
than ``reanchor_s`` (a camera clock running off, a stream restarted), the anchor is reset
and counted in ``reanchors`` (live sources only: a file's frames are timed by its pts from
the first frame's anchor).

A stream that cannot be opened raises :class:`CameraError`; one that stops delivering frames
raises :class:`CameraStalled` after ``read_timeout_s`` (FFmpeg's own I/O timeout): never a
hang. A file simply ends.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2

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
