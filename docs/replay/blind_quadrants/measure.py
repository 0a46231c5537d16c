"""Quadrants none of whose cameras are given to a full update (the three back cameras dead: quadrants 2 and 3 of the
bundled rig), and every camera dark: what their slices read, measured three ways (docs/replay.md, "A quadrant without
cameras", thirty-second session).

    python measure.py EXPORT_DIR LIDAR_ONLY_EXPORT_DIR DATASET SPLIT|all

Run before that session's change: "zeros lifted" was what a full update did (the quadrant lifted from zero features and
stamped fresh), "no image BEV" what a slice read without images (an all-zero map). With the change both read the
camera-less BEV (the lift of zero features) and give the same score, and the full update clears the quadrant, so the
fallback detector gets it without the forget_images call below. Run on that code, the "zeros lifted" variants
measure the camera-less BEV too (their quadrant updates now clear), and "no image BEV" is no longer an all-zero map."""
import sys
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.detector_config import DetectorConfig
from streamdet.runtime_ort.pipeline import sample_images
from streamdet.studies.common import StudyData, score_variants, sweep_points

export, fallback, root = sys.argv[1], sys.argv[2], sys.argv[3]
split = None if sys.argv[4] == "all" else sys.argv[4]
dead = ("CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
det = StreamingDetector(export)
fb = StreamingDetector(export, DetectorConfig(fallback_export_dir=fallback))
blind_q = [q for q in range(4) if not set(det.quadrant_cameras((q,))) - set(dead)]
print("quadrants blind with", dead, "dead:", blind_q, flush=True)
lidar_only = StreamingDetector(fallback)
nobev = StreamingDetector(export)  # never updated: zero image BEV everywhere


def detect(_i, sample):
    images = sample_images(det, sample)
    ts = sample.timestamp_us * 1e-6
    pts = sweep_points(sample)
    live = {c: a for c, a in images.items() if c not in dead}
    out = {}
    det.update_images(images, timestamp=ts)
    out["all"] = det.detect_sweep(pts, timestamp=ts)
    det.update_images(live, timestamp=ts)
    out["back dead: zeros lifted"] = det.detect_sweep(pts, timestamp=ts)
    det.forget_images(quadrants=blind_q)
    out["back dead: no image BEV"] = det.detect_sweep(pts, timestamp=ts)
    fb.update_images(live, timestamp=ts)
    fb.forget_images(quadrants=blind_q)
    out["back dead: LiDAR-only fallback"] = fb.detect_sweep(pts, timestamp=ts)
    for q in range(4):  # a camera that does not see q: q is lifted from zero features alone
        other = next(c for c in det.camera_names if c not in det.quadrant_cameras((q,)))
        det.update_images({other: images[other]}, timestamp=ts, quadrants=(q,))
    out["none: zeros lifted"] = det.detect_sweep(pts, timestamp=ts)
    out["none: no image BEV"] = nobev.detect_sweep(pts, timestamp=ts)
    out["none: LiDAR-only"] = lidar_only.detect_sweep(pts, timestamp=ts)
    return out


scores, n = score_variants(StudyData(root, split=split), detect)
print(f"{n} samples of {root} ({split or 'every split'}), export {export}")
for k, s in scores.items():
    print(f"{k:34s} mAP {100 * s.metrics.mean_ap:.1f}  NDS {100 * s.metrics.nd_score:.1f}")
