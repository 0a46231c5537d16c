"""Boxes under evaluation: the devkit's ``EvalBoxes`` of ``DetectionBox`` as one columnar record of arrays.

All coordinates are in the nuScenes *global* frame, as in a results JSON file. Rows are grouped by sample in
the order of ``sample_tokens``, and keep their order inside a sample: this is the order of the devkit's
``EvalBoxes.all``, on which its score-sort tie-breaking and its matching tie-breaking depend.

An entry of a results file (one box) reads::

    {"sample_token": str, "translation": [x, y, z], "size": [w, l, h], "rotation": [w, x, y, z],
     "velocity": [vx, vy], "detection_name": str, "detection_score": float, "attribute_name": str}

Ground truth carries two more keys, as the devkit's DetectionBox does: ``ego_translation`` (box centre minus
the ego position at the sample's LiDAR time, global axes, metres) and ``num_pts`` (LiDAR + radar points
inside the box; -1 = unknown). ``velocity`` may be NaN (or null) where the annotation has none.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import chain

import numpy as np

from streamdet.core.json_input import is_finite_number, short_repr  # noqa: F401 (public here too)
from streamdet.evaluation.config import DetectionConfig

# The devkit's DETECTION_NAMES and ATTRIBUTE_NAMES (nuscenes/eval/detection/constants.py).
DETECTION_NAMES: tuple[str, ...] = DetectionConfig().class_names
ATTRIBUTE_NAMES: tuple[str, ...] = (
    "pedestrian.moving",
    "pedestrian.sitting_lying_down",
    "pedestrian.standing",
    "cycle.with_rider",
    "cycle.without_rider",
    "vehicle.moving",
    "vehicle.parked",
    "vehicle.stopped",
)
_INT64 = (-(1 << 63), 1 << 63)  # num_pts is stored as int64: [min, max)
# What a coordinate may be: a JSON number (numpy's too, from callers in Python). Not a bool, which is an int to Python
# and 1.0 to numpy, nor a string, which numpy's float conversion parses ("5.1", "nan"): both are serializer bugs
# that would score as plausible boxes.
_NUMBER_TYPES = (int, float, np.integer, np.floating)
_NOT_NUMBER_TYPES = (bool, np.bool_)


@dataclass(frozen=True, eq=False)
class EvalBoxes:
    """N boxes over the samples ``sample_tokens`` (a sample may have none), global frame, float64."""

    sample_tokens: tuple[str, ...]
    sample_index: np.ndarray  # (N,) int64 into sample_tokens, non-decreasing
    translation: np.ndarray  # (N, 3) box centre, m
    size: np.ndarray  # (N, 3) w, l, h, m
    rotation: np.ndarray  # (N, 4) quaternion w, x, y, z
    velocity: np.ndarray  # (N, 2) vx, vy, m/s; NaN = unknown
    ego_translation: np.ndarray  # (N, 3) centre minus ego position, m
    num_pts: np.ndarray  # (N,) int64; -1 = unknown (predictions)
    detection_name: np.ndarray  # (N,) str
    detection_score: np.ndarray  # (N,) float64; -1 for ground truth
    attribute_name: np.ndarray  # (N,) str; "" = none

    def __post_init__(self) -> None:
        n = len(self.sample_index)
        shapes = {
            "sample_index": (n,), "translation": (n, 3), "size": (n, 3), "rotation": (n, 4), "velocity": (n, 2),
            "ego_translation": (n, 3), "num_pts": (n,), "detection_name": (n,), "detection_score": (n,),
            "attribute_name": (n,),
        }  # fmt: skip
        for name, shape in shapes.items():
            got = np.shape(getattr(self, name))
            if got != shape:
                raise ValueError(f"EvalBoxes.{name} must have shape {shape}, got {got}")
        if n and (np.any(np.diff(self.sample_index) < 0) or self.sample_index[0] < 0
                  or self.sample_index[-1] >= len(self.sample_tokens)):  # fmt: skip
            raise ValueError("EvalBoxes.sample_index must be non-decreasing indices into sample_tokens")
        if len(set(self.sample_tokens)) != len(self.sample_tokens):
            raise ValueError("EvalBoxes.sample_tokens must be unique")

    def __len__(self) -> int:
        return len(self.sample_index)

    @property
    def ego_dist(self) -> np.ndarray:
        """(N,) xy distance to the ego vehicle, m (the devkit's ``DetectionBox.ego_dist``)."""
        e = self.ego_translation
        return np.sqrt(e[:, 0] ** 2 + e[:, 1] ** 2)

    def select(self, mask: np.ndarray) -> EvalBoxes:
        """The boxes where ``mask`` (bool (N,) or increasing indices) holds, over the same samples."""
        return EvalBoxes(
            sample_tokens=self.sample_tokens,
            **{name: getattr(self, name)[mask] for name in _ARRAY_FIELDS},
        )

    def with_ego_position(self, ego_xyz_by_sample: Mapping[str, Sequence[float]]) -> EvalBoxes:
        """``ego_translation`` = translation - ego position of the box's sample (devkit ``add_center_dist``).

        Boxes of samples missing from ``ego_xyz_by_sample`` keep their ``ego_translation``.
        """
        ego = np.array([ego_xyz_by_sample.get(t, (np.nan,) * 3) for t in self.sample_tokens], dtype=np.float64)
        ego = ego.reshape(len(self.sample_tokens), 3)[self.sample_index]  # (N, 3)
        known = ~np.isnan(ego[:, :1])
        fields = {name: getattr(self, name) for name in _ARRAY_FIELDS}
        fields["ego_translation"] = np.where(known, self.translation - ego, self.ego_translation)
        return EvalBoxes(sample_tokens=self.sample_tokens, **fields)

    # ---- JSON entries ---------------------------------------------------------------------------
    @classmethod
    def from_results(cls, results: Mapping[str, Sequence[Mapping]], source: str = "results") -> EvalBoxes:
        """Parse and validate ``{sample_token: [entry, ...]}``; ``source`` names the input in error messages."""
        if not isinstance(results, Mapping):
            raise ValueError(f"{source} must map sample tokens to lists of boxes, got {type(results).__name__}")
        flat: list = []
        counts = []
        for token, entries in results.items():
            if not isinstance(entries, (list, tuple)):
                raise ValueError(f"{source}[{token!r}] must be a list of boxes, got {type(entries).__name__}")
            flat.extend(entries)
            counts.append(len(entries))
        tokens = tuple(str(t) for t in results)
        sample_index = np.repeat(np.arange(len(tokens), dtype=np.int64), counts)
        try:
            # Whole columns at once: a million boxes parse in seconds, not minutes.
            return cls(sample_tokens=tokens, sample_index=sample_index, **_columns(flat, tokens, sample_index))
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError):  # Overflow: a JSON int past float64/int64
            pass
        # Entry by entry: slower, and names the first bad entry in its error.
        rows = [
            _parse_entry(entry, token, f"{source}[{token!r}][{i}]")
            for token, entries in results.items()
            for i, entry in enumerate(entries)
        ]
        n = len(rows)
        cols = list(zip(*rows)) if rows else [()] * 9
        return cls(
            sample_tokens=tokens,
            sample_index=sample_index,
            translation=np.array(cols[0], dtype=np.float64).reshape(n, 3),
            size=np.array(cols[1], dtype=np.float64).reshape(n, 3),
            rotation=np.array(cols[2], dtype=np.float64).reshape(n, 4),
            velocity=np.array(cols[3], dtype=np.float64).reshape(n, 2),
            ego_translation=np.array(cols[4], dtype=np.float64).reshape(n, 3),
            num_pts=np.array(cols[5], dtype=np.int64).reshape(n),
            detection_name=np.array(cols[6], dtype=np.str_).reshape(n),
            detection_score=np.array(cols[7], dtype=np.float64).reshape(n),
            attribute_name=np.array(cols[8], dtype=np.str_).reshape(n),
        )


