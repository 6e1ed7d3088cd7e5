"""Replay sessions: a session replays one recording through a fusion engine
(``replay.Replayer``) and keeps what the API and the stream serve: the history of fused states
(``history``), the latest port structure, the designated targets (``targets``), the berth line
(``berth``) and the clients watching. Several clients may watch one session; each gets the
newest frame only (``stream.LatestSlot``).

Threads: the replay thread calls the ``FrameSink`` methods below; the API reads under
``Session.lock``. Frame messages for the stream (overlay JSON + JPEG) are built once per frame
in the replay thread and only while somebody watches.
"""

from __future__ import annotations

import copy
import ctypes
import itertools
import json
import logging
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from engine.camera import Projector
from engine.driver import EngineFactory, FusionEngine
from engine.targets import Structure
from estimator.integrity import IntegrityConfig
from estimator.prediction import predict_outlines
from estimator.tracking import TargetParams
from recordings.format import Recording, RecordingError

from .alarms import AlarmBook
from .berth import Berth
from .catalog import RecordingCatalog
from .errors import Conflict, NotFound, TooMany, Unprocessable
from .history import FRAME_MATCH_S, History, is_current
from .overlay import OverlayConfig, build_overlay, pose_dict, status_dict
from .replay import FrameResult, Replayer, ReplayState, Scout, ScoutPool
from .targets import Target, TargetBook

log = logging.getLogger(__name__)

JPEG_QUALITY = 80
# The stream's picture is halved until it is at most this wide: a bridge screen shows the video
# in part of its width, the browser scales the picture to the camera's size (header width and
# height, in which the overlay is drawn), and a 1920×1200 JPEG costs four times a 960×600 one.
STREAM_MAX_WIDTH = 1280
FRAME_BUFFER = 30  # recent frames kept (3 s): a click on a frame just shown, catch-up
STRUCTURE_EVERY = 10  # frames between structure snapshots while not shown (a seek)
NO_PICTURE = np.zeros((0, 0, 3), np.uint8)  # what a listener gets between frames (on_tick)



def stream_picture(image: np.ndarray) -> np.ndarray:
    """The frame as streamed: halved (2×2 block means) until at most ``STREAM_MAX_WIDTH``."""
    while image.shape[1] > STREAM_MAX_WIDTH:
        image = cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2),
                           interpolation=cv2.INTER_AREA)
    return image

class Subscriber(Protocol):
    """A watching client (see ``stream.LatestSlot``); ``offer`` is called from any thread."""

    def offer(self, header: bytes, jpeg: bytes | None) -> None: ...

    def end(self, reason: str) -> None: ...


@dataclass(frozen=True)
class WaterLevel:
    down_m: float  # the water plane's down coordinate in the engine's (world) frame
    source: str
    known: bool = True  # False: a placeholder (no installation constant, no request)


def water_level(rec: Recording, body_height_m: float | None) -> WaterLevel:
    """Where the water is in the engine's frame, whose origin is the body origin (IMU) at the
    start (``estimator.pipeline``): ``body_height_m`` below it, from the request or else the
    installation constant ``hull.json → body_origin_height_m``. Never from the reference: the
    display must not depend on scoring data."""
    if body_height_m is not None:
        return WaterLevel(float(body_height_m), "request")
    if rec.hull.body_origin_height_m is not None:
        return WaterLevel(float(rec.hull.body_origin_height_m), "hull.json")
    return WaterLevel(0.0, "unknown: set body_origin_height_m in hull.json or body_height_m",
                      known=False)


