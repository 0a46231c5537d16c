"""Camera images of the synthetic world: per-pixel ray casting with a depth test, shading and texture.

Each pixel's ray (through the pixel centre, OpenCV pinhole, no distortion) meets the ground plane, the sky or
the nearest solid part (``synth_shapes``; leaves have gaps) of an object, so objects hide each other and the
ground. The candidate pixels of a part are the projected hull of its bounding box; their rays are then intersected
exactly with the part. The ground pattern is looked up in a pre-sampled raster of ``synth_materials.ground``.
Shading is Lambertian per pixel under a sun plus ambient light; objects cast shadows on the ground
(``shadow_raster``); each camera has its own exposure gain and white balance per frame (``Exposure``). The cameras
are global-shutter and render the world at the time they are given: the writer gives each the moment the LiDAR
crosses its optical axis (``synth_writer.camera_trigger_times_s``, world 6 on; until then the sample timestamp), so
a moving object sits where it is then, behind its annotated pose at the sweep's end, as on real nuScenes.
``Render.object_id`` is the per-pixel object the writer turns into masks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from streamdet.calibration.camera import invert_transform
from streamdet.core.boxes import box_corners_3d
from streamdet.data.synth_kinds import NUM_ANNOTATED_KINDS, Kind
from streamdet.data.synth_materials import ASPHALT, GROUND_PERIOD_M, Mat, cross_street, ground, shade
from streamdet.data.synth_raycast import ray_shape_entry
from streamdet.data.synth_render_raster import hull_span_pixels
from streamdet.data.synth_world import Scene

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

    def _shadow_texels(self, n_texels: int) -> np.ndarray:
        """(G,) int64: the flat index of the texel of an (n_texels, n_texels) ``shadow_raster`` under each ground
        pixel of ``_background``, -1 off the raster (the raster is in the ego frame, as the ground points are)."""
        key = ("shadow_texels", n_texels)
        if key not in self._cache:
            ground_xy = self._background()[1]
            ix = np.floor((ground_xy[:, 0] + SHADOW_HALF_M) / SHADOW_TEXEL_M).astype(np.int64)
            iy = np.floor((ground_xy[:, 1] + SHADOW_HALF_M) / SHADOW_TEXEL_M).astype(np.int64)
            inside = (ix >= 0) & (ix < n_texels) & (iy >= 0) & (iy < n_texels)
            self._cache[key] = np.where(inside, ix * n_texels + iy, -1)
        return self._cache[key]

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


@dataclass(frozen=True)
class Exposure:
    """A camera's exposure gain and white balance (per-channel gains) for one frame."""

    gain: float = 1.0
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)

    @classmethod
    def draw(cls, rng: np.random.Generator, gain_sigma: float = 0.18, wb_sigma: float = 0.05) -> "Exposure":
        """Log-normal gain and white balance: auto-exposure and auto-white-balance that differ per camera and frame."""
        return cls(float(np.exp(rng.normal(0.0, gain_sigma))), tuple(float(v) for v in np.exp(rng.normal(0.0, wb_sigma, 3))))


SHADOW_TEXEL_M = 0.1
SHADOW_HALF_M = 60.0  # shadows are drawn on the ground within this distance of the ego (BEV square)


