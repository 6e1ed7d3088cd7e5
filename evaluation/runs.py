"""Fusion runs of the evaluation, through the server's own engine path (``engine.driver``).

The VO runs ONCE over the video (``engine.driver.run_vo``); every fusion run replays the IMU
samples, the GNSS epochs and those VO outputs in time order (``recording_messages``) through
``dispatch`` — exactly what a session does with the frames — and records the fused state at
every frame. Should the fusion restart the VO (a world it found wrong, ``VoCoupling``), the
run goes on from that frame with the engine's own VO on the frames, as a session would.
A run may also keep what the tracking and landmark evaluations need: the port
structure after every frame from a given one on (the designated targets are followed on it as
the server follows them), the landmarks' positions as their view counts reach checkpoints, and
the last view of every landmark.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from engine.driver import (
    VoFrameMessage,
    VoPass,
    dispatch,
    frame_preparer,
    is_frame,
    recording_messages,
)
from engine.messages import FrameMessage, GnssMessage, SensorMessage, group_gnss, sensor_messages
from engine.targets import Structure
from estimator.integrity import Alert
from estimator.pipeline import Fusion, FusionOptions
from estimator.vo import VoOutput
from recordings.format import Recording

VIEW_CHECKPOINTS = (1, 2, 3, 5, 10, 20, 50, 100, 200, 400)
STALE_S = 0.15  # a state further than this from its frame's time is no position (no IMU)
TRUTH_STRIDE = 5  # frames between the landmarks' last views kept (their rendered truth)


@dataclass
class FusionRun:
    """One fusion run sampled at the frame times (NaN before the INS starts)."""

    label: str
    time: np.ndarray  # (N,) gpst of the frames
    states: list[Any]  # FusedState per frame (None before the INS starts)
    origin_time: float | None
    wall_s: float
    timing_ms: dict[str, float]
    structure: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # final, refined
    structure_raw: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # final, raw
    converged_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    structures: dict[int, Structure] = field(default_factory=dict)  # frame → after it
    # checkpoint → (ids, reported positions) of the landmarks reaching that many views
    view_history: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    last_views: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)  # id → (k, uv)
    alerts: list[Alert] = field(default_factory=list)  # the engine's faults, raised and cleared
    # The VO output the run used at each frame: the cached pass's, or its own VO's from a
    # restart on (``_own_vo_from``); empty for runs made otherwise.
    vo_outputs: list[Any] = field(default_factory=list)

    def __post_init__(self) -> None:
        n = len(self.time)
        self.position, self.velocity, self.euler = (np.full((n, 3), np.nan) for _ in range(3))
        self.C = np.full((n, 3, 3), np.nan)
        self.scale = np.full(n, np.nan)  # VO scale (m per VO unit), NaN when not tracking
        for k, s in enumerate(self.states):
            if s is None or abs(float(s.time) - self.time[k]) > STALE_S:
                continue  # no position at this frame
            self.position[k], self.velocity[k] = s.position_ned, s.velocity_ned
            self.euler[k], self.C[k] = s.euler, s.C_body_to_level
            if s.status.scale is not None:
                self.scale[k] = s.status.scale


@dataclass
class Collect:
    """What a run keeps beyond the states: structures after every frame from
    ``structures_from`` on, the landmark view history and last views."""

    structures_from: int | None = None
    landmarks: bool = False


def fuse(rec: Recording, vo: VoPass, options: FusionOptions, label: str, until: float,
         collect: Collect | None = None) -> FusionRun:
    """One fusion run of ``rec`` up to gpst ``until`` with the cached VO outputs."""
    collect = collect or Collect()
    engine = Fusion(rec.calibration, rec.nav, options)
    frames = [o for o in vo.outputs if o.time <= until]
    states: list[Any] = [None] * len(frames)
    used_vo: list[VoOutput | None] = [None] * len(frames)
    structures: dict[int, Structure] = {}
    history = _ViewHistory() if collect.landmarks else None
    last_views: dict[int, tuple[int, np.ndarray]] = {}
    tic = time.perf_counter()
    messages = recording_messages(rec, until=until, vo=frames)
    while (msg := next(messages, None)) is not None:
        if isinstance(msg, VoFrameMessage) and engine.vo_restart_due:
            # The fusion restarts the VO (its world was found wrong): the cached outputs are
            # no longer this run's. From this frame on the engine runs its own VO on the
            # frames, restarted as the live engine's would be.
            msg, messages = _own_vo_from(rec, engine, msg, until)
        state = dispatch(engine, msg)
        if not is_frame(msg):
            continue
        k = msg.index
        states[k] = state
        used_vo[k] = engine.last_vo
        if collect.structures_from is not None and k >= collect.structures_from:
            structures[k] = Structure.of(engine, msg.t)
        if history is not None:
            history.add(engine)
            if k % TRUTH_STRIDE == 0 and engine.last_vo is not None:
                for pid, uv in zip(*engine.last_vo.observations, strict=True):
                    last_views[int(pid)] = (k, np.asarray(uv, float))
    run = FusionRun(label, np.array([o.time for o in frames], float), states,
                    engine.origin_time, time.perf_counter() - tic, dict(engine.timing()),
                    structures=structures, last_views=last_views, alerts=engine.alerts(),
                    vo_outputs=used_vo)
    if engine.origin_time is not None:
        run.structure = engine.structure()
        run.structure_raw = engine.structure(refined=False)
        run.converged_ids = engine.converged_ids(run.structure[2])
    if history is not None:
        run.view_history = history.result()
    return run


def _own_vo_from(rec: Recording, engine: Fusion, msg: VoFrameMessage, until: float
                 ) -> tuple[FrameMessage, Iterator[SensorMessage]]:
    """Frame ``msg`` as a real frame, and the recording's messages after it with frames."""
    frame = FrameMessage(msg.t, msg.index, rec.read_frame(msg.index))
    return frame, sensor_messages(rec, after=msg.t, until=until,
                                  prepare=frame_preparer(engine))


