"""The one WxH parser every CLI uses."""

import click
import pytest

from streamdet.cli_utils import parse_resolution, resolution_callback


@pytest.mark.parametrize("text, expected", [("800x450", (800, 450)), ("1200X675", (1200, 675)), ("16x16", (16, 16))])
def test_parse_resolution(text, expected):
    assert parse_resolution(text) == expected


@pytest.mark.parametrize(
    "text, kwargs, message",
    [
        ("800", {}, "expected WIDTHxHEIGHT"),
        ("800x450x3", {}, "expected WIDTHxHEIGHT"),
        ("axb", {}, "expected WIDTHxHEIGHT"),
        ("-800x450", {}, "expected WIDTHxHEIGHT"),
        ("", {}, "expected WIDTHxHEIGHT"),
        ("0x450", {}, "must be positive"),
        ("8x8", {"min_px": 16, "max_px": 4096}, "16..4096"),
        ("5000x450", {"min_px": 16, "max_px": 4096}, "16..4096"),
        ("801x450", {"multiple_of": 2}, "even"),
    ],
)
def test_parse_resolution_rejects_with_the_bad_value(text, kwargs, message):
    with pytest.raises(click.BadParameter, match=message) as info:
        parse_resolution(text, **kwargs)
    assert repr(text) in str(info.value)


def test_callback_passes_none_and_tuples():
    cb = resolution_callback(multiple_of=2)
    assert cb(None, None, None) is None
    assert cb(None, None, ("800x450", "1600x900")) == ((800, 450), (1600, 900))
