"""What would the phase-locked image lane make of other stage costs? A simulation, the lane's own code on a clock
that only moves when work is done.

    python -m streamdet.benchmarks.lane_sim --export-dir EXPORT [--costs-from REPLAY_DIR] [--cost-scale 0.7] ...

The real ``PhaseLockedImageLane`` (``runtime_ort/phase_locked_lane.py``, no worker thread) is driven by the events of
a drive at sensor rates: slice arrivals (the scan end of each of ``num_slices`` sectors of a rotation) and camera
frames fired as the LiDAR crosses each camera's optical axis (``replay/triggers.py``: ``lidar_synced_triggers``;
the CLI takes the axes of the rig the export's LUT was built from, else the bundled nuScenes sample's,
``replay/cost.py: AXES_DEG``). Its detector does no work: it advances the
clock by the stage costs, per camera frame encoded (``encode_ms``), per camera term run (``term_ms``, once per
frame: the per-camera lift's first convolution, ``camera_terms.py``) and per quadrant lifted (``tail_ms``), each
drawn with a relative spread ``jitter``. The quadrants' cameras are the export's (its LUT). The staleness added of
every slice is then what ``streamdet-replay`` measures (``replay/record.py``): the capture time of the newest frames
of its quadrants' cameras by its scan start, minus the timestamp of the image BEV it reads, the quadrant's newest
lift that ended by the slice's arrival plus ``read_delay_ms`` (0: a free slice worker reads it as it arrives).

What it leaves out, so what it is for: the slice lane and the rest of the process are not simulated (no core
shared, no GIL, no slices waiting), so it answers "how fresh could the images be with a core for the image lane at
these costs", the question of issue 22's AVX-512 line; ``--costs-from`` takes the costs a phase-locked replay
measured (``costs_from_replay``: its stage table per frame encoded and per tail) and ``--cost-scale`` asks what a faster
part or a lighter model would give. docs/replay.md compares it with replays ("The image half on two cores of the
AVX-512 Xeon").
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Callable, Iterable, Mapping

import click

from streamdet.cli_utils import FiniteFloatRange
import numpy as np

from streamdet.core.sectors import NUM_QUADRANTS, quadrants_of_sector
from streamdet.progress import progressbar
from streamdet.replay.cost import AXES_DEG
from streamdet.replay.record import STALE_MS
from streamdet.replay.source import LidarSweep
from streamdet.replay.triggers import camera_axis_azimuths_deg, lidar_synced_triggers
from streamdet.runtime_ort.detector import ImageUpdate, StreamingDetector
from streamdet.runtime_ort.export_settings import export_rig
from streamdet.runtime_ort.phase_locked_lane import PhaseLockedImageLane, PhaseLockStats

STAGES = {"image_encoder": "encode_ms", "lifter_partial": "term_ms", "lifter_tail": "tail_ms"}  # replay stage -> cost


@dataclass(frozen=True)
class LaneCosts:
    encode_ms: float  # encoding one camera frame
    term_ms: float  # one camera's term run (per-camera lifts), once per frame
    tail_ms: float  # lifting one quadrant from its cameras' terms
    jitter: float = 0.0  # relative standard deviation of every cost (a normal draw, clipped at 0)

    def __post_init__(self) -> None:
        for name in ("encode_ms", "term_ms", "tail_ms", "jitter"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"LaneCosts.{name} must be a finite number >= 0, got {v!r}")

    def scaled(self, factor: float) -> "LaneCosts":
        if isinstance(factor, bool) or not isinstance(factor, (int, float)) or not math.isfinite(factor) or factor <= 0:
            raise ValueError(f"the cost scale must be a finite number > 0, got {factor!r}")
        return LaneCosts(self.encode_ms * factor, self.term_ms * factor, self.tail_ms * factor, self.jitter)


@dataclass(frozen=True)
class SimConfig:
    lidar_hz: float = 20.0  # LiDAR rotations per second (nuScenes)
    num_slices: int = 8  # slices per rotation
    camera_hz: float = 12.0  # camera frames per second, each camera (nuScenes)
    seconds: float = 10.0  # simulated drive
    warm_up_s: float = 0.5  # slices before this are not scored (the lane locks to the rotation first)
    lift_margin_ms: float = 2.0  # LaneConfig.lift_margin_ms
    read_delay_ms: float = 0.0  # after its arrival, when a slice reads the image BEV
    delivery_ms: float = 0.0  # a frame reaches the lane this long after its capture
    seed: int = 0  # of the cost jitter
    axes_deg: Mapping[str, float] = field(default_factory=lambda: dict(AXES_DEG))  # cameras' optical axes, LiDAR frame

    def __post_init__(self) -> None:
        for name in ("lidar_hz", "camera_hz", "seconds"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"SimConfig.{name} must be a finite number > 0, got {v!r}")
        for name in ("warm_up_s", "lift_margin_ms", "read_delay_ms", "delivery_ms"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"SimConfig.{name} must be a finite number >= 0, got {v!r}")
        if self.warm_up_s >= self.seconds:
            raise ValueError(f"SimConfig.warm_up_s ({self.warm_up_s}) must be shorter than the drive ({self.seconds} s)")
        if not self.axes_deg:
            raise ValueError("SimConfig.axes_deg names no camera")


@dataclass(frozen=True)
class SimResult:
    staleness_ms: np.ndarray  # (S,) staleness added of every scored slice
    recent_frames: np.ndarray  # (S,) camera frames delivered in the rotation before its scan start
    busy_cores: float  # share of one core the lane's work took
    stats: PhaseLockStats

    def by_recent_frames(self, threshold_ms: float = STALE_MS) -> dict[int, tuple[int, int]]:
        """Frames delivered in the rotation before the scan start -> (stale slices, slices), as
        ``replay.record.staleness_by_recent_images`` counts a replay's."""
        stale = self.staleness_ms > threshold_ms
        return {int(n): (int(stale[self.recent_frames == n].sum()), int((self.recent_frames == n).sum()))
                for n in np.unique(self.recent_frames)}  # fmt: skip

    def summary(self, threshold_ms: float = STALE_MS) -> dict:
        p50, p95, p99 = (float(np.percentile(self.staleness_ms, p)) for p in (50, 95, 99))
        return {"staleness_added_ms": {"p50": p50, "p95": p95, "p99": p99}, "slices": int(self.staleness_ms.size),
                "stale_share": float(np.mean(self.staleness_ms > threshold_ms)), "busy_cores": self.busy_cores,
                "by_recent_frames": {str(k): list(v) for k, v in self.by_recent_frames(threshold_ms).items()},
                "lane": vars(self.stats)}  # fmt: skip


