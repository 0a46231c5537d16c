"""A numpy TF buffer over ``tf2_msgs/TFMessage`` (``/tf`` and ``/tf_static``): the poses the rig is built from.

An edge ``parent -> child`` stores the child frame's pose in the parent frame (``transform`` of a
``geometry_msgs/TransformStamped`` whose ``header.frame_id`` is the parent), i.e. the map from child coordinates
to parent coordinates: ``sensor2ego`` for ``base_link -> LIDAR_TOP``, ``ego2global`` for ``map -> base_link``.
Lookups return nuScenes-style records ``{"rotation": [w, x, y, z], "translation": [x, y, z]}`` so the rig comes
out of the same ``Rig.from_nuscenes_records`` arithmetic as the nuScenes tables. A direct edge at an exact stamp
returns the message's own numbers, untouched; a stamp between two messages is interpolated (linear translation,
spherical rotation); a chain of edges is composed.

Like tf2's buffer, it keeps the last ``cache_s`` seconds of each time-stamped edge (10 s by default, tf2's
default cache time), counted back from the edge's newest stamp and pruned as transforms are added, so a node fed
``/tf`` for hours holds a bounded buffer; static transforms are kept for ever. A lookup it cannot answer (no path
between the frames, or a stamp outside an edge's kept stamps) raises ``TfLookupError``: a KeyError (what a missing
path raised before) and a ``RosMessageError`` (a ValueError), so a node's per-message handler catches it with the
adapters' other errors.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from streamdet.calibration.camera import invert_transform, make_transform, matrix_to_quaternion, quaternion_to_matrix
from streamdet.core.json_input import is_finite_number
from streamdet.runtime_ort.ros.header import NS_PER_S, RosMessageError, header_msg, is_integer, shown, stamp_ns


TF_QUATERNION_NORM2_TOL = 0.01  # tf2 BufferCore::setTransform: |q|^2 may differ from 1 by this much
DEFAULT_CACHE_S = 10.0  # tf2's BufferCore::DEFAULT_CACHE_TIME: how far back from its newest stamp an edge is kept
MSG = "geometry_msgs/TransformStamped"

Record = dict  # {"rotation": [w, x, y, z], "translation": [x, y, z]}


class TfLookupError(KeyError, RosMessageError):
    """A lookup the buffer cannot answer: no TF path between the frames, or a stamp outside an edge's kept stamps.

    A KeyError for callers written against the earlier "no path" KeyError, and a ValueError (RosMessageError) so that
    one ``except ValueError`` covers every adapter's refusal."""

    def __str__(self) -> str:  # KeyError's str() quotes its argument as a key's repr; this is a sentence
        return str(self.args[0]) if self.args else ""


@dataclass
class _Edge:
    stamps: list[int] = field(default_factory=list)  # sorted ns; empty for a static edge
    records: list[Record] = field(default_factory=list)
    static: Record | None = None


