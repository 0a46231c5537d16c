"""The export's parity inputs: real data from the bundled nuScenes sample.

Its six images (resized to the export resolution; seeded noise where the rig names cameras the sample lacks) and
its LiDAR sweep cut into ``num_slices`` slices, of which the one with the most points (most pillars, most boxes) is
pillarized with ``runtime_ort/pillarize.py``. Only the cameras the LUT reads for that slice's quadrants are encoded;
a LiDAR-only export has no images at all.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.calibration.camera import Rig
from streamdet.calibration.lut import Lut
from streamdet.calibration.quadrant_lut import quadrant_lut
from streamdet.calibration.slice_maps import slice_maps
from streamdet.data.sample import Sample, load_bundled_sample, load_image
from streamdet.data.slicing import slice_sample
from streamdet.models.presets import Preset
from streamdet.runtime_ort.pillarize import Pillars, pillarize


@dataclass(frozen=True, eq=False)
class ParityInputs:
    images: np.ndarray | None  # (J, H, W, 3) uint8 in rig order; None for a LiDAR-only export
    real_images: bool  # False where the rig names cameras the bundled sample lacks (seeded noise instead)
    cameras: tuple[int, ...]  # rig indices of the cameras the LUT reads for `quadrants` (at least one; () no images)
    pillars: Pillars
    quadrants: tuple[int, ...]
    slice_index: int
    points: np.ndarray  # (N, 6) float32 the slice's points: ``pillars`` pillarised, what the runtime parity feeds
    num_maps: int  # Q of the slice graph: one map per quadrant, or 1 without the crop (calibration/slice_maps.py)
    slice_crop: bool = True  # False: the slice graph runs one whole-grid map (Preset.slice_crop)

    @property
    def num_points(self) -> int:
        return len(self.points)

    @property
    def images_read(self) -> np.ndarray:
        """(J', H, W, 3): the images of the cameras the parity quadrants read."""
        return self.images[list(self.cameras)]

    def describe(self) -> str:
        maps = "" if self.slice_crop else ", one whole-grid map"
        lidar = (f"LiDAR slice {self.slice_index} ({self.num_points} points, {self.pillars.num_pillars} pillars, "
                 f"quadrants {list(self.quadrants)}{maps})")  # fmt: skip
        if self.images is None:
            return f"{lidar} of the bundled nuScenes sample; no images (LiDAR-only model)"
        imgs = "bundled nuScenes images" if self.real_images else "seeded noise images (the rig's cameras are not the sample's)"
        return (
            f"{self.images.shape[0]} {imgs} at {self.images.shape[2]}x{self.images.shape[1]} ({len(self.cameras)} read "
            f"by the parity quadrants and encoded), {lidar}"
        )


def parity_inputs(rig: Rig | None, lut: Lut | None, preset: Preset, size: tuple[int, int], num_slices: int,
                  seed: int) -> ParityInputs:  # fmt: skip
    """The parity inputs of an export; ``rig`` and ``lut`` None for a LiDAR-only one (no images)."""
    sample: Sample = load_bundled_sample()
    pl, quadrants, k, points = busiest_slice(sample, preset, num_slices)
    num_maps = slice_maps(preset.grid, quadrants, preset.slice_crop).count
    if rig is None or lut is None:
        return ParityInputs(None, False, (), pl, quadrants, k, points, num_maps, preset.slice_crop)
    width, height = size
    if set(rig.names) <= set(sample.image_paths):
        images = np.stack([load_image(sample.image_paths[n], size) for n in rig.names])  # (J, H, W, 3)
        real = True
    else:
        images = np.random.default_rng(seed).integers(0, 256, (len(rig), height, width, 3), dtype=np.uint8)
        real = False
    # the cameras the runtime encodes for these quadrants (its per-quadrant LUTs say which)
    cams = tuple(sorted({j for q in quadrants for j in quadrant_lut(lut, q).camera_indices})) or (0,)
    return ParityInputs(images, real, cams, pl, quadrants, k, points, num_maps, preset.slice_crop)


def busiest_slice(sample: Sample, preset: Preset, num_slices: int) -> tuple[Pillars, tuple[int, ...], int, np.ndarray]:
    """The pillars, quadrants, index and (N, 6) points of the sample's slice with the most points: the parity slice."""
    slices = slice_sample(sample, num_slices)
    k = int(np.argmax([len(s.points) for s in slices]))
    sl = slices[k]
    pl = pillarize(sl.points, preset.grid, sl.quadrants, preset.pillars.max_points_per_pillar, preset.pillars.max_pillars,
                   crop=preset.slice_crop)  # fmt: skip
    return pl, tuple(sl.quadrants), k, sl.points


def scatter_cameras(features_read: np.ndarray, cams: tuple[int, ...], num_cameras: int) -> np.ndarray:
    """(J', C, Hf, Wf) features of cameras `cams` -> (J, C, Hf, Wf) with zeros for the cameras not read."""
    full = np.zeros((num_cameras, *features_read.shape[1:]), dtype=features_read.dtype)
    full[list(cams)] = features_read
    return full
