"""Procedural textured port and the camera renderer of the simulator (SPEC section 8).

World = the scenario's local-level NED frame: the sea surface is the plane down = 0, the quay face
the vertical plane north = 0 over ``quay_east_range``, land at north > 0, quay top at
down = -quay_height_m. Camera frame: right, down, forward; ``x_cam = C_level_to_camera @ (x - p)``.

The port is a set of planar textured convex polygons ("faces"; boxes are made of faces). A frame
is rendered with numpy and OpenCV only:

1. the background on a half-resolution grid: sky (gradient and clouds on a plane 1.2 km up) and
   water (the plane down = 0 with three wave layers travelling at their deep-water phase speeds
   in different directions, Fresnel sky reflection and sun glints), both found per pixel from
   the ray direction;
2. every face not culled, near to far: its texture-to-image homography ``K [R U, R V, R O + t]``
   (valid even when part of the face is behind the camera), warped over the bounding box of its
   near-clipped polygon, written where it is nearer than the z-buffer. The z-buffer holds inverse
   depth, which is affine in image coordinates on a plane, so it costs one broadcast add per
   face, and faces entirely behind what is drawn are skipped before warping;
3. reflections of the structure in the water (screen space, mirrored about each column's
   waterline, broken up by the waves, weighted by the Fresnel term);
4. the ideal image (rendered with a margin) is distorted like a real lens with a precomputed
   remap, then exposure drift, vignetting and Gaussian noise are applied.

Textures carry ripmaps (separate x / y reduction) chosen by the projected texel footprint, which
avoids aliasing on oblique surfaces. Everything is 4-channel (BGRA) because OpenCV's warps and
remaps are markedly faster on 4 channels than on 3.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from estimator.records import CameraCalibration

from .scenarios import Scenario

NEAR_M = 0.15  # near clipping plane (camera z), m
HALF = 2  # background is computed at 1/HALF resolution

# Sun: south-south-west, 40 deg up (unit vector towards the sun, NED).
_SUN_AZ, _SUN_EL = np.radians(215.0), np.radians(40.0)
SUN_DIR = np.array([np.cos(_SUN_EL) * np.cos(_SUN_AZ), np.cos(_SUN_EL) * np.sin(_SUN_AZ),
                    -np.sin(_SUN_EL)])

SKY_ZENITH = np.array([196.0, 140.0, 88.0])  # BGR
SKY_HORIZON = np.array([226.0, 214.0, 200.0])
HAZE = np.array([205.0, 198.0, 188.0])


# ============================================================================= camera model

def camera_calibration(scenario: Scenario) -> CameraCalibration:
    """Pinhole + OpenCV distortion camera of a scenario (square pixels, centred principal point)."""
    w, h = scenario.camera_size
    f = 0.5 * w / np.tan(np.radians(scenario.camera_hfov_deg) / 2.0)
    K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    return CameraCalibration(
        width=w, height=h, K=K, distortion=np.array(scenario.camera_distortion, dtype=float),
        C_camera_to_body=scenario.C_camera_to_body,
        lever_arm_body=np.array(scenario.camera_lever_arm, dtype=float),
    )


def project_points(points_ned: np.ndarray, C_level_to_camera: np.ndarray,
                   camera_position_ned: np.ndarray,
                   camera: CameraCalibration) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixel coordinates (N,2) and camera depth z (N,) of NED points.

    Points at or behind the camera (depth <= 0) get NaN pixel coordinates."""
    pts = np.atleast_2d(np.asarray(points_ned, dtype=float))
    R = np.asarray(C_level_to_camera, dtype=float)
    tvec = -R @ np.asarray(camera_position_ned, dtype=float)
    depth = pts @ R[2] + tvec[2]
    uv = np.full((len(pts), 2), np.nan)
    front = depth > 1e-6
    if np.any(front):
        rvec, _ = cv2.Rodrigues(R)
        proj, _ = cv2.projectPoints(pts[front].reshape(-1, 1, 3), rvec, tvec, camera.K,
                                    camera.distortion)
        uv[front] = proj.reshape(-1, 2)
    return uv, depth


@dataclass
class _CameraModel:
    """Per-camera precomputations: ideal render size/intrinsics, distortion maps, vignette."""

    K: np.ndarray  # intrinsics of the ideal (undistorted) render, same focal length
    size: tuple[int, int]  # (width, height) of the ideal render
    map1: np.ndarray  # distorted pixel -> ideal render pixel (fixed point maps)
    map2: np.ndarray
    vignette: np.ndarray  # (h, w, 3) uint8, 255 = no fall-off
    noise: np.ndarray  # (h + 64, w + 64, 3) int16 noise bank
    xs: np.ndarray  # ideal-render pixel columns (float32)
    ys: np.ndarray

    @classmethod
    def build(cls, camera: CameraCalibration, seed: int) -> _CameraModel:
        w, h = camera.width, camera.height
        K, dist = np.asarray(camera.K, float), np.asarray(camera.distortion, float)
        # Where every distorted pixel comes from in the ideal (pinhole) image.
        gx, gy = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        pix = np.stack([gx.ravel(), gy.ravel()], axis=1).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
        norm = cv2.undistortPoints(pix, K, dist, R=None, P=None, criteria=crit).reshape(h, w, 2)
        lo = norm.reshape(-1, 2).min(axis=0)
        hi = norm.reshape(-1, 2).max(axis=0)
        fx, fy = K[0, 0], K[1, 1]
        pad = 3.0  # pixels, so bilinear reads never fall off the ideal image
        cx, cy = -lo[0] * fx + pad, -lo[1] * fy + pad
        wr = int(np.ceil((hi[0] - lo[0]) * fx + 2 * pad)) + 1
        hr = int(np.ceil((hi[1] - lo[1]) * fy + 2 * pad)) + 1
        wr += (-wr) % (2 * HALF)  # the sky is computed at quarter resolution
        hr += (-hr) % (2 * HALF)
        Kr = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        mx = (norm[..., 0] * fx + cx).astype(np.float32)
        my = (norm[..., 1] * fy + cy).astype(np.float32)
        map1, map2 = cv2.convertMaps(mx, my, cv2.CV_16SC2)
        # Natural vignetting ~cos^4 of the field angle, softened (the lens is not that bad).
        r2 = norm[..., 0] ** 2 + norm[..., 1] ** 2
        vig = 0.35 + 0.65 / (1.0 + r2) ** 2
        vig = np.clip(vig / vig.max() * 255.0, 0, 255).astype(np.uint8)
        rng = np.random.default_rng(seed + 7919)
        noise = np.rint(rng.standard_normal((h + 64, w + 64, 3)) * 2.2).astype(np.int16)
        return cls(K=Kr, size=(wr, hr), map1=map1, map2=map2,
                   vignette=np.repeat(vig[..., None], 3, axis=2), noise=noise,
                   xs=np.arange(wr, dtype=np.float32), ys=np.arange(hr, dtype=np.float32))


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

