"""calibration/ must work in a vehicle process without PyTorch (its sources never import it: tests/test_import_graph.py)."""

from __future__ import annotations

import subprocess
import sys

SCRIPT = r"""
import sys
sys.modules["torch"] = None  # any `import torch` now raises ImportError
try:
    import torch  # noqa: F401
except ImportError:
    pass
else:
    raise SystemExit("torch block did not work")
import numpy as np
import streamdet.calibration as C
K = [[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]]
cam2lidar = C.make_transform(np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]), [0, 0, 0])  # looking along +x
rig = C.Rig((C.Camera("CAM", K, np.linalg.inv(cam2lidar), 64, 48),), np.eye(4), np.eye(4))
grid = C.GridSpec(x_range_m=(-4.0, 4.0), y_range_m=(-4.0, 4.0), z_range_m=(-1.0, 1.0), voxel_xy_m=0.5, voxel_z_m=1.0)
lut = C.build_lut(rig, grid)
assert lut.index.shape == (4, 1, 2, 8, 8), lut.index.shape
assert (lut.weight > 0).any()
assert not any(m == "torch" or m.startswith("torch.") for m in sys.modules if sys.modules[m] is not None)
print("ok")
"""


def test_import_and_build_lut_without_torch() -> None:
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ok"
