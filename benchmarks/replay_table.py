"""The table of ``benchmarks/replay_ab.sh``: one row per (time scale, variant), one value per round in each cell.

    python -m streamdet.benchmarks.replay_table OUT_DIR [--plot FILE.png]

``--plot``: also a picture, one panel per time scale: the distribution (CDF) of the staleness added by processing
over every fused slice of a variant's rounds, the variant's image-lane CPU per rotation in its legend.

Reads ``OUT_DIR/r<round>_scale<S>_<label>/replay.json`` (``streamdet-replay --out``, streaming mode) and
``OUT_DIR/probes_gflops.txt`` (``<run name> <GFLOP/s>`` per line, the host-speed probe before each run). The table
names the CPU its runs ran on (the replay's ``config.cpu``: model, vector extensions, usable threads), and the
staleness picture draws issue 22's target for it: p95 <= 25 ms with AVX-512, <= 100 ms on an AVX2-only part; a CPU
with neither (ARM, or flags that could not be read) has no target, and none is drawn or claimed for it. A line
under the table gives the garbage collector's full collections during the drives where the replays recorded them
(they stop every Python thread: docs/replay.md, "Full garbage collections stall the lanes"), and lines after it
where the stale slices are (staleness added > 25 ms, by the image sets released in the rotation before their scan
start, rounds pooled: ``replay.record.staleness_by_recent_images``): stale slices gathered after bursts of frames
mean an image lane short of time for a burst, not on average.

    python -m streamdet.benchmarks.replay_table OUT_DIR --baseline LABEL [--target-ms MS]

``--baseline``: instead of the table, issue 22's line for every other variant, scale by scale, counted over rounds:
staleness added p95 within the target (default: the CPU's, as above; ``--target-ms`` sets it, a finite number above
0, e.g. 100 where a faster part emulates an AVX2-only one by a time scale, and it must be given for a CPU without a
target; the p95 is read at the capture clock's microsecond, ``replay.record.capture_gap_ms``), no slice dropped (of
more than none), slice p99 at most the baseline variant's **in the same round**, and the issue's accuracy term,
streaming mAP at least the baseline's in the same round; then the rounds meeting all four. The rounds counted are
every round either variant ran at that scale: a round one of them lacks (an interrupted A/B, a replay that failed)
meets no term it enters and is named, and so does a value the replay could not give (no fused slice, no score).
"""

from __future__ import annotations

import json
import math
import re
import sys
import textwrap
from pathlib import Path

import numpy as np

from streamdet.replay.record import STALE_MS, Recording, capture_gap_ms, full_collections, staleness_by_recent_images
from streamdet.replay.report import cpu_line, stale_cells

RUN = re.compile(r"r(\d+)_scale([0-9.]+)_(.+)")
HEADER = ("| scale | variant | staleness added p50 / p95 ms | image age p95 ms | slice p99 ms | dropped "
          "(coalesced) | image-lane CPU ms / rotation | cores slice / image lane | streaming mAP | probe GFLOP/s |")  # fmt: skip
STALENESS_TARGET_MS = {True: 25.0, False: 100.0}  # issue 22's p95 target, by whether the CPU has AVX-512 (with AVX2)
TARGET_ISA = {True: "AVX-512", False: "AVX2-only"}


def staleness_target(cpu: dict) -> float | None:
    """Issue 22's staleness p95 target for a CPU (a replay's ``config.cpu``): AVX-512 (avx512f) 25 ms, AVX2 without
    it 100 ms; None for any other (an ARM part, flags that could not be read): the issue names no target for it, and
    "no AVX-512" does not make a part an AVX2 one."""
    flags = cpu.get("flags") or ()
    if "avx512f" in flags:
        return STALENESS_TARGET_MS[True]
    if "avx2" in flags:
        return STALENESS_TARGET_MS[False]
    return None


def no_target_label(cpu: dict) -> str:
    """Why a CPU has no ``staleness_target``, by what was found: "no issue 22 target for asimd/asimddp (no AVX2)",
    or "... for unknown SIMD flags" where none were read."""
    flags = list(cpu.get("flags") or ())
    found = "/".join(flags) + " (no AVX2)" if flags else "unknown SIMD flags"
    return f"no issue 22 target for {cpu.get('model', 'this CPU')}: {found}"


