"""What a replay prints and writes: the CPU it ran on, one row per mode, per-class scores, stage work, JSON.

The JSON (``--json``) has exactly the keys of issue 20: ``{"config": {...}, "modes": {"streaming" | "full_sweep" |
"sequential": {map_streaming, map_offline, nds_streaming, latency_ms {p50, p95, p99, max}, slices_dropped,
slices_total, image_age_ms {p50, p95}}}}``; everything else (per class, moving / static, lane CPU, stage GMAC, every
slice's record) goes to ``--out DIR`` (``replay.json``).
"""

from __future__ import annotations

import math

import numpy as np

from streamdet.core.cpu import cpu_info, cpu_line  # noqa: F401  (cpu_info re-exported: moved to core.cpu, imported from here too)
from streamdet.replay.record import STALE_MS, full_collections, percentiles, staleness_by_recent_images
from streamdet.replay.run import ModeResult, ReplayResult


def mode_key(mode: str) -> str:
    """The JSON key of a mode: ``full-sweep`` -> ``full_sweep``."""
    return mode.replace("-", "_")


def mode_summary(result: ModeResult) -> dict:
    """The issue's per-mode JSON object."""
    recs = result.recordings
    lat = np.concatenate([r.latencies_ms() for r in recs]) if recs else np.zeros(0)
    ages = np.concatenate([r.image_ages_ms() for r in recs]) if recs else np.zeros(0)
    s = result.scores
    return {
        "map_streaming": _num(s.streaming.map),
        "map_offline": _num(s.offline.map),
        "nds_streaming": _num(s.streaming.nds),
        "latency_ms": percentiles(lat, (50, 95, 99)),
        "slices_dropped": sum(r.slices_dropped for r in recs),
        "slices_total": sum(len(r.slices) for r in recs),
        "image_age_ms": {k: v for k, v in percentiles(ages, (50, 95)).items() if k != "max"},
    }


def image_lane_summary(result: ModeResult) -> dict:
    """Issue 22's figures of a mode: staleness added by processing (``SliceRecord.staleness_ms``) p50 / p95 / p99 /
    max, and the image lane's CPU milliseconds per LiDAR rotation (the runner's own count; None without one)."""
    recs = result.recordings
    stale = np.concatenate([r.staleness_ms() for r in recs]) if recs else np.zeros(0)
    cpu = [r.image_lane_cpu_s for r in recs if math.isfinite(r.image_lane_cpu_s)]
    rotations = sum(r.rotations for r in recs if math.isfinite(r.image_lane_cpu_s))
    return {"staleness_ms": percentiles(stale, (50, 95, 99)),
            "image_lane_cpu_ms_per_rotation": 1e3 * sum(cpu) / rotations if cpu and rotations else None}  # fmt: skip


def json_report(result: ReplayResult, info: dict) -> dict:
    config = {**result.config.to_dict(), "num_slices": result.num_slices, "precision_label": result.precision_label,
              "scenes": list(result.scenes), "cpu": info, "ground_truth": result.truth_source,
              "notes": list(result.notes), "camera_terms_used": result.camera_terms,
              "providers_used": list(result.providers)}  # fmt: skip
    return {"config": config, "modes": {mode_key(m): mode_summary(r) for m, r in result.modes.items()}}


def details_report(result: ReplayResult, info: dict) -> dict:
    """Everything: the JSON report plus per-class / moving / static scores, lane CPU, stages and every record."""
    out = json_report(result, info)
    for mode, r in result.modes.items():
        out["modes"][mode_key(mode)].update(
            streaming=r.scores.streaming.to_dict(), offline=r.scores.offline.to_dict(),
            per_scene_map_streaming=r.scores.per_scene_streaming_map, images_superseded=sum(x.images_superseded for x in r.recordings),
            cpu_share=_cpu_share(r), stages=r.stages, recordings=[x.to_dict() for x in r.recordings],
            slices_fallback=_fallbacks(r),
            slices_coalesced=_coalesced(r),
            **image_lane_summary(r),
        )  # fmt: skip
    return out


def _coalesced(r: ModeResult) -> int:
    """Emitted slices detected in one run with other slices (LaneConfig.coalesce_slices)."""
    return sum(1 for x in r.recordings for s in x.slices if s.emitted and s.coalesced > 1)


def _coalesced_note(r: ModeResult) -> str:
    """The slices-dropped cell's note on coalesced slices (none: nothing)."""
    n = _coalesced(r)
    held = sum(x.slices_held for x in r.recordings)
    return (f" ({n} coalesced" + (f", {held} runs held for the pair" if held else "") + ")") if n else ""


