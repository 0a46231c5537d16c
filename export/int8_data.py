"""Real calibration inputs of the int8 graphs: samples drawn from a nuScenes-format dataset (or the bundled sample)
and each graph's feeds recorded while the fp32 export's runtime detects them.

Calibration. Ranges come from real graph inputs (``record_graph_inputs``): the feeds the fp32 ``StreamingDetector``
of the staged export hands its sessions while it detects each sample as every tool runs it
(``runtime_ort.pipeline.detect_sample``): camera images for the encoder, the fp32 encoder's features of those
images with the sample's own LUT for the lifter, and pillarised LiDAR slices with the fp32 lifter's image BEV for
the slice graph (a LiDAR-only export: the pillarised slices alone, no image is read). Never random tensors: a ReLU
network's activation ranges on noise have nothing to do with its ranges on images. MinMax calibration: Percentile
and Entropy keep a histogram of every activation of every input in memory. ``CalibMaxIntermediateOutputs`` is not
used: onnxruntime 1.32 clears the data it collected without merging it and then fails with "No data is collected".
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from streamdet.calibration.camera import CalibrationError
from streamdet.core.constants import BUNDLED_SAMPLE_SOURCE
from streamdet.data.sample import Sample, load_bundled_sample
from streamdet.data.splits import SplitsFileMissing, split_sample_tokens, split_scenes
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.pipeline import detect_sample, use_sample_calibration
from streamdet.runtime_ort.recording import Feeds, GraphRecording  # noqa: F401 (Feeds: public here too)

BUNDLED_SOURCE = BUNDLED_SAMPLE_SOURCE
DEFAULT_CALIBRATION_SAMPLES = 8  # samples of a --calibration-data dataset (6 images and n slices each)


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
    (all of it without a ``splits.json``; one that is there must name a train split, else
    ``Int8CalibrationDataError``), or the bundled nuScenes sample when ``data_dir`` is None.

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
        split = calibration_split(data_dir)
        try:
            reader = NuScenesReader(data_dir, version)
            tokens = split_sample_tokens(reader, data_dir, split)
        except (OSError, KeyError, ValueError) as e:
            raise Int8CalibrationDataError(f"calibration data {str(data_dir)!r}: {e}") from None
        if not tokens:
            raise Int8CalibrationDataError(f"calibration data {str(data_dir)!r} holds no samples")
        pick = np.unique(np.linspace(0, len(tokens) - 1, min(num_samples, len(tokens))).round().astype(int))
        try:
            samples = tuple(reader.get(tokens[i]) for i in pick)
        except (OSError, KeyError, ValueError) as e:
            raise Int8CalibrationDataError(f"calibration data {str(data_dir)!r}: {e}") from None
        source, split = str(data_dir), split or "all"
    for s in samples:
        missing = [n for n in camera_names if n not in s.image_paths]
        if missing:
            raise Int8CalibrationDataError(
                f"calibration sample {s.token} of {source} has no image of cameras {missing} (the export's rig needs "
                f"{list(camera_names)}); calibrate on data from this rig with --calibration-data"
            )
    return CalibrationSamples(samples, source, version, split)


def calibration_split(data_dir: str | Path) -> str | None:
    """The split of ``data_dir`` the calibration draws from: "train", or None (every sample) where the dataset has
    no splits.json. One that is there but unreadable, malformed or without a train split raises
    ``Int8CalibrationDataError`` naming the file: falling back to every sample would calibrate on the held-out val
    scenes too."""
    try:
        split_scenes(data_dir, "train")
    except SplitsFileMissing:
        return None
    except (OSError, ValueError) as e:  # json.JSONDecodeError and the file readers' errors are ValueErrors
        raise Int8CalibrationDataError(f"calibration data {str(data_dir)!r}: {e}") from None
    return "train"


def record_graph_inputs(detector: StreamingDetector, samples: Sequence[Sample]) -> GraphRecording:
    """Every graph run of the (fp32) ``detector`` over ``samples``, recorded: each graph's real inputs.

    Each sample goes through the runtime as every tool feeds it (``runtime_ort.pipeline.detect_sample``): its images
    with a LUT of its own rig (the swap happens before the recording starts), then its sweep slice by slice. Slices without a pillar run no graph.
    A LiDAR-only export records its slice graph alone: no image is read.
    """
    recording = GraphRecording()
    for sample in samples:
        try:
            if detector.uses_images:
                use_sample_calibration(detector, sample)
            with detector.recording(recording):
                detect_sample(detector, sample)
        except (CalibrationError, OSError) as e:
            raise Int8CalibrationDataError(f"calibration sample {sample.token}: {e}") from None
    return recording
