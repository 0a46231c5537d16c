"""Compare two runs on the same ground truth: B - A per figure, with a paired bootstrap interval over scenes.

A *run* is a folder written by ``streamdet-eval --data ... --save-results DIR`` (``results.json``, ``gt.json`` and,
from this version on, ``samples.json``; the format, its writer and its reader are ``saved_run``) or a results JSON
file (then the ground truth comes from ``gt_path``). ``samples.json`` holds, per sample, its scene and its LiDAR
pose, and the export's slice count.

With it the bootstrap resamples scenes, and the comparison adds subsets: per slice (boxes whose BEV centre lies in
slice k, predictions too), boxes cut by a slice border (centre or a BEV corner in two slices, predictions too),
and ground truth with at most ``few_points`` LiDAR + radar points (predictions are not located by point count:
unmatched ones count everywhere, see ``bootstrap``). Without it, samples are resampled on their own (a warning
says the interval is then too narrow) and only the few-points subset is available. The ground truth's
``bike_racks`` (gt.json) apply the devkit's bike-rack rule, as in the files mode.

With a single cluster (one scene, or one sample without samples.json) the interval is undefined: it is printed as
'undefined', nothing is starred, and the JSON says ``"interval_defined": false`` (top level and per figure), with
``"p_not_positive": null`` per figure (``ci_lo`` / ``ci_hi`` stay numbers that bound nothing). With
fewer than ``bootstrap.FEW_CLUSTERS`` clusters a note says the interval is unreliable (``"few_clusters": true``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from streamdet.core.boxes import BOX_DIM
from streamdet.core.sectors import slice_index_of
from streamdet.core.slicing import boxes_in_sector
from streamdet.evaluation.bootstrap import FEW_CLUSTERS, MIN_CLUSTERS, Difference, GtSubset, match_tables, paired_bootstrap
from streamdet.evaluation.config import DetectionConfig
from streamdet.evaluation.detection_eval import filter_eval_boxes, ordered_classes
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.results import global_to_lidar

# The saved-run format moved to saved_run; these names stay importable from here, where they were defined.
from streamdet.evaluation.saved_run import (  # noqa: F401
    SAMPLES_FILE,
    Run,
    SampleInfo,
    load_run,
    read_sample_info,
    write_sample_info,
)

FEW_POINTS = 5  # the subset: objects with at most this many points
# Per-slice subsets only up to this many slices: each subset costs a whole bootstrap, and a samples.json saying 4096
# slices made 4097 of them (hours at the default draws). Beyond it the per-slice rows are skipped, with a note.
MAX_SLICE_SUBSETS = 64
# Two runs' ground truths are the same when every box agrees to these tolerances (float64 through JSON round-trips
# exactly; the tolerance only absorbs a ground truth regenerated on another machine). Metres, m/s, quaternion units.
GT_ATOL = 1e-6
GT_RTOL = 1e-9
POSE_ATOL = 1e-9  # samples.json poses: rotation entries and metres


@dataclass(frozen=True)
class Comparison:
    subsets: dict[str, dict[str, Difference]]  # subset name -> figure -> difference
    num_samples: int
    num_clusters: int
    clustered_by: str  # "scene" or "sample"
    num_draws: int
    notes: list[str] = field(default_factory=list)

    @property
    def interval_defined(self) -> bool:
        """At least ``MIN_CLUSTERS`` clusters: the bootstrap had something to resample."""
        return self.num_clusters >= MIN_CLUSTERS

    @property
    def few_clusters(self) -> bool:
        """Fewer than ``FEW_CLUSTERS`` clusters: any interval is unreliable (too narrow), see ``bootstrap``."""
        return self.num_clusters < FEW_CLUSTERS

    def to_dict(self) -> dict:
        # interval_defined / few_clusters / min_reliable_clusters were added later: older readers ignore them
        return {"num_samples": self.num_samples, "num_clusters": self.num_clusters, "clustered_by": self.clustered_by,
                "num_draws": self.num_draws, "interval_defined": self.interval_defined,
                "few_clusters": self.few_clusters, "min_reliable_clusters": FEW_CLUSTERS, "notes": self.notes,
                "subsets": {s: {k: d.to_dict() for k, d in figs.items()} for s, figs in self.subsets.items()}}  # fmt: skip


def _canonical_rows(boxes: EvalBoxes, sample_of: np.ndarray) -> np.ndarray:
    """Row order that sorts ``boxes`` by (sample, class, attribute, points, centre, size): the order a ground-truth
    file happens to list a sample's boxes in does not make it another ground truth."""
    t, s = boxes.translation, boxes.size
    return np.lexsort((s[:, 2], s[:, 1], s[:, 0], t[:, 2], t[:, 1], t[:, 0], boxes.num_pts, boxes.attribute_name,
                       boxes.detection_name, sample_of))  # fmt: skip