class _CostedDetector:
    """The lane's detector: no work, the clock advanced by the costs; remembers each quadrant's lifts."""

    uses_images = True

    def __init__(self, clock: "ManualClock", costs: LaneCosts, cameras: Mapping[int, tuple[str, ...]], rng: np.random.Generator) -> None:
        self.clock, self.costs, self.rng = clock, costs, rng
        self.camera_names = tuple(dict.fromkeys(n for q in range(NUM_QUADRANTS) for n in cameras[q]))
        self._cameras = cameras
        self.config = SimpleNamespace(start_deg=0.0, clockwise=False)
        self.busy_s = 0.0
        self.lifts: list[list[tuple[float, float]]] = [[] for _ in range(NUM_QUADRANTS)]  # (end s, timestamp)
        self._termed: dict[int, np.ndarray] = {}  # id -> the feature array (held: a freed array's id is reused)

    def _spend(self, ms: float) -> None:
        s = ms * 1e-3 * max(0.0, 1.0 + self.costs.jitter * self.rng.standard_normal()) if self.costs.jitter else ms * 1e-3
        self.clock.t += s
        self.busy_s += s

    def quadrant_cameras(self, quadrants) -> tuple[str, ...]:
        seen = {n for q in quadrants for n in self._cameras[q]}
        return tuple(n for n in self.camera_names if n in seen)

    def encode_images(self, images):
        for _ in images:
            self._spend(self.costs.encode_ms)
        return {n: np.zeros(1, np.float32) for n in images}  # a new array per frame: its terms are made once

    def prepare_terms(self, encoded) -> int:
        for feats in encoded.values():
            self._term(feats)
        return len(encoded)

    def _term(self, feats: np.ndarray) -> None:
        if id(feats) not in self._termed:
            self._spend(self.costs.term_ms)
            self._termed[id(feats)] = feats

    def forget_images(self, through=None, quadrants=None, cameras_out=False) -> None:
        """Quadrants none of whose cameras has a frame (before the lane locks): no lift to cost, nothing to record."""

    def update_images(self, images, timestamp=None, quadrants=None, encoded=None, camera_timestamps=None):
        qs = tuple(range(NUM_QUADRANTS)) if quadrants is None else tuple(quadrants)
        for feats in encoded.values():
            self._term(feats)
        for _ in qs:
            self._spend(self.costs.tail_ms)
        for q in qs:
            self.lifts[q].append((self.clock.t, timestamp))
        return ImageUpdate(timestamp, tuple(images), (), quadrants=qs)


