"""Recordings catalogue and replay sessions.

A session replays one recording through a fusion engine (``replay.Replayer``) and keeps what
the API and the stream serve: the history of fused states, the latest port structure, the
designated targets with their tracks, the berth line, and the clients watching. Several
clients may watch one session; each gets the newest frame only (``stream.LatestSlot``).

Threads: the replay thread calls the ``FrameSink`` methods below; the API reads under
``Session.lock``. Frame messages for the stream (overlay JSON + JPEG) are built once per frame
in the replay thread and only while somebody watches.
"""

from __future__ import annotations

import bisect
import copy
import itertools
import json
import logging
import math
import re
import threading
import time
import uuid
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from estimator.frames import ecef_to_ned, geodetic_to_ecef, wrap_angle
from estimator.landmarks import camera_pose_covariance
from estimator.prediction import predict_outlines
from estimator.tracking import (
    DESIGNATION_RADIUS_PX,
    DesignatedTarget,
    TargetParams,
    point_on_ray,
    structure_point_at,
)
from recordings.format import Recording, RecordingError, load, summary

from .engine import EngineFactory, FusionEngine
from .geometry import (
    CameraPose,
    Projector,
    berth_metrics,
    camera_pose,
    hull_outline_ne,
    water_plane_point,
)
from .overlay import (
    OverlayConfig,
    TargetInput,
    build_overlay,
    pose_dict,
    status_dict,
    target_readout,
)
from .replay import FrameResult, Replayer, ReplayState

log = logging.getLogger(__name__)

RECORDING_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
JPEG_QUALITY = 80
FRAME_BUFFER = 30  # recent frames kept (3 s): a click on a frame just shown, catch-up
TARGET_WINDOW_PX = 31  # template side of the image tracker, full-size pixels
FRAME_MATCH_S = 0.06  # a frame_time matches a stored frame within this (frames are 0.1 s apart)
# A target is refreshed on the structure (re-anchored, triangulated in its solved views) this
# often.
TARGET_REFRESH_S = 1.0


# ------------------------------------------------------------------------------- errors


class ApiError(Exception):
    """An error the API reports as-is: HTTP status and a message saying what is wrong."""

    status = 400

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class BadRequest(ApiError):
    status = 400


class NotFound(ApiError):
    status = 404


class Conflict(ApiError):
    status = 409


class Unprocessable(ApiError):
    status = 422


class TooMany(ApiError):
    status = 429


# ---------------------------------------------------------------------------- catalogue


@dataclass(frozen=True)
class RecordingEntry:
    name: str
    path: Path
    default: bool
    manifest: dict[str, Any] | None  # None when manifest.json cannot be read
    problem: str | None


