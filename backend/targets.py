"""A session's designated targets: what the API and the stream serve of each (its track over
time, its status in the current frame). Designation and following are the engine path's
(``engine.targets``), shared with the evaluation; this module keeps the targets of one
session and turns them into readouts."""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from engine.camera import CameraPose, Projector, camera_pose
from engine.targets import (
    Designation,
    DesignationError,
    FollowedTarget,
    Structure,
    camera_view,
    designate,
)
from estimator.tracking import range_with_sigma
from recordings.format import Recording

from .errors import Conflict, NotFound, Unprocessable
from .geometry import hull_outline_ne
from .overlay import TargetInput, target_readout

log = logging.getLogger(__name__)

Frame = tuple[int, float, np.ndarray]  # index, gpst, BGR image
# A click this close (px) to a target's on the same frame is that target again (a double
# click: a user trial's 12 clicks in 1.3 s made 12 identical targets, labels piled up).
SAME_CLICK_PX = 3.0


@dataclass
class Target:
    id: str
    label: str | None
    designation: Designation
    position_ned: np.ndarray
    designated_gpst: float  # replay time when designated
    frame_gpst: float  # time of the frame whose pixel was clicked
    uv: tuple[float, float]
    track: list[dict[str, Any]] = field(default_factory=list)
    # Image tracking (``engine.targets.FollowedTarget``): the clicked point followed in the
    # video frame by frame, its 3-D point refined from the tracked views; "lost" is shown
    # (the distance is then that of the 3-D point, not of a point seen in this frame).
    follower: FollowedTarget | None = None
    status: str = "tracking"  # "tracking" | "lost"
    tracked_uv: tuple[float, float] | None = None
    score: float | None = None
    reason: str = ""
    distance_sigma_m: float | None = None  # 1-σ of the distance from the 3-D point's covariance

    @property
    def method(self) -> str:
        return self.designation.method

    @property
    def support(self) -> int:
        return len(self.designation.anchor_ids)

    @property
    def views(self) -> int:
        """Tracked views the 3-D point is triangulated from (0: the click's point)."""
        return 0 if self.follower is None else self.follower.tracker.refined_views


