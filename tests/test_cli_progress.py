"""streamdet.progress: click's bar on a terminal, timed plain lines in a log, a pipe or CI."""

from __future__ import annotations

import io

import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from streamdet.data.synth_cli import main as synth_main
from streamdet.progress import LineProgress, counted, progressbar


class Clock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def lines(stream: io.StringIO) -> list[str]:
    return stream.getvalue().splitlines()


def test_a_terminal_gets_clicks_bar():
    bar = progressbar(length=3, label="x", file=Terminal())
    assert not isinstance(bar, LineProgress)
    with bar:
        bar.update(3)


def test_a_log_gets_plain_lines_on_stderr_unless_told(capsys):
    stream = io.StringIO()
    with progressbar(length=3, label="x", file=stream) as bar:
        assert isinstance(bar, LineProgress)
    assert lines(stream) == ["x (3 steps)", "x: 0/3 done in 0 s"]
    with progressbar(length=3, label="y"):
        pass
    out, err = capsys.readouterr()
    assert out == "" and err.splitlines()[0] == "y (3 steps)"  # progress is not a result


def test_lines_at_start_per_interval_and_at_the_end():
    clock, out = Clock(), io.StringIO()
    with progressbar(length=120, label="simulating 3 scene(s)", file=out, interval_s=10, clock=clock) as bar:
        assert lines(out) == ["simulating 3 scene(s) (120 steps)"]
        clock.t += 5
        bar.update(10)  # before the interval: no line
        assert len(lines(out)) == 1
        clock.t += 7
        bar.update(30)
        assert lines(out)[-1] == "simulating 3 scene(s): 40/120 (33 %), 12 s, about 24 s left"
        clock.t += 3
        bar.update(1)  # 3 s after the last line: none
        assert len(lines(out)) == 2
        clock.t += 3600
        bar.update(79)
    assert lines(out)[-1] == "simulating 3 scene(s): 120/120 done in 1 h 00 min"
    assert len(lines(out)) == 4


def test_iteration_counts_each_item_and_shows_it():
    clock, out = Clock(), io.StringIO()
    seen = []
    with progressbar(["a", "b", "c"], label="subsets", item_show_func=lambda s: s and f"now {s}", file=out,
                     interval_s=1, clock=clock) as bar:  # fmt: skip
        for item in bar:
            seen.append(item)
            clock.t += 61
    assert seen == ["a", "b", "c"] and bar.pos == 3
    assert lines(out)[1] == "subsets: 1/3 (33 %), 1 min 01 s, about 2 min 02 s left, now a"
    assert lines(out)[-1] == "subsets: 3/3 done in 3 min 03 s"


def test_a_length_set_later_and_a_generator_of_unknown_length():
    clock, out = Clock(), io.StringIO()
    with progressbar(length=1, label="detecting", file=out, interval_s=1, clock=clock) as bar:
        bar.length = 600  # the sample count is known once the dataset is open
        clock.t += 2
        bar.update(300)
    assert lines(out)[1].startswith("detecting: 300/600 (50 %), 2 s, about 2 s left")
    out = io.StringIO()
    with progressbar((i for i in range(4)), label="gen", file=out, interval_s=1, clock=clock) as bar:
        for _ in bar:
            clock.t += 1
    assert lines(out) == ["gen", "gen: 1, 1 s", "gen: 2, 2 s", "gen: 3, 3 s", "gen: 4, 4 s", "gen: 4 done in 4 s"]


def test_a_count_alone_and_an_empty_loop():
    clock, out = Clock(), io.StringIO()
    with LineProgress(label="sweeps detected", write=lambda line: out.write(line + "\n"), interval_s=1, clock=clock) as counter:
        clock.t += 1
        counter.update(2)
        with pytest.raises(TypeError, match="nothing to iterate"):
            next(iter(counter))
    assert lines(out) == ["sweeps detected", "sweeps detected: 2, 1 s", "sweeps detected: 2 done in 1 s"]
    out = io.StringIO()
    with progressbar(range(0), label="none", file=out, clock=clock) as bar:
        assert list(bar) == []
    assert lines(out) == ["none (0 steps)", "none: 0/0 done in 0 s"]


