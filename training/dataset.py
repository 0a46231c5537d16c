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
import shutil
import warnings
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from streamdet.core.table_version import DEFAULT_TABLE_VERSION
from streamdet.calibration.camera import Rig
from streamdet.calibration.sectors import cameras_overlapping_sector
from streamdet.core.boxes import BOX_DIM
from streamdet.core.classes import CLASS_NAMES, NUM_CLASSES
from streamdet.core.file_input import read_regular_file
from streamdet.core.file_output import writer_alive
from streamdet.core.json_input import read_json, short_repr
from streamdet.core.sectors import check_num_slices, quadrants_of_sector
from streamdet.core.slicing import boxes_in_sector, split_sweep
from streamdet.data.nuscenes import LIDAR_CHANNEL, NuScenesReader
from streamdet.data.splits import SPLITS_FILE, split_scenes
from streamdet.models.presets import Preset
from streamdet.runtime_ort.pillarize import Pillars, pillarize
from streamdet.training.targets import MapTargets, TargetConfig, build_targets

# v2: the key and meta.json carry the data's fingerprint (``data_fingerprint``); a v1 folder is never matched again
CACHE_FORMAT = "streamdet-train-cache-v2"
CACHE_SOURCE_FILE = "source.json"  # {root, version, split, image_size}: small, read when pruning stale caches
_TMP_MARK = ".tmp"  # a cache being written: <folder name>.tmp<pid of its writer>
MAX_CACHE_META_BYTES = 1 << 30  # meta.json: tokens and rigs, a few kB per sample (about 100 MB for trainval)
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
    version: str = DEFAULT_TABLE_VERSION,
    cache_dir: str | Path | None = None,
    progress=None,
    echo: Callable[[str], None] | None = None,
) -> SampleStore:
    """Read every sample of the split's scenes (in table order). ``image_size`` (W, H) resizes the images;
    None skips them. With ``cache_dir``, a finished cache of the same dataset, split and size is memory-mapped
    instead, and a new one is written after reading; the caches it supersedes are removed then
    (``prune_stale_caches``), each named to ``echo``."""
    reader = NuScenesReader(root, version)
    scenes = set(split_scenes(root, split))
    tokens = tuple(t for t in reader.sample_tokens if reader.scene_name(t) in scenes)
    if not tokens:
        raise ValueError(f"split {split!r} of {root} holds no samples (scenes {sorted(scenes)})")
    folder = fingerprint = None
    if cache_dir is not None:
        # The data's fingerprint is part of the key: a regenerated or edited dataset (same tokens, other boxes, sweeps
        # or images) gets a new cache instead of silently training on the old one's arrays.
        fingerprint = data_fingerprint(reader, root, version, tokens, with_images=image_size is not None)
        source = _cache_source(root, version, split, image_size)
        key = hashlib.sha256(json.dumps({**source, "tokens": tokens, "data": fingerprint}).encode()).hexdigest()[:16]
        folder = Path(cache_dir) / f"{split}-{key}"
        if (folder / "meta.json").is_file():
            return _load_cache(folder, tokens, image_size, fingerprint)

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
        _save_cache(store, folder, fingerprint, source)
        for stale in prune_stale_caches(folder):
            if echo is not None:
                echo(f"removed the stale training cache {stale} (superseded by {folder.name})")
    return store


def _cache_source(root: str | Path, version: str, split: str, image_size: tuple[int, int] | None) -> dict:
    """What a cache folder is a cache of, but for the data's fingerprint: a newer folder of the same source
    replaces an older one (``prune_stale_caches``)."""
    size = None if image_size is None else [int(v) for v in image_size]
    return {"root": str(Path(root).resolve()), "version": version, "split": split, "image_size": size}


def data_fingerprint(reader: NuScenesReader, root: str | Path, version: str, tokens: tuple[str, ...], with_images: bool) -> str:
    """sha256 over (name, size, mtime_ns) of every file a store of ``tokens`` is read from: the tables, splits.json,
    each sample's key-frame LiDAR file and (``with_images``) its camera images.

    Sizes and modification times, not the bytes: hashing trainval's sweeps and images on every start would cost as
    much as decoding them, which the cache exists to avoid; any rewrite (``streamdet-synth --overwrite``, an edited
    table) changes the mtime."""
    entries = []

    def add(path: Path) -> None:
        st = path.stat()
        entries.append((str(path), st.st_size, st.st_mtime_ns))

    table_dir = Path(root) / version
    for path in sorted(table_dir.iterdir()):
        if path.is_file():
            add(path)
    if (Path(root) / SPLITS_FILE).is_file():
        add(Path(root) / SPLITS_FILE)
    wanted = set(tokens)
    files: dict[str, list[Path]] = {t: [] for t in tokens}
    for sd in reader.rows("sample_data"):
        # the reader checked sample_token and is_key_frame of every row when it indexed the table
        if sd["is_key_frame"] is not True or sd["sample_token"] not in wanted:
            continue
        sd = reader.row("sample_data", sd)
        channel = reader.channel(sd)
        if channel == LIDAR_CHANNEL or (with_images and channel.startswith("CAM_")):
            files[sd["sample_token"]].append(reader.file(sd))
    for token in tokens:
        for path in sorted(files[token]):
            add(path)
    return hashlib.sha256(json.dumps(entries).encode()).hexdigest()


