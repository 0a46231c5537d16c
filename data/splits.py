"""``splits.json``: which scenes of a nuScenes-format dataset form each split, read in one place.

The file sits at the dataset root (``streamdet-synth`` writes it) and maps a split name to a list of scene names::

    {"train": ["scene-0000", ...], "val": ["scene-0007", ...]}
"""

from __future__ import annotations

from pathlib import Path

from streamdet.core.json_input import read_json, short_repr
from streamdet.data.nuscenes import NuScenesReader

SPLITS_FILE = "splits.json"


class SplitsFileMissing(FileNotFoundError, ValueError):
    """The dataset has no splits.json (a FileNotFoundError for file readers, a ValueError for input checks)."""


MAX_SPLITS_BYTES = 64 << 20  # nuScenes trainval's 850 scene names are 20 kB: a larger file is not a splits.json


def split_scenes(root: str | Path, split: str) -> tuple[str, ...]:
    """Scene names of ``split`` from ``root/splits.json``; a missing or malformed file or split raises naming the
    file (ValueError; SplitsFileMissing where there is no file)."""
    path = Path(root) / SPLITS_FILE
    if not path.is_file():
        if path.exists():  # a FIFO, a device or a folder: never opened
            raise ValueError(f"{path} is not a regular file (a FIFO, a device or a folder?); it must name the scenes of split {split!r}")
        raise SplitsFileMissing(f"{path} not found; it must name the scenes of split {split!r}")
    splits = read_json(path, "splits file", MAX_SPLITS_BYTES)
    if not isinstance(splits, dict):
        raise ValueError(f"{path} must map split names to lists of scene names, got a JSON {type(splits).__name__}")
    if split not in splits:
        raise ValueError(f"{path} has no split {split!r}; it has {sorted(splits)[:20]}")
    if not isinstance(splits[split], list):
        raise ValueError(f"{path}: split {split!r} must be a list of scene names, got {short_repr(splits[split])}")
    scenes = splits[split]
    bad = next((s for s in scenes if type(s) is not str), None)
    if bad is not None:
        raise ValueError(f"{path}: split {split!r} must list scene names (strings), got {short_repr(bad)}")
    return tuple(scenes)


def has_split(root: str | Path, split: str) -> bool:
    """Whether ``root/splits.json`` exists, parses and lists scenes for ``split``. Every defect reads as False, a
    broken file as a missing one: a caller that must tell them apart (and refuse a broken one) calls
    ``split_scenes`` and catches ``SplitsFileMissing`` alone."""
    try:
        split_scenes(root, split)
    except (OSError, ValueError):  # json.JSONDecodeError is a ValueError
        return False
    return True


def split_sample_tokens(reader: NuScenesReader, root: str | Path, split: str | None) -> list[str]:
    """Sample tokens (table order) of the split's scenes, or every sample when ``split`` is None."""
    tokens = reader.sample_tokens
    if split is None:
        return tokens
    scenes = set(split_scenes(root, split))
    chosen = [t for t in tokens if reader.scene_name(t) in scenes]
    if not chosen:
        known = {reader.scene_name(t) for t in tokens}
        unknown = sorted(scenes - known)[:5]
        why = f": its scenes {unknown} are not in the tables" if unknown else ""
        raise ValueError(f"split {split!r} of {root} holds no samples{why}")
    return chosen
