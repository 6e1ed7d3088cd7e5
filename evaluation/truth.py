"""The truth the evaluation scores against (never seen by the estimator): the true camera poses
at the frames, true projections of scene points, the rebuilt scene of a simulated recording,
and the clicks an officer would make on true quay points."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np

from backend.geometry import berth_metrics
from estimator.frames import euler_to_dcm
from estimator.records import CameraCalibration
from recordings.format import Recording
from recordings.sim.scenarios import SCENARIOS
from recordings.sim.scene import PortScene

CLICK_KINDS = ("quay", "fender", "ladder")  # on the quay wall (bollards: see the report)
CLICK_RANGE_M = (5.0, 30.0)
CLICK_MARGIN_PX = 40.0  # clicked points at least this far inside the image
CLICK_SPACING_PX = 120.0  # clicks of one frame at least this far apart
DEFAULT_CLICK_TIMES_S = (45.0, 52.0, 60.0, 66.0, 72.0, 78.0)  # s after the start


@dataclass
class Truth:
    """True camera poses at the frame times, in the reference frame."""

    C_level_to_camera: np.ndarray  # (N,3,3)
    position: np.ndarray  # (N,3) camera centre
    origin: np.ndarray  # reference position of the fusion's world origin


def true_cameras(rec: Recording, times: np.ndarray, origin_time: float | None) -> Truth:
    """True camera poses at ``times`` (gpst) and the reference position at ``origin_time``."""
    assert rec.reference is not None
    pos, _vel, eul = rec.reference.interpolate(times)
    cam = rec.calibration.camera
    Cs = np.array([euler_to_dcm(*e) for e in eul])
    lever = np.asarray(cam.lever_arm_body, float)
    cpos = pos + np.einsum("nij,j->ni", Cs, lever)
    C_lc = np.einsum("nij,jk->nki", Cs, np.asarray(cam.C_camera_to_body, float))
    origin = rec.reference.interpolate(origin_time)[0] if origin_time is not None else \
        np.full(3, np.nan)
    return Truth(C_lc, cpos, origin)


def project(camera: CameraCalibration, C: np.ndarray, p: np.ndarray, X: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels (N,2) and depths (N,) of points X (N,3); NaN pixels behind."""
    X = np.asarray(X, float).reshape(-1, 3)
    xc = (X - p) @ C.T
    uv = np.full((len(X), 2), np.nan)
    front = xc[:, 2] > 0.2
    if front.any():
        proj, _ = cv2.projectPoints(xc[front], np.zeros(3), np.zeros(3),
                                    np.asarray(camera.K, float),
                                    np.asarray(camera.distortion, float))
        uv[front] = proj.reshape(-1, 2)
    return uv, xc[:, 2]


def rebuild_scene(rec: Recording) -> PortScene | None:
    """The simulator's scene of a simulated recording (None for a real one or a mismatch)."""
    m = rec.manifest
    if getattr(m, "scenario", None) not in SCENARIOS or getattr(m, "seed", None) is None:
        return None
    scene = PortScene.build(SCENARIOS[m.scenario], int(m.seed))
    pts = rec.scene_points
    if pts is None or len(pts) != len(scene.points) or \
            np.max(np.abs(np.asarray(pts, float) - scene.points)) > 1e-3:
        return None
    return scene


@dataclass
class Click:
    frame: int  # index of the clicked video frame
    uv: tuple[float, float]  # clicked pixel (distorted)
    point: int | None = None  # index into rec.scene_points; None: the one under the pixel
    label: str = ""


def default_clicks(rec: Recording, times_s: Sequence[float] = DEFAULT_CLICK_TIMES_S,
                   per_time: int = 3, kinds: Sequence[str] = CLICK_KINDS,
                   range_m: tuple[float, float] = CLICK_RANGE_M, seed: int = 0) -> list[Click]:
    """Designated quay points for the evaluation: at each of ``times_s`` (s after the
    start) up to ``per_time`` true scene points of ``kinds`` at ``range_m`` from the camera,
    in view (and, for a simulated recording, not hidden behind anything), spread across the
    image; the click is their true projection."""
    if rec.reference is None or rec.scene_points is None:
        return []
    frame_t = np.asarray(rec.frame_times, float)
    start = float(rec.manifest.start_gpst)
    kinds_all = np.array(rec.scene_point_kinds or [""] * len(rec.scene_points))
    pts = np.asarray(rec.scene_points, float)
    pick = np.flatnonzero(np.isin(kinds_all, list(kinds)))
    scene = rebuild_scene(rec)
    rng = np.random.default_rng(seed)
    out: list[Click] = []
    for ts in times_s:
        k = int(np.argmin(np.abs(frame_t - (start + ts))))
        cand, uv = _candidates(rec, scene, pts[pick], frame_t[k], range_m)
        chosen: list[int] = []
        for j in rng.permutation(cand):
            if all(np.linalg.norm(uv[j] - uv[i]) > CLICK_SPACING_PX for i in chosen):
                chosen.append(int(j))
            if len(chosen) >= per_time:
                break
        for j in chosen:
            out.append(Click(frame=k, uv=(float(uv[j, 0]), float(uv[j, 1])),
                             point=int(pick[j]), label=f"{kinds_all[pick[j]]}@{ts:g}s"))
    return out


