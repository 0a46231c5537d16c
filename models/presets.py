"""Model presets: every architectural number of the detector, in frozen dataclasses.

This module is torch-free on purpose: the export manifest stores ``Preset.to_dict()`` and the vehicle runtime
reads it back with ``Preset.from_dict`` without PyTorch.

The presets:

- ``paper``: the numbers of the paper and of DESIGN.md (0.2 m pillars over [-51.2, 51.2] m, 0.5 m image voxels,
  c = 64, ResNet-50 + FPN at 1600 x 900, CenterPoint single head at output stride 4, top 500, 10 classes).
- ``small``: ours, sized for CPU real time and for training within an hour on a 2-core machine. 0.4 m pillars
  (quadrant 128 x 128), 2 m image voxels (quadrant volume 4 x 128 x 128: the lifter's 3D convolutions cost half
  what 1 m voxels cost; its z-stride and pooling still end in one BEV map), c = 32, a half-width ResNet-18
  (``width_divisor=2``, base width 32) at a native 384 x 216, a three-scale BEV encoder whose stages all run at
  stride >= 2, and the head at 0.8 m cells (64 x 64 per quadrant). The half-width backbone has a quarter of the
  MACs and parameters of ResNet-18 (a checkpoint is ~13 MB) and cannot load torchvision's ImageNet
  weights, which it never does anyway (nothing is downloaded): its encoder is trained here, from scratch or from
  ``streamdet-train-image`` on the synthetic world's masks. The
  graphs take any image size, so ``streamdet-bench --resolution 800x450`` still runs it. The slice graph's GMAC
  per quadrant: ``streamdet-bench --flops-only`` (benchmarks/flops_report.py).
- ``tiny``: for unit tests; every size minimal so a forward and backward pass take milliseconds.
- ``small_v2``: ``small`` with the camera-lane options of issue 19 on (frozen backbone BatchNorm after image
  pretraining, image BEV normalised at fusion, two LUT heights per voxel) and the flat lifter (2D convolutions over
  z stacked into channels, ``LifterConfig.form``; its checkpoints from before it are volume and export as such);
  the others keep them off.
- ``small_v3``: ``small_v2`` with the image BEV brought to the point BEV's RMS at fusion instead of a learnt gain
  (``image_bev_target="point"``); the shipped model's preset (``core.constants.DEFAULT_PRESET``; its recipe, with the
  image-side class loss of ``streamdet-train --image-class-weight``, in ``models/weights/small.json``).
- ``small_v3_lite``: ``small_v3`` with a quarter-width ResNet-18 at 320 x 180: a lighter image lane for the
  phase-locked schedule (issue 22), the rest unchanged.
- ``small_v3_thin``: ``small_v3_lite`` with half the BEV encoder's widths and 8-channel head branches: a lighter
  slice net for 2-core AVX2-only parts at nuScenes rates (issue 22); camera lane and pillar net unchanged. Trained
  once and not bundled: it drops fewer slices there but scores lower (docs/replay.md, "A thinner slice net").
- ``small_v3_swift``: ``small_v3_thin`` with a lighter camera lane: 224 x 126 images and a factorised residual conv
  in the flat lifter (``LifterConfig.residual="separable"``), for the phase-locked image lane (issue 22). Bundled:
  ``models/weights/small_v3_swift.pt`` (``streamdet-export --preset small_v3_swift`` loads it by default).

Any LiDAR-only variant (``use_image=False``) may drop the quadrant crop (``slice_crop=False``: one whole-grid map
per slice, the paper's baseline set-up; ``streamdet-train --no-image --no-crop``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import reprlib
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from streamdet.calibration.grid import GridSpec
from streamdet.calibration.slice_maps import map_cells
from streamdet.core.classes import CLASS_NAMES

# what the image BEV is scaled to at fusion (models/image_bev_norm.py): a learnt RMS, or the point BEV's RMS
IMAGE_BEV_TARGETS = ("learnt", "point")

# Upper bounds of the architectural numbers: generous (each far past every shipped preset) but finite, so that a preset
# read from a file (a checkpoint's, a manifest's) cannot ask for a model or a buffer of terabytes. A checkpoint's
# preset is further held to its own tensors (training/checkpoint.py builds the model on the meta device first).
MAX_CHANNELS = 4096  # any channel width: channels, num_filters, num_upsample_filters, head_channels
MAX_IMAGE_PX = 65536  # ImageConfig.width_px / height_px
MAX_PILLARS = 1 << 22  # PillarConfig.max_pillars (the paper's 30000; the grid has 262144 cells)
MAX_POINTS_PER_PILLAR = 1024
MAX_BEV_STAGES = 8  # entries of BevEncoderConfig.layer_nums
MAX_LAYERS_PER_STAGE = 64  # each BevEncoderConfig.layer_nums entry
MAX_STRIDE = 64  # layer_strides, upsample factors (u or 1/u), head.out_stride, lifter z strides
MAX_KERNEL = 15  # HeadConfig.final_kernel
MAX_LUT_HEIGHTS = 64  # LifterConfig.lut_heights_per_voxel
MAX_DETECTIONS = 1 << 24  # PostConfig.top_k (clamped to classes x cells where used) / max_detections

# The nuScenes CenterPoint task grouping of the multi-head variant (classes of similar size share a task).
NUSCENES_TASKS: tuple[tuple[str, ...], ...] = (
    ("car",),
    ("truck", "construction_vehicle"),
    ("bus", "trailer"),
    ("barrier",),
    ("motorcycle", "bicycle"),
    ("pedestrian", "traffic_cone"),
)


@dataclass(frozen=True)
class ImageConfig:
    width_px: int = 1600  # network input size; the LUT is built for the same size
    height_px: int = 900
    backbone_depth: int = 50  # 18 (BasicBlock) or 50 (Bottleneck), torchvision layouts
    width_divisor: int = 1  # base width 64 // divisor; > 1 (small, tiny) rules out torchvision's ImageNet weights
    feature_stride: int = 4  # the FPN output level; the lifter LUT is built for this stride
    # the backbone's normalisation (models/norms.py): "batch", "frozen_batch" (running statistics only, e.g. after
    # image pretraining) or "group"; the latter two do not depend on the batch of six correlated cameras
    norm: str = "batch"

    def __post_init__(self) -> None:
        _check_types(self)
        _check_positive_int(self, "width_px", "height_px", "width_divisor")
        _check_at_most(self, MAX_IMAGE_PX, "width_px", "height_px")
        if self.backbone_depth not in (18, 50):
            raise ValueError(f"ImageConfig.backbone_depth must be 18 or 50, got {self.backbone_depth!r}")
        if 64 % self.width_divisor:
            raise ValueError(f"ImageConfig.width_divisor must divide 64, got {self.width_divisor!r}")
        if self.norm not in ("batch", "frozen_batch", "group"):
            raise ValueError(f"ImageConfig.norm must be 'batch', 'frozen_batch' or 'group', got {self.norm!r}")
        if self.feature_stride != 4:
            raise ValueError(f"ImageConfig.feature_stride must be 4 (the FPN's output level), got {self.feature_stride!r}")

    @property
    def feature_height(self) -> int:
        return math.ceil(self.height_px / self.feature_stride)

    @property
    def feature_width(self) -> int:
        return math.ceil(self.width_px / self.feature_stride)


@dataclass(frozen=True)
class PillarConfig:
    max_points_per_pillar: int = 20  # M; CenterPoint-pillar nuScenes setting
    max_pillars: int = 30000  # P upper bound per slice
    num_point_features: int = 11  # x, y, z, r, t, s, 3 offsets to the pillar mean, 2 to the cell centre

    def __post_init__(self) -> None:
        _check_types(self)
        _check_positive_int(self, "max_points_per_pillar", "max_pillars")
        _check_at_most(self, MAX_POINTS_PER_PILLAR, "max_points_per_pillar")
        _check_at_most(self, MAX_PILLARS, "max_pillars")
        if self.num_point_features != 11:
            raise ValueError(
                f"PillarConfig.num_point_features must be 11 (the pillar_features contract), got {self.num_point_features!r}"
            )


LIFTER_FORMS = ("volume", "flat")
LIFTER_RESIDUALS = ("conv", "separable")


@dataclass(frozen=True)
class LifterConfig:
    # "volume": the paper's lifter, 3D convolutions over the voxel volume (models/lifter.py); "flat": the volume's
    # z planes stacked into channels and 2D convolutions only (Fast-BEV's space-to-channel, models/flat_lifter.py),
    # a fraction of the MACs so that one quadrant's lift fits between two slices (issue 22)
    form: str = "volume"
    z_conv_stride: int = 2  # the z-strided Conv3d: 0.5 m voxels -> 1 m (form "volume")
    z_pool: int = 2  # AvgPool along z after it: 1 m -> 2 m, then max over what is left (form "volume")
    # heights sampled per image voxel by the projection LUT (calibration/lut.py heights_per_voxel); 1 = the centre.
    # A property of the trained model: training, export and every LUT rebuild must use the same value.
    lut_heights_per_voxel: int = 1
    # the flat lifter's residual k3 conv (form "flat" only): "conv", a full C -> C conv, or "separable", a depthwise
    # k3 conv then a 1x1 conv (MobileNet's factorisation, about a seventh of the MACs): with the image-half layout this
    # conv is most of a quadrant's tail in the phase-locked image lane (issue 22)
    residual: str = "conv"

    def __post_init__(self) -> None:
        _check_types(self)
        _check_positive_int(self, "z_conv_stride", "z_pool", "lut_heights_per_voxel")
        _check_at_most(self, MAX_STRIDE, "z_conv_stride", "z_pool")
        _check_at_most(self, MAX_LUT_HEIGHTS, "lut_heights_per_voxel")
        if self.form not in LIFTER_FORMS:
            raise ValueError(f"LifterConfig.form must be one of {LIFTER_FORMS}, got {self.form!r}")
        if self.residual not in LIFTER_RESIDUALS:
            raise ValueError(f"LifterConfig.residual must be one of {LIFTER_RESIDUALS}, got {self.residual!r}")
        if self.residual != "conv" and self.form != "flat":
            raise ValueError(f"LifterConfig.residual={self.residual!r} needs form 'flat', got form {self.form!r}")


@dataclass(frozen=True)
class BevEncoderConfig:
    """CenterPoint RPN: stage i = one k3 conv with stride layer_strides[i] then layer_nums[i] k3 convs;
    deblock i brings stage i to the head stride (upsample_strides[i] > 1: transposed conv, < 1: strided conv)."""

    layer_nums: tuple[int, ...] = (3, 5, 5)  # extra convs after each stage's first conv
    layer_strides: tuple[int, ...] = (1, 2, 2)  # relative to the previous stage; cumulative 1, 2, 4 pillar cells
    num_filters: tuple[int, ...] = (64, 128, 256)
    upsample_strides: tuple[float, ...] = (0.25, 0.5, 1.0)  # each scale to stride 4
    num_upsample_filters: tuple[int, ...] = (128, 128, 128)  # concat = 384 channels into the head

    def __post_init__(self) -> None:
        _check_types(self)
        n = len(self.layer_nums)
        for name in ("layer_strides", "num_filters", "upsample_strides", "num_upsample_filters"):
            if len(getattr(self, name)) != n:
                raise ValueError(
                    f"BevEncoderConfig.{name} must have {n} entries like layer_nums, got {getattr(self, name)!r}"
                )
        if n == 0:
            raise ValueError("BevEncoderConfig.layer_nums must not be empty")
        if any(v < 0 for v in self.layer_nums):
            raise ValueError(f"BevEncoderConfig.layer_nums must be >= 0, got {self.layer_nums!r}")
        for name in ("layer_strides", "num_filters", "num_upsample_filters"):
            if any(int(v) != v or v < 1 for v in getattr(self, name)):
                raise ValueError(f"BevEncoderConfig.{name} must be positive integers, got {getattr(self, name)!r}")
        if any(not v > 0 for v in self.upsample_strides):
            raise ValueError(f"BevEncoderConfig.upsample_strides must be > 0, got {self.upsample_strides!r}")
        if n > MAX_BEV_STAGES:
            raise ValueError(f"BevEncoderConfig.layer_nums has {n} stages, over the limit {MAX_BEV_STAGES}")
        for name, limit in (("layer_nums", MAX_LAYERS_PER_STAGE), ("layer_strides", MAX_STRIDE),
                            ("num_filters", MAX_CHANNELS), ("num_upsample_filters", MAX_CHANNELS)):  # fmt: skip
            if any(v > limit for v in getattr(self, name)):
                raise ValueError(f"BevEncoderConfig.{name} must be <= {limit}, got {getattr(self, name)!r}")
        if any(not 1.0 / MAX_STRIDE <= v <= MAX_STRIDE for v in self.upsample_strides):
            raise ValueError(f"BevEncoderConfig.upsample_strides must be in [1/{MAX_STRIDE}, {MAX_STRIDE}], got {self.upsample_strides!r}")

    @property
    def cumulative_strides(self) -> tuple[int, ...]:
        return tuple(math.prod(self.layer_strides[: i + 1]) for i in range(len(self.layer_strides)))

    @property
    def out_channels(self) -> int:
        return sum(self.num_upsample_filters)


@dataclass(frozen=True)
class HeadConfig:
    head_channels: int = 64  # shared conv output and every branch's hidden conv
    multi_head: bool = False  # False: one head for all classes (the paper); True: CenterPoint's task heads
    tasks: tuple[tuple[str, ...], ...] = NUSCENES_TASKS  # used only when multi_head
    out_stride: int = 4  # head map cell = out_stride pillar cells
    final_kernel: int = 3  # kernel of each branch's output conv (CenterPoint: 3)
    heatmap_bias_init: float = -2.19  # CenterPoint: sigmoid(-2.19) ~ 0.1 prior

    def __post_init__(self) -> None:
        _check_types(self)
        _check_positive_int(self, "head_channels", "out_stride", "final_kernel")
        _check_at_most(self, MAX_CHANNELS, "head_channels")
        _check_at_most(self, MAX_STRIDE, "out_stride")
        _check_at_most(self, MAX_KERNEL, "final_kernel")
        if self.final_kernel % 2 == 0:
            raise ValueError(f"HeadConfig.final_kernel must be odd (same-size padding), got {self.final_kernel!r}")
        flat = [c for task in self.tasks for c in task]
        if sorted(flat) != sorted(CLASS_NAMES):
            raise ValueError(f"HeadConfig.tasks must cover each of {CLASS_NAMES} exactly once, got {self.tasks!r}")


@dataclass(frozen=True)
class PostConfig:
    top_k: int = 500  # detections per quadrant out of the graph (the paper's top 500)
    score_threshold: float = 0.1  # applied by the runtime after the graph
    nms_iou_threshold: tuple[float, ...] = (0.2,) * len(CLASS_NAMES)  # BEV rotated IoU, per class in CLASS_NAMES order
    max_detections: int = 500  # per slice after NMS

    def __post_init__(self) -> None:
        _check_types(self)
        _check_positive_int(self, "top_k", "max_detections")
        _check_at_most(self, MAX_DETECTIONS, "top_k", "max_detections")
        if not 0.0 <= self.score_threshold < 1.0:
            raise ValueError(f"PostConfig.score_threshold must be in [0, 1), got {self.score_threshold!r}")
        if len(self.nms_iou_threshold) != len(CLASS_NAMES) or any(not 0.0 < t <= 1.0 for t in self.nms_iou_threshold):
            raise ValueError(
                f"PostConfig.nms_iou_threshold must hold {len(CLASS_NAMES)} values in (0, 1], got {self.nms_iou_threshold!r}"
            )


@dataclass(frozen=True)
class Preset:
    name: str
    grid: GridSpec = field(default_factory=GridSpec)
    channels: int = 64  # c: pillar features, FPN output and image BEV alike
    image: ImageConfig = field(default_factory=ImageConfig)
    pillars: PillarConfig = field(default_factory=PillarConfig)
    lifter: LifterConfig = field(default_factory=LifterConfig)
    bev: BevEncoderConfig = field(default_factory=BevEncoderConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    post: PostConfig = field(default_factory=PostConfig)
    use_image: bool = True  # False: the LiDAR-only streaming baseline (image_bev is then only read for its shape)
    # True: the image BEV is scaled per channel before fusion (models/image_bev_norm.py) to a learnt RMS
    # (image_bev_target "learnt") or to the point BEV's RMS on the cells that hold points ("point")
    image_bev_norm: bool = False
    image_bev_target: str = "learnt"  # one of IMAGE_BEV_TARGETS
    # True: a slice's net runs on the quadrants it touches (the paper's crop, Sec. III-C); False: on one map of the
    # whole grid per slice, as the paper's LiDAR-only baselines (calibration/slice_maps.py). LiDAR-only nets only.
    slice_crop: bool = True

    def __post_init__(self) -> None:
        _check_types(self)
        _check_positive_int(self, "channels")
        _check_at_most(self, MAX_CHANNELS, "channels")
        if self.image_bev_target not in IMAGE_BEV_TARGETS:
            raise ValueError(f"Preset.image_bev_target must be one of {IMAGE_BEV_TARGETS}, got {self.image_bev_target!r}")
        if self.use_image and not self.slice_crop:
            raise ValueError(
                f"Preset {self.name!r}: slice_crop=False (one whole-grid map per slice) is supported for the LiDAR-only "
                "net only (use_image=False): the image lane's LUT, lifter and cache are built on quadrant maps"
            )
        g = self.grid
        for i, s in enumerate(self.bev.cumulative_strides):
            if g.quadrant_ny % s or g.quadrant_nx % s:
                raise ValueError(
                    f"Preset {self.name!r}: quadrant {g.quadrant_ny} x {g.quadrant_nx} cells is not divisible by "
                    f"bev stage {i}'s stride {s} (bev.layer_strides={self.bev.layer_strides})"
                )
            if abs(s / self.bev.upsample_strides[i] - self.head.out_stride) > 1e-9:
                raise ValueError(
                    f"Preset {self.name!r}: bev.upsample_strides[{i}]={self.bev.upsample_strides[i]} brings stride {s} "
                    f"to {s / self.bev.upsample_strides[i]}, not head.out_stride={self.head.out_stride}"
                )
            u = self.bev.upsample_strides[i]
            factor = u if u >= 1 else 1.0 / u
            if abs(factor - round(factor)) > 1e-9:
                raise ValueError(f"Preset {self.name!r}: bev.upsample_strides[{i}]={u} is neither an integer nor 1/integer")
        if g.quadrant_ny % self.head.out_stride or g.quadrant_nx % self.head.out_stride:
            raise ValueError(
                f"Preset {self.name!r}: quadrant {g.quadrant_ny} x {g.quadrant_nx} is not divisible by head.out_stride={self.head.out_stride}"
            )
        z_div = self.lifter.z_conv_stride * self.lifter.z_pool
        if self.lifter.form == "volume" and g.nz % z_div:
            raise ValueError(
                f"Preset {self.name!r}: grid.nz={g.nz} image voxels is not divisible by lifter z_conv_stride * z_pool = {z_div}"
            )

    # ---- derived sizes -----------------------------------------------------------------------------
    @property
    def num_classes(self) -> int:
        return len(CLASS_NAMES)

    @property
    def head_cell_m(self) -> float:
        """Edge of one head-map cell in metres."""
        return self.grid.voxel_xy_m * self.head.out_stride

    @property
    def map_cells(self) -> tuple[int, int]:
        """(rows, cols) of one slice map in pillar cells: a quadrant, or the whole grid without the crop."""
        return map_cells(self.grid, self.slice_crop)

    @property
    def head_map_size(self) -> tuple[int, int]:
        """(Hh, Wh) of one slice map's head maps (a quadrant's, or the whole grid's without the crop)."""
        rows, cols = self.map_cells
        return rows // self.head.out_stride, cols // self.head.out_stride

    @property
    def top_k(self) -> int:
        """Detections per quadrant out of the graph: post.top_k clamped to classes x cells."""
        hh, wh = self.head_map_size
        return min(self.post.top_k, self.num_classes * hh * wh)

    # ---- serialisation -----------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"name": self.name, "grid": self.grid.to_dict(), "channels": self.channels}
        for name in ("image", "pillars", "lifter", "bev", "head", "post"):
            d[name] = _plain(dataclasses.asdict(getattr(self, name)))
        d["use_image"] = self.use_image
        # options added after manifests were shipped are written only when set: a preset without them keeps the
        # exact dict (and manifest) it had
        if d["image"]["norm"] == "batch":
            del d["image"]["norm"]
        if d["lifter"]["lut_heights_per_voxel"] == 1:
            del d["lifter"]["lut_heights_per_voxel"]
        if d["lifter"]["residual"] == "conv":
            del d["lifter"]["residual"]
        if self.image_bev_norm:
            d["image_bev_norm"] = True
        if self.image_bev_target != "learnt":
            d["image_bev_target"] = self.image_bev_target
        if not self.slice_crop:
            d["slice_crop"] = False
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Preset":
        """The preset of ``to_dict`` (a manifest's, a checkpoint's), read as untrusted: ValueError (one line, naming
        the field) for a malformed one. Every value must have its field's own type, never coerced: an integer where
        an int is (8.9 channels is refused, not read as 8), true / false where a bool is (``"no"`` is refused, not
        read as True), a finite number where a float is, a string, a list of them. A field absent from a sub-config
        takes its default (an option added after the file was written: ``to_dict`` leaves defaults out); the
        top-level fields (but the optional image_bev_norm, image_bev_target, slice_crop), ``head.tasks`` and
        ``post.nms_iou_threshold`` are required."""
        try:
            if not isinstance(d, Mapping):
                raise ValueError(f"preset dict is malformed: expected a mapping of fields, got {_short(d)}")
            return cls(
                name=_typed(d["name"], str, "name"),
                grid=_grid(d["grid"]),
                channels=_typed(d["channels"], int, "channels"),
                image=_sub_config(ImageConfig, d["image"], "image"),
                pillars=_sub_config(PillarConfig, d["pillars"], "pillars"),
                lifter=_sub_config(LifterConfig, d["lifter"], "lifter"),
                bev=_sub_config(BevEncoderConfig, d["bev"], "bev"),
                head=_sub_config(HeadConfig, d["head"], "head", required=("tasks",)),
                post=_sub_config(PostConfig, d["post"], "post", required=("nms_iou_threshold",)),
                use_image=_typed(d["use_image"], bool, "use_image"),
                image_bev_norm=_typed(d.get("image_bev_norm", False), bool, "image_bev_norm"),
                image_bev_target=_typed(d.get("image_bev_target", "learnt"), str, "image_bev_target"),
                slice_crop=_typed(d.get("slice_crop", True), bool, "slice_crop"),
            )
        except KeyError as e:
            raise ValueError(f"preset dict lacks the field {e.args[0]!r}") from None
        except (TypeError, AttributeError, OverflowError, ZeroDivisionError, RecursionError) as e:  # a value the
            # checks above let through but a dataclass cannot take: still one line, never a traceback
            raise ValueError(f"preset dict is malformed: {e}") from None


