"""Replay of a recording as a live feed (backend/replay.py): message order, pacing, pause, seek
and checkpoints. Uses a short simulated recording (made once per test session) and small
engine doubles; one test runs the real fusion engine to check that a checkpoint continues
exactly like the original."""

from __future__ import annotations

import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from backend.replay import FrameResult, Replayer, ReplayState, Scout, snapshot
from engine.driver import dispatch
from engine.messages import FrameMessage, GnssMessage, ImuMessage, group_gnss, sensor_messages
from recordings.format import Recording, load


@pytest.fixture(scope="module")
def rec(sim_recording: Path) -> Recording:
    return load(sim_recording)


# ------------------------------------------------------------------------------ messages


def test_messages_are_in_time_order_like_a_live_feed(rec: Recording):
    kinds = {ImuMessage: 0, GnssMessage: 1, FrameMessage: 2}
    messages = list(sensor_messages(rec))
    keys = [(m.t, kinds[type(m)]) for m in messages]
    assert keys == sorted(keys)  # at equal time tags: IMU, then GNSS, then the frame
    assert sum(isinstance(m, ImuMessage) for m in messages) == len(rec.imu)
    frames = [m for m in messages if isinstance(m, FrameMessage)]
    assert [f.index for f in frames] == list(range(len(rec.frame_times)))
    assert frames[0].image.shape == (rec.calibration.camera.height,
                                     rec.calibration.camera.width, 3)
    gnss = [m for m in messages if isinstance(m, GnssMessage)]
    assert len(gnss) == len(rec.gnss[0]) == 13
    for m in gnss:  # one message per time tag with the four receivers' epochs
        assert len(m.epochs) == 4
        assert all(e is not None and abs(e.time - m.t) < 1e-6 for e in m.epochs)


def test_messages_after_a_time_and_missing_receivers(rec: Recording):
    t_cut = float(rec.frame_times[50])
    later = list(sensor_messages(rec, after=t_cut))
    assert later and all(m.t > t_cut for m in later)
    assert next(m for m in later if isinstance(m, FrameMessage)).index == 51
    # a receiver that missed an epoch leaves a None in its slot
    saved = rec.gnss[2]
    try:
        rec.gnss[2] = saved[:5] + saved[6:]
        groups = group_gnss(rec)
        assert groups[5].epochs[2] is None and groups[5].epochs[1] is not None
    finally:
        rec.gnss[2] = saved


# ------------------------------------------------------------------------------- replayer


@dataclass
class _State:
    time: float
    value: float


class SumEngine:
    """Deterministic double: its 'state' depends on every message it has seen."""

    def __init__(self) -> None:
        self.total = 0.0
        self.frames = 0

    def process_imu(self, t, gyro, accel) -> None:
        self.total += float(accel[2]) * 1e-3 + float(t - 1.4e9) * 1e-6

    def process_gnss(self, t, epochs) -> None:
        self.total += sum(len(e.satellites) for e in epochs if e is not None)

    def process_frame(self, t, image) -> _State:
        self.frames += 1
        self.total += float(image[::50, ::50].mean())
        return _State(t, self.total)

    def state(self) -> _State | None:
        return None

    def structure(self):
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=int)

    def solved_views(self) -> None:
        return None

    def timing(self) -> dict:
        return {}


@dataclass
class Sink:
    results: list[FrameResult] = field(default_factory=list)
    rewinds: list[float | None] = field(default_factory=list)
    states: list[ReplayState] = field(default_factory=list)
    event: threading.Event = field(default_factory=threading.Event)
    jumped: list[tuple[float, object]] = field(default_factory=list)

    def on_frame(self, result: FrameResult, engine) -> None:
        self.results.append(result)

    def on_rewind(self, t: float | None) -> None:
        self.rewinds.append(t)
        self.results = [r for r in self.results if t is not None and r.t <= t]

    def on_history(self, states: list[tuple[float, object]]) -> None:
        self.jumped += states

    def on_state(self, state: ReplayState) -> None:
        self.states.append(state)
        if state in (ReplayState.ENDED, ReplayState.PAUSED, ReplayState.ERROR):
            self.event.set()