def streaming_runs(out: Path, with_config: bool = False):
    """(round, scale, label, run name, the streaming mode of its replay.json[, its config]) of every
    r<round>_scale<S>_<label> run."""
    for f in sorted(out.glob("r*_scale*_*/replay.json")):
        m = RUN.fullmatch(f.parent.name)
        if m is None:
            continue
        replay = json.loads(f.read_text())
        modes = replay["modes"]
        if "streaming" not in modes:
            raise ValueError(f"{f}: no streaming mode in this replay, so no streaming recordings (streamdet-replay --mode streaming --out)")
        run = (int(m.group(1)), float(m.group(2)), m.group(3), f.parent.name, modes["streaming"])
        yield run + (replay.get("config", {}),) if with_config else run


def machines(out: Path) -> list[dict]:
    """The distinct CPUs (the replay's ``config.cpu``) the runs of ``out`` ran on, in the order first met; runs
    written before replays recorded it are left out."""
    seen: list[dict] = []
    for *_, config in streaming_runs(out, with_config=True):
        cpu = config.get("cpu")
        if cpu and cpu not in seen:
            seen.append(cpu)
    return seen


def collect(out: Path) -> dict[tuple[float, str], list[tuple[int, dict, float]]]:
    """(scale, label) -> [(round, the streaming mode's summary, probe GFLOP/s)], rounds in order."""
    probes_file = out / "probes_gflops.txt"
    probes = {}
    if probes_file.is_file():
        for line in probes_file.read_text().splitlines():
            parts = line.split()
            if len(parts) == 2:
                probes[parts[0]] = float(parts[1])
    rows: dict[tuple[float, str], list[tuple[int, dict, float]]] = {}
    for rnd, scale, label, name, streaming in streaming_runs(out):
        rows.setdefault((scale, label), []).append((rnd, streaming, probes.get(name, float("nan"))))
    for runs in rows.values():
        runs.sort(key=lambda r: r[0])
    return rows


def table(out: Path) -> str:
    rows = collect(out)
    if not rows:
        raise ValueError(f"{out}: no r<round>_scale<S>_<label>/replay.json found")
    cpus = machines(out)
    if len(cpus) > 1:
        lines = ["CPUs (they differ across runs: compare rows of one CPU only): " + "; ".join(map(cpu_line, cpus)), ""]
    else:
        lines = ["CPU: " + (cpu_line(cpus[0]) if cpus else "not recorded"), ""]
    lines += [HEADER, "|---|---|---|---|---|---|---|---|---|---|"]

    def cells(runs, fn) -> str:
        return ", ".join(fn(s, p) for _, s, p in runs)

    for (scale, label), runs in sorted(rows.items()):
        lines.append("| " + " | ".join([
            f"{scale:g}", label,
            cells(runs, lambda s, p: _fmt(s["staleness_ms"]["p50"], "%.0f") + " / " + _fmt(s["staleness_ms"]["p95"], "%.0f")),
            cells(runs, lambda s, p: _fmt(s["image_age_ms"]["p95"], "%.0f")),
            cells(runs, lambda s, p: _fmt(s["latency_ms"]["p99"], "%.1f")),
            cells(runs, _dropped),
            cells(runs, lambda s, p: _fmt(s["image_lane_cpu_ms_per_rotation"], "%.1f")),
            cells(runs, _cores),
            cells(runs, lambda s, p: _fmt(s["map_streaming"], "%.1f", 100)),
            cells(runs, lambda s, p: _fmt(p, "%.0f")),
        ]) + " |")  # fmt: skip
    gc_line = _full_collections(rows)
    return "\n".join(lines + ([] if gc_line is None else ["", gc_line]) + _stale_by_burst(out))


def _fmt(value: float | None, spec: str, scale: float = 1.0) -> str:
    """A cell's number, or "-" where the replay wrote none (a percentile of no slice, an undefined mAP: JSON null)."""
    return "-" if value is None else spec % (scale * value)


