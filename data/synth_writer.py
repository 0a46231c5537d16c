"""Generate a synthetic dataset in the nuScenes table format and file layout.

``DIR/<version>/*.json`` holds the 13 nuScenes tables with the field names of v1.0-mini (so both
``streamdet.data.nuscenes.NuScenesReader`` and the devkit's ``NuScenes`` table loader read it), LiDAR sweeps go to
``DIR/samples/LIDAR_TOP/*.pcd.bin`` (key frames) and ``DIR/sweeps/LIDAR_TOP/`` (the sweeps between them), images to
``DIR/samples/CAM_*/*.jpg`` (key frames) and, with ``SynthConfig.camera_hz``, ``DIR/sweeps/CAM_*/`` (the camera's
frames between them, ``synth_camera_frames.py``), and ``DIR/splits.json`` names the train / val scenes. Beside each LiDAR file a
``<file>.time`` (float32 per point, the firing time after the sweep start) is a streamdet extension that the
devkit ignores and ``NuScenesReader`` returns as ``Sample.point_time_s``.

Beside each image ``<file>.jpg`` a ``<file>.jpg.mask.npz`` (the devkit ignores it) holds the per-pixel object masks
the renderer knows, at the image's resolution: ``data/synth_masks.py`` defines the format.

``DIR/world.json`` names the world version (``synth_world.WORLD_VERSION``) and, per scene, its start time, roads
and look-alike distractors (read by ``streamdet-synth stats``).

The rig is the real one of the bundled nuScenes sample: LiDAR and camera mountings (calibrated_sensor) and
intrinsics, scaled to the chosen resolution, which must keep the cameras' aspect (``resolution_problem``: the rule
``calibration.lut.check_rig_fits`` that streamdet-train, streamdet-export and the runtime apply). As in nuScenes,
each camera exposes when the LiDAR sweeps across its optical axis (``camera_trigger_times_s``; world 6 on, until then
all at the sweep end): its image shows the ego and every object where they are at that instant, and its
sample_data carries that timestamp and an ego_pose of that time, 2.6 to 45 ms before the key frame's (the LiDAR's:
the sweep end, where the annotations are); docs/synth/timing.md. Every scene, sample and sweep
draws its randomness from its own ``numpy`` generator seeded by (seed, scene, ...), so a dataset is a pure function
of its config.
"""

from __future__ import annotations

import functools
import json
import math
import numbers
import shutil
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from streamdet.calibration.camera import (
    CalibrationError, Rig, make_transform, quaternion_to_matrix,
)  # fmt: skip
from streamdet.calibration.lut import ASPECT_TOLERANCE, check_rig_fits
from streamdet.core.constants import MAX_RESOLUTION_PX, MIN_RESOLUTION_PX, STEM_STRIDE
from streamdet.core.json_input import read_json
from streamdet.core.table_version import DEFAULT_TABLE_VERSION, table_version_problem
from streamdet.data.sample import bundled_sample_dir
from streamdet.data.synth_camera_frames import CameraFrame, camera_frames, camera_trigger_times_s, rotations_per_interval
from streamdet.data.synth_lidar import LidarConfig, SimSweep, simulate_sweep
from streamdet.data.synth_masks import MASK_SUFFIX  # noqa: F401 (re-exported)
from streamdet.data.synth_render import CameraModel, Exposure, Render, render_camera, shadow_raster
from streamdet.data.splits import SPLITS_FILE
from streamdet.data.synth_tables import TABLE_NAMES, Tables, link_records, write_tables
from streamdet.data.synth_trajectories import TRAJECTORIES_FILE, write_trajectories
from streamdet.data.synth_world import (
    DISTRACTOR_KINDS,
    MAX_WORLD_BYTES,
    WORLD_FILE,
    WORLD_VERSION,
    Kind,
    Scene,
    WorldConfig,
    make_scene,
)


DEFAULT_VERSION = DEFAULT_TABLE_VERSION


