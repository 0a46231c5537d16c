"""The benchmark's output: the text table, the pass/fail lines of the issue's targets, and the JSON document.

Units: GMAC = 1e9 multiply-accumulates (the paper's "GFLOPS" column); GFLOP/s counts 2 FLOPs per MAC; times are
milliseconds of wall clock. Every time figure is a median unless labelled otherwise, with its repeat count.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

from streamdet.benchmarks.prepost import format_prepost, prepost_to_dict
from streamdet.benchmarks.probe import ProbeResult
from streamdet.benchmarks.streaming import LaneStats, StreamingResult, sweeps_per_round
from streamdet.benchmarks.streaming_schedules import format_schedules
from streamdet.benchmarks.table import CROP_PAIRS, RowResult
from streamdet.benchmarks.timing import MIN_P95_SAMPLES, TimingStats

# The targets (a benchmark, not timed tests).
TORCH_OVER_ORT_MIN = 1.3  # onnxruntime fp32 at least this much faster than PyTorch eager, every graph
CROP_SPEEDUP_MIN = 3.5  # cropped rows this much faster than uncropped (their MAC ratio is 4)
PEAK_FRACTION_MIN = 0.60  # conv-heavy graphs reach this fraction of the matmul probe
BUSY_OVER_IDLE_P95_MAX = 1.5  # slice p95 with a busy image lane vs idle
REAL_TIME_FACTOR_MAX = 1.0  # slice p50 over the per-slice budget of a 10 Hz LiDAR
# Other processes using more than this share of the CPUs the benchmark may run on (on average during the run), or
# more than BUSY_OTHER_CPUS of them where that is more, flag a busy machine: relative, so a few daemons on a many-core
# host do not; the floor keeps a 1- or 2-CPU machine's threshold where it was (0.2 CPUs).
BUSY_OTHER_FRACTION = 0.1
BUSY_OTHER_CPUS = 0.2
INT8_SPEEDUP_MIN = {"image": 2.5, "conv3d": 2.5, "slice": 1.0}  # int8 over fp32, by row kind (int8 issue)

UNITS = "GMAC = 1e9 multiply-accumulates (FLOPs = 2 x MACs); times in ms of wall clock (median, p95 in brackets)"
# The peak probe runs at the start and at the end: a best run that changed by more than this between them means the
# machine's speed changed during the run (a neighbour, a clock change), which no busy-CPU figure may show (a slowed
# host, benchmarks/RESULTS.md: probe 168 against 422 GFLOP/s quiet, other processes at 0.008 CPUs).
PROBE_DRIFT_MAX = 0.15
# MIN_P95_SAMPLES (benchmarks/timing.py, as prepost.py reads it too): a p95 of fewer samples prints "n/a" and
# decides no target.


def probe_drift(start: ProbeResult, end: ProbeResult) -> float:
    """The end probe's best run over the start's, less 1 (-0.25: a quarter slower at the end)."""
    return end.gflops_per_s / start.gflops_per_s - 1.0


def busy_threshold(cpus: int | None) -> float:
    """The other processes' CPUs above which a run on ``cpus`` CPUs was on a busy machine (None: BUSY_OTHER_CPUS)."""
    return max(BUSY_OTHER_CPUS, BUSY_OTHER_FRACTION * (cpus or 0))


@dataclass(frozen=True)
class Target:
    name: str
    met: bool | None  # None: could not be evaluated (say why in detail)
    detail: str

    def line(self) -> str:
        verdict = {True: "MET   ", False: "MISSED", None: "n/a   "}[self.met]
        return f"  [{verdict}] {self.name}: {self.detail}"


def _by_key(rows: Sequence[RowResult]) -> dict[str, RowResult]:
    return {r.key: r for r in rows}