class Session:
    """One replay of one recording, watched by any number of clients."""

    def __init__(self, session_id: str, name: str, rec: Recording,
                 engine_factory: EngineFactory, options: dict[str, Any],
                 speed: float | None, prediction_seconds: int = 5,
                 checkpoint_interval_s: float | None = 10.0,
                 body_height_m: float | None = None,
                 integrity: IntegrityConfig | None = None,
                 runner: Callable[[Callable[[], FusionEngine], Session], Any] | None = None,
                 scouts: ScoutPool | None = None) -> None:
        """``runner``: what feeds the engine instead of a ``Replayer`` of ``rec`` (a live
        source: ``backend.live_session``), made from the engine factory and the session.
        ``scouts``: where the look-ahead engine is shared from (else the replay has its own;
        none when checkpoints are off)."""
        self.id = session_id
        self.name = name
        self.rec = rec
        self.options = options
        self.prediction_seconds = prediction_seconds
        self.created = time.time()
        self.lock = threading.RLock()
        self.projector = Projector(rec.calibration.camera)
        self.water, make_engine, scout_key = engine_setup(rec, engine_factory, options,
                                                          integrity, body_height_m)
        self.overlay_config = OverlayConfig(prediction_seconds=prediction_seconds,
                                            water_down_m=self.water.down_m)
        self.history = History(rec, self.lock)
        self.start_gpst = self.history.start_gpst
        self.targets = TargetBook(rec, self.projector, self.lock)
        self.berth = Berth(rec, self.projector, self.water.down_m if self.water.known else None,
                           self.history.origin_in_recording, self.lock)
        self.alarms = AlarmBook(self.start_gpst)
        self._structure = Structure(None)
        self._frames: deque[tuple[int, float, np.ndarray]] = deque(maxlen=FRAME_BUFFER)
        self._subscribers: set[Subscriber] = set()
        # When the last client left (monotonic s); None while watched. A session nobody has
        # watched for a while (a browser that crashed) may be reclaimed by the manager.
        self.unwatched_since: float | None = time.monotonic()
        # Called once the last client has gone: the page that opened the session asked for
        # it to go with its watchers (``SessionManager.delete_when_unwatched``).
        self.on_unwatched: Callable[[], None] | None = None
        # The last frame played to clients (or that would have been, unwatched): what a client
        # joining now must see, even while paused.
        self._current_frame: tuple[FrameResult, Any | None, Any | None] | None = None
        # the engine's status while it has no state (initialising: why, in its own words)
        self._bare_status: Any | None = None
        self._last_state: Any | None = None  # the fusion's latest, current or not: its status
        self._timing: dict[str, Any] = {}
        self.frame_listeners: list[Callable[[Session, FrameResult], None]] = []
        self.closers: list[Callable[[], None]] = []  # called when the session closes
        self.live = runner is not None
        shared = engine_inputs(rec)
        scout: bool | Scout = checkpoint_interval_s is not None
        if scout and scouts is not None:
            scout = scouts.get(scout_key, lambda: Scout(rec, make_engine, shared))
        self.replayer = runner(make_engine, self) if runner is not None else Replayer(
            rec, make_engine, self, speed=speed, checkpoint_interval_s=checkpoint_interval_s,
            shared=shared, scout=scout)

    @property
    def end_gpst(self) -> float:
        return self.history.end_gpst

    # --------------------------------------------------------------------- life cycle

    def start(self, paused: bool = False) -> None:
        self.replayer.start(paused=paused)

    def close(self) -> None:
        """Stop the replay thread and release what the session holds (the thread's engine,
        checkpoints and decoder go with the thread; here the history, frames, targets and
        the clients)."""
        self.replayer.stop()
        with self.lock:
            subscribers = list(self._subscribers)
            self._subscribers.clear()
            self.frame_listeners.clear()
            self._frames.clear()
            self._current_frame = None
            self._structure = Structure(None)
            self.history.rewind(None)
            self.targets.clear()
        for sub in subscribers:
            sub.end("the session was deleted")
        for close in self.closers:
            try:
                close()
            except Exception:
                log.exception("closing what followed the session failed")
        self.closers.clear()

    def live_status(self) -> dict[str, Any] | None:
        """Inputs and recording of a live session (None for a replay)."""
        return self.replayer.live_status() if self.live else None

    # ------------------------------------------------------------------ FrameSink (replay)

    def on_frame(self, result: FrameResult, engine: FusionEngine) -> None:
        structure = None
        alerts = _engine_alerts(engine)
        if result.live or result.index % STRUCTURE_EVERY == 0:
            try:
                structure = Structure.of(engine, result.t)
                self._timing = dict(engine.timing())
            except Exception:  # the structure is a by-product: never stop the replay for it
                log.exception("engine.structure(), solved_views() or timing() failed")
        state, pose = self._fused(result.state, result.t)
        bare = _engine_status(engine) if state is None else None
        with self.lock:
            self._bare_status = bare
            if structure is not None:
                self._structure = structure
            self._frames.append((result.index, result.t, result.image))
            self._take(result.t, state, pose, *alerts)
            if pose is not None:
                self.targets.on_frame(pose, result.index, result.image, self._structure)
            watched = bool(self._subscribers)
            listeners = list(self.frame_listeners)
            if result.live:
                self._current_frame = (result, state, pose)
        if result.live and watched:
            try:
                self._publish(self._frame_message(result, state, pose))
            except Exception:  # a bad overlay must not stop the replay: log, send none
                log.exception("frame message of frame %d failed", result.index)
        self._tell(listeners, result)

    def on_tick(self, t: float, state: Any, engine: FusionEngine) -> None:
        """The fusion's state at gpst ``t`` between frames (a live camera silent while the
        other sensors go on): the pose, the alarms, the berth figures and the frame listeners
        (the bridge's heading, the 3-D view's track: they read the state, not the picture)
        go on from it, and the page gets its last picture again with it (``picture_t``:
        nothing drawn on that old picture)."""
        alerts = _engine_alerts(engine)
        state, pose = self._fused(state, t)
        with self.lock:
            self._take(t, state, pose, *alerts)
            listeners = list(self.frame_listeners)
            shown = self._current_frame
            watched = bool(self._subscribers)
        if watched and shown is not None:
            last = shown[0]
            try:
                self._publish(self._frame_message(
                    FrameResult(last.index, t, last.image, state, True, time.time()), state,
                    pose, picture_t=last.t))
            except Exception:
                log.exception("frame message between frames failed")
        self._tell(listeners, FrameResult(-1, t, NO_PICTURE, state, True, time.time()))

    @staticmethod
    def _fused(state: Any | None, t: float) -> tuple[Any | None, Any | None]:
        """The engine's state at gpst ``t`` (a copy: the engine goes on) and the same as the
        pose there, or None: a state left behind (no IMU since) says why in its status; it
        is no pose of ``t`` — no overlay, berth figures, trajectory row or target view."""
        state = copy.deepcopy(state) if state is not None else None
        return state, state if is_current(state, t) else None

    def _take(self, t: float, state: Any | None, pose: Any | None, alerts: list[Any],
              active: list[Any]) -> None:
        """The alarms and the trajectory from a state at gpst ``t`` (lock held); ``alerts``,
        ``active``: the engine's alert history and its active alerts (``_engine_alerts``)."""
        if state is not None:
            self._last_state = state
            self.alarms.update(state, alerts, self.berth.metrics(pose), active)
        if pose is not None:
            self.history.append(t, pose)

    def _tell(self, listeners: list[Callable[[Session, FrameResult], None]],
              result: FrameResult) -> None:
        for listener in listeners:
            try:
                listener(self, result)
            except Exception:
                log.exception("frame listener failed")

    def on_rewind(self, t: float | None) -> None:
        with self.lock:
            self._last_state = None
            self.history.rewind(t)
            self.targets.rewind(t)
            self.alarms.rewind()
            self._frames.clear()

    def on_history(self, states: list[tuple[float, Any]]) -> None:
        for t, state in states:  # the scout's own copies: nobody else holds them
            self.history.append(t, state)

    def on_state(self, state: ReplayState) -> None:
        header = json.dumps({"type": "status", "session": self.status_brief()})
        self._publish((header.encode(), None))

    # ---------------------------------------------------------------------- stream

    def subscribe(self, subscriber: Subscriber) -> None:
        with self.lock:
            self._subscribers.add(subscriber)
            self.unwatched_since = None
            current = self._current_frame
        subscriber.offer(json.dumps({"type": "status",
                                     "session": self.status_brief()}).encode(), None)
        if current is not None:  # a new client sees the current frame at once (even paused)
            try:
                subscriber.offer(*self._frame_message(*current))
            except Exception:
                log.exception("frame message for a new client failed")

    def unsubscribe(self, subscriber: Subscriber) -> None:
        with self.lock:
            self._subscribers.discard(subscriber)
            gone = not self._subscribers and not self.live  # the ship's session stays
            if gone:
                self.unwatched_since = time.monotonic()
            then = self.on_unwatched if gone else None
        if then is not None:  # off the caller's thread: the stream's event loop must not
            # wait for the replay to stop
            threading.Thread(target=then, name=f"delete-{self.id}", daemon=True).start()

    def watched(self) -> bool:
        with self.lock:
            return bool(self._subscribers)

    def redraw_if_paused(self) -> None:
        """While paused no frame flows: re-send the frame on screen so that a new target or
        berth line shows at once."""
        if self.replayer.state is not ReplayState.PAUSED:
            return
        with self.lock:
            current = self._current_frame if self._subscribers else None
        if current is None:
            return
        try:
            self._publish(self._frame_message(*current))
        except Exception:  # a redraw is a courtesy: never fail the request for it
            log.exception("redraw of the paused frame failed")

    def _publish(self, message: tuple[bytes, bytes | None]) -> None:
        with self.lock:
            subscribers = list(self._subscribers)
        for sub in subscribers:
            sub.offer(*message)

    def _frame_message(self, result: FrameResult, state: Any | None, pose: Any | None,
                       picture_t: float | None = None) -> tuple[bytes, bytes]:
        """Header JSON (without its closing brace: the sender appends its send time) and the
        JPEG of one frame: the fusion's ``state`` says its status, ``pose`` (the state when it
        is current at the frame, else None) what is drawn. ``picture_t``: the gpst of the
        picture when it is an older one than ``result.t`` (a live camera silent; a frozen one
        repeating it, ``FusionStatus.picture_since``): nothing is drawn on it, and the header
        says how old it is."""
        if picture_t is None and state is not None:
            picture_t = getattr(state.status, "picture_since", None)
        ok, jpeg = cv2.imencode(".jpg", stream_picture(result.image),
                                [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise RuntimeError(f"JPEG encoding of frame {result.index} failed")
        with self.lock:
            s = self._structure
            structure = (s.points, s.sigma, s.ids)
            targets = self.targets.inputs()
            berth = self.berth.world(pose)
            berth_line = self.berth.line
            replay = self.replayer.status()
        header: dict[str, Any] = {
            "type": "frame",
            "session": self.id,
            "frame": result.index,
            "t": round(result.t - self.start_gpst, 6),
            "gpst": result.t,
            "width": self.projector.width,
            "height": self.projector.height,
            "jpeg_bytes": len(jpeg),
            "replay": {"state": replay["state"], "speed": replay["speed"],
                       "lag_s": round(replay["lag_s"], 3),
                       "behind_s": round(replay["behind_s"], 3),
                       "achieved_speed": None if replay["achieved_speed"] is None
                       else round(replay["achieved_speed"], 3),
                       "scouted_s": None if replay.get("scouted_gpst") is None
                       else round(replay["scouted_gpst"] - self.start_gpst, 3)},
            "processed_at": result.processed_wall,
            "alarms": self.alarms.active(),
            "live": _live_brief(self.live_status()),
        }
        status = state.status if state is not None else self._bare_status
        header["status"] = None if status is None else status_dict(status)
        if pose is None:
            header.update(pose=None, overlay=None)
        else:
            header["pose"] = pose_dict(pose, self.start_gpst)
            header["overlay"] = build_overlay(
                pose, self.rec.calibration.camera, self.rec.hull, self.projector, structure,
                targets, berth, self.overlay_config,
                (None, None) if berth_line is None else (berth_line.sigma_m,
                                                         berth_line.sigma_deg),
                None if berth_line is None else berth_line.drift_since(pose))
            readout = header["overlay"]["berth"]
            if readout is not None and berth_line is not None:
                readout.update(berth_line.describe())
            with self.lock:
                self.targets.readouts(header["overlay"]["targets"])
            if picture_t is not None:
                _off_the_picture(header["overlay"])
        header["picture_t"] = None if picture_t is None else round(picture_t - self.start_gpst, 6)
        text = json.dumps(header, separators=(",", ":"), allow_nan=False)
        return text[:-1].encode(), jpeg.tobytes()

    # ------------------------------------------------------------------------ control

    def control(self, action: str, t: float | None = None, speed: float | None | str = None
                ) -> None:
        if action == "play":
            if not self.replayer.play():
                raise Conflict("the replay is at the end of the recording; to play it again "
                               "seek first (e.g. {\"action\": \"seek\", \"time\": 0}): the "
                               "fused history after the seek target is then recomputed")
        elif action == "pause":
            self.replayer.pause()
        elif action == "seek":
            if t is None:
                raise Unprocessable("action 'seek' needs 'time' (seconds from the recording "
                                    "start)")
            self.replayer.seek(self.history.gpst(t))
        elif action == "speed":
            if speed is None:
                raise Unprocessable("action 'speed' needs 'speed' (a positive factor or 'max')")
            self.replayer.set_speed(None if speed == "max" else float(speed))
            # no state changes: the screens watching are told (each shows the speed it runs at)
            self.on_state(self.replayer.state)
        else:
            raise Unprocessable(f"unknown action {action!r}")

    # ---------------------------------------------------------------------- queries

    def status_brief(self) -> dict[str, Any]:
        replay = self.replayer.status()
        with self.lock:
            # the latest status the fusion gave, also when it had no pose for its frame
            latest = self._last_state or self.history.latest()
            status = latest.status if latest is not None else self._bare_status
            fused = None if status is None else status_dict(status)
            clients = len(self._subscribers)
        target = replay["seek_target_gpst"]
        return {
            "id": self.id,
            "recording": self.name,
            "state": replay["state"],
            "time_s": round(replay["time_gpst"] - self.start_gpst, 6),
            "duration_s": round(self.end_gpst - self.start_gpst, 6),
            "speed": replay["speed"] if replay["speed"] is not None else "max",
            "playing": replay["playing"],
            "seek_target_s": None if target is None else round(target - self.start_gpst, 6),
            "lag_s": round(replay["lag_s"], 4),
            "behind_s": round(replay["behind_s"], 3),
            "achieved_speed": None if (a := replay["achieved_speed"]) is None else round(a, 3),
            "frames_processed": replay["frames_processed"],
            "frames_total": len(self.rec.frame_times),
            "clients": clients,
            "error": replay["error"],
            "fusion": fused,
            "timing_ms": {k: round(float(v), 3) for k, v in self.timing().items()},
            "checkpoints_s": [round(c - self.start_gpst, 3) for c in replay["checkpoints"]],
            # a look-ahead engine that failed is said here (seeks are then slower, no more)
            "checkpoint_note": replay["checkpoint_note"] or replay.get("scout_error"),
            "scouted_s": None if replay.get("scouted_gpst") is None
            else round(replay["scouted_gpst"] - self.start_gpst, 3),
            "prediction_seconds": self.prediction_seconds,
            "options": self.options,
            "has_reference": self.rec.reference is not None,
            "water_level": {"down_m": self.water.down_m, "source": self.water.source},
            "created_at": self.created,
            "live": self.live_status(),
        }

    def timing(self) -> dict[str, Any]:
        with self.lock:
            return dict(self._timing)

    def current_state(self) -> Any:
        """The fused pose now: 409 while there is none (initialising, or the fusion's last
        state is behind the frame on screen: no IMU since)."""
        with self.lock:
            _result, shown, pose = self._current_frame or (None, None, None)
        if shown is not None and pose is None:  # a state, but not a pose of the frame shown
            ig = getattr(shown.status, "integrity", None)
            why = ig.reasons[0] if ig is not None and ig.reasons else \
                "the fusion's last state is behind the video"
            raise Conflict(f"no current pose: {why} (the last fused pose is at "
                           f"{float(shown.time) - self.start_gpst:.3f} s)")
        state = self.history.latest()
        if state is None:
            raise Conflict("no fused pose yet: the engine is still initialising "
                           f"(session state {self.replayer.state.value})")
        return state

    def structure(self) -> Structure:
        with self.lock:
            return self._structure

    def prediction(self, seconds: int) -> tuple[Any, list[np.ndarray]]:
        state = self.current_state()
        return state, predict_outlines(state, self.rec.hull, seconds)

    def report(self, after_s: float = 0.0) -> dict[str, Any]:
        return {"session": self.id, **self.history.report(self.name, after_s)}

    # ---------------------------------------------------------------------- targets

    def designate(self, frame_t: float | None, u: float, v: float, label: str | None
                  ) -> Target:
        """A designated target at pixel (u, v) of the frame at ``frame_t`` (None: the
        current one), tracked from there on (``targets.TargetBook.designate``). Not while
        seeking: the frame on screen is then one the replay is leaving (a user trial's click
        during a seek was designated on the 22.9 s frame at 74.2 s, 10 m off)."""
        if self.replayer.state is ReplayState.SEEKING:
            raise Conflict("the replay is seeking: designate on the frame it stops at")
        state = self.current_state() if frame_t is None else self.history.frame_state(frame_t)
        index = self._frame_index(float(state.time))
        picture_t = float(np.asarray(self.rec.frame_times, dtype=float)[index])
        if abs(picture_t - float(state.time)) > FRAME_MATCH_S:
            # a live camera silent while the other sensors go on (``on_tick``): the pose has
            # moved on from the last picture, and a click on it is no click on the present
            raise Conflict(f"no picture at {float(state.time) - self.start_gpst:.1f} s: the "
                           f"camera's last frame is from {picture_t - self.start_gpst:.1f} s")
        frozen = getattr(state.status, "picture_since", None)
        if frozen is not None:  # the picture is an older one again: the same
            raise Conflict(f"the camera is frozen at {float(state.time) - self.start_gpst:.1f} "
                           f"s: its picture is the one of {frozen - self.start_gpst:.1f} s")
        with self.lock:
            buffered = list(self._frames)
            structure = self._structure
        image = next((img for i, _t, img in buffered if i == index), None)
        if image is None:
            image = self.rec.read_frame(index)
        later = [(f, st) for f in buffered if f[0] > index
                 and (st := self.history.at_gpst(f[1])) is not None]
        target = self.targets.designate(state, self.current_state(), u, v, label, structure,
                                        self.water.down_m if self.water.known else None,
                                        lambda: self._earlier_frames(index), image, later)
        self.redraw_if_paused()
        return target

    def delete_target(self, target_id: str) -> None:
        self.targets.delete(target_id)
        self.redraw_if_paused()

    def _frame_index(self, t: float) -> int:
        times = np.asarray(self.rec.frame_times, dtype=float)
        return int(np.argmin(np.abs(times - t)))

    def _earlier_frames(self, index: int) -> list[tuple[float, np.ndarray]]:
        """(time, gray image) of the frames before frame ``index`` that a designated target
        tracks back through (``TargetParams.track_back_s``), from the recording; none when
        they cannot be read (the target then starts from the click alone)."""
        times = self.rec.frame_times
        start = int(np.searchsorted(times, times[index] - TargetParams.track_back_s))
        out = []
        try:
            for _i, t, img in itertools.islice(self.rec.frames(start), index - start):
                out.append((float(t), cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)))
        except (RecordingError, OSError, cv2.error) as exc:
            log.warning("frames before frame %d unreadable (%s): no track back", index, exc)
            return []
        return out

    # -------------------------------------------------------------------- berth line

    def set_berth_line_ned(self, line_ne: np.ndarray, snap: bool = False) -> None:
        """Two plan points; with ``snap`` fitted to the quay face's points near them."""
        self.berth.set_ned(line_ne, snap, self.structure(), self.history.latest())
        self.redraw_if_paused()

    def set_berth_line_image(self, frame_t: float | None, points_uv: np.ndarray) -> None:
        """Berth line from two clicks on the quay of a frame (``berth.Berth.set_image``)."""
        state = self.current_state() if frame_t is None else self.history.frame_state(frame_t)
        self.berth.set_image(state, points_uv, self.structure())
        self.redraw_if_paused()

    def set_berth_line_from_bow(self, distance_m: float, bearing_deg: float) -> None:
        self.berth.set_from_bow(self.current_state(), distance_m, bearing_deg)
        self.redraw_if_paused()

    def nudge_berth_line(self, offset_m: float, rotate_deg: float) -> None:
        self.berth.nudge(self.history.latest(), offset_m, rotate_deg)
        self.redraw_if_paused()

    def berth_status(self) -> dict[str, Any]:
        if self.berth.line is None:
            raise NotFound("this session has no berth line: PUT one (from two clicks on the "
                           "quay in a frame, two plan points, or typed in from the bow)")
        try:
            state = self.current_state()
        except Conflict:  # the line without figures: none would be current
            state = None
        return self.berth.status(state, self.start_gpst, placed_by=self.history.latest())

    def clear_berth_line(self) -> None:
        self.berth.clear()
        self.redraw_if_paused()


def _live_brief(live: dict[str, Any] | None) -> dict[str, Any] | None:
    """What every frame of a live session carries: the record indicator and the inputs that
    are not streaming."""
    if live is None:
        return None
    rec = live["recording"]
    return {"recording": bool(rec and rec["recording"]),
            "record_s": None if not rec else rec["duration_s"],
            "inputs_down": [h["name"] for h in live["inputs"] if h["state"] != "streaming"]}


# ----------------------------------------------------------------------------- manager


def engine_inputs(rec: Recording) -> tuple[Any, ...]:
    """What an engine reads but never changes: its copies (checkpoints, the scout's) share
    these instead of copying them."""
    return rec, rec.calibration, rec.nav


def engine_setup(rec: Recording, engine_factory: EngineFactory, options: dict[str, Any],
                 integrity: IntegrityConfig | None, body_height_m: float | None
                 ) -> tuple[WaterLevel, Callable[[], FusionEngine], str]:
    """The water level of a session, how its engine is made, and the key of that engine
    (sessions with the same key compute the same states: they may share a scout)."""
    water = water_level(rec, body_height_m)
    engine_options = dict(options)
    if integrity is not None:
        engine_options["integrity"] = integrity
    # A step of the gyro's rate of turn beyond what the hull turns is the gyro's.
    engine_options.setdefault("hull_length_m", float(rec.hull.length))
    if water.known:
        # The landmark refinement drops points on or below the water (reflections).
        engine_options.setdefault("body_origin_height_m", water.down_m)
        if rec.hull.sea_surface is not None:
            # ... and the sea surface's height pins the height of the world origin.
            engine_options.setdefault("sea_surface", rec.hull.sea_surface)
    key = json.dumps([str(rec.path), id(engine_factory), engine_options],
                     sort_keys=True, default=repr)
    return water, lambda: engine_factory(rec.calibration, rec.nav, dict(engine_options)), key


class SessionManager:
    """Creates, finds and closes sessions (bounded: each one is a CPU-bound thread).

    The limit is atomic: a slot is reserved under the lock before the (slow) recording load
    and session construction, and given back if they fail, so concurrent creates never pass
    it. A session leaves the registry under the lock before it is closed, so it is deleted
    (or reclaimed) exactly once."""

    def __init__(self, catalog: RecordingCatalog, engine_factory: EngineFactory,
                 max_sessions: int = 4, checkpoint_interval_s: float | None = 10.0,
                 abandoned_after_s: float = 120.0,
                 integrity: IntegrityConfig | None = None) -> None:
        self.catalog = catalog
        self.integrity = integrity  # alert limits of every session (None: the engine's own)
        self.engine_factory = engine_factory
        self.max_sessions = max_sessions
        self.abandoned_after_s = abandoned_after_s
        self.checkpoint_interval_s = checkpoint_interval_s
        self._sessions: dict[str, Session] = {}
        # look-ahead engines shared by the sessions of one recording (none: checkpoints off)
        self.scouts = ScoutPool() if checkpoint_interval_s is not None else None
        self._reserved = 0  # slots taken by creations under way
        self._lock = threading.Lock()
        self.created_listeners: list[Callable[[Session], None]] = []
        self.closed_listeners: list[Callable[[Session], None]] = []

    def create(self, recording: str, speed: float | None, options: dict[str, Any],
               paused: bool = False, prediction_seconds: int = 5,
               body_height_m: float | None = None) -> Session:
        with self._lock:
            reclaimed = None
            if len(self._sessions) + self._reserved >= self.max_sessions:
                reclaimed = self._take_abandoned()
                if reclaimed is None:
                    raise TooMany(f"{len(self._sessions) + self._reserved} sessions are open "
                                  f"(the limit is {self.max_sessions}) and all were watched "
                                  f"within the last {self.abandoned_after_s:g} s; delete one "
                                  "first")
            self._reserved += 1
        session: Session | None = None
        try:
            if reclaimed is not None:
                self._close(reclaimed)
            rec = self.catalog.load(recording)
            session = Session(uuid.uuid4().hex[:12], recording, rec, self.engine_factory,
                              options, speed, prediction_seconds, self.checkpoint_interval_s,
                              body_height_m, self.integrity, scouts=self.scouts)
        finally:
            with self._lock:
                self._reserved -= 1
                if session is not None:
                    self._sessions[session.id] = session
        try:
            for listener in self.created_listeners:
                listener(session)
            session.start(paused=paused)
        except BaseException:
            self.delete(session.id)
            raise
        return session

    def add(self, rec: Recording, name: str, runner: Callable[..., Any],
            options: dict[str, Any], prediction_seconds: int = 10,
            integrity: IntegrityConfig | None = None) -> Session:
        """Register and start a session fed by ``runner`` (a live one), outside the limit:
        it is the ship's own and is never reclaimed."""
        session = Session(uuid.uuid4().hex[:12], name, rec, self.engine_factory, options,
                          1.0, prediction_seconds, None, None, integrity or self.integrity,
                          runner=runner)
        session.unwatched_since = None  # never reclaimed as abandoned
        with self._lock:
            self._sessions[session.id] = session
        for listener in self.created_listeners:
            listener(session)
        session.start()
        return session

    def _take_abandoned(self) -> Session | None:
        """The session unwatched the longest, if longer than ``abandoned_after_s``, taken out
        of the registry (lock held); the caller closes it."""
        now = time.monotonic()
        idle = [(now - s.unwatched_since, s.id) for s in self._sessions.values()
                if s.unwatched_since is not None]
        if not idle or max(idle)[0] < self.abandoned_after_s:
            return None
        seconds, victim = max(idle)
        log.info("reclaiming session %s, unwatched for %.0f s", victim, seconds)
        return self._sessions.pop(victim)

    def get(self, session_id: str) -> Session:
        with self._lock:
            session = self._sessions.get(session_id)
        if session is None:  # never list the others: their ids are what controls them
            raise NotFound(f"no session {session_id!r} (deleted, reclaimed or never created)")
        return session

    def all(self) -> list[Session]:
        with self._lock:
            return list(self._sessions.values())

    def delete(self, session_id: str) -> None:
        with self._lock:
            session = self._sessions.pop(session_id, None)
        if session is None:
            raise NotFound(f"no session {session_id!r} (deleted, reclaimed or never created)")
        self._close(session)

    def delete_when_unwatched(self, session_id: str) -> bool:
        """Delete the session now if no client watches it (True), else once the last one has
        gone: a page closing (or reloading) must not take a session another tab joined —
        and the targets locked in it — with it."""
        session = self.get(session_id)
        if session.live:
            return False  # the ship's session stays
        session.on_unwatched = lambda: self._delete_quietly(session_id)
        if session.watched():
            return False
        self._delete_quietly(session_id)
        return True

    def _delete_quietly(self, session_id: str) -> None:
        try:
            self.delete(session_id)
        except NotFound:
            pass  # deleted meanwhile

    def _close(self, session: Session) -> None:
        session.close()
        for listener in self.closed_listeners:
            try:
                listener(session)
            except Exception:  # a listener (the 3-D view) must not keep a session alive
                log.exception("closed listener failed for session %s", session.id)
        _return_freed_memory()

    def warm(self, recording: str, options: dict[str, Any]) -> None:
        """Start the look-ahead engine of ``recording`` with ``options`` now, before anyone
        opens it: the first page's seeks are then quick too."""
        if self.scouts is None:
            return
        rec = self.catalog.load(recording)
        _water, make_engine, key = engine_setup(rec, self.engine_factory, options,
                                                self.integrity, None)
        self.scouts.get(key, lambda: Scout(rec, make_engine, engine_inputs(rec)))

    def close_all(self) -> None:
        for session in self.all():
            try:
                self.delete(session.id)
            except NotFound:
                pass
        if self.scouts is not None:
            self.scouts.close()


def _load_malloc_trim() -> Callable[[int], int] | None:
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None


_malloc_trim = _load_malloc_trim()


def _return_freed_memory() -> None:
    """Hand the heap memory a closed session freed back to the system (glibc only).

    Why: glibc keeps freed memory in its arenas. A replay's video frames (1.7 MB each, 30
    buffered per session) come from them once glibc's dynamic mmap threshold has risen, so
    after a session is gone its frames stay counted in the RSS: a high-water mark that steps
    up whenever a session buffered more than any before it, and reads as a leak. The session's
    objects themselves are released (the tests check that a deleted session is freed; the
    Python-traced memory is flat over create/delete cycles, viewer on or off): ``malloc_trim``
    only returns memory that is already free."""
    if _malloc_trim is not None:
        _malloc_trim(0)


def _engine_status(engine: FusionEngine) -> Any | None:
    """The engine's status without a state (``Fusion.status``: initialising, and why; a user
    trial's page said only "no fused position yet" for 25 s after a live restart)."""
    status = getattr(engine, "status", None)
    if not callable(status):
        return None
    try:
        return status()
    except Exception:  # a by-product: never stop the replay for it
        log.exception("engine.status() failed")
        return None


def _engine_alerts(engine: FusionEngine) -> tuple[list[Any], list[Any]]:
    """The engine's alert history and its active alerts with their current words (an engine
    without them: none)."""
    return (list(getattr(engine, "alerts", list)()),
            list(getattr(engine, "active_alerts", list)()))


def _off_the_picture(overlay: dict[str, Any]) -> None:
    """An overlay for an old picture: nothing drawn on it (grid, hull, points, predicted
    outlines, berth line, target marks); the plan and the read-outs stay."""
    video = overlay["video"]
    video["hull"], video["prediction"] = [], []
    video["grid"]["lines"], video["grid"]["nodes"] = [], {"ned": [], "uv": []}
    video["points"] = {key: [] for key in video["points"]}
    if overlay.get("berth") is not None:
        overlay["berth"]["polylines"] = []
    for target in overlay.get("targets") or []:
        target["visible"] = False
