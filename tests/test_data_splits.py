"""data/splits.py: the one reader of splits.json, on the synthetic dataset and on broken files."""

from __future__ import annotations

import json
import shutil

import pytest

from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.splits import SplitsFileMissing, has_split, split_sample_tokens, split_scenes


def test_split_tokens_follow_the_scenes(tiny_synth_data):
    reader = NuScenesReader(tiny_synth_data, "v1.0-synth")
    splits = json.loads((tiny_synth_data / "splits.json").read_text())
    for name, scenes in splits.items():
        assert split_scenes(tiny_synth_data, name) == tuple(scenes) and has_split(tiny_synth_data, name)
        if scenes:
            want = [t for t in reader.sample_tokens if reader.scene_name(t) in set(scenes)]  # naive: filter by scene
            assert split_sample_tokens(reader, tiny_synth_data, name) == want
    assert split_sample_tokens(reader, tiny_synth_data, None) == reader.sample_tokens


@pytest.mark.parametrize(
    "content, match",
    [
        (None, "splits.json not found; it must name the scenes of split 'val'"),
        ("{not json", "Expecting property name"),
        ('["val"]', "must map split names to lists of scene names, got a JSON list"),
        ('{"val": "scene-0"}', r"split 'val' must be a list of scene names, got 'scene-0'"),
        ('{"train": []}', r"has no split 'val'; it has \['train'\]"),
        ('{"val": ["scene-0", 7]}', r"split 'val' must list scene names \(strings\), got 7"),
        ('{"val": [{"name": "scene-0"}]}', r"must list scene names \(strings\), got \{'name'"),
        ('{"val": [1' + "0" * 5000 + "]}", "splits file .*splits.json is not valid JSON"),
        ("[" * 100_000 + "]" * 100_000, "nests too deeply"),
        (b"\xff\xfe{}", "not UTF-8"),
    ],
)
def test_broken_splits_file(tmp_path, content, match):
    if isinstance(content, bytes):
        (tmp_path / "splits.json").write_bytes(content)
    elif content is not None:
        (tmp_path / "splits.json").write_text(content)
    with pytest.raises(ValueError, match=match):
        split_scenes(tmp_path, "val")
    assert not has_split(tmp_path, "val")


def test_missing_file_is_both_a_file_error_and_a_value_error(tmp_path):
    with pytest.raises(SplitsFileMissing) as info:
        split_scenes(tmp_path, "train")
    assert isinstance(info.value, FileNotFoundError) and isinstance(info.value, ValueError)


def test_a_split_without_samples_is_refused(tiny_synth_data, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(tiny_synth_data, root)
    (root / "splits.json").write_text(json.dumps({"val": ["no-such-scene"]}))
    with pytest.raises(ValueError, match="split 'val' of .* holds no samples"):
        split_sample_tokens(NuScenesReader(root, "v1.0-synth"), root, "val")


def test_a_split_of_unknown_scenes_names_them(tmp_path):
    """A typo in a scene name left "holds no samples" with nothing to go on."""
    import json as _json

    from streamdet.data.splits import split_sample_tokens

    (tmp_path / "splits.json").write_text(_json.dumps({"val": ["synth-0-000"]}))
    reader = type("Reader", (), {"sample_tokens": ["t0"], "scene_name": lambda self, t: "synth-0-0000"})()  # NuScenesReader's two reads
    with pytest.raises(ValueError, match=r"holds no samples: its scenes \['synth-0-000'\] are not in the tables"):
        split_sample_tokens(reader, tmp_path, "val")
