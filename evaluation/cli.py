"""``streamdet-eval``: nuScenes detection metrics of a results file against a ground-truth file.

The command has two stages, so that input modes share the second: *inputs* (``--gt`` / ``--results`` files,
through ``load_eval_inputs``, or ``--data DIR``, which runs an export over a dataset split with the ONNX
runtime, ``dataset_eval.evaluate_dataset``) produce ground truth and predictions; the metrics are then printed
as one table and optionally written as JSON.
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import numpy as np

from streamdet.cli_utils import (
    MAX_SLICES,
    PRECISION_CHOICES,
    check_folder_creatable,
    check_output_parent,
    check_results_folder,
    image_precision_option,
    json_output_option,
    providers_option,
    refuse_image_lane_options,
    refuse_output_over_inputs,
    split_list,
    version_option,
    dataset_inputs,
    write_json_output,
)
from streamdet.evaluation.run_cli import OTHER_TOOLS_FOLDERS, export_reads_images
from streamdet.core.constants import DEFAULT_EXPORT_DIR
from streamdet.core.errors import first_line
from streamdet.evaluation.bootstrap import FEW_CLUSTERS
from streamdet.evaluation.config import TP_METRICS, DetectionConfig
from streamdet.evaluation.detection_eval import evaluate
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.metrics import DetectionMetrics
from streamdet.evaluation.results import load_eval_inputs
from streamdet.evaluation.saved_run import RESULTS_FILE, SAVED_FILES, save_run
from streamdet.progress import counted

_TP_SHORT = {"trans_err": "ATE", "scale_err": "ASE", "orient_err": "AOE", "vel_err": "AVE", "attr_err": "AAE"}
# --bootstrap: 10^5 draws resolve a 95 % interval far below any figure's printed precision; 10^9 ran for hours.
MAX_DRAWS = 100_000


def _parse_classes(value: str | None) -> tuple[str, ...] | None:
    if value is None:
        return None
    names = tuple(split_list(value, "--classes", "class"))
    known = DetectionConfig().class_names
    bad = [n for n in names if n not in known]
    if bad:
        raise click.BadParameter(f"unknown class {bad[0]!r}; choose from {','.join(known)}", param_hint="--classes")
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


def _evaluate_and_report(gt: EvalBoxes, pred: EvalBoxes, classes: tuple[str, ...] | None, json_path: Path | None,
                         bike_racks: dict | None = None, gt_path: Path | None = None,
                         results_path: Path | None = None, notes: tuple[str, ...] = ()) -> None:  # fmt: skip
    try:
        metrics = evaluate(gt, pred, classes=classes, bike_racks=bike_racks)
    except ValueError as e:  # evaluate knows boxes, not files: say which files its complaint is about
        where = f"{results_path} (against {gt_path}): " if results_path is not None else ""
        raise click.ClickException(f"{where}{e}") from None
    click.echo(format_table(metrics))
    for note in notes:
        click.echo(f"note: {note}")
    _note_absent_classes(metrics, set(gt.detection_name.tolist()))
    if bike_racks is None and np.isin(gt.detection_name, ("bicycle", "motorcycle")).any():
        # only where the rule could matter: a cycle in a rack would count here and not in the devkit
        click.echo(f"note: {gt_path or 'the ground truth'} has no bike_racks: the devkit's bike-rack rule is not applied")
    if json_path is not None:
        write_json_output(json_path, metrics.to_dict())
        click.echo(f"wrote {json_path}")


def _note_absent_classes(metrics: DetectionMetrics, present: set[str]) -> None:
    """A line under the table for the classes averaged that have no ground-truth box: the devkit's rule (AP 0, TP
    errors 1) is kept, and said, so that a 0 is not read as the detector's failure."""
    absent = [c for c in metrics.classes if c not in present]
    if absent:
        click.echo(f"note: no ground-truth box of {', '.join(absent)}: AP 0 and TP errors 1 by the devkit's rule, "
                   "counted in mAP and NDS (--classes chooses the classes averaged)")  # fmt: skip