class TargetBook:
    """The targets of one session (all methods take the session's lock)."""

    def __init__(self, rec: Recording, projector: Projector, lock: threading.RLock) -> None:
        self.rec = rec
        self.projector = projector
        self.lock = lock
        self._targets: dict[str, Target] = {}
        self._counter = 0

    def designate(self, state: Any, now: Any, u: float, v: float, label: str | None,
                  structure: Structure, water_down_m: float | None,
                  earlier: Callable[[], list[tuple[float, np.ndarray]]], image: np.ndarray,
                  later: Iterable[tuple[Frame, Any]]) -> Target:
        """A target at pixel (u, v) of the frame of ``state`` (``now``: the latest state);
        ``earlier`` gives the frames before it (decoded only for a structure point),
        ``later`` the frames after it already played with their states."""
        p = self.projector
        if not (-0.5 <= u <= p.width - 0.5 and -0.5 <= v <= p.height - 0.5):
            raise Unprocessable(f"pixel ({u:g}, {v:g}) is outside the {p.width}x{p.height} "
                                "image")
        with self.lock:
            same = next((t for t in self._targets.values()
                         if abs(t.frame_gpst - float(state.time)) < 1e-3
                         and math.hypot(t.uv[0] - u, t.uv[1] - v) <= SAME_CLICK_PX), None)
        if same is not None:  # a double click, or the same request again
            raise Conflict(f"{same.id} already measures pixel ({same.uv[0]:g}, "
                           f"{same.uv[1]:g}) of this frame")
        view = camera_view(state, self.rec.calibration.camera)
        if water_down_m is not None and self.on_own_hull(state, view, u, v, water_down_m):
            raise Unprocessable(f"pixel ({u:g}, {v:g}) is on the ship herself (her deck or "
                                "side in view): nothing there to measure")
        try:
            des = designate(p, view, u, v, structure, water_down_m)
        except DesignationError as exc:
            raise Unprocessable(str(exc)) from None
        before = earlier() if des.method == "structure" else []
        index = int(np.argmin(np.abs(np.asarray(self.rec.frame_times, float) - state.time)))
        with self.lock:
            self._counter += 1
            target = Target(id=f"T{self._counter}", label=label, designation=des,
                            position_ned=des.position_ned, designated_gpst=float(now.time),
                            frame_gpst=float(state.time), uv=(u, v))
            self._start(target, image, view, index, before, structure)
            for (i, _t, img), st in later:
                if i > index:
                    self._follow(target, st, i, img, structure)
            self._targets[target.id] = target
            self._track(target, now)
        return target

    def on_own_hull(self, state: Any, view: Any, u: float, v: float, water_down_m: float
                    ) -> bool:
        """Whether pixel (u, v) shows the ship herself: its ray, from the camera down to the
        water, passes through the hull (the outline from the waterline up to the deck,
        ``Hull.freeboard_m``; False when the recording does not give it)."""
        freeboard = self.rec.hull.freeboard_m
        pose = CameraPose(view.C_level_to_camera, view.position_ned)
        ray = self.projector.pixel_ray(pose, u, v)
        if freeboard is None or ray[2] <= 1e-6:
            return False
        deck_down = water_down_m - freeboard
        # from where the ray is at deck height (or the camera, if below it) to the water
        start = max(0.0, (deck_down - pose.position_ned[2]) / ray[2])
        end = (water_down_m - pose.position_ned[2]) / ray[2]
        if end <= start:
            return False
        outline = hull_outline_ne(state, self.rec.hull).astype(np.float32)
        for s in np.linspace(start, end, 12):
            north, east = pose.position_ned[:2] + s * ray[:2]
            if cv2.pointPolygonTest(outline, (float(north), float(east)), False) >= 0:
                return True
        return False

    def _start(self, target: Target, image: np.ndarray, view: Any, index: int,
               earlier: list[tuple[float, np.ndarray]], structure: Structure) -> None:
        try:
            target.follower = FollowedTarget(self.projector, target.designation, image,
                                             target.uv, view, index, earlier, structure.views)
            target.position_ned = target.follower.position_ned
        except Exception as exc:  # no image tracking: the target keeps its 3-D point, lost
            log.exception("the image tracker of target %s could not start", target.id)
            target.status, target.reason = "lost", f"image tracking unavailable: {exc}"
            # its distance still has the designation's σ (a click by the image's edge showed
            # "114 m" with none)
            target.distance_sigma_m = range_with_sigma(
                target.position_ned, target.designation.covariance, view.position_ned)[1]
            return
        target.tracked_uv, target.score = target.uv, 1.0
        # Its σ from the click on: a frame drawn before the next one is followed shows it too.
        target.distance_sigma_m = target.follower.tracker.distance(view)[1]

    def on_frame(self, state: Any, index: int, image: np.ndarray, structure: Structure
                 ) -> None:
        """Track every target in a new frame and extend the tracks (lock held)."""
        for target in self._targets.values():
            self._follow(target, state, index, image, structure)
            self._track(target, state)

    def _follow(self, target: Target, state: Any, index: int, image: np.ndarray,
                structure: Structure) -> None:
        """One frame of a target's image tracking."""
        follower = target.follower
        if follower is None or index == follower.frame_index:
            return
        try:
            st = follower.follow(index, image, camera_view(state, self.rec.calibration.camera),
                                 structure)
        except Exception:  # a tracking failure must not stop the replay
            log.exception("tracking target %s failed on frame %d", target.id, index)
            target.status, target.reason = "lost", "tracking failed"
            follower.frame_index = -2
            return
        target.position_ned = follower.position_ned
        target.status = st.status
        target.tracked_uv = None if st.uv is None else (float(st.uv[0]), float(st.uv[1]))
        target.score = st.score
        target.reason = st.reason
        target.distance_sigma_m = st.distance_sigma_m

    def _track(self, target: Target, state: Any) -> None:
        pose = camera_pose(state, self.rec.calibration.camera)
        visible, uv = self.projector.project_points(pose, target.position_ned[None])
        entry: dict[str, Any] = {
            "t": round(float(state.time) - float(self.rec.manifest.start_gpst), 6),
            "gpst": float(state.time),
            "position_ned": np.round(target.position_ned, 4).tolist(),
            "visible": bool(visible[0]),
            "uv": np.round(uv[0], 2).tolist() if visible[0] else None,
            "status": target.status,
            "tracked_uv": None if target.tracked_uv is None else
            [round(target.tracked_uv[0], 2), round(target.tracked_uv[1], 2)],
            "score": None if target.score is None else round(float(target.score), 3),
            "reason": target.reason,
            "distance_sigma_m": _rounded(target.distance_sigma_m),
        }
        entry.update(target_readout(target.position_ned, pose, hull_outline_ne(state,
                                                                               self.rec.hull)))
        if target.track and target.track[-1]["gpst"] == entry["gpst"]:
            target.track[-1] = entry
        else:
            target.track.append(entry)

    def rewind(self, t: float | None) -> None:
        """The replay went back to gpst ``t`` (the start when None): tracks are cut there and
        the trackers resume from their 3-D points (lock held)."""
        for target in self._targets.values():
            target.track = [p for p in target.track if t is not None and p["gpst"] <= t]
            if target.follower is not None:
                target.follower.frame_index = -2

    def readouts(self, entries: list[dict[str, Any]]) -> None:
        """The overlay's target readouts with the image tracking: drawn at the tracked point,
        and a lost one not drawn on the video, its label saying so (lock held)."""
        for entry in entries:
            target = self._targets.get(entry.get("id"))
            if target is None:
                continue
            entry["status"] = target.status
            entry["distance_sigma_m"] = _rounded(target.distance_sigma_m)
            if target.status == "tracking" and target.tracked_uv is not None:
                entry["uv"] = [round(target.tracked_uv[0], 1), round(target.tracked_uv[1], 1)]
                entry["visible"] = True
            elif target.status == "lost":
                entry["visible"], entry["uv"] = False, None
                entry["label"] = f"{target.label or target.id} (lost)"
                entry["reason"] = target.reason

    def inputs(self) -> list[TargetInput]:
        """What the overlay draws of the targets (lock held)."""
        return [TargetInput(t.id, t.position_ned, t.label) for t in self._targets.values()]

    def all(self) -> list[Target]:
        with self.lock:
            return list(self._targets.values())

    def get(self, target_id: str) -> Target:
        with self.lock:
            if target_id not in self._targets:
                raise NotFound(f"no target {target_id!r} in this session (targets: "
                               f"{', '.join(self._targets) or 'none'})")
            return self._targets[target_id]

    def clear(self) -> None:
        with self.lock:
            self._targets.clear()

    def delete(self, target_id: str) -> None:
        with self.lock:
            self.get(target_id)
            del self._targets[target_id]


def _rounded(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 3)
