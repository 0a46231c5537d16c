"""Camera images of the synthetic world: per-pixel ray casting with a depth test, shading and texture.

Each pixel's ray (through the pixel centre, OpenCV pinhole, no distortion) meets the ground plane, the sky or
the nearest box whose surface is solid there (``synth_materials.surface`` alpha), so objects hide each other
and the ground. Each face of a box turned towards the camera is clipped to the near plane, projected and filled
with OpenCV to find its candidate pixels; their rays are then intersected exactly with the face's plane and
depth-tested, nearest box first, so the cost is about one ray-plane test per covered pixel. The ground pattern
is looked up in a pre-sampled raster of ``synth_materials.ground``. Shading is Lambertian per face under a sun
plus ambient light. The cameras are global-shutter and expose at the sample timestamp (the end of the LiDAR sweep),
so the rendered objects sit exactly at their annotated poses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from streamdet.calibration.camera import invert_transform
from streamdet.core.boxes import box_corners_3d
from streamdet.data.synth_materials import GROUND_PERIOD_M, ground, surface
from streamdet.data.synth_raycast import world_to_local
from streamdet.data.synth_world import NUM_ANNOTATED_KINDS, Scene

NEAR_M = 0.05
SKY_HORIZON = np.array([0.80, 0.85, 0.90], dtype=np.float32)
SKY_ZENITH = np.array([0.35, 0.55, 0.85], dtype=np.float32)
HAZE_DISTANCE_M = 350.0  # the ground fades into the horizon haze over this distance
AMBIENT = 0.45
SUN = 0.65


@dataclass(frozen=True, eq=False)
class CameraModel:
    """A camera mounted on the ego car: intrinsics at the render resolution and its pose in the ego frame."""

    name: str
    K: np.ndarray  # (3, 3) for (width, height)
    cam2ego: np.ndarray  # (4, 4)
    width: int
    height: int
    _cache: dict = field(default_factory=dict, repr=False)  # per-pixel rays and what depends on them only

    @property
    def origin_ego(self) -> np.ndarray:
        return self.cam2ego[:3, 3]

    @property
    def rays_ego(self) -> np.ndarray:
        """(H, W, 3) float32 unit ray directions through the pixel centres, in the ego frame."""
        if "rays" not in self._cache:
            u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)  # (H, W)
            pix = np.stack([u, v, np.ones_like(u)], axis=-1)  # (H, W, 3)
            rays = pix @ np.linalg.inv(self.K).T @ self.cam2ego[:3, :3].T
            self._cache["rays"] = (rays / np.linalg.norm(rays, axis=-1, keepdims=True)).astype(np.float32)
        return self._cache["rays"]

    def _background(self) -> tuple[np.ndarray, ...]:
        """Ground pixels (flat indices), their ego-frame ground points and distances, the haze blend
        (1 - haze, haze * horizon colour) and the sky colours of all pixels.

        The ego stays level on the ground plane, so where a pixel meets the ground in the ego frame never
        changes; only the texture under it moves.
        """
        if "background" not in self._cache:
            rays = self.rays_ego.reshape(-1, 3).astype(np.float64)  # (H * W, 3)
            down = rays[:, 2] < -1e-6
            t = np.where(down, -self.origin_ego[2] / np.where(down, rays[:, 2], -1.0), np.inf)
            g = np.flatnonzero(t < HAZE_DISTANCE_M * 4)
            up = np.clip(rays[:, 2], 0.0, 1.0)[:, None] ** 0.6
            sky = ((1 - up) * SKY_HORIZON + up * SKY_ZENITH).astype(np.float32)  # (H * W, 3)
            hit_xy = (self.origin_ego[:2] + t[g, None] * rays[g, :2]).astype(np.float32)  # (G, 2)
            haze = (np.minimum(t[g] / HAZE_DISTANCE_M, 1.0) ** 1.5).astype(np.float32)[:, None]  # (G, 1)
            self._cache["background"] = (g, hit_xy, t[g].astype(np.float32), 1 - haze, haze * SKY_HORIZON, sky)
        return self._cache["background"]

    def _noise(self) -> np.ndarray:
        """(H, W, 3) float32 sensor noise, drawn once per camera; frames use it rolled by a random offset."""
        if "noise" not in self._cache:
            rng = np.random.default_rng(0x5E7507)
            self._cache["noise"] = rng.normal(0.0, 0.012, size=(self.height, self.width, 3)).astype(np.float32)
        return self._cache["noise"]

    @classmethod
    def from_record(cls, name: str, sensor2ego: np.ndarray, K_native: np.ndarray, native_size: tuple[int, int],
                    size: tuple[int, int]) -> "CameraModel":
        """A camera at ``size`` (width, height) from its calibration at ``native_size``."""
        scale = np.diag([size[0] / native_size[0], size[1] / native_size[1], 1.0])
        return cls(name, scale @ np.asarray(K_native, dtype=np.float64), np.asarray(sensor2ego, dtype=np.float64), int(size[0]), int(size[1]))


@dataclass(frozen=True, eq=False)
class Render:
    image: np.ndarray  # (H, W, 3) uint8 RGB
    object_id: np.ndarray  # (H, W) int64 index into scene.objects of the visible surface, -1 for ground / sky
    own_pixels: np.ndarray  # (K,) int64 pixels each object would cover with nothing in front of it


def render_camera(scene: Scene, t_s: float, camera: CameraModel, rng: np.random.Generator | None = None) -> Render:
    """Render one camera at scene time ``t_s`` (the ego pose and the objects at that instant)."""
    h, w = camera.height, camera.width
    rays = camera.rays_ego  # (H, W, 3)
    origin = camera.origin_ego
    ego2global = scene.ego2global(t_s)
    rot2 = ego2global[:2, :2]
    sun_ego = ego2global[:3, :3].T @ scene.sun_dir_world

    # Ground and sky.
    g, ground_xy, t_ground, clear, haze_rgb, sky = camera._background()
    color = sky.copy()  # (H * W, 3)
    zbuf = np.full(h * w, np.inf, dtype=np.float32)
    zbuf[g] = t_ground
    # Road coordinates of the ground points (elementwise: tiny BLAS products are slow on a busy machine).
    wx = rot2[0, 0] * ground_xy[:, 0] + rot2[0, 1] * ground_xy[:, 1] + (ego2global[0, 3] - scene.road_origin_xy[0])
    wy = rot2[1, 0] * ground_xy[:, 0] + rot2[1, 1] * ground_xy[:, 1] + (ego2global[1, 3] - scene.road_origin_xy[1])
    (ux, uy), (nx, ny) = scene.road_u, scene.road_n
    albedo = ground_atlas(wx * ux + wy * uy, wx * nx + wy * ny)
    lum = np.float32(AMBIENT + SUN * max(sun_ego[2], 0.0))
    color[g] = albedo * (clear * lum) + haze_rgb
    color = color.reshape(h, w, 3)  # (H, W, 3)
    zbuf = zbuf.reshape(h, w)  # (H, W)
    object_id = np.full((h, w), -1, dtype=np.int64)

    # Objects, nearest first so most hidden pixels fail the depth test before they are shaded.
    objs = scene.objects
    own = np.zeros(len(objs), dtype=np.int64)
    boxes = objs.boxes_at(t_s)  # (K, 9) world
    centers = np.concatenate([(boxes[:, :2] - ego2global[:2, 3]) @ rot2, boxes[:, 2:3]], axis=1)  # (K, 3) ego
    yaws = boxes[:, 6] - np.arctan2(rot2[1, 0], rot2[0, 0])
    ego2cam = invert_transform(camera.cam2ego)
    rays_flat = rays.reshape(-1, 3)  # (H * W, 3)
    zflat, cflat, idflat = zbuf.reshape(-1), color.reshape(-1, 3), object_id.reshape(-1)  # flat views: (H * W,), (H * W, 3)
    order = np.argsort(np.linalg.norm(centers - origin, axis=1))
    order = order[_in_view(centers[order], objs.size_wlh[order], yaws[order], ego2cam, camera)]
    for k in order:
        half = objs.size_wlh[k, [1, 0, 2]] / 2  # along the box's x (l), y (w), z (h)
        o_local = world_to_local(origin, centers[k], yaws[k])
        c, s = float(np.cos(yaws[k])), float(np.sin(yaws[k]))
        parts = []
        for axis, sign, pix in _visible_faces(o_local, half, centers[k], yaws[k], ego2cam, camera):
            # Exact ray-plane intersection with the candidate face, then the face's extent.
            d = rays_flat[pix]  # (P, 3) float32, ego frame
            d_axis = (c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2])  # box frame components
            den = d_axis[axis]
            t = (sign * half[axis] - o_local[axis]) / np.where(np.abs(den) < 1e-9, np.float32(1e-9), den)
            b_ax, c_ax = (axis + 1) % 3, (axis + 2) % 3
            pb = o_local[b_ax] + t * d_axis[b_ax]
            pc = o_local[c_ax] + t * d_axis[c_ax]
            ok = (np.abs(pb) <= half[b_ax] + 1e-6) & (np.abs(pc) <= half[c_ax] + 1e-6) & (t > 0)
            if objs.kind[k] >= NUM_ANNOTATED_KINDS:
                ok &= t < zflat[pix]  # clutter: only what is in front matters, no visibility bookkeeping
            idx = np.flatnonzero(ok)
            if not len(idx):
                continue
            p_local = np.empty((len(idx), 3), dtype=np.float32)
            p_local[:, axis] = sign * half[axis]
            p_local[:, b_ax] = pb[idx]
            p_local[:, c_ax] = pc[idx]
            normal = np.zeros(3)
            normal[axis] = sign
            normal = np.array([c * normal[0] - s * normal[1], s * normal[0] + c * normal[1], normal[2]])
            lum = AMBIENT + SUN * max(float(normal @ sun_ego), 0.0) + 0.08 * normal[2]
            parts.append((axis, sign, pix[idx], t[idx], p_local, lum))
        if not parts:
            continue
        pix = np.concatenate([q[2] for q in parts])  # faces of a convex box never share a pixel
        t = np.concatenate([q[3] for q in parts])
        axis = np.concatenate([np.full(len(q[2]), q[0]) for q in parts])
        sign = np.concatenate([np.full(len(q[2]), q[1], dtype=np.float32) for q in parts])
        lum = np.concatenate([np.full(len(q[2]), q[5], dtype=np.float32) for q in parts])
        p_local = np.concatenate([q[4] for q in parts])
        albedo, alpha, _ = surface(int(objs.kind[k]), axis, sign, p_local, half, objs.color[k], objs.color2[k], objs.flag[k])
        if objs.kind[k] < NUM_ANNOTATED_KINDS:
            own[k] = int(alpha.sum())
        front = np.flatnonzero(alpha & (t < zflat[pix]))
        target = pix[front]
        zflat[target] = t[front]
        cflat[target] = albedo[front] * lum[front, None]
        idflat[target] = k

    if rng is not None:
        noise = camera._noise()
        shift = rng.integers(0, noise.shape[0])
        color += np.roll(noise, shift, axis=0)
    image = cv2.convertScaleAbs(color, alpha=255.0)  # saturating float -> uint8 in one pass
    return Render(image=image, object_id=object_id, own_pixels=own)


_ATLAS: dict = {}
ATLAS_TEXEL_M = 0.05
ATLAS_HALF_WIDTH_M = 40.0  # beyond: the edge texel (grass behind the buildings)


def ground_atlas(s: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(P, 3) float32 ground albedo by lookup in a pre-sampled, s-periodic raster of ``synth_materials.ground``."""
    if "albedo" not in _ATLAS:
        ss = (np.arange(round(GROUND_PERIOD_M / ATLAS_TEXEL_M)) + 0.5) * ATLAS_TEXEL_M
        dd = (np.arange(round(2 * ATLAS_HALF_WIDTH_M / ATLAS_TEXEL_M)) + 0.5) * ATLAS_TEXEL_M - ATLAS_HALF_WIDTH_M
        grid_s, grid_d = np.meshgrid(ss, dd, indexing="ij")  # (S, D)
        albedo, _ = ground(grid_s, grid_d)
        _ATLAS["albedo"] = albedo.reshape(-1, 3)  # (S * D, 3)
        _ATLAS["shape"] = grid_s.shape
    n_s, n_d = _ATLAS["shape"]
    i = (np.floor(np.asarray(s) * (1.0 / ATLAS_TEXEL_M)).astype(np.int64)) % n_s
    j = np.clip(np.floor((np.asarray(d) + ATLAS_HALF_WIDTH_M) * (1.0 / ATLAS_TEXEL_M)).astype(np.int64), 0, n_d - 1)
    return _ATLAS["albedo"][i * n_d + j]


