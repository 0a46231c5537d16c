"""``streamdet-synth``: write a synthetic camera + LiDAR dataset in the nuScenes format (and preview pictures)."""

from __future__ import annotations

from pathlib import Path

import click

from streamdet.cli_utils import resolution_callback
from streamdet.data.synth_world import WorldConfig
from streamdet.data.synth_writer import DEFAULT_VERSION, SynthConfig, generate_dataset


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Dataset root to write: tables go to OUT/<version>/, files to OUT/samples/ and OUT/sweeps/.")
@click.option("--scenes", default=2, show_default=True, type=click.IntRange(min=1), help="Number of scenes.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0), help="Random seed; the same seed writes the same dataset.")
@click.option("--resolution", default="800x450", show_default=True, callback=resolution_callback(min_px=16, max_px=4096),
              help="Camera image size WIDTHxHEIGHT (intrinsics of the real rig scaled to it).")
@click.option("--samples-per-scene", default=10, show_default=True, type=click.IntRange(min=1),
              help="Key frames per scene, 0.5 s apart (2 Hz, as nuScenes).")
@click.option("--sweeps-per-sample", default=1, show_default=True, type=click.IntRange(1, 10),
              help="LiDAR sweeps per key-frame interval including the key frame (nuScenes has 10, at 20 Hz).")
@click.option("--version", "version", default=DEFAULT_VERSION, show_default=True, help="Name of the table folder (the nuScenes 'version').")
@click.option("--preview", is_flag=True, help="Also write pictures of the first key frame to OUT/preview/: the six cameras with the ground truth and a bird's-eye view coloured by slice (8 slices).")
@click.option("--workers", default=1, show_default=True, type=click.IntRange(min=1),
              help="Processes simulating scenes in parallel (the output does not depend on it).")
@click.option("--overwrite", is_flag=True, help="Write into OUT even if it already holds a dataset of this version.")
def main(out_dir: Path, scenes: int, seed: int, resolution: tuple[int, int], samples_per_scene: int,
         sweeps_per_sample: int, version: str, preview: bool, workers: int, overwrite: bool) -> None:
    """Generate a synthetic street dataset readable by streamdet's nuScenes reader and the nuScenes devkit."""
    table_dir = out_dir / version
    if table_dir.exists() and not overwrite:
        raise click.ClickException(f"{table_dir} already exists; pass --overwrite or choose another --out")
    if out_dir.exists() and not out_dir.is_dir():
        raise click.ClickException(f"--out {out_dir} exists and is not a folder")
    try:
        config = SynthConfig(num_scenes=scenes, seed=seed, resolution=resolution, sweeps_per_sample=sweeps_per_sample,
                             version=version, world=WorldConfig(samples_per_scene=samples_per_scene))
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    total = scenes * samples_per_scene
    try:
        with click.progressbar(length=total, label=f"simulating {scenes} scene(s)", show_pos=True) as bar:
            summary = generate_dataset(out_dir, config, progress=bar.update, workers=workers)
    except OSError as e:
        raise click.ClickException(f"cannot write the dataset under {out_dir}: {e}") from None
    click.echo(
        f"wrote {len(summary.scenes)} scenes, {summary.num_samples} key frames, {summary.num_sweeps} LiDAR sweeps "
        f"(mean {summary.mean_points_per_sweep:.0f} points), {summary.num_images} images "
        f"({resolution[0]}x{resolution[1]}), {summary.num_annotations} box annotations in {summary.seconds:.1f} s"
    )
    click.echo(f"  tables: {table_dir}/  files: {out_dir / 'samples'}/, {out_dir / 'sweeps'}/  splits: {out_dir / 'splits.json'}")
    if preview:
        from streamdet.data.nuscenes import NuScenesReader
        from streamdet.data.preview import write_previews

        reader = NuScenesReader(out_dir, version)
        for path in write_previews(reader.get(0), out_dir / "preview", n_slices=8):
            click.echo(f"  preview: {path}")


if __name__ == "__main__":
    main()
