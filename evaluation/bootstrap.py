"""Paired bootstrap over scenes of the nuScenes detection metrics: how sure is a difference between two runs?

Matching is per sample (a prediction only ever matches ground truth of its own sample) and the devkit's greedy
order inside a sample is the global score order restricted to it, so whether a prediction is a true positive,
and its TP errors, do not depend on which other samples are scored. ``match_tables`` therefore matches once;
``weighted_metrics`` then scores any multiset of samples (a bootstrap draw: integer weights per sample) by
repeating each prediction as many times as its sample is drawn. That equals scoring a dataset in which every
drawn scene is copied, exactly, as long as no two *different* predictions share a score (copies of one
prediction share its score and its outcome, so their tie order cannot matter); the test pairs it with that
naive duplication.

Subsets (``GtSubset``) follow the Waymo convention: the ground truth outside the subset is not counted, a
prediction matched to it is ignored (neither TP nor FP), and an unmatched prediction counts as a false positive
where ``pred_keep`` holds (default: everywhere).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from streamdet.evaluation.config import TP_METRICS, DetectionConfig
from streamdet.evaluation.detection_eval import (
    detection_metrics,
    filter_eval_boxes,
    greedy_match,
    metric_curves,
    ordered_classes,
    score_order,
    tp_errors,
)
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.metrics import DetectionMetricData, DetectionMetrics


@dataclass(frozen=True)
class GtSubset:
    """Which boxes a subset scores: ground-truth rows kept, and where an unmatched prediction counts as FP."""

    gt_keep: np.ndarray  # (G,) bool over the *filtered* ground truth of match_tables' input
    pred_keep: np.ndarray | None = None  # (P,) bool over the filtered predictions; None = every prediction


@dataclass(frozen=True, eq=False)
class MatchTable:
    """The predictions of one class at one threshold, in the devkit's score order, with their outcome."""

    score: np.ndarray  # (P,) descending
    is_tp: np.ndarray  # (P,) bool
    sample: np.ndarray  # (P,) int64 index into the sample list
    errors: dict[str, np.ndarray]  # TP metric -> (P,) error of each TP (NaN elsewhere)
    npos: np.ndarray  # (S,) int64 ground-truth boxes of the class per sample


def match_tables(
    gt: EvalBoxes,
    pred: EvalBoxes,
    classes: Sequence[str],
    config: DetectionConfig = DetectionConfig(),
    subset: GtSubset | None = None,
    filtered: bool = False,
    bike_racks: Mapping[str, np.ndarray] | None = None,
) -> tuple[tuple[str, ...], dict[tuple[str, float], MatchTable]]:
    """Match once: (the samples, in gt's order; a table per (class, threshold)). Inputs as ``evaluate`` takes them.

    ``filtered``: the boxes already went through ``filter_eval_boxes`` (a subset's masks refer to those rows);
    otherwise they are filtered here, with ``bike_racks`` as ``evaluate`` takes them. A class without ground truth
    gets a table all of false positives: ``weighted_metrics`` then scores it as ``evaluate`` does (AP 0, TP errors 1).
    """
    if set(gt.sample_tokens) != set(pred.sample_tokens):
        raise ValueError("predictions must cover exactly the ground-truth samples")
    if not filtered:
        gt = filter_eval_boxes(gt, config.class_range_m, bike_racks)
        pred = filter_eval_boxes(pred, config.class_range_m, bike_racks)
    if subset is not None:
        _check_subset(subset, len(gt), len(pred))
    samples = gt.sample_tokens
    rank = {t: i for i, t in enumerate(samples)}
    pred_sample = np.array([rank[t] for t in pred.sample_tokens], dtype=np.int64)[pred.sample_index]  # (P,)
    tables = {}
    for c in ordered_classes(classes, config):
        gmask, pmask = gt.detection_name == c, pred.detection_name == c
        gt_c, pred_c = gt.select(gmask), pred.select(pmask)
        gt_keep = np.ones(len(gt_c), bool) if subset is None else subset.gt_keep[gmask]
        pred_keep = np.ones(len(pred_c), bool) if subset is None or subset.pred_keep is None else subset.pred_keep[pmask]
        npos = np.bincount(gt_c.sample_index[gt_keep], minlength=len(samples)).astype(np.int64)
        order = score_order(pred_c.detection_score)
        for th in config.dist_ths_m:
            matched = greedy_match(gt_c, pred_c, order, th)
            # Waymo-style: a match to ground truth outside the subset is ignored; an unmatched box counts where kept.
            # (Indexed only where matched: a class without ground truth has an empty gt_keep.)
            counted = pred_keep[order]
            hit = matched >= 0
            counted[hit] = gt_keep[matched[hit]]
            o, m = order[counted], matched[counted]
            tables[c, th] = MatchTable(
                score=pred_c.detection_score[o], is_tp=m >= 0, sample=pred_sample[pmask][o],
                errors=_tp_errors(gt_c, pred_c, o, m, c), npos=npos,
            )  # fmt: skip
    return samples, tables


