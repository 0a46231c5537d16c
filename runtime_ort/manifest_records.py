"""What an export measured about itself, as recorded in its manifest (``manifest.py``: ``parity`` and ``int8``): each
graph's ONNX output against its reference, the whole pipeline's boxes fp16 against fp32, and for int8 exports the
calibration data, what was quantized and the error against fp32. Recorded, read back, never acted on by the runtime.
"""

from __future__ import annotations

from dataclasses import dataclass


def known_fields(cls: type, d: dict) -> dict:
    """The entries of ``d`` that name fields of the dataclass ``cls`` (the keys a record of it was written with)."""
    return {k: d[k] for k in cls.__dataclass_fields__ if k in d}


@dataclass(frozen=True)
class ParityRecord:
    """One graph's ONNX output against its reference: max |a - b| <= tolerance_rel * scale, the scale the
    reference's range floored at a fraction of its magnitude (export/parity.py; ``output_scale``, absent in manifests
    written before it: the range)."""

    graph: str
    precision: str  # the graph checked
    reference: str  # "torch" (for fp32 graphs) or "onnx-fp32" (for fp16 graphs)
    output: str
    max_abs_diff: float
    output_range: float  # max - min of the reference output
    tolerance_rel: float
    passed: bool
    note: str = ""
    output_scale: float | None = None  # what tolerance_rel is relative to; None: output_range

    @classmethod
    def from_dict(cls, d: dict) -> "ParityRecord":
        return cls(**known_fields(cls, d))


@dataclass(frozen=True)
class PipelineParity:
    """Decoded boxes of the whole pipeline (real sample, one slice), fp16 graphs against fp32 graphs."""

    slice_index: int
    num_slices: int
    num_points: int  # points in the slice
    num_pillars: int
    score_threshold: float
    score_band: float  # boxes with |score - threshold| <= band in either run are excluded from the count check
    count_fp32: int  # boxes with score >= threshold + band
    count_fp16: int
    excluded_in_band: int  # boxes (either run) inside the band, not compared
    excluded_at_top_k: int  # unpaired boxes within the band of their run's K-th score, not compared
    excluded_near_ties: int  # boxes whose peak is within the band of a neighbour's score (parity.py), not compared
    max_centre_diff_m: float  # over matched boxes (nan when there are none)
    centre_tolerance_m: float
    passed: bool
    note: str = ""

    @classmethod
    def from_dict(cls, d: dict) -> "PipelineParity":
        return cls(**known_fields(cls, d))


@dataclass(frozen=True)
class Int8Calibration:
    """Where the int8 graphs' activation ranges came from."""

    source: str  # "bundled:nuscenes_sample" or the dataset directory given to --calibration-data
    version: str  # nuScenes table folder, e.g. "v1.0-synth"
    split: str  # scenes the samples came from ("train" from splits.json, or "all")
    sample_tokens: tuple[str, ...]
    num_images: int  # encoder calibration images
    num_volumes: int  # lifter calibration inputs (all four quadrants each)
    num_slices: int  # slice-graph calibration inputs (non-empty slices)
    method: str  # onnxruntime CalibrationMethod name, e.g. "MinMax"
    reduce_range: bool  # 7-bit weights
    parity_held_out: bool  # True when the parity sample is not among the calibration samples
    seconds: float

    @classmethod
    def from_dict(cls, d: dict) -> "Int8Calibration":
        return cls(**{**{k: d[k] for k in cls.__dataclass_fields__}, "sample_tokens": tuple(d["sample_tokens"])})


@dataclass(frozen=True)
class Int8GraphRecord:
    """One int8 graph: the ops that run on int8 inputs and the nodes kept float on purpose."""

    graph: str
    quantized_ops: dict  # op type -> nodes between DequantizeLinear and QuantizeLinear (int8 in onnxruntime)
    float_nodes: dict  # reason -> number of nodes kept float for it

    @classmethod
    def from_dict(cls, d: dict) -> "Int8GraphRecord":
        return cls(graph=str(d["graph"]), quantized_ops=dict(d["quantized_ops"]), float_nodes=dict(d["float_nodes"]))


@dataclass(frozen=True)
class Int8OutputParity:
    """One output of an int8 graph against the fp32 graph: ||int8 - fp32|| / ||fp32|| over the parity inputs."""

    graph: str
    output: str
    inputs: str  # "same": both graphs fed the same fp32 inputs; "pipeline": each fed by its own precision's graphs
    rel_l2_error: float
    max_abs_diff: float
    num_inputs: int
    note: str = ""

    @classmethod
    def from_dict(cls, d: dict) -> "Int8OutputParity":
        return cls(**known_fields(cls, d))


@dataclass(frozen=True)
class BoxAgreement:
    """Decoded boxes (score >= threshold) of the int8 pipeline against the fp32 pipeline, all slices of a sample.

    Boxes pair greedily by centre distance within ``pair_radius_m``, same slice, quadrant and label.
    """

    num_slices: int
    score_threshold: float
    pair_radius_m: float
    count_fp32: int
    count_int8: int
    matched: int
    max_centre_diff_m: float  # over matched pairs (nan when none)
    mean_centre_diff_m: float
    max_score_diff: float
    note: str = ""

    @classmethod
    def from_dict(cls, d: dict) -> "BoxAgreement":
        return cls(**known_fields(cls, d))


@dataclass(frozen=True)
class Int8Record:
    calibration: Int8Calibration
    graphs: tuple[Int8GraphRecord, ...]
    parity: tuple[Int8OutputParity, ...]
    boxes: BoxAgreement | None

    @classmethod
    def from_dict(cls, d: dict) -> "Int8Record":
        return cls(
            calibration=Int8Calibration.from_dict(d["calibration"]),
            graphs=tuple(Int8GraphRecord.from_dict(g) for g in d["graphs"]),
            parity=tuple(Int8OutputParity.from_dict(p) for p in d["parity"]),
            boxes=BoxAgreement.from_dict(d["boxes"]) if d.get("boxes") else None,
        )
