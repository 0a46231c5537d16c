"""Issue 16's five reproducers, each as a regression test: path confinement of every manifest-named file,
the newest images kept across a calibration swap, a cancelled future that does not break the runner,
num_slices 0 / bool refused, and one-line named errors where tracebacks were."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.calibration.camera import CalibrationError
from streamdet.runtime_ort.calib_cli import main as calib_main
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.lanes import LaneConfig, SliceDropped, StreamingRunner
from streamdet.runtime_ort.manifest import ManifestError, read_manifest, sha256_file

ROOT = Path(__file__).resolve().parents[1]
CALIBRATION = ROOT / "data" / "nuscenes_sample" / "calibration.json"


@pytest.fixture
def export_copy(tiny_export, tmp_path) -> Path:
    """A private copy of the shared tiny export, inside tmp_path/box (tmp_path itself holds the 'outside' files)."""
    out = tmp_path / "box" / "tiny"
    shutil.copytree(tiny_export, out)
    return out


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


def _edit_manifest(export_dir: Path, change) -> None:
    path = export_dir / "manifest.json"
    d = json.loads(path.read_text())
    change(d)
    path.write_text(json.dumps(d))


def _snapshot(root: Path) -> dict[str, tuple[int, bytes]]:
    """Every file under root (symlinks as their target text) with its mode and bytes."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_symlink():
            out[str(p)] = (0, os.readlink(p).encode())
        elif p.is_file():
            out[str(p)] = (p.stat().st_mode, p.read_bytes())
    return out


def _images(det: StreamingDetector, sample, seed: int | None = None) -> dict[str, np.ndarray]:
    img = det.image
    if seed is None:
        arr = sample.load_images((img.width, img.height))
        return {n: arr[sample.rig.names.index(n)] for n in det.camera_names}
    rng = np.random.default_rng(seed)
    return {n: rng.integers(0, 256, (img.height, img.width, 3), dtype=np.uint8) for n in det.camera_names}


# ---- 1. path confinement ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("target", ["absolute", "parent", "subdir", "hidden"])
def test_lut_file_outside_the_export_is_refused_for_reading_and_writing(export_copy, tmp_path, target):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    name = {"absolute": str(victim), "parent": "../../victim.txt", "subdir": "sub/lut.npz", "hidden": ".lut.npz"}[target]
    _edit_manifest(export_copy, lambda d: d["lut"].update(file=name))
    before = _snapshot(tmp_path)
    with pytest.raises(ManifestError, match="plain file name"):
        read_manifest(export_copy)
    with pytest.raises(ManifestError, match="plain file name"):
        StreamingDetector(export_copy, DetectorConfig(verify_sha256=False))
    result = CliRunner().invoke(calib_main, ["lut", "--calibration", str(CALIBRATION), "--export-dir", str(export_copy)])
    assert result.exit_code != 0 and "plain file name" in result.output
    assert _snapshot(tmp_path) == before  # nothing written anywhere, the victim untouched


@pytest.mark.parametrize("name", ["lut.npz", "slice_head.onnx", "manifest.json"])
def test_a_symlink_out_of_the_export_is_refused(export_copy, tmp_path, name):
    outside = tmp_path / f"outside-{name}"
    shutil.copy(export_copy / name, outside)
    (export_copy / name).unlink()
    (export_copy / name).symlink_to(outside)
    before = _snapshot(tmp_path)
    if name != "manifest.json":  # reading a manifest through a symlink is harmless; the files it names are not
        with pytest.raises(ManifestError, match="outside the export directory"):
            read_manifest(export_copy)
    result = CliRunner().invoke(calib_main, ["lut", "--calibration", str(CALIBRATION), "--export-dir", str(export_copy)])
    # refused whichever file escapes: an export that names a file elsewhere is not touched at all
    assert result.exit_code != 0 and "outside the export directory" in result.output
    assert _snapshot(tmp_path) == before


def test_a_symlink_inside_the_export_is_followed(export_copy):
    (export_copy / "slice_head.onnx").rename(export_copy / "slice_head.real.onnx")
    (export_copy / "slice_head.onnx").symlink_to("slice_head.real.onnx")
    det = StreamingDetector(export_copy)
    assert det.slice_head.path.name == "slice_head.real.onnx"


