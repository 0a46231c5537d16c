"""`DetectorConfig`, what a `StreamingDetector` is built with, and the error of an image-lane call on a LiDAR-only
export. Every field is checked when the config is made, so a bad value fails where it is written."""

from __future__ import annotations

import numbers
import os
from dataclasses import dataclass

import numpy as np

from streamdet.core.constants import MAX_SESSION_THREADS, PRECISIONS
from streamdet.core.providers import parse_providers
from streamdet.core.scan_layout import check_layout
from streamdet.core.sectors import check_num_slices
from streamdet.runtime_ort.fallback import check_fallback_age
from streamdet.runtime_ort.nms import NmsConfig

MAX_LANE_THREADS = MAX_SESSION_THREADS  # intra-op threads of one lane's sessions (core/constants.py says why)

def lane_precision_label(precision: str, image_precision: str | None) -> str:
    """``"fp32"``, or ``"int8 image lane + fp32 slices"`` when the image lane runs another precision than the slices."""
    if image_precision is None or image_precision == precision:
        return precision
    return f"{image_precision} image lane + {precision} slices"


class NoImageLaneError(ValueError):
    """An image-lane call (images, calibration, image size) on a LiDAR-only export, which has no image lane."""


class DetectorClosed(RuntimeError):
    """A call that runs a graph on a StreamingDetector after its close() (or the end of its ``with`` block)."""


