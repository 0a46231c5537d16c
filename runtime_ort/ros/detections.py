"""``Detections`` -> ``vision_msgs/Detection3DArray`` (for the stack) and ``visualization_msgs/MarkerArray`` (for
viewers: Foxglove, RViz).

Boxes stay in the LiDAR frame they were detected in (the header's ``frame_id``, the cloud's). A box
``x, y, z, w, l, h, yaw`` becomes a pose at its geometric centre with the yaw as a quaternion about +z, and a size
``(l, w, h)`` along the box's own x (the heading), y and z, which is how BoundingBox3D and a CUBE marker read it.
vision_msgs has no velocity field: the velocity is not carried (the results JSON keeps it).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from streamdet.core.boxes import BOX_DIM, H, L, W, X, Y, YAW, Z
from streamdet.core.classes import CLASS_NAMES, class_color_rgb
from streamdet.core.json_input import is_finite_number
from streamdet.core.rotations import yaw_to_quaternion
from streamdet.runtime_ort.ros.header import INT32_MAX, INT32_MIN, RosMessageError, duration_msg, header_msg, int_field, shown

CUBE, TEXT_VIEW_FACING = 1, 9  # visualization_msgs/Marker types
ADD, DELETE, DELETEALL = 0, 2, 3  # visualization_msgs/Marker actions
TEXT_HEIGHT_M = 0.8
DETECTIONS, MARKERS = "vision_msgs/Detection3DArray", "visualization_msgs/MarkerArray"


def yaw_quaternion(yaw: float) -> dict:
    """A ``geometry_msgs/Quaternion`` dict of a rotation by ``yaw`` radians about +z."""
    w, _, _, z = yaw_to_quaternion(float(yaw)).tolist()
    return {"x": 0.0, "y": 0.0, "z": z, "w": w}


def box_pose(box: np.ndarray) -> dict:
    """A ``geometry_msgs/Pose`` dict at the box's geometric centre, heading along its x."""
    position = {"x": float(box[X]), "y": float(box[Y]), "z": float(box[Z])}
    return {"position": position, "orientation": yaw_quaternion(box[YAW])}


def box_size(box: np.ndarray) -> dict:
    """A ``geometry_msgs/Vector3`` dict of the box's extent along its own x (length), y (width) and z (height)."""
    return {"x": float(box[L]), "y": float(box[W]), "z": float(box[H])}


def detection3d_array_message(
    boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, stamp_ns: int, frame_id: str,
    class_names: Sequence[str] = CLASS_NAMES,
) -> dict:  # fmt: skip
    """A ``vision_msgs/Detection3DArray`` dict: one Detection3D per box, one hypothesis (class name, score) each.

    ``boxes`` (N, 9) in ``frame_id``; ``labels`` index ``class_names``. Detection ids are empty: vision_msgs keeps
    an id for the same object across messages (a tracker's), which a per-slice detector does not know, and allows
    an empty one; a box's row was read as an identity it is not. The velocity (vx, vy) has no field here: it is in
    the results JSON and ``Detections``.
    """
    boxes, scores, labels = _check(boxes, scores, labels, class_names, DETECTIONS)
    header = header_msg(stamp_ns, frame_id)
    detections = []
    for i in range(len(boxes)):
        pose = box_pose(boxes[i])
        detections.append({
            "header": header,
            "results": [{
                "hypothesis": {"class_id": class_names[int(labels[i])], "score": float(scores[i])},
                "pose": {"pose": pose, "covariance": [0.0] * 36},
            }],
            "bbox": {"center": pose, "size": box_size(boxes[i])},
            "id": "",
        })  # fmt: skip
    return {"header": header, "detections": detections}


