"""The synthetic world's fast paths give the same bytes as their plain formulations (generation speed, issue 18)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import streamdet.data.synth_raycast as synth_raycast
import streamdet.data.synth_render as synth_render
from streamdet.data.synth_materials import ground, ground_reflectance, shade
from streamdet.data.synth_raycast import _row_sum, ray_box_entry
from streamdet.data.synth_render_raster import hull_span_pixels
from streamdet.data.synth_world import WorldConfig, make_scene
from streamdet.data.synth_writer import real_rig_records


def _naive_ray_box_entry(o, d, half):
    """The slab test with numpy's reductions over the slab axis (the plain formulation)."""
    d_safe = np.where(np.abs(d) < 1e-12, 1e-12, d)
    inv = 1.0 / d_safe
    t1 = (-half - o) * inv
    t2 = (half - o) * inv
    t_near = np.minimum(t1, t2)
    t_far = np.maximum(t1, t2).min(axis=1)
    axis = np.argmax(t_near, axis=1)
    t_near = t_near.max(axis=1)
    hit = (t_near <= t_far) & (t_near > 0.0)
    sign = -np.sign(d_safe[np.arange(len(axis)), axis])
    return hit, np.where(hit, t_near, np.inf), axis, sign


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_ray_box_entry_equals_axis_reductions(seed, dtype):
    rng = np.random.default_rng(seed)
    n = 3000
    o = rng.normal(0.0, 5.0, size=(n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    half = rng.uniform(0.1, 3.0, size=(n, 3))
    d[rng.uniform(size=(n, 3)) < 0.05] = 0.0  # rays parallel to a slab
    on_face = rng.uniform(size=(n, 3)) < 0.05
    o[on_face] = half[on_face]  # origins on a slab plane
    d[:100] = (0.6, 0.6, np.sqrt(1 - 0.72))  # aimed at a corner: slabs entered at the same t (first axis wins)
    o[:100] = -5.0 * d[:100]
    half[:100] = 1.0
    o, d, half = o.astype(dtype), d.astype(dtype), half.astype(dtype)
    for got, ref in zip(ray_box_entry(o, d, half), _naive_ray_box_entry(o, d, half)):
        assert got.dtype == ref.dtype
        np.testing.assert_array_equal(got, ref)
    single = ray_box_entry(np.broadcast_to(o[0], o.shape), d, half[0])  # one origin and box for all rays
    for got, ref in zip(single, _naive_ray_box_entry(np.broadcast_to(o[0], o.shape), d, half[0])):
        np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("columns", [2, 3])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_row_sum_equals_numpy_sum(columns, dtype):
    rng = np.random.default_rng(columns)
    x = (rng.normal(size=(5000, columns)) * rng.lognormal(0.0, 3.0, size=(5000, columns))).astype(dtype)
    got = _row_sum(x)
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, x.sum(axis=1))
    np.testing.assert_array_equal(np.sqrt(_row_sum(x * x)), np.linalg.norm(x, axis=1))


@pytest.mark.parametrize("cross_s", [None, 12.3])
def test_ground_reflectance_equals_grounds(cross_s):
    rng = np.random.default_rng(0)
    s, d = rng.uniform(-100.0, 100.0, 20000), rng.uniform(-40.0, 40.0, 20000)
    got = ground_reflectance(s, d, cross_s)
    ref = ground(s, d, cross_s)[1]
    assert got.dtype == ref.dtype
    np.testing.assert_array_equal(got, ref)
    assert ground_reflectance(np.zeros(0), np.zeros(0), cross_s).shape == (0,)


def _sequential_scenery(part, pix, parts, m, o_cam, near_t, rays_flat, zflat, cflat, idflat, sun_ego) -> None:
    """Single-box scenery drawn box by box in the given order with a strict depth test (the plain formulation)."""
    if not len(part):
        return
    bounds = np.flatnonzero(np.r_[True, part[1:] != part[:-1], True])
    for a, b in zip(bounds[:-1], bounds[1:]):
        p = int(part[a])
        px = pix[a:b]
        px = px[near_t[p] < zflat[px]]
        if not len(px):
            continue
        d = rays_flat[px] @ m[p].T
        _, t, axis, sign = ray_box_entry(np.broadcast_to(o_cam[p], d.shape), d, parts.half[p].astype(np.float32))
        front = np.flatnonzero(t < zflat[px])
        if not len(front):
            continue
        px, t, axis, sign = px[front], t[front], axis[front], sign[front]
        n_part = np.zeros((len(px), 3))
        n_part[np.arange(len(px)), axis] = sign
        p_part = o_cam[p] + t[:, None] * d[front]
        albedo, _, _, _, _ = shade(np.full(len(px), parts.mat[p]), np.broadcast_to(parts.albedo[p], (len(px), 3)),
                                   np.full(len(px), parts.refl[p]), p_part, np.broadcast_to(parts.half[p], (len(px), 3)), n_part)
        n_ego = n_part @ m[p].astype(np.float64)
        lum = synth_render.AMBIENT + synth_render.SUN * np.maximum(n_ego @ sun_ego, 0.0) + 0.08 * n_ego[:, 2]
        zflat[px] = t
        cflat[px] = albedo * lum[:, None].astype(np.float32)
        idflat[px] = parts.owner[p]


def _assert_renders_equal_with(index, monkeypatch, name, plain_impl):
    """Every camera of one sample renders the same image, ids and own-pixel counts with ``synth_render.<name>``
    replaced by its plain version."""
    scene = make_scene(11, index, WorldConfig(samples_per_scene=2))
    rig = real_rig_records((160, 90))
    t_s = float(scene.sample_times_s[1])
    shadows = synth_render.shadow_raster(scene, t_s)
    fast = [synth_render.render_camera(scene, t_s, cam, np.random.default_rng(0), shadows=shadows) for cam in rig.models]
    monkeypatch.setattr(synth_render, name, plain_impl)
    plain = [synth_render.render_camera(scene, t_s, cam, np.random.default_rng(0), shadows=shadows) for cam in rig.models]
    for a, b in zip(fast, plain):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.object_id, b.object_id)
        np.testing.assert_array_equal(a.own_pixels, b.own_pixels)


