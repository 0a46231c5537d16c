"""The CLIs' shared output checks (streamdet.cli_utils, toplevel/cli_utils.py): two outputs that are one file, and a file output whose
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


def test_an_output_that_is_a_hard_link_is_refused(tmp_path):
    """``ln ds/splits.json out.json; --json out.json`` would write through to the dataset's file."""
    from streamdet.cli_utils import refuse_output_over_inputs

    data = tmp_path / "ds"
    data.mkdir()
    (data / "splits.json").write_text("{}")
    link = tmp_path / "out.json"
    link.hardlink_to(data / "splits.json")
    with pytest.raises(click.BadParameter, match="is a hard link of another file"):
        refuse_output_over_inputs(link, "--json", [("--data", data)])
    with pytest.raises(click.BadParameter, match="is a hard link"):
        refuse_output_over_inputs(link, "--json", [])  # whatever the inputs: the other name may be anyone's
    (tmp_path / "plain.json").write_text("{}")
    refuse_output_over_inputs(tmp_path / "plain.json", "--json", [("--data", data)])  # an ordinary file is replaced


def test_an_input_folder_reached_under_another_name_is_found(tmp_path):
    """A bind mount or a case-insensitive file system spells an input folder otherwise: the folders above the output
    are compared by identity (here a symlinked parent stands in for another spelling)."""
    from streamdet.cli_utils import refuse_output_over_inputs

    data = tmp_path / "ds"
    (data / "sub").mkdir(parents=True)
    alias = tmp_path / "alias"
    alias.symlink_to(data, target_is_directory=True)
    with pytest.raises(click.BadParameter, match="lies inside the input --data"):
        refuse_output_over_inputs(alias / "sub" / "x.json", "--json", [("--data", data)])


@pytest.mark.skipif(not hasattr(__import__("os"), "mkfifo"), reason="named pipes are POSIX")
def test_not_a_file_names_a_fifo_and_a_missing_file(tmp_path):
    import os

    from streamdet.cli_utils import not_a_file

    os.mkfifo(tmp_path / "fifo")
    assert not_a_file(tmp_path / "fifo").startswith("is not a regular file")
    assert not_a_file(tmp_path).startswith("is not a regular file")
    assert not_a_file(tmp_path / "missing") == "does not exist"
    (tmp_path / "dangling").symlink_to(tmp_path / "missing")
    assert not_a_file(tmp_path / "dangling") == "does not exist"


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs a folder that takes no new file (Linux /proc)")
def test_check_output_parent_finds_a_folder_that_takes_no_file():
    with pytest.raises(click.BadParameter, match="cannot write into the folder of '/proc/x.json'"):
        check_output_parent(Path("/proc/x.json"), "--json")


def test_check_output_parent_leaves_no_probe_behind(tmp_path):
    check_output_parent(tmp_path / "x.json", "--json")
    assert list(tmp_path.iterdir()) == []


def test_an_output_that_is_no_regular_file_is_refused_before_any_work(tmp_path):
    """A FIFO made writing hang for ever after the whole run; a link to a device went elsewhere."""
    import os

    fifo = tmp_path / "out.json"
    os.mkfifo(fifo)
    (tmp_path / "dev.json").symlink_to("/dev/null")
    (tmp_path / "loop1").symlink_to(tmp_path / "loop2")
    (tmp_path / "loop2").symlink_to(tmp_path / "loop1")
    (tmp_path / "dangling.json").symlink_to(tmp_path / "gone" / "x.json")
    for bad, said in ((fifo, "not a regular file"), (tmp_path / "dev.json", "not a regular file"),
                      (tmp_path / "loop1", "broken link or a link loop"), (tmp_path / "dangling.json", "broken link")):  # fmt: skip
        with pytest.raises(click.BadParameter, match=said) as info:
            check_output_parent(bad, "--json")
        assert str(bad) in str(info.value.message)
    (tmp_path / "target.json").write_text("{}")
    (tmp_path / "link.json").symlink_to(tmp_path / "target.json")
    check_output_parent(tmp_path / "link.json", "--json")  # a link to a regular file is a file to write