def test_streamdet_calib_writes_only_lut_and_manifest_atomically(export_copy, tmp_path):
    before = _snapshot(tmp_path)
    graph_mode = (export_copy / "slice_head.onnx").stat().st_mode
    rig = json.loads(CALIBRATION.read_text())
    rig["cameras"][0]["lidar2cam"]["matrix"][0][3] += 0.05  # a new calibration: the LUT changes
    new_calib = tmp_path / "calib.json"
    new_calib.write_text(json.dumps(rig))
    before[str(new_calib)] = (new_calib.stat().st_mode, new_calib.read_bytes())
    result = CliRunner().invoke(calib_main, ["lut", "--calibration", str(new_calib), "--export-dir", str(export_copy)])
    assert result.exit_code == 0, result.output
    after = _snapshot(tmp_path)
    changed = {Path(p).name for p in set(before) | set(after) if before.get(p) != after.get(p)}
    assert changed == {"lut.npz", "manifest.json"}  # no temp file left, nothing else touched
    assert (export_copy / "manifest.json").stat().st_mode == graph_mode  # 0644 under umask 022, as the graphs
    assert (export_copy / "lut.npz").stat().st_mode == graph_mode
    read_manifest(export_copy)  # the manifest names the new LUT's sha256


def test_the_runtime_never_hashes_a_file_outside_the_export(export_copy, tmp_path, monkeypatch):
    _edit_manifest(export_copy, lambda d: d["lut"].update(file="/etc/passwd"))
    hashed = []
    import streamdet.runtime_ort.manifest as manifest_module

    monkeypatch.setattr(manifest_module, "sha256_file", lambda p: hashed.append(p) or "0" * 64)
    with pytest.raises(ManifestError):
        read_manifest(export_copy)
    assert not any("passwd" in str(p) for p in hashed)


@pytest.mark.parametrize("source", ["/etc/passwd", "../../victim.json", "bundled:../../../../etc/passwd"])
def test_the_calibration_source_is_read_only_from_the_package_or_the_export(export_copy, tmp_path, source):
    shutil.copy(CALIBRATION, tmp_path / "victim.json")
    _edit_manifest(export_copy, lambda d: d["lut"].update(calibration_source=source))
    with pytest.raises(ValueError, match="not a bundled file or a file inside the export directory"):
        StreamingDetector(export_copy, DetectorConfig(image_size=(256, 144)))


