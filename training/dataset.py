"""Per-slice training samples, as the paper builds them: a slice, the camera images around it, its ground truth.

``SampleStore`` holds what training reads from a nuScenes-format dataset (sweeps, boxes, resized images, rigs)
in memory, and mirrors it to a ``.npy`` cache folder so the next run (or the next model) skips the JPEG
decoding. ``SliceDataset`` turns store sample i into a ``SampleItem``: the sample's images and its n streaming
slices (``core/slicing.py``), each pillarised with the runtime's own ``runtime_ort/pillarize.py`` and given
CenterPoint targets on every quadrant it touches. ``collate`` (``training/batching.py``) stacks items into one
batch whose quadrant maps share the batch-norm statistics.

No augmentation: a rotation or flip of the points would have to move the cameras too (the projection LUT is
built for the fixed rig), and the paper trains without one. Randomness (the slice count when several are
trained, the subset of slices) comes from ``(seed, epoch, index)`` only, so any process or worker builds the
same item.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from streamdet.calibration.camera import Rig
from streamdet.calibration.sectors import cameras_overlapping_sector
from streamdet.core.boxes import BOX_DIM
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.sectors import check_num_slices, quadrants_of_sector
from streamdet.core.slicing import boxes_in_sector, split_sweep
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.splits import split_scenes
from streamdet.models.presets import Preset
from streamdet.runtime_ort.pillarize import Pillars, pillarize
from streamdet.training.targets import MapTargets, TargetConfig, build_targets

CACHE_FORMAT = "streamdet-train-cache-v1"
CAMERA_MODES = ("all", "overlapping")


@dataclass(frozen=True)
class DataConfig:
    num_slices: tuple[int, ...] = (8,)  # slice counts; each item draws one (the slice index feature s depends on it)
    max_slices_per_sample: int | None = None  # a random subset of a sample's slices per item; None: all of them
    # "all": the image BEV of a quadrant comes from every camera, as the runtime's image lane builds it (and one
    # lift per touched quadrant serves all slices there); "overlapping": each slice sees only the cameras whose
    # FoV overlaps its sector (the paper's wording), the others read as zero features like a missing camera.
    camera_mode: str = "all"
    min_lidar_points: int = 1  # boxes with fewer LiDAR points in the sweep are not targets (the eval ignores them)
    targets: TargetConfig = field(default_factory=TargetConfig)

    def __post_init__(self) -> None:
        counts = tuple(self.num_slices)
        if not counts:
            raise ValueError("DataConfig.num_slices must name at least one slice count")
        for n in counts:
            check_num_slices(n)
        object.__setattr__(self, "num_slices", counts)
        m = self.max_slices_per_sample
        if m is not None and (isinstance(m, bool) or not isinstance(m, int) or m < 1):
            raise ValueError(f"DataConfig.max_slices_per_sample must be None or a positive integer, got {m!r}")
        if self.camera_mode not in CAMERA_MODES:
            raise ValueError(f"DataConfig.camera_mode must be one of {CAMERA_MODES}, got {self.camera_mode!r}")
        if isinstance(self.min_lidar_points, bool) or not isinstance(self.min_lidar_points, int) or self.min_lidar_points < 0:
            raise ValueError(f"DataConfig.min_lidar_points must be a non-negative integer, got {self.min_lidar_points!r}")


# ---- the store ------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SampleStore:
    """Samples of one split, flattened into arrays (row ranges per sample given by the offset arrays)."""

    tokens: tuple[str, ...]  # (S,) sample tokens
    rigs: tuple[Rig, ...]  # (S,) cameras + lidar2ego + ego2global of each sample
    points: np.ndarray  # (sum N, 5) float32 sweeps: x, y, z, intensity (0..255), ring
    point_offsets: np.ndarray  # (S + 1,) int64
    boxes: np.ndarray  # (sum M, 9) float32 ground truth, LiDAR frame
    labels: np.ndarray  # (sum M,) int64, -1 = not a detection class
    num_lidar_pts: np.ndarray  # (sum M,) int64
    num_radar_pts: np.ndarray  # (sum M,) int64
    box_offsets: np.ndarray  # (S + 1,) int64
    images: np.ndarray | None  # (S, J, H, W, 3) uint8 RGB at the training size; None for LiDAR-only training

    def __len__(self) -> int:
        return len(self.tokens)

    def sweep(self, i: int) -> np.ndarray:
        return self.points[self.point_offsets[i] : self.point_offsets[i + 1]]

    def box_rows(self, i: int) -> slice:
        return slice(int(self.box_offsets[i]), int(self.box_offsets[i + 1]))

    @property
    def image_size(self) -> tuple[int, int] | None:
        """(width, height) of the stored images."""
        return None if self.images is None else (int(self.images.shape[3]), int(self.images.shape[2]))

    def class_sets(self, min_lidar_points: int = 1) -> list[np.ndarray]:
        """Per sample, the detection classes present among its targets (for class-balanced sampling)."""
        out = []
        for i in range(len(self)):
            rows = self.box_rows(i)
            lab = self.labels[rows]
            keep = (lab >= 0) & (self.num_lidar_pts[rows] >= min_lidar_points)
            out.append(np.unique(lab[keep]))
        return out


def build_store(
    root: str | Path,
    split: str,
    image_size: tuple[int, int] | None,
    version: str = "v1.0-synth",
    cache_dir: str | Path | None = None,
    progress=None,
) -> SampleStore:
    """Read every sample of the split's scenes (in table order). ``image_size`` (W, H) resizes the images;
    None skips them. With ``cache_dir``, a finished cache of the same dataset, split and size is memory-mapped
    instead, and a new one is written after reading."""
    reader = NuScenesReader(root, version)
    scenes = set(split_scenes(root, split))
    tokens = tuple(t for t in reader.sample_tokens if reader.scene_name(t) in scenes)
    if not tokens:
        raise ValueError(f"split {split!r} of {root} holds no samples (scenes {sorted(scenes)})")
    key = hashlib.sha256(
        json.dumps({"root": str(Path(root).resolve()), "version": version, "split": split, "tokens": tokens,
                    "image_size": image_size}).encode()  # fmt: skip
    ).hexdigest()[:16]
    folder = Path(cache_dir) / f"{split}-{key}" if cache_dir is not None else None
    if folder is not None and (folder / "meta.json").is_file():
        return _load_cache(folder)

    points, boxes, labels, n_lidar, n_radar, rigs, images = [], [], [], [], [], [], []
    for i, token in enumerate(tokens):
        s = reader.get(token)
        points.append(np.asarray(s.points, np.float32))
        boxes.append(np.asarray(s.gt_boxes, np.float32))
        labels.append(s.gt_labels.astype(np.int64))
        n_lidar.append(s.num_lidar_pts.astype(np.int64))
        n_radar.append(s.num_radar_pts.astype(np.int64))
        rigs.append(s.rig)
        if image_size is not None:
            images.append(s.load_images(image_size))  # (J, H, W, 3)
        if progress is not None:
            progress(i + 1, len(tokens))
    store = SampleStore(
        tokens=tokens,
        rigs=tuple(rigs),
        points=np.concatenate(points),
        point_offsets=np.cumsum([0] + [len(p) for p in points]).astype(np.int64),
        boxes=np.concatenate(boxes).reshape(-1, BOX_DIM),
        labels=np.concatenate(labels),
        num_lidar_pts=np.concatenate(n_lidar),
        num_radar_pts=np.concatenate(n_radar),
        box_offsets=np.cumsum([0] + [len(b) for b in boxes]).astype(np.int64),
        images=np.stack(images) if image_size is not None else None,
    )
    if folder is not None:
        _save_cache(store, folder)
    return store


_ARRAYS = ("points", "point_offsets", "boxes", "labels", "num_lidar_pts", "num_radar_pts", "box_offsets", "images")


def _save_cache(store: SampleStore, folder: Path) -> None:
    tmp = folder.with_name(folder.name + f".tmp{os.getpid()}")
    tmp.mkdir(parents=True, exist_ok=True)
    for name in _ARRAYS:
        value = getattr(store, name)
        if value is not None:
            np.save(tmp / f"{name}.npy", value)
    meta = {"format": CACHE_FORMAT, "tokens": list(store.tokens), "rigs": [r.to_dict() for r in store.rigs]}
    (tmp / "meta.json").write_text(json.dumps(meta))  # written last: a folder with meta.json is complete
    try:
        os.replace(tmp, folder)
    except OSError:  # another process finished the same cache first; theirs is identical
        pass


def _load_cache(folder: Path) -> SampleStore:
    meta = json.loads((folder / "meta.json").read_text())
    if meta.get("format") != CACHE_FORMAT:
        raise ValueError(f"{folder}: not a {CACHE_FORMAT} cache (format {meta.get('format')!r}); delete it")
    arrays = {}
    for name in _ARRAYS:
        path = folder / f"{name}.npy"
        arrays[name] = np.load(path, mmap_mode="r") if path.is_file() else None
    return SampleStore(tokens=tuple(meta["tokens"]), rigs=tuple(Rig.from_calibration_json(r) for r in meta["rigs"]), **arrays)


# ---- items ----------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SliceItem:
    index: int  # k
    num_slices: int  # n
    quadrants: tuple[int, ...]  # increasing
    camera_names: tuple[str, ...]  # cameras overlapping the sector, rig order
    pillars: Pillars
    targets: tuple[MapTargets, ...]  # one per slice map: per quadrant in `quadrants` order, or one without the crop


@dataclass(frozen=True, eq=False)
class SampleItem:
    sample_index: int
    rig: Rig
    images: np.ndarray | None  # (J, H, W, 3) uint8
    slices: tuple[SliceItem, ...]


class SliceDataset:
    """Store sample i -> a ``SampleItem`` with its slices, pillars and targets (a map-style dataset)."""

    def __init__(self, store: SampleStore, preset: Preset, config: DataConfig = DataConfig(), seed: int = 0) -> None:
        if preset.use_image and store.images is None:
            raise ValueError(f"preset {preset.name!r} uses images but the store was built without them (image_size=None)")
        if preset.use_image and store.image_size != (preset.image.width_px, preset.image.height_px):
            raise ValueError(
                f"store images are {store.image_size} (W, H) but preset {preset.name!r} wants "
                f"{(preset.image.width_px, preset.image.height_px)}"
            )
        self.store = store
        self.preset = preset
        self.config = config
        self.seed = seed
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.store)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def class_sets(self) -> list[np.ndarray]:
        return self.store.class_sets(self.config.min_lidar_points)

    def __getitem__(self, i: int) -> SampleItem:
        if not 0 <= i < len(self):
            raise IndexError(f"sample index {i} out of range for {len(self)} samples")
        cfg, p, s = self.config, self.preset, self.store
        rng = np.random.default_rng((self.seed, self.epoch, i))
        n = int(cfg.num_slices[rng.integers(len(cfg.num_slices))])
        ks = np.arange(n)
        if cfg.max_slices_per_sample is not None and cfg.max_slices_per_sample < n:
            ks = np.sort(rng.choice(n, cfg.max_slices_per_sample, replace=False))
        rows = s.box_rows(i)
        keep = (s.labels[rows] >= 0) & (s.num_lidar_pts[rows] >= cfg.min_lidar_points)
        boxes = np.asarray(s.boxes[rows][keep], np.float64)
        labels = np.asarray(s.labels[rows][keep])
        parts = split_sweep(np.asarray(s.sweep(i)), n)
        rig = s.rigs[i]
        slices = []
        for k in ks.tolist():
            quadrants = quadrants_of_sector(k, n)
            in_slice = boxes_in_sector(boxes, k, n)
            pillars = pillarize(parts[k], p.grid, quadrants, p.pillars.max_points_per_pillar, p.pillars.max_pillars,
                                crop=p.slice_crop)  # fmt: skip
            targets = tuple(
                build_targets(boxes[in_slice], labels[in_slice], q, p.grid, p.head.out_stride, cfg.targets, len(CLASS_NAMES))
                for q in (quadrants if p.slice_crop else (None,))  # without the crop: one map of the whole grid
            )
            cams = cameras_overlapping_sector(rig, k, n) if p.use_image else ()
            slices.append(SliceItem(k, n, quadrants, cams, pillars, targets))
        images = np.asarray(s.images[i]) if p.use_image else None
        return SampleItem(sample_index=i, rig=rig, images=images, slices=tuple(slices))


def class_balanced_indices(class_sets: list[np.ndarray], seed: int) -> np.ndarray:
    """CBGS (Zhu et al. 2019, as mmdetection3d's CBGSDataset): per present class, draw samples containing it
    (with replacement) until every class holds about 1 / num_classes of the resampled list. Returns sample
    indices (a multiset); samples without any class are left out."""
    present = sorted({int(c) for cs in class_sets for c in cs})
    if not present:
        raise ValueError("class-balanced sampling needs at least one sample with a target box")
    per_class = {c: np.array([i for i, cs in enumerate(class_sets) if c in cs]) for c in present}
    total = sum(len(v) for v in per_class.values())
    rng = np.random.default_rng(seed)
    frac = 1.0 / len(present)
    out = []
    for c in present:
        ratio = frac / (len(per_class[c]) / total)
        out.append(rng.choice(per_class[c], int(len(per_class[c]) * ratio)))
    return np.concatenate(out).astype(np.int64)
