"""Replay of a recording through a fusion engine, exactly as a live feed would deliver it.

The recording's streams come as one time-ordered sequence of sensor messages
(``engine.messages.sensor_messages``).

``Replayer`` runs the engine on those messages in a background thread (the numerics are
CPU-bound; the web server's event loop must stay responsive) at real-time pace, at a chosen
speed or as fast as possible, with play / pause / seek / speed. Every processed frame is handed
to a ``FrameSink`` together with whether it is *live* (shown to clients) or part of a seek.

Seek: forward = fast-forward from the current position (the estimator is causal, so this is
exactly what a restart would compute); backward = restore the nearest cached checkpoint
before the target (a deep copy of the engine taken every ``checkpoint_interval_s`` of
recording time, ~10 ms for the real engine) and fast-forward from there, or restart from the
start when there is none (the target precedes the first checkpoint, or the engine cannot be
copied). Frames computed while seeking are not sent to clients.

The scout (``scout=True``): a second engine runs through the whole recording ahead of the
replay, in its own thread, whenever the replay leaves it room (paused, ended, or playing at
its pace without falling behind; never while the replay seeks or runs flat out). It leaves an
engine copy every ``SCOUT_INTERVAL_S`` and the state of every frame. A seek anywhere the scout
has been — forward or backward — then restores the scout's copy nearest before the target and
fast-forwards at most ``SCOUT_INTERVAL_S`` of recording; the states of the frames a forward
seek jumps over come from the scout (``FrameSink.on_history``), so the history has no gap.
The same engine on the same messages computes the same states: the copies are exact.
"""

from __future__ import annotations

import copy
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, Protocol

import numpy as np

from engine.driver import FusionEngine, dispatch, frame_preparer
from engine.messages import FrameMessage, SensorMessage, sensor_messages
from recordings.format import Recording

log = logging.getLogger(__name__)

MAX_LAG_S = 0.5  # when the engine falls further behind real time, the clock is re-anchored
VIDEO_LATE_S = 1.0  # the other sensors this far past the next frame's time: the video has ended
SCOUT_INTERVAL_S = 2.0  # recording s between the scout's engine copies: ~1 s of fast-forward
SCOUT_MAX_CHECKPOINTS = 48  # ~4 MB each (the real engine); beyond, every other copy goes
#                             and the interval doubles
SCOUT_LAG_S = 0.1  # the scout pauses while the replay is later than this on its clock


def snapshot(engine: FusionEngine, shared: tuple[Any, ...] = ()) -> FusionEngine:
    """Deep copy of an engine that continues exactly like the original.

    Shared, not copied: the objects in ``shared`` (the engine's inputs: calibration, navigation
    data — never modified by an engine) and OpenCV objects, which cannot be copied and which
    engines hold as stateless configured tools (feature detectors).
    """
    memo: dict[int, Any] = {id(o): o for o in shared}
    seen: set[int] = set(memo)
    stack: list[Any] = [engine]
    while stack:
        obj = stack.pop()
        if id(obj) in seen or isinstance(obj, np.ndarray | str | bytes | int | float):
            continue
        seen.add(id(obj))
        if type(obj).__module__.startswith("cv2"):
            memo[id(obj)] = obj
        elif isinstance(obj, dict):
            stack.extend(obj.values())
        elif isinstance(obj, list | tuple | set | frozenset | deque):
            stack.extend(obj)
        elif hasattr(obj, "__dict__"):
            stack.extend(vars(obj).values())
    return copy.deepcopy(engine, memo)


# ----------------------------------------------------------------------------- replayer


class ReplayState(StrEnum):
    STARTING = "starting"
    PLAYING = "playing"
    PAUSED = "paused"
    SEEKING = "seeking"
    ENDED = "ended"
    ERROR = "error"
    STOPPED = "stopped"


