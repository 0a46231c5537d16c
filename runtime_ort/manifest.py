"""The export manifest (``manifest.json``): everything the runtime needs to run an export, without the model code.

The runtime that reads it owns it; the exporter (``streamdet.export``) and ``streamdet-calib`` write it. Like all
of runtime_ort it never imports torch, onnx or any other export-side dependency: numpy and the standard library only.

Schema (``MANIFEST_VERSION`` = 1), one JSON object; ``manifest.schema.json`` beside this module is the normative
definition (types, ranges, sizes), validated by ``Manifest.from_dict`` before any record is built::

    version            int, MANIFEST_VERSION
    preset_name        str, e.g. "small"
    preset             dict, Preset.to_dict() of the exported model (opaque to the runtime except "grid")
    grid               dict, GridSpec.to_dict()
    class_names        [str], CLASS_NAMES of core/classes.py in label order
    num_slices         int, slices per sweep the export (and its parity check) assumed
    image              {width, height, feature_stride, feature_width, feature_height, camera_names}; null in a
                       LiDAR-only export (preset use_image false)
    normalisation      {input: "uint8 RGB (J, H, W, 3)", scale, mean_rgb, std_rgb}: applied inside image_encoder;
                       null in a LiDAR-only export
    post               dict, decode/NMS settings of the preset (score_threshold, ...), for the runtime;
                       top_k_per_quadrant (and top_k, the same number) is K, the boxes the slice graph decodes per map
    graphs             [GraphEntry]: name ("image_encoder" | "volumetric_lifter" | "slice_head"), precision
                       ("fp32" | "fp16" | "int8"), file, sha256, opset, inputs/outputs [{name, shape, dtype}], gmac
    lut                {file, sha256, calibration_sha256, calibration_source (a path, or the bundled sample's)}; null
                       in a LiDAR-only export (the cameras and image size are ``image``'s)
    parity             [ParityRecord] (one per graph and precision) and a "pipeline" PipelineParity, as measured
                       by the export itself; a record whose check compared nothing holds max_abs_diff NaN
    source             {checkpoint: path or null, checkpoint_sha256, seed (of fixed-seed weights; null with a
                       checkpoint), parity_input (what the parity checks ran on), parity_seed (of the parity check's
                       noise images; null where they are real or absent), torch, onnx, onnxruntime versions}
    int8               null, or Int8Record when the export wrote int8 graphs (optional; absent in older manifests):
                       {calibration: Int8Calibration (the data the ranges came from), graphs: [Int8GraphRecord]
                       (what was quantized and what was kept float, and why), parity: [Int8OutputParity] (relative L2
                       error of every output against fp32), boxes: BoxAgreement (decoded boxes of the int8 pipeline
                       against the fp32 pipeline)}. Measured and recorded, never pass/fail: int8 is an approximation.
    image_layout       "image_bev" | "image_half" (optional; absent: "image_bev"): the map the lifter graph outputs
                       and the slice graph takes, the image BEV or the BEV encoder's image half computed in the
                       lifter graph (core/image_layout.py); the graphs' signatures are checked against it
    lut_layout         "slots" | "compact" (optional; absent: "slots"): the lifter graph's LUT inputs, K slots per
                       voxel or the compacted valid pairs (core/lut_layout.py); checked likewise

Which graphs a manifest must list follows from ``preset["use_image"]`` (absent means true, as in manifests written
before LiDAR-only exports existed): a camera + LiDAR export lists all three graphs in fp32 with ``image``,
``normalisation`` and ``lut``; a LiDAR-only export (the paper's streaming baseline) lists ``slice_head`` only, whose
inputs are the pillar tensors and ``quadrants`` (the slice's quadrant ids, read for their count Q), and no image
spec, normalisation or LUT. Anything in between is refused, so a fused export that lost its image graphs is never
taken for a LiDAR-only one. ``preset["slice_crop"]`` false (absent means true) marks a LiDAR-only export without the
quadrant crop: its slice graph runs one map of the whole grid per slice and takes the pillar tensors alone; a fused
preset with it is refused.

Shapes use ints for fixed dimensions and strings ("J", "P", "Q", "H", "W", "Hf", "Wf") for dynamic ones.
The manifest is written last, after every file it names: an export directory without ``manifest.json``
is incomplete.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Callable

from streamdet.calibration.lut_file import MAX_LUT_FILE_BYTES
from streamdet.core.constants import MANIFEST_NAME, PRECISIONS
from streamdet.core.file_input import InputFileError, read_regular_file
from streamdet.core.file_output import atomic_write_file
from streamdet.core.image_layout import IMAGE_BEV, IMAGE_HALF, IMAGE_LAYOUTS
from streamdet.core.lut_layout import LUT_LAYOUTS, LUT_SLOTS
from streamdet.runtime_ort.schema import SchemaViolation, validate
from streamdet.runtime_ort.manifest_records import (  # noqa: F401 (re-exported: the manifest's records)
    BoxAgreement, Int8Calibration, Int8GraphRecord, Int8OutputParity, Int8Record, ParityRecord, PipelineParity,
    known_fields as _known_fields)

MANIFEST_VERSION = 1
LUT_NAME = "lut.npz"
GRAPH_NAMES: tuple[str, ...] = ("image_encoder", "volumetric_lifter", "slice_head")
IMAGE_GRAPH_NAMES: tuple[str, ...] = ("image_encoder", "volumetric_lifter")  # the image lane; absent when LiDAR-only
_DTYPES = ("uint8", "int32", "int64", "float16", "float32")
MAX_MANIFEST_BYTES = 16 << 20  # a real manifest is tens of kB; a larger file is refused before it is parsed
MAX_MANIFEST_DEPTH = 32  # JSON nesting; a real manifest nests 5 deep


class ManifestError(ValueError):
    """A manifest that is missing, malformed or inconsistent with the files beside it."""


def export_file(export_dir: str | os.PathLike, name: str, what: str = "file") -> Path:
    """``export_dir / name`` for a file the manifest names, confined to the export directory.

    ``name`` must be a plain file name (no directory part, not hidden, not ``..``); the path is resolved (symlinks
    followed) and must still lie directly inside the resolved export directory, so neither a name nor a symlink can
    make the runtime or ``streamdet-calib`` read or write a file elsewhere. The file need not exist (a writer's
    target); readers check ``is_file`` themselves.
    """
    _check_plain_name(what, name)
    try:
        root = Path(export_dir).resolve()
        path = (root / name).resolve()
    except (OSError, RuntimeError) as e:  # RuntimeError: a symlink loop (Python before 3.13)
        raise ManifestError(f"{what} {name!r} in {export_dir} cannot be resolved: {' '.join(str(e).split())}") from None
    if path.parent != root:
        raise ManifestError(f"{what} {name!r} in {root} resolves to {path}, outside the export directory (a symlink?)")
    return path


MAX_GRAPH_BYTES = (2 << 30) - 1  # protobuf's limit on one serialized message: a larger file is no ONNX graph


def read_export_file(export_dir: str | os.PathLike, entry: GraphEntry | LutEntry, what: str, verify_sha256: bool) -> tuple[Path, bytes]:
    """(path, bytes) of the file ``entry`` names: confined to the export directory (``export_file``), a regular
    file within its limit (MAX_GRAPH_BYTES, MAX_LUT_FILE_BYTES), and, with ``verify_sha256``, hashing to the
    manifest's sha256. ManifestError naming the file otherwise."""
    limit = MAX_LUT_FILE_BYTES if isinstance(entry, LutEntry) else MAX_GRAPH_BYTES
    path = export_file(export_dir, entry.file, what)
    try:
        raw = read_regular_file(path, limit)
    except InputFileError as e:
        if e.reason == "missing":
            raise ManifestError(f"{path} is named in the manifest but missing ({what})") from None
        raise ManifestError(f"{what}: {e}") from None
    if verify_sha256:
        got = hashlib.sha256(raw).hexdigest()
        if got != entry.sha256:
            raise ManifestError(f"{path} has sha256 {got[:12]}..., the manifest says {entry.sha256[:12]}...")
    return path, raw