def marker_array_message(
    boxes: np.ndarray, labels: np.ndarray, stamp_ns: int, frame_id: str, scores: np.ndarray | None = None,
    names: Sequence[str] | None = None, ns: str = "streamdet", lifetime_s: float = 0.0, replace: bool = False,
    alpha: float = 0.5, stale_ids: Sequence[int] = (), class_names: Sequence[str] = CLASS_NAMES,
) -> dict:  # fmt: skip
    """A ``visualization_msgs/MarkerArray`` dict: a translucent CUBE per box coloured by class and a text label
    above it (the class name, and the score when ``scores`` is given; ``names`` overrides the text's name).

    Markers of namespace ``ns`` and ``ns + "/labels"`` have ids 0..N-1. ``lifetime_s`` 0 keeps them until replaced;
    ``replace`` starts the array with a DELETEALL so the boxes of the previous array disappear; ``stale_ids``
    deletes those ids of both namespaces (the previous array's boxes beyond this one's count).
    """
    if not (is_finite_number(alpha) and 0 <= alpha <= 1):  # ColorRGBA.a: a viewer draws NaN or 7 as it pleases
        raise ValueError(f"{MARKERS}: alpha (the boxes' color.a) must be a number in [0, 1], got {shown(alpha)}")
    stale_ids = [int_field(i, f"{MARKERS}: stale_ids entry (a Marker id, int32)", INT32_MIN, INT32_MAX) for i in stale_ids]
    boxes, shown_scores, labels = _check(boxes, scores, labels, class_names, MARKERS, allow_other=True, optional_scores=True)
    if names is not None and len(names) != len(boxes):
        raise RosMessageError(f"{MARKERS}: names must have {len(boxes)} entries, got {len(names)}")
    header = header_msg(stamp_ns, frame_id)
    lifetime = duration_msg(lifetime_s)
    markers = [_marker(header, ns, 0, DELETEALL, lifetime)] if replace else []
    for i in range(len(boxes)):
        label = int(labels[i])
        r, g, b = (v / 255.0 for v in class_color_rgb(label))  # ColorRGBA takes 0..1
        name = names[i] if names is not None else (class_names[label] if 0 <= label < len(class_names) else "other")
        cube = _marker(header, ns, i, ADD, lifetime)
        colour = {"r": r, "g": g, "b": b, "a": float(alpha)}
        cube.update(type=CUBE, pose=box_pose(boxes[i]), scale=box_size(boxes[i]), color=colour)
        text = _marker(header, f"{ns}/labels", i, ADD, lifetime)
        above = box_pose(boxes[i])
        above["position"]["z"] += float(boxes[i, H]) / 2 + TEXT_HEIGHT_M / 2
        text.update(type=TEXT_VIEW_FACING, pose=above, scale={"x": 0.0, "y": 0.0, "z": TEXT_HEIGHT_M},
                    color={"r": r, "g": g, "b": b, "a": 1.0},
                    text=name if scores is None else f"{name} {float(shown_scores[i]):.2f}")  # fmt: skip
        markers += [cube, text]
    for i in stale_ids:
        markers += [_marker(header, ns, i, DELETE, lifetime), _marker(header, f"{ns}/labels", i, DELETE, lifetime)]
    return {"markers": markers}


def _marker(header: dict, ns: str, marker_id: int, action: int, lifetime: dict) -> dict:
    return {
        "header": header,
        "ns": ns,
        "id": int(marker_id),
        "type": CUBE,
        "action": action,
        "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
        "scale": {"x": 1.0, "y": 1.0, "z": 1.0},
        "color": {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.0},
        "lifetime": lifetime,
        "frame_locked": False,
        "points": [],
        "colors": [],
        "text": "",
        "mesh_resource": "",
        "mesh_use_embedded_materials": False,
    }


def _check(boxes, scores, labels, class_names, what: str, allow_other: bool = False, optional_scores: bool = False):
    """boxes, scores (zeros for None when ``optional_scores``) and labels as arrays, or a RosMessageError naming ``what``
    (the message being built), the box and the value."""
    boxes = _floats(boxes, "boxes", what)
    if boxes.ndim != 2 or boxes.shape[1] != BOX_DIM:
        raise RosMessageError(f"{what}: boxes must be (N, {BOX_DIM}) x, y, z, w, l, h, yaw, vx, vy; got shape {boxes.shape}")
    n = len(boxes)
    scores = np.zeros(n) if scores is None and optional_scores else _floats(scores, "scores", what)
    labels = np.asarray(labels)
    if scores.shape != (n,) or labels.shape != (n,):
        raise RosMessageError(f"{what}: scores and labels must be ({n},) to match boxes, got {scores.shape} and {labels.shape}")
    if n and not np.issubdtype(labels.dtype, np.integer):
        raise RosMessageError(f"{what}: labels must be integers, got dtype {labels.dtype}")
    bad = (labels >= len(class_names)) | (labels < (-1 if allow_other else 0))
    if np.any(bad):
        raise RosMessageError(f"{what}: labels {sorted(set(labels[bad].tolist()))} are outside 0..{len(class_names) - 1}")
    # vx, vy are not checked: vision_msgs carries no velocity
    if not np.all(np.isfinite(boxes[:, :7])):
        i = int(np.argmax(~np.isfinite(boxes[:, :7]).all(axis=1)))
        raise RosMessageError(f"{what}: boxes hold NaN or infinite centre, size or yaw values (box {i}: {boxes[i, :7].tolist()})")
    # a zero or negative extent is no box: BoundingBox3D.size and a CUBE's scale would draw it inside out or not at all
    sizes = boxes[:, [W, L, H]]
    if not np.all(sizes > 0):
        i = int(np.argmax(~(sizes > 0).all(axis=1)))
        raise RosMessageError(f"{what}: box {i} has size w, l, h {sizes[i].tolist()}; sizes must be > 0")
    if not np.all(np.isfinite(scores)):  # ObjectHypothesis.score: a NaN fails every threshold and sorts anywhere
        i = int(np.argmax(~np.isfinite(scores)))
        raise RosMessageError(f"{what}: score of box {i} is {float(scores[i])}; scores must be finite")
    return boxes, scores, labels


def _floats(values, name: str, what: str) -> np.ndarray:
    try:
        array = np.asarray(values, dtype=np.float64) if values is not None else None  # None would become NaN
    except (TypeError, ValueError, OverflowError):  # strings, ragged rows, an int past float64
        array = None
    if array is None:
        raise RosMessageError(f"{what}: {name} must be an array of numbers, got {shown(values)}")
    return array