# ---- the layout of a dataset's root ----------------------------------------------------------------------------
# What generate_dataset (and the CLI's --preview) write beside the table folder. A --version that names one of them
# would mix the 13 tables into the LiDAR sweeps or the pictures; --overwrite deletes exactly these and nothing else.
LAYOUT_FILES = (SPLITS_FILE, WORLD_FILE, TRAJECTORIES_FILE)
LAYOUT_DIRS = ("samples", "sweeps", "maps", "preview")
# The training cache streamdet-train keeps in its --data folder by default (training/cli.py): streamdet's, and
# derived from the dataset, so it is not someone else's file; it is left in place (it checks its data fingerprint).
TRAINING_CACHE_DIR = ".streamdet_cache"
RESERVED_NAMES = LAYOUT_FILES + LAYOUT_DIRS + (TRAINING_CACHE_DIR,)


def version_problem(version: object) -> str | None:
    """Why ``version`` cannot name the table folder (``OUT/<version>/``), or None.

    It must be one plain folder name inside OUT: not ``.`` or ``..`` (the tables would land in OUT or its parent),
    no path separator (``/``, or ``\\`` which is one on Windows), no NUL, and none of the layout's own names.
    Names are compared case-insensitively: on a case-insensitive file system ``Samples`` is ``samples``.
    """
    problem = table_version_problem(version)
    if problem is not None:
        return problem
    if version.casefold() in {n.casefold() for n in RESERVED_NAMES}:
        return (f"{version!r} is a name the dataset's own layout uses ({', '.join(RESERVED_NAMES)}): the tables "
                "would be mixed into it; choose another")
    return None


@functools.lru_cache(maxsize=1)
def _bundled_rig() -> Rig:
    """The camera rig of the bundled nuScenes sample, at its own image size: the one every dataset is written with."""
    return Rig.from_calibration_json(bundled_sample_dir() / "calibration.json")


def _fits(rig: Rig, width: int, height: int) -> bool:
    try:
        check_rig_fits(rig, rig.names, width, height)
    except CalibrationError:
        return False
    return True


def fitting_resolutions(width: int, height: int, rig: Rig | None = None) -> list[tuple[int, int]]:
    """The image sizes nearest ``width`` x ``height`` that ``rig`` (default: the bundled one) fits, each side
    MIN_RESOLUTION_PX..MAX_RESOLUTION_PX: the one of the nearest width, then the one of the nearest height (one
    entry where they are the same size; ties go to the size nearer the camera's aspect). Sizes a model can take too
    (sides multiples of STEM_STRIDE: streamdet-export's rule) come first: a size suggested here is one every tool
    takes. Whether a size fits is ``check_rig_fits``'s decision, not a rule of this module's."""
    rig = _bundled_rig() if rig is None else rig
    cam = rig.cameras[0]
    aspect = cam.width / cam.height
    lo, hi = MIN_RESOLUTION_PX, MAX_RESOLUTION_PX
    sizes = {(round(h * aspect), h) for h in range(lo, hi + 1)} | {(w, round(w / aspect)) for w in range(lo, hi + 1)}
    sizes = [(w, h) for w, h in sorted(sizes) if lo <= w <= hi and lo <= h <= hi and _fits(rig, w, h)]
    if not sizes:
        return []
    model_sizes = [(w, h) for w, h in sizes if w % STEM_STRIDE == 0 and h % STEM_STRIDE == 0]
    sizes = model_sizes or sizes
    by_width = min(sizes, key=lambda s: (abs(s[0] - width), abs(s[1] - s[0] / aspect)))
    by_height = min(sizes, key=lambda s: (abs(s[1] - height), abs(s[0] - s[1] * aspect)))
    return [by_width] if by_width == by_height else [by_width, by_height]