def sha256_file(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def graph_file_name(name: str, precision: str) -> str:
    """``slice_head.onnx`` for fp32, ``slice_head.fp16.onnx`` for fp16, ``slice_head.int8.onnx`` for int8."""
    _check_choice("graph name", name, GRAPH_NAMES)
    _check_choice("precision", precision, PRECISIONS)
    return f"{name}.onnx" if precision == "fp32" else f"{name}.{precision}.onnx"


@dataclass(frozen=True)
class TensorSpec:
    name: str
    shape: tuple[int | str, ...]  # ints fixed, strings name a dynamic dimension
    dtype: str  # numpy dtype name, one of _DTYPES

    def __post_init__(self) -> None:
        if not self.name:
            raise ManifestError("TensorSpec.name must be a non-empty string")
        _check_choice(f"dtype of tensor {self.name!r}", self.dtype, _DTYPES)
        for d in self.shape:
            if not (isinstance(d, str) and d) and not (isinstance(d, int) and d >= 0):
                raise ManifestError(f"shape of tensor {self.name!r} has a bad dimension {d!r} (int >= 0 or a name)")

    @classmethod
    def from_dict(cls, d: dict) -> "TensorSpec":
        return cls(name=str(d["name"]), shape=tuple(_as_int(v) for v in d["shape"]), dtype=str(d["dtype"]))


@dataclass(frozen=True)
class GraphEntry:
    name: str  # one of GRAPH_NAMES
    precision: str  # "fp32", "fp16" or "int8" (fp16 and int8 graphs keep fp32 inputs and outputs)
    file: str  # relative to the export directory
    sha256: str
    opset: int
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]
    gmac: float  # multiply-accumulates (1e9) at the exported resolution, per the shapes in `gmac_at`
    gmac_at: dict = field(default_factory=dict)  # the dynamic sizes gmac was counted at, e.g. {"J": 1, "Q": 1}

    def __post_init__(self) -> None:
        _check_choice("GraphEntry.name", self.name, GRAPH_NAMES)
        _check_choice(f"precision of graph {self.name!r}", self.precision, PRECISIONS)
        _check_sha(f"sha256 of {self.file!r}", self.sha256)
        if not isinstance(self.opset, int) or self.opset < 7:
            raise ManifestError(f"opset of {self.file!r} must be an int >= 7, got {self.opset!r}")
        _check_plain_name("graph file", self.file)

    @classmethod
    def from_dict(cls, d: dict) -> "GraphEntry":
        return cls(
            name=str(d["name"]),
            precision=str(d["precision"]),
            file=str(d["file"]),
            sha256=str(d["sha256"]),
            opset=_as_int(d["opset"]),
            inputs=tuple(TensorSpec.from_dict(t) for t in d["inputs"]),
            outputs=tuple(TensorSpec.from_dict(t) for t in d["outputs"]),
            gmac=float(d["gmac"]),
            gmac_at=dict(d.get("gmac_at", {})),
        )


