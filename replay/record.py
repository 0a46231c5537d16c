"""The record of a replay: what happened to every slice and every image set, in drive time.

A slice's **latency** runs from its last point scanned (``scan_end_s``) to its detections being available
(``emit_s``, when its future completed). Its **image age** is how old the camera picture behind the image BEV it
was fused with was when the slice lane read it: ``start_s`` minus the capture time of that image set. A slice
dropped by the lane's back-pressure has no start, end or emission; an image set superseded by a newer one before
the image lane reached it likewise. ``queue_depth`` counts the jobs of the same lane released and not yet started
when this one was released. ``cpu_s`` is the CPU time of the worker thread during the job (onnxruntime with one
intra-op thread computes on that thread).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from streamdet.core.json_input import short_repr
from streamdet.runtime_ort.postprocess import Detections


@dataclass(slots=True)
class SliceRecord:
    sweep: int
    slice_index: int
    num_slices: int
    scan_end_s: float
    num_points: int
    release_s: float = float("nan")
    queue_depth: int = 0
    start_s: float = float("nan")
    end_s: float = float("nan")
    emit_s: float = float("nan")
    dropped: bool = False
    image_capture_s: float = float("nan")  # capture time of the image set behind the BEV it was fused with
    newest_capture_s: float = float("nan")  # capture time of the newest image set released by its scan start
    cpu_s: float = 0.0
    num_detections: int = 0
    fallback: bool = False  # the LiDAR-only fallback's graph ran (SliceResult.fallback)
    coalesced: int = 1  # slices detected in the run that detected this one (SliceResult.coalesced; 1: its own run)
    detections: Detections | None = field(default=None, repr=False)

    @property
    def emitted(self) -> bool:
        return bool(np.isfinite(self.emit_s))

    @property
    def latency_ms(self) -> float:
        return (self.emit_s - self.scan_end_s) * 1e3

    @property
    def image_age_ms(self) -> float:
        return (self.start_s - self.image_capture_s) * 1e3

    @property
    def staleness_ms(self) -> float:
        """Staleness added by processing: how much older the images it was fused with were than the newest ones that
        had arrived by its scan start (the age of the image BEV at fusion minus the age of those newest images;
        negative when images that came during the scan made it in), at the capture clock's resolution
        (``capture_gap_ms``)."""
        return capture_gap_ms(self.newest_capture_s, self.image_capture_s)

    def to_dict(self) -> dict:
        return _json_fields(self, exclude=("detections",))


CAPTURE_CLOCK_US = 1.0  # resolution of capture stamps: nuScenes stamps whole microseconds, and float64 seconds of a Unix epoch resolve about 0.24 us


def capture_gap_ms(later_s: float, earlier_s: float) -> float:
    """``later_s - earlier_s`` in milliseconds, rounded to the capture clock (``CAPTURE_CLOCK_US``). The replay's
    stamps are float seconds, so two frames one 100 ms camera interval apart differ by 100.00000000000009 ms: rounded,
    a gap that is a whole number of clock ticks stays one, and a target such as issue 22's "p95 <= 100 ms" reads it as
    the 100 ms it is. NaN stays NaN."""
    return float(np.round((later_s - earlier_s) * 1e6 / CAPTURE_CLOCK_US) * CAPTURE_CLOCK_US / 1e3)


@dataclass(slots=True)
class ImageRecord:
    index: int
    capture_s: float
    release_s: float = float("nan")
    queue_depth: int = 0
    start_s: float = float("nan")
    end_s: float = float("nan")
    emit_s: float = float("nan")
    superseded: bool = False
    cpu_s: float = 0.0

    def to_dict(self) -> dict:
        return _json_fields(self)


@dataclass(frozen=True)
class Recording:
    """One mode played over one drive."""

    mode: str
    drive: str
    time_scale: float
    slices: tuple[SliceRecord, ...]
    images: tuple[ImageRecord, ...]
    wall_s: float  # wall seconds from the first release to the last emission
    player_cpu_s: float  # CPU seconds of the player's thread (releases and bookkeeping)
    process_cpu_s: float  # CPU seconds of the whole process over the replay
    image_lane_cpu_s: float = float("nan")  # CPU seconds of the runner's image lane (its own count; nan: none)
    rotations: int = 0  # LiDAR rotations played
    phase_lock: dict | None = None  # a phase-locked image lane's PhaseLockStats (lifts, skips, ...); None otherwise
    # the garbage collector's pauses during the drive, per generation (runtime_ort/heap.py: GcPauses.to_dict)
    gc_pauses: dict | None = None
    slices_held: int = 0  # slice runs whose first slice waited for the next one of its quadrant (LaneConfig.pair_hold_load)
    # slice runs whose K-th decoded box passed the score threshold (StreamingDetector.slice_runs_at_top_k)
    slice_runs_at_top_k: int = 0

    @property
    def drive_s(self) -> float:
        return self.wall_s / self.time_scale

    def latencies_ms(self) -> np.ndarray:
        return np.array([s.latency_ms for s in self.slices if s.emitted], dtype=np.float64)

    def image_ages_ms(self) -> np.ndarray:
        ages = [s.image_age_ms for s in self.slices if s.emitted and np.isfinite(s.image_capture_s)]
        return np.array(ages, dtype=np.float64)

    def staleness_ms(self) -> np.ndarray:
        """``SliceRecord.staleness_ms`` of every emitted slice fused with images of the drive (a slice whose scan
        started before the first image set has none)."""
        values = [s.staleness_ms for s in self.slices if s.emitted and np.isfinite(s.image_capture_s + s.newest_capture_s)]
        return np.array(values, dtype=np.float64)

    @property
    def slices_dropped(self) -> int:
        return sum(s.dropped for s in self.slices)

    @property
    def images_superseded(self) -> int:
        return sum(i.superseded for i in self.images)

    @classmethod
    def from_dict(cls, d: dict) -> "Recording":
        """The inverse of ``to_dict`` (a recording of a saved ``replay.json``), detections left out: they are not
        saved. Fields a replay of an older version did not write keep their defaults; keys it does not know are
        ignored."""
        for key in ("slices", "images"):
            if not isinstance(d.get(key) if isinstance(d, dict) else None, list):
                raise ValueError(f"a Recording's {key!r} must be a JSON list of records, got {short_repr(d.get(key) if isinstance(d, dict) else d)}")
        slices = tuple(SliceRecord(**_known_fields(SliceRecord, x)) for x in d["slices"])
        images = tuple(ImageRecord(**_known_fields(ImageRecord, x)) for x in d["images"])
        return cls(**_known_fields(cls, d, exclude=("slices", "images")), slices=slices, images=images)

    def to_dict(self) -> dict:
        out = _json_fields(self, exclude=("slices", "images"))
        out["slices"] = [s.to_dict() for s in self.slices]
        out["images"] = [i.to_dict() for i in self.images]
        return out


def _json_fields(record, exclude: tuple[str, ...] = ()) -> dict:
    """A record's fields by name, NaN written as None (JSON has no NaN)."""
    values = {f.name: getattr(record, f.name) for f in fields(record) if f.name not in exclude}
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in values.items()}