class _Texture:
    """BGRA texture with lazily computed ripmap levels (x and y halved independently)."""

    def __init__(self, image: np.ndarray):
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
class _Face:
    origin: np.ndarray  # world position of texture coordinate (0, 0)
    u_axis: np.ndarray  # unit vector of texture columns (right as seen from the front)
    v_axis: np.ndarray  # unit vector of texture rows (down as seen from the front)
    size: tuple[float, float]  # (w, h) metres covered by the texture
    texture: _Texture
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


class _Builder:
    """Collects faces and scene points; bakes sun shading and aerial haze into textures."""

    def __init__(self, rng: np.random.Generator, viewpoint: np.ndarray, haze_m: float):
        self.rng = rng
        self.viewpoint = viewpoint
        self.haze_m = haze_m
        self.faces: list[_Face] = []
        self.points: list[np.ndarray] = []
        self.normals: list[np.ndarray] = []
        self.kinds: list[str] = []

    def _bake(self, img: np.ndarray, normal: np.ndarray, centre: np.ndarray,
              lit: bool = True) -> np.ndarray:
        """Lambert shading from the sun plus sky ambient, and distance haze, into a texture
        (the far backdrop, ``lit=False``, is painted in its hazy colours already)."""
        if not lit:
            return img
        up = max(0.0, -normal[2])
        shade = 0.58 + 0.42 * max(0.0, float(normal @ SUN_DIR)) + 0.08 * up
        d = float(np.linalg.norm(centre - self.viewpoint))
        fog = 1.0 - np.exp(-d / self.haze_m)
        out = img.astype(np.float32)
        out[..., :3] = out[..., :3] * (shade * (1 - fog)) + HAZE * fog
        return _to_u8(out)

    def face(self, origin, u_axis, v_axis, w: float, h: float, img: np.ndarray, kind: str,
             polygon_uv=None, two_sided=False, points=(), lit=True) -> _Face:
        """Add a face from an (unshaded) texture image covering [0, w] x [0, h] metres."""
        origin, u_axis, v_axis = np.asarray(origin, float), _unit(u_axis), _unit(v_axis)
        if polygon_uv is None:
            polygon_uv = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=float)
        normal = np.cross(v_axis, u_axis)
        centre = origin + u_axis * w / 2 + v_axis * h / 2
        alpha = img.shape[2] == 4
        tex = _Texture(self._bake(img, normal, centre, lit))
        f = _Face(origin, u_axis, v_axis, (w, h), tex, kind, np.asarray(polygon_uv, float),
                  two_sided, alpha)
        self.faces.append(f)
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
            poly = np.array([[a - ua, 0], [b - ua, 0], [b - ua, h], [a - ua, h]])
            self.face(np.asarray(origin, float) + u_axis * ua, u_axis, v_axis, ub - ua, h, sub,
                      kind, polygon_uv=poly, lit=lit, two_sided=two_sided)
        v_axis = _unit(v_axis)
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

def _paint_quay_wall(rng: np.random.Generator, length: float, height: float, waterline: float,
                     ppm: float, style: str, east0: float) -> tuple[np.ndarray, list]:
    """Quay face: concrete blocks/panels, coping with a yellow edge, wet zone and algae,
    fenders, ladders, painted numbers. ``waterline`` = v of the sea surface."""
    p = _Painter(length, height, ppm, (150, 156, 158), rng)
    coping = 0.3 if style == "marina" else 0.5
    # blocks (marina) or cast panels (terminal)
    if style == "marina":
        bh, bl, joint = 0.45, 1.25, 0.025
        row, v = 0, coping
        while v < height:
            off = (row % 2) * bl / 2 + rng.uniform(-0.1, 0.1)
            u = -off
            while u < length:
                ln = bl * rng.uniform(0.85, 1.15)
                s = rng.uniform(0.82, 1.12)
                p.rect(u + joint / 2, v + joint / 2, u + ln - joint / 2, v + bh - joint / 2,
                       np.array([150, 156, 158]) * s)
                p.rect(u - joint / 2, v, u + joint / 2, v + bh, (92, 96, 98))
                u += ln
            p.rect(0, v - joint / 2, length, v + joint / 2, (92, 96, 98))
            v += bh
            row += 1
    else:
        for u in np.arange(0.0, length, 10.0):
            s = rng.uniform(0.9, 1.08)
            p.rect(u, coping, u + 10.0, height, np.array([150, 156, 158]) * s)
            p.rect(u - 0.02, coping, u + 0.02, height, (95, 99, 101))
        p.rect(0, coping + 0.5 * (waterline - coping) - 0.02, length,
               coping + 0.5 * (waterline - coping) + 0.02, (105, 110, 112))
    # coping beam and its painted yellow edge
    p.rect(0, 0, length, coping, (168, 172, 172))
    p.rect(0, coping - 0.025, length, coping + 0.005, (100, 104, 105))
    p.rect(0, 0, length, 0.12 if style == "marina" else 0.2, (40, 196, 232))
    p.grain(0.6, 0.07)
    p.streaks(int(length * 1.2), 0.9 * waterline, 0.35)
    p.streaks(int(length * 0.15), 0.6 * waterline, 0.45, color=(40, 70, 120))  # rust
    # wet zone with algae and barnacles above the waterline
    f = p.img.astype(np.float32)
    vv = (np.arange(p.H, dtype=np.float32) + 0.5) / ppm
    tide = waterline - (0.35 if style == "marina" else 0.8)
    wobble = _fbm(rng, 1, p.W, 2.0 * ppm, 3)[0] * 0.06
    vmat = vv[:, None] - wobble[None, :]
    wet = np.clip((vmat - tide) / 0.08, 0, 1)[..., None]
    algae = np.clip((vmat - (waterline - 0.25)) / 0.1, 0, 1)[..., None]
    f = f * (1 - 0.45 * wet)
    f = f * (1 - 0.5 * algae) + np.array([40, 85, 60], np.float32) * 0.5 * algae
    p.img = _to_u8(f)
    specks = rng.random((p.H, p.W)) < 0.02 * wet[..., 0]
    p.img[specks] = (p.img[specks] * 1.5).clip(0, 255).astype(np.uint8)

    spacing_fender = 4.0 if style == "marina" else 16.0
    spacing_ladder = 20.0 if style == "marina" else 50.0
    ladders = np.arange(spacing_ladder * 0.55, length, spacing_ladder)
    # fenders
    for u in np.arange(spacing_fender * 0.5, length, spacing_fender):
        if np.min(np.abs(ladders - u)) < 1.5:
            continue
        if style == "marina":
            if int(u / spacing_fender) % 3 == 0:
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
        half = 0.25 if style == "marina" else 0.3
        rail = 0.06 if style == "marina" else 0.12
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
    spacing_no = 15.0 if style == "marina" else 25.0
    for i, u in enumerate(np.arange(spacing_no * 0.3, length, spacing_no)):
        if np.min(np.abs(ladders - u)) < 2.5:
            u += 3.0
        num = f"{int((east0 + u) // spacing_no) + 20:02d}"
        if style == "marina":
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


