"""CPU speed benchmark behind ``refiner-rt bench --cpu``: the full ``refine()`` path, models side by side, each row
next to its roofline bound.

What is timed is what robot code pays per call: crop every box out of a 640x480 BGR frame with the
shared crop rule, run the network, compose ``q_in * q_out`` in float64 (models trained in the viewing-ray frame
get the frame's ``K``, as robot code gives it). Models are measured interleaved (round-robin, several rounds) so
that drift of a shared machine hits all of them alike, and every ratio comes from one run. Reported: median (p50)
and p90 latency per call and refinements per second (``batch / p50``).

With no ``--model``, it times:

* the shipped refiners (trained weights; INT8 and fp32): by default one representative object, the first
  shipped (every shipped model has the same architecture, so they run at the same speed; ``--shipped all`` times
  each, ``--shipped none`` none);
* the paper's networks, :data:`DEFAULT_ARCHS` (``shallow``, the paper's network; ``vggm``, its deep variant) and any
  ``--variant`` configs, built with random weights and exported (speed does not depend on the weight values), each
  in fp32 and, quantised in the same run with :mod:`export.quantize`'s default scheme, in INT8. This needs the
  training extra (torch); without it (a runtime-only install) only the shipped models are timed, and the output says
  so. The built networks are also timed in PyTorch eager mode (batches up to :data:`TORCH_MAX_BATCH`) for the
  onnxruntime/PyTorch ratio.

Every row says which weights it has (``weights``: ``trained``, ``random`` or ``user-supplied``), and onnxruntime rows
give their speed over the paper's shallow network (``ratio_over_shallow``) at the same threads and batch, INT8
over INT8 and fp32 over fp32.

Roofline (when the ``onnx`` package is installed): a lower bound on the time of one inference from the
machine's measured limits (see :class:`MachineLimits`):

    t_memory  = weight bytes per call / memory bandwidth     (every weight is read once per call, any batch)
    t_compute = batch * (fp32 FLOPs / fp32 peak + int8 ops / int8 peak)   (per crop, peaks at the row's threads)
    bound     = batch / max(t_memory, t_compute)  refinements/s

The limits are measured inside every (threads, batch) cell, interleaved round by round with the models, so a
machine loaded by other work lowers the limits and the models alike; each limit is the best of its rounds (the
least disturbed), each model the median of its calls. Each row reports ``roofline_ratio = fps / bound``: 1.0 would
be the hardware limit for that inference. The bound covers the network only (not cropping or composition), counts
weights but not activations, and assumes weights come from DRAM, so a model whose weights stay in the L2/L3 caches
between calls can beat it. A ratio above 1 therefore says the bound was not a bound (limits under-measured, or
weights served from cache), not that the model beat the hardware: such a row gets no ratio (``None``, and "n/a" in
the table), and ``roofline_note`` says why.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import platform
import statistics
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import click
import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.errors import TRAINING_INSTALL, ModelError
from refiner_rt.checks import MAX_BATCH, validate_boxes
from refiner_rt.preprocess import crop_batch
from refiner_rt.session import available_cores

log = logging.getLogger(__name__)

FRAME_W, FRAME_H = 640, 480
# Intrinsics of the synthetic frame (YCB-Video's camera), passed to models trained in the viewing-ray frame.
FRAME_K = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])


def frame_K(sess):
    """The synthetic frame's intrinsics for a model in the viewing-ray frame (it requires K), else None: validating
    an unused K would add to a camera-frame model's timings."""
    return FRAME_K if sess.contract.rotation_frame == "ray" else None


DEFAULT_ARCHS = ("shallow", "vggm")  # the paper's networks, random weights; the shipped refiners join them
TORCH_MAX_BATCH = 8  # PyTorch eager VGG-M takes ~2 s per call at batch 32: only smaller batches are timed
BANDWIDTH_BUFFER_MB = 256  # much larger than the L3 caches of the CPUs the project runs on (32 MB)
PEAK_MATMUL_SIZE = 1024  # M = N = K of the matrix products that measure the compute peaks


@dataclass
class BenchRow:
    """One measured cell: a model on a runtime at a batch size and thread count, with its roofline bound.

    Attributes:
        arch: registered architecture (from the model's metadata).
        runtime: ``"onnxruntime"`` or ``"torch"`` (eager).
        threads: threads the network ran on.
        batch: boxes per ``refine()`` call.
        fps: refinements per second, ``batch / p50``.
        p50_ms, p90_ms: latency percentiles of one call (ms).
        calls: number of timed calls.
        model: label: the architecture, a ``--variant`` label, a shipped model's object id, or the file stem of a
            ``--model``.
        quantization: the metadata ``quantization`` of the ONNX model (``"none"`` for fp32; an INT8 scheme of
            :data:`refiner_rt.metadata.QUANTIZATIONS`).
        weights: ``"trained"`` (a shipped model), ``"random"`` (built for the benchmark) or ``"user-supplied"``.
        config: the config overrides of a ``--variant`` (JSON object), else ``{}``.
        ratio_shallow_over_vggm: shallow / VGG-M fps at the same runtime, quantisation, threads and batch
            (default configs only; on the shallow row).
        ratio_onnxruntime_over_torch: this onnxruntime row's fps over the PyTorch eager fp32 fps of the same network.
        ratio_over_shallow: this onnxruntime row's fps over the paper's shallow network's (the row labelled
            ``shallow``, or a ``--model`` file ``shallow.onnx`` / ``shallow.int8.onnx``) at the same threads and batch,
            INT8 over INT8 and fp32 over fp32 (None on that row itself, or without one).
        weight_bytes: bytes of weights read per call.
        flops_per_call: fp32 floating-point operations per call (2 per multiply-add; convolutions and fully
            connected layers).
        int8_ops_per_call: int8 operations per call (2 per multiply-add) of the quantised layers.
        bound_fps: roofline bound in refinements per second (None without the ``onnx`` package).
        bound: ``"memory"`` or ``"compute"``: which limit sets the bound.
        roofline_ratio: ``fps / bound_fps`` when at most 1; None when above (see ``roofline_note``).
        roofline_note: why a row with a bound has no ratio, else None.
        bandwidth_gbs, peak_fp32_gflops, peak_int8_gops: the limits measured in this row's cell (interleaved with
            the models; peaks at the row's thread count).
    """

    arch: str
    runtime: str
    threads: int
    batch: int
    fps: float
    p50_ms: float
    p90_ms: float
    calls: int
    model: str
    quantization: str = "none"
    weights: str = "random"
    config: dict = field(default_factory=dict)
    ratio_shallow_over_vggm: float | None = None
    ratio_onnxruntime_over_torch: float | None = None
    ratio_over_shallow: float | None = None
    weight_bytes: int | None = None
    flops_per_call: float | None = None
    int8_ops_per_call: float | None = None
    bound_fps: float | None = None
    bound: str | None = None
    roofline_ratio: float | None = None
    roofline_note: str | None = None
    bandwidth_gbs: float | None = None
    peak_fp32_gflops: float | None = None
    peak_int8_gops: float | None = None


