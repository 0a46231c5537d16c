"""Real calibration inputs of the int8 graphs: samples drawn from a nuScenes-format dataset (or the bundled sample)
and each graph's feeds computed from them by the fp32 graphs upstream.

Calibration. Ranges come from real graph inputs (``graph_inputs``): camera images for the encoder, the fp32
encoder's features of those images with each sample's own LUT for the lifter, and pillarised LiDAR slices with the
fp32 lifter's image BEV for the slice graph (a LiDAR-only export: the pillarised slices alone, no image is read). Never random tensors: a ReLU network's activation ranges on noise have
nothing to do with its ranges on images. MinMax calibration: Percentile and Entropy keep a histogram of every
activation of every input in memory. ``CalibMaxIntermediateOutputs`` is not used: onnxruntime 1.32 clears the data
it collected without merging it and then fails with "No data is collected".
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from streamdet.calibration.lut import Lut, build_lut
from streamdet.core.constants import BUNDLED_SAMPLE_SOURCE
from streamdet.data.sample import Sample, load_bundled_sample, load_image
from streamdet.data.slicing import slice_sample
from streamdet.data.splits import has_split, split_sample_tokens
from streamdet.runtime_ort.pillarize import pillarize

BUNDLED_SOURCE = BUNDLED_SAMPLE_SOURCE
DEFAULT_CALIBRATION_SAMPLES = 8  # samples of a --calibration-data dataset (6 images and n slices each)

Feeds = dict[str, np.ndarray]


class Int8CalibrationDataError(ValueError):
    """int8 calibration data that cannot be used, stated in one line (camera calibration errors are
    ``streamdet.calibration.CalibrationError``)."""


@dataclass(frozen=True, eq=False)
class CalibrationSamples:
    samples: tuple[Sample, ...]
    source: str  # BUNDLED_SOURCE or the dataset directory
    version: str
    split: str  # "train" or "all"


def dataset_version(root: str | Path) -> str:
    """The nuScenes table folder under ``root`` (``v1.0-*`` holding sample.json); a test split is never used."""
    root = Path(root)
    if not root.is_dir():
        raise Int8CalibrationDataError(f"calibration data {str(root)!r} is not a directory")
    found = sorted(p.name for p in root.glob("v1.0-*") if (p / "sample.json").is_file())
    usable = [v for v in found if not v.endswith("-test")]
    if not usable:
        raise Int8CalibrationDataError(
            f"calibration data {str(root)!r} holds no nuScenes table folder (v1.0-*/sample.json)"
            + (f"; only the test split {found}" if found else "")
        )
    return usable[0]


def load_calibration_samples(data_dir: str | Path | None, num_samples: int, camera_names: Sequence[str]) -> CalibrationSamples:
    """Samples to calibrate on: ``num_samples`` spread evenly over the train split of a nuScenes-format dataset
    (all of it without a ``splits.json``), or the bundled nuScenes sample when ``data_dir`` is None.

    Every sample must have an image of each of ``camera_names`` (the export's rig).
    """
    if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 1:
        raise Int8CalibrationDataError(f"calibration samples must be a positive integer, got {num_samples!r}")
    if data_dir is None:
        samples: tuple[Sample, ...] = (load_bundled_sample(),)
        source, version, split = BUNDLED_SOURCE, "v1.0-mini", "all"
    else:
        from streamdet.data.nuscenes import NuScenesReader

        version = dataset_version(data_dir)
        try:
            reader = NuScenesReader(data_dir, version)
            has_train = has_split(data_dir, "train")
            tokens = split_sample_tokens(reader, data_dir, "train" if has_train else None)
        except (OSError, KeyError, ValueError) as e:
            raise Int8CalibrationDataError(f"calibration data {str(data_dir)!r}: {e}") from None
        if not tokens:
            raise Int8CalibrationDataError(f"calibration data {str(data_dir)!r} holds no samples")
        pick = np.unique(np.linspace(0, len(tokens) - 1, min(num_samples, len(tokens))).round().astype(int))
        try:
            samples = tuple(reader.get(tokens[i]) for i in pick)
        except (OSError, KeyError, ValueError) as e:
            raise Int8CalibrationDataError(f"calibration data {str(data_dir)!r}: {e}") from None
        source, split = str(data_dir), "train" if has_train else "all"
    for s in samples:
        missing = [n for n in camera_names if n not in s.image_paths]
        if missing:
            raise Int8CalibrationDataError(
                f"calibration sample {s.token} of {source} has no image of cameras {missing} (the export's rig needs "
                f"{list(camera_names)}); calibrate on data from this rig with --calibration-data"
            )
    return CalibrationSamples(samples, source, version, split)


@dataclass(frozen=True)
class GraphInputs:
    """Real inputs of the three graphs (fp32 graphs upstream), one list of feed dicts per graph."""

    image_encoder: list[Feeds]
    volumetric_lifter: list[Feeds]
    slice_head: list[Feeds]
    slice_sources: list[tuple[int, tuple[int, ...]]] = field(default_factory=list)  # per slice feed: (position of its
    # sample in the volumetric_lifter feeds, the quadrants its image_bev was cut from)

    def for_graph(self, name: str) -> list[Feeds]:
        return getattr(self, name)


def sample_lut(sample: Sample, camera_names: Sequence[str], grid, feature_stride: int, size: tuple[int, int],
               heights_per_voxel: int = 1) -> Lut:  # fmt: skip
    """The sample's own projection LUT (its rig, resized to the export's images), cameras in export order."""
    if tuple(sample.rig.names) != tuple(camera_names):
        raise Int8CalibrationDataError(
            f"sample {sample.token} has cameras {list(sample.rig.names)}; the export's rig orders them "
            f"{list(camera_names)}: the LUT rows would not match the encoded images"
        )
    return build_lut(sample.rig, grid, feature_stride, size, heights_per_voxel=heights_per_voxel)


def graph_inputs(
    samples: Sequence[Sample],
    sessions32: Mapping[str, Any],
    camera_names: Sequence[str],
    size: tuple[int, int],
    preset: Any,
    num_slices: int,
    luts: Sequence[Lut] | None = None,
) -> GraphInputs:
    """Run the fp32 encoder and lifter over the samples to get each graph's real inputs.

    ``sessions32``: onnxruntime sessions of the fp32 graphs by name; ``size`` (W, H) of the export's images;
    ``preset`` the exported ``Preset`` (grid, feature stride, pillar limits); ``luts`` one per sample, default
    each sample's own (``sample_lut``). Slices without a pillar are left out (the runtime does not run them).

    A LiDAR-only preset (``use_image`` False) has only the slice graph: its feeds are the pillar tensors and the
    slice's quadrant ids, no image is read (``camera_names`` may be empty, ``sessions32`` need only hold slice_head),
    and the encoder and lifter lists stay empty.
    """
    if not preset.use_image:
        return _lidar_graph_inputs(samples, preset, num_slices)
    enc, lift, sl = [], [], []
    sources = []
    pil = preset.pillars
    for i, sample in enumerate(samples):
        images = np.stack([load_image(sample.image_paths[n], size) for n in camera_names])  # (J, H, W, 3)
        lut = luts[i] if luts is not None else sample_lut(sample, camera_names, preset.grid, preset.image.feature_stride,
                                                          size, preset.lifter.lut_heights_per_voxel)  # fmt: skip
        (features,) = sessions32["image_encoder"].run(None, {"images": images})  # (J, C, Hf, Wf)
        lifter_feeds = {"features": features, "lut_index": lut.index, "lut_weight": lut.weight}
        (bev,) = sessions32["volumetric_lifter"].run(None, lifter_feeds)  # (4, C, Yq, Xq)
        enc.append({"images": images})
        lift.append(lifter_feeds)
        for s in slice_sample(sample, num_slices):
            pl = pillarize(s.points, preset.grid, s.quadrants, pil.max_points_per_pillar, pil.max_pillars)
            if pl.num_pillars == 0:
                continue
            sl.append({**pl.as_feeds(), "image_bev": np.ascontiguousarray(bev[list(s.quadrants)])})  # (Q, C, Yq, Xq)
            sources.append((i, tuple(s.quadrants)))
    return GraphInputs(enc, lift, sl, sources)


def _lidar_graph_inputs(samples: Sequence[Sample], preset: Any, num_slices: int) -> GraphInputs:
    """The LiDAR-only slice graph's real inputs: every non-empty slice of every sample, pillarised."""
    sl, sources = [], []
    pil = preset.pillars
    for i, sample in enumerate(samples):
        for s in slice_sample(sample, num_slices):
            pl = pillarize(s.points, preset.grid, s.quadrants, pil.max_points_per_pillar, pil.max_pillars, crop=preset.slice_crop)
            if pl.num_pillars:  # without the crop the graph takes no quadrant ids (one whole-grid map)
                sl.append(pl.as_feeds(tuple(s.quadrants) if preset.slice_crop else None))
                sources.append((i, tuple(s.quadrants)))
    return GraphInputs([], [], sl, sources)