def _dropped(s: dict, probe: float) -> str:
    """Slices dropped, with the coalesced ones in brackets where the lane ran any (LaneConfig.coalesce_slices)."""
    coalesced = s.get("slices_coalesced", 0)
    return f"{s['slices_dropped']} ({coalesced})" if coalesced else str(s["slices_dropped"])


def _stale_by_burst(out: Path) -> list[str]:
    """Lines of stale slices by the image sets released in the rotation before their scan start, one per (scale,
    variant), rounds pooled; none where the replays hold no fused slice."""
    pooled: dict[tuple[float, str, float], list[Recording]] = {}  # (scale, label, LiDAR period s) -> every round's
    for _, scale, label, name, streaming, config in streaming_runs(out, with_config=True):
        if not config.get("lidar_hz") or not streaming.get("recordings"):
            continue
        try:
            recs = [Recording.from_dict(r) for r in streaming["recordings"]]
        except (KeyError, TypeError, ValueError) as e:  # ValueError: a field of the wrong type (replay/record.py)
            raise ValueError(f"{name}: recordings not as streamdet-replay writes them ({type(e).__name__}: {e})") from None
        pooled.setdefault((scale, label, 1.0 / config["lidar_hz"]), []).extend(recs)
    counts = {(scale, label): staleness_by_recent_images(recs, period) for (scale, label, period), recs in sorted(pooled.items())}
    lines = [f"- {label} (scale {scale:g}): {stale_cells(c)}" for (scale, label), c in counts.items() if c]
    if not lines:
        return []
    return ["", f"stale slices (staleness added > {STALE_MS:g} ms) by image sets released in the rotation before the "
            "scan start (rounds pooled):", *lines]  # fmt: skip


def _full_collections(rows: dict[tuple[float, str], list[tuple[int, dict, float]]]) -> str | None:
    """One line on the garbage collector's full collections during the drives (``gc_pauses`` of the recordings,
    replays since 2026-12-04): "none in N runs", or per variant with any, per round the count and the longest pause.
    None when no run recorded them."""
    per_variant = {key: [full_collections([r.get("gc_pauses") for r in summary.get("recordings") or []])
                         for _, summary, _ in runs] for key, runs in sorted(rows.items())}  # fmt: skip
    measured = sum(f is not None for runs in per_variant.values() for f in runs)
    if measured == 0:
        return None
    with_any = {k: v for k, v in per_variant.items() if any(f is not None and f[0] for f in v)}
    if not with_any:
        return f"full garbage collections during the drives: none in {measured} run(s)"
    cell = lambda f: "-" if f is None else "0" if f[0] == 0 else "%d (%.1f ms)" % f  # noqa: E731
    return "full garbage collections during the drives (per round: count, longest pause): " + "; ".join(
        f"{label} (scale {scale:g}) {', '.join(map(cell, v))}" for (scale, label), v in with_any.items()
    )


def _cores(summary: dict, probe: float) -> str:
    """The slice and image lanes' CPU in cores, e.g. ``1.30 / 0.60``; ``-`` where not recorded. The image lane's is
    its own thread time over the wall time where the recordings hold it (the ``cpu_share`` of older replays charged
    only the image sets' updates: under the phase-locked schedule about half the lane)."""
    share = summary.get("cpu_share") or {}
    if "slice_lane" not in share or "image_lane" not in share:
        return "-"
    image = share["image_lane"]
    recs = summary.get("recordings") or []
    if recs and all(r.get("image_lane_cpu_s") is not None and r.get("wall_s") for r in recs):
        image = sum(r["image_lane_cpu_s"] for r in recs) / sum(r["wall_s"] for r in recs)
    return "%.2f / %.2f" % (share["slice_lane"], image)


def staleness(out: Path) -> dict[tuple[float, str], np.ndarray]:
    """(scale, label) -> staleness added (ms) of every emitted slice fused with drive images, all rounds pooled
    (``replay.record.SliceRecord.staleness_ms`` from the slices of replay.json)."""
    pooled: dict[tuple[float, str], list[float]] = {}
    for _, scale, label, _, streaming in streaming_runs(out):
        values = pooled.setdefault((scale, label), [])
        for rec in streaming.get("recordings", []):
            for sl in rec["slices"]:
                newest, used = sl.get("newest_capture_s"), sl.get("image_capture_s")
                if sl.get("emit_s") is not None and newest is not None and used is not None:
                    values.append(capture_gap_ms(newest, used))
    return {k: np.asarray(v, np.float64) for k, v in pooled.items()}


