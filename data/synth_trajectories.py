"""Where every annotated object of the synthetic world is at any time: the ``trajectories.npz`` sidecar.

The key-frame tables stay nuScenes-compatible (annotations at 2 Hz, at each sweep's end); a detector scored at the
moment its output is emitted (``streamdet-replay``) needs the world between key frames too. The generator samples
every annotated object's box and the ego pose at ``rate_hz`` over each scene's whole time span (the earliest sweep
included) through ``Objects.boxes_at`` and ``Scene.ego2global``, so the file follows whatever motion the world
model has; a reader interpolates linearly between samples (exact for the straight constant-velocity tracks).

``DIR/trajectories.npz`` (a streamdet extension the devkit ignores), per scene ``S`` (the scene name):

    S/times_us      (T,) int64 dataset timestamps of the samples
    S/boxes         (T, K, 9) float64 world boxes x, y, z, w, l, h, yaw, vx, vy (nuScenes global frame)
    S/names         (K,) str detection class of each object
    S/ego2global    (T, 4, 4) float64 ego pose
    S/attributes    (T, K) uint8 each object's nuScenes attribute at each sample, an index into
                    ``synth_tables.ATTRIBUTE_NAMES`` (0: none); optional (absent in datasets written before it)
"""

from __future__ import annotations

import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from streamdet.core.classes import CLASS_NAMES
from streamdet.core.errors import first_line
from streamdet.data.synth_tables import ATTRIBUTE_NAMES, attribute_indices
from streamdet.data.synth_world import KIND_SPECS, make_scene

if TYPE_CHECKING:
    from streamdet.data.synth_writer import SynthConfig

TRAJECTORIES_FILE = "trajectories.npz"
MEMBERS = ("times_us", "boxes", "names", "ego2global")
ATTRIBUTES_MEMBER = "attributes"  # optional: files written before it have none
# The most one member may declare uncompressed (checked in the zip directory before it is inflated): a scene of
# minutes at 100 Hz with hundreds of objects is tens of MB; a small file declaring more is a zip bomb.
MAX_MEMBER_BYTES = 1 << 30
# |x|, |y|, |z| of a box centre or the ego in the global frame: nuScenes maps span a few km. Beyond this a box is
# no object a detector could see (a file edited or corrupted), not a place.
MAX_ABS_COORD_M = 1e6


def write_trajectories(out: str | Path, config: SynthConfig, rate_hz: float = 100.0) -> Path:
    """Write ``out/trajectories.npz`` for the scenes of ``config`` (the dataset ``generate_dataset`` writes)."""
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
    arrays: dict[str, np.ndarray] = {}
    world = config.world
    # From one key-frame interval before the first key frame (its earliest sweep) to the last sweep's end.
    start_s = -world.sample_interval_s
    end_s = world.sweep_duration_s + world.sample_interval_s * (world.samples_per_scene - 1) + 1.0 / rate_hz
    times_s = np.arange(start_s, end_s + 1e-9, 1.0 / rate_hz)  # (T,)
    for index in range(config.num_scenes):
        scene = make_scene(config.seed, index, world)
        objs = scene.objects
        keep = np.flatnonzero(objs.annotated)
        boxes = np.stack([objs.boxes_at(float(t))[keep] for t in times_s])  # (T, K, 9)
        arrays[f"{scene.name}/times_us"] = np.array([scene.timestamp_us(float(t)) for t in times_s], dtype=np.int64)
        arrays[f"{scene.name}/boxes"] = boxes.astype(np.float64)
        arrays[f"{scene.name}/names"] = np.array([KIND_SPECS[int(k)].detection_class for k in objs.kind[keep]], dtype=np.str_)
        arrays[f"{scene.name}/ego2global"] = np.stack([scene.ego2global(float(t)) for t in times_s])  # (T, 4, 4)
        speed = np.linalg.norm(objs.velocity[keep], axis=-1)  # (K,)
        codes = attribute_indices(objs.kind[keep], speed, objs.flag[keep], objs.parked[keep])  # (K,)
        # One row per sample: constant along a scene today (speeds and roles do not change), (T, K) in the file so
        # that a world whose objects start or stop needs no new format.
        arrays[f"{scene.name}/{ATTRIBUTES_MEMBER}"] = np.ascontiguousarray(np.broadcast_to(codes, boxes.shape[:2]))
    path = Path(out) / TRAJECTORIES_FILE
    np.savez_compressed(path, **arrays)
    return path


