"""``streamdet-synth``: write a synthetic camera + LiDAR dataset in the nuScenes format (and preview pictures),
and ``streamdet-synth stats DIR`` to measure a dataset against the real nuScenes sample.

``streamdet-synth --out DIR ...`` (no subcommand) is the generator, as it always was: the group runs the
``generate`` command whenever the first argument is an option (a generate invocation always starts with one; a word
that names no subcommand, ``streamdet-synth stat DIR``, is click's "No such command" error).
"""

from __future__ import annotations

import gc
import multiprocessing
import os
import signal
import sys
import threading
import traceback
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import click

from streamdet.cli_utils import (
    MAX_THREADS,
    FiniteFloatRange,
    RESOLUTION_RANGE_HELP,
    check_folder_creatable,
    check_output_parent,
    check_plot_format,
    json_output_option,
    refuse_output_over_inputs,
    refuse_same_outputs,
    resolution_callback,
    write_json_output,
)
from streamdet.core.errors import first_line
from streamdet.core.points import SWEEP_DURATION_S
from streamdet.data.synth_memory import PEAK_BYTES_PER_PIXEL, memory_problem
from streamdet.data.synth_staging import StagedDataset
from streamdet.data.synth_stats import open_samples
from streamdet.data.synth_world import WorldConfig
from streamdet.data.synth_writer import (
    DEFAULT_VERSION,
    GenerationSummary,
    RootSurvey,
    SynthConfig,
    remove_dataset_entries,
    resolution_problem,
    survey_root,
    version_problem,
)
from streamdet.progress import progressbar


# Upper bounds of the numeric options, far past any documented use (nuScenes: 1000 scenes of about 40 key frames),
# short of a run that never ends (--scenes 10**12) or a layout that allocates terabytes (--samples-per-scene 10**12).
MAX_SCENES = 10_000
MAX_SAMPLES_PER_SCENE = 1000  # 500 s of drive per scene at 2 Hz
MAX_STATS_SAMPLES = 1_000_000  # key frames measured by `stats` (nuScenes has 40k)
MAX_CAMERA_HZ = round(1.0 / SWEEP_DURATION_S, 6)  # once per rotation of the LiDAR (20 Hz)
KEY_FRAME_HZ = round(1.0 / WorldConfig().sample_interval_s, 6)  # each key frame adds its exposure to --camera-hz's
EXIT_TERMINATED = 128 + signal.SIGTERM  # 143, as a shell reports a process ended by SIGTERM


