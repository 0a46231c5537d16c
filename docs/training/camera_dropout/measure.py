"""What a fused export scores when cameras are missing, as the runtime feeds it (docs/training/RESULTS.md, "Camera
dropout", thirty-third session). Every sample is detected in one pass per variant, ONNX fp32, 8 slices:

- all: every camera;
- front dead: CAM_FRONT gives no frame (the runtime lifts it from zero features: SliceResult.cameras_missing);
- back dead: the three back cameras give none (quadrants 2 and 3 of the bundled rig see none of their cameras and
  read the camera-less BEV; quadrants 0 and 1 lose one camera each);
- all dark: no camera ever (every quadrant reads the camera-less BEV, StreamingDetector.blank_image_bev).

    python measure.py EXPORT_DIR DATASET SPLIT|all OUT_DIR [--max-samples N]

Writes OUT_DIR/<variant>/ in streamdet-eval's --save-results form (results.json, gt.json, samples.json), so that
`streamdet-eval --compare A/<variant> B/<variant> --bootstrap 1000` gives paired intervals over scenes, and
OUT_DIR/scores.json (mAP and NDS per variant)."""
import argparse
import json
from pathlib import Path

from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.splits import split_sample_tokens
from streamdet.evaluation.compare import SAMPLES_FILE, write_sample_info
from streamdet.evaluation.dataset_eval import ground_truth_entries, prediction_entries
from streamdet.evaluation.config import DetectionConfig
from streamdet.evaluation.results import write_results_json
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.pipeline import sample_images
from streamdet.studies.common import StudyData, score_variants, sweep_points

ap = argparse.ArgumentParser()
ap.add_argument("export")
ap.add_argument("data")
ap.add_argument("split")
ap.add_argument("out", type=Path)
ap.add_argument("--max-samples", type=int, default=None)
args = ap.parse_args()
split = None if args.split == "all" else args.split
DEAD = {"front dead": ("CAM_FRONT",), "back dead": ("CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")}
det = StreamingDetector(args.export)
dark = StreamingDetector(args.export)  # never given an image: every quadrant reads the camera-less BEV
config = DetectionConfig()
saved: dict[str, dict[str, list]] = {}
gt: dict[str, list] = {}
scenes, poses, ego = {}, {}, {}
reader = NuScenesReader(args.data, "v1.0-synth")


def detect(_i, sample):
    images = sample_images(det, sample)
    ts = sample.timestamp_us * 1e-6
    pts = sweep_points(sample)
    out = {}
    det.update_images(images, timestamp=ts)
    out["all"] = det.detect_sweep(pts, timestamp=ts)
    for name, dead in DEAD.items():
        det.update_images({c: a for c, a in images.items() if c not in dead}, timestamp=ts)
        out[name] = det.detect_sweep(pts, timestamp=ts)
    out["all dark"] = dark.detect_sweep(pts, timestamp=ts)
    gt[sample.token] = ground_truth_entries(sample)
    scenes[sample.token] = reader.scene_name(sample.token)
    poses[sample.token] = (sample.lidar2ego, sample.ego2global)
    ego[sample.token] = sample.ego2global[:3, 3].tolist()
    for name, d in out.items():
        saved.setdefault(name, {})[sample.token] = prediction_entries(sample, d, config.max_boxes_per_sample)
    return out


def progress(done, total):
    if done % 50 == 0 or done == total:
        print(f"{done}/{total} samples", flush=True)


scores, n = score_variants(StudyData(args.data, split=split, max_samples=args.max_samples), detect, progress)
args.out.mkdir(parents=True, exist_ok=True)
doc = {"export": args.export, "data": args.data, "split": args.split, "samples": n, "variants": {}}
for name, s in scores.items():
    print(f"{name:12s} mAP {100 * s.metrics.mean_ap:.2f}  NDS {100 * s.metrics.nd_score:.2f}")
    doc["variants"][name] = {"mAP": s.metrics.mean_ap, "NDS": s.metrics.nd_score}
    d = args.out / name.replace(" ", "_")
    d.mkdir(exist_ok=True)
    write_results_json(d / "results.json", saved[name], {"use_camera": True, "use_lidar": True})
    write_results_json(d / "gt.json", gt, {"use_camera": False, "use_lidar": False}, ego_positions=ego)
    write_sample_info(d / SAMPLES_FILE, scenes, poses, 8)
(args.out / "scores.json").write_text(json.dumps(doc, indent=1) + "\n")
