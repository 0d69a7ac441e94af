"""The training package's part of ``refiner-rt bench``: the paper's networks with random weights, PyTorch eager
rows and the roofline, added to the runtime's timer (:mod:`refiner_rt.bench`) as a
:class:`refiner_rt.bench.BenchExtension`. Plugged into ``refiner-rt`` as its ``bench`` command in a full install
(``export.commands``); without the training package the runtime's own ``bench`` runs. Torch and onnx are imported
only when a command needs them.

What the runtime's bench times (the full ``refine()`` path of ONNX files) is unchanged; this adds:

* the paper's networks, :data:`refiner_rt.bench.DEFAULT_ARCHS` (``shallow``, the paper's network; ``vggm``, its deep
  variant) and any ``--variant`` configs, built with random weights and exported (speed does not depend on the
  weight values), each in fp32 and, quantised in the same run with :mod:`export.quantize`'s default scheme, in INT8
  (:func:`export.bench_models.build_default_models`); the built networks also timed in PyTorch eager mode (batches
  up to :data:`TORCH_MAX_BATCH`) for the onnxruntime/PyTorch ratio;
* the roofline (when the ``onnx`` package is installed): a lower bound on the time of one inference from the
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

import statistics
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.bench import (
    BenchExtension,
    BenchModel,
    BenchRow,
    bench_command,
    measure_interleaved,
    time_calls,
)
from refiner_rt.bench import machine_info as runtime_machine_info
from refiner_rt.checks import validate_boxes
from refiner_rt.preprocess import crop_batch

__all__ = ["PaperBench", "TorchRefiner", "MachineLimits", "ModelCost", "LimitProbe", "machine_info", "model_cost",
           "measure_bandwidth", "measure_peak", "measure_limits", "roofline_bound", "describe_roofline", "bench_cmd",
           "TORCH_MAX_BATCH"]

TORCH_MAX_BATCH = 8  # PyTorch eager VGG-M takes ~2 s per call at batch 32: only smaller batches are timed
BANDWIDTH_BUFFER_MB = 256  # much larger than the L3 caches of the CPUs the project runs on (32 MB)
PEAK_MATMUL_SIZE = 1024  # M = N = K of the matrix products that measure the compute peaks


def machine_info() -> dict:
    """:func:`refiner_rt.bench.machine_info`, with torch's version and the instruction set torch dispatches to
    (``torch.backends.cpu.get_cpu_capability()``, e.g. ``"AVX2"``, ``"AVX512"``) when torch is installed."""
    info = runtime_machine_info()
    try:
        import torch

        info["torch"] = torch.__version__
        info["cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    except ModuleNotFoundError:
        info["torch"] = info["cpu_capability"] = None
    return info


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
    return nbytes / statistics.median(time_calls(copy, repeats))


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
    return ops / statistics.median(time_calls(run, repeats))


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



# ---------------------------------------------------------------------------------------------------- PyTorch eager
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


# ---------------------------------------------------------------------------------------------------- the extension
class PaperBench(BenchExtension):
    """The training package's :class:`refiner_rt.bench.BenchExtension`: random-weight builds, PyTorch eager rows and
    the roofline (module docstring)."""

    def __init__(self):
        self.with_torch, self.probe, self.costs = False, None, None
        self._torch_runners: dict = {}

    def machine_info(self, info: dict) -> dict:
        return machine_info()

    def build_models(self, specs, workdir: Path, int8: bool, echo) -> list[BenchModel]:
        from export.bench_models import build_default_models

        return build_default_models(specs, workdir, int8=int8, echo=echo)

    def start(self, bench_models: list[BenchModel], with_torch: bool, echo) -> str:
        self.with_torch, self._torch_runners = with_torch, {}
        self.bench_models = bench_models
        self.probe, self.costs = _roofline_inputs(bench_models, echo)
        return " (and per roofline limit, measured in every cell)" if self.probe is not None else ""

    def cell_runners(self, bench_models, threads: int, batch: int, image, boxes, q_in) -> dict:
        runners = {}
        if self.with_torch and any(m.torch_model is not None for m in bench_models):
            if threads not in self._torch_runners:
                import torch

                torch.set_num_threads(threads)
                self._torch_runners = {threads: {i: TorchRefiner(m.torch_model, threads)
                                                 for i, m in enumerate(bench_models) if m.torch_model is not None}}
            if batch <= TORCH_MAX_BATCH:
                runners.update({("torch", i): (lambda r=r: r.refine(image, boxes, q_in))
                                for i, r in self._torch_runners[threads].items()})
        if self.probe is not None and self.costs:
            runners.update(self.probe.runners(threads))
        return runners

    def finish_cell(self, threads: int, latencies: dict, cell: list) -> None:
        if self.probe is None or not self.costs:
            return
        limits = self.probe.limits(threads, latencies)
        for i, row in cell:
            if i in self.costs:
                _fill_roofline(row, self.costs[i], limits)

    def summary(self, rows: list[BenchRow], bench_models: list[BenchModel]) -> list[str]:
        if self.probe is None:
            return []
        lines = [_describe_limits(rows)]
        thread_counts = sorted({r.threads for r in rows if r.bandwidth_gbs is not None})
        if thread_counts:
            first = _cell_limits(rows, thread_counts)
            lines.append("\n".join(describe_roofline(m.label, self.costs[i], first, thread_counts)
                                    for i, m in enumerate(bench_models) if i in self.costs))
        return lines


bench_cmd = bench_command(PaperBench())  # `refiner-rt bench` in a full install (export.commands plugs it in)