def wait_for(predicate, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError("timed out")
        time.sleep(0.01)


def test_replay_as_fast_as_possible_then_seek_back_from_a_checkpoint(rec: Recording):
    sink = Sink()
    replayer = Replayer(rec, SumEngine, sink, speed=None, checkpoint_interval_s=3.0)
    replayer.start()
    try:
        wait_for(lambda: replayer.state == ReplayState.ENDED)
        straight = {r.index: r.state.value for r in sink.results}
        assert len(straight) == len(rec.frame_times)
        assert all(r.live for r in sink.results)
        checkpoints = replayer.status()["checkpoints"]
        start = rec.manifest.start_gpst
        assert np.round(np.array(checkpoints) - start, 3).tolist() == [3.0, 6.0, 9.0, 12.0]
        # seek back to 7.5 s: restore the 6 s checkpoint, fast-forward without showing frames
        replayer.pause()
        replayer.seek(start + 7.5)
        wait_for(lambda: replayer.state == ReplayState.PAUSED and sink.results
                 and sink.results[-1].live and sink.results[-1].t >= rec.frame_times[75])
        assert sink.rewinds[-1] == pytest.approx(checkpoints[1])
        replayed = [r for r in sink.results if r.t > checkpoints[1]]
        assert [r.live for r in replayed] == [False] * (len(replayed) - 1) + [True]
        assert replayed[-1].index == 75  # paused on the first frame at/after the target
        for r in replayed:
            assert r.state.value == straight[r.index]  # identical to the uninterrupted run
        # seek before the first checkpoint: restart from the start
        replayer.seek(start + 1.0)
        wait_for(lambda: sink.results and sink.results[-1].index == 10
                 and replayer.state == ReplayState.PAUSED)
        assert sink.rewinds[-1] is None
        assert sink.results[-1].state.value == straight[10]
    finally:
        replayer.stop()


def test_the_scout_runs_ahead_and_seeks_start_from_its_copies(rec: Recording):
    """Paused at the start, the scout runs the whole recording; a forward seek then jumps to
    its copy nearest before the target (the states jumped over come from the scout), a
    backward one too, and both give exactly the states of an uninterrupted run."""
    straight, engine = {}, SumEngine()
    for m in sensor_messages(rec):
        if (state := dispatch(engine, m)) is not None:
            straight[m.t] = state.value
    sink = Sink()
    replayer = Replayer(rec, SumEngine, sink, speed=1.0, scout=True)
    replayer.start(paused=True)
    try:
        assert replayer.scout is not None
        wait_for(lambda: replayer.scout.done, 60)
        start = rec.manifest.start_gpst
        copies = [replayer.scout.checkpoint(t + 0.05) for t in rec.frame_times]
        spaced = sorted({c.t for c in copies if c is not None})
        assert len(spaced) == 6 and np.allclose(np.diff(spaced), 2.0, atol=0.11)
        assert replayer.status()["scouted_gpst"] == pytest.approx(rec.frame_times[-1], abs=0.1)
        for target in (start + 10.55, start + 4.25):  # forward, then backward
            rewound = len(sink.rewinds)
            replayer.seek(target)
            wait_for(lambda rewound=rewound, target=target: len(sink.rewinds) > rewound
                     and replayer.state == ReplayState.PAUSED and sink.results[-1].live
                     and sink.results[-1].t >= target)
            cp = replayer.scout.checkpoint(target)
            assert sink.rewinds[-1] == pytest.approx(cp.t)
            recomputed = [r for r in sink.results if r.t > cp.t]
            assert 1 <= len(recomputed) <= 21  # at most 2 s of frames after the copy
            assert recomputed[-1].live and recomputed[-1].t >= target
            for r in recomputed:
                assert r.state.value == straight[r.t]
        # the forward jump left no gap: the frames it skipped came from the scout, exact
        assert len(sink.jumped) >= 80
        for t, state in sink.jumped:
            assert state.value == straight[t]
    finally:
        replayer.stop()
    assert replayer.scout.checkpoint(float("inf")) is None  # the copies are released


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice: Linux")
def test_the_scout_runs_at_the_lowest_priority(rec: Recording):
    """At 1x the replay keeps pace and the scout runs, so it must leave the processor to
    the replay, the stream and the server: its thread has nice 19, the others keep theirs."""
    scout = Scout(rec, SumEngine)
    scout.attach(object(), lambda: True)  # a busy replay: the scout waits, its thread alive
    scout.start()
    try:
        tid = scout._thread.native_id
        wait_for(lambda: os.getpriority(os.PRIO_PROCESS, tid) == 19, 5)
        assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) < 19
    finally:
        scout.stop()


