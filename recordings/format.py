"""Recording format version 1: reader, validation, summary and writers (see README.md beside).

``load`` checks everything it reads and raises ``RecordingError`` naming the file, the line or
field and what is wrong. Problems real data legitimately has (IMU gaps, a video a few frames
shorter than ``frames.csv``) are not fatal: they are collected in ``Recording.warnings`` and
shown by ``summary``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import queue
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np

from estimator.compass import MIN_RECEIVERS
from estimator.frames import (
    datetime_from_gpst,
    ecef_to_geodetic,
    ned_to_ecef,
    week_tow_from_gpst,
    wrap_angle,
)
from estimator.records import (
    Calibration,
    CameraCalibration,
    GnssEpoch,
    Hull,
    ImuCalibration,
    ImuData,
    NavigationData,
)
from recordings import rinex
from recordings.rinex import ObsHeader

FORMAT_NAME = "berthing-aid-recording"
FORMAT_VERSION = 1
SUPPORTED_VERSIONS = (1,)

IMU_COLUMNS = ("time_gpst", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
FRAME_COLUMNS = ("frame", "time_gpst")
REFERENCE_COLUMNS = (
    "time_gpst", "north", "east", "down", "lat_deg", "lon_deg", "height",
    "roll_deg", "pitch_deg", "yaw_deg", "v_north", "v_east", "v_down",
)
SCENE_POINT_COLUMNS = ("north", "east", "down", "kind")

# Standard file names inside a recording (what the writers produce).
MANIFEST_FILE = "manifest.json"
CALIBRATION_FILE = "calibration.json"
HULL_FILE = "hull.json"
VIDEO_FILE = "video.mp4"
FRAMES_FILE = "frames.csv"
IMU_FILE = "imu.csv"
NAV_FILE = "gnss/nav.rnx"
REFERENCE_FILE = "reference/trajectory.csv"
SCENE_POINTS_FILE = "reference/scene_points.csv"

VIDEO_FPS = 10.0
IMU_GAP_FACTOR = 5.0  # a gap is an interval longer than this many nominal sample intervals
VIDEO_GAP_FACTOR = 2.5  # ... and in the video, than this many frame intervals (one dropped
# frame is not worth a line)
EARLY_END_S = 1.0  # a stream ending this long before the recording does is noted
COMPASS_RECEIVERS = 4
_REQUIRED_FILE_KEYS = ("video", "frame_times", "imu", "gnss_obs", "gnss_nav", "calibration",
                       "hull")
_OPTIONAL_FILE_KEYS = ("reference", "scene_points")
_MANIFEST_KEYS = ("format", "version", "name", "scenario", "seed", "start_gpst", "duration_s",
                  "origin_llh_deg", "files")
_DISTORTION_LENGTHS = (4, 5, 8, 12, 14)  # what OpenCV accepts
_ROTATION_TOL = 1e-6
_SYSTEM_ORDER = "GREJCSI"  # the usual RINEX listing order of constellations


class RecordingError(ValueError):
    """A recording is missing something or holds invalid data; the message names the file,
    the line or field, and what is wrong."""


class RecordingWarning(UserWarning):
    """Non-fatal problem found while reading a recording (e.g. the video ends early)."""


def gnss_obs_file(receiver: int) -> str:
    """Standard relative path of receiver ``receiver``'s observation file (1-based)."""
    return f"gnss/rx{receiver}.obs"


def default_files(receivers: int | Sequence[str] = 4, reference: bool = True) -> dict[str, Any]:
    """The ``files`` section of a manifest naming the standard files; ``receivers`` is the
    number of receivers (standard names ``gnss/rx<i>.obs``) or their observation file names."""
    if isinstance(receivers, int):
        obs = [gnss_obs_file(i + 1) for i in range(receivers)]
    else:
        obs = [str(r) for r in receivers]
    return {
        "video": VIDEO_FILE,
        "frame_times": FRAMES_FILE,
        "imu": IMU_FILE,
        "gnss_obs": obs,
        "gnss_nav": NAV_FILE,
        "calibration": CALIBRATION_FILE,
        "hull": HULL_FILE,
        "reference": REFERENCE_FILE if reference else None,
        "scene_points": SCENE_POINTS_FILE if reference else None,
    }


# ------------------------------------------------------------------------------ records


@dataclass
class Manifest:
    name: str
    scenario: str | None  # None for a real recording
    seed: int | None  # simulator seed; None for a real recording
    start_gpst: float  # GPS seconds of the first sample
    duration_s: float
    origin_llh_deg: tuple[float, float, float]  # local-level origin: lat, lon (deg), height (m)
    files: dict[str, Any] = field(default_factory=default_files)
    version: int = FORMAT_VERSION
    extra: dict[str, Any] = field(default_factory=dict)  # unknown top-level keys, kept as is

    def __post_init__(self) -> None:
        lat, lon, h = (float(x) for x in self.origin_llh_deg)
        self.origin_llh_deg = (lat, lon, h)

    @property
    def origin_llh(self) -> np.ndarray:
        """Origin as (lat rad, lon rad, h m), the form ``estimator.frames`` takes."""
        lat, lon, h = self.origin_llh_deg
        return np.array([math.radians(lat), math.radians(lon), h])


