"""Start weights for small_v3_swift from a small_v3_thin checkpoint (issue 22, twentieth session).

Every tensor whose name and shape are the same in both models is copied (image encoder, the lifter's input norm and
projection, pillar net, BEV encoder, head); the lifter's factorised residual (depthwise k3 + 1x1 + BN) starts from
its fresh initialisation. The image encoder's weights do not depend on the image size, so the 320 x 180 encoder
starts the 224 x 126 one. Usage: python init_swift.py THIN_WEIGHTS OUT_WEIGHTS
"""

from __future__ import annotations

import sys

import torch

from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset
from streamdet.training.checkpoint import load_weights, save_weights


def main(src: str, dst: str) -> None:
    thin, preset = load_weights(src)
    if preset.name != "small_v3_thin":
        raise SystemExit(f"{src}: expected a small_v3_thin checkpoint, got preset {preset.name!r}")
    swift_preset = get_preset("small_v3_swift")
    torch.manual_seed(0)
    swift = build_detector(swift_preset)
    theirs = thin.state_dict()
    mine = swift.state_dict()
    copied = {k: theirs[k] for k, v in mine.items() if k in theirs and theirs[k].shape == v.shape}
    fresh = sorted(set(mine) - set(copied))
    swift.load_state_dict({**mine, **copied})
    save_weights(dst, swift_preset, swift, meta={"init_from": src, "fresh": fresh})
    print(f"{dst}: {len(copied)} tensors from {src}, fresh: {', '.join(fresh)}")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    main(sys.argv[1], sys.argv[2])
