"""onnxruntime sessions: explicit options and providers, cached I/O metadata, input checks that name the problem.

Each graph gets its own session with its own thread pool. On a small CPU the lanes of the streaming detector
run concurrently, so every session defaults to one intra-op thread and no spinning: a session that spins
would burn the core the other lane needs and slow the slice lane while the image lane runs (a thread pool still
spinning after its last run slowing the graph run next: benchmarks/RESULTS.md, section "Measurements behind design
choices (moved from code docstrings on 2026-12-01)", **Timing**).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort
from onnxruntime.capi import onnxruntime_pybind11_state as _ort_state

from streamdet.core.providers import (  # noqa: F401 (parse_providers and the names: public here too)
    AUTO_PROVIDERS,
    CPU_PROVIDER,
    CUDA_PROVIDER,
    PROVIDER_ALIASES,
    PROVIDERS_ENV,
    TENSORRT_PROVIDER,
    parse_providers,
)
from streamdet.runtime_ort.manifest import ManifestError
from streamdet.runtime_ort.signature import TensorSignature

log = logging.getLogger(__name__)

# onnxruntime's own exception classes (InvalidProtobuf, InvalidArgument, Fail, ...) derive from Exception only;
# they are turned into the runtime's named errors here, with the graph file in a one-line message.
ORT_ERRORS: tuple[type[BaseException], ...] = tuple(
    c for c in vars(_ort_state).values() if isinstance(c, type) and issubclass(c, Exception)
)


class GraphRunError(RuntimeError):
    """onnxruntime failed while running a graph that loaded and whose inputs were checked (resources, a provider)."""


def ort_message(e: BaseException) -> str:
    """onnxruntime's message on one line, without its ``[ONNXRuntimeError] : 2 : INVALID_ARGUMENT :`` prefix."""
    text = " ".join(str(e).split())
    return text.rsplit(" : ", 1)[-1] if text.startswith("[ONNXRuntimeError]") else text


def graph_run_error(graph: str, e: BaseException) -> GraphRunError:
    """The GraphRunError of onnxruntime's exception ``e`` in a run of ``graph`` (its file name, or what names it):
    the one message of every graph run that fails, whichever session ran it."""
    return GraphRunError(f"{graph}: onnxruntime failed: {ort_message(e)}")


# Preference order when neither the caller nor STREAMDET_PROVIDERS names providers: those this onnxruntime build has.
# TensorRT only when asked for: it builds an engine per graph and input-shape range at start-up (minutes), a choice
# for a deployment that caches its engines (runtime_ort/tensorrt.py), not a default.
PREFERRED_PROVIDERS: tuple[str, ...] = (CUDA_PROVIDER, CPU_PROVIDER)
CPU_ONLY: tuple[str, ...] = (CPU_PROVIDER,)  # the exporter's and the benchmarks' sessions: they measure the CPU


class ProviderError(ValueError):
    """An execution provider named explicitly that this onnxruntime build lacks or could not start."""


def default_providers(environ: dict[str, str] | None = None) -> tuple[str, ...] | None:
    """The providers ``STREAMDET_PROVIDERS`` names (``parse_providers``); None where it is unset, empty or ``auto``."""
    text = (os.environ if environ is None else environ).get(PROVIDERS_ENV, "")
    return parse_providers(text, f"environment variable {PROVIDERS_ENV}") if text.strip() else None


_ORT_TO_NUMPY = {
    "tensor(float)": np.float32,
    "tensor(float16)": np.float16,
    "tensor(int64)": np.int64,
    "tensor(int32)": np.int32,
    "tensor(uint8)": np.uint8,
    "tensor(bool)": np.bool_,
}


@dataclass(frozen=True)
class SessionConfig:
    # None: STREAMDET_PROVIDERS's, else CUDA > CPU, whichever this build offers (PREFERRED_PROVIDERS)
    providers: tuple[str, ...] | None = None
    intra_op_threads: int = 1  # per session; 0 lets onnxruntime use every core (fine when nothing runs beside it)
    allow_spinning: bool = False  # spinning threads steal the core of the concurrent lane
    enable_profiling: bool = False  # onnxruntime's JSON profile (for `streamdet-bench --profile`)
    # where a profiling session writes its JSON; None: the current directory (never beside the graphs: an export
    # directory is read-only to the runtime)
    profile_dir: str | os.PathLike | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.intra_op_threads, int) or self.intra_op_threads < 0:
            raise ValueError(f"SessionConfig.intra_op_threads must be an int >= 0, got {self.intra_op_threads!r}")


