"""Free-viewpoint 3-D view of a session in viser (thesis fig. 34).

Scene (local-level NED at the world origin, near the berth, so float32 on the wire is at most
a few hundred metres from zero; the scene's up direction is -z = up):

Colours: ``PALETTES`` (day; night dimmed and warm, with viser's dark mode: ``set_theme``).

* ``/reference`` grey: the reference trajectory, when the recording has one;
* ``/fused/chunk_NNNN`` red: the fused trajectory in frozen chunks of ``CHUNK`` segments plus
  ``/fused/tail`` (the open chunk, re-sent while it grows): each update sends at most one
  chunk's worth of segments, never the whole path;
* ``/structure/chunk_NNNN`` blue: port-structure points appended as new ids appear; every
  ``STRUCTURE_REFRESH_S`` they are consolidated into one node so that refined positions show;
* ``/ship`` (pose updated per frame): the hull outline and ``/ship/camera`` the frustum;
* ``/water_grid``: 2 m cells on the plane down = 0, re-centred on the ship;
* ``/berth_line`` magenta: the berth line at the water, with a vertical fence up to the quay
  top it stands for; ``/targets/<id>`` orange: the designated targets, labelled.

The view follows one session (the newest one by default). It is updated from the replay
thread, throttled; frames computed during a seek are skipped and the path is rebuilt from the
session history once the seek is done.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import threading
import time
from typing import Any

import numpy as np
import viser
import viser.transforms as vtf

from .overlay import grid_radius
from .replay import FrameResult
from .sessions import Session

log = logging.getLogger(__name__)

CHUNK = 50  # trajectory segments per frozen chunk
POINT_CHUNK = 2000  # new structure points per chunk before consolidation
STRUCTURE_REFRESH_S = 20.0
POSE_PERIOD_S = 0.1
STRUCTURE_PERIOD_S = 1.0
# Colours by theme. Night, as on bridge equipment: dark background, every colour dimmed and
# warm (no white, no saturated green or blue), as the page's night palette.
PALETTES: dict[str, dict[str, tuple[int, int, int]]] = {
    "day": {"fused": (220, 30, 30), "structure": (40, 90, 230), "reference": (150, 150, 150),
            "hull": (250, 200, 40), "berth": (230, 40, 200), "target": (255, 140, 30),
            "camera": (20, 20, 20), "grid_cell": (60, 160, 60), "grid_section": (30, 120, 30)},
    "night": {"fused": (150, 40, 20), "structure": (90, 70, 90), "reference": (80, 60, 50),
              "hull": (140, 100, 30), "berth": (130, 40, 90), "target": (160, 80, 20),
              "camera": (90, 50, 30), "grid_cell": (60, 40, 20), "grid_section": (80, 50, 20)},
}
NIGHT_BRAND = (120, 40, 10)
BERTH_FENCE_M = 1.5  # the berth line's fence: this high above the water
GRID_CELL_M = 2.0


def _wxyz(C: np.ndarray) -> np.ndarray:
    return vtf.SO3.from_matrix(np.asarray(C, dtype=float)).wxyz


def _segments(points: np.ndarray) -> np.ndarray:
    """(N,3) polyline → (N-1,2,3) segments."""
    p = np.asarray(points, dtype=np.float32)
    return np.stack([p[:-1], p[1:]], axis=1)


class ViserView:
    """The viser server and the scene of the followed session."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080) -> None:
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner; we print URLs
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("-z")
        self.host = host
        self._lock = threading.RLock()
        self._session: Session | None = None
        self._nodes: dict[str, Any] = {}  # top-level nodes (removing one removes its children)
        self._children: dict[str, Any] = {}
        self._chunks: list[Any] = []
        self._path_count = 0  # trajectory points already in frozen chunks + tail
        self._path_last: np.ndarray | None = None
        self._tail: list[np.ndarray] = []
        self._point_ids: set[int] = set()
        self._point_chunks: list[Any] = []
        self._last_pose = 0.0
        self._last_structure = 0.0
        self._last_consolidation = 0.0
        self._last_t = -math.inf
        self._needs_rebuild = False
        self._framed = False  # initial camera pointed at this session's ship yet
        self._berth_key: tuple | None = None
        self._targets: dict[str, Any] = {}
        self.theme = "day"
        self._color = PALETTES["day"]

    @property
    def port(self) -> int:
        return self.server.get_port()

    def url(self, host: str | None = None) -> str:
        host = host or ("127.0.0.1" if self.host in ("0.0.0.0", "::") else self.host)
        if ":" in host:  # IPv6 literal
            host = f"[{host}]"
        return f"http://{host}:{self.port}/"

    def set_theme(self, theme: str) -> None:
        """Day or night for every viewer of this 3-D view (one viser server: the last page
        to switch sets it): the panel's dark mode and the scene's colours, redrawn."""
        if theme not in PALETTES:
            raise ValueError(f"theme {theme!r} is neither " + " nor ".join(PALETTES))
        with self._lock:
            self.theme, self._color = theme, PALETTES[theme]
            night = theme == "night"
            self.server.gui.configure_theme(dark_mode=night, show_share_button=False,
                                            brand_color=NIGHT_BRAND if night else None)
            if self._session is not None:
                self.follow(self._session)  # redrawn in the new colours

    @property
    def session_id(self) -> str | None:
        return self._session.id if self._session is not None else None

    def stop(self) -> None:
        with self._lock:
            self._detach()
        self.server.stop()

    # ---------------------------------------------------------------------- following

    def follow(self, session: Session) -> None:
        with self._lock:
            self._detach()
            self._session = session
            self._framed = False
            session.frame_listeners.append(self.on_frame)
            self._build_static(session)
            # show what the session has so far at once (it may be paused or ended)
            self._rebuild_path(session)
            self._draw_reference(session)
            self._last_consolidation = 0.0
            self._update_structure(session, time.monotonic())
            state = session.history.latest()
            if state is not None:
                self._update_pose(state)
            self._update_berth_and_targets(session, state)

    def forget(self, session: Session) -> None:
        with self._lock:
            if self._session is session:
                self._detach()

    def _detach(self) -> None:
        if self._session is not None:
            try:
                self._session.frame_listeners.remove(self.on_frame)
            except ValueError:
                pass
        self._session = None
        for handle in [*self._nodes.values(), *self._chunks, *self._point_chunks,
                       *self._targets.values()]:
            try:
                handle.remove()
            except Exception:  # already removed by a parent
                pass
        self._nodes.clear()
        self._children.clear()
        self._chunks.clear()
        self._point_chunks.clear()
        self._point_ids.clear()
        self._targets.clear()
        self._berth_key = None
        self._tail = []
        self._path_count = 0
        self._path_last = None
        self._last_t = -math.inf

    def _build_static(self, session: Session) -> None:
        scene = self.server.scene
        rec = session.rec
        hull = np.asarray(rec.hull.outline_body, dtype=float)[:, :2]
        outline = np.column_stack([hull, np.zeros(len(hull))])
        closed = np.vstack([outline, outline[:1]])
        # the ship's axes are pure red, green and blue: not at night
        self._nodes["ship"] = scene.add_frame("/ship", show_axes=self.theme != "night",
                                              axes_length=1.0, axes_radius=0.03)
        self._children["hull"] = scene.add_line_segments(
            "/ship/hull", _segments(closed), self._color["hull"], thickness=3.0,
            thickness_units="screen")
        cam = rec.calibration.camera
        fov = 2.0 * math.atan2(cam.height / 2.0, float(cam.K[1, 1]))
        self._children["camera"] = scene.add_camera_frustum(
            "/ship/camera", fov=fov, aspect=cam.width / cam.height, scale=1.0,
            color=self._color["camera"],
            wxyz=_wxyz(cam.C_camera_to_body), position=tuple(cam.lever_arm_body))
        water = session.water.down_m
        size = 2.0 * grid_radius(max(water - float(cam.lever_arm_body[2]), 0.5))
        self._nodes["grid"] = scene.add_grid(
            "/water_grid", width=size, height=size, plane="xy", cell_size=GRID_CELL_M,
            section_size=10 * GRID_CELL_M, cell_color=self._color["grid_cell"],
            section_color=self._color["grid_section"], position=(0.0, 0.0, water))

    # ---------------------------------------------------------------------- per frame

    def on_frame(self, session: Session, result: FrameResult) -> None:
        """Frame listener (replay thread)."""
        if not result.live:
            self._needs_rebuild = True
            return
        with self._lock:
            if session is not self._session:
                return
            if result.t < self._last_t:
                self._needs_rebuild = True
            self._last_t = result.t
            now = time.monotonic()
            try:
                if self._needs_rebuild:
                    self._rebuild_path(session)
                    self._draw_reference(session)
                    self._needs_rebuild = False
                elif "reference" not in self._nodes and result.state is not None:
                    self._draw_reference(session)
                elif result.state is not None:
                    self._append_path(np.asarray(result.state.position_ned, dtype=float))
                if result.state is not None and now - self._last_pose >= POSE_PERIOD_S:
                    self._update_pose(result.state)
                    self._last_pose = now
                if now - self._last_structure >= STRUCTURE_PERIOD_S:
                    self._update_structure(session, now)
                    self._update_berth_and_targets(session, result.state)
                    self._last_structure = now
            except Exception:  # the 3-D view is secondary: never break the replay for it
                log.exception("viser update failed")

    def _draw_reference(self, session: Session) -> None:
        """The reference in the world frame, matched at the first fused pose (as the report)."""
        old = self._nodes.pop("reference", None)
        if old is not None:
            old.remove()
        aligned = session.history.reference_alignment()
        if aligned is None or session.rec.reference is None:
            return
        ref = session.rec.reference.position_ned[::10] - aligned[1]  # 10 Hz is plenty
        self._nodes["reference"] = self.server.scene.add_line_segments(
            "/reference", _segments(ref), self._color["reference"], thickness=2.0,
            thickness_units="screen")

    def _frame_view(self, state: Any) -> None:
        """Point the viewers' initial camera ("Reset View") at the approach: above and behind
        the ship, looking ahead along its heading towards the berth."""
        forward = np.asarray(state.C_body_to_level, dtype=float)[:, 0] * [1.0, 1.0, 0.0]
        forward /= max(float(np.linalg.norm(forward)), 1e-9)
        ship = np.asarray(state.position_ned, dtype=float)
        self.server.initial_camera.look_at = ship + 30.0 * forward
        self.server.initial_camera.position = ship - 30.0 * forward + [0.0, 0.0, -35.0]
        self._framed = True

    def _update_pose(self, state: Any) -> None:
        if not self._framed:
            self._frame_view(state)
        ship = self._nodes["ship"]
        ship.position = np.asarray(state.position_ned, dtype=float)
        ship.wxyz = _wxyz(state.C_body_to_level)
        centre = np.round(np.asarray(state.position_ned[:2], dtype=float) / (5 * GRID_CELL_M))
        self._nodes["grid"].position = np.array([*(centre * 5 * GRID_CELL_M),
                                                 self._session.water.down_m])

    # trajectory: frozen chunks + a growing tail

    def _append_path(self, p: np.ndarray) -> None:
        if self._path_last is None:
            self._path_last = p
            self._tail = [p]
            return
        self._tail.append(p)
        self._path_last = p
        if len(self._tail) - 1 >= CHUNK:
            self._freeze_tail()
        elif len(self._tail) >= 2:
            self._set_tail()

    def _set_tail(self) -> None:
        segments = _segments(np.array(self._tail))
        if "tail" in self._nodes:
            self._nodes["tail"].points = segments
        else:
            self._nodes["tail"] = self.server.scene.add_line_segments(
                "/fused/tail", segments, self._color["fused"], thickness=3.0,
                thickness_units="screen")

    def _freeze_tail(self) -> None:
        segments = _segments(np.array(self._tail))
        name = f"/fused/chunk_{len(self._chunks):04d}"
        self._chunks.append(self.server.scene.add_line_segments(
            name, segments, self._color["fused"], thickness=3.0, thickness_units="screen"))
        self._tail = [self._tail[-1]]  # the next chunk starts where this one ends
        tail = self._nodes.pop("tail", None)
        if tail is not None:
            tail.remove()

    def _rebuild_path(self, session: Session) -> None:
        for handle in self._chunks:
            handle.remove()
        self._chunks.clear()
        tail = self._nodes.pop("tail", None)
        if tail is not None:
            tail.remove()
        self._tail, self._path_last = [], None
        _times, positions = session.history.arrays()
        for p in positions:
            self._append_path(p)

    # berth line and targets: what the officer set on the page, in the same scene

    def _update_berth_and_targets(self, session: Session, state: Any | None) -> None:
        line = session.berth.world(state)
        key = None if line is None else tuple(np.round(line, 3).ravel().tolist())
        if key != self._berth_key:
            old = self._nodes.pop("berth", None)
            if old is not None:
                old.remove()
            if line is not None:
                water = session.water.down_m
                foot = np.column_stack([line, np.full(2, water)])
                top = foot - [0.0, 0.0, BERTH_FENCE_M]
                segments = np.array([[foot[0], foot[1]], [top[0], top[1]], [foot[0], top[0]],
                                     [foot[1], top[1]]], dtype=np.float32)
                self._nodes["berth"] = self.server.scene.add_line_segments(
                    "/berth_line", segments, self._color["berth"], thickness=5.0,
                    thickness_units="screen")
            self._berth_key = key
        seen = set()
        for target in session.targets.all():
            seen.add(target.id)
            position = np.asarray(target.position_ned, dtype=float)
            handle = self._targets.get(target.id)
            if handle is None:
                handle = self._targets[target.id] = self.server.scene.add_icosphere(
                    f"/targets/{target.id}", radius=0.35, color=self._color["target"],
                    position=position)
                self.server.scene.add_label(f"/targets/{target.id}/label",
                                            target.label or target.id)
            else:
                handle.position = position
        for gone in set(self._targets) - seen:
            self._targets.pop(gone).remove()

    # structure: new ids appended in chunks, consolidated now and then

    def _update_structure(self, session: Session, now: float) -> None:
        structure = session.structure()
        pts, ids = structure.points, structure.ids
        if len(pts) == 0:
            return
        ids = np.asarray(ids)
        consolidate = (now - self._last_consolidation >= STRUCTURE_REFRESH_S
                       or len(self._point_chunks) >= 16)
        if consolidate:
            for handle in self._point_chunks:
                handle.remove()
            self._point_chunks.clear()
            self._point_ids = set(ids.tolist())
            self._point_chunks.append(self._add_points("/structure/all", pts))
            self._last_consolidation = now
            return
        new = np.array([i not in self._point_ids for i in ids.tolist()], dtype=bool)
        if not new.any():
            return
        for start in range(0, int(new.sum()), POINT_CHUNK):
            chunk = pts[new][start:start + POINT_CHUNK]
            name = f"/structure/chunk_{len(self._point_chunks):04d}"
            self._point_chunks.append(self._add_points(name, chunk))
        self._point_ids.update(ids[new].tolist())

    def _add_points(self, name: str, pts: np.ndarray) -> Any:
        return self.server.scene.add_point_cloud(
            name, np.asarray(pts, dtype=np.float32), self._color["structure"], point_size=0.15,
            precision="float32", point_shape="circle")