@dataclass
class ReferenceTrajectory:
    """True trajectory of the body origin (scoring only). Angles are degrees as in the file."""

    time: np.ndarray  # (N,) gpst s, strictly increasing
    position_ned: np.ndarray  # (N,3) m in the local level frame at the manifest origin
    llh_deg: np.ndarray  # (N,3) lat, lon (deg), ellipsoidal height (m)
    euler_deg: np.ndarray  # (N,3) roll, pitch, yaw (deg)
    velocity_ned: np.ndarray  # (N,3) m/s
    _euler_unwrapped: np.ndarray | None = field(default=None, init=False, repr=False,
                                                compare=False)

    def __post_init__(self) -> None:
        self.time = np.asarray(self.time, dtype=float)
        n = len(self.time)
        for name in ("position_ned", "llh_deg", "euler_deg", "velocity_ned"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (n, 3):
                raise ValueError(f"ReferenceTrajectory.{name} has shape {value.shape}, "
                                 f"expected ({n}, 3)")
            setattr(self, name, value)

    @classmethod
    def from_ned(cls, time: np.ndarray, position_ned: np.ndarray, velocity_ned: np.ndarray,
                 euler_deg: np.ndarray, origin_llh: np.ndarray) -> ReferenceTrajectory:
        """Build from NED positions, filling ``llh_deg``; ``origin_llh`` is (lat rad, lon rad,
        h m) as in ``estimator.frames`` (``Manifest.origin_llh``)."""
        origin = np.asarray(origin_llh, dtype=float)
        if abs(origin[0]) > np.pi / 2 or abs(origin[1]) > 2 * np.pi:
            raise ValueError(f"origin_llh {origin.tolist()} looks like degrees; pass radians")
        pos = np.asarray(position_ned, dtype=float).reshape(-1, 3)
        lat, lon, h = ecef_to_geodetic(ned_to_ecef(pos, origin).T)  # vectorised over columns
        llh_deg = np.column_stack([np.degrees(lat), np.degrees(lon), h])
        return cls(time=time, position_ned=pos, llh_deg=llh_deg, euler_deg=euler_deg,
                   velocity_ned=velocity_ned)

    def __len__(self) -> int:
        return len(self.time)

    def interpolate(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position_ned, velocity_ned, euler) at time(s) ``t`` by linear interpolation.

        ``euler`` is (roll, pitch, yaw) in RADIANS (code convention), yaw wrapped to (-pi, pi]
        after interpolating the unwrapped angle, so 179 deg -> -179 deg passes through 180
        rather than 0. Shapes are (3,) for a scalar ``t`` and (M,3) for an array; times outside
        the trajectory give NaN rather than a silently clamped value.
        """
        if len(self.time) == 0:
            raise ValueError("interpolate on an empty reference trajectory")
        if self._euler_unwrapped is None:
            self._euler_unwrapped = np.unwrap(np.radians(self.euler_deg), axis=0)
        t_arr = np.asarray(t, dtype=float)
        tt = np.atleast_1d(t_arr)

        def interp(values: np.ndarray) -> np.ndarray:
            return np.column_stack([np.interp(tt, self.time, values[:, i]) for i in range(3)])

        position = interp(self.position_ned)
        velocity = interp(self.velocity_ned)
        euler = wrap_angle(interp(self._euler_unwrapped))
        outside = (tt < self.time[0]) | (tt > self.time[-1])
        for a in (position, velocity, euler):
            a[outside] = np.nan
        if t_arr.ndim == 0:
            return position[0], velocity[0], euler[0]
        return position, velocity, euler


@dataclass
class VideoInfo:
    width: int
    height: int
    fps: float
    frame_count: int  # as decoded / reported by the container


@dataclass
class Recording:
    path: Path
    manifest: Manifest
    calibration: Calibration
    hull: Hull
    imu: ImuData
    frame_times: np.ndarray  # (F,) gpst s of video frame i
    gnss: list[list[GnssEpoch]]  # one list per receiver (antenna i); empty if not loaded
    gnss_headers: list[ObsHeader]
    nav: NavigationData  # empty if GNSS was not loaded
    reference: ReferenceTrajectory | None
    scene_points: np.ndarray | None  # (P,3) NED m
    scene_point_kinds: list[str] | None
    video_info: VideoInfo | None = None
    gnss_loaded: bool = True
    warnings: list[str] = field(default_factory=list)  # non-fatal problems found by load

    def video_path(self) -> Path:
        return self.path / self.manifest.files["video"]

    def _open_video(self) -> cv2.VideoCapture:
        path = self.video_path()
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise RecordingError(f"{path}: cannot open the video (missing, unreadable or an "
                                 "unsupported codec)")
        return cap

    def frames(self, start: int = 0) -> Iterator[tuple[int, float, np.ndarray]]:
        """Iterate (frame index, time_gpst, BGR image) from frame ``start``.

        Opens the video immediately (an unreadable video raises here, not at the first
        ``next``). Stops with a ``RecordingWarning`` when the video ends before ``frames.csv``;
        frames beyond ``frames.csv`` have no time and are not returned.
        """
        return _without_prepared(self.prepared_frames(start, None))

    def prepared_frames(self, start: int, prepare: Callable[[np.ndarray], Any] | None
                        ) -> Iterator[tuple[int, float, np.ndarray, Any]]:
        """As ``frames``, each with ``prepare(image)`` (None without ``prepare``), made in the
        decoding thread: a pure function of the image that the consumer would otherwise
        compute on its own critical path."""
        n = len(self.frame_times)
        if not 0 <= start <= n:
            raise IndexError(f"start frame {start} outside 0..{n}")
        cap = self._open_video()
        _skip_to(cap, self.video_path(), start)
        return self._iter_frames(cap, start, n, prepare)

    def _iter_frames(self, cap: cv2.VideoCapture, start: int, n: int,
                     prepare: Callable[[np.ndarray], Any] | None
                     ) -> Iterator[tuple[int, float, np.ndarray, Any]]:
        reads = _read_ahead(cap, n - start, prepare)
        try:
            for i in range(start, n):
                ok, image, prepared = next(reads)
                if not ok:
                    warnings.warn(
                        f"{self.video_path()}: the video ends at frame {i} but "
                        f"{self.manifest.files['frame_times']} lists {n} frames; stopping",
                        RecordingWarning, stacklevel=2)
                    return
                yield i, float(self.frame_times[i]), image, prepared
        finally:
            reads.close()  # the reading thread stops before the video is released
            cap.release()

    def read_frame(self, index: int) -> np.ndarray:
        """BGR image of frame ``index`` (random access; prefer ``frames`` for sequences)."""
        n = len(self.frame_times)
        if not 0 <= index < n:
            raise IndexError(f"frame {index} outside 0..{n - 1}")
        cap = self._open_video()
        try:
            _skip_to(cap, self.video_path(), index)
            ok, image = cap.read()
        finally:
            cap.release()
        if not ok:
            raise RecordingError(f"{self.video_path()}: cannot decode frame {index}")
        return image


def _without_prepared(frames: Iterator[tuple[int, float, np.ndarray, Any]]
                      ) -> Iterator[tuple[int, float, np.ndarray]]:
    with contextlib.closing(frames):  # stopped early: the reading thread stops too
        for i, t, image, _ in frames:
            yield i, t, image


RAW_MJPEG_SUFFIXES = (".mjpeg", ".mjpg")  # concatenated JPEGs: what a live session writes


READ_AHEAD_FRAMES = 3


def _read_ahead(cap: cv2.VideoCapture, count: int,
                prepare: Callable[[np.ndarray], Any] | None = None
                ) -> Iterator[tuple[bool, np.ndarray | None, Any]]:
    """``cap.read()`` results with ``prepare(image)`` of each (None without it), up to
    ``count``, decoded by a thread up to ``READ_AHEAD_FRAMES`` ahead: the decoder (which
    releases the GIL) works on another core while the caller processes the last frame. The
    frames and their order are those of ``cap.read()``; an error in the thread (or in
    ``prepare``) is raised here."""
    slots: queue.Queue = queue.Queue(maxsize=READ_AHEAD_FRAMES)
    stop = threading.Event()

    def offer(item: tuple) -> None:
        while not stop.is_set():  # the reader may have stopped taking
            try:
                slots.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def read() -> None:
        try:
            for _ in range(count):
                ok, image = cap.read()
                prepared = prepare(image) if ok and prepare is not None else None
                offer((ok, image, prepared, None))
                if not ok or stop.is_set():
                    return
        except BaseException as exc:  # handed to the reader, never lost with the thread
            offer((False, None, None, exc))

    thread = threading.Thread(target=read, name="video-read-ahead", daemon=True)
    thread.start()
    try:
        for _ in range(count):
            ok, image, prepared, error = slots.get()
            if error is not None:
                raise error
            yield ok, image, prepared
            if not ok:
                return
    finally:
        stop.set()
        thread.join()


def _skip_to(cap: cv2.VideoCapture, path: Path, index: int) -> None:
    """Position ``cap`` before frame ``index``. A raw MJPEG stream has no index to seek in
    (FFmpeg would silently stay at frame 0): its frames are skipped one by one."""
    if not index:
        return
    if path.suffix.lower() in RAW_MJPEG_SUFFIXES:
        for _ in range(index):
            if not cap.grab():
                return
    else:
        cap.set(cv2.CAP_PROP_POS_FRAMES, index)


# ------------------------------------------------------------------------- JSON helpers


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RecordingError(f"{path}: file not found") from None
    except UnicodeDecodeError as exc:
        raise RecordingError(f"{path}: not UTF-8 text ({exc.reason})") from None
    except json.JSONDecodeError as exc:
        raise RecordingError(f"{path}: line {exc.lineno}: invalid JSON: {exc.msg}") from None
    if not isinstance(data, dict):
        raise RecordingError(f"{path}: the top level must be a JSON object")
    return data


def _get(path: Path, obj: dict[str, Any], key: str, where: str = "") -> Any:
    """obj[key], or a RecordingError naming the JSON path (``camera.fx``)."""
    jpath = f"{where}.{key}" if where else key
    if not isinstance(obj, dict):
        raise RecordingError(f"{path}: {where or 'top level'} must be a JSON object")
    if key not in obj:
        raise RecordingError(f"{path}: missing field {jpath}")
    return obj[key]


def _number(path: Path, value: Any, jpath: str) -> float:
    # bool is an int subclass in Python but never a meaningful number here
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise RecordingError(f"{path}: {jpath} must be a finite number, got {value!r}")
    return float(value)


def _array(path: Path, value: Any, jpath: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """A finite float array of the given shape (None = any length)."""
    what = " x ".join("n" if s is None else str(s) for s in shape)
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise RecordingError(f"{path}: {jpath} must be a {what} array of numbers, "
                             f"got {value!r}") from None
    ok = arr.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, arr.shape,
                                                                            strict=False))
    if not ok or isinstance(value, str | bool):
        raise RecordingError(f"{path}: {jpath} must be a {what} array of numbers, "
                             f"got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise RecordingError(f"{path}: {jpath} contains a non-finite value")
    return arr


def _positive_int(path: Path, value: Any, jpath: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise RecordingError(f"{path}: {jpath} must be a positive integer, got {value!r}")
    return value


def _rotation(path: Path, value: Any, jpath: str) -> np.ndarray:
    C = _array(path, value, jpath, (3, 3))
    err = float(np.abs(C @ C.T - np.eye(3)).max())
    if err > _ROTATION_TOL or np.linalg.det(C) < 0:
        raise RecordingError(f"{path}: {jpath} is not a rotation matrix (|C Cᵀ - I| = {err:.2e},"
                             f" det = {np.linalg.det(C):.6f})")
    return C


# --------------------------------------------------------------------------- manifest


def _parse_manifest(path: Path) -> Manifest:
    data = _read_json(path)
    fmt = data.get("format")
    if fmt != FORMAT_NAME:
        raise RecordingError(f"{path}: field format is {fmt!r}, expected {FORMAT_NAME!r} "
                             "(not a berthing-aid recording)")
    version = _get(path, data, "version")
    if isinstance(version, bool) or version not in SUPPORTED_VERSIONS:
        raise RecordingError(f"{path}: unsupported format version {version!r} (this reader "
                             f"supports {', '.join(map(str, SUPPORTED_VERSIONS))})")
    name = _get(path, data, "name")
    if not isinstance(name, str) or not name:
        raise RecordingError(f"{path}: name must be a non-empty string, got {name!r}")
    scenario = data.get("scenario")
    if scenario is not None and not isinstance(scenario, str):
        raise RecordingError(f"{path}: scenario must be a string or null, got {scenario!r}")
    seed = data.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
        raise RecordingError(f"{path}: seed must be an integer or null, got {seed!r}")
    start = _number(path, _get(path, data, "start_gpst"), "start_gpst")
    if start <= 0:
        raise RecordingError(f"{path}: start_gpst must be GPS seconds since 1980-01-06, "
                             f"got {start}")
    duration = _number(path, _get(path, data, "duration_s"), "duration_s")
    if duration <= 0:
        raise RecordingError(f"{path}: duration_s must be positive, got {duration}")
    origin = _array(path, _get(path, data, "origin_llh_deg"), "origin_llh_deg", (3,))
    if not (-90 <= origin[0] <= 90 and -180 <= origin[1] <= 360):
        raise RecordingError(f"{path}: origin_llh_deg {origin.tolist()} is not a latitude, "
                             "longitude (deg), height (m)")
    files = _parse_files(path, _get(path, data, "files"))
    extra = {k: v for k, v in data.items() if k not in _MANIFEST_KEYS}
    return Manifest(name=name, scenario=scenario, seed=seed, start_gpst=start,
                    duration_s=duration, origin_llh_deg=tuple(origin.tolist()), files=files,
                    version=version, extra=extra)


def _parse_files(path: Path, files: Any) -> dict[str, Any]:
    if not isinstance(files, dict):
        raise RecordingError(f"{path}: files must be a JSON object")
    out = dict(files)
    for key in _REQUIRED_FILE_KEYS:
        value = _get(path, files, key, "files")
        if key == "gnss_obs":
            if (not isinstance(value, list) or not value
                    or not all(isinstance(v, str) and v for v in value)):
                raise RecordingError(f"{path}: files.gnss_obs must be a non-empty list of "
                                     f"file names (one per receiver), got {value!r}")
        elif not isinstance(value, str) or not value:
            raise RecordingError(f"{path}: files.{key} must be a file name, got {value!r}")
    for key in _OPTIONAL_FILE_KEYS:
        value = files.get(key)
        if value is not None and (not isinstance(value, str) or not value):
            raise RecordingError(f"{path}: files.{key} must be a file name or null, "
                                 f"got {value!r}")
        out[key] = value
    return out


def _check_files_exist(root: Path, manifest_path: Path, files: dict[str, Any]) -> None:
    named: list[tuple[str, str]] = []
    for key in (*_REQUIRED_FILE_KEYS, *_OPTIONAL_FILE_KEYS):
        value = files[key]
        if isinstance(value, list):
            named += [(f"{key}[{i}]", v) for i, v in enumerate(value)]
        elif value is not None:
            named.append((key, value))
    for key, rel in named:
        if not (root / rel).is_file():
            raise RecordingError(f"{manifest_path}: files.{key} names {rel!r}, which does not "
                                 f"exist ({root / rel})")


# ------------------------------------------------------------------- calibration, hull


def _parse_calibration(path: Path) -> Calibration:
    data = _read_json(path)
    cam = _get(path, data, "camera")

    def cam_field(key: str) -> Any:
        return _get(path, cam, key, "camera")

    width = _positive_int(path, cam_field("width"), "camera.width")
    height = _positive_int(path, cam_field("height"), "camera.height")
    fx, fy, cx, cy = (_number(path, cam_field(k), f"camera.{k}") for k in ("fx", "fy", "cx", "cy"))
    if fx <= 0 or fy <= 0:
        raise RecordingError(f"{path}: camera.fx and camera.fy must be positive")
    distortion = _array(path, cam_field("distortion"), "camera.distortion", (None,))
    if len(distortion) not in _DISTORTION_LENGTHS:
        raise RecordingError(f"{path}: camera.distortion has {len(distortion)} coefficients, "
                             f"expected one of {_DISTORTION_LENGTHS} (OpenCV model)")
    camera = CameraCalibration(
        width=width, height=height,
        K=np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]),
        distortion=distortion,
        C_camera_to_body=_rotation(path, cam_field("C_camera_to_body"),
                                   "camera.C_camera_to_body"),
        lever_arm_body=_array(path, cam_field("lever_arm_body"), "camera.lever_arm_body", (3,)),
    )
    antennas = _array(path, _get(path, data, "antennas_body"), "antennas_body", (None, 3))
    if len(antennas) == 0:
        raise RecordingError(f"{path}: antennas_body is empty")
    return Calibration(camera=camera, antennas_body=antennas,
                       imu=_parse_imu_calibration(path, data.get("imu")))


def _parse_imu_calibration(path: Path, imu: Any) -> ImuCalibration:
    # The section and each key are optional (a real IMU may come without a known error model);
    # an unknown key is rejected because it is almost certainly a misspelling.
    cal = ImuCalibration()
    if imu is None:
        return cal
    if not isinstance(imu, dict):
        raise RecordingError(f"{path}: imu must be a JSON object")
    shapes = {"gyro_scale_factor": (3,), "gyro_misalignment": (3, 3),
              "accel_scale_factor": (3,), "accel_misalignment": (3, 3), "lever_arm_body": (3,)}
    for key, value in imu.items():
        if key not in shapes:
            raise RecordingError(f"{path}: unknown field imu.{key} (expected some of "
                                 f"{', '.join(shapes)})")
        setattr(cal, key, _array(path, value, f"imu.{key}", shapes[key]))
    return cal


def _parse_hull(path: Path) -> Hull:
    data = _read_json(path)
    outline = _array(path, _get(path, data, "outline_body"), "outline_body", (None, 2))
    if len(outline) < 3:
        raise RecordingError(f"{path}: outline_body needs at least 3 points, has {len(outline)}")
    length = _number(path, _get(path, data, "length"), "length")
    beam = _number(path, _get(path, data, "beam"), "beam")
    if length <= 0 or beam <= 0:
        raise RecordingError(f"{path}: length and beam must be positive")
    berth = data.get("berth_line_ned")
    berth_line = None if berth is None else _array(path, berth, "berth_line_ned", (2, 2))
    height = data.get("body_origin_height_m")
    height = None if height is None else _number(path, height, "body_origin_height_m")
    sea = data.get("sea_surface_height_m")
    sea = None if sea is None else _number(path, sea, "sea_surface_height_m")
    if sea is not None and not -200.0 <= sea <= 200.0:
        raise RecordingError(f"{path}: sea_surface_height_m {sea} is not a height of the sea "
                             "above the ellipsoid (geoid heights lie within ±110 m)")
    sea_sigma = _number(path, data.get("sea_surface_sigma_m", 1.0), "sea_surface_sigma_m")
    if sea_sigma <= 0:
        raise RecordingError(f"{path}: sea_surface_sigma_m must be positive, got {sea_sigma}")
    freeboard = data.get("freeboard_m")
    freeboard = None if freeboard is None else _number(path, freeboard, "freeboard_m")
    if freeboard is not None and not 0.0 < freeboard <= 40.0:
        raise RecordingError(f"{path}: freeboard_m {freeboard} is not a deck height above the "
                             "waterline (0 … 40 m)")
    return Hull(outline_body=outline, length=length, beam=beam, berth_line_ned=berth_line,
                body_origin_height_m=height, sea_surface_height_m=sea,
                sea_surface_sigma_m=sea_sigma, freeboard_m=freeboard)


# -------------------------------------------------------------------------------- CSV


def read_calibration(path: str | Path) -> Calibration:
    """Read and check a ``calibration.json`` (e.g. an installation's, for a live session)."""
    return _parse_calibration(Path(path))


def read_hull(path: str | Path) -> Hull:
    """Read and check a ``hull.json``."""
    return _parse_hull(Path(path))


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise RecordingError(f"{path}: not UTF-8 text ({exc.reason})") from None


def _data_lines(path: Path, columns: Sequence[str]) -> tuple[list[str], np.ndarray]:
    """Check the header; return the data lines and their 1-based line numbers (blank lines
    and ``#`` comments skipped)."""
    lines = _read_lines(path)
    if not lines:
        raise RecordingError(f"{path}: empty file (expected the header {','.join(columns)})")
    header = [h.strip() for h in lines[0].split(",")]
    if header != list(columns):
        raise RecordingError(f"{path}: line 1: header is {lines[0].strip()!r}, expected "
                             f"{','.join(columns)!r}")
    numbers = [i for i in range(1, len(lines))
               if lines[i].strip() and not lines[i].lstrip().startswith("#")]
    return [lines[i] for i in numbers], np.array(numbers, dtype=int) + 1


def _read_numeric_csv(path: Path, columns: Sequence[str], torn: list[str] | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(data (N,k) float64, line numbers (N,)) of an all-numeric CSV; every value finite.

    With ``torn`` (a list for notes), a last line cut short by a power loss is dropped and
    noted there: files written live end every record with a newline, so an unterminated last
    line that does not parse, or has fewer decimals than the line before, is a torn write."""
    body, line_no = _data_lines(path, columns)
    k = len(columns)
    if torn is not None and body and _is_torn(path, body, k):
        torn.append(f"{path.name}: the last line ({line_no[-1]}) was cut short (a power loss "
                    "while recording?) and is left out")
        body, line_no = body[:-1], line_no[:-1]
    if not body:
        return np.empty((0, k)), line_no
    try:
        # fast path: numpy's C parser; on any error fall back to a line scan for the message
        data = np.loadtxt(body, delimiter=",", dtype=float, ndmin=2)
    except ValueError:
        data = None
    if data is None or data.shape[1] != k:
        _raise_bad_line(path, body, line_no, columns)
    bad = ~np.isfinite(data)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise RecordingError(f"{path}: line {line_no[row]}: {columns[col]} is "
                             f"{data[row, col]} (NaN/inf not allowed)")
    return data, line_no


def _is_torn(path: Path, body: list[str], k: int) -> bool:
    if rinex.ends_with_newline(path):
        return False
    last = body[-1].split(",")
    if len(last) != k:
        return True
    try:
        [float(v) for v in last]
    except ValueError:
        return True
    if len(body) < 2:
        return False
    before = body[-2].split(",")
    return len(before) == k and any(_decimals(a) < _decimals(b)
                                    for a, b in zip(last, before, strict=True))


def _decimals(field: str) -> int:
    head, dot, tail = field.strip().partition(".")
    return len(tail) if dot else 0


def _raise_bad_line(path: Path, body: list[str], line_no: np.ndarray,
                    columns: Sequence[str]) -> None:
    for text, n in zip(body, line_no, strict=True):
        fields = text.split(",")
        if len(fields) != len(columns):
            raise RecordingError(f"{path}: line {n}: {len(fields)} columns, expected "
                                 f"{len(columns)} ({','.join(columns)})")
        for name, value in zip(columns, fields, strict=True):
            try:
                float(value)
            except ValueError:
                raise RecordingError(f"{path}: line {n}: {name} is {value.strip()!r}, "
                                     "not a number") from None
    raise RecordingError(f"{path}: cannot parse as CSV with columns {','.join(columns)}")


def _check_increasing(path: Path, name: str, t: np.ndarray, line_no: np.ndarray) -> None:
    d = np.diff(t)
    bad = np.flatnonzero(d <= 0)
    if len(bad):
        k = bad[0] + 1
        what = "duplicates" if d[bad[0]] == 0 else "goes back from"
        raise RecordingError(f"{path}: line {line_no[k]}: {name} {t[k]:.6f} {what} the "
                             f"previous value {t[k - 1]:.6f} (line {line_no[k - 1]}); times must "
                             "strictly increase")


def _check_span(path: Path, t: np.ndarray, manifest: Manifest, what: str) -> None:
    # A stream must overlap the manifest's span: catches times written as time of week or
    # seconds since start instead of GPS seconds since 1980 (longer logs are fine).
    lo, hi = manifest.start_gpst, manifest.start_gpst + manifest.duration_s
    if len(t) == 0:
        raise RecordingError(f"{path}: no {what}")
    if t[-1] < lo - 1.0 or t[0] > hi + 1.0:
        raise RecordingError(
            f"{path}: {what} span {t[0]:.3f}..{t[-1]:.3f} s lies outside the recording "
            f"({lo:.3f}..{hi:.3f} s from manifest start_gpst/duration_s); times must be GPS "
            "seconds since 1980-01-06")


def _read_imu(path: Path, cut_short: bool = False) -> tuple[ImuData, list[str]]:
    """The IMU samples as logged. Time tags that do not increase are kept (a logger's clock
    can step back): the engine drops such samples and says so; the load notes them."""
    notes: list[str] = []
    data, line_no = _read_numeric_csv(path, IMU_COLUMNS, notes if cut_short else None)
    if len(data) < 2:
        raise RecordingError(f"{path}: needs at least 2 samples, has {len(data)}")
    back = np.flatnonzero(np.diff(data[:, 0]) <= 0)
    if len(back):
        k = back[0] + 1
        notes.append(f"{path.name}: {len(back)} time tag(s) do not increase, the first at line "
                     f"{line_no[k]} ({data[k, 0]:.6f} after {data[k - 1, 0]:.6f}): those "
                     "samples are dropped by the engine")
    return ImuData(time=data[:, 0].copy(), gyro=data[:, 1:4].copy(),
                   accel=data[:, 4:7].copy()), notes


def _read_frame_times(path: Path, torn: list[str] | None) -> np.ndarray:
    data, line_no = _read_numeric_csv(path, FRAME_COLUMNS, torn)
    if len(data) == 0:
        raise RecordingError(f"{path}: no frames")
    expected = np.arange(len(data))
    wrong = np.flatnonzero(data[:, 0] != expected)
    if len(wrong):
        k = wrong[0]
        raise RecordingError(f"{path}: line {line_no[k]}: frame is {data[k, 0]:g}, expected "
                             f"{k} (frames are numbered 0, 1, 2... one row per video frame)")
    _check_increasing(path, "time_gpst", data[:, 1], line_no)
    return data[:, 1].copy()


def _read_reference(path: Path) -> ReferenceTrajectory:
    data, line_no = _read_numeric_csv(path, REFERENCE_COLUMNS)
    if len(data) < 2:
        raise RecordingError(f"{path}: needs at least 2 samples, has {len(data)}")
    _check_increasing(path, "time_gpst", data[:, 0], line_no)
    return ReferenceTrajectory(time=data[:, 0].copy(), position_ned=data[:, 1:4].copy(),
                               llh_deg=data[:, 4:7].copy(), euler_deg=data[:, 7:10].copy(),
                               velocity_ned=data[:, 10:13].copy())


def _read_scene_points(path: Path) -> tuple[np.ndarray, list[str]]:
    body, line_no = _data_lines(path, SCENE_POINT_COLUMNS)
    points = np.empty((len(body), 3))
    kinds: list[str] = []
    for i, (text, n) in enumerate(zip(body, line_no, strict=True)):
        fields = [f.strip() for f in text.split(",")]
        if len(fields) != 4:
            raise RecordingError(f"{path}: line {n}: {len(fields)} columns, expected 4 "
                                 f"({','.join(SCENE_POINT_COLUMNS)})")
        for j in range(3):
            try:
                points[i, j] = float(fields[j])
            except ValueError:
                raise RecordingError(f"{path}: line {n}: {SCENE_POINT_COLUMNS[j]} is "
                                     f"{fields[j]!r}, not a number") from None
            if not math.isfinite(points[i, j]):
                raise RecordingError(f"{path}: line {n}: {SCENE_POINT_COLUMNS[j]} is "
                                     f"{fields[j]} (NaN/inf not allowed)")
        if not fields[3]:
            raise RecordingError(f"{path}: line {n}: empty kind")
        kinds.append(fields[3])
    return points, kinds


# ------------------------------------------------------------------------ video, GNSS


def _probe_video(path: Path) -> VideoInfo:
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise RecordingError(f"{path}: cannot open the video (unreadable or an unsupported "
                                 "codec)")
        ok, image = cap.read()
        if not ok or image is None:
            raise RecordingError(f"{path}: the video holds no decodable frame")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if count <= 0:
            # some containers do not record the count: decode through to count the frames
            count = 1
            while cap.grab():
                count += 1
        return VideoInfo(width=int(image.shape[1]), height=int(image.shape[0]),
                         fps=float(cap.get(cv2.CAP_PROP_FPS)), frame_count=count)
    finally:
        cap.release()


T = TypeVar("T")


def _rinex_call(path: Path, func: Callable[..., T], *args: Any) -> T:
    """Run a RINEX reader, turning its errors into RecordingError with the file named."""
    try:
        return func(*args)
    except ValueError as exc:  # RinexError, and a UnicodeDecodeError on a binary file
        msg = str(exc)
        if path.name not in msg:
            msg = f"{path}: {msg}"
        raise RecordingError(msg) from exc


def _load_gnss(root: Path, manifest: Manifest, manifest_path: Path, calibration: Calibration,
               torn: list[str] | None = None
               ) -> tuple[list[list[GnssEpoch]], list[ObsHeader]]:
    obs_files = manifest.files["gnss_obs"]
    n_ant = len(calibration.antennas_body)
    if len(obs_files) != n_ant:
        raise RecordingError(f"{manifest_path}: files.gnss_obs names {len(obs_files)} receivers "
                             f"but calibration.json antennas_body has {n_ant} antennas "
                             "(receiver i must be antenna i)")
    gnss: list[list[GnssEpoch]] = []
    headers: list[ObsHeader] = []
    for rel in obs_files:
        path = root / rel
        obs = _rinex_call(path, rinex.read_obs, path, torn is not None)
        if torn is not None and obs.cut_short:
            torn.append(f"{rel}: {obs.cut_short}")
        epochs = _rinex_call(path, rinex.l1_epochs, obs)
        if epochs and not any(e.satellites for e in epochs):
            types = "; ".join(f"{sys}: {' '.join(codes)}"
                              for sys, codes in obs.header.obs_types.items())
            raise RecordingError(f"{path}: no L1 pseudorange or carrier phase in any epoch "
                                 f"(observation types {types or 'none'})")
        times = np.array([e.time for e in epochs])
        if not len(times):
            gnss.append(epochs)  # a receiver that delivered nothing (judged with the others)
            headers.append(obs.header)
            continue
        d = np.diff(times)
        if (d <= 0).any():
            k = int(np.flatnonzero(d <= 0)[0]) + 1
            raise RecordingError(f"{path}: epoch {k + 1} "
                                 f"({datetime_from_gpst(times[k]).isoformat()} GPST) is not "
                                 "after the previous epoch")
        _check_span(path, times, manifest, "L1 observation epochs")
        gnss.append(epochs)
        headers.append(obs.header)
    if not any(gnss):
        raise RecordingError(f"{root / obs_files[0]}: no L1 observation epochs (nor in the other "
                             "receivers' files)")
    return gnss, headers


# ------------------------------------------------------------------------------- load


def check_manifest(path: str | Path) -> tuple[Path, Manifest]:
    """The recording directory at ``path`` (or its manifest.json) and its manifest, checked
    as far as that goes without reading the data: the manifest valid, every file it names
    there (what a listing can afford; ``load`` reads and checks the rest)."""
    root = Path(path)
    if root.is_file() and root.name == MANIFEST_FILE:
        root = root.parent
    if not root.is_dir():
        raise RecordingError(f"{root}: not a recording directory")
    manifest_path = root / MANIFEST_FILE
    if not manifest_path.is_file():
        raise RecordingError(f"{manifest_path}: missing manifest (not a recording directory?)")
    manifest = _parse_manifest(manifest_path)
    _check_files_exist(root, manifest_path, manifest.files)
    if not _cut_short(manifest):
        _check_whole_lines(root, manifest.files)
    return root, manifest


# The line-oriented files: each record a line, the last one ended like the others
_TEXT_FILE_KEYS = ("frame_times", "imu", "gnss_obs", "gnss_nav", "reference", "scene_points")


def _check_whole_lines(root: Path, files: dict[str, Any]) -> None:
    """Each text file ends with a line end: one that stops inside a line was cut short (a
    copy or a download broken off). Its last byte only, so a listing can afford it and says
    what opening it would (a user trial: a recording listed fine, then refused on open);
    a live recording that did not end cleanly is let through (``load`` leaves its torn
    record out)."""
    for key in _TEXT_FILE_KEYS:
        value = files.get(key)
        for rel in value if isinstance(value, list) else [value] if value else []:
            path = root / rel
            size = path.stat().st_size
            if not size:
                continue
            with path.open("rb") as f:
                f.seek(size - 1)
                if f.read(1) not in (b"\n", b"\r"):
                    raise RecordingError(f"{path}: ends inside a line, the file was cut short "
                                         f"({size} bytes)")


def load(path: str | Path, *, load_gnss: bool = True) -> Recording:
    """Read and validate a recording directory (or its manifest.json).

    With ``load_gnss=False`` the RINEX files are only checked to exist (fast, e.g. for the
    video alone): ``gnss`` and ``gnss_headers`` are empty and ``nav`` has no ephemerides.
    """
    root, manifest = check_manifest(path)
    manifest_path, files = root / MANIFEST_FILE, manifest.files

    calibration = _parse_calibration(root / files["calibration"])
    hull = _parse_hull(root / files["hull"])
    notes: list[str] = []
    # a live recording that did not end cleanly (power loss): its last records may be torn
    torn = notes if _cut_short(manifest) else None

    frames_path = root / files["frame_times"]
    frame_times = _read_frame_times(frames_path, torn)
    _check_span(frames_path, frame_times, manifest, "frame times")
    video_path = root / files["video"]
    video = _probe_video(video_path)
    if torn is not None and _torn_jpeg(video_path):
        torn.append(f"{files['video']}: the last frame was cut short and is left out")
        video = dataclasses.replace(video, frame_count=video.frame_count - 1)
        frame_times = frame_times[:video.frame_count]
    cam = calibration.camera
    if (video.width, video.height) != (cam.width, cam.height):
        raise RecordingError(f"{video_path}: frame size {video.width}x{video.height} does not "
                             f"match {files['calibration']} camera.width/height "
                             f"{cam.width}x{cam.height}")
    if video.frame_count != len(frame_times):
        notes.append(f"{files['video']} has {video.frame_count} frames but "
                     f"{files['frame_times']} lists {len(frame_times)}")

    imu_path = root / files["imu"]
    imu, imu_notes = _read_imu(imu_path, torn is not None)
    notes += imu_notes
    _check_span(imu_path, imu.time, manifest, "IMU samples")
    gaps = time_gaps(imu.time)
    if gaps:
        notes.append(f"{files['imu']} has {len(gaps)} gap(s), longest {max(g[1] for g in gaps):.3f}"
                     f" s at {gaps[0][0]:.3f}")
    notes += _early_ends(manifest, {files["imu"]: float(np.max(imu.time)),
                                    files["frame_times"]: float(frame_times[-1])})

    if load_gnss:
        gnss, headers = _load_gnss(root, manifest, manifest_path, calibration, torn)
        if len(gnss) < MIN_RECEIVERS:
            notes.append(f"{len(gnss)} receivers: the GNSS compass needs {MIN_RECEIVERS} for "
                         "its own attitude fix (the fusion then starts from the course over "
                         "ground, and holds the heading with the antennas it has)")
        elif len(gnss) != COMPASS_RECEIVERS:
            notes.append(f"{len(gnss)} receivers, not the compass's {COMPASS_RECEIVERS}: its "
                         "attitude from the baselines it has")
        notes += _early_ends(manifest, {rel: eps[-1].time for rel, eps in
                                        zip(files["gnss_obs"], gnss, strict=True) if eps})
        notes += [f"{rel}: no epochs (the receiver delivered none; the others' are used)"
                  for rel, eps in zip(files["gnss_obs"], gnss, strict=True) if not eps]
        nav_path = root / files["gnss_nav"]
        nav = _rinex_call(nav_path, rinex.read_nav, nav_path)
        if not nav.ephemerides:
            raise RecordingError(f"{nav_path}: no ephemerides")
    else:
        gnss, headers, nav = [], [], NavigationData()

    reference = None
    if files["reference"] is not None:
        reference = _read_reference(root / files["reference"])
    points = kinds = None
    if files["scene_points"] is not None:
        points, kinds = _read_scene_points(root / files["scene_points"])

    return Recording(path=root, manifest=manifest, calibration=calibration, hull=hull, imu=imu,
                     frame_times=frame_times, gnss=gnss, gnss_headers=headers, nav=nav,
                     reference=reference, scene_points=points, scene_point_kinds=kinds,
                     video_info=video, gnss_loaded=load_gnss, warnings=notes)


def _cut_short(manifest: Manifest) -> bool:
    live = manifest.extra.get("live")
    return isinstance(live, dict) and live.get("complete") is False


def _torn_jpeg(path: Path) -> bool:
    """A raw MJPEG video whose last JPEG lacks its end-of-image marker."""
    if path.suffix.lower() not in (".mjpeg", ".mjpg"):
        return False
    with path.open("rb") as f:
        f.seek(max(0, path.stat().st_size - 64))
        tail = f.read()
    return not tail.rstrip(b"\r\n\x00 ").endswith(b"\xff\xd9")  # padding after EOI is fine


def _early_ends(manifest: Manifest, last: dict[str, float]) -> list[str]:
    """Streams (file → last time tag) that end more than ``EARLY_END_S`` before the
    recording does."""
    end = manifest.start_gpst + manifest.duration_s
    return [f"{name} ends at {t - manifest.start_gpst:.1f} s of the recording's "
            f"{manifest.duration_s:g} s" for name, t in last.items() if t < end - EARLY_END_S]


def time_gaps(time: np.ndarray, factor: float = IMU_GAP_FACTOR) -> list[tuple[float, float]]:
    """(start time, length s) of every interval longer than ``factor`` x the median one (the
    IMU's samples, the video's frames)."""
    if len(time) < 2:
        return []
    d = np.diff(time)
    nominal = float(np.median(d))
    idx = np.flatnonzero(d > factor * nominal)
    return [(float(time[i]), float(d[i])) for i in idx]


# ---------------------------------------------------------------------------- summary


def _gpst_text(gpst: float) -> str:
    return datetime_from_gpst(gpst).isoformat(timespec="milliseconds") + " GPST"


def summary(rec: Recording) -> dict[str, Any]:
    """What a recording holds, as plain JSON-serialisable values (``berthing-aid info``)."""
    m, files = rec.manifest, rec.manifest.files
    week, tow = week_tow_from_gpst(m.start_gpst)
    info: dict[str, Any] = {
        "path": str(rec.path),
        "name": m.name,
        "scenario": m.scenario,
        "seed": m.seed,
        "start": {"gpst": m.start_gpst, "iso": _gpst_text(m.start_gpst), "week": week,
                  "tow": round(tow, 6)},
        "duration_s": m.duration_s,
        "origin_llh_deg": list(m.origin_llh_deg),
    }
    v = rec.video_info
    info["video"] = {
        "file": files["video"],
        "width": v.width if v else None,
        "height": v.height if v else None,
        # the rate the frame times give (a raw MJPEG stream's container says 25 whatever)
        "fps": round(1.0 / float(np.median(np.diff(rec.frame_times))), 3)
        if len(rec.frame_times) > 1 else None,
        "container_fps": v.fps if v else None,
        "frame_count": v.frame_count if v else None,
        "frame_times": len(rec.frame_times),
        "frame_count_mismatch": bool(v and v.frame_count != len(rec.frame_times)),
        "first_gpst": float(rec.frame_times[0]),
        "last_gpst": float(rec.frame_times[-1]),
        # frames missing (a camera silent for a while, a live feed that stalled)
        "gaps": [{"start_gpst": s, "length_s": round(d, 3)}
                 for s, d in time_gaps(rec.frame_times, VIDEO_GAP_FACTOR)],
    }
    t = rec.imu.time
    gaps = time_gaps(t)
    info["imu"] = {
        "file": files["imu"],
        "rate_hz": round(1.0 / float(np.median(np.diff(t))), 3),
        "count": len(rec.imu),
        "first_gpst": float(t[0]),
        "last_gpst": float(t[-1]),
        "gaps": [{"start_gpst": s, "length_s": round(d, 6)} for s, d in gaps],
    }
    receivers = []
    for rel, epochs, header in zip(files["gnss_obs"], rec.gnss, rec.gnss_headers, strict=False):
        receivers.append(_receiver_summary(rel, epochs, header))
    info["gnss"] = {"loaded": rec.gnss_loaded, "receivers": receivers}
    per_system: dict[str, dict[str, int]] = {}
    for sat, ephs in sorted(rec.nav.ephemerides.items()):
        entry = per_system.setdefault(sat[0], {"satellites": 0, "ephemerides": 0})
        entry["satellites"] += 1
        entry["ephemerides"] += len(ephs)
    info["nav"] = {"file": files["gnss_nav"], "loaded": rec.gnss_loaded, "systems": per_system}
    info["reference"] = {"present": rec.reference is not None,
                         "samples": len(rec.reference) if rec.reference is not None else 0}
    info["scene_points"] = len(rec.scene_points) if rec.scene_points is not None else None
    info["warnings"] = list(rec.warnings)
    return info


def _receiver_summary(rel: str, epochs: list[GnssEpoch], header: ObsHeader) -> dict[str, Any]:
    counts = np.array([len(e.satellites) for e in epochs])
    present = {sat[0] for e in epochs for sat in e.satellites}
    systems = sorted(present, key=lambda c: (_SYSTEM_ORDER.index(c) if c in _SYSTEM_ORDER
                                             else len(_SYSTEM_ORDER), c))
    slips = sum(1 for e in epochs for o in e.satellites.values() if o.lli & 1)
    times = np.array([e.time for e in epochs])
    steps = np.diff(times)
    interval = header.interval
    if interval is None and len(epochs) > 1:
        interval = float(np.median(steps))
    # epochs missing (a receiver silent for a while): spacing beyond 1.5 intervals
    holes = np.flatnonzero(steps > 1.5 * interval) if interval else np.zeros(0, int)
    return {
        "file": rel,
        "epochs": len(epochs),
        "interval_s": interval,
        "first_gpst": epochs[0].time if epochs else None,
        "last_gpst": epochs[-1].time if epochs else None,
        "satellites_per_epoch": {
            "min": int(counts.min()) if len(counts) else 0,
            "mean": round(float(counts.mean()), 2) if len(counts) else 0.0,
            "max": int(counts.max()) if len(counts) else 0,
        },
        "systems": "".join(systems),
        "cycle_slip_flags": slips,
        "gaps": [{"start_gpst": float(times[k]), "length_s": round(float(steps[k]), 3)}
                 for k in holes],
    }


def format_summary(info: dict[str, Any]) -> str:
    """Human-readable, aligned text of a ``summary`` dict."""
    rows: list[tuple[str, str]] = [("name", info["name"])]
    if info.get("scenario"):
        seed = info.get("seed")
        rows.append(("scenario", info["scenario"] + (f" (seed {seed})" if seed is not None
                                                       else "")))
    else:
        rows.append(("scenario", "real recording"))
    s = info["start"]
    rows.append(("start", f"{s['iso']}  (week {s['week']}, tow {s['tow']:.3f} s)"))
    rows.append(("duration", f"{info['duration_s']:.1f} s"))
    lat, lon, h = info["origin_llh_deg"]
    rows.append(("origin", f"lat {lat:.7f} deg, lon {lon:.7f} deg, h {h:.2f} m"))
    v = info["video"]
    fps = "?" if v["fps"] is None else f"{v['fps']:.1f}"
    rows.append(("video", f"{v['file']}: {v['width']}x{v['height']} @ {fps} fps, "
                          f"{v['frame_count']} frames (frame times: {v['frame_times']})"
                          + ("  MISMATCH" if v["frame_count_mismatch"] else "")
                          + (f", {len(v['gaps'])} gap(s), longest "
                             f"{max(g['length_s'] for g in v['gaps']):.1f} s at "
                             f"{v['gaps'][0]['start_gpst'] - info['start']['gpst']:.1f} s"
                             if v["gaps"] else "")))
    imu = info["imu"]
    gaps = imu["gaps"]
    gap_text = (f"{len(gaps)} gap(s), longest {max(g['length_s'] for g in gaps):.3f} s"
                if gaps else "no gaps")
    rows.append(("imu", f"{imu['file']}: {imu['count']} samples @ {imu['rate_hz']:.1f} Hz, "
                        f"{gap_text}"))
    gnss = info["gnss"]
    if not gnss["loaded"]:
        rows.append(("gnss", "not loaded"))
    for i, r in enumerate(gnss["receivers"], start=1):
        spe = r["satellites_per_epoch"]
        interval = f" @ {r['interval_s']:g} s" if r["interval_s"] else ""
        rows.append((f"gnss rx{i}",
                     f"{r['file']}: {r['epochs']} epochs{interval}, satellites "
                     f"{spe['min']}/{spe['mean']:.1f}/{spe['max']} (min/mean/max), systems "
                     f"{r['systems'] or '-'}, {r['cycle_slip_flags']} cycle-slip flags"
                     + (f", {len(r['gaps'])} gap(s), longest "
                        f"{max(g['length_s'] for g in r['gaps']):g} s" if r["gaps"] else "")))
    nav = info["nav"]
    if nav["loaded"]:
        per = ", ".join(f"{sys} {e['ephemerides']} ({e['satellites']} sats)"
                        for sys, e in nav["systems"].items())
        rows.append(("nav", f"{nav['file']}: {per or 'no ephemerides'}"))
    ref = info["reference"]
    rows.append(("reference", f"yes ({ref['samples']} samples)" if ref["present"] else "no"))
    sp = info["scene_points"]
    rows.append(("scene points", str(sp) if sp is not None else "none"))
    for w in info["warnings"]:
        rows.append(("warning", w))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k.ljust(width)}  {val}" for k, val in rows)


# ---------------------------------------------------------------------------- writers


def _write_json(path: Path, data: dict[str, Any]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    return path


def _finite(values: np.ndarray, what: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if not np.isfinite(arr).all():
        raise RecordingError(f"{what}: refusing to write NaN/inf")
    return arr


def _list(values: Any) -> list:
    return np.asarray(values, dtype=float).tolist()


def write_manifest(directory: str | Path, manifest: Manifest) -> Path:
    """Write ``manifest.json``."""
    clash = set(manifest.extra) & set(_MANIFEST_KEYS)
    if clash:
        raise RecordingError(f"manifest extra keys {sorted(clash)} clash with standard fields")
    data: dict[str, Any] = {
        "format": FORMAT_NAME,
        "version": manifest.version,
        "name": manifest.name,
        "scenario": manifest.scenario,
        "seed": manifest.seed,
        "start_gpst": float(manifest.start_gpst),
        "duration_s": float(manifest.duration_s),
        "origin_llh_deg": [float(x) for x in manifest.origin_llh_deg],
        "files": manifest.files,
        **manifest.extra,
    }
    return _write_json(Path(directory) / MANIFEST_FILE, data)


def write_calibration(directory: str | Path, calibration: Calibration) -> Path:
    """Write ``calibration.json`` (the intrinsics must be a plain pinhole K without skew)."""
    cam = calibration.camera
    K = np.asarray(cam.K, dtype=float)
    if K.shape != (3, 3) or K[0, 1] != 0 or K[1, 0] != 0 or K[2].tolist() != [0, 0, 1]:
        raise RecordingError(f"calibration camera.K {K.tolist()} cannot be written as "
                             "fx, fy, cx, cy (skew or non-standard last row)")
    imu = calibration.imu
    data = {
        "camera": {
            "width": int(cam.width), "height": int(cam.height),
            "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
            "cy": float(K[1, 2]),
            "distortion": _list(cam.distortion),
            "C_camera_to_body": _list(cam.C_camera_to_body),
            "lever_arm_body": _list(cam.lever_arm_body),
        },
        "antennas_body": _list(calibration.antennas_body),
        "imu": {
            "gyro_scale_factor": _list(imu.gyro_scale_factor),
            "gyro_misalignment": _list(imu.gyro_misalignment),
            "accel_scale_factor": _list(imu.accel_scale_factor),
            "accel_misalignment": _list(imu.accel_misalignment),
            "lever_arm_body": _list(imu.lever_arm_body),
        },
    }
    return _write_json(Path(directory) / CALIBRATION_FILE, data)


def write_hull(directory: str | Path, hull: Hull) -> Path:
    """Write ``hull.json``."""
    data: dict[str, Any] = {
        "outline_body": _list(hull.outline_body),
        "length": float(hull.length),
        "beam": float(hull.beam),
        "berth_line_ned": None if hull.berth_line_ned is None else _list(hull.berth_line_ned),
        "body_origin_height_m": hull.body_origin_height_m,
        "sea_surface_height_m": hull.sea_surface_height_m,
        "sea_surface_sigma_m": float(hull.sea_surface_sigma_m),
        "freeboard_m": hull.freeboard_m,
    }
    return _write_json(Path(directory) / HULL_FILE, data)


def _write_csv(path: Path, columns: Sequence[str], data: np.ndarray, fmt: Sequence[str]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, data, fmt=list(fmt), delimiter=",", header=",".join(columns), comments="",
               newline="\n", encoding="utf-8")
    return path


def write_imu(directory: str | Path, imu: ImuData) -> Path:
    """Write ``imu.csv`` (time to 1 µs, gyro and accel to 1e-9)."""
    t = _finite(imu.time, "imu.time")
    n = len(t)
    gyro = _finite(imu.gyro, "imu.gyro").reshape(n, 3)
    accel = _finite(imu.accel, "imu.accel").reshape(n, 3)
    data = np.column_stack([t, gyro, accel])
    return _write_csv(Path(directory) / IMU_FILE, IMU_COLUMNS, data, ["%.6f"] + ["%.9f"] * 6)


def write_frame_times(directory: str | Path, times: np.ndarray) -> Path:
    """Write ``frames.csv``: frame i (0-based) and its GPS time."""
    t = _finite(times, "frame times").ravel()
    data = np.column_stack([np.arange(len(t)), t])
    return _write_csv(Path(directory) / FRAMES_FILE, FRAME_COLUMNS, data, ["%d", "%.6f"])


def write_reference(directory: str | Path, ref: ReferenceTrajectory) -> Path:
    """Write ``reference/trajectory.csv``."""
    data = np.column_stack([ref.time, ref.position_ned, ref.llh_deg, ref.euler_deg,
                            ref.velocity_ned])
    _finite(data, "reference trajectory")
    fmt = (["%.6f"] + ["%.6f"] * 3 + ["%.10f", "%.10f", "%.6f"] + ["%.8f"] * 3
           + ["%.6f"] * 3)
    return _write_csv(Path(directory) / REFERENCE_FILE, REFERENCE_COLUMNS, data, fmt)


def write_scene_points(directory: str | Path, points: np.ndarray, kinds: Sequence[str]) -> Path:
    """Write ``reference/scene_points.csv``."""
    pts = _finite(points, "scene points").reshape(-1, 3)
    if len(kinds) != len(pts):
        raise RecordingError(f"scene points: {len(pts)} points but {len(kinds)} kinds")
    for kind in kinds:
        if not kind or "," in kind or "\n" in kind or kind != kind.strip():
            raise RecordingError(f"scene points: kind {kind!r} must be a non-empty word "
                                 "without commas")
    path = Path(directory) / SCENE_POINTS_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [",".join(SCENE_POINT_COLUMNS)]
    lines += [f"{p[0]:.6f},{p[1]:.6f},{p[2]:.6f},{k}" for p, k in zip(pts, kinds, strict=True)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


class VideoWriter:
    """``video.mp4`` writer: a context manager around cv2.VideoWriter ('mp4v', 10 fps)."""

    def __init__(self, path: str | Path, size: tuple[int, int], fps: float = VIDEO_FPS) -> None:
        self.path = Path(path)
        self.size = (int(size[0]), int(size[1]))  # width, height
        self.fps = fps
        self.count = 0
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot open a video writer ({exc})") from exc
        self._writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                       self.size)
        if not self._writer.isOpened():
            raise RecordingError(f"{self.path}: cannot open a video writer ('mp4v', "
                                 f"{self.size[0]}x{self.size[1]} @ {fps} fps)")

    def write(self, image: np.ndarray) -> None:
        """Append one BGR uint8 frame of the writer's size."""
        expected = (self.size[1], self.size[0], 3)
        if image.shape != expected or image.dtype != np.uint8:
            # cv2 silently drops frames of the wrong size: refuse them instead
            raise RecordingError(f"{self.path}: frame {self.count} is {image.dtype} "
                                 f"{image.shape}, expected uint8 {expected}")
        self._writer.write(image)
        self.count += 1

    def close(self) -> None:
        self._writer.release()

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
