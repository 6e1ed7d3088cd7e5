"""The camera renderer of the simulator: the seed's port (``port``) under the
seed's light and water (``variety``), seen by a camera with a real lens.

World = the scenario's local-level NED frame: the sea surface is the plane down = 0, the quay face
the vertical plane north = 0 over ``quay_east_range``, land at north > 0. Camera frame: right,
down, forward; ``x_cam = C_level_to_camera @ (x - p)``.

The port is a set of planar textured convex polygons ("faces"): the static port, boats that
move (moved rigidly each frame) and the ship's own hull (carried with the camera). A frame is
rendered with numpy and OpenCV only:

1. the background on a half-resolution grid: sky (gradient, the sun and its glow, clouds on a
   plane 1.2 km up) and water (the plane down = 0 with three wave layers travelling at their
   deep-water phase speeds in different directions, Fresnel reflection, sun glints, the port's
   cast shadow), both found per pixel from the ray direction. What the water reflects is the
   sky or, where there is one, the port itself: the faces are drawn a second time, at half
   resolution, by the camera mirrored in the water plane (``R diag(1, 1, -1)`` at the mirrored
   position), keeping only what lies beyond the water surface along each ray — a geometrically
   exact mirror image, then displaced by the wave slopes (calm water: a sharp mirror; choppy:
   broken streaks) and weighted by the Fresnel term;
2. every face not culled, near to far: its texture-to-image homography ``K [R U, R V, R O + t]``
   (valid even when part of the face is behind the camera), warped over the bounding box of its
   near-clipped polygon, written where it is nearer than the z-buffer. The z-buffer holds inverse
   depth, which is affine in image coordinates on a plane, so it costs one broadcast add per
   face, and faces entirely behind what is drawn are skipped before warping. The water keeps
   its own depth: a reflection is not a surface;
3. glare when the sun is in or near the picture (bloom round the sun, veiling light);
4. the ideal image (rendered with a margin) is distorted like a real lens with a precomputed
   remap, then exposure (drift, steps, auto-exposure following the picture), vignetting and
   Gaussian noise are applied.

Cast shadows are baked into the textures once, at ``PortScene.build``: the static port is drawn
(depth only) by a camera 4 km away towards the sun, and each texel of a sunlit face is lit when
nothing in that shadow map lies between it and the sun.

Textures carry ripmaps (separate x / y reduction) chosen by the projected texel footprint, which
avoids aliasing on oblique surfaces. Everything is 4-channel (BGRA) because OpenCV's warps and
remaps are markedly faster on 4 channels than on 3.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import cv2
import numpy as np

from estimator.records import CameraCalibration

from . import variety
from .port import (
    Builder,
    Face,
    Mover,
    _build_marina,
    _build_terminal,
    _own_large_ship,
    _own_small_boat,
    _periodic_noise,
)
from .scenarios import Scenario

NEAR_M = 0.15  # near clipping plane (camera z), m
HALF = 2  # background and reflections are computed at 1/HALF resolution
MIRROR = np.diag([1.0, 1.0, -1.0])  # reflection in the water plane down = 0
MIRROR_MIN_AREA_PX = 40.0  # smaller faces are not drawn in the reflections (half-res px²)
SHADOW_MAP_PX = 2048
AE_TARGET = 118.0  # grey level the auto-exposure aims at


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
class _View:
    """A pinhole view to draw faces into: intrinsics, size, pixel coordinate ramps."""

    K: np.ndarray
    size: tuple[int, int]  # width, height
    xs: np.ndarray
    ys: np.ndarray

    @classmethod
    def of(cls, K: np.ndarray, size: tuple[int, int]) -> _View:
        return cls(K=K, size=size, xs=np.arange(size[0], dtype=np.float32),
                   ys=np.arange(size[1], dtype=np.float32))


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
    half: _View  # the ideal render at 1/HALF resolution (background, reflections)

    @classmethod
    def build(cls, camera: CameraCalibration, seed: int, noise_sigma: float) -> _CameraModel:
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
        noise = np.rint(rng.standard_normal((h + 64, w + 64, 3)) * noise_sigma).astype(np.int16)
        # half-resolution pixel i covers full-resolution pixels HALF i .. HALF i + HALF - 1
        Kh = np.array([[fx / HALF, 0.0, (cx - 0.5 * (HALF - 1)) / HALF],
                       [0.0, fy / HALF, (cy - 0.5 * (HALF - 1)) / HALF], [0.0, 0.0, 1.0]])
        return cls(K=Kr, size=(wr, hr), map1=map1, map2=map2,
                   vignette=np.repeat(vig[..., None], 3, axis=2), noise=noise,
                   xs=np.arange(wr, dtype=np.float32), ys=np.arange(hr, dtype=np.float32),
                   half=_View.of(Kh, (wr // HALF, hr // HALF)))




# ========================================================================= face drawing

def _stack(faces: list[Face]) -> dict:
    """Stacked face geometry for vectorised culling and drawing."""
    F = len(faces)
    verts = np.zeros((F, 6, 3))
    nv = np.zeros(F, int)
    for i, f in enumerate(faces):
        w = f.world(f.polygon_uv)
        nv[i] = len(w)
        verts[i, :len(w)] = w
        verts[i, len(w):] = w[-1]
    base = [f.texture.levels[(0, 0)].shape for f in faces]
    return dict(
        verts=verts, nv=nv,
        normal=np.array([f.normal for f in faces]).reshape(F, 3),
        origin=np.array([f.origin for f in faces]).reshape(F, 3),
        u_axis=np.array([f.u_axis for f in faces]).reshape(F, 3),
        v_axis=np.array([f.v_axis for f in faces]).reshape(F, 3),
        ppm=np.array([[sh[1] / f.size[0], sh[0] / f.size[1]]
                      for sh, f in zip(base, faces, strict=True)]).reshape(F, 2),
        max_level=np.array([[f.texture.max_lx, f.texture.max_ly] for f in faces]).reshape(F, 2),
        two_sided=np.array([f.two_sided for f in faces], bool))


def _moved(arr: dict, C: np.ndarray, t: np.ndarray) -> dict:
    """Stacked faces rotated by C and translated by t (a mover, the own ship)."""
    out = dict(arr)
    out["verts"] = arr["verts"] @ C.T + t
    out["origin"] = arr["origin"] @ C.T + t
    for k in ("normal", "u_axis", "v_axis"):
        out[k] = arr[k] @ C.T
    return out


def _concat(arrs: list[dict]) -> dict:
    return {k: np.concatenate([a[k] for a in arrs]) for k in arrs[0]}


def _draw_faces(faces: list[Face], arr: dict, cam, R: np.ndarray, p: np.ndarray,
                img: np.ndarray | None, zbuf: np.ndarray, zlim: np.ndarray | None = None,
                min_area_px: float = 0.0) -> None:
    """Cull, then draw faces near to far so hidden ones are rejected before warping.

    ``cam``: a view (K, size, xs, ys). ``R`` may be a reflection (the mirrored camera).
    ``img`` None: depth only. ``zlim``: draw only farther than this inverse depth per pixel
    (what lies beyond the water surface, for the reflections). Faces (not cut by the near
    plane) that project smaller than ``min_area_px`` are left out."""
    if not faces:
        return
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
    inv_min = 1.0 / np.maximum(zk.max(axis=1), NEAR_M)
    pts_all = np.stack([px, py], axis=-1)
    if min_area_px > 0.0:  # shoelace area (repeated padding vertices add nothing)
        area = 0.5 * np.abs(np.sum(px * np.roll(py, -1, axis=1) - py * np.roll(px, -1, axis=1),
                                   axis=1))
        big = clip | (area >= min_area_px)
    else:
        big = np.ones(len(idx), bool)
    box = np.stack([np.maximum(np.floor(px.min(axis=1)), 0),
                    np.maximum(np.floor(py.min(axis=1)), 0),
                    np.minimum(np.floor(px.max(axis=1)) + 2, W),
                    np.minimum(np.floor(py.max(axis=1)) + 2, H)], axis=1).astype(int)
    ocam_k = ocam[idx]
    nv_k = arr["nv"][idx]
    # a polygon cut by the near plane is also cut to the view (a little wider), so that its
    # projected corners stay near the image and its outline exact
    m = 0.25
    frustum = np.array([[1.0, 0.0, -(xl - m)], [-1.0, 0.0, xr + m], [0.0, 1.0, -(yt - m)],
                        [0.0, -1.0, yb + m], [0.0, 0.0, 1.0]])
    for j in order:
        if not big[j]:
            continue
        if clip[j]:
            poly = _clip_frustum(vk[j, :nv_k[j]], frustum)
            if len(poly) < 3:
                continue
            pts = np.empty((len(poly), 2))
            pts[:, 0] = poly[:, 0] / poly[:, 2] * fx + cx
            pts[:, 1] = poly[:, 1] / poly[:, 2] * fy + cy
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
        lsub = None
        if zlim is not None:
            lsub = zlim[y0:y1, x0:x1]
            if inv_min[j] >= cv2.minMaxLoc(lsub)[1]:
                continue  # entirely this side of the water surface (or no water there)
        _draw_face(faces[idx[j]], pts, pa[j], pb[j], pc[j], (x0, y0, x1, y1), int(lx[j]),
                   int(ly[j]), uc[j], vcv[j], ocam_k[j], cam, img, zsub, lsub)


def _draw_face(f: Face, pts: np.ndarray, a: float, b: float, c: float,
               box: tuple[int, int, int, int], lx: int, ly: int, u_c: np.ndarray,
               v_c: np.ndarray, o_c: np.ndarray, cam, img: np.ndarray | None,
               zsub: np.ndarray, lsub: np.ndarray | None) -> None:
    x0, y0, x1, y1 = box
    inv = (np.float32(a) * cam.xs[x0:x1])[None, :] + \
        (np.float32(b) * cam.ys[y0:y1] + np.float32(c))[:, None]
    mask = cv2.compare(inv, zsub, cv2.CMP_GT)
    if lsub is not None:
        mask = cv2.bitwise_and(mask, cv2.compare(inv, lsub, cv2.CMP_LT))
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
    if img is not None or f.alpha:
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
        if img is not None:
            cv2.copyTo(warped, mask, img[y0:y1, x0:x1])
    cv2.copyTo(inv, mask, zsub)


def _clip_frustum(poly: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman clip of a camera-frame polygon to ``planes @ x >= 0`` (the last one
    ``z >= 0``, taken as z >= NEAR_M)."""
    for k, plane in enumerate(planes):
        off = NEAR_M if k == len(planes) - 1 else 0.0
        d = poly @ plane - off
        inside = d >= 0.0
        if inside.all():
            continue
        out = []
        n = len(poly)
        for i in range(n):
            a, b = poly[i], poly[(i + 1) % n]
            if inside[i]:
                out.append(a)
            if inside[i] != inside[(i + 1) % n]:
                out.append(a + d[i] / (d[i] - d[(i + 1) % n]) * (b - a))
        if len(out) < 3:
            return np.zeros((0, 3))
        poly = np.array(out)
    return poly


