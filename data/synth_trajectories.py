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
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from streamdet.data.synth_world import KIND_SPECS, make_scene

if TYPE_CHECKING:
    from streamdet.data.synth_writer import SynthConfig

TRAJECTORIES_FILE = "trajectories.npz"


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
    """The scene's trajectories from ``root/trajectories.npz``; None when the dataset has no such file or scene."""
    path = Path(root) / TRAJECTORIES_FILE
    if not path.is_file():
        return None
    with np.load(path) as f:
        if f"{scene_name}/times_us" not in f.files:
            return None
        return Trajectories(*(f[f"{scene_name}/{k}"] for k in ("times_us", "boxes", "names", "ego2global")))
