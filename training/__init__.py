"""streamdet.training: CenterPoint targets and losses, per-slice data, the trainer (torch).

- ``targets``: ``TargetConfig``, ``build_targets`` (Gaussian heatmap + regression rows of one quadrant head map),
  ``gaussian_radius``, ``draw_gaussians`` (numpy)
- ``losses``: ``LossConfig``, ``loss_terms`` (FastFocal + masked L1 sums per task), ``CenterPointLoss``
- ``dataset``: ``DataConfig``, ``build_store`` / ``SampleStore`` (in-memory + .npy cache), ``SliceDataset``,
  ``class_balanced_indices``
- ``batching``: ``Collator`` (crop-and-stack of slice maps, batched LUT), ``Batch``
- ``model``: ``TrainingModel`` (the DDP-wrappable training forward)
- ``image_class``: the image-side class loss beside detection (``ImageBevClassifier``, training-only)
- ``schedule``: ``OneCycle`` over steps or wall time
- ``distributed``: torchrun / gloo process group, ``CrossProcessBatchNorm``
- ``checkpoint``: training checkpoints and shipped weights (``load_weights``)
- ``trainer``: ``TrainConfig``, ``train``; ``cli``: ``streamdet-train``
- ``torch_eval``: ``TorchSweepDetector`` (the PyTorch model scored like the ONNX runtime)

Nothing is imported here, so ``import streamdet.training.targets`` does not pull in the trainer.
"""
