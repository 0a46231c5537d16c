"""Vectorised ray casting against the ground plane, boxes, ellipsoids and cylinders (the synthetic sensors' geometry).

Both the LiDAR and the cameras use these functions on the same object parts, so a point and a pixel see the same
surface.
Rays are ``origin + t * direction`` with unit directions, so ``t`` is a distance in metres.
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12


def ray_box_entry(
    origins_local: np.ndarray, dirs_local: np.ndarray, half_extent: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Slab test of rays against axis-aligned boxes centred at the origin of their local frame.

    origins_local, dirs_local: (P, 3) in the box frame; half_extent: (P, 3) or (3,) half sizes along x, y, z.
    Returns ``hit`` (P,) bool, ``t`` (P,) entry distance (inf where no hit), ``axis`` (P,) int64 of the entered
    face (0: +-x, 1: +-y, 2: +-z) and ``sign`` (P,) float64 (+1 / -1: which of the two faces, its outward
    normal is ``sign * e_axis``). A ray starting inside a box does not hit it (the sensor is never inside one).
    """
    o = np.asarray(origins_local)
    d = np.asarray(dirs_local)
    half = np.asarray(half_extent)
    d_safe = np.where(np.abs(d) < _EPS, _EPS, d)
    inv = 1.0 / d_safe
    t1 = (-half - o) * inv  # (P, 3)
    t2 = (half - o) * inv
    t_near = np.minimum(t1, t2)
    t_exit = np.maximum(t1, t2, out=t1)
    # Reductions over the 3 slabs column by column (numpy's axis reductions over a length-3 axis are slow); the
    # same values as min / max / argmax (first maximum) over the axis.
    t_far = np.minimum(np.minimum(t_exit[:, 0], t_exit[:, 1]), t_exit[:, 2])
    n0, n1, n2 = t_near[:, 0], t_near[:, 1], t_near[:, 2]
    n01 = np.maximum(n0, n1)
    axis = np.where(n2 > n01, 2, np.where(n1 > n0, 1, 0))  # the last slab entered is the face the ray crosses
    t_near = np.maximum(n01, n2)
    hit = (t_near <= t_far) & (t_near > 0.0)
    sign = -np.sign(d_safe[np.arange(len(axis)), axis])
    return hit, np.where(hit, t_near, np.inf), axis, sign


def ray_ground(origins: np.ndarray, dirs: np.ndarray, ground_z_m: float = 0.0) -> np.ndarray:
    """(P,) distance to the plane z = ground_z along each ray (inf for rays that never reach it)."""
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    dz = d[..., 2]
    down = dz < -1e-9
    t = np.where(down, (ground_z_m - o[..., 2]) / np.where(down, dz, -1.0), np.inf)
    return np.where(t > 0, t, np.inf)


def world_to_local(points: np.ndarray, centers: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """(P, 3) points (or directions, with centers 0) in the frames of boxes rotated by yaw about z."""
    rel = np.asarray(points, dtype=np.float64) - centers
    c, s = np.cos(yaws), np.sin(yaws)
    return np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1], rel[..., 2]], axis=-1)


