"""One sample through the streaming detector: its camera images with its own calibration, then its sweep slice by
slice. Every tool that runs an export on recorded samples goes through here (``streamdet-run``, ``streamdet-eval``,
the studies), so they all feed the detector the same way a vehicle would.

- ``use_sample_calibration``: the detector's LUT swapped to the sample's rig when the rig differs (same graphs,
  a new LUT; the cached image BEV is dropped, not lifted again: the sample's own images follow).
- ``sample_images``: the sample's images at the detector's image size, by camera name, after
  ``use_sample_calibration``.
- ``feed_images``: those images through the image lane at the sample's time.
- ``update_by_quadrant``: images through the image lane quadrant by quadrant, as the phase-locked lane feeds them.
- ``detect_sample``: ``feed_images`` (when the export has an image lane), then the sweep through
  ``StreamingDetector.detect_sweep_slices``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from streamdet.calibration.camera import CalibrationError
from streamdet.core.sectors import NUM_QUADRANTS

if TYPE_CHECKING:  # a type only: the embedded detector (warm_up imports update_by_quadrant) needs no dataset reader
    from streamdet.data.sample import Sample
    from streamdet.runtime_ort.detector import ImageUpdate, StreamingDetector, SweepResult
    from streamdet.runtime_ort.postprocess import Detections


@dataclass(frozen=True, eq=False)
class SampleResult:
    """What ``detect_sample`` did with one sample."""

    sweep: SweepResult  # every slice's points and result, and the sweep merged
    images: ImageUpdate | None  # the image update; None: no image was fed (LiDAR-only export, or images=False)

    @property
    def detections(self) -> Detections:
        return self.sweep.detections


def sample_time_s(sample: Sample) -> float:
    """The sample's LiDAR timestamp in seconds: the time its images and slices are fed at."""
    return sample.timestamp_us * 1e-6


def use_sample_calibration(detector: StreamingDetector, sample: Sample) -> None:
    """Swap the detector's LUT to one built from the sample's rig, unless the LUT in use was built from it.

    On a swap the cached image BEV is dropped rather than lifted again under the new LUT: every caller feeds the
    sample's images next, which replace it (a synthetic world has a rig per sample, so the re-lift was a lift per
    sample thrown away). Until then the detector reads no image."""
    if sample.rig.sha256() != detector.lut.calibration_sha256:
        try:  # another rig than the current LUT's: rebuild the LUT
            detector.set_calibration(sample.rig, relift=False)
        except CalibrationError as e:  # a rig the export cannot take (another aspect, other cameras): name the sample
            first = next(iter(sample.image_paths.values()), None)
            where = f"sample {sample.token}" + (f" ({sample_folder(first)})" if first is not None else "")
            raise CalibrationError(f"{where}: {e}") from None


# the folders of a nuScenes dataset's files (sample_data filenames: samples/CAM_FRONT/x.jpg, sweeps/LIDAR_TOP/y.bin)
_DATASET_FILE_FOLDERS = ("samples", "sweeps")
SAMPLE_CALIBRATION = "calibration.json"  # what makes a folder one sample in the bundled layout (data/sample.py)


def sample_folder(image: Path) -> Path:
    """The folder a sample was read from, for messages, from one of its image files: the sample folder of the
    bundled layout (calibration.json beside the files it names, or above them), else the dataset root of the
    nuScenes layout (``DATA/samples/CAM_FRONT/x.jpg``), else the image's own folder."""
    for folder in image.parents:
        if (folder / SAMPLE_CALIBRATION).is_file():
            return folder  # the bundled layout: the sample folder itself (whatever its name)
        if folder.name in _DATASET_FILE_FOLDERS:
            return folder.parent  # the dataset layout: its root
    return image.parent


def sample_images(detector: StreamingDetector, sample: Sample) -> dict[str, np.ndarray]:
    """The sample's camera images (H, W, 3) uint8 at the detector's image size, by name, for the cameras the
    export reads; the detector's LUT is rebuilt from the sample's rig first if it was built from another rig."""
    use_sample_calibration(detector, sample)
    size = (detector.image.width, detector.image.height)
    images = sample.load_images(size)  # (J, H, W, 3) in rig order
    return {name: images[j] for j, name in enumerate(sample.rig.names) if name in detector.camera_names}


def feed_images(detector: StreamingDetector, sample: Sample, timestamp: float | None = None) -> ImageUpdate:
    """The sample's images through the image lane (``sample_images``) at ``timestamp`` (None: the sample's)."""
    ts = sample_time_s(sample) if timestamp is None else timestamp
    return detector.update_images(sample_images(detector, sample), timestamp=ts)


def update_by_quadrant(detector: StreamingDetector, images: dict[str, np.ndarray], timestamp: float) -> tuple[ImageUpdate, ...]:
    """``images`` through the image lane as the phase-locked lane feeds it: every camera encoded once (its per-camera
    lift terms made with it, where the detector has them), then the quadrants updated one by one from their cameras.
    The updates of quadrants 0..3."""
    encoded = detector.encode_images(images)
    detector.prepare_terms(encoded)
    updates = []
    for q in range(NUM_QUADRANTS):
        cams = [n for n in detector.quadrant_cameras([q]) if n in images]
        updates.append(detector.update_images({n: images[n] for n in cams}, timestamp, quadrants=[q],
                                              encoded={n: encoded[n] for n in cams}))  # fmt: skip
    return tuple(updates)


def detect_sample(
    detector: StreamingDetector, sample: Sample, num_slices: int | None = None, images: bool = True
) -> SampleResult:
    """Detect one sample: its images first (skipped for a LiDAR-only export, or with ``images`` False: the
    detector keeps the image BEV it has), then its sweep in ``num_slices`` slices (None: the detector's)."""
    ts = sample_time_s(sample)
    update = feed_images(detector, sample, ts) if images and detector.uses_images else None
    sweep = detector.detect_sweep_slices(np.asarray(sample.points, np.float32), timestamp=ts, num_slices=num_slices)
    return SampleResult(sweep, update)