def _paint_facade(rng: np.random.Generator, w: float, h: float, ppm: float,
                  storey: float = 3.2, style: str = "flats") -> tuple[np.ndarray, list]:
    """Building facade: wall colour, rows of windows, ground floor shop fronts and signs."""
    palettes = [(205, 215, 222), (175, 195, 210), (150, 160, 170), (95, 110, 160),
                (200, 200, 195), (185, 200, 205), (120, 135, 150)]
    wall = np.array(palettes[rng.integers(len(palettes))], float)
    p = _Painter(w, h, ppm, wall, rng)
    p.grain(2.0, 0.05)
    if style == "shed":
        # corrugated cladding with a roller door and a few windows high up
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
    glass = np.array([95, 80, 60], float) * rng.uniform(0.8, 1.2)
    frame = np.array([215, 218, 220], float)
    n_floors = max(1, int((h - 0.8) / storey))
    ground = storey + 0.8
    win_w, win_h = rng.uniform(1.1, 1.8), rng.uniform(1.2, 1.7)
    pitch = win_w + rng.uniform(0.9, 2.0)
    n_cols = max(1, int((w - 1.0) / pitch))
    margin = (w - n_cols * pitch) / 2 + (pitch - win_w) / 2
    bands = style == "office"
    for fl in range(1, n_floors):
        v_top = h - ground - fl * storey + (storey - win_h) * 0.6
        if v_top < 0.5:
            break
        if bands:
            p.rect(0, v_top - 0.1, w, v_top + win_h + 0.1, glass * 0.9)
        for c in range(n_cols):
            u = margin + c * pitch
            g = glass * rng.uniform(0.75, 1.25)
            if rng.random() < 0.12:
                g = np.array([150, 170, 185])  # blinds down
            p.rect(u - 0.06, v_top - 0.06, u + win_w + 0.06, v_top + win_h + 0.06, frame)
            p.rect(u, v_top, u + win_w, v_top + win_h, g)
            p.rect(u, v_top + win_h * 0.45, u + win_w, v_top + win_h * 0.48, frame * 0.9)
            p.corners(u, v_top, u + win_w, v_top + win_h, "building")
            if style == "flats" and rng.random() < 0.5:
                # balcony rail
                p.rect(u - 0.3, v_top + win_h + 0.05, u + win_w + 0.3,
                       v_top + win_h + 0.12, wall * 0.6)
    # ground floor: shop windows, doors, a sign board
    v0 = h - ground
    u = rng.uniform(0.5, 2.0)
    while u < w - 2.0:
        sw = rng.uniform(2.0, 4.5)
        if u + sw > w - 0.5:
            break
        p.rect(u, v0 + 1.2, u + sw, h - 0.15, glass * 0.7)
        p.corners(u, v0 + 1.2, u + sw, h - 0.15, "building")
        u += sw + rng.uniform(0.8, 2.5)
    if w > 8:
        colours = [(40, 40, 190), (170, 90, 20), (30, 150, 30), (30, 160, 220), (230, 230, 230)]
        sc = np.array(colours[rng.integers(len(colours))])
        su = rng.uniform(0.5, w - 6.0)
        p.rect(su, v0 + 0.2, su + 5.0, v0 + 0.95, sc)
        p.text("MARINE" if rng.random() < 0.5 else "CAFE", su + 0.3, v0 + 0.33, 0.45,
               (255, 255, 255) if sc.sum() < 500 else (20, 20, 20))
        p.corners(su, v0 + 0.2, su + 5.0, v0 + 0.95, "building")
    p.rect(0, 0, w, 0.45, wall * 0.75)  # parapet
    for u in rng.uniform(0.5, w - 0.5, size=max(1, int(w / 15))):
        p.rect(u, 0.45, u + 0.12, h, wall * 0.8)  # down pipes
    p.streaks(int(w), h * 0.6, 0.12)
    return p.img, p.points


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


# =================================================================================== scene

