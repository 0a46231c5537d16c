"""onnxruntime's execution providers by name: the short names of ``--providers`` / ``STREAMDET_PROVIDERS`` and their
parsing. Standard library only (every package imports core, the CLIs before onnxruntime loads); which providers an
onnxruntime build has, and which a session started, is runtime_ort/sessions.py's."""

from __future__ import annotations

import re

CPU_PROVIDER = "CPUExecutionProvider"
CUDA_PROVIDER = "CUDAExecutionProvider"
TENSORRT_PROVIDER = "TensorrtExecutionProvider"
PROVIDERS_ENV = "STREAMDET_PROVIDERS"  # the providers of every session whose caller names none (as --providers)
AUTO_PROVIDERS = "auto"
# Short names; any onnxruntime name ("...ExecutionProvider", any case for those listed) is taken as well.
PROVIDER_ALIASES = {
    "cpu": CPU_PROVIDER,
    "cuda": CUDA_PROVIDER,
    "tensorrt": TENSORRT_PROVIDER,
    "trt": TENSORRT_PROVIDER,
    "rocm": "ROCMExecutionProvider",
    "migraphx": "MIGraphXExecutionProvider",
    "openvino": "OpenVINOExecutionProvider",
    "dml": "DmlExecutionProvider",
    "coreml": "CoreMLExecutionProvider",
    "qnn": "QNNExecutionProvider",
    "xnnpack": "XnnpackExecutionProvider",
}
_KNOWN = {p.lower(): p for p in (*PROVIDER_ALIASES.values(), "DnnlExecutionProvider", "CANNExecutionProvider",
                                  "NnapiExecutionProvider", "VitisAIExecutionProvider", "AzureExecutionProvider")}  # fmt: skip
_PROVIDER_NAME = re.compile(r"[A-Za-z][A-Za-z0-9]*ExecutionProvider")  # a provider newer than the list above


def parse_providers(text: str, source: str = "--providers") -> tuple[str, ...] | None:
    """Providers from a comma-separated list of short (``cpu``, ``cuda``, ``tensorrt``, ...) or onnxruntime names
    (``CUDAExecutionProvider``), in order of preference; ``auto`` (or nothing): None, the default order. ``source``
    names where the text came from in the ValueError a bad list raises."""
    names = [n.strip() for n in str(text).split(",")]
    if names == [""] or [n.lower() for n in names] == [AUTO_PROVIDERS]:
        return None
    chosen: list[str] = []
    for name in names:
        full = PROVIDER_ALIASES.get(name.lower()) or _KNOWN.get(name.lower())
        if full is None and _PROVIDER_NAME.fullmatch(name):
            full = name
        if full is None:
            raise ValueError(f"{source}: unknown execution provider {name!r} (short names: {AUTO_PROVIDERS}, "
                             f"{', '.join(PROVIDER_ALIASES)}; or an onnxruntime name such as CUDAExecutionProvider)")  # fmt: skip
        if full in chosen:
            raise ValueError(f"{source}: {name!r} names {full} twice in {text!r}")
        chosen.append(full)
    return tuple(chosen)
