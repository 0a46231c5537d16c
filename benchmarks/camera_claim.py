"""Issue 19's decision: does the camera lane reproduce the paper's central claim here, or refute it?

    python -m streamdet.benchmarks.camera_claim --compare8 C8.json --compare32 C32.json
        [--gate-drop G.json ...] [--gate-noise N.json ...] [--probe P.json ...] [--json OUT] [--plot OUT.png]

``C8`` / ``C32``: ``streamdet-eval --compare LIDAR FUSED --json`` at 8 and 32 slices (A = the LiDAR-only runs, B =
the fused runs; groups of seeds give the mean of the seeds, the bootstrap resampling them). The gate files are
each fused run's ``streamdet-study drop-camera --no-cameras --json`` and ``calib-noise --level 5,50 --json`` at 8
slices, the probe files ``python -m streamdet.benchmarks.image_bev_probe --json``.

The rules (the issue's):

- **gate**: removing every camera (``drop-camera --no-cameras``: an all-zero image BEV in the issue-19 runs, the
  runtime's camera-less BEV since 2026-12-05, a smaller loss) costs >= 3 mAP and (5 deg, 50 cm) extrinsic noise
  >= 2 mAP on every fused run,
  else the comparison is **void** (a fused model that does not use its cameras says nothing about cameras);
- **reproduced**: fused - LiDAR-only >= +3 mAP at 8 slices, >= +5 at 32 and >= +10 bicycle AP (8 slices), each
  95 % interval excluding 0;
- **refuted**: the image lane reached its figures (probe balanced accuracy >= 0.6, image / point RMS at fusion in
  [0.5, 2] and train / eval image BEV RMS within 10 %, all read from the probe files; the LUT coverage of item 3 is
  measured elsewhere, ``benchmarks/lut_coverage.py``) and the mAP intervals at 8 and 32 slices still include 0;
- otherwise **undecided**, with the rule that failed.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import click

GATE_DROP_MAP = 3.0  # mAP points every camera removed must cost
GATE_NOISE_MAP = 2.0  # mAP points (5 deg, 50 cm) noise must cost
NEED_8, NEED_32, NEED_BICYCLE = 3.0, 5.0, 10.0  # mAP / AP points of "reproduced"
PROBE_MIN = 0.6  # balanced accuracy of the image BEV's linear probe
SCALE_RANGE = (0.5, 2.0)  # image / point BEV RMS on occupied cells at fusion, eval mode
TRAIN_EVAL_TOLERANCE = 0.10  # |train / eval image BEV RMS - 1|
SEEDS_PER_SIDE = 3  # training seeds the issue asks of each side; fewer: the verdict is marked preliminary


@dataclass(frozen=True)
class Row:
    """One figure of the table: B - A in points with its 95 % interval, and the bar it must clear."""

    label: str
    lidar: float
    fused: float
    diff: float
    lo: float
    hi: float
    need: float
    interval_defined: bool = True  # False: the comparison resampled fewer than 2 scenes (evaluation/bootstrap.py)

    @property
    def excludes_zero(self) -> bool:
        return self.interval_defined and (self.lo > 0 or self.hi < 0)

    @property
    def met(self) -> bool:
        return self.diff >= self.need and self.interval_defined and self.lo > 0


@dataclass(frozen=True)
class Decision:
    verdict: str  # reproduced | refuted | void | undecided
    reason: str
    rows: tuple[Row, ...]
    gate: tuple[tuple[str, float, float], ...] = ()  # (run, drop-cameras cost, noise cost) in mAP points
    probe: tuple[float, ...] = ()
    scales: tuple[tuple[float, float], ...] = ()  # per fused run: (image / point RMS at fusion, train / eval RMS)
    notes: tuple[str, ...] = field(default=())

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "reason": self.reason,
                "rows": [{**r.__dict__, "excludes_zero": r.excludes_zero, "met": r.met} for r in self.rows],
                "gate": [{"run": g[0], "drop_cameras_cost": g[1], "calib_noise_cost": g[2]} for g in self.gate],
                "probe_balanced_accuracy": list(self.probe),
                "image_over_point_rms": [sc[0] for sc in self.scales], "train_over_eval_rms": [sc[1] for sc in self.scales],
                "notes": list(self.notes)}  # fmt: skip


def _row(doc: dict, key: str, label: str, need: float) -> Row:
    try:
        d = doc["subsets"]["all"][key]
        defined = bool(d.get("interval_defined", True))  # absent in comparisons written before the flag
        return Row(label, 100 * d["A"], 100 * d["B"], 100 * d["B_minus_A"], 100 * d["ci_lo"], 100 * d["ci_hi"], need, defined)
    except (KeyError, TypeError) as e:
        raise ValueError(f"a comparison file lacks subsets.all.{key} ({e}): is it streamdet-eval --compare --json output?") from None


def _gate_costs(drop: dict, noise: dict) -> tuple[float, float]:
    try:
        drop_cost = 100 * (drop["all_cameras"]["mAP"] - drop["no_cameras"]["mAP"])
    except (KeyError, TypeError):
        raise ValueError("a drop-camera file lacks all_cameras / no_cameras mAP: run the study with --no-cameras --json") from None
    try:
        level = next(lv for lv in noise["levels"] if abs(lv["max_angle_deg"] - 5) < 1e-9 and abs(lv["max_translation_m"] - 0.5) < 1e-9)
        noise_cost = 100 * (noise["reference"]["mAP"] - level["mAP_mean"])
    except (KeyError, TypeError, StopIteration):
        raise ValueError("a calib-noise file lacks the (5 deg, 50 cm) level: run the study with --level 5,50 --json") from None
    return drop_cost, noise_cost


def _runs(doc: dict, side: str) -> int:
    """Runs (seeds) on one side of a --compare JSON: a path, or a list of paths for a group."""
    value = doc.get(side)
    return len(value) if isinstance(value, list) else 1


def _scale_ok(image_over_point: float, train_over_eval: float) -> bool:
    return SCALE_RANGE[0] <= image_over_point <= SCALE_RANGE[1] and abs(train_over_eval - 1.0) <= TRAIN_EVAL_TOLERANCE


def decide(compare8: dict, compare32: dict, gates: Sequence[tuple[str, dict, dict]] = (),
           probes: Sequence[float] = (), scales: Sequence[tuple[float, float]] = ()) -> Decision:  # fmt: skip
    """The verdict from the comparisons (B = fused), each fused run's gate files, probe accuracies and scales
    ((image / point RMS at fusion, train / eval image BEV RMS) per fused run)."""
    rows = (_row(compare8, "mAP", "mAP, 8 slices", NEED_8), _row(compare32, "mAP", "mAP, 32 slices", NEED_32),
            _row(compare8, "AP/bicycle", "bicycle AP, 8 slices", NEED_BICYCLE))  # fmt: skip
    gate = tuple((name, *_gate_costs(drop, noise)) for name, drop, noise in gates)
    notes = []
    seeds = min(_runs(c, side) for c in (compare8, compare32) for side in ("A", "B"))
    if seeds < SEEDS_PER_SIDE:
        notes.append(f"preliminary: {seeds} seed(s) on a side, the issue asks {SEEDS_PER_SIDE} per side "
                     "(streamdet-eval --compare A1,A2,A3 B1,B2,B3)")  # fmt: skip
    if not gate:
        notes.append("no gate files: the image-use gate was not checked")
    failed = [g for g in gate if g[1] < GATE_DROP_MAP or g[2] < GATE_NOISE_MAP]
    if failed:
        g = failed[0]
        return Decision("void", f"image-use gate failed on {g[0]}: zeroing every camera costs {g[1]:.1f} mAP (needs >= "
                        f"{GATE_DROP_MAP:g}), (5 deg, 50 cm) noise {g[2]:.1f} (needs >= {GATE_NOISE_MAP:g})",
                        rows, gate, tuple(probes), tuple(scales), tuple(notes))  # fmt: skip
    if all(r.met for r in rows):
        return Decision("reproduced", "every figure clears its bar with an interval excluding 0", rows, gate,
                        tuple(probes), tuple(scales), tuple(notes))  # fmt: skip
    probe_ok = bool(probes) and min(probes) >= PROBE_MIN
    scale_ok = bool(scales) and all(_scale_ok(*sc) for sc in scales)
    if probe_ok and scale_ok and not rows[0].excludes_zero and not rows[1].excludes_zero:
        return Decision("refuted", "the image lane reaches its figures and the mAP intervals at 8 and 32 slices include 0",
                        rows, gate, tuple(probes), tuple(scales), tuple(notes))  # fmt: skip
    missing = [r.label for r in rows if not r.met]
    why = f"not reproduced ({', '.join(missing)} short of its bar or its interval holds 0)"
    if not probe_ok:
        why += f"; not refuted either: the probe's balanced accuracy {min(probes) if probes else float('nan'):.2f} (needs >= {PROBE_MIN})"
    elif not scale_ok:
        why += ("; not refuted either: the image BEV's scale is off its figures (image / point RMS in "
                f"[{SCALE_RANGE[0]:g}, {SCALE_RANGE[1]:g}], train / eval within {TRAIN_EVAL_TOLERANCE:.0%})"
                if scales else "; not refuted either: no image BEV scale figures given")  # fmt: skip
    else:
        why += "; not refuted either: a mAP interval excludes 0"
    return Decision("undecided", why, rows, gate, tuple(probes), tuple(scales), tuple(notes))


def format_decision(d: Decision) -> str:
    lines = ["| figure | LiDAR-only | fused | fused - LiDAR-only | 95 % interval | bar | met |", "|---|---|---|---|---|---|---|"]
    for r in d.rows:
        lines.append(f"| {r.label} | {r.lidar:.1f} | {r.fused:.1f} | {r.diff:+.1f} | [{r.lo:+.1f}, {r.hi:+.1f}] | "
                     f">= +{r.need:g} | {'yes' if r.met else 'no'} |")  # fmt: skip
    for name, drop, noise in d.gate:
        lines.append(f"\ngate {name}: every camera removed costs {drop:.1f} mAP (>= {GATE_DROP_MAP:g}), "
                     f"(5 deg, 50 cm) noise {noise:.1f} (>= {GATE_NOISE_MAP:g})")  # fmt: skip
    if d.probe:
        lines.append("image BEV probe balanced accuracy: " + ", ".join(f"{p:.2f}" for p in d.probe) + f" (>= {PROBE_MIN})")
    if d.scales:
        lines.append("image / point RMS at fusion: " + ", ".join(f"{sc[0]:.2f}" for sc in d.scales)
                     + f" (in [{SCALE_RANGE[0]:g}, {SCALE_RANGE[1]:g}]); train / eval image BEV RMS: "
                     + ", ".join(f"{sc[1]:.2f}" for sc in d.scales) + f" (within {TRAIN_EVAL_TOLERANCE:.0%})")  # fmt: skip
    lines.append(f"\n**{d.verdict}**: {d.reason}")
    lines.extend(f"note: {n}" for n in d.notes)
    return "\n".join(lines)


def _read(path: Path) -> dict:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise click.ClickException(f"cannot read {path}: {e}") from None


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--compare8", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="streamdet-eval --compare LIDAR FUSED --json at 8 slices.")
@click.option("--compare32", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="The same at 32 slices.")
@click.option("--gate-drop", multiple=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Per fused run: streamdet-study drop-camera --no-cameras --json (repeat; pairs with --gate-noise).")
@click.option("--gate-noise", multiple=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Per fused run: streamdet-study calib-noise --level 5,50 --json (repeat, same order).")
@click.option("--probe", multiple=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Per fused run: image_bev_probe --json (repeat).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also write the decision here.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also draw the decision here (PNG): fused - LiDAR-only per figure at 8 and 32 slices with its 95 % interval.")
def main(compare8: Path, compare32: Path, gate_drop: tuple[Path, ...], gate_noise: tuple[Path, ...],
         probe: tuple[Path, ...], json_path: Path | None, plot_path: Path | None) -> None:  # fmt: skip
    """Issue 19's verdict (reproduced / refuted / void / undecided) and its table."""
    if len(gate_drop) != len(gate_noise):
        raise click.UsageError(f"--gate-drop and --gate-noise pair up per fused run: got {len(gate_drop)} and {len(gate_noise)}")
    try:
        docs = [_read(p) for p in probe]
        probes = [float(d["probe_balanced_accuracy_image"]) for d in docs]
        scales = [(float(d["image_over_point_rms"]), float(d["train_over_eval_rms"])) for d in docs]
    except (KeyError, TypeError, ValueError) as e:
        raise click.ClickException(f"a probe file lacks {e} (write it with python -m streamdet.benchmarks.image_bev_probe --json)") from None
    gates = [(str(d.parent.name), _read(d), _read(n)) for d, n in zip(gate_drop, gate_noise)]
    doc8, doc32 = _read(compare8), _read(compare32)
    try:
        decision = decide(doc8, doc32, gates, probes, scales)
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    click.echo(format_decision(decision))
    if json_path is not None:
        json_path.write_text(json.dumps(decision.to_dict(), indent=1) + "\n")
        click.echo(f"wrote {json_path}")
    if plot_path is not None:
        from streamdet.benchmarks.camera_claim_plot import plot_claim

        needs = {("mAP", 8): NEED_8, ("mAP", 32): NEED_32, ("AP bicycle", 8): NEED_BICYCLE}
        try:
            plot_claim(doc8, doc32, plot_path, verdict=decision.verdict, needs=needs)
        except (OSError, ValueError) as e:
            raise click.ClickException(f"cannot draw {plot_path}: {e}") from None
        click.echo(f"wrote {plot_path}")


if __name__ == "__main__":
    main()
