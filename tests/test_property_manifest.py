"""Property tests: generated manifests (a real export's manifest under random edits) and generated calibration files.

Every input ends in a valid result or one of the project's named errors, never another exception; the runtime's
schema validator agrees with jsonschema on every input; streamdet-calib never writes a file outside the export,
nor inside it anything but lut.npz and manifest.json. Profiles: tests/conftest.py (CI bounded; HYPOTHESIS_PROFILE=long).
"""

from __future__ import annotations

import copy
import json
import os
import shutil
import tempfile
from pathlib import Path

import pytest

hypothesis = pytest.importorskip("hypothesis")
jsonschema = pytest.importorskip("jsonschema")

from hypothesis import event, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from streamdet.calibration.camera import CalibrationError, Rig  # noqa: E402
from streamdet.runtime_ort.calib_cli import LutMismatch, rebuild_lut  # noqa: E402
from streamdet.runtime_ort.detector import NoImageLaneError, StreamingDetector  # noqa: E402
from streamdet.runtime_ort.manifest import Manifest, ManifestError  # noqa: E402
from streamdet.runtime_ort.schema import SchemaViolation, manifest_schema, validate  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _costly(ci_examples: int) -> int:
    """Examples for a property whose inputs cost a graph run or a file tree: a few in CI, 1/20 of the profile's beyond."""
    return max(ci_examples, settings().max_examples // 20)
CALIBRATION = ROOT / "data" / "nuscenes_sample" / "calibration.json"
NAMED = (ManifestError, CalibrationError, NoImageLaneError, LutMismatch)

HOSTILE_STRINGS = ["../x", "/etc/passwd", ".hidden", "a/b", "lut.npz", "", "slice_head.onnx", "fp16", "int8", "float64",
                   "J", "manifest.json", "..", "x" * 300, "CAM_FRONT", "\x00", "bundled:../../etc/passwd"]  # fmt: skip
LEAVES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.sampled_from([0, 1, -1, 2, 3, 4, 7, 8, 16, 4096, 4097, 10**9 + 1]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, 0.5, 1.0, 8.0, -0.0, 1e300]),
    st.text(max_size=12),
    st.sampled_from(HOSTILE_STRINGS),
)
JSON = st.recursive(LEAVES, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
                    max_leaves=8)  # fmt: skip


def _paths(node, prefix=()):
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, (*prefix, i))


def _apply(doc, path, action, value):
    """doc edited at path: replaced by value, deleted, or (lists) value appended; a vanished path is skipped."""
    if not path:
        return value if action == "replace" else doc
    node = doc
    try:
        for key in path[:-1]:
            node = node[key]
        last = path[-1]
        if action == "delete" and isinstance(node, dict):
            node.pop(last, None)
        elif action == "delete" and isinstance(node, list) and isinstance(last, int) and last < len(node):
            del node[last]
        elif action == "append" and isinstance(node[last], list):
            node[last].append(value)
        else:
            node[last] = value
    except (KeyError, IndexError, TypeError):
        pass
    return doc


@pytest.fixture(scope="module")
def base(tiny_export) -> dict:
    return json.loads((tiny_export / "manifest.json").read_text())


@st.composite
def edited(draw, base: dict, runtime_fields_only: bool = False):
    doc = copy.deepcopy(base)
    paths = [p for p in _paths(base) if p]
    if runtime_fields_only:  # the fields the runtime reads: a higher hit rate on the checks that load graphs
        paths = [p for p in paths if p[0] in ("preset", "grid", "post", "graphs", "class_names", "num_slices", "image", "lut")]
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(paths))
        # for the runtime's fields mostly plausible wrong values: a higher hit rate past the schema, on the graph checks
        actions = ["nudge", "nudge", "nudge", "delete", "replace"] if runtime_fields_only else ["replace", "replace", "delete", "append", "nudge", "nudge"]
        action = draw(st.sampled_from(actions))
        old = _get(doc, path)
        if action == "nudge" and isinstance(old, (int, float)) and not isinstance(old, bool):
            # a plausible wrong value (an edited dimension, a shifted extrinsic): the checks beyond the schema
            doc = _apply(doc, path, "replace", draw(st.sampled_from([old + 1, old - 1, old * 2, -old, 0, old + 0.5])))
        else:
            doc = _apply(doc, path, "replace" if action == "nudge" else action, draw(JSON))
    return doc


def _get(doc, path):
    try:
        for key in path:
            doc = doc[key]
        return doc
    except (KeyError, IndexError, TypeError):
        return None


def _jsonschema_valid(doc) -> bool:
    return jsonschema.Draft202012Validator(manifest_schema()).is_valid(doc)


# The base manifest is read once per module; the strategies need it at collection time, so read it lazily.
@given(data=st.data())
def test_generated_manifests_parse_or_are_named_errors(base, data):
    doc = data.draw(edited(base))
    ours = True
    try:
        validate(doc)
    except SchemaViolation:
        ours = False
    assert ours == _jsonschema_valid(doc)  # one definition: the runtime's validator is jsonschema's verdict
    try:
        m = Manifest.from_dict(doc)
    except ManifestError:
        event("refused")
        return
    event("accepted")
    assert ours and isinstance(m, Manifest)


@given(data=st.data())
def test_random_json_documents_are_named_errors(data):
    doc = data.draw(JSON)
    with pytest.raises(ManifestError):
        Manifest.from_dict(doc)