def _candidates(rec: Recording, scene: PortScene | None, pts: np.ndarray, t: float,
                range_m: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Indexes of ``pts`` clickable at gpst ``t`` (in the image, in range, visible) and
    their true pixels."""
    assert rec.reference is not None
    cam = rec.calibration.camera
    pos, _v, e = rec.reference.interpolate(t)
    if not np.isfinite(pos).all():
        return np.zeros(0, int), np.zeros((0, 2))
    C_bl = euler_to_dcm(*e)
    C = (C_bl @ cam.C_camera_to_body).T
    c = pos + C_bl @ np.asarray(cam.lever_arm_body, float)
    uv, z = project(cam, C, c, pts)
    rng_m = np.linalg.norm(pts - c, axis=1)
    m = CLICK_MARGIN_PX
    ok = (np.isfinite(uv).all(axis=1) & (uv[:, 0] > m) & (uv[:, 0] < cam.width - 1 - m)
          & (uv[:, 1] > m) & (uv[:, 1] < cam.height - 1 - m)
          & (rng_m >= range_m[0]) & (rng_m <= range_m[1]))
    cand = np.flatnonzero(ok)
    if scene is not None and len(cand):
        start = float(rec.manifest.start_gpst)
        _img, depth = scene.render(C, c, t - start, cam, np.random.default_rng(0),
                                   return_depth=True)
        vis = [clickable(depth, uv[j], z[j]) for j in cand]
        cand = cand[np.array(vis, bool)]
    return cand, uv


def clickable(depth: np.ndarray, uv: np.ndarray, z: float, tolerance: float = 0.03) -> bool:
    """Whether a scene point at camera depth ``z`` projecting at pixel ``uv`` is what a click
    there designates, by the rendered ``depth`` image: it shows in the click's 3x3 pixels
    (within ``tolerance`` of its depth) and nothing nearer does. A click on the silhouette of
    a moored boat before the quay designates the boat (the product takes the nearest surface
    under a click), so the quay point behind it is no truth for that click."""
    u, v = int(round(uv[0])), int(round(uv[1]))
    dz = depth[v - 1:v + 2, u - 1:u + 2]
    return bool(dz.size == 9 and np.isfinite(dz).all()
                and np.min(np.abs(dz - z)) < tolerance * z
                and np.min(dz) > (1.0 - tolerance) * z)


def clicked_point(rec: Recording, truth: Truth, click: Click) -> int | None:
    """The scene point under the click: the given one, else the nearest true projection
    within 3 px (the nearest to the camera when several)."""
    if click.point is not None:
        return int(click.point)
    k = click.frame
    uv, z = project(rec.calibration.camera, truth.C_level_to_camera[k], truth.position[k],
                    rec.scene_points)
    d = np.linalg.norm(uv - np.asarray(click.uv, float), axis=1)
    near = np.flatnonzero(np.nan_to_num(d, nan=np.inf) < 3.0)
    if not len(near):
        return None
    return int(near[np.argmin(z[near])])


def scene_depth(scene: Any, truth: Truth, k: int, t_rel: float, camera: CameraCalibration
                ) -> np.ndarray:
    """The rendered true depth map at frame ``k`` (``t_rel`` s after the start)."""
    _img, depth = scene.render(truth.C_level_to_camera[k], truth.position[k], t_rel, camera,
                               np.random.default_rng(0), return_depth=True)
    return depth


def quay_foot_clicks(rec: Recording, gpst: float, fractions: Sequence[float] = (0.2, 0.8),
                     margin_px: float = 40.0) -> tuple[np.ndarray, float] | None:
    """Pixels an officer would click on the quay's water line (the recording's berth line,
    hull.json, on the water) seen from the true camera at ``gpst``: at ``fractions`` of the
    visible stretch of it, and the true bow distance to it. Only the foot not hidden (by a
    moored boat, for a simulated recording) counts as visible; None when under 20 of its
    points (every 0.25 m) are."""
    if rec.reference is None or rec.hull.berth_line_ned is None:
        return None
    line = np.asarray(rec.hull.berth_line_ned, float).reshape(2, 2)
    s = np.linspace(0.0, 1.0, max(int(np.linalg.norm(line[1] - line[0]) / 0.25), 2))
    foot = np.column_stack([line[0] + s[:, None] * (line[1] - line[0]), np.zeros_like(s)])
    truth = true_cameras(rec, np.array([gpst]), None)
    cam = rec.calibration.camera
    uv, z = project(cam, truth.C_level_to_camera[0], truth.position[0], foot)
    ok = (np.isfinite(uv).all(axis=1) & (uv[:, 0] > margin_px)
          & (uv[:, 0] < cam.width - 1 - margin_px) & (uv[:, 1] > 0) & (uv[:, 1] < cam.height - 1))
    scene = rebuild_scene(rec)
    if scene is not None and ok.any():
        depth = scene_depth(scene, truth, 0, gpst - float(rec.manifest.start_gpst), cam)
        for j in np.flatnonzero(ok):  # the pixel just above the foot shows the wall
            u, v = int(round(uv[j, 0])), int(round(uv[j, 1])) - 2
            seen = depth[max(v, 0), u]
            ok[j] = bool(np.isfinite(seen) and abs(seen - z[j]) < 0.05 * z[j])
    visible = np.flatnonzero(ok)
    if len(visible) < 20:
        return None
    clicks = uv[[visible[int(f * (len(visible) - 1))] for f in fractions]]
    pos, vel, euler = rec.reference.interpolate(gpst)
    state = SimpleNamespace(position_ned=pos, euler=euler, velocity_ned=vel, rate_of_turn=0.0)
    return clicks, float(berth_metrics(state, rec.hull, line)["bow_distance_m"])