class _DefaultGroup(click.Group):
    """A group that runs ``generate`` when the first argument is an option other than help (the old invocation,
    ``streamdet-synth --out DIR ...``). Any other first word is a subcommand's name, or click's "No such command"
    error with its "Did you mean" hint (``stat``): not a generate run told that --out is missing."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if args and args[0].startswith("-") and args[0] not in self.get_help_option_names(ctx):
            args = ["generate"] + list(args)
        return super().parse_args(ctx, args)


class _Terminated(SystemExit):
    """What the run's SIGTERM handler raises in the main thread (`_SigtermStopsRun`): it unwinds the run as Ctrl-C
    does (StagedDataset removes what the run wrote); left uncaught, it ends the process with EXIT_TERMINATED."""

    def __init__(self) -> None:
        super().__init__(EXIT_TERMINATED)


class _SigtermStopsRun:
    """While open, SIGTERM (``timeout``, ``kill``, ``docker stop``, a scheduler's time limit) stops the run as Ctrl-C
    does, where its default action ended the process at once and left the staging folder behind: it raises
    `_Terminated` in the main thread, and the first one ends the worker processes too (their scenes are the staging
    folder's, and would otherwise run to their end first). Once the caller's cleanup has begun (`stopping`), more
    are ignored (SIGKILL still ends the process). An exception raised in a signal handler is lost where C code
    clears the errors of what it calls (numpy's probe of an operand's special attributes, at ``mat == Mat.STRIPES``),
    and the run went on: `check` raises it again, called at each key frame and before the dataset is moved into
    place. A worker forked while it is open ends at SIGTERM as by default. The previous handler is restored on
    leaving. Outside the main thread, or where the previous handler was set from C (it could not be put back), it
    installs nothing."""

    def __init__(self) -> None:
        self.received = False
        self.stopping = False  # set by the caller as it cleans up: further SIGTERMs would cut the cleanup short
        self._pid = os.getpid()
        self._previous = None
        self._installed = False

    def __enter__(self) -> _SigtermStopsRun:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.getsignal(signal.SIGTERM)
            if self._previous is not None:
                signal.signal(signal.SIGTERM, self._handle)
                self._installed = True
        return self

    def __exit__(self, *exc_info) -> None:
        if self._installed:
            signal.signal(signal.SIGTERM, self._previous)
            self._installed = False

    def check(self) -> None:
        """Raise `_Terminated` where SIGTERM came and the run goes on (its first exception lost)."""
        if self.received and not self.stopping:
            raise _Terminated()

    def _handle(self, signum: int, frame) -> None:
        if os.getpid() != self._pid:  # a worker process, forked with this handler: the default action
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGTERM)
            return
        if self.stopping:
            return
        if not self.received:
            self.received = True
            for child in multiprocessing.active_children():  # the scene workers of generate_dataset
                child.terminate()
        raise _Terminated()


@click.group(cls=_DefaultGroup, context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Synthetic street data in the nuScenes format: `streamdet-synth --out DIR ...` (the generate command) writes
    a dataset; `streamdet-synth stats DIR` measures one against the real nuScenes sample."""


def _version(value: str) -> str:
    problem = version_problem(value)
    if problem:
        raise click.BadParameter(problem, param_hint="--version")
    return value


def _resolution(ctx: click.Context, param: click.Parameter, value: str) -> tuple[int, int]:
    """WIDTHxHEIGHT in range, and of the cameras' aspect (``resolution_problem``): refused before any work, as
    streamdet-train, streamdet-export and the runtime would refuse the dataset afterwards."""
    size = resolution_callback()(ctx, param, value)
    problem = resolution_problem(size)
    if problem:
        raise click.BadParameter(problem, ctx=ctx, param=param)
    return size


def _listing(entries, limit: int = 8) -> str:
    """'a/, b.json, c/ and 3 more': folders marked with a slash."""
    names = [e.name + ("/" if e.is_dir() and not e.is_symlink() else "") for e in entries]
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def _check_out_dir(out_dir: Path, version: str, overwrite: bool) -> tuple[Path, ...]:
    """What must be deleted before writing into ``out_dir`` (with --overwrite: the dataset it holds), else a
    ClickException. A dataset's splits.json, world.json and samples/ are shared by every --version, so writing a
    second dataset beside one replaced the first one's split and world silently: without --overwrite, OUT must be
    new or empty."""
    if out_dir.exists() and not out_dir.is_dir():
        raise click.BadParameter(f"{out_dir} exists and is not a folder", param_hint="--out")
    check_folder_creatable(out_dir, "--out")  # a broken link or a loop: said now, not after the simulation
    try:
        if not out_dir.is_dir() or not any(out_dir.iterdir()):
            return ()
        survey = survey_root(out_dir)
    except OSError as e:
        raise click.ClickException(f"--out {out_dir}: cannot list the folder: {e}") from None
    if not survey.dataset and not survey.foreign:
        # streamdet's training cache alone (what a failed --overwrite leaves: the old dataset deleted, the new one
        # removed): as an empty folder; the cache stays, and checks its data fingerprint before any use
        return ()
    if survey.marker_problem is not None:
        raise click.ClickException(
            f"--out {out_dir} is a non-empty folder that is not a streamdet-synth dataset ({survey.marker_problem}; "
            f"it holds {_listing(survey.dataset + survey.kept + survey.foreign)}): "
            + ("--overwrite replaces only a streamdet-synth dataset and deletes nothing here" if overwrite
               else "refusing to write into it")
            + "; choose a new or empty folder"
        )
    if survey.foreign:
        raise click.ClickException(
            f"--out {out_dir} holds a streamdet-synth dataset and other entries ({_listing(survey.foreign)}): "
            "--overwrite would replace only the dataset's own files, and these would be left mixed into the new "
            "one; move them out, or choose a new or empty folder"
        )
    if not overwrite:
        raise click.ClickException(_occupied(out_dir, version, survey))
    return survey.dataset


def _occupied(out_dir: Path, version: str, survey: RootSurvey) -> str:
    """The message for an --out that holds a synth dataset, without --overwrite."""
    held = _listing(survey.dataset)
    if (out_dir / version).exists():
        return (f"{out_dir / version} already exists: --out {out_dir} holds a streamdet-synth dataset ({held}); "
                "pass --overwrite to replace it (those are deleted first), or choose another --out")
    return (f"--out {out_dir} already holds a streamdet-synth dataset ({held}); another --version beside it would "
            "replace its splits.json, world.json and files under samples/: pass --overwrite to replace the whole "
            "dataset (those are deleted first), or choose another --out")


@main.command("generate", context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Dataset root to write: tables go to OUT/<version>/, key frames' files to OUT/samples/, and "
                   "the sweeps between key frames (--sweeps-per-sample above 1, --camera-hz) to OUT/sweeps/.")
@click.option("--scenes", default=2, show_default=True, type=click.IntRange(1, MAX_SCENES),
              help=f"Number of scenes (1..{MAX_SCENES}).")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0), help="Random seed; the same seed writes the same dataset.")