@dataclass(frozen=True, eq=False)
class Trajectories:
    """One scene's sampled object boxes and ego poses; ``boxes_at`` interpolates between samples."""

    times_us: np.ndarray  # (T,) int64
    boxes: np.ndarray  # (T, K, 9) world boxes
    names: np.ndarray  # (K,) str
    ego2global: np.ndarray  # (T, 4, 4)
    attributes: np.ndarray | None = None  # (T, K) uint8 codes of ATTRIBUTE_NAMES; None: the file has none

    def attributes_at(self, t_us: float) -> np.ndarray | None:
        """(K,) attribute names at ``t_us`` (the sample at or before it: an attribute holds until the next); None
        when the file records none."""
        if self.attributes is None:
            return None
        i, w = self._bracket(t_us)
        return np.array(ATTRIBUTE_NAMES, dtype=object)[self.attributes[i + 1 if w >= 1.0 else i]]

    def _bracket(self, t_us: float) -> tuple[int, float]:
        t = self.times_us
        if not t[0] <= t_us <= t[-1]:
            raise ValueError(f"time {t_us:.0f} us is outside the trajectories' span [{t[0]}, {t[-1]}] us")
        i = int(np.clip(np.searchsorted(t, t_us, side="right") - 1, 0, len(t) - 2))
        return i, float((t_us - t[i]) / (t[i + 1] - t[i]))

    def boxes_at(self, t_us: float) -> np.ndarray:
        """(K, 9) world boxes at dataset time ``t_us``: centre, velocity linear; yaw along the shorter arc."""
        i, w = self._bracket(t_us)
        a, b = self.boxes[i], self.boxes[i + 1]
        out = a + w * (b - a)
        dyaw = np.mod(b[:, 6] - a[:, 6] + np.pi, 2 * np.pi) - np.pi
        out[:, 6] = a[:, 6] + w * dyaw
        return out

    def ego_xyz_at(self, t_us: float) -> np.ndarray:
        i, w = self._bracket(t_us)
        return self.ego2global[i, :3, 3] + w * (self.ego2global[i + 1, :3, 3] - self.ego2global[i, :3, 3])


def load_trajectories(root: str | Path, scene_name: str) -> Trajectories | None:
    """The scene's trajectories from ``root/trajectories.npz``; None when the dataset has no such file or scene.

    The file is checked before use (ValueError naming it): a readable .npz, no pickled arrays, members within
    MAX_MEMBER_BYTES, and for the scene: ``times_us`` (T >= 2,) integers strictly increasing, ``boxes`` (T, K, 9)
    finite floats with centres within MAX_ABS_COORD_M and positive sizes, ``names`` (K,) detection classes,
    ``ego2global`` (T, 4, 4) finite floats."""
    path = Path(root) / TRAJECTORIES_FILE
    if not path.is_file():
        if path.exists() and not path.is_dir():  # a FIFO or a device: a broken dataset, not one without the sidecar
            raise ValueError(f"{path} is not a regular file (a FIFO or a device?): no trajectories can be read from it")
        return None
    keys = [f"{scene_name}/{k}" for k in MEMBERS]
    try:
        with open(path, "rb") as fh:
            head = fh.read(6)
        # named here: np.load reports a non-zip file as "pickled (object) data", which it is not
        if head == b"\x93NUMPY":
            raise ValueError("it holds one .npy array, not an .npz archive")
        if not zipfile.is_zipfile(path):
            raise ValueError("not an .npz archive (no zip directory: truncated, or another kind of file)")
        # allow_pickle=False: the file comes with the dataset; whatever numpy's default, it is data, never code
        f = np.load(path, allow_pickle=False)
        if not isinstance(f, np.lib.npyio.NpzFile):  # a .npy after all: an array, no archive to close
            raise ValueError("it holds one .npy array, not an .npz archive")
        with f:
            if keys[0] not in f.files:
                return None
            missing = [k for k in keys if k not in f.files]
            if missing:
                raise ValueError(f"scene {scene_name!r} lacks {missing}")
            for k in keys:
                size = f.zip.getinfo(f"{k}.npy").file_size
                if size > MAX_MEMBER_BYTES:
                    raise ValueError(f"{k} declares {size} bytes uncompressed, over the {MAX_MEMBER_BYTES}-byte cap")
            arrays = [f[k] for k in keys]
            attr_key = f"{scene_name}/{ATTRIBUTES_MEMBER}"
            attributes = None
            if attr_key in f.files:
                size = f.zip.getinfo(f"{attr_key}.npy").file_size
                if size > MAX_MEMBER_BYTES:
                    raise ValueError(f"{attr_key} declares {size} bytes uncompressed, over the {MAX_MEMBER_BYTES}-byte cap")
                attributes = f[attr_key]
    except (ValueError, OSError, EOFError, KeyError, zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error) as e:
        raise ValueError(f"trajectories file {path}: {first_line(e)}") from None
    checked = _checked(path, scene_name, *arrays)
    if attributes is not None:
        t, k = checked[1].shape[:2]
        if attributes.shape != (t, k) or attributes.dtype.kind not in "iu" or (attributes.size and
                                                                               not 0 <= int(attributes.min()) <= int(attributes.max()) < len(ATTRIBUTE_NAMES)):  # fmt: skip
            raise ValueError(f"trajectories file {path}: scene {scene_name!r}: attributes must be ({t}, {k}) integer codes "
                             f"0..{len(ATTRIBUTE_NAMES) - 1}, got {attributes.dtype} {attributes.shape}")  # fmt: skip
        attributes = attributes.astype(np.uint8)
    return Trajectories(*checked, attributes)


