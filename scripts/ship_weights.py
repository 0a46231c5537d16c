#!/usr/bin/env python
"""Ships one training run as a bundled model: copies its ``model.pt`` (weights format, no optimizer state) into
``models/weights/`` and writes the JSON beside it with the recipe, the file's hash and every score on record.

    python scripts/ship_weights.py --run RUN_DIR --eval EVAL_DIR --out models/weights/small.pt \
        --data-recipe "streamdet-synth ..." --recipe "streamdet-train ..." [--attach NAME=FILE.json ...]

RUN_DIR is a finished ``streamdet-train`` folder (model.pt, config.json, metrics.jsonl); EVAL_DIR is what
``scripts/issue19_eval.sh`` wrote for it (eval_<n>.json per slice count, gate_*.json for a fused model). Each
``--attach`` JSON (a ``streamdet-eval --compare`` result, a probe, the camera_claim verdict) is stored whole under
``evidence.NAME``. Nothing is measured here: every figure comes from a file that names its command.
"""

from __future__ import annotations

import argparse
import datetime
import json
import shutil
import sys
from pathlib import Path

from streamdet.export.weights import SHIPPED_MAX_BYTES as MAX_BYTES
from streamdet.runtime_ort.manifest import sha256_file


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise SystemExit(f"ship_weights: cannot read {path}: {e}") from None


def _last_metrics(run: Path) -> dict:
    lines = [ln for ln in (run / "metrics.jsonl").read_text().splitlines() if ln.strip()]
    if not lines:
        raise SystemExit(f"ship_weights: {run}/metrics.jsonl is empty")
    return json.loads(lines[-1])


def _scores(eval_dir: Path) -> dict:
    """eval_<n>.json per slice count (streamdet-eval --json) reduced to mAP, NDS and AP per class."""
    scores = {}
    for path in sorted(eval_dir.glob("eval_*.json"), key=lambda p: int(p.stem.split("_")[1])):
        d = _read_json(path)
        scores[f"{d['num_slices']}_slices"] = {
            "mAP": d["mAP"], "NDS": d["NDS"], "num_samples": d["num_samples"], "precision": d["precision"],
            "AP": {c: d["per_class"][c]["AP"] for c in d["classes"]},
        }
    if not scores:
        raise SystemExit(f"ship_weights: no eval_<n>.json in {eval_dir}")
    return scores


def _gates(eval_dir: Path) -> dict:
    return {p.stem: _read_json(p) for p in sorted(eval_dir.glob("gate_*.json"))}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, required=True, help="finished streamdet-train folder (model.pt)")
    ap.add_argument("--eval", type=Path, required=True, help="its evaluation folder (eval_<n>.json, gate_*.json)")
    ap.add_argument("--out", type=Path, required=True, help="destination .pt (the JSON is written beside it)")
    ap.add_argument("--data-recipe", required=True, help="the commands that made the training and evaluation data")
    ap.add_argument("--recipe", required=True, help="the command(s) that trained the run")
    ap.add_argument("--machine", default="2-vCPU AMD EPYC (Zen 4, AVX-512 VNNI/BF16), 1 torch thread, fp32",
                    help="where it was trained")
    ap.add_argument("--note", action="append", default=[], help="a sentence for the JSON's notes (repeatable)")
    ap.add_argument("--attach", action="append", default=[], metavar="NAME=FILE",
                    help="a JSON file stored whole under evidence.NAME (repeatable)")
    args = ap.parse_args(argv)

    src = args.run / "model.pt"
    if not src.is_file():
        raise SystemExit(f"ship_weights: {src} not found (is the run finished?)")
    size = src.stat().st_size
    if size > MAX_BYTES:
        raise SystemExit(f"ship_weights: {src} is {size / 1e6:.1f} MB, over the {MAX_BYTES / 1e6:.0f} MB limit")
    config = _read_json(args.run / "config.json")
    last = _last_metrics(args.run)
    evidence = {}
    for item in args.attach:
        name, sep, path = item.partition("=")
        if not sep or not name:
            raise SystemExit(f"ship_weights: --attach takes NAME=FILE, got {item!r}")
        evidence[name] = _read_json(Path(path))

    args.out.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, args.out)
    preset = config["preset"]
    doc = {
        "file": args.out.name,
        "preset": preset["name"],
        "use_image": preset.get("use_image", True),
        "format": "{'format': 'streamdet-weights-v1', 'preset': Preset.to_dict(), 'model': state_dict (fp32), 'meta': {...}}",
        "sha256": sha256_file(args.out),
        "size_bytes": args.out.stat().st_size,
        "shipped": datetime.date.today().isoformat(),
        "trained_on": {
            "data": args.data_recipe,
            "not_real_data": "trained on synthetic data only: on real nuScenes frames (e.g. the bundled sample) its "
                             "detections are not meaningful",
        },
        "training": {
            "command": args.recipe,
            "machine": args.machine,
            "steps": last["step"],
            "wall_minutes": round(last["elapsed_s"] / 60.0, 1),
            "final_loss": last["loss"],
            "config": config["train"],
            "run_dir": str(args.run),
        },
        "scores_val": {
            "metric": "nuScenes detection mAP / NDS (devkit-identical, streamdet.evaluation), all slices of a sweep "
                      "detected and merged by per-class NMS; streamdet-eval --split all on the evaluation world",
            **_scores(args.eval),
        },
        "gates": _gates(args.eval),
        "evidence": evidence,
        "notes": args.note,
    }
    json_path = args.out.with_suffix(".json")
    json_path.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {args.out} ({doc['size_bytes'] / 1e6:.1f} MB, sha256 {doc['sha256'][:12]}) and {json_path}")


if __name__ == "__main__":
    sys.exit(main())
