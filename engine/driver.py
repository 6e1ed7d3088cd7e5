"""The one loop that feeds sensor messages to a fusion engine: the server's replay and live
sessions, the replay report, the tracking evaluation and the campaign all go through
``dispatch``, so a fix in the server's path is what the evaluation measures.

A frame reaches the engine either as an image (``FrameMessage``: the engine runs its VO) or,
when the VO has already been run over the video once (the evaluation fuses the same video many
times with different options), as that VO's output (``VoFrameMessage``). Both end the same way:
the VO output goes to ``process_vo`` and the fused state at the frame time comes back.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from estimator.integrity import FrameCheck, checked_vo
from estimator.records import Calibration, GnssEpoch, NavigationData
from estimator.vo import VisualOdometry, VoOutput
from recordings.format import Recording

from .messages import FrameMessage, GnssMessage, ImuMessage, SensorMessage, sensor_messages


@dataclass(frozen=True)
class VoFrameMessage:
    """A video frame already through the VO: its output (cached by ``run_vo``)."""

    t: float
    index: int
    vo: VoOutput


EngineMessage = SensorMessage | VoFrameMessage


@runtime_checkable
class FusionEngine(Protocol):
    """What the engine path needs from a fusion engine (``estimator.pipeline.Fusion``).

    The returned states are ``estimator.options.FusedState``-like objects: ``time``,
    ``position_ned``, ``llh_deg``, ``velocity_ned``, ``euler``, ``C_body_to_level``,
    ``rate_of_turn`` (and, optionally, its ``rate_of_turn_sigma``), ``omega_body``,
    ``position_cov``, ``position_drift_cov``, ``velocity_cov``, ``attitude_cov`` and ``status``
    (``phase``, ``compass_fixed``, ``satellites``, ``vo_status``, ``scale``,
    ``scale_converged``, ``message``).
    """

    def process_imu(self, t: float, gyro: np.ndarray, accel: np.ndarray) -> None: ...

    def process_gnss(self, t: float, epochs: Sequence[GnssEpoch | None]) -> None: ...

    # An engine may also have ``prepare_frame(image)``, a pure function of the image the
    # frame reader then runs ahead in its thread (``frame_preparer``); its result comes back
    # as ``process_frame(t, image, prepared, following)``, ``following`` the next frame's
    # when the reader has it (else None). Engines without one are never given any.
    def process_frame(self, t: float, image: np.ndarray) -> Any | None: ...

    def process_vo(self, out: VoOutput) -> None: ...

    # An engine may also have ``turn_rates(gyro)``: raw gyro samples' rates of turn (rad/s,
    # bias removed), with which a live session carries the heading it sends to the bridge
    # over the samples the engine has not reached yet (``Fusion.turn_rates``).

    # An engine may also have ``tick(t)``: no message has come until gpst t (a live feed gone
    # quiet), so that it declares the silence (``Fusion.tick``); a live session calls it.

    def state(self, at: float | None = None) -> Any | None: ...

    def structure(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    # The structure window's views with their solved attitudes
    # (``estimator.landmarks.SolvedViews``), None without them: the designated targets are
    # triangulated in them.
    def solved_views(self) -> Any | None: ...

    def timing(self) -> dict: ...

    # The faults the engine raised and cleared (``estimator.integrity.Alert``), in time order.
    def alerts(self) -> list: ...

    # The faults active now, each with its current words (a count that goes on, an age).
    def active_alerts(self) -> list: ...


# (calibration, nav, options as a dict of FusionOptions fields) -> engine
EngineFactory = Callable[[Calibration, NavigationData, dict[str, Any]], FusionEngine]


def create_engine(calibration: Calibration, nav: NavigationData,
                  options: dict[str, Any]) -> FusionEngine:
    """The real estimator (``estimator.pipeline.Fusion``) with ``FusionOptions(**options)``."""
    from estimator.pipeline import Fusion, FusionOptions

    return Fusion(calibration, nav, FusionOptions(**options))


def is_frame(msg: EngineMessage) -> bool:
    return isinstance(msg, FrameMessage | VoFrameMessage)


def dispatch(engine: FusionEngine, msg: EngineMessage) -> Any | None:
    """Feed one message to the engine; the fused state at a frame's time, else None."""
    if isinstance(msg, ImuMessage):
        engine.process_imu(msg.t, msg.gyro, msg.accel)
        return None
    if isinstance(msg, GnssMessage):
        engine.process_gnss(msg.t, list(msg.epochs))
        return None
    if isinstance(msg, VoFrameMessage):
        engine.process_vo(msg.vo)
        return engine.state(at=msg.t)
    if msg.prepared is not None:
        return engine.process_frame(msg.t, msg.image, msg.prepared, msg.following)
    return engine.process_frame(msg.t, msg.image)


def frame_preparer(engine: FusionEngine) -> Callable[[np.ndarray], Any] | None:
    """The engine's ``prepare_frame``, for the frame reader to run ahead (None if it has
    none)."""
    return getattr(engine, "prepare_frame", None)


def recording_messages(rec: Recording, until: float | None = None,
                       vo: Sequence[VoOutput] | None = None) -> Iterator[EngineMessage]:
    """The recording's messages in time order up to gpst ``until`` (all when None); with
    ``vo`` (the VO's outputs of frames 0, 1, …, from ``run_vo``) the frames come as
    ``VoFrameMessage`` without decoding the video."""
    if vo is None:
        return sensor_messages(rec, until=until)
    kept = [o for o in vo if until is None or o.time <= until]
    return _with_vo_frames(sensor_messages(rec, until=until, frames=False), kept)


def _with_vo_frames(messages: Iterable[SensorMessage], vo: Sequence[VoOutput]
                    ) -> Iterator[EngineMessage]:
    """Merge cached VO outputs as frames into the (frame-less) messages, IMU and GNSS first
    at equal times."""
    frames = iter(VoFrameMessage(float(o.time), k, o) for k, o in enumerate(vo))
    frame = next(frames, None)
    for msg in messages:
        while frame is not None and frame.t < msg.t:
            yield frame
            frame = next(frames, None)
        yield msg
    while frame is not None:
        yield frame
        frame = next(frames, None)


@dataclass
class VoPass:
    """The VO run once over a recording's video (``run_vo``)."""

    outputs: list[VoOutput]
    vo_ms: float  # per frame
    decode_ms: float  # per frame


def run_vo(rec: Recording, until: float | None = None) -> VoPass:
    """The engine's VO (the one ``Fusion.process_frame`` runs) over the video up to gpst
    ``until``: its outputs frame by frame and its cost."""
    vo = VisualOdometry(rec.calibration.camera)
    check = FrameCheck()
    outputs: list[VoOutput] = []
    t_vo = t_dec = 0.0
    tic = time.perf_counter()
    for _, t, image, prepared in rec.prepared_frames(0, vo.prepare):
        if until is not None and t > until:
            break
        t1 = time.perf_counter()
        t_dec += t1 - tic
        outputs.append(checked_vo(vo, check, t, image, prepared))
        tic = time.perf_counter()
        t_vo += tic - t1
    n = max(len(outputs), 1)
    return VoPass(outputs, 1e3 * t_vo / n, 1e3 * t_dec / n)