# ============================================================================== shadows

@dataclass
class _SunView:
    """A camera far away towards the sun: its depth map of the static port is the shadow map."""

    view: _View
    R: np.ndarray
    p: np.ndarray
    inv_depth: np.ndarray

    @classmethod
    def render(cls, faces: list[Face], sun_dir: np.ndarray, centre: np.ndarray,
               radius: float, size: int = SHADOW_MAP_PX, distance: float = 4000.0) -> _SunView:
        z = -np.asarray(sun_dir, float)
        up = np.array([0.0, 0.0, -1.0])
        x = np.cross(up, z)
        x /= np.linalg.norm(x)
        R = np.array([x, np.cross(z, x), z])
        f = 0.5 * size * distance / radius
        K = np.array([[f, 0.0, 0.5 * size - 0.5], [0.0, f, 0.5 * size - 0.5], [0, 0, 1.0]])
        view = _View.of(K, (size, size))
        p = np.asarray(centre, float) + np.asarray(sun_dir, float) * distance
        zbuf = np.zeros((size, size), np.float32)
        _draw_faces(faces, _stack(faces), view, R, p, None, zbuf)
        return cls(view, R, p, zbuf)

    def lit(self, points: np.ndarray, bias_m: float = 0.3) -> np.ndarray:
        """1 where nothing lies between a point (..., 3) and the sun, else 0 (float32)."""
        xc = (points - self.p) @ self.R.T
        K = self.view.K
        u = np.rint(xc[..., 0] / xc[..., 2] * K[0, 0] + K[0, 2]).astype(int)
        v = np.rint(xc[..., 1] / xc[..., 2] * K[1, 1] + K[1, 2]).astype(int)
        n = self.view.size[0]
        inside = (u >= 0) & (u < n) & (v >= 0) & (v < n)
        zm = np.zeros(u.shape, np.float64)
        zm[inside] = self.inv_depth[v[inside], u[inside]]
        blocker = np.where(zm > 0, 1.0 / np.maximum(zm, 1e-12), np.inf)
        return (xc[..., 2] <= blocker + bias_m).astype(np.float32)

    def face_lit(self, face: Face, shape: tuple[int, int], sun_dir: np.ndarray,
                 spacing_m: float = 0.2) -> np.ndarray:
        """Lit fraction of a face's texels (shape = texture height, width), soft-edged."""
        w, h = face.size
        nu = int(np.clip(np.ceil(w / spacing_m), 2, max(shape[1], 2)))
        nv = int(np.clip(np.ceil(h / spacing_m), 2, max(shape[0], 2)))
        uu = (np.arange(nu) + 0.5) * (w / nu)
        vv = (np.arange(nv) + 0.5) * (h / nv)
        n = face.normal
        if n @ sun_dir < 0:  # a two-sided face lit from its back
            n = -n
        X = face.origin + uu[None, :, None] * face.u_axis + vv[:, None, None] * face.v_axis
        lit = self.lit(X + 0.25 * n)  # off the surface: no self-shadowing
        return cv2.resize(lit, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


@dataclass
class _WaterShadow:
    """Lit fraction of the water surface on a north-east grid (255 = sunlit)."""

    image: np.ndarray  # uint8 (rows north, columns east)
    origin_ne: tuple[float, float]
    res_m: float

    @classmethod
    def from_sun(cls, sun: _SunView, north: tuple[float, float], east: tuple[float, float],
                 res_m: float) -> _WaterShadow:
        n = np.arange(north[0], north[1], res_m) + 0.5 * res_m
        e = np.arange(east[0], east[1], res_m) + 0.5 * res_m
        X = np.stack([*np.meshgrid(n, e, indexing="ij"), np.full((len(n), len(e)), -0.05)],
                     axis=-1)
        lit = cv2.GaussianBlur(sun.lit(X), (0, 0), 1.0)
        return cls(_to_u8(lit * 255.0), (north[0], east[0]), res_m)

    def affine(self) -> np.ndarray:
        """(north, east, 1) -> (column, row, 1) of the image."""
        r = self.res_m
        return np.array([[0.0, 1 / r, -self.origin_ne[1] / r - 0.5],
                         [1 / r, 0.0, -self.origin_ne[0] / r - 0.5], [0, 0, 1.0]])


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(img, 0, 255).astype(np.uint8)



# =================================================================================== scene

# What the sun's shadow map covers (centre north, east, down; radius, m) and the water grid
# whose cast shadow is kept (north range, east range, resolution m), per scene kind.
_SHADOW_REGION = {"marina": ((50.0, 0.0, -10.0), 200.0, (-120.0, 0.0), (-160.0, 160.0), 0.4),
                  "container-terminal": ((100.0, 0.0, -20.0), 420.0, (-250.0, 0.0),
                                         (-400.0, 400.0), 1.0)}


@dataclass
class PortScene:
    """The textured port of a scenario's seed, its moving boats and the ship's own hull, plus
    the time-varying water and sky, under the seed's light."""

    scenario: Scenario  # as the seed has it (``variety.seeded``)
    seed: int
    look: variety.Look
    faces: list[Face]
    points: np.ndarray  # (N, 3) well-textured scene points of the static port (true NED)
    point_kinds: list[str]
    point_normals: np.ndarray  # (N, 3) outward normal of the surface each point lies on
    outline_ne: np.ndarray  # (M, 2) quay face edge
    movers: list[Mover]
    own: list[Face]  # the ship's own hull, body frame
    water_layers: list[tuple[np.ndarray, float, float, float, np.ndarray, float]]
    clouds: np.ndarray  # tileable cloud cover texture (uint8)
    water_shadow: _WaterShadow | None
    exposure_phase: tuple[float, float]
    vignetting: bool = True  # lens fall-off towards the corners
    _cameras: dict = field(default_factory=dict, repr=False)
    _arrays: dict = field(default_factory=dict, repr=False)

    # ------------------------------------------------------------------------- building
    @classmethod
    def build(cls, scenario: Scenario, seed: int, look: variety.Look | None = None
              ) -> PortScene:
        """The port of ``scenario``'s recording ``seed`` (deterministic: the same from the
        base scenario or from ``variety.seeded(scenario, seed)``). ``look``: another port,
        light and water than the seed's (e.g. ``variety.reference_look``; the details are
        still drawn from the seed)."""
        sc = variety.seeded(scenario, seed)
        if look is None:
            look = variety.look(scenario, seed)
        else:
            sc = dataclasses.replace(sc, quay_height_m=look.port.quay_height_m)
        rng = np.random.default_rng(seed)
        kf = np.array(sc.path_keyframes)
        viewpoint = np.array([kf[:, 1].mean(), kf[:, 2].mean(), -5.0])
        b = Builder(rng, viewpoint, look.light)
        if sc.scene_kind == "marina":
            outline = _build_marina(b, sc, look.port)
            with b.own_ship():
                _own_small_boat(b, sc)
        elif sc.scene_kind == "container-terminal":
            outline = _build_terminal(b, sc, look.port)
            with b.own_ship():
                _own_large_ship(b, sc)
        else:
            raise ValueError(f"unknown scene kind {sc.scene_kind!r}")
        light = look.light
        water_shadow = None
        if light.direct > 0.1 and light.sun_el_deg > 1.0:
            centre, radius, wn, we, wres = _SHADOW_REGION[sc.scene_kind]
            casters = [f for f in b.faces if f.kind not in ("far", "ground")]
            sun = _SunView.render(casters, light.sun_dir, np.array(centre), radius)
            b.finish(lambda f, shape: sun.face_lit(f, shape, light.sun_dir))
            water_shadow = _WaterShadow.from_sun(sun, wn, we, wres)
        else:
            b.finish(lambda f, shape: None)
        layers = []
        # (texture, metres per texel, drift direction, amplitude, velocity, wavelength)
        for wavelength, heading, amp in look.water.layers:
            # deep-water phase speed: the patterns on real water change that fast, so water
            # features do not move with the port (nor with each other)
            speed = np.sqrt(9.81 * wavelength / (2 * np.pi))
            n = 256
            # waves travel along texture x; the layer is rotated to its drift direction
            direction = np.radians(heading)
            tex = _periodic_noise(rng, n, k_peak=n / 10.0, k_width=n / 14.0, direction=0.0,
                                  sharpness=1)
            tex = np.clip(128 + 42 * tex, 0, 255).astype(np.uint8)
            vel = speed * np.array([np.cos(direction), np.sin(direction)])
            layers.append((tex, wavelength / 10.0, direction, amp, vel, wavelength))
        clouds = _periodic_noise(rng, 512, 5.0, 4.0) + 0.5 * _periodic_noise(rng, 512, 14, 8)
        clouds = np.clip(128 + 55 * clouds, 0, 255).astype(np.uint8)
        return cls(scenario=sc, seed=seed, look=look, faces=b.faces, points=np.array(b.points),
                   point_kinds=list(b.kinds), point_normals=np.array(b.normals),
                   outline_ne=outline, movers=b.movers, own=b.own, water_layers=layers,
                   clouds=clouds, water_shadow=water_shadow,
                   exposure_phase=tuple(rng.uniform(0, 2 * np.pi, 2)))

    # --------------------------------------------------------------------------- access
    def scene_points(self) -> tuple[np.ndarray, list[str]]:
        """(N, 3) true NED positions of strong image corners on the static structure and their
        kind (boats that move are not in it)."""
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
            model = _CameraModel.build(camera, self.seed, self.look.light.noise_sigma)
            self._cameras[key] = model
        return model

    def _static_arrays(self) -> dict:
        if "static" not in self._arrays:
            self._arrays["static"] = _stack(self.faces)
            self._arrays["movers"] = [_stack(m.faces) for m in self.movers]
            self._arrays["own"] = _stack(self.own) if self.own else None
        return self._arrays["static"]

    def _dynamic(self, t: float, R: np.ndarray, p: np.ndarray,
                 camera: CameraCalibration) -> tuple[list[Face], dict | None]:
        """The movers at time t and the own hull carried with the camera, in the world."""
        self._static_arrays()
        faces: list[Face] = []
        arrs = []
        for m, arr in zip(self.movers, self._arrays["movers"], strict=True):
            ne = m.boat.position(t)
            arrs.append(_moved(arr, np.eye(3), np.array([ne[0], ne[1], 0.0])))
            faces += m.faces
        if self._arrays["own"] is not None and self.sees_own_hull(camera):
            C_b_l = R.T @ np.asarray(camera.C_camera_to_body, float).T
            origin = p - C_b_l @ np.asarray(camera.lever_arm_body, float)
            arrs.append(_moved(self._arrays["own"], C_b_l, origin))
            faces += self.own
        return faces, (_concat(arrs) if arrs else None)

    def sees_own_hull(self, camera: CameraCalibration) -> bool:
        """A camera on a small boat's stem (within 1 m of the bow) sits in the pulpit and sees
        nothing of the boat; one farther aft looks over the foredeck. A large ship's bridge
        camera may see her deck and side."""
        sc = self.scenario
        if sc.scene_kind != "marina":
            return True
        fwd = float(camera.lever_arm_body[0]) - sc.motion_centre_body[0]
        return fwd < 0.5 * sc.hull_length_m - 1.0

    def exposure_gain(self, t: float) -> float:
        """The camera's gain at time t before the auto-exposure: the seed's exposure, a slow
        drift of a few % and the exposure steps (each ramps the gain to its own level, the
        seed's gain times its factor: the exposure hunts, it does not run away)."""
        a, b = self.exposure_phase
        L = self.look.light
        level = 1.0
        for t0, factor, ramp in L.exposure_steps:
            x = float(np.clip((t - t0) / ramp, 0.0, 1.0))
            level += (factor - level) * (0.5 - 0.5 * np.cos(np.pi * x))
        return float(L.exposure * level * (1.0 + 0.045 * np.sin(2 * np.pi * t / 37.0 + a)
                                           + 0.02 * np.sin(2 * np.pi * t / 9.3 + b)))

    # --------------------------------------------------------------------------- render
    def render(self, C_level_to_camera: np.ndarray, camera_position_ned: np.ndarray, t: float,
               camera: CameraCalibration, rng: np.random.Generator,
               return_depth: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Camera frame (height, width, 3) BGR uint8, distorted like the real lens.

        With ``return_depth`` also the camera depth z (float32, inf for sky) per pixel: of the
        surface seen (the water's own depth where the water is seen, reflections or not)."""
        cam = self._camera_model(camera)
        R = np.asarray(C_level_to_camera, float)
        p = np.asarray(camera_position_ned, float)
        dyn_faces, dyn = self._dynamic(t, R, p, camera)
        img, zbuf = self._background(cam, R, p, t, dyn_faces, dyn)
        _draw_faces(self.faces, self._static_arrays(), cam, R, p, img, zbuf)
        if dyn is not None:
            _draw_faces(dyn_faces, dyn, cam, R, p, img, zbuf)
        self._glare(cam, R, img, zbuf)
        out = cv2.remap(img, cam.map1, cam.map2, cv2.INTER_LINEAR)
        out = cv2.cvtColor(out, cv2.COLOR_BGRA2BGR)
        gain = self.exposure_gain(t)
        ae = self.look.light.auto_exposure
        if ae > 0.0:  # the camera's auto-exposure, following the picture (instantly)
            small = cv2.resize(out, (out.shape[1] // 8, out.shape[0] // 8),
                               interpolation=cv2.INTER_AREA)
            mean = float(np.mean(small.astype(np.float32) @ np.float32([0.11, 0.59, 0.3])))
            gain *= float(np.clip((AE_TARGET / max(mean * gain, 1.0)) ** ae, 0.6, 1.8))
        if self.vignetting:
            out = cv2.multiply(out, cam.vignette, scale=gain / 255.0)
        else:
            out = cv2.convertScaleAbs(out, alpha=gain)
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

    def _background(self, cam: _CameraModel, R: np.ndarray, p: np.ndarray, t: float,
                    dyn_faces: list[Face], dyn: dict | None) -> tuple[np.ndarray, np.ndarray]:
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
        if r_sky:
            sky = self._sky(cam, R, p, t, r_sky)
            for k in range(3):
                planes[k][:r_sky] = sky[k]
        if r_water < Hh:
            refl = self._mirror(cam, R, p, r_water, h_cam, dyn_faces, dyn)
            water, is_water = self._water(cam, R, p, t, r_water, h_cam, refl)
            for k in range(3):
                if r_sky > r_water:  # rows crossed by the horizon
                    water[k] = np.where(is_water, water[k], planes[k][r_water:])
                planes[k][r_water:] = water[k]
        alpha = np.zeros((Hh, Wh), np.uint8)
        half = cv2.merge([cv2.convertScaleAbs(q) for q in planes] + [alpha])
        img = cv2.resize(half, (W, H), interpolation=cv2.INTER_LINEAR)
        # water inverse depth at full resolution: 1/z = ray_down / h
        xs = (cam.xs - cx) / fx
        ys = (cam.ys - cy) / fy
        inv = (float(R[0, 2] / h_cam) * xs)[None, :] + \
            ((float(R[1, 2]) * ys + float(R[2, 2])) / h_cam)[:, None]
        zbuf = np.maximum(inv, np.float32(0.0))
        return img, zbuf

    def _mirror(self, cam: _CameraModel, R: np.ndarray, p: np.ndarray, row0: int, h_cam: float,
                dyn_faces: list[Face], dyn: dict | None) -> np.ndarray:
        """The port mirrored in the water plane (BGRA, half-res rows from row0; alpha 0 where
        the water reflects the sky): the faces seen by the mirrored camera beyond the water
        surface along each ray."""
        view = cam.half
        Wh, Hh = view.size
        Rm, pm = R @ MIRROR, MIRROR @ p
        # inverse depth of the water surface on the half-res grid (0: no water)
        K = view.K
        xs = (view.xs - K[0, 2]) / K[0, 0]
        ys = (view.ys[row0:] - K[1, 2]) / K[1, 1]
        zlim = np.zeros((Hh, Wh), np.float32)
        zlim[row0:] = np.maximum((float(R[0, 2] / h_cam) * xs)[None, :]
                                 + ((float(R[1, 2]) * ys + float(R[2, 2])) / h_cam)[:, None], 0.0)
        img = np.zeros((Hh, Wh, 4), np.uint8)
        zbuf = np.zeros((Hh, Wh), np.float32)
        # (small faces are left out: the waves would break them up anyway)
        _draw_faces(self.faces, self._static_arrays(), view, Rm, pm, img, zbuf, zlim,
                    MIRROR_MIN_AREA_PX)
        if dyn is not None:
            _draw_faces(dyn_faces, dyn, view, Rm, pm, img, zbuf, zlim, MIRROR_MIN_AREA_PX)
        return img[row0:]

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

    def _sky_colour(self, sin_el: np.ndarray, cos_sun: np.ndarray) -> list[np.ndarray]:
        """Clear-sky colour planes (B, G, R) from the sine of the elevation and the cosine of
        the angle to the sun: horizon-to-zenith gradient and the glow round the sun."""
        L = self.look.light
        g = cv2.sqrt(np.clip(sin_el * np.float32(1 / 0.6), 0.0, 1.0))
        glow = 0.55 * cv2.exp((cos_sun - 1.0) * np.float32(1 / 0.004)) + \
            0.45 * cv2.exp((cos_sun - 1.0) * np.float32(1 / 0.12))
        # the afterglow hugs the horizon
        glow = glow * (1.0 - 0.6 * np.clip(sin_el * np.float32(1 / 0.3), 0.0, 1.0))
        return [hor + (zen - hor) * g + gl * glow for hor, zen, gl in
                zip(L.sky_horizon, L.sky_zenith, L.sky_glow, strict=True)]

    def _water(self, cam: _CameraModel, R: np.ndarray, p: np.ndarray, t: float, row0: int,
               h_cam: float, refl: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        """Water colour planes (B, G, R) on the half-res rows from row0, and the water mask."""
        Hh = cam.size[1] // HALF
        L, Wt = self.look.light, self.look.water
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
        sx, sy, sz = L.sun_dir.tolist()
        cos_sun = (rn * sx + re * sy - rd * sz) / norm  # the reflected ray towards the sun
        # the sky it reflects (smooth: computed on every other half-res pixel)
        sub = (slice(None, None, 2), slice(None, None, 2))
        size = (rd.shape[1], rd.shape[0])
        reflected = [cv2.resize(c, size, interpolation=cv2.INTER_LINEAR)
                     for c in self._sky_colour((rd / norm)[sub], cos_sun[sub])]
        # the port mirrored, shifted by the wave slopes (none where it meets its waterline:
        # there the reflection's own rows are the displaced ones)
        wob = np.float32(Wt.wobble_px / HALF)
        map_y = np.arange(refl.shape[0], dtype=np.float32)[:, None] + wob * shade
        map_x = np.arange(refl.shape[1], dtype=np.float32)[None, :] + \
            np.float32(0.4) * wob * np.roll(shade, 7, axis=1)
        mirror = cv2.remap(refl, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        b, g, r, a = cv2.split(mirror)
        a = a.astype(np.float32) * np.float32(1 / 255.0)
        reflected = [sky + (port.astype(np.float32) - sky) * a
                     for sky, port in zip(reflected, (b, g, r), strict=True)]
        # sun glints: small crests of the short waves, strongest near the sun's mirror image
        glare = 0.3 + 0.7 * cv2.exp((cos_sun - 1.0) * np.float32(1 / 0.08))
        sun_on_water = np.float32(min(L.direct / 0.45, 1.6) if L.sun_el_deg > 0 else 0.0)
        glint = np.clip((fine - 2.2) * 2.5, 0.0, 1.0) * glare * (150.0 * sun_on_water)
        deep = [np.float32(c) for c in Wt.deep]
        if self.water_shadow is not None:  # the port's shadow: no glints, a darker body
            ws = self.water_shadow
            lit = cv2.warpPerspective(ws.image, ws.affine() @ G, (rn.shape[1], rn.shape[0]),
                                      flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                      borderMode=cv2.BORDER_CONSTANT, borderValue=255)
            lit = lit.astype(np.float32) * np.float32(1 / 255.0)
            glint = glint * lit
            deep = [d * (0.7 + 0.3 * lit) for d in deep]
        colour = [d + (s - d) * mix + glint for d, s in zip(deep, reflected, strict=True)]
        return colour, is_water

    def _sky(self, cam: _CameraModel, R: np.ndarray, p: np.ndarray, t: float,
             rows_half: int) -> list[np.ndarray]:
        """Sky colour planes on the first ``rows_half`` half-res rows (computed at quarter
        resolution: the sky is smooth)."""
        L = self.look.light
        step = 2 * HALF
        Wq, Hq = cam.size[0] // step, cam.size[1] // step
        nq = min(Hq, rows_half // 2 + 2)
        rn, re, rd = self._rays(cam, R, step, nq)
        norm = cv2.sqrt(rn * rn + re * re + rd * rd)
        sin_el = -rd / norm
        sx, sy, sz = L.sun_dir.tolist()
        cos_sun = (rn * sx + re * sy + rd * sz) / norm
        base = self._sky_colour(sin_el, cos_sun)
        # the sun's disc (0.8 deg: a little blooming) where it is not behind the clouds
        disc = np.float32(0.0)
        if L.sun_el_deg > -0.5 and L.direct > 0.1:
            disc = np.clip((cos_sun - np.float32(np.cos(np.radians(0.8)))) * np.float32(1e5),
                           0.0, 1.0)
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
        threshold = np.float32(175.0 - 110.0 * L.cloud_cover)
        cover = np.clip((cl - threshold) * np.float32(1 / 60.0), 0.0, 1.0)
        cover = cover * cv2.sqrt(cover) * np.maximum(fade, np.float32(L.cloud_cover))
        shading = 1.0 - 0.14 * np.clip((cl - 175.0) * np.float32(1 / 80.0), 0.0, 1.0)
        out = []
        for col, cc in zip(base, L.cloud_colour, strict=True):
            col = col + (np.float32(cc) * shading - col) * cover
            col = col + (np.float32(250.0) - col) * disc * (1.0 - cover)
            col = cv2.resize(col, (Wq * 2, nq * 2), interpolation=cv2.INTER_LINEAR)
            out.append(col[:rows_half])
        return out

    def _glare(self, cam: _CameraModel, R: np.ndarray, img: np.ndarray,
               zbuf: np.ndarray) -> None:
        """Veiling glare and bloom when the sun is in or near the picture and not hidden."""
        L = self.look.light
        if L.glare <= 0.0 or L.sun_el_deg < -0.5 or L.direct < 0.1:
            return
        s = R @ L.sun_dir
        if s[2] < 0.3:  # more than ~73 deg off the axis: the lens hood keeps it out
            return
        W, H = cam.size
        u = cam.K[0, 0] * s[0] / s[2] + cam.K[0, 2]
        v = cam.K[1, 1] * s[1] / s[2] + cam.K[1, 2]
        visible = 1.0
        if 0 <= u < W and 0 <= v < H:  # the sun in the picture: is it behind something?
            iu, iv = int(u), int(v)
            patch = zbuf[max(iv - 6, 0):iv + 7, max(iu - 6, 0):iu + 7]
            visible = float(np.mean(patch == 0.0))
        strength = L.glare * visible * float(np.clip((s[2] - 0.3) / 0.6, 0.0, 1.0))
        if strength < 0.02:
            return
        step = 8
        gx = (np.arange(W // step + 1, dtype=np.float32) * step - np.float32(u))
        gy = (np.arange(H // step + 1, dtype=np.float32) * step - np.float32(v))
        r = cv2.sqrt(gx[None, :] ** 2 + gy[:, None] ** 2) * np.float32(1.0 / W)
        bloom = np.float32(strength) * (160.0 * cv2.exp(-r * np.float32(1 / 0.04))
                                        + 45.0 * cv2.exp(-r * np.float32(1 / 0.25)) + 18.0)
        small = cv2.merge([cv2.convertScaleAbs(bloom, alpha=c) for c in L.sun_colour]
                          + [np.zeros(bloom.shape, np.uint8)])
        cv2.add(img, cv2.resize(small, (W, H), interpolation=cv2.INTER_LINEAR), dst=img)