# ---------------------------------------------------------------------------------------------------- machine
# The vector instruction sets that decide onnxruntime's fp32 and int8 kernels (MLAS picks them at run time).
_SIMD_FLAG_PREFIXES = ("sse4", "avx", "fma", "f16c", "amx", "vnni")


def cpu_flags() -> list[str]:
    """The CPU's vector-instruction flags from ``/proc/cpuinfo`` (``avx2``, ``avx512f``, ``avx512_vnni``, ``fma``...);
    empty where that file does not exist (not Linux)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return sorted(f for f in line.split(":", 1)[1].split() if f.startswith(_SIMD_FLAG_PREFIXES))
    except OSError:
        pass
    return []


def machine_info() -> dict:
    """CPU model, its vector-instruction flags, core count and library versions of this machine; with torch
    installed also the instruction set torch dispatches to (``torch.backends.cpu.get_cpu_capability()``, e.g.
    ``"AVX2"``, ``"AVX512"``), else None."""
    import onnxruntime

    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    info = {
        "cpu": cpu,
        "cpu_flags": cpu_flags(),
        "cores": available_cores(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "onnxruntime": onnxruntime.__version__,
        "platform": platform.platform(),
    }
    try:
        import torch

        info["torch"] = torch.__version__
        info["cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    except ModuleNotFoundError:
        info["torch"] = info["cpu_capability"] = None
    return info


def synthetic_frame(batch: int, seed: int = 0):
    """A 640x480 BGR frame, ``batch`` boxes of varied size (xyxy pixels) and ``batch`` coarse rotations (wxyz)."""
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (FRAME_H, FRAME_W, 3), dtype=np.uint8)
    side = rng.uniform(60, 200, size=batch)
    cx = rng.uniform(100, FRAME_W - 100, size=batch)
    cy = rng.uniform(100, FRAME_H - 100, size=batch)
    boxes = np.stack([cx - side / 2, cy - side / 2, cx + side / 2, cy + side * 0.4], axis=1)
    q_in = rq.sample_rotation_noise(batch, "uniform", 0, 180, rng)
    return image, boxes, q_in


# ---------------------------------------------------------------------------------------------------- roofline
@dataclass(frozen=True)
class MachineLimits:
    """The machine's measured limits for the roofline.

    Attributes:
        bandwidth: DRAM bandwidth in bytes/s: ``numpy.copyto`` of a buffer much larger than L3
            (:data:`BANDWIDTH_BUFFER_MB`), counting the bytes read plus the bytes written (STREAM's "copy"
            convention), one thread.
        peak_fp32: ``{threads: FLOP/s}`` of onnxruntime's fp32 ``MatMul`` on 1024x1024 matrices (the MLAS kernels
            the models use).
        peak_int8: ``{threads: ops/s}`` of onnxruntime's ``MatMulInteger`` (uint8 x int8, the kernels of the
            quantised layers) on 1024x1024 matrices. Measured, not derived from the fp32 peak.
    """

    bandwidth: float
    peak_fp32: dict
    peak_int8: dict

    def as_dict(self) -> dict:
        return {
            "bandwidth_gbs": self.bandwidth / 1e9,
            "peak_fp32_gflops": {str(k): v / 1e9 for k, v in self.peak_fp32.items()},
            "peak_int8_gops": {str(k): v / 1e9 for k, v in self.peak_int8.items()},
        }


@dataclass(frozen=True)
class ModelCost:
    """What one inference of a model must move and compute.

    Attributes:
        weight_bytes: bytes of all initializers (weights, biases, scales) as stored in the graph.
        flops: fp32 FLOPs per crop (2 per multiply-add of convolutions and fully connected layers).
        int8_ops: int8 operations per crop (2 per multiply-add of the quantised layers).
        quantization: the model's metadata ``quantization`` (``"none"`` when absent).
    """

    weight_bytes: int
    flops: float
    int8_ops: float
    quantization: str = "none"


def _copy_runner(megabytes: int):
    """A callable that copies a ``megabytes`` buffer once, and the bytes it moves (read + written)."""
    n = megabytes * 2**20
    src = np.ones(n, dtype=np.uint8)
    dst = np.zeros(n, dtype=np.uint8)  # touched: no page faults in the timed copies
    return (lambda: np.copyto(dst, src)), 2 * n


def measure_bandwidth(megabytes: int = BANDWIDTH_BUFFER_MB, repeats: int = 5) -> float:
    """DRAM bandwidth in bytes/s: median of ``repeats`` numpy copies of a buffer, (read + written bytes) / time."""
    copy, nbytes = _copy_runner(megabytes)
    return nbytes / statistics.median(_time_calls(copy, repeats))


def _matmul_model(int8: bool, size: int) -> bytes:
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    if int8:
        b = rng.integers(-127, 128, (size, size), dtype=np.int8)
        a_type, node = TensorProto.UINT8, helper.make_node("MatMulInteger", ["a", "b"], ["y"])
        y_type = TensorProto.INT32
    else:
        b = rng.standard_normal((size, size)).astype(np.float32)
        a_type, node, y_type = TensorProto.FLOAT, helper.make_node("MatMul", ["a", "b"], ["y"]), TensorProto.FLOAT
    graph = helper.make_graph(
        [node], "peak",
        [helper.make_tensor_value_info("a", a_type, [size, size])],
        [helper.make_tensor_value_info("y", y_type, [size, size])],
        initializer=[numpy_helper.from_array(b, "b")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    return model.SerializeToString()


def _matmul_runner(int8: bool, threads: int, size: int):
    """A callable that runs one ``size``-cubed fp32 ``MatMul`` or int8 ``MatMulInteger`` in onnxruntime, and its
    operation count (2 per multiply-add)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    sess = ort.InferenceSession(_matmul_model(int8, size), options, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (size, size), dtype=np.uint8) if int8 else rng.standard_normal((size, size)).astype(np.float32)
    feed = {"a": a}
    sess.run(None, feed)
    return (lambda: sess.run(None, feed)), 2.0 * size**3