@pytest.mark.parametrize("index", [0, 3])
def test_scenery_nearest_first_equals_sequential_drawing(index, monkeypatch):
    _assert_renders_equal_with(index, monkeypatch, "_draw_scenery", _sequential_scenery)


@pytest.mark.parametrize("index", [0, 1, 3])
def test_part_pixel_spans_render_as_polygon_fills(index, monkeypatch):
    """The row-span candidates draw the same images, ids and own-pixel counts as filling each hull with OpenCV."""
    _assert_renders_equal_with(index, monkeypatch, "_part_pixels", synth_render._filled_part_pixels)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hull_span_pixels_hold_the_hull_and_little_else(seed):
    rng = np.random.default_rng(seed)
    width, height, margin = 64, 48, 0.25
    n = 40
    # Boxes of random size, pose and distance in front of a pinhole camera (the hull of a projected box is bounded
    # by its projected edges, which the spans rely on).
    rot, _ = np.linalg.qr(rng.normal(size=(n, 3, 3)))  # (n, 3, 3)
    half = rng.uniform(0.05, 3.0, size=(n, 1, 3))
    centre = np.stack([rng.uniform(-6, 6, n), rng.uniform(-5, 5, n), rng.uniform(4.0, 30.0, n)], axis=1)[:, None]
    cam = np.einsum("nij,ncj->nci", rot, synth_render._CORNERS[None] * half) + centre  # (n, 8, 3)
    k = np.array([[40.0, 0.0, width / 2], [0.0, 40.0, height / 2], [0.0, 0.0, 1.0]])
    uv = (cam @ k.T)[..., :2] / cam[..., 2:3] - 0.5  # (n, 8, 2)
    uv[0] = [[5.0 + sx * 10, 7.0 + sy * 10] for sx in (0, 1) for sy in (0, 1) for _ in (0, 1)]  # a box seen end-on
    box, pix = hull_span_pixels(uv, width, height, margin)
    assert np.all(np.diff(box) >= 0)  # boxes in order
    cols, rows = np.meshgrid(np.arange(width), np.arange(height))  # (H, W)
    centres = np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.float32)  # (H * W, 2) pixel centres
    for b in range(n):
        got = pix[box == b]
        assert np.all(np.diff(got) > 0)  # row-major, each pixel once
        hull = cv2.convexHull(uv[b].astype(np.float32))
        dist = np.array([cv2.pointPolygonTest(hull, tuple(map(float, c)), True) for c in centres])  # > 0 inside
        inside = np.flatnonzero(dist >= 0)
        assert np.isin(inside, got).all(), f"box {b}: hull pixels missing"
        assert np.all(dist[got] >= -margin * np.sqrt(2) - 1e-4), f"box {b}: pixels beyond the margin"
    np.testing.assert_array_equal(pix[box == 0], [r * width + c for r in range(7, 18) for c in range(5, 16)])


