"""The live sources of one installation, merged in time order on GNSS time.

:class:`LiveSource` opens the devices of a :class:`live.config.LiveConfig` — four UBX
receivers, the IMU (text protocol or ESF-RAW in a receiver's stream), the camera — each read
in its own thread, and hands the engine the same messages a recording replayed gives
(``engine.messages``: ``ImuMessage``, ``GnssMessage`` grouping the receivers' epochs of one
time tag, ``FrameMessage``), in the same order: time, then IMU before GNSS before frames at
equal times. :class:`TimeAligner` does the merging:

- **GNSS time is the time base.** IMU samples carry gpst (text protocol) or are dated by the
  receiver (ESF-RAW); the camera's frames are timed on the host's monotonic clock, mapped to
  gpst by :class:`GnssClock` from the arrival of the receivers' epochs (the epoch that
  arrived with the least delay over a window sets the offset), minus the camera latency.
- **Watermarks.** A message is released when no stream can still deliver an earlier one: each
  stream delivers in time order, so a stream whose latest message is at or after time t has
  nothing before t to come; the receivers, which tag epochs on a known grid, have nothing
  before their latest epoch + one epoch interval − ``RECEIVER_GRID_SLACK_S``.
- **A stream that stops or lags is a fault, not a hang.** A message never waits more than
  ``max_lag_s`` (wall time) for a silent stream: the stream is then marked lagging and not
  waited for until it speaks again; what it delivers later than the merge has got is dropped
  and counted (``late``). A device that stops (``StreamStalled``, a broken connection) is
  marked stopped and reconnected every ``RECONNECT_S``. The engine sees the gap and its
  integrity layer declares it (``imu-silent``, ``receiver-N-silent``, ``video-silent``).

Ephemerides from the receivers' SFRBX are assembled in the consumer's thread (the engine's),
in stream order, so that an epoch's broadcast ephemerides are known when it is released.
"""

from __future__ import annotations

import heapq
import logging
import math
import queue
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from engine.messages import GNSS_GROUP_TOLERANCE_S, FrameMessage, GnssMessage, ImuMessage
from estimator.records import GnssEpoch, NavigationData

from .camera import CameraError, CameraSource
from .config import LiveConfig
from .streams import StreamStalled, open_stream
from .text_imu import TextImuSource
from .ubx_gnss import EphemerisAssembler, UbxGnssSource
from .ubx_imu import EsfRawDecoder

__all__ = ["GnssClock", "StreamHealth", "TimeAligner", "LiveSource"]

log = logging.getLogger(__name__)

# Receivers tag epochs on their measurement grid to within milliseconds, so nothing earlier
# than the next grid time minus this can still come from one (half an interval made a frame
# just after an epoch's midpoint wait up to 0.5 s for the next epoch)
RECEIVER_GRID_SLACK_S = 0.1
RECONNECT_S = 1.0  # a stopped device is reopened this often
UNTIMED_FRAMES_KEPT_S = 5.0  # frames wait this long for the first GNSS epoch to time them
# A time tag this far ahead of the GNSS clock (the host's clock mapped) cannot be: the sample
# or epoch is dropped and counted. Let in, one receiver's epoch an hour ahead moved the merge
# an hour on and every later message of every sensor was late (a user trial: no position,
# the other sensors blamed, the recording ruined).
FUTURE_TOLERANCE_S = 0.5
ERROR_SHOWN_S = 10.0  # a dropped message's error stays on its input this long
_IMU, _GNSS, _FRAME = 0, 1, 2


