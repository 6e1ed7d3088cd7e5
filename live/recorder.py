"""Recording while live: a live session's messages written in the recording format as they come.

The result is an ordinary recording (``recordings/README.md``) that replays and scores like
any other: ``gnss/rx1.obs`` … ``rx4.obs`` (RINEX 3, the project's writer, from the decoded
RAWX epochs), ``gnss/nav.rnx`` (the ephemerides assembled from SFRBX, and the seed),
``video.mjpeg`` with ``frames.csv``, ``imu.csv``, ``calibration.json`` and ``hull.json`` of the
installation, and ``manifest.json``.

Power loss: every record (a CSV line, an observation epoch, a frame) is written whole with one
``write`` and flushed at once, and the files are ``fsync``-ed every ``SYNC_S``; the video is
raw MJPEG (concatenated JPEGs: no index or trailer to write at the end, a cut frame is just
the last, undecodable one); ``manifest.json`` and ``nav.rnx`` are replaced atomically
(written beside, then renamed) whenever they change, the manifest's ``duration_s`` at every
sync. A recording cut at any instant therefore loads up to the last sync (a record being
written at the cut may be lost with it). ``manifest.json → live`` says whether the session
ended cleanly (``"complete": true``) and what the inputs lost.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

from engine.messages import FrameMessage, GnssMessage, ImuMessage
from estimator.frames import geodetic_to_ecef
from estimator.records import Calibration, GnssEpoch, Hull, NavigationData
from recordings.format import (
    FRAME_COLUMNS,
    IMU_COLUMNS,
    Manifest,
    default_files,
    write_calibration,
    write_hull,
    write_manifest,
)
from recordings.rinex import obs_epoch_lines, obs_header, write_nav

__all__ = ["SYNC_S", "VIDEO_FILE", "LiveRecorder"]

SYNC_S = 1.0
VIDEO_FILE = "video.mjpeg"
JPEG_QUALITY = 90
RECORDED_SYSTEMS = "GEJC"  # written to the observation headers (GLONASS when its slots are known)


class LiveRecorder:
    """Writes one live recording into ``directory`` (new or empty)."""

    def __init__(self, directory: str | Path, *, name: str, calibration: Calibration,
                 hull: Hull, origin_llh_deg: tuple[float, float, float], receivers: int = 4):
        self.directory = Path(directory)
        if self.directory.exists() and any(self.directory.iterdir()):
            raise FileExistsError(f"{self.directory}: not empty; a live recording needs a new "
                                  "directory")
        (self.directory / "gnss").mkdir(parents=True, exist_ok=True)
        self.name = name
        self.origin_llh_deg = origin_llh_deg
        self.receivers = receivers
        write_calibration(self.directory, calibration)
        write_hull(self.directory, hull)
        files = default_files(receivers, reference=False)
        files["video"] = VIDEO_FILE
        self.files = files
        self._imu = self._open(files["imu"], ",".join(IMU_COLUMNS) + "\n")
        self._frames_csv = self._open(files["frame_times"], ",".join(FRAME_COLUMNS) + "\n")
        self._video = (self.directory / VIDEO_FILE).open("wb")
        self._obs: list[IO[str] | None] = [None] * receivers
        self._obs_systems: list[str] = [""] * receivers
        self.dropped_satellites = 0  # of systems not in a file's header
        self.frames = 0
        self.imu_samples = 0
        self.epochs = [0] * receivers
        self.start_gpst: float | None = None
        self.last_gpst: float | None = None
        self._nav_count = -1
        self._last_sync = time.monotonic()
        self.notes: dict[str, Any] = {}
        self.closed = False

    def _open(self, rel: str, header: str) -> IO[str]:
        f = (self.directory / rel).open("w", encoding="ascii", newline="\n")
        f.write(header)
        f.flush()
        return f

    # ------------------------------------------------------------------ records

    def write(self, msg: ImuMessage | GnssMessage | FrameMessage, nav: NavigationData,
              glonass_slots: dict[str, int] | None = None) -> None:
        """One message of the live merge (time order), ``nav``: the ephemerides so far."""
        if self.closed:
            return
        if self.start_gpst is None:
            self.start_gpst = msg.t
        self.last_gpst = msg.t
        if isinstance(msg, ImuMessage):
            self._imu.write("{:.6f},{:.9f},{:.9f},{:.9f},{:.9f},{:.9f},{:.9f}\n".format(
                msg.t, *msg.gyro, *msg.accel))
            self._imu.flush()
            self.imu_samples += 1
        elif isinstance(msg, GnssMessage):
            for i, epoch in enumerate(msg.epochs):
                if epoch is not None:
                    self._write_epoch(i, epoch, glonass_slots or {})
        elif isinstance(msg, FrameMessage):
            jpeg = msg.jpeg  # an MJPEG camera's frame is kept as it came, not re-encoded
            if jpeg is None:
                ok, encoded = cv2.imencode(".jpg", msg.image,
                                           [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
                if not ok:
                    raise RuntimeError(f"frame {self.frames}: JPEG encoding failed")
                jpeg = encoded.tobytes()
            self._video.write(jpeg)
            self._video.flush()
            self._frames_csv.write(f"{self.frames},{msg.t:.6f}\n")
            self._frames_csv.flush()
            self.frames += 1
        self._maybe_nav(nav)
        if time.monotonic() - self._last_sync >= SYNC_S:
            self.sync()

    def _open_obs(self, i: int, t: float, slots: dict[str, int]) -> IO[str]:
        """Receiver ``i``'s observation file, its header written (first epoch at ``t``)."""
        f = self._obs[i]
        if f is None:
            glonass = {s: k for s, k in slots.items() if s[0] == "R"}
            systems = [s for s in "GREJC" if s in RECORDED_SYSTEMS or (s == "R" and glonass)]
            lat, lon, h = (np.radians(self.origin_llh_deg[0]), np.radians(self.origin_llh_deg[1]),
                           self.origin_llh_deg[2])
            header = obs_header(systems, t, marker_name=f"{self.name} antenna {i + 1}",
                                receiver_type="LIVE UBX", approx_position_ecef=geodetic_to_ecef(
                                    lat, lon, h), interval=1.0,
                                comments=["written live by berthing-aid from UBX RXM-RAWX"],
                                glonass_slots=glonass or None)
            f = (self.directory / self.files["gnss_obs"][i]).open("w", encoding="ascii",
                                                                   newline="\n")
            f.write("\n".join(header) + "\n")
            self._obs[i] = f
            self._obs_systems[i] = "".join(systems)
        return f

    def _write_epoch(self, i: int, epoch: GnssEpoch, slots: dict[str, int]) -> None:
        f = self._open_obs(i, epoch.time, slots)
        kept = {s: o for s, o in epoch.satellites.items() if s[0] in self._obs_systems[i]
                and (s[0] != "R" or s in slots)}
        self.dropped_satellites += len(epoch.satellites) - len(kept)
        lines = obs_epoch_lines(GnssEpoch(epoch.time, kept, epoch.flag))
        f.write("\n".join(lines) + "\n")
        f.flush()
        self.epochs[i] += 1

    def _maybe_nav(self, nav: NavigationData) -> None:
        count = sum(len(v) for v in nav.ephemerides.values())
        if count == self._nav_count or count == 0:
            return
        self._nav_count = count
        path = self.directory / self.files["gnss_nav"]
        tmp = path.with_suffix(".tmp")
        write_nav(tmp, nav)
        _fsync_path(tmp)
        os.replace(tmp, path)

    # ------------------------------------------------------------------ sync

    def sync(self, complete: bool = False) -> None:
        """Flush to disk and rewrite the manifest (atomically) with the span so far."""
        self._last_sync = time.monotonic()
        for f in (self._imu, self._frames_csv, self._video, *self._obs):
            if f is not None and not f.closed:
                f.flush()
                os.fsync(f.fileno())
        if self.start_gpst is None or self.last_gpst is None:
            return
        # every receiver the manifest names has its file, if only a header: one that never
        # delivered made the whole recording unreadable (a user trial)
        for i, f in enumerate(self._obs):
            if f is None:
                self._open_obs(i, self.start_gpst, {}).flush()
        manifest = Manifest(version=1, name=self.name, scenario=None, seed=None,
                            start_gpst=self.start_gpst,
                            duration_s=max(self.last_gpst - self.start_gpst, 0.0),
                            origin_llh_deg=list(self.origin_llh_deg), files=self.files,
                            extra={"live": {"complete": complete, **self.notes}})
        written = write_manifest(self.directory / ".pending", manifest)
        _fsync_path(written)
        os.replace(written, self.directory / written.name)  # atomic: old or new, never half

    def close(self) -> None:
        if self.closed:
            return
        self.sync(complete=True)
        self.closed = True
        for f in (self._imu, self._frames_csv, self._video, *self._obs):
            if f is not None:
                f.close()

    def status(self) -> dict[str, Any]:
        return {"directory": str(self.directory), "recording": not self.closed,
                "frames": self.frames, "imu_samples": self.imu_samples,
                "epochs": list(self.epochs),
                "duration_s": 0.0 if self.start_gpst is None or self.last_gpst is None
                else round(self.last_gpst - self.start_gpst, 3)}


def _fsync_path(path: Path) -> None:
    with path.open("rb") as f:
        os.fsync(f.fileno())
