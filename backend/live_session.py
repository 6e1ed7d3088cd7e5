"""Live sessions: the same ``Session`` (history, stream, page, alarms) fed by live devices.

A live session differs from a replay only in where the sensor messages come from: a
``live.source.LiveSource`` (the devices of a ``live.config.LiveConfig``, merged in time order
on GNSS time) instead of ``engine.messages.sensor_messages(recording)``. :class:`LiveRunner`
takes the replayer's place in the session: it runs ``engine.driver.dispatch`` on every
message in one thread and hands each frame to the session; a second thread takes the messages
from the source and queues them for the engine and for a third thread, which writes the
recording (``live.recorder.LiveRecorder``): the recording never waits for the engine, and the
engine never waits for the disk (an ``fsync`` a second). An engine slower than the sensors
skips video frames (never IMU or GNSS) once more than ``MAX_QUEUED_FRAMES`` wait, and says how
many: the officer sees a picture at most that old, not a growing lag. There is nothing to pause
or seek in a live feed: those controls are refused (the recording written live replays with
them).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import queue
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from engine.driver import FusionEngine, dispatch, frame_preparer
from engine.messages import FrameMessage, ImuMessage
from estimator.integrity import IntegrityConfig
from estimator.records import ImuData, NavigationData
from live.bridge import (
    Iec450Sender,
    NmeaOutput,
    NmeaTcpServer,
    SentenceSink,
    bridge_alerts,
    bridge_state,
)
from live.config import BridgeConfig, LiveConfig
from live.nmea import SentenceMaker
from live.recorder import VIDEO_FILE, LiveRecorder
from live.source import LiveSource
from recordings.format import Manifest, Recording, default_files, read_calibration, read_hull
from recordings.rinex import read_nav

from .errors import Conflict
from .replay import FrameResult, ReplayState
from .sessions import Session, SessionManager

log = logging.getLogger(__name__)

FIRST_MESSAGE_TIMEOUT_S = 30.0
MAX_QUEUED_FRAMES = 4  # 0.4 s of video at 10 fps: beyond, the engine skips frames to keep up
MAX_UNWRITTEN = 1200  # ~11 s of messages (~190 MB of frames) waiting for a stalled disk
# The bridge's heading is carried on queued gyro samples no farther apart than this (a gap:
# the rest on the rate of turn)
CARRY_MAX_STEP_S = 0.1
QUIET_TICK_S = 0.5  # no message for this long: the engine is told the time (sensors silent)


@dataclasses.dataclass(frozen=True)
class _Quiet:
    """No message from any sensor until ``t`` (gpst, from the source's clock)."""

    t: float


class LiveRunner:
    """Runs the engine on a live source in a thread (the ``Replayer``'s interface)."""

    def __init__(self, source: LiveSource, make_engine: Any, sink: Session, rec: Recording,
                 recorder: LiveRecorder | None, first: Any,
                 integrity: IntegrityConfig | None = None) -> None:
        self.source = source
        self._make_engine = make_engine
        self._sink = sink
        self.rec = rec
        self.recorder = recorder
        self._first = first
        self._state = ReplayState.STARTING
        self._error: str | None = None
        self._t = float(first.t)
        self._frames = 0
        self._lag = 0.0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._frame_times = np.empty(1024)
        self._queue: collections.deque[Any] = collections.deque([first])  # for the engine
        self._queued_frames = int(isinstance(first, FrameMessage))
        self._arrived = threading.Condition(self._lock)
        self.skipped_frames = 0  # frames the engine skipped to keep up with the sensors
        self.recording_error: str | None = None
        self._to_record: queue.SimpleQueue[tuple[Any, NavigationData | None] | None] = \
            queue.SimpleQueue()
        self._nav_count = -1
        self._prepare: Callable[[np.ndarray], Any] | None = None  # the engine's prepare_frame
        self._last_frame: FrameMessage | None = None  # shown again, with the status, if quiet
        # the camera silent this long (sensor time) is declared by the engine: the session is
        # then ticked with the state between frames (``_between_frames``)
        self._video_silent_s = (integrity or IntegrityConfig()).video_silent_s
        self._ticked = -np.inf
        self._thread = threading.Thread(target=self._run, name="live-session", daemon=True)
        self._pump = threading.Thread(target=self._take_messages, name="live-source",
                                      daemon=True)
        self._writer = threading.Thread(target=self._record, name="live-recorder", daemon=True)

    # ------------------------------------------------------------------ control

    def start(self, paused: bool = False) -> None:
        if self.recorder is not None:
            self._to_record.put((self._first, self._nav_if_new()))
            self._writer.start()
        self._pump.start()
        self._thread.start()

    def play(self) -> bool:
        if self._state == ReplayState.ERROR:
            raise Conflict(f"the live session stopped: {self._error}; restart the server")
        return True  # a live feed is always playing

    def pause(self) -> None:
        raise Conflict("a live session cannot be paused: the ship does not wait (replay its "
                       "recording to pause)")

    def set_speed(self, speed: float | None) -> None:
        raise Conflict("a live session runs at real time")

    def seek(self, t: float) -> None:
        raise Conflict("a live session cannot seek: replay its recording to look back")

    def stop(self, timeout: float | None = 5.0) -> None:
        self._stop.set()
        with self._arrived:
            self._arrived.notify_all()
        for thread in (self._thread, self._pump):
            if thread.is_alive() and threading.current_thread() is not thread:
                thread.join(timeout)
        self._to_record.put(None)  # after what the source gave: the recording is complete
        if self._writer.is_alive():
            self._writer.join(timeout)
        self.source.close()
        if self.recorder is not None:
            try:
                self.recorder.close()
            except OSError:
                log.exception("closing the live recording failed")
        with self._lock:
            self._state = ReplayState.STOPPED

    @property
    def state(self) -> ReplayState:
        return self._state

    def status(self) -> dict[str, Any]:
        with self._lock:
            return {
                "state": self._state.value, "time_gpst": self._t, "playing": True,
                "speed": 1.0, "seek_target_gpst": None, "frames_processed": self._frames,
                "lag_s": self._lag, "behind_s": 0.0, "achieved_speed": None,
                "error": self._error,
                "checkpoints": [], "checkpoint_note": "live: no checkpoints",
            }

    def live_status(self) -> dict[str, Any]:
        rec = None if self.recorder is None else self.recorder.status()
        return {"inputs": self.source.health(), "recording": rec,
                "skipped_frames": self.skipped_frames, "recording_error": self.recording_error}

    # ------------------------------------------------------------------ thread

    def _run(self) -> None:
        try:
            engine = self._make_engine()
        except Exception as exc:
            log.exception("cannot start the fusion engine")
            self._fail(f"cannot start the fusion engine: {exc}")
            return
        self._prepare = frame_preparer(engine)  # the pump makes it for the frames from now
        with self._lock:
            self._state = ReplayState.PLAYING
        self._notify(ReplayState.PLAYING)
        while True:
            msg = self._next_for_engine()
            if msg is None:
                return
            try:
                self._process(engine, msg)
            except Exception as exc:  # noqa: BLE001 - the thread has nobody to raise to
                log.exception("live session failed at t=%.3f", msg.t)
                self._fail(f"live session failed at gpst {msg.t:.3f}: {exc!r}")
                return

    def _take_messages(self) -> None:
        """The sensors' messages as they come: queued for the engine and for the recording."""
        while not self._stop.is_set():
            msg = self.source.next(0.2)
            if msg is None:
                continue
            if isinstance(msg, FrameMessage) and self._prepare is not None:
                msg = self._prepared(msg)
            with self._arrived:
                self._queue.append(msg)
                self._queued_frames += isinstance(msg, FrameMessage)
                self._arrived.notify()
            if self.recorder is not None and self.recording_error is None:
                if self._to_record.qsize() > MAX_UNWRITTEN:
                    self.recording_error = (f"the disk cannot keep up: more than "
                                            f"{MAX_UNWRITTEN} messages waited to be written")
                    log.error("live recording stopped: %s", self.recording_error)
                    continue
                self._to_record.put((msg, self._nav_if_new()))

    def _prepared(self, msg: FrameMessage) -> FrameMessage:
        """The frame with the engine's ``prepare_frame`` made here, in the pump's thread, off
        the engine's critical path. Should it fail, the engine makes it (and says why)."""
        try:
            return dataclasses.replace(msg, prepared=self._prepare(msg.image))
        except Exception:  # noqa: BLE001 - the engine's own call reports it
            return msg

    def _nav_if_new(self) -> NavigationData | None:
        """A copy of the ephemerides when the source has assembled new ones (the source's own
        object changes in its thread while the recorder writes)."""
        nav = self.source.nav
        count = sum(len(v) for v in nav.ephemerides.values())
        if count == self._nav_count:
            return None
        self._nav_count = count
        return dataclasses.replace(nav, ephemerides={s: list(v)
                                                     for s, v in nav.ephemerides.items()})

    def _record(self) -> None:
        """The recorder's thread: writes what the source gave, in order, until told to end."""
        assert self.recorder is not None
        nav = NavigationData()
        while (item := self._to_record.get()) is not None:
            msg, new_nav = item
            nav = new_nav or nav
            if self.recording_error is not None:
                continue  # the disk failed: the navigation goes on, the page says so
            try:
                self.recorder.write(msg, nav, {})
            except Exception as exc:  # noqa: BLE001 - a full disk must not stop the navigation
                log.exception("writing the live recording failed")
                self.recording_error = f"writing the recording failed: {exc!r}"

    def _next_for_engine(self) -> Any:
        """The next message for the engine (None once stopped); video frames are skipped while
        more than ``MAX_QUEUED_FRAMES`` wait (the engine is behind the sensors). After
        ``QUIET_TICK_S`` without any, and every as long again, a ``_Quiet`` with the time."""
        with self._arrived:
            while True:
                waited = time.monotonic()
                while not self._queue and not self._stop.is_set():
                    self._arrived.wait(0.1)
                    if not self._queue and time.monotonic() - waited >= QUIET_TICK_S:
                        now = self.source.aligner.clock.to_gpst(time.monotonic())
                        held = self.source.aligner.waiting_from
                        if now is not None and held is not None:
                            # the merge holds messages from then on, waiting for one
                            # stream: the others are not silent (a user trial: a stalled
                            # receiver was declared first as "no IMU sample")
                            now = min(now, held - 1e-3)
                        if now is not None and now > self._t:
                            return _Quiet(float(now))
                        waited = time.monotonic()
                if self._stop.is_set():
                    return None
                msg = self._queue.popleft()
                if not isinstance(msg, FrameMessage):
                    return msg
                self._queued_frames -= 1
                if self._queued_frames < MAX_QUEUED_FRAMES:
                    return msg
                self.skipped_frames += 1

    def _process(self, engine: FusionEngine, msg: Any) -> None:
        if isinstance(msg, _Quiet):
            self._quiet(engine, msg.t)
            return
        fused = dispatch(engine, msg)
        with self._lock:
            self._t = msg.t
        if not isinstance(msg, FrameMessage):
            self._between_frames(engine, msg.t)
            return
        n = self._frames
        if n >= len(self._frame_times):
            self._frame_times = np.concatenate([self._frame_times, np.empty(n)])
        self._frame_times[n] = msg.t
        self.rec.frame_times = self._frame_times[:n + 1]  # what designation looks frames up in
        with self._lock:
            self._frames = n + 1
            now = self.source.aligner.clock.to_gpst(time.monotonic())
            self._lag = 0.0 if now is None else max(0.0, now - msg.t)  # behind the sensors
        self._last_frame = msg
        self._sink.on_frame(FrameResult(msg.index, msg.t, msg.image, fused, True, time.time(),
                                        self.turned_after(engine, msg.t)), engine)

    def turned_after(self, engine: FusionEngine, t: float) -> tuple[float, float] | None:
        """(rad, s): how far the ship turned after gpst ``t`` by the gyro samples queued for
        the engine (received, not yet processed), and over how long; None without any. The
        bridge's heading is carried on them rather than on the rate of turn at ``t`` (a CI
        run: 1 s behind at a turn's start, the HDT 1.0° off)."""
        turn_rates = getattr(engine, "turn_rates", None)
        if turn_rates is None:
            return None
        with self._arrived:
            imu = [m for m in self._queue if isinstance(m, ImuMessage) and m.t > t]
        rates = turn_rates(np.array([m.gyro for m in imu])) if imu else None
        if rates is None:  # none queued, or no INS yet
            return None
        times = np.array([t, *(m.t for m in imu)])
        steps = np.diff(times)
        # up to the first gap or unusable sample: the rest is the rate of turn's
        usable = np.isfinite(rates) & (steps <= CARRY_MAX_STEP_S)
        n = len(usable) if usable.all() else int(np.argmin(usable))
        return (float(rates[:n] @ steps[:n]), float(times[n] - t)) if n else None

    def _between_frames(self, engine: FusionEngine, t: float) -> None:
        """The camera silent while the other sensors go on: every ``QUIET_TICK_S``, once the
        engine has declared it (``video_silent_s``), the session gets the current state — or
        the pose, the alarms and the berth figures would stay at the last frame's, trusted
        (a user trial: a 6 s camera outage, /pose 7 s old and "tracking")."""
        last = self._last_frame
        if last is None or t - last.t < self._video_silent_s or t - self._ticked < QUIET_TICK_S:
            return
        self._ticked = t
        self._sink.on_tick(t, engine.state(at=t), engine)

    def _quiet(self, engine: FusionEngine, t: float) -> None:
        """Every sensor silent until ``t``: the engine declares it, and the page gets the
        status (the last picture again, no pose: ``history.is_current``) within a second."""
        tick = getattr(engine, "tick", None)
        if tick is None:
            return
        tick(t)
        with self._lock:
            self._t = t
        last = self._last_frame
        if last is not None:
            self._sink.on_frame(FrameResult(last.index, t, last.image, engine.state(at=t), True,
                                            time.time()), engine)

    def _fail(self, message: str) -> None:
        with self._lock:
            self._error = message
            self._state = ReplayState.ERROR
        self._notify(ReplayState.ERROR)

    def _notify(self, state: ReplayState) -> None:
        try:
            self._sink.on_state(state)
        except Exception:
            log.exception("the session failed on state %s", state.value)


# ----------------------------------------------------------------------------- bridge


class BridgeFeed:
    """A session frame listener sending NMEA to the bridge (module docstring)."""

    def __init__(self, config: BridgeConfig, *, simulated: bool = False,
                 now_gpst: Callable[[], float | None] | None = None) -> None:
        """``now_gpst``: the sensors' time now (live), to send each state as of now."""
        self.now_gpst = now_gpst
        sinks: list[SentenceSink] = []
        self.udp = self.tcp = None
        if config.udp is not None:
            self.udp = Iec450Sender(config.udp, config.source_id)
            sinks.append(self.udp)
        if config.tcp is not None:
            self.tcp = NmeaTcpServer(*config.tcp)
            sinks.append(self.tcp)
        self.output = NmeaOutput(sinks, SentenceMaker(leap_seconds=config.leap_seconds),
                                 config.rates_hz)
        self.simulated = simulated
        self.sent = 0

    def __call__(self, session: Session, result: FrameResult) -> None:
        if result.state is None or not result.live:
            return
        now = self.now_gpst() if self.now_gpst is not None else None
        ahead = 0.0 if now is None else now - float(result.state.time)
        self.sent += len(self.output.update(bridge_state(result.state, simulated=self.simulated,
                                                         ahead_s=ahead,
                                                         turned=result.turned_after)))
        self.sent += len(self.output.alerts(bridge_alerts(session.alarms.all(),
                                                          session.start_gpst)))

    def close(self) -> None:
        if self.udp is not None:
            self.udp.close()
        if self.tcp is not None:
            self.tcp.close()


# ----------------------------------------------------------------------------- start


def live_recording_stub(config: LiveConfig, start_gpst: float, nav: NavigationData,
                        directory: Path) -> Recording:
    """The ``Recording`` a live session serves from: the installation (calibration, hull,
    origin) of the config, the live recording's directory, times growing as frames come."""
    calibration = read_calibration(config.calibration)
    hull = read_hull(config.hull)
    files = default_files(len(config.receivers), reference=False)
    files["video"] = VIDEO_FILE
    manifest = Manifest(name=config.name, scenario=None, seed=None, start_gpst=start_gpst,
                        duration_s=0.0, origin_llh_deg=config.origin_llh_deg, files=files)
    t = np.array([start_gpst])
    return Recording(path=directory, manifest=manifest, calibration=calibration, hull=hull,
                     imu=ImuData(t, np.zeros((1, 3)), np.zeros((1, 3))), frame_times=t,
                     gnss=[], gnss_headers=[], nav=nav, reference=None, scene_points=None,
                     scene_point_kinds=None)


def start_live_session(manager: SessionManager, config: LiveConfig, *,
                       options: dict[str, Any] | None = None,
                       integrity: IntegrityConfig | None = None,
                       first_message_timeout_s: float = FIRST_MESSAGE_TIMEOUT_S) -> Session:
    """Open the devices, wait for the first message, and start the live session (registered
    with ``manager``; recording under ``config.record_dir`` when set)."""
    seed = read_nav(config.nav_seed) if config.nav_seed is not None else None
    source = LiveSource(config, seed).start()
    deadline = time.monotonic() + first_message_timeout_s
    first = None
    while first is None and time.monotonic() < deadline:
        first = source.next(0.2)
    if first is None:
        health = "; ".join(f"{h['name']}: {h['state']}" + (f" ({h['error']})" if h['error']
                                                          else "") for h in source.health())
        source.close()
        raise ConnectionError(f"no sensor message within {first_message_timeout_s:g} s "
                              f"({health})")
    recorder = None
    directory = config.path.parent
    if config.record_dir is not None:
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        directory = config.record_dir / f"{config.name}-{stamp}"
        recorder = LiveRecorder(directory, name=f"{config.name}-{stamp}",
                                calibration=read_calibration(config.calibration),
                                hull=read_hull(config.hull),
                                origin_llh_deg=config.origin_llh_deg,
                                receivers=len(config.receivers))
    rec = live_recording_stub(config, float(first.t), source.nav, directory)

    def runner(make_engine: Any, session: Session) -> LiveRunner:
        return LiveRunner(source, make_engine, session, rec, recorder, first, integrity)

    session = manager.add(rec, config.name, runner, options or {}, integrity=integrity)
    if config.bridge.udp is not None or config.bridge.tcp is not None:
        clock = source.aligner.clock
        feed = BridgeFeed(config.bridge, now_gpst=lambda: clock.to_gpst(time.monotonic()))
        session.frame_listeners.append(feed)
        session.closers.append(feed.close)
    return session