def shadow_raster(scene: Scene, t_s: float) -> np.ndarray:
    """(S, S) uint8 ego-frame BEV raster of the ground in the shade of objects at time t (1: shaded).

    Every part's bounding box is projected along the sun onto the ground plane and filled; each camera takes the
    raster of its own exposure time. Objects and the ground's undulation are not shaded by other objects (ground
    shadows only).
    """
    n = int(round(2 * SHADOW_HALF_M / SHADOW_TEXEL_M))
    raster = np.zeros((n, n), dtype=np.uint8)
    ego2global = scene.ego2global(t_s)
    rot2 = ego2global[:2, :2]
    sun = ego2global[:3, :3].T @ scene.sun_dir_world  # (3,) ego frame
    if sun[2] <= 0.05:
        return raster
    objs = scene.objects
    centres, yaws, _ = objs.poses_at(t_s)
    ego_c = np.concatenate([(centres[:, :2] - ego2global[:2, 3]) @ rot2, centres[:, 2:3]], axis=1)  # (K, 3) ego
    ego_yaw = yaws - np.arctan2(rot2[1, 0], rot2[0, 0])
    reach = np.linalg.norm(ego_c[:, :2], axis=1) - 0.5 * np.hypot(objs.size_wlh[:, 0], objs.size_wlh[:, 1])
    near = np.flatnonzero((reach < SHADOW_HALF_M) & (objs.kind != Kind.CURB))
    if not len(near):
        return raster
    parts = objs.parts
    pair, part = parts.expand(near)
    k = near[pair]
    corners = _CORNERS[None] * parts.half[part][:, None, :]  # (R, 8, 3) part frame
    box = np.einsum("rij,rcj->rci", parts.rot[part], corners) + parts.center[part][:, None, :]  # (R, 8, 3) box frame
    c, s_ = np.cos(ego_yaw[k])[:, None], np.sin(ego_yaw[k])[:, None]
    x = c * box[..., 0] - s_ * box[..., 1] + ego_c[k, 0:1]
    y = s_ * box[..., 0] + c * box[..., 1] + ego_c[k, 1:2]
    z = box[..., 2] + ego_c[k, 2:3]
    gx = x - z * sun[0] / sun[2]
    gy = y - z * sun[1] / sun[2]
    pix = np.stack([(gx + SHADOW_HALF_M) / SHADOW_TEXEL_M, (gy + SHADOW_HALF_M) / SHADOW_TEXEL_M], axis=-1)  # (R, 8, 2)
    pix = np.round(pix * _SUBPIXEL).astype(np.int64)
    pix = np.clip(pix, -(1 << 28), 1 << 28).astype(np.int32)
    for poly in pix:
        hull = cv2.convexHull(poly)
        cv2.fillConvexPoly(raster, hull, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    return raster  # indexed [x, y]


_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)  # (8, 3)