def evaluate_targets(rows: Sequence[RowResult], peak: ProbeResult, streaming: StreamingResult | None) -> list[Target]:
    targets = []
    ratios = [(r, r.torch_over_ort) for r in rows]
    measured = [(r, x) for r, x in ratios if x is not None]
    if measured:
        misses = [f"{r.module} {x:.2f}x" for r, x in measured if x < TORCH_OVER_ORT_MIN]
        worst = min(x for _, x in measured)
        skipped = len(ratios) - len(measured)
        rewritten = [r.torch_export.median_ms / r.fp32.median_ms for r, _ in measured if r.torch_export is not None]
        targets.append(
            Target(
                f"onnxruntime fp32 >= {TORCH_OVER_ORT_MIN}x faster than PyTorch eager (the module as trained), each graph",
                not misses,
                (f"worst {worst:.2f}x" + (f"; below: {', '.join(misses)}" if misses else ""))
                + (f" ({skipped} row(s) without PyTorch timing)" if skipped else "")
                + (f"; against PyTorch on the export's rewrites: worst {min(rewritten):.2f}x" if rewritten else ""),
            )
        )
    else:
        targets.append(Target(f"onnxruntime fp32 >= {TORCH_OVER_ORT_MIN}x faster than PyTorch eager", None, "no PyTorch timing"))

    by_key = _by_key(rows)
    for full, cropped, what in CROP_PAIRS:
        a, b = by_key.get(full), by_key.get(cropped)
        if a is None or b is None:
            continue
        speedups = {"fp32": a.fp32.median_ms / b.fp32.median_ms}
        if a.fp16 is not None and b.fp16 is not None:
            speedups["fp16"] = a.fp16.median_ms / b.fp16.median_ms
        targets.append(
            Target(
                f"cropping speeds the {what} up >= {CROP_SPEEDUP_MIN}x",
                speedups["fp32"] >= CROP_SPEEDUP_MIN,
                ", ".join(f"{k} {v:.2f}x" for k, v in speedups.items()) + f" (MAC ratio {a.gmac / b.gmac:.2f})",
            )
        )

    targets.extend(_int8_targets(rows))
    fractions = [(r, r.gflops_per_s / peak.gflops_per_s) for r in rows]
    low = [f"{r.module} {f:.0%}" for r, f in fractions if f < PEAK_FRACTION_MIN]
    targets.append(
        Target(
            f"conv-heavy graphs >= {PEAK_FRACTION_MIN:.0%} of the measured peak ({peak.gflops_per_s:.0f} GFLOP/s)",
            not low,
            f"range {min(f for _, f in fractions):.0%}..{max(f for _, f in fractions):.0%}" + (f"; below: {', '.join(low)}" if low else ""),
        )
    )

    if streaming is None:
        targets.append(Target("streaming targets", None, "streaming section skipped"))
        return targets
    s = streaming
    targets.append(_busy_over_idle_target(s))
    for label, lane in (("image lane idle", s.idle), ("image lane busy", s.busy)):
        rtf = s.real_time_factor(lane)
        targets.append(
            Target(
                f"slice lane keeps up with a 10 Hz LiDAR in {s.num_slices} slices ({label})",
                rtf <= REAL_TIME_FACTOR_MAX,
                f"p50 {lane.latency.median_ms:.2f} ms vs budget {s.slice_budget_ms:.2f} ms: real-time factor {rtf:.2f}",
            )
        )
    for stage, what in (("pre", "pillarize 30,000 points"), ("post", "post-process 500 candidates")):
        cases = [c for c in s.prepost if c.stage == stage]
        if cases:
            targets.append(
                Target(
                    f"{what} <= {cases[0].budget_ms:g} ms (p50, every case)",
                    all(c.met for c in cases),
                    "; ".join(f"{c.name.split(', ', 1)[1]} {c.stats.median_ms:.2f} ms" for c in cases),
                )
            )
    return targets


def _busy_over_idle_target(s: StreamingResult) -> Target:
    """Busy over idle slice p95, judged only where both p95s rest on MIN_P95_SAMPLES samples or more (met None
    below: a p95 of 16 samples is nearly their maximum, one outlier decides it)."""
    name = f"slice p95 with a busy image lane <= {BUSY_OVER_IDLE_P95_MAX}x idle"
    busy, idle = s.busy.latency, s.idle.latency
    if min(busy.count, idle.count) < MIN_P95_SAMPLES:
        return Target(name, None, f"p95 of {busy.count} busy / {idle.count} idle samples: fewer than {MIN_P95_SAMPLES} "
                                  "(the JSON has the figures, with their counts)")  # fmt: skip
    return Target(name, s.busy_over_idle_p95 <= BUSY_OVER_IDLE_P95_MAX,
                  f"{busy.p95_ms:.2f} / {idle.p95_ms:.2f} ms = {s.busy_over_idle_p95:.2f}x")  # fmt: skip