@dataclass(frozen=True)
class ImageSpec:
    width: int  # pixels the export (and the LUT) assume
    height: int
    feature_stride: int  # 4: Hf = ceil(H / stride)
    feature_width: int
    feature_height: int
    camera_names: tuple[str, ...]  # LUT camera order = order of the images fed to image_encoder

    def __post_init__(self) -> None:
        for name in ("width", "height", "feature_stride", "feature_width", "feature_height"):
            v = getattr(self, name)
            if not isinstance(v, int) or v <= 0:
                raise ManifestError(f"image.{name} must be a positive int, got {v!r}")
        if not self.camera_names:
            raise ManifestError("image.camera_names must name at least one camera")

    @classmethod
    def from_dict(cls, d: dict) -> "ImageSpec":
        return cls(
            width=_as_int(d["width"]),
            height=_as_int(d["height"]),
            feature_stride=_as_int(d["feature_stride"]),
            feature_width=_as_int(d["feature_width"]),
            feature_height=_as_int(d["feature_height"]),
            camera_names=tuple(d["camera_names"]),
        )


@dataclass(frozen=True)
class Normalisation:
    """Applied inside image_encoder.onnx: x = (rgb_uint8 * scale - mean) / std. Recorded for reference only."""

    input: str = "uint8 RGB (J, H, W, 3)"
    scale: float = 1.0 / 255.0
    mean_rgb: tuple[float, float, float] = (0.485, 0.456, 0.406)  # ImageNet
    std_rgb: tuple[float, float, float] = (0.229, 0.224, 0.225)

    @classmethod
    def from_dict(cls, d: dict) -> "Normalisation":
        return cls(input=str(d["input"]), scale=float(d["scale"]), mean_rgb=tuple(d["mean_rgb"]), std_rgb=tuple(d["std_rgb"]))