_ARRAYS = ("points", "point_offsets", "boxes", "labels", "num_lidar_pts", "num_radar_pts", "box_offsets", "images")


def _save_cache(store: SampleStore, folder: Path, fingerprint: str | None, source: dict) -> None:
    tmp = folder.with_name(folder.name + f"{_TMP_MARK}{os.getpid()}")
    tmp.mkdir(parents=True, exist_ok=True)
    (tmp / CACHE_SOURCE_FILE).write_text(json.dumps(source))
    for name in _ARRAYS:
        value = getattr(store, name)
        if value is not None:
            np.save(tmp / f"{name}.npy", value)
    meta = {"format": CACHE_FORMAT, "data_fingerprint": fingerprint, "tokens": list(store.tokens),
            "rigs": [r.to_dict() for r in store.rigs]}
    (tmp / "meta.json").write_text(json.dumps(meta))  # written last: a folder with meta.json is complete
    try:
        os.replace(tmp, folder)
    except OSError:  # another process finished the same cache first; theirs is identical (same key, same data)
        shutil.rmtree(tmp, ignore_errors=True)


# A cache folder's name, as build_store makes it: <split>-<16 hex digits>, and .tmp<pid> while being written.
_CACHE_NAME = re.compile(r"(?P<base>.+-[0-9a-f]{16})(?:\.tmp(?P<pid>[0-9]{1,10}))?")


def prune_stale_caches(folder: Path) -> list[Path]:
    """Remove the cache folders beside ``folder`` that it supersedes, and return them: complete caches of the same
    source (dataset root, version, split, image size: ``source.json``) built from other data, whose arrays no
    later run can load, and caches left half-written by a process that is gone. A cache of another source, one
    from before ``source.json`` existed, one a live process is writing, and anything not named as a cache stay:
    a cache folder given by ``--cache-dir`` may be shared."""
    source = _read_source(folder)
    if source is None:
        return []
    removed = []
    for other in sorted(folder.parent.iterdir()):
        match = _CACHE_NAME.fullmatch(other.name)
        if other == folder or match is None or other.is_symlink() or not other.is_dir():
            continue
        if match["pid"] is not None:
            stale = not writer_alive(int(match["pid"]))
        else:
            stale = (other / "meta.json").is_file() and _read_source(other) == source
        if not stale:
            continue
        try:
            shutil.rmtree(other)
        except OSError as e:  # not ours to remove (permissions), or removed meanwhile by another run
            if other.exists():
                warnings.warn(f"could not remove the stale training cache {other}: {e}", stacklevel=2)
            continue
        removed.append(other)
    return removed


def _read_source(folder: Path) -> dict | None:
    """A cache folder's ``source.json``, or None where it has none or an unreadable one (such a folder is kept)."""
    try:
        doc = json.loads(read_regular_file(folder / CACHE_SOURCE_FILE, 1 << 16))  # never a FIFO: it would block
    except (ValueError, OSError, RecursionError):  # InputFileError is a ValueError
        return None
    return doc if isinstance(doc, dict) else None


