"""Stack several ``SampleItem``s into one training batch: the paper's crop-and-stack (Sec. III-C).

Every slice contributes one map per quadrant it touches (one with n >= 4); the maps of all slices are stacked
along Q, slice-major, quadrants increasing, exactly as the runtime stacks one slice's quadrants. So the BEV
encoder and head see Q = (number of slice maps) and their batch norms share statistics across the batch.

Image lane: the images of all samples are stacked along J and encoded in one call. The lifter runs on *lift
entries*, each one quadrant volume of one sample; a slice map reads the image BEV of its entry (``map_source``).
With camera mode "all" a sample's entry for quadrant q serves every slice in q (as the runtime's cached image
BEV does); with "overlapping" each slice map gets its own entry whose LUT sends the non-overlapping cameras to
the all-zero sentinel row, which is what zero features for those cameras would give.

LUT rows of sample b shift by ``b * J * Hf * Wf`` and every sentinel moves to the batch's one sentinel row,
``B * J * Hf * Wf`` (the feature table the lifter builds is ``(B * J * Hf * Wf + 1, C)``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.calibration.lut import Lut, check_rig_fits
from streamdet.calibration.lut_build import build_lut
from streamdet.models.presets import Preset
from streamdet.training.dataset import CAMERA_MODES, SampleItem, SampleStore


@dataclass
class Batch:
    """One training batch; tensors only (plus counts), ready for ``.to(device)``."""

    images: Tensor | None  # (B * J, H, W, 3) uint8
    lut_index: Tensor | None  # (L, K, Z, Yq, Xq) int64 rows of the batch feature table
    lut_weight: Tensor | None  # (L, K, Z, Yq, Xq) float32
    map_source: Tensor | None  # (Qm,) int64 lift entry feeding each slice map
    map_sample: Tensor | None  # (Qm,) int64 sample (of the batch's B) each slice map belongs to
    pillar_features: Tensor  # (P, M, 11) float32
    pillar_mask: Tensor  # (P, M) float32
    pillar_index: Tensor  # (P,) int64 into the stacked slice maps: map * Yq * Xq + row * Xq + col ((ny, nx) maps
    # without the crop)
    heatmap: Tensor  # (Qm, num_classes, Hh, Wh) float32
    index: Tensor  # (Qm, K_obj) int64
    mask: Tensor  # (Qm, K_obj) bool
    label: Tensor  # (Qm, K_obj) int64
    box: Tensor  # (Qm, K_obj, 10) float32
    num_samples: int
    num_slices: int
    # store indices of the samples left out of this batch for holding no pillar in any of their slices (a sweep that
    # is empty, all NaN or outside the grid); the trainer counts and names them
    skipped: tuple[int, ...] = ()
    # objects beyond their head map's cap (TargetConfig.max_objects), summed over the batch's maps: no target, so
    # the trainer counts them (the run would otherwise never say that a crowded scene lost boxes)
    num_dropped: int = 0

    @property
    def num_maps(self) -> int:
        return self.heatmap.shape[0]

    def to(self, device: torch.device | str) -> "Batch":
        moved = {}
        for f in fields(self):
            v = getattr(self, f.name)
            moved[f.name] = v.to(device, non_blocking=True) if isinstance(v, Tensor) else v
        return Batch(**moved)


def check_rig_fits_preset(rig: Rig, preset: Preset, where: str) -> None:
    """ValueError (one line, led by ``where``: the dataset and sample) unless the preset's images fit every camera of
    ``rig``: ``calibration.lut.check_rig_fits``, the rule streamdet-export and the runtime apply to the same rig. A
    camera of another aspect would be trained on distorted images, with a LUT of intrinsics that no longer describe
    them, and no export of the model could run on its data afterwards."""
    img = preset.image
    try:
        check_rig_fits(rig, rig.names, img.width_px, img.height_px)
    except CalibrationError as e:
        raise ValueError(
            f"{where}: its cameras do not fit the {img.width_px}x{img.height_px} images of preset {preset.name!r}, "
            f"which streamdet-export and the runtime would refuse too ({e}); train on a dataset whose cameras have "
            "the aspect of the preset's images"
        ) from None


class Collator:
    """``collate(items) -> Batch``; builds (and caches) one projection LUT per rig at the preset's image size, each
    rig checked first (``check_rig_fits_preset``); ``check_store`` checks a whole dataset before training."""

    def __init__(self, preset: Preset, camera_mode: str = "all") -> None:
        if camera_mode not in CAMERA_MODES:
            raise ValueError(f"camera_mode must be one of {CAMERA_MODES}, got {camera_mode!r}")
        self.preset = preset
        self.camera_mode = camera_mode
        self._luts: dict[str, Lut] = {}

    def check_store(self, store: SampleStore, dataset: str | Path) -> None:
        """``check_rig_fits_preset`` for every sample of ``store`` (read from ``dataset``), before any batch is made
        (in a loader's worker process the error would come wrapped in a traceback). LiDAR-only presets read no
        image."""
        if not self.preset.use_image:
            return
        for token, rig in zip(store.tokens, store.rigs):
            check_rig_fits_preset(rig, self.preset, f"dataset {dataset}, sample {token}")

    def lut(self, rig: Rig, where: str = "a sample") -> Lut:
        key = rig.sha256()
        if key not in self._luts:
            check_rig_fits_preset(rig, self.preset, where)
            img = self.preset.image
            self._luts[key] = build_lut(rig, self.preset.grid, img.feature_stride, image_size=(img.width_px, img.height_px),
                                        heights_per_voxel=self.preset.lifter.lut_heights_per_voxel)  # fmt: skip
        return self._luts[key]

    def __call__(self, items: list[SampleItem]) -> Batch:
        if not items:
            raise ValueError("collate needs at least one sample")
        p = self.preset
        # A sample whose slices hold no pillar at all has nothing for the model to read while its boxes would still
        # be targets, and a batch of only such samples made the pillar net fail on zero pillars mid-epoch (hours into
        # a run): such samples are left out and named in ``skipped``, a batch of none comes back empty (num_samples
        # 0) and the trainer skips it. A sample with pillars in some slice trains as before.
        skipped = tuple(it.sample_index for it in items if not any(len(sl.pillars.index) for sl in it.slices))
        items = [it for it in items if it.sample_index not in skipped]
        if not items:
            return self.empty_batch(skipped)
        rows, cols = p.map_cells  # a quadrant, or the whole grid without the crop (calibration/slice_maps.py)
        cells = rows * cols
        feats, masks, indices = [], [], []
        heat, obj_index, obj_mask, obj_label, obj_box = [], [], [], [], []
        map_source: list[int] = []
        map_sample: list[int] = []
        entries: list[tuple[int, int, tuple[str, ...] | None]] = []  # (sample b, quadrant, cameras or None = all)
        entry_of: dict[tuple[int, int], int] = {}
        num_maps = 0
        num_dropped = 0
        for b, item in enumerate(items):
            for sl in item.slices:
                pil = sl.pillars
                feats.append(pil.features)
                masks.append(pil.mask)
                # pillar_index is qi * cells + cell within the slice's own stack; shift to the batch stack.
                indices.append(pil.index + num_maps * cells)
                # one map per quadrant with the crop (a fused net's maps read their quadrant's image BEV); one map of
                # the whole grid without it (LiDAR-only: the quadrant is not read)
                for q, t in zip(sl.quadrants if p.slice_crop else (None,), sl.targets):
                    heat.append(t.heatmap)
                    obj_index.append(t.index)
                    obj_mask.append(t.mask)
                    obj_label.append(t.label)
                    obj_box.append(t.box)
                    num_dropped += int(t.num_dropped)
                    if p.use_image:
                        map_sample.append(b)
                        if self.camera_mode == "all":
                            key = (b, q)
                            if key not in entry_of:
                                entry_of[key] = len(entries)
                                entries.append((b, q, None))
                            map_source.append(entry_of[key])
                        else:
                            map_source.append(len(entries))
                            entries.append((b, q, sl.camera_names))
                    num_maps += 1

        images = lut_index = lut_weight = source = sample_of_map = None
        if p.use_image:
            images = torch.from_numpy(np.stack([it.images for it in items]))  # (B, J, H, W, 3)
            num_cams = images.shape[1]
            images = images.reshape(-1, *images.shape[2:])  # (B * J, H, W, 3)
            idx, wgt = self._lift_entries(items, entries, num_cams)
            lut_index, lut_weight = torch.from_numpy(idx), torch.from_numpy(wgt)
            source = torch.tensor(map_source, dtype=torch.int64)
            sample_of_map = torch.tensor(map_sample, dtype=torch.int64)

        m = p.pillars.max_points_per_pillar
        return Batch(
            images=images,
            lut_index=lut_index,
            lut_weight=lut_weight,
            map_source=source,
            map_sample=sample_of_map,
            pillar_features=torch.from_numpy(np.concatenate(feats) if feats else np.zeros((0, m, 11), np.float32)),
            pillar_mask=torch.from_numpy(np.concatenate(masks) if masks else np.zeros((0, m), np.float32)),
            pillar_index=torch.from_numpy(np.concatenate(indices) if indices else np.zeros(0, np.int64)),
            heatmap=torch.from_numpy(np.stack(heat)),
            index=torch.from_numpy(np.stack(obj_index)),
            mask=torch.from_numpy(np.stack(obj_mask)),
            label=torch.from_numpy(np.stack(obj_label)),
            box=torch.from_numpy(np.stack(obj_box)),
            num_samples=len(items),
            num_slices=sum(len(it.slices) for it in items),
            skipped=skipped,
            num_dropped=num_dropped,
        )

    def empty_batch(self, skipped: tuple[int, ...]) -> Batch:
        """A batch that holds no sample (every one was ``skipped``): zero-length tensors, never stepped on."""
        m = self.preset.pillars.max_points_per_pillar
        none = torch.zeros(0, dtype=torch.int64)
        return Batch(images=None, lut_index=None, lut_weight=None, map_source=None, map_sample=None,
                     pillar_features=torch.zeros(0, m, 11), pillar_mask=torch.zeros(0, m), pillar_index=none,
                     heatmap=torch.zeros(0), index=none, mask=torch.zeros(0, dtype=torch.bool), label=none,
                     box=torch.zeros(0), num_samples=0, num_slices=0, skipped=skipped)  # fmt: skip

    def _lift_entries(self, items: list[SampleItem], entries, num_cams: int) -> tuple[np.ndarray, np.ndarray]:
        rows_per_image = self.preset.image.feature_height * self.preset.image.feature_width
        batch_sentinel = len(items) * num_cams * rows_per_image
        out_idx, out_w = [], []
        for b, q, cams in entries:
            item = items[b]
            lut = self.lut(item.rig, f"sample {item.sample_index}")
            if lut.num_cameras != num_cams:
                raise ValueError(f"sample {item.sample_index}: its LUT has {lut.num_cameras} cameras but the batch images have {num_cams}")
            idx = lut.index[q].astype(np.int64)  # (K, Z, Yq, Xq)
            empty = idx == lut.sentinel
            if cams is not None:
                allowed = np.zeros(num_cams + 1, bool)  # the extra slot is the sentinel's "camera"
                allowed[[item.rig.names.index(c) for c in cams]] = True
                empty |= ~allowed[np.minimum(idx // rows_per_image, num_cams)]
            out_idx.append(np.where(empty, batch_sentinel, idx + b * num_cams * rows_per_image))
            out_w.append(lut.weight[q])
        return np.stack(out_idx), np.stack(out_w).astype(np.float32)  # (L, K, Z, Yq, Xq) each