@dataclass(frozen=True)
class DetectorConfig:
    precision: str = "fp32"  # fp32 | fp16 | int8; the export must hold graphs of that precision
    # The image lane's graphs (encoder + lifter) in another precision; None: ``precision``. On an x86 CPU, "int8"
    # here with fp32 slices halves the image lane's time (camera features half as old) and leaves the slice graph
    # exact; its int8 sibling is not faster (README, "Which precision").
    image_lane_precision: str | None = None
    # onnxruntime execution providers by preference ("cuda", "CUDAExecutionProvider", ...; the CPU is always appended
    # as the fallback); None: STREAMDET_PROVIDERS's, else CUDA > CPU, whichever onnxruntime has (runtime_ort/sessions.py)
    providers: tuple[str, ...] | None = None
    # Intra-op threads per session (0: every core; <= 64). Each session keeps its own pool, so the image lane's two to
    # four sessions hold that many threads each (asleep while idle: no spinning); the lanes run at once, so the threads
    # busy together are about image_lane_threads + slice_lane_threads (x the runner's slice workers, which share the
    # slice session): past the usable CPUs they only take turns (the detector logs a warning).
    image_lane_threads: int = 1  # the image encoder's, the lifter's and the per-camera terms' sessions
    slice_lane_threads: int = 1  # the slice session's (and the LiDAR-only fallback's)
    num_slices: int | None = None  # slices per sweep (1, 2 or a multiple of 4); None: the number the export was made for
    # (W, H) px of the images fed to the encoder; None: the export's. The graphs are dynamic in H and W, so another
    # size only needs a LUT built for it: from the export's calibration source at start, then set_calibration.
    image_size: tuple[int, int] | None = None
    # The LiDAR's scan layout (core/sectors.py): the azimuth where its sweep, and slice 0, starts (a multiple of 90 in
    # [-360, 360)), and whether it turns clockwise seen from above (nuScenes' LIDAR_TOP does, from about 180). Slices
    # are numbered in the order the sensor delivers them; the points' features do not depend on it (core/slicing.py)
    start_deg: float = 0.0
    clockwise: bool = False
    score_threshold: float | None = None  # None: the export's post.score_threshold
    # Per-class NMS inside a slice and across a sweep. None: the export's post settings, i.e. circle NMS with
    # max_out = post.max_detections and, for NmsKind.ROTATED, post.nms_iou_threshold per class (the detector's
    # `config.nms` then holds the resolved NmsConfig).
    nms: NmsConfig | None = None
    restrict_to_sector: bool = False  # keep only boxes centred in the slice's own sector
    verify_sha256: bool = True  # refuse graphs whose bytes differ from the manifest
    enable_profiling: bool = False  # onnxruntime profiles of every session (written on close())
    # where those profiles go (never inside an export: refused when the detector opens); None: the current directory
    profile_dir: str | os.PathLike | None = None
    # A LiDAR-only export whose slice graph runs the slices that have no usable camera features (no image BEV yet,
    # or one older than fallback_after_s): runtime_ort/fallback.py. None: those slices read the camera-less BEV
    # (StreamingDetector.blank_image_bev), which the shipped models read far worse than the LiDAR-only model's.
    fallback_export_dir: str | os.PathLike | None = None
    fallback_after_s: float | None = None  # None: fall back only where a quadrant has no image BEV at all
    # Per-camera lifts for image updates (runtime_ort/camera_terms.py): a quadrant update recomputes only the
    # cameras whose frames changed, a full update is one term run per camera and one tail per quadrant instead of the
    # lifter graph (fewer rows: docs/replay.md). None: where the export's lifter splits (the flat lifter) and the
    # image lane is fp32 or int8; True: required (ValueError where it cannot); False: every update runs the lifter
    # graph (with an int8 lane its BEV differs from the terms' by about the int8 lifter's own error).
    camera_terms: bool | None = None
    # Where TensorRT keeps its engines between runs (only with TensorrtExecutionProvider among the providers);
    # None: runtime_ort/tensorrt.py's default_cache_dir ($STREAMDET_TENSORRT_CACHE, else ~/.cache/streamdet/tensorrt).
    tensorrt_cache_dir: str | os.PathLike | None = None

    @property
    def image_precision(self) -> str:
        """Precision of the image lane's graphs."""
        return self.image_lane_precision or self.precision

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise ValueError(f"DetectorConfig.precision must be one of {PRECISIONS}, got {self.precision!r}")
        for name in ("image_lane_threads", "slice_lane_threads"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= v <= MAX_LANE_THREADS:
                raise ValueError(f"DetectorConfig.{name} must be an int in 0..{MAX_LANE_THREADS} (0: every core), got {v!r}")
            object.__setattr__(self, name, int(v))  # onnxruntime's options take a Python int, not a numpy one
        if self.num_slices is not None:
            if isinstance(self.num_slices, bool) or not isinstance(self.num_slices, (int, np.integer)):
                raise ValueError(f"DetectorConfig.num_slices must be None or an int (1, 2 or a multiple of 4), got {self.num_slices!r}")
            try:
                check_num_slices(int(self.num_slices))
            except ValueError as e:
                raise ValueError(f"DetectorConfig.num_slices: {e}") from None
        try:
            start_deg, clockwise = check_layout(self.start_deg, self.clockwise, from_data=False)  # one known layout
        except ValueError as e:
            raise ValueError(f"DetectorConfig.{e}") from None
        object.__setattr__(self, "start_deg", start_deg)
        object.__setattr__(self, "clockwise", clockwise)
        if self.score_threshold is not None and (
            isinstance(self.score_threshold, bool) or not isinstance(self.score_threshold, numbers.Real)
            or not 0.0 <= self.score_threshold <= 1.0
        ):
            raise ValueError(f"DetectorConfig.score_threshold must be None or a number in [0, 1], got {self.score_threshold!r}")
        if self.nms is not None and not isinstance(self.nms, NmsConfig):
            raise ValueError(f"DetectorConfig.nms must be None or an NmsConfig, got {type(self.nms).__name__}")
        if self.camera_terms is not None and not isinstance(self.camera_terms, bool):
            raise ValueError(f"DetectorConfig.camera_terms must be None, True or False, got {self.camera_terms!r}")
        for name in ("restrict_to_sector", "verify_sha256", "enable_profiling"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"DetectorConfig.{name} must be True or False, got {getattr(self, name)!r}")
        if self.providers is not None and (
            isinstance(self.providers, str) or not all(isinstance(p, str) for p in self.providers)
        ):
            raise ValueError(f"DetectorConfig.providers must be None or a tuple of provider names, got {self.providers!r}")
        if self.providers:  # short names ("cuda") become onnxruntime's; an unknown one raises here, not at the first session
            object.__setattr__(self, "providers", parse_providers(",".join(self.providers), "DetectorConfig.providers"))
        if self.tensorrt_cache_dir is not None and not isinstance(self.tensorrt_cache_dir, (str, os.PathLike)):
            raise ValueError(f"DetectorConfig.tensorrt_cache_dir must be None or a path, got {self.tensorrt_cache_dir!r}")
        if self.image_lane_precision is not None and self.image_lane_precision not in PRECISIONS:
            raise ValueError(
                f"DetectorConfig.image_lane_precision must be None or one of {PRECISIONS}, got {self.image_lane_precision!r}"
            )
        if self.profile_dir is not None and not isinstance(self.profile_dir, (str, os.PathLike)):
            raise ValueError(f"DetectorConfig.profile_dir must be None or a path, got {self.profile_dir!r}")
        if self.fallback_export_dir is not None and not isinstance(self.fallback_export_dir, (str, os.PathLike)):
            raise ValueError(f"DetectorConfig.fallback_export_dir must be None or a path, got {self.fallback_export_dir!r}")
        check_fallback_age(self.fallback_after_s, self.fallback_export_dir)
        if self.image_size is not None:
            size = tuple(self.image_size)
            if len(size) != 2 or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v > 0 for v in size):
                raise ValueError(f"DetectorConfig.image_size must be (width, height) in positive pixels, got {self.image_size!r}")
            object.__setattr__(self, "image_size", (int(size[0]), int(size[1])))