@dataclass
class PortScene:
    """The static textured port of a scenario, plus the time-varying water and sky."""

    scenario: Scenario
    seed: int
    faces: list[_Face]
    points: np.ndarray  # (N, 3) well-textured scene points (true NED)
    point_kinds: list[str]
    point_normals: np.ndarray  # (N, 3) outward normal of the surface each point lies on
    outline_ne: np.ndarray  # (M, 2) quay face edge
    water_layers: list[tuple[np.ndarray, float, float, float, np.ndarray, float]]
    clouds: np.ndarray  # tileable cloud cover texture (uint8)
    exposure_phase: tuple[float, float]
    vignetting: bool = True  # lens fall-off towards the corners
    _cameras: dict = field(default_factory=dict, repr=False)
    _arrays: dict = field(default_factory=dict, repr=False)

    # ------------------------------------------------------------------------- building
    @classmethod
    def build(cls, scenario: Scenario, seed: int) -> PortScene:
        """Procedural port for a scenario; deterministic for a seed."""
        rng = np.random.default_rng(seed)
        kf = np.array(scenario.path_keyframes)
        viewpoint = np.array([kf[:, 1].mean(), kf[:, 2].mean(), -5.0])
        if scenario.scene_kind == "marina":
            b = _Builder(rng, viewpoint, haze_m=4500.0)
            outline = _build_marina(b, scenario)
        elif scenario.scene_kind == "container-terminal":
            b = _Builder(rng, viewpoint, haze_m=3500.0)
            outline = _build_terminal(b, scenario)
        else:
            raise ValueError(f"unknown scene kind {scenario.scene_kind!r}")
        layers = []
        # (texture, metres per texel, drift speed m/s, drift direction, rotation, amplitude)
        for wavelength, heading, amp in ((7.0, 200.0, 1.0), (1.6, 115.0, 0.75),
                                         (0.4, 330.0, 0.6)):
            # deep-water phase speed: the patterns on real water change that fast, so water
            # features do not move with the port (nor with each other)
            speed = np.sqrt(9.81 * wavelength / (2 * np.pi))
            n = 256
            # waves travel along texture x; the layer is rotated to its drift direction
            direction = np.radians(heading + rng.uniform(-15, 15))
            tex = _periodic_noise(rng, n, k_peak=n / 10.0, k_width=n / 14.0, direction=0.0,
                                  sharpness=1)
            tex = np.clip(128 + 42 * tex, 0, 255).astype(np.uint8)
            vel = speed * np.array([np.cos(direction), np.sin(direction)])
            layers.append((tex, wavelength / 10.0, direction, amp, vel, wavelength))
        clouds = _periodic_noise(rng, 512, 5.0, 4.0) + 0.5 * _periodic_noise(rng, 512, 14, 8)
        clouds = np.clip(128 + 55 * clouds, 0, 255).astype(np.uint8)
        return cls(scenario=scenario, seed=seed, faces=b.faces, points=np.array(b.points),
                   point_kinds=list(b.kinds), point_normals=np.array(b.normals),
                   outline_ne=outline, water_layers=layers,
                   clouds=clouds, exposure_phase=tuple(rng.uniform(0, 2 * np.pi, 2)))

    # --------------------------------------------------------------------------- access
    def scene_points(self) -> tuple[np.ndarray, list[str]]:
        """(N, 3) true NED positions of strong image corners on the structure and their kind."""
        return self.points.copy(), list(self.point_kinds)

    def quay_outline_ne(self) -> np.ndarray:
        """(M, 2) north, east polyline of the quay face edge."""
        return self.outline_ne.copy()

    # -------------------------------------------------------------------------- helpers
    def _camera_model(self, camera: CameraCalibration) -> _CameraModel:
        key = (camera.width, camera.height, np.asarray(camera.K, float).tobytes(),
               np.asarray(camera.distortion, float).tobytes())
        model = self._cameras.get(key)
        if model is None:
            model = _CameraModel.build(camera, self.seed)
            self._cameras[key] = model
        return model

    def _face_arrays(self) -> dict:
        """Stacked face geometry for vectorised culling."""
        if not self._arrays:
            F = len(self.faces)
            verts = np.zeros((F, 6, 3))
            nv = np.zeros(F, int)
            for i, f in enumerate(self.faces):
                w = f.world(f.polygon_uv)
                nv[i] = len(w)
                verts[i, :len(w)] = w
                verts[i, len(w):] = w[-1]
            base = [f.texture.levels[(0, 0)].shape for f in self.faces]
            self._arrays.update(
                verts=verts, nv=nv,
                normal=np.array([f.normal for f in self.faces]),
                origin=np.array([f.origin for f in self.faces]),
                u_axis=np.array([f.u_axis for f in self.faces]),
                v_axis=np.array([f.v_axis for f in self.faces]),
                ppm=np.array([[sh[1] / f.size[0], sh[0] / f.size[1]]
                              for sh, f in zip(base, self.faces, strict=True)]),
                max_level=np.array([[f.texture.max_lx, f.texture.max_ly] for f in self.faces]),
                two_sided=np.array([f.two_sided for f in self.faces]))
        return self._arrays

    def exposure_gain(self, t: float) -> float:
        """Slow auto-exposure drift (a few %)."""
        a, b = self.exposure_phase
        return float(1.0 + 0.045 * np.sin(2 * np.pi * t / 37.0 + a)
                     + 0.02 * np.sin(2 * np.pi * t / 9.3 + b))

    # --------------------------------------------------------------------------- render
    def render(self, C_level_to_camera: np.ndarray, camera_position_ned: np.ndarray, t: float,
               camera: CameraCalibration, rng: np.random.Generator,
               return_depth: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Camera frame (height, width, 3) BGR uint8, distorted like the real lens.

        With ``return_depth`` also the camera depth z (float32, inf for sky) per pixel."""
        cam = self._camera_model(camera)
        R = np.asarray(C_level_to_camera, float)
        p = np.asarray(camera_position_ned, float)
        img, zbuf, water_info = self._background(cam, R, p, t)
        zwater = zbuf.copy()
        self._draw_faces(cam, R, p, img, zbuf)
        if water_info is not None:
            self._reflect(cam, img, zbuf, zwater, water_info)
        out = cv2.remap(img, cam.map1, cam.map2, cv2.INTER_LINEAR)
        out = cv2.cvtColor(out, cv2.COLOR_BGRA2BGR)
        if self.vignetting:
            out = cv2.multiply(out, cam.vignette, scale=self.exposure_gain(t) / 255.0)
        else:
            out = cv2.convertScaleAbs(out, alpha=self.exposure_gain(t))
        h, w = camera.height, camera.width
        oy, ox = rng.integers(0, 64, size=2)
        noise = cam.noise[oy:oy + h, ox:ox + w]
        out = cv2.add(out, np.ascontiguousarray(noise), dtype=cv2.CV_8U)
        if not return_depth:
            return out
        inv = cv2.remap(zbuf, cam.map1, cam.map2, cv2.INTER_NEAREST)
        with np.errstate(divide="ignore"):
            depth = np.where(inv > 0, 1.0 / inv, np.inf).astype(np.float32)
        return out, depth

    def _background(self, cam: _CameraModel, R: np.ndarray, p: np.ndarray,
                    t: float) -> tuple[np.ndarray, np.ndarray]:
        """Sky and water (BGRA, full ideal-render size) and the water's inverse depth.

        Works on per-channel planes: numpy broadcasting to 3 channels is many times slower."""
        W, H = cam.size
        Wh, Hh = W // HALF, H // HALF
        fx, fy, cx, cy = (float(v) for v in (cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]))
        h_cam = float(max(-p[2], 0.05))
        # ray down component (camera z = 1) is affine: which half-res rows see water / sky
        yn = ((np.arange(Hh) * HALF + (HALF - 1) / 2) - cy) / fy
        xe = (np.array([0, Wh - 1]) * HALF + (HALF - 1) / 2 - cx) / fx
        rd_ends = R[0, 2] * xe[None, :] + (R[1, 2] * yn + R[2, 2])[:, None]
        water_rows = np.nonzero(rd_ends.max(axis=1) > 1e-5)[0]
        sky_rows = np.nonzero(rd_ends.min(axis=1) <= 1e-5)[0]
        planes = [np.empty((Hh, Wh), np.float32) for _ in range(3)]
        r_sky = int(sky_rows[-1]) + 1 if len(sky_rows) else 0
        r_water = int(water_rows[0]) if len(water_rows) else Hh
        water_info = None
        if r_sky:
            sky = self._sky(cam, R, p, t, r_sky)
            for k in range(3):
                planes[k][:r_sky] = sky[k]
        if r_water < Hh:
            water, is_water, fres, shade = self._water(cam, R, p, t, r_water, h_cam)
            water_info = (r_water, fres, shade)
            for k in range(3):
                if r_sky > r_water:  # rows crossed by the horizon
                    water[k] = np.where(is_water, water[k], planes[k][r_water:])
                planes[k][r_water:] = water[k]
        # alpha 0: faces write their (opaque) alpha, so alpha marks structure for reflections
        alpha = np.zeros((Hh, Wh), np.uint8)
        half = cv2.merge([cv2.convertScaleAbs(q) for q in planes] + [alpha])
        img = cv2.resize(half, (W, H), interpolation=cv2.INTER_LINEAR)
        # water inverse depth at full resolution: 1/z = ray_down / h
        xs = (cam.xs - cx) / fx
        ys = (cam.ys - cy) / fy
        inv = (float(R[0, 2] / h_cam) * xs)[None, :] + \
            ((float(R[1, 2]) * ys + float(R[2, 2])) / h_cam)[:, None]
        zbuf = np.maximum(inv, np.float32(0.0))
        return img, zbuf, water_info

    def _reflect(self, cam: _CameraModel, img: np.ndarray, zbuf: np.ndarray,
                 zwater: np.ndarray, water_info) -> None:
        """Reflections of the structure in the water, screen space at half resolution.

        In each image column the lowest structure stands on the water; mirroring the picture
        about that waterline is exact for vertical structure seen by a level camera, and good
        enough for the rest once the waves have broken it up. Weighted by the Fresnel term."""
        r0, fres, shade = water_info
        W, H = cam.size
        Wh, Hh = W // HALF, H // HALF
        water_full = cv2.compare(zbuf, zwater, cv2.CMP_EQ)
        water_full[zwater <= 0] = 0
        # half-res pixel = water if any of its full-res pixels is, so that the row above the
        # waterline is pure structure in the (area-averaged) half-res picture
        water = cv2.resize(water_full, (Wh, Hh), interpolation=cv2.INTER_AREA) > 0
        # first water row below the lowest non-water pixel of each column
        last = Hh - 1 - np.argmax(~water[::-1], axis=0)
        y_w = np.where(water.all(axis=0), 0, last + 1)
        y_lo = max(int(y_w.min()), r0)
        if y_lo >= Hh - 1:
            return
        rows = np.arange(y_lo, Hh, dtype=np.float32)
        sh = shade[y_lo - r0:]
        fr = fres[y_lo - r0:]
        # mirror rows, displaced by the wave slopes (a broken, shimmering reflection)
        # (the reflection meets its object at the waterline: no displacement there)
        yw = y_w.astype(np.float32)[None, :]
        below = rows[:, None] - yw
        wobble = np.clip(below * np.float32(1 / 6.0), 0.0, 3.0) * sh
        map_y = np.minimum(2.0 * yw - 1.0 - rows[:, None] + wobble, yw - 1.0)
        map_x = np.arange(Wh, dtype=np.float32)[None, :] + 0.4 * np.roll(wobble, 7, axis=1)
        small = cv2.resize(img, (Wh, Hh), interpolation=cv2.INTER_AREA)
        refl = cv2.remap(small, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0)
        b, g, r, a = cv2.split(refl)
        # the mirrored structure takes the place of the sky in the Fresnel mix
        wgt = fr * (a.astype(np.float32) * np.float32(1 / 255.0))
        # water above the lowest structure of a column does not see it mirrored; one half-res
        # row of slack for the upsampling to full resolution
        wgt[below < -1.0] = 0.0
        skyc = ((0.65 * SKY_HORIZON + 0.35 * SKY_ZENITH) * 0.9).tolist()
        delta = [(c.astype(np.float32) - np.float32(skyc[k])) * wgt
                 for k, c in enumerate((b, g, r))]
        delta.append(np.zeros_like(wgt))
        y0 = y_lo * HALF
        full = cv2.resize(cv2.merge(delta), (W, H - y0), interpolation=cv2.INTER_LINEAR)
        sub = img[y0:]
        out = cv2.add(sub, full.astype(np.int16), dtype=cv2.CV_8U)
        cv2.copyTo(out, water_full[y0:], sub)

    @staticmethod
    def _rays(cam: _CameraModel, R: np.ndarray, step: int, rows: int, row0: int = 0):
        """NED ray components (camera z = 1) on a grid of ``step``-pixel cells."""
        W = cam.size[0] // step
        # python floats: numpy float64 scalars would promote the float32 grids to float64
        fx, fy, cx, cy = (float(v) for v in (cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]))
        xn = ((np.arange(W, dtype=np.float32) * step + (step - 1) / 2) - cx) / fx
        yn = ((np.arange(row0, row0 + rows, dtype=np.float32) * step + (step - 1) / 2) - cy) / fy
        return [(np.float32(R[0, i]) * xn)[None, :] + (np.float32(R[1, i]) * yn
                                                      + np.float32(R[2, i]))[:, None]
                for i in range(3)]

    @staticmethod
    def _plane_homography(cam: _CameraModel, R: np.ndarray, p: np.ndarray, down: float,
                          step: int, row0: int) -> np.ndarray:
        """Homography from grid cells (``step`` pixels, rows from row0) to (north, east) on the
        horizontal plane at ``down``."""
        O = np.array([0.0, 0.0, down])
        H_plane = cam.K @ np.column_stack([R[:, 0], R[:, 1], R @ (O - p)])
        S = np.array([[step, 0, (step - 1) / 2], [0, step, (step - 1) / 2 + step * row0],
                      [0, 0, 1.0]])
        return np.linalg.inv(H_plane) @ S

    def _water(self, cam: _CameraModel, R: np.ndarray, p: np.ndarray, t: float, row0: int,
               h_cam: float) -> tuple[list[np.ndarray], np.ndarray]:
        """Water colour planes (B, G, R) on the half-res rows from row0, and the water mask."""
        Hh = cam.size[1] // HALF
        rn, re, rd = self._rays(cam, R, HALF, Hh - row0, row0)
        is_water = rd > 1e-5
        rd = np.maximum(rd, np.float32(1e-5))
        norm = cv2.sqrt(rn * rn + re * re + rd * rd)
        q = norm / rd  # slant range / camera height
        footprint = q * q * np.float32(h_cam / cam.K[0, 0])  # along-range size of a pixel, m
        fp_row = footprint.min(axis=1)
        shade = np.zeros_like(rd)
        fine = np.zeros_like(rd)  # short waves only, for glints
        G = self._plane_homography(cam, R, p, 0.0, HALF, row0)
        for k, (tex, texel, rot, amp, vel, wavelength) in enumerate(self.water_layers):
            # fade a layer out where a pixel covers more than a fraction of its wavelength;
            # rows where it is faded everywhere are skipped
            live = np.nonzero(fp_row < wavelength / 2.5)[0]
            if len(live) == 0:
                continue
            r = int(live[0])
            c, s = np.cos(rot), np.sin(rot)
            off = vel * t
            A = np.array([[c / texel, s / texel, -(c * off[0] + s * off[1]) / texel],
                          [-s / texel, c / texel, (s * off[0] - c * off[1]) / texel],
                          [0, 0, 1.0]])
            T = np.array([[1.0, 0, 0], [0, 1.0, r], [0, 0, 1.0]])
            lay = cv2.warpPerspective(tex, A @ G @ T, (rn.shape[1], rn.shape[0] - r),
                                      flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                      borderMode=cv2.BORDER_WRAP)
            wgt = np.clip((wavelength / 2.5 - footprint[r:]) * np.float32(5.0 / wavelength),
                          0.0, 1.0)
            contrib = (lay.astype(np.float32) - 128.0) * wgt
            shade[r:] += contrib * np.float32(amp / 42.0)
            if k == len(self.water_layers) - 1:
                fine[r:] += contrib * np.float32(1.0 / 42.0)
        x = 1.0 - rd / norm  # 1 - sine of the grazing angle
        x2 = x * x
        fres = 0.02 + 0.98 * x2 * x2 * x
        # wave slopes tilt the reflected ray: more sky or more depth, less so looking down
        mix = np.clip(fres + (0.08 + 0.2 * fres) * shade, 0.0, 1.0)
        # sun glints: small crests of the short waves, strongest near the sun's mirror image
        sx, sy, sz = SUN_DIR.tolist()
        cos_sun = (rn * sx + re * sy - rd * sz) / norm
        glare = 0.3 + 0.7 * cv2.exp((cos_sun - 1.0) * np.float32(1 / 0.08))
        glint = np.clip((fine - 2.2) * 2.5, 0.0, 1.0) * glare * 150.0
        deep = (70.0, 68.0, 38.0)
        skyc = ((0.65 * SKY_HORIZON + 0.35 * SKY_ZENITH) * 0.9).tolist()
        colour = [deep[k] + (skyc[k] - deep[k]) * mix + glint for k in range(3)]
        return colour, is_water, fres, shade

    def _sky(self, cam: _CameraModel, R: np.ndarray, p: np.ndarray, t: float,
             rows_half: int) -> list[np.ndarray]:
        """Sky colour planes on the first ``rows_half`` half-res rows (computed at quarter
        resolution: the sky is smooth)."""
        step = 2 * HALF
        Wq, Hq = cam.size[0] // step, cam.size[1] // step
        nq = min(Hq, rows_half // 2 + 2)
        rn, re, rd = self._rays(cam, R, step, nq)
        norm = cv2.sqrt(rn * rn + re * re + rd * rd)
        sin_el = -rd / norm
        g = cv2.sqrt(np.clip(sin_el * np.float32(1 / 0.6), 0.0, 1.0))
        # clouds on a plane 1.2 km up drifting slowly, fading out towards the horizon
        alt, texel = 1200.0, 22.0
        G = self._plane_homography(cam, R, p, p[2] - alt, step, 0)
        off = np.array([2.0, 3.5]) * t
        A = np.array([[1 / texel, 0, -off[0] / texel], [0, 1 / texel, -off[1] / texel],
                      [0, 0, 1.0]])
        cl = cv2.warpPerspective(self.clouds, A @ G, (Wq, nq),
                                 flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_WRAP).astype(np.float32)
        fade = np.clip(sin_el * np.float32(7.0) - 0.42, 0.0, 1.0)  # ~6 to 20 km away
        cover = np.clip((cl - 145.0) * np.float32(1 / 60.0), 0.0, 1.0)
        cover = cover * cv2.sqrt(cover) * fade
        cloud = 242.0 * (1.0 - 0.12 * np.clip((cl - 175.0) * np.float32(1 / 80.0), 0.0, 1.0))
        out = []
        for hor, zen in zip(SKY_HORIZON.tolist(), SKY_ZENITH.tolist(), strict=True):
            col = hor + (zen - hor) * g
            col = col + (cloud - col) * cover
            col = cv2.resize(col, (Wq * 2, nq * 2), interpolation=cv2.INTER_LINEAR)
            out.append(col[:rows_half])
        return out

    def _draw_faces(self, cam: _CameraModel, R: np.ndarray, p: np.ndarray, img: np.ndarray,
                    zbuf: np.ndarray) -> None:
        """Cull, then draw faces near to far so hidden ones are rejected before warping."""
        arr = self._face_arrays()
        W, H = cam.size
        K = cam.K
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        vc = (arr["verts"] - p) @ R.T  # (F, 6, 3) camera coordinates
        ncam = arr["normal"] @ R.T
        ocam = (arr["origin"] - p) @ R.T
        dcam = np.einsum("ij,ij->i", ncam, ocam)  # < 0: front side towards the camera
        x, y, z = vc[..., 0], vc[..., 1], vc[..., 2]
        xl, xr = -cx / fx, (W - 1 - cx) / fx
        yt, yb = -cy / fy, (H - 1 - cy) / fy
        keep = ((dcam < 0) | arr["two_sided"]) & (np.abs(dcam) > 1e-9)
        keep &= (z > NEAR_M).any(axis=1)
        keep &= ~(x < xl * z).all(axis=1) & ~(x > xr * z).all(axis=1)
        keep &= ~(y < yt * z).all(axis=1) & ~(y > yb * z).all(axis=1)
        idx = np.nonzero(keep)[0]
        if len(idx) == 0:
            return
        vk, zk = vc[idx], z[idx]
        clip = (zk < NEAR_M).any(axis=1)
        zs = np.where(zk < NEAR_M, 1.0, zk)
        px = vk[..., 0] / zs * fx + cx
        py = vk[..., 1] / zs * fy + cy
        # plane inverse depth 1/z = a x + b y + c per face
        nk, dk = ncam[idx], dcam[idx]
        pa = nk[:, 0] / (fx * dk)
        pb = nk[:, 1] / (fy * dk)
        pc = (nk[:, 2] - nk[:, 0] * cx / fx - nk[:, 1] * cy / fy) / dk
        # ripmap level from the projected texel footprint at the polygon centroid
        cen = vk.mean(axis=1)
        cz = np.maximum(cen[:, 2], NEAR_M)
        xn, yn = cen[:, 0] / cz, cen[:, 1] / cz
        uc, vcv = arr["u_axis"][idx] @ R.T, arr["v_axis"][idx] @ R.T
        gu = fx / cz * np.hypot(uc[:, 0] - xn * uc[:, 2], uc[:, 1] - yn * uc[:, 2])
        gv = fx / cz * np.hypot(vcv[:, 0] - xn * vcv[:, 2], vcv[:, 1] - yn * vcv[:, 2])
        lx = np.floor(np.log2(np.maximum(arr["ppm"][idx, 0] / np.maximum(gu, 1e-9), 1.0)) + 0.3)
        ly = np.floor(np.log2(np.maximum(arr["ppm"][idx, 1] / np.maximum(gv, 1e-9), 1.0)) + 0.3)
        lx = np.minimum(lx, arr["max_level"][idx, 0]).astype(int)
        ly = np.minimum(ly, arr["max_level"][idx, 1]).astype(int)
        zmin = zk.min(axis=1)
        order = np.argsort(np.where(clip, 0.0, zmin))
        inv_max = 1.0 / np.maximum(zmin, NEAR_M)
        pts_all = np.stack([px, py], axis=-1)
        box = np.stack([np.maximum(np.floor(px.min(axis=1)), 0),
                        np.maximum(np.floor(py.min(axis=1)), 0),
                        np.minimum(np.floor(px.max(axis=1)) + 2, W),
                        np.minimum(np.floor(py.max(axis=1)) + 2, H)], axis=1).astype(int)
        ocam_k = ocam[idx]
        nv_k = arr["nv"][idx]
        for j in order:
            if clip[j]:
                poly = _clip_near(vk[j, :nv_k[j]])
                if len(poly) < 3:
                    continue
                pts = np.empty((len(poly), 2))
                pts[:, 0] = poly[:, 0] / poly[:, 2] * fx + cx
                pts[:, 1] = poly[:, 1] / poly[:, 2] * fy + cy
                pts = np.clip(pts, -1e5, 1e5)
                x0 = max(int(pts[:, 0].min()), 0)
                y0 = max(int(pts[:, 1].min()), 0)
                x1 = min(int(pts[:, 0].max()) + 2, W)
                y1 = min(int(pts[:, 1].max()) + 2, H)
            else:
                pts = pts_all[j, :nv_k[j]]
                x0, y0, x1, y1 = box[j]
            if x1 <= x0 or y1 <= y0:
                continue
            zsub = zbuf[y0:y1, x0:x1]
            if inv_max[j] <= cv2.minMaxLoc(zsub)[0]:
                continue  # entirely behind what is already drawn
            self._draw_face(self.faces[idx[j]], pts, pa[j], pb[j], pc[j], (x0, y0, x1, y1),
                            int(lx[j]), int(ly[j]), uc[j], vcv[j], ocam_k[j], cam, img, zsub)

    def _draw_face(self, f: _Face, pts: np.ndarray, a: float, b: float, c: float,
                   box: tuple[int, int, int, int], lx: int, ly: int, u_c: np.ndarray,
                   v_c: np.ndarray, o_c: np.ndarray, cam: _CameraModel, img: np.ndarray,
                   zsub: np.ndarray) -> None:
        x0, y0, x1, y1 = box
        inv = (np.float32(a) * cam.xs[x0:x1])[None, :] + \
            (np.float32(b) * cam.ys[y0:y1] + np.float32(c))[:, None]
        mask = cv2.compare(inv, zsub, cv2.CMP_GT)
        poly_mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(poly_mask, np.rint((pts - (x0, y0)) * 16).astype(np.int32), 255,
                           cv2.LINE_8, 4)
        mask = cv2.bitwise_and(mask, poly_mask)
        bx, by, bw, bh = cv2.boundingRect(mask)
        if bw == 0:
            return
        if bw * bh < 0.8 * mask.size:  # partly hidden: warp only where it can show
            mask, inv = mask[by:by + bh, bx:bx + bw], inv[by:by + bh, bx:bx + bw]
            zsub = zsub[by:by + bh, bx:bx + bw]
            x0, y0, x1, y1 = x0 + bx, y0 + by, x0 + bx + bw, y0 + by + bh
        tex = f.texture.level(lx, ly)
        su, sv = tex.shape[1] / f.size[0], tex.shape[0] / f.size[1]
        # texel (column, row; centres at integers) -> metres -> ideal image pixel in the box
        M = np.empty((3, 3))
        M[:, 0], M[:, 1], M[:, 2] = u_c, v_c, o_c
        M = cam.K @ M @ np.array([[1 / su, 0, 0.5 / su], [0, 1 / sv, 0.5 / sv], [0, 0, 1.0]])
        M[0] -= x0 * M[2]
        M[1] -= y0 * M[2]
        warped = cv2.warpPerspective(tex, M, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REPLICATE)
        if f.alpha:
            _, opaque = cv2.threshold(cv2.extractChannel(warped, 3), 127, 255,
                                      cv2.THRESH_BINARY)
            mask = cv2.bitwise_and(mask, opaque.reshape(mask.shape))
        cv2.copyTo(warped, mask, img[y0:y1, x0:x1])
        cv2.copyTo(inv, mask, zsub)


def _clip_near(poly: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman clip of a camera-frame polygon against z >= NEAR_M."""
    inside = poly[:, 2] >= NEAR_M
    if inside.all():
        return poly
    out = []
    n = len(poly)
    for k in range(n):
        a, b = poly[k], poly[(k + 1) % n]
        ia, ib = a[2] >= NEAR_M, b[2] >= NEAR_M
        if ia:
            out.append(a)
        if ia != ib:
            s = (NEAR_M - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.array(out) if out else np.zeros((0, 3))


# ============================================================================ the marina

def _bollard(b: _Builder, n: float, e: float, top_down: float, size: float, colour,
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


def _boat(b: _Builder, n: float, e: float, yaw: float, length: float, beam: float,
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
    # hull sides: clockwise outline seen from above, so the outward normal is left of travel
    for k in range(len(outline)):
        a2 = np.array(outline[k])
        b2 = np.array(outline[(k + 1) % len(outline)])
        pa = c + a2[0] * fwd + a2[1] * right
        pb = c + b2[0] * fwd + b2[1] * right
        w = float(np.linalg.norm(pb - pa))
        h = bot_d - top_d
        along = _unit(pb - pa)
        normal = np.cross(along, np.array([0, 0, 1.0]))  # outward for this orientation
        if normal @ (0.5 * (pa + pb) - c) < 0:
            normal = -normal

        def paint(w, h, k=k):
            p = _Painter(w, h, ppm, hull_col, rng)
            p.rect(0, 0, w, 0.08, (200, 200, 200))
            p.rect(0, h - 0.4 - 0.12, w, h - 0.4, stripe)
            if w > 2.5 and k in (0, 3):
                p.text(name, 0.3 * w, 0.25 * (h - 0.4), 0.22, stripe)
            p.grain(0.5, 0.03, 2)
            return p.img, []
        mid = 0.5 * (pa + pb) + np.array([0, 0, 0.5 * (top_d + bot_d)])
        b.rect_face(mid, normal, (0, 0, 1.0), w, h, paint, "boat")
    # deck (pentagon) seen from above
    deck = np.array(outline)
    u_ax, v_ax = right, -fwd
    o = c + (L / 2) * fwd - (B / 2) * right + np.array([0, 0, top_d])
    poly = np.array([[(q[1] + B / 2), (L / 2 - q[0])] for q in deck])
    img, _ = _plain((200, 205, 205), rng, ppm=20.0, grain=0.05)(B, L)
    b.face(o, u_ax, v_ax, B, L, img, "boat", polygon_uv=poly)
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


def _build_marina(b: _Builder, sc: Scenario) -> np.ndarray:
    rng = b.rng
    e0, e1 = sc.quay_east_range
    qh = sc.quay_height_m
    below = 0.8
    L = e1 - e0
    # quay wall face (normal south)
    img, pts = _paint_quay_wall(rng, L, qh + below, qh, 64.0, "marina", e0)
    b.long_face((0.0, e0, -qh), (0, 1, 0), (0, 0, 1), L, qh + below, img, "quay", 10.0,
                points=pts)
    # quay top (apron strip) and the promenade behind it
    def paving(w, h, ppm=12.0):
        p = _Painter(w, h, ppm, (165, 170, 170), rng)
        for v in np.arange(0, h, 1.0):
            p.rect(0, v, w, v + 0.03, (130, 134, 134))
        p.rect(0, h - 0.12, w, h, (40, 196, 232))  # yellow edge line
        p.grain(1.0, 0.06)
        return p.img
    b.long_face((8.0, e0 - 40.0, -qh), (0, 1, 0), (-1, 0, 0), L + 80.0, 8.0,
                paving(L + 80.0, 8.0), "quay", 20.0)
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
                    rocks(length, slope_len), "shore", 25.0)
        b.long_face((30.0, a_e, -qh), (0, 1, 0), (-1, 0, 0), length, 30.0,
                    _plain((95, 130, 110), rng, ppm=2.0, grain=0.15, cell_m=4.0)(length, 30.0)[0],
                    "shore", 50.0)
    # bollards on the quay edge
    for e in np.arange(e0 + 4.0, e1 - 2.0, 8.0):
        _bollard(b, 0.45, e, -qh, 0.3, (38, 38, 40))
    # floating pontoon with two guide piles, and a gangway
    pe, pw, plen, pfb = 20.0, 2.5, 24.0, 0.45

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
    b.box((-plen / 2, pe + pw / 2, (-pfb + 0.3) / 2), AXES_NED, (plen / 2, pw / 2,
                                                               (pfb + 0.3) / 2),
          pontoon, "pontoon")

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
    for pn in (-7.0, -19.0):
        b.box((pn, pe + pw + 0.35, -1.5), AXES_NED, (0.28, 0.28, 2.5), pile, "pontoon")
    # moored boats: along the quay (west and east parts) and along the pontoon
    for e in (-52.0, -43.0, 38.0, 48.0):
        ln = rng.uniform(7.0, 10.0)
        _boat(b, -1.6 - rng.uniform(0, 0.4), e, np.radians(90.0 + 180.0 * (rng.random() < 0.5)),
              ln, 2.6, 0.9, sail=rng.random() < 0.6)
    for pn in (-6.0, -15.0):
        _boat(b, pn, pe + pw + 1.9, np.radians(180.0), rng.uniform(7, 9), 2.6, 0.9,
              sail=rng.random() < 0.7)
    _boat(b, -12.0, pe - 1.8, np.radians(180.0), 8.0, 2.6, 1.0, sail=True)
    # buildings behind the promenade (30-80 m north)
    e = e0 - 30.0
    while e < e1 + 30.0:
        w = rng.uniform(12.0, 28.0)
        d = rng.uniform(10.0, 18.0)
        ht = float(rng.choice([7.0, 10.0, 13.0, 16.0, 22.0]))
        n0 = rng.uniform(30.0, 55.0)
        style = "office" if rng.random() < 0.35 else "flats"

        def facade(side, fw, fh, style=style):
            if side == "top":
                return _plain((130, 135, 140), rng, 4.0)(fw, fh)
            return _paint_facade(rng, fw, fh, 20.0, style=style)
        b.box((n0 + d / 2, e + w / 2, -qh - ht / 2), AXES_NED, (d / 2, w / 2, ht / 2), facade,
              "building")
        e += w + rng.uniform(3.0, 12.0)
    # trees along the promenade and between buildings (crossed sprites)
    for e in np.arange(e0 - 20.0, e1 + 20.0, 15.0) + rng.uniform(-3, 3):
        if rng.random() < 0.2:
            continue
        th = rng.uniform(5.0, 8.0)
        tw = th * rng.uniform(0.65, 0.85)
        spr = _tree_sprite(rng, tw, th, 16.0)
        n = rng.uniform(14.0, 22.0)
        for ang in (0.0, np.pi / 2):
            u = np.array([np.cos(ang + 0.3), np.sin(ang + 0.3), 0.0])
            b.face(np.array([n, e, -qh - th]) - u * tw / 2, u, (0, 0, 1), tw, th, spr, "tree",
                   two_sided=True)
    # far town and the mountains to the north (Rokko behind Nishinomiya)
    _backdrop(b, 280.0, 1600.0, 30.0, "city", (165, 165, 162), -qh)
    _backdrop(b, 2600.0, 12000.0, 480.0, "hills", (118, 128, 106), -qh)
    # quay face edge with the pontoon
    return np.array([[0.0, e0], [0.0, pe], [-plen, pe], [-plen, pe + pw], [0.0, pe + pw],
                     [0.0, e1]])


def _backdrop(b: _Builder, north: float, width: float, height: float, kind: str, colour,
              ground: float) -> None:
    """A far silhouette (city or hills) facing south, one continuous sprite cut into panels;
    its bottom is hidden below the ground."""
    ppm = min(6.0, 9000.0 / width)
    spr = _skyline_sprite(b.rng, width, height, ppm, kind, colour)
    b.long_face((north, -width / 2, ground - height + 2.0), (0, 1, 0), (0, 0, 1), width, height,
                spr, "far", width / 6.0, lit=False)


# ================================================================= the container terminal

def _crane(b: _Builder, e: float, ground: float, number: int) -> None:
    """Ship-to-shore gantry crane: legs on rails at north 3 and 33, lattice boom over the
    water, machinery house, A-frame and forestays, trolley with a hanging container."""
    rng = b.rng
    red, white = (40, 45, 190), (232, 232, 230)
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


def _container_block(b: _Builder, n0: float, e0: float, bays: int, rows: int, tiers: int,
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


def _build_terminal(b: _Builder, sc: Scenario) -> np.ndarray:
    rng = b.rng
    e0, e1 = sc.quay_east_range
    qh = sc.quay_height_m
    ground = -qh
    below = 1.5
    L = e1 - e0
    img, pts = _paint_quay_wall(rng, L, qh + below, qh, 24.0, "terminal", e0)
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
    n_cr = int(rng.integers(3, 5))
    for k in range(n_cr):
        _crane(b, -165.0 + k * 70.0 + rng.uniform(-8, 8), ground, 11 + k)
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
            if rng.random() < 0.85:
                _container_block(b, n0, e, bays, 6, int(rng.integers(1, 6)), ground)
            e += bays * 12.2 + rng.uniform(4.0, 14.0)
    # buildings: terminal office, warehouses
    e = e0 - 60.0
    while e < e1 + 60.0:
        w = rng.uniform(30.0, 90.0)
        d = rng.uniform(20.0, 40.0)
        shed = rng.random() < 0.6
        ht = rng.uniform(10.0, 16.0) if shed else float(rng.choice([16.0, 22.0, 28.0]))
        n0 = rng.uniform(225.0, 260.0)

        def facade(side, fw, fh, shed=shed):
            if side == "top":
                return _plain((150, 152, 150), rng, 2.0)(fw, fh)
            return _paint_facade(rng, fw, fh, 8.0, style="shed" if shed else "office")
        b.box((n0 + d / 2, e + w / 2, ground - ht / 2), AXES_NED, (d / 2, w / 2, ht / 2), facade,
              "building")
        e += w + rng.uniform(10.0, 40.0)
    # a feeder ship moored at the west end of the berth
    _moored_ship(b, -160.0, 110.0, 20.0)
    _backdrop(b, 900.0, 5000.0, 60.0, "city", (165, 165, 162), ground)
    _backdrop(b, 6000.0, 30000.0, 800.0, "hills", (150, 152, 134), ground)
    return np.array([[0.0, e0], [0.0, e1]])


def _moored_ship(b: _Builder, e_mid: float, length: float, beam: float) -> None:
    """Container feeder alongside (bow east): hull, accommodation at the stern, deck cargo."""
    rng = b.rng
    n_mid = -beam / 2 - 0.8
    fb = 7.0  # freeboard, m
    hull_col = (80, 45, 25)
    L, B = length, beam
    c = np.array([n_mid, e_mid, 0.0])
    fwd, right = np.array([0.0, 1.0, 0.0]), np.array([-1.0, 0.0, 0.0])
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
    e_start = e_mid - L / 2 + 15.0
    for k in range(5):
        tiers = int(rng.integers(2, 5))
        e_a = e_start + k * 14.0

        def paint(side, w, h):
            if side == "top":
                return _paint_containers(rng, w, h, 12.2, 2.44, 6.0, "ship", top=True)
            if side in ("left", "right"):
                return _paint_containers(rng, w, h, 2.44, 2.6, 10.0, "ship")
            return _paint_containers(rng, w, h, 12.2, 2.6, 10.0, "ship")
        Wd = 7 * 2.44
        b.box((n_mid, e_a + 6.1, -fb - tiers * 1.3), AXES_NED, (Wd / 2, 6.1, tiers * 1.3), paint,
              "ship")