@click.option("--resolution", default="800x450", show_default=True, callback=_resolution, metavar="WxH",
              help=f"Camera image size WIDTHxHEIGHT, {RESOLUTION_RANGE_HELP}, of the real rig's aspect (16:9, as the "
                   "other tools require; intrinsics of the real rig scaled to it). Memory grows with it (about "
                   f"{PEAK_BYTES_PER_PIXEL * 1e6 / 1e9:.1f} GB per megapixel per --workers process): a run this machine "
                   "cannot hold is refused before it starts.")
@click.option("--samples-per-scene", default=10, show_default=True, type=click.IntRange(1, MAX_SAMPLES_PER_SCENE),
              help=f"Key frames per scene, 0.5 s apart (2 Hz, as nuScenes); 1..{MAX_SAMPLES_PER_SCENE}.")
@click.option("--sweeps-per-sample", default=1, show_default=True, type=click.IntRange(1, 10),
              help="LiDAR sweeps per key-frame interval including the key frame, 1..10 (nuScenes has 10, at 20 Hz).")
@click.option("--camera-hz", default=0.0, show_default=True, type=FiniteFloatRange(0.0, MAX_CAMERA_HZ),
              help="Camera exposures a second, each as the LiDAR crosses the camera's axis (nuScenes: 12, with "
                   "--sweeps-per-sample 10, which a replay needs to find a frame at each of its triggers: "
                   "docs/synth/timing.md); 0: at key frames only (2 Hz). The key frames' own exposures are added to "
                   f"this rate's: a camera gets at least this rate and up to {KEY_FRAME_HZ:g} Hz more, by camera and "
                   "--sweeps-per-sample (with 10, a rate of 10 gives as many frames as 12). The frames between key "
                   "frames go to OUT/sweeps/CAM_*/ as nuScenes files its camera sweeps (no masks, no annotations; training reads key "
                   "frames only, streamdet-replay and streamdet-bag read them all). Rendering time grows with the "
                   f"rate: 12 Hz renders 6 to 7 times the images. At most {MAX_CAMERA_HZ:g} (once per LiDAR rotation).")
@click.option("--version", "version", default=DEFAULT_VERSION, show_default=True,
              callback=lambda ctx, param, value: _version(value),
              help="Name of the table folder (the nuScenes 'version'): one folder name, not one of the layout's own.")
@click.option("--preview", is_flag=True, help="Also write pictures of the first key frame to OUT/preview/: the six cameras with the ground truth and a bird's-eye view coloured by slice (8 slices).")
@click.option("--workers", default=1, show_default=True, type=click.IntRange(1, MAX_THREADS),
              help=f"Processes simulating scenes in parallel, 1..{MAX_THREADS} (the output does not depend on it).")