def resolve_providers(requested: tuple[str, ...] | None) -> list[str]:
    """The providers to use, in order: ``requested``, else ``STREAMDET_PROVIDERS``'s, else those of
    PREFERRED_PROVIDERS this build has. Providers named (by the caller or the variable) that this build lacks raise
    ProviderError; the CPU is appended as the fallback for ops an accelerator lacks."""
    available = ort.get_available_providers()
    if requested:  # short names ("cuda") as onnxruntime's; an unknown one raises ValueError naming it
        requested = parse_providers(",".join(requested), "providers")
    if requested is None:
        requested = default_providers()
    if requested is None:
        chosen = [p for p in PREFERRED_PROVIDERS if p in available]
    else:
        missing = [p for p in requested if p not in available]
        if missing:
            raise ProviderError(f"execution providers {missing} are not available in this onnxruntime build (it has "
                                f"{available}; a GPU needs the onnxruntime-gpu wheel: README, \"Set-up\")")  # fmt: skip
        chosen = list(requested)
        if TENSORRT_PROVIDER in chosen and CUDA_PROVIDER not in chosen and CUDA_PROVIDER in available:
            # onnxruntime's advice: the nodes TensorRT rejects run on CUDA, not on the CPU with copies either way
            chosen.insert(chosen.index(TENSORRT_PROVIDER) + 1, CUDA_PROVIDER)
    if CPU_PROVIDER not in chosen:
        chosen.append(CPU_PROVIDER)  # fallback for ops the accelerator provider lacks
    return chosen


def without_tensorrt(providers: tuple[str, ...] | None) -> tuple[str, ...] | None:
    """``providers`` less TensorRT (with CUDA in its place where the build has it), for small graphs whose shapes change
    with every camera and quadrant (the per-camera terms): TensorRT would build an engine for each new shape on the
    image lane. None (the default order) stays None: it never picks TensorRT."""
    if providers is None:
        providers = default_providers()
        if providers is None:
            return None
    if TENSORRT_PROVIDER not in providers:
        return providers
    rest = [p for p in providers if p != TENSORRT_PROVIDER]
    if CUDA_PROVIDER not in rest and CUDA_PROVIDER in ort.get_available_providers():
        rest.insert(0, CUDA_PROVIDER)
    return tuple(rest) or (CPU_PROVIDER,)


def check_started(path: str | os.PathLike, wanted: list[str], started: list[str], explicit: bool) -> None:
    """onnxruntime falls back to the CPU (printing its own "EP Error" banner) when a provider it has fails to start
    (a missing CUDA or cuDNN library, no GPU): a provider named explicitly that did not start raises ProviderError;
    under the default order the fallback is logged."""
    lost = [p for p in wanted if p not in started]
    if not lost:
        return
    message = (f"{Path(path).name}: onnxruntime could not start {lost} (the session runs on {started}); its own log "
               "above says why (a missing CUDA, cuDNN or TensorRT library, or no GPU)")  # fmt: skip
    if explicit:
        raise ProviderError(message + "; choose others with --providers / DetectorConfig.providers")
    log.warning("%s", message)


def session_options(config: SessionConfig = SessionConfig(), profile_prefix: str | None = None) -> ort.SessionOptions:
    """The onnxruntime options of every session streamdet opens: all graph optimisations (the int8 graphs' fused
    kernels need them), sequential execution, ``config``'s threads and spinning; errors only in the log (fp16
    graphs on CPU log a warning per wrapped op). ``profile_prefix`` is where a profiling session writes."""
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.intra_op_num_threads = config.intra_op_threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if config.allow_spinning else "0")
    opts.log_severity_level = 3
    if config.enable_profiling:
        opts.enable_profiling = True
        if profile_prefix is not None:
            opts.profile_file_prefix = profile_prefix
    return opts


# The exporter's sessions (parity, int8 calibration): the CPU, every core (nothing runs beside an export).
EXPORT_SESSION = SessionConfig(providers=CPU_ONLY, intra_op_threads=0)


def _open(src: str | bytes, opts: ort.SessionOptions, config: SessionConfig, providers: list[str], name: str | os.PathLike,
          provider_options: Mapping[str, Mapping[str, str]] | None = None) -> ort.InferenceSession:  # fmt: skip
    """An onnxruntime session on ``providers`` (``resolve_providers(config.providers)``), each with its options where
    given, checked to run on them (``check_started``); onnxruntime's own errors propagate."""
    options = provider_options or {}
    session = ort.InferenceSession(src, sess_options=opts, providers=[(p, dict(options[p])) if p in options else p for p in providers])
    # onnxruntime's Python session otherwise answers a provider failing in run() (a TensorRT engine rebuild, an
    # enqueue) by printing "EP Error", recreating itself on the CPU without our options and going on: the failure is
    # raised instead (GraphRunError), and the providers recorded stay the ones that run
    session.disable_fallback()
    check_started(name, providers, session.get_providers(), explicit=config.providers is not None or default_providers() is not None)
    return session