def resolution_problem(resolution: tuple[int, int]) -> str | None:
    """Why images of ``resolution`` (width, height) do not fit the rig a dataset is written with, or None.

    The rule is ``calibration.lut.check_rig_fits``, the one streamdet-train, streamdet-export and the runtime
    (streamdet-eval, -replay, -study, -run) apply: the images must have the aspect of the rig's cameras, since a
    camera's intrinsics scaled to another aspect describe a distorted image. A dataset at such a size could be
    written, but no tool could use it; the message names the nearest sizes that fit."""
    width, height = resolution
    rig = _bundled_rig()
    if _fits(rig, width, height):
        return None
    cams = ", ".join(f"{w}x{h}, aspect {w / h:.4f}" for w, h in sorted({(c.width, c.height) for c in rig.cameras}))
    near = [f"{w}x{h}" for w, h in fitting_resolutions(width, height, rig)]
    return (f"{width}x{height} (aspect {width / height:.4f}) does not fit the cameras of the rig a dataset is written "
            f"with ({cams}): streamdet-train, streamdet-export and the runtime refuse images of another aspect than "
            f"their cameras' (within {ASPECT_TOLERANCE:.1%}: calibration.lut.check_rig_fits); the nearest "
            f"{'size that fits' if len(near) == 1 else 'sizes that fit'}: {' or '.join(near) or 'none'}")




@dataclass(frozen=True)
class RootSurvey:
    """The entries of an existing dataset root, sorted: what a synth dataset consists of, and the rest."""

    dataset: tuple[Path, ...]  # layout files and folders, table folders: what --overwrite replaces
    kept: tuple[Path, ...]  # streamdet's training cache: neither the dataset's nor foreign
    foreign: tuple[Path, ...]  # anything else: someone else's, never deleted
    marker_problem: str | None  # why world.json does not mark a streamdet-synth dataset; None where it does


def survey_root(root: Path) -> RootSurvey:
    """Sort the entries of ``root`` (an existing folder) into a synth dataset's, streamdet's cache and the rest.

    A table folder counts as the dataset's only when it holds nothing but nuScenes table files (``sample.json``
    among them). Whether the whole is a streamdet-synth dataset is decided by its world.json alone: a real nuScenes
    root has the same ``samples/``, ``sweeps/``, ``maps/`` and table names, and must never be taken for one.
    """
    dataset, kept, foreign = [], [], []
    for entry in sorted(Path(root).iterdir()):
        if entry.name in LAYOUT_FILES + LAYOUT_DIRS or _is_table_folder(entry):
            dataset.append(entry)
        elif entry.name == TRAINING_CACHE_DIR:
            kept.append(entry)
        else:
            foreign.append(entry)
    return RootSurvey(tuple(dataset), tuple(kept), tuple(foreign), _world_problem(Path(root)))


def _is_table_folder(path: Path) -> bool:
    if path.is_symlink() or not path.is_dir():
        return False
    names = {p.name for p in path.iterdir()}
    tables = {f"{n}.json" for n in TABLE_NAMES}
    return "sample.json" in names and names <= tables and all((path / n).is_file() for n in names)


def _world_problem(root: Path) -> str | None:
    """None if ``root/world.json`` is a streamdet-synth world sidecar, else why not (in words)."""
    path = root / WORLD_FILE
    if not path.is_file():
        return f"it has no {WORLD_FILE}"
    try:
        doc = read_json(path, "world file", MAX_WORLD_BYTES)
    except ValueError as e:
        return str(e)
    if type(doc) is not dict or "world_version" not in doc or type(doc.get("scenes")) is not dict:
        return f"its {WORLD_FILE} is not a streamdet-synth world file (no 'world_version' and 'scenes')"
    return None


def remove_dataset_entries(entries: tuple[Path, ...]) -> None:
    """Delete what ``survey_root`` sorted as a synth dataset's. A symlinked entry (``samples/`` linked to another
    disk) loses the link only: what it points to is not inside the dataset root."""
    for entry in entries:
        if entry.is_symlink() or not entry.is_dir():
            entry.unlink()
        else:
            shutil.rmtree(entry)