def ground_truth_difference(a: EvalBoxes, b: EvalBoxes) -> str | None:
    """None if ``a`` and ``b`` hold the same boxes per sample (any order within a sample, values within GT_ATOL /
    GT_RTOL), else what differs first, naming the sample. Sample tokens, box counts *and* the boxes themselves are
    compared: only the first run's ground truth scores a comparison, so a run scored against moved boxes must not
    pass for one scored against these."""
    tokens_a, tokens_b = set(a.sample_tokens), set(b.sample_tokens)
    only_a = [t for t in a.sample_tokens if t not in tokens_b]
    only_b = [t for t in b.sample_tokens if t not in tokens_a]
    if only_a or only_b:
        first, side = (only_a[0], "the first") if only_a else (only_b[0], "the second")
        return (f"sample {first!r} is only in {side} ({len(a.sample_tokens)} vs {len(b.sample_tokens)} samples, "
                f"{len(only_a) + len(only_b)} not in both)")  # fmt: skip
    position = {t: k for k, t in enumerate(a.sample_tokens)}
    sample_a = a.sample_index
    sample_b = np.array([position[t] for t in b.sample_tokens], np.int64)[b.sample_index]
    counts_a = np.bincount(sample_a, minlength=len(position))
    counts_b = np.bincount(sample_b, minlength=len(position))
    if np.any(counts_a != counts_b):
        k = int(np.flatnonzero(counts_a != counts_b)[0])
        return f"sample {a.sample_tokens[k]!r} has {counts_a[k]} vs {counts_b[k]} boxes"
    ra, rb = _canonical_rows(a, sample_a), _canonical_rows(b, sample_b)
    fields = ("detection_name", "attribute_name", "num_pts", "translation", "size", "rotation", "velocity", "ego_translation")
    differs = np.zeros((len(fields), len(a)), bool)  # field x row
    for k, name in enumerate(fields):
        va, vb = getattr(a, name)[ra], getattr(b, name)[rb]
        if va.ndim == 1:
            differs[k] = va != vb
        else:
            differs[k] = ~np.isclose(va, vb, rtol=GT_RTOL, atol=GT_ATOL, equal_nan=True).all(axis=1)
    if not differs.any():
        return None
    row = int(np.flatnonzero(differs.any(axis=0))[0])
    name = fields[int(np.flatnonzero(differs[:, row])[0])]
    ia, ib = int(ra[row]), int(rb[row])
    token = a.sample_tokens[sample_a[ia]]
    # the field is named: a ground truth saved before attributes and unknown velocities were kept differs only there
    return (f"sample {token!r} differs in {name}: a {a.detection_name[ia]} at {np.round(a.translation[ia], 3).tolist()} "
            f"({_field_text(a, name, ia)}) vs a {b.detection_name[ib]} at {np.round(b.translation[ib], 3).tolist()} "
            f"({_field_text(b, name, ib)})")


def _field_text(boxes: EvalBoxes, name: str, row: int) -> str:
    value = getattr(boxes, name)[row]
    return f"{name} {value.tolist() if isinstance(value, np.ndarray) else repr(value.item())}"


def bike_racks_difference(a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray]) -> str | None:
    """None if the two ``bike_racks`` hold the same racks per sample (to GT_ATOL / GT_RTOL, in order), else what
    differs first, naming the sample."""
    for token in sorted(set(a) | set(b)):
        ra, rb = np.asarray(a.get(token, np.zeros((0, 10)))), np.asarray(b.get(token, np.zeros((0, 10))))
        if ra.shape != rb.shape:
            return f"sample {token!r} has {len(ra)} vs {len(rb)} bicycle racks"
        if not np.allclose(ra, rb, rtol=GT_RTOL, atol=GT_ATOL):
            return f"sample {token!r} has another bicycle rack"
    return None