@dataclass
class FrameResult:
    index: int
    t: float  # gpst
    image: np.ndarray  # BGR
    state: Any | None  # FusedState, None while the engine has no solution yet
    live: bool  # False while seeking (computed but not shown)
    processed_wall: float  # time.time() when the engine returned
    # live, the engine behind the sensors: (rad, s) the ship turned after ``t`` by the gyro
    # samples already received, and over how long (``LiveRunner.turned_after``)
    turned_after: tuple[float, float] | None = None


class FrameSink(Protocol):
    """Receives the replay's output. Called in the replay thread; ``engine`` may be queried
    (``structure``, ``timing``) during the call only."""

    def on_frame(self, result: FrameResult, engine: FusionEngine) -> None: ...

    def on_rewind(self, t: float | None) -> None:
        """Results after gpst ``t`` (all results when None) are void: the replay went back."""

    def on_state(self, state: ReplayState) -> None: ...

    def on_history(self, states: list[tuple[float, Any]]) -> None:
        """(gpst, state) of frames a forward seek jumped over (computed by the scout), in
        time order, before the ``on_rewind`` to where the replay resumes."""


@dataclass
class _Checkpoint:
    t: float  # gpst of the frame after which the engine was copied
    engine: FusionEngine


class Scout:
    """A second engine run through the recording ahead of the replay (module docstring).

    One scout may serve several replays of the same recording and engine options
    (``ScoutPool``): each attaches ``busy()`` (it needs the processor: the scout waits) and
    ``progress()`` (called after each copy and at the end, so that its clients are told)."""

    def __init__(self, rec: Recording, make_engine: Callable[[], FusionEngine],
                 shared: tuple[Any, ...] = (), interval_s: float = SCOUT_INTERVAL_S,
                 max_checkpoints: int = SCOUT_MAX_CHECKPOINTS) -> None:
        self.rec = rec
        self._make_engine = make_engine
        self._waiters: dict[int, tuple[Callable[[], bool], Callable[[], None] | None]] = {}
        self._shared = shared
        self.interval_s = interval_s
        self._max_checkpoints = max_checkpoints
        self._lock = threading.Lock()
        self._checkpoints: list[_Checkpoint] = []
        self._states: list[tuple[float, Any]] = []  # (gpst, state) of every frame with one
        self.frontier = float(rec.manifest.start_gpst)  # gpst of the last message run
        self.done = False
        self.error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"scout-{rec.manifest.name}",
                                        daemon=True)

    def attach(self, owner: object, busy: Callable[[], bool],
               progress: Callable[[], None] | None = None) -> None:
        with self._lock:
            self._waiters[id(owner)] = (busy, progress)

    def detach(self, owner: object) -> None:
        with self._lock:
            self._waiters.pop(id(owner), None)

    @property
    def attached(self) -> int:
        with self._lock:
            return len(self._waiters)

    def _busy(self) -> bool:
        with self._lock:
            waiters = list(self._waiters.values())
        return any(busy() for busy, _ in waiters)

    def start(self) -> None:
        """Start running (once; later calls do nothing)."""
        with self._lock:
            if self._thread.ident is not None or self._stop.is_set():
                return
            self._thread.start()

    def stop(self, timeout: float | None = 5.0) -> None:
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        with self._lock:
            self._checkpoints, self._states = [], []

    def checkpoint(self, t: float) -> _Checkpoint | None:
        """The newest engine copy from before gpst ``t`` (a copy is taken after its frame:
        a seek to that very frame must start earlier to show it)."""
        with self._lock:
            usable = [c for c in self._checkpoints if c.t < t]
            return usable[-1] if usable else None

    def states(self, after: float, until: float) -> list[tuple[float, Any]]:
        """(gpst, state) of the frames in (after, until]."""
        with self._lock:
            return [(t, s) for t, s in self._states if after < t <= until]

    def _tell(self) -> None:
        with self._lock:
            waiters = list(self._waiters.values())
        for _, progress in waiters:
            if progress is not None:
                try:
                    progress()
                except Exception:  # telling the clients is a courtesy: the scout goes on
                    log.exception("scout progress callback failed")

    def _run(self) -> None:
        messages: Iterator[SensorMessage] = iter(())
        _lowest_priority()
        try:
            engine = self._make_engine()
            messages = sensor_messages(self.rec, prepare=frame_preparer(engine))
            last = float(self.rec.manifest.start_gpst)
            for msg in messages:
                while self._busy():
                    if self._stop.wait(0.05):
                        return
                if self._stop.is_set():
                    return
                fused = dispatch(engine, msg)
                with self._lock:
                    self.frontier = msg.t
                    if isinstance(msg, FrameMessage) and fused is not None:
                        self._states.append((msg.t, copy.deepcopy(fused)))
                if isinstance(msg, FrameMessage) and msg.t - last >= self.interval_s:
                    copied = snapshot(engine, self._shared)
                    last = msg.t
                    with self._lock:
                        self._checkpoints.append(_Checkpoint(msg.t, copied))
                        if len(self._checkpoints) > self._max_checkpoints:
                            del self._checkpoints[1::2]
                            self.interval_s *= 2
                    self._tell()
            self.done = True
            self._tell()
        except BaseException as exc:  # noqa: B036 - the replay goes on without look-ahead
            log.exception("the scout stopped")
            self.error = f"the look-ahead engine stopped: {exc!r}"
        finally:
            close = getattr(messages, "close", None)
            if close is not None:
                close()