def measure_peak(int8: bool, threads: int, size: int = PEAK_MATMUL_SIZE, repeats: int = 7) -> float:
    """Operations per second of onnxruntime's fp32 ``MatMul`` or int8 ``MatMulInteger`` (2 ops per multiply-add)."""
    run, ops = _matmul_runner(int8, threads, size)
    return ops / statistics.median(_time_calls(run, repeats))


def measure_limits(thread_counts) -> MachineLimits:
    """Bandwidth once, fp32 and int8 peaks for each thread count, measured back to back (not interleaved with
    models: :class:`LimitProbe` is what the benchmark uses)."""
    return MachineLimits(
        bandwidth=measure_bandwidth(),
        peak_fp32={n: measure_peak(False, n) for n in thread_counts},
        peak_int8={n: measure_peak(True, n) for n in thread_counts},
    )


class LimitProbe:
    """The roofline's limit measurements as runners that take turns with the models in
    :func:`measure_interleaved`, so that the limits and the models of one cell see the same machine.

    Args:
        megabytes: size of the copied buffer (bandwidth).
        size: side of the matrices (peaks).
    """

    BANDWIDTH, FP32, INT8 = "limit:bandwidth", "limit:fp32", "limit:int8"

    def __init__(self, megabytes: int = BANDWIDTH_BUFFER_MB, size: int = PEAK_MATMUL_SIZE):
        self._copy = _copy_runner(megabytes)
        self._size = size
        self._matmuls: dict = {}

    def runners(self, threads: int) -> dict:
        """``{key: callable}`` for the bandwidth and the fp32 and int8 peaks at ``threads`` threads."""
        for int8 in (False, True):
            if (int8, threads) not in self._matmuls:
                self._matmuls[(int8, threads)] = _matmul_runner(int8, threads, self._size)
        return {self.BANDWIDTH: self._copy[0], self.FP32: self._matmuls[(False, threads)][0],
                self.INT8: self._matmuls[(True, threads)][0]}

    def limits(self, threads: int, latencies: dict) -> MachineLimits:
        """The limits from the latencies :func:`measure_interleaved` measured for :meth:`runners`: each the best
        (fastest) of its calls, the one least disturbed by other work."""
        best = {key: min(latencies[key]) for key in (self.BANDWIDTH, self.FP32, self.INT8)}
        return MachineLimits(
            bandwidth=self._copy[1] / best[self.BANDWIDTH],
            peak_fp32={threads: self._matmuls[(False, threads)][1] / best[self.FP32]},
            peak_int8={threads: self._matmuls[(True, threads)][1] / best[self.INT8]},
        )


_CONV_OPS = {"Conv": 1, "ConvInteger": 1, "QLinearConv": 3}  # op -> index of the weight input
_MATMUL_OPS = {"Gemm": (0, 1), "MatMul": (0, 1), "MatMulInteger": (0, 1), "QLinearMatMul": (0, 3), "QGemm": (0, 3)}
_INT8_OPS = {"ConvInteger", "QLinearConv", "MatMulInteger", "QLinearMatMul", "QGemm"}


def model_cost(path) -> ModelCost:
    """Weight bytes and per-crop operations of an ONNX refiner, counted from its graph (batch fixed to 1).

    Convolutions count ``output elements * (C_in / group * kH * kW)`` multiply-adds; ``Gemm``/``MatMul`` count
    ``rows * K * N``. A layer is int8 when its operator is (``MatMulInteger``, ``QLinearConv``...) or, in QDQ
    graphs, when its weight comes through ``DequantizeLinear``. Everything else (pooling, elementwise) is ignored.
    """
    import onnx
    from onnx import helper, shape_inference

    proto = onnx.load(str(path))
    graph = proto.graph
    weight_bytes = 0
    shapes: dict[str, list] = {}
    for t in graph.initializer:
        itemsize = np.dtype(helper.tensor_dtype_to_np_dtype(t.data_type)).itemsize
        weight_bytes += int(np.prod(t.dims, dtype=np.int64)) * itemsize
        shapes[t.name] = list(t.dims)
        if len(t.raw_data) > 4096:  # weights: shape inference needs their dims only (and is 500x faster without)
            t.ClearField("raw_data")
    for value in graph.input:
        value.type.tensor_type.shape.dim[0].dim_value = 1
    inferred = shape_inference.infer_shapes(proto, data_prop=True).graph
    for value in [*inferred.value_info, *inferred.input, *inferred.output]:
        dims = [d.dim_value if d.HasField("dim_value") else None for d in value.type.tensor_type.shape.dim]
        shapes.setdefault(value.name, dims)
    dequantized = {o: n.input[0] for n in graph.node if n.op_type == "DequantizeLinear" for o in n.output}
    flops = int8_ops = 0.0
    for node in graph.node:
        if node.op_type in _CONV_OPS:
            w = shapes.get(dequantized.get(node.input[_CONV_OPS[node.op_type]], node.input[_CONV_OPS[node.op_type]]))
            out = shapes.get(node.output[0])
            if not w or not out or None in out:
                continue
            macs = float(np.prod(out)) * float(np.prod(w[1:]))
            weight_input = node.input[_CONV_OPS[node.op_type]]
        elif node.op_type in _MATMUL_OPS:
            ia, ib = _MATMUL_OPS[node.op_type]
            a, b = shapes.get(node.input[ia]), shapes.get(node.input[ib])
            if not a or not b or None in a or None in b:
                continue
            trans_b = any(at.name == "transB" and at.i for at in node.attribute)
            k, n = (b[-1], b[-2]) if trans_b else (b[-2], b[-1])
            macs = float(np.prod(a[:-1])) * k * n
            weight_input = node.input[ib]
        else:
            continue
        if node.op_type in _INT8_OPS or weight_input in dequantized:
            int8_ops += 2 * macs
        else:
            flops += 2 * macs
    quantization = next((p.value for p in proto.metadata_props if p.key == "quantization"), "none")
    return ModelCost(weight_bytes=weight_bytes, flops=flops, int8_ops=int8_ops, quantization=quantization)