def _fallbacks(r: ModeResult) -> int:
    """Emitted slices that ran the LiDAR-only fallback's graph (ReplayConfig.fallback_export_dir)."""
    return sum(1 for x in r.recordings for s in x.slices if s.emitted and s.fallback)


def _cpu_share(r: ModeResult) -> dict[str, float]:
    """Cores each part used over the mode's wall time. The image lane's is the runner's own count of its thread
    time where it has one: the image sets' updates miss work no set owns (under the phase-locked schedule, frames
    encoded ahead and the later lifts of a frame are charged to no image set)."""
    wall = sum(x.wall_s for x in r.recordings) or 1e-9
    lane = [x.image_lane_cpu_s for x in r.recordings]
    if lane and all(math.isfinite(v) for v in lane):
        image_lane = sum(lane)
    else:
        image_lane = sum(i.cpu_s for x in r.recordings for i in x.images)
    return {
        "slice_lane": sum(s.cpu_s for x in r.recordings for s in x.slices) / wall,
        "image_lane": image_lane / wall,
        "player": sum(x.player_cpu_s for x in r.recordings) / wall,
        "process": sum(x.process_cpu_s for x in r.recordings) / wall,
    }


def _delivery(config) -> str:
    ms = config.camera_delivery_ms
    return "delivered at capture" if ms == 0 else f"delivered {ms:g} ms after capture"


