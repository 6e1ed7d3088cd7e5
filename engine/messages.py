"""Sensor messages: what any source (a recording replayed, live receivers) hands the engine.

``sensor_messages`` merges a recording's streams into one time-ordered sequence: IMU samples,
GNSS epochs of the four receivers grouped by their (common-clock) time tag, and video frames.
At equal time tags IMU comes first, then GNSS, then the frame: the engine has propagated to
``t`` before it sees a measurement taken at ``t``, as with a live feed where the 100 Hz IMU has
the smallest latency.
"""

from __future__ import annotations

import contextlib
import heapq
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimator.records import GnssEpoch
from recordings.format import Recording

# Priority of the message kinds at equal time tags (see the module docstring).
_IMU, _GNSS, _FRAME = 0, 1, 2
GNSS_GROUP_TOLERANCE_S = 1e-3  # receivers on one clock tag the same epoch identically


@dataclass(frozen=True)
class ImuMessage:
    t: float
    gyro: np.ndarray  # (3,) rad/s, body
    accel: np.ndarray  # (3,) m/s^2, body


@dataclass(frozen=True)
class GnssMessage:
    t: float
    epochs: tuple[GnssEpoch | None, ...]  # one per receiver; None when a receiver missed it


@dataclass(frozen=True)
class FrameMessage:
    t: float
    index: int
    image: np.ndarray  # BGR
    jpeg: bytes | None = None  # the camera's own JPEG when it sent one (recorded as is)
    # The engine's ``prepare_frame`` of the image, made ahead by the reading thread (None:
    # the engine makes it itself, on its own time).
    prepared: Any = None
    # The next frame's ``prepared`` when the reader already has it (a recording): the engine
    # may start on it while the other sensors' messages in between are processed.
    following: Any = None


SensorMessage = ImuMessage | GnssMessage | FrameMessage


def group_gnss(rec: Recording) -> list[GnssMessage]:
    """The receivers' epochs grouped by time tag, in time order (one message per tag)."""
    receivers = len(rec.gnss)
    tags: dict[int, list[GnssEpoch | None]] = {}
    times: dict[int, float] = {}
    for rx, epochs in enumerate(rec.gnss):
        for epoch in epochs:
            key = int(round(epoch.time / GNSS_GROUP_TOLERANCE_S))
            slot = tags.setdefault(key, [None] * receivers)
            slot[rx] = epoch
            times.setdefault(key, epoch.time)
    return [GnssMessage(times[key], tuple(tags[key])) for key in sorted(tags)]


def sensor_messages(rec: Recording, after: float | None = None, until: float | None = None,
                    frames: bool = True, prepare: Callable[[np.ndarray], Any] | None = None
                    ) -> Iterator[SensorMessage]:
    """All sensor messages of ``rec`` in time order: those strictly after ``after`` and at or
    before ``until`` (gpst) when given; without ``frames``, IMU and GNSS only. Frames are
    decoded by a thread a few frames ahead, which also makes each one's ``prepare`` (the
    engine's ``prepare_frame``) when given."""
    lo = -np.inf if after is None else after
    hi = np.inf if until is None else until

    def imu() -> Iterator[tuple[float, int, int, SensorMessage]]:
        data = rec.imu
        first = int(np.searchsorted(data.time, lo, side="right"))
        last = int(np.searchsorted(data.time, hi, side="right"))
        for i in range(first, last):
            t = float(data.time[i])
            yield t, _IMU, i, ImuMessage(t, data.gyro[i], data.accel[i])

    def gnss() -> Iterator[tuple[float, int, int, SensorMessage]]:
        for i, msg in enumerate(group_gnss(rec)):
            if lo < msg.t <= hi:
                yield msg.t, _GNSS, i, msg

    def video() -> Iterator[tuple[float, int, int, SensorMessage]]:
        first = int(np.searchsorted(rec.frame_times, lo, side="right"))
        if not frames or first >= len(rec.frame_times):
            return
        with contextlib.closing(rec.prepared_frames(first, prepare)) as decoded:
            # one frame held back, to hand its successor's ``prepared`` along with it (the
            # reading thread is a few frames ahead: no wait)
            held = next(decoded, None)
            while held is not None:
                index, t, image, prepared = held
                if t > hi:
                    return
                held = next(decoded, None)
                following = None if held is None or held[1] > hi else held[3]
                yield t, _FRAME, index, FrameMessage(t, index, image, prepared=prepared,
                                                     following=following)

    for _t, _kind, _i, msg in heapq.merge(imu(), gnss(), video(), key=lambda m: m[:3]):
        yield msg