def roofline_bound(cost: ModelCost, batch: int, threads: int, limits: MachineLimits) -> tuple[float, str]:
    """``(refinements/s, "memory" | "compute")``: the roofline bound of one call at ``batch`` crops."""
    t_memory = cost.weight_bytes / limits.bandwidth
    t_compute = batch * (cost.flops / limits.peak_fp32[threads] + cost.int8_ops / limits.peak_int8[threads])
    return batch / max(t_memory, t_compute, 1e-12), "memory" if t_memory >= t_compute else "compute"


def describe_roofline(label: str, cost: ModelCost, limits: MachineLimits, threads) -> str:
    """One line for people: what bounds this model, at batch 1, per thread count."""
    t_mem = cost.weight_bytes / limits.bandwidth
    parts = []
    for n in threads:
        t_cpu = cost.flops / limits.peak_fp32[n] + cost.int8_ops / limits.peak_int8[n]
        parts.append(f"{n} thr {t_cpu * 1e3:.3f} ms")
    ops = f"{cost.flops / 1e6:.1f} MFLOP fp32" + (f" + {cost.int8_ops / 1e6:.1f} Mop int8" if cost.int8_ops else "")
    return (
        f"  {label} ({cost.quantization}): weights {cost.weight_bytes / 1e6:.1f} MB/call -> {t_mem * 1e3:.3f} ms; "
        f"{ops} per crop -> {', '.join(parts)} at batch 1"
    )


# ---------------------------------------------------------------------------------------------------- runners
class TorchRefiner:
    """The refine() path with a PyTorch eager network instead of onnxruntime (for the ratio row).

    Same crop rule and composition as :class:`refiner_rt.RefinerSession`; only the network call differs.
    """

    def __init__(self, model, threads: int):
        import torch

        self.torch = torch
        self.model = model.eval()
        self.threads = threads
        self.size = int(model.input_size)
        self.context = float(getattr(model, "config", {}).get("crop_context", 1.2))
        self._buffer = np.zeros((0, self.size, self.size, 3), dtype=np.uint8)

    def refine(self, image, boxes, q_in):
        torch = self.torch
        boxes = validate_boxes(boxes, image.shape)
        q_in = rq.normalize(q_in)
        if len(self._buffer) < len(boxes):
            self._buffer = np.zeros((len(boxes), self.size, self.size, 3), dtype=np.uint8)
        crops = crop_batch(image, boxes, self.size, self.context, out=self._buffer)
        with torch.inference_mode():
            q_out = self.model(torch.from_numpy(crops), torch.from_numpy(q_in.astype(np.float32))).numpy()
        return rq.normalize(rq.multiply(q_in, rq.normalize(q_out.astype(np.float64))))


