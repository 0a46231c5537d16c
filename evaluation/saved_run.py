"""A run saved by ``streamdet-eval --data ... --save-results DIR``: the files of its folder, written and read here.

``SAVED_FILES``:

- ``results.json``: the detections scored, in the nuScenes submission format (``results.write_results_json``);
- ``gt.json``: the ground truth they were scored against, the same layout with ``ego_translation`` / ``num_pts`` per
  box, ``ego_positions`` and ``bike_racks`` (see ``results``); the files mode scores the two again
  (``--gt DIR/gt.json --results DIR/results.json``) to the same figures;
- ``samples.json``: per sample its scene and LiDAR pose, and the export's slicing, which ``--compare`` reads::

    {"num_slices": n, "start_deg": 0.0,
     "samples": {sample_token: {"scene": name, "lidar2ego": 4x4, "ego2global": 4x4}}}

A folder saved before ``samples.json`` existed holds only the first two, and a ``gt.json`` written before the
bike racks were saved has no ``bike_racks``: both are still read (``load_run``), the missing parts as unknown.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from streamdet.core.json_input import DuplicateKeyError, unique_keys_object
from streamdet.core.sectors import check_num_slices
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.results import load_eval_inputs, write_results_json

RESULTS_FILE = "results.json"
GT_FILE = "gt.json"
SAMPLES_FILE = "samples.json"
SAVED_FILES = (RESULTS_FILE, GT_FILE, SAMPLES_FILE)  # what save_run writes, in this order


@dataclass(frozen=True)
class SampleInfo:
    """What ``samples.json`` says: scene and LiDAR pose per sample, the slicing of the run."""

    scenes: dict[str, str]
    lidar2ego: dict[str, np.ndarray]
    ego2global: dict[str, np.ndarray]
    num_slices: int
    start_deg: float = 0.0


@dataclass(frozen=True)
class Run:
    """A saved run as read back (or a results file scored against a ground-truth file)."""

    gt: EvalBoxes
    pred: EvalBoxes
    info: SampleInfo | None
    where: str
    gt_where: str = ""  # the ground-truth file, for messages ("" = unknown: ``where`` is named instead)
    info_where: str = ""  # the samples.json read, for messages
    # the ground-truth file's bike racks ({sample_token: (R, 10)}, see results); None: the file names none
    bike_racks: dict[str, np.ndarray] | None = None
    notes: tuple[str, ...] = ()  # what reading the results file found the devkit would refuse (EvalInputs.notes)


def save_run(
    save_dir: str | os.PathLike,
    *,
    predictions: Mapping[str, Sequence[Mapping]],
    ground_truth: Mapping[str, Sequence[Mapping]],
    ego_positions: Mapping[str, Sequence[float]],
    scenes: Mapping[str, str],
    poses: Mapping[str, tuple[np.ndarray, np.ndarray]],
    num_slices: int,
    use_camera: bool,
    bike_racks: Mapping[str, np.ndarray | Sequence[Sequence[float]]] | None = None,
    start_deg: float = 0.0,
) -> list[Path]:
    """Write ``SAVED_FILES`` into ``save_dir`` (made if missing); returns their paths.

    ``predictions`` / ``ground_truth``: results entries per sample, global frame (``results.boxes_to_results`` /
    ``boxes_to_gt``); ``ego_positions``: each sample's ego position; ``scenes`` / ``poses``: each sample's scene and
    (lidar2ego, ego2global); ``bike_racks``: the ground truth's racks ({sample_token: (R, 10)}; None writes none).

    The files are written beside their places first and renamed once all are: a failed write (OSError, or a
    ValueError for entries the evaluation would refuse) leaves no run of mixed or missing files, and a folder that
    held an earlier run keeps it whole.
    """
    save_dir = Path(save_dir)
    staged = {name: save_dir / f".{name}.{os.getpid()}.tmp" for name in SAVED_FILES}
    try:
        save_dir.mkdir(parents=True, exist_ok=True)
        write_results_json(staged[RESULTS_FILE], predictions, {"use_camera": bool(use_camera), "use_lidar": True})
        write_results_json(staged[GT_FILE], ground_truth, {"use_camera": False, "use_lidar": False},
                           ego_positions=ego_positions, bike_racks=bike_racks)  # fmt: skip
        write_sample_info(staged[SAMPLES_FILE], scenes, poses, num_slices, start_deg)
        for name, tmp in staged.items():
            os.replace(tmp, save_dir / name)
    except BaseException:
        for tmp in staged.values():
            tmp.unlink(missing_ok=True)
        raise
    return [save_dir / name for name in SAVED_FILES]


def write_sample_info(path: Path, scenes: Mapping[str, str], poses: Mapping[str, tuple[np.ndarray, np.ndarray]],
                      num_slices: int, start_deg: float = 0.0) -> None:  # fmt: skip
    """``samples.json`` beside a saved run (see the module doc)."""
    doc = {"num_slices": int(num_slices), "start_deg": float(start_deg), "samples": {
        t: {"scene": scenes[t], "lidar2ego": np.asarray(poses[t][0]).tolist(), "ego2global": np.asarray(poses[t][1]).tolist()}
        for t in scenes}}  # fmt: skip
    Path(path).write_text(json.dumps(doc) + "\n")


def read_sample_info(path: Path) -> SampleInfo:
    """``samples.json`` as written by ``write_sample_info``; ValueError naming the file when it is not one."""
    try:
        # a sample listed twice would keep its last scene and pose silently; the file is small, the check cheap
        doc = json.loads(Path(path).read_text(), object_pairs_hook=unique_keys_object)
        n = int(doc["num_slices"])
        start = float(doc.get("start_deg", 0.0))
        check_num_slices(n, start)
        samples = doc["samples"]
        scenes = {t: str(s["scene"]) for t, s in samples.items()}
        l2e = {t: _matrix(s["lidar2ego"]) for t, s in samples.items()}
        e2g = {t: _matrix(s["ego2global"]) for t, s in samples.items()}
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"cannot read {path}: {e}") from None
    except DuplicateKeyError as e:  # a ValueError: before the catch-all below, which would call it a wrong field
        raise ValueError(f"{path}: {e}; a samples file holds each key once") from None
    except RecursionError:
        raise ValueError(f"{path} nests too deeply to be a samples file") from None
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as e:  # Overflow: a JSON int past float64
        raise ValueError(f"{path} is not a samples file (num_slices, samples: scene, lidar2ego, ego2global): {e}") from None
    return SampleInfo(scenes=scenes, lidar2ego=l2e, ego2global=e2g, num_slices=n, start_deg=start)


def _matrix(value: object) -> np.ndarray:
    m = np.asarray(value, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"a pose must be a finite 4x4 matrix, got shape {m.shape}")
    return m


def load_run(run: str | os.PathLike, gt_path: str | os.PathLike | None = None) -> Run:
    """A saved folder (results.json, gt.json, optional samples.json) or a results file scored against ``gt_path``
    (which, given with a folder, replaces the folder's gt.json)."""
    run = Path(run)
    if run.is_dir():
        results, gt_file = run / RESULTS_FILE, Path(gt_path) if gt_path is not None else run / GT_FILE
        for f in (results, gt_file):
            if not f.is_file():
                what = "is not a regular file (a FIFO, a device or a folder?)" if f.exists() else "is missing"
                raise ValueError(f"{run} is not a run saved by streamdet-eval --save-results: {f.name} {what}")
        info_path = run / SAMPLES_FILE
        if info_path.exists() and not info_path.is_file():  # a FIFO or a folder: another run's file must not stand in
            raise ValueError(f"{info_path} is not a regular file (a FIFO, a device or a folder?)")
        info = read_sample_info(info_path) if info_path.is_file() else None
    elif run.is_file():
        if gt_path is None:
            raise ValueError(f"{run} is a results file: give the ground truth with --gt")
        results, gt_file, info = run, Path(gt_path), None
    elif run.exists():
        raise ValueError(f"{run} is neither a saved run's folder nor a results file (a FIFO or a device?)")
    else:
        raise ValueError(f"{run} does not exist")
    inputs = load_eval_inputs(gt_file, results)
    info_where = str(run / SAMPLES_FILE) if info is not None else ""
    return Run(gt=inputs.gt, pred=inputs.pred, info=info, where=str(run), gt_where=str(gt_file), info_where=info_where,
               bike_racks=inputs.bike_racks, notes=inputs.notes)  # fmt: skip
