"""onnxruntime's TensorRT provider options for an export's graphs: an engine cache on disk and, for graphs whose
dynamic dimensions all have known ranges, an explicit shape profile.

TensorRT builds an engine per graph for a range of input shapes. Without a profile, onnxruntime builds one for the
first shapes it sees and rebuilds (seconds each) whenever a run leaves the range seen so far: the slice graph's
pillar count ``P`` changes every slice, so the first seconds of a drive would rebuild again and again. A profile
covering ``P`` from 1 to the export's ``max_pillars`` is built once; the engine cache keeps it across processes.
The per-camera term graphs never run on TensorRT (their row counts change with every camera and quadrant:
``sessions.without_tensorrt``), nor do int8 graphs (uint8 activations; TensorRT takes symmetric int8 only).
The option names are onnxruntime's (its TensorRT execution provider documentation, "Configurations"); shapes are
written ``name:d0xd1x...`` and joined by commas. Not run on a GPU in this repository's CI (it has none).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from streamdet.runtime_ort.manifest import TensorSpec

CACHE_ENV = "STREAMDET_TENSORRT_CACHE"  # the engine cache directory where DetectorConfig names none


def default_cache_dir(environ: Mapping[str, str] | None = None) -> Path:
    """``$STREAMDET_TENSORRT_CACHE``, else ``$XDG_CACHE_HOME/streamdet/tensorrt``, else ``~/.cache/streamdet/tensorrt``:
    never beside the graphs (an export directory is read-only to the runtime)."""
    env = os.environ if environ is None else environ
    if env.get(CACHE_ENV):
        return Path(env[CACHE_ENV])
    base = Path(env["XDG_CACHE_HOME"]) if env.get("XDG_CACHE_HOME") else Path.home() / ".cache"
    return base / "streamdet" / "tensorrt"


def profile_shapes(inputs: Sequence[TensorSpec], dims: Mapping[str, tuple[int, int, int]]) -> dict[str, str] | None:
    """TensorRT's ``trt_profile_min/opt/max_shapes`` of a graph's inputs, each named dimension taken from ``dims``
    (name -> (min, opt, max)); None when an input has a named dimension ``dims`` lacks (TensorRT needs every dynamic
    input in an explicit profile, so such a graph gets none and builds from the shapes it sees)."""
    if not any(isinstance(d, str) for spec in inputs for d in spec.shape):
        return None  # a static graph needs no profile
    shapes: dict[str, list[str]] = {"min": [], "opt": [], "max": []}
    for spec in inputs:
        if not any(isinstance(d, str) for d in spec.shape):
            continue
        if any(isinstance(d, str) and d not in dims for d in spec.shape):
            return None
        for i, key in enumerate(("min", "opt", "max")):
            size = "x".join(str(dims[d][i] if isinstance(d, str) else d) for d in spec.shape)
            shapes[key].append(f"{spec.name}:{size}")
    return {f"trt_profile_{key}_shapes": ",".join(v) for key, v in shapes.items()}


def check_dim_ranges(dims: Mapping[str, tuple[int, int, int]]) -> None:
    """Each range is (min, opt, max) ints with 1 <= min <= opt <= max; a bad one raises ValueError naming it."""
    for name, r in dims.items():
        if len(r) != 3 or not all(isinstance(v, int) and not isinstance(v, bool) for v in r) or not 1 <= r[0] <= r[1] <= r[2]:
            raise ValueError(f"TensorRT shape range of dimension {name!r} must be ints 1 <= min <= opt <= max, got {r!r}")


def tensorrt_options(inputs: Sequence[TensorSpec], dims: Mapping[str, tuple[int, int, int]], cache_dir: str | os.PathLike,
                     fp16: bool = False) -> dict[str, str]:  # fmt: skip
    """The TensorRT provider options of one graph: engine and timing caches in ``cache_dir`` (onnxruntime names an
    engine by the graph's structure and the library versions, not by its weights: give each graph file its own
    folder, as the detector does by its sha256), the shape profile of ``profile_shapes`` where every dynamic dimension
    has a range, and ``trt_fp16_enable`` for an fp16 graph."""
    check_dim_ranges(dims)
    options = {
        "trt_engine_cache_enable": "True",
        "trt_engine_cache_path": os.fspath(cache_dir),
        "trt_timing_cache_enable": "True",
        "trt_timing_cache_path": os.fspath(cache_dir),
    }
    if fp16:
        options["trt_fp16_enable"] = "True"
    options.update(profile_shapes(inputs, dims) or {})
    return options