# ---- reading a preset dict (Preset.from_dict) ---------------------------------------------------------------


def _short(value: Any) -> str:
    """A value for a one-line message: its type and a repr cut short (a field may hold a megabyte list)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        return f"an integer of {value.bit_length()} bits"  # past 4300 digits repr itself fails
    text = reprlib.repr(value)  # nesting and lengths capped: a deeply nested list is no RecursionError
    return f"{type(value).__name__} {text if len(text) <= 60 else text[:57] + '...'}"


def _finite(value: Any) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer past float range
        return False


def _typed(value: Any, hint: Any, where: str) -> Any:
    """``value`` if it has the type ``hint`` (int, float, bool, str, tuple[X, ...] as a list or tuple: returned as a
    tuple), else ValueError naming ``where``."""
    return _checked(value, hint, where, "preset dict is malformed: ", _FILE_WORDS)


# how ``_checked`` names a bool and a sequence: in a preset dict (JSON: true / false, a list) and in Python, where a
# config's sequence must be a tuple (the configs are frozen, so hashable: a list field would make them unhashable)
_FILE_WORDS = ("true or false", "a list", (list, tuple))
_PYTHON_WORDS = ("True or False", "a tuple", (tuple,))


def _checked(value: Any, hint: Any, where: str, prefix: str, words: tuple[str, str, tuple[type, ...]]) -> Any:
    """``_typed``'s check, its messages prefixed with ``prefix`` and naming bools and sequences with ``words``."""
    boolean, sequence, sequence_types = words
    if hint is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{prefix}{where} must be {boolean}, got {_short(value)}")
    elif hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{prefix}{where} must be an integer, got {_short(value)}")
        if value.bit_length() > 63:  # every field's own bound is far below; such a number is no preset's
            raise ValueError(f"{prefix}{where} must be an integer below 2**63, got {_short(value)}")
    elif hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not _finite(value):
            raise ValueError(f"{prefix}{where} must be a finite number, got {_short(value)}")
    elif hint is str:
        if not isinstance(value, str):
            raise ValueError(f"{prefix}{where} must be a string, got {_short(value)}")
    elif typing.get_origin(hint) is tuple:
        if not isinstance(value, sequence_types):
            raise ValueError(f"{prefix}{where} must be {sequence}, got {_short(value)}")
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_checked(v, args[0], f"{where}[{i}]", prefix, words) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ValueError(f"{prefix}{where} must hold {len(args)} entries, got {_short(value)}")
        return tuple(_checked(v, a, f"{where}[{i}]", prefix, words) for i, (v, a) in enumerate(zip(value, args)))
    else:  # a field type this reader does not know: a programming error, named rather than let through
        raise TypeError(f"{where}: no reader for the field type {hint!r}")
    return value