def _checked(path: Path, scene: str, times: np.ndarray, boxes: np.ndarray, names: np.ndarray,
             ego2global: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The scene's arrays as ``Trajectories`` reads them, or a ValueError naming the file, the scene and the array."""

    def bad(what: str) -> ValueError:
        return ValueError(f"trajectories file {path}: scene {scene!r}: {what}")

    if times.ndim != 1 or times.dtype.kind not in "iu" or len(times) < 2:
        raise bad(f"times_us must be at least 2 integer timestamps (T,), got {times.dtype} {times.shape}")
    times = times.astype(np.int64)
    if np.any(np.diff(times) <= 0):  # interpolation divides by the gap between samples
        i = int(np.flatnonzero(np.diff(times) <= 0)[0])
        raise bad(f"times_us must increase strictly, got {times[i]} then {times[i + 1]} at index {i + 1}")
    t = len(times)
    if boxes.dtype.kind != "f" or boxes.ndim != 3 or boxes.shape[0] != t or boxes.shape[2] != 9:
        raise bad(f"boxes must be floats of shape ({t}, K, 9), got {boxes.dtype} {boxes.shape}")
    k = boxes.shape[1]
    if names.ndim != 1 or names.dtype.kind != "U" or len(names) != k:
        raise bad(f"names must be {k} strings (one per object of boxes), got {names.dtype} {names.shape}")
    unknown = sorted(set(names.tolist()) - set(CLASS_NAMES))
    if unknown:
        raise bad(f"names holds {unknown[:3]}, not detection classes {list(CLASS_NAMES)}")
    if ego2global.dtype.kind != "f" or ego2global.shape != (t, 4, 4):
        raise bad(f"ego2global must be floats of shape ({t}, 4, 4), got {ego2global.dtype} {ego2global.shape}")
    for name, arr in (("boxes", boxes), ("ego2global", ego2global)):
        if not np.isfinite(arr).all():
            raise bad(f"{name} holds non-finite values (NaN or inf)")
    far = max(float(np.abs(boxes[..., :3]).max(initial=0.0)), float(np.abs(ego2global[:, :3, 3]).max(initial=0.0)))
    if far > MAX_ABS_COORD_M:
        raise bad(f"a position {far:.3g} m from the origin, beyond {MAX_ABS_COORD_M:g} m")
    if k and not (boxes[..., 3:6] > 0).all():
        raise bad(f"box sizes (w, l, h) must be > 0, got a minimum of {float(boxes[..., 3:6].min())}")
    return times, boxes.astype(np.float64), names, ego2global.astype(np.float64)