def render_camera(scene: Scene, t_s: float, camera: CameraModel, rng: np.random.Generator | None = None,
                  shadows: np.ndarray | None = None, exposure: Exposure | None = None) -> Render:
    """Render one camera at scene time ``t_s`` (the ego pose and the objects at that instant).

    ``shadows``: the frame's ``shadow_raster`` (none drawn without it); ``exposure``: gain and white balance
    (drawn from ``rng`` when omitted and ``rng`` is given).
    """
    h, w = camera.height, camera.width
    rays = camera.rays_ego  # (H, W, 3)
    origin = camera.origin_ego
    ego2global = scene.ego2global(t_s)
    rot2 = ego2global[:2, :2]
    sun_ego = ego2global[:3, :3].T @ scene.sun_dir_world

    # Sky everywhere and the ground's depth; the ground is shaded after the objects, where none covers it.
    g, ground_xy, t_ground, clear, haze_rgb, sky = camera._background()
    color = sky.copy()  # (H * W, 3)
    zbuf = np.full(h * w, np.inf, dtype=np.float32)
    zbuf[g] = t_ground
    color = color.reshape(h, w, 3)  # (H, W, 3)
    zbuf = zbuf.reshape(h, w)  # (H, W)
    object_id = np.full((h, w), -1, dtype=np.int64)

    # Objects: every candidate (pixel, part) pair of the objects in view is intersected at once; each pixel keeps
    # its nearest solid part if that is nearer than the ground.
    objs = scene.objects
    parts = objs.parts
    own = np.zeros(len(objs), dtype=np.int64)  # (K,) pixels each annotated object covers by itself
    centres, yaws_w, _ = objs.poses_at(t_s)
    centers = np.concatenate([(centres[:, :2] - ego2global[:2, 3]) @ rot2, centres[:, 2:3]], axis=1)  # (K, 3) ego
    yaws = yaws_w - np.arctan2(rot2[1, 0], rot2[0, 0])
    ego2cam = invert_transform(camera.cam2ego)
    rays_flat = rays.reshape(-1, 3)  # (H * W, 3)
    zflat, cflat, idflat = zbuf.reshape(-1), color.reshape(-1, 3), object_id.reshape(-1)  # flat views: (H * W,), (H * W, 3)
    visible = np.flatnonzero(_in_view(centers, objs.size_wlh, yaws, ego2cam, camera))
    if len(visible):
        # Ego -> part frame per part: x_part = M (x_ego - c_box) - R_p^T c_p with M = R_p^T R_box^T.
        c, s = np.cos(yaws), np.sin(yaws)
        box_t = np.zeros((len(objs), 3, 3))
        box_t[:, 0, 0], box_t[:, 0, 1], box_t[:, 1, 0], box_t[:, 1, 1], box_t[:, 2, 2] = c, s, -s, c, 1.0
        _, all_parts = parts.expand(visible)
        m = np.zeros((len(parts.mat), 3, 3))
        o_cam = np.zeros((len(parts.mat), 3))
        m[all_parts] = np.einsum("pji,pjk->pik", parts.rot[all_parts], box_t[parts.owner[all_parts]])
        o_cam[all_parts] = np.einsum("pij,pj->pi", m[all_parts], origin - centers[parts.owner[all_parts]]) - np.einsum(
            "pji,pj->pi", parts.rot[all_parts], parts.center[all_parts])  # the camera in each part's frame
        # The nearest a part can be: the distance to its bounding box (exact for boxes, a lower bound otherwise).
        near_t = np.linalg.norm(np.maximum(np.abs(o_cam) - parts.half, 0.0), axis=1)
        m, o_cam = m.astype(np.float32), o_cam.astype(np.float32)
        # Nearest objects first, in a few groups: clutter behind what is already drawn is skipped unintersected.
        reach = np.linalg.norm(centers[visible] - origin, axis=1) - 0.5 * np.linalg.norm(objs.size_wlh[visible], axis=1)
        ordered = visible[np.argsort(reach)]
        # Large single-box scenery (buildings, walls, curbs) is drawn box by box afterwards, without sorting.
        scenery = np.isin(objs.kind[ordered], _SCENERY)
        small = ordered[~scenery]
        groups = np.array_split(small, min(3, len(small))) if len(small) else []
        # The candidate pixels of every small object's parts at once (grouped by part in this order), cut per group.
        part, pix = _part_pixels(small, centers, yaws, parts, ego2cam, camera)
        group_of = np.zeros(len(objs), dtype=np.int64)  # (K,)
        for i, group in enumerate(groups):
            group_of[group] = i
        cuts = np.searchsorted(group_of[parts.owner[part]], np.arange(len(groups) + 1))  # where each group's pairs start
        for i in range(len(groups)):
            _draw_parts(part[cuts[i] : cuts[i + 1]], pix[cuts[i] : cuts[i + 1]], objs, parts, m, o_cam, near_t, rays_flat,
                        zflat, cflat, idflat, own, sun_ego, h * w)
        # The scenery keeps the polygon fills: its rays go through a BLAS product whose last digits depend on the
        # batch of pixels around them, so the same candidates keep the same bytes (the parts' products do not).
        part, pix = _filled_part_pixels(ordered[scenery], centers, yaws, parts, ego2cam, camera)
        _draw_scenery(part, pix, parts, m, o_cam, near_t, rays_flat, zflat, cflat, idflat, sun_ego)

    seen = np.flatnonzero(idflat[g] < 0)  # ground pixels no object covers
    texels = None if shadows is None else camera._shadow_texels(shadows.shape[0])[seen]
    _shade_ground(scene, ego2global, sun_ego, shadows, texels, _rows(ground_xy, seen), _rows(clear, seen),
                  _rows(haze_rgb, seen), g[seen], cflat)

    if exposure is None and rng is not None:
        exposure = Exposure.draw(rng)
    if exposure is not None:
        gains = np.float32(exposure.gain) * np.asarray(exposure.white_balance, dtype=np.float32)  # (3,)
        for c in range(3):  # channel by channel: the same products, without numpy's slow length-3 inner loop
            color[..., c] *= gains[c]
    if rng is not None:
        noise = camera._noise()
        shift = rng.integers(0, noise.shape[0])
        color[shift:] += noise[: h - shift]  # the noise rolled down by shift rows
        color[:shift] += noise[h - shift :]
    image = cv2.convertScaleAbs(color, alpha=255.0)  # saturating float -> uint8 in one pass
    return Render(image=image, object_id=object_id, own_pixels=own)


def _shade_ground(scene: Scene, ego2global: np.ndarray, sun_ego: np.ndarray, shadows: np.ndarray | None,
                  texels: np.ndarray | None, ground_xy: np.ndarray, clear: np.ndarray, haze_rgb: np.ndarray, pix: np.ndarray,
                  cflat: np.ndarray) -> None:
    """Colour the ground pixels ``pix`` (flat) from their ego-frame ground points (G, 2), their texels of the
    ``shadows`` raster (G,) (``CameraModel._shadow_texels``) and haze blend (``clear`` (G, 1), ``haze_rgb`` (G, 3)):
    the ground pattern, the cross street, the sun unless in an object's shadow."""
    rot2 = ego2global[:2, :2]
    # Road coordinates of the ground points (elementwise: tiny BLAS products are slow on a busy machine).
    wx = rot2[0, 0] * ground_xy[:, 0] + rot2[0, 1] * ground_xy[:, 1] + (ego2global[0, 3] - scene.road_origin_xy[0])
    wy = rot2[1, 0] * ground_xy[:, 0] + rot2[1, 1] * ground_xy[:, 1] + (ego2global[1, 3] - scene.road_origin_xy[1])
    (ux, uy), (nx, ny) = scene.road_u, scene.road_n
    s_road, d_road = wx * ux + wy * uy, wx * nx + wy * ny
    albedo = ground_atlas(s_road, d_road)
    if scene.cross_s_m is not None:
        cross = cross_street(s_road, d_road, scene.cross_s_m)
        albedo[cross] = ASPHALT * 0.95
    sun_lum = np.float32(SUN * max(sun_ego[2], 0.0))
    lum = np.full(len(pix), np.float32(AMBIENT) + sun_lum, dtype=np.float32)
    if shadows is not None:
        on = np.flatnonzero(texels >= 0)
        shaded = np.zeros(len(pix), dtype=bool)
        shaded[on] = np.take(shadows.reshape(-1), texels[on]) > 0
        lum[shaded] = AMBIENT
    _put_rows(cflat, pix, _scaled_rows(albedo, (clear * lum[:, None])[:, 0], haze_rgb))