def plot(out: Path, path: Path) -> None:
    """The staleness CDFs of every variant, one panel per time scale, to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, stale, cpus = collect(out), staleness(out), machines(out)
    # the targets of the CPUs that have one; none recorded (older replays): both, each labelled by its instruction set
    targets = sorted({t for cpu in cpus if (t := staleness_target(cpu)) is not None})
    if not cpus:
        targets = sorted(set(STALENESS_TARGET_MS.values()))
    untargeted = [no_target_label(cpu) for cpu in cpus if staleness_target(cpu) is None]
    scales = sorted({scale for scale, _ in rows})
    fig, axes = plt.subplots(1, len(scales), figsize=(6.5 * len(scales), 4.2), squeeze=False)
    for ax, scale in zip(axes[0], scales):
        for (s, label), runs in sorted(rows.items()):
            values = np.sort(stale.get((s, label), np.zeros(0)))
            if s != scale or values.size == 0:
                continue
            cpu = ", ".join(_fmt(r[1]["image_lane_cpu_ms_per_rotation"], "%.1f") for r in runs)
            ax.step(values, np.arange(1, values.size + 1) / values.size, where="post", label=f"{label} (lane CPU {cpu} ms/rot)")
        for target in targets:
            isa = TARGET_ISA[target == STALENESS_TARGET_MS[True]]
            ax.axvline(target, color="grey", linestyle=":", linewidth=1, label=f"issue 22 target, {isa}: p95 <= {target:g} ms")
        for label in untargeted:  # a legend line without a drawn target
            ax.plot([], [], linestyle="none", label=label)
        ax.set_xlabel("staleness added by processing (ms)")
        ax.set_ylabel("fraction of fused slices")
        title = f"time scale {scale:g}" + (f", {cpu_line(cpus[0])}" if len(cpus) == 1 else "")
        ax.set_title(textwrap.fill(title, 80), fontsize=9)  # a long CPU line (its flags) would run off the figure
        ax.set_ylim(0, 1.01)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def line_against(out: Path, baseline: str, target_ms: float | None = None) -> str:
    """Issue 22's line per (scale, variant) against the variant ``baseline``, rounds counted (module docstring)."""
    rows = collect(out)
    if not any(label == baseline for _, label in rows):
        labels = sorted({label for _, label in rows})
        raise ValueError(f"{out}: no variant {baseline!r} to compare with (variants: {', '.join(labels) or 'none'})")
    if target_ms is None:
        cpus = machines(out)
        untargeted = [no_target_label(cpu) for cpu in cpus if staleness_target(cpu) is None]
        if untargeted:
            raise ValueError(f"{out}: {'; '.join(untargeted)}: give --target-ms")
        targets = {staleness_target(cpu) for cpu in cpus}
        if len(targets) != 1:
            raise ValueError(f"{out}: the runs name {len(targets)} staleness targets by their CPUs: give --target-ms")
        (target_ms,) = targets
    check_target_ms(target_ms)
    lines = [f"issue 22's line against `{baseline}`: staleness added p95 <= {target_ms:g} ms, no slice dropped, slice "
             f"p99 <= `{baseline}`'s and streaming mAP >= `{baseline}`'s in the same round (rounds meeting each term, "
             f"then all four; counted over every round either variant ran at the scale, a round one of them lacks "
             f"meeting none)"]  # fmt: skip
    for (scale, label), runs in sorted(rows.items()):
        if label == baseline:
            continue
        base = {rnd: s for rnd, s, _ in rows.get((scale, baseline), [])}
        mine = {rnd: s for rnd, s, _ in runs}
        rounds = sorted(set(base) | set(mine))
        terms = {rnd: _line_terms(mine.get(rnd), base.get(rnd), target_ms) for rnd in rounds}
        n = len(rounds)
        count = lambda i: sum(t[i] for t in terms.values())  # noqa: E731
        whole = sum(all(t) for t in terms.values())
        notes = [f"no {who} run in round(s) {', '.join(map(str, missing))}"
                 for who, missing in ((f"`{label}`", [r for r in rounds if r not in mine]),
                                      (f"`{baseline}`", [r for r in rounds if r not in base])) if missing]  # fmt: skip
        lines.append(f"- scale {scale:g}, {label}: staleness {count(0)} of {n}, none dropped {count(1)} of {n}, "
                     f"p99 {count(2)} of {n}, streaming mAP >= `{baseline}`'s {count(3)} of {n}; the whole line "
                     f"{whole} of {n}" + (f" ({'; '.join(notes)})" if notes else ""))  # fmt: skip
    return "\n".join(lines)