def _bike_racks(runs: Sequence[Run], notes: list[str]) -> dict[str, np.ndarray] | None:
    """The bike racks that score every run: those of the runs' ground-truth files that name some (they must
    agree), None when none does. A run whose file names none (saved before racks were) is scored with the others'
    racks, and a note says so."""
    declared = [r for r in runs if r.bike_racks is not None]
    if not declared:
        return None
    for other in declared[1:]:
        difference = bike_racks_difference(declared[0].bike_racks, other.bike_racks)
        if difference is not None:
            raise ValueError(f"{declared[0].where} and {other.where} are not scored on the same ground truth "
                             f"({_gt_name(declared[0])} vs {_gt_name(other)}): {difference}")  # fmt: skip
    if len(declared) < len(runs):
        notes.append(f"bike_racks of {_gt_name(declared[0])} serve the runs whose ground truth names none: "
                     + ", ".join(r.where for r in runs if r.bike_racks is None))  # fmt: skip
    return declared[0].bike_racks


def _gt_name(run: Run) -> str:
    return run.gt_where or run.where


def _same_ground_truth(first: Run, other: Run) -> None:
    difference = ground_truth_difference(first.gt, other.gt)
    if difference is not None:
        raise ValueError(f"{first.where} and {other.where} are not scored on the same ground truth "
                         f"({_gt_name(first)} vs {_gt_name(other)}): {difference}")  # fmt: skip


def _same_sample_info(first: Run, other: Run, tokens: Sequence[str], slicing: bool) -> None:
    """The samples.json of two runs must agree on what the comparison reads from them: every scored sample's scene
    (the bootstrap's clusters) and pose, and with ``slicing`` (per-slice and cut-by-border subsets) the slicing."""
    a, b = first.info, other.info  # both runs have a samples.json (compare_runs' choice)
    where = f"{first.info_where or first.where} and {other.info_where or other.where} disagree"
    for t in tokens:
        if a.scenes[t] != b.scenes[t]:
            raise ValueError(f"{where}: sample {t!r} is in scene {a.scenes[t]!r} vs {b.scenes[t]!r}")
        for name in ("lidar2ego", "ego2global"):
            if not np.allclose(getattr(a, name)[t], getattr(b, name)[t], rtol=0.0, atol=POSE_ATOL):
                raise ValueError(f"{where}: sample {t!r} has another {name} pose")
    if slicing and (a.num_slices, a.start_deg) != (b.num_slices, b.start_deg):
        raise ValueError(f"{where}: {a.num_slices} vs {b.num_slices} slices (start {a.start_deg:g} vs "
                         f"{b.start_deg:g} deg); the per-slice subsets need one slicing: compare without subsets "
                         "(--no-subsets)")  # fmt: skip


def _lidar_boxes(boxes: EvalBoxes, info: SampleInfo) -> np.ndarray:
    """(N, 9) the boxes in their sample's LiDAR frame."""
    out = np.zeros((len(boxes), BOX_DIM))
    for s, token in enumerate(boxes.sample_tokens):
        rows = np.flatnonzero(boxes.sample_index == s)
        if len(rows) == 0:
            continue
        if token not in info.scenes:
            raise ValueError(f"samples.json has no entry for sample {token!r}")
        out[rows] = global_to_lidar(boxes.translation[rows], boxes.size[rows], boxes.rotation[rows],
                                    np.nan_to_num(boxes.velocity[rows]), info.lidar2ego[token], info.ego2global[token])  # fmt: skip
    return out


def slice_masks(boxes: EvalBoxes, info: SampleInfo) -> tuple[np.ndarray, np.ndarray]:
    """(slice of the BEV centre (N,) int64, cut by a slice border (N,) bool) of each box."""
    lidar = _lidar_boxes(boxes, info)
    n = info.num_slices
    centre = slice_index_of(lidar[:, 0], lidar[:, 1], n, info.start_deg) if len(lidar) else np.zeros(0, np.int64)
    touched = np.stack([boxes_in_sector(lidar, k, n, info.start_deg) for k in range(n)], axis=1) if len(lidar) else np.zeros((0, n), bool)
    return centre, touched.sum(axis=1) > 1 if n > 1 else np.zeros(len(lidar), bool)


