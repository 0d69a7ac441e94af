"""Checkpoint -> ONNX export with the refiner-rt metadata contract and an enforced parity check.

    from export import export_checkpoint, export_model
    report = export_checkpoint("ckpt.pt", "refiner.onnx")   # raises ParityError instead of writing a bad model
    print(report.summary())

See :mod:`export.onnx_export` for the graph contract and the exporter decisions (dynamo exporter, how VGG-M's
LRN is written, uint8 input in OpenCV), :mod:`export.parity` for the checks, and :mod:`export.quantize` for INT8
models (``quantize_model``; schemes, the agreement bound and why dynamic MatMul/Gemm quantisation is the default).
"""

from __future__ import annotations

# The names below load lazily (PEP 562): importing a torch-free submodule such as export.defaults (what
# `refiner-rt export --help` needs) must not import torch through this package.
_LAZY = {
    "DEFAULT_LRN_LOWERING": "export.defaults",
    "DEFAULT_OPSET": "export.defaults",
    "MIN_OPSET": "export.defaults",
    "LRN_LOWERINGS": "export.onnx_export",
    "ExportReport": "export.onnx_export",
    "ParityError": "export.onnx_export",
    "build_model_metadata": "export.onnx_export",
    "export_checkpoint": "export.onnx_export",
    "export_model": "export.onnx_export",
    "to_onnx_proto": "export.onnx_export",
    "DEFAULT_TOL": "export.parity",
    "MIN_PARITY_INPUTS": "export.parity",
    "ParityResult": "export.parity",
    "check_parity": "export.parity",
}

__all__ = [
    "DEFAULT_LRN_LOWERING",
    "DEFAULT_OPSET",
    "DEFAULT_TOL",
    "MIN_OPSET",
    "MIN_PARITY_INPUTS",
    "ExportReport",
    "LRN_LOWERINGS",
    "ParityError",
    "ParityResult",
    "build_model_metadata",
    "check_parity",
    "export_checkpoint",
    "export_model",
    "to_onnx_proto",
]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'export' has no attribute {name!r}")