def _known_fields(cls, d: dict, exclude: tuple[str, ...] = ()) -> dict:
    """The inverse of ``_json_fields``: the keys of ``d`` that name fields of ``cls``, None read back as NaN for a
    float field (a time or CPU count that was NaN); an optional field keeps None (``phase_lock``)."""
    if not isinstance(d, dict):
        raise ValueError(f"a {cls.__name__} record must be a JSON object, got {short_repr(d)}")
    out = {}
    for f in fields(cls):
        if f.name in d and f.name not in exclude:
            v = d[f.name]
            out[f.name] = float("nan") if v is None and f.type in ("float", float) else v
            _check_scalar(cls, f.name, f.type, out[f.name])
    return out


# The scalar field types a record holds, by their annotation (strings: ``from __future__ import annotations``), and
# the JSON values each accepts; a report over a float "soon" failed deep inside numpy.
_SCALARS = {"float": (int, float), "int": (int,), "bool": (bool,), "str": (str,)}


def _check_scalar(cls, name: str, annotation: object, value: object) -> None:
    kinds = _SCALARS.get(annotation if isinstance(annotation, str) else getattr(annotation, "__name__", ""))
    if kinds is None:
        return  # a container or an optional field: its readers check it
    if (isinstance(value, bool) and bool not in kinds) or not isinstance(value, kinds):
        raise ValueError(f"{cls.__name__}.{name} must be a JSON {annotation}, got {short_repr(value)}")


def full_collections(gc_pauses: list[dict | None]) -> tuple[int, float] | None:
    """(count, longest pause ms) of the garbage collector's full collections over recordings' ``gc_pauses``
    (``Recording.gc_pauses`` or its JSON); None when none of them recorded any (replays before 2026-12-04)."""
    full = [p["gen2"] for p in gc_pauses if p]
    if not full:
        return None
    return sum(g["collections"] for g in full), max(g["max_ms"] for g in full)


def percentiles(values: np.ndarray, qs: tuple[float, ...] = (50, 95, 99)) -> dict[str, float | None]:
    """{"p50": ..., "p95": ..., "p99": ..., "max": ...}; None when there are no values."""
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        return {**{f"p{q:g}": None for q in qs}, "max": None}
    return {**{f"p{q:g}": float(np.percentile(values, q)) for q in qs}, "max": float(values.max())}


STALE_MS = 25.0  # staleness added above which a slice counts as stale in the breakdown below (issue 22's AVX-512 line)


def staleness_by_recent_images(
    recordings: list[Recording], period_s: float, threshold_ms: float = STALE_MS
) -> dict[int, tuple[int, int]]:
    """Where the stale slices are: number of image sets released in the rotation before a slice's scan start ->
    (slices whose staleness added exceeds ``threshold_ms``, slices with a staleness added), over every emitted slice
    fused with images of its drive.

    An image lane that keeps up on average but not with a burst of frames (LiDAR-synchronised cameras firing in one
    rotation) shows its stale slices gathered at the high counts; one that is simply too slow, at every count. A
    slice's scan start is taken as ``scan_end_s - period_s / num_slices`` (equal sectors); an image set counts when
    released in ``[scan start - period_s, scan start)``, superseded or not (the lane had it to consider)."""
    if isinstance(period_s, bool) or not (isinstance(period_s, (int, float)) and np.isfinite(period_s) and period_s > 0):
        raise ValueError(f"period_s must be a finite number of seconds > 0, got {period_s!r}")
    out: dict[int, list[int]] = {}
    for rec in recordings:
        released = np.sort(np.array([i.release_s for i in rec.images if np.isfinite(i.release_s)], dtype=np.float64))
        for s in rec.slices:
            if not (s.emitted and np.isfinite(s.image_capture_s + s.newest_capture_s)):
                continue
            start = s.scan_end_s - period_s / s.num_slices
            n = int(np.searchsorted(released, start, side="left") - np.searchsorted(released, start - period_s, side="left"))
            counts = out.setdefault(n, [0, 0])
            counts[0] += bool(s.staleness_ms > threshold_ms)
            counts[1] += 1
    return {n: (stale, total) for n, (stale, total) in sorted(out.items())}
