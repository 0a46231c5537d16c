"""Profile the phase-locked lane's graphs (encoder, term, tail) of an export: per-op kernel time per run."""
import sys, json, collections, glob, os
import numpy as np
import streamdet.runtime_ort.export_open as D  # where the detector builds its SessionConfig
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector_config import DetectorConfig
from streamdet.runtime_ort.pipeline import use_sample_calibration, sample_time_s, sample_images

exp = os.path.abspath(sys.argv[1]); prefix = os.path.abspath(sys.argv[2]); reps = int(sys.argv[3]) if len(sys.argv) > 3 else 30
_orig = D.SessionConfig
def patched(*a, **k):
    k["enable_profiling"] = True
    return _orig(*a, **k)
D.SessionConfig = patched
os.makedirs(prefix, exist_ok=True); os.chdir(prefix)
for f in glob.glob("*.json"): os.remove(f)
sample = load_bundled_sample()
d = StreamingDetector(exp, DetectorConfig(precision="int8", image_lane_precision="int8", enable_profiling=True, camera_terms=True))
use_sample_calibration(d, sample)
imgs = sample_images(d, sample)
t = sample_time_s(sample)
for i in range(reps):
    for q in range(4):
        d.update_images(imgs, timestamp=t + i * 0.05 + q * 0.01, quadrants=[q])
import gc, onnxruntime as ort
files = []
for o in gc.get_objects():
    if isinstance(o, ort.InferenceSession):
        try:
            files.append(o.end_profiling())
        except Exception:
            pass
files = [f for f in files if f]
for f in sorted(set(files) | set(glob.glob("*.json"))):
    try:
        ev = json.load(open(f))
    except Exception:
        continue
    node = collections.Counter(); cnt = collections.Counter(); n = 0; run_us = []
    for e in ev:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            node[e["args"]["op_name"]] += e["dur"]
        if e.get("cat") == "Session" and e["name"] == "model_run":
            n += 1; run_us.append(e["dur"])
    if not n: continue
    print(f"{os.path.basename(f)}: runs {n}, run median {np.median(run_us)/1e3:.3f} ms, kernel sum {sum(node.values())/n/1e3:.3f} ms")
    for op, us in node.most_common(10):
        print(f"   {op:22s} {us/n/1e3:.3f} ms")