_SCENERY = np.array([Kind.BUILDING, Kind.WALL, Kind.CURB])  # unannotated, one box part each


def _draw_scenery(part, pix, parts, m, o_cam, near_t, rays_flat, zflat, cflat, idflat, sun_ego) -> None:
    """Draw single-box scenery from its candidate (part, flat pixel) pairs, grouped by part (``_part_pixels``):
    each pixel shows the nearest box in front of what is drawn, ties going to the box first in the pairs (as
    drawing them one by one in that order with a strict depth test would).

    The boxes are visited nearest first (by their distance from the camera), so a pixel already covered by a
    nearer box skips the boxes behind it unintersected; the order of the pairs only breaks exact depth ties.
    """
    if not len(part):
        return
    bounds = np.flatnonzero(np.r_[True, part[1:] != part[:-1], True])  # run starts, then the end
    starts, ends = bounds[:-1], bounds[1:]
    rank = np.full(len(zflat), -1, dtype=np.int64)  # per pixel: the run drawn there (-1: not scenery, wins ties)
    for run in np.argsort(near_t[part[starts]], kind="stable"):
        a, b = starts[run], ends[run]
        p = int(part[a])
        px = pix[a:b]
        px = px[near_t[p] <= zflat[px]]
        if not len(px):
            continue
        d = _rows(rays_flat, px) @ m[p].T  # (R, 3) part frame
        t, entries, d_safe = _box_entry(o_cam[p], d, parts.half[p].astype(np.float32))
        z = zflat[px]
        front = np.flatnonzero((t < z) | ((t == z) & (rank[px] > run)))
        if not len(front):
            continue
        axis, sign = _box_entry_face(entries, d_safe)
        px, t, axis, sign = px[front], t[front], axis[front], sign[front]
        n_part = np.zeros((len(px), 3))
        n_part[np.arange(len(px)), axis] = sign
        p_part = _scaled_rows(_rows(d, front), t, o_cam[p])  # the hit points: o + t d
        albedo, _, _, _, _ = shade(np.full(len(px), parts.mat[p]), np.broadcast_to(parts.albedo[p], (len(px), 3)),
                                   np.full(len(px), parts.refl[p]), p_part, np.broadcast_to(parts.half[p], (len(px), 3)), n_part)
        n_ego = n_part @ m[p].astype(np.float64)  # M^T n for row vectors
        lum = AMBIENT + SUN * np.maximum(n_ego @ sun_ego, 0.0) + 0.08 * n_ego[:, 2]
        zflat[px] = t
        rank[px] = run
        _put_rows(cflat, px, _scaled_rows(albedo, lum.astype(np.float32)))
        idflat[px] = parts.owner[p]


