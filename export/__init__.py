"""streamdet.export: PyTorch -> the three ONNX graphs, their fp16 siblings, lut.npz and manifest.json.

Modules: ``onnx_export`` (tracing, names, dynamic axes), ``fp16`` (conversion and its workarounds), ``parity``
(checks against PyTorch and between precisions), ``weights`` (checkpoints), ``exporter`` (one export run),
``cli`` (``streamdet-export``), ``manifest`` (the schema the runtime reads).

This file imports nothing: ``streamdet.export.manifest`` is imported by the torch-free runtime.
"""