def _int8_targets(rows: Sequence[RowResult]) -> list[Target]:
    """int8 >= 2.5x fp32 for the image encoder and the lifter convolutions (3D, or the flat lifter's 2D ones), faster than fp32 for the slice graph (no
    lines when nothing was timed in int8, --no-int8)."""
    targets: list[Target] = []
    if all(r.int8 is None for r in rows):
        return targets
    for kind, what in (("image", "image encoder"), ("conv3d", "lifter convolutions"), ("slice", "slice graph")):
        least = INT8_SPEEDUP_MIN[kind]
        kind_rows = [r for r in rows if r.kind == kind]
        timed = [(r, r.int8_speedup) for r in kind_rows if r.int8_speedup is not None]
        if not kind_rows:
            continue
        name = f"int8 {'faster than' if least == 1.0 else f'>= {least}x'} fp32, {what}"
        if not timed:
            targets.append(Target(name, None, "no int8 timing"))
            continue
        targets.append(
            Target(name, all(x > least if least == 1.0 else x >= least for _, x in timed),
                   ", ".join(f"{r.module} {x:.2f}x" for r, x in timed))  # fmt: skip
        )
    return targets


# ---- text ----------------------------------------------------------------------------------------------------
def _ms(stats: TimingStats | None) -> str:
    if stats is None:
        return "-"
    digits = 1 if stats.median_ms >= 10 else 2
    p95 = f"{stats.p95_ms:.{digits}f}" if stats.count >= MIN_P95_SAMPLES else "n/a"
    return f"{stats.median_ms:.{digits}f} ({p95})"


def _noise(stats: TimingStats) -> str:
    return f"{stats.min_ms:.3g}-{stats.max_ms:.3g}"


def _pillar_words(pillars: dict | None) -> str:
    if not pillars:
        return ""
    return (
        f" of the bundled nuScenes sweep ({pillars['uncropped']:,} pillars on the whole grid; the cropped row: "
        f"{pillars['cropped']:,} in quadrant {pillars['cropped_quadrant']}, the busiest)"
    )


def _identity(m: dict) -> str:
    """", GenuineIntel family 6 model 167 stepping 1" of the machine's cpu_identity; "" where unknown (older results)."""
    ident = m.get("cpu_identity") or {}
    words = [str(ident["vendor_id"])] if ident.get("vendor_id") else []
    words += [f"{k} {ident[k]}" for k in ("family", "model", "stepping") if ident.get(k) is not None]
    return (", " + " ".join(words)) if words else ""


def _probe_words(p: ProbeResult) -> str:
    return f"best {p.gflops_per_s:.1f} (median {p.median_gflops_per_s:.1f})"