def test_hull_span_pixels_empty_and_outside():
    box, pix = hull_span_pixels(np.zeros((0, 8, 2)), 32, 24, 0.25)
    assert box.shape == pix.shape == (0,)
    far = np.full((2, 8, 2), -50.0)
    far[1] += 200.0
    box, pix = hull_span_pixels(far, 32, 24, 0.25)
    assert len(box) == len(pix) == 0


@pytest.mark.parametrize("seed", [0, 1])
def test_box_entry_of_one_box_equals_ray_box_entry(seed):
    rng = np.random.default_rng(seed)
    n = 3000
    o = rng.normal(0.0, 8.0, size=3).astype(np.float32)
    half = rng.uniform(0.5, 6.0, size=3).astype(np.float32)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[rng.uniform(size=(n, 3)) < 0.05] = 0.0  # rays parallel to a slab
    d[:50] = -o / np.linalg.norm(o)  # aimed at the centre
    d = d.astype(np.float32)
    hit, t_ref, axis_ref, sign_ref = ray_box_entry(np.broadcast_to(o, d.shape), d, half)
    t, entries, d_safe = synth_render._box_entry(o, d, half)
    assert t.dtype == t_ref.dtype
    np.testing.assert_array_equal(t, t_ref)
    want = np.flatnonzero(hit)
    axis, sign = synth_render._box_entry_face(entries[want], d_safe[want])
    np.testing.assert_array_equal(axis, axis_ref[want])
    np.testing.assert_array_equal(sign, sign_ref[want])
    assert synth_render._RAY_EPS == synth_raycast._EPS


@pytest.mark.parametrize("seed", [0, 1])
def test_pixel_depth_order_equals_lexsort(seed):
    rng = np.random.default_rng(seed)
    runs = [np.sort(rng.choice(5000, rng.integers(1, 300), replace=False)) for _ in range(40)]  # part by part
    pix = np.concatenate(runs)
    t = rng.uniform(0.1, 80.0, len(pix)).astype(np.float32)
    t[rng.uniform(size=len(t)) < 0.2] = 7.5  # depth ties on a pixel: the first pair stays first
    t[:3] = [np.float32(1e-30), np.finfo(np.float32).max, np.float32(3.0)]
    np.testing.assert_array_equal(synth_render._pixel_depth_order(pix, t), np.lexsort((t, pix)))
    np.testing.assert_array_equal(synth_render._pixel_depth_order(pix, t.astype(np.float64)), np.lexsort((t, pix)))
    assert len(synth_render._pixel_depth_order(np.zeros(0, np.int64), np.zeros(0, np.float32))) == 0


