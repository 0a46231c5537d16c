"""The studies' two ways in from a PyTorch checkpoint (both need torch, imported when called): a LiDAR-only baseline
evaluated with PyTorch, and a camera + LiDAR checkpoint exported first. Everything else of the studies runs an
export through onnxruntime without torch."""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from pathlib import Path

from streamdet.data.sample import Sample
from streamdet.runtime_ort.postprocess import Detections
from streamdet.studies.common import StudyError
from streamdet.studies.slices import SlicedDetector


def torch_sliced_detector(checkpoint: str | Path, threads: int = 1, device: str = "cpu") -> SlicedDetector:
    """A checkpoint evaluated with PyTorch (``training.torch_eval``), for a LiDAR-only baseline that has not been
    exported (``streamdet-export --checkpoint`` turns one into its slice graph, for ``--baseline-export-dir``).
    Scored exactly as the ONNX models; needs torch.

    ``threads`` sets torch's intra-op threads for the whole process: on a shared 2-core machine the default (all
    cores) made the 32-slice sweep many times slower than one thread (benchmarks/RESULTS.md).
    """
    try:
        torch = importlib.import_module("torch")  # lazily: everything else in this module stays torch-free
        from streamdet.training.checkpoint import load_weights
        from streamdet.training.torch_eval import TorchSweepDetector
    except ImportError as e:
        raise StudyError(f"--baseline-checkpoint needs PyTorch (pip install '.[export]'): {e}") from None
    torch.set_num_threads(threads)
    try:
        model, preset = load_weights(checkpoint)
    except ValueError as e:
        raise StudyError(str(e)) from None
    kind = "camera + LiDAR" if preset.use_image else "LiDAR only"

    class _Torch:
        description = f"checkpoint {checkpoint} ({preset.name}, {kind}, PyTorch fp32 on {device})"
        uses_images = bool(preset.use_image)  # streamdet-study refuses a camera + LiDAR model as the LiDAR-only baseline

        def __call__(self, sample: Sample, slice_counts: Sequence[int]) -> dict[int, Detections]:
            return {n: TorchSweepDetector(model, num_slices=n, device=device)(sample) for n in slice_counts}

    return _Torch()


def export_checkpoint(
    checkpoint: str | Path, out_dir: str | Path, precision: str = "fp32", image_precision: str | None = None
) -> Path:
    """Export a camera + LiDAR checkpoint into ``out_dir`` with ``streamdet.export`` (needs torch); the export dir."""
    if "int8" in (precision, image_precision):
        raise StudyError("--checkpoint exports fp32 / fp16 only; make the int8 export first and pass --export-dir")
    try:
        from streamdet.export.exporter import ExportError, ExportOptions, run_export  # imports torch
        from streamdet.training.checkpoint import load_checkpoint
    except ImportError as e:
        raise StudyError(f"--checkpoint needs PyTorch to export it (pip install '.[export]'): {e}") from None
    try:
        preset = load_checkpoint(checkpoint)["preset"]
    except ValueError as e:
        raise StudyError(str(e)) from None
    if not preset.get("use_image", True):
        raise StudyError(f"checkpoint {checkpoint} is a LiDAR-only model: pass it as --baseline-checkpoint")
    fp16 = "fp16" in (precision, image_precision)
    opts = ExportOptions(preset=str(preset["name"]), checkpoint=str(checkpoint), fp16=fp16, out_dir=str(out_dir))
    try:
        result = run_export(opts)
    except (ExportError, ValueError) as e:
        raise StudyError(f"exporting {checkpoint}: {e}") from None
    if not result.parity_passed:  # the runtime would refuse the graphs, naming a temporary folder gone by then
        failed = [f"{p.graph} {p.precision} {p.output}" for p in result.manifest.parity if not p.passed]
        raise StudyError(f"exporting {checkpoint}: the graphs failed their parity check ({', '.join(failed) or 'fp16 pipeline'}); "
                         f"`streamdet-export --checkpoint {checkpoint} --out DIR` writes them with the record")  # fmt: skip
    return result.out_dir