@dataclass(frozen=True)
class SynthConfig:
    """What ``generate_dataset`` writes."""

    num_scenes: int = 2
    seed: int = 0
    resolution: tuple[int, int] = (800, 450)  # image width, height in pixels
    sweeps_per_sample: int = 1  # LiDAR sweeps per key-frame interval, key frame included (nuScenes: 10)
    # Camera exposures a second, lidar-synced (synth_camera_frames.py); 0: at key frames only (2 Hz). nuScenes: 12.
    camera_hz: float = 0.0
    version: str = DEFAULT_VERSION
    jpeg_quality: int = 92
    val_fraction: float = 0.2  # the last scenes go to val
    world: WorldConfig = field(default_factory=WorldConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)

    def __post_init__(self) -> None:
        if not (isinstance(self.num_scenes, int) and self.num_scenes >= 1):
            raise ValueError(f"SynthConfig.num_scenes must be an integer >= 1, got {self.num_scenes!r}")
        w, h = self.resolution
        lo, hi = MIN_RESOLUTION_PX, MAX_RESOLUTION_PX
        if not (isinstance(w, int) and isinstance(h, int) and lo <= w <= hi and lo <= h <= hi):
            raise ValueError(f"SynthConfig.resolution must be (width, height) with {lo}..{hi} pixels each, "
                             f"got {self.resolution!r}")
        problem = resolution_problem((w, h))
        if problem:
            raise ValueError(f"SynthConfig.resolution {problem}")
        if not (isinstance(self.sweeps_per_sample, int) and 1 <= self.sweeps_per_sample <= 20):
            raise ValueError(f"SynthConfig.sweeps_per_sample must be an integer in 1..20, got {self.sweeps_per_sample!r}")
        if self.world.sample_interval_s / self.sweeps_per_sample < self.world.sweep_duration_s - 1e-9:
            raise ValueError(
                f"SynthConfig.sweeps_per_sample={self.sweeps_per_sample}: sweeps of {self.world.sweep_duration_s} s "
                f"do not fit {self.sweeps_per_sample} times in the {self.world.sample_interval_s} s key-frame interval"
            )
        problem = version_problem(self.version)
        if problem:
            raise ValueError(f"SynthConfig.version {problem}")
        rate_hz = 1.0 / self.world.sweep_duration_s  # the LiDAR's: a camera exposes at a crossing, once a rotation at most
        if (isinstance(self.camera_hz, bool) or not isinstance(self.camera_hz, numbers.Real) or not math.isfinite(self.camera_hz)
                or not 0.0 <= self.camera_hz <= rate_hz + 1e-9):
            raise ValueError(f"SynthConfig.camera_hz must be 0 (key frames only) or a rate up to the LiDAR's {rate_hz:g} Hz, "
                             f"got {self.camera_hz!r}")
        if self.camera_hz > 0 and rotations_per_interval(self.world.sample_interval_s, self.world.sweep_duration_s) is None:
            raise ValueError(f"SynthConfig.camera_hz > 0 needs a key-frame interval of whole LiDAR rotations, got "
                             f"{self.world.sample_interval_s} s / {self.world.sweep_duration_s} s")


@dataclass(frozen=True, eq=False)
class RigRecords:
    """The real rig as nuScenes calibrated_sensor fields, plus render models at the output resolution."""

    lidar: dict  # {"translation", "rotation"} LIDAR_TOP -> ego
    cameras: tuple[dict, ...]  # {"name", "translation", "rotation", "camera_intrinsic" (at the resolution)}
    models: tuple[CameraModel, ...]

    @property
    def lidar2ego(self) -> np.ndarray:
        return make_transform(quaternion_to_matrix(self.lidar["rotation"]), self.lidar["translation"])