class RecordingCatalog:
    """The recordings the server may open: the sub-directories of ``directory`` that hold a
    ``manifest.json``, plus the default recording. Requests name a recording; only names
    from this listing are ever turned into paths."""

    def __init__(self, directory: Path | None, default: Path | None, cache_size: int = 2) -> None:
        self.directory = directory.resolve() if directory else None
        self.default = default.resolve() if default else None
        self._cache: OrderedDict[Path, Recording] = OrderedDict()
        self._cache_size = cache_size
        self._lock = threading.Lock()
        self._loading: dict[Path, threading.Lock] = {}

    @staticmethod
    def _read_manifest(path: Path) -> tuple[dict[str, Any] | None, str | None]:
        try:
            data = json.loads((path / "manifest.json").read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            return None, f"manifest.json cannot be read: {exc}"
        if not isinstance(data, dict):
            return None, "manifest.json is not a JSON object"
        return data, None

    def entries(self) -> dict[str, RecordingEntry]:
        """Name → entry, rescanned on each call (recordings may be added while running)."""
        found: dict[str, RecordingEntry] = {}
        if self.directory is not None and self.directory.is_dir():
            for child in sorted(self.directory.iterdir()):
                if (child.is_dir() and RECORDING_NAME.match(child.name)
                        and (child / "manifest.json").is_file()):
                    manifest, problem = self._read_manifest(child)
                    found[child.name] = RecordingEntry(child.name, child.resolve(),
                                                       child.resolve() == self.default,
                                                       manifest, problem)
        if self.default is not None and not any(e.default for e in found.values()):
            name = self.default.name
            if name in found or not RECORDING_NAME.match(name):
                name = "default"
            manifest, problem = (self._read_manifest(self.default)
                                 if self.default.is_dir() else (None, "directory not found"))
            found[name] = RecordingEntry(name, self.default, True, manifest, problem)
        return found

    def default_name(self) -> str | None:
        return next((e.name for e in self.entries().values() if e.default), None)

    def resolve(self, name: str) -> RecordingEntry:
        """The entry named ``name``; 400 for a name that is not a plain directory name, 404
        for an unknown one. Nothing from ``name`` reaches the file system."""
        if not isinstance(name, str) or not name:
            raise BadRequest("recording name is empty")
        if "/" in name or "\\" in name:
            raise BadRequest(f"recording name {name!r} contains a path separator; use a name "
                             "from GET /api/recordings")
        if name in (".", "..") or ".." in name:
            raise BadRequest(f"recording name {name!r} contains '..'; use a name from "
                             "GET /api/recordings")
        if not RECORDING_NAME.match(name):
            raise BadRequest(f"recording name {name!r} is not a plain name (letters, digits, "
                             "'.', '_', '-'; at most 128 characters)")
        entries = self.entries()
        if name not in entries:
            known = ", ".join(sorted(entries)) or "none"
            raise NotFound(f"no recording named {name!r} (available: {known})")
        return entries[name]

    def load(self, name: str) -> Recording:
        """The loaded recording (cached, most recently used first)."""
        entry = self.resolve(name)
        with self._lock:
            if entry.path in self._cache:
                self._cache.move_to_end(entry.path)
                return self._cache[entry.path]
            path_lock = self._loading.setdefault(entry.path, threading.Lock())
        with path_lock:  # one load per recording even when requests race
            with self._lock:
                if entry.path in self._cache:
                    return self._cache[entry.path]
            try:
                rec = load(entry.path)
            except RecordingError as exc:
                raise Unprocessable(f"recording {name!r} cannot be read: {exc}") from None
            with self._lock:
                self._cache[entry.path] = rec
                while len(self._cache) > self._cache_size:
                    self._cache.popitem(last=False)
            return rec

    def summary(self, name: str) -> dict[str, Any]:
        info = summary(self.load(name))
        info.pop("path", None)  # the server's file layout is none of the client's business
        return info


# ------------------------------------------------------------------------------ session


class Subscriber(Protocol):
    """A watching client (see ``stream.LatestSlot``); ``offer`` is called from any thread."""

    def offer(self, header: bytes, jpeg: bytes | None) -> None: ...

    def end(self, reason: str) -> None: ...


@dataclass
class Target:
    id: str
    label: str | None
    method: str  # "structure" or "water-plane"
    position_ned: np.ndarray
    designated_gpst: float  # replay time when designated
    frame_gpst: float  # time of the frame whose pixel was clicked
    uv: tuple[float, float]
    anchor_ids: np.ndarray  # structure point ids under the click (empty for water-plane)
    anchor_mean: np.ndarray | None  # their mean position when designated
    support: int
    track: list[dict[str, Any]] = field(default_factory=list)
    # Image tracking (``estimator.tracking.DesignatedTarget``): the clicked point followed in
    # the video frame by frame, its 3-D point refined from the tracked views; "lost" is shown
    # (the distance is then that of the 3-D point, not of a point seen in this frame).
    tracker: DesignatedTarget | None = None
    frame_index: int = -1  # last frame the tracker has seen
    status: str = "tracking"  # "tracking" | "lost"
    tracked_uv: tuple[float, float] | None = None
    score: float | None = None
    reason: str = ""
    distance_sigma_m: float | None = None  # 1-σ of the distance from the 3-D point's covariance
    refreshed_t: float = -math.inf  # structure time the target was last refreshed on


@dataclass
class BerthLine:
    line_ne: np.ndarray  # (2,2) north, east
    source: str  # "recording", "ned" or "image"
    # "world": the engine's frame; "recording": the recording's local level (hull.json), mapped
    # to the world frame through the fused absolute position (SPP-anchored: metre-level)
    frame: str = "world"


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
                 body_height_m: float | None = None) -> None:
        self.id = session_id
        self.name = name
        self.rec = rec
        self.options = options
        self.prediction_seconds = prediction_seconds
        self.created = time.time()
        self.start_gpst = float(rec.manifest.start_gpst)
        self.end_gpst = float(max(rec.frame_times[-1], rec.imu.time[-1]))
        self.lock = threading.RLock()
        self.projector = Projector(rec.calibration.camera)
        self.water = water_level(rec, body_height_m)
        self.overlay_config = OverlayConfig(prediction_seconds=prediction_seconds,
                                            water_down_m=self.water.down_m)
        # history of fused states, one per processed frame, in time order
        self._times: list[float] = []
        self._states: list[Any] = []
        self._structure: tuple[np.ndarray, np.ndarray, np.ndarray] = (
            np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=int))
        self._structure_t: float | None = None
        self._views: Any | None = None  # engine.solved_views() at _structure_t
        self._latest_state: Any | None = None
        self._targets: dict[str, Target] = {}
        self._target_counter = 0
        self._frames: deque[tuple[int, float, np.ndarray]] = deque(maxlen=FRAME_BUFFER)
        self.berth_line: BerthLine | None = None
        if rec.hull.berth_line_ned is not None:
            self.berth_line = BerthLine(np.asarray(rec.hull.berth_line_ned, float).reshape(2, 2),
                                        "recording", frame="recording")
        self._subscribers: set[Subscriber] = set()
        # When the last client left (monotonic s); None while watched. A session nobody has
        # watched for a while (a browser that crashed) may be reclaimed by the manager.
        self.unwatched_since: float | None = time.monotonic()
        # The last frame played to clients (or that would have been, unwatched): what a client
        # joining now must see, even while paused.
        self._current_frame: tuple[FrameResult, Any | None] | None = None
        self._timing: dict[str, Any] = {}
        self.frame_listeners: list[Callable[[Session, FrameResult], None]] = []
        engine_options = dict(options)
        if self.water.known:
            # The landmark refinement drops points on or below the water (reflections).
            engine_options.setdefault("body_origin_height_m", self.water.down_m)
        self.replayer = Replayer(
            rec, lambda: engine_factory(rec.calibration, rec.nav, dict(engine_options)), self,
            speed=speed, checkpoint_interval_s=checkpoint_interval_s,
            shared=(rec, rec.calibration, rec.nav))

    # --------------------------------------------------------------------- life cycle

    def start(self, paused: bool = False) -> None:
        self.replayer.start(paused=paused)

    def close(self) -> None:
        self.replayer.stop()
        with self.lock:
            subscribers = list(self._subscribers)
            self._subscribers.clear()
            self.frame_listeners.clear()
        for sub in subscribers:
            sub.end(f"session {self.id} was deleted")

    # ------------------------------------------------------------------ FrameSink (replay)

    def on_frame(self, result: FrameResult, engine: FusionEngine) -> None:
        refresh = result.live or len(self._times) % 10 == 0
        structure = views = None
        if refresh:
            try:
                pts, sigma, ids = engine.structure()
                structure = (np.array(pts, dtype=float).reshape(-1, 3),
                             np.array(sigma, dtype=float).ravel(), np.array(ids).ravel())
                views = engine.solved_views()
            except Exception:  # the structure is a by-product: never stop the replay for it
                log.exception("engine.structure() or solved_views() failed")
            try:
                self._timing = dict(engine.timing())
            except Exception:
                log.exception("engine.timing() failed")
        state = copy.deepcopy(result.state) if result.state is not None else None
        with self.lock:
            if structure is not None:
                self._structure, self._structure_t = structure, result.t
                self._views = views
            self._frames.append((result.index, result.t, result.image))
            if state is not None:
                self._latest_state = state
                self._times.append(result.t)
                self._states.append(state)
                self._update_targets(state, result.index, result.image)
            watched = bool(self._subscribers)
            listeners = list(self.frame_listeners)
            if result.live:
                self._current_frame = (result, state)
        if result.live and watched:
            try:
                self._publish(self._frame_message(result, state))
            except Exception:  # a bad overlay must not stop the replay: log, send none
                log.exception("frame message of frame %d failed", result.index)
        for listener in listeners:
            try:
                listener(self, result)
            except Exception:
                log.exception("frame listener failed")

    def on_rewind(self, t: float | None) -> None:
        with self.lock:
            keep = 0 if t is None else bisect.bisect_right(self._times, t)
            del self._times[keep:], self._states[keep:]
            self._latest_state = self._states[-1] if self._states else None
            for target in self._targets.values():
                target.track = [p for p in target.track
                                if t is not None and p["gpst"] <= t]
                target.frame_index = -2  # the tracker resumes from the projected 3-D point
            self._frames.clear()

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
            if not self._subscribers:
                self.unwatched_since = time.monotonic()

    @property
    def client_count(self) -> int:
        with self.lock:
            return len(self._subscribers)

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

    def _frame_message(self, result: FrameResult, state: Any | None) -> tuple[bytes, bytes]:
        """Header JSON (without its closing brace: the sender appends its send time) and the
        JPEG of one frame."""
        ok, jpeg = cv2.imencode(".jpg", result.image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise RuntimeError(f"JPEG encoding of frame {result.index} failed")
        with self.lock:
            structure = self._structure
            targets = [TargetInput(t.id, t.position_ned, t.label) for t in self._targets.values()]
            berth = self._berth_world(state)
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
                       "lag_s": round(replay["lag_s"], 3)},
            "processed_at": result.processed_wall,
        }
        if state is None:
            header.update(pose=None, status=None, overlay=None)
        else:
            header["pose"] = pose_dict(state, self.start_gpst)
            header["status"] = status_dict(state.status)
            header["overlay"] = build_overlay(state, self.rec.calibration.camera, self.rec.hull,
                                              self.projector, structure, targets, berth,
                                              self.overlay_config)
            with self.lock:
                self._tracking_readouts(header["overlay"]["targets"])
        text = json.dumps(header, separators=(",", ":"), allow_nan=False)
        return text[:-1].encode(), jpeg.tobytes()

    # ------------------------------------------------------------------------ control

    def gpst(self, t: float) -> float:
        """Recording-relative seconds → gpst, checked against the recording span."""
        duration = self.end_gpst - self.start_gpst
        if not 0.0 <= t <= duration + 1e-9:
            raise Unprocessable(f"time {t:g} s is outside the recording (0 … {duration:.3f} s)")
        return self.start_gpst + t

    def control(self, action: str, t: float | None = None, speed: float | None | str = None
                ) -> None:
        if action == "play":
            self.replayer.play()
        elif action == "pause":
            self.replayer.pause()
        elif action == "seek":
            if t is None:
                raise Unprocessable("action 'seek' needs 'time' (seconds from the recording "
                                    "start)")
            self.replayer.seek(self.gpst(t))
        elif action == "speed":
            if speed is None:
                raise Unprocessable("action 'speed' needs 'speed' (a positive factor or 'max')")
            self.replayer.set_speed(None if speed == "max" else float(speed))
        else:
            raise Unprocessable(f"unknown action {action!r}")

    # ---------------------------------------------------------------------- queries

    def status_brief(self) -> dict[str, Any]:
        replay = self.replayer.status()
        with self.lock:
            fused = None
            if self._latest_state is not None:
                fused = status_dict(self._latest_state.status)
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
            "frames_processed": replay["frames_processed"],
            "frames_total": len(self.rec.frame_times),
            "clients": clients,
            "error": replay["error"],
            "fusion": fused,
            "timing_ms": {k: round(float(v), 3) for k, v in self.timing().items()},
            "checkpoints_s": [round(c - self.start_gpst, 3) for c in replay["checkpoints"]],
            "checkpoint_note": replay["checkpoint_note"],
            "prediction_seconds": self.prediction_seconds,
            "options": self.options,
            "has_reference": self.rec.reference is not None,
            "water_level": {"down_m": self.water.down_m, "source": self.water.source},
            "created_at": self.created,
        }

    def timing(self) -> dict[str, Any]:
        with self.lock:
            return dict(self._timing)

    def latest_state(self) -> Any | None:
        with self.lock:
            return self._latest_state

    def current_state(self) -> Any:
        with self.lock:
            if self._latest_state is None:
                raise Conflict("no fused pose yet: the engine is still initialising "
                               f"(session state {self.replayer.state.value})")
            return self._latest_state

    def state_at(self, t: float) -> Any:
        """The stored state of the last frame at or before recording time ``t`` (s)."""
        g = self.gpst(t)
        with self.lock:
            if not self._times:
                raise Conflict("no fused pose stored yet")
            if g > self._times[-1] + FRAME_MATCH_S:
                raise Conflict(f"t = {t:g} s has not been replayed yet (fused poses up to "
                               f"{self._times[-1] - self.start_gpst:.3f} s)")
            i = bisect.bisect_right(self._times, g + 1e-9) - 1
            if i < 0:
                raise NotFound(f"no fused pose at or before t = {t:g} s (the first is at "
                               f"{self._times[0] - self.start_gpst:.3f} s)")
            return self._states[i]

    def frame_state(self, t: float) -> Any:
        """The stored state of the frame at recording time ``t`` (within FRAME_MATCH_S)."""
        g = self.gpst(t)
        with self.lock:
            if not self._times:
                raise Conflict("no fused pose stored yet")
            # The stored frame nearest to t: the newest frame itself must match (t + tolerance
            # may lie beyond the history by a rounding error).
            i = bisect.bisect_left(self._times, g - FRAME_MATCH_S)
            if i < len(self._times) and abs(self._times[i] - g) <= FRAME_MATCH_S:
                return self._states[i]
            last = self._times[-1] - self.start_gpst
        if g > self.gpst(last) + FRAME_MATCH_S:
            raise Conflict(f"t = {t:g} s has not been replayed yet (fused poses up to "
                           f"{last:.3f} s)")
        raise NotFound(f"no fused pose for a frame at t = {t:g} s")

    def trajectory(self) -> dict[str, Any]:
        with self.lock:
            states = list(self._states)
        rows = [pose_dict(s, self.start_gpst) for s in states]
        return {
            "session": self.id,
            "count": len(rows),
            "t": [r["t"] for r in rows],
            "position_ned": [r["position_ned"] for r in rows],
            "llh_deg": [r["llh_deg"] for r in rows],
            "velocity_ned": [r["velocity_ned"] for r in rows],
            "euler_deg": [r["euler_deg"] for r in rows],
            "position_std_m": [r["position_std_m"] for r in rows],
            "phase": [str(s.status.phase) for s in states],
        }

    def trajectory_csv(self) -> str:
        with self.lock:
            states = list(self._states)
        lines = ["t,gpst,north,east,down,lat_deg,lon_deg,height,roll_deg,pitch_deg,yaw_deg,"
                 "v_north,v_east,v_down,std_north,std_east,std_down,phase"]
        for s in states:
            p = pose_dict(s, self.start_gpst)
            values = [f"{p['t']:.3f}", f"{p['gpst']:.6f}",
                      *(f"{x:.4f}" for x in p["position_ned"]),
                      f"{p['llh_deg'][0]:.9f}", f"{p['llh_deg'][1]:.9f}",
                      f"{p['llh_deg'][2]:.4f}", *(f"{x:.4f}" for x in p["euler_deg"]),
                      *(f"{x:.4f}" for x in p["velocity_ned"]),
                      *(f"{x:.4f}" for x in p["position_std_m"]), str(s.status.phase)]
            lines.append(",".join(values))
        return "\n".join(lines) + "\n"

    def history_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(times (N,), body positions (N,3)) of the fused trajectory so far."""
        with self.lock:
            times = np.array(self._times)
            pos = np.array([s.position_ned for s in self._states]).reshape(-1, 3)
        return times, pos

    def structure(self) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], float | None]:
        with self.lock:
            return self._structure, self._structure_t

    def prediction(self, seconds: int) -> tuple[Any, list[np.ndarray]]:
        state = self.current_state()
        return state, predict_outlines(state, self.rec.hull, seconds)

    # ---------------------------------------------------------------------- targets

    def designate(self, frame_t: float | None, u: float, v: float, label: str | None
                  ) -> Target:
        """A 3-D point for pixel (u, v) of a frame: from the port-structure points near that
        image ray (the nearest surface under the click, ``structure_point_at``), else where
        the ray meets the water plane. From that frame on the point is tracked in the video
        (``estimator.tracking.DesignatedTarget``) and its 3-D point refined from the views."""
        p = self.projector
        if not (-0.5 <= u <= p.width - 0.5 and -0.5 <= v <= p.height - 0.5):
            raise Unprocessable(f"pixel ({u:g}, {v:g}) is outside the {p.width}x{p.height} "
                                "image")
        state = self.current_state() if frame_t is None else self.frame_state(frame_t)
        cam = self.rec.calibration.camera
        pose = camera_pose(state, cam)
        ray = p.pixel_ray(pose, u, v)
        focal = 0.5 * float(cam.K[0, 0] + cam.K[1, 1])
        (pts, sigma, ids), _ = self.structure()
        anchors = np.zeros(0, dtype=int)
        anchor_mean = None
        found = None
        if len(pts):
            _visible, uv = p.project_points(pose, pts)
            found = structure_point_at(pts, sigma, uv, np.array([u, v]), pose.position_ned, ray,
                                       focal)
        if found is not None:
            point, cov, near = found
            method = "structure"
            anchors = np.asarray(ids)[near]
            anchor_mean = pts[near].mean(axis=0)
        else:
            hit = water_plane_point(pose.position_ned, ray, self.water.down_m)
            if hit is None:
                raise Unprocessable(
                    f"pixel ({u:g}, {v:g}) has no port-structure point within "
                    f"{2 * DESIGNATION_RADIUS_PX:g} px and its ray does not meet the water "
                    "plane (above the horizon)")
            point, method = hit, "water-plane"
            _, cov = point_on_ray(hit[None], None, pose.position_ned, ray, focal)
        # Decoded before the lock is taken (a few hundred ms): the replay goes on meanwhile.
        earlier = self._earlier_frames(self._frame_index(float(state.time))) \
            if method == "structure" else []
        with self.lock:
            self._target_counter += 1
            target = Target(id=f"T{self._target_counter}", label=label, method=method,
                            position_ned=point, designated_gpst=float(
                                self._latest_state.time),
                            frame_gpst=float(state.time), uv=(u, v), anchor_ids=anchors,
                            anchor_mean=anchor_mean, support=len(anchors))
            self._start_tracking(target, state, cov, earlier)
            self._targets[target.id] = target
            self._track(target, self._latest_state)
        self.redraw_if_paused()
        return target

    def _camera(self, state: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(C_level_to_camera, camera centre, 6x6 pose covariance or None) of a state."""
        cam = self.rec.calibration.camera
        pose = camera_pose(state, cam)
        cov = None
        p_cov, a_cov = getattr(state, "position_cov", None), getattr(state, "attitude_cov", None)
        if p_cov is not None and a_cov is not None:
            lever = np.asarray(state.C_body_to_level, dtype=float) @ np.asarray(
                cam.lever_arm_body, dtype=float)
            cov = camera_pose_covariance(p_cov, a_cov, lever)
            if not np.isfinite(cov).all():
                cov = None
        return pose.C_level_to_camera, pose.position_ned, cov

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

    def _start_tracking(self, target: Target, state: Any, cov: np.ndarray,
                        earlier: list[tuple[float, np.ndarray]]) -> None:
        """The image tracker on the clicked frame (tracked back through ``earlier``, its 3-D
        point triangulated in the structure's solved views), brought up to the latest frame
        from the frame buffer (called with the lock held; a few ms per buffered frame)."""
        index = self._frame_index(float(state.time))
        image = next((img for i, _t, img in self._frames if i == index), None)
        try:
            if image is None:
                image = self.rec.read_frame(index)
            window = max(15, int(round(TARGET_WINDOW_PX * self.projector.width / 960.0)) | 1)
            C, c, pose_cov = self._camera(state)
            target.tracker = DesignatedTarget(
                self.rec.calibration.camera, image, np.array(target.uv), target.position_ned,
                cov, C, c, pose_cov, params=TargetParams(window=window),
                refine=target.method == "structure", t=float(state.time),
                earlier_frames=earlier, views=self._views)
            target.position_ned = target.tracker.position_ned
        except Exception as exc:  # no image tracking: the target keeps its 3-D point, lost
            log.exception("the image tracker of target %s could not start", target.id)
            target.tracker, target.status = None, "lost"
            target.reason = f"image tracking unavailable: {exc}"
            return
        target.frame_index = index
        target.tracked_uv, target.score = target.uv, 1.0
        for i, t, img in list(self._frames):
            if i > target.frame_index:
                st = self.state_at_gpst(t)
                if st is not None:
                    self._follow(target, st, i, img)

    def state_at_gpst(self, t: float) -> Any | None:
        """The stored state of the frame at gpst ``t`` (None when there is none)."""
        i = bisect.bisect_left(self._times, t - 1e-6)
        if i < len(self._times) and abs(self._times[i] - t) < 1e-6:
            return self._states[i]
        return None

    def _follow(self, target: Target, state: Any, index: int, image: np.ndarray) -> None:
        """One frame of a target's image tracking (lock held)."""
        tr = target.tracker
        if tr is None or index == target.frame_index:
            return
        try:
            C, c, cov = self._camera(state)
            t = float(state.time)
            if index == target.frame_index + 1:
                st = tr.update(t, image, C, c, cov)
            else:  # a seek or a gap: take it back where its 3-D point projects
                st = tr.resume(t, image, C, c, cov)
        except Exception:  # a tracking failure must not stop the replay
            log.exception("tracking target %s failed on frame %d", target.id, index)
            target.status, target.reason = "lost", "tracking failed"
            target.frame_index = -2
            return
        target.frame_index = index
        self._refresh(target, C, c)
        target.position_ned = tr.position_ned
        target.status = st.status
        target.tracked_uv = None if st.uv is None else (float(st.uv[0]), float(st.uv[1]))
        target.score = st.score
        target.reason = st.reason
        target.distance_sigma_m = st.distance_sigma_m

    def _refresh(self, target: Target, C: np.ndarray, c: np.ndarray) -> None:
        """A target's 3-D point from the latest structure, at most once a second
        (``DesignatedTarget.refresh``; lock held)."""
        pts, sigma, _ids = self._structure
        t = self._structure_t
        if t is None or 0.0 <= t - target.refreshed_t < TARGET_REFRESH_S:
            return  # (a structure older than the last one: the replay went back, go on)
        target.refreshed_t = t
        _visible, uv = self.projector.project_points(CameraPose(C, c), pts)
        target.tracker.refresh(pts, sigma, uv, C, c, self._views)

    def _update_targets(self, state: Any, index: int, image: np.ndarray) -> None:
        """Track every target in the new frame and extend the tracks (lock held)."""
        for target in self._targets.values():
            self._follow(target, state, index, image)
            self._track(target, state)

    def _track(self, target: Target, state: Any) -> None:
        pose = camera_pose(state, self.rec.calibration.camera)
        visible, uv = self.projector.project_points(pose, target.position_ned[None])
        entry: dict[str, Any] = {
            "t": round(float(state.time) - self.start_gpst, 6),
            "gpst": float(state.time),
            "position_ned": np.round(target.position_ned, 4).tolist(),
            "visible": bool(visible[0]),
            "uv": np.round(uv[0], 2).tolist() if visible[0] else None,
            "status": target.status,
            "tracked_uv": None if target.tracked_uv is None else
            [round(target.tracked_uv[0], 2), round(target.tracked_uv[1], 2)],
            "score": None if target.score is None else round(float(target.score), 3),
            "reason": target.reason,
            "distance_sigma_m": None if target.distance_sigma_m is None else
            round(float(target.distance_sigma_m), 3),
        }
        entry.update(target_readout(target.position_ned, pose, hull_outline_ne(state,
                                                                               self.rec.hull)))
        if target.track and target.track[-1]["gpst"] == entry["gpst"]:
            target.track[-1] = entry
        else:
            target.track.append(entry)

    def _tracking_readouts(self, readouts: list[dict[str, Any]]) -> None:
        """The overlay's target readouts with the image tracking: drawn at the tracked point,
        and a lost one not drawn on the video, its label saying so (lock held)."""
        for entry in readouts:
            target = self._targets.get(entry.get("id"))
            if target is None:
                continue
            entry["status"] = target.status
            entry["distance_sigma_m"] = None if target.distance_sigma_m is None else \
                round(float(target.distance_sigma_m), 3)
            if target.status == "tracking" and target.tracked_uv is not None:
                entry["uv"] = [round(target.tracked_uv[0], 1), round(target.tracked_uv[1], 1)]
                entry["visible"] = True
            elif target.status == "lost":
                entry["visible"], entry["uv"] = False, None
                entry["label"] = f"{target.label or target.id} (lost)"
                entry["reason"] = target.reason

    def targets(self) -> list[Target]:
        with self.lock:
            return list(self._targets.values())

    def target(self, target_id: str) -> Target:
        with self.lock:
            if target_id not in self._targets:
                known = ", ".join(self._targets) or "none"
                raise NotFound(f"no target {target_id!r} in session {self.id} "
                               f"(targets: {known})")
            return self._targets[target_id]

    def delete_target(self, target_id: str) -> None:
        with self.lock:
            self.target(target_id)
            del self._targets[target_id]
        self.redraw_if_paused()

    # -------------------------------------------------------------------- berth line

    def set_berth_line_ned(self, line_ne: np.ndarray) -> BerthLine:
        line = np.asarray(line_ne, dtype=float).reshape(2, 2)
        if np.linalg.norm(line[1] - line[0]) < 0.1:
            raise Unprocessable("the berth line's two points are less than 0.1 m apart")
        with self.lock:
            self.berth_line = BerthLine(line, "ned")
        self.redraw_if_paused()
        return self.berth_line

    def set_berth_line_image(self, frame_t: float | None, points_uv: np.ndarray) -> BerthLine:
        """Berth line from two pixels on the quay's water line (rays meet the water plane)."""
        state = self.current_state() if frame_t is None else self.frame_state(frame_t)
        pose = camera_pose(state, self.rec.calibration.camera)
        ends = []
        for u, v in np.asarray(points_uv, dtype=float).reshape(2, 2):
            p = self.projector
            if not (-0.5 <= u <= p.width - 0.5 and -0.5 <= v <= p.height - 0.5):
                raise Unprocessable(f"pixel ({u:g}, {v:g}) is outside the {p.width}x{p.height}"
                                    " image")
            hit = water_plane_point(pose.position_ned, p.pixel_ray(pose, u, v),
                                    self.water.down_m)
            if hit is None:
                raise Unprocessable(f"pixel ({u:g}, {v:g}) is above the horizon: its ray does "
                                    "not meet the water plane")
            ends.append(hit[:2])
        line = self.set_berth_line_ned(np.array(ends))
        with self.lock:
            self.berth_line = BerthLine(line.line_ne, "image")
        return self.berth_line

    def berth_status(self) -> dict[str, Any]:
        """The berth line with the bow/stern distance and approach speed at the current pose."""
        with self.lock:
            line, state = self.berth_line, self._latest_state
        out: dict[str, Any] = {"line_ne": None, "source": None, "t": None,
                               "bow_distance_m": None, "stern_distance_m": None,
                               "bow_approach_mps": None, "stern_approach_mps": None}
        if line is None:
            return out
        out["source"] = line.source
        world = self._berth_world(state)
        if world is not None:
            out["line_ne"] = world.round(3).tolist()
        if state is not None and world is not None:
            out["t"] = float(state.time) - self.start_gpst
            out.update(berth_metrics(state, self.rec.hull, world))
        return out

    # ------------------------------------------------------------------------- frames

    def origin_in_recording(self, state: Any) -> np.ndarray:
        """The world origin in the recording's local level (manifest origin), from the fused
        absolute position (``llh_deg``, SPP-anchored) of ``state``."""
        lat, lon, h = (float(x) for x in state.llh_deg)
        absolute = ecef_to_ned(geodetic_to_ecef(np.radians(lat), np.radians(lon), h),
                               self.rec.manifest.origin_llh)
        return absolute - np.asarray(state.position_ned, dtype=float)

    def _berth_world(self, state: Any | None) -> np.ndarray | None:
        line = self.berth_line
        if line is None:
            return None
        if line.frame == "world":
            return line.line_ne
        if state is None:
            return None
        return line.line_ne - self.origin_in_recording(state)[:2]

    def reference_alignment(self) -> tuple[float, np.ndarray] | None:
        """(time, offset) with reference = world + offset, matched at the first fused pose:
        the engine's trajectory starts from its own origin (no base station), so it is
        compared with the reference from the same starting point, as in the thesis."""
        ref = self.rec.reference
        with self.lock:
            if ref is None or not self._states:
                return None
            first = self._states[0]
        p_ref, _v, _e = ref.interpolate(float(first.time))
        if not np.isfinite(p_ref).all():
            return None
        return float(first.time), p_ref - np.asarray(first.position_ned, dtype=float)

    def clear_berth_line(self) -> None:
        with self.lock:
            self.berth_line = None
        self.redraw_if_paused()

    # -------------------------------------------------------------------------- report

    def _absolute(self, state: Any) -> np.ndarray:
        return self.origin_in_recording(state) + np.asarray(state.position_ned, dtype=float)

    def report(self, after_s: float = 0.0) -> dict[str, Any]:
        """Horizontal and heading error of the fused states so far against the reference."""
        ref = self.rec.reference
        if ref is None:
            raise NotFound(f"recording {self.name!r} has no reference trajectory (its manifest "
                           "names no reference file), so the session cannot be evaluated")
        with self.lock:
            times = np.array(self._times)
            states = list(self._states)
        if len(times) == 0:
            raise Conflict("no fused pose stored yet: nothing to evaluate")
        aligned = self.reference_alignment()
        if aligned is None:
            raise Conflict("the first fused pose is outside the reference span")
        est_pos = np.array([s.position_ned for s in states]).reshape(-1, 3) + aligned[1]
        abs_pos = np.array([self._absolute(s) for s in states]).reshape(-1, 3)
        est_yaw = np.array([float(s.euler[2]) for s in states])
        phases = [str(s.status.phase) for s in states]
        keep = times >= self.start_gpst + after_s
        ref_pos, _v, ref_euler = ref.interpolate(times)
        keep &= np.isfinite(ref_pos).all(axis=1)
        if not keep.any():
            raise Conflict(f"no fused pose after {after_s:g} s inside the reference span yet")
        horizontal = np.linalg.norm(est_pos[keep, :2] - ref_pos[keep, :2], axis=1)
        absolute = np.linalg.norm(abs_pos[keep, :2] - ref_pos[keep, :2], axis=1)
        vertical = est_pos[keep, 2] - ref_pos[keep, 2]
        heading = np.degrees(wrap_angle(est_yaw[keep] - ref_euler[keep, 2]))
        t_rel = np.round(times[keep] - self.start_gpst, 6)

        def stats(e: np.ndarray, signed: bool) -> dict[str, float]:
            a = np.abs(e)
            return {
                "rms": float(np.sqrt(np.mean(e**2))),
                "std": float(np.std(e)),
                "mean": float(np.mean(e)) if signed else float(np.mean(a)),
                "max": float(a.max()),
                "max_at_s": float(t_rel[int(np.argmax(a))]),
            }

        counts: dict[str, int] = {}
        for phase, k in zip(phases, keep, strict=True):
            if k:
                counts[phase] = counts.get(phase, 0) + 1
        return {
            "session": self.id,
            "recording": self.name,
            "after_s": after_s,
            "from_s": float(t_rel[0]),
            "to_s": float(t_rel[-1]),
            "samples": int(keep.sum()),
            "phases": counts,
            "aligned_at_s": round(aligned[0] - self.start_gpst, 6),
            "horizontal_error_m": stats(horizontal, signed=False),
            "absolute_horizontal_error_m": stats(absolute, signed=False),
            "vertical_error_m": stats(vertical, signed=True),
            "heading_error_deg": stats(heading, signed=True),
        }


