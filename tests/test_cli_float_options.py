"""Every float-range option of every tool (and of the benchmark scripts with a click main) refuses "nan", which
click's FloatRange lets through its bounds (every comparison with NaN is false): streamdet.cli_utils.FiniteFloatRange."""

from __future__ import annotations

import importlib

import click
import pytest
from click.testing import CliRunner

from streamdet.cli_utils import FiniteFloatRange

TOOLS = ("streamdet.export.cli", "streamdet.benchmarks.cli", "streamdet.evaluation.run_cli", "streamdet.runtime_ort.calib_cli",
         "streamdet.data.synth_cli", "streamdet.training.cli", "streamdet.evaluation.cli", "streamdet.studies.cli",
         "streamdet.training.image_pretrain_cli", "streamdet.bag.cli", "streamdet.replay.cli", "streamdet.replay.cost",
         "streamdet.benchmarks.lane_sim", "streamdet.benchmarks.schedule_model", "streamdet.benchmarks.lut_coverage")  # fmt: skip


def _float_ranges(command: click.Command, path: str):
    for param in command.params:
        if isinstance(param.type, click.FloatRange) or param.type is click.FLOAT:  # type=float: no bounds, NaN too
            yield f"{path} {param.opts[0]}", param.type
    if isinstance(command, click.Group):
        for name, sub in command.commands.items():
            yield from _float_ranges(sub, f"{path} {name}")


def _options():
    found = []
    for module in TOOLS:
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as e:  # an optional extra (ros) not installed
            pytest.skip(f"{module}: {e.name} not installed")
        command = getattr(mod, "main", None) or getattr(mod, "cli", None)
        if isinstance(command, click.Command):
            found += list(_float_ranges(command, module))
    return found


def test_every_float_range_option_is_finite():
    options = _options()
    assert len(options) >= 20  # the search found the tools' options
    plain = [name for name, kind in options if not isinstance(kind, FiniteFloatRange)]
    assert plain == []


@pytest.mark.parametrize("text", ["nan", "NaN", "-nan"])
def test_nan_is_refused_with_the_options_name(text):
    @click.command()
    @click.option("--rate-hz", type=FiniteFloatRange(0, 100, min_open=True))
    def cmd(rate_hz):
        click.echo(repr(rate_hz))

    result = CliRunner().invoke(cmd, ["--rate-hz", text])
    assert result.exit_code == 2 and "--rate-hz" in result.output and "is not a number" in result.output
    assert CliRunner().invoke(cmd, ["--rate-hz", "12.5"]).output == "12.5\n"
    assert CliRunner().invoke(cmd, ["--rate-hz", "inf"]).exit_code == 2  # FloatRange's own bounds still hold
