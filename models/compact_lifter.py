"""The export's lifter reading a compacted LUT (``calibration/compact_lut.py``) instead of K slots with sentinels.

``CompactLifter(export_lifter)`` takes ``features``, ``multi_index`` / ``multi_weight`` (K, M) (the voxels seen by
two or more cameras) and ``final_index`` / ``final_weight`` (Q, Z, Yq, Xq) (one row of ``[table; multi]`` per
voxel) and returns what the wrapped lifter returns on the K-slot LUT the compact form was made from: the gather is
the same sum per voxel (bit for bit in numpy, ``tests/test_compact_lut.py``), the convolutions are the wrapped
lifter's. A FoldedLifter's (and a FlatLifterExport's) gather is z-major, so the (Q, Z, Yq, Xq) index is permuted in the graph (an int32 map,
1 / C of the volume) as FoldedLifter permutes its LUT.

The export form of the lifter in the ``compact`` LUT layout (``streamdet-export --lut-layout compact``,
core/lut_layout.py; the runtime compacts each LUT it lifts with once). Measured against the K-slot lifter in
``benchmarks/compact_lifter.py``: docs/replay.md ("Less work per lift").
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from streamdet.models.lifter import VolumetricLifter, feature_table
from streamdet.models.flat_lifter import FlatLifterExport
from streamdet.models.lifter_fold import FoldedLifter


class CompactLifter(nn.Module):
    """``forward(features (J, C, Hf, Wf), multi_index (K, M) int32, multi_weight (K, M), final_index (Q, Z, Yq, Xq)
    int32, final_weight (Q, Z, Yq, Xq)) -> image_bev (Q, C, Yq, Xq)``, the wrapped lifter's function."""

    def __init__(self, lifter: FoldedLifter | FlatLifterExport | VolumetricLifter) -> None:
        super().__init__()
        if not isinstance(lifter, (FoldedLifter, FlatLifterExport, VolumetricLifter)):
            raise TypeError(
                f"CompactLifter wraps a FoldedLifter, a FlatLifterExport or a VolumetricLifter, got {type(lifter).__name__}"
            )
        self.lifter = lifter
        self.z_major = isinstance(lifter, (FoldedLifter, FlatLifterExport))  # both gather z-major

    def forward(self, features: Tensor, multi_index: Tensor, multi_weight: Tensor, final_index: Tensor,
                final_weight: Tensor) -> Tensor:  # fmt: skip
        table = feature_table(features)  # (R + 1, C), the sentinel row last
        c = table.shape[1]
        k = multi_index.shape[0]
        # M as -1: ONNX's Reshape reads a 0 in the shape as "keep that input dim", so an M = 0 LUT (no two cameras
        # overlap) would be reshaped to (K, C, C)
        multi = table.index_select(0, multi_index.reshape(-1)).reshape(k, -1, c)  # (K, M, C)
        multi = (multi * multi_weight.unsqueeze(-1)).sum(dim=0)  # (M, C) the multi-camera voxels combined
        ext = torch.cat([table, multi], dim=0)  # (R + 1 + M, C)
        q, z, yq, xq = final_index.shape
        if self.z_major:
            index = final_index.permute(0, 2, 3, 1)  # (Q, Yq, Xq, Z)
            weight = final_weight.permute(0, 2, 3, 1)  # (Q, Yq, Xq, Z)
        else:
            index, weight = final_index, final_weight  # (Q, Z, Yq, Xq)
        rows = ext.index_select(0, index.reshape(-1)) * weight.reshape(-1, 1)  # (V, C)
        if self.z_major:
            folded = rows.reshape(q, yq, xq, z * c).permute(0, 3, 1, 2)  # (Q, Z*C, Yq, Xq): channel z * C + c
            return self.lifter.convs.folded(folded)
        volume = rows.reshape(q, z, yq, xq, c).permute(0, 4, 1, 2, 3)  # (Q, C, Z, Yq, Xq)
        return self.lifter.convs(volume)