def _check_subset(subset: GtSubset, n_gt: int, n_pred: int) -> None:
    if np.shape(subset.gt_keep) != (n_gt,):
        raise ValueError(f"GtSubset.gt_keep must be ({n_gt},) over the filtered ground truth, got {np.shape(subset.gt_keep)}")
    if subset.pred_keep is not None and np.shape(subset.pred_keep) != (n_pred,):
        raise ValueError(f"GtSubset.pred_keep must be ({n_pred},) over the filtered predictions, got {np.shape(subset.pred_keep)}")


def _tp_errors(gt: EvalBoxes, pred: EvalBoxes, order: np.ndarray, matched: np.ndarray, c: str) -> dict[str, np.ndarray]:
    """``detection_eval.tp_errors`` of the matched predictions, spread over all of ``order`` (NaN where unmatched)."""
    tp = matched >= 0
    out = {}
    for key, values in tp_errors(gt, pred, matched[tp], order[tp], c).items():
        full = np.full(len(order), np.nan)
        full[tp] = values
        out[key] = full
    return out


def metric_data(table: MatchTable, weights: np.ndarray) -> DetectionMetricData:
    """``accumulate``'s curves for the multiset of samples drawn ``weights`` (S,) times each."""
    npos = float(np.dot(weights, table.npos))
    reps = weights[table.sample]  # (P,)
    if npos == 0 or not np.any(table.is_tp & (reps > 0)):  # before the copies: common in draws, and the answer
        return DetectionMetricData.no_predictions()
    idx = np.repeat(np.arange(len(table.score)), reps)  # copies stay adjacent: one score, one outcome
    is_tp = table.is_tp[idx]
    errors = {key: table.errors[key][idx][is_tp] for key in TP_METRICS}
    return metric_curves(is_tp, table.score[idx], npos, errors)


def weighted_metrics(
    tables: Mapping[tuple[str, float], MatchTable], classes: Sequence[str], weights: np.ndarray,
    config: DetectionConfig = DetectionConfig(),
) -> DetectionMetrics:  # fmt: skip
    """``evaluate``'s result on the samples drawn ``weights`` times each (all ones: the data as it is)."""
    data = {(c, th): metric_data(tables[c, th], weights) for c in classes for th in config.dist_ths_m}
    return detection_metrics(data, tuple(classes), config)


def summary(metrics: DetectionMetrics) -> dict[str, float]:
    """The figures a comparison reports: mAP, NDS and each class's AP (keys ``AP/<class>``)."""
    return {"mAP": metrics.mean_ap, "NDS": metrics.nd_score, **{f"AP/{c}": ap for c, ap in metrics.mean_dist_aps.items()}}


# A resampling interval needs at least this many clusters: with one, every draw is the whole data again, so the
# percentile "interval" collapses onto the point estimate (only the runs of a group of seeds still vary) and says
# nothing about the scene-to-scene spread. Below it no difference is called significant.
MIN_CLUSTERS = 2
# Below this many clusters the interval is defined but unreliable, and the comparison says so in a note: n clusters
# give only C(2n-1, n) distinct draws (3, 10, 35 for n = 2, 3, 4; 126 for 5), so the 2.5 % and 97.5 % ends rest on
# a few of them, and a percentile bootstrap over few clusters is too narrow (it never sees a scene unlike the ones
# it has). A chosen threshold, not a derived one: more clusters are better still.
FEW_CLUSTERS = 5


@dataclass(frozen=True)
class Difference:
    """B minus A for one figure: on the data as it is, and the bootstrap's percentile interval.

    ``interval_defined`` is False when the draws resampled fewer than ``MIN_CLUSTERS`` clusters: ``lo`` / ``hi`` are
    then still the draws' percentiles (kept so that the fields stay numbers) but do not bound anything, and
    ``significant`` is False whatever they are. ``to_dict`` then writes ``p_not_positive`` as None (JSON null):
    with one scene it is 0 or 1 by the sign of the point difference alone, which a script would read as
    certainty."""

    a: float
    b: float
    diff: float
    lo: float  # lower end of the interval of the difference
    hi: float
    p_not_positive: float  # share of bootstrap draws in which B - A <= 0
    interval_defined: bool = True

    @property
    def significant(self) -> bool:
        """The interval is defined and excludes 0 (the '*' of the printed table)."""
        return self.interval_defined and (self.lo > 0 or self.hi < 0)

    def to_dict(self) -> dict[str, float | bool | None]:
        # ci_lo / ci_hi stay numbers even when undefined: readers of the JSON (benchmarks/camera_claim.py) take them
        # as numbers and check interval_defined; p_not_positive, read on its own as a p-value, becomes null
        p = self.p_not_positive if self.interval_defined else None
        return {"A": self.a, "B": self.b, "B_minus_A": self.diff, "ci_lo": self.lo, "ci_hi": self.hi,
                "p_not_positive": p, "interval_defined": self.interval_defined,
                "significant": self.significant}  # fmt: skip