class _ViewHistory:
    """The landmarks' reported positions as their view counts reach ``VIEW_CHECKPOINTS``."""

    def __init__(self) -> None:
        self.parts: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {
            c: [] for c in VIEW_CHECKPOINTS}
        self.prev = np.zeros(0, np.int64)

    def add(self, engine: Fusion) -> None:
        ids, views = engine.landmark_views()
        if not len(views):
            return
        prev = np.zeros(len(views), np.int64)
        prev[:len(self.prev)] = self.prev[:len(views)]
        for c in VIEW_CHECKPOINTS:
            hit = np.flatnonzero((prev < c) & (views >= c))
            if len(hit):
                self.parts[c].append((ids[hit], engine.landmark_positions(ids[hit])))
        self.prev = views

    def result(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        return {c: (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]))
                for c, parts in self.parts.items() if parts}


@dataclass
class RunSet:
    """The recording cut to the evaluated span, its VO pass and the fusion runs (by label)."""

    rec: Recording
    start: float  # gpst of the recording start
    end: float  # gpst of the end of the evaluated span
    vo: VoPass
    progress: Callable[[str], None]
    runs: dict[str, FusionRun] = field(default_factory=dict)

    @property
    def duration(self) -> float:
        return self.end - self.start

    @property
    def frame_times(self) -> np.ndarray:
        return np.array([o.time for o in self.vo.outputs], float)

    @cached_property
    def gnss(self) -> list[GnssMessage]:
        """The GNSS epochs of the span, grouped by time tag."""
        return [m for m in group_gnss(self.rec) if m.t <= self.end + 1e-9]

    @cached_property
    def imu(self) -> tuple[np.ndarray, np.ndarray]:
        """(times, raw gyro) of the IMU samples of the span."""
        keep = self.rec.imu.time <= self.end + 1e-9
        return self.rec.imu.time[keep], self.rec.imu.gyro[keep]

    def fuse(self, label: str, options: FusionOptions, collect: Collect | None = None
             ) -> FusionRun:
        """A fusion run with ``options`` (cached by label)."""
        if label not in self.runs:
            run = fuse(self.rec, self.vo, options, label, self.end + 1e-9, collect)
            self.runs[label] = run
            started = "never started" if run.origin_time is None else \
                f"origin at +{run.origin_time - self.start:.1f} s"
            self.progress(f"{label}: {run.wall_s:.1f} s "
                          f"({self.duration / max(run.wall_s, 1e-9):.1f}x real time), {started}")
        return self.runs[label]
