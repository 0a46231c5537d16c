"""``streamdet-bench``: per-module cost of the detector. For now only the MAC count (``--flops-only``)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from streamdet.models.presets import get_preset, preset_names


def parse_resolution(ctx: click.Context | None, param: click.Parameter | None, value: str | None) -> tuple[int, int] | None:
    """'800x450' -> (800, 450)."""
    if value is None:
        return None
    parts = value.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise click.BadParameter(f"expected WIDTHxHEIGHT in pixels like 800x450, got {value!r}", ctx=ctx, param=param)
    w, h = (int(p) for p in parts)
    if w < 1 or h < 1:
        raise click.BadParameter(f"width and height must be positive, got {value!r}", ctx=ctx, param=param)
    return w, h


@click.command()
@click.option("--flops-only", is_flag=True, help="Only count multiply-accumulates (GMAC) per module; time nothing.")
@click.option(
    "--preset",
    type=click.Choice(preset_names()),
    default="paper",
    show_default=True,
    help="Model preset to measure.",
)
@click.option(
    "--resolution",
    callback=parse_resolution,
    metavar="WxH",
    help="Image size for the image-encoding row, e.g. 800x450 (default: the paper's 1600x900, 1200x675 and 800x450).",
)
@click.option(
    "--json",
    "json_path",
    type=click.Path(dir_okay=False, path_type=Path),
    help='Also write the rows as JSON {"rows": [{"module", "gmac", "paper_gmac"}, ...]} to this file.',
)
def main(flops_only: bool, preset: str, resolution: tuple[int, int] | None, json_path: Path | None) -> None:
    """Report the cost of each module of the streaming detector (the paper's Table 3)."""
    if not flops_only:
        raise click.ClickException("timing is not available yet; run with --flops-only for the GMAC report")
    from streamdet.benchmarks.flops_report import PAPER_RESOLUTIONS, format_rows, gmac_rows  # torch import: only when needed

    rows = gmac_rows(get_preset(preset), [resolution] if resolution else PAPER_RESOLUTIONS)
    click.echo(format_rows(preset, rows))
    if json_path is not None:
        doc = {
            "preset": preset,
            "unit": "GMAC (1e9 multiply-accumulates; FLOPs = 2 x MACs)",
            "rows": [r.to_dict() for r in rows],
        }
        try:
            json_path.write_text(json.dumps(doc, indent=2) + "\n")
        except OSError as e:
            raise click.ClickException(f"cannot write --json {json_path}: {e.strerror}") from None
