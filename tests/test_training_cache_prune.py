"""Stale training caches: a cache rebuilt for changed data removes the one it supersedes, and nothing else (caches of
another split, image size or dataset, caches from before source.json, folders a live process is writing, folders
not named as caches, symlinks)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from streamdet.training.dataset import CACHE_SOURCE_FILE, build_store, prune_stale_caches

SIZE = (128, 72)  # the shared tiny dataset's image size (conftest)


def _cache(parent: Path, name: str, source: dict | None, complete: bool = True) -> Path:
    folder = parent / name
    folder.mkdir(parents=True)
    if source is not None:
        (folder / CACHE_SOURCE_FILE).write_text(json.dumps(source))
    if complete:
        (folder / "meta.json").write_text("{}")
    return folder


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


SOURCE = {"root": "/data/synth", "version": "v1.0-synth", "split": "train", "image_size": [128, 72]}


def test_prune_removes_only_what_the_new_cache_supersedes(tmp_path):
    new = _cache(tmp_path, "train-" + "a" * 16, SOURCE)
    old = _cache(tmp_path, "train-" + "b" * 16, SOURCE)
    keep = [
        _cache(tmp_path, "train-" + "c" * 16, {**SOURCE, "image_size": [256, 144]}),  # another image size
        _cache(tmp_path, "val-" + "d" * 16, {**SOURCE, "split": "val"}),  # another split
        _cache(tmp_path, "train-" + "e" * 16, {**SOURCE, "root": "/data/other"}),  # another dataset
        _cache(tmp_path, "train-" + "f" * 16, None),  # from before source.json: whose it is is unknown
        _cache(tmp_path, "train-" + "0" * 16, SOURCE, complete=False),  # no meta.json: not a finished cache
        _cache(tmp_path, "mine", SOURCE),  # not named as a cache
        _cache(tmp_path, "train-" + "1" * 16 + f".tmp{os.getpid()}", SOURCE, complete=False),  # being written
    ]
    bad_source = _cache(tmp_path, "train-" + "2" * 16, None)
    (bad_source / CACHE_SOURCE_FILE).write_text("[1, 2")  # unreadable: kept
    keep.append(bad_source)
    dead = _cache(tmp_path, "train-" + "3" * 16 + f".tmp{_dead_pid()}", SOURCE, complete=False)  # writer gone
    link = tmp_path / ("train-" + "4" * 16)
    link.symlink_to(old, target_is_directory=True)  # a link is never followed into a removal
    (tmp_path / ("train-" + "5" * 16)).write_text("a file")

    removed = prune_stale_caches(new)

    assert sorted(removed) == sorted([old, dead])
    assert not old.exists() and not dead.exists()
    assert new.is_dir() and all(k.is_dir() for k in keep) and link.is_symlink()
    assert (tmp_path / ("train-" + "5" * 16)).is_file()


def test_prune_without_own_source_removes_nothing(tmp_path):
    new = _cache(tmp_path, "train-" + "a" * 16, None)
    old = _cache(tmp_path, "train-" + "b" * 16, SOURCE)
    assert prune_stale_caches(new) == [] and old.is_dir()


def test_prune_warns_when_it_cannot_remove(tmp_path, monkeypatch):
    new = _cache(tmp_path, "train-" + "a" * 16, SOURCE)
    old = _cache(tmp_path, "train-" + "b" * 16, SOURCE)

    def refuse(path, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(shutil, "rmtree", refuse)  # as for a folder of another user
    with pytest.warns(UserWarning, match="could not remove the stale training cache"):
        assert prune_stale_caches(new) == []
    assert old.is_dir()


def test_rebuilt_cache_replaces_the_stale_one(tiny_train_data, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(tiny_train_data, data)  # the shared dataset is never touched
    cache = tmp_path / "cache"
    first = build_store(data, "train", SIZE, cache_dir=cache)
    no_images = build_store(data, "train", None, cache_dir=cache)  # another source: stays
    (old,) = [p for p in cache.iterdir() if json.loads((p / CACHE_SOURCE_FILE).read_text())["image_size"] == list(SIZE)]

    table = next((data / "v1.0-synth").glob("*.json"))
    os.utime(table, ns=(table.stat().st_atime_ns, table.stat().st_mtime_ns + 10**9))  # the data changed
    said: list[str] = []
    again = build_store(data, "train", SIZE, cache_dir=cache, echo=said.append)

    assert not old.exists()
    assert len(said) == 1 and str(old) in said[0] and "stale training cache" in said[0]
    folders = sorted(p.name for p in cache.iterdir())
    assert len(folders) == 2  # the new cache of the images' source, and the LiDAR-only one
    assert np.array_equal(again.points, first.points) and no_images.images is None
    cached = build_store(data, "train", SIZE, cache_dir=cache, echo=said.append)  # reads the new cache: no pruning
    assert isinstance(cached.points, np.memmap) and len(said) == 1