def _data_inputs(data_dir: Path, version: str, split: str | None, export_dir: Path, slices: int | None,
                 precision: str, max_samples: int | None, classes: tuple[str, ...] | None, json_path: Path | None,
                 save_dir: Path | None = None, image_precision: str | None = None,
                 providers: tuple[str, ...] | None = None) -> None:  # fmt: skip
    """``--data`` mode: run the ONNX runtime over the split, then the same report as the files mode."""
    from streamdet.evaluation.dataset_eval import OnnxSweepDetector, evaluate_dataset  # onnxruntime, not torch

    try:
        detector = OnnxSweepDetector(export_dir, precision=precision, num_slices=slices, image_precision=image_precision,
                                     providers=providers)  # fmt: skip
    except (ValueError, OSError) as e:  # ManifestError is a ValueError
        raise click.ClickException(f"--export-dir {export_dir}: {first_line(e)}") from None
    n = detector.detector.num_slices
    label = detector.detector.precision_label  # "int8 image lane + fp32 slices" when the lanes differ
    try:
        with counted(f"detecting ({label}, {n} slices)") as progress:  # the sample count is known once the data is read
            result = evaluate_dataset(detector, data_dir, version=version, split=split, classes=classes,
                                      max_samples=max_samples, progress=progress)  # fmt: skip
    except (ValueError, OSError, KeyError) as e:  # the dataset's own defects (NuScenesReader names table and row)
        text = str(e.args[0]) if isinstance(e, KeyError) and e.args else str(e)  # KeyError's str() adds quotes
        raise click.ClickException((text.strip().splitlines() or [type(e).__name__])[0]) from None
    except MemoryError:  # not an input error to run_edge: say what ran out, not a traceback
        raise click.ClickException(f"out of memory while detecting over {data_dir} with {n} slices per sweep: "
                                   "try fewer --slices or --max-samples") from None
    click.echo(f"{result.num_samples} samples of {data_dir} ({split or 'all'} split), export {export_dir} ({label}), "
               f"{n} slices per sweep, {result.seconds:.1f} s")  # fmt: skip
    click.echo(format_table(result.metrics))
    _note_absent_classes(result.metrics, {e["detection_name"] for entries in result.ground_truth.values() for e in entries})
    if json_path is not None:
        lanes = {"image_precision": detector.detector.config.image_precision} if detector.detector.uses_images else {}
        doc = {**result.metrics.to_dict(), "num_samples": result.num_samples, "num_slices": n,
               "precision": detector.detector.config.precision, **lanes,
               "providers": list(detector.detector.providers),
               "export_dir": str(export_dir), "data_dir": str(data_dir), "split": split}  # fmt: skip
        write_json_output(json_path, doc)
        click.echo(f"wrote {json_path}")
    if save_dir is not None:
        try:
            written = save_run(save_dir, predictions=result.predictions, ground_truth=result.ground_truth,
                               ego_positions=result.ego_positions, scenes=result.scenes, poses=result.poses,
                               num_slices=n, use_camera=detector.detector.uses_images, bike_racks=result.bike_racks)  # fmt: skip
        except OSError as e:
            raise click.ClickException(f"cannot write --save-results {save_dir}: {e.strerror or e}") from None
        click.echo(f"wrote {', '.join(map(str, written[:-1]))} and {written[-1]}")


def _run_group(arg: str) -> list[Path]:
    """One side of --compare: a run, or several runs separated by commas (seeds of one recipe). An empty entry or a
    run named twice (one run counted as two seeds; a folder and its own results.json are one run) is refused,
    naming it."""
    paths = [Path(p) for p in split_list(arg, "--compare", "run", key=lambda p: _run_key(Path(p)))]
    for p in paths:
        if not p.exists():
            raise click.UsageError(f"--compare: {p} does not exist")
    return paths


# The options of one mode only, by parameter name: given in another mode they would be ignored, silently.
_MODE_OPTIONS = {
    "dataset": ("version", "split", "export_dir", "slices", "precision", "image_precision", "providers", "max_samples",
                "save_dir"),
    "compare": ("draws", "seed", "no_subsets"),
}


def _refuse_other_modes_options(ctx: click.Context, mode: str) -> None:
    """UsageError naming the options given on the command line that only another mode reads (a default is not
    given): ``--gt G --results R --split train`` evaluated the files and ignored the split."""
    given = []
    for other, names in _MODE_OPTIONS.items():
        if other == mode:
            continue
        for param in ctx.command.params:
            if param.name in names and ctx.get_parameter_source(param.name) is click.core.ParameterSource.COMMANDLINE:
                given.append((other, param.opts[0]))
    if given:
        listed = ", ".join(f"{opt} ({other} mode)" for other, opt in given)
        raise click.UsageError(f"{listed} not read in the {mode} mode; drop {'them' if len(given) > 1 else 'it'}")