def test_sessions_of_one_recording_share_a_scout_and_the_server_warms_it(sim_recording: Path):
    """The manager's sessions on the same recording and options share one scout: a second
    session's seeks are quick at once, deleting a session leaves the scout to the others, and
    ``warm`` starts it before any session. At most two are kept; an unused one goes."""
    from backend.catalog import RecordingCatalog
    from backend.models import FusionOptionsModel
    from backend.replay import Scout, ScoutPool
    from backend.sessions import SessionManager
    from engine.driver import create_engine

    manager = SessionManager(RecordingCatalog(None, sim_recording), create_engine)
    name = manager.catalog.default_name()
    options = FusionOptionsModel().model_dump()  # what a page opens a session with
    try:
        manager.warm(name, options)
        assert manager.scouts is not None
        (warm,) = manager.scouts._scouts.values()
        wait_for(lambda: warm.done, 120)  # ran before any session was opened
        a = manager.create(name, 1.0, options, paused=True)
        b = manager.create(name, 1.0, options, paused=True)
        assert a.replayer.scout is warm and b.replayer.scout is warm and warm.attached == 2
        other = manager.create(name, 1.0, {**options, "use_vo": False}, paused=True)
        assert other.replayer.scout is not warm  # other options: other states, its own
        manager.delete(a.id)
        assert warm.attached == 1 and warm.checkpoint(float("inf")) is not None  # still there
        start = b.rec.manifest.start_gpst
        tic = time.monotonic()
        b.control("seek", 10.55, None)
        wait_for(lambda: b.replayer.state == ReplayState.PAUSED
                 and b.replayer.status()["time_gpst"] >= start + 10.5, 60)
        recomputed = b.replayer.status()["frames_processed"]
        assert b.history.latest() is not None and len(b.history.arrays()[0]) >= 90
        print(f"seek in a session opened after the warm scout: {time.monotonic() - tic:.2f} s "
              f"({recomputed} frames counted)")
    finally:
        manager.close_all()
    assert warm.checkpoint(float("inf")) is None  # stopped with the server
    # the pool keeps two: the least recently used one that nobody uses goes
    pool = ScoutPool(size=2)
    made = [pool.get(k, lambda: Scout(manager.catalog.load(name), SumEngine)) for k in "abc"]
    try:
        assert list(pool._scouts) == ["b", "c"] and made[0].checkpoint(float("inf")) is None
        made[1].attach(made, lambda: True)  # "b" in use: not evicted; "c" is
        pool.get("d", lambda: Scout(manager.catalog.load(name), SumEngine))
        assert list(pool._scouts) == ["b", "d"]
    finally:
        pool.close()


