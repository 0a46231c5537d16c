"""The image-lane schedules on a modelled computer: what staleness each schedule and trigger model can reach when
the stages take given times, whatever else the machine runs.

``python -m streamdet.benchmarks.schedule_model [--seconds 10] [--encode-ms 4.5] [--lift-ms 16] [--slice-ms 6.3]``
plays a made-up drive at nuScenes rates (``replay.cost.synthetic_drive``: 20 Hz x 8 slices, six 12 Hz cameras
at the nuScenes sample's axes) on the wall clock through the real `StreamingRunner` (its slice lane, its ``full`` or
``phase-locked`` image lane) around a detector that *sleeps* for the stage times instead of computing: encoding
``encode_ms`` per camera frame, lifting ``lift_ms`` per quadrant (a full update lifts four), ``slice_ms`` per slice.
Each quadrant is stamped as the runtime stamps it (the oldest frame of the cameras that see it), so the staleness
added by processing, the image age and the slices dropped are the replay's own measures. Sleeping takes no CPU, so
the lanes do not compete for cores here: this isolates what the *schedule* costs from what the CPU costs (the
replay on the real export measures both). The defaults are the quiet-machine stage times of the int8 image lane on
the README's AMD EPYC Zen 4 (docs/replay.md). Results: docs/replay.md, section "Camera triggers and the
image-lane schedules (issue 22)", paragraphs "The schedules on a modelled computer" and "What the geometry allows".
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import click

from streamdet.cli_utils import FiniteFloatRange
import numpy as np

from streamdet.core.sectors import NUM_QUADRANTS
from streamdet.replay.clock import WallClock
from streamdet.replay.cost import AXES_DEG, CAMERAS, synthetic_drive
from streamdet.replay.player import PlayerConfig, play
from streamdet.replay.record import percentiles
from streamdet.replay.triggers import TRIGGER_MODELS
from streamdet.runtime_ort.detector import ImageUpdate, SliceResult
from streamdet.runtime_ort.lanes import SCHEDULES, LaneConfig
from streamdet.runtime_ort.postprocess import Detections

FLOOR_LIFT_MS = (0.0, 3.0, 5.0, 10.0, 15.0, 20.0, 30.0)  # lift times of the floor table
HALF_FOV_DEG = 35.0  # the nuScenes cameras' half field of view (about 70 deg wide; CAM_BACK's 110 is wider)


class _Config:
    start_deg = 0.0
    clockwise = False


class SleepingDetector:
    """A StreamingDetector's interface whose stages sleep for modelled times; quadrants stamped like the runtime's."""

    uses_images = True
    camera_names = CAMERAS

    def __init__(self, encode_ms: float, lift_ms: float, slice_ms: float, num_slices: int = 8) -> None:
        self.encode_s, self.lift_s, self.slice_s = encode_ms / 1e3, lift_ms / 1e3, slice_ms / 1e3
        self.num_slices = num_slices
        self.config = _Config()
        self._stamps: list[float | None] = [None] * NUM_QUADRANTS
        self._lock = threading.Lock()
        self.busy_s = 0.0  # modelled image-lane seconds (what its CPU would be)

    def quadrant_cameras(self, quadrants) -> tuple[str, ...]:
        """Cameras whose field of view overlaps the quadrants (by azimuth)."""
        out = []
        for name in CAMERAS:
            lo, hi = AXES_DEG[name] - HALF_FOV_DEG, AXES_DEG[name] + HALF_FOV_DEG
            if any(_overlaps(lo, hi, 90.0 * q, 90.0 * (q + 1)) for q in quadrants):
                out.append(name)
        return tuple(out)

    def check_images(self, images) -> None:
        pass

    def encode_images(self, images) -> dict[str, np.ndarray]:
        self._sleep(self.encode_s * len(images))
        return {n: np.zeros(1, np.float32) for n in images}

    def update_images(self, images, timestamp=None, quadrants=None, encoded=None, camera_timestamps=None):
        wanted = tuple(range(NUM_QUADRANTS)) if quadrants is None else tuple(quadrants)
        fresh = [n for n in images if not encoded or n not in encoded]
        self._sleep(self.encode_s * len(fresh) + self.lift_s * len(wanted))
        stamps = camera_timestamps or {}
        with self._lock:
            for q in wanted:
                seen = [stamps.get(n, timestamp) for n in self.quadrant_cameras([q]) if n in images]
                self._stamps[q] = min(seen) if seen else timestamp
        return ImageUpdate(timestamp, tuple(images), (), quadrants=wanted)

    def detect_slice(self, points, slice_index, timestamp=None, num_slices=None):
        n = num_slices or self.num_slices
        q = slice_index * NUM_QUADRANTS // n if n >= NUM_QUADRANTS else None
        with self._lock:
            stamps = [s for s in (self._stamps if q is None else [self._stamps[q]]) if s is not None]
        time.sleep(self.slice_s)
        ts = min(stamps) if stamps else None
        return SliceResult(Detections.empty(), slice_index, n, timestamp, ts, len(points), 0, 0)

    def _sleep(self, seconds: float) -> None:
        self.busy_s += seconds
        time.sleep(seconds)


def _overlaps(lo: float, hi: float, a: float, b: float) -> bool:
    return any(lo + s < b and hi + s > a for s in (-360.0, 0.0, 360.0))


def staleness_floor_ms(drive, quadrant_cameras, lift_s: float, num_slices: int = 8, skip_rotations: int = 4,
                       delivery_s: float = 0.0) -> np.ndarray:  # fmt: skip
    """Per slice, the least staleness any schedule could add when a lift takes ``lift_s``: the oldest of the newest
    frames of its quadrant's cameras by its scan start, minus the oldest of those that arrived ``lift_s`` before the
    slice itself arrived (every quadrant lifted just in time, as if the lane had a core per quadrant). Negative:
    frames that came during the scan could make it in. The first rotations (no frame of some camera yet) are left out.
    ``delivery_s``: a frame arrives that long after its capture (a real camera's exposure, readout and transport;
    the replay delivers at capture, 0); staleness still compares capture times."""
    from streamdet.core.sectors import quadrants_of_sector
    from streamdet.replay.schedule import slice_sweep

    times: dict[str, list[float]] = {}
    for s in drive.image_sets:
        for n in s.images:
            times.setdefault(n, []).append(s.capture_s)
    arrays = {n: np.asarray(t) for n, t in times.items()}

    def oldest_newest(cams, t: float) -> float:
        t = t - delivery_s  # captured by then = arrived by t
        picks = [arrays[n][i] for n in cams if (i := int(np.searchsorted(arrays[n], t, side="right")) - 1) >= 0]
        return min(picks) if len(picks) == len(cams) else float("nan")

    out = []
    for sweep in drive.sweeps[skip_rotations:]:
        for s in slice_sweep(sweep, num_slices):
            cams = [n for n in quadrant_cameras(quadrants_of_sector(s.slice_index, num_slices)) if n in arrays]
            scan_start = sweep.start_s + sweep.duration_s * s.slice_index / num_slices
            out.append(1e3 * (oldest_newest(cams, scan_start) - oldest_newest(cams, s.scan_end_s - lift_s)))
    return np.asarray(out)


def measure(schedule: str, trigger: str, seconds: float, encode_ms: float, lift_ms: float, slice_ms: float) -> dict:
    drive = synthetic_drive(seconds, camera_trigger=trigger, points=3_600, image_size=(8, 8))
    det = SleepingDetector(encode_ms, lift_ms, slice_ms)
    lanes = LaneConfig(schedule=schedule, lidar_hz=20.0)
    rec = play(drive, det, WallClock(), PlayerConfig("streaming", 8, lanes=lanes))
    st = percentiles(rec.staleness_ms(), (50, 95))
    age = percentiles(rec.image_ages_ms(), (50, 95))
    lat = percentiles(rec.latencies_ms(), (99,))
    return {"schedule": schedule, "trigger": trigger, "staleness_p50": st["p50"], "staleness_p95": st["p95"],
            "age_p95": age["p95"], "latency_p99": lat["p99"], "dropped": rec.slices_dropped,
            "busy_ms_per_rotation": 1e3 * det.busy_s / rec.rotations, "phase_lock": rec.phase_lock}  # fmt: skip


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--seconds", type=FiniteFloatRange(min=1.0), default=10.0, show_default=True, help="Drive seconds per run.")
@click.option("--encode-ms", type=FiniteFloatRange(min=0), default=4.5, show_default=True, help="Encoder ms per camera frame.")
@click.option("--lift-ms", type=FiniteFloatRange(min=0), default=16.0, show_default=True, help="Lifter ms per quadrant.")
@click.option("--slice-ms", type=FiniteFloatRange(min=0), default=6.3, show_default=True, help="Slice graph ms per slice.")
@click.option("--export-dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Take the floor's cameras per quadrant from this export's LUT (default: by the cameras' azimuths).")
@click.option("--delivery-ms", "delivery_ms", default="", show_default=True,
              help="Also print the lidar-synced floor for these camera delivery delays (capture to arrival), e.g. "
                   "'0,10,20,30,50': where a lift must end depends on when frames arrive in the rotation.")
def main(seconds: float, encode_ms: float, lift_ms: float, slice_ms: float, export_dir: Path | None, delivery_ms: str) -> None:
    """Staleness, image age and image-lane time per rotation of each schedule under each trigger model."""
    try:
        delays = [float(x) for x in delivery_ms.split(",") if x.strip()]
    except ValueError:
        raise click.BadParameter(f"a comma-separated list of milliseconds, got {delivery_ms!r}", param_hint="--delivery-ms") from None
    if any(not (d >= 0 and np.isfinite(d)) for d in delays):
        raise click.BadParameter(f"delays must be finite and >= 0 ms, got {delivery_ms!r}", param_hint="--delivery-ms")
    click.echo(f"modelled stages: encode {encode_ms} ms / frame, lift {lift_ms} ms / quadrant, slice {slice_ms} ms; "
               f"{seconds:g} s of drive per run (sleeping, not computing)")  # fmt: skip
    click.echo("| trigger | schedule | staleness added p50 / p95 ms | image age p95 ms | latency p99 ms | dropped | "
               "image lane ms / rotation |")  # fmt: skip
    click.echo("|---|---|---|---|---|---|---|")
    for trigger in TRIGGER_MODELS:
        for schedule in SCHEDULES:
            r = measure(schedule, trigger, seconds, encode_ms, lift_ms, slice_ms)
            click.echo(f"| {trigger} | {schedule} | {r['staleness_p50']:.0f} / {r['staleness_p95']:.0f} | {r['age_p95']:.0f} "
                       f"| {r['latency_p99']:.1f} | {r['dropped']} | {r['busy_ms_per_rotation']:.1f} |")  # fmt: skip
    click.echo("\nthe floor: least staleness added any schedule could reach, every quadrant lifted just in time "
               "(staleness_floor_ms), p50 / p95 ms")  # fmt: skip
    click.echo("| trigger | " + " | ".join(f"lift {ms:g} ms" for ms in FLOOR_LIFT_MS) + " |")
    click.echo("|---|" + "---|" * len(FLOOR_LIFT_MS))
    quadrant_cameras = SleepingDetector(encode_ms, lift_ms, slice_ms).quadrant_cameras
    if export_dir is not None:
        if not (export_dir / "manifest.json").is_file():
            raise click.ClickException(f"{export_dir} holds no manifest.json: pass an export directory")
        from streamdet.runtime_ort.detector import StreamingDetector

        quadrant_cameras = StreamingDetector(export_dir).quadrant_cameras
    for trigger in TRIGGER_MODELS:
        drive = synthetic_drive(max(seconds, 10.0), camera_trigger=trigger, points=3_600, image_size=(8, 8))
        cells = []
        for ms in FLOOR_LIFT_MS:
            f = staleness_floor_ms(drive, quadrant_cameras, ms / 1e3)
            cells.append(f"{np.nanpercentile(f, 50):.0f} / {np.nanpercentile(f, 95):.0f}")
        click.echo(f"| {trigger} | " + " | ".join(cells) + " |")
    if delays:
        click.echo("\nthe lidar-synced floor when frames arrive a delay after capture, p50 / p95 ms")
        click.echo("| delivery delay | " + " | ".join(f"lift {ms:g} ms" for ms in FLOOR_LIFT_MS) + " |")
        click.echo("|---|" + "---|" * len(FLOOR_LIFT_MS))
        drive = synthetic_drive(max(seconds, 10.0), camera_trigger="lidar-synced", points=3_600, image_size=(8, 8))
        for delay in delays:
            cells = []
            for ms in FLOOR_LIFT_MS:
                f = staleness_floor_ms(drive, quadrant_cameras, ms / 1e3, delivery_s=delay / 1e3)
                cells.append(f"{np.nanpercentile(f, 50):.0f} / {np.nanpercentile(f, 95):.0f}")
            click.echo(f"| {delay:g} ms | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
