"""When each synthetic camera exposes: as the LiDAR crosses its optical axis (nuScenes' trigger; docs/synth/timing.md).

- **Key frames.** Every camera exposes once per key frame, at its crossing in the key frame's sweep
  (``camera_trigger_times_s``; world 6 on).
- **Between key frames** (``SynthConfig.camera_hz`` > 0; nuScenes runs its cameras at 12 Hz). Exposure ``i`` of a
  camera is its first crossing at or after ``t0 + i / camera_hz``, where ``t0`` is the start of the scene's first
  written LiDAR sweep. That is the rule of the replay's ``lidar-synced`` trigger model (``replay/triggers.py``) on the
  drive the replay reads from the dataset, so a replay at that camera rate finds a frame recorded at each trigger.
  Intervals are whole rotations (50 or 100 ms for 12 Hz cameras on the 20 Hz LiDAR). The key frames' exposures are
  added: each key frame whose rotation that grid does not pick adds a frame, so a camera's mean rate is at least
  ``camera_hz`` (and the key frames' 2 Hz) and up to ``camera_hz + 2`` Hz, by camera and ``sweeps_per_sample`` (with
  10 the key frames lie on odd rotations of the grid, and a rate whose grid picks even ones gets all of the 2 Hz).
  The LiDAR turns whether or not its sweep is written: with fewer sweeps per key-frame interval than rotations the
  cameras still expose at their own rate, and a replay, which sees only the written sweeps, triggers at fewer of them.

A frame between key frames belongs to the next key frame (its ``sample_token``), as nuScenes files its sweeps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from streamdet.calibration.camera import optical_axis_azimuth_deg
from streamdet.data.synth_lidar import LidarConfig, scan_fraction

if TYPE_CHECKING:
    from streamdet.data.synth_writer import RigRecords


@dataclass(frozen=True)
class CameraFrame:
    """One exposure of one camera."""

    t_s: float  # scene time of the exposure: when the LiDAR crossed the camera's optical axis
    key_index: int  # the key frame it is filed under: the first at or after it (the last for none after)
    is_key: bool  # the key frame's own exposure (samples/, with a mask); else a camera sweep (sweeps/, no mask)


def camera_trigger_times_s(rig: RigRecords, t_end_s: float, sweep_s: float, lidar: LidarConfig = LidarConfig()) -> dict[str, float]:
    """Scene time at which each camera of ``rig`` exposes for the sweep ending at ``t_end_s``: when the LiDAR, turning
    as ``lidar`` says, crosses the camera's optical axis (nuScenes: "the exposure of a camera is triggered when the
    top LiDAR sweeps across the centre of the camera's FOV"), ``t_end - sweep + scan_fraction(axis) * sweep``."""
    ego2lidar = rig.lidar2ego[:3, :3].T
    axes = {m.name: optical_axis_azimuth_deg(ego2lidar @ m.cam2ego[:3, :3]) for m in rig.models}
    return {name: float(t_end_s - sweep_s + float(scan_fraction(az, lidar)) * sweep_s) for name, az in axes.items()}


def rotations_per_interval(interval_s: float, sweep_s: float) -> int | None:
    """Whole LiDAR rotations in a key-frame interval; None where the interval is not a whole number of them."""
    r = interval_s / sweep_s
    return int(round(r)) if abs(r - round(r)) < 1e-6 and round(r) >= 1 else None


def camera_frames(
    rig: RigRecords,
    key_times_s: np.ndarray,
    interval_s: float,
    sweep_s: float,
    first_sweep_start_s: float,
    camera_hz: float,
    lidar: LidarConfig = LidarConfig(),
) -> dict[str, list[CameraFrame]]:
    """Every exposure of every camera of a scene, by camera name, in time order (see the module doc).

    ``key_times_s``: the key frames' times (each its sweep's end), ``interval_s`` apart; ``sweep_s``: one rotation;
    ``first_sweep_start_s``: where the scene's first written sweep starts; ``camera_hz``: 0 for key frames only.
    """
    key_times = np.asarray(key_times_s, dtype=np.float64)
    names = [m.name for m in rig.models]
    frames: dict[str, list[CameraFrame]] = {name: [] for name in names}
    if not camera_hz > 0:
        for k, t_key in enumerate(key_times):
            times = camera_trigger_times_s(rig, float(t_key), sweep_s, lidar)
            for name in names:
                frames[name].append(CameraFrame(times[name], k, True))
        return frames
    per = rotations_per_interval(interval_s, sweep_s)
    if per is None:
        raise ValueError(f"camera frames between key frames need whole rotations per key-frame interval, got "
                         f"{interval_s} s / {sweep_s} s")
    last = len(key_times) - 1
    # Rotations numbered from key frame 0's (r = 0); rotation r ends `(k * per - r)` rotations before key frame k,
    # its own or the next: key frames' exposures come out exactly as camera_trigger_times_s of their sweep gives them.
    first = -math.ceil((key_times[0] - first_sweep_start_s) / sweep_s) - 1
    rotations = np.arange(first, last * per + 1)  # (R,)
    key_of = np.clip(-(-rotations // per), 0, last)  # (R,) the key frame at or after each rotation
    ends = key_times[key_of] - (key_of * per - rotations) * sweep_s  # (R,)
    crossing = [camera_trigger_times_s(rig, float(t), sweep_s, lidar) for t in ends]
    for name in names:
        times = np.array([c[name] for c in crossing])  # (R,) increasing
        usable = np.flatnonzero(times >= first_sweep_start_s - 1e-9)
        # The replay's rule (replay/triggers.lidar_synced_triggers), in drive time from the first sweep's start.
        drive = times[usable] - first_sweep_start_s
        nominal = np.arange(0.0, drive[-1] + 1e-9, 1.0 / camera_hz)
        picked = np.searchsorted(drive, nominal - 1e-9)
        chosen = set(usable[picked[picked < len(usable)]].tolist())
        chosen |= set(np.flatnonzero(rotations == key_of * per).tolist())  # every key frame's own exposure
        for i in sorted(chosen):
            k = int(key_of[i])
            frames[name].append(CameraFrame(float(times[i]), k, bool(rotations[i] == k * per)))
    return frames