def ort_session(model: str | os.PathLike | bytes, config: SessionConfig = EXPORT_SESSION) -> ort.InferenceSession:
    """A plain onnxruntime session of a graph file or serialized model, with ``session_options``: for tools that
    feed a graph its raw inputs (the exporter's parity and int8 calibration) rather than run an export."""
    src = model if isinstance(model, bytes) else os.fspath(model)
    name = "<graph>" if isinstance(model, bytes) else model
    return _open(src, session_options(config), config, resolve_providers(config.providers), name)


class GraphSession:
    """One ONNX graph in one onnxruntime session, with its I/O metadata read once."""

    def __init__(self, path: str | Path, config: SessionConfig = SessionConfig(), model: bytes | None = None,
                 provider_options: Mapping[str, Mapping[str, str]] | None = None) -> None:  # fmt: skip
        """``model``: the graph's bytes, already read (and checked) by the caller, which onnxruntime loads instead of
        opening ``path`` again (``manifest.read_export_file``); ``path`` then names the graph in messages.
        ``provider_options``: onnxruntime's options of a provider by its name (TensorRT's shape profiles and engine
        cache: runtime_ort/tensorrt.py), used where that provider is among the session's."""
        self.path = Path(path)
        prefix = Path(config.profile_dir if config.profile_dir is not None else ".") / (self.path.with_suffix("").name + ".profile")
        if config.enable_profiling:
            prefix.parent.mkdir(parents=True, exist_ok=True)
        opts = session_options(config, profile_prefix=str(prefix))
        providers = resolve_providers(config.providers)
        try:
            self.session = _open(model if model is not None else str(self.path), opts, config, providers, self.path, provider_options)
        except ORT_ERRORS as e:
            if providers != [CPU_PROVIDER]:  # an accelerator's engine build or kernel, more likely than the file
                raise ProviderError(f"{self.path}: onnxruntime cannot create a session of this graph on {providers}: "
                                    f"{ort_message(e)} (if --providers cpu loads it, these providers cannot run it)") from None  # fmt: skip
            # a truncated, empty or foreign file that passed (or skipped) the sha256 check
            raise ManifestError(f"{self.path}: onnxruntime cannot load this graph: {ort_message(e)}") from None
        self.providers = tuple(self.session.get_providers())
        log.info("%s: providers %s, %d intra-op thread(s)", self.path.name, list(self.providers), config.intra_op_threads)
        self.input_names = tuple(i.name for i in self.session.get_inputs())
        self.output_names = tuple(o.name for o in self.session.get_outputs())
        self.input_dtypes = {i.name: _ORT_TO_NUMPY.get(i.type) for i in self.session.get_inputs()}
        self.input_ranks = {i.name: len(i.shape) for i in self.session.get_inputs()}
        self.inputs = tuple(_signature(i) for i in self.session.get_inputs())  # what the graph really declares
        self.outputs = tuple(_signature(o) for o in self.session.get_outputs())

    def run(self, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        """Run with the feeds by input name; a missing, extra or mistyped input raises ValueError naming it."""
        if set(feeds) != set(self.input_names):
            raise ValueError(
                f"{self.path.name}: inputs must be {list(self.input_names)}, got {sorted(feeds)}"
            )
        for name, value in feeds.items():
            want = self.input_dtypes[name]
            if value.dtype != want:
                raise ValueError(f"{self.path.name}: input {name!r} must be {np.dtype(want)}, got {value.dtype}")
            if value.ndim != self.input_ranks[name]:
                raise ValueError(f"{self.path.name}: input {name!r} must have rank {self.input_ranks[name]}, got shape {value.shape}")
        try:
            return self.session.run(list(self.output_names), feeds)
        except ORT_ERRORS as e:
            raise graph_run_error(self.path.name, e) from None

    def end_profiling(self) -> str:
        return self.session.end_profiling()


def _signature(arg) -> TensorSignature:
    """A session input or output (onnxruntime NodeArg) as a TensorSignature: named or unknown dimensions are None."""
    dtype = _ORT_TO_NUMPY.get(arg.type)
    shape = tuple(d if isinstance(d, int) else None for d in arg.shape)
    return TensorSignature(arg.name, np.dtype(dtype).name if dtype is not None else arg.type, shape)