def _load_cache(folder: Path, tokens: tuple[str, ...], image_size: tuple[int, int] | None, fingerprint: str) -> SampleStore:
    """The store a cache folder holds, every array checked against meta.json and the expected tokens before training
    reads it: the folder lives inside the dataset by default and travels with it, so it is input like the tables."""
    path = folder / "meta.json"
    meta = read_json(path, "training cache meta", MAX_CACHE_META_BYTES)
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(meta).__name__}; delete {folder}")
    if meta.get("format") != CACHE_FORMAT:
        raise ValueError(f"{folder}: not a {CACHE_FORMAT} cache (format {short_repr(meta.get('format'))}); delete it")
    if meta.get("data_fingerprint") != fingerprint:
        raise ValueError(f"{path}: built from other data than {folder.parent} now holds (data_fingerprint "
                         f"{short_repr(meta.get('data_fingerprint'))}); delete {folder}")  # fmt: skip
    if meta.get("tokens") != list(tokens):
        raise ValueError(f"{path}: 'tokens' are not the split's {len(tokens)} sample tokens in table order; delete {folder}")
    rigs_doc = meta.get("rigs")
    if not isinstance(rigs_doc, list) or len(rigs_doc) != len(tokens):
        got = f"a list of {len(rigs_doc)}" if isinstance(rigs_doc, list) else type(rigs_doc).__name__
        raise ValueError(f"{path}: 'rigs' must be a list of {len(tokens)} calibration objects, got {got}; delete {folder}")
    rigs = []
    for i, doc in enumerate(rigs_doc):
        if not isinstance(doc, dict):
            raise ValueError(f"{path}: rigs[{i}] must be a calibration object, got {short_repr(doc)}; delete {folder}")
        try:
            rigs.append(Rig.from_calibration_json(doc))
        except (ValueError, KeyError, TypeError, AttributeError, IndexError) as e:
            raise ValueError(f"{path}: rigs[{i}] is not a camera rig: {e}; delete {folder}") from None
    arrays = {}
    for name in _ARRAYS:
        file = folder / f"{name}.npy"
        if not file.is_file():
            arrays[name] = None
            continue
        try:
            # never pickles: an object array is refused here whatever numpy's default (mmap refuses it too)
            arrays[name] = np.load(file, mmap_mode="r", allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:  # truncated, not .npy, an object dtype
            raise ValueError(f"{file}: not a readable .npy array ({e}); delete {folder}") from None
    _check_cache_arrays(folder, arrays, len(tokens), rigs, image_size)
    return SampleStore(tokens=tuple(tokens), rigs=tuple(rigs), **arrays)


# dtype and trailing shape of each cached array, as build_store makes them (None: its own check)
_ARRAY_SPECS = {
    "points": (np.float32, (5,)),
    "point_offsets": (np.int64, ()),
    "boxes": (np.float32, (BOX_DIM,)),
    "labels": (np.int64, ()),
    "num_lidar_pts": (np.int64, ()),
    "num_radar_pts": (np.int64, ()),
    "box_offsets": (np.int64, ()),
}


def _check_cache_arrays(folder: Path, a: dict, num_samples: int, rigs: list[Rig], image_size: tuple[int, int] | None) -> None:
    """ValueError naming the array file unless every array has build_store's dtype and shape, the offsets cut the
    flat arrays into ``num_samples`` ranges, labels are detection classes (or -1), boxes and point counts are sane.

    The points' values are not scanned: a trainval cache holds gigabytes of them, read through the memory map only
    as training reaches each sample (and a sweep read from the dataset is not scanned either)."""

    def bad(name: str, why: str) -> ValueError:
        return ValueError(f"{folder / (name + '.npy')}: {why}; delete {folder}")

    for name, (dtype, tail) in _ARRAY_SPECS.items():
        arr = a[name]
        if arr is None:
            raise ValueError(f"{folder / (name + '.npy')} is missing: an incomplete cache; delete {folder}")
        if arr.dtype != dtype or arr.ndim != 1 + len(tail) or tuple(arr.shape[1:]) != tail:
            want = f"(N, {', '.join(map(str, tail))})" if tail else "(N,)"
            raise bad(name, f"expected a {np.dtype(dtype)} array of shape {want}, got {arr.dtype} {tuple(arr.shape)}")
    for offsets, flat in (("point_offsets", "points"), ("box_offsets", "boxes")):
        off = np.asarray(a[offsets])
        if len(off) != num_samples + 1 or off[0] != 0 or off[-1] != len(a[flat]) or np.any(np.diff(off) < 0):
            raise bad(offsets, f"expected {num_samples + 1} non-decreasing offsets from 0 to {len(a[flat])} (the rows of "
                               f"{flat}.npy), got {short_repr(off.tolist())}")  # fmt: skip
    m = len(a["boxes"])
    for name in ("labels", "num_lidar_pts", "num_radar_pts"):
        if len(a[name]) != m:
            raise bad(name, f"{len(a[name])} rows for {m} boxes")
    labels = np.asarray(a["labels"])
    if m and (labels.min() < -1 or labels.max() >= NUM_CLASSES):
        raise bad("labels", f"labels must be -1 (not a detection class) or 0..{NUM_CLASSES - 1}, got "
                            f"{int(labels.min())}..{int(labels.max())}")  # fmt: skip
    if m and not np.isfinite(np.asarray(a["boxes"])).all():
        raise bad("boxes", "holds non-finite values (NaN or inf)")
    for name in ("num_lidar_pts", "num_radar_pts"):
        if m and np.asarray(a[name]).min() < 0:
            raise bad(name, f"negative point counts (min {int(np.asarray(a[name]).min())})")
    images = a["images"]
    if image_size is None:
        if images is not None:
            raise bad("images", "a cache built without images holds images")
        return
    if images is None:
        raise ValueError(f"{folder / 'images.npy'} is missing: an incomplete cache; delete {folder}")
    w, h = image_size
    cams = {len(r) for r in rigs}
    if (images.dtype != np.uint8 or images.ndim != 5 or images.shape[0] != num_samples or images.shape[2:] != (h, w, 3)
            or cams != {images.shape[1]}):  # fmt: skip
        want = f"({num_samples}, {'/'.join(map(str, sorted(cams)))}, {h}, {w}, 3)"
        raise bad("images", f"expected uint8 RGB images of shape {want}, got {images.dtype} {tuple(images.shape)}")


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
