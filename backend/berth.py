"""A session's berth line: set from two (north, east) points, from two pixels of a frame, or
given by the recording; the bow and stern distance and approach speed against it."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.camera import Projector, camera_pose, water_plane_point
from recordings.format import Recording

from .errors import Unprocessable
from .geometry import berth_metrics

MIN_LENGTH_M = 0.1  # the two points of a berth line at least this far apart


@dataclass
class BerthLine:
    line_ne: np.ndarray  # (2,2) north, east
    source: str  # "recording", "ned" or "image"
    # "world": the engine's frame; "recording": the recording's local level (hull.json), mapped
    # to the world frame through the fused absolute position (SPP-anchored: metre-level)
    frame: str = "world"


class Berth:
    """The berth line of a session (``line`` may be None)."""

    def __init__(self, rec: Recording, projector: Projector, water_down_m: float,
                 origin_in_recording: Callable[[Any], np.ndarray], lock: threading.RLock
                 ) -> None:
        self.rec = rec
        self.projector = projector
        self.water_down_m = water_down_m
        self._origin_in_recording = origin_in_recording
        self.lock = lock
        self.line: BerthLine | None = None
        if rec.hull.berth_line_ned is not None:
            self.line = BerthLine(np.asarray(rec.hull.berth_line_ned, float).reshape(2, 2),
                                  "recording", frame="recording")

    def set_ned(self, line_ne: np.ndarray, source: str = "ned") -> BerthLine:
        line = np.asarray(line_ne, dtype=float).reshape(2, 2)
        if np.linalg.norm(line[1] - line[0]) < MIN_LENGTH_M:
            raise Unprocessable(f"the berth line's two points are less than {MIN_LENGTH_M:g} m "
                                "apart")
        with self.lock:
            self.line = BerthLine(line, source)
            return self.line

    def set_image(self, state: Any, points_uv: np.ndarray) -> BerthLine:
        """Berth line from two pixels on the quay's water line of the frame of ``state`` (their
        rays meet the water plane)."""
        pose = camera_pose(state, self.rec.calibration.camera)
        p = self.projector
        ends = []
        for u, v in np.asarray(points_uv, dtype=float).reshape(2, 2):
            if not (-0.5 <= u <= p.width - 0.5 and -0.5 <= v <= p.height - 0.5):
                raise Unprocessable(f"pixel ({u:g}, {v:g}) is outside the {p.width}x{p.height}"
                                    " image")
            hit = water_plane_point(pose.position_ned, p.pixel_ray(pose, u, v),
                                    self.water_down_m)
            if hit is None:
                raise Unprocessable(f"pixel ({u:g}, {v:g}) is above the horizon: its ray does "
                                    "not meet the water plane")
            ends.append(hit[:2])
        return self.set_ned(np.array(ends), source="image")

    def clear(self) -> None:
        with self.lock:
            self.line = None

    def world(self, state: Any | None) -> np.ndarray | None:
        """The line in the engine's world frame (None without a line, or for a recording's
        line before the first fused state)."""
        line = self.line
        if line is None:
            return None
        if line.frame == "world":
            return line.line_ne
        if state is None:
            return None
        return line.line_ne - self._origin_in_recording(state)[:2]

    def status(self, state: Any | None, start_gpst: float) -> dict[str, Any]:
        """The line with the bow/stern distance and approach speed at ``state``."""
        with self.lock:
            line = self.line
        out: dict[str, Any] = {"line_ne": None, "source": None, "t": None,
                               "bow_distance_m": None, "stern_distance_m": None,
                               "bow_approach_mps": None, "stern_approach_mps": None}
        if line is None:
            return out
        out["source"] = line.source
        world = self.world(state)
        if world is not None:
            out["line_ne"] = world.round(3).tolist()
        if state is not None and world is not None:
            out["t"] = float(state.time) - start_gpst
            out.update(berth_metrics(state, self.rec.hull, world))
        return out