def test_counted_starts_with_the_first_report():
    clock, written = Clock(), []
    with counted("  samples read", written.append, interval_s=1, clock=clock):
        pass  # a cache hit: nothing read, nothing said
    assert written == []
    with counted("  samples read", written.append, interval_s=1, clock=clock) as progress:
        clock.t += 30  # opening the dataset is not reading it
        progress(1, 4)
        clock.t += 1
        progress(2, 4)
        progress(4, 4)
    assert written == ["  samples read (4 steps)", "  samples read: 2/4 (50 %), 1 s, about 1 s left",
                       "  samples read: 4/4 done in 1 s"]  # fmt: skip
    written.clear()
    with pytest.raises(OSError):
        with counted("sweeps", written.append, clock=clock) as progress:
            progress(1)
            raise OSError("truncated bag")
    assert written == ["sweeps"]


def test_counted_without_write_follows_the_stream():
    term = Terminal()
    with pytest.raises(ValueError):
        with counted("slices", file=term) as progress:
            progress(1, 3)
            raise ValueError("bad split")
    assert "slices  [####" in term.getvalue() and term.getvalue().endswith("\n")  # click's bar, its line ended
    log, clock = io.StringIO(), Clock()
    with counted("slices", file=log, clock=clock) as progress:
        progress(1, 3)
        progress(3, 3)
    assert lines(log) == ["slices (3 steps)", "slices: 3/3 done in 0 s"]
    log = io.StringIO()
    with counted("sweeps", file=log, clock=clock) as progress:  # no total: lines (click's bar needs one)
        progress(5)
    assert lines(log) == ["sweeps", "sweeps: 5 done in 0 s"]


def test_an_error_writes_no_end_line():
    out = io.StringIO()
    with pytest.raises(KeyError):
        with progressbar(length=5, label="x", file=out) as bar:
            bar.update(1)
            raise KeyError("bad row")
    assert lines(out) == ["x (5 steps)"]


def test_malformed_use_is_refused():
    with pytest.raises(ValueError, match="interval_s must be > 0 seconds, got 0"):
        progressbar(length=1, label="x", file=io.StringIO(), interval_s=0)
    with pytest.raises(ValueError, match="nan"):
        progressbar(length=1, label="x", file=io.StringIO(), interval_s=float("nan"))
    with pytest.raises(RuntimeError, match="inside its `with` block"):
        next(iter(progressbar(range(2), label="x", file=io.StringIO())))

    class Closed(io.StringIO):
        def isatty(self):
            raise ValueError("I/O operation on closed file")

    assert isinstance(progressbar(length=1, label="x", file=Closed()), LineProgress)


@settings(max_examples=60, deadline=None)
@given(steps=st.lists(st.tuples(st.integers(0, 50), st.floats(0, 30)), max_size=40), interval=st.floats(0.5, 20))
def test_lines_are_rate_limited_and_the_count_is_exact(steps, interval):
    clock, out = Clock(), io.StringIO()
    total = sum(n for n, _ in steps)
    with progressbar(length=total, label="p", file=out, interval_s=interval, clock=clock) as bar:
        for n, dt in steps:
            clock.t += dt
            bar.update(n)
    elapsed = sum(dt for _, dt in steps)
    middle = lines(out)[1:-1]
    assert len(middle) <= elapsed / interval + 1e-9
    assert lines(out)[-1].startswith(f"p: {total}/{total} done in ")
    assert all(line.startswith("p: ") and "%" in line for line in middle)


def test_a_cli_run_under_a_pipe_ends_with_a_done_line(tmp_path):
    # CliRunner's streams are not terminals: click's bar printed its label alone here before
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(tmp_path / "gen"), "--scenes", "1",
                                             "--samples-per-scene", "2", "--resolution", "32x18"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "simulating 1 scene(s) (2 steps)" in result.stderr
    assert "simulating 1 scene(s): 2/2 done in " in result.stderr
    assert "simulating" not in result.stdout  # progress is not a result


def test_a_count_known_only_later_opens_with_it(tiny_synth_data, tmp_path):
    """streamdet-bag export learns its message count from the dataset: its first line said "(1 steps)" (a placeholder
    length), then counted to 150."""
    from streamdet.bag.cli import main as bag_main

    result = CliRunner().invoke(bag_main, ["export", "--data", str(tiny_synth_data), "--out", str(tmp_path / "d.mcap")])
    assert result.exit_code == 0, result.output
    progress = [line for line in result.stderr.splitlines() if line.startswith("writing ")]
    total = int(progress[0].rsplit("(", 1)[1].split()[0])
    assert total > 1 and f": {total}/{total} done in " in progress[-1]