_ARRAY_FIELDS = (
    "sample_index", "translation", "size", "rotation", "velocity", "ego_translation", "num_pts",
    "detection_name", "detection_score", "attribute_name",
)  # fmt: skip


def _columns(entries: list, tokens: tuple[str, ...], sample_index: np.ndarray) -> dict[str, np.ndarray]:
    """The arrays of ``entries``; raises (without naming the culprit) on anything ``_parse_entry`` would refuse."""
    n = len(entries)

    def vectors(key: str, dim: int, allow_nan: bool = False) -> np.ndarray:
        rows = [e[key] for e in entries]
        if not _all_numbers(rows, allow_none=allow_nan):
            raise TypeError(key)
        a = np.array(rows, dtype=np.float64)  # ragged: raises
        a = a.reshape(0, dim) if n == 0 else a
        if a.shape != (n, dim):
            raise ValueError(key)
        ok = np.isfinite(a) | (np.isnan(a) if allow_nan else False)
        if not ok.all():
            raise ValueError(key)
        return a

    if not all(isinstance(e, Mapping) for e in entries):
        raise TypeError("entry")
    if any(e["sample_token"] != tokens[s] for e, s in zip(entries, sample_index.tolist())):
        raise ValueError("sample_token")
    size, rotation = vectors("size", 3), vectors("rotation", 4)
    if np.any(size <= 0) or np.any(np.sum(rotation * rotation, axis=1) < 1e-12):
        raise ValueError("size or rotation")
    scores = [e.get("detection_score", -1.0) for e in entries]
    num_pts = [e.get("num_pts", -1) for e in entries]
    if not all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) for v in scores):
        raise TypeError("detection_score")
    if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in num_pts):
        raise TypeError("num_pts")
    names = np.array([e["detection_name"] for e in entries], dtype=np.str_).reshape(n)
    attributes = np.array([e.get("attribute_name", "") for e in entries], dtype=np.str_).reshape(n)
    if not (np.isin(names, DETECTION_NAMES).all() and np.isin(attributes, ("", *ATTRIBUTE_NAMES)).all()):
        raise ValueError("detection_name or attribute_name")
    if not {type(e["detection_name"]) for e in entries} <= {str}:
        raise TypeError("detection_name")
    score_arr = np.array(scores, dtype=np.float64).reshape(n)
    if not np.isfinite(score_arr).all():
        raise ValueError("detection_score")
    ego = [e["ego_translation"] if "ego_translation" in e else (0.0, 0.0, 0.0) for e in entries]
    if not _all_numbers(ego):
        raise TypeError("ego_translation")
    return {
        "translation": vectors("translation", 3),
        "size": size,
        "rotation": rotation,
        "velocity": vectors("velocity", 2, allow_nan=True),
        "ego_translation": _finite(np.array(ego, dtype=np.float64), (n, 3)),
        "num_pts": np.array(num_pts, dtype=np.int64).reshape(n),
        "detection_name": names,
        "detection_score": score_arr,
        "attribute_name": attributes,
    }


