"""The MAC rows of the paper's Table 3, counted on the actual modules (no timing).

Benchmark input as in the paper: one image and 30,000 points. The points are the bundled nuScenes sweep's, pillarized
by the runtime (``benchmarks/sweep_pillars.py``): the "uncropped" rows run the modules on one map the size of the
whole grid (Q = 1, 512 x 512 for the paper) with every pillar of those points, the "cropped" rows on one quadrant
with the pillars of the busiest quadrant. Everything runs on the meta device, so only shapes are computed.

All figures are GMAC (1e9 multiply-accumulates; FLOPs = 2 x MACs), the unit of the paper's "GFLOPS" column.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from streamdet.benchmarks.sweep_pillars import SweepPillars, busiest_quadrant_pillars, whole_grid_pillars
from streamdet.models.detector import SliceNet, build_lifter
from streamdet.models.flops import count_gmac
from streamdet.models.image_encoder import ImageEncoder
from streamdet.models.presets import Preset, get_preset

BENCH_NUM_POINTS = 30_000
BENCH_NUM_IMAGES = 1
LUT_CAMERAS_PER_VOXEL = 2  # K of the nuScenes rig; the gather it sizes costs no MACs
PAPER_RESOLUTIONS: tuple[tuple[int, int], ...] = ((1600, 900), (1200, 675), (800, 450))

# Table 3 of the paper, GMAC ("GFLOPS" there; they are multiply-accumulates).
PAPER_SLICE_MULTI_HEAD = 180.2
PAPER_SLICE_SINGLE_HEAD = 161.6
PAPER_SLICE_CROPPED = 40.43
PAPER_CONV3D = 715.7
PAPER_CONV3D_CROPPED = 178.9
PAPER_IMAGE: dict[tuple[int, int], float] = {(1600, 900): 126.5, (1200, 675): 71.6, (800, 450): 32.1}


@dataclass(frozen=True)
class GmacRow:
    module: str
    gmac: float
    paper_gmac: float | None  # None when the preset is not the paper's or the paper has no such row

    def to_dict(self) -> dict:
        return {"module": self.module, "gmac": self.gmac, "paper_gmac": self.paper_gmac}


def _slice_gmac(preset: Preset, cropped: bool) -> float:
    pillars = slice_row_pillars(preset, cropped)
    p, m = pillars.mask.shape
    map_ny, map_nx = pillars.map_ny, pillars.map_nx
    with torch.device("meta"):
        net = SliceNet(preset).eval()
        args = (
            torch.empty(p, m, preset.pillars.num_point_features),  # (P, M, 11)
            torch.empty(p, m),  # (P, M)
            torch.zeros(p, dtype=torch.int64),  # (P,)
            torch.empty(1, preset.channels, map_ny, map_nx),  # (Q=1, C, Y, X)
        )
    return count_gmac(net, *args)


def slice_row_pillars(preset: Preset, cropped: bool) -> SweepPillars:
    """The pillars a slice row runs on: every pillar of the 30,000 points, or the busiest quadrant's."""
    make = busiest_quadrant_pillars if cropped else whole_grid_pillars
    return make(preset.grid, preset.pillars.max_points_per_pillar, preset.pillars.max_pillars, BENCH_NUM_POINTS)


def _lifter_gmac(preset: Preset, map_ny: int, map_nx: int) -> float:
    with torch.device("meta"):
        net = build_lifter(preset).eval()
        lut_shape = (1, LUT_CAMERAS_PER_VOXEL, preset.grid.nz, map_ny, map_nx)  # (Q=1, K, Z, Y, X)
        args = (
            torch.empty(BENCH_NUM_IMAGES, preset.channels, preset.image.feature_height, preset.image.feature_width),
            torch.zeros(lut_shape, dtype=torch.int32),
            torch.empty(lut_shape),
        )
    return count_gmac(net, *args)


def _image_gmac(preset: Preset, width_px: int, height_px: int) -> float:
    with torch.device("meta"):
        net = ImageEncoder(preset.image, preset.channels).eval()
        images = torch.empty(BENCH_NUM_IMAGES, height_px, width_px, 3, dtype=torch.uint8)
    return count_gmac(net, images)


def gmac_rows(preset: Preset, resolutions: Sequence[tuple[int, int]] = PAPER_RESOLUTIONS) -> list[GmacRow]:
    """The Table 3 rows for ``preset``; image rows at each (width_px, height_px) of ``resolutions``."""
    if not resolutions:
        raise ValueError("gmac_rows needs at least one image resolution")
    for w, h in resolutions:
        if w < 1 or h < 1:
            raise ValueError(f"image resolution must be positive, got {w}x{h}")
    g = preset.grid
    is_paper = preset == get_preset("paper")

    def paper(value: float) -> float | None:
        return value if is_paper else None

    multi = dataclasses.replace(preset, head=dataclasses.replace(preset.head, multi_head=True))
    single = dataclasses.replace(preset, head=dataclasses.replace(preset.head, multi_head=False))
    # the paper's lifter runs 3D convolutions; the flat lifter (models/flat_lifter.py) 2D ones over z in channels
    lifter_convs = "3D convolutions" if preset.lifter.form == "volume" else "flat lifter (2D convolutions, z in channels)"
    rows = [
        GmacRow("points + BEV enc + multi-head", _slice_gmac(multi, cropped=False), paper(PAPER_SLICE_MULTI_HEAD)),
        GmacRow("points + BEV enc + single head", _slice_gmac(single, cropped=False), paper(PAPER_SLICE_SINGLE_HEAD)),
        GmacRow(
            "points + BEV enc + single head, cropped (1 quadrant)",
            _slice_gmac(single, cropped=True),
            paper(PAPER_SLICE_CROPPED),
        ),
        GmacRow(f"{lifter_convs} ({g.nx}x{g.ny}x{g.nz} volume)", _lifter_gmac(preset, g.ny, g.nx), paper(PAPER_CONV3D)),
        GmacRow(
            f"{lifter_convs}, cropped (1 quadrant)",
            _lifter_gmac(preset, g.quadrant_ny, g.quadrant_nx),
            paper(PAPER_CONV3D_CROPPED),
        ),
    ]
    for w, h in resolutions:
        figure = PAPER_IMAGE.get((w, h))
        rows.append(GmacRow(f"image encoding {w}x{h}", _image_gmac(preset, w, h), paper(figure) if figure else None))
    return rows


def format_rows(preset_name: str, rows: Sequence[GmacRow]) -> str:
    """A plain-text table: module, GMAC, the paper's GMAC and our / paper."""
    width = max(len(r.module) for r in rows)
    lines = [
        f"preset {preset_name}: {BENCH_NUM_IMAGES} image, {BENCH_NUM_POINTS:,} points of the bundled nuScenes sweep "
        "(cropped: its busiest quadrant's); GMAC = 1e9 multiply-accumulates (FLOPs = 2 x MACs)",
        f"{'module':<{width}}  {'GMAC':>9}  {'paper GMAC':>10}  {'ratio':>6}",
    ]
    for r in rows:
        paper = f"{r.paper_gmac:10.2f}" if r.paper_gmac is not None else f"{'-':>10}"
        ratio = f"{r.gmac / r.paper_gmac:6.3f}" if r.paper_gmac else f"{'-':>6}"
        lines.append(f"{r.module:<{width}}  {r.gmac:9.3f}  {paper}  {ratio}")
    return "\n".join(lines)