def format_header(meta: dict, peak: ProbeResult, probes: tuple[ProbeResult, ProbeResult] | None = None) -> str:
    """The machine, the software, the method and the peak probe; ``probes``: the probe at the start and at the end
    (apart, and a WARNING where their best runs differ by more than PROBE_DRIFT_MAX); None: the merged one alone."""
    m = meta["machine"]
    if m.get("cpu_flags_source", "/proc/cpuinfo") is None:  # absent in results recorded before it
        flags = "SIMD flags unknown"
    else:
        flags = ", ".join(m["cpu_flags"]) or "none of the SIMD flags reports list"
        flags += ": numpy's CPU features" if m.get("cpu_flags_source") == "numpy" else ""
    if m.get("cpuid_mask"):  # absent in results recorded before the mask existed
        flags += f"; CPUID masked to {m['cpuid_mask']}: the kernels' instruction set, not the silicon's"
    lines = [
        f"streamdet-bench  {meta['date']}  preset {meta['preset']}",
        f"machine: {m['cpu_model']} ({flags}){_identity(m)}, {m['logical_cpus']} logical CPUs"
        + (f" ({usable} usable by this process)" if (usable := m.get("usable_cpus")) is not None else "")  # absent in older results
        + f", {meta['threads']} threads; "
        f"load average (1/5/15 min) {'/'.join(str(v) for v in m['load_average_1_5_15'])} at start; "
        + (
            f"other processes used {others:.2f} CPUs on average during the run"
            if (others := meta.get("other_cpu_use")) is not None
            else "CPU use of other processes unknown"
        ),
        f"onnxruntime {m['onnxruntime']} (CPU, ORT_ENABLE_ALL), torch {m['torch']} (eager, inference_mode); "
        f"repeats {meta['repeat']} after {meta['warmup']} warm-up run(s), {meta['budget_s']:.0f} s budget per measurement"
        + (
            f"; a row's measurements take turns in {rounds} rounds, each turn after {meta['settle_s'] * 1e3:.0f} ms of "
            "untimed runs"
            if (rounds := meta.get("rounds"))
            else ""
        ),
        f"peak probe: {peak.size}^3 fp32 MatMul in onnxruntime, best of {peak.runs} runs (at the start and the end): "
        f"{peak.gflops_per_s:.1f} GFLOP/s (median {peak.median_gflops_per_s:.1f})"
        + (f"; at the start {_probe_words(probes[0])}, at the end {_probe_words(probes[1])}" if probes else "")
        + (
            f"; estimate from FMA width x the reported {m['cpu_mhz']:.0f} MHz x "
            + (f"{cores} physical core(s)" if (cores := m.get("peak_estimate_cores")) else f"{meta['threads']} threads")
            + f" (not a bound): {estimate:.0f} GFLOP/s"
            if (estimate := m.get("peak_estimate_gflops_per_s", m.get("nominal_peak_gflops_per_s")))
            else ""
        ),
        f"input as in the paper's Table 3: 1 image, 30,000 points{_pillar_words(meta.get('slice_pillars'))}; {UNITS}",
    ]
    others = meta.get("other_cpu_use")
    # the CPUs that figure counts (its affinity set); results before it was recorded counted the whole machine's
    watched = m.get("other_cpu_use_cpus")
    cpus = watched or m.get("logical_cpus")
    if others is not None and others > busy_threshold(cpus):
        of = f"{others:.2f} of the {watched} CPUs this process may run on" if watched else f"{others:.2f} of {cpus} CPUs"
        lines.append(
            f"WARNING: the machine was busy: other processes used {of} during the run, "
            "so these times are pessimistic and noisy; re-run on a quiet machine"
        )
    if probes and abs(drift := probe_drift(*probes)) > PROBE_DRIFT_MAX:
        lines.append(
            f"WARNING: the peak probe's best run changed by {drift:+.0%} between the start ({probes[0].gflops_per_s:.1f} "
            f"GFLOP/s) and the end ({probes[1].gflops_per_s:.1f}): the machine's speed changed during the run (a "
            "neighbour, a clock change), so rows timed minutes apart are not comparable; re-run on a quiet machine"
        )
    return "\n".join(lines)


def format_rows(rows: Sequence[RowResult], peak: ProbeResult) -> str:
    header = (
        "module", "GMAC", "onnx/torch", "ms fp32 (p95)", "ms fp16 (p95)", "ms int8 (p95)", "fp32/int8", "ms torch", "torch/ort",
        "GFLOP/s", "% peak", "fp32 min-max", "n",
    )  # fmt: skip
    table = []
    for r in rows:
        ratio = r.torch_over_ort
        table.append(
            (
                r.module,
                f"{r.gmac:.3f}",
                "-" if r.graph_ratio is None else f"{r.graph_ratio:.3f}",
                _ms(r.fp32),
                _ms(r.fp16),
                _ms(r.int8),
                "-" if r.int8_speedup is None else f"{r.int8_speedup:.2f}",
                "-" if r.torch is None else (f"{r.torch.median_ms:.1f}" if r.torch.median_ms >= 10 else f"{r.torch.median_ms:.2f}"),
                "-" if ratio is None else f"{ratio:.2f}",
                f"{r.gflops_per_s:.1f}",
                f"{r.gflops_per_s / peak.gflops_per_s:.0%}",
                _noise(r.fp32),
                f"{r.fp32.count}",
            )
        )
    widths = [max(len(str(x)) for x in col) for col in zip(header, *table)]
    fmt = lambda cells: "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))  # noqa: E731
    lines = [fmt(header)] + [fmt(t) for t in table]
    notes = [f"  {r.module}: {note}" for r in rows for note in r.notes]
    timed = [st for r in rows for st in (r.fp32, r.fp16, r.int8) if st is not None]
    if any(st.count < MIN_P95_SAMPLES for st in timed):
        notes.append(f"  p95 n/a: fewer than {MIN_P95_SAMPLES} timed runs (the JSON has it, with the count)")
    if any(r.gflops_per_s > peak.gflops_per_s for r in rows):
        notes.append(
            "  % peak above 100: onnxruntime's convolution kernels outrun its own large MatMul here; the probe is the "
            "attainable MatMul rate, not an upper bound (nor is the estimate in the header)"
        )
    if notes:
        lines += ["notes:"] + notes
    profiled = [r for r in rows if r.profiles]
    if profiled:
        lines.append("onnxruntime profile, top ops by kernel time (fp32):")
        lines += [f"  {r.module}: {r.profiles['fp32'].format()}" for r in profiled if "fp32" in r.profiles]
    return "\n".join(lines)