def compare_runs(
    run_a: Run | Sequence[Run], run_b: Run | Sequence[Run], classes: Sequence[str] | None = None, num_draws: int = 1000,
    seed: int = 0, config: DetectionConfig = DetectionConfig(), few_points: int = FEW_POINTS, subsets: bool = True,
    progress: Callable[[str, int, int], None] | None = None,
) -> Comparison:  # fmt: skip
    """B - A for mAP, NDS and per-class AP, on all boxes and (``subsets``) per slice / cut / few-points subset.

    A side given as several runs (training seeds of one recipe) is their mean, and the bootstrap resamples its runs
    too (``paired_bootstrap``); every run must be scored on the same ground truth. ``progress(subset, done, total)``
    is called after each subset's bootstrap (the long part: each subset draws ``num_draws`` times).

    ``classes`` are averaged as ``evaluate(classes=...)`` averages them, in every subset: a named class without
    ground truth (in the data or in a subset) scores AP 0 and TP errors 1, and a note says so. Default: the classes
    present in the filtered ground truth, and in a subset those of them present there."""
    runs_a = [run_a] if isinstance(run_a, Run) else list(run_a)
    runs_b = [run_b] if isinstance(run_b, Run) else list(run_b)
    if not runs_a or not runs_b:
        raise ValueError("each side of a comparison needs at least one run")
    first = runs_a[0]
    for other in runs_a[1:] + runs_b:
        _same_ground_truth(first, other)
    notes: list[str] = [n for r in runs_a + runs_b for n in r.notes]
    racks = _bike_racks(runs_a + runs_b, notes)
    gt = filter_eval_boxes(first.gt, config.class_range_m, racks)
    preds_a = [filter_eval_boxes(r.pred, config.class_range_m, racks) for r in runs_a]
    preds_b = [filter_eval_boxes(r.pred, config.class_range_m, racks) for r in runs_b]
    if len(gt) == 0:
        raise ValueError(f"{first.where}: the ground truth holds no box with points within its class range: nothing to compare")
    present = set(gt.detection_name.tolist())
    named = classes is not None
    # the config's order, as evaluate: the means over classes then sum in the same order
    classes = ordered_classes(classes, config) if named else tuple(c for c in config.class_names if c in present)
    absent = [c for c in classes if c not in present]
    if absent:
        notes.append(f"no ground-truth box of {', '.join(absent)}: AP 0 and TP errors 1 by the devkit's rule, counted "
                     "in mAP and NDS")  # fmt: skip
    # Every samples.json must agree (scenes, poses, slicing): one of them serves every run, so a run's own file
    # read as another's would silently change the clusters or the slices of the others.
    with_info = [r for r in runs_a + runs_b if r.info is not None]
    for r in with_info:
        missing = [t for t in gt.sample_tokens if t not in r.info.scenes]
        if missing:
            raise ValueError(f"{r.info_where or SAMPLES_FILE} names no scene for sample {missing[0]!r}")
    for other in with_info[1:]:
        _same_sample_info(with_info[0], other, gt.sample_tokens, subsets)
    info = with_info[0].info if with_info else None
    if with_info and len(with_info) < len(runs_a) + len(runs_b):
        notes.append(f"samples.json of {with_info[0].where} serves the runs without one: "
                     + ", ".join(r.where for r in runs_a + runs_b if r.info is None))  # fmt: skip
    if info is None:
        clusters = np.arange(len(gt.sample_tokens))
        clustered_by = "sample"
        notes.append("no samples.json: samples resampled one by one; samples of one scene are correlated, so the "
                     "interval is too narrow")  # fmt: skip
    else:
        names = [info.scenes[t] for t in gt.sample_tokens]
        clusters = np.unique(names, return_inverse=True)[1].astype(np.int64)
        clustered_by = "scene"
    if len(runs_a) > 1 or len(runs_b) > 1:
        notes.append(f"A is the mean of {len(runs_a)} run(s), B of {len(runs_b)}; each draw resamples the runs too")
    notes.extend(cluster_notes(int(clusters.max()) + 1, clustered_by))

    # per subset: (ground truth kept, predictions kept per run of A, per run of B); None = everything
    subset_defs: dict[str, tuple[np.ndarray, list, list] | None] = {"all": None}
    if subsets:
        few = (gt.num_pts >= 1) & (gt.num_pts <= few_points)
        subset_defs[f"gt<={few_points}pts"] = (few, [None] * len(preds_a), [None] * len(preds_b))
        if info is not None:
            gt_slice, gt_cut = slice_masks(gt, info)
            masks_a = [slice_masks(p, info) for p in preds_a]
            masks_b = [slice_masks(p, info) for p in preds_b]
            subset_defs["cut_by_slice_border"] = (gt_cut, [m[1] for m in masks_a], [m[1] for m in masks_b])
            if info.num_slices <= MAX_SLICE_SUBSETS:
                for k in range(info.num_slices):
                    subset_defs[f"slice{k}"] = (gt_slice == k, [m[0] == k for m in masks_a], [m[0] == k for m in masks_b])
            else:
                notes.append(f"{info.num_slices} slices: no per-slice subsets above {MAX_SLICE_SUBSETS} slices "
                             "(each costs a whole bootstrap)")  # fmt: skip
        else:
            notes.append("no samples.json: no per-slice or cut-by-border subsets")
    out = {}
    absent_in_subsets = []
    for done, (name, sub) in enumerate(subset_defs.items(), start=1):
        keep = np.ones(len(gt), bool) if sub is None else sub[0]
        with_gt = tuple(c for c in classes if np.any(gt.detection_name[keep] == c))
        sub_classes = classes if named else with_gt  # named classes stay, as in evaluate(classes=...)
        if name != "all" and with_gt and len(with_gt) < len(sub_classes):
            absent_in_subsets.append(name)
        if not with_gt:
            notes.append(f"{name}: no ground truth of the compared classes, skipped")
        else:
            def tables(preds, pred_keeps):
                return [match_tables(gt, p, sub_classes, config, None if sub is None else GtSubset(keep, pk), filtered=True)[1]
                        for p, pk in zip(preds, pred_keeps)]  # fmt: skip

            ta = tables(preds_a, [None] * len(preds_a) if sub is None else sub[1])
            tb = tables(preds_b, [None] * len(preds_b) if sub is None else sub[2])
            out[name] = paired_bootstrap(ta, tb, sub_classes, clusters, num_draws, seed, config=config)
        if progress is not None:
            progress(name, done, len(subset_defs))
    if absent_in_subsets:
        notes.append(f"{_count(len(absent_in_subsets), 'subset')} ({', '.join(absent_in_subsets[:3])}"
                     f"{', ...' if len(absent_in_subsets) > 3 else ''}) lack ground truth of some of the classes named: "
                     "AP 0 and TP errors 1 there, as evaluate")  # fmt: skip
    return Comparison(subsets=out, num_samples=len(gt.sample_tokens), num_clusters=int(clusters.max()) + 1,
                      clustered_by=clustered_by, num_draws=num_draws, notes=notes)  # fmt: skip


