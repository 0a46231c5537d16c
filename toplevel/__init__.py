"""streamdet: camera + LiDAR streaming 3D object detection for the edge.

Subpackages: calibration (numpy), runtime_ort (numpy + onnxruntime), evaluation (numpy), data (numpy),
models / export / training (torch), benchmarks (CLI only).
"""

__version__ = "0.1.0"