@dataclass(frozen=True)
class LutEntry:
    file: str  # "lut.npz"
    sha256: str
    calibration_sha256: str  # of the calibration JSON the LUT was built from
    calibration_source: str  # a path, or "bundled:nuscenes_sample/calibration.json"

    def __post_init__(self) -> None:
        _check_sha("lut.sha256", self.sha256)
        _check_plain_name("lut.file", self.file)  # as graph files: never a path out of the export directory

    @classmethod
    def from_dict(cls, d: dict) -> "LutEntry":
        return cls(
            file=str(d["file"]),
            sha256=str(d["sha256"]),
            calibration_sha256=str(d["calibration_sha256"]),
            calibration_source=str(d["calibration_source"]),
        )


@dataclass(frozen=True)
class Manifest:
    preset_name: str
    preset: dict
    grid: dict
    class_names: tuple[str, ...]
    num_slices: int
    image: ImageSpec | None  # None exactly when the preset has use_image false (LiDAR-only)
    normalisation: Normalisation | None  # likewise
    post: dict
    graphs: tuple[GraphEntry, ...]
    lut: LutEntry | None  # likewise
    parity: tuple[ParityRecord, ...] = ()
    pipeline_parity: PipelineParity | None = None
    source: dict = field(default_factory=dict)
    int8: Int8Record | None = None  # calibration and parity of the int8 graphs, when there are any
    # the map the lifter hands the slice graph (core/image_layout.py); absent in older manifests: image_bev
    image_layout: str = IMAGE_BEV
    # how the lifter graph reads the LUT (core/lut_layout.py); absent in older manifests: slots
    lut_layout: str = LUT_SLOTS
    version: int = MANIFEST_VERSION

    def __post_init__(self) -> None:
        if self.version != MANIFEST_VERSION:
            raise ManifestError(f"manifest version {self.version!r} is not supported (expected {MANIFEST_VERSION})")
        if not self.class_names:
            raise ManifestError("class_names must not be empty")
        _check_choice("image_layout", self.image_layout, IMAGE_LAYOUTS)
        if self.image_layout == IMAGE_HALF:  # the image half's shape is the BEV encoder's first stage's (core/image_layout.py)
            bev = self.preset.get("bev")
            if not isinstance(bev, dict) or not bev.get("layer_strides") or not bev.get("num_filters"):
                raise ManifestError(f"image_layout {IMAGE_HALF!r} needs preset.bev.layer_strides and preset.bev.num_filters "
                                    f"(the BEV encoder's first stage), got preset.bev {bev!r:.200}")  # fmt: skip
        _check_choice("lut_layout", self.lut_layout, LUT_LAYOUTS)
        if not isinstance(self.num_slices, int) or self.num_slices < 1:
            raise ManifestError(f"num_slices must be a positive int, got {self.num_slices!r}")
        seen = set()
        for g in self.graphs:
            key = (g.name, g.precision)
            if key in seen:
                raise ManifestError(f"graph {g.name!r} ({g.precision}) is listed twice")
            seen.add(key)
        if any(g.precision == "int8" for g in self.graphs) and self.int8 is None:
            raise ManifestError("graphs of precision int8 are listed without the int8 record (calibration data, parity)")
        self._check_modality(seen)

    def _check_modality(self, seen: set[tuple[str, str]]) -> None:
        """The graphs and image fields the preset's use_image calls for, and no others (see the module doc)."""
        use_image = self.preset.get("use_image", True)
        if not isinstance(use_image, bool):
            raise ManifestError(f"preset.use_image must be true or false, got {use_image!r}")
        crop = self.preset.get("slice_crop", True)
        if not isinstance(crop, bool):
            raise ManifestError(f"preset.slice_crop must be true or false, got {crop!r}")
        if use_image and not crop:
            raise ManifestError("preset.slice_crop false (whole-grid slice maps) is for a LiDAR-only preset only, "
                                "this one has use_image true")  # fmt: skip
        for name in self.required_graphs:
            if (name, "fp32") not in seen:
                why = " (the preset reads images: use_image is true)" if name in IMAGE_GRAPH_NAMES else ""
                raise ManifestError(f"manifest lists no fp32 graph {name!r}{why}")
        image_fields = {"image": self.image, "normalisation": self.normalisation, "lut": self.lut}
        if use_image:
            absent = [k for k, v in image_fields.items() if v is None]
            if absent:
                raise ManifestError(f"manifest of a camera + LiDAR preset (use_image true) has no {', '.join(absent)}")
            return
        extra = sorted({f"{n} ({p})" for n, p in seen if n in IMAGE_GRAPH_NAMES})
        if extra:
            raise ManifestError(f"manifest of a LiDAR-only preset (use_image false) lists image graphs: {', '.join(extra)}")
        present = [k for k, v in image_fields.items() if v is not None]
        if present:
            raise ManifestError(f"manifest of a LiDAR-only preset (use_image false) has {', '.join(present)}; expected null")

    @property
    def use_image(self) -> bool:
        """False for a LiDAR-only export: no image lane, no LUT, the slice graph alone."""
        return bool(self.preset.get("use_image", True))

    @property
    def slice_crop(self) -> bool:
        """False for a LiDAR-only export without the quadrant crop: one whole-grid map per slice, no quadrant ids
        fed (calibration/slice_maps.py); absent (every export before it) means True."""
        return bool(self.preset.get("slice_crop", True))

    @property
    def required_graphs(self) -> tuple[str, ...]:
        """The graphs every precision of this export consists of."""
        return GRAPH_NAMES if self.use_image else ("slice_head",)

    def graph(self, name: str, precision: str = "fp32") -> GraphEntry:
        for g in self.graphs:
            if g.name == name and g.precision == precision:
                return g
        have = sorted({g.precision for g in self.graphs if g.name == name})
        raise ManifestError(f"manifest has no {precision} graph {name!r} (precisions present: {have})")

    @property
    def precisions(self) -> tuple[str, ...]:
        """Precisions for which all required graphs (three, or the slice graph of a LiDAR-only export) are present."""
        have = {(g.name, g.precision) for g in self.graphs}
        return tuple(p for p in PRECISIONS if all((n, p) in have for n in self.required_graphs))

    def files(self) -> tuple[tuple[GraphEntry | LutEntry, str], ...]:
        """Every file the manifest names, with what it is (for messages): the graphs, then the LUT."""
        graphs = tuple((g, f"graph file of {g.name} ({g.precision})") for g in self.graphs)
        return graphs + (((self.lut, "lut.file"),) if self.lut is not None else ())

    def to_dict(self) -> dict:
        return _jsonable(asdict(self))

    @classmethod
    def from_dict(cls, d: dict) -> "Manifest":
        if not isinstance(d, dict):
            raise ManifestError(f"manifest must be a JSON object, got {type(d).__name__}")
        try:
            validate(d)  # manifest.schema.json: every type, range and size, before any record is built
        except SchemaViolation as e:
            raise ManifestError(str(e)) from None
        try:
            return cls(
                version=_as_int(d["version"]),
                preset_name=str(d["preset_name"]),
                preset=dict(d["preset"]),
                grid=dict(d["grid"]),
                class_names=tuple(d["class_names"]),
                num_slices=_as_int(d["num_slices"]),
                image=_optional(ImageSpec.from_dict, d["image"]),
                normalisation=_optional(Normalisation.from_dict, d["normalisation"]),
                post=dict(d["post"]),
                graphs=tuple(GraphEntry.from_dict(g) for g in d["graphs"]),
                lut=_optional(LutEntry.from_dict, d["lut"]),
                parity=tuple(ParityRecord.from_dict(p) for p in d.get("parity", ())),
                pipeline_parity=PipelineParity.from_dict(d["pipeline_parity"]) if d.get("pipeline_parity") else None,
                source=dict(d.get("source", {})),
                int8=Int8Record.from_dict(d["int8"]) if d.get("int8") else None,
                image_layout=str(d.get("image_layout", IMAGE_BEV)),
                lut_layout=str(d.get("lut_layout", LUT_SLOTS)),
            )
        except KeyError as e:
            raise ManifestError(f"manifest is missing the field {e.args[0]!r}") from None
        except (TypeError, AttributeError) as e:
            raise ManifestError(f"manifest has a malformed field: {e}") from None


