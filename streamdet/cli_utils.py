"""Option parsing shared by the command-line tools (click and streamdet.core only: no torch)."""

from __future__ import annotations

import click

from streamdet.core.constants import PRECISIONS

# Every tool that takes an image size spells it the same way.
RESOLUTION_HELP = "WIDTHxHEIGHT in pixels, such as 800x450"


def parse_resolution(text: str, *, min_px: int = 1, max_px: int | None = None, multiple_of: int = 1) -> tuple[int, int]:
    """'800x450' -> (800, 450); raises click.BadParameter quoting the bad value.

    ``multiple_of`` is the stride the image size must divide by (the ResNet stem's 2 for tools that export);
    ``min_px``/``max_px`` bound each side (the renderer's sane range for the synthetic world).
    """
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise click.BadParameter(f"expected {RESOLUTION_HELP}, got {text!r}")
    width, height = (int(p) for p in parts)
    if width <= 0 or height <= 0:
        raise click.BadParameter(f"width and height must be positive, got {text!r}")
    if width < min_px or height < min_px or (max_px is not None and (width > max_px or height > max_px)):
        raise click.BadParameter(f"width and height must be {min_px}..{max_px} pixels, got {text!r}")
    if width % multiple_of or height % multiple_of:
        raise click.BadParameter(
            f"{text!r}: width and height must be positive and even (the ResNet stem has stride {multiple_of}); "
            "they need not be multiples of 4, 800x450 works"
        )
    return width, height


def resolution_callback(*, min_px: int = 1, max_px: int | None = None, multiple_of: int = 1):
    """A click callback for a WxH option; ``multiple=True`` options get a tuple of sizes, None stays None."""

    def callback(ctx: click.Context | None, param: click.Parameter | None, value):
        if value is None:
            return None
        if isinstance(value, tuple):
            return tuple(parse_resolution(v, min_px=min_px, max_px=max_px, multiple_of=multiple_of) for v in value)
        return parse_resolution(value, min_px=min_px, max_px=max_px, multiple_of=multiple_of)

    return callback


# The graph precisions an export can hold.
PRECISION_CHOICES = PRECISIONS


def image_precision_option(flag: str = "--image-precision", dest: str = "image_precision"):
    """The option that runs the image lane (encoder + lifter) in another precision than the slices."""
    return click.option(
        flag,
        dest,
        type=click.Choice(PRECISION_CHOICES),
        default=None,
        help="Run the image lane's graphs (image encoder + lifter) in this precision instead; the export must hold "
        "them. On x86 CPUs int8 here with fp32 slices halves the image lane's time (fresher camera features) "
        "and keeps the slice graph exact. Default: the same precision as the slices.",
    )