def format_report(result: ReplayResult, info: dict) -> str:
    c = result.config
    period_ms = 1000.0 / c.lidar_hz / result.num_slices
    lines = [
        f"streamdet-replay: {len(result.scenes)} scene(s) of {c.data} ({c.split or 'all'}), {result.precision_label}, "
        f"LiDAR {c.lidar_hz:g} Hz x {result.num_slices} slices ({period_ms:.2f} ms per slice), " + (
            f"cameras {c.camera_hz:g} Hz ({c.camera_trigger} triggers, {_delivery(c)})" if result.uses_images
            else "no cameras (a LiDAR-only export)"),
        f"time scale {c.time_scale:g} (latencies in drive time = wall / {c.time_scale:g}); CPU: {cpu_line(info)}; "
        + (f"onnxruntime {', '.join(result.providers)}; " if result.providers else "")
        + f"{c.threads} thread(s) per session"
        + (f" ({c.image_lane_threads} in the image lane's)" if c.image_lane_threads not in (None, c.threads) else "")
        + f", {c.lanes.max_in_flight} slice worker(s), queue {c.lanes.queue_size}"
        + (f", image lane at nice +{c.lanes.image_lane_nice}" if c.lanes.image_lane_nice and result.uses_images else "")
        + (f", image lane yields at {c.lanes.image_lane_yield_slices} waiting slice(s)"
           if c.lanes.image_lane_yield_slices and result.uses_images else "")
        + (f", up to {c.lanes.coalesce_slices} waiting slices coalesced per run" if c.lanes.coalesce_slices > 1 else "")
        + (f", a quadrant's first slice held for the next above load {c.lanes.pair_hold_load:g}" if c.lanes.pair_hold_load is not None else ""),
        f"ground truth at emission time: {result.truth_source}",
        *[f"  {note}" for note in result.notes],
        "",
        "| mode | streaming mAP | offline mAP | NDS | latency p50 / p95 / p99 / max ms | slices dropped | images superseded "
        "| image age p50 / p95 ms | CPU slice / image lane |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for mode, r in result.modes.items():
        m = mode_summary(r)
        lat, age, cpu = m["latency_ms"], m["image_age_ms"], _cpu_share(r)
        superseded = sum(x.images_superseded for x in r.recordings)
        lines.append(
            f"| {mode} | {_pct(m['map_streaming'])} | {_pct(m['map_offline'])} | {_pct(m['nds_streaming'])} "
            f"| {_ms(lat['p50'])} / {_ms(lat['p95'])} / {_ms(lat['p99'])} / {_ms(lat['max'])} "
            f"| {m['slices_dropped']} of {m['slices_total']}{_coalesced_note(r)} | {superseded} of {sum(len(x.images) for x in r.recordings)} "
            f"| {_ms(age['p50'])} / {_ms(age['p95'])} | {100 * cpu['slice_lane']:.0f} % / {100 * cpu['image_lane']:.0f} % |"
        )
    if c.fallback_export_dir is not None:
        after = "" if c.fallback_after_s is None else f" or image BEV older than {1e3 * c.fallback_after_s:g} ms"
        lines += ["", f"LiDAR-only fallback {c.fallback_export_dir} (slices without image BEV{after}): "
                  + ", ".join(f"{mode} {_fallbacks(r)}" for mode, r in result.modes.items()) + " slices"]  # fmt: skip
    at_cap = {mode: sum(x.slice_runs_at_top_k for x in r.recordings) for mode, r in result.modes.items()}
    if any(at_cap.values()):
        lines += ["", "slice runs whose K-th decoded box passed the score threshold (the graph's top-K cap may have cut "
                  "boxes; streamdet-export --top-k): " + ", ".join(f"{mode} {n}" for mode, n in at_cap.items())]  # fmt: skip
    image_lane = ["", _image_lane_table(result)] if result.uses_images else []
    lines += ["", _gc_line(result), *image_lane, "", _per_class_table(result), "", _stage_table(result), "",
              *_targets(result, period_ms)]  # fmt: skip
    return "\n".join(lines)


def _gc_line(result: ReplayResult) -> str:
    """The garbage collector's full collections during the drives (they stall every Python thread)."""
    how = "heap frozen at each drive's start" if result.config.freeze_heap else "heap not frozen"
    parts = []
    for mode, r in result.modes.items():
        full = full_collections([x.gc_pauses for x in r.recordings])
        if full is not None:
            parts.append(f"{mode} {full[0]} (longest {full[1]:.1f} ms)")
    return f"garbage collector ({how}): full collections during the drives: " + (", ".join(parts) or "not measured")


def _image_lane_table(result: ReplayResult) -> str:
    schedule = result.config.lanes.schedule
    terms = ", per-camera lifts" if result.camera_terms and schedule == "phase-locked" else ""
    rows = [f"image lane, schedule {schedule!r}{terms}:",
            "| mode | staleness added p50 / p95 / p99 / max ms | image age p50 / p95 ms | image-lane CPU ms per rotation |",
            "|---|---|---|---|"]  # fmt: skip
    for mode, r in result.modes.items():
        m, lane = mode_summary(r), image_lane_summary(r)
        st, age, cpu = lane["staleness_ms"], m["image_age_ms"], lane["image_lane_cpu_ms_per_rotation"]
        rows.append(f"| {mode} | {_ms(st['p50'])} / {_ms(st['p95'])} / {_ms(st['p99'])} / {_ms(st['max'])} "
                    f"| {_ms(age['p50'])} / {_ms(age['p95'])} | {_ms(cpu)} |")  # fmt: skip
    for mode, r in result.modes.items():
        stats = [x.phase_lock for x in r.recordings if x.phase_lock is not None]
        if stats:
            total = {k: sum(s[k] for s in stats) for k in stats[0]}
            rows.append(f"{mode}, phase-locked lane: {total['quadrant_lifts']} quadrant lifts, {total['full_updates']} full "
                        f"updates before the lock, {total['quadrants_skipped']} passes skipped (too late), "
                        + (f"{total['ready_lifts']} lifted from the frames ready, " if total.get("ready_lifts") else "")
                        + f"{total['late_lifts']} lifts ended after their slice's predicted arrival"
                        + (f", held back {total['yields']} times for waiting slices ({total['yielded_ms']:.0f} ms, "
                           f"{total.get('holds_cut', 0)} cut at 0.1 s)" if total.get("yields") else "")
                        + (f", {total['cameras_timed_out']} camera frames timed out, {total.get('quadrants_cleared', 0)} "
                           "quadrants left without image" if total.get("cameras_timed_out") else "")
                        + (f", {total['slices_out_of_order']} slices out of order (not taken for the phase)"
                           if total.get("slices_out_of_order") else "")
                        + (f", {total['errors']} steps raised (logged)" if total.get("errors") else ""))  # fmt: skip
    for mode, r in result.modes.items():
        line = _stale_by_burst(r, 1.0 / result.config.lidar_hz)
        if line:
            rows.append(f"{mode}, {line}")
    return "\n".join(rows)


def _stale_by_burst(r: ModeResult, period_s: float) -> str:
    """Slices with staleness added > STALE_MS by the image sets released in the rotation before their scan start
    (``staleness_by_recent_images``): whether the image lane falls behind only after bursts of frames."""
    counts = staleness_by_recent_images(list(r.recordings), period_s)
    if not counts:
        return ""
    return f"staleness added > {STALE_MS:g} ms by image sets released in the rotation before the scan start: {stale_cells(counts)}"


def stale_cells(counts: dict[int, tuple[int, int]]) -> str:
    """``staleness_by_recent_images``'s counts as ``2: 44 of 438 (10 %), 3: ...``."""
    return ", ".join(f"{n}: {stale} of {total} ({100 * stale / total:.0f} %)" for n, (stale, total) in counts.items())


def _per_class_table(result: ReplayResult) -> str:
    classes = [c for c in next(iter(result.modes.values())).scores.offline.classes]
    head = "| AP streaming / offline | " + " | ".join(classes) + " | moving | static |"
    rows = [head, "|---" * (len(classes) + 3) + "|"]
    for mode, r in result.modes.items():
        s, o = r.scores.streaming, r.scores.offline
        cells = [f"{_pct(s.per_class_ap.get(c))} / {_pct(o.per_class_ap.get(c))}" for c in classes]
        cells += [f"{_pct(s.map_moving)} / {_pct(o.map_moving)}", f"{_pct(s.map_static)} / {_pct(o.map_static)}"]
        rows.append(f"| {mode} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def _stage_table(result: ReplayResult) -> str:
    rows = ["| stage (mode) | runs | mean ms | GMAC / run | GFLOP/s |", "|---|---|---|---|---|"]
    for mode, r in result.modes.items():
        for stage in ("slice_head", "image_encoder", "volumetric_lifter", "lifter_partial", "lifter_tail"):
            st = r.stages.get(stage)
            if st and "gflop_per_s" in st:
                rows.append(f"| {stage} ({mode}) | {st['runs']} | {st['mean_ms']:.2f} | {st['gmac_per_run']:.3f} | {st['gflop_per_s']:.1f} |")
            elif st:  # the per-camera lift's pieces (camera_terms.py): no MAC count
                rows.append(f"| {stage} ({mode}) | {st['runs']} | {st['mean_ms']:.2f} | - | - |")
    return "\n".join(rows)


def _targets(result: ReplayResult, period_ms: float) -> list[str]:
    out = ["targets (issue 20):"]
    if "streaming" in result.modes:
        m = mode_summary(result.modes["streaming"])
        p99, age = m["latency_ms"]["p99"], m["image_age_ms"]["p95"]
        out.append(f"  streaming: slices dropped {m['slices_dropped']} (target 0) "
                   f"{'met' if m['slices_dropped'] == 0 else 'MISSED'}; latency p99 {_ms(p99)} ms "
                   f"(target {2 * period_ms:.1f} ms, two slice periods) {_met(p99, 2 * period_ms)}; image age p95 {_ms(age)} ms "
                   f"(target 150 ms) {_met(age, 150.0)}")  # fmt: skip
    if "streaming" in result.modes and "full-sweep" in result.modes:
        s, f = result.modes["streaming"].scores, result.modes["full-sweep"].scores
        diff = 100 * (s.streaming.map - f.streaming.map)
        per = [s.per_scene_streaming_map[k] - f.per_scene_streaming_map[k] for k in s.per_scene_streaming_map]
        spread = f" (per scene {100 * np.mean(per):+.1f} +- {100 * np.std(per):.1f}, min {100 * min(per):+.1f}, n={len(per)})" if per else ""
        verdict = "MISSED" if diff <= 0 else ("met" if not per or min(per) > 0 else "met pooled, not in every scene")
        out.append(f"  streaming mAP at emission time, streaming - full-sweep: {diff:+.1f}{spread} {verdict}")
    if "sequential" in result.modes:
        lat = [r.latencies_ms() for r in result.modes["sequential"].recordings]
        growth = [np.polyfit(np.arange(len(x)), x, 1)[0] for x in lat if len(x) > 2]
        if growth:
            out.append(f"  sequential: latency grows {np.mean(growth) * result.num_slices * result.config.lidar_hz:+.0f} ms "
                       f"per second of drive (first {lat[0][0]:.1f} ms, last {lat[0][-1]:.1f} ms in {result.scenes[0]})")  # fmt: skip
    return out


def _met(value: float | None, target: float) -> str:
    return "n/a" if value is None else ("met" if value <= target else "MISSED")


def _num(x: float | None) -> float | None:
    return None if x is None or (isinstance(x, float) and math.isnan(x)) else float(x)


def _pct(x: float | None) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.1f}"


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"
