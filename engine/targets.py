"""Designated targets on the engine path: a click turned into a 3-D point (``designate``) and
the target followed frame by frame (``FollowedTarget``). The server's sessions and the
tracking evaluation both use these, so the evaluation measures what the officer sees.

A click takes the port-structure points near its image ray (the nearest surface under the
click, ``estimator.tracking.structure_point_at``), else the point where the ray meets the water
plane. From that frame on the point is tracked in the video (``DesignatedTarget``: image
tracker + a landmark EKF), tracked back through the frames before the click, and re-anchored /
triangulated on the port structure at most once a second (``TARGET_REFRESH_S``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from estimator.landmarks import SolvedViews, camera_pose_covariance
from estimator.records import CameraCalibration, CameraView
from estimator.tracking import (
    DESIGNATION_RADIUS_PX,
    DesignatedTarget,
    TargetParams,
    TargetState,
    depth_edge,
    point_on_ray,
    shows_surface,
    structure_point_at,
    under_water,
)

from .camera import CameraPose, Projector, camera_pose, water_plane_point

TARGET_REFRESH_S = 1.0  # a target is refreshed on the port structure at most this often
TARGET_WINDOW_PX = 31  # template side of the image tracker at 960 px of image width
# What stands on the water up to a quay's top (its face, fenders, moored hulls): a click the
# port structure does not place may be on any of it, nearer than where its ray meets the water.
WATER_PLANE_STANDING_M = 3.0
# Farther than this fraction of focal length x camera height, one pixel of the click moves
# where its ray meets the water by more than that fraction: no distance to give (a user trial
# read "796 m ±398" for a quay corner 37 m off, before the structure had points there).
WATER_PLANE_MAX_PIXEL_FRACTION = 0.1


class DesignationError(ValueError):
    """Nothing to designate under a click (no structure near it, above the horizon)."""


@dataclass(frozen=True)
class Structure:
    """The port structure as the engine gave it after one frame (``Fusion.structure``) and the
    structure window's solved views (``Fusion.solved_views``)."""

    t: float | None  # gpst of that frame; None: nothing yet
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (N,3) NED, m
    sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (N,) 1-σ, m
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    views: SolvedViews | None = None

    @classmethod
    def of(cls, engine: Any, t: float) -> Structure:
        pts, sigma, ids = engine.structure()
        return cls(float(t), np.array(pts, dtype=float).reshape(-1, 3),
                   np.array(sigma, dtype=float).ravel(), np.array(ids).ravel(),
                   engine.solved_views())


@dataclass(frozen=True)
class Designation:
    """The 3-D point under a click."""

    position_ned: np.ndarray
    covariance: np.ndarray  # (3,3) m²
    method: str  # "structure" | "water-plane"
    anchor_ids: np.ndarray  # structure point ids under the click (empty for water-plane)
    anchor_mean: np.ndarray | None  # their mean position
    water_down_m: float | None = None  # the water plane's down (m) when it is known
    # (nearest, farthest) range of the structure inside the click's template when it straddles
    # a depth edge (``estimator.tracking.depth_edge``)
    edge_span_m: tuple[float, float] | None = None


def camera_view(state: Any, camera: CameraCalibration) -> CameraView:
    """The camera pose of a fused state at its time, with its covariance (from the fused
    position and attitude covariance, None when the state has none)."""
    pose = camera_pose(state, camera)
    cov = None
    p_cov, a_cov = getattr(state, "position_cov", None), getattr(state, "attitude_cov", None)
    if p_cov is not None and a_cov is not None:
        lever = np.asarray(state.C_body_to_level, dtype=float) @ np.asarray(
            camera.lever_arm_body, dtype=float)
        cov = camera_pose_covariance(p_cov, a_cov, lever)
        if not np.isfinite(cov).all():
            cov = None
    return CameraView(float(state.time), pose.C_level_to_camera, pose.position_ned, cov)


def designate(projector: Projector, view: CameraView, u: float, v: float,
              structure: Structure, water_down_m: float | None) -> Designation:
    """The 3-D point for pixel (u, v) of the frame seen from ``view``: the structure points
    near its ray, else the water plane at ``water_down_m`` (None: unknown, no fallback)."""
    pose = CameraPose(view.C_level_to_camera, view.position_ned)
    ray = projector.pixel_ray(pose, u, v)
    focal = projector.camera.focal_px
    if len(structure.points):
        _visible, uv = projector.project_points(pose, structure.points)
        found = structure_point_at(structure.points, structure.sigma, uv, np.array([u, v]),
                                   pose.position_ned, ray, focal)
        # structure points under the water are a reflection's on calm water: the pixel
        # shows the water, placed by its plane below
        if found is not None and not under_water(found[0], found[1], water_down_m):
            point, cov, near = found
            half = target_window(projector.width) // 2
            edge = depth_edge(structure.points, structure.sigma, uv, np.array([u, v]),
                              pose.position_ned, half)
            if not shows_surface(uv[near], np.array([u, v]), half):
                cov = cov + _beside_template(point, pose.position_ned, ray, water_down_m, focal)
            return Designation(point, cov, "structure", np.asarray(structure.ids)[near],
                               structure.points[near].mean(axis=0), water_down_m, edge)
    hit = None if water_down_m is None else \
        water_plane_point(pose.position_ned, ray, water_down_m)
    if hit is None:
        raise DesignationError(
            f"pixel ({u:g}, {v:g}) has no port-structure point within "
            f"{2 * DESIGNATION_RADIUS_PX:g} px and its ray does not meet the water plane "
            "(above the horizon, or the water level is unknown)")
    # 2σ along the ray reaches back to where it is WATER_PLANE_STANDING_M above the water.
    height = float(water_down_m) - float(pose.position_ned[2])  # type: ignore[arg-type]
    reach = float(np.linalg.norm(hit[:2] - pose.position_ned[:2]))
    if not _pixel_bounds_water(reach, height, focal):
        raise DesignationError(
            f"pixel ({u:g}, {v:g}) has no port-structure point within "
            f"{2 * DESIGNATION_RADIUS_PX:g} px, and its ray meets the water {reach:.0f} m off, "
            f"where one pixel moves it by over {100 * WATER_PLANE_MAX_PIXEL_FRACTION:.0f} %: "
            "no distance to give there yet")
    fraction = max(0.1, 0.5 * min(WATER_PLANE_STANDING_M, height) / height)
    _, cov = point_on_ray(hit[None], None, pose.position_ned, ray, focal,
                          ray_sigma_fraction=fraction)
    return Designation(hit, cov, "water-plane", np.zeros(0, np.int64), None, water_down_m)