def local_normals(axis: np.ndarray, sign: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """(P, 3) outward face normals in the world frame from ``ray_box_entry``'s axis / sign and the box yaw."""
    n_local = np.zeros(axis.shape + (3,))
    np.put_along_axis(n_local, axis[..., None], sign[..., None], axis=-1)
    c, s = np.cos(yaws), np.sin(yaws)
    return np.stack([c * n_local[..., 0] - s * n_local[..., 1], s * n_local[..., 0] + c * n_local[..., 1], n_local[..., 2]], axis=-1)


# Part shapes (``synth_shapes``): every shape lives in its own frame, centred, with half extents (a, b, c).
SHAPE_BOX = 0
SHAPE_ELLIPSOID = 1  # the ellipsoid inscribed in the box
SHAPE_CYLINDER = 2  # elliptic cylinder along the part's z axis, capped at z = +-c


def ray_shape_entry(
    origins: np.ndarray, dirs: np.ndarray, half: np.ndarray, shape: np.ndarray, with_normal: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Entry distance (Q,) (inf where missed) and outward unit normal (Q, 3) of rays against centred shapes.

    origins, dirs: (Q, 3) in each shape's frame (dirs unit length, so t is in metres); half: (Q, 3) half extents;
    shape: (Q,) SHAPE_*. A ray starting inside a shape does not hit it. Float32 inputs are computed in float32
    (the cameras); ``with_normal=False`` skips the normals (returned as None).
    """
    dtype = np.float32 if np.asarray(origins).dtype == np.float32 and np.asarray(dirs).dtype == np.float32 else np.float64
    o = np.asarray(origins, dtype=dtype)
    d = np.asarray(dirs, dtype=dtype)
    half = np.asarray(half, dtype=dtype)
    shape = np.asarray(shape)
    t = np.full(len(o), np.inf, dtype=dtype)
    normal = np.zeros((len(o), 3), dtype=dtype) if with_normal else None
    box_mask = shape == SHAPE_BOX
    if box_mask.all():  # (the common case: skip the gathers)
        hit, tb, axis, sign = ray_box_entry(o, d, half)
        if with_normal:
            normal[np.arange(len(o)), axis] = sign
        return tb.astype(dtype, copy=False), (None if normal is None else normal)
    box = np.flatnonzero(box_mask)
    if len(box):
        hit, tb, axis, sign = ray_box_entry(o[box], d[box], half[box])
        t[box] = tb
        if with_normal:
            normal[box, axis] = sign
    ell = np.flatnonzero(shape == SHAPE_ELLIPSOID)
    if len(ell):
        os_, ds = o[ell] / half[ell], d[ell] / half[ell]  # the unit sphere, same parameter t
        te = _quadratic_entry(_row_sum(ds * ds), 2 * _row_sum(os_ * ds), _row_sum(os_ * os_) - 1.0)
        t[ell] = te
        if with_normal:
            p = o[ell] + np.where(np.isfinite(te), te, 0.0)[:, None] * d[ell]
            normal[ell] = p / half[ell] ** 2
    cyl = np.flatnonzero(shape == SHAPE_CYLINDER)
    if len(cyl):
        oc, dc, hc = o[cyl], d[cyl], half[cyl]
        os_, ds = oc[:, :2] / hc[:, :2], dc[:, :2] / hc[:, :2]
        ts = _quadratic_entry(_row_sum(ds * ds), 2 * _row_sum(os_ * ds), _row_sum(os_ * os_) - 1.0)
        zs = oc[:, 2] + np.where(np.isfinite(ts), ts, 0.0) * dc[:, 2]
        ts = np.where(np.abs(zs) <= hc[:, 2], ts, np.inf)
        dz = np.where(np.abs(dc[:, 2]) < _EPS, _EPS, dc[:, 2])
        cap_sign = -np.sign(dz)  # the cap facing the ray
        tc = (cap_sign * hc[:, 2] - oc[:, 2]) / dz
        pc = oc[:, :2] + tc[:, None] * dc[:, :2]
        inside_cap = _row_sum((pc / hc[:, :2]) ** 2) <= 1.0
        tc = np.where(inside_cap & (tc > 0) & (np.abs(oc[:, 2]) > hc[:, 2]), tc, np.inf)
        side = ts <= tc
        t[cyl] = np.minimum(ts, tc)
        if with_normal:
            p = oc + np.where(np.isfinite(t[cyl]), t[cyl], 0.0)[:, None] * dc
            n = np.zeros_like(p)
            n[:, :2] = p[:, :2] / hc[:, :2] ** 2
            n = np.where(side[:, None], n, np.stack([np.zeros(len(p)), np.zeros(len(p)), cap_sign], axis=1))
            normal[cyl] = n
    if not with_normal:
        return t, None
    norm = np.sqrt(_row_sum(normal * normal))[:, None]  # (np.linalg.norm's values)
    return t, normal / np.maximum(norm, _EPS)


def _row_sum(x: np.ndarray) -> np.ndarray:
    """(Q,) sums of the 2 or 3 columns of x (Q, n), left to right: the values of ``x.sum(axis=1)`` without numpy's slow
    reduction over a short axis."""
    s = x[:, 0] + x[:, 1]
    for j in range(2, x.shape[1]):
        s += x[:, j]
    return s


def _quadratic_entry(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Smaller positive root of a t^2 + b t + c = 0 for rays starting outside (c > 0); inf where none."""
    disc = b * b - 4 * a * c
    root = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * np.maximum(a, _EPS))
    return np.where((disc >= 0) & (c > 0) & (root > 0), root, np.inf)