def _count(n: int, what: str) -> str:
    return f"{n} {what}" if n == 1 else f"{n} {what}s"


def cluster_notes(num_clusters: int, clustered_by: str) -> list[str]:
    """What the number of clusters does to the interval: undefined below MIN_CLUSTERS, unreliable below FEW_CLUSTERS."""
    if num_clusters < MIN_CLUSTERS:
        return [f"only {_count(num_clusters, clustered_by)}: the bootstrap interval is undefined (every draw is the "
                f"whole data again) and no difference is marked significant; compare on at least {FEW_CLUSTERS} "
                f"{clustered_by}s"]  # fmt: skip
    if num_clusters < FEW_CLUSTERS:
        return [f"only {num_clusters} {clustered_by}s: a bootstrap over fewer than {FEW_CLUSTERS} clusters gives "
                "intervals that are too narrow; read '*' with caution"]  # fmt: skip
    return []


def format_comparison(c: Comparison, name_a: str, name_b: str) -> str:
    """A table: per subset and figure, A, B, B - A and its interval; '*' where the interval excludes 0.

    With fewer than ``MIN_CLUSTERS`` clusters the interval column reads 'undefined' and nothing is starred."""
    interval = "95 % interval" if c.interval_defined else f"no interval (it needs {MIN_CLUSTERS} {c.clustered_by}s or more)"
    lines = [f"A = {name_a}", f"B = {name_b}",
             f"paired bootstrap over {_count(c.num_clusters, c.clustered_by)} ({c.num_samples} samples), "
             f"{c.num_draws} draws, {interval}",
             f"{'subset':<22}{'figure':<26}{'A':>8}{'B':>8}{'B-A':>8}{'interval':>20}"]  # fmt: skip
    lines.append("-" * len(lines[-1]))
    for subset, figs in c.subsets.items():
        for fig, d in figs.items():
            if subset != "all" and fig != "mAP":
                continue  # subsets: mAP in the table, everything in the JSON
            if not d.interval_defined:
                lines.append(f"{subset:<22}{fig:<26}{d.a:>8.4f}{d.b:>8.4f}{d.diff:>+8.4f}   {'undefined':>18}")
                continue
            star = " *" if d.significant else ""
            lines.append(f"{subset:<22}{fig:<26}{d.a:>8.4f}{d.b:>8.4f}{d.diff:>+8.4f}   [{d.lo:+.4f}, {d.hi:+.4f}]{star}")
    lines.extend(f"note: {n}" for n in c.notes)
    return "\n".join(lines)