def _saved_run_folders(path: Path) -> list[Path]:
    """The saved runs ``path`` (a --gt or --results file) lies in: its folder, spelled and resolved, where that folder
    holds every file --save-results writes (``SAVED_FILES``, regular files), which --compare reads as a run. Not a
    folder with only results.json and gt.json (a run saved before samples.json existed, or a user's own two files
    under the usual names): such a folder may take the --json, beside the two files."""
    folders = [path.parent]
    try:
        folders.append(path.resolve().parent)  # a link into a saved run: the files it reads are that run's
    except (OSError, RuntimeError):  # a link loop: the reading names it
        pass
    runs: list[Path] = []
    for folder in folders:
        if all((folder / name).is_file() for name in SAVED_FILES) and folder not in runs:
            runs.append(folder)
    return runs


def _run_key(path: Path) -> Path:
    """What makes two runs one: the results file each reads, resolved (a folder reads its results.json). Not the
    folder: several results files in one folder are several runs, and a folder and its own results.json are one."""
    return ((path / RESULTS_FILE) if path.is_dir() else path).resolve()


def _compare(run_a: str, run_b: str, gt_path: Path | None, classes: tuple[str, ...] | None, draws: int, seed: int,
             json_path: Path | None, subsets: bool = True) -> None:  # fmt: skip
    """``--compare`` mode: B - A with a paired bootstrap interval over scenes (``evaluation.compare``)."""
    from streamdet.evaluation.compare import compare_runs, format_comparison, load_run

    group_a, group_b = _run_group(run_a), _run_group(run_b)
    keys_b = {_run_key(p) for p in group_b}
    both = [p for p in group_a if _run_key(p) in keys_b]
    if both:
        shown, key = both[0].resolve(), _run_key(both[0])
        reads = "" if shown == key else f" (both read {key})"
        raise click.UsageError(f"--compare: {shown} is on both sides{reads}; a run compared with itself differs by nothing")
    refuse_output_over_inputs(json_path, "--json", [("--gt", gt_path), *(("--compare run", p) for p in group_a + group_b)])
    check_output_parent(json_path, "--json")  # now, not after the bootstrap
    try:
        a = [load_run(p, gt_path) for p in group_a]
        b = [load_run(p, gt_path) for p in group_b]
        # one step per subset (all boxes, few points, cut by a border, each slice): each draws `draws` times
        with counted(f"bootstrap ({draws} draws per subset)", item_show_func=lambda name: name) as progress:
            comparison = compare_runs(a, b, classes=classes, num_draws=draws, seed=seed, subsets=subsets,
                                      progress=lambda name, done, total: progress(done, total, name))
    except ValueError as e:
        raise click.ClickException(first_line(e)) from None
    name_a, name_b = ", ".join(map(str, group_a)), ", ".join(map(str, group_b))
    click.echo(format_comparison(comparison, name_a, name_b))
    if json_path is not None:
        def one_or_list(group: list[Path]):
            return str(group[0]) if len(group) == 1 else [str(p) for p in group]

        doc = {"A": one_or_list(group_a), "B": one_or_list(group_b), "seed": seed, **comparison.to_dict()}
        write_json_output(json_path, doc)
        click.echo(f"wrote {json_path}")


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option(
    "--gt", "gt_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
    help="Ground-truth JSON: {'results': {sample_token: [box, ...]}} in the nuScenes global frame, each box with "
    "'ego_translation' and 'num_pts', optionally 'bike_racks' for the devkit's bike-rack rule (see "
    "streamdet.evaluation.results). Files mode, with --results.",
)  # fmt: skip
@click.option(
    "--results", "results_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
    help="Predictions in the official nuScenes submission format {'meta': ..., 'results': ...}, covering every "
    "ground-truth sample. Files mode, with --gt.",
)  # fmt: skip
@click.option(
    "--data", "data_dir", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
    help="Dataset mode: a nuScenes-format dataset root (e.g. from streamdet-synth); the export is run over it with "
    "onnxruntime (all cameras, every slice, per-sweep NMS) and scored against its ground truth.",
)  # fmt: skip
@version_option(help="Dataset mode: the table folder under --data.")
@click.option("--split", default="val", show_default=True,
              help="Dataset mode: scenes of this split in DATA/splits.json; 'all' for every sample.")  # fmt: skip