def _check_types(obj: Any) -> None:
    """Each field of the config dataclass ``obj`` of its own type, as strictly as ``Preset.from_dict`` reads it
    (``_typed``: no bool for an int, a finite number for a float, ...), a tuple for a sequence and a sub-config
    (the grid included) of its class: else ValueError naming the field and quoting the value. Called first in each
    ``__post_init__``, so that a config the constructor takes is one whose ``to_dict`` reads back."""
    for name, hint in _fields(type(obj)).items():
        value, where = getattr(obj, name), f"{type(obj).__name__}.{name}"
        if typing.get_origin(hint) is None and isinstance(hint, type) and hint not in (bool, int, float, str):
            if not isinstance(value, hint):
                raise ValueError(f"{where} must be a {hint.__name__}, got {_short(value)}")
        else:
            _checked(value, hint, where, "", _PYTHON_WORDS)


@functools.cache
def _fields(config: type) -> dict[str, Any]:
    """The fields of a config dataclass and their types (resolved: this module's annotations are strings); cached,
    so not to be modified."""
    hints = typing.get_type_hints(config)
    return {f.name: hints[f.name] for f in dataclasses.fields(config)}


def _sub_config(config: type, raw: Any, key: str, required: tuple[str, ...] = ()) -> Any:
    """``config(**raw)`` with every entry of ``raw`` checked (``_typed``); an absent field takes its default."""
    if not isinstance(raw, Mapping):
        raise ValueError(f"preset dict is malformed: {key} must be a mapping of {config.__name__}'s fields, got {_short(raw)}")
    fields = _fields(config)
    for name in required:
        if name not in raw:
            raise KeyError(name)
    kwargs = {}
    for name, value in raw.items():
        if name not in fields:
            raise ValueError(f"preset dict is malformed: {key}.{name} is not a field of {config.__name__} "
                             f"(it has {', '.join(fields)})")  # fmt: skip
        kwargs[name] = _typed(value, fields[name], f"{key}.{name}")
    return config(**kwargs)