class ManualClock:
    """A clock in seconds that only moves when told (``clock.t = ...``): the lane's ``clock`` in `play_events` and
    in tests that step a lane by hand."""

    def __init__(self, t: float = 0.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def play_events(lane: PhaseLockedImageLane, clock, events: Iterable[tuple[float, Callable[[], object]]]) -> None:
    """Drive a lane without a worker thread (``thread=False``) through ``events``, (time s, action) in time order, on
    ``clock`` (its ``t`` attribute is the lane's clock): the lane's ``step`` runs whenever it asked to be called
    again and after every action, which runs with the clock at its time (never moved back: work ran past it).

    Every event due by the time a step returns is delivered before the next step plans: slices and frames that came
    while the lane worked reach it together, as they reach the runner's lane (its worker plans after its update
    ends, with everything submitted meanwhile). Delivering one of them per step lagged the lane's view of the drive
    behind its own work, more the busier it was; what that did to the stale shares, and the gap to a driver that
    delivers every event at its own time, is measured in docs/replay.md ("Ready lifts, and each camera's budget",
    its caveat)."""
    events = list(events)
    wake = None
    i = 0
    while i < len(events):
        t, action = events[i]
        while wake is not None and wake <= t:
            clock.t = max(clock.t, wake)
            wake = lane.step(clock.t)
        clock.t = max(clock.t, t)
        action()
        i += 1
        while i < len(events) and events[i][0] <= clock.t:  # came while the lane worked: delivered at once
            events[i][1]()
            i += 1
        wake = lane.step(clock.t)


def simulate(costs: LaneCosts, quadrant_cameras: Mapping[int, tuple[str, ...]], config: SimConfig = SimConfig()) -> SimResult:
    """Play ``config``'s drive through the phase-locked lane at ``costs``; ``quadrant_cameras``: quadrant -> the
    cameras its lift reads (every quadrant 0..3; each camera needs an axis in ``config.axes_deg``)."""
    missing = [q for q in range(NUM_QUADRANTS) if not quadrant_cameras.get(q)]
    if missing:
        raise ValueError(f"quadrant_cameras names no camera for quadrant(s) {missing}")
    unknown = sorted({n for q in range(NUM_QUADRANTS) for n in quadrant_cameras[q]} - set(config.axes_deg))
    if unknown:
        raise ValueError(f"cameras without an optical axis in SimConfig.axes_deg: {unknown}")
    clock = ManualClock()
    det = _CostedDetector(clock, costs, quadrant_cameras, np.random.default_rng(config.seed))
    n, period = config.num_slices, 1.0 / config.lidar_hz
    lane = PhaseLockedImageLane(det, n, 0.0, config.lidar_hz, config.lift_margin_ms * 1e-3, clock=clock, thread=False,
                                superseded=lambda: RuntimeError("superseded"))  # fmt: skip
    rotations = int(config.seconds * config.lidar_hz)
    empty = np.zeros((0, 5), np.float32)
    sweeps = [LidarSweep(r, (r + 1) * period, period, empty, None, np.eye(4), np.eye(4)) for r in range(rotations)]
    cams = det.camera_names
    captures = lidar_synced_triggers(sweeps, {c: config.axes_deg[c] for c in cams}, config.camera_hz)  # camera -> (F,) s
    delivery = config.delivery_ms * 1e-3
    arrivals = [(r * period + (k + 1) * period / n, k) for r in range(rotations) for k in range(n)]  # scan ends
    frame = np.zeros((1, 1, 3), np.uint8)
    slices = [(t, 0, functools.partial(lane.observe_slice, k, t)) for t, k in arrivals]
    frames = [(t + delivery, 1, functools.partial(lane.submit_images, {c: frame}, t)) for c in cams for t in captures[c]]
    play_events(lane, clock, [(t, act) for t, _, act in sorted(slices + frames, key=lambda e: (e[0], e[1]))])
    delivered = np.sort(np.concatenate([captures[c] + delivery for c in cams]))
    read = config.read_delay_ms * 1e-3
    stale, recent = [], []
    for t, k in arrivals:
        start = t - period / n
        if start < config.warm_up_s:
            continue
        qs = quadrants_of_sector(k, n)
        newest = []
        for c in det.quadrant_cameras(qs):
            i = int(np.searchsorted(captures[c], start - delivery, side="right")) - 1
            if i >= 0:
                newest.append(captures[c][i])
        stamps = [max((ts for end, ts in det.lifts[q] if end <= t + read), default=math.nan) for q in qs]
        if not newest or any(math.isnan(s) for s in stamps):
            continue  # before its cameras' first frame or its quadrant's first lift: the replay scores none either
        stale.append((min(newest) - min(stamps)) * 1e3)
        recent.append(int(np.searchsorted(delivered, start, "left") - np.searchsorted(delivered, start - period, "left")))
    return SimResult(np.array(stale), np.array(recent, dtype=np.int64), det.busy_s / config.seconds, lane.stats)


def costs_from_replay(path: str | Path, jitter: float = 0.0) -> LaneCosts:
    """The stage costs a phase-locked replay measured (``streamdet-replay --out DIR``: DIR or its replay.json;
    streaming mode): the encoder's and the term runs' total time per camera frame encoded (the lane encodes several
    fresh frames in one run, and runs a camera's terms again where a lift needs them) and the tail's mean per run."""
    p = Path(path)
    p = p / "replay.json" if p.is_dir() else p
    mode = json.loads(p.read_text())["modes"]["streaming"]
    stages = mode.get("stages") or {}
    missing = [s for s in STAGES if s not in stages]
    if missing:
        raise ValueError(f"{p}: the replay's stage table has no {missing} (a phase-locked replay with per-camera lifts has them)")
    locks = [r.get("phase_lock") for r in mode.get("recordings") or []]
    frames = sum(x["cameras_encoded"] for x in locks if x)
    if not frames:
        raise ValueError(f"{p}: no frames encoded by a phase-locked image lane in this replay (the costs are per frame)")
    total = {s: stages[s]["runs"] * stages[s]["mean_ms"] for s in STAGES}  # ms
    return LaneCosts(total["image_encoder"] / frames, total["lifter_partial"] / frames, stages["lifter_tail"]["mean_ms"], jitter)


def export_layout(export_dir: str | Path) -> tuple[dict[int, tuple[str, ...]], dict[str, float] | None]:
    """(quadrant -> the cameras the export's LUT reads in it, camera -> optical axis azimuth in degrees of the rig
    the LUT was built from; None where the runtime may not read that rig: ``export_settings.export_rig``)."""
    with StreamingDetector(export_dir) as det:
        cameras = {q: det.quadrant_cameras([q]) for q in range(NUM_QUADRANTS)}
        try:
            axes = camera_axis_azimuths_deg(export_rig(det.manifest, Path(export_dir)))
        except (ValueError, OSError):
            axes = None
    return cameras, axes


@click.command()
@click.option("--export-dir", required=True, type=click.Path(exists=True, file_okay=False),
              help="Export whose LUT says which cameras each quadrant's lift reads.")
@click.option("--costs-from", type=click.Path(exists=True),
              help="A replay's output folder (or its replay.json): its measured encoder, term and tail means as the costs.")
@click.option("--encode-ms", type=FiniteFloatRange(min=0), help="Encoding one camera frame, ms (overrides --costs-from).")
@click.option("--term-ms", type=FiniteFloatRange(min=0), help="One camera's term run, ms (overrides --costs-from).")
@click.option("--tail-ms", type=FiniteFloatRange(min=0), help="Lifting one quadrant from its terms, ms (overrides --costs-from).")
@click.option("--cost-scale", multiple=True, type=FiniteFloatRange(min=0, min_open=True), default=(1.0,), show_default=True,
              help="Multiply every cost by this; repeat for a row per scale.")
@click.option("--jitter", type=FiniteFloatRange(min=0), default=0.0, show_default=True, help="Relative spread of every cost.")
@click.option("--seconds", type=FiniteFloatRange(min=1), default=10.0, show_default=True, help="Simulated drive.")
@click.option("--seeds", type=click.IntRange(min=1), default=1, show_default=True, help="Runs per scale (jitter seeds 0..N-1).")
@click.option("--lidar-hz", type=FiniteFloatRange(min=0, min_open=True), default=20.0, show_default=True, help="LiDAR rotations per second.")
@click.option("--slices", "num_slices", type=click.IntRange(min=1), default=8, show_default=True, help="Slices per rotation.")
@click.option("--camera-hz", type=FiniteFloatRange(min=0, min_open=True), default=12.0, show_default=True, help="Frames per second per camera.")
@click.option("--read-delay-ms", type=FiniteFloatRange(min=0), default=0.0, show_default=True,
              help="After its arrival, when a slice reads the image BEV (0: at once, a free slice worker).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), help="Also write every row's figures here.")
def main(export_dir, costs_from, encode_ms, term_ms, tail_ms, cost_scale, jitter, seconds, seeds, lidar_hz, num_slices,
         camera_hz, read_delay_ms, json_path) -> None:  # fmt: skip
    """Staleness added by the phase-locked image lane at given stage costs, with a core of its own (see the module doc)."""
    base = {}
    if costs_from:
        try:
            base = vars(costs_from_replay(costs_from))
        except (ValueError, KeyError, OSError) as e:  # JSON errors are ValueErrors
            raise click.ClickException(f"--costs-from {costs_from}: {type(e).__name__}: {e}") from None
    for name, value in (("encode_ms", encode_ms), ("term_ms", term_ms), ("tail_ms", tail_ms)):
        if value is not None:
            base[name] = value
    missing = [n for n in ("encode_ms", "term_ms", "tail_ms") if n not in base]
    if missing:
        raise click.UsageError(f"no cost for {', '.join(missing)}: give --costs-from or --{missing[0].replace('_', '-')}")
    try:
        costs = LaneCosts(base["encode_ms"], base["term_ms"], base["tail_ms"], jitter)
        cameras, axes = export_layout(export_dir)
        config = SimConfig(lidar_hz=lidar_hz, num_slices=num_slices, camera_hz=camera_hz, seconds=seconds, read_delay_ms=read_delay_ms,
                           axes_deg=axes or dict(AXES_DEG))  # fmt: skip
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    where = "the export's calibration" if axes else "the bundled nuScenes sample (the export's calibration is not readable here)"
    click.echo(f"camera axes from {where}: " + ", ".join(f"{n} {a:.1f} deg" for n, a in config.axes_deg.items()))
    click.echo(f"costs: encode {costs.encode_ms:.2f} ms per frame, term {costs.term_ms:.2f} ms per frame, tail "
               f"{costs.tail_ms:.2f} ms per quadrant, jitter {jitter:g}; {lidar_hz:g} Hz x {num_slices} slices, "
               f"{camera_hz:g} Hz lidar-synced cameras, {seconds:g} s x {seeds} seed(s)")  # fmt: skip
    click.echo(f"| cost scale | staleness added p50 / p95 / p99 ms | slices stale (> {STALE_MS:g} ms) | stale where the rotation "
               "before brought the most frames | image lane busy (cores) |\n|---|---|---|---|---|")  # fmt: skip
    rows = []
    with progressbar(cost_scale, label="simulating") as scales:
        for scale in scales:
            results = [simulate(costs.scaled(scale), cameras, SimConfig(**{**vars(config), "seed": s})) for s in range(seeds)]
            st = np.concatenate([r.staleness_ms for r in results])
            recent = np.concatenate([r.recent_frames for r in results])
            stats = PhaseLockStats(**{k: sum(getattr(r.stats, k) for r in results) for k in vars(results[0].stats)})  # all seeds
            pooled = SimResult(st, recent, float(np.mean([r.busy_cores for r in results])), stats)
            most = int(recent.max()) if recent.size else 0
            six = pooled.by_recent_frames().get(most, (0, 0))
            rows.append({"cost_scale": scale, **pooled.summary()})
            s = rows[-1]["staleness_added_ms"]
            click.echo(f"| {scale:g} | {s['p50']:.0f} / {s['p95']:.0f} / {s['p99']:.0f} | {100 * rows[-1]['stale_share']:.1f} % "
                       f"| {six[0]} of {six[1]} ({most} frames) | {pooled.busy_cores:.2f} |")  # fmt: skip
    if json_path:
        Path(json_path).write_text(json.dumps({"costs": vars(costs), "config": {k: v for k, v in vars(config).items()},
                                               "rows": rows}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