def real_rig_records(resolution: tuple[int, int], calibration_path: str | Path | None = None) -> RigRecords:
    """LiDAR and camera mountings and intrinsics of the bundled real sample, at ``resolution`` (width, height)."""
    path = Path(calibration_path) if calibration_path else bundled_sample_dir() / "calibration.json"
    calib = json.loads(path.read_text())
    lidar = calib["lidar"]["sensor2ego"]
    cams, models = [], []
    for c in calib["cameras"]:
        s2e = c["sensor2ego"]
        model = CameraModel.from_record(
            c["name"],
            make_transform(quaternion_to_matrix(s2e["rotation_wxyz"]), s2e["translation"]),
            np.asarray(c["K"], dtype=np.float64),
            (int(c["width"]), int(c["height"])),
            resolution,
        )
        cams.append(
            {
                "name": c["name"],
                "translation": list(map(float, s2e["translation"])),
                "rotation": list(map(float, s2e["rotation_wxyz"])),
                "camera_intrinsic": model.K.tolist(),
            }
        )
        models.append(model)
    return RigRecords(
        lidar={"translation": list(map(float, lidar["translation"])), "rotation": list(map(float, lidar["rotation_wxyz"]))},
        cameras=tuple(cams),
        models=tuple(models),
    )


@dataclass(frozen=True, eq=False)
class SimFrame:
    """Everything simulated for one key frame."""

    scene: Scene
    index: int  # key frame number in the scene
    t_s: float  # scene time of the key frame (end of its sweep)
    timestamp_us: int
    sweep: SimSweep  # the key-frame sweep
    past_sweeps: tuple[SimSweep, ...]  # the sweeps between the previous key frame and this one, newest first
    renders: dict[str, Render]  # by camera name
    camera_times_s: dict[str, float]  # by camera name: scene time of its exposure (camera_trigger_times_s)
    annotated: np.ndarray  # (M,) int64 indices into scene.objects of the annotated objects
    num_lidar_pts: np.ndarray  # (M,) points of the key-frame sweep inside each annotated box (count_points_in_boxes)
    visibility: np.ndarray  # (M,) float: visible / unoccluded pixels over the six cameras (NaN: in no image)


def simulate_frame(scene: Scene, index: int, rig: RigRecords, config: SynthConfig) -> SimFrame:
    """Simulate key frame ``index`` of ``scene``: its sweeps, the six images and the annotation facts."""
    t_s = float(scene.sample_times_s[index])
    lidar2ego = rig.lidar2ego
    step = scene.config.sample_interval_s / config.sweeps_per_sample
    sweeps = []
    for j in range(config.sweeps_per_sample):
        rng = np.random.default_rng([config.seed, scene.index, index, j, 1])
        sweeps.append(simulate_sweep(scene, t_s - j * step, lidar2ego, rng, config.lidar))
    renders = {}
    # Each camera at its own exposure time: the ego, the objects and their shadows where they are then.
    camera_times = camera_trigger_times_s(rig, t_s, scene.config.sweep_duration_s, config.lidar)
    for c, model in enumerate(rig.models):
        rng, exposure = _key_frame_camera(config, scene, index, c)
        t_cam = camera_times[model.name]
        renders[model.name] = render_camera(scene, t_cam, model, rng, shadows=shadow_raster(scene, t_cam), exposure=exposure)
    objs = scene.objects
    ego_xy = scene.ego_xy(t_s)
    boxes = objs.boxes_at(t_s)
    dist = np.linalg.norm(boxes[:, :2] - ego_xy, axis=1)
    annotated = np.flatnonzero(objs.annotated & (dist <= scene.config.annotation_range_m))
    # nuScenes' num_lidar_pts: the key-frame sweep's points inside the box at the sample time, as the devkit's
    # points_in_box counts them, not the rays that hit the object: a mover's points that trail its key-time box (by
    # up to a sweep's motion) are left out, and ground, a neighbour's bumper or a pole inside the box count.
    lidar2global = scene.ego2global(sweeps[0].t_end_s) @ lidar2ego
    points_global = sweeps[0].points[:, :3].astype(np.float64) @ lidar2global[:3, :3].T + lidar2global[:3, 3]
    own = sum(r.own_pixels for r in renders.values())
    seen = sum(np.bincount(r.object_id[r.object_id >= 0], minlength=len(objs)) for r in renders.values())
    with np.errstate(invalid="ignore", divide="ignore"):
        visibility = np.where(own > 0, seen / np.maximum(own, 1), np.nan)
    return SimFrame(
        scene=scene,
        index=index,
        t_s=t_s,
        timestamp_us=scene.timestamp_us(t_s),
        sweep=sweeps[0],
        past_sweeps=tuple(sweeps[1:]),
        renders=renders,
        camera_times_s=camera_times,
        annotated=annotated,
        num_lidar_pts=count_points_in_boxes(points_global, boxes[annotated]),
        visibility=visibility[annotated],
    )