def test_real_time_pace_pause_and_speed(rec: Recording):
    sink = Sink()
    replayer = Replayer(rec, SumEngine, sink, speed=4.0)
    t0 = time.monotonic()
    replayer.start()
    try:
        wait_for(lambda: len(sink.results) >= 21)  # 2 s of recording at 4x: ~0.5 s
        elapsed = time.monotonic() - t0
        assert 0.45 < elapsed < 3.0  # never ahead of the clock; generous when CPUs are busy
        replayer.pause()
        wait_for(lambda: replayer.state == ReplayState.PAUSED)
        n = len(sink.results)
        time.sleep(0.3)
        assert len(sink.results) == n  # paused means paused
        replayer.set_speed(20.0)
        t1 = time.monotonic()
        replayer.play()
        wait_for(lambda: replayer.state == ReplayState.ENDED)
        remaining = (rec.frame_times[-1] - sink.results[n - 1].t) / 20.0
        assert remaining - 0.05 < time.monotonic() - t1 < remaining + 2.0
    finally:
        replayer.stop()


def test_engine_failure_is_reported_and_play_restarts(rec: Recording):
    class Failing(SumEngine):
        def process_frame(self, t, image):
            if self.frames == 5:
                raise FloatingPointError("diverged")
            return super().process_frame(t, image)

    sink = Sink()
    replayer = Replayer(rec, Failing, sink, speed=None)
    replayer.start()
    try:
        wait_for(lambda: replayer.state == ReplayState.ERROR)
        status = replayer.status()
        assert "diverged" in status["error"] and len(sink.results) == 5
        # play restarts: a new engine (no checkpoint yet: from the start) up to where it failed
        assert replayer.play()
        wait_for(lambda: sink.rewinds == [None])
    finally:
        replayer.stop()
    assert replayer.state == ReplayState.STOPPED


def test_any_failure_in_the_thread_ends_in_error_and_the_thread_waits_for_a_restart(
        rec: Recording):
    class Fatal(BaseException):  # not an Exception: only the thread's guard catches it
        pass

    engines: list[SumEngine] = []

    class Dying(SumEngine):
        def __init__(self) -> None:
            super().__init__()
            engines.append(self)

        def process_frame(self, t, image):
            if len(engines) == 1 and self.frames == 5:
                raise Fatal("out of luck")
            return super().process_frame(t, image)

    sink = Sink()
    replayer = Replayer(rec, Dying, sink, speed=None)
    replayer.start()
    try:
        wait_for(lambda: sink.states and sink.states[-1] == ReplayState.ERROR)  # told
        assert replayer.state == ReplayState.ERROR
        assert "out of luck" in replayer.status()["error"]
        assert replayer._thread.is_alive()  # waiting for a restart, not dead
        replayer.seek(float(rec.frame_times[20]))
        wait_for(lambda: replayer.state == ReplayState.ENDED)
        assert len(engines) == 2 and replayer.status()["error"] is None
        assert [r.index for r in sink.results] == list(range(len(rec.frame_times)))
        n = len(sink.results)
        assert not replayer.play()  # at the end: nothing thrown away, the caller must seek
        time.sleep(0.2)
        assert replayer.state == ReplayState.ENDED and len(sink.results) == n
    finally:
        replayer.stop()
    assert not replayer._thread.is_alive()


def test_snapshot_of_the_real_engine_continues_identically(rec: Recording):
    from estimator.pipeline import Fusion, FusionOptions

    engine = Fusion(rec.calibration, rec.nav, FusionOptions())
    messages = sensor_messages(rec)
    for msg in messages:
        dispatch(engine, msg)
        if isinstance(msg, FrameMessage) and msg.index == 30:
            break
    copy = snapshot(engine, shared=(rec, rec.calibration, rec.nav))
    assert copy.calibration is engine.calibration  # inputs shared, state copied
    last_a = last_b = None
    for _, msg in zip(range(300), messages, strict=False):  # ~1.5 s more
        a, b = dispatch(engine, msg), dispatch(copy, msg)
        if a is not None:
            last_a, last_b = a, b
    assert last_a is not None
    # Equal to rounding: numpy's vectorised sums may round differently on a copied array's
    # memory (1e-8 m, 2e-9 rad over the 12 s seen); a copy that missed some state is far off.
    np.testing.assert_allclose(last_a.position_ned, last_b.position_ned, rtol=0, atol=1e-6)
    np.testing.assert_allclose(last_a.euler, last_b.euler, rtol=0, atol=1e-7)
