"""How a LiDAR dataset looks to a detector: the cues that tell a synthetic world from real nuScenes, measured.

``dataset_stats`` reads every key frame of a nuScenes-format dataset (or the bundled real sample) and measures,
per detection class and 10 m range bin (BEV distance of the box centre from the LiDAR):

- ``face``: of the points inside each box, the share within ``FACE_M`` of a box face and the median distance to
  the nearest face (a world whose objects are their boxes puts nearly every point on a face);
- ``intensity``: median and mean intensity (0..255) of the in-box points, and the median over all objects;
- ``points``: median number of points inside a box, and the share of boxes within 50 m holding at most 5;
- ``heading``: for vehicles, the angle between the heading and the nearest road axis (synthetic data that names
  its roads in ``world.json``; n/a elsewhere), and the share more than 10 degrees off;
- ``distractors``: unannotated look-alikes (bollards, signs, bins, ...) within 40 m of the ego per key frame
  against annotated pedestrians + traffic cones + bicycles there (from ``world.json``; n/a elsewhere);
- ``classes``: each class's share of the annotations; ``sweep``: points per key-frame sweep.

Everything is computed on the points and boxes as the dataset stores them (LiDAR frame), so synthetic and real
data go through the same code. The result is a plain dict (JSON-ready); ``format_table`` prints one or two of
them side by side and ``plot_stats`` draws them.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable

import numpy as np

from streamdet.data.sample import NUMBER, FieldKind, Sample, bundled_sample_dir, check_fields, load_bundled_sample, numbers
from streamdet.data.synth_world import MAX_WORLD_BYTES, WORLD_FILE
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.json_input import is_finite_number, read_json, short_repr

FACE_M = 0.05  # a point this close to a box face counts as "on the face"
RANGE_BIN_M = 10.0
RANGE_BINS = ("0-10", "10-20", "20-30", "30-40", "40-50", "50+")
SPARSE_POINTS = 5  # boxes with at most this many points count as sparse
SPARSE_RANGE_M = 50.0
DISTRACTOR_RANGE_M = 40.0
HEADING_OFF_DEG = 10.0
VEHICLES = ("car", "truck", "bus", "construction_vehicle", "trailer")
SMALL_CLASSES = ("pedestrian", "traffic_cone", "bicycle")  # what the distractors imitate
# world.json, as far as the stats read it (synth_writer.world_sidecar writes it; other fields are not read)
_XY = numbers(2)
_WORLD_FIELDS = {"world_version": FieldKind(lambda v: type(v) is int, "an integer (synth_world.WORLD_VERSION)"),
                 "scenes": FieldKind(lambda v: type(v) is dict, "an object of scenes by name")}
_SCENE_FIELDS = {"roads": FieldKind(lambda v: type(v) is list, "a list of road strips"),
                 "distractors_xy": FieldKind(lambda v: type(v) is list and all(_XY.test(p) for p in v),
                                             "a list of [x, y] pairs of finite numbers")}
_ROAD_FIELDS = {"origin_xy": _XY, "yaw": NUMBER,
                "half_width_m": FieldKind(lambda v: is_finite_number(v) and v >= 0, "a finite number >= 0")}  # fmt: skip


def open_samples(root: str | Path) -> tuple[str, int, Callable[[int], Sample], dict | None]:
    """(label, count, get(i), world sidecar or None) for a nuScenes-format dataset or a bundled-sample folder."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset folder not found: {root}")
    if (root / "calibration.json").is_file() and (root / "boxes.json").is_file():
        sample = load_bundled_sample(root)
        return f"real sample ({root.name})", 1, lambda i: sample, None
    versions = sorted(p.parent.name for p in root.glob("*/sample.json"))
    if not versions:
        raise FileNotFoundError(f"{root} holds neither nuScenes tables (<version>/sample.json) nor a bundled sample")
    from streamdet.data.nuscenes import NuScenesReader

    reader = NuScenesReader(root, versions[0])
    world = _read_world(root)
    label = f"{root.name} ({versions[0]}" + (f", world {world['world_version']})" if world else ")")
    return label, len(reader), reader.get, world


