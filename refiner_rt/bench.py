"""CPU speed benchmark behind ``refiner-rt bench --cpu``: the full ``refine()`` path, models side by side, each row
next to its roofline bound.

What is timed is what robot code pays per call: crop every box out of a 640x480 BGR frame with the
shared crop rule, run the network, compose ``q_in * q_out`` in float64. Models are measured
interleaved (round-robin, several rounds) so that drift of a shared machine hits all of them alike,
and every ratio comes from one run. Reported: median (p50) and p90 latency per call and
refinements per second (``batch / p50``).

With no ``--model``, the registered architectures (default: ``shallow``, the paper's network; ``fusion``, the
project's refiner; ``vggm``, the paper's deep variant) and any ``--variant`` configs are built with random
weights and exported (speed does not depend on the weight values), each in fp32 and, quantised in the same run
with :mod:`export.quantize`'s default scheme, in INT8; this needs the training extra (torch). The same networks
are also timed in PyTorch eager mode (batches up to :data:`TORCH_MAX_BATCH`) for the onnxruntime/PyTorch ratio.

Roofline (when the ``onnx`` package is installed): a lower bound on the time of one inference from the
machine's measured limits (see :class:`MachineLimits`):

    t_memory  = weight bytes per call / memory bandwidth     (every weight is read once per call, any batch)
    t_compute = batch * (fp32 FLOPs / fp32 peak + int8 ops / int8 peak)   (per crop, peaks at the row's threads)
    bound     = batch / max(t_memory, t_compute)  refinements/s

Each row reports ``roofline_ratio = fps / bound``: 1.0 would be the hardware limit for that inference. The bound
covers the network only (not cropping or composition), counts weights but not activations, and assumes weights
come from DRAM: a model whose weights fit in the 32 MB L3 (the INT8 ones) can beat its memory bound.
"""

from __future__ import annotations

import json
import logging
import platform
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import click
import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.errors import ModelError
from refiner_rt.preprocess import crop_batch, validate_boxes
from refiner_rt.session import MAX_BATCH, available_cores

log = logging.getLogger(__name__)

FRAME_W, FRAME_H = 640, 480
# Intrinsics of the synthetic frame (YCB-Video's camera), passed to models trained in the viewing-ray frame.
FRAME_K = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])
DEFAULT_ARCHS = ("shallow", "fusion", "vggm")
TORCH_MAX_BATCH = 8  # PyTorch eager VGG-M takes ~2 s per call at batch 32: only smaller batches are timed
BANDWIDTH_BUFFER_MB = 512  # much larger than the 32 MB L3
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
        model: label: the architecture, a ``--variant`` label, or the file stem of a ``--model``.
        quantization: ``"none"``, ``"dynamic-int8"`` or ``"static-qdq-int8"`` (metadata of the ONNX model).
        config: the config overrides of a ``--variant`` (JSON object), else ``{}``.
        ratio_shallow_over_vggm: shallow / VGG-M fps at the same runtime, quantisation, threads and batch
            (default configs only; on the shallow row).
        ratio_onnxruntime_over_torch: this onnxruntime row's fps over the PyTorch eager fp32 fps of the same network.
        weight_bytes: bytes of weights read per call.
        flops_per_call: fp32 floating-point operations per call (2 per multiply-add; convolutions and fully
            connected layers).
        int8_ops_per_call: int8 operations per call (2 per multiply-add) of the quantised layers.
        bound_fps: roofline bound in refinements per second (None without the ``onnx`` package).
        bound: ``"memory"`` or ``"compute"``: which limit sets the bound.
        roofline_ratio: ``fps / bound_fps``.
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
    config: dict = field(default_factory=dict)
    ratio_shallow_over_vggm: float | None = None
    ratio_onnxruntime_over_torch: float | None = None
    weight_bytes: int | None = None
    flops_per_call: float | None = None
    int8_ops_per_call: float | None = None
    bound_fps: float | None = None
    bound: str | None = None
    roofline_ratio: float | None = None


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
    """CPU model, its vector-instruction flags, core count and library versions of this machine."""
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
    except ModuleNotFoundError:
        info["torch"] = None
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
        bandwidth: DRAM bandwidth in bytes/s: ``numpy.copyto`` of a 512 MB buffer (much larger than L3), counting
            the bytes read plus the bytes written (STREAM's "copy" convention), median of several copies, one
            thread.
        peak_fp32: ``{threads: FLOP/s}`` of onnxruntime's fp32 ``MatMul`` on 1024x1024 matrices (the MLAS kernels
            the models use), median of several runs.
        peak_int8: ``{threads: ops/s}`` of onnxruntime's ``MatMulInteger`` (uint8 x int8, the VNNI kernels of the
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