def read_manifest(export_dir: str | os.PathLike, verify_files: bool = True) -> Manifest:
    """Read and validate ``export_dir/manifest.json`` against ``manifest.schema.json``.

    The file is capped at MAX_MANIFEST_BYTES and MAX_MANIFEST_DEPTH levels of nesting. Every file the manifest
    names must resolve (symlinks followed) inside the export directory, always; with verify_files each must also
    exist with its sha256. Any defect raises ManifestError naming the file.
    """
    export_dir = Path(export_dir)
    path = export_dir / MANIFEST_NAME
    try:
        exists, regular = path.exists(), path.is_file()
    except OSError as e:  # an export directory that may not be listed (no x permission)
        raise ManifestError(f"{path}: cannot be read: {e.strerror or e}") from None
    if not regular:
        raise ManifestError(f"{path} is not a regular file (a FIFO, a device or a folder?)" if exists else
                            f"{path} does not exist: not a (complete) streamdet export directory")  # fmt: skip
    export_file(export_dir, MANIFEST_NAME, "the manifest")  # confined as the files it names: no symlink out
    too_deep = ManifestError(f"{path} nests deeper than {MAX_MANIFEST_DEPTH} levels: not a streamdet manifest")
    try:
        raw = read_regular_file(path, MAX_MANIFEST_BYTES)
    except InputFileError as e:
        if e.too_large:
            raise ManifestError(f"{path} is larger than {MAX_MANIFEST_BYTES >> 20} MiB: not a streamdet manifest") from None
        raise ManifestError(f"{path}: {e.reason}") from None
    try:
        d = json.loads(raw.decode("utf-8"))
    except (OSError, ValueError) as e:  # ValueError: JSONDecodeError, UnicodeDecodeError, an integer of over 4300 digits
        raise ManifestError(f"{path} is not readable JSON: {e}") from None
    except RecursionError:  # deeper than the parser's stack
        raise too_deep from None
    if _depth(d) > MAX_MANIFEST_DEPTH:
        raise too_deep
    try:
        m = Manifest.from_dict(d)
    except ManifestError as e:
        raise ManifestError(f"{path}: {e}") from None
    for entry, what in m.files():
        if verify_files:  # bounded and hashed as loaders read them; the bytes are dropped at once
            read_export_file(export_dir, entry, what, verify_sha256=True)
        else:
            export_file(export_dir, entry.file, what)
    return m