class GnssClock:
    """The host's monotonic clock → gpst, from the arrival times of GNSS epochs.

    Each epoch gives gpst − arrival = offset − delay (the receiver's output and transport
    delay, ≥ 0); the largest value over the last ``window`` epochs is the one with the least
    delay, taken as the offset. Values more than ``FUTURE_TOLERANCE_S`` above the median are
    a wrong time tag, not a short delay: left out. Unknown (None) until ``MIN_EPOCHS`` epochs
    give a median: the first epoch alone, tagged an hour ahead, set the clock an hour on (a
    user trial)."""

    MIN_EPOCHS = 3

    def __init__(self, window: int = 60):
        self._samples: deque[float] = deque(maxlen=window)
        self._offset: float | None = None

    def observe(self, t_gpst: float, arrival_mono: float) -> None:
        if not math.isfinite(t_gpst):
            return
        self._samples.append(t_gpst - arrival_mono)
        if len(self._samples) < self.MIN_EPOCHS:
            return
        top = statistics.median(self._samples) + FUTURE_TOLERANCE_S
        self._offset = max(v for v in self._samples if v <= top)

    @property
    def offset(self) -> float | None:
        return self._offset

    def to_gpst(self, mono: float) -> float | None:
        off = self.offset
        return None if off is None else mono + off


@dataclass
class StreamHealth:
    """What the session shows of one input."""

    name: str
    state: str = "connecting"  # connecting / streaming / lagging / stopped
    received: int = 0
    late: int = 0  # dropped: arrived after the merge had passed its time
    ahead: int = 0  # dropped: time tag ahead of the GNSS clock (``FUTURE_TOLERANCE_S``)
    error_until: float = -math.inf  # (monotonic) a dropped message's error shown until then
    last_gpst: float | None = None
    error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "state": self.state, "received": self.received,
                "late": self.late, "ahead": self.ahead, "last_gpst": self.last_gpst,
                "error": self.error}


