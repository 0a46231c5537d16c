"""The CLIs' shared output checks (streamdet/cli_utils.py): two outputs that are one file, and a file output whose
folder is missing, refused before any work."""

from __future__ import annotations

from pathlib import Path

import click
import pytest

from streamdet.cli_utils import check_output_parent, refuse_same_outputs


def test_refuse_same_outputs(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.png"
    refuse_same_outputs([("--json", a), ("--plot", b), ("--profile", None)])
    for twin in (a, tmp_path / "." / "a.json"):
        with pytest.raises(click.BadParameter, match="is also the --json file") as info:
            refuse_same_outputs([("--json", a), ("--plot", twin)])
        assert info.value.param_hint == "--plot"
    a.write_text("{}")
    (tmp_path / "link.json").symlink_to(a)
    (tmp_path / "hard.json").hardlink_to(a)
    for twin in ("link.json", "hard.json"):
        with pytest.raises(click.BadParameter, match="is also the --json file"):
            refuse_same_outputs([("--json", a), ("--plot", tmp_path / twin)])


def test_check_output_parent(tmp_path):
    for good in (tmp_path / "x.json", Path("relative.json"), None):
        check_output_parent(good, "--json")
    with pytest.raises(click.BadParameter, match="is a folder"):
        check_output_parent(tmp_path, "--json")
    for bad in (tmp_path / "missing" / "x.json", Path("/proc/no/such/x.json")):
        with pytest.raises(click.BadParameter, match="does not exist"):
            check_output_parent(bad, "--json")
    (tmp_path / "file").write_text("")
    with pytest.raises(click.BadParameter, match="not a folder"):
        check_output_parent(tmp_path / "file" / "x.json", "--json")


def test_check_plot_format():
    from streamdet.cli_utils import check_plot_format

    for good in (Path("a.png"), Path("a.PDF"), Path("a.svg"), Path("plot"), None):  # no suffix: matplotlib's PNG
        check_plot_format(good)
    for bad in (Path("a.json"), Path("a.docx")):
        with pytest.raises(click.BadParameter, match=rf"cannot write --plot {bad}: matplotlib has no \{bad.suffix} format"):
            check_plot_format(bad)