def _lane_line(label: str, lane: LaneStats | TimingStats) -> str:
    t = lane.latency if isinstance(lane, LaneStats) else lane
    n = f"n={t.count}" + (f" of {t.requested} (time budget)" if t.reduced else "")
    p95 = f"{t.p95_ms:8.2f} ms" if t.count >= MIN_P95_SAMPLES else f"{'n/a':>11}"  # under 20: the max, near enough
    return f"  {label:<44} p50 {t.median_ms:8.2f} ms  p95 {p95}  min-max {_noise(t)} ms  {n}"


def _p95_ms(t: TimingStats) -> str:
    """"12.3 ms", or "n/a" under MIN_P95_SAMPLES samples."""
    return f"{t.p95_ms:.1f} ms" if t.count >= MIN_P95_SAMPLES else "n/a"


def _busy_over_idle(s: StreamingResult) -> str:
    """"1.23x", or "n/a" where either lane has fewer than MIN_P95_SAMPLES samples (as its p95 prints)."""
    if min(s.busy.latency.count, s.idle.latency.count) < MIN_P95_SAMPLES:
        return "n/a"
    return f"{s.busy_over_idle_p95:.2f}x"


def _stage(lane: LaneStats, name: str) -> str:
    s = lane.stages.get(name)
    return "-" if s is None else f"{s['p50_ms']:.2f}"


def _lift(lane: LaneStats) -> str:
    """The lift's stages: the lifter graph, or (DetectorConfig.camera_terms) a term run per camera and a tail per
    quadrant, which is how the detector lifts by default where the export allows it."""
    if "volumetric_lifter" in lane.stages or "lifter_tail" not in lane.stages:
        return f"lifter p50 {_stage(lane, 'volumetric_lifter')} ms"
    return (f"lift through per-camera terms: term p50 {_stage(lane, 'lifter_partial')} ms a camera, "
            f"tail p50 {_stage(lane, 'lifter_tail')} ms a quadrant")


def _turns(s: StreamingResult) -> str:
    """How the slice-lane phases were taken: in turns (how many rounds), or one after the other."""
    phases = "idle" + (f", idle with {s.all_cores} threads" if s.idle_all_cores is not None else "") + " and busy"
    if s.phase_rounds > 1:
        return (f"({phases} taken in turns: {s.phase_rounds} rounds of {', '.join(map(str, _per_round(s)))} sweep(s) "
                "each, the busy image lane started and stopped every round)")  # fmt: skip
    if s.config.sweeps == 1:
        return f"({phases}: one sweep each, in one round)"
    return (f"({phases} one after the other, not in turns: an image update takes too long to stop the busy image lane "
            "every round, StreamingConfig.image_budget_s)")  # fmt: skip


def _per_round(s: StreamingResult) -> list[int]:
    return sorted(set(sweeps_per_round(s.config.sweeps, s.phase_rounds)), reverse=True)