# ----------------------------------------------------------------------------- manager


class SessionManager:
    """Creates, finds and closes sessions (bounded: each one is a CPU-bound thread)."""

    def __init__(self, catalog: RecordingCatalog, engine_factory: EngineFactory,
                 max_sessions: int = 4, checkpoint_interval_s: float | None = 10.0,
                 abandoned_after_s: float = 120.0) -> None:
        self.catalog = catalog
        self.engine_factory = engine_factory
        self.max_sessions = max_sessions
        self.abandoned_after_s = abandoned_after_s
        self.checkpoint_interval_s = checkpoint_interval_s
        self._sessions: dict[str, Session] = {}
        self._lock = threading.Lock()
        self.created_listeners: list[Callable[[Session], None]] = []
        self.closed_listeners: list[Callable[[Session], None]] = []

    def create(self, recording: str, speed: float | None, options: dict[str, Any],
               paused: bool = False, prediction_seconds: int = 5,
               body_height_m: float | None = None) -> Session:
        with self._lock:
            full = len(self._sessions) >= self.max_sessions
        if full and not self._reclaim_abandoned():
            raise TooMany(f"{len(self._sessions)} sessions are open (the limit is "
                          f"{self.max_sessions}) and all were watched within the last "
                          f"{self.abandoned_after_s:g} s; delete one first")
        rec = self.catalog.load(recording)
        session = Session(uuid.uuid4().hex[:12], recording, rec, self.engine_factory, options,
                          speed, prediction_seconds, self.checkpoint_interval_s, body_height_m)
        with self._lock:
            self._sessions[session.id] = session
        for listener in self.created_listeners:
            listener(session)
        session.start(paused=paused)
        return session

    def _reclaim_abandoned(self) -> bool:
        """Delete the session unwatched the longest, if longer than ``abandoned_after_s``."""
        now = time.monotonic()
        idle = [(now - s.unwatched_since, s.id) for s in self.all()
                if s.unwatched_since is not None]
        if not idle or max(idle)[0] < self.abandoned_after_s:
            return False
        log.info("reclaiming session %s, unwatched for %.0f s", max(idle)[1], max(idle)[0])
        self.delete(max(idle)[1])
        return True

    def get(self, session_id: str) -> Session:
        with self._lock:
            session = self._sessions.get(session_id)
            known = ", ".join(self._sessions) or "none"
        if session is None:
            raise NotFound(f"no session {session_id!r} (open sessions: {known})")
        return session

    def all(self) -> list[Session]:
        with self._lock:
            return list(self._sessions.values())

    def delete(self, session_id: str) -> None:
        session = self.get(session_id)
        with self._lock:
            self._sessions.pop(session_id, None)
        session.close()
        for listener in self.closed_listeners:
            listener(session)

    def close_all(self) -> None:
        for session in self.all():
            self.delete(session.id)
