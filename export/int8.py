"""int8 siblings of exported graphs, by concept (this module re-exports them all, as ``q8`` in the exporter):

- ``int8_quantize``: static QDQ quantization of one graph (format, what stays float and why, ``quantize_graph``);
- ``int8_rewrites``: the ONNX rewrites applied to a graph before it is quantized (same function, faster int8);
- ``int8_data``: the real calibration inputs (samples of a dataset or the bundled sample, each graph's feeds as
  the fp32 export's runtime records them);
- ``int8_parity``: int8 against fp32 (relative L2 of every output, boxes paired by label and centre), from the
  runs the fp32 and int8 detectors recorded.

The export's int8 steps that use them are export/int8_steps.py.
"""

from __future__ import annotations

import warnings

from streamdet.export.int8_data import (
    BUNDLED_SOURCE,
    DEFAULT_CALIBRATION_SAMPLES,
    CalibrationSamples,
    Feeds,
    Int8CalibrationDataError,
    dataset_version,
    load_calibration_samples,
    record_graph_inputs,
)
from streamdet.export.int8_parity import (
    BOX_SCORE_THRESHOLD,
    Int8Parity,
    _slice_parity,
    box_agreement,
    dense_parity,
    int8_parity,
    pair_boxes,
    relative_l2,
)
from streamdet.export.int8_quantize import (
    ACTIVATION_TYPE,
    HEAD_OUTPUT_NOTE,
    INPUT_NORM_NOTE,
    LIFTER_GATHER_NOTE,
    LIFTER_POOL_NOTE,
    PILLAR_NOTE,
    WEIGHT_TYPE,
    Int8Config,
    QuantizedGraph,
    float_nodes,
    quantize_graph,
    quantized_ops,
)
from streamdet.export.int8_rewrites import normalisation_as_batchnorm, transposed_convs_as_depth_to_space

__all__ = [
    "ACTIVATION_TYPE", "BOX_SCORE_THRESHOLD", "BUNDLED_SOURCE", "DEFAULT_CALIBRATION_SAMPLES", "HEAD_OUTPUT_NOTE",
    "INPUT_NORM_NOTE", "LIFTER_GATHER_NOTE", "LIFTER_POOL_NOTE", "PILLAR_NOTE", "WEIGHT_TYPE", "CalibrationSamples",
    "Feeds", "Int8CalibrationDataError", "Int8Config", "Int8Parity", "QuantizedGraph", "_slice_parity",
    "box_agreement", "dataset_version", "dense_parity", "float_nodes", "int8_parity", "load_calibration_samples",
    "normalisation_as_batchnorm", "pair_boxes", "quantize_graph", "quantized_ops", "record_graph_inputs",
    "relative_l2", "transposed_convs_as_depth_to_space",
]  # fmt: skip


def __getattr__(name: str):
    # The int8 calibration-data error was called CalibrationError, like the camera calibration's: renamed apart.
    if name == "CalibrationError":
        warnings.warn("streamdet.export.int8.CalibrationError is deprecated: use Int8CalibrationDataError",
                      DeprecationWarning, stacklevel=2)  # fmt: skip
        return Int8CalibrationDataError
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