def format_streaming(s: StreamingResult) -> str:
    pts = f"{min(s.num_points):,}..{max(s.num_points):,}"
    lines = [
        f"streaming ({s.preset} export, {s.precision_label}, {', '.join(s.providers) or 'CPUExecutionProvider'}, "
        "1 intra-op thread per session; bundled nuScenes sweep in "
        f"{s.num_slices} slices of {pts} points; {s.num_cameras} cameras at {s.image_size[0]}x{s.image_size[1]})",
        _lane_line("slice lane, image lane idle", s.idle),
        *(
            [_lane_line(f"slice lane, image lane idle, {s.all_cores} threads", s.idle_all_cores)]
            if s.idle_all_cores is not None
            else []
        ),
        _lane_line("slice lane, image lane busy", s.busy),
        _lane_line("slice lane, one sequential queue", s.sequential_slice),
        f"    (queue: {s.sequential_horizon_ms:.0f} ms of arrivals, slices every {s.slice_budget_ms:.2f} ms, images at "
        f"{s.config.image_hz:g} Hz: {s.sequential_images_served} image updates served, {s.sequential_images_superseded} "
        f"superseded; slice wait p50 {s.sequential_wait.median_ms:.1f} ms, p95 {_p95_ms(s.sequential_wait)}, "
        f"n={s.sequential_wait.count})",
        f"  busy / idle slice p95: {_busy_over_idle(s)} ({s.image_busy_updates} image updates finished while the "
        "busy slices ran; the image lane ran throughout)",
        "    " + _turns(s),
        _lane_line(f"image lane alone ({s.num_cameras} cameras)", s.image_alone),
        f"    encoder p50 {_stage(s.image_alone, 'image_encoder')} ms, {_lift(s.image_alone)}"
        + (f"; with slices running: update p50 {_stage(s.busy, 'image_total')} ms" if "image_total" in s.busy.stages else ""),
    ]
    for label, lane in (("idle", s.idle), ("busy", s.busy)):
        pre, post, graph = lane.share("pre"), lane.share("post"), lane.share("slice_head")
        if pre is not None:
            lines.append(
                f"  slice time split ({label}): pre {pre:.0%} ({_stage(lane, 'pre')} ms p50), graph {graph:.0%} "
                f"({_stage(lane, 'slice_head')} ms), post {post:.0%} ({_stage(lane, 'post')} ms); pre + post {pre + post:.0%}"
            )
    for key, prof in sorted(s.profiles.items()):
        lines.append(f"  profile {key}: {prof.run_ms:.2f} ms per run (median of {prof.runs}); {prof.format()}")
    lines.append(
        f"  real-time (10 Hz LiDAR, {s.num_slices} slices -> {s.slice_budget_ms:.2f} ms per slice): factor "
        f"{s.real_time_factor(s.idle):.2f} idle, {s.real_time_factor(s.busy):.2f} busy (<= 1 keeps up)"
        + (
            f"; {s.real_time_factor(s.idle_all_cores):.2f} idle with {s.all_cores} slice threads"
            if s.idle_all_cores is not None
            else ""
        )
    )
    lines += format_schedules(s.schedules)
    if s.prepost:
        lines.append(format_prepost(s.prepost))
    return "\n".join(lines)


def format_report(
    doc_meta: dict, rows: Sequence[RowResult], peak: ProbeResult, streaming: StreamingResult | None, targets: Sequence[Target],
    probes: tuple[ProbeResult, ProbeResult] | None = None,
) -> str:
    parts = [format_header(doc_meta, peak, probes), "", format_rows(rows, peak)]
    if streaming is not None:
        parts += ["", format_streaming(streaming)]
    parts += ["", "targets:"] + [t.line() for t in targets]
    return "\n".join(parts)


# ---- JSON ----------------------------------------------------------------------------------------------------
def _stats(stats: TimingStats | None) -> dict | None:
    return None if stats is None else stats.to_dict()


def row_to_dict(r: RowResult, peak: ProbeResult) -> dict:
    return {
        "module": r.module,
        "key": r.key,
        "gmac": r.gmac,
        "graph_gmac": r.graph_gmac,
        "graph_gmac_ratio": r.graph_ratio,
        "ms_fp32": r.fp32.median_ms,
        "ms_fp16": None if r.fp16 is None else r.fp16.median_ms,
        "ms_int8": None if r.int8 is None else r.int8.median_ms,
        "int8_speedup": r.int8_speedup,
        "ms_torch": None if r.torch is None else r.torch.median_ms,
        "torch_over_ort": r.torch_over_ort,
        "gflops_per_s": r.gflops_per_s,
        "peak_fraction": r.gflops_per_s / peak.gflops_per_s,
        "fp32": _stats(r.fp32),
        "fp16": _stats(r.fp16),
        "int8": _stats(r.int8),
        "torch": _stats(r.torch),
        "ms_torch_export_form": None if r.torch_export is None else r.torch_export.median_ms,
        "torch_export_form": _stats(r.torch_export),
        "fp16_error": r.fp16_error,
        "int8_error": r.int8_error,
        "notes": list(r.notes),
        "profile": {k: v.to_dict(top=10) for k, v in r.profiles.items()},
    }


