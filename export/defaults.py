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

DEFAULT_SCHEME = "dynamic-int8"
MAX_MEAN_DEG = 2.0   # bound on the mean INT8-vs-fp32 geodesic difference of q_out (degrees)
MAX_MAX_DEG = 15.0   # bound on the largest difference (degrees)
SCHEMES = ("dynamic-int8", "static-qdq-int8", "static-qdq-int8-conv", "static-qdq-int8-conv-float-pose")
CALIBRATED_SCHEMES = ("static-qdq-int8", "static-qdq-int8-conv", "static-qdq-int8-conv-float-pose")  # need calibration crops (a dataset's, for a model in use)
# static-qdq-int8-conv (export.quantize): the convolutions with at least CONV_MIN_CHANNELS input channels are
# quantised (the first, on the 3-channel image, stays fp32), and the fully connected layers with at least
# CONV_SCHEME_FC_MIN_WEIGHTS weights, "static"ally or "dynamic"ally; 7-bit weights when CONV_SCHEME_REDUCE_RANGE.
CONV_MIN_CHANNELS = 16
CONV_SCHEME_FC = "dynamic"
CONV_SCHEME_FC_MIN_WEIGHTS = 65536
CONV_SCHEME_REDUCE_RANGE = True