def test_a_calibration_source_inside_the_export_is_used_when_unchanged(export_copy):
    shutil.copy(CALIBRATION, export_copy / "calibration.json")
    _edit_manifest(export_copy, lambda d: d["lut"].update(calibration_source="calibration.json"))
    assert StreamingDetector(export_copy, DetectorConfig(image_size=(256, 144))).lut.image_width == 256
    doc = json.loads(CALIBRATION.read_text())
    doc["cameras"][0]["lidar2cam"]["matrix"][0][3] += 0.5
    (export_copy / "calibration.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match="changed since the export"):
        StreamingDetector(export_copy, DetectorConfig(image_size=(256, 144)))


# ---- 2. the newest images survive a calibration swap --------------------------------------------------------------
class _GatedLift:
    """Wraps detector._lift: the lift of the features `gate_on` (by identity) waits until `release` is set."""

    def __init__(self, det: StreamingDetector) -> None:
        self.det = det
        self.inner = det._lift
        self.gate_on: np.ndarray | None = None
        self.entered = threading.Event()
        self.release = threading.Event()

    def __call__(self, features, lut):
        if self.gate_on is not None and features is self.gate_on:
            self.entered.set()
            assert self.release.wait(30)
        return self.inner(features, lut)


def _perturbed_rig(sample, shift_m: float):
    from streamdet.calibration.perturb import perturb_rig

    return perturb_rig(sample.rig, 0.0, shift_m, seed=1)


def test_a_calibration_relift_never_overwrites_newer_images(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    gate = _GatedLift(det)
    det._lift = gate
    det.update_images(_images(det, sample, seed=1), timestamp=1.0)
    gate.gate_on = det.image_state.features  # the re-lift of image set A blocks
    rig = _perturbed_rig(sample, 0.5)
    t = threading.Thread(target=det.set_calibration, args=(rig,))
    t.start()
    assert gate.entered.wait(30)
    images_b = _images(det, sample, seed=2)
    det.update_images(images_b, timestamp=2.0)  # finishes while A is being re-lifted
    gate.release.set()
    t.join(30)
    assert det.image_timestamp == 2.0
    state = det.image_state
    assert state.lut is det.lut
    assert np.array_equal(state.bev, gate.inner(state.features, det.lut))  # B, lifted with the new calibration


def test_images_lifted_under_the_old_calibration_are_lifted_again(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    inner = det._lift
    det.update_images(_images(det, sample, seed=1), timestamp=1.0)
    old_lut = det.lut
    entered, release = threading.Event(), threading.Event()

    def lift(features, lut):  # B's lift with the old LUT waits until the calibration swap has returned
        if lut is old_lut and threading.current_thread().name == "update-b":
            entered.set()
            assert release.wait(30)
        return inner(features, lut)

    det._lift = lift
    t = threading.Thread(target=det.update_images, args=(_images(det, sample, seed=2), 2.0), name="update-b")
    t.start()
    assert entered.wait(30)
    det.set_calibration(_perturbed_rig(sample, 0.5))  # re-lifts A, installs it, returns
    release.set()
    t.join(30)
    state = det.image_state
    assert det.image_timestamp == 2.0 and state.lut is det.lut and det.lut is not old_lut
    assert np.array_equal(state.bev, inner(state.features, det.lut))


def test_the_issue_reproducer_keeps_the_newest_images(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    rig = _perturbed_rig(sample, 0.3)
    for i in range(3):
        t = threading.Thread(target=det.update_images, args=(_images(det, sample, seed=i), float(10 + i)))
        t.start()
        time.sleep(0.002 * i)
        det.set_calibration(rig)
        t.join(30)
        assert det.image_timestamp == float(10 + i)


# ---- 3. a cancelled future does not break the runner --------------------------------------------------------------
class _SlowDetector:
    """Just enough of a StreamingDetector for the runner: every slice waits for `go`."""

    uses_images = True

    def __init__(self) -> None:
        self.go = threading.Event()
        self.started = threading.Event()
        self.seen: list[int] = []

    def detect_slice(self, points, slice_index, timestamp=None):
        self.started.set()
        assert self.go.wait(30)
        self.seen.append(slice_index)
        return slice_index


def test_a_cancelled_future_never_breaks_the_next_submit():
    det = _SlowDetector()
    runner = StreamingRunner(det, LaneConfig(max_in_flight=1, queue_size=1))
    pts = np.zeros((1, 6), np.float32)
    first = runner.submit_slice(pts, 0)
    assert det.started.wait(30)  # the worker runs the first; the second waits
    second = runner.submit_slice(pts, 1)
    assert second.cancel()
    third = runner.submit_slice(pts, 2)  # raised InvalidStateError into the driver's thread before the fix
    det.go.set()
    assert first.result(30) == 0 and third.result(30) == 2
    assert second.cancelled() and det.seen == [0, 2]
    assert runner.slices_dropped == 0  # a cancelled slice is not a dropped one
    assert runner.close(timeout=30)


def test_the_issue_reproducer_with_the_real_detector(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    from streamdet.core.slicing import split_sweep

    slices = split_sweep(sample.points, 8)
    with StreamingRunner(det, LaneConfig(max_in_flight=1, queue_size=1)) as runner:
        futures = [runner.submit_slice(slices[k], k) for k in range(3)]
        futures[1].cancel()
        extra = runner.submit_slice(slices[3], 3)
        for f in (futures[0], futures[2], extra):
            try:
                assert f.result(60).num_points > 0
            except SliceDropped:
                pass  # a waiting slice may be dropped for a newer one: that is the policy, not a failure


# ---- 4. num_slices 0 and booleans ---------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [0, -4, 3, True, False, 8.0, "8"])
def test_num_slices_zero_or_bool_is_refused(bad):
    with pytest.raises(ValueError, match="DetectorConfig.num_slices"):
        DetectorConfig(num_slices=bad)


def test_slices_zero_on_the_command_line_is_an_error(tiny_export, tmp_path):
    from streamdet.evaluation.run_cli import main as run_main

    result = CliRunner().invoke(run_main, ["--export-dir", str(tiny_export), "--slices", "0", "--out", str(tmp_path / "o")])
    # a usage error naming the option and its range, as in eval, replay and bag (CLI review 40, L7)
    assert result.exit_code == 2 and "--slices" in result.output and "1<=x<=4096" in result.output
    assert "Traceback" not in result.output


@pytest.mark.parametrize(
    "path",
    [("num_slices",), ("image", "width"), ("preset", "pillars", "max_points_per_pillar"), ("preset", "channels"),
     ("graphs", 0, "opset")],
)
def test_manifest_booleans_in_integer_fields_are_refused(export_copy, path):
    def change(d):
        node = d
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = True

    _edit_manifest(export_copy, change)
    with pytest.raises(ManifestError, match="expected integer, got bool"):
        read_manifest(export_copy)


# ---- 5. one-line named errors where tracebacks were ---------------------------------------------------------------
@pytest.mark.parametrize("damage", ["empty", "truncated", "garbage"])
def test_a_damaged_graph_with_its_sha256_updated_is_a_manifest_error(export_copy, damage):
    f = export_copy / "slice_head.onnx"
    data = f.read_bytes()
    f.write_bytes({"empty": b"", "truncated": data[: len(data) // 3], "garbage": os.urandom(4096)}[damage])
    _edit_manifest(export_copy, lambda d: [g.update(sha256=sha256_file(f)) for g in d["graphs"] if g["file"] == f.name])
    with pytest.raises(ManifestError, match=r"slice_head.onnx: (onnxruntime cannot load this graph|not an ONNX model)"):
        StreamingDetector(export_copy)


def test_a_manifest_nested_100k_levels_deep_is_a_manifest_error(export_copy):
    (export_copy / "manifest.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ManifestError, match="nests deeper than"):
        read_manifest(export_copy)
    (export_copy / "manifest.json").write_text(json.dumps({"source": json.loads("[" * 40 + "]" * 40)}))  # parses, too deep
    with pytest.raises(ManifestError, match="nests deeper than 32"):
        read_manifest(export_copy)


def test_a_huge_manifest_is_refused_before_parsing(export_copy):
    with open(export_copy / "manifest.json", "w") as f:
        f.write('{"pad": "' + "x" * (17 << 20) + '"}')
    with pytest.raises(ManifestError, match="larger than 16 MiB"):
        read_manifest(export_copy)


def test_max_points_per_pillar_that_disagrees_with_the_graph_fails_at_load(export_copy):
    _edit_manifest(export_copy, lambda d: d["preset"]["pillars"].update(max_points_per_pillar=16))
    with pytest.raises(ManifestError, match=r"slice_head.onnx .*'pillar_features' has dimension 1 = 8 in the graph"):
        StreamingDetector(export_copy)


def test_a_binary_calibration_file_is_a_calibration_error(tiny_export, tmp_path):
    bad = tmp_path / "calibration.json"
    bad.write_bytes(bytes(range(256)) * 8)
    det = StreamingDetector(tiny_export)
    with pytest.raises(CalibrationError, match="not UTF-8 text"):
        det.set_calibration(bad)
    result = CliRunner().invoke(calib_main, ["lut", "--calibration", str(bad), "--export-dir", str(tiny_export)])
    assert result.exit_code != 0 and "not UTF-8 text" in result.output


def _entry(code: str, env: dict | None = None, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, **(env or {})}, timeout=120, **kw)  # fmt: skip


@pytest.mark.parametrize("tool, argv", [("export", ["--help"]), ("bench", ["--flops-only"])])
def test_a_torch_tool_without_torch_is_one_line(tool, argv):
    """streamdet-export needs torch at import, streamdet-bench only when it measures: the same one-line hint, never a
    traceback."""
    proc = _entry(
        f"""
        import sys
        sys.modules["torch"] = None  # as in the torch-free vehicle install
        sys.argv = ["streamdet-{tool}", *{argv!r}]
        from streamdet.cli_utils import {tool}_main
        {tool}_main()
        """
    )
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith(f"streamdet-{tool}: error: needs the Python package 'torch'")
    assert "pip install 'streamdet[export]' (from a checkout: pip install '.[export]'" in proc.stderr


def test_ctrl_c_during_start_up_exits_130_without_traceback(tmp_path):
    slow = tmp_path / "slow_import_cli.py"
    slow.write_text("import time\nprint('importing', flush=True)\ntime.sleep(60)\nimport click\nmain = click.Command('x')\n")
    proc = subprocess.Popen(
        # A shell starts background jobs with SIGINT ignored and Python keeps an inherited SIG_IGN: restore Python's
        # own handler, as a terminal-started command has it, so the test does not depend on how pytest was started.
        [sys.executable, "-c", "import signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
         "from streamdet.cli_utils import run_edge; raise SystemExit(run_edge('slow_import_cli', 'streamdet-x'))"],
        cwd=ROOT, env={**os.environ, "PYTHONPATH": str(tmp_path)}, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert proc.stdout.readline().strip() == "importing"  # Ctrl-C while the command's module loads (torch, in real life)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err == "streamdet-x: interrupted\n"


@pytest.mark.parametrize("missing, extra, hinted", [("torch", "export", True), ("torch._C", "export", True),
                                                    ("mcap", "ros", True), ("somelib", "export", False),
                                                    ("torch", None, False)])  # fmt: skip
def test_a_late_missing_module_is_the_extras_hint_only_where_the_extra_installs_it(tmp_path, monkeypatch, capsys,
                                                                                   missing, extra, hinted):
    """A module missing while a command runs gets its extra's one-line hint where that extra installs it; any other
    is a bug (its traceback), which installing an extra would not mend."""
    from streamdet.cli_utils import run_edge

    module = f"late_import_cli_{missing.replace('.', '_')}_{extra}"  # one module per case: imported modules stay cached
    (tmp_path / f"{module}.py").write_text(
        "import click\n"
        "@click.command()\n"
        "def main():\n"
        f"    raise ModuleNotFoundError('no module', name={missing!r})\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    if not hinted:
        with pytest.raises(ModuleNotFoundError):
            run_edge(module, "streamdet-x", extra=extra, args=[])
        return
    assert run_edge(module, "streamdet-x", extra=extra, args=[]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"streamdet-x: error: needs the Python package {missing!r}") and err.count("\n") == 1
    assert f"pip install 'streamdet[{extra}]'" in err and ("torch==2.13.0" in err) == (extra == "export")
