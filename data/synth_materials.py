"""Surface materials of the synthetic world: albedo (camera), reflectance and return behaviour (LiDAR).

Every part of every object (``synth_shapes``) is made of one material. A material does not name a class: car
paint, clothing, plastic, concrete and foliage draw their reflectance from overlapping ranges, dark paint, tyres
and glass reflect little (glass mostly lets the beam through: no return), and retroreflective plates sit on
vehicles, cones, signs and bollards alike. Colour comes from the part (an instance's paint or clothing colour),
and a few materials add a pattern computed from the hit point in the part's frame (barrier stripes, building
windows, leaves with gaps), so a surface looks the same from every camera and at every time.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from streamdet.data.synth_road import CROSS_HALF_WIDTH_M, LANE_WIDTH_M, ROAD_HALF_WIDTH_M, SIDEWALK_OUTER_M

ASPHALT = np.array([0.30, 0.30, 0.31], dtype=np.float32)
GROUND_PERIOD_M = 36.0  # the ground pattern repeats along the road (a multiple of 0.3, 1.5, 4 and 9 m)


class Mat(IntEnum):
    PAINT = 0
    GLASS = 1
    TYRE = 2
    METAL = 3
    PLASTIC = 4
    RETRO = 5  # retroreflective sheeting: number plates, reflectors, cone collars, sign faces
    LAMP = 6
    SKIN = 7
    CLOTH = 8
    CONCRETE = 9
    STRIPES = 10  # barrier boards: the part colour and white in diagonal stripes
    WOOD = 11
    FOLIAGE = 12  # leaves: gaps the sensors see through
    BARK = 13
    FACADE = 14  # a building face with glass windows
    SPOKED = 15  # a bicycle wheel: a tyre on a metal rim round an open disc of thin spokes that beams mostly pass
    WEATHERED = 16  # sun-faded, grimy plastic of street furniture left outside for years: water-filled barriers, bins, feet


@dataclass(frozen=True)
class MaterialSpec:
    reflectance: tuple[float, float]  # uniform range of the LiDAR reflectance (0..1) drawn per part
    return_scale: float  # chance a beam is returned rather than let through (glass lets most beams through)
    follows_albedo: bool  # reflectance scaled by the part's brightness (dark paint / cloth return little)
    gloss: float = 1.0  # incidence exponent of the return (1: Lambertian); glossy paint and metal return little off-normal


MATERIALS: dict[Mat, MaterialSpec] = {
    Mat.PAINT: MaterialSpec((0.03, 0.15), 1.0, True, 6.0),
    Mat.GLASS: MaterialSpec((0.03, 0.08), 0.2, False, 4.0),
    Mat.TYRE: MaterialSpec((0.04, 0.1), 1.0, False, 1.5),
    Mat.METAL: MaterialSpec((0.06, 0.22), 1.0, False, 2.0),
    Mat.PLASTIC: MaterialSpec((0.05, 0.2), 1.0, True, 1.0),
    Mat.RETRO: MaterialSpec((0.5, 0.9), 1.0, False),
    Mat.LAMP: MaterialSpec((0.15, 0.45), 1.0, False),
    Mat.SKIN: MaterialSpec((0.08, 0.2), 1.0, False),
    Mat.CLOTH: MaterialSpec((0.03, 0.2), 1.0, True),
    Mat.CONCRETE: MaterialSpec((0.03, 0.1), 1.0, True),  # weathered grey concrete is darker than fresh
    Mat.STRIPES: MaterialSpec((0.03, 0.1), 1.0, False),  # dirty, scuffed boards
    Mat.WOOD: MaterialSpec((0.06, 0.16), 1.0, False),
    Mat.FOLIAGE: MaterialSpec((0.06, 0.2), 1.0, False),
    Mat.BARK: MaterialSpec((0.05, 0.12), 1.0, False),
    Mat.FACADE: MaterialSpec((0.08, 0.25), 1.0, False),
    Mat.SPOKED: MaterialSpec((0.04, 0.1), 1.0, False, 1.5),  # the tyre's; the open disc inside is set in ``shade``
    Mat.WEATHERED: MaterialSpec((0.02, 0.07), 1.0, True),
}

SPOKED_RIM = 0.82  # a spoked wheel's tyre and rim: the outer part of its radius (the rest is spokes and gaps)
SPOKED_TYRE = 0.9  # ... of which the inner part, up to here, is the silver rim and the rest the tyre
SPOKED_RETURN = 0.1  # chance a beam meeting the spokes' disc comes back from a 2 mm spoke rather than passing


_RETURN_SCALE = np.array([MATERIALS[Mat(m)].return_scale for m in range(len(Mat))])
_GLOSS = np.array([MATERIALS[Mat(m)].gloss for m in range(len(Mat))])


def draw_reflectance(mat: Mat, albedo: np.ndarray, rng: np.random.Generator) -> float:
    """A part's LiDAR reflectance: from its material's range, darker for dark paint and cloth."""
    spec = MATERIALS[mat]
    r = float(rng.uniform(*spec.reflectance))
    if spec.follows_albedo:
        r *= float(np.clip(0.55 + 0.7 * float(np.mean(albedo)), 0.55, 1.2))
    return r


def hash_noise(ix: np.ndarray, iy: np.ndarray, seed: int = 0) -> np.ndarray:
    """Deterministic per-lattice-cell value in [0, 1) (an integer hash, vectorised)."""
    h = (np.asarray(ix, dtype=np.int64) * 73856093) ^ (np.asarray(iy, dtype=np.int64) * 19349663) ^ (seed * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF).astype(np.float32) / 65536.0


def shade(
    mat: np.ndarray, albedo: np.ndarray, refl: np.ndarray, p: np.ndarray, half: np.ndarray, normal: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Albedo (Q, 3) float32, alpha (Q,) bool, reflectance (Q,), return scale (Q,) and gloss (Q,) of hits on parts.

    mat, albedo, refl: the hit parts' material, colour and reflectance; p, normal: (Q, 3) hit points and normals
    in each part's frame; half: (Q, 3) the parts' half extents.
    """
    mat = np.asarray(mat)
    albedo = np.array(albedo, dtype=np.float32)
    refl = np.array(refl, dtype=np.float64)
    alpha = np.ones(len(mat), dtype=bool)
    scale = _RETURN_SCALE[mat]
    gloss = _GLOSS[mat]
    stripes = mat == Mat.STRIPES
    if np.any(stripes):
        q = p[stripes]
        white = np.mod(np.floor((q[:, 0] + q[:, 1] + q[:, 2]) / 0.35), 2) == 0
        albedo[np.flatnonzero(stripes)[white]] = (0.93, 0.93, 0.9)
    leaves = mat == Mat.FOLIAGE
    if np.any(leaves):
        q = p[leaves]
        u = q[:, 0] + 0.7 * q[:, 2]
        v = q[:, 1] - 0.5 * q[:, 2]
        leaf = hash_noise(np.floor(u / 0.22), np.floor(v / 0.22), 11)
        albedo[leaves] *= (0.6 + 0.7 * leaf)[:, None]
        alpha[leaves] = hash_noise(np.floor(u / 0.45), np.floor(v / 0.45), 13) > 0.2  # gaps between the leaves
    facade = mat == Mat.FACADE
    if np.any(facade):
        q, n, h = p[facade], normal[facade], half[facade]
        lat = np.where(np.abs(n[:, 0]) > np.abs(n[:, 1]), q[:, 1], q[:, 0])
        zb = q[:, 2] + h[:, 2]
        col = np.mod(lat, 3.0)
        floor = np.mod(zb, 3.2)
        vertical = np.abs(n[:, 2]) < 0.5
        window = vertical & (col > 0.7) & (col < 2.3) & (((floor > 1.0) & (floor < 2.4) & (zb > 3.2)) | ((zb > 0.4) & (zb < 2.8)))
        idx = np.flatnonzero(facade)[window]
        albedo[idx] = albedo[idx] * 0.25 + np.float32([0.1, 0.13, 0.17])
        refl[idx] = 0.05
        scale[idx] = 0.8  # windows with blinds and rooms behind them
        gloss[idx] = MATERIALS[Mat.GLASS].gloss
    spoked = mat == Mat.SPOKED
    if np.any(spoked):  # a cylinder along its part's z: the radius in x, y
        q, h = p[spoked], half[spoked]
        radial = np.hypot(q[:, 0] / h[:, 0], q[:, 1] / h[:, 1])
        inner = np.flatnonzero(spoked)[radial < SPOKED_RIM]
        scale[inner] = SPOKED_RETURN
        refl[inner] = MATERIALS[Mat.METAL].reflectance[1]
        gloss[inner] = MATERIALS[Mat.METAL].gloss
        rim = np.flatnonzero(spoked)[(radial >= SPOKED_RIM) & (radial < SPOKED_TYRE)]
        albedo[rim] = (0.62, 0.62, 0.64)
        refl[rim] = MATERIALS[Mat.METAL].reflectance[1]
        gloss[rim] = MATERIALS[Mat.METAL].gloss
    return np.clip(albedo, 0.0, 1.0), alpha, refl, scale, gloss