@click.option("--overwrite", is_flag=True,
              help="Replace the streamdet-synth dataset OUT already holds (any version): its tables, samples/, sweeps/, "
                   "maps/, preview/, splits.json, world.json and trajectories.npz are deleted first. A folder that is "
                   "not such a dataset, or holds other files too, is refused all the same.")
def generate(out_dir: Path, scenes: int, seed: int, resolution: tuple[int, int], samples_per_scene: int,
         sweeps_per_sample: int, camera_hz: float, version: str, preview: bool, workers: int, overwrite: bool) -> None:
    """Generate a synthetic street dataset readable by streamdet's nuScenes reader and the nuScenes devkit."""
    try:
        config = SynthConfig(num_scenes=scenes, seed=seed, resolution=resolution, sweeps_per_sample=sweeps_per_sample,
                             camera_hz=camera_hz, version=version, world=WorldConfig(samples_per_scene=samples_per_scene))
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    # Before any work: the largest resolutions need GBs per process, and numpy ran out minutes into the run.
    problem = memory_problem(resolution, workers, scenes)
    if problem:
        raise click.ClickException(problem)
    table_dir = out_dir / version
    replaced = _check_out_dir(out_dir, version, overwrite)
    deleted = _listing(replaced)  # listed while they exist (folders marked)
    previews: list[Path] = []
    sigterm = _SigtermStopsRun()

    def finish(root: Path) -> None:  # in the staging folder: the previews are part of what appears at once
        sigterm.check()  # last before the dataset is moved into --out
        if preview:
            from streamdet.data.nuscenes import NuScenesReader
            from streamdet.data.preview import write_previews

            reader = NuScenesReader(root, version)
            previews.extend(out_dir / p.relative_to(root) for p in write_previews(reader.get(0), root / "preview", n_slices=8))

    staged: StagedDataset | None = None
    deleting = ""  # `deleted` once --overwrite has begun deleting it
    with sigterm:  # SIGTERM unwinds the run as Ctrl-C does, for this run only
        try:
            # Everything that needs no simulation is checked and made before any is run, and before --overwrite
            # deletes anything: --out (and its parents) made, the staging folder beside it and its table folder. The
            # dataset is written there and renamed into --out at the end: an error, Ctrl-C or SIGTERM leaves --out as
            # it was (StagedDataset).
            try:
                staged = StagedDataset(out_dir, config)
            except OSError as e:
                raise click.ClickException(f"cannot write the dataset under {out_dir}: {e}") from None
            if replaced:
                click.echo(f"replacing the streamdet-synth dataset in {out_dir}: deleting {deleted}")
                deleting = deleted
                _delete_previous(staged, replaced)
            summary = _simulate(staged, scenes * samples_per_scene, scenes, workers, resolution, deleted, finish,
                                sigterm.check)
        except BaseException as e:
            if not sigterm.received:
                raise
            sigterm.stopping = True
            _release_quietly(e)
            click.echo(f"streamdet-synth: stopped by SIGTERM: {_terminated(out_dir, deleting, staged)}", err=True)
            raise SystemExit(EXIT_TERMINATED) from None
    click.echo(
        f"wrote {len(summary.scenes)} scenes, {summary.num_samples} key frames, {summary.num_sweeps} LiDAR sweeps "
        f"(mean {summary.mean_points_per_sweep:.0f} points), {summary.num_images} images "
        f"({resolution[0]}x{resolution[1]}{_sweep_images(summary)}), {summary.num_annotations} box annotations in "
        f"{summary.seconds:.1f} s"
    )
    click.echo(f"  tables: {table_dir}/  files: {_files(out_dir, summary)}  splits: {out_dir / 'splits.json'}")
    for path in previews:
        click.echo(f"  preview: {path}")


def _delete_previous(staged: StagedDataset, replaced: tuple[Path, ...]) -> None:
    """--overwrite: delete the dataset --out held (``replaced``); on any error, Ctrl-C or SIGTERM the staging
    folder goes too."""
    try:
        remove_dataset_entries(replaced)
    except BaseException as e:
        staged.abandon()
        if isinstance(e, OSError):
            raise click.ClickException(f"cannot delete the previous dataset in {staged.out}: {e}") from None
        raise


