"""The streaming section's image-lane schedules: ``full`` vs ``phase-locked`` on the bundled sample at nuScenes rates.

The bundled nuScenes sweep is played as a drive of ``seconds`` (the same rotation every 1 / 20 s, released slice by
slice as the LiDAR scans it; the six bundled images, each camera triggered by ``trigger``, 12 Hz on average) through
the runtime's `StreamingRunner` on the wall clock, once per schedule, each with a fresh, warmed-up detector
(``replay.player.play``, streaming mode). Reported per schedule: the staleness added by processing, the image age,
the slice latency p99, the slices dropped and the image lane's CPU per LiDAR rotation - issue 22's measures, on
the machine at hand. The images never change, so only timing is measured, not accuracy (``streamdet-replay``
scores detections on a dataset).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from streamdet.data.sample import load_bundled_sample
from streamdet.replay.clock import WallClock
from streamdet.replay.player import PlayerConfig, play
from streamdet.replay.record import percentiles
from streamdet.replay.source import Drive, ImageSet, LidarSweep
from streamdet.replay.triggers import camera_axis_azimuths_deg, lidar_synced_triggers, simultaneous_triggers
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.sessions import CPU_ONLY
from streamdet.runtime_ort.lanes import SCHEDULES, LaneConfig

LIDAR_HZ = 20.0  # nuScenes rates
CAMERA_HZ = 12.0


def bundled_drive(seconds: float, images: dict[str, np.ndarray], trigger: str, start_deg: float = 0.0) -> Drive:
    """The bundled sweep every rotation for ``seconds`` (point times from the azimuth), ``images`` by ``trigger``."""
    sample = load_bundled_sample()
    period = 1.0 / LIDAR_HZ
    sweeps = tuple(LidarSweep(i, (i + 1) * period, period, sample.points, None, sample.lidar2ego, sample.ego2global)
                   for i in range(max(2, int(seconds * LIDAR_HZ))))  # fmt: skip
    if trigger == "lidar-synced":
        axes = camera_axis_azimuths_deg(sample.rig)
        triggers = lidar_synced_triggers(sweeps, {n: axes[n] for n in images}, CAMERA_HZ, start_deg)
    else:
        triggers = simultaneous_triggers(sweeps[-1].end_s, CAMERA_HZ, tuple(images))
    moments: dict[float, list[str]] = {}
    for name in images:
        for t in triggers[name]:
            moments.setdefault(float(t), []).append(name)
    sets = tuple(ImageSet(i, t, {n: images[n] for n in moments[t]}, t) for i, t in enumerate(sorted(moments)))
    return Drive("bundled", sweeps, sets, 0, sample.rig)


def measure_schedules(
    export_dir: str | Path, precision: str, image_precision: str | None, seconds: float, trigger: str = "lidar-synced",
    slice_workers: int | None = None,
) -> dict[str, dict]:
    """Per schedule: staleness and image age (ms p50 / p95), slice latency p99 ms, slices dropped / total, image-lane
    CPU ms per rotation, and the phase-locked lane's counts. ``slice_workers``: the slice lane's worker threads
    (``LaneConfig.max_in_flight``; None: its default), the same for both schedules."""
    from streamdet.replay.run import warm_up  # the replay's warm-up: one image update, one sweep, each quadrant alone

    out = {}
    for schedule in SCHEDULES:
        det = StreamingDetector(export_dir, DetectorConfig(precision=precision, image_lane_precision=image_precision,
                                                           providers=CPU_ONLY))  # fmt: skip
        img = det.manifest.image
        stacked = load_bundled_sample().load_images((img.width, img.height))  # (J, H, W, 3) rig order
        images = {n: np.ascontiguousarray(stacked[j]) for j, n in enumerate(det.camera_names)}
        drive = bundled_drive(seconds, images, trigger, det.config.start_deg)
        warm_up(det, drive, det.num_slices, per_quadrant=schedule == "phase-locked")
        lanes = LaneConfig(schedule=schedule, lidar_hz=LIDAR_HZ)
        if slice_workers is not None:
            lanes = dataclasses.replace(lanes, max_in_flight=slice_workers)
        rec = play(drive, det, WallClock(), PlayerConfig("streaming", det.num_slices, det.config.start_deg, lanes=lanes))
        det.close()
        out[schedule] = {
            "trigger": trigger,
            "slice_workers": lanes.max_in_flight,
            "staleness_ms": percentiles(rec.staleness_ms(), (50, 95)),
            "image_age_ms": percentiles(rec.image_ages_ms(), (50, 95)),
            "latency_ms": percentiles(rec.latencies_ms(), (50, 99)),
            "slices_dropped": rec.slices_dropped,
            "slices_total": len(rec.slices),
            "image_lane_cpu_ms_per_rotation": 1e3 * rec.image_lane_cpu_s / max(1, rec.rotations),
            "phase_lock": rec.phase_lock,
        }
    return out


def format_schedules(schedules: dict[str, dict]) -> list[str]:
    lines = []
    for name, r in schedules.items():
        st, age, lat = r["staleness_ms"], r["image_age_ms"], r["latency_ms"]
        lines.append(
            f"  image lane '{name}' ({r['trigger']} cameras, {LIDAR_HZ:g} Hz x slices, {CAMERA_HZ:g} Hz, "
            f"{r['slice_workers']} slice worker(s)): staleness added "
            f"p50 {_ms(st['p50'])} / p95 {_ms(st['p95'])} ms, image age p95 {_ms(age['p95'])} ms, slice p99 "
            f"{_ms(lat['p99'])} ms, {r['slices_dropped']} of {r['slices_total']} slices dropped, image lane "
            f"{r['image_lane_cpu_ms_per_rotation']:.1f} ms CPU per rotation"
        )
    return lines


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"