def _beside_template(point: np.ndarray, camera_ned: np.ndarray, ray: np.ndarray,
                     water_down_m: float | None, focal_px: float) -> np.ndarray:
    """(3,3) covariance along the ray for a click whose anchors do not show its surface
    (``shows_surface``: none on the click, fewer than two within half its template's side):
    nothing the target's tracker follows ties the click to their surface, so it may be
    theirs or anything on the ray up to where it meets the water (half that span is 1 σ).
    Where the ray meets the water too far off to bound anything
    (``WATER_PLANE_MAX_PIXEL_FRACTION``), or not at all, half the anchors' range is the
    span. On the 20 small-boat yardstick seeds, designations with every anchor outside the
    template's square were within 2σ for 19 of 26 clicks (short mostly: the anchors on a
    hull or fender before the quay clicked); its corners are ``near_click``'s figures."""
    u = np.asarray(ray, float) / np.linalg.norm(ray)
    c = np.asarray(camera_ned, float)
    r = float(np.linalg.norm(np.asarray(point, float) - c))
    hit = None if water_down_m is None else water_plane_point(c, u, water_down_m)
    span = 0.5 * r
    if hit is not None and _pixel_bounds_water(float(np.linalg.norm(hit[:2] - c[:2])),
                                               float(water_down_m) - float(c[2]), focal_px):
        span = abs(float(np.linalg.norm(hit - c)) - r)
    return (0.5 * span) ** 2 * np.outer(u, u)


def _pixel_bounds_water(reach_m: float, height_m: float, focal_px: float) -> bool:
    """Whether a ray meeting the water ``reach_m`` off (horizontally) from a camera
    ``height_m`` above it still places a point there: one pixel moves it by at most
    ``WATER_PLANE_MAX_PIXEL_FRACTION`` of that reach."""
    return reach_m <= WATER_PLANE_MAX_PIXEL_FRACTION * focal_px * height_m


def target_window(image_width: int) -> int:
    """Template side (px, odd) of the image tracker for an image this wide."""
    return max(15, int(round(TARGET_WINDOW_PX * image_width / 960.0)) | 1)


class FollowedTarget:
    """A designated target followed through the frames (module docstring)."""

    def __init__(self, projector: Projector, designation: Designation, image: np.ndarray,
                 uv: tuple[float, float], view: CameraView, index: int,
                 earlier_frames: list[tuple[float, np.ndarray]], views: SolvedViews | None
                 ) -> None:
        self.projector = projector
        self.designation = designation
        # Seeded by the clicked frame: the same click gives the same track, in the server
        # and in the evaluation.
        self.tracker = DesignatedTarget(
            projector.camera, image, np.asarray(uv, float), designation.position_ned,
            designation.covariance, view, params=TargetParams(window=target_window(
                projector.width)), seed=index, earlier_frames=earlier_frames, views=views,
            water_down_m=designation.water_down_m, edge_span_m=designation.edge_span_m)
        self.frame_index = index  # last frame followed
        self.refreshed_t = -math.inf  # structure time of the last refresh

    @property
    def position_ned(self) -> np.ndarray:
        return self.tracker.position_ned

    def follow(self, index: int, image: np.ndarray, view: CameraView,
               structure: Structure) -> TargetState:
        """One frame: tracked on from the last one (or, after a gap or a seek, taken back
        where its 3-D point projects), then refreshed on the structure when it is due."""
        if index == self.frame_index + 1:
            state = self.tracker.update(image, view)
        else:
            state = self.tracker.resume(image, view)
        self.frame_index = index
        self._refresh(view, structure)
        return state

    def _refresh(self, view: CameraView, structure: Structure) -> None:
        t = structure.t
        if t is None or 0.0 <= t - self.refreshed_t < TARGET_REFRESH_S:
            return  # (a structure older than the last one: the replay went back, go on)
        self.refreshed_t = t
        pose = CameraPose(view.C_level_to_camera, view.position_ned)
        _visible, uv = self.projector.project_points(pose, structure.points)
        self.tracker.refresh(structure.points, structure.sigma, uv, view, structure.views)