def write_manifest(manifest: Manifest, export_dir: str | os.PathLike) -> Path:
    """Write ``manifest.json`` atomically (temp file + rename), so a reader never sees half a manifest."""
    text = json.dumps(manifest.to_dict(), indent=1, allow_nan=True) + "\n"
    return atomic_write(export_dir, MANIFEST_NAME, lambda f: f.write(text.encode("utf-8")))


def atomic_write(export_dir: str | os.PathLike, name: str, write: Callable[[BinaryIO], Any]) -> Path:
    """Write the file ``name`` of ``export_dir`` atomically: ``write(f)`` into a hidden temp file beside it, then a rename.

    ``name`` is confined as every manifest-named file is (``export_file``), and the rename replaces a symlink at
    the target instead of writing through it. The file gets the permissions of a plain ``open()`` (0666 minus the
    umask), like the graphs beside it, not mkstemp's 0600. A failure removes the temp file.
    """
    return atomic_write_file(export_file(export_dir, name), write)


def _optional(parse: Any, value: Any) -> Any:
    """``parse(value)``, or None for a JSON null (the image fields of a LiDAR-only manifest)."""
    return None if value is None else parse(value)


def _check_choice(what: str, value: Any, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ManifestError(f"{what} must be one of {list(choices)}, got {value!r}")


def _check_sha(what: str, value: str) -> None:
    if not (isinstance(value, str) and len(value) == 64 and all(c in "0123456789abcdef" for c in value)):
        raise ManifestError(f"{what} must be 64 lowercase hex digits, got {value!r}")


def _as_int(value: Any) -> Any:
    """An integral float (JSON ``8.0``, an integer to JSON Schema) as an int; anything else unchanged (checked later)."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


def _check_plain_name(what: str, name: str) -> None:
    if not isinstance(name, str) or not name or Path(name).name != name or name.startswith(".") or "\\" in name:
        raise ManifestError(f"{what} must be a plain file name inside the export directory, got {name!r}")


def _depth(doc: Any) -> int:
    """Nesting depth of parsed JSON, without recursion (a hostile document may nest deeper than the stack)."""
    deepest, stack = 0, [(doc, 1)]
    while stack:
        node, level = stack.pop()
        if isinstance(node, (dict, list)):
            deepest = max(deepest, level)
            if level > MAX_MANIFEST_DEPTH:
                return level
            stack.extend((v, level + 1) for v in (node.values() if isinstance(node, dict) else node))
    return deepest


def _jsonable(x: Any) -> Any:
    """Tuples to lists, numpy scalars to Python numbers (asdict keeps whatever the fields hold)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if hasattr(x, "item") and callable(x.item) and getattr(x, "shape", None) == ():
        return x.item()
    return x