def _key_frame_camera(config: SynthConfig, scene: Scene, key_index: int, camera: int) -> tuple[np.random.Generator, Exposure]:
    """The random generator of key frame ``key_index``'s image of camera ``camera`` (its index in the rig), and the
    auto exposure drawn from it first: the camera's sweeps filed under that key frame take the same exposure."""
    rng = np.random.default_rng([config.seed, scene.index, key_index, camera, 2])
    return rng, Exposure.draw(rng)


def scene_camera_frames(scene: Scene, rig: RigRecords, config: SynthConfig) -> dict[str, list[CameraFrame]]:
    """Every camera exposure of ``scene`` (``synth_camera_frames.camera_frames``), by camera name, in time order."""
    c = scene.config
    step = c.sample_interval_s / config.sweeps_per_sample
    times = scene.sample_times_s
    first_sweep_start = float(times[0]) - (config.sweeps_per_sample - 1) * step - c.sweep_duration_s
    return camera_frames(rig, times, c.sample_interval_s, c.sweep_duration_s, first_sweep_start, config.camera_hz, config.lidar)


def render_camera_sweep(scene: Scene, rig: RigRecords, config: SynthConfig, camera: int, frame: CameraFrame) -> np.ndarray:
    """(H, W, 3) uint8 RGB image of camera ``camera`` (its index in the rig) at a camera sweep ``frame``: the scene
    at that instant, with the exposure of the key frame it is filed under (auto exposure settles over many frames,
    it does not jump at each), its own sensor noise."""
    model = rig.models[camera]
    _, exposure = _key_frame_camera(config, scene, frame.key_index, camera)
    rng = np.random.default_rng([config.seed, scene.index, camera, scene.timestamp_us(frame.t_s), 3])
    render = render_camera(scene, frame.t_s, model, rng, shadows=shadow_raster(scene, frame.t_s), exposure=exposure)
    return render.image


# Box-point pairs tested at once by count_points_in_boxes: bounds its memory (a few arrays of 8 bytes per pair).
_PAIR_CHUNK = 1 << 21