def paired_bootstrap(
    tables_a: Mapping[tuple[str, float], MatchTable] | Sequence[Mapping[tuple[str, float], MatchTable]],
    tables_b: Mapping[tuple[str, float], MatchTable] | Sequence[Mapping[tuple[str, float], MatchTable]],
    classes: Sequence[str],
    cluster_of_sample: np.ndarray,
    num_draws: int = 1000,
    seed: int = 0,
    confidence: float = 0.95,
    config: DetectionConfig = DetectionConfig(),
) -> dict[str, Difference]:
    """Resample clusters (scenes) with replacement, the same draw for both runs; B - A per figure of ``summary``.

    ``cluster_of_sample`` (S,) int gives each sample's scene; samples of a scene are correlated (one street, one
    traffic), so resampling samples instead would give intervals that are too narrow.

    Each side may be a sequence of runs (training seeds of one recipe, scored on the same samples): its figure is
    then the mean over its runs, and every draw also resamples each side's runs with replacement (a two-level
    bootstrap: scenes, shared by both sides, and seeds), so the interval holds the seed-to-seed spread as well.

    With fewer than ``MIN_CLUSTERS`` distinct clusters there is nothing to resample: the draws are still made (the
    figures keep their shape) but every ``Difference`` has ``interval_defined=False`` and is never ``significant``.
    With one cluster and one run a side every draw is the whole data, so the draws are that difference, unscored.
    """
    runs_a = [tables_a] if isinstance(tables_a, Mapping) else list(tables_a)
    runs_b = [tables_b] if isinstance(tables_b, Mapping) else list(tables_b)
    if not runs_a or not runs_b:
        raise ValueError(f"each side needs at least one run, got {len(runs_a)} and {len(runs_b)}")
    cluster_of_sample = np.asarray(cluster_of_sample)
    if cluster_of_sample.ndim != 1 or not np.issubdtype(cluster_of_sample.dtype, np.integer):
        raise ValueError(f"cluster_of_sample must be (S,) integers, got shape {cluster_of_sample.shape} dtype {cluster_of_sample.dtype}")
    if len(cluster_of_sample) == 0:
        raise ValueError("no sample to bootstrap over")
    if num_draws < 1 or not 0 < confidence < 1:
        raise ValueError(f"need num_draws >= 1 and 0 < confidence < 1, got {num_draws}, {confidence}")
    _, cluster = np.unique(cluster_of_sample, return_inverse=True)
    n_clusters = int(cluster.max()) + 1
    defined = n_clusters >= MIN_CLUSTERS
    ones = np.ones(len(cluster), dtype=np.int64)

    def mean_summary(runs, picks, weights) -> dict[str, float]:
        # a run drawn twice is scored once (a draw of three runs holds about two distinct ones); same figures
        scored: dict[int, dict[str, float]] = {}
        for i in picks:
            if i not in scored:
                scored[i] = summary(weighted_metrics(runs[i], classes, weights, config))
        each = [scored[i] for i in picks]
        return {k: float(np.mean([e[k] for e in each])) for k in each[0]}

    full_a = mean_summary(runs_a, range(len(runs_a)), ones)
    full_b = mean_summary(runs_b, range(len(runs_b)), ones)
    rng = np.random.default_rng(seed)
    draws: dict[str, list[float]] = {k: [] for k in full_a}
    if n_clusters == 1 and len(runs_a) == len(runs_b) == 1:
        # every draw is the whole data again, scored as above: the draws are that difference, not re-scored
        # (a thousand draws per subset took minutes to say "undefined")
        draws = {k: [full_b[k] - full_a[k]] * num_draws for k in full_a}
        num_draws = 0
    for _ in range(num_draws):
        counts = np.bincount(rng.integers(0, n_clusters, n_clusters), minlength=n_clusters)  # (C,) times drawn
        w = counts[cluster]  # (S,) a sample counts as often as its scene was drawn
        picks_a = rng.integers(0, len(runs_a), len(runs_a)) if len(runs_a) > 1 else [0]
        picks_b = rng.integers(0, len(runs_b), len(runs_b)) if len(runs_b) > 1 else [0]
        sa = mean_summary(runs_a, picks_a, w)
        sb = mean_summary(runs_b, picks_b, w)
        for k in draws:
            draws[k].append(sb[k] - sa[k])
    tail = 100 * (1 - confidence) / 2
    out = {}
    for k, values in draws.items():
        v = np.asarray(values)
        out[k] = Difference(a=full_a[k], b=full_b[k], diff=full_b[k] - full_a[k], lo=float(np.percentile(v, tail)),
                            hi=float(np.percentile(v, 100 - tail)), p_not_positive=float(np.mean(v <= 0)),
                            interval_defined=defined)  # fmt: skip
    return out