class TimeAligner:
    """Merges the live streams into one time-ordered message sequence (module docstring).

    Producers call :meth:`put` from any thread; one consumer calls :meth:`next`.
    Stream names: ``imu``, ``camera``, ``rx1`` … ``rxN``; items: ``ImuMessage``, a
    ``FrameMessage`` timed on the monotonic clock, a ``GnssEpoch``, or ``("sfrbx", msg, hint)``
    for the ephemeris ``apply`` callback.
    """

    def __init__(self, receivers: int, max_lag_s: float = 0.5,
                 apply_sfrbx: Callable[[Any, float | None], None] | None = None,
                 clock: GnssClock | None = None, camera_latency_s: float = 0.0):
        self.receivers = receivers
        self.camera_latency_s = camera_latency_s
        self.max_lag_s = max_lag_s
        self.apply_sfrbx = apply_sfrbx
        self.clock = clock or GnssClock()
        self._queue: queue.Queue[tuple[str, Any, float]] = queue.Queue()
        names = ["imu", "camera"] + [f"rx{i + 1}" for i in range(receivers)]
        self.health = {n: StreamHealth(n) for n in names}
        self._last: dict[str, float] = {n: -math.inf for n in names}  # newest time delivered
        self._lagging: set[str] = set(names)  # until a stream speaks it is not waited for...
        self._started: float | None = None  # first data: see _waits_for
        self._imu: deque[tuple[ImuMessage, float]] = deque()
        self._frames: deque[tuple[FrameMessage, float]] = deque()
        self._untimed: deque[tuple[FrameMessage, float]] = deque()
        self._groups: dict[int, tuple[list[GnssEpoch | None], float]] = {}  # key -> epochs
        self._group_keys: list[int] = []  # heap
        self._released: tuple[float, int] = (-math.inf, -1)
        self._interval = 1.0  # receivers' epoch interval, learned
        self._last_group_t: float | None = None
        self.stopped: set[str] = set()
        self._undated: dict[str, list[Any]] = {}  # SFRBX received before any epoch
        self._early: list[tuple[str, GnssEpoch, float]] = []  # epochs before the clock is known
        # gpst of the earliest message held back while the merge waits for a stream (None:
        # nothing held): the sensors are not silent up to it (read by the live session's
        # thread)
        self.waiting_from: float | None = None

    # ------------------------------------------------------------------ producers

    def put(self, stream: str, item: Any) -> None:
        self._queue.put((stream, item, time.monotonic()))

    def set_state(self, stream: str, state: str, error: str | None = None) -> None:
        self._queue.put((stream, ("state", state, error), time.monotonic()))

    # ------------------------------------------------------------------ consumer

    def next(self, timeout: float | None = None) -> ImuMessage | GnssMessage | FrameMessage | None:
        """The next message in time order; None when none is due within ``timeout`` s."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            self._drain(block_s=0.0)
            msg, wait = self._release(time.monotonic())
            if msg is not None:
                return msg
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                return None
            block = 0.05 if wait is None else max(0.001, min(wait, 0.05))
            if deadline is not None:
                block = min(block, max(0.0, deadline - now))
            self._drain(block_s=block)

    def _drain(self, block_s: float) -> None:
        try:
            first = self._queue.get(timeout=block_s) if block_s > 0 else \
                self._queue.get_nowait()
        except queue.Empty:
            return
        self._take(*first)
        while True:
            try:
                self._take(*self._queue.get_nowait())
            except queue.Empty:
                return

    def _take(self, stream: str, item: Any, arrival: float) -> None:
        h = self.health[stream] if stream in self.health else None
        if isinstance(item, tuple) and item and item[0] == "state":
            _, state, error = item
            if h is not None:
                h.state, h.error = state, error
            if state == "stopped":
                self.stopped.add(stream)
                self._lagging.add(stream)
            else:
                self.stopped.discard(stream)
            return
        if isinstance(item, tuple) and item and item[0] == "sfrbx":
            if item[2] is None:  # before the receiver's first epoch: dated by that epoch
                self._undated.setdefault(stream, []).append(item[1])
            elif self.apply_sfrbx is not None:
                self.apply_sfrbx(item[1], item[2])
            return
        assert h is not None
        h.received += 1
        if self._started is None:
            self._started = arrival
        if isinstance(item, ImuMessage):
            if not self._ahead(item.t, arrival, h):
                self._accept(stream, item.t, _IMU, h, arrival,
                             lambda: self._imu.append((item, arrival)))
        elif isinstance(item, GnssEpoch):
            self.clock.observe(item.time, arrival)
            if self.clock.offset is None:  # judged once the clock is known
                self._early.append((stream, item, arrival))
                return
            early, self._early = self._early, []
            for args in [*early, (stream, item, arrival)]:
                self._epoch(*args)
        elif isinstance(item, FrameMessage):
            self._untimed.append((item, arrival))
            self._time_frames()

    def _epoch(self, stream: str, epoch: GnssEpoch, arrival: float) -> None:
        h = self.health[stream]
        if self._ahead(epoch.time, arrival, h):
            return
        for msg in self._undated.pop(stream, []):
            if self.apply_sfrbx is not None:
                self.apply_sfrbx(msg, epoch.time)
        self._accept(stream, epoch.time, _GNSS, h, arrival,
                     lambda: self._add_epoch(stream, epoch, arrival))
        self._time_frames()

    def _ahead(self, t: float, arrival: float, h: StreamHealth) -> bool:
        """Whether a time tag ``t`` is ahead of the GNSS clock at its arrival (dropped)."""
        now = self.clock.to_gpst(arrival)
        if now is None or not math.isfinite(t) or t <= now + FUTURE_TOLERANCE_S:
            return False
        h.ahead += 1
        h.error = f"time tag {t - now:.1f} s ahead of the receivers' clock: dropped"
        h.error_until = arrival + ERROR_SHOWN_S
        return True

    def _accept(self, stream: str, t: float, kind: int, h: StreamHealth, arrival: float,
                add: Callable[[], None]) -> None:
        if not math.isfinite(t) or t <= self._last[stream]:
            h.late += 1  # not after the stream's previous message: dropped
            return
        self._last[stream] = t
        h.last_gpst = t
        if h.state in ("connecting", "lagging", "stopped"):
            h.state = "streaming"
        if arrival >= h.error_until:
            h.error = None  # delivering: what went wrong before is over
        # ... and waited for again (a reconnected device was not: its data a few ms late
        # were dropped for the rest of the run, a user trial's 18 % of the frames)
        self.stopped.discard(stream)
        self._lagging.discard(stream)
        if (t, kind) <= self._released:
            h.late += 1
            return
        add()

    def _add_epoch(self, stream: str, epoch: GnssEpoch, arrival: float) -> None:
        key = int(round(epoch.time / GNSS_GROUP_TOLERANCE_S))
        if key not in self._groups:
            self._groups[key] = ([None] * self.receivers, arrival)
            heapq.heappush(self._group_keys, key)
        self._groups[key][0][int(stream[2:]) - 1] = epoch

    def _time_frames(self) -> None:
        """Frames timed on the host clock → gpst once the GNSS clock is known."""
        now = time.monotonic()
        while self._untimed:
            frame, arrival = self._untimed[0]
            t = self.clock.to_gpst(frame.t)
            if t is None:
                if now - arrival > UNTIMED_FRAMES_KEPT_S:
                    self._untimed.popleft()
                    self.health["camera"].late += 1
                    continue
                return
            self._untimed.popleft()
            timed = FrameMessage(t, frame.index, frame.image, frame.jpeg)
            self._accept("camera", t, _FRAME, self.health["camera"], arrival,
                         lambda timed=timed, arrival=arrival: self._frames.append((timed,
                                                                                   arrival)))

    # ------------------------------------------------------------------ merging

    def _waits_for(self, stream: str, now: float) -> bool:
        """Whether the merge waits for ``stream`` (not lagging, not stopped)."""
        if stream in self.stopped:
            return False
        if stream in self._lagging:
            # a stream that never spoke is waited for only at the start
            return (self._last[stream] == -math.inf and self._started is not None
                    and now - self._started < 2 * self.max_lag_s)
        return True

    def _patience(self, stream: str, now: float, head_arrival: float) -> float:
        """Seconds the merge still waits for ``stream`` (≤ 0: it is lagging). A receiver is
        late ``max_lag_s`` after its next epoch is due, the camera ``max_lag_s`` after its
        latency, the IMU ``max_lag_s`` after the message waiting for it arrived."""
        if stream.startswith("rx"):
            gpst_now = self.clock.to_gpst(now)
            if gpst_now is not None and math.isfinite(self._last[stream]):
                due = self._last[stream] + self._interval
                return due + self.max_lag_s - gpst_now
            return head_arrival + self.max_lag_s + self._interval - now
        extra = self.camera_latency_s + 0.1 if stream == "camera" else 0.0
        return head_arrival + self.max_lag_s + extra - now

    def _promise(self, stream: str) -> float:
        """No message of ``stream`` earlier than this can still come (gpst)."""
        last = self._last[stream]
        if stream.startswith("rx"):
            return last + self._interval - min(RECEIVER_GRID_SLACK_S, 0.5 * self._interval)
        return last

    def _gnss_head(self) -> tuple[float, list[GnssEpoch | None], float] | None:
        if not self._group_keys:
            return None
        key = self._group_keys[0]
        epochs, arrival = self._groups[key]
        t = next(e.time for e in epochs if e is not None)
        return t, epochs, arrival

    def _release(self, now: float):
        """(message or None, seconds until a lag deadline when none)."""
        heads = []
        if self._imu:
            heads.append((self._imu[0][0].t, _IMU, self._imu[0][1], "imu"))
        g = self._gnss_head()
        if g is not None:
            heads.append((g[0], _GNSS, g[2], "gnss"))
        if self._frames:
            heads.append((self._frames[0][0].t, _FRAME, self._frames[0][1], "camera"))
        if not heads:
            self.waiting_from = None
            return None, None
        t, kind, arrival, which = min(heads)
        self.waiting_from = t
        blockers = []
        for stream in self.health:
            if stream == which or (which == "gnss" and stream.startswith("rx")):
                continue
            if not self._waits_for(stream, now):
                continue
            if stream.startswith("rx"):
                safe = self._promise(stream) > t
            elif stream == "camera":
                safe = self._last[stream] >= t and not self._untimed
            else:
                safe = self._last[stream] >= t
            if not safe:
                blockers.append(stream)
        if which == "gnss":
            assert g is not None
            blockers += [f"rx{i + 1}" for i, e in enumerate(g[1])
                         if e is None and self._waits_for(f"rx{i + 1}", now)
                         and self._last[f"rx{i + 1}"] < t]
        remaining = [self._patience(b, now, arrival) for b in blockers]
        if any(r > 0 for r in remaining):
            return None, min(r for r in remaining if r > 0)
        for stream in blockers:  # waited long enough: not waited for until it speaks again
            self._lagging.add(stream)
            if self.health[stream].state == "streaming":
                self.health[stream].state = "lagging"
        self._released = (t, kind)
        self.waiting_from = None
        if which == "imu":
            return self._imu.popleft()[0], None
        if which == "camera":
            return self._frames.popleft()[0], None
        key = heapq.heappop(self._group_keys)
        epochs, _ = self._groups.pop(key)
        if self._last_group_t is not None and 0.0 < t - self._last_group_t < 30.0:
            self._interval = min(self._interval, t - self._last_group_t) \
                if self._interval_known else t - self._last_group_t
            self._interval_known = True
        self._last_group_t = t
        return GnssMessage(t, tuple(epochs)), None

    _interval_known = False


class _QueuedAssembler:
    """Stands in for the shared :class:`EphemerisAssembler` in a receiver's thread: SFRBX go
    through the aligner's queue to the consumer's thread, in stream order."""

    def __init__(self, real: EphemerisAssembler, aligner: TimeAligner, stream: str):
        self.nav = real.nav
        self._aligner, self._stream = aligner, stream

    def add_sfrbx(self, msg: Any, time_hint: float | None) -> None:
        self._aligner.put(self._stream, ("sfrbx", msg, time_hint))


class LiveSource:
    """The devices of a configuration, read in threads and merged (module docstring)."""

    def __init__(self, config: LiveConfig, nav_seed: NavigationData | None = None,
                 camera_clock: Callable[[], float] = time.monotonic):
        self.config = config
        self.assembler = EphemerisAssembler(nav_seed)
        self.aligner = TimeAligner(len(config.receivers), config.max_lag_s,
                                   apply_sfrbx=self.assembler.add_sfrbx,
                                   camera_latency_s=config.camera.latency_s)
        self._camera_clock = camera_clock
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._closers: dict[str, Callable[[], None]] = {}
        # each input's decoder (its ``rejected_total`` and ``last_rejection``, when it has),
        # and what the decoders of its earlier connections rejected (a reconnection must not
        # wipe the evidence: a user trial saw 7 rejections, then 0 a second later)
        self._decoders: dict[str, Any] = {}
        self._rejected_before: dict[str, tuple[int, str | None]] = {}
        self._lock = threading.Lock()
        self.leap_seconds: int | None = None

    @property
    def nav(self) -> NavigationData:
        return self.assembler.nav

    # ------------------------------------------------------------------ threads

    def start(self) -> LiveSource:
        cfg = self.config
        if cfg.imu.kind == "text":  # a UDP port is bound first: nothing sent to it is lost
            self._spawn("imu", lambda: open_stream(cfg.imu.url or "", cfg.stall_timeout_s),
                        lambda s: self._decoder("imu", TextImuSource(s)))
        for i, url in enumerate(cfg.receivers):
            self._spawn(f"rx{i + 1}", lambda url=url: open_stream(url, cfg.stall_timeout_s),
                        lambda s, i=i: self._receiver(s, i))
        self._spawn("camera", lambda: None, lambda _s: CameraSource(
            cfg.camera.url, latency_s=cfg.camera.latency_s, clock=self._camera_clock,
            read_timeout_s=cfg.stall_timeout_s))
        return self

    def _receiver(self, stream: Any, i: int) -> Iterable[Any]:
        imu = None
        if self.config.imu.kind == "esf" and self.config.imu.receiver == i + 1:
            imu = EsfRawDecoder(self.config.imu.offset_s)
        name = f"rx{i + 1}"
        src = UbxGnssSource(stream, assembler=_QueuedAssembler(self.assembler, self.aligner,
                                                                name),  # type: ignore[arg-type]
                            imu=imu, name=name)
        self._decoder(name, src)
        for item in src:
            if src.rawx.leap_seconds is not None:
                self.leap_seconds = src.rawx.leap_seconds
            yield item

    def _decoder(self, name: str, decoder: Any) -> Any:
        with self._lock:
            old = self._decoders.get(name)
            if old is not None:
                n, last = self._rejected_before.get(name, (0, None))
                self._rejected_before[name] = (n + int(getattr(old, "rejected_total", 0)),
                                               getattr(old, "last_rejection", None) or last)
            self._decoders[name] = decoder
        return decoder

    def _spawn(self, name: str, opener: Callable[[], Any],
               reader: Callable[[Any], Iterable[Any]]) -> None:
        th = threading.Thread(target=self._run_reader, args=(name, opener, reader),
                              name=f"live-{name}", daemon=True)
        th.start()
        self._threads.append(th)

    def _run_reader(self, name: str, opener: Callable[[], Any],
                    reader: Callable[[Any], Iterable[Any]]) -> None:
        """Open, read until the device stops, report, reopen — until closed."""
        while not self._stop.is_set():
            stream = None
            try:
                stream = opener()
                if stream is not None:
                    with self._lock:
                        self._closers[name] = stream.close
                for item in reader(stream):
                    if self._stop.is_set():
                        return
                    target = "imu" if isinstance(item, ImuMessage) else name
                    self.aligner.put(target, item)
                reason = "the stream ended"
            except (StreamStalled, CameraError, ConnectionError, OSError, ValueError) as exc:
                reason = str(exc)
            except Exception as exc:  # a reader must never die unseen
                log.exception("live input %s failed", name)
                reason = f"failed: {exc!r}"
            finally:
                if stream is not None:
                    try:
                        stream.close()
                    except OSError:
                        pass
            if self._stop.is_set():
                return
            self.aligner.set_state(name, "stopped", reason)
            if name == f"rx{self.config.imu.receiver}" and self.config.imu.kind == "esf":
                self.aligner.set_state("imu", "stopped", reason)
            self._stop.wait(RECONNECT_S)

    # ------------------------------------------------------------------ consumer

    def next(self, timeout: float | None = None) -> ImuMessage | GnssMessage | FrameMessage | None:
        return self.aligner.next(timeout)

    def messages(self) -> Iterator[ImuMessage | GnssMessage | FrameMessage]:
        while not self._stop.is_set():
            msg = self.next(0.2)
            if msg is not None:
                yield msg

    def health(self) -> list[dict[str, Any]]:
        """Each input's ``StreamHealth``, with what its decoder rejected (bad checksums,
        garbage lines): an input that sends only garbage is "silent" to the engine, and this
        says why (a user trial)."""
        with self._lock:
            decoders, before = dict(self._decoders), dict(self._rejected_before)
        out = []
        for name, h in self.aligner.health.items():
            d = h.as_dict()
            dec = decoders.get(name)
            n, last = before.get(name, (0, None))
            d["rejected"] = n + int(getattr(dec, "rejected_total", 0))
            d["last_rejection"] = getattr(dec, "last_rejection", None) or last
            out.append(d)
        return out

    def close(self) -> None:
        self._stop.set()
        with self._lock:
            closers = list(self._closers.values())
        for close in closers:
            try:
                close()
            except OSError:
                pass
        for th in self._threads:
            th.join(timeout=3)
