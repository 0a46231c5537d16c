"""streamdet.export: PyTorch -> the three ONNX graphs, their fp16 siblings, lut.npz and manifest.json.

Modules: ``onnx_export`` (tracing, names, dynamic axes), ``fp16`` (conversion and its workarounds), ``parity``
(checks against PyTorch and between precisions), ``weights`` (checkpoints), ``exporter`` (one export run),
``cli`` (``streamdet-export``). The manifest schema the export writes is ``streamdet.runtime_ort.manifest``: the
runtime that reads it owns it, so a vehicle process needs runtime_ort and calibration, not this package.
"""