def _lowest_priority() -> None:
    """The calling thread yields the processor to every other one (on Linux a thread has a
    nice value of its own): the look-ahead engine takes only what the replay, the stream
    and the server leave. Its wait while the replay is busy is not enough: at 1x the replay
    keeps pace, and the scout then took the core the JPEG encoding and the overlay need."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
    except (AttributeError, OSError):  # elsewhere the wait alone
        pass


class ScoutPool:
    """The scouts of a server, one per recording and engine options, shared by the sessions
    that replay them (a page reloaded, a second screen, a session made again: its seeks are
    quick at once). At most ``size`` are kept: beyond, the least recently asked for that no
    replay uses is stopped (each holds up to ~190 MB of engine copies)."""

    def __init__(self, size: int = 2) -> None:
        self.size = size
        self._scouts: dict[str, Scout] = {}  # in the order last asked for
        self._lock = threading.Lock()

    def get(self, key: str, make: Callable[[], Scout]) -> Scout:
        """The running scout of ``key``, or a new one from ``make()`` (started)."""
        gone: list[Scout] = []
        with self._lock:
            scout = self._scouts.pop(key, None)
            if scout is None or scout.error is not None:
                if scout is not None:
                    gone.append(scout)
                scout = make()
            self._scouts[key] = scout
            for old_key in list(self._scouts)[:-1]:
                if len(self._scouts) <= self.size:
                    break
                if self._scouts[old_key].attached == 0:
                    gone.append(self._scouts.pop(old_key))
        for old in gone:
            old.stop()
        scout.start()
        return scout

    def close(self) -> None:
        with self._lock:
            scouts, self._scouts = list(self._scouts.values()), {}
        for scout in scouts:
            scout.stop()


@dataclass
class _Loop:
    """The replay thread's working state."""

    engine: FusionEngine | None = None
    messages: Iterator[SensorMessage] = field(default_factory=lambda: iter(()))
    pending: SensorMessage | None = None  # taken from the iterator, not yet processed
    target: float | None = None  # gpst the current fast-forward runs to
    anchor: tuple[float, float, float] | None = None  # (wall, gpst, speed) of the pacing clock
    notified: ReplayState | None = None  # the state the sink was last told


