"""Checkpoint -> ONNX export with the refiner-rt metadata contract and an enforced parity check.

    from export import export_checkpoint, export_model
    report = export_checkpoint("ckpt.pt", "refiner.onnx")   # raises ParityError instead of writing a bad model
    print(report.summary())

See :mod:`export.onnx_export` for the graph contract and the exporter decisions (dynamo exporter, how VGG-M's
LRN is written, uint8 input in OpenCV), :mod:`export.parity` for the checks, and :mod:`export.quantize` for INT8
models (``quantize_model``; schemes, the agreement bound and why dynamic MatMul/Gemm quantisation is the default).
"""

from __future__ import annotations

import importlib

# Lazy, like ``models``: ``export.bench_models`` (the benchmark's model builder behind ``refiner-rt bench``) must
# import without torch, so that the runtime-only install times ``--model`` files; the exporter loads on first use.
_EXPORTS = {
    **dict.fromkeys(["DEFAULT_LRN_LOWERING", "DEFAULT_OPSET", "LRN_LOWERINGS", "MIN_OPSET", "ExportReport",
                     "ParityError", "build_model_metadata", "export_checkpoint", "export_model", "to_onnx_proto"],
                    "export.onnx_export"),
    **dict.fromkeys(["DEFAULT_TOL", "MIN_PARITY_INPUTS", "ParityResult", "check_parity"], "export.parity"),
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
    if name not in _EXPORTS:
        raise AttributeError(f"module 'export' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