def _time_calls(fn, n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def measure_interleaved(runners: dict, seconds: float, rounds: int = 5, min_calls: int = 3) -> dict[object, list[float]]:
    """Per-call latencies (s) of several callables, measured round-robin.

    Each runner gets about ``seconds`` of calls in total (at least ``min_calls``), spread over up to ``rounds``
    rounds; within a round the runners take turns, so slow drift of the machine is shared by all. Warm-up:
    up to 3 calls, fewer for slow runners (at most ~0.3 s each).
    """
    per_call = {}
    for name, fn in runners.items():
        warm = []
        while len(warm) < 3 and sum(warm) < 0.3:
            warm += _time_calls(fn, 1)
        per_call[name] = max(statistics.median(warm), 1e-6)
    plan = {name: max(min_calls, int(seconds / t)) for name, t in per_call.items()}
    lat = {name: [] for name in runners}
    for r in range(rounds):
        for name, fn in runners.items():
            n = plan[name] // rounds + (1 if r < plan[name] % rounds else 0)
            lat[name].extend(_time_calls(fn, n))
    return lat


def _percentile(values, q):
    return float(np.percentile(np.asarray(values), q))


# ---------------------------------------------------------------------------------------------------- models
@dataclass
class BenchModel:
    """A model to time: an ONNX file, optionally the PyTorch network it was exported from, and what its weights
    are (``"trained"``, ``"random"`` or ``"user-supplied"``)."""

    label: str
    path: Path
    torch_model: object = None
    config: dict = field(default_factory=dict)
    weights: str = "random"
    # a RefinerCascade row: the fine refiner's file and the path timed, "fine" (the gate holds: coarse_views +
    # fine_views passes) or "coarse" (coarse then fine: coarse_views + 2 * fine_views passes)
    fine_path: Path | None = None
    cascade_path: str | None = None


def parse_variant(text: str) -> tuple[str, str, dict]:
    """``[LABEL=]ARCH:JSON`` -> ``(label, arch, config overrides)``; the label defaults to ``ARCH:JSON`` compacted.

    Raises:
        click.BadParameter: not that form, or the JSON is not an object.
    """
    head, sep, body = text.partition(":")
    label, _, arch = head.rpartition("=")
    try:
        config = json.loads(body) if sep else None
    except json.JSONDecodeError:
        config = None
    if not arch.strip() or not isinstance(config, dict):
        raise click.BadParameter(
            f"expected [LABEL=]ARCH:JSON, e.g. 'shallow-h512=shallow:{{\"head_widths\": [512, 256, 64]}}'; got {text!r}"
        )
    arch = arch.strip()
    return (label.strip() or f"{arch}:{json.dumps(config, separators=(',', ':'))}"), arch, config


# ---------------------------------------------------------------------------------------------------- benchmark
def run_bench(
    bench_models: list[BenchModel],
    batches=(1, 8, 32),
    threads=(1, 0),
    seconds: float = 1.0,
    with_torch: bool = True,
    probe: LimitProbe | None = None,
    costs: dict | None = None,
    progress=None,
) -> list[BenchRow]:
    """Measure every (batch, threads) cell for every model; returns the rows with ratios and bounds filled in.

    Args:
        bench_models: the models (PyTorch eager is timed for those that carry a network, when ``with_torch``).
        batches: boxes per call.
        threads: thread counts; ``0`` means all available cores.
        seconds: approximate time spent per model and cell (the limit measurements get the same).
        with_torch: time PyTorch eager too (batches up to :data:`TORCH_MAX_BATCH`).
        probe: measures the machine's limits for the roofline, interleaved with the models in every cell; or None.
        costs: ``{model index: ModelCost}`` for the roofline, or None.
        progress: optional callable advanced by one after each cell.
    """
    from refiner_rt.session import RefinerSession

    rows: list[BenchRow] = []
    for nthreads in threads:
        n = nthreads or available_cores()
        sessions = [RefinerSession(m.path, threads=n) for m in bench_models]
        refiners = [s if m.fine_path is None else _cascade(s, m, n) for s, m in zip(sessions, bench_models)]
        torch_runners = {}
        if with_torch and any(m.torch_model is not None for m in bench_models):
            import torch

            torch.set_num_threads(n)
            torch_runners = {i: TorchRefiner(m.torch_model, n) for i, m in enumerate(bench_models) if m.torch_model is not None}
        for batch in batches:
            image, boxes, q_in = synthetic_frame(batch)
            runners = {("onnxruntime", i): (lambda s=s, K=frame_K(sessions[i]): s.refine(image, boxes, q_in, K=K))
                       for i, s in enumerate(refiners)}
            if batch <= TORCH_MAX_BATCH:
                runners.update({("torch", i): (lambda r=r: r.refine(image, boxes, q_in)) for i, r in torch_runners.items()})
            if probe is not None and costs:
                runners.update(probe.runners(n))
            latencies = measure_interleaved(runners, seconds)
            limits = probe.limits(n, latencies) if probe is not None and costs else None
            for key, values in latencies.items():
                if not isinstance(key, tuple):
                    continue  # a limit measurement
                runtime, i = key
                m, contract = bench_models[i], sessions[i].contract
                p50 = _percentile(values, 50)
                row = BenchRow(
                    arch=contract.arch,
                    runtime=runtime,
                    threads=n,
                    batch=batch,
                    fps=batch / p50,
                    p50_ms=p50 * 1e3,
                    p90_ms=_percentile(values, 90) * 1e3,
                    calls=len(values),
                    model=m.label,
                    quantization=contract.quantization if runtime == "onnxruntime" else "none",
                    weights=m.weights,
                    config=dict(m.config),
                )
                if limits is not None and i in costs:
                    _fill_roofline(row, costs[i], limits)
                rows.append(row)
            if progress:
                progress()
    _fill_ratios(rows)
    return rows


def _cascade(coarse, m: BenchModel, threads: int):
    """The :class:`refiner_rt.RefinerCascade` a cascade row times: with the widest gates (30 degrees) the fine
    refiner's first result stands, the path of inputs already close (coarse_views + fine_views passes); with a gate
    no correction fits under, every input takes the long way (the fine refiner again from the coarse result:
    coarse_views + 2 * fine_views), both with the cascade's default view counts."""
    from refiner_rt.cascade import RefinerCascade
    from refiner_rt.session import RefinerSession

    fine = RefinerSession(m.fine_path, threads=threads)
    return RefinerCascade(coarse, fine, gate_deg=1e-9 if m.cascade_path == "coarse" else 30.0, coarse_gate_deg=30.0)


def _fill_roofline(row: BenchRow, cost: ModelCost, limits: MachineLimits) -> None:
    """The row's bound from its cell's limits, and its ratio when that is a sane one (at most 1)."""
    n, batch = row.threads, row.batch
    row.weight_bytes = cost.weight_bytes
    row.flops_per_call, row.int8_ops_per_call = cost.flops * batch, cost.int8_ops * batch
    row.bound_fps, row.bound = roofline_bound(cost, batch, n, limits)
    row.bandwidth_gbs = limits.bandwidth / 1e9
    row.peak_fp32_gflops, row.peak_int8_gops = limits.peak_fp32[n] / 1e9, limits.peak_int8[n] / 1e9
    ratio = row.fps / row.bound_fps
    if ratio <= 1.0:
        row.roofline_ratio = ratio
    else:
        row.roofline_note = (
            f"ran at {ratio:.2f}x its bound: the bound is not one here (limits under-measured on a busy machine, "
            "or weights served from cache rather than DRAM), so no ratio is given"
        )


def _fill_ratios(rows: list[BenchRow]) -> None:
    """Same-run ratios: shallow/VGG-M per (runtime, quantisation, threads, batch) for default configs;
    onnxruntime/torch per model (over the fp32 PyTorch eager row of the same network); and onnxruntime rows over
    the shallow network at the same threads and batch, INT8 over INT8 and fp32 over fp32."""
    by_cell = {(r.runtime, r.model, r.quantization, r.threads, r.batch): r for r in rows}
    # The paper's network: the row labelled "shallow" (built), or "shallow.int8" and the like (--model files).
    shallow = {(r.threads, r.batch, r.quantization != "none"): r for r in rows
               if r.runtime == "onnxruntime" and r.arch == "shallow" and r.model.split(".")[0] == "shallow"}
    for r in rows:
        if r.arch == "shallow" and r.model == "shallow":
            vggm = by_cell.get((r.runtime, "vggm", r.quantization, r.threads, r.batch))
            if vggm is not None and vggm.arch == "vggm":
                r.ratio_shallow_over_vggm = r.fps / vggm.fps
        if r.runtime == "onnxruntime":
            t = by_cell.get(("torch", r.model, "none", r.threads, r.batch))
            if t is not None:
                r.ratio_onnxruntime_over_torch = r.fps / t.fps
            ref = shallow.get((r.threads, r.batch, r.quantization != "none"))
            if ref is not None and ref is not r:
                r.ratio_over_shallow = r.fps / ref.fps


def format_table(rows: list[BenchRow]) -> str:
    """A Markdown table of the rows (what the CLI prints and the README quotes)."""
    head = (
        "| model | weights | runtime | quant | threads | batch | refinements/s | p50 ms | p90 ms | over shallow "
        "| shallow/VGG-M | ORT/torch | bound/s | of bound |"
    )
    sep = "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    lines = [head, sep]
    order = {}
    for r in rows:
        order.setdefault(r.model, len(order))
    for r in sorted(rows, key=lambda r: (r.threads, r.batch, order[r.model], r.runtime, r.quantization)):
        over = f"{r.ratio_over_shallow:.2f}x" if r.ratio_over_shallow else ""
        ratio = f"{r.ratio_shallow_over_vggm:.1f}x" if r.ratio_shallow_over_vggm else ""
        ort_t = f"{r.ratio_onnxruntime_over_torch:.1f}x" if r.ratio_onnxruntime_over_torch else ""
        bound = f"{r.bound_fps:,.0f} ({r.bound[:3]})" if r.bound_fps else ""
        share = f"{r.roofline_ratio:.0%}" if r.roofline_ratio else ("n/a*" if r.roofline_note else "")
        lines.append(
            f"| {r.model} | {r.weights} | {r.runtime} | {r.quantization} | {r.threads} | {r.batch} | {r.fps:,.0f} | "
            f"{r.p50_ms:.3f} | {r.p90_ms:.3f} | {over} | {ratio} | {ort_t} | {bound} | {share} |"
        )
    if any(r.roofline_note for r in rows):
        lines.append("")
        lines.append("n/a*: the row ran faster than the bound measured in its cell, so that bound is not one (limits "
                     "under-measured on a busy machine, or weights served from cache rather than DRAM): no ratio.")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------- CLI
def _int_list(ctx, param, value):
    try:
        out = [int(v) for v in str(value).split(",") if v.strip()]
    except ValueError:
        raise click.BadParameter(f"expected comma-separated integers, e.g. 1,8; got {value!r}") from None
    if not out or any(v < 0 for v in out):
        raise click.BadParameter(f"expected non-negative integers, e.g. 1,8; got {value!r}")
    return out


def _threads_list(ctx, param, value):
    items = [v.strip() for v in str(value).split(",") if v.strip()]
    out = []
    for v in items:
        if v == "all":
            out.append(0)
        elif v.isdigit() and int(v) > 0:
            out.append(int(v))
        else:
            raise click.BadParameter(f"expected thread counts (positive integers or 'all'), e.g. 1,all; got {value!r}")
    if not out:
        raise click.BadParameter("expected at least one thread count")
    return out


def _variants(ctx, param, value):
    return [parse_variant(v) for v in value]


def _roofline_inputs(bench_models, echo):
    """A :class:`LimitProbe` and per-model costs, or ``(None, None)`` without the ``onnx`` package."""
    try:
        import onnx  # noqa: F401  (graph parsing and the peak-measuring graphs)
    except ModuleNotFoundError:
        echo("Roofline skipped: it needs the 'onnx' package to read the graphs.")
        return None, None
    costs = {}
    for i, m in enumerate(bench_models):
        if m.fine_path is not None:
            continue  # a cascade is several networks: no single-graph bound
        try:
            costs[i] = model_cost(m.path)
        except Exception as exc:  # onnx's shape inference on a graph it cannot follow: that row goes without a bound
            echo(f"Roofline skipped for {m.label}: its graph cannot be costed ({type(exc).__name__}: {exc})")
    return LimitProbe(), costs


def _shipped_option(ctx, param, value):
    value = str(value).strip()
    if value in ("", "none"):
        return []
    if value in ("first", "all"):
        return value
    return [v.strip() for v in value.split(",") if v.strip()]


def bench_command(build_models=None) -> click.Command:
    """The ``refiner-rt bench`` command. ``build_models(specs, workdir, int8=, echo=)`` builds the random-weight
    models timed when no ``--model`` is given; the training side supplies it (``export.bench_models``), since the
    runtime never imports training code. Without it only the shipped models and ``--model`` files can be timed."""

    @click.command("bench")
    @click.option("--cpu", "cpu", is_flag=True, default=True, help="Benchmark on the CPU (the only device supported; default).")
    @click.option(
        "--model",
        "model_paths",
        multiple=True,
        type=click.Path(exists=True, dir_okay=False, path_type=Path),
        help="An exported refiner-rt ONNX model (repeatable); then only these are timed. Default: the shipped "
        "refiners (--shipped) and random-weight models of --archs and --variant.",
    )
    @click.option(
        "--shipped",
        default="first",
        show_default=True,
        callback=_shipped_option,
        help="Shipped refiners to time, INT8 and fp32, with their trained weights: 'first' (one representative: "
        "they all share one architecture, so they run at one speed), 'all', 'none', or YCB ids (comma-separated).",
    )
    @click.option("--archs", default=",".join(DEFAULT_ARCHS), show_default=True,
                  help="Registered architectures to build with random weights when no --model is given (the paper's "
                  "networks by default; add 'fusion' for the project's refiner with random weights).")
    @click.option(
        "--variant",
        "variants",
        multiple=True,
        callback=_variants,
        help="Also build an architecture with config overrides, [LABEL=]ARCH:JSON (repeatable), e.g. "
        "'shallow-h512=shallow:{\"head_widths\": [512, 256, 64]}' for a first head layer of 512 instead of 1024.",
    )
    @click.option("--int8/--no-int8", "with_int8", default=True, show_default=True, help="Also time each built model quantised to INT8 (export.quantize's default scheme).")
    @click.option("--batch", "batches", default="1,8,32", show_default=True, callback=_int_list, help="Boxes per refine() call.")
    @click.option("--threads", "threads", default="1,all", show_default=True, callback=_threads_list, help="Thread counts ('all' = every core).")
    @click.option("--seconds", default=1.0, show_default=True, type=click.FloatRange(0.05, 600), help="Measuring time per model and cell (at least 3 calls).")
    @click.option("--torch/--no-torch", "with_torch", default=True, show_default=True, help=f"Also time PyTorch eager for the built models at batches up to {TORCH_MAX_BATCH} (when torch is installed).")
    @click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write the rows (with the run's context) as a JSON list.")
    def bench_cmd(cpu, model_paths, shipped, archs, variants, with_int8, batches, threads, seconds, with_torch, json_path):
        """CPU speed of the full refine() path (crop + inference + compose): the shipped refiners beside the paper's
        networks, fp32 and INT8, each row next to its roofline bound (measured interleaved with the models)."""
        if 0 in batches:
            raise click.BadParameter("batch sizes must be >= 1", param_hint="--batch")
        if max(batches) > MAX_BATCH:
            raise click.BadParameter(f"batch sizes must be at most {MAX_BATCH} (RefinerSession's MAX_BATCH crops per call)",
                                     param_hint="--batch")
        machine = machine_info()

        def echo(msg):
            click.echo(msg, err=True)

        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="refiner-rt-bench-") as tmp:
            bench_models, weights = _prepare_models(model_paths, shipped, archs, variants, with_int8, Path(tmp), echo,
                                                     build_models)
            probe, costs = _roofline_inputs(bench_models, echo)
            echo(
                f"Timing refine() on a {FRAME_W}x{FRAME_H} frame: {len(bench_models)} model(s), batches {batches}, "
                f"threads {[t or 'all' for t in threads]}, ~{seconds:g} s per model and cell"
                + (" (and per roofline limit, measured in every cell)" if probe is not None else "")
            )
            # A bar on a terminal only: elsewhere click prints its bare label, a stray "cells" line in the output.
            stream = contextlib.nullcontext(sys.stderr) if sys.stderr.isatty() else open(os.devnull, "w")  # noqa: SIM115
            with stream as bar_stream, click.progressbar(length=len(threads) * len(batches),
                                                         label="timing cells (threads x batches)",
                                                         file=bar_stream) as bar:
                try:
                    rows = run_bench(
                        bench_models, batches, threads, seconds, with_torch, probe, costs, progress=lambda: bar.update(1)
                    )
                except ModelError as exc:  # a model that loaded but fails when it runs
                    raise click.ClickException(str(exc)) from None
        wall = time.perf_counter() - t0
        click.echo("")
        click.echo(f"Machine: {machine['cpu']}, {machine['cores']} cores, vector flags {' '.join(machine['cpu_flags']) or '?'}"
                   f" (torch dispatch: {machine['cpu_capability'] or 'n/a'}), onnxruntime {machine['onnxruntime']}, "
                   f"torch {machine['torch']}")
        click.echo(f"Weights: {weights}. Full refine() path, medians over interleaved rounds; wall {wall:.0f} s.")
        if probe is not None:
            click.echo(_describe_limits(rows))
            thread_counts = sorted({r.threads for r in rows if r.bandwidth_gbs is not None})
            if thread_counts:
                first = _cell_limits(rows, thread_counts)
                click.echo("\n".join(describe_roofline(m.label, costs[i], first, thread_counts)
                                     for i, m in enumerate(bench_models) if i in costs))
        click.echo(format_table(rows))
        if json_path:
            # A list of rows (what machines read); each row carries the run's context.
            context = {"machine": machine, "weights_note": weights, "frame": [FRAME_W, FRAME_H],
                       "seconds_per_cell": seconds, "wall_s": wall}
            json_path.write_text(json.dumps([{**asdict(r), **context} for r in rows], indent=2))
            click.echo(f"Wrote {json_path}")

    return bench_cmd


def _training_builder():
    """``export.bench_models.build_default_models``: the training package's builder of the random-weight networks
    (a source checkout's; the runtime wheel does not carry it)."""
    try:  # by name: the runtime never imports the training package statically
        build_default_models = importlib.import_module("export.bench_models").build_default_models
    except ModuleNotFoundError as exc:
        raise click.ClickException(
            f"building the random-weight models needs the training package ({exc.name!r} is missing): "
            f"{TRAINING_INSTALL}; or time the shipped models alone (--archs '') or your own files (--model)"
        ) from None
    return build_default_models


def _prepare_models(model_paths, shipped, archs: str, variants, with_int8: bool, workdir: Path, echo,
                    build_models=None) -> tuple[list, str]:
    """The models to time and a note on their weights: the given files; or the shipped models and random-weight
    builds (and their INT8)."""
    if model_paths:
        from refiner_rt.session import RefinerSession

        seen, bench_models = set(), []
        for p in model_paths:
            try:  # the whole contract, before any timing: a bad file is a one-line error, not a traceback
                RefinerSession(p, threads=1)
            except ModelError as exc:
                raise click.BadParameter(str(exc), param_hint="'--model'") from None
            label = p.stem if p.stem not in seen else str(p)
            seen.add(label)
            bench_models.append(BenchModel(label, p, weights="user-supplied"))
        return bench_models, "user-supplied models"
    specs = [(a.strip(), a.strip(), {}) for a in archs.split(",") if a.strip()] + list(variants)
    labels = [label for label, _, _ in specs]
    if len(set(labels)) != len(labels):
        raise click.BadParameter(f"model labels must be unique; got {labels}", param_hint="'--variant'")
    shipped_models, shipped_note = _shipped_models(shipped)
    notes = [shipped_note] if shipped_note else []
    built: list[BenchModel] = []
    if specs and importlib.util.find_spec("torch") is None:
        if not shipped_models:
            raise click.ClickException(
                "building the random-weight models needs torch and the training package (" + TRAINING_INSTALL
                + "), and no shipped model is selected to time instead; pass exported models with --model"
            )
        echo(f"torch is not installed, so the random-weight models {labels} cannot be built: timing only the "
             f"shipped models (--model FILE times others; the training extra builds the paper's networks).")
        notes.append(f"{', '.join(labels)} not timed (needs torch)")
    elif specs:
        if build_models is None:
            build_models = _training_builder()
        echo(f"Building random-weight models {labels} (speed does not depend on weight values)...")
        built = build_models(specs, workdir, int8=with_int8, echo=echo)
        notes.append(f"{', '.join(labels)}: random weights (speed does not depend on weight values)")
    bench_models = shipped_models + built
    if not bench_models:
        raise click.BadParameter("nothing to benchmark: give --archs, --variant, --shipped or --model",
                                 param_hint="'--archs'")
    return bench_models, "; ".join(notes)


def _shipped_models(selection) -> tuple[list, str]:
    """The shipped models to time (INT8 and fp32 of each; trained weights) and a note saying which, from the
    ``--shipped`` value: ``"first"``, ``"all"`` or a list of YCB ids (empty: none)."""
    from refiner_rt.pretrained import pretrained_model, pretrained_models

    if not selection:
        return [], ""
    available = pretrained_models()
    if selection in ("first", "all"):
        chosen = available[:1] if selection == "first" else available
    else:
        try:
            chosen = [pretrained_model(obj) for obj in selection]
        except (ValueError, TypeError) as exc:
            raise click.BadParameter(str(exc), param_hint="'--shipped'") from None
    out = []
    for m in chosen:
        for int8 in (True, False):
            if m.files.get("int8" if int8 else "fp32"):
                path = m.path(int8=int8)  # labelled by file stem: 003_cracker_box.int8 and 003_cracker_box
                out.append(BenchModel(path.stem, path, config=dict(m.config), weights="trained"))
        if "fine" in m.stages and m.fine["files"].get("int8"):  # the cascade of the INT8 files, both of its paths
            from refiner_rt.cascade import DEFAULT_COARSE_VIEWS as c, DEFAULT_FINE_VIEWS as v

            for way, passes in (("fine", f"{c + v} passes"), ("coarse", f"{c + 2 * v} passes")):
                out.append(BenchModel(f"{m.object_id}.cascade.{way} ({passes})", m.path(int8=True), config=dict(m.config),
                                      weights="trained", fine_path=m.path(int8=True, stage="fine"), cascade_path=way))
    if not chosen:
        return [], "no shipped model to time"
    ids = ", ".join(m.object_id for m in chosen)
    if selection == "first" and len(available) > 1:
        return out, (f"shipped {ids}: trained weights, INT8 and fp32 (one representative of the {len(available)} "
                     f"shipped refiners, which share one architecture; --shipped all times each)")
    return out, f"shipped {ids}: trained weights, INT8 and fp32"


def _cell_limits(rows: list[BenchRow], thread_counts) -> MachineLimits:
    """Per thread count, the limits of that thread count's first cell with a bound (for the summary lines)."""
    first = {}
    for r in rows:
        if r.bandwidth_gbs is not None and r.threads not in first:
            first[r.threads] = r
    return MachineLimits(
        bandwidth=min(r.bandwidth_gbs for r in first.values()) * 1e9,
        peak_fp32={n: first[n].peak_fp32_gflops * 1e9 for n in thread_counts if n in first},
        peak_int8={n: first[n].peak_int8_gops * 1e9 for n in thread_counts if n in first},
    )


def _describe_limits(rows: list[BenchRow]) -> str:
    cells = {}
    for r in rows:
        if r.bandwidth_gbs is not None:
            cells.setdefault((r.threads, r.batch), r)
    if not cells:
        return "Roofline: no row could be costed."
    bw = [r.bandwidth_gbs for r in cells.values()]
    peaks = "; ".join(
        f"{n} thr: fp32 {min(c.peak_fp32_gflops for (t, _), c in cells.items() if t == n):.0f}-"
        f"{max(c.peak_fp32_gflops for (t, _), c in cells.items() if t == n):.0f} GFLOP/s, int8 "
        f"{min(c.peak_int8_gops for (t, _), c in cells.items() if t == n):.0f}-"
        f"{max(c.peak_int8_gops for (t, _), c in cells.items() if t == n):.0f} Gop/s"
        for n in sorted({t for t, _ in cells})
    )
    return (
        f"Roofline: measured in each of the {len(cells)} cells, interleaved with the models (best of its rounds): "
        f"bandwidth {min(bw):.1f}-{max(bw):.1f} GB/s (numpy copy of {BANDWIDTH_BUFFER_MB} MB, read + write); "
        f"onnxruntime MatMul peaks {peaks}. Bound = batch / max(weight bytes / bandwidth, batch x ops / peak); "
        "inference only, weights assumed to come from DRAM; a row that beats its bound gets no ratio."
    )