@click.option("--export-dir", type=click.Path(file_okay=False, path_type=Path), default=Path(DEFAULT_EXPORT_DIR),
              show_default=True, help="Dataset mode: export directory written by streamdet-export.")  # fmt: skip
@click.option("--slices", type=click.IntRange(1, MAX_SLICES), default=None,
              help=f"Dataset mode: slices per sweep (1, 2 or a multiple of 4, up to {MAX_SLICES}); default: the export's.")  # fmt: skip
@click.option("--precision", type=click.Choice(PRECISION_CHOICES), default="fp32", show_default=True,
              help="Dataset mode: which graphs of the export to run.")  # fmt: skip
@image_precision_option()
@providers_option()
@click.option("--max-samples", type=click.IntRange(min=1), default=None, help="Dataset mode: score only the first N samples of the split.")
@json_output_option("Also write the figures here as JSON: mAP, NDS, classes, tp_errors, per_class.")
@click.option(
    "--save-results", "save_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
    help="Dataset mode: also write what was scored to this folder: results.json (the detections, nuScenes "
    "submission format), gt.json (the ground truth, with its bicycle racks), which the files mode scores again "
    "with --gt / --results to the same figures, and samples.json (scenes and poses, for --compare). An earlier saved "
    "run there is replaced (a note on stderr says so); an export or a dataset folder is refused. Default: none.",
)  # fmt: skip
@click.option(
    "--classes", default=None, metavar="NAME[,NAME...]",
    help="Evaluate and average only these classes (e.g. car,pedestrian,bicycle); default: files mode all 10, as the "
    "devkit; dataset mode the classes with a ground-truth box with points; compare mode the classes left with such "
    "a box after the devkit's class-range and bike-rack filters. A class whose boxes all lie beyond its range counts "
    "as AP 0 in the dataset mode but drops out of --compare, so a saved run's mAP can differ there: give --compare "
    "the classes the dataset mode printed to get its figures again.",
)  # fmt: skip
@click.option(
    "--compare", "compare_runs", nargs=2, type=str, default=None,
    metavar="RUN_A RUN_B",
    help="Compare two runs on the same ground truth: B - A for mAP, NDS and per-class AP with a paired bootstrap "
    "95 % interval over scenes, also per slice, for boxes cut by a slice border and for boxes with at most 5 points. "
    "A run is a folder written by --save-results, or a results file (then give --gt). Either side may be several "
    "runs separated by commas (seeds of one recipe): their mean, the bootstrap resampling the runs too. With one "
    f"scene the interval is undefined and nothing is marked significant; with fewer than {FEW_CLUSTERS} a note says "
    "it is unreliable.",
)  # fmt: skip
@click.option("--bootstrap", "draws", type=click.IntRange(1, MAX_DRAWS), default=1000, show_default=True,
              help=f"Compare mode: bootstrap draws per subset, 1..{MAX_DRAWS}.")  # fmt: skip
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Compare mode: seed of the bootstrap draws.")  # fmt: skip
@click.option("--no-subsets", "no_subsets", is_flag=True,
              help="Compare mode: bootstrap all boxes only, without the per-slice, cut-by-border and few-points "
              "subsets (each subset costs as much as the headline: 35 of them at 32 slices).")  # fmt: skip