def _line_terms(s: dict | None, base: dict | None, target_ms: float) -> tuple[bool, bool, bool, bool]:
    """One round's four terms: staleness added p95 within the target (at the capture clock, ``capture_gap_ms``:
    replays before it stored 100 ms as 100.00000000000009), no slice dropped of more than none, slice p99 at most the
    baseline's, streaming mAP at least the baseline's. A run missing, or a value the replay could not give (JSON
    null: no fused slice, no emitted slice, no score), meets no term it enters."""
    if s is None:
        return (False, False, False, False)
    p95 = s["staleness_ms"]["p95"]
    fresh = p95 is not None and round(p95, 3) <= target_ms  # round to the microsecond, as capture_gap_ms
    kept = s["slices_dropped"] == 0 and s.get("slices_total", 1) > 0  # replays before slices_total: not checked
    if base is None:
        return (fresh, kept, False, False)
    p99, base_p99 = s["latency_ms"]["p99"], base["latency_ms"]["p99"]
    tail = p99 is not None and base_p99 is not None and p99 <= base_p99
    score, base_score = s.get("map_streaming"), base.get("map_streaming")
    scored = score is not None and base_score is not None and score >= base_score
    return (fresh, kept, tail, scored)


def check_target_ms(target_ms: float) -> None:
    """A staleness target must be a finite positive number of milliseconds (``inf`` would pass every round)."""
    if not (math.isfinite(target_ms) and target_ms > 0):
        raise ValueError(f"--target-ms must be a finite number of milliseconds above 0, got {target_ms!r}")


USAGE = ("usage: python -m streamdet.benchmarks.replay_table OUT_DIR [--plot FILE.png] "
         "[--baseline LABEL [--target-ms MS]]")


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if "--help" in args or "-h" in args:  # before the parsing below, which would take it for OUT_DIR
        print(f"{USAGE}\n\n{__doc__ or ''}")
        return 0
    plot_path = None
    if "--plot" in args:
        i = args.index("--plot")
        if i + 1 >= len(args):
            print("replay_table: --plot needs a file name", file=sys.stderr)
            return 2
        plot_path = Path(args[i + 1])
        del args[i : i + 2]
    options = {}
    for flag, convert in (("--baseline", str), ("--target-ms", float)):
        if flag in args:
            i = args.index(flag)
            try:
                options[flag] = convert(args[i + 1])
            except (IndexError, ValueError):
                print(f"replay_table: {flag} needs a value", file=sys.stderr)
                return 2
            del args[i : i + 2]
    if len(args) != 1 or ("--target-ms" in options and "--baseline" not in options):
        print(USAGE, file=sys.stderr)
        return 2
    if "--target-ms" in options:
        try:
            check_target_ms(options["--target-ms"])
        except ValueError as e:
            print(f"replay_table: {e}", file=sys.stderr)
            return 2
    try:
        if "--baseline" in options:
            print(line_against(Path(args[0]), options["--baseline"], options.get("--target-ms")))
        else:
            print(table(Path(args[0])))
        if plot_path is not None:
            plot(Path(args[0]), plot_path)
    except (ValueError, OSError, KeyError, json.JSONDecodeError) as e:
        print(f"replay_table: {e}", file=sys.stderr)
        return 1
    except ImportError:
        print("replay_table: --plot needs matplotlib (pip install matplotlib)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
