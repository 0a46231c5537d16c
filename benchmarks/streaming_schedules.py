"""The streaming section's image-lane schedules: ``full`` vs ``phase-locked`` on the bundled sample at nuScenes rates.

The bundled nuScenes sweep is played as a drive (the same rotation every 1 / 20 s, released slice by slice as the
LiDAR scans it; the six bundled images, each camera triggered by ``trigger``, 12 Hz on average) through the runtime's
`StreamingRunner` on the wall clock (``replay.player.play``, streaming mode), each play with a fresh, warmed-up
detector. The schedules take turns: ``rounds`` rounds of ``seconds / rounds`` each per schedule, in the order A B, B A,
A B, ... (a steady drift of the machine's speed falls on both alike), and a schedule's figures pool its rounds: two
plays made one after the other compare the machine's states as much as the schedules (benchmarks/RESULTS.md,
**Timing**). Reported per schedule: the staleness added by processing, the image age, the slice latency p99, the
slices dropped and the image lane's CPU per LiDAR rotation - issue 22's measures, on the machine at hand. The images
never change, so only timing is measured, not accuracy (``streamdet-replay`` scores detections on a dataset).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from streamdet.data.sample import load_bundled_sample
from streamdet.replay.clock import WallClock
from streamdet.replay.player import PlayerConfig, play
from streamdet.replay.record import Recording, percentiles
from streamdet.replay.source import Drive, ImageSet, LidarSweep
from streamdet.replay.triggers import camera_axis_azimuths_deg, lidar_synced_triggers, simultaneous_triggers
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.sessions import CPU_ONLY
from streamdet.runtime_ort.lanes import SCHEDULES, LaneConfig

LIDAR_HZ = 20.0  # nuScenes rates
CAMERA_HZ = 12.0
SCHEDULE_ROUNDS = 2  # rounds in which the schedules take turns (StreamingConfig.schedule_rounds)


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
    slice_workers: int | None = None, rounds: int = SCHEDULE_ROUNDS,
) -> dict[str, dict]:
    """Per schedule: staleness and image age (ms p50 / p95), slice latency p99 ms, slices dropped / total, image-lane
    CPU ms per rotation, and the phase-locked lane's counts, pooled over ``rounds`` plays of ``seconds / rounds``
    taken in turns with the other schedule (module docstring). ``slice_workers``: the slice lane's worker threads
    (``LaneConfig.max_in_flight``; None: its default), the same for both schedules."""
    if isinstance(rounds, bool) or not isinstance(rounds, int) or rounds < 1:
        raise ValueError(f"rounds must be a positive integer, got {rounds!r}")
    plays: dict[str, list[Recording]] = {schedule: [] for schedule in SCHEDULES}
    workers = {}
    for r in range(rounds):
        for schedule in SCHEDULES if r % 2 == 0 else reversed(SCHEDULES):
            lanes = LaneConfig(schedule=schedule, lidar_hz=LIDAR_HZ)
            if slice_workers is not None:
                lanes = dataclasses.replace(lanes, max_in_flight=slice_workers)
            workers[schedule] = lanes.max_in_flight
            plays[schedule].append(_play(export_dir, precision, image_precision, seconds / rounds, trigger, lanes))
    return {schedule: {"trigger": trigger, "slice_workers": workers[schedule], **_pooled(plays[schedule]),
                       "rounds": rounds, "seconds_per_round": seconds / rounds}
            for schedule in SCHEDULES}  # fmt: skip


def _play(export_dir: str | Path, precision: str, image_precision: str | None, seconds: float, trigger: str,
          lanes: LaneConfig) -> Recording:  # fmt: skip
    """One play of the bundled drive through a fresh detector, warmed up as the replay warms it."""
    from streamdet.replay.run import warm_up  # the replay's warm-up: one image update, one sweep, each quadrant alone

    det = StreamingDetector(export_dir, DetectorConfig(precision=precision, image_lane_precision=image_precision,
                                                       providers=CPU_ONLY))  # fmt: skip
    try:
        img = det.manifest.image
        stacked = load_bundled_sample().load_images((img.width, img.height))  # (J, H, W, 3) rig order
        images = {n: np.ascontiguousarray(stacked[j]) for j, n in enumerate(det.camera_names)}
        drive = bundled_drive(seconds, images, trigger, det.config.start_deg)
        warm_up(det, drive, det.num_slices, per_quadrant=lanes.schedule == "phase-locked")
        return play(drive, det, WallClock(), PlayerConfig("streaming", det.num_slices, det.config.start_deg, lanes=lanes))
    finally:
        det.close()


def _pooled(recs: list[Recording]) -> dict:
    """The figures of one schedule over all its plays: percentiles of the pooled samples, sums of the counts."""
    locks = [r.phase_lock for r in recs]
    rotations = sum(r.rotations for r in recs)
    return {
        "staleness_ms": percentiles(np.concatenate([r.staleness_ms() for r in recs]), (50, 95)),
        "image_age_ms": percentiles(np.concatenate([r.image_ages_ms() for r in recs]), (50, 95)),
        "latency_ms": percentiles(np.concatenate([r.latencies_ms() for r in recs]), (50, 99)),
        "slices_dropped": sum(r.slices_dropped for r in recs),
        "slices_total": sum(len(r.slices) for r in recs),
        "image_lane_cpu_ms_per_rotation": 1e3 * sum(r.image_lane_cpu_s for r in recs) / max(1, rotations),
        # a phase-locked lane's counts (PhaseLockStats: every field a count, or milliseconds held back) add up
        "phase_lock": None if any(lock is None for lock in locks) else {k: sum(lock[k] for lock in locks) for k in locks[0]},
    }


def format_schedules(schedules: dict[str, dict]) -> list[str]:
    lines = []
    for name, r in schedules.items():
        st, age, lat = r["staleness_ms"], r["image_age_ms"], r["latency_ms"]
        rounds = r.get("rounds", 1)  # absent in results recorded before the schedules took turns
        turns = (f", in turns with the other schedule: {rounds} rounds of {r['seconds_per_round']:g} s" if rounds > 1
                 else ", one play")  # fmt: skip
        lines.append(
            f"  image lane '{name}' ({r['trigger']} cameras, {LIDAR_HZ:g} Hz x slices, {CAMERA_HZ:g} Hz, "
            f"{r['slice_workers']} slice worker(s){turns}): staleness added "
            f"p50 {_ms(st['p50'])} / p95 {_ms(st['p95'])} ms, image age p95 {_ms(age['p95'])} ms, slice p99 "
            f"{_ms(lat['p99'])} ms, {r['slices_dropped']} of {r['slices_total']} slices dropped, image lane "
            f"{r['image_lane_cpu_ms_per_rotation']:.1f} ms CPU per rotation"
        )
    return lines


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"