@pytest.mark.parametrize("bad", ["", ".", "..", "../tables", "/etc", "a/b", "a\\b", "v\x00", "v" * 256])
def test_a_table_version_is_one_folder_name_everywhere(tmp_path, bad):
    from click.testing import CliRunner

    from streamdet.bag.cli import main as bag_main
    from streamdet.core.table_version import table_version_problem
    from streamdet.data.nuscenes import NuScenesReader
    from streamdet.replay.cli import main as replay_main
    from streamdet.studies.cli import main as study_main

    assert table_version_problem(bad) is not None and table_version_problem("v1.0-mini") is None
    with pytest.raises(ValueError, match="version must be"):
        NuScenesReader(tmp_path, bad)
    if "\x00" in bad:
        return  # not an argv string
    for main, args in ((replay_main, ["--data", str(tmp_path)]), (study_main, ["slices", "--data", str(tmp_path)]),
                       (bag_main, ["export", "--data", str(tmp_path), "--out", str(tmp_path / "b.mcap")])):  # fmt: skip
        result = CliRunner().invoke(main, [*args, "--version", bad])
        assert result.exit_code == 2 and "--version" in result.output and "Traceback" not in result.output, result.output


def test_a_linked_table_folder_is_an_input_too(tmp_path):
    from streamdet.cli_utils import dataset_inputs, refuse_output_over_inputs

    tables = tmp_path / "elsewhere" / "tables"
    tables.mkdir(parents=True)
    (tables / "scene.json").write_text("[]")
    data = tmp_path / "data"
    data.mkdir()
    (data / "v1.0-synth").symlink_to(tables)
    inputs = dataset_inputs(data)
    assert [p for _, p in inputs] == [data, data / "v1.0-synth"]
    for out in (tables / "scene.json", tables / "new.json"):  # outside --data, inside the tables it reads
        with pytest.raises(click.BadParameter, match="v1.0-synth"):
            refuse_output_over_inputs(out, "--json", inputs)
    refuse_output_over_inputs(tmp_path / "elsewhere" / "ok.json", "--json", inputs)
    assert dataset_inputs(tmp_path / "missing") == [("--data", tmp_path / "missing")]


def test_a_symlink_loop_is_an_input_error_in_one_line():
    from streamdet.cli_utils import describe_error, is_input_error

    e = RuntimeError("Symlink loop from '/tmp/x/loop1'")
    assert is_input_error(e) and describe_error(e) == "'/tmp/x/loop1': a symlink loop (a link that leads back to itself)"
    assert not is_input_error(RuntimeError("something else"))


def test_eval_files_mode_refuses_a_fifo_json_before_scoring(tmp_path):
    """The files mode scored, printed, then blocked for ever opening the FIFO."""
    import os

    from click.testing import CliRunner

    from streamdet.evaluation.cli import main as eval_main

    os.mkfifo(tmp_path / "out.json")
    (tmp_path / "gt.json").write_text("{}")
    (tmp_path / "results.json").write_text("{}")
    res = CliRunner().invoke(eval_main, ["--gt", str(tmp_path / "gt.json"), "--results", str(tmp_path / "results.json"),
                                         "--json", str(tmp_path / "out.json")])  # fmt: skip
    assert res.exit_code == 2 and "not a regular file" in res.output


def test_a_folder_output_that_is_a_broken_link_or_a_loop_is_refused_before_any_work(tmp_path):
    """`streamdet-replay --out loop1` and `streamdet-synth generate --out loop1` said "File exists" after the work."""
    from click.testing import CliRunner

    from streamdet.cli_utils import check_folder_creatable
    from streamdet.data.synth_cli import main as synth_main

    (tmp_path / "loop1").symlink_to(tmp_path / "loop2")
    (tmp_path / "loop2").symlink_to(tmp_path / "loop1")
    (tmp_path / "dangling").symlink_to(tmp_path / "gone")
    for bad in ("loop1", "dangling"):
        with pytest.raises(click.BadParameter, match="broken link or a link loop"):
            check_folder_creatable(tmp_path / bad / "sub", "--out")
    res = CliRunner().invoke(synth_main, ["generate", "--out", str(tmp_path / "loop1"), "--scenes", "1"])
    assert res.exit_code == 2 and "broken link or a link loop" in res.output and "simulating" not in res.output
    # synth stats measured DATA_DIR first and only then found --reference missing
    res = CliRunner().invoke(synth_main, ["stats", str(tmp_path), "--reference", str(tmp_path / "loop1")])
    assert res.exit_code == 2 and "is no dataset folder" in res.output and "measuring" not in res.output
