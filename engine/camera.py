"""Camera geometry of the engine path: the camera pose of a fused state, projection of
level-frame geometry into the distorted image, pixel rays, the water plane.

Frames (``estimator.frames``): positions are NED in the local-level frame at the world origin,
the camera frame is right-down-forward, ``C_A_to_B`` rotates A coordinates into B. The water
plane is ``down = plane_down``. Image coordinates are distorted pixels (what the video shows),
using the recording's OpenCV distortion model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from estimator.records import CameraCalibration

NEAR_M = 0.2  # near plane: geometry closer to the camera than this is clipped away
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
_FRUSTUM_MARGIN = 0.02  # normalised units beyond the image border kept when clipping lines


@dataclass(frozen=True)
class CameraPose:
    C_level_to_camera: np.ndarray  # (3,3)
    position_ned: np.ndarray  # (3,) camera centre

    def to_camera(self, points_ned: np.ndarray) -> np.ndarray:
        """(N,3) level-frame points in camera coordinates."""
        return (np.asarray(points_ned, dtype=float).reshape(-1, 3) - self.position_ned) \
            @ self.C_level_to_camera.T

    def ray_to_level(self, direction_camera: np.ndarray) -> np.ndarray:
        return self.C_level_to_camera.T @ direction_camera


def camera_pose(state: Any, camera: CameraCalibration) -> CameraPose:
    """Camera pose of a fused state (body origin position, ``C_body_to_level``)."""
    C_b_l = np.asarray(state.C_body_to_level, dtype=float)
    C_c_l = C_b_l @ camera.C_camera_to_body
    position = np.asarray(state.position_ned, dtype=float) + C_b_l @ camera.lever_arm_body
    return CameraPose(C_c_l.T, position)


class Projector:
    """Projection of level-frame geometry into the distorted image of one camera.

    Lines are clipped in 3-D against the near plane and against the frustum of the image
    (enlarged by a small margin) before projecting: the distortion polynomial is only valid
    inside the field of view, far outside it points fold back into the image.
    """

    def __init__(self, camera: CameraCalibration, near: float = NEAR_M) -> None:
        self.camera = camera
        self.K = np.asarray(camera.K, dtype=float)
        self.dist = np.asarray(camera.distortion, dtype=float)
        self.width, self.height = int(camera.width), int(camera.height)
        self.near = near
        # Frustum bounds in normalised (undistorted) coordinates from the image border.
        n = 64
        us = np.linspace(-0.5, self.width - 0.5, n)
        vs = np.linspace(-0.5, self.height - 0.5, n)
        border = np.concatenate([
            np.column_stack([us, np.full(n, -0.5)]), np.column_stack([us, np.full(n, self.height
                                                                                  - 0.5)]),
            np.column_stack([np.full(n, -0.5), vs]), np.column_stack([np.full(n, self.width
                                                                              - 0.5), vs]),
        ])
        xy = self.undistort(border)
        m = _FRUSTUM_MARGIN
        self.x_min, self.x_max = xy[:, 0].min() - m, xy[:, 0].max() + m
        self.y_min, self.y_max = xy[:, 1].min() - m, xy[:, 1].max() + m

    # ---------------------------------------------------------------- points

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Normalised image coordinates (N,2) of distorted pixels (N,2)."""
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        return cv2.undistortPoints(pts, self.K, self.dist, None, None, None,
                                   _UNDISTORT_CRITERIA).reshape(-1, 2)

    def project_camera(self, points_camera: np.ndarray) -> np.ndarray:
        """Distorted pixels (N,2) of camera-frame points (N,3) in front of the camera."""
        pts = np.asarray(points_camera, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0:
            return np.zeros((0, 2))
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist)
        return uv.reshape(-1, 2)

    def in_frustum(self, points_camera: np.ndarray) -> np.ndarray:
        """Mask of camera-frame points in front of the near plane and inside the frustum."""
        p = np.asarray(points_camera, dtype=float).reshape(-1, 3)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = p[:, 0] / z, p[:, 1] / z
        return ((z >= self.near) & (x >= self.x_min) & (x <= self.x_max)
                & (y >= self.y_min) & (y <= self.y_max))

    def in_image(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return ((uv[:, 0] >= -0.5) & (uv[:, 0] <= self.width - 0.5)
                & (uv[:, 1] >= -0.5) & (uv[:, 1] <= self.height - 0.5))

    def project_points(self, pose: CameraPose, points_ned: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
        """(visible mask (N,), pixels (N,2), NaN where not visible) of level-frame points."""
        pc = pose.to_camera(points_ned)
        visible = self.in_frustum(pc)
        uv = np.full((len(pc), 2), np.nan)
        if visible.any():
            uv[visible] = self.project_camera(pc[visible])
            inside = self.in_image(uv[visible])
            idx = np.flatnonzero(visible)
            visible[idx[~inside]] = False
            uv[idx[~inside]] = np.nan
        return visible, uv

    def pixel_ray(self, pose: CameraPose, u: float, v: float) -> np.ndarray:
        """Unit direction (level frame) of the ray through distorted pixel (u, v)."""
        x, y = self.undistort(np.array([[u, v]]))[0]
        d = pose.ray_to_level(np.array([x, y, 1.0]))
        return d / np.linalg.norm(d)

    # ----------------------------------------------------------------- lines

    def clip_segments(self, a: np.ndarray, b: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Clip camera-frame segments a→b (N,3) to the near plane and the frustum.

        Liang–Barsky on the five half-spaces f(P) >= 0 (all linear in P). Returns the
        clipped ends and the mask of segments with something left.
        """
        a = np.asarray(a, dtype=float).reshape(-1, 3)
        b = np.asarray(b, dtype=float).reshape(-1, 3)
        planes = np.array([  # f(P) = n . P - near*[plane is the near plane]
            [0.0, 0.0, 1.0],
            [-1.0, 0.0, self.x_max],
            [1.0, 0.0, -self.x_min],
            [0.0, -1.0, self.y_max],
            [0.0, 1.0, -self.y_min],
        ])
        offsets = np.array([-self.near, 0.0, 0.0, 0.0, 0.0])
        fa = a @ planes.T + offsets  # (N,5)
        fb = b @ planes.T + offsets
        s0 = np.zeros(len(a))
        s1 = np.ones(len(a))
        keep = np.ones(len(a), dtype=bool)
        for i in range(len(planes)):
            da, db = fa[:, i], fb[:, i]
            keep &= ~((da < 0) & (db < 0))
            with np.errstate(divide="ignore", invalid="ignore"):
                s = da / (da - db)  # where f crosses zero
            entering = (da < 0) & (db >= 0)
            leaving = (da >= 0) & (db < 0)
            s0 = np.where(entering, np.maximum(s0, s), s0)
            s1 = np.where(leaving, np.minimum(s1, s), s1)
        keep &= s0 < s1
        d = b - a
        return a + s0[:, None] * d, a + s1[:, None] * d, keep

    def project_segments(self, pose: CameraPose, a_ned: np.ndarray, b_ned: np.ndarray,
                         px_per_sample: float = 24.0) -> list[np.ndarray]:
        """Polylines (k,2) of distorted pixels, one per visible level-frame segment a→b.

        The clipped segment is sampled evenly in the undistorted image plane (a straight line
        stays straight there) and each sample is distorted, so the drawn line follows the lens
        curvature.
        """
        ca, cb, keep = self.clip_segments(pose.to_camera(a_ned), pose.to_camera(b_ned))
        if not keep.any():
            return []
        ca, cb = ca[keep], cb[keep]
        na, nb = ca[:, :2] / ca[:, 2:], cb[:, :2] / cb[:, 2:]
        f = float(max(self.K[0, 0], self.K[1, 1]))
        length_px = f * np.linalg.norm(nb - na, axis=1)
        counts = np.clip(np.ceil(length_px / px_per_sample).astype(int) + 1, 2, 64)
        samples = [na[i] + np.linspace(0.0, 1.0, counts[i])[:, None] * (nb[i] - na[i])
                   for i in range(len(na))]
        flat = np.concatenate(samples)
        uv = self.project_camera(np.column_stack([flat, np.ones(len(flat))]))
        return np.split(uv, np.cumsum(counts)[:-1])

    def project_polygon(self, pose: CameraPose, polygon_ned: np.ndarray) -> list[np.ndarray]:
        """Visible pieces of a closed polygon (N,3) as polylines."""
        p = np.asarray(polygon_ned, dtype=float)
        return self.project_segments(pose, p, np.roll(p, -1, axis=0))


def water_plane_point(origin: np.ndarray, direction: np.ndarray, plane_down: float = 0.0,
                      max_range: float = 5000.0) -> np.ndarray | None:
    """Intersection of a level-frame ray with the water plane down = ``plane_down`` (None if
    it misses: camera under water, ray level or looking up, or farther than ``max_range``)."""
    height = plane_down - float(origin[2])
    if height <= 0.0 or direction[2] <= 1e-9:
        return None
    s = height / direction[2]
    return None if s > max_range else origin + s * direction