def _lane(lane: LaneStats) -> dict:
    return {"latency": lane.latency.to_dict(), "stages": {k: dict(v) for k, v in lane.stages.items()}}


def streaming_to_dict(s: StreamingResult) -> dict:
    return {
        "export_dir": s.export_dir,
        "preset": s.preset,
        "precision": s.precision,
        "image_precision": s.image_precision or s.precision,
        "num_slices": s.num_slices,
        "points_per_slice": list(s.num_points),
        "image_size": list(s.image_size),
        "num_cameras": s.num_cameras,
        "threads_per_session": 1,
        "providers": list(s.providers),  # the slice session's (the bench pins the CPU provider)
        "slice_budget_ms": s.slice_budget_ms,
        "slice_idle": _lane(s.idle),
        "slice_busy": _lane(s.busy),
        "slice_idle_all_cores": None if s.idle_all_cores is None else _lane(s.idle_all_cores),
        "all_cores": s.all_cores,
        "image_updates_during_busy": s.image_busy_updates,
        "busy_over_idle_p95": s.busy_over_idle_p95,
        # idle, idle with all_cores threads and busy took turns in this many rounds (1: one after the other), a share
        # of config.sweeps each round (phase_sweeps_per_round)
        "phase_rounds": s.phase_rounds,
        "phase_sweeps_per_round": sweeps_per_round(s.config.sweeps, s.phase_rounds),
        "sequential": {
            "slice_latency": s.sequential_slice.to_dict(),
            "slice_wait": s.sequential_wait.to_dict(),
            "images_served": s.sequential_images_served,
            "images_superseded": s.sequential_images_superseded,
            "horizon_ms": s.sequential_horizon_ms,
            "image_hz": s.config.image_hz,
        },
        "image_lane_alone": _lane(s.image_alone),
        "pre_post_share_idle": _sum_share(s.idle),
        "pre_post_share_busy": _sum_share(s.busy),
        "real_time_factor_idle": s.real_time_factor(s.idle),
        "real_time_factor_busy": s.real_time_factor(s.busy),
        "keeps_up_idle": s.real_time_factor(s.idle) <= REAL_TIME_FACTOR_MAX,
        "keeps_up_busy": s.real_time_factor(s.busy) <= REAL_TIME_FACTOR_MAX,
        "config": dataclasses.asdict(s.config),
        "profiles": {k: v.to_dict(top=10) for k, v in s.profiles.items()},
        "prepost": prepost_to_dict(s.prepost),
        "image_lane_schedules": s.schedules,
    }


def _sum_share(lane: LaneStats) -> float | None:
    return lane.share("pre", "post")


def peak_to_dict(peak: ProbeResult, probes: tuple[ProbeResult, ProbeResult] | None = None) -> dict:
    """The merged probe (the keys of every result), and with ``probes`` each apart and the drift between them."""
    out = peak.to_dict()
    if probes is not None:
        start, end = probes
        out |= {"start": start.to_dict(), "end": end.to_dict(), "end_over_start": end.gflops_per_s / start.gflops_per_s,
                "drift_warning": abs(probe_drift(start, end)) > PROBE_DRIFT_MAX}  # fmt: skip
    return out


def build_document(
    meta: dict, rows: Sequence[RowResult], peak: ProbeResult, streaming: StreamingResult | None, targets: Sequence[Target],
    probes: tuple[ProbeResult, ProbeResult] | None = None,
) -> dict:
    """The JSON document; docs/cli.md ("streamdet-bench") describes its keys, schema_version in meta."""
    return {
        "meta": meta,
        "units": UNITS,
        "peak": peak_to_dict(peak, probes),
        "rows": [row_to_dict(r, peak) for r in rows],
        "streaming": None if streaming is None else streaming_to_dict(streaming),
        "targets": [{"name": t.name, "met": t.met, "detail": t.detail} for t in targets],
    }
