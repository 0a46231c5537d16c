"""An export killed with SIGKILL leaves hidden staging folders; the next export into the same place removes them,
and puts back a previous export that the killed one had moved aside."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from streamdet.export.options import ExportError
from streamdet.export.staging import STAGING_MARKER, STAGING_MARKER_TEXT, clean_stale_staging, make_staging_dir

ROOT = Path(__file__).resolve().parents[1]


def _killed_writer(out_dir: Path, also_move_aside: bool) -> int:
    """A process that stages an export as export/staging.py names and marks it (the folder carries the pid and a
    marker naming it; asserted by test_a_killed_exports_partial_folder_is_cleaned_by_the_next and
    test_staging_folders_carry_the_marker), optionally moves the old export aside, and is then killed with SIGKILL.
    Plain Python, so the test does not wait for onnx to import in a second process."""
    code = textwrap.dedent(
        f"""
        import os, sys, tempfile, time
        from pathlib import Path
        out = Path({str(out_dir)!r})
        def mark(folder):
            (folder / {STAGING_MARKER!r}).write_text(f"{STAGING_MARKER_TEXT} {{os.getpid()}}\\n")
        tmp = Path(tempfile.mkdtemp(prefix=f".{{out.name}}.partial-{{os.getpid()}}-", dir=out.parent))
        mark(tmp)
        (tmp / "slice_head.onnx").write_bytes(b"half")
        if {also_move_aside!r}:
            old = Path(tempfile.mkdtemp(prefix=f".{{out.name}}.old-{{os.getpid()}}-", dir=out.parent))
            mark(old)
            os.replace(out, old / "export")  # the first rename of commit_staging_dir; killed before the second
        print("staged", flush=True)
        time.sleep(60)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "staged"
    proc.send_signal(signal.SIGKILL)
    proc.wait(30)
    return proc.pid


def _hidden(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


def test_a_killed_exports_partial_folder_is_cleaned_by_the_next(tmp_path):
    out = tmp_path / "exp"
    _killed_writer(out, also_move_aside=False)
    assert len(_hidden(tmp_path)) == 1  # the hidden partial folder the kill left
    tmp = make_staging_dir(out)
    assert _hidden(tmp_path) == [tmp.name] and f"partial-{os.getpid()}-" in tmp.name


def test_an_export_moved_aside_by_a_killed_commit_is_put_back(tmp_path):
    out = tmp_path / "exp"
    out.mkdir()
    (out / "manifest.json").write_text("{}")
    _killed_writer(out, also_move_aside=True)
    assert not out.exists()
    clean_stale_staging(out)
    assert (out / "manifest.json").read_text() == "{}" and _hidden(tmp_path) == []


def test_folders_of_a_running_export_are_kept(tmp_path):
    out = tmp_path / "exp"
    mine = tmp_path / f".exp.partial-{os.getpid()}-abc"
    mine.mkdir()
    legacy = tmp_path / ".exp.partial-xyz"  # written before pids were in the name: owner unknown, kept
    legacy.mkdir()
    clean_stale_staging(out)
    assert mine.is_dir() and legacy.is_dir()


def _export_like(folder: Path) -> Path:
    """A folder holding what an export holds: a streamdet manifest naming its graphs and LUT, those files, and an
    onnxruntime profile of one graph (DetectorConfig.enable_profiling)."""
    import json

    folder.mkdir()
    manifest = {"preset": {}, "graphs": [{"name": "slice_head", "file": "slice_head.onnx"},
                                        {"name": "slice_head", "file": "slice_head.int8.onnx"}],
                "lut": {"file": "lut.npz"}}  # fmt: skip
    (folder / "manifest.json").write_text(json.dumps(manifest))
    for name in ("slice_head.onnx", "slice_head.int8.onnx", "lut.npz", "slice_head.int8.profile_2026-12-05_08-25-13_754.json"):
        (folder / name).write_bytes(b"x")
    return folder


def test_an_export_with_only_its_own_files_may_be_replaced(tmp_path):
    from streamdet.export.staging import check_replaceable

    check_replaceable(_export_like(tmp_path / "exp"))
    check_replaceable(tmp_path / "absent")
    (tmp_path / "empty").mkdir()
    check_replaceable(tmp_path / "empty")


@pytest.mark.parametrize("extra", ["notes.txt", "calibration.json", "src/", "other.profile_1.json", "lut.npz.bak"])
def test_an_export_holding_other_files_is_refused_and_kept(tmp_path, extra):
    from streamdet.export.staging import check_replaceable

    out = _export_like(tmp_path / "exp")
    (out / extra.rstrip("/")).mkdir() if extra.endswith("/") else (out / extra).write_text("mine")
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(ExportError, match=r"holds a streamdet export and other entries \(" + re.escape(extra)):
        make_staging_dir(out)
    assert sorted(p.name for p in out.iterdir()) == before and _hidden(tmp_path) == []
    with pytest.raises(ExportError):
        check_replaceable(out)


@pytest.mark.parametrize("manifest", ['{"name": "my web app"}', "[]", "not json", '{"graphs": "x", "preset": {}}'])
def test_a_folder_whose_manifest_is_not_streamdets_is_refused(tmp_path, manifest):
    out = tmp_path / "app"
    out.mkdir()
    (out / "manifest.json").write_text(manifest)
    (out / "index.html").write_text("<html>")
    with pytest.raises(ExportError, match="not a streamdet export"):
        make_staging_dir(out)
    assert (out / "index.html").read_text() == "<html>"


def test_export_out_inside_the_calibration_dataset_is_refused(tmp_path):
    from click.testing import CliRunner

    from streamdet.export.cli import main as export_main

    data = tmp_path / "ds"
    data.mkdir()
    res = CliRunner().invoke(export_main, ["--preset", "tiny", "--int8", "--calibration-data", str(data),
                                           "--out", str(data / "exp")])  # fmt: skip
    assert res.exit_code == 2 and "lies inside the input --calibration-data" in res.output
    assert list(data.iterdir()) == []


def test_export_out_through_a_symlink_replaces_its_target_and_keeps_the_link(tmp_path):
    from click.testing import CliRunner

    from streamdet.export.cli import main as export_main

    target = tmp_path / "v1"
    link = tmp_path / "current"
    link.symlink_to(target, target_is_directory=True)  # dangling until the first export
    for _ in range(2):  # made, then replaced
        res = CliRunner().invoke(export_main, ["--preset", "tiny", "--slices", "4", "--out", str(link)])
        assert res.exit_code == 0, res.output
        assert link.is_symlink() and (target / "manifest.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["current", "v1"]
