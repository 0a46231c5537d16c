"""What the player itself costs: a drive at nuScenes rates played on the wall clock through a detector that does nothing.

``python -m streamdet.replay.cost [--seconds 10]`` prints the CPU the process spent while playing (the player
thread's releases and bookkeeping, the runner's copies of the data it is handed, the lanes' threads and futures)
as a share of one core, for each mode; the issue's target is under 5 %. The drive is made up (a ring of points
per rotation, ~34,000 points as the synthetic LiDAR gives, six 384x216 cameras), so no dataset or export is needed.
Slicing the sweeps happens before the clock starts (``release_schedule``) and is reported apart.
"""

from __future__ import annotations

import time

import click

from streamdet.core.points import NUSCENES_CAMERA_HZ, NUSCENES_LIDAR_HZ
from streamdet.cli_utils import FiniteFloatRange
import numpy as np

from streamdet.replay.clock import WallClock
from streamdet.replay.modes import MODES
from streamdet.replay.player import PlayerConfig, play
from streamdet.replay.schedule import release_schedule
from streamdet.replay.source import Drive, ImageSet, LidarSweep
from streamdet.replay.triggers import DEFAULT_TRIGGER, check_trigger, lidar_synced_triggers, simultaneous_triggers
from streamdet.runtime_ort.detector import ImageUpdate, SliceResult
from streamdet.runtime_ort.postprocess import Detections

CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
# optical axes' azimuths (deg, LiDAR frame) of the bundled real nuScenes sample's cameras (data/nuscenes_sample)
AXES_DEG = dict(zip(CAMERAS, (90.2, 33.5, 145.0, 269.7, 198.4, 339.1)))


class NoOpDetector:
    """Answers every slice with no detections and every image set at once."""

    uses_images = True

    def __init__(self) -> None:
        self._image_ts = None

    def detect_slice(self, points, slice_index, timestamp=None, num_slices=None):
        return SliceResult(Detections.empty(), slice_index, num_slices or 8, timestamp, self._image_ts, len(points), 0, 0)

    def update_images(self, images, timestamp=None, **options):
        self._image_ts = timestamp
        return ImageUpdate(timestamp, tuple(images), ())


def synthetic_drive(seconds: float, lidar_hz: float = NUSCENES_LIDAR_HZ, camera_hz: float = NUSCENES_CAMERA_HZ, points: int = 34_000,
                    image_size: tuple[int, int] = (384, 216), camera_trigger: str = DEFAULT_TRIGGER) -> Drive:  # fmt: skip
    """A made-up drive of ``seconds``: rotations of ``points`` points fired counter-clockwise, six cameras
    triggered by ``camera_trigger`` (``triggers.py``; lidar-synced at the nuScenes sample's axes)."""
    check_trigger(camera_trigger)
    rng = np.random.default_rng(0)
    period = 1.0 / lidar_hz
    az = np.sort(rng.uniform(0, 2 * np.pi, points))
    pts = np.zeros((points, 5), np.float32)
    pts[:, 0], pts[:, 1] = 20 * np.cos(az), 20 * np.sin(az)
    times = az / (2 * np.pi) * period
    sweeps = tuple(LidarSweep(i, (i + 1) * period, period, pts, times, np.eye(4), np.eye(4)) for i in range(int(seconds * lidar_hz)))
    w, h = image_size
    image = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    if camera_trigger == "lidar-synced":
        triggers = lidar_synced_triggers(sweeps, AXES_DEG, camera_hz)
    else:
        triggers = simultaneous_triggers(seconds - 1e-9, camera_hz, CAMERAS)
    moments: dict[float, list[str]] = {}
    for c in CAMERAS:
        for t in triggers[c]:
            moments.setdefault(float(t), []).append(c)
    sets = tuple(ImageSet(i, t, {c: image for c in moments[t]}, t) for i, t in enumerate(sorted(moments)))
    return Drive("no-op", sweeps, sets, 0)


def measure(seconds: float, mode: str, num_slices: int = 8) -> dict:
    drive = synthetic_drive(seconds)
    cpu0 = time.process_time()
    release_schedule(drive, num_slices)
    schedule_cpu = time.process_time() - cpu0
    rec = play(drive, NoOpDetector(), WallClock(), PlayerConfig(mode, num_slices))
    return {
        "mode": mode,
        "drive_s": seconds,
        "process_cpu_share": rec.process_cpu_s / rec.wall_s,  # play() builds its schedule before it starts counting
        "player_thread_cpu_share": rec.player_cpu_s / rec.wall_s,
        "schedule_cpu_s_per_drive_s": schedule_cpu / seconds,
        "latency_p99_ms": float(np.percentile(rec.latencies_ms(), 99)),
    }


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--seconds", type=FiniteFloatRange(min=1.0), default=10.0, show_default=True, help="Drive seconds per mode.")
def main(seconds: float) -> None:
    """The player's own CPU with a no-op detector, per mode (target: under 5 % of one core)."""
    click.echo("mode        process CPU   player thread   slicing (before play)   no-op latency p99")
    for mode in MODES:
        r = measure(seconds, mode)
        click.echo(f"{mode:<12}{100 * r['process_cpu_share']:>9.1f} %{100 * r['player_thread_cpu_share']:>13.1f} %"
                   f"{100 * r['schedule_cpu_s_per_drive_s']:>19.1f} %{r['latency_p99_ms']:>17.2f} ms")  # fmt: skip


if __name__ == "__main__":
    main()
