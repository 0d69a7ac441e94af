"""The exporter's option values (opsets, LRN lowerings, INT8 schemes and bounds) in a module without torch.

``refiner-rt export --help`` reads them from here, so it answers without importing torch; :mod:`export.onnx_export`
and :mod:`export.quantize` import them from here too (one definition each).
"""

from __future__ import annotations

DEFAULT_OPSET = 18
MIN_OPSET = 18  # the dynamo exporter's native opset; conversion to lower opsets fails for these graphs

# How VGG-M's local response norms are written into the graph (export.onnx_export.LRN_LOWERINGS maps each name to
# its lowering function; a test holds the two in step).
LRN_LOWERING_NAMES = ("LRN", "decomposed")
DEFAULT_LRN_LOWERING = "decomposed"

SCHEMES = ("dynamic-int8", "static-qdq-int8")
DEFAULT_SCHEME = "dynamic-int8"
MAX_MEAN_DEG = 2.0   # bound on the mean INT8-vs-fp32 geodesic difference of q_out (degrees)
MAX_MAX_DEG = 15.0   # bound on the largest difference (degrees)