class TfBuffer:
    """Static and time-stamped transforms between named frames; not thread-safe (one reader feeds it).

    ``max_extrapolation_ns`` (default 0): how far past an edge's first or last kept stamp a lookup may take that
    pose. ``cache_s`` (default ``DEFAULT_CACHE_S``, 10 s as tf2): how many seconds of each time-stamped edge are
    kept, back from its newest stamp; older transforms are dropped when a newer one is added. None keeps every
    transform (a tool that looks up a whole recording afterwards; memory grows with it)."""

    def __init__(self, max_extrapolation_ns: int = 0, cache_s: float | None = DEFAULT_CACHE_S) -> None:
        # refused by name: int() gives its own message for NaN and OverflowError for inf and truncates 0.5; a
        # negative reach acts as 0 and can only be a caller's mistake (a sign slip in a tolerance)
        value = max_extrapolation_ns
        integral = is_integer(value) or (is_finite_number(value) and float(value).is_integer())  # 5e7 is fine
        if not (integral and value >= 0):
            raise ValueError(f"TfBuffer.max_extrapolation_ns must be a whole number of ns >= 0, got {shown(value)}")
        self.max_extrapolation_ns = int(value)  # how far past the first / last stamp a lookup may reach
        if cache_s is not None and not (is_finite_number(cache_s) and cache_s > 0):
            raise ValueError(f"TfBuffer.cache_s must be a number of seconds > 0 or None (keep all), got {shown(cache_s)}")
        self.cache_s = cache_s
        self._cache_ns = None if cache_s is None else round(cache_s * NS_PER_S)
        self._edges: dict[tuple[str, str], _Edge] = {}
        self._parent: dict[str, str] = {}

    def add(self, msg: Any, static: bool = False) -> None:
        """Every ``TransformStamped`` of a ``tf2_msgs/TFMessage``; ``static`` for ``/tf_static``.

        All or nothing: every transform is checked before any is stored, so a refused message changes nothing."""
        transforms = msg.transforms
        if not isinstance(transforms, (list, tuple)):
            kind = type(transforms).__name__
            raise RosMessageError(f"tf2_msgs/TFMessage.transforms must be a list of {MSG}, got {kind} {shown(transforms)}")
        self._add([_parse(ts) for ts in transforms], static)

    def add_transform(self, ts: Any, static: bool = False) -> None:
        """One ``geometry_msgs/TransformStamped``; a refused one changes nothing."""
        self._add([_parse(ts)], static)

    def _add(self, parsed: list[tuple[str, str, Record, int]], static: bool) -> None:
        # The tree is checked on a copy, so that a refusal (here or in _parse) leaves no parent link behind: one
        # corrupt message from a wrong parent would otherwise refuse every later valid transform of its child.
        parents = dict(self._parent)
        for parent, child, _, _ in parsed:
            known = parents.get(child)
            if known is not None and known != parent:
                raise RosMessageError(f"{MSG} {parent!r} -> {child!r}: frame {child!r} has two parents, {known!r} and {parent!r}: "
                                      "TF is a tree")  # fmt: skip
            parents[child] = parent
        self._parent = parents
        for parent, child, record, stamp in parsed:
            edge = self._edges.setdefault((parent, child), _Edge())
            if static:
                edge.static = record
                continue
            i = bisect.bisect_left(edge.stamps, stamp)
            if i < len(edge.stamps) and edge.stamps[i] == stamp:
                edge.records[i] = record
            else:
                edge.stamps.insert(i, stamp)
                edge.records.insert(i, record)
            if self._cache_ns is not None:
                # tf2's TimeCache::pruneList: the newest stamp stays, whatever the window, so an edge is never emptied
                old = bisect.bisect_left(edge.stamps, edge.stamps[-1] - self._cache_ns)
                if old:
                    del edge.stamps[:old], edge.records[:old]

    @property
    def frames(self) -> set[str]:
        return set(self._parent) | set(self._parent.values())

    def lookup(self, parent: str, child: str, stamp: int) -> Record:
        """The pose of ``child`` in ``parent`` at ``stamp`` (ns) as a record; TfLookupError says why not."""
        parent, child = _frame(parent, "TfBuffer.lookup parent"), _frame(child, "TfBuffer.lookup child")
        if (parent, child) in self._edges:
            return self._edge_record(parent, child, stamp)
        up_child = self._chain(child)
        up_parent = self._chain(parent)
        common = next((f for f in up_child if f in up_parent), None)
        if common is None:
            raise TfLookupError(f"no TF path from {parent!r} to {child!r}; known frames {sorted(self.frames)}")
        child2common = self._compose(up_child[: up_child.index(common) + 1], stamp)
        parent2common = self._compose(up_parent[: up_parent.index(common) + 1], stamp)
        child2parent = invert_transform(parent2common) @ child2common
        rotation = matrix_to_quaternion(child2parent[:3, :3])
        return {"rotation": rotation.tolist(), "translation": child2parent[:3, 3].tolist()}

    # ---- internals ------------------------------------------------------------------------------------
    def _chain(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self._parent:
            chain.append(self._parent[chain[-1]])
            if len(chain) > 1000:
                raise RosMessageError(f"TF loop above frame {frame!r}")
        return chain

    def _compose(self, chain: list[str], stamp: int) -> np.ndarray:
        """(4, 4) map from the first frame of ``chain`` to its last, through each parent."""
        out = np.eye(4)
        for child, parent in zip(chain, chain[1:]):
            rec = self._edge_record(parent, child, stamp)
            out = make_transform(quaternion_to_matrix(rec["rotation"]), rec["translation"]) @ out
        return out

    def _edge_record(self, parent: str, child: str, stamp: int) -> Record:
        edge = self._edges[(parent, child)]
        if edge.static is not None:
            return edge.static
        stamps = edge.stamps
        i = bisect.bisect_left(stamps, stamp)
        if i < len(stamps) and stamps[i] == stamp:
            return edge.records[i]
        if i == 0 or i == len(stamps):
            end = stamps[0] if i == 0 else stamps[-1]
            if abs(stamp - end) <= self.max_extrapolation_ns:
                return edge.records[0 if i == 0 else -1]
            kept = "" if self.cache_s is None else f"; the buffer keeps the last {self.cache_s:g} s of each edge (cache_s)"
            raise TfLookupError(
                f"TF {parent!r} -> {child!r} at {stamp} ns is outside its {len(stamps)} stamps "
                f"[{stamps[0]}, {stamps[-1]}] (max_extrapolation_ns {self.max_extrapolation_ns}){kept}"
            )
        a, b = edge.records[i - 1], edge.records[i]
        w = (stamp - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
        t = (1 - w) * np.asarray(a["translation"]) + w * np.asarray(b["translation"])
        q = _slerp(np.asarray(a["rotation"]), np.asarray(b["rotation"]), w)
        return {"rotation": q.tolist(), "translation": t.tolist()}


def transform_stamped_msg(parent: str, child: str, record: Record, stamp: int) -> dict:
    """A ``geometry_msgs/TransformStamped`` dict of a record (child pose in parent)."""
    w, x, y, z = (float(v) for v in record["rotation"])
    tx, ty, tz = (float(v) for v in record["translation"])
    return {
        "header": header_msg(stamp, parent),
        "child_frame_id": child,
        "transform": {"translation": {"x": tx, "y": ty, "z": tz}, "rotation": {"x": x, "y": y, "z": z, "w": w}},
    }


def _parse(ts: Any) -> tuple[str, str, Record, int]:
    """(parent, child, record, stamp) of a ``TransformStamped``, every field checked; nothing is stored here."""
    parent = _frame(ts.header.frame_id, f"{MSG} header.frame_id")
    child = _frame(ts.child_frame_id, f"{MSG} child_frame_id")
    if parent == child:
        raise RosMessageError(f"{MSG} needs two different frame ids, got {parent!r} -> {child!r}")
    stamp = stamp_ns(ts.header.stamp, f"{MSG} header.stamp")  # a static one's too: a corrupt stamp, a corrupt message
    r, t = ts.transform.rotation, ts.transform.translation
    record = {"rotation": [_number(r, axis, "rotation") for axis in "wxyz"],
              "translation": [_number(t, axis, "translation") for axis in "xyz"]}  # fmt: skip
    # Checked and normalised here, once, so that an exact lookup, an interpolation and a chain all see the same
    # edges. tf2 accepts a quaternion whose squared norm is within 0.01 of 1 (drivers and URDFs write rounded
    # ones, 0.707 for 1/sqrt(2)) and refuses others (TF_DENORMALIZED_QUATERNION): so do we.
    q, xyz = np.asarray(record["rotation"]), np.asarray(record["translation"])
    if not (np.isfinite(q).all() and np.isfinite(xyz).all() and abs(float(q @ q) - 1.0) <= TF_QUATERNION_NORM2_TOL):
        raise RosMessageError(f"{MSG} {parent!r} -> {child!r} at {stamp} ns: rotation {record['rotation']} "
                              f"must be a unit quaternion (squared norm within {TF_QUATERNION_NORM2_TOL} of 1, as tf2 "
                              f"requires) and translation {record['translation']} finite")  # fmt: skip
    if abs(float(q @ q) - 1.0) > 1e-12:  # a unit one to float precision is kept as given
        record["rotation"] = (q / np.linalg.norm(q)).tolist()
    return parent, child, record, stamp


def _number(vector: Any, axis: str, name: str) -> float:
    """One component of a ``geometry_msgs`` Quaternion / Vector3 as a float. Not a number is refused by name: float()
    would take '1.5' and True, and raise TypeError for None, OverflowError for 10**400. A NaN or inf float is left
    to the unit-quaternion / finite check, which quotes the whole rotation and translation."""
    value = getattr(vector, axis)
    if isinstance(value, (float, np.floating)) or (is_integer(value) and is_finite_number(value)):
        return float(value)
    raise RosMessageError(f"{MSG} transform.{name}.{axis} must be a float64 number, got {shown(value)}")


def _frame(name: Any, what: str) -> str:
    """A frame id without its leading slash (tf2's carry none; ROS 1 bags often do); anything but a non-empty str is
    refused rather than turned into the frame 'None'."""
    if not isinstance(name, str) or not name.lstrip("/"):
        raise RosMessageError(f"{what} must be a non-empty frame id (str), got {shown(name)}")
    return name.lstrip("/")


def _slerp(q0: np.ndarray, q1: np.ndarray, w: float) -> np.ndarray:
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    dot = float(q0 @ q1)
    if dot < 0:  # the shorter arc
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + w * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1 - w) * theta) * q0 + np.sin(w * theta) * q1) / np.sin(theta)