def _read_world(root: Path) -> dict | None:
    """``root``'s world.json, checked as far as the stats read it; None where there is none (real nuScenes).

    One that is there but unreadable or malformed is a ValueError naming it and the field, where
    ``synth_world.world_version_of`` reads it as no world: a report's label loses only the version, but the heading
    and distractor figures come from this file, and "no world" would print them n/a, as for real data. Both read
    the file alike (``read_json``, ``MAX_WORLD_BYTES``, an integer ``world_version``), so a world measured here has
    the version world_version_of names.
    """
    path = root / WORLD_FILE
    if not path.is_file():
        if path.exists():  # a FIFO would block the read; a folder is no world
            raise ValueError(f"world file {path} is not a regular file (a FIFO, a device or a folder?)")
        return None
    world = read_json(path, "world file", MAX_WORLD_BYTES)
    check_fields(world, _WORLD_FIELDS, f"world file {path}")
    for name, scene in world["scenes"].items():
        where = f"world file {path} scenes[{short_repr(name)}]"
        check_fields(scene, _SCENE_FIELDS, where, optional=frozenset(_SCENE_FIELDS))
        for i, road in enumerate(scene.get("roads", [])):
            check_fields(road, _ROAD_FIELDS, f"{where} roads[{i}]")
    return world