def ground(s: np.ndarray, d: np.ndarray, cross_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Albedo (P, 3) float32 and reflectance (P,) float32 of the ground at road coordinates (s along, d left).

    Asphalt with lane markings (the centre line, dashed lines between the two lanes of each direction, edge
    lines between the lanes and the parking strips), tiled sidewalks and grass beyond: the layout of
    ``synth_road``; plain asphalt where a cross street at ``cross_s`` crosses them.
    """
    s, d, ad, grain, road, sidewalk, painted, cross = _ground_layout(s, d, cross_s)
    patch = hash_noise(np.mod(np.floor(s / 4.0), GROUND_PERIOD_M / 4.0), np.floor(d / 4.0), 2)
    shade_ = (0.85 + 0.2 * grain + 0.1 * patch)[..., None]
    albedo = np.where(road[..., None], ASPHALT * shade_, np.float32([0.33, 0.45, 0.22]) * (0.7 + 0.5 * grain)[..., None])
    tile = (np.mod(s, 1.5) < 0.05) | (np.mod(ad - ROAD_HALF_WIDTH_M, 1.5) < 0.05)
    side_rgb = np.where(tile[..., None], np.float32([0.45, 0.45, 0.44]), np.float32([0.66, 0.65, 0.62]) * (0.92 + 0.12 * grain)[..., None])
    albedo = np.where(sidewalk[..., None], side_rgb, albedo)
    marking, centre = painted
    albedo = np.where(marking[..., None], np.float32([0.92, 0.92, 0.9]), albedo)
    albedo = np.where(centre[..., None], np.float32([0.9, 0.75, 0.2]), albedo)
    if cross is not None:
        albedo = np.where(cross[..., None], ASPHALT * shade_, albedo)
    return albedo.astype(np.float32), _ground_reflectance(grain, road, sidewalk, painted, cross)


def ground_reflectance(s: np.ndarray, d: np.ndarray, cross_s: float | None = None) -> np.ndarray:
    """(P,) float32: ``ground``'s reflectance alone (what the LiDAR needs), without the albedo."""
    _, _, _, grain, road, sidewalk, painted, cross = _ground_layout(s, d, cross_s)
    return _ground_reflectance(grain, road, sidewalk, painted, cross)


def _ground_layout(s, d, cross_s):
    """What ``ground`` and ``ground_reflectance`` share: s, d, |d|, the grain noise, the road and sidewalk masks,
    the (dashed and edge line, centre line) masks and the cross-street mask (None without a cross street)."""
    s = np.asarray(s, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    ad = np.abs(d)
    # The noise repeats every GROUND_PERIOD_M along the road so the renderer can pre-sample one period.
    grain = hash_noise(np.mod(np.floor(s / 0.3), GROUND_PERIOD_M / 0.3), np.floor(d / 0.3), 1)
    road = ad < ROAD_HALF_WIDTH_M
    sidewalk = (ad >= ROAD_HALF_WIDTH_M) & (ad < SIDEWALK_OUTER_M)
    marking = (np.abs(ad - LANE_WIDTH_M) < 0.07) & (np.mod(s, 9.0) < 3.0)  # 3 m dashes every 9 m
    marking |= np.abs(ad - 2 * LANE_WIDTH_M) < 0.09
    centre = ad < 0.1
    cross = cross_street(s, d, cross_s) if cross_s is not None else None
    return s, d, ad, grain, road, sidewalk, (marking, centre), cross


def _ground_reflectance(grain, road, sidewalk, painted, cross) -> np.ndarray:
    marking, centre = painted
    refl = np.where(road, 0.17 + 0.05 * grain, np.where(sidewalk, 0.22 + 0.05 * grain, 0.2 + 0.06 * grain))
    refl = np.where(marking | centre, 0.45, refl)
    if cross is not None:
        refl = np.where(cross, 0.17 + 0.05 * grain, refl)
    return refl.astype(np.float32)


def cross_street(s: np.ndarray, d: np.ndarray, cross_s: float) -> np.ndarray:
    """(P,) bool: road coordinates on the cross street's asphalt, beside the main road."""
    return (np.abs(np.asarray(s) - cross_s) < CROSS_HALF_WIDTH_M) & (np.abs(np.asarray(d)) >= ROAD_HALF_WIDTH_M)