def main(gt_path: Path | None, results_path: Path | None, data_dir: Path | None, version: str, split: str,
         export_dir: Path, slices: int | None, precision: str, image_precision: str | None,
         providers: tuple[str, ...] | None, max_samples: int | None, json_path: Path | None, classes: str | None, save_dir: Path | None,
         compare_runs: tuple[str, str] | None = None, draws: int = 1000, seed: int = 0,
         no_subsets: bool = False) -> None:  # fmt: skip
    """nuScenes detection mAP, TP errors and NDS, computed as nuscenes-devkit 1.2.0 (detection_cvpr_2019).

    Three modes: --gt with --results (two JSON files), --data (run an export over a dataset split), or
    --compare RUN_A RUN_B (two saved runs, or two comma-separated groups of runs; paired bootstrap over scenes).
    The devkit's bike-rack filter needs the bicycle-rack annotations: the dataset mode reads them, a ground-truth
    file carries them as 'bike_racks' (gt.json of --save-results does); without them it is skipped, with a note.
    Without GT attributes, every attribute error is 1.
    """
    class_list = _parse_classes(classes)
    mode = "compare" if compare_runs else "dataset" if data_dir is not None else "files"
    _refuse_other_modes_options(click.get_current_context(), mode)
    if compare_runs:
        if data_dir is not None or results_path is not None or save_dir is not None:
            raise click.UsageError("--compare reads two saved runs; do not combine it with --data / --results / --save-results")
        _compare(compare_runs[0], compare_runs[1], gt_path, class_list, draws, seed, json_path, subsets=not no_subsets)
        return
    if data_dir is not None:
        if gt_path is not None or results_path is not None:
            raise click.UsageError("--data runs the detector itself; do not combine it with --gt / --results")
        if slices is not None and slices not in (1, 2) and slices % 4:
            raise click.BadParameter(f"{slices} must be 1, 2 or a multiple of 4", param_hint="--slices")
        refuse_image_lane_options(click.get_current_context(), export_dir, ("image_precision",), export_reads_images)
        inputs = [*dataset_inputs(data_dir), ("--export-dir", export_dir)]
        refuse_output_over_inputs(json_path, "--json", inputs)
        refuse_output_over_inputs(save_dir, "--save-results", inputs)
        # --save-results writes its files after the --json: one of them would replace the figures just written
        saved = {(save_dir / name).resolve() for name in SAVED_FILES} if save_dir is not None else set()
        if json_path is not None and json_path.resolve() in saved:
            raise click.BadParameter(f"{str(json_path)!r} is one of the files --save-results {save_dir} writes "
                                     f"({', '.join(SAVED_FILES)}); choose another path", param_hint="--json")  # fmt: skip
        check_output_parent(json_path, "--json")  # now, not after the whole split was detected
        check_folder_creatable(save_dir, "--save-results")
        if save_dir is not None and save_dir.is_dir():  # a folder or a FIFO where a file goes: found now, not after detecting
            for name in SAVED_FILES:
                check_output_parent(save_dir / name, "--save-results")
        # last: the note that an earlier saved run is replaced comes only once nothing else is refused
        check_results_folder(save_dir, "--save-results", SAVED_FILES, "saved run", OTHER_TOOLS_FOLDERS)
        _data_inputs(data_dir, version, None if split == "all" else split, export_dir, slices, precision, max_samples,
                     class_list, json_path, save_dir, image_precision, providers)  # fmt: skip
        return
    if image_precision is not None:
        raise click.UsageError("--image-precision is for the dataset mode (--data), which runs the detector")
    if save_dir is not None:
        raise click.UsageError("--save-results is for the dataset mode (--data): the files mode already has its files")
    if gt_path is None or results_path is None:
        raise click.UsageError("give --gt and --results (files mode), or --data (dataset mode)")
    refuse_output_over_inputs(json_path, "--json", [("--gt", gt_path), ("--results", results_path)])
    # a saved run's other files (samples.json, which --compare reads) lie beside the two inputs
    for option, path in (("--gt", gt_path), ("--results", results_path)):
        siblings = {(path.parent / name).resolve() for name in SAVED_FILES}
        if json_path is not None and json_path.resolve() in siblings:
            raise click.BadParameter(f"{str(json_path)!r} is a file of the saved run beside {option} {path} "
                                     f"({', '.join(SAVED_FILES)}); choose another path", param_hint="--json")  # fmt: skip
    # and the saved run itself is an input, as --compare reads it: no tool writes into a saved run's folder
    refuse_output_over_inputs(json_path, "--json", [(f"{option}'s saved run", folder)
                                                    for option, path in (("--gt", gt_path), ("--results", results_path))
                                                    for folder in _saved_run_folders(path)])  # fmt: skip
    check_output_parent(json_path, "--json")  # a FIFO there blocked the write after the scoring
    try:
        inputs = load_eval_inputs(gt_path, results_path)
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    if len(inputs.gt) == 0:  # every AP would be 0 by definition: a score of nothing, not a result
        raise click.ClickException(f"{gt_path}: the ground truth holds no box, so there is nothing to evaluate")
    _evaluate_and_report(inputs.gt, inputs.pred, class_list, json_path, inputs.bike_racks, gt_path, results_path,
                         inputs.notes)  # fmt: skip


if __name__ == "__main__":
    main()