_GRID_FIELDS = {"x_range_m": tuple[float, float], "y_range_m": tuple[float, float], "z_range_m": tuple[float, float],
                "voxel_xy_m": float, "voxel_z_m": float}  # GridSpec.to_dict's, all required  # fmt: skip


def _grid(raw: Any) -> GridSpec:
    """The grid of ``GridSpec.to_dict``, every field checked first (GridSpec.from_dict would read "0.4" as 0.4)."""
    if not isinstance(raw, Mapping):
        raise ValueError(f"preset dict is malformed: grid must be a mapping of GridSpec's fields, got {_short(raw)}")
    for name in raw:
        if name not in _GRID_FIELDS:
            raise ValueError(f"preset dict is malformed: grid.{name} is not a field of GridSpec (it has {', '.join(_GRID_FIELDS)})")
    checked = {}
    for name, hint in _GRID_FIELDS.items():
        if name not in raw:
            raise KeyError(f"grid.{name}")
        checked[name] = _typed(raw[name], hint, f"grid.{name}")
    return GridSpec.from_dict(checked)


def _plain(x: Any) -> Any:
    """Tuples -> lists, recursively, so to_dict() is JSON-ready and compares equal after a JSON round trip."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (tuple, list)):
        return [_plain(v) for v in x]
    return x


def _check_positive_int(obj: Any, *names: str) -> None:
    for name in names:
        v = getattr(obj, name)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{type(obj).__name__}.{name} must be a positive integer, got {v!r}")


def _check_at_most(obj: Any, limit: int, *names: str) -> None:
    """After ``_check_positive_int``: each field at most ``limit``."""
    for name in names:
        v = getattr(obj, name)
        if v > limit:
            raise ValueError(f"{type(obj).__name__}.{name} must be <= {limit}, got {v!r}")


def _paper() -> Preset:
    return Preset(name="paper")  # every default above is the paper's number


def _small() -> Preset:
    return Preset(
        name="small",
        grid=GridSpec(voxel_xy_m=0.4, voxel_z_m=2.0),  # 256 x 256 pillars, quadrant 128 x 128; volume z 4
        channels=32,
        image=ImageConfig(width_px=384, height_px=216, backbone_depth=18, width_divisor=2),  # features 96 x 54
        pillars=PillarConfig(max_points_per_pillar=16, max_pillars=8000),
        bev=BevEncoderConfig(
            # every stage strided: the 128 x 128 full-resolution convs would cost more than the rest together
            layer_nums=(1, 1, 1),
            layer_strides=(2, 2, 2),  # cumulative 2, 4, 8 pillar cells = 0.8, 1.6, 3.2 m
            num_filters=(32, 64, 128),
            upsample_strides=(1.0, 2.0, 4.0),  # all to stride 2 (0.8 m head cells)
            num_upsample_filters=(32, 32, 32),
        ),
        head=HeadConfig(head_channels=16, out_stride=2),
    )


def _tiny() -> Preset:
    return Preset(
        name="tiny",
        grid=GridSpec(x_range_m=(-12.8, 12.8), y_range_m=(-12.8, 12.8), voxel_xy_m=0.4, voxel_z_m=2.0),  # 64 x 64 x 4
        channels=8,
        image=ImageConfig(width_px=128, height_px=72, backbone_depth=18, width_divisor=8),
        pillars=PillarConfig(max_points_per_pillar=8, max_pillars=1024),
        bev=BevEncoderConfig(
            layer_nums=(1, 1),
            layer_strides=(1, 2),
            num_filters=(8, 16),
            upsample_strides=(0.5, 1.0),
            num_upsample_filters=(8, 8),
        ),
        head=HeadConfig(head_channels=8, out_stride=2),
        post=PostConfig(top_k=50),
    )


def _small_v2() -> Preset:
    # small with the camera lane's fixes of issue 19: a backbone BatchNorm frozen after image pretraining
    # (streamdet-train-image, then streamdet-train --init), the image BEV brought to the point BEV's scale at
    # fusion, two heights per 2 m voxel in the LUT (coverage of short objects: docs/training/issue19_plan.md)
    small = _small()
    return dataclasses.replace(
        small,
        name="small_v2",
        image=dataclasses.replace(small.image, norm="frozen_batch"),
        # the flat lifter (issue 22): a quadrant's lift short enough for the phase-locked image lane, and a fused
        # training step that is no longer mostly Conv3d backward
        lifter=dataclasses.replace(small.lifter, form="flat", lut_heights_per_voxel=2),
        image_bev_norm=True,
    )


def _small_v3() -> Preset:
    # small_v2 with the image BEV brought to the point BEV's RMS on occupied cells instead of a learnt gain (issue 19
    # item 2: trained, small_v2's learnt gain kept the image half well below the point half's scale; measured in
    # docs/training/issue19_plan.md)
    return dataclasses.replace(_small_v2(), name="small_v3", image_bev_target="point")


def _small_v3_lite() -> Preset:
    # small_v3 with a lighter image lane for the phase-locked schedule (issue 22): a quarter-width ResNet-18 (base
    # width 16) at 320 x 180 (features 80 x 45). The encoder is the image lane's largest cost per camera frame and
    # the staleness a slice sees is bounded below by a frame's encode + lift; this one's int8 encoder costs about
    # 0.4 of small_v3's per frame (measured: docs/replay.md "A lighter image lane"). Everything after the encoder
    # (lifter, two LUT heights, fusion, slice net) is small_v3's.
    v3 = _small_v3()
    return dataclasses.replace(
        v3, name="small_v3_lite", image=dataclasses.replace(v3.image, width_px=320, height_px=180, width_divisor=4)
    )


def _small_v3_thin() -> Preset:
    # small_v3_lite with a thinner slice net for 2-core AVX2-only parts at nuScenes rates (issue 22): the slice graph
    # runs 160 times a second there, and small_v3_lite's needed more than one of the two cores (docs/replay.md "On an
    # AVX2-only part"). Half the BEV encoder's widths and a head of 8 channels per branch: about a third of the slice
    # graph's MACs. The camera lane (encoder, lifter) and the pillar net are small_v3_lite's, so a run can start from
    # its weights (streamdet-train --init models/weights/small_lite.pt).
    lite = _small_v3_lite()
    return dataclasses.replace(
        lite,
        name="small_v3_thin",
        bev=dataclasses.replace(lite.bev, num_filters=(16, 32, 64), num_upsample_filters=(16, 16, 16)),
        head=dataclasses.replace(lite.head, head_channels=8),
    )


def _small_v3_swift() -> Preset:
    # small_v3_thin with a lighter camera lane for the phase-locked image lane's 25 ms line (issue 22): 224 x 126
    # images (features 56 x 32, about half the encoder's MACs at 320 x 180: the frame a slice waits for must be
    # encoded, its term run and the quadrant's tail run within about 9 ms of the camera's trigger, and the encoder is
    # the largest of the three) and the flat lifter's residual conv factorised (depthwise k3 + 1x1), the largest conv
    # of a quadrant's tail with the image-half layout. The weights of every layer but that residual keep their
    # shapes, so a run can start from small_v3_thin's (docs/training/issue22/reproduce_swift.sh).
    thin = _small_v3_thin()
    return dataclasses.replace(
        thin,
        name="small_v3_swift",
        image=dataclasses.replace(thin.image, width_px=224, height_px=126),
        lifter=dataclasses.replace(thin.lifter, residual="separable"),
    )


_PRESETS = {
    "paper": _paper,
    "small": _small,
    "tiny": _tiny,
    "small_v2": _small_v2,
    "small_v3": _small_v3,
    "small_v3_lite": _small_v3_lite,
    "small_v3_thin": _small_v3_thin,
    "small_v3_swift": _small_v3_swift,
}


def preset_names() -> tuple[str, ...]:
    return tuple(_PRESETS)


def get_preset(name: str) -> Preset:
    """The named preset; ``dataclasses.replace`` derives variants (e.g. ``use_image=False``)."""
    try:
        return _PRESETS[name]()
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; known presets: {', '.join(_PRESETS)}") from None