def _simulate(staged: StagedDataset, total: int, scenes: int, workers: int, resolution: tuple[int, int], deleted: str,
              finish, check) -> GenerationSummary:
    """``staged.generate`` behind a progress bar of ``total`` key frames, its errors as one-line ClickExceptions that
    say what the abandoned run left (``deleted``: the previous dataset --overwrite deleted, listed); ``check()`` at
    each progress report."""
    out_dir = staged.out
    try:
        with progressbar(length=total, label=f"simulating {scenes} scene(s)") as bar:
            def progress(n: int) -> None:
                check()
                bar.update(n)

            return staged.generate(progress=progress, workers=workers, finish=finish)
    except (OSError, ValueError) as e:
        raise click.ClickException(f"cannot write the dataset under {out_dir}: {e}; {_abandoned(out_dir, deleted, staged.left)}") from None
    except (MemoryError, BrokenProcessPool) as e:
        # The estimate passed, yet memory ran out (other programs took it meanwhile, or a limit the probe does not
        # see); a worker the kernel kills for memory breaks the pool without a MemoryError of its own.
        if isinstance(e, MemoryError):
            what = f"out of memory ({first_line(e)})"
        else:
            what = f"a worker process ended abruptly, as one killed for memory does ({first_line(e)})"
        fewer = " or fewer --workers" if workers > 1 and scenes > 1 else ""
        raise click.ClickException(
            f"--resolution {resolution[0]}x{resolution[1]} with --workers {workers}: {what}; choose a lower "
            f"--resolution{fewer}; {_abandoned(out_dir, deleted, staged.left)}") from None
    except KeyboardInterrupt:
        click.echo(f"streamdet-synth: {_abandoned(out_dir, deleted, staged.left)}", err=True)
        raise


def _terminated(out_dir: Path, deleting: str, staged: StagedDataset | None) -> str:
    """What a run stopped by SIGTERM left; the run is abandoned (again: the exception may have cut short a cleanup
    under way) unless its dataset was complete in ``out_dir`` already."""
    if staged is None:  # stopped while StagedDataset was made: it removed what it had made
        return _abandoned(out_dir, "", [])
    if staged.done:
        return f"the run had ended: the dataset in {out_dir} is complete"
    staged.abandon()
    return _abandoned(out_dir, deleting, staged.left)


def _release_quietly(exc: BaseException | None) -> None:
    """Free the locals of the finished frames that ``exc`` and the exceptions it chains hold, with Python's
    "Exception ignored in" reports muted meanwhile. SIGTERM may cut a file write anywhere (in numpy's zip writer of
    a mask, between its entry and its close): the half-closed writer then complained of its closed file as it was
    collected at exit, a traceback after the one-line note. Its file is removed with the staging folder anyway."""
    hook = sys.unraisablehook
    sys.unraisablehook = lambda unraisable: None
    try:
        todo, seen = [exc], set()
        while todo:
            e = todo.pop()
            if e is not None and id(e) not in seen:
                seen.add(id(e))
                traceback.clear_frames(e.__traceback__)  # the frames still running (this one's callers) are skipped
                todo += [e.__cause__, e.__context__]
        gc.collect()
    finally:
        sys.unraisablehook = hook


def _files(out_dir: Path, summary: GenerationSummary) -> str:
    """The file folders the run wrote: OUT/samples/, and OUT/sweeps/ where there were sweeps between key frames."""
    between = summary.num_sweeps > summary.num_samples or summary.num_images > summary.num_key_images
    return f"{out_dir / 'samples'}/" + (f", {out_dir / 'sweeps'}/" if between else "")


def _sweep_images(summary) -> str:
    sweeps = summary.num_images - summary.num_key_images
    return f"; {summary.num_key_images} at key frames, {sweeps} between" if sweeps else ""


