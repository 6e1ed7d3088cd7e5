"""The procedural textured port of the simulator: textures, faces and the builders of the marina
and the container terminal, as drawn for a seed by ``variety``.

World = the scenario's local-level NED frame: the sea surface is the plane down = 0, the quay face
the vertical plane north = 0 over ``quay_east_range``, land at north > 0, quay top at
down = -quay_height_m. The port is a set of planar textured convex polygons ("faces"; boxes are
made of faces): the static port, the boats that move (each its own group of faces, moved rigidly
at render time) and the ship's own hull (in the body frame, carried with the camera).

Textures are painted unlit; ``Builder.finish`` bakes the seed's light into them once every face
exists: sky light, sunlight by Lambert's law and the cast shadows the renderer found
(``scene.PortScene.build``), then aerial haze.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import cv2
import numpy as np

from .scenarios import Scenario
from .variety import FACADE_STYLES, Boat, Light, Port

# ======================================================================= procedural noise

def _fbm(rng: np.random.Generator, h: int, w: int, cell_px: float, octaves: int = 4,
         gain: float = 0.5) -> np.ndarray:
    """Smooth fractal noise (h, w), zero mean, unit std; feature size ~cell_px."""
    # sum the octaves on a grid where the finest one still spans 2 cells, upsample once
    scale = max(1.0, cell_px / 2 ** (octaves - 1) / 2.0)
    hs, ws = max(2, int(np.ceil(h / scale))), max(2, int(np.ceil(w / scale)))
    out = np.zeros((hs, ws), np.float32)
    amp = 1.0
    for o in range(octaves):
        c = max(cell_px / 2 ** o / scale, 1.0)
        gh, gw = int(hs / c) + 3, int(ws / c) + 3
        g = rng.standard_normal((gh, gw)).astype(np.float32)
        up = cv2.resize(g, (int(gw * c), int(gh * c)), interpolation=cv2.INTER_CUBIC)
        out += amp * up[:hs, :ws]
        amp *= gain
    if (hs, ws) != (h, w):
        out = cv2.resize(out, (int(round(ws * scale)), int(round(hs * scale))),
                         interpolation=cv2.INTER_LINEAR)[:h, :w]
    out -= out.mean()
    return out / (out.std() + 1e-6)


def _periodic_noise(rng: np.random.Generator, n: int, k_peak: float, k_width: float,
                    direction: float | None = None, sharpness: int = 2) -> np.ndarray:
    """Tileable band-pass noise (n, n), unit std: spectrum ring at k_peak cycles per tile,
    optionally concentrated around a propagation direction (crests across it)."""
    white = rng.standard_normal((n, n))
    k = np.fft.fftfreq(n) * n
    kx, ky = np.meshgrid(k, k)
    kk = np.hypot(kx, ky)
    amp = np.exp(-(((kk - k_peak) / k_width) ** 2))
    if direction is not None:
        ang = np.arctan2(ky, kx)
        amp *= np.cos(ang - direction) ** (2 * sharpness)
    amp[0, 0] = 0.0
    out = np.real(np.fft.ifft2(np.fft.fft2(white) * amp))
    return (out / (out.std() + 1e-9)).astype(np.float32)


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(img, 0, 255).astype(np.uint8)


def _shade_noise(img: np.ndarray, noise: np.ndarray, amount: float) -> np.ndarray:
    """Multiply a BGR uint8 image by (1 + amount * noise)."""
    f = img.astype(np.float32) * (1.0 + amount * noise[..., None])
    return _to_u8(f)


# ================================================================ texture painting helpers

class _Painter:
    """Draws in metres on a texture of a given pixel density (row 0 = top, v downwards)."""

    def __init__(self, w_m: float, h_m: float, ppm: float, color, rng: np.random.Generator):
        self.ppm = ppm
        self.w_m, self.h_m = w_m, h_m
        self.W = max(2, int(round(w_m * ppm)))
        self.H = max(2, int(round(h_m * ppm)))
        self.img = np.empty((self.H, self.W, 3), np.uint8)
        self.img[:] = np.asarray(color, dtype=np.uint8)
        self.rng = rng
        self.points: list[tuple[float, float, str]] = []

    def px(self, u: float) -> int:
        return int(round(u * self.ppm))

    def rect(self, u0, v0, u1, v1, color, img=None) -> None:
        x0, y0, x1, y1 = self.px(u0), self.px(v0), self.px(u1) - 1, self.px(v1) - 1
        if x1 >= x0 and y1 >= y0:
            cv2.rectangle(self.img if img is None else img, (x0, y0), (x1, y1),
                          tuple(int(c) for c in color), -1)

    def line(self, u0, v0, u1, v1, width_m, color) -> None:
        th = max(1, int(round(width_m * self.ppm)))
        cv2.line(self.img, (self.px(u0), self.px(v0)), (self.px(u1), self.px(v1)),
                 tuple(int(c) for c in color), th, cv2.LINE_AA)

    def circle(self, u, v, r_m, color, thickness_m: float | None = None) -> None:
        th = -1 if thickness_m is None else max(1, int(round(thickness_m * self.ppm)))
        cv2.circle(self.img, (self.px(u), self.px(v)), max(1, self.px(r_m)),
                   tuple(int(c) for c in color), th, cv2.LINE_AA)

    def text(self, s: str, u, v, height_m, color, thickness_m: float | None = None) -> float:
        """Text with its top-left corner at (u, v); returns the width in metres."""
        font = cv2.FONT_HERSHEY_DUPLEX
        (tw, th), _ = cv2.getTextSize(s, font, 1.0, 1)
        scale = height_m * self.ppm / th
        thick = max(1, int(round((thickness_m or height_m * 0.14) * self.ppm)))
        cv2.putText(self.img, s, (self.px(u), self.px(v + height_m)), font, scale,
                    tuple(int(c) for c in color), thick, cv2.LINE_AA)
        return tw * scale / self.ppm

    def corners(self, u0, v0, u1, v1, kind: str) -> None:
        """Record the four corners of a high-contrast rectangle as scene points."""
        self.points += [(u0, v0, kind), (u1, v0, kind), (u0, v1, kind), (u1, v1, kind)]

    def grain(self, cell_m: float, amount: float, octaves: int = 4) -> None:
        n = _fbm(self.rng, self.H, self.W, max(cell_m * self.ppm, 1.0), octaves)
        fine = self.rng.standard_normal((self.H, self.W)).astype(np.float32)
        self.img = _shade_noise(self.img, 0.8 * n + 0.35 * fine, amount)

    def streaks(self, count: int, length_m: float, amount: float, color=None) -> None:
        """Vertical run-off stains hanging from the top edge (or anywhere)."""
        f = self.img.astype(np.float32)
        for _ in range(count):
            u = self.rng.uniform(0, self.w_m)
            v0 = self.rng.uniform(0, 0.3 * self.h_m)
            wd = self.rng.uniform(0.05, 0.5)
            ln = self.rng.uniform(0.3, 1.0) * length_m
            x0, x1 = self.px(u - wd / 2), self.px(u + wd / 2) + 1
            y0, y1 = self.px(v0), self.px(v0 + ln) + 1
            x0, y0 = max(x0, 0), max(y0, 0)
            x1, y1 = min(x1, self.W), min(y1, self.H)
            if x1 <= x0 or y1 <= y0:
                continue
            fade = np.linspace(1.0, 0.0, y1 - y0, dtype=np.float32)[:, None, None]
            across = np.sin(np.linspace(0, np.pi, x1 - x0, dtype=np.float32))[None, :, None]
            a = amount * fade * across * self.rng.uniform(0.4, 1.0)
            target = np.zeros(3, np.float32) if color is None else np.asarray(color, np.float32)
            f[y0:y1, x0:x1] = f[y0:y1, x0:x1] * (1 - a) + target * a
        self.img = _to_u8(f)




# ================================================================ faces, textures, builder

class Texture:
    """BGRA texture with lazily computed ripmap levels (x and y halved independently)."""

    def __init__(self, image: np.ndarray):
        self.set(image)

    def set(self, image: np.ndarray) -> None:
        if image.shape[2] == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2BGRA)
        self.levels: dict[tuple[int, int], np.ndarray] = {(0, 0): np.ascontiguousarray(image)}
        h, w = image.shape[:2]
        self.max_lx = max(0, int(np.log2(max(w, 1))) - 1)
        self.max_ly = max(0, int(np.log2(max(h, 1))) - 1)

    def level(self, lx: int, ly: int) -> np.ndarray:
        key = (lx, ly)
        img = self.levels.get(key)
        if img is None:
            base = self.levels[(0, 0)]
            h, w = base.shape[:2]
            size = (max(1, int(round(w / 2 ** lx))), max(1, int(round(h / 2 ** ly))))
            img = cv2.resize(base, size, interpolation=cv2.INTER_AREA)
            self.levels[key] = img
        return img


@dataclass
class Face:
    origin: np.ndarray  # position of texture coordinate (0, 0)
    u_axis: np.ndarray  # unit vector of texture columns (right as seen from the front)
    v_axis: np.ndarray  # unit vector of texture rows (down as seen from the front)
    size: tuple[float, float]  # (w, h) metres covered by the texture
    texture: Texture
    kind: str
    polygon_uv: np.ndarray  # (K, 2) convex outline in metres, K <= 6
    two_sided: bool = False
    alpha: bool = False

    @property
    def normal(self) -> np.ndarray:
        """Outward normal (the side the texture is seen from)."""
        return np.cross(self.v_axis, self.u_axis)

    def world(self, uv: np.ndarray) -> np.ndarray:
        uv = np.atleast_2d(uv)
        return self.origin + uv[:, :1] * self.u_axis + uv[:, 1:2] * self.v_axis


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


@dataclass
class Mover:
    """A boat that moves: its faces built about its position at t = 0, translated by
    ``boat.position(t)`` (its heading is fixed)."""

    boat: Boat
    faces: list[Face]


@dataclass
class _Unbaked:
    face: Face
    image: np.ndarray  # the painted (unlit) texture
    centre: np.ndarray  # world centre (for the haze), at t = 0 for a mover
    lit: bool
    static: bool  # part of the static port (receives cast shadows)
    body: bool  # the own ship (body frame: its orientation in the world changes)


class Builder:
    """Collects faces (static port, movers, own ship) and scene points; bakes the light into
    the textures at the end (``finish``)."""

    def __init__(self, rng: np.random.Generator, viewpoint: np.ndarray, light: Light):
        self.rng = rng
        self.viewpoint = viewpoint
        self.light = light
        self.faces: list[Face] = []  # the static port
        self.movers: list[Mover] = []
        self.own: list[Face] = []  # the ship's own hull, body frame
        self.points: list[np.ndarray] = []
        self.normals: list[np.ndarray] = []
        self.kinds: list[str] = []
        self._target = self.faces
        self._offset = np.zeros(3)
        self._unbaked: list[_Unbaked] = []

    # -- groups --------------------------------------------------------------------------
    @contextmanager
    def mover(self, boat: Boat) -> Iterator[None]:
        """Faces added inside go to a mover, built about the world origin: build the boat at
        (0, 0) and it is placed at ``boat.position(t)``. Its corners are no scene points (the
        scene points are the static port's)."""
        m = Mover(boat, [])
        with self._group(m.faces, np.array([boat.north, boat.east, 0.0])):
            yield
        self.movers.append(m)

    @contextmanager
    def own_ship(self) -> Iterator[None]:
        """Faces added inside are the ship's own hull, in the body frame."""
        with self._group(self.own, None):
            yield

    @contextmanager
    def _group(self, target: list[Face], offset: np.ndarray | None) -> Iterator[None]:
        saved = self._target, self._offset
        self._target, self._offset = target, offset
        try:
            yield
        finally:
            self._target, self._offset = saved

    # -- faces ---------------------------------------------------------------------------
    def face(self, origin, u_axis, v_axis, w: float, h: float, img: np.ndarray, kind: str,
             polygon_uv=None, two_sided=False, points=(), lit=True) -> Face:
        """Add a face from an (unlit) texture image covering [0, w] x [0, h] metres."""
        origin, u_axis, v_axis = np.asarray(origin, float), _unit(u_axis), _unit(v_axis)
        if polygon_uv is None:
            polygon_uv = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=float)
        normal = np.cross(v_axis, u_axis)
        f = Face(origin, u_axis, v_axis, (w, h), Texture(img[:2, :2]), kind,
                 np.asarray(polygon_uv, float), two_sided, img.shape[2] == 4)
        self._target.append(f)
        static = self._target is self.faces
        body = self._offset is None
        centre = origin + u_axis * w / 2 + v_axis * h / 2 + (0.0 if body else self._offset)
        self._unbaked.append(_Unbaked(f, img, centre, lit, static, body))
        if static:
            for u, v, k in points:
                self.points.append(f.world(np.array([u, v]))[0])
                self.normals.append(normal)
                self.kinds.append(k)
        return f

    def long_face(self, origin, u_axis, v_axis, w: float, h: float, img: np.ndarray,
                  kind: str, chunk_m: float, points=(), lit=True, two_sided=False) -> None:
        """A long face split into chunks (tighter bounding boxes and per-chunk mip levels)."""
        u_axis = _unit(u_axis)
        ppm = img.shape[1] / w
        n = max(1, int(np.ceil(w / chunk_m)))
        edges = np.linspace(0.0, w, n + 1)
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            x0, x1 = int(round(a * ppm)), int(round(b * ppm))
            # one texel of overlap so bilinear filtering is seamless across chunks
            sub = img[:, max(0, x0 - 1):min(img.shape[1], x1 + 1)]
            ua = max(0, x0 - 1) / ppm
            ub = min(img.shape[1], x1 + 1) / ppm
            # a sprite's chunk starts at its first row with anything opaque (tighter boxes)
            top = 0.0
            if sub.shape[2] == 4:
                rows = np.flatnonzero(sub[:, :, 3].max(axis=1) > 0)
                top = rows[0] / img.shape[0] * h if len(rows) else h
            poly = np.array([[a - ua, top], [b - ua, top], [b - ua, h], [a - ua, h]])
            self.face(np.asarray(origin, float) + u_axis * ua, u_axis, v_axis, ub - ua, h, sub,
                      kind, polygon_uv=poly, lit=lit, two_sided=two_sided)
        v_axis = _unit(v_axis)
        if self._target is self.faces:
            for u, v, k in points:  # points in the frame of the whole (unsplit) face
                self.points.append(np.asarray(origin, float) + u * u_axis + v * v_axis)
                self.normals.append(np.cross(v_axis, u_axis))
                self.kinds.append(k)

    def rect_face(self, centre, normal, v_axis, w: float, h: float, paint: Callable,
                  kind: str, two_sided=False, lit=True) -> None:
        """Rectangle centred at ``centre`` with outward ``normal``; ``paint(w, h)`` returns
        (image, points)."""
        n, v = _unit(normal), _unit(v_axis)
        u = np.cross(n, v)
        origin = np.asarray(centre, float) - u * w / 2 - v * h / 2
        img, pts = paint(w, h)
        self.face(origin, u, v, w, h, img, kind, two_sided=two_sided, points=pts, lit=lit)

    def box(self, centre, axes: np.ndarray, half: tuple[float, float, float],
            paint: Callable[[str, float, float], tuple[np.ndarray, list]], kind: str,
            skip: tuple[str, ...] = ("bottom",)) -> None:
        """Box with columns of ``axes`` = (forward, right, down) unit vectors and half sizes;
        ``paint(side, w, h)`` for side in front/back/right/left/top/bottom."""
        c = np.asarray(centre, float)
        a, b, d = axes[:, 0], axes[:, 1], axes[:, 2]
        ha, hb, hd = half
        sides = {
            "front": (a, d, c + a * ha, 2 * hb, 2 * hd),
            "back": (-a, d, c - a * ha, 2 * hb, 2 * hd),
            "right": (b, d, c + b * hb, 2 * ha, 2 * hd),
            "left": (-b, d, c - b * hb, 2 * ha, 2 * hd),
            "top": (-d, -a, c - d * hd, 2 * hb, 2 * ha),
            "bottom": (d, a, c + d * hd, 2 * hb, 2 * ha),
        }
        for name, (n, v, ctr, w, h) in sides.items():
            if name in skip:
                continue
            self.rect_face(ctr, n, v, w, h, lambda w, h, name=name: paint(name, w, h), kind)

    def beam(self, p0, p1, width: float, paint: Callable, kind: str, up_hint=(0, 0, -1.0),
             ends: bool = False, segment_m: float = 25.0) -> None:
        """Square-section beam between two points (no end caps unless asked: they are hidden
        in joints). Long beams are split so that diagonal ones get small bounding boxes."""
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        a = _unit(p1 - p0)
        hint = np.asarray(up_hint, float)
        if abs(a @ _unit(hint)) > 0.95:
            hint = np.array([1.0, 0.0, 0.0])
        b = _unit(np.cross(-hint, a))
        d = np.cross(a, b)
        L = float(np.linalg.norm(p1 - p0))
        skip = () if ends else ("front", "back")
        n = 1 if abs(a[2]) > 0.9 else max(1, int(np.ceil(L / segment_m)))
        for k in range(n):
            q0, q1 = p0 + (p1 - p0) * k / n, p0 + (p1 - p0) * (k + 1) / n
            self.box((q0 + q1) / 2, np.column_stack([a, b, d]), (L / n / 2, width / 2, width / 2),
                     paint, kind, skip=skip)

    # -- light ---------------------------------------------------------------------------
    def finish(self, shadow: Callable[[Face, tuple[int, int]], np.ndarray | None]) -> None:
        """Bake the light into every texture: sky light, sunlight (Lambert) times the
        ``shadow(face, (height, width))`` lit fraction of each texel (None: all lit), then
        aerial haze; the far backdrop (unlit) is only tinted and hazed."""
        L = self.light
        s = L.sun_dir
        amb = np.asarray(L.ambient_colour, np.float32) * np.float32(L.ambient)
        sun = np.asarray(L.sun_colour, np.float32) * np.float32(L.direct)
        haze = np.asarray(L.haze, np.float32)
        # the backdrop is painted in clear-day hazy colours: scale it like a lit surface
        tint = (amb + 0.5 * sun) / np.float32(0.58 + 0.21)
        for u in self._unbaked:
            f, img = u.face, u.image
            out = img.astype(np.float32)
            n = f.normal
            if u.body:
                # the own hull turns with the ship: an average sun on it
                shade = amb * (1.0 + 0.08 * max(0.0, -n[2])) + sun * 0.5 * max(0.0, -n[2])
                out[..., :3] *= shade
            elif not u.lit:
                fog = np.float32(0.3 + 0.7 * (1.0 - np.exp(-np.linalg.norm(
                    u.centre - self.viewpoint) / L.haze_m)))
                out[..., :3] = out[..., :3] * tint * (1 - fog) + haze * fog * 0.85
            else:
                lam = abs(float(n @ s)) if f.two_sided else max(0.0, float(n @ s))
                up = max(0.0, -n[2])
                d = float(np.linalg.norm(u.centre - self.viewpoint))
                fog = np.float32(1.0 - np.exp(-d / L.haze_m))
                lit = shadow(f, img.shape[:2]) if (u.static and lam > 0.0) else None
                base = amb * np.float32(1.0 + 0.08 * up)
                if lit is None:
                    shade = base + sun * np.float32(lam)
                    out[..., :3] = out[..., :3] * (shade * (1 - fog)) + haze * fog
                else:
                    shade = base[None, None, :] + sun[None, None, :] * \
                        (np.float32(lam) * lit)[..., None]
                    out[..., :3] = out[..., :3] * shade * (1 - fog) + haze * fog
            f.texture.set(_to_u8(out))
        self._unbaked = []