def _draw_parts(part, pix, objs, parts, m, o_cam, near_t, rays_flat, zflat, cflat, idflat, own, sun_ego, n_pix) -> None:
    """Intersect the candidate (part, flat pixel) pairs (R,), (R,) of a group of objects (``_part_pixels``) and
    draw each pixel's nearest solid part where it is nearer than what is drawn (updates the flat depth, colour,
    id buffers and ``own`` in place)."""
    if not len(part):
        return
    k = parts.owner[part]
    # Unannotated objects need no visibility bookkeeping: skip pairs already hidden by what is drawn.
    ann = objs.kind[k] < NUM_ANNOTATED_KINDS
    keep = np.flatnonzero(ann | (near_t[part] < zflat[pix]))
    part, pix, k, ann = part[keep], pix[keep], k[keep], ann[keep]
    d_part = np.einsum("rij,rj->ri", _rows(m, part), _rows(rays_flat, pix))  # (R, 3) float32
    o_part = _rows(o_cam, part)
    t, _ = ray_shape_entry(o_part, d_part, _rows(parts.half, part).astype(np.float32), parts.shape[part], with_normal=False)
    ok = np.isfinite(t)
    foliage = ok & (parts.mat[part] == Mat.FOLIAGE)
    if np.any(foliage):  # leaves have gaps: only foliage needs its alpha before the depth test
        idx = np.flatnonzero(foliage)
        p = _rows(o_part, idx) + t[idx, None] * _rows(d_part, idx)
        _, alpha, _, _, _ = shade(parts.mat[part[idx]], _rows(parts.albedo, part[idx]), parts.refl[part[idx]], p,
                                  _rows(parts.half, part[idx]), np.zeros_like(p))  # (a leaf's gaps do not depend on the normal)
        ok[idx[~alpha]] = False
    ok = np.flatnonzero(ok)
    part, pix, t, k, ann, o_part, d_part = (_rows(v, ok) for v in (part, pix, t, k, ann, o_part, d_part))
    if np.any(ann):  # pixels each annotated object covers by itself (its own parts may hide each other)
        key = np.sort(k[ann] * n_pix + pix[ann], kind="stable")  # (runs of sorted pixels per part: a fast merge)
        key = key[np.r_[True, key[1:] != key[:-1]]]  # np.unique's values
        own += np.bincount(key // n_pix, minlength=len(own))
    # Nearest part per pixel, if nearer than what is drawn.
    srt = _pixel_depth_order(pix, t)
    first = srt[np.r_[True, pix[srt][1:] != pix[srt][:-1]]] if len(srt) else srt
    first = first[t[first] < zflat[pix[first]]]
    part, pix, t, k, o_part, d_part = (_rows(v, first) for v in (part, pix, t, k, o_part, d_part))
    half = _rows(parts.half, part)
    _, n_part = ray_shape_entry(o_part.astype(np.float64), d_part.astype(np.float64), half, parts.shape[part])
    p_part = _scaled_rows(d_part, t, o_part)
    albedo, _, _, _, _ = shade(parts.mat[part], _rows(parts.albedo, part), parts.refl[part], p_part, half, n_part)
    # Shade with the part normal in the ego frame: n_ego = M^T n_part.
    n_ego = np.einsum("rji,rj->ri", _rows(m, part).astype(np.float64), n_part)
    lum = AMBIENT + SUN * np.maximum(n_ego @ sun_ego, 0.0) + 0.08 * n_ego[:, 2]
    zflat[pix] = t
    _put_rows(cflat, pix, _scaled_rows(albedo, lum.astype(np.float32)))
    idflat[pix] = k


def _pixel_depth_order(pix: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The permutation of ``np.lexsort((t, pix))`` (by pixel, then depth, stable) for hit depths t > 0.

    Positive float32 depths order as their bit patterns, so pixel and depth pack into one int64 key and one stable
    sort; the pairs come in runs of sorted pixels (part by part), which a merge sort takes quickly.
    """
    if t.dtype != np.float32 or not len(t):
        return np.lexsort((t, pix))
    key = (pix.astype(np.int64) << 32) | t.view(np.int32).astype(np.int64)  # (R,)
    return np.argsort(key, kind="stable")


def _box_entry(o: np.ndarray, d: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``ray_box_entry`` for rays d (R, 3) from one origin o (3,) into one box of half extents (3,), same dtype:
    the same entry distances t (R,) (inf where missed), with the slab entries (R, 3) and the guarded directions
    (R, 3) that ``_box_entry_face`` turns into the entered face of the rays wanted (the same values, in fewer
    passes: the slab planes are computed once, the face only where needed)."""
    d_safe = np.where(np.abs(d) < _RAY_EPS, _RAY_EPS, d)
    inv = 1.0 / d_safe
    lo, hi = -half - o, half - o  # (3,) the slab planes relative to the origin
    t_near = np.empty_like(inv)  # (R, 3)
    t_exit = np.empty_like(inv)
    for c in range(3):  # column by column (numpy broadcasts a (3,) row over (R, 3) several times slower)
        t1, t2 = lo[c] * inv[:, c], hi[c] * inv[:, c]
        np.minimum(t1, t2, out=t_near[:, c])
        np.maximum(t1, t2, out=t_exit[:, c])
    t_far = np.minimum(np.minimum(t_exit[:, 0], t_exit[:, 1]), t_exit[:, 2])
    t_in = np.maximum(np.maximum(t_near[:, 0], t_near[:, 1]), t_near[:, 2])
    hit = (t_in <= t_far) & (t_in > 0.0)
    return np.where(hit, t_in, np.inf), t_near, d_safe


def _box_entry_face(t_near: np.ndarray, d_safe: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``ray_box_entry``'s axis (R,) int64 and sign (R,) of the entered face from ``_box_entry``'s slab entries
    and guarded directions (column by column: no gathers of rows)."""
    n0, n1, n2 = t_near[:, 0], t_near[:, 1], t_near[:, 2]
    last2, last1 = n2 > np.maximum(n0, n1), n1 > n0  # the last slab entered is the face crossed (first on ties)
    axis = np.where(last2, 2, np.where(last1, 1, 0))
    return axis, -np.sign(np.where(last2, d_safe[:, 2], np.where(last1, d_safe[:, 1], d_safe[:, 0])))


_RAY_EPS = 1e-12  # synth_raycast's guard for direction components near 0


def _scaled_rows(rows: np.ndarray, scale: np.ndarray, offset: np.ndarray | None = None) -> np.ndarray:
    """``rows * scale[:, None] (+ offset)`` for rows (R, 3), scale (R,) and offset (3,) or (R, 3): the same values,
    column by column (numpy broadcasts over a length-3 last axis several times slower)."""
    operands = (rows, scale) if offset is None else (rows, scale, offset)
    out = np.empty(rows.shape, dtype=np.result_type(*operands))
    for c in range(rows.shape[1]):
        np.multiply(rows[:, c], scale, out=out[:, c])
        if offset is not None:
            out[:, c] += offset[..., c]
    return out


def _rows(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``a[index]`` for an integer index array along the first axis (np.take: the same values, several times faster
    than fancy indexing when the rows are a few values wide)."""
    return np.take(a, index, axis=0)


def _put_rows(buf: np.ndarray, index: np.ndarray, rows: np.ndarray) -> None:
    """``buf[index] = rows`` for a C-contiguous (N, C) buffer and distinct indices: each row put as one C-value
    item (the same bytes, several times faster than fancy assignment of rows)."""
    item = np.dtype((np.void, buf.dtype.itemsize * buf.shape[1]))
    np.put(buf.view(item).reshape(-1), index, np.ascontiguousarray(rows, dtype=buf.dtype).view(item).reshape(-1))


def _part_pixels(order: np.ndarray, centers: np.ndarray, yaws: np.ndarray, parts, ego2cam: np.ndarray,
                 camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """(part, flat pixel) candidate pairs of every part of the objects ``order``, grouped by part in order, each
    part's pixels row-major: the pixels whose centres lie in the projected hull of the part's bounding box (plus
    a margin). The caller intersects each candidate pixel's ray with the part exactly.

    The corners of all parts are projected at once; the parts wholly in front of the near plane get their hull's
    row spans all at once (``hull_span_pixels``); a part whose box reaches behind the near plane is clipped face by
    face and filled (``_clipped_part_pixels``) unless it lies wholly beside the image. The candidates differ from
    ``_filled_part_pixels``' by pixels no ray of the part meets, so the drawing is the same where every pair is
    computed on its own (``_draw_parts``: einsum and elementwise work, whatever the batch).
    """
    if not len(order):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    cam = _part_corners_cam(order, centers, yaws, parts, ego2cam)  # (R, 8, 3)
    _, part = parts.expand(order)
    z = cam[..., 2]
    behind = z.min(axis=1) < NEAR_M
    gone = z.max(axis=1) < NEAR_M
    hom = cam @ camera.K.T  # (R, 8, 3) homogeneous pixel coordinates (u z, v z, z)
    width, height = camera.width, camera.height
    beside = _beside_image(hom, camera)
    front = np.flatnonzero(~behind & ~beside)
    uv = hom[front, :, :2] / z[front][..., None] - 0.5  # (F, 8, 2) pixel-centre coordinates
    # A part reaching far beyond the image keeps its polygon fill with the corners clamped to OpenCV's fixed-point
    # range, as before this fast path (the clamp distorts its hull: a few of its pixels go undrawn, see
    # _clamped_hull_pixels); the rest get their hull's row spans.
    lo = np.maximum(np.floor(uv.min(axis=1)) - 1, 0.0)  # (F, 2) u0, v0
    wide = np.any(np.abs(uv - lo[:, None, :]) > _FIXED_LIMIT_PX, axis=(1, 2))
    idx, pix = hull_span_pixels(uv[~wide], width, height, _HULL_MARGIN_PX)
    idx = front[~wide][idx]
    extra = [(r, _clamped_hull_pixels(uv[i], camera)) for i, r in zip(np.flatnonzero(wide).tolist(), front[wide].tolist())]
    extra += [(r, _clipped_part_pixels(cam[r], camera)) for r in np.flatnonzero(behind & ~gone & ~beside).tolist()]
    extra = [(r, px) for r, px in extra if len(px)]
    if extra:  # merge in part order (the depth test breaks exact ties by this order)
        idx = np.concatenate([idx] + [np.full(len(px), r, dtype=np.int64) for r, px in extra])
        pix = np.concatenate([pix] + [px for _, px in extra])
        srt = np.argsort(idx, kind="stable")
        idx, pix = idx[srt], pix[srt]
    return part[idx], pix


_FIXED_LIMIT_PX = (1 << 20) / (1 << 8)  # OpenCV fixed-point coordinates are clamped to +-2^20 at shift 8
_HULL_MARGIN_PX = 0.25  # candidates reach this far beyond the projected hull: far more than float32 rays stray
_BESIDE_PX = 3.0  # a part's corners this far beside the image leave no candidate pixel (the fill adds 1-2 px)


def _filled_part_pixels(order: np.ndarray, centers: np.ndarray, yaws: np.ndarray, parts, ego2cam: np.ndarray,
                        camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """``_part_pixels``' pairs from a polygon fill per part: the projected hull of its bounding box filled with
    OpenCV (with its outline: about a pixel of margin; corners clamped to OpenCV's fixed-point range), clipped to
    the near plane face by face where the box reaches behind it. A Python loop over the parts: slow for many."""
    if not len(order):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    _, part = parts.expand(order)
    cam = _part_corners_cam(order, centers, yaws, parts, ego2cam)  # (R, 8, 3)
    z = cam[..., 2]
    hom = cam @ camera.K.T  # (R, 8, 3)
    uv = hom[..., :2] / np.maximum(z, NEAR_M)[..., None] - 0.5  # (R, 8, 2) pixel-centre coordinates
    out_part, out_pix = [], []
    for r in np.flatnonzero((z.max(axis=1) >= NEAR_M) & ~_beside_image(hom, camera)).tolist():
        px = _clipped_part_pixels(cam[r], camera) if z[r].min() < NEAR_M else _filled_hull_pixels(uv[r], camera)
        out_part.append(np.full(len(px), part[r], dtype=np.int64))
        out_pix.append(px)
    if not out_part:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    return np.concatenate(out_part), np.concatenate(out_pix)


def _beside_image(hom: np.ndarray, camera: CameraModel) -> np.ndarray:
    """(R,) bool: boxes (R, 8, 3 homogeneous pixel coordinates (u z, v z, z) of their corners) wholly beside the
    image by more than any candidate margin: every corner outside one side plane of the frustum, a convex set, so
    the faces clipped to the near plane are outside it too and no pixel of the image can see the box."""
    z = hom[..., 2]
    m = _BESIDE_PX + 0.5
    beside = np.all(hom[..., 0] < -m * z, axis=1) | np.all(hom[..., 0] > (camera.width - 1 + m) * z, axis=1)
    return beside | np.all(hom[..., 1] < -m * z, axis=1) | np.all(hom[..., 1] > (camera.height - 1 + m) * z, axis=1)


def _part_corners_cam(order: np.ndarray, centers: np.ndarray, yaws: np.ndarray, parts, ego2cam: np.ndarray) -> np.ndarray:
    """(R, 8, 3) the bounding-box corners of every part of the objects ``order`` in the camera frame."""
    pair, part = parts.expand(order)
    k = order[pair]
    corners = _CORNERS[None] * parts.half[part][:, None, :]  # (R, 8, 3) part frame
    box = np.einsum("rij,rcj->rci", parts.rot[part], corners) + parts.center[part][:, None, :]  # (R, 8, 3) box frame
    c, s = np.cos(yaws[k])[:, None], np.sin(yaws[k])[:, None]
    ego = np.stack([c * box[..., 0] - s * box[..., 1], s * box[..., 0] + c * box[..., 1], box[..., 2]], axis=-1) + centers[k][:, None, :]
    return ego @ ego2cam[:3, :3].T + ego2cam[:3, 3]  # (R, 8, 3)


def _clipped_part_pixels(cam: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Flat pixels of a box (8, 3 camera-frame corners) that reaches behind the near plane: its faces clipped to
    z >= NEAR_M, projected, and the hull of them filled with its outline (a pixel of margin)."""
    polys = [_clip_near(cam[list(face)]) for face in _FACES]
    pts = np.concatenate([p for p in polys if len(p)]) if any(len(p) for p in polys) else np.zeros((0, 3))
    if len(pts) < 3:
        return np.zeros(0, dtype=np.int64)
    return _filled_hull_pixels((pts @ camera.K.T)[:, :2] / pts[:, 2:3] - 0.5, camera)


def _clamped_hull_pixels(uv: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Flat pixels of the filled hull (with its outline) of a part's projected corners (8, 2), in OpenCV's fixed
    point relative to the clipped bounding rectangle, clamped to its range.

    The clamp moves corners far beyond the image (a part reaching close to the camera plane) and so tilts the
    hull's edges: a few pixels whose rays meet the part are left out. The renderer keeps this for such parts so
    its output stays the same bytes as before the row-span fast path (``hull_span_pixels``).
    """
    return _filled_hull_pixels(uv, camera)


def _filled_hull_pixels(q: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Flat pixels of the filled hull (with its outline: about a pixel of margin) of points q (N, 2) in pixel-centre
    coordinates, drawn in OpenCV's fixed point within their bounding rectangle clipped to the image."""
    width, height = camera.width, camera.height
    u0 = max(int(np.floor(q[:, 0].min())) - 1, 0)
    u1 = min(int(np.ceil(q[:, 0].max())) + 2, width)
    v0 = max(int(np.floor(q[:, 1].min())) - 1, 0)
    v1 = min(int(np.ceil(q[:, 1].max())) + 2, height)
    if u0 >= u1 or v0 >= v1:
        return np.zeros(0, dtype=np.int64)
    pts2 = np.round((q - [u0, v0]) * _SUBPIXEL).astype(np.int64)
    pts2 = np.clip(pts2, -(1 << 20), 1 << 20).astype(np.int32)
    mask = np.zeros((v1 - v0, u1 - u0), dtype=np.uint8)
    hull = cv2.convexHull(pts2)
    cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    cv2.polylines(mask, [hull], True, 1, thickness=1, lineType=cv2.LINE_8, shift=_SHIFT)
    points = cv2.findNonZero(mask)  # (N, 1, 2) x, y row by row, as np.nonzero orders them (3x faster); None if empty
    if points is None:
        return np.zeros(0, dtype=np.int64)
    points = points.reshape(-1, 2).astype(np.int64)
    return (points[:, 1] + v0) * width + points[:, 0] + u0


# The six faces of a box as corner indices of _CORNERS (x-, x+, y-, y+, z-, z+), each a closed loop.
_FACES = ((0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5))


_ATLAS: dict = {}
ATLAS_TEXEL_M = 0.05
ATLAS_HALF_WIDTH_M = 40.0  # beyond: the edge texel (grass behind the buildings)
_ATLAS_ROWS = 24  # atlas rows (along the road) sampled per call of ``ground``


def ground_atlas(s: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(P, 3) float32 ground albedo by lookup in a pre-sampled, s-periodic raster of ``synth_materials.ground``."""
    if "albedo" not in _ATLAS:
        ss = (np.arange(round(GROUND_PERIOD_M / ATLAS_TEXEL_M)) + 0.5) * ATLAS_TEXEL_M
        dd = (np.arange(round(2 * ATLAS_HALF_WIDTH_M / ATLAS_TEXEL_M)) + 0.5) * ATLAS_TEXEL_M - ATLAS_HALF_WIDTH_M
        grid_s, grid_d = np.meshgrid(ss, dd, indexing="ij")  # (S, D)
        albedo = np.empty(grid_s.shape + (3,), dtype=np.float32)  # (S, D, 3)
        for i in range(0, len(ss), _ATLAS_ROWS):  # a few rows at a time: ``ground`` works texel by texel, in cache
            albedo[i : i + _ATLAS_ROWS] = ground(grid_s[i : i + _ATLAS_ROWS], grid_d[i : i + _ATLAS_ROWS])[0]
        _ATLAS["albedo"] = albedo.reshape(-1, 3)  # (S * D, 3)
        _ATLAS["shape"] = grid_s.shape
    n_s, n_d = _ATLAS["shape"]
    # The texel indices stay integer-valued floats until the end (the same values as integer floor-mod and clip,
    # without numpy's slow int64 modulo).
    i = np.mod(np.floor(np.asarray(s) * (1.0 / ATLAS_TEXEL_M)), float(n_s))
    j = np.clip(np.floor((np.asarray(d) + ATLAS_HALF_WIDTH_M) * (1.0 / ATLAS_TEXEL_M)), 0.0, n_d - 1.0)
    return np.take(_ATLAS["albedo"], (i * n_d + j).astype(np.int64), axis=0)


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