def _all_numbers(rows: list, allow_none: bool = False) -> bool:
    """Whether every value of the vectors ``rows`` is a number (``_NUMBER_TYPES``; None too with ``allow_none``).
    The distinct types of all values, then a check per type: one pass in C over the values, not a Python test each.
    A row that is not iterable raises TypeError (the caller's fallback names the entry)."""
    return all(_is_number_type(t) or (allow_none and t is type(None)) for t in set(map(type, chain.from_iterable(rows))))


def _is_number_type(t: type) -> bool:
    return issubclass(t, _NUMBER_TYPES) and not issubclass(t, _NOT_NUMBER_TYPES)


def _finite(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    a = a.reshape(shape) if a.size == 0 else a
    if a.shape != shape or not np.isfinite(a).all():
        raise ValueError("ego_translation")
    return a


def _numbers(entry: Mapping, key: str, n: int, where: str, allow_nan: bool = False) -> list[float]:
    value = entry[key]
    ok = isinstance(value, (list, tuple)) and len(value) == n
    if ok:
        # float() would take "5.1", "nan" and True: JSON numbers only, as detection_score and num_pts
        wrong = [v for v in value if not (_is_number_type(type(v)) or (allow_nan and v is None))]
        if any(isinstance(v, (str, *_NOT_NUMBER_TYPES)) for v in wrong):
            raise ValueError(f"{where}.{key} must be {n} finite numbers (JSON numbers, not strings or booleans), "
                             f"got {short_repr(value)}")  # fmt: skip
        ok = not wrong
    if ok:
        try:
            out = [math.nan if (v is None and allow_nan) else float(v) for v in value]
        except (TypeError, ValueError, OverflowError):  # OverflowError: an int past float64 (10**400)
            ok = False
        else:
            ok = all(math.isfinite(v) or (allow_nan and math.isnan(v)) for v in out)
    if not ok:
        raise ValueError(f"{where}.{key} must be {n} finite numbers, got {short_repr(value)}")
    return out


def _parse_entry(entry: Mapping, token: str, where: str) -> tuple:
    if not isinstance(entry, Mapping):
        raise ValueError(f"{where} must be a JSON object, got {type(entry).__name__}")
    for key in ("sample_token", "translation", "size", "rotation", "velocity", "detection_name"):
        if key not in entry:
            raise ValueError(f"{where} has no {key!r} field (keys: {sorted(entry)})")
    if entry["sample_token"] != token:
        raise ValueError(f"{where}.sample_token must be the sample it is listed under ({token!r}), got {entry['sample_token']!r}")
    translation = _numbers(entry, "translation", 3, where)
    size = _numbers(entry, "size", 3, where)
    if min(size) <= 0:
        raise ValueError(f"{where}.size must be > 0 in every dimension (w, l, h), got {entry['size']!r}")
    rotation = _numbers(entry, "rotation", 4, where)
    if sum(v * v for v in rotation) < 1e-12:
        raise ValueError(f"{where}.rotation must be a non-zero quaternion (w, x, y, z), got {entry['rotation']!r}")
    velocity = _numbers(entry, "velocity", 2, where, allow_nan=True)
    ego = _numbers(entry, "ego_translation", 3, where) if "ego_translation" in entry else [0.0, 0.0, 0.0]
    num_pts = entry.get("num_pts", -1)
    if isinstance(num_pts, bool) or not isinstance(num_pts, (int, np.integer)) or not _INT64[0] <= num_pts < _INT64[1]:
        raise ValueError(f"{where}.num_pts must be an integer (int64), got {short_repr(num_pts)}")
    name = entry["detection_name"]
    if name not in DETECTION_NAMES:
        raise ValueError(f"{where}.detection_name must be one of {DETECTION_NAMES}, got {name!r}")
    score = entry.get("detection_score", -1.0)
    if not is_finite_number(score):
        raise ValueError(f"{where}.detection_score must be a finite number, got {short_repr(score)}")
    attribute = entry.get("attribute_name", "")
    if attribute != "" and attribute not in ATTRIBUTE_NAMES:
        raise ValueError(f"{where}.attribute_name must be '' or one of {ATTRIBUTE_NAMES}, got {attribute!r}")
    return translation, size, rotation, velocity, ego, int(num_pts), name, float(score), attribute