def _axes_yaw(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


AXES_NED = np.eye(3)  # box axes forward = north, right = east, down


def _plain(color, rng: np.random.Generator, ppm: float = 8.0, grain: float = 0.06,
           cell_m: float = 1.0) -> Callable:
    """Painter of a plain weathered surface of one colour."""
    def paint(*args):
        w, h = args[-2], args[-1]
        p = _Painter(w, h, min(ppm, 600 / max(w, h, 0.01)), color, rng)
        p.grain(cell_m, grain)
        return p.img, []
    return paint


# ========================================================================= port textures

def _paint_wall_material(p: _Painter, rng: np.random.Generator, top: float, material: str,
                         marina: bool, concrete) -> None:
    """The quay face below the coping (rows from ``top`` down): the wall's material."""
    length, height = p.w_m, p.h_m
    base = np.asarray(concrete, float)
    joint_col = base * 0.6
    if material in ("blocks", "stone"):
        stone = material == "stone"
        v, row = top, 0
        while v < height:
            bh = (rng.uniform(0.25, 0.55) if stone else (0.45 if marina else 1.0))
            off = (row % 2) * 0.6 + rng.uniform(-0.1, 0.1)
            u = -off
            while u < length:
                ln = rng.uniform(0.45, 1.4) if stone else (1.25 if marina else 2.5) * \
                    rng.uniform(0.85, 1.15)
                s = rng.uniform(0.75, 1.15) if stone else rng.uniform(0.82, 1.12)
                col = base * s
                if stone:  # warmer, more varied stones
                    col = col * np.array([rng.uniform(0.8, 1.0), rng.uniform(0.9, 1.05), 1.05])
                j = 0.03 if stone else 0.025
                p.rect(u + j / 2, v + j / 2, u + ln - j / 2, v + bh - j / 2, col)
                p.rect(u - j / 2, v, u + j / 2, v + bh, joint_col)
                u += ln
            p.rect(0, v - 0.0125, length, v + 0.0125, joint_col)
            v += bh
            row += 1
    elif material == "panels":
        pw = 5.0 if marina else 10.0
        for u in np.arange(0.0, length, pw):
            s = rng.uniform(0.92, 1.06)
            p.rect(u, top, u + pw, height, base * s)
            p.rect(u - 0.02, top, u + 0.02, height, base * 0.64)
            for tie in (0.25, 0.75):  # form-tie holes
                for v in np.arange(top + 0.4, height, 0.9):
                    p.circle(u + tie * pw, v, 0.03, base * 0.55)
    else:  # steel sheet piling: trapezoidal pans, painted or rusty, under a concrete cap
        steel = np.array([60.0, 60.0, 64.0]) if rng.random() < 0.5 else \
            np.array([45.0, 70.0, 110.0])
        p.rect(0, top, length, height, steel)
        pitch = 0.6 if marina else 1.2
        x = np.arange(p.W, dtype=np.float32) / p.ppm % pitch / pitch
        # the pans' four faces: front, flank facing left, back, flank facing right
        shade = np.select([x < 0.3, x < 0.5, x < 0.8], [1.0, 0.72, 0.86], 1.22)
        y0 = p.px(top)
        f = p.img[y0:].astype(np.float32) * shade[None, :, None].astype(np.float32)
        p.img[y0:] = _to_u8(f)
        p.streaks(int(length * 0.6), 0.8 * (height - top), 0.5, color=(30, 60, 110))


def _paint_quay_wall(rng: np.random.Generator, length: float, height: float, waterline: float,
                     ppm: float, style: str, east0: float, material: str = "blocks",
                     concrete=(150, 156, 158)) -> tuple[np.ndarray, list]:
    """Quay face: the wall's material, coping with a yellow edge, wet zone and algae, fenders,
    ladders, painted numbers. ``waterline`` = v of the sea surface."""
    marina = style == "marina"
    p = _Painter(length, height, ppm, concrete, rng)
    coping = (0.3 if marina else 0.5) + (0.3 if material == "sheet-pile" else 0.0)
    _paint_wall_material(p, rng, coping, material, marina, concrete)
    if material == "panels" and not marina:
        p.rect(0, coping + 0.5 * (waterline - coping) - 0.02, length,
               coping + 0.5 * (waterline - coping) + 0.02, np.asarray(concrete) * 0.7)
    # coping beam and its painted yellow edge
    cop = np.asarray(concrete, float) * 1.1
    p.rect(0, 0, length, coping, cop)
    p.rect(0, coping - 0.025, length, coping + 0.005, cop * 0.6)
    p.rect(0, 0, length, 0.12 if marina else 0.2, (40, 196, 232))
    p.grain(0.6, 0.07)
    p.streaks(int(length * 1.2), 0.9 * waterline, 0.35)
    p.streaks(int(length * 0.15), 0.6 * waterline, 0.45, color=(40, 70, 120))  # rust
    # wet zone with algae and barnacles above the waterline
    f = p.img.astype(np.float32)
    vv = (np.arange(p.H, dtype=np.float32) + 0.5) / ppm
    tide = waterline - (0.35 if marina else 0.8)
    wobble = _fbm(rng, 1, p.W, 2.0 * ppm, 3)[0] * 0.06
    vmat = vv[:, None] - wobble[None, :]
    wet = np.clip((vmat - tide) / 0.08, 0, 1)[..., None]
    algae = np.clip((vmat - (waterline - 0.25)) / 0.1, 0, 1)[..., None]
    f = f * (1 - 0.45 * wet)
    f = f * (1 - 0.5 * algae) + np.array([40, 85, 60], np.float32) * 0.5 * algae
    p.img = _to_u8(f)
    specks = rng.random((p.H, p.W)) < 0.02 * wet[..., 0]
    p.img[specks] = (p.img[specks] * 1.5).clip(0, 255).astype(np.uint8)

    spacing_fender = float(rng.choice([4.0, 6.0])) if marina else float(rng.choice([12.0, 16.0]))
    spacing_ladder = float(rng.choice([15.0, 20.0, 30.0])) if marina else 50.0
    ladders = np.arange(spacing_ladder * 0.55, length, spacing_ladder)
    tyres = rng.random() < 0.6  # tyres and D-fender strips, or strips only
    # fenders
    for u in np.arange(spacing_fender * 0.5, length, spacing_fender):
        if np.min(np.abs(ladders - u)) < 1.5:
            continue
        if marina:
            if int(u / spacing_fender) % 3 == 0 or not tyres:
                # black rubber D-fender strip
                w, top, bot = 0.25, coping + 0.1, min(waterline + 0.1, height)
                p.rect(u - w / 2 + 0.03, top + 0.03, u + w / 2 + 0.05, bot, (55, 58, 60))
                p.rect(u - w / 2, top, u + w / 2, bot, (30, 31, 33))
                p.rect(u - 0.03, top, u + 0.03, bot, (48, 50, 52))
                p.points += [(u - w / 2, top, "fender"), (u + w / 2, top, "fender")]
            else:
                # car tyre hanging on a chain
                r, vc = 0.33, coping + 0.45 + rng.uniform(-0.05, 0.05)
                p.line(u, 0.05, u, vc - r, 0.025, (60, 62, 64))
                p.circle(u + 0.04, vc + 0.04, r, (70, 72, 74))
                p.circle(u, vc, r, (28, 28, 30))
                p.circle(u, vc, r * 0.5, (120, 124, 126))
                p.circle(u, vc, r * 0.5, (45, 45, 47), thickness_m=0.03)
                p.circle(u - 0.08, vc - 0.08, r * 0.85, (52, 52, 55), thickness_m=0.02)
        else:
            # cell fender: black rubber panel with a frontal pad frame
            w, top = 2.2, coping + 0.3
            bot = min(top + 2.5, waterline + 0.4)
            p.rect(u - w / 2 + 0.15, top + 0.15, u + w / 2 + 0.25, bot + 0.15, (70, 74, 76))
            p.rect(u - w / 2, top, u + w / 2, bot, (30, 31, 34))
            p.rect(u - w / 2 + 0.25, top + 0.25, u + w / 2 - 0.25, bot - 0.25, (48, 50, 54))
            p.points += [(u - w / 2, top, "fender"), (u + w / 2, top, "fender"),
                         (u - w / 2 + 0.25, top + 0.25, "fender"),
                         (u + w / 2 - 0.25, top + 0.25, "fender")]
    # ladders (yellow rails and rungs, a recess behind)
    for u in ladders:
        half = 0.25 if marina else 0.3
        rail = 0.06 if marina else 0.12
        p.rect(u - half - 0.1, coping, u + half + 0.1, height, (80, 84, 86))
        p.rect(u - half, 0, u - half + rail, height, (35, 185, 225))
        p.rect(u + half - rail, 0, u + half, height, (35, 185, 225))
        step = 0.3
        for k, v in enumerate(np.arange(coping + 0.15, height, step)):
            p.rect(u - half, v, u + half, v + rail * 0.8, (35, 185, 225))
            if v + step + rail < waterline - 0.1 and k % 2 == 0:
                # inner corners of a ladder cell: recess (dark) framed by yellow
                p.points += [(u - half + rail, v + rail * 0.8, "ladder"),
                             (u + half - rail, v + rail * 0.8, "ladder")]
    # painted numbers on dark plates
    spacing_no = 15.0 if marina else 25.0
    for i, u in enumerate(np.arange(spacing_no * 0.3, length, spacing_no)):
        if np.min(np.abs(ladders - u)) < 2.5:
            u += 3.0
        num = f"{int((east0 + u) // spacing_no) + 20:02d}"
        if marina:
            ph, pw = 0.42, 0.62
            top = coping + 0.08
            p.rect(u, top, u + pw, top + ph, (70, 45, 25) if i % 2 else (30, 30, 30))
            p.text(num, u + 0.08, top + 0.08, ph - 0.16, (240, 240, 240))
            p.corners(u, top, u + pw, top + ph, "quay")
        else:
            # bollard number painted on the coping, and a large white berth mark
            p.rect(u, 0.05, u + 0.9, 0.41, (30, 30, 30))
            p.text(num, u + 0.12, 0.1, 0.26, (235, 235, 235))
            p.corners(u, 0.05, u + 0.9, 0.41, "quay")
            top = coping + 0.2
            p.rect(u + 4.0, top, u + 5.4, top + 1.5, (235, 235, 235))
            p.text(str(i % 10), u + 4.25, top + 0.2, 1.1, (25, 25, 25), 0.18)
            p.corners(u + 4.0, top, u + 5.4, top + 1.5, "quay")
    return p.img, p.points


FACADE_PALETTE = [(205, 215, 222), (175, 195, 210), (150, 160, 170), (95, 110, 160),
                  (200, 200, 195), (185, 200, 205), (120, 135, 150), (225, 228, 230)]


def _paint_facade(rng: np.random.Generator, w: float, h: float, ppm: float,
                  storey: float = 3.2, style: str = "flats",
                  repetitive: bool = False) -> tuple[np.ndarray, list]:
    """Building facade of a style (``variety.FACADE_STYLES`` or "shed"): wall, rows of
    windows, ground floor shop fronts and signs. ``repetitive``: every window bay the same
    (a curtain wall or a slab block whose bays a tracker cannot tell apart)."""
    wall = np.array(FACADE_PALETTE[rng.integers(len(FACADE_PALETTE))], float)
    if style == "brick":
        wall = np.array([60, 80, 140], float) * rng.uniform(0.8, 1.15)
    p = _Painter(w, h, ppm, wall, rng)
    if style == "shed":
        # corrugated cladding with a roller door and a few windows high up
        p.grain(2.0, 0.05)
        ribs = (np.sin(np.arange(p.W) / ppm * 2 * np.pi / 0.25) * 10).astype(np.float32)
        p.img = _to_u8(p.img.astype(np.float32) + ribs[None, :, None])
        for u in np.arange(6.0, w - 6.0, 14.0):
            dw, dh = 5.0, min(6.0, h - 1.0)
            p.rect(u, h - dh, u + dw, h, (120, 120, 118))
            for v in np.arange(h - dh + 0.3, h, 0.3):
                p.rect(u, v, u + dw, v + 0.03, (95, 95, 95))
            p.corners(u, h - dh, u + dw, h, "building")
        p.rect(0, 0, w, 0.5, wall * 0.7)
        p.streaks(int(w / 2), h * 0.5, 0.2)
        return p.img, p.points
    if style == "blank":
        # rendered wall with hardly any texture: a door, a vent, a sign at most
        p.grain(3.0, 0.015, 2)
        for u in rng.uniform(1.0, max(w - 2.5, 1.5), size=int(rng.integers(0, 3))):
            p.rect(u, h - 2.4, u + 1.2, h, wall * 0.55)
            p.corners(u, h - 2.4, u + 1.2, h, "building")
        p.rect(0, 0, w, 0.3, wall * 0.85)
        p.streaks(int(w / 4), h * 0.3, 0.06)
        return p.img, p.points
    if style == "brick":
        # courses of bricks with light mortar joints (vectorised: thousands of bricks)
        course, brick = 0.075, 0.22
        v = (np.arange(p.H, dtype=np.float32) + 0.5) / ppm
        u = (np.arange(p.W, dtype=np.float32) + 0.5) / ppm
        row = np.floor(v / course)
        bed = (v % course) < 0.7 / ppm
        head = ((u[None, :] + 0.5 * brick * (row[:, None] % 2)) % brick) < 0.7 / ppm
        tone = rng.uniform(0.8, 1.15, size=(int(row.max()) + 1, int(w / brick) + 2))
        col = np.floor((u[None, :] + 0.5 * brick * (row[:, None] % 2)) / brick).astype(int)
        f = p.img.astype(np.float32) * tone[row.astype(int)[:, None], col][..., None]
        f[bed[:, None] | head] = (150, 160, 170)
        p.img = _to_u8(f)
        p.grain(0.8, 0.06)
    else:
        p.grain(2.0, 0.05)
    glass = np.array([95, 80, 60], float) * rng.uniform(0.8, 1.2)
    frame = np.array([215, 218, 220], float)
    if style == "curtain":
        # glass curtain wall: a mullion grid, the same cell everywhere
        mull = np.array(FACADE_PALETTE[rng.integers(len(FACADE_PALETTE))], float) * 0.8
        p.rect(0, 0, w, h, glass)
        grad = np.linspace(1.25, 0.85, p.H, dtype=np.float32)[:, None, None]  # sky reflection
        p.img = _to_u8(p.img.astype(np.float32) * grad)
        cw = rng.uniform(1.2, 2.0)
        for u in np.arange(0.0, w + 1e-6, cw):
            p.rect(u - 0.06, 0, u + 0.06, h, mull)
        for v in np.arange(0.0, h + 1e-6, storey):
            p.rect(0, v - 0.12, w, v + 0.12, mull)
            for u in np.arange(cw, w - 1e-6, cw):
                p.points.append((u, v, "building"))
        if not repetitive:
            for _ in range(int(w * h / 40)):
                u, v = rng.uniform(0, w - cw), rng.uniform(0, h - storey)
                u, v = u - u % cw, v - v % storey
                p.rect(u + 0.06, v + 0.12, u + cw - 0.06, v + storey - 0.12,
                       glass * rng.uniform(0.7, 1.3))
        return p.img, p.points
    n_floors = max(1, int((h - 0.8) / storey))
    ground = storey + 0.8
    win_w, win_h = rng.uniform(1.1, 1.8), rng.uniform(1.2, 1.7)
    pitch = win_w + rng.uniform(0.9, 2.0)
    n_cols = max(1, int((w - 1.0) / pitch))
    margin = (w - n_cols * pitch) / 2 + (pitch - win_w) / 2
    bands = style == "office"
    balconies = style == "flats" and rng.random() < 0.6
    for fl in range(1, n_floors):
        v_top = h - ground - fl * storey + (storey - win_h) * 0.6
        if v_top < 0.5:
            break
        if bands:
            p.rect(0, v_top - 0.1, w, v_top + win_h + 0.1, glass * 0.9)
        for c in range(n_cols):
            u = margin + c * pitch
            g = glass if repetitive else glass * rng.uniform(0.75, 1.25)
            if not repetitive and rng.random() < 0.12:
                g = np.array([150, 170, 185])  # blinds down
            p.rect(u - 0.06, v_top - 0.06, u + win_w + 0.06, v_top + win_h + 0.06, frame)
            p.rect(u, v_top, u + win_w, v_top + win_h, g)
            p.rect(u, v_top + win_h * 0.45, u + win_w, v_top + win_h * 0.48, frame * 0.9)
            p.corners(u, v_top, u + win_w, v_top + win_h, "building")
            if balconies and (repetitive or rng.random() < 0.5):
                p.rect(u - 0.3, v_top + win_h + 0.05, u + win_w + 0.3,
                       v_top + win_h + 0.12, wall * 0.6)
    # ground floor: shop windows, doors, a sign board
    v0 = h - ground
    u = 1.0 if repetitive else rng.uniform(0.5, 2.0)
    while u < w - 2.0:
        sw = 3.0 if repetitive else rng.uniform(2.0, 4.5)
        if u + sw > w - 0.5:
            break
        p.rect(u, v0 + 1.2, u + sw, h - 0.15, glass * 0.7)
        p.corners(u, v0 + 1.2, u + sw, h - 0.15, "building")
        u += sw + (1.5 if repetitive else rng.uniform(0.8, 2.5))
    if w > 8 and not repetitive:
        colours = [(40, 40, 190), (170, 90, 20), (30, 150, 30), (30, 160, 220), (230, 230, 230)]
        sc = np.array(colours[rng.integers(len(colours))])
        su = rng.uniform(0.5, w - 6.0)
        p.rect(su, v0 + 0.2, su + 5.0, v0 + 0.95, sc)
        p.text("MARINE" if rng.random() < 0.5 else "CAFE", su + 0.3, v0 + 0.33, 0.45,
               (255, 255, 255) if sc.sum() < 500 else (20, 20, 20))
        p.corners(su, v0 + 0.2, su + 5.0, v0 + 0.95, "building")
    p.rect(0, 0, w, 0.45, wall * 0.75)  # parapet
    if not repetitive:
        for u in rng.uniform(0.5, w - 0.5, size=max(1, int(w / 15))):
            p.rect(u, 0.45, u + 0.12, h, wall * 0.8)  # down pipes
    p.streaks(int(w), h * 0.6, 0.12)
    return p.img, p.points


def _facade_style(rng: np.random.Generator, port: Port) -> str:
    return FACADE_STYLES[int(rng.choice(len(FACADE_STYLES), p=np.asarray(port.facade_weights)
                                        / np.sum(port.facade_weights)))]


CONTAINER_COLOURS = [(175, 125, 45), (45, 50, 170), (60, 120, 40), (30, 110, 220),
                     (150, 150, 150), (225, 225, 220), (50, 50, 120), (40, 190, 220),
                     (110, 60, 30), (140, 120, 30), (40, 40, 40)]

def _paint_containers(rng: np.random.Generator, w: float, h: float, cell_w: float,
                      cell_h: float, ppm: float, kind: str, top: bool = False,
                      colours: np.ndarray | None = None) -> tuple[np.ndarray, list]:
    """A wall (or roof) of stacked containers: grid of cells with corrugation and gaps."""
    p = _Painter(w, h, ppm, (35, 35, 35), rng)
    nu, nv = max(1, int(round(w / cell_w))), max(1, int(round(h / cell_h)))
    cw, ch = w / nu, h / nv
    gap = 0.08
    for i in range(nu):
        for j in range(nv):
            c = np.array(CONTAINER_COLOURS[rng.integers(len(CONTAINER_COLOURS))], float)
            if colours is not None:
                c = colours[(i + 3 * j) % len(colours)]
            c = c * rng.uniform(0.85, 1.1)
            u0, v0 = i * cw + gap / 2, j * ch + gap / 2
            u1, v1 = (i + 1) * cw - gap / 2, (j + 1) * ch - gap / 2
            p.rect(u0, v0, u1, v1, c)
            if not top:
                p.rect(u0, v0, u1, v0 + 0.12, c * 0.75)  # top rail
                p.rect(u0, v1 - 0.1, u1, v1, c * 0.7)  # bottom rail
                if cell_w > 5 and rng.random() < 0.35:
                    p.text(["MSK", "ONE", "CMA", "EVG", "COS", "HPL"][rng.integers(6)],
                           u0 + 2.0, v0 + 0.6, 0.9, (235, 235, 235))
                if cell_w < 5:  # door end: locking bars
                    for uu in np.linspace(u0 + 0.3, u1 - 0.3, 4):
                        p.rect(uu - 0.03, v0 + 0.15, uu + 0.03, v1 - 0.15, c * 0.6)
            if i > 0 and j > 0 and not top:  # roofs are seen too obliquely for good corners
                p.points.append((i * cw, j * ch, kind))
    if not top:
        rib = (np.cos(np.arange(p.W) / ppm * 2 * np.pi / 0.3) * 9).astype(np.float32)
        p.img = _to_u8(p.img.astype(np.float32) + rib[None, :, None])
    p.grain(1.5, 0.05, 3)
    return p.img, p.points


def _lattice(rng: np.random.Generator, w: float, h: float, ppm: float, color,
             panel: float, chord: float) -> np.ndarray:
    """See-through truss (BGRA): top and bottom chords, verticals and diagonals."""
    p = _Painter(w, h, ppm, color, rng)
    alpha = np.zeros((p.H, p.W), np.uint8)
    th = max(2, int(round(chord * ppm)))
    thd = max(1, int(round(chord * 0.55 * ppm)))
    cv2.rectangle(alpha, (0, 0), (p.W - 1, th - 1), 255, -1)
    cv2.rectangle(alpha, (0, p.H - th), (p.W - 1, p.H - 1), 255, -1)
    n = max(1, int(round(w / panel)))
    xs = np.linspace(0, p.W - 1, n + 1).astype(int)
    for k, x in enumerate(xs):
        cv2.line(alpha, (int(x), 0), (int(x), p.H - 1), 255, thd)
        if k < n:
            a, b = (0, p.H - 1) if k % 2 == 0 else (p.H - 1, 0)
            cv2.line(alpha, (int(x), a), (int(xs[k + 1]), b), 255, thd)
    p.grain(2.0, 0.05, 2)
    return np.dstack([p.img, alpha])


def _tree_sprite(rng: np.random.Generator, w: float, h: float, ppm: float) -> np.ndarray:
    """Deciduous tree (BGRA): ragged round canopy on a thin trunk."""
    p = _Painter(w, h, ppm, (45, 60, 75), rng)
    yy, xx = np.mgrid[0:p.H, 0:p.W].astype(np.float32) / ppm
    cx, cy, rx, ry = w / 2, 0.38 * h, 0.47 * w, 0.36 * h
    edge = _fbm(rng, p.H, p.W, 0.5 * ppm, 3)
    canopy = ((xx - cx) / rx) ** 2 + ((yy - cy) / ry) ** 2 + 0.22 * edge < 1.0
    trunk = (np.abs(xx - cx) < 0.035 * w + 0.02 * (yy - cy)) & (yy > cy)
    leaves = _fbm(rng, p.H, p.W, 0.25 * ppm, 3)
    light = np.clip(1.15 - 0.6 * (yy - (cy - ry)) / (2 * ry), 0.6, 1.2)
    green = np.array([50, 105, 70], np.float32) * rng.uniform(0.85, 1.15)
    col = green * (light * (1 + 0.22 * leaves))[..., None]
    img = np.where(canopy[..., None], col, p.img.astype(np.float32))
    alpha = ((canopy | trunk) * 255).astype(np.uint8)
    return np.dstack([_to_u8(img), alpha])


def _skyline_sprite(rng: np.random.Generator, w: float, h: float, ppm: float, kind: str,
                    base_color) -> np.ndarray:
    """Far backdrop (BGRA): mountain ridges ("hills") or city blocks ("city") silhouette."""
    p = _Painter(w, h, ppm, base_color, rng)
    rows = (np.arange(p.H, dtype=np.float32)[:, None] + 0.5) / ppm
    col = np.asarray(base_color, np.float32)
    if kind == "hills":
        ridge = _fbm(rng, 1, p.W, p.W / 5.0, 5, 0.45)[0]
        top = h * np.clip(0.42 - 0.2 * ridge, 0.05, 0.9)
        below = np.clip((rows - top[None, :]) / (0.6 * h), 0, 1)
        forest = _fbm(rng, p.H, p.W, 6.0, 3)
        # darker and greener lower down, hazier towards the ridge line
        shade = (0.92 + 0.05 * forest) * (1.05 - 0.25 * below)
    else:
        top = np.full(p.W, 0.95 * h, np.float32)
        u = 0.0
        while u < w:
            bw = rng.uniform(0.004, 0.012) * w
            bh = rng.uniform(0.1, 0.9) * h
            sl = slice(p.px(u), p.px(u + bw))
            top[sl] = np.minimum(top[sl], h - bh)
            u += bw + rng.uniform(0.0, 0.004) * w
        tone = np.repeat(rng.uniform(0.85, 1.1, size=p.W // 8 + 1), 8)[:p.W]
        win = (((np.arange(p.H) // 2) % 3 == 0)[:, None] & ((np.arange(p.W) // 2) % 3 == 0)
               [None, :]) & (rng.random((p.H, p.W)) < 0.5)
        shade = tone[None, :] * (1.0 - 0.12 * win)
    alpha = (rows >= top[None, :]).astype(np.uint8) * 255
    img = col[None, None, :] * shade[..., None]
    return np.dstack([_to_u8(img), alpha])




# ============================================================================ the marina

def _bollard(b: Builder, n: float, e: float, top_down: float, size: float, colour,
             kind: str = "bollard", cap: bool = True) -> None:
    """Mooring bollard: post with a wider cap (left out for bollards only seen from afar);
    a white band on the sides."""
    rng = b.rng
    body_h, cap_h = 1.3 * size, 0.3 * size

    def paint_body(side, w, h):
        p = _Painter(w, h, min(200.0, 60 / size), colour, rng)
        p.grain(0.1, 0.08, 2)
        if side in ("back", "left", "right", "front"):
            m = 0.18 * w
            p.rect(m, 0.25 * h, w - m, 0.55 * h, (225, 225, 225))
            p.corners(m, 0.25 * h, w - m, 0.55 * h, kind)
        return p.img, p.points

    def paint_cap(side, w, h):
        p = _Painter(w, h, min(200.0, 60 / size), np.asarray(colour) * 0.85, rng)
        p.grain(0.1, 0.08, 2)
        return p.img, []

    d_body = top_down - body_h / 2
    b.box((n, e, d_body), AXES_NED, (size / 2, size / 2, body_h / 2), paint_body, kind,
          skip=("bottom", "top") if cap else ("bottom",))
    if cap:
        b.box((n, e, top_down - body_h - cap_h / 2), AXES_NED,
              (0.7 * size, 0.7 * size, cap_h / 2), paint_cap, kind, skip=())


def _hull_sides(b: Builder, c: np.ndarray, fwd: np.ndarray, right: np.ndarray,
                outline: list[tuple[float, float]], top_d: float, bot_d: float,
                paint: Callable[[float, float, int], tuple[np.ndarray, list]], kind: str) -> None:
    """Vertical hull plating along a closed outline (forward, right) from ``top_d`` down to
    ``bot_d``, seen from outside."""
    for k in range(len(outline)):
        a2 = np.array(outline[k])
        b2 = np.array(outline[(k + 1) % len(outline)])
        pa = c + a2[0] * fwd + a2[1] * right
        pb = c + b2[0] * fwd + b2[1] * right
        w = float(np.linalg.norm(pb - pa))
        normal = np.cross(_unit(pb - pa), np.array([0, 0, 1.0]))
        if normal @ (0.5 * (pa + pb) - c) < 0:
            normal = -normal
        mid = 0.5 * (pa + pb) + np.array([0, 0, 0.5 * (top_d + bot_d)])
        b.rect_face(mid, normal, (0, 0, 1.0), w, bot_d - top_d,
                    lambda w, h, k=k: paint(w, h, k), kind)


def _deck(b: Builder, c: np.ndarray, fwd: np.ndarray, right: np.ndarray,
          outline: list[tuple[float, float]], L: float, B: float, down: float,
          img: np.ndarray, kind: str) -> None:
    """The deck inside a pointed outline, seen from above (texture rows run aft)."""
    o = c + (L / 2) * fwd - (B / 2) * right + np.array([0, 0, down])
    poly = np.array([[(q[1] + B / 2), (L / 2 - q[0])] for q in outline])
    b.face(o, right, -fwd, B, L, img, kind, polygon_uv=poly)


def _boat(b: Builder, n: float, e: float, yaw: float, length: float, beam: float,
          freeboard: float, sail: bool) -> None:
    """Moored yacht / motor boat: pointed hull prism, cabin, optional mast."""
    rng = b.rng
    axes = _axes_yaw(yaw)
    fwd, right = axes[:, 0], axes[:, 1]
    c = np.array([n, e, 0.0])
    hull_col = [(235, 235, 232), (230, 228, 220), (120, 60, 25), (40, 40, 40)][rng.integers(4)]
    stripe = [(150, 70, 20), (40, 40, 170), (60, 60, 60)][rng.integers(3)]
    L, B = length, beam
    outline = [(-L / 2, -B / 2), (L / 4, -B / 2), (L / 2, 0.0), (L / 4, B / 2), (-L / 2, B / 2)]
    top_d, bot_d = -freeboard, 0.4
    ppm = 40.0
    name = ["SEA BREEZE", "KAZE", "AOI MARU", "NAGISA", "HOPE", "MINATO"][rng.integers(6)]

    def paint(w, h, k):
        p = _Painter(w, h, ppm, hull_col, rng)
        p.rect(0, 0, w, 0.08, (200, 200, 200))
        p.rect(0, h - 0.4 - 0.12, w, h - 0.4, stripe)
        if w > 2.5 and k in (0, 3):
            p.text(name, 0.3 * w, 0.25 * (h - 0.4), 0.22, stripe)
        p.grain(0.5, 0.03, 2)
        return p.img, []
    _hull_sides(b, c, fwd, right, outline, top_d, bot_d, paint, "boat")
    _deck(b, c, fwd, right, outline, L, B, top_d,
          _plain((200, 205, 205), rng, ppm=20.0, grain=0.05)(B, L)[0], "boat")
    # cabin with a dark window band
    cab_l, cab_w, cab_h = 0.35 * L, 0.6 * B, 0.55 + 0.1 * L * (not sail)

    def paint_cabin(side, w, h):
        p = _Painter(w, h, ppm, (228, 228, 228), rng)
        if side != "top":
            p.rect(0.12 * w, 0.2 * h, 0.88 * w, 0.55 * h, (45, 40, 35))
            p.corners(0.12 * w, 0.2 * h, 0.88 * w, 0.55 * h, "boat")
        p.grain(0.5, 0.03, 2)
        return p.img, p.points
    cab_c = c - 0.05 * L * fwd + np.array([0, 0, top_d - cab_h / 2])
    b.box(cab_c, axes, (cab_l / 2, cab_w / 2, cab_h / 2), paint_cabin, "boat")
    if sail:
        mast_h = 1.3 * L
        base = c + 0.12 * L * fwd + np.array([0, 0, top_d - cab_h])
        b.beam(base, base + np.array([0, 0, -mast_h]), 0.14,
               _plain((210, 212, 214), rng, ppm=40.0, grain=0.03), "boat", up_hint=fwd,
               ends=False)


def _place_boat(b: Builder, boat: Boat) -> None:
    """A boat of the port: in the static port, or a mover when it moves."""
    build = {"yacht": lambda n, e: _boat(b, n, e, np.radians(boat.yaw_deg), boat.length,
                                          boat.beam, boat.freeboard, boat.sail),
             "feeder": lambda n, e: _moored_ship(b, n, e, np.radians(boat.yaw_deg),
                                                 boat.length, boat.beam, boat.freeboard),
             "tug": lambda n, e: _tug(b, n, e, np.radians(boat.yaw_deg))}[boat.kind]
    if boat.moves:
        with b.mover(boat):
            build(0.0, 0.0)
    else:
        build(boat.north, boat.east)


def _tower_crane(b: Builder, n: float, e: float, ground: float, height: float, jib: float,
                 yaw: float, colours) -> None:
    """Construction tower crane: lattice mast, jib and counter-jib, cab, counterweight."""
    rng = b.rng
    col, dark = colours
    half = 1.0
    for k in range(4):  # the mast's four lattice sides
        ang = k * np.pi / 2
        u = np.array([np.cos(ang), np.sin(ang), 0.0])
        off = np.cross(u, [0, 0, 1.0]) * half
        lat = _lattice(rng, 2 * half, height, 10.0, col, 2.0, 0.18)
        b.face(np.array([n, e, ground - height]) + off - u * half, u, (0, 0, 1), 2 * half,
               height, lat, "crane", two_sided=True)
    fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    side = np.cross([0, 0, 1.0], fwd)
    top = np.array([n, e, ground - height])
    for s in (-0.8, 0.8):  # jib and counter-jib: two lattice girders
        lat = _lattice(rng, jib * 1.3, 1.6, 10.0, col, 1.6, 0.15)
        b.face(top - fwd * 0.3 * jib + side * s + np.array([0, 0, -1.6]), fwd, (0, 0, 1),
               jib * 1.3, 1.6, lat, "crane", two_sided=True)
    b.box(top - fwd * 0.27 * jib + np.array([0, 0, -1.0]), np.column_stack(
        [fwd, side, [0, 0, 1.0]]), (1.5, 1.2, 1.0), _plain((120, 124, 126), rng, 10.0),
        "crane", skip=())
    b.box(top + fwd * 1.8 + np.array([0, 0, 0.8]), np.column_stack([fwd, side, [0, 0, 1.0]]),
          (1.0, 1.0, 0.9), _plain(dark, rng, 12.0), "crane", skip=())


def _own_small_boat(b: Builder, sc: Scenario) -> None:
    """The boat's own foredeck, pulpit rail and topsides (body frame: forward, right, down;
    the waterline is ``-reference_point_down_m`` below the body origin)."""
    rng = b.rng
    outline = [tuple(q) for q in np.asarray(sc.hull_outline()) - sc.motion_centre_body]
    L, B = sc.hull_length_m, sc.hull_beam_m
    waterline = -sc.reference_point_down_m
    deck = waterline - sc.freeboard_m
    c = np.array([*np.asarray(sc.motion_centre_body, float), 0.0])
    fwd, right = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])

    def paint_deck(w, h):  # w across, h along (rows run aft from the bow)
        p = _Painter(w, h, 60.0, (222, 226, 226), rng)
        p.grain(0.05, 0.04, 2)
        p.rect(0.5 * w - 0.3, 0.9, 0.5 * w + 0.3, 1.5, (150, 154, 156))  # anchor locker
        p.rect(0.5 * w - 0.02, 0.35, 0.5 * w + 0.02, 0.9, (90, 90, 92))  # chain
        for s in (0.12, 0.88):  # teak toe-rails
            p.rect(s * w - 0.04, 0.0, s * w + 0.04, h, (60, 100, 150))
        p.rect(0.5 * w - 0.35, 2.2, 0.5 * w + 0.35, 2.9, (70, 70, 72))  # fore hatch
        return p.img

    _deck(b, c, fwd, right, outline, L, B, deck, paint_deck(B, L), "own-ship")

    def topsides(w, h, k):
        p = _Painter(w, h, 40.0, (236, 236, 232), rng)
        p.rect(0, 0.0, w, 0.06, (160, 160, 160))
        p.grain(0.4, 0.03, 2)
        return p.img, []
    _hull_sides(b, c, fwd, right, outline, deck, waterline + 0.1, topsides, "own-ship")
    # stainless pulpit: a rail 0.45 m above the deck round the bow on four stanchions (thin
    # two-sided strips facing up / sideways)
    steel = _plain((205, 208, 210), rng, ppm=200.0, grain=0.05)
    x_bow, x_sh = outline[0][0], outline[1][0]
    rail_d = deck - 0.45
    tube = 0.035
    rail = [np.array([x_sh - 0.5, -0.42 * B, rail_d]), np.array([x_bow - 0.25, -0.12, rail_d]),
            np.array([x_bow - 0.25, 0.12, rail_d]), np.array([x_sh - 0.5, 0.42 * B, rail_d])]
    for a, c2 in zip(rail[:-1], rail[1:], strict=True):
        along = c2 - a
        n_seg = max(1, int(np.ceil(np.linalg.norm(along) / 0.6)))
        side = _unit(np.cross(along, [0.0, 0.0, 1.0])) * tube / 2
        for k in range(n_seg):
            q = a + along * k / n_seg
            b.face(q - side, along / n_seg, side, float(np.linalg.norm(along)) / n_seg, tube,
                   steel(1.0, 0.04)[0], "own-ship", two_sided=True)
    for q in rail:
        b.face(q + np.array([0.0, -tube / 2, 0.0]), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), tube, 0.45,
               steel(0.04, 0.5)[0], "own-ship", two_sided=True)


def _build_marina(b: Builder, sc: Scenario, port: Port) -> np.ndarray:
    rng = b.rng
    e0, e1 = sc.quay_east_range
    qh = port.quay_height_m
    below = 0.8
    L = e1 - e0
    # quay wall face (normal south)
    img, pts = _paint_quay_wall(rng, L, qh + below, qh, 64.0, "marina", e0,
                                port.quay_material, port.concrete)
    b.long_face((0.0, e0, -qh), (0, 1, 0), (0, 0, 1), L, qh + below, img, "quay", 10.0,
                points=pts)
    # quay top (apron strip) and the promenade behind it
    pave = np.array([(165, 170, 170), (150, 160, 175), (140, 150, 165),
                     (175, 175, 168)][rng.integers(4)], float)
    slab = float(rng.choice([0.5, 1.0, 2.0]))

    def paving(w, h, ppm=12.0):
        p = _Painter(w, h, ppm, pave, rng)
        for v in np.arange(0, h, slab):
            p.rect(0, v, w, v + 0.03, pave * 0.8)
        p.rect(0, h - 0.12, w, h, (40, 196, 232))  # yellow edge line
        p.grain(1.0, 0.06)
        return p.img
    b.long_face((8.0, e0 - 40.0, -qh), (0, 1, 0), (-1, 0, 0), L + 80.0, 8.0,
                paving(L + 80.0, 8.0), "quay", 20.0)
    # the land behind: streets up to 150 m (beside the promenade from 30 m, behind the
    # revetments), then the town out to the hills (a little lower: never coplanar)
    ground = _plain(pave * 0.85, rng, ppm=3.0, grain=0.1, cell_m=3.0)
    b.long_face((150.0, e0 - 40.0, -qh), (0, 1, 0), (-1, 0, 0), L + 80.0, 142.0,
                ground(L + 80.0, 142.0)[0], "ground", 40.0)
    for a, z in ((-460.0, e0 - 40.0), (e1 + 40.0, 460.0)):
        b.long_face((150.0, a, -qh), (0, 1, 0), (-1, 0, 0), z - a, 120.0,
                    ground(z - a, 120.0)[0], "ground", 100.0)
    b.long_face((2600.0, -1500.0, -qh + 0.05), (0, 1, 0), (-1, 0, 0), 3000.0, 2450.0,
                _plain(pave * 0.7, rng, 0.2, 0.2, 50.0)(3000.0, 2450.0)[0], "ground", 600.0)
    # rubble revetments continuing the shore beyond the quay ends
    for side in (-1, 1):
        start = e0 if side < 0 else e1
        length = 400.0
        a_e = start - length if side < 0 else start
        slope_v = _unit((-3.0, 0.0, qh + 0.8))  # from the crest down to the toe

        def rocks(w, h, ppm=10.0):
            p = _Painter(w, h, ppm, (60, 66, 70), rng)
            for _ in range(int(w * h * 2.2)):
                u, v = rng.uniform(0, w), rng.uniform(0, h)
                r = rng.uniform(0.25, 0.6)
                col = np.array([120, 128, 135]) * rng.uniform(0.6, 1.25)
                cv2.ellipse(p.img, (p.px(u), p.px(v)), (p.px(r), p.px(r * 0.7)),
                            rng.uniform(0, 180), 0, 360, tuple(int(x) for x in col), -1,
                            cv2.LINE_AA)
            p.grain(0.3, 0.1, 2)
            return p.img
        slope_len = float(np.hypot(3.0, qh + 0.8))
        b.long_face((0.0, a_e, -qh), (0, 1, 0), slope_v, length, slope_len,
                    rocks(length, slope_len), "shore", 40.0)
        b.long_face((30.0, a_e, -qh), (0, 1, 0), (-1, 0, 0), length, 30.0,
                    _plain((95, 130, 110), rng, ppm=2.0, grain=0.15, cell_m=4.0)(length, 30.0)[0],
                    "shore", 50.0)
    # bollards on the quay edge
    spacing = float(rng.choice([6.0, 8.0, 10.0]))
    for e in np.arange(e0 + 4.0, e1 - 2.0, spacing):
        _bollard(b, 0.45, e, -qh, 0.3, (38, 38, 40))
    outline = np.array([[0.0, e0], [0.0, e1]])
    if port.pontoon is not None:  # floating pontoon with guide piles
        pe, plen, pw = port.pontoon
        pfb = 0.45

        def pontoon(side, w, h):
            if side == "top":
                p = _Painter(w, h, 24.0, (90, 120, 150), rng)
                for u in np.arange(0, w, 0.15):
                    p.rect(u, 0, u + 0.012, h, (60, 80, 100))
                p.grain(0.4, 0.08, 2)
                return p.img, []
            p = _Painter(w, h, 32.0, (190, 192, 190), rng)
            p.rect(0, 0, w, 0.12, (35, 35, 38))  # rubber rub-rail
            for u in np.arange(2.0, w - 0.5, 2.5):
                p.rect(u - 0.015, 0.12, u + 0.015, h, (120, 122, 122))
                p.points.append((u, 0.12, "pontoon"))
            p.grain(0.4, 0.05, 2)
            return p.img, p.points
        b.box((-plen / 2, pe + pw / 2, (-pfb + 0.3) / 2), AXES_NED,
              (plen / 2, pw / 2, (pfb + 0.3) / 2), pontoon, "pontoon")

        def pile(side, w, h):
            p = _Painter(w, h, 40.0, (70, 72, 75), rng)
            if side == "top":
                return p.img, []
            p.rect(0, 0, w, 0.5, (40, 196, 232))
            p.rect(0, 0.5, w, 0.62, (30, 30, 30))
            p.rect(0.3 * w, 1.2, 0.7 * w, 1.5, (230, 230, 230))  # pile number plate
            p.streaks(3, h * 0.8, 0.4, color=(40, 70, 120))
            p.corners(0.3 * w, 1.2, 0.7 * w, 1.5, "pontoon")
            return p.img, p.points
        for pn in np.arange(-6.0, -plen + 2.0, -12.0):
            b.box((pn, pe + pw + 0.35, -1.5), AXES_NED, (0.28, 0.28, 2.5), pile, "pontoon")
        outline = np.array([[0.0, e0], [0.0, pe], [-plen, pe], [-plen, pe + pw],
                            [0.0, pe + pw], [0.0, e1]])
    for boat in port.boats:
        _place_boat(b, boat)
    # buildings behind the promenade
    e = e0 - 40.0
    while e < e1 + 40.0:
        ht = float(rng.choice(port.heights_m))
        w = rng.uniform(14.0, 26.0) if ht > 30.0 else rng.uniform(10.0, 30.0)
        d = rng.uniform(10.0, 18.0)
        n0 = rng.uniform(*port.setback_m)
        style = _facade_style(rng, port)
        rep = bool(rng.random() < port.repetitive)
        storey = float(rng.uniform(2.9, 3.6))
        roof = _plain((130, 135, 140), rng, 4.0)

        def facade(side, fw, fh, style=style, rep=rep, storey=storey, roof=roof):
            if side == "top":
                return roof(fw, fh)
            return _paint_facade(rng, fw, fh, 20.0, storey, style=style, repetitive=rep)
        b.box((n0 + d / 2, e + w / 2, -qh - ht / 2), AXES_NED, (d / 2, w / 2, ht / 2), facade,
              "building")
        e += w + rng.uniform(*port.gap_m)
    # trees along the promenade and between buildings (crossed sprites)
    for e in np.arange(e0 - 20.0, e1 + 20.0, 15.0) + rng.uniform(-3, 3):
        if rng.random() > port.trees:
            continue
        th = rng.uniform(5.0, 8.0)
        tw = th * rng.uniform(0.65, 0.85)
        spr = _tree_sprite(rng, tw, th, 16.0)
        n = rng.uniform(11.0, 14.0)
        for ang in (0.0, np.pi / 2):
            u = np.array([np.cos(ang + 0.3), np.sin(ang + 0.3), 0.0])
            b.face(np.array([n, e, -qh - th]) - u * tw / 2, u, (0, 0, 1), tw, th, spr, "tree",
                   two_sided=True)
    for _ in range(port.cranes):  # a building site behind the front row
        _tower_crane(b, rng.uniform(port.setback_m[1] + 20.0, port.setback_m[1] + 60.0),
                     rng.uniform(e0, e1), -qh, rng.uniform(35.0, 60.0), rng.uniform(30.0, 50.0),
                     rng.uniform(0, 2 * np.pi), port.crane_colours)
    # far town and the mountains to the north (Rokko behind Nishinomiya)
    if port.town:
        _backdrop(b, 280.0, 1600.0, rng.uniform(20.0, 45.0), "city", (165, 165, 162), -qh)
    if port.hills_m > 0.0:
        _backdrop(b, 2600.0, 12000.0, port.hills_m, "hills", (118, 128, 106), -qh)
    return outline


def _backdrop(b: Builder, north: float, width: float, height: float, kind: str, colour,
              ground: float) -> None:
    """A far silhouette (city or hills) facing south, one continuous sprite cut into panels;
    its bottom is hidden below the ground."""
    ppm = min(6.0, 9000.0 / width)
    spr = _skyline_sprite(b.rng, width, height, ppm, kind, colour)
    b.long_face((north, -width / 2, ground - height + 2.0), (0, 1, 0), (0, 0, 1), width, height,
                spr, "far", width / 8.0, lit=False)
# ================================================================= the container terminal

def _crane(b: Builder, e: float, ground: float, number: int, colours) -> None:
    """Ship-to-shore gantry crane: legs on rails at north 3 and 33, lattice boom over the
    water, machinery house, A-frame and forestays, trolley with a hanging container."""
    rng = b.rng
    red, white = colours
    leg_top = ground - 45.0

    def leg(side, w, h):
        p = _Painter(w, h, 12.0, white, rng)
        for v in np.arange(0.0, 8.0, 4.0):
            p.rect(0, v, w, v + 2.0, red)
        if side in ("back", "front"):
            p.rect(0.2 * w, 12.0, 0.8 * w, 14.0, (30, 30, 30))
            p.text(str(number), 0.28 * w, 12.3, 1.3, (240, 240, 240))
            p.corners(0.2 * w, 12.0, 0.8 * w, 14.0, "crane")
            p.rect(0.3 * w, h - 3.5, 0.7 * w, h - 0.5, (90, 90, 92))  # access door
            p.corners(0.3 * w, h - 3.5, 0.7 * w, h - 0.5, "crane")
        p.grain(1.0, 0.05, 2)
        return p.img, p.points
    for n in (3.0, 33.0):
        for de in (-9.0, 9.0):
            b.box((n, e + de, (ground + leg_top) / 2), AXES_NED, (0.9, 0.9, 22.5), leg, "crane",
                  skip=("bottom", "top"))
    girder = _plain(red, rng, 10.0, 0.05)
    whitep = _plain(white, rng, 10.0, 0.05)
    for de in (-9.0, 9.0):
        b.beam((3.0, e + de, ground - 14.0), (33.0, e + de, ground - 14.0), 1.6, whitep, "crane")
    b.beam((3.0, e - 9.0, leg_top), (3.0, e + 9.0, leg_top), 2.0, whitep, "crane")
    b.beam((33.0, e - 9.0, leg_top), (33.0, e + 9.0, leg_top), 2.0, whitep, "crane")
    # boom: two lattice girders (two-sided see-through faces) and cross girders
    n_tip, n_back, dz = -52.0, 50.0, 4.5
    for de in (-8.0, 8.0):
        lat = _lattice(rng, n_back - n_tip, dz, 10.0, red, 4.5, 0.45)
        b.long_face((n_back, e + de, leg_top - dz), (-1, 0, 0), (0, 0, 1), n_back - n_tip, dz,
                    lat, "crane", 26.0, two_sided=True)
    for nn in (n_tip + 1.0, 10.0):
        b.beam((nn, e - 8.0, leg_top - 0.4), (nn, e + 8.0, leg_top - 0.4), 0.8, girder, "crane")

    def house(side, w, h):
        p = _Painter(w, h, 10.0, white, rng)
        p.rect(0, h - 1.2, w, h, red)
        if side not in ("top", "bottom"):
            for u in np.arange(1.0, w - 2.0, 3.0):
                p.rect(u, 1.5, u + 1.6, 2.8, (70, 60, 50))
                p.corners(u, 1.5, u + 1.6, 2.8, "crane")
        p.grain(1.0, 0.04, 2)
        return p.img, p.points
    b.box((38.0, e, leg_top - dz - 3.5), AXES_NED, (8.0, 8.5, 3.5), house, "crane", skip=())
    # A-frame and forestays
    apex_d = leg_top - dz - 28.0
    for de in (-8.0, 8.0):
        b.beam((26.0, e + de, leg_top - dz), (34.0, e + de * 0.6, apex_d), 1.2, whitep, "crane")
        b.beam((46.0, e + de, leg_top - dz), (34.0, e + de * 0.6, apex_d), 1.2, whitep, "crane")
        b.beam((34.0, e + de * 0.6, apex_d), (n_tip + 2.0, e + de, leg_top - dz), 0.35, girder,
               "crane", ends=False)
    b.beam((34.0, e - 5.0, apex_d), (34.0, e + 5.0, apex_d), 1.2, girder, "crane")
    # trolley over the water, a container on the spreader
    tn = rng.uniform(-30.0, -5.0)
    b.box((tn, e, leg_top + 1.5), AXES_NED, (3.0, 7.0, 1.5), whitep, "crane", skip=())
    hang = leg_top + rng.uniform(12.0, 22.0)
    for de in (-3.0, 3.0):  # hoist ropes: thin two-sided strips facing the water
        b.face((tn, e + de - 0.05, leg_top + 3.0), (0, 1, 0), (0, 0, 1), 0.1,
               hang - 2.6 - leg_top - 3.0, _plain((40, 40, 40), rng, 20.0)(0.1, 10.0)[0],
               "crane", two_sided=True)
    col = CONTAINER_COLOURS[rng.integers(len(CONTAINER_COLOURS))]

    def box_c(side, w, h):
        return _paint_containers(rng, w, h, 12.2 if w > 6 else 2.44, 2.6, 10.0, "crane",
                                 colours=np.array([col], float))
    b.box((tn, e, hang - 1.3), AXES_NED, (1.22, 6.1, 1.3), box_c, "crane", skip=())


def _container_block(b: Builder, n0: float, e0: float, bays: int, rows: int, tiers: int,
                     ground: float) -> None:
    """Container stack block: containers along east (12.2 m), rows along north (2.44 m)."""
    rng = b.rng
    L, Wd, Ht = bays * 12.2, rows * 2.44, tiers * 2.6

    def paint(side, w, h):
        if side == "top":
            return _paint_containers(rng, w, h, 12.2, 2.44, 6.0, "container", top=True)
        if side in ("left", "right"):  # faces towards east/west: container ends
            return _paint_containers(rng, w, h, 2.44, 2.6, 10.0, "container")
        return _paint_containers(rng, w, h, 12.2, 2.6, 10.0, "container")
    b.box((n0 + Wd / 2, e0 + L / 2, ground - Ht / 2), AXES_NED, (Wd / 2, L / 2, Ht / 2), paint,
          "container")


def _build_terminal(b: Builder, sc: Scenario, port: Port) -> np.ndarray:
    rng = b.rng
    e0, e1 = sc.quay_east_range
    qh = port.quay_height_m
    ground = -qh
    below = 1.5
    L = e1 - e0
    img, pts = _paint_quay_wall(rng, L, qh + below, qh, 24.0, "terminal", e0,
                                port.quay_material, port.concrete)
    b.long_face((0.0, e0, -qh), (0, 1, 0), (0, 0, 1), L, qh + below, img, "quay", 25.0,
                points=pts)
    # apron: concrete slabs, crane rails, lane markings, hatch-cover bays
    apron_d = 60.0

    def apron(w, h, ppm=8.0):
        p = _Painter(w, h, ppm, (160, 165, 166), rng)
        p.grain(3.0, 0.07)
        for u in np.arange(0, w, 6.0):
            p.rect(u, 0, u + 0.05, h, (128, 132, 133))
        for v in np.arange(0, h, 6.0):
            p.rect(0, v, w, v + 0.05, (128, 132, 133))
        for rail_n in (3.0, 33.0):
            v = h - rail_n
            p.rect(0, v - 0.4, w, v + 0.4, (175, 178, 180))
            p.rect(0, v - 0.09, w, v + 0.09, (60, 62, 66))
        for lane_n in (8.0, 14.0, 20.0, 26.0, 40.0, 48.0):
            v = h - lane_n
            for u in np.arange(0.0, w, 9.0):
                p.rect(u, v - 0.1, u + 6.0, v + 0.1, (235, 235, 235))
        p.rect(0, h - 0.25, w, h, (40, 196, 232))
        for u in np.arange(5.0, w, 30.0):
            p.rect(u, h - 55.0, u + 12.0, h - 52.0, (40, 190, 225))
            p.corners(u, h - 55.0, u + 12.0, h - 52.0, "quay")
        return p.img, p.points
    img, pts = apron(L + 200.0, apron_d)
    b.long_face((apron_d, e0 - 100.0, ground), (0, 1, 0), (-1, 0, 0), L + 200.0, apron_d, img,
                "quay", 25.0, points=pts)

    def yard(w, h, ppm=3.0):
        p = _Painter(w, h, ppm, (105, 108, 110), rng)
        p.grain(5.0, 0.08)
        for u in np.arange(0, w, 12.6):
            p.rect(u, 0, u + 0.15, h, (200, 200, 200))
        return p.img
    b.long_face((220.0, e0 - 100.0, ground), (0, 1, 0), (-1, 0, 0), L + 200.0, 160.0,
                yard(L + 200.0, 160.0), "ground", 100.0)
    b.long_face((1800.0, e0 - 1500.0, ground), (0, 1, 0), (-1, 0, 0), L + 3000.0, 1580.0,
                _plain((110, 118, 115), rng, 0.2, 0.2, 50.0)(L + 3000.0, 1580.0)[0],
                "ground", 700.0)
    # bollards on the quay edge
    for e in np.arange(e0 + 10.0, e1, 20.0):
        _bollard(b, 0.9, e, ground, 0.6, (40, 42, 45), cap=False)
    # cranes
    spacing = rng.uniform(55.0, 80.0)
    for k in range(port.cranes):
        e = (k - 0.5 * (port.cranes - 1)) * spacing + rng.uniform(-8, 8)
        _crane(b, e, ground, 11 + k, port.crane_colours)
    # light masts between apron and yard
    for e in np.arange(e0 + 20.0, e1, 65.0):
        pole = _plain((175, 178, 180), rng, 12.0, 0.04)
        b.beam((62.0, e, ground), (62.0, e, ground - 32.0), 0.7, pole, "mast", ends=False)

        def lamp(side, w, h):
            p = _Painter(w, h, 12.0, (60, 60, 62), rng)
            if side in ("top", "bottom"):
                return p.img, []
            for u in np.arange(0.2, w - 0.5, 0.9):
                p.rect(u, 0.3, u + 0.6, h - 0.3, (215, 230, 235))
                p.corners(u, 0.3, u + 0.6, h - 0.3, "mast")
            return p.img, p.points
        # seen from below by a bridge camera: needs its bottom face
        b.box((62.0, e, ground - 33.0), AXES_NED, (0.6, 2.5, 1.0), lamp, "mast", skip=())
    # container stacks
    for n0 in (75.0, 100.0, 125.0, 150.0, 175.0):
        e = e0 - 40.0 + rng.uniform(0, 20)
        while e < e1 + 40.0:
            bays = int(rng.integers(3, 7))
            if rng.random() < port.stack_fill:
                _container_block(b, n0, e, bays, 6, int(rng.integers(1, port.stack_tiers + 1)),
                                 ground)
            e += bays * 12.2 + rng.uniform(4.0, 14.0)
    # buildings: terminal office, warehouses
    e = e0 - 60.0
    while e < e1 + 60.0:
        w = rng.uniform(30.0, 90.0)
        d = rng.uniform(20.0, 40.0)
        shed = rng.random() < 0.6
        ht = rng.uniform(10.0, 16.0) if shed else float(rng.choice(port.heights_m))
        n0 = rng.uniform(*port.setback_m)
        style = "shed" if shed else _facade_style(rng, port)
        rep = bool(rng.random() < port.repetitive)

        def facade(side, fw, fh, style=style, rep=rep):
            if side == "top":
                return _plain((150, 152, 150), rng, 2.0)(fw, fh)
            return _paint_facade(rng, fw, fh, 8.0, style=style, repetitive=rep)
        b.box((n0 + d / 2, e + w / 2, ground - ht / 2), AXES_NED, (d / 2, w / 2, ht / 2), facade,
              "building")
        e += w + rng.uniform(10.0, 40.0)
    for boat in port.boats:  # feeder ships moored at the ends of the berth, a tug
        _place_boat(b, boat)
    if port.town:
        _backdrop(b, 900.0, 5000.0, rng.uniform(40.0, 80.0), "city", (165, 165, 162), ground)
    if port.hills_m > 0.0:
        _backdrop(b, 6000.0, 30000.0, port.hills_m, "hills", (150, 152, 134), ground)
    return np.array([[0.0, e0], [0.0, e1]])


def _moored_ship(b: Builder, n_mid: float, e_mid: float, yaw: float, length: float,
                 beam: float, fb: float) -> None:
    """Container feeder (alongside): hull, accommodation at the stern, deck cargo."""
    rng = b.rng
    hull_col = [(80, 45, 25), (40, 40, 40), (60, 90, 30), (110, 60, 30)][rng.integers(4)]
    L, B = length, beam
    c = np.array([n_mid, e_mid, 0.0])
    axes = _axes_yaw(yaw)
    fwd, right = axes[:, 0], axes[:, 1]
    down = np.array([0.0, 0.0, 1.0])
    outline = [(-L / 2, -B / 2), (L / 2 - 14.0, -B / 2), (L / 2, 0.0), (L / 2 - 14.0, B / 2),
               (-L / 2, B / 2)]

    def hull(w, h, k=0):
        p = _Painter(w, h, 10.0, hull_col, rng)
        p.rect(0, h - 1.8, w, h, (40, 40, 150))  # boot-top
        p.rect(0, 0, w, 0.3, (220, 220, 220))
        if w > 60:
            p.text("PACIFIC FEEDER", 0.35 * w, 1.5, 1.8, (235, 235, 235))
        for u in (1.5, w - 3.0):  # draft marks
            for v in np.arange(h - 1.8, 2.5, -1.0):
                p.rect(u, v - 0.3, u + 0.5, v, (235, 235, 235))
                p.corners(u, v - 0.3, u + 0.5, v, "ship")
        p.grain(1.0, 0.05, 2)
        return p.img, p.points
    for k in range(len(outline)):
        a2, b2 = np.array(outline[k]), np.array(outline[(k + 1) % len(outline)])
        pa = c + a2[0] * fwd + a2[1] * right
        pb = c + b2[0] * fwd + b2[1] * right
        w = float(np.linalg.norm(pb - pa))
        normal = np.cross(_unit(pb - pa), np.array([0, 0, 1.0]))
        if normal @ (0.5 * (pa + pb) - c) < 0:
            normal = -normal
        h = fb + 1.0
        b.rect_face(0.5 * (pa + pb) + np.array([0, 0, -fb / 2 + 0.5]), normal, (0, 0, 1.0), w,
                    h, lambda w, h, k=k: hull(w, h, k), "ship")
    o = c + (L / 2) * fwd - (B / 2) * right + np.array([0, 0, -fb])
    poly = np.array([[(q[1] + B / 2), (L / 2 - q[0])] for q in outline])
    b.face(o, right, -fwd, B, L, _plain((70, 80, 90), rng, 2.0)(B, L)[0], "ship",
           polygon_uv=poly)

    def accom(side, w, h):
        p = _Painter(w, h, 10.0, (232, 232, 228), rng)
        if side != "top":
            for v in np.arange(1.0, h - 1.5, 2.8):
                for u in np.arange(0.8, w - 1.2, 2.0):
                    p.rect(u, v, u + 1.1, v + 1.0, (70, 60, 50))
                    p.corners(u, v, u + 1.1, v + 1.0, "ship")
            p.rect(0, 0, w, 0.6, (60, 60, 60))
        return p.img, p.points
    st = c - (L / 2 - 8.0) * fwd
    b.box(st + np.array([0, 0, -fb - 7.0]), np.column_stack([fwd, right, [0, 0, 1.0]]),
          (5.0, B / 2 - 1.0, 7.0), accom, "ship")
    b.box(st - 3.0 * fwd + np.array([0, 0, -fb - 17.0]),
          np.column_stack([fwd, right, [0, 0, 1.0]]), (1.8, 2.2, 3.0),
          _plain((40, 40, 160), rng, 10.0), "ship")
    # deck cargo in blocks between the accommodation and the bow
    axes = np.column_stack([fwd, right, down])
    for k in range(int((L - 30.0) / 14.0)):
        tiers = int(rng.integers(2, 5))

        def paint(side, w, h):
            if side == "top":
                return _paint_containers(rng, w, h, 12.2, 2.44, 6.0, "ship", top=True)
            if side in ("front", "back"):
                return _paint_containers(rng, w, h, 2.44, 2.6, 10.0, "ship")
            return _paint_containers(rng, w, h, 12.2, 2.6, 10.0, "ship")
        ctr = c + (-L / 2 + 15.0 + k * 14.0 + 6.1) * fwd + np.array([0, 0, -fb - tiers * 1.3])
        b.box(ctr, axes, (6.1, 7 * 2.44 / 2, tiers * 1.3), paint, "ship")


def _tug(b: Builder, n: float, e: float, yaw: float) -> None:
    """Harbour tug: a short beamy hull, black fendering, a tall wheelhouse."""
    rng = b.rng
    axes = _axes_yaw(yaw)
    fwd, right = axes[:, 0], axes[:, 1]
    c = np.array([n, e, 0.0])
    L, B, fb = 28.0, 9.0, 3.0
    outline = [(-L / 2, -B / 2), (L / 2 - 6.0, -B / 2), (L / 2, 0.0), (L / 2 - 6.0, B / 2),
               (-L / 2, B / 2)]
    colour = [(40, 45, 170), (30, 30, 30), (40, 120, 200)][rng.integers(3)]

    def hull(w, h, k):
        p = _Painter(w, h, 20.0, colour, rng)
        p.rect(0, 0, w, 0.9, (30, 30, 32))  # fendering
        p.rect(0, h - 1.0, w, h, (40, 40, 130))
        p.grain(0.5, 0.05, 2)
        return p.img, []
    _hull_sides(b, c, fwd, right, outline, -fb, 1.0, hull, "boat")
    _deck(b, c, fwd, right, outline, L, B, -fb, _plain((70, 90, 80), rng, 6.0)(B, L)[0],
          "boat")

    def house(side, w, h):
        p = _Painter(w, h, 20.0, (232, 232, 228), rng)
        if side != "top":
            p.rect(0.08 * w, 0.15 * h, 0.92 * w, 0.45 * h, (50, 45, 40))
        return p.img, []
    b.box(c + 2.0 * fwd + np.array([0, 0, -fb - 3.0]), np.column_stack([fwd, right, [0, 0, 1.0]]),
          (3.5, 3.2, 3.0), house, "boat")


def _own_large_ship(b: Builder, sc: Scenario) -> None:
    """The ship's own main deck, hatch covers, side plating and rail (body frame; seen in the
    lower corner of the picture when the bridge-wing camera looks down and forward)."""
    rng = b.rng
    mc = np.asarray(sc.motion_centre_body, float)
    outline = [tuple(q) for q in np.asarray(sc.hull_outline()) - mc]
    L, B = sc.hull_length_m, sc.hull_beam_m
    waterline = -sc.reference_point_down_m
    deck = waterline - sc.freeboard_m
    c = np.array([*mc, 0.0])
    fwd, right = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    hull_col = [(40, 40, 130), (50, 50, 50), (90, 60, 30)][rng.integers(3)]

    def plating(w, h, k):
        p = _Painter(w, h, 4.0, hull_col, rng)
        p.rect(0, 0, w, 1.2, (225, 225, 225))  # sheer strake / bulwark top
        for u in np.arange(6.0, w, 12.0):
            p.rect(u, 0.0, u + 0.25, h, np.asarray(hull_col) * 0.8)
        p.grain(2.0, 0.06, 2)
        return p.img, []
    _hull_sides(b, c, fwd, right, outline, deck - 1.2, waterline + 0.5, plating, "own-ship")

    def paint_deck(w, h):
        p = _Painter(w, h, 2.0, (60, 110, 70), rng)
        p.grain(3.0, 0.08, 2)
        return p.img
    _deck(b, c, fwd, right, outline, L, B, deck, paint_deck(B, L), "own-ship")
    hatch = _plain((40, 90, 150), rng, 4.0, 0.05)
    for x in np.arange(-0.5 * L + 50.0, 0.5 * L - 25.0, 16.0):
        b.box(c + np.array([x, 0.0, deck - 1.0]), np.eye(3), (6.5, 0.36 * B, 1.0),
              lambda side, w, h: hatch(w, h), "own-ship")
