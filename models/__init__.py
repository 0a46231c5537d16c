"""streamdet.models: the detector in PyTorch (training and export side).

One concept per module: ``presets`` (torch-free configs), ``resnet``, ``fpn``, ``image_encoder``, ``lifter``,
``pillars``, ``bev_encoder``, ``heads``, ``detector`` (ImageEncoder / VolumetricLifter / SliceNet, StreamDetector,
build_detector), ``decode`` (SliceDecoder), ``flops``, and the export form: ``export_form`` (``to_export_form``, which
applies ``lifter_fold``, ``slice_split`` and ``bn_fold``). Nothing is imported here, so that
``streamdet.models.presets`` stays importable without torch.
"""