def range_bin(distance_m: np.ndarray) -> np.ndarray:
    """(M,) index into RANGE_BINS of BEV distances."""
    return np.minimum((np.asarray(distance_m) // RANGE_BIN_M).astype(np.int64), len(RANGE_BINS) - 1)


def in_box_face_distance(points_xyz: np.ndarray, boxes: np.ndarray) -> list[np.ndarray]:
    """For each box (M, >=7: x, y, z, w, l, h, yaw), the distances (P_m,) of its inside points to the nearest face."""
    out = []
    for box in np.asarray(boxes, dtype=np.float64):
        rel = points_xyz - box[:3]
        c, s = math.cos(box[6]), math.sin(box[6])
        local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=1)  # (N, 3)
        margin = np.array([box[4], box[3], box[5]]) / 2 - np.abs(local)  # (N, 3) along l, w, h
        depth = margin.min(axis=1)
        out.append(depth[depth >= 0])
    return out


def _inside_mask(points_xyz: np.ndarray, box: np.ndarray) -> np.ndarray:
    rel = points_xyz - box[:3]
    c, s = math.cos(box[6]), math.sin(box[6])
    lx = c * rel[:, 0] + s * rel[:, 1]
    ly = -s * rel[:, 0] + c * rel[:, 1]
    return (np.abs(lx) <= box[4] / 2) & (np.abs(ly) <= box[3] / 2) & (np.abs(rel[:, 2]) <= box[5] / 2)


def _angle_off_axes_deg(yaw: float, axes: list[float]) -> float:
    """Smallest angle (0..90 deg) between a heading and any of the road axes (direction-free)."""
    best = 90.0
    for a in axes:
        d = abs((yaw - a + math.pi / 2) % math.pi - math.pi / 2)
        best = min(best, math.degrees(d))
    return best


def dataset_stats(root: str | Path, max_samples: int | None = None, progress: Callable[[int], None] | None = None) -> dict:
    """Measure ``root`` (a nuScenes-format dataset or a bundled-sample folder); see the module docstring."""
    label, count, get, world = open_samples(root)
    if max_samples is not None:
        count = min(count, int(max_samples))
    rows: list[dict] = []  # one per box
    sweep_points: list[int] = []
    distractors: list[int] = []
    small_objects: list[int] = []
    for i in range(count):
        sample = get(i)
        first_row = len(rows)
        pts = np.asarray(sample.points, dtype=np.float64)
        xyz = pts[:, :3]
        sweep_points.append(len(pts))
        l2g = sample.lidar2global
        yaw_offset = math.atan2(l2g[1, 0], l2g[0, 0])
        scene = world["scenes"].get(sample.scene_name) if world else None
        for m, box in enumerate(np.asarray(sample.gt_boxes, dtype=np.float64)):
            label_id = int(sample.gt_labels[m])
            if label_id < 0:
                continue
            inside = _inside_mask(xyz, box)
            dist = in_box_face_distance(xyz[inside], box[None])[0]
            heading = None
            if scene is not None and CLASS_NAMES[label_id] in VEHICLES:
                centre = l2g[:3, :3] @ box[:3] + l2g[:3, 3]
                heading = _angle_off_axes_deg(box[6] + yaw_offset, _road_axes_at(scene, centre[:2]))
            rows.append(
                {
                    "cls": CLASS_NAMES[label_id],
                    "bin": int(range_bin(np.hypot(box[0], box[1]))),
                    "range": float(np.hypot(box[0], box[1])),
                    "points": int(inside.sum()),
                    "face_dist": dist,
                    "intensity": pts[inside, 3],
                    "heading_off_deg": heading,
                }
            )
        if scene is not None:
            ego_xy = sample.ego2global[:2, 3]
            xy = np.asarray(scene.get("distractors_xy", []), dtype=np.float64).reshape(-1, 2)
            distractors.append(int(np.sum(np.linalg.norm(xy - ego_xy, axis=1) <= DISTRACTOR_RANGE_M)))
            near = [r for r in rows[first_row:] if r["cls"] in SMALL_CLASSES and r["range"] <= DISTRACTOR_RANGE_M]
            small_objects.append(len(near))
        if progress is not None:
            progress(1)
    return _summarise(label, count, rows, sweep_points, distractors if world else None, small_objects if world else None, world)


def _road_axes_at(scene: dict, xy: np.ndarray) -> list[float]:
    """Yaws of the roads whose strip contains ``xy`` (the nearest road's where none does)."""
    return road_axes_at(scene.get("roads", []), xy)


def road_axes_at(roads: list[dict], xy: np.ndarray) -> list[float]:
    """Yaws of the road strips ({origin_xy, yaw, half_width_m}) containing ``xy``; else the nearest road's yaw."""
    on, nearest, best = [], [], math.inf
    for r in roads:
        rel = np.asarray(xy, dtype=np.float64) - np.asarray(r["origin_xy"], dtype=np.float64)
        lateral = abs(float(rel @ np.array([-math.sin(r["yaw"]), math.cos(r["yaw"])])))
        if lateral <= float(r["half_width_m"]):
            on.append(float(r["yaw"]))
        if lateral - float(r["half_width_m"]) < best:
            best, nearest = lateral - float(r["half_width_m"]), [float(r["yaw"])]
    return on or nearest


def _median(values) -> float | None:
    v = np.asarray(values, dtype=np.float64)
    return float(np.median(v)) if len(v) else None


def _summarise(label: str, count: int, rows: list[dict], sweep_points: list[int], distractors, small, world) -> dict:
    classes = [c for c in CLASS_NAMES if any(r["cls"] == c for r in rows)]
    per_class: dict[str, dict] = {}
    all_intensity = []
    for c in classes:
        mine = [r for r in rows if r["cls"] == c]
        face = np.concatenate([r["face_dist"] for r in mine]) if mine else np.zeros(0)
        inten = np.concatenate([r["intensity"] for r in mine]) if mine else np.zeros(0)
        obj_med = [float(np.median(r["intensity"])) for r in mine if len(r["intensity"])]
        all_intensity.extend(obj_med)
        bins = {}
        for b, name in enumerate(RANGE_BINS):
            rb = [r for r in mine if r["bin"] == b]
            if not rb:
                continue
            fb = np.concatenate([r["face_dist"] for r in rb])
            bins[name] = {
                "boxes": len(rb),
                "points_median": _median([r["points"] for r in rb]),
                "face_share": float(np.mean(fb < FACE_M)) if len(fb) else None,
                "face_median_m": _median(fb),
            }
        per_class[c] = {
            "boxes": len(mine),
            "share_of_annotations": len(mine) / max(len(rows), 1),
            "face_share": float(np.mean(face < FACE_M)) if len(face) else None,
            "face_median_m": _median(face),
            "intensity_median": _median(inten),
            "intensity_mean": float(np.mean(inten)) if len(inten) else None,
            "bins": bins,
        }
    within = [r for r in rows if r["range"] <= SPARSE_RANGE_M]
    vehicles = [r["heading_off_deg"] for r in rows if r["heading_off_deg"] is not None]
    return {
        "label": label,
        "world_version": (world or {}).get("world_version"),
        "samples": count,
        "boxes": len(rows),
        "points_per_sweep_mean": float(np.mean(sweep_points)) if sweep_points else None,
        "points_per_sweep_median": _median(sweep_points),
        "intensity_all_objects_median": _median(all_intensity),  # median over objects of each object's median
        "sparse_share_within_50m": float(np.mean([r["points"] <= SPARSE_POINTS for r in within])) if within else None,
        "vehicles_heading_measured": len(vehicles),
        "vehicles_off_road_axis_share": float(np.mean(np.asarray(vehicles) > HEADING_OFF_DEG)) if vehicles else None,
        "vehicles_heading_off_median_deg": _median(vehicles),
        "distractors_within_40m_per_frame": float(np.mean(distractors)) if distractors else None,
        "small_objects_within_40m_per_frame": float(np.mean(small)) if small else None,
        "classes": per_class,
    }


def reference_dir() -> Path:
    """The default reference: the bundled real nuScenes sample."""
    return bundled_sample_dir()


def _fmt(v, pct: bool = False, digits: int = 0) -> str:
    if v is None:
        return "n/a"
    if pct:
        return f"{100 * v:.0f} %"
    return f"{v:.{digits}f}"


def table_rows(stats: dict, classes: tuple[str, ...] = CLASS_NAMES) -> list[tuple[str, str]]:
    """(figure, value) rows of one dataset's stats in a fixed order: the same keys for every dataset ("-": no box)."""
    out = [
        ("key frames / boxes", f"{stats['samples']} / {stats['boxes']}"),
        ("points per sweep (mean)", _fmt(stats["points_per_sweep_mean"])),
        ("in-box intensity, all-object median", _fmt(stats["intensity_all_objects_median"], digits=1)),
        ("boxes <= 50 m with <= 5 points", _fmt(stats["sparse_share_within_50m"], pct=True)),
        ("vehicles > 10 deg off the road axis", _fmt(stats["vehicles_off_road_axis_share"], pct=True)),
        ("distractors <= 40 m per frame", _fmt(stats["distractors_within_40m_per_frame"], digits=1)),
        ("peds + cones + bicycles <= 40 m per frame", _fmt(stats["small_objects_within_40m_per_frame"], digits=1)),
    ]
    for c in classes:
        s = stats["classes"].get(c)
        out.append((f"{c}: share of annotations", "-" if s is None else _fmt(s["share_of_annotations"], pct=True)))
        face_med = None if s is None or s["face_median_m"] is None else 100 * s["face_median_m"]
        out.append((f"{c}: in-box pts <= 5 cm of a face (median cm)", "-" if s is None else f"{_fmt(s['face_share'], pct=True)} ({_fmt(face_med)})"))
        out.append((f"{c}: in-box intensity median / mean", "-" if s is None else f"{_fmt(s['intensity_median'])} / {_fmt(s['intensity_mean'])}"))
        for name in RANGE_BINS:
            b = None if s is None else s["bins"].get(name)
            value = "-" if b is None else f"{b['boxes']}, {_fmt(b['points_median'])}, {_fmt(b['face_share'], pct=True)}"
            out.append((f"{c} {name} m: boxes, median pts, face share", value))
    return out


def format_table(stats: dict, reference: dict | None = None) -> str:
    """A markdown table of ``stats`` (and ``reference`` beside it); rows without a value on either side are left out."""
    columns = [stats] + ([reference] if reference is not None else [])
    values = [table_rows(s) for s in columns]
    lines = ["| figure | " + " | ".join(s["label"] for s in columns) + " |", "|---|" + "---|" * len(columns)]
    for i, (key, _) in enumerate(values[0]):
        cells = [v[i][1] for v in values]
        if all(c == "-" for c in cells):
            continue
        lines.append(f"| {key} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_stats(path: str | Path, stats: list[dict]) -> Path:
    """A PNG with four panels (median points per box by range bin for car / pedestrian, in-box intensity
    median per class, face share per class), one series per dataset."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    x = np.arange(len(RANGE_BINS))
    for ax, cls in zip(axes[0], ("car", "pedestrian")):
        for s in stats:
            bins = s["classes"].get(cls, {}).get("bins", {})
            y = [bins.get(b, {}).get("points_median") for b in RANGE_BINS]
            ax.plot(x, [np.nan if v is None else v for v in y], marker="o", label=s["label"])
        ax.set_xticks(x, RANGE_BINS)
        ax.set_yscale("symlog")  # linear through 0 (a median of 0 points is common far out), log above
        ax.set_ylim(bottom=0)  # counts: autoscaling padded the axis below 0 and drew negative ticks
        ax.set_xlabel("range bin (m)")
        ax.set_ylabel(f"median points per {cls} box")
        ax.legend(fontsize=7)
    width = 0.8 / max(len(stats), 1)
    cx = np.arange(len(CLASS_NAMES))
    for ax, key, ylabel in ((axes[1][0], "intensity_median", "in-box intensity median"),
                            (axes[1][1], "face_share", f"in-box points within {100 * FACE_M:.0f} cm of a face")):
        for j, s in enumerate(stats):
            y = [s["classes"].get(c, {}).get(key) for c in CLASS_NAMES]
            ax.bar(cx + j * width, [np.nan if v is None else v for v in y], width, label=s["label"])
        ax.set_xticks(cx + width * (len(stats) - 1) / 2, [c.replace("_", "\n") for c in CLASS_NAMES], fontsize=7)
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def to_json(stats: dict) -> dict:
    """``stats`` as written by ``--json`` (already plain; kept as a function so the format has one owner)."""
    return json.loads(json.dumps(stats))
