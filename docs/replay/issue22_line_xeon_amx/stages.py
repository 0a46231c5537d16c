"""Per-stage int8 timing of the issue-22 export through the runtime (thirty-second session, docs/replay.md "A 2-vCPU
Intel Xeon guest with AMX"): encode 6 random frames, lift each quadrant alone, 8 slices of 20,000 random points; the
medians of 30 rounds. Run as `python stages.py LABEL EXPORT_DIR` (the export benchmarks/issue22_line.sh makes),
natively, under benchmarks/avx2_only.sh, or with a CPUID mask that hides AMX alone preloaded (avx2_only.c with only
leaf 7 EDX bits 22, 24, 25 and leaf 7.1 EAX bit 21 cleared, and its setenv dropped)."""
import statistics, sys, time
import numpy as np
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.detector_config import DetectorConfig
exp = sys.argv[2]
det = StreamingDetector(exp, DetectorConfig(precision="int8", image_lane_precision="int8"))
det.warm_up()
h, w = det.image_size if hasattr(det, "image_size") else (126, 224)
rng = np.random.default_rng(0)
imgs = {c: rng.integers(0, 255, (h, w, 3), np.uint8) for c in det.camera_names}
pts = rng.normal(0, 15, (20000, 6)).astype(np.float32); pts[:, 2] = rng.uniform(-2, 2, len(pts)); pts[:, 3:] = rng.uniform(0, 1, (len(pts), 3))
t = {"encode6": [], "lift_q": [], "slice": []}
for r in range(30):
    t0 = time.perf_counter(); enc = det.encode_images(imgs); t1 = time.perf_counter()
    t["encode6"].append((t1 - t0) * 1e3)
    for q in range(4):
        t0 = time.perf_counter(); det.update_images(imgs, float(r), quadrants=(q,), encoded=enc); t["lift_q"].append((time.perf_counter() - t0) * 1e3)
    for k in range(8):
        t0 = time.perf_counter(); det.detect_slice(pts, k, float(r)); t["slice"].append((time.perf_counter() - t0) * 1e3)
print(sys.argv[1], " ".join(f"{k} {statistics.median(v):.2f}" for k, v in t.items()), flush=True)