@settings(max_examples=_costly(15))
@given(data=st.data())
def test_generated_manifests_load_or_are_named_errors_and_calib_writes_only_its_two_files(tiny_export, base, data):
    doc = data.draw(edited(base, runtime_fields_only=True))
    symlink = data.draw(st.sampled_from([None, None, "lut.npz", "manifest.json", "slice_head.onnx"]))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        exp = tmp / "box" / "exp"
        shutil.copytree(tiny_export, exp)
        (exp / "manifest.json").write_text(json.dumps(doc, allow_nan=True))
        if symlink is not None:
            outside = tmp / f"outside-{symlink}"
            shutil.move(exp / symlink, outside)
            (exp / symlink).symlink_to(outside)
        try:
            StreamingDetector(exp)
            event("detector loaded")
        except NAMED + (ValueError,) as e:
            event(f"detector refused: {type(e).__name__}")
        outside_before = _snapshot(tmp, skip=exp)
        inside_before = _snapshot(exp)
        try:
            rebuild_lut(CALIBRATION, exp)
            event("calib wrote")
        except NAMED as e:
            event(f"calib refused: {type(e).__name__}")
        assert _snapshot(tmp, skip=exp) == outside_before  # nothing outside the export is ever written
        changed = {p for p in set(inside_before) | set(_snapshot(exp)) if inside_before.get(p) != _snapshot(exp).get(p)}
        assert changed <= {"lut.npz", "manifest.json"}


def _snapshot(root: Path, skip: Path | None = None) -> dict[str, bytes]:
    out = {}
    for dirpath, _, files in os.walk(root):
        if skip is not None and Path(dirpath).resolve() == skip.resolve():
            continue
        for f in files:
            p = Path(dirpath) / f
            out[str(p.relative_to(root))] = os.readlink(p).encode() if p.is_symlink() else p.read_bytes()
    return out


# ---- calibration files ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def calibration_doc() -> dict:
    return json.loads(CALIBRATION.read_text())


@pytest.fixture(scope="module")
def detector(tiny_export) -> StreamingDetector:
    return StreamingDetector(tiny_export)


@given(data=st.data())
def test_generated_calibrations_are_rigs_or_calibration_errors(calibration_doc, data):
    doc = data.draw(edited(calibration_doc))
    try:
        rig = Rig.from_calibration_json(doc)
    except CalibrationError:
        event("refused")
        return
    event("accepted")
    assert isinstance(rig, Rig)


@settings(max_examples=_costly(20))
@given(data=st.data())
def test_set_calibration_swaps_or_refuses_without_changing_the_lut(detector, calibration_doc, data):
    doc = data.draw(edited(calibration_doc))
    as_file = data.draw(st.booleans())
    before = detector.lut
    try:
        if as_file:
            with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as f:
                f.write(json.dumps(doc, allow_nan=True))
            try:
                detector.set_calibration(f.name)
            finally:
                os.unlink(f.name)
        else:
            detector.set_calibration(doc)
    except CalibrationError:
        event("refused")
        assert detector.lut is before  # a refusal never changes the LUT in use
        return
    if detector.lut is before:  # only for the rig the LUT in use was built from: nothing to swap, no LUT built
        event("the rig in use again")
        assert Rig.from_calibration_json(doc).sha256() == before.calibration_sha256
        return
    event("swapped")
    assert detector.lut is not before


@given(raw=st.binary(max_size=512))
def test_random_bytes_as_a_calibration_file_are_calibration_errors(raw):
    with tempfile.NamedTemporaryFile("wb", suffix=".json", delete=False) as f:
        f.write(raw)
    try:
        with pytest.raises(CalibrationError):
            Rig.from_calibration_json(f.name)
    finally:
        os.unlink(f.name)


# ---- LUT files -----------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def lut_parts(tiny_export) -> tuple:
    import numpy as np

    with np.load(tiny_export / "lut.npz") as z:
        return z["index"], z["weight"], json.loads(str(z["meta"]))


@settings(max_examples=_costly(25))
@given(data=st.data())
def test_generated_lut_files_load_or_are_calibration_errors(lut_parts, data):
    import numpy as np

    from streamdet.calibration.lut import Lut

    index, weight, meta = lut_parts
    kind = data.draw(st.sampled_from(["meta", "meta", "tables", "npy", "bytes"]))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "lut.npz"
        if kind == "meta":
            doc = data.draw(edited(meta))
            np.savez(path, index=index, weight=weight, meta=np.array(json.dumps(doc, allow_nan=True)))
        elif kind == "tables":
            bad = index.copy()
            flat = bad.reshape(-1)
            flat[data.draw(st.integers(0, flat.size - 1))] = data.draw(st.integers(-(2**31), 2**31 - 1))
            np.savez(path, index=bad, weight=weight, meta=np.array(json.dumps(meta)))
        elif kind == "npy":
            np.save(path, index)
            os.replace(str(path) + ".npy", path) if os.path.exists(str(path) + ".npy") else None
        else:
            path.write_bytes(data.draw(st.binary(max_size=256)))
        try:
            lut = Lut.load(path)
        except CalibrationError:
            event(f"{kind}: refused")
            return
        event(f"{kind}: loaded")
        assert lut.index.shape == index.shape or kind == "meta"