class Replayer:
    """Plays ``rec`` through an engine made by ``make_engine`` in a daemon thread."""

    def __init__(self, rec: Recording, make_engine: Callable[[], FusionEngine], sink: FrameSink,
                 speed: float | None = 1.0, checkpoint_interval_s: float | None = 10.0,
                 max_checkpoints: int = 20, shared: tuple[Any, ...] = (),
                 scout: bool | Scout = False) -> None:
        """``scout``: True, a scout of its own (stopped with the replay); a ``Scout``, one
        shared with other replays of the same recording and engine (left running)."""
        self.rec = rec
        self._shared = shared  # engine inputs a snapshot shares instead of copying
        self._make_engine = make_engine
        self._sink = sink
        self._cond = threading.Condition()
        self._speed = speed  # None = as fast as possible
        self._playing = True
        self._seek_to: float | None = None  # gpst target of a pending seek command
        self._seek_goal: float | None = None  # gpst target of the seek being run
        self._stop = False
        self._state = ReplayState.STARTING
        self._error: str | None = None
        self._t = float(rec.manifest.start_gpst)  # time of the last processed message
        self._frames = 0
        self._lag = 0.0  # s the last message was late on the replay clock
        self._behind = 0.0  # recording s lost to re-anchoring since the clock last started
        self._clock_start: tuple[float, float] | None = None  # (wall, gpst) it last started
        self._checkpoint_interval = checkpoint_interval_s
        self._max_checkpoints = max_checkpoints
        self._checkpoints: list[_Checkpoint] = []
        self._checkpoint_note: str | None = None
        self._thread = threading.Thread(target=self._run, name=f"replay-{rec.manifest.name}",
                                        daemon=True)
        self._own_scout = scout is True
        self.scout = (Scout(rec, make_engine, shared) if scout is True
                      else scout if isinstance(scout, Scout) else None)

    def _needs_processor(self) -> bool:
        """Whether the replay wants the processor now (the scout waits): seeking, running
        flat out, or later than ``SCOUT_LAG_S`` on its clock."""
        with self._cond:
            if self._stop:
                return False
            if self._state in (ReplayState.SEEKING, ReplayState.STARTING):
                return True
            if self._state != ReplayState.PLAYING or not self._playing:
                return False
            return self._speed is None or self._lag > SCOUT_LAG_S

    # ------------------------------------------------------------------ control (any thread)

    def start(self, paused: bool = False) -> None:
        """Start the replay thread; ``paused``: stop on the first frame (shown to clients)."""
        self._playing = not paused
        if paused:
            self._seek_to = float(self.rec.manifest.start_gpst)
        self._thread.start()
        if self.scout is not None:
            self.scout.attach(self, self._needs_processor,
                              lambda: self._sink.on_state(self._state))
            self.scout.start()

    def play(self) -> bool:
        """Play on. At the end of the recording nothing changes and False is returned: playing
        again means seeking back (which recomputes the history after the seek target), and
        that is the client's explicit choice. After an error the engine restarts from the
        newest checkpoint before the replay position (or from the start) and recomputes up to
        it before playing on."""
        with self._cond:
            if self._state == ReplayState.ENDED and self._seek_to is None:
                return False
            if self._state == ReplayState.ERROR and self._seek_to is None:
                self._seek_to = self._t
            self._playing = True
            self._cond.notify_all()
            return True

    def pause(self) -> None:
        with self._cond:
            self._playing = False
            self._cond.notify_all()

    def set_speed(self, speed: float | None) -> None:
        with self._cond:
            self._speed = speed
            self._cond.notify_all()

    def seek(self, t: float) -> None:
        """Seek to gpst ``t`` (clamped to the recording by the caller)."""
        with self._cond:
            self._seek_to = float(t)
            self._cond.notify_all()

    def stop(self, timeout: float | None = 5.0) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self.scout is not None:
            self.scout.detach(self)
            if self._own_scout:
                self.scout.stop(timeout)
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)

    def status(self) -> dict[str, Any]:
        with self._cond:
            return {
                "state": self._state.value,
                "time_gpst": self._t,
                "playing": self._playing,
                "speed": self._speed,
                # a pending seek, or the one running (the page shows its target and progress)
                "seek_target_gpst": self._seek_to if self._seek_to is not None else
                self._seek_goal if self._state == ReplayState.SEEKING else None,
                "frames_processed": self._frames,
                "lag_s": self._lag,
                "behind_s": self._behind,
                "achieved_speed": self._achieved_speed(),
                "error": self._error,
                "checkpoints": [c.t for c in self._checkpoints],
                "checkpoint_note": self._checkpoint_note,
                "scouted_gpst": None if self.scout is None else self.scout.frontier,
                "scout_error": None if self.scout is None else self.scout.error,
            }

    def _achieved_speed(self) -> float | None:
        """Recording seconds per wall second since the clock last started (a play, a seek,
        a new speed), once a second has passed; None while not pacing (paused, flat out)."""
        if self._clock_start is None or not self._playing or self._speed is None \
                or self._state != ReplayState.PLAYING:
            return None
        wall = time.monotonic() - self._clock_start[0]
        return (self._t - self._clock_start[1]) / wall if wall >= 1.0 else None

    @property
    def state(self) -> ReplayState:
        return self._state

    # ---------------------------------------------------------------- replay thread

    def _scout_jump(self, goal: float) -> bool:
        """Whether a forward seek to ``goal`` is quicker from a scout's copy than onward."""
        cp = None if self.scout is None else self.scout.checkpoint(goal)
        return cp is not None and cp.t > self._t + SCOUT_INTERVAL_S

    def _restart(self, target: float) -> tuple[FusionEngine, Iterator[SensorMessage]]:
        """Engine and message iterator positioned before ``target`` (gpst): from the newest
        checkpoint (the replay's or the scout's) before it, else from the start."""
        with self._cond:
            usable = [c for c in self._checkpoints if c.t < target]  # (as Scout.checkpoint)
            self._checkpoints = usable
        scouted = None if self.scout is None else self.scout.checkpoint(target)
        if scouted is not None and (not usable or scouted.t > usable[-1].t):
            usable = [*usable, scouted]
        if usable:
            cp = usable[-1]
            try:
                engine = snapshot(cp.engine, self._shared)  # the checkpoint stays pristine
            except Exception as exc:  # a copy that worked once should work again; be safe
                log.warning("checkpoint restore failed (%s); restarting from the start", exc)
            else:
                if cp is scouted and cp.t > self._t and self.scout is not None:
                    self._sink.on_history(self.scout.states(self._t, cp.t))  # jumped over
                self._sink.on_rewind(cp.t)
                with self._cond:
                    self._t = cp.t
                    self._frames = int(np.searchsorted(self.rec.frame_times, cp.t, "right"))
                return engine, sensor_messages(self.rec, after=cp.t,
                                               prepare=frame_preparer(engine))
        with self._cond:
            self._checkpoints = []
            self._t = float(self.rec.manifest.start_gpst)
            self._frames = 0
        self._sink.on_rewind(None)
        engine = self._make_engine()
        return engine, sensor_messages(self.rec, prepare=frame_preparer(engine))

    def _maybe_checkpoint(self, engine: FusionEngine, t: float) -> None:
        if self._checkpoint_interval is None or self._checkpoint_note is not None:
            return
        if self.scout is not None and self.scout.frontier >= t:
            return  # the scout has been here, with denser copies
        last = self._checkpoints[-1].t if self._checkpoints else self.rec.manifest.start_gpst
        if t - last < self._checkpoint_interval:
            return
        try:
            copied = snapshot(engine, self._shared)
        except Exception as exc:  # an engine holding something that cannot be copied
            self._checkpoint_note = f"checkpoints disabled: the engine cannot be copied ({exc})"
            log.info(self._checkpoint_note)
            return
        with self._cond:
            self._checkpoints.append(_Checkpoint(t, copied))
            if len(self._checkpoints) > self._max_checkpoints:
                del self._checkpoints[1::2]  # thin out evenly, keep the first

    def _idle(self) -> bool:
        """Nothing to do until a command arrives (called with the condition held)."""
        if self._stop or self._seek_to is not None:
            return False
        return self._state in (ReplayState.ENDED, ReplayState.ERROR) or not self._playing

    def _fail(self, message: str) -> None:
        with self._cond:
            self._error = message
            self._state = ReplayState.ERROR

    def _run(self) -> None:
        """The thread body. Whatever fails in it — the engine, the recording, the pacing, the
        sink, or code that looks safe — ends in ERROR with the message, told to the sink (the
        API status and the stream show it); the thread then waits for a restart (seek, play)
        or for stop. No failure ends the thread unseen."""
        loop = _Loop()
        try:
            loop.engine = self._make_engine()
            loop.messages = sensor_messages(self.rec, prepare=frame_preparer(loop.engine))
        except Exception as exc:
            log.exception("cannot start the replay")
            self._fail(f"cannot start the fusion engine: {exc}")
        try:
            while True:
                try:
                    self._loop(loop)
                    return  # stopped
                except BaseException as exc:  # noqa: B036 - a thread has nobody to raise to
                    log.exception("replay thread failed")
                    self._fail(f"replay failed: {exc!r}")
                    self._release(loop)
                    loop = _Loop(notified=loop.notified)
                    self._notify(loop, ReplayState.ERROR)
                    if not self._wait_for_restart():
                        return
        finally:
            self._release(loop)
            with self._cond:
                self._state = ReplayState.STOPPED
                self._checkpoints = []  # engine copies: the largest thing a replay holds

    def _notify(self, loop: _Loop, state: ReplayState) -> None:
        """Tell the sink the state once; a sink that fails is logged (the state stands)."""
        if state == loop.notified:
            return
        loop.notified = state
        try:
            self._sink.on_state(state)
        except Exception:
            log.exception("the sink failed on state %s", state.value)

    def _wait_for_restart(self) -> bool:
        """After a failure: wait for a seek (play after an error is one) or stop; False on
        stop."""
        with self._cond:
            while not self._stop and self._seek_to is None:
                self._cond.wait()
            return not self._stop

    @staticmethod
    def _release(loop: _Loop) -> None:
        """Close the message iterator now (it holds the video decoder) and drop the engine."""
        close = getattr(loop.messages, "close", None)
        loop.messages, loop.pending, loop.engine = iter(()), None, None
        if close is not None:
            try:
                close()
            except Exception:
                log.exception("closing the recording's messages failed")

    def _loop(self, loop: _Loop) -> None:
        # The sink is only ever called with the condition released: its callbacks take the
        # session's lock, and API threads holding that lock read this replayer's status.
        while True:
            state, speed, goal, restart = self._command(loop)
            self._notify(loop, state)
            if state == ReplayState.STOPPED:
                return
            if goal is not None:
                loop.target, loop.anchor = goal, None
                if restart and not self._restart_loop(loop, goal):
                    continue
            with self._cond:
                if loop.target is None and self._idle():
                    loop.anchor = None
                    self._cond.wait()
                    continue
            msg = self._next_message(loop)
            if msg is None:
                continue
            if loop.target is None and speed is not None:
                loop.anchor = self._pace(msg.t, speed, loop.anchor)
                if loop.anchor is None:  # a command arrived while waiting: handle it first
                    continue
            loop.pending = None
            self._process(loop, msg)

    def _command(self, loop: _Loop) -> tuple[ReplayState, float | None, float | None, bool]:
        """The state the commands put the replay in: (state, speed, seek goal, whether the
        engine restarts for it)."""
        goal: float | None = None
        restart = False
        with self._cond:
            if self._stop:
                self._state = ReplayState.STOPPED
            elif self._seek_to is not None:
                goal, self._seek_to = self._seek_to, None
                self._seek_goal = goal
                restart = (goal < self._t or loop.engine is None
                           or self._state == ReplayState.ERROR or self._scout_jump(goal))
                self._error = None
                self._state = ReplayState.SEEKING
            elif loop.target is not None:
                self._state = ReplayState.SEEKING
            elif self._state not in (ReplayState.ENDED, ReplayState.ERROR):
                self._state = ReplayState.PLAYING if self._playing else ReplayState.PAUSED
            return self._state, self._speed, goal, restart

    def _restart_loop(self, loop: _Loop, goal: float) -> bool:
        self._release(loop)
        try:
            loop.engine, loop.messages = self._restart(goal)
        except Exception as exc:
            log.exception("cannot restart the replay")
            self._fail(f"cannot restart the fusion engine: {exc}")
            loop.target = None
            return False
        return True

    def _next_message(self, loop: _Loop) -> SensorMessage | None:
        """The message to process next (kept as pending until it is); None at the end or
        when the recording cannot be read (the state says which)."""
        if loop.pending is None:
            try:
                loop.pending = next(loop.messages)
            except StopIteration:
                with self._cond:
                    self._state = ReplayState.ENDED
                loop.target = None
                return None
            except Exception as exc:  # a broken video or file while replaying
                log.exception("replay input failed")
                self._fail(f"reading the recording failed: {exc}")
                loop.target = None
                return None
        return loop.pending

    def _process(self, loop: _Loop, msg: SensorMessage) -> None:
        """One message through the engine; a frame's result to the sink."""
        engine = loop.engine
        assert engine is not None
        try:
            fused = dispatch(engine, msg)
        except Exception as exc:
            log.exception("fusion engine failed at t=%.3f", msg.t)
            self._fail(f"fusion engine failed at gpst {msg.t:.3f}: {exc!r}")
            loop.target = None
            return
        with self._cond:
            self._t = msg.t
            if isinstance(msg, FrameMessage):
                self._frames += 1
            frames = self._frames
        if not isinstance(msg, FrameMessage):
            if (ended := self._video_ended(msg.t, frames)) is not None:
                self._fail(ended)  # the page would keep its last picture and say all is well
                loop.target = None
            return
        target = loop.target
        live = target is None or msg.t >= target
        try:
            self._sink.on_frame(FrameResult(msg.index, msg.t, msg.image, fused, live,
                                            time.time()), engine)
        except Exception as exc:  # the session's bookkeeping failed: serving on would lie
            log.exception("frame sink failed at frame %d", msg.index)
            self._fail(f"serving frame {msg.index} failed: {exc!r}")
            loop.target = None
            return
        self._maybe_checkpoint(engine, msg.t)
        if target is not None and msg.t >= target:
            loop.target = None  # seek done: playing or paused resumes from here

    def _video_ended(self, t: float, frames: int) -> str | None:
        """Why the replay cannot go on at ``t`` with ``frames`` frames shown: the video ended
        (cut short, or shorter than the other sensors) more than ``VIDEO_LATE_S`` ago."""
        times, start = self.rec.frame_times, self.rec.manifest.start_gpst
        if frames < len(times) and t > times[frames] + VIDEO_LATE_S:
            last = times[frames - 1] - start if frames else 0.0
            return (f"the video ends at frame {frames} ({last:.1f} s) "
                    f"though the frame times list {len(times)} frames: no picture after it, "
                    "the replay stops here")
        if frames == len(times) and len(times) and t > times[-1] + VIDEO_LATE_S:
            return (f"the recording's video ends at {times[-1] - start:.1f} s, its other "
                    "sensors go on: no picture after it, the replay stops here")
        return None

    def _pace(self, t: float, speed: float, anchor: tuple[float, float, float] | None
              ) -> tuple[float, float, float] | None:
        """Sleep until message time ``t`` is due on the replay clock; None when a command
        arrived meanwhile. Re-anchors when behind by more than MAX_LAG_S (no catch-up burst).
        A new speed starts the clock afresh: what was lost at the old one is not behind now
        (a user trial: 4x then 1x, keeping pace, and still "behind real time by 17 s")."""
        now = time.monotonic()
        if anchor is None or anchor[2] != speed:
            with self._cond:
                self._lag = self._behind = 0.0
                self._clock_start = (now, t)
            return now, t, speed
        due = anchor[0] + (t - anchor[1]) / speed
        with self._cond:
            self._lag = max(0.0, now - due)
            if now - due > MAX_LAG_S:
                self._behind += (now - due) * speed  # the engine is slower than real time
                return now, t, speed
            while True:
                if self._stop or self._seek_to is not None or not self._playing:
                    return None
                if self._speed != speed:
                    return None
                remaining = due - time.monotonic()
                if remaining <= 0:
                    return anchor
                self._cond.wait(min(remaining, 1.0))  # bounded: any speed, any clock


