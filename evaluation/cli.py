"""``streamdet-eval``: nuScenes detection metrics of a results file against a ground-truth file.

The command has two stages, so that other input modes can share the second: *inputs* (today only
``--gt`` / ``--results`` files, through ``load_gt_and_predictions``) produce ground truth and predictions
as ``EvalBoxes`` in the global frame; ``_evaluate_and_report`` evaluates and prints / writes them. A
``--data DIR`` mode (running the ONNX runtime over a dataset) plugs in as another producer of the pair.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import click

from streamdet.evaluation.config import TP_METRICS, DetectionConfig
from streamdet.evaluation.detection_eval import evaluate
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.metrics import DetectionMetrics
from streamdet.evaluation.results import load_gt_and_predictions

_TP_SHORT = {"trans_err": "ATE", "scale_err": "ASE", "orient_err": "AOE", "vel_err": "AVE", "attr_err": "AAE"}


def _parse_classes(value: str | None) -> tuple[str, ...] | None:
    if value is None:
        return None
    names = tuple(n.strip() for n in value.split(",") if n.strip())
    known = DetectionConfig().class_names
    bad = [n for n in names if n not in known]
    if bad or not names:
        raise click.BadParameter(f"unknown class {bad[0]!r}; choose from {','.join(known)}" if bad else "no class given",
                                 param_hint="--classes")  # fmt: skip
    return names


def format_table(metrics: DetectionMetrics) -> str:
    """Per-class AP (mean and per threshold) and TP errors, then mAP / NDS and the classes they average."""
    ths = metrics.config.dist_ths_m
    head = f"{'class':<22}{'AP':>7}" + "".join(f"{'AP@' + f'{t:g}':>8}" for t in ths)
    head += "".join(f"{_TP_SHORT[m]:>7}" for m in TP_METRICS)
    lines = [head, "-" * len(head)]
    mean_dist_aps = metrics.mean_dist_aps
    for c in metrics.classes:
        row = f"{c:<22}{mean_dist_aps[c]:>7.4f}" + "".join(f"{metrics.label_aps[c][t]:>8.4f}" for t in ths)
        row += "".join(f"{_fmt(metrics.label_tp_errors[c][m]):>7}" for m in TP_METRICS)
        lines.append(row)
    lines.append("-" * len(head))
    tp = metrics.tp_errors
    lines.append(f"mAP {metrics.mean_ap:.4f}   NDS {metrics.nd_score:.4f}   " + "  ".join(f"m{_TP_SHORT[m]} {_fmt(tp[m])}" for m in TP_METRICS))
    lines.append(f"mAP / NDS average {len(metrics.classes)} classes: {', '.join(metrics.classes)}")
    return "\n".join(lines)


def _fmt(x: float) -> str:
    return "n/a" if math.isnan(x) else f"{x:.3f}"


def _evaluate_and_report(gt: EvalBoxes, pred: EvalBoxes, classes: tuple[str, ...] | None, json_path: Path | None) -> None:
    try:
        metrics = evaluate(gt, pred, classes=classes)
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    click.echo(format_table(metrics))
    if json_path is not None:
        try:
            json_path.write_text(json.dumps(metrics.to_dict(), indent=1, allow_nan=False) + "\n")
        except OSError as e:
            raise click.ClickException(f"cannot write --json {json_path}: {e.strerror or e}") from None
        click.echo(f"wrote {json_path}")


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option(
    "--gt", "gt_path", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Ground-truth JSON: {'results': {sample_token: [box, ...]}} in the nuScenes global frame, each box with "
    "'ego_translation' and 'num_pts' (see streamdet.evaluation.results).",
)  # fmt: skip
@click.option(
    "--results", "results_path", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Predictions in the official nuScenes submission format {'meta': ..., 'results': ...}, covering every "
    "ground-truth sample.",
)  # fmt: skip
@click.option(
    "--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
    help="Also write the figures here as JSON: mAP, NDS, classes, tp_errors, per_class.",
)  # fmt: skip
@click.option(
    "--classes", default=None, metavar="NAME[,NAME...]",
    help="Evaluate and average only these classes (e.g. car,pedestrian,bicycle); default all 10, as the devkit.",
)  # fmt: skip
def main(gt_path: Path, results_path: Path, json_path: Path | None, classes: str | None) -> None:
    """nuScenes detection mAP, TP errors and NDS, computed as nuscenes-devkit 1.2.0 (detection_cvpr_2019).

    The devkit's bike-rack filter needs the bicycle-rack annotations, which these files do not hold: it is
    skipped. Without GT attributes, every attribute error is 1.
    """
    class_list = _parse_classes(classes)
    try:
        gt, pred = load_gt_and_predictions(gt_path, results_path)
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    _evaluate_and_report(gt, pred, class_list, json_path)


if __name__ == "__main__":
    main()