def _abandoned(out_dir: Path, deleted: str, left: list[str]) -> str:
    """What an abandoned run left: nothing of its own (else what); with --overwrite, no previous dataset either
    (``deleted``: its entries, listed; "" without one)."""
    if left:
        text = f"could not remove all that this run had written: {'; '.join(left)}"
    else:
        text = f"removed what this run had written ({out_dir} is as it was before the run"
        text += ", less the previous dataset)" if deleted else ")"
    if deleted:
        text += (f"; the previous dataset ({deleted}) was deleted before the run started, as --overwrite "
                 "does: run again to write a new one")
    return text


@main.command("stats", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("data_dir", type=click.Path(path_type=Path))
@click.option("--reference", "reference_dir", type=click.Path(path_type=Path), default=None,
              help="Dataset to compare with (nuScenes tables or a bundled-sample folder); default: the bundled real nuScenes sample.")
@click.option("--no-reference", is_flag=True, help="Measure DATA_DIR alone (not with --reference).")
@json_output_option("Also write both measurements as JSON to this file (its folder must exist).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also draw them to this file, a PNG or another format matplotlib writes, by its suffix "
                   "(needs matplotlib; its folder must exist).")
@click.option("--max-samples", type=click.IntRange(1, MAX_STATS_SAMPLES), default=None,
              help=f"Measure only the first N key frames (1..{MAX_STATS_SAMPLES}).")
def stats(data_dir: Path, reference_dir: Path | None, no_reference: bool, json_path: Path | None, plot_path: Path | None,
          max_samples: int | None) -> None:
    """Measure DATA_DIR's LiDAR cues (points on box faces, in-box intensity, points per box by range, vehicle
    headings, distractors, class shares, points per sweep) per class and 10 m bin, beside a reference."""
    from streamdet.data.synth_stats import dataset_stats, format_table, plot_stats, reference_dir as default_reference

    if no_reference and reference_dir is not None:
        raise click.BadParameter("--no-reference measures DATA_DIR alone: give one of --reference and --no-reference",
                                 param_hint="--reference")  # fmt: skip
    reference = None if no_reference else (reference_dir or default_reference())
    _check_stats_outputs(data_dir, reference, json_path, plot_path)
    results = []
    for path in [data_dir] + ([] if reference is None else [reference]):
        try:
            _, count, _, _ = open_samples(path)
            count = min(count, max_samples) if max_samples else count
            with progressbar(length=count, label=f"measuring {path}") as bar:
                results.append(dataset_stats(path, max_samples=max_samples, progress=bar.update))
        except (FileNotFoundError, ValueError, KeyError) as e:
            raise click.ClickException(f"cannot measure {path}: {e}") from None
    click.echo(format_table(results[0], results[1] if len(results) > 1 else None))
    if json_path is not None:
        doc = {"data": results[0], "reference": results[1] if len(results) > 1 else None}
        write_json_output(json_path, doc, allow_nan=True)
        click.echo(f"  json: {json_path}")
    if plot_path is not None:
        click.echo(f"  plot: {plot_stats(plot_path, results)}")


def _check_stats_outputs(data_dir: Path, reference: Path | None, json_path: Path | None, plot_path: Path | None) -> None:
    """Refuse, before measuring (minutes on a large dataset), outputs that cannot be written or would replace an
    input: ``--json DATA_DIR/splits.json`` replaced the split file of the dataset it measured."""
    for option, folder in (("DATA_DIR", data_dir), ("--reference", reference)):
        if folder is not None and not Path(folder).is_dir():  # both are measured in turn: a bad reference said first
            why = "not a folder" if Path(folder).exists() else "does not exist (or is a broken link)"
            raise click.BadParameter(f"{str(folder)!r} is no dataset folder: {why}", param_hint=option)
    outputs = [("--json", json_path), ("--plot", plot_path)]
    for option, path in outputs:
        refuse_output_over_inputs(path, option, [("DATA_DIR", data_dir), ("--reference", reference)])
        check_output_parent(path, option)  # no folders made on the way: a typo in the folder is an error
    refuse_same_outputs(outputs)
    if plot_path is not None:
        check_plot_format(plot_path)




if __name__ == "__main__":
    main()
