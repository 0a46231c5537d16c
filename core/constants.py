"""Names shared by the exporter, the manifest and the runtime: graph precisions and bundled-file sources."""

from __future__ import annotations

# The graph precisions an export can hold, in the order the manifest lists them.
PRECISIONS: tuple[str, ...] = ("fp32", "fp16", "int8")

# A source recorded in a manifest as "bundled:<path>" names a file shipped inside streamdet.data, not a path on
# the exporting machine.
BUNDLED_PREFIX = "bundled:"
BUNDLED_SAMPLE_DIR = "nuscenes_sample"  # the bundled real nuScenes sample, under streamdet.data
BUNDLED_SAMPLE_SOURCE = BUNDLED_PREFIX + BUNDLED_SAMPLE_DIR
BUNDLED_CALIBRATION_SOURCE = BUNDLED_SAMPLE_SOURCE + "/calibration.json"

# The shipped model (models/weights/small.pt) is of this preset; `streamdet-export` without arguments writes it to
# exports/<preset>, which every command that reads an export takes by default.
EXPORTS_ROOT = "exports"  # streamdet-export writes EXPORTS_ROOT/<preset> without --out
DEFAULT_PRESET = "small_v3"
DEFAULT_EXPORT_DIR = f"{EXPORTS_ROOT}/{DEFAULT_PRESET}"
MANIFEST_NAME = "manifest.json"  # what makes a folder an export (runtime_ort/manifest.py reads and writes it)

# The image sizes the tools run at (export, bench, synth, study): each side 16..4096 px. 4096 px is 2.5x nuScenes'
# 1600x900 (a 4K camera fits); past it a tool's image tensors alone run to gigabytes (30000x30000 asked the export
# for 2.7 GB in one image). calibration.camera.MAX_IMAGE_PX (65536) bounds what a file may declare, not what runs.
MIN_RESOLUTION_PX = 16
MAX_RESOLUTION_PX = 4096
STEM_STRIDE = 2  # the image encoder's ResNet stem stride: a model's image width and height are multiples of it
# Intra-op threads of one onnxruntime session (a lane's): one graph of this size gains nothing past a few dozen, and
# hundreds (180 a session, each with its own stack) made onnxruntime hang at start under a 6 GB address-space limit.
MAX_SESSION_THREADS = 64