def count_points_in_boxes(points_xyz: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(M,) int64: how many of the points (N, 3) lie inside each box (M, >=7: x, y, z, w, l, h, yaw, all in one
    frame), the boundary included, as the nuScenes devkit's ``points_in_box`` decides (nuScenes' num_lidar_pts).

    Only the points within a box's bounding circle along one axis are tested: the points are sorted along the axis
    the boxes spread over most, so a street along either world axis does not pair every box with every point."""
    pts = np.asarray(points_xyz, dtype=np.float64)
    b = np.asarray(boxes, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or b.ndim != 2 or b.shape[1] < 7:
        raise ValueError(f"count_points_in_boxes takes points (N, 3) and boxes (M, >=7), got {pts.shape} and {b.shape}")
    m = len(b)
    if m == 0 or len(pts) == 0:
        return np.zeros(m, dtype=np.int64)
    axis = int(np.argmax(np.ptp(b[:, :2], axis=0)))
    order = np.argsort(pts[:, axis], kind="stable")
    coord = pts[order, axis]
    reach = 0.5 * np.hypot(b[:, 3], b[:, 4]) + 1e-6  # the BEV bounding circle, and rounding slack
    lo = np.searchsorted(coord, b[:, axis] - reach, side="left")
    hi = np.searchsorted(coord, b[:, axis] + reach, side="right")
    counts = hi - lo
    out = np.zeros(m, dtype=np.int64)
    first = 0
    while first < m:  # boxes in chunks of about _PAIR_CHUNK candidate pairs (at least one box)
        total = np.cumsum(counts[first:])
        last = first + max(1, int(np.searchsorted(total, _PAIR_CHUNK, side="right")))
        box = np.arange(first, last)
        pair = np.repeat(box, counts[box])  # (P,) box of each candidate pair
        offsets = np.cumsum(counts[box]) - counts[box]
        idx = order[lo[pair] + np.arange(len(pair)) - np.repeat(offsets, counts[box])]
        rel = pts[idx] - b[pair, :3]
        c, s = np.cos(b[pair, 6]), np.sin(b[pair, 6])
        inside = ((np.abs(c * rel[:, 0] + s * rel[:, 1]) <= b[pair, 4] / 2)
                  & (np.abs(-s * rel[:, 0] + c * rel[:, 1]) <= b[pair, 3] / 2)
                  & (np.abs(rel[:, 2]) <= b[pair, 5] / 2))  # fmt: skip
        out += np.bincount(pair[inside], minlength=m)
        first = last
    return out


@dataclass(frozen=True)
class GenerationSummary:
    out_dir: Path
    version: str
    scenes: tuple[str, ...]
    num_samples: int
    num_sweeps: int
    num_images: int  # key frames' and camera sweeps'
    num_annotations: int
    mean_points_per_sweep: float
    seconds: float
    num_key_images: int = 0  # of num_images, those of key frames


def generate_dataset(
    out_dir: str | Path,
    config: SynthConfig = SynthConfig(),
    progress: Callable[[int], None] | None = None,
    workers: int = 1,
) -> GenerationSummary:
    """Write ``config.num_scenes`` scenes into ``out_dir``.

    ``progress(n)`` is told of every n finished key frames (per key frame with one worker, per scene with
    several). ``workers`` > 1 simulates scenes in that many processes; the output is the same bytes.
    """
    if not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # world.json first: it marks the folder as a synth dataset, so that a run interrupted later still leaves a folder
    # that --overwrite recognises and may replace (without it, the half-written samples/ look like anyone's).
    write_world_sidecar(out, config)
    rig = real_rig_records(config.resolution)
    rows = Tables(config.seed).static(rig)
    results: list[_SceneResult] = []
    if workers == 1 or config.num_scenes == 1:
        for s in range(config.num_scenes):
            results.append(_write_scene(out, config, s, progress))
    else:
        pool = ProcessPoolExecutor(max_workers=min(workers, config.num_scenes))
        try:
            futures = [pool.submit(_write_scene, out, config, s, None) for s in range(config.num_scenes)]
            for future in as_completed(futures):
                if progress is not None:
                    progress(future.result().num_samples)
            results = [f.result() for f in futures]  # scene order, whatever order they finished in
        finally:
            # after an error or Ctrl-C the scenes not started are cancelled (a plain `with` waited for every one of
            # them), and the running ones end before this returns: a caller removing the folder races no worker
            pool.shutdown(wait=True, cancel_futures=True)
    for result in results:
        for name, scene_rows in result.rows.items():
            rows[name].extend(scene_rows)
    write_tables(out / config.version, out, rows, config.seed)
    names = [r.name for r in results]
    n_val = min(config.num_scenes - 1, max(1, round(config.val_fraction * config.num_scenes))) if config.num_scenes > 1 else 0
    splits = {"train": names[: len(names) - n_val], "val": names[len(names) - n_val :]}
    (out / SPLITS_FILE).write_text(json.dumps(splits, indent=1))
    write_trajectories(out, config)  # trajectories.npz: every object's pose at any time (streamdet-replay)
    point_counts = [c for r in results for c in r.point_counts]
    return GenerationSummary(
        out_dir=out,
        version=config.version,
        scenes=tuple(names),
        num_samples=len(rows["sample"]),
        num_sweeps=len(point_counts),
        num_images=sum(1 for r in rows["sample_data"] if r["fileformat"] == "jpg"),
        num_key_images=sum(1 for r in rows["sample_data"] if r["fileformat"] == "jpg" and r["is_key_frame"]),
        num_annotations=len(rows["sample_annotation"]),
        mean_points_per_sweep=float(np.mean(point_counts)),
        seconds=time.perf_counter() - start,
    )


@dataclass(frozen=True)
class _SceneResult:
    name: str
    rows: dict[str, list[dict]]  # the scene's rows of the per-scene tables
    point_counts: list[int]
    num_samples: int


def _write_scene(out: Path, config: SynthConfig, index: int, progress: Callable[[int], None] | None) -> _SceneResult:
    """Simulate scene ``index``, write its files and return its table rows (runs in a worker process too)."""
    rig = real_rig_records(config.resolution)
    tables = Tables(config.seed)
    tables.static(rig)
    scene = make_scene(config.seed, index, config.world)
    log_token, sensor_tokens = tables.scene_start(scene, rig)
    lidar_chain: list[dict] = []
    point_counts = []
    frames = scene_camera_frames(scene, rig, config)
    for k in range(scene.config.samples_per_scene):
        frame = simulate_frame(scene, k, rig, config)
        sample_token = tables.sample(scene, frame)
        # Sweeps between the previous key frame and this one, oldest first, then the key frame.
        for sweep in reversed(frame.past_sweeps):
            lidar_chain.append(tables.lidar_data(out, scene, sample_token, sweep, sensor_tokens, key=False))
            point_counts.append(len(sweep.points))
        lidar_chain.append(tables.lidar_data(out, scene, sample_token, frame.sweep, sensor_tokens, key=True))
        point_counts.append(len(frame.sweep.points))
        for c, cam in enumerate(rig.cameras):
            # The camera's sweeps since the previous key frame, oldest first, then its key-frame image.
            for f in frames[cam["name"]]:
                if f.key_index == k and not f.is_key:
                    image = render_camera_sweep(scene, rig, config, c, f)
                    tables.camera_sweep_data(out, scene, sample_token, cam["name"], f.t_s, image, sensor_tokens, config)
            tables.camera_data(out, scene, sample_token, frame, cam["name"], sensor_tokens, config)
        tables.annotations(scene, sample_token, frame)
        if progress is not None:
            progress(1)
    link_records(lidar_chain)
    tables.scene_end(scene, log_token)
    return _SceneResult(
        name=scene.name,
        rows={name: tables.rows[name] for name in Tables.SCENE_TABLES},
        point_counts=point_counts,
        num_samples=scene.config.samples_per_scene,
    )


def world_sidecar(config: SynthConfig) -> dict:
    """What ``world.json`` holds: the world version, and per scene its start time, roads and distractors."""
    scenes = {}
    for i in range(config.num_scenes):
        scene = make_scene(config.seed, i, config.world)
        objs = scene.objects
        distractor = np.isin(objs.kind, [int(k) for k in DISTRACTOR_KINDS])
        scenes[scene.name] = {
            "start_us": scene.start_us,
            "roads": [{"origin_xy": list(map(float, r.origin_xy)), "yaw": float(r.yaw), "half_width_m": float(r.half_width_m)}
                      for r in scene.roads],
            "distractors_xy": objs.center0[distractor, :2].round(3).tolist(),
            "distractor_kinds": [Kind(int(k)).name.lower() for k in objs.kind[distractor]],
        }
    # camera_hz: how often the cameras expose (0: at key frames only), which a replay's image age depends on
    return {"world_version": WORLD_VERSION, "camera_hz": float(config.camera_hz), "scenes": scenes}


def write_world_sidecar(out: Path, config: SynthConfig) -> Path:
    """Write ``world.json`` beside the tables (a streamdet extension the devkit ignores)."""
    path = Path(out) / WORLD_FILE
    path.write_text(json.dumps(world_sidecar(config), indent=0))
    return path