def test_products_of_the_span_candidates_do_not_depend_on_the_batch():
    """The row-span candidates differ from the polygon fills by pixels that miss, so each candidate's products must
    not depend on which other rows share its batch: the parts' einsums and the stacked corner projections do not
    (the scenery's 2-D BLAS product of rays does, so the scenery keeps the fills)."""
    rng = np.random.default_rng(0)
    for n in (1, 7, 64, 1001):
        m32 = rng.normal(size=(n, 3, 3)).astype(np.float32)
        r32 = rng.normal(size=(n, 3)).astype(np.float32)
        m64, n64 = rng.normal(size=(n, 3, 3)), rng.normal(size=(n, 3))
        corners, k = rng.normal(size=(n, 8, 3)) * 30.0, rng.normal(size=(3, 3)) * 300.0
        full = (np.einsum("rij,rj->ri", m32, r32), np.einsum("rji,rj->ri", m64, n64), corners @ k.T)
        for size in (1, 2, 3, 5, 9, 17):
            rows = np.sort(rng.integers(0, n, size))
            np.testing.assert_array_equal(np.einsum("rij,rj->ri", m32[rows], r32[rows]), full[0][rows])
            np.testing.assert_array_equal(np.einsum("rji,rj->ri", m64[rows], n64[rows]), full[1][rows])
            np.testing.assert_array_equal(corners[rows] @ k.T, full[2][rows])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_scaled_rows_equal_broadcasting(dtype):
    rng = np.random.default_rng(0)
    rows = rng.normal(size=(500, 3)).astype(dtype)
    scale = rng.normal(size=500).astype(dtype)
    for offset in (None, rng.normal(size=3).astype(dtype), rng.normal(size=(500, 3)).astype(dtype)):
        got = synth_render._scaled_rows(rows, scale, offset)
        ref = rows * scale[:, None] if offset is None else offset + scale[:, None] * rows
        assert got.dtype == ref.dtype and got.flags["C_CONTIGUOUS"]
        np.testing.assert_array_equal(got, ref)
    assert synth_render._scaled_rows(np.zeros((0, 3), dtype), np.zeros(0, dtype)).shape == (0, 3)


def test_filled_hull_pixels_equal_the_mask_nonzero():
    """The fill's pixels read with cv2.findNonZero come in np.nonzero's order, and none from an empty fill."""
    rng = np.random.default_rng(0)
    camera = real_rig_records((64, 48)).models[0]
    for _ in range(30):
        q = rng.normal([30.0, 20.0], rng.uniform(0.3, 30.0), size=(8, 2))
        got = synth_render._filled_hull_pixels(q, camera)
        u0, v0 = max(int(np.floor(q[:, 0].min())) - 1, 0), max(int(np.floor(q[:, 1].min())) - 1, 0)
        u1, v1 = min(int(np.ceil(q[:, 0].max())) + 2, 64), min(int(np.ceil(q[:, 1].max())) + 2, 48)
        if u0 >= u1 or v0 >= v1:
            assert len(got) == 0
            continue
        fixed = np.clip(np.round((q - [u0, v0]) * 256).astype(np.int64), -(1 << 20), 1 << 20).astype(np.int32)
        mask = np.zeros((v1 - v0, u1 - u0), dtype=np.uint8)
        hull = cv2.convexHull(fixed)
        cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8, shift=8)
        cv2.polylines(mask, [hull], True, 1, thickness=1, lineType=cv2.LINE_8, shift=8)
        rows, cols = np.nonzero(mask)
        np.testing.assert_array_equal(got, (rows + v0) * 64 + cols + u0)
    assert len(synth_render._filled_hull_pixels(np.full((8, 2), -500.0), camera)) == 0


def test_ground_atlas_sampled_in_row_blocks_equals_one_call():
    synth_render.ground_atlas(np.zeros(1), np.zeros(1))  # builds the atlas
    texel, half_width = synth_render.ATLAS_TEXEL_M, synth_render.ATLAS_HALF_WIDTH_M
    ss = (np.arange(round(synth_render.GROUND_PERIOD_M / texel)) + 0.5) * texel
    dd = (np.arange(round(2 * half_width / texel)) + 0.5) * texel - half_width
    grid_s, grid_d = np.meshgrid(ss, dd, indexing="ij")
    np.testing.assert_array_equal(synth_render._ATLAS["albedo"], ground(grid_s, grid_d)[0].reshape(-1, 3))