def measure_bandwidth(megabytes: int = BANDWIDTH_BUFFER_MB, repeats: int = 5) -> float:
    """DRAM bandwidth in bytes/s: median of ``repeats`` numpy copies of a buffer, (read + written bytes) / time."""
    n = megabytes * 2**20
    src = np.ones(n, dtype=np.uint8)
    dst = np.zeros(n, dtype=np.uint8)  # touched: no page faults in the timed copies
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        np.copyto(dst, src)
        times.append(time.perf_counter() - t0)
    return 2 * n / statistics.median(times)


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


def measure_peak(int8: bool, threads: int, size: int = PEAK_MATMUL_SIZE, repeats: int = 7) -> float:
    """Operations per second of onnxruntime's fp32 ``MatMul`` or int8 ``MatMulInteger`` (2 ops per multiply-add)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    sess = ort.InferenceSession(_matmul_model(int8, size), options, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (size, size), dtype=np.uint8) if int8 else rng.standard_normal((size, size)).astype(np.float32)
    sess.run(None, {"a": a})
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sess.run(None, {"a": a})
        times.append(time.perf_counter() - t0)
    return 2.0 * size**3 / statistics.median(times)


def measure_limits(thread_counts) -> MachineLimits:
    """Bandwidth once, fp32 and int8 peaks for each thread count."""
    return MachineLimits(
        bandwidth=measure_bandwidth(),
        peak_fp32={n: measure_peak(False, n) for n in thread_counts},
        peak_int8={n: measure_peak(True, n) for n in thread_counts},
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
    """A model to time: an ONNX file, and optionally the PyTorch network it was exported from."""

    label: str
    path: Path
    torch_model: object = None
    config: dict = field(default_factory=dict)


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


def _disk_needed(model, int8: bool) -> int:
    """Bytes of disk that exporting ``model`` (and quantising it) writes at most, with a margin.

    The fp32 file holds every weight in 4 bytes; quantisation writes a pre-processed fp32 copy and the INT8 file.
    """
    weights = 4 * sum(p.numel() for p in model.parameters())
    return int(weights * (3 if int8 else 1) * 1.2) + (16 << 20)


def _space_message(workdir: Path, need: int, label: str) -> str:
    free = shutil.disk_usage(workdir).free
    return (f"not enough free disk space in {workdir} for {label}'s ONNX files: they need about {need / 1e6:.0f} MB, "
            f"{free / 1e6:.0f} MB is free; free some space or point TMPDIR at a folder with more")


def _check_free_space(workdir: Path, need: int, label: str) -> None:
    """Raise a ClickException naming the folder and the sizes when ``need`` bytes do not fit in ``workdir``."""
    if shutil.disk_usage(workdir).free < need:
        raise click.ClickException(_space_message(workdir, need, label))


class _disk_full_is_clear:
    """Context manager: an error while writing model files becomes a clear disk-space error when the disk is full.

    A file cut short by a full disk otherwise surfaces later as an unrelated parse error
    (onnx's ``DecodeError: Wire format was corrupt``) from the step that reads it back.
    """

    def __init__(self, workdir: Path, need: int, label: str):
        self.workdir, self.need, self.label = workdir, need, label

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc is None or isinstance(exc, click.ClickException):
            return False
        if shutil.disk_usage(self.workdir).free < self.need:
            message = _space_message(self.workdir, self.need, self.label)
            raise click.ClickException(f"{message} ({exc_type.__name__}: {exc})") from exc
        return False


def build_default_models(specs, workdir: Path, int8: bool = True, echo=None) -> list[BenchModel]:
    """Random-weight networks exported to ONNX in ``workdir`` (and their INT8 versions).

    Args:
        specs: ``(label, arch, config overrides)`` triples.
        workdir: where the ONNX files go.
        int8: also quantise each with :data:`export.quantize.DEFAULT_SCHEME`.
        echo: optional callable for progress lines.

    Returns:
        The fp32 models (with their PyTorch networks), then the INT8 ones.
    """
    try:
        import torch

        import models
        from export import export_model
        from export.quantize import DEFAULT_SCHEME, quantize_model
    except ModuleNotFoundError as exc:
        raise click.ClickException(
            f"building the default benchmark models needs {exc.name!r} (pip install 'refiner-rt[train]'); "
            "or pass exported models with --model"
        ) from exc
    fp32, quantized = [], []
    for i, (label, arch, config) in enumerate(specs):
        torch.manual_seed(0)
        try:
            model = models.build_refiner(arch, **config).eval()
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="'--archs' / '--variant'") from exc
        path = workdir / f"model{i}.onnx"
        need = _disk_needed(model, int8)
        _check_free_space(workdir, need, label)
        t0 = time.perf_counter()
        with _disk_full_is_clear(workdir, need, label):
            export_model(model, path, checkpoint_sha256="random-weights")
        line = f"  {label}: exported in {time.perf_counter() - t0:.1f} s"
        fp32.append(BenchModel(label, path, model, config))
        if int8:
            # Random weights: the agreement says nothing about a trained model's accuracy, so it is shown, not enforced.
            with _disk_full_is_clear(workdir, need, label):
                report = quantize_model(path, workdir / f"model{i}.int8.onnx", scheme=DEFAULT_SCHEME, enforce=False)
            a = report.agreement
            line += (f", {DEFAULT_SCHEME} in {report.seconds:.1f} s (vs fp32 with random weights: mean {a.mean_deg:.3f}, "
                     f"max {a.max_deg:.3f} deg)")
            quantized.append(BenchModel(label, report.path, None, config))
        if echo:
            echo(line)
    return fp32 + quantized


# ---------------------------------------------------------------------------------------------------- benchmark
def run_bench(
    bench_models: list[BenchModel],
    batches=(1, 8, 32),
    threads=(1, 0),
    seconds: float = 1.0,
    with_torch: bool = True,
    limits: MachineLimits | None = None,
    costs: dict | None = None,
    progress=None,
) -> list[BenchRow]:
    """Measure every (batch, threads) cell for every model; returns the rows with ratios and bounds filled in.

    Args:
        bench_models: the models (PyTorch eager is timed for those that carry a network, when ``with_torch``).
        batches: boxes per call.
        threads: thread counts; ``0`` means all available cores.
        seconds: approximate time spent per model and cell.
        with_torch: time PyTorch eager too (batches up to :data:`TORCH_MAX_BATCH`).
        limits: the machine's limits for the roofline, or None.
        costs: ``{model index: ModelCost}`` for the roofline, or None.
        progress: optional callable advanced by one after each cell.
    """
    from refiner_rt.session import RefinerSession

    rows: list[BenchRow] = []
    for nthreads in threads:
        n = nthreads or available_cores()
        sessions = [RefinerSession(m.path, threads=n) for m in bench_models]
        torch_runners = {}
        if with_torch and any(m.torch_model is not None for m in bench_models):
            import torch

            torch.set_num_threads(n)
            torch_runners = {i: TorchRefiner(m.torch_model, n) for i, m in enumerate(bench_models) if m.torch_model is not None}
        for batch in batches:
            image, boxes, q_in = synthetic_frame(batch)
            # K only where the model needs it: validating an unused K would add to camera-frame models' timings
            runners = {("onnxruntime", i): (lambda s=s, K=FRAME_K if s.contract.rotation_frame == "ray" else None:
                                            s.refine(image, boxes, q_in, K=K)) for i, s in enumerate(sessions)}
            if batch <= TORCH_MAX_BATCH:
                runners.update({("torch", i): (lambda r=r: r.refine(image, boxes, q_in)) for i, r in torch_runners.items()})
            for (runtime, i), values in measure_interleaved(runners, seconds).items():
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
                    config=dict(m.config),
                )
                if limits is not None and costs and i in costs:
                    c = costs[i]
                    row.weight_bytes = c.weight_bytes
                    row.flops_per_call, row.int8_ops_per_call = c.flops * batch, c.int8_ops * batch
                    row.bound_fps, row.bound = roofline_bound(c, batch, n, limits)
                    row.roofline_ratio = row.fps / row.bound_fps
                rows.append(row)
            if progress:
                progress()
    _fill_ratios(rows)
    return rows


def _fill_ratios(rows: list[BenchRow]) -> None:
    """Same-run ratios: shallow/VGG-M per (runtime, quantisation, threads, batch) for default configs, and
    onnxruntime/torch per model (over the fp32 PyTorch eager row of the same network)."""
    by_cell = {(r.runtime, r.model, r.quantization, r.threads, r.batch): r for r in rows}
    for r in rows:
        if r.arch == "shallow" and r.model == "shallow":
            vggm = by_cell.get((r.runtime, "vggm", r.quantization, r.threads, r.batch))
            if vggm is not None and vggm.arch == "vggm":
                r.ratio_shallow_over_vggm = r.fps / vggm.fps
        if r.runtime == "onnxruntime":
            t = by_cell.get(("torch", r.model, "none", r.threads, r.batch))
            if t is not None:
                r.ratio_onnxruntime_over_torch = r.fps / t.fps


def format_table(rows: list[BenchRow]) -> str:
    """A Markdown table of the rows (what the CLI prints and the README quotes)."""
    head = (
        "| model | runtime | quant | threads | batch | refinements/s | p50 ms | p90 ms | shallow/VGG-M | ORT/torch "
        "| bound/s | of bound |"
    )
    sep = "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    lines = [head, sep]
    order = {}
    for r in rows:
        order.setdefault(r.model, len(order))
    for r in sorted(rows, key=lambda r: (r.threads, r.batch, order[r.model], r.runtime, r.quantization)):
        ratio = f"{r.ratio_shallow_over_vggm:.1f}x" if r.ratio_shallow_over_vggm else ""
        ort_t = f"{r.ratio_onnxruntime_over_torch:.1f}x" if r.ratio_onnxruntime_over_torch else ""
        bound = f"{r.bound_fps:,.0f} ({r.bound[:3]})" if r.bound_fps else ""
        share = f"{r.roofline_ratio:.0%}" if r.roofline_ratio else ""
        lines.append(
            f"| {r.model} | {r.runtime} | {r.quantization} | {r.threads} | {r.batch} | {r.fps:,.0f} | "
            f"{r.p50_ms:.3f} | {r.p90_ms:.3f} | {ratio} | {ort_t} | {bound} | {share} |"
        )
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


def _roofline_inputs(bench_models, thread_counts, echo):
    """Machine limits and per-model costs, or ``(None, None)`` without the ``onnx`` package."""
    try:
        import onnx  # noqa: F401  (graph parsing and the peak-measuring graphs)
    except ModuleNotFoundError:
        echo("Roofline skipped: it needs the 'onnx' package to read the graphs.")
        return None, None
    echo(f"Measuring the roofline limits (numpy copy of {BANDWIDTH_BUFFER_MB} MB; onnxruntime MatMul fp32 and int8)...")
    limits = measure_limits(thread_counts)
    costs = {}
    for i, m in enumerate(bench_models):
        try:
            costs[i] = model_cost(m.path)
        except Exception as exc:  # onnx's shape inference on a graph it cannot follow: that row goes without a bound
            echo(f"Roofline skipped for {m.label}: its graph cannot be costed ({type(exc).__name__}: {exc})")
    return limits, costs


@click.command("bench")
@click.option("--cpu", "cpu", is_flag=True, default=True, help="Benchmark on the CPU (the only device supported; default).")
@click.option(
    "--model",
    "model_paths",
    multiple=True,
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="An exported refiner-rt ONNX model (repeatable). Default: random-weight models of --archs and --variant.",
)
@click.option("--archs", default=",".join(DEFAULT_ARCHS), show_default=True, help="Registered architectures to build when no --model is given.")
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
def bench_cmd(cpu, model_paths, archs, variants, with_int8, batches, threads, seconds, with_torch, json_path):
    """CPU speed of the full refine() path (crop + inference + compose): models side by side, fp32 and INT8,
    each row next to its roofline bound."""
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
        bench_models, weights = _prepare_models(model_paths, archs, variants, with_int8, Path(tmp), echo)
        thread_counts = sorted({t or available_cores() for t in threads})
        limits, costs = _roofline_inputs(bench_models, thread_counts, echo)
        echo(
            f"Timing refine() on a {FRAME_W}x{FRAME_H} frame: {len(bench_models)} model(s), batches {batches}, "
            f"threads {[t or 'all' for t in threads]}, ~{seconds:g} s per model and cell"
        )
        with click.progressbar(length=len(threads) * len(batches), label="cells", file=sys.stderr) as bar:
            try:
                rows = run_bench(
                    bench_models, batches, threads, seconds, with_torch, limits, costs, progress=lambda: bar.update(1)
                )
            except ModelError as exc:  # a model that loaded but fails when it runs
                raise click.ClickException(str(exc)) from None
    wall = time.perf_counter() - t0
    click.echo("")
    click.echo(f"Machine: {machine['cpu']}, {machine['cores']} cores, onnxruntime {machine['onnxruntime']}, torch {machine['torch']}")
    click.echo(f"Weights: {weights}. Full refine() path, medians over interleaved rounds; wall {wall:.0f} s.")
    if limits is not None:
        click.echo(_describe_limits(limits, thread_counts))
        click.echo("\n".join(describe_roofline(m.label, costs[i], limits, thread_counts) for i, m in enumerate(bench_models)))
    click.echo(format_table(rows))
    if json_path:
        # A list of rows (what machines read); each row carries the run's context.
        context = {"machine": machine, "weights": weights, "frame": [FRAME_W, FRAME_H], "seconds_per_cell": seconds,
                   "wall_s": wall, **(limits.as_dict() if limits is not None else {})}
        json_path.write_text(json.dumps([{**asdict(r), **context} for r in rows], indent=2))
        click.echo(f"Wrote {json_path}")


def _prepare_models(model_paths, archs: str, variants, with_int8: bool, workdir: Path, echo) -> tuple[list, str]:
    """The models to time and a note on their weights: the given files, or random-weight builds (and INT8)."""
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
            bench_models.append(BenchModel(label, p))
        return bench_models, "user-supplied models"
    specs = [(a.strip(), a.strip(), {}) for a in archs.split(",") if a.strip()] + list(variants)
    if not specs:
        raise click.BadParameter("nothing to benchmark: give --archs, --variant or --model", param_hint="'--archs'")
    labels = [label for label, _, _ in specs]
    if len(set(labels)) != len(labels):
        raise click.BadParameter(f"model labels must be unique; got {labels}", param_hint="'--variant'")
    echo(f"Building random-weight models {labels} (speed does not depend on weight values)...")
    return build_default_models(specs, workdir, int8=with_int8, echo=echo), "random weights (speed does not depend on weight values)"


def _describe_limits(limits: MachineLimits, thread_counts) -> str:
    peaks = ", ".join(
        f"{n} thr: fp32 {limits.peak_fp32[n] / 1e9:.0f} GFLOP/s, int8 {limits.peak_int8[n] / 1e9:.0f} Gop/s"
        for n in thread_counts
    )
    return (
        f"Roofline: bandwidth {limits.bandwidth / 1e9:.1f} GB/s (numpy copy of {BANDWIDTH_BUFFER_MB} MB, read + "
        f"write); onnxruntime MatMul peaks {peaks}. Bound = batch / max(weight bytes / bandwidth, "
        "batch x ops / peak); inference only, weights assumed to come from DRAM."
    )
