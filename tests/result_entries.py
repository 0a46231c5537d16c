"""Test helper (not a test module): nuScenes results / ground-truth entries for the evaluation tests."""

from __future__ import annotations

import math


def result_entry(token: str, xy, name: str, score: float | None, num_pts: int = 5, yaw: float = 0.0) -> dict:
    """A detection (``score``) or, with ``score`` None, a ground-truth box holding ``num_pts`` LiDAR points, at
    ``xy`` (m) with heading ``yaw`` (rad): 1 x 2 x 1.5 m, still."""
    e = {"sample_token": token, "translation": [float(xy[0]), float(xy[1]), 1.0], "size": [1.0, 2.0, 1.5],
         "rotation": [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)], "velocity": [0.0, 0.0],
         "detection_name": name, "attribute_name": ""}  # fmt: skip
    if score is None:
        return e | {"ego_translation": e["translation"], "num_pts": num_pts, "detection_score": -1.0}
    return e | {"detection_score": score}