def _in_view(centers: np.ndarray, size_wlh: np.ndarray, yaws: np.ndarray, ego2cam: np.ndarray, camera: CameraModel) -> np.ndarray:
    """(K,) bool: a box may show in the image (not wholly behind the camera or beside the image)."""
    boxes = np.concatenate([centers, size_wlh, yaws[:, None], np.zeros((len(yaws), 2))], axis=1)
    pts = box_corners_3d(boxes) @ ego2cam[:3, :3].T + ego2cam[:3, 3]  # (K, 8, 3) camera frame
    z = pts[..., 2]
    uv = (pts @ camera.K.T)[..., :2] / np.maximum(z, NEAR_M)[..., None]
    in_front = z.min(axis=1) > NEAR_M
    outside = (uv[..., 0].max(axis=1) < -1) | (uv[..., 0].min(axis=1) > camera.width + 1)
    outside |= (uv[..., 1].max(axis=1) < -1) | (uv[..., 1].min(axis=1) > camera.height + 1)
    return (z.max(axis=1) > NEAR_M) & ~(in_front & outside)


def _visible_faces(o_local, half, center, yaw, ego2cam, camera: CameraModel) -> list[tuple[int, int, np.ndarray]]:
    """(axis, sign, flat pixel indices) of the box faces turned towards the camera, as candidate pixels.

    Each face is clipped to the near plane, projected and filled with OpenCV (plus a one-pixel border so no
    pixel whose centre ray meets the face is missed); the caller intersects the rays exactly.
    """
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    to_cam = ego2cam[:3, :3] @ rot
    offset = ego2cam[:3, :3] @ center + ego2cam[:3, 3]
    out = []
    for axis in range(3):
        for sign in (1, -1):
            if sign * o_local[axis] <= half[axis]:
                continue  # back face
            b, c2 = (axis + 1) % 3, (axis + 2) % 3
            quad = np.zeros((4, 3))
            quad[:, axis] = sign * half[axis]
            quad[:, b] = np.array([1, -1, -1, 1]) * half[b]
            quad[:, c2] = np.array([1, 1, -1, -1]) * half[c2]
            poly = _clip_near(quad @ to_cam.T + offset)
            if len(poly) < 3:
                continue
            uv = (poly @ camera.K.T)[:, :2] / poly[:, 2:3] - 0.5  # pixel-centre coordinates
            u0 = max(int(np.floor(uv[:, 0].min())) - 1, 0)
            u1 = min(int(np.ceil(uv[:, 0].max())) + 2, camera.width)
            v0 = max(int(np.floor(uv[:, 1].min())) - 1, 0)
            v1 = min(int(np.ceil(uv[:, 1].max())) + 2, camera.height)
            if u0 >= u1 or v0 >= v1:
                continue
            mask = np.zeros((v1 - v0, u1 - u0), dtype=np.uint8)
            pts = np.round((uv - [u0, v0]) * _SUBPIXEL).astype(np.int32)
            pts = np.clip(pts, -(1 << 20), 1 << 20)  # keep OpenCV's fixed point in range for grazing faces
            cv2.fillConvexPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=_SHIFT)
            cv2.polylines(mask, [pts], True, 1, thickness=2, lineType=cv2.LINE_8, shift=_SHIFT)
            rows, cols = np.nonzero(mask)
            if len(rows):
                out.append((axis, sign, (rows + v0) * camera.width + cols + u0))
    return out


def _clip_near(poly: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (N, 3), camera frame, to z >= NEAR_M."""
    out = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        a_in, b_in = a[2] >= NEAR_M, b[2] >= NEAR_M
        if a_in:
            out.append(a)
        if a_in != b_in:
            f = (NEAR_M - a[2]) / (b[2] - a[2])
            out.append(a + f * (b - a))
    return np.array(out).reshape(-1, 3)  # (M, 3)


_SHIFT = 8
_SUBPIXEL = 1 << _SHIFT
