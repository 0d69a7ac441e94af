"""The runtime's CPU timer behind ``refiner-rt bench --cpu``: the full ``refine()`` path of ONNX models, side by side.

What is timed is what robot code pays per call: crop every box out of a 640x480 BGR frame with the
shared crop rule, run the network, compose ``q_in * q_out`` in float64 (models trained in the viewing-ray frame
get the frame's ``K``, as robot code gives it). Models are measured interleaved (round-robin, several rounds) so
that drift of a shared machine hits all of them alike, and every ratio comes from one run. Reported: median (p50)
and p90 latency per call and refinements per second (``batch / p50``).

With no ``--model``, it times the shipped refiners (trained weights; INT8 and fp32): by default one representative
object, the first shipped (every shipped model has the same architecture, so they run at the same speed;
``--shipped all`` times each, ``--shipped none`` none), and the paper's networks, :data:`DEFAULT_ARCHS` (``shallow``,
the paper's network; ``vggm``, its deep variant) and any ``--variant`` configs, built with random weights.

This module times ONNX files through ``refine()`` and nothing else. What needs the training package comes from a
:class:`BenchExtension`: the training package's (``export.bench``, which plugs its ``bench`` command into
``refiner-rt`` in a full install) builds the paper's networks with random weights (and their INT8), times them in
PyTorch eager mode too, and puts each row beside its roofline bound. In a runtime-only install only the shipped
models and ``--model`` files are timed, and the output says so.

Every row says which weights it has (``weights``: ``trained``, ``random`` or ``user-supplied``), and onnxruntime rows
give their speed over the paper's shallow network (``ratio_over_shallow``) at the same threads and batch, INT8
over INT8 and fp32 over fp32.
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
    """CPU model, its vector-instruction flags, core count and library versions of this machine (``torch`` and
    ``cpu_capability`` None: the runtime never imports torch; ``export.bench.machine_info`` fills them in)."""
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


# ---------------------------------------------------------------------------------------------------- runners
def time_calls(fn, n: int) -> list[float]:
    """Wall seconds of ``n`` calls of ``fn``, one by one."""
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
            warm += time_calls(fn, 1)
        per_call[name] = max(statistics.median(warm), 1e-6)
    plan = {name: max(min_calls, int(seconds / t)) for name, t in per_call.items()}
    lat = {name: [] for name in runners}
    for r in range(rounds):
        for name, fn in runners.items():
            n = plan[name] // rounds + (1 if r < plan[name] % rounds else 0)
            lat[name].extend(time_calls(fn, n))
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
class BenchExtension:
    """What a package adds to ``refiner-rt bench``; this base adds nothing (the runtime's own bench). The training
    package's subclass (``export.bench``) builds the paper's networks with random weights, times them in PyTorch
    eager mode and measures the roofline. Each hook is called by :func:`bench_command` and :func:`run_bench`."""

    def machine_info(self, info: dict) -> dict:
        """The machine's description (:func:`machine_info`), completed."""
        return info

    def build_models(self, specs, workdir: Path, int8: bool, echo) -> list[BenchModel]:
        """Random-weight networks for ``specs`` (``(label, arch, config)``), exported to ONNX in ``workdir``."""
        raise click.ClickException(
            f"building the random-weight models needs the training package: {TRAINING_INSTALL}; or time the "
            "shipped models alone (--archs '') or your own files (--model)")

    def start(self, bench_models: list[BenchModel], with_torch: bool, echo) -> str:
        """Called once before timing; returns what the timing line adds (empty: nothing)."""
        return ""

    def cell_runners(self, bench_models: list[BenchModel], threads: int, batch: int, image, boxes, q_in) -> dict:
        """Callables timed in the cell with the models: keys ``(runtime, model index)`` make rows; other keys are
        the extension's own measurements, handed back to :meth:`finish_cell`."""
        return {}

    def finish_cell(self, threads: int, latencies: dict, cell: list) -> None:
        """Complete the cell's rows (``[(model index, BenchRow)]``) from its latencies."""

    def summary(self, rows: list[BenchRow], bench_models: list[BenchModel]) -> list[str]:
        """Lines printed above the table."""
        return []


def run_bench(
    bench_models: list[BenchModel],
    batches=(1, 8, 32),
    threads=(1, 0),
    seconds: float = 1.0,
    extension: BenchExtension | None = None,
    progress=None,
) -> list[BenchRow]:
    """Measure every (batch, threads) cell for every model; returns the rows with their ratios filled in.

    Args:
        bench_models: the models; each is timed through :meth:`refiner_rt.RefinerSession.refine` (or a cascade's).
        batches: boxes per call.
        threads: thread counts; ``0`` means all available cores.
        seconds: approximate time spent per model and cell.
        extension: what else each cell times, interleaved with the models (:meth:`BenchExtension.cell_runners`),
            and what it adds to the cell's rows (:meth:`BenchExtension.finish_cell`); None: nothing.
        progress: optional callable advanced by one after each cell.
    """
    from refiner_rt.session import RefinerSession

    extension = extension or BenchExtension()
    rows: list[BenchRow] = []
    for nthreads in threads:
        n = nthreads or available_cores()
        sessions = [RefinerSession(m.path, threads=n) for m in bench_models]
        refiners = [s if m.fine_path is None else _cascade(s, m, n) for s, m in zip(sessions, bench_models)]
        for batch in batches:
            image, boxes, q_in = synthetic_frame(batch)
            runners = {("onnxruntime", i): (lambda s=s, K=frame_K(sessions[i]): s.refine(image, boxes, q_in, K=K))
                       for i, s in enumerate(refiners)}
            runners.update(extension.cell_runners(bench_models, n, batch, image, boxes, q_in))
            latencies = measure_interleaved(runners, seconds)
            cell = []
            for key, values in latencies.items():
                if not isinstance(key, tuple):
                    continue  # the extension's own measurement (a machine limit)
                runtime, i = key
                m, contract = bench_models[i], sessions[i].contract
                p50 = _percentile(values, 50)
                cell.append((i, BenchRow(
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
                )))
            extension.finish_cell(n, latencies, cell)
            rows += [row for _, row in cell]
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


def _shipped_option(ctx, param, value):
    value = str(value).strip()
    if value in ("", "none"):
        return []
    if value in ("first", "all"):
        return value
    return [v.strip() for v in value.split(",") if v.strip()]


def bench_command(extension: BenchExtension | None = None) -> click.Command:
    """The ``refiner-rt bench`` command, with what ``extension`` adds (:class:`BenchExtension`; None: the runtime's
    own: the shipped models and ``--model`` files). The training package builds its own with its extension, since
    the runtime never imports training code."""
    extension = extension or BenchExtension()

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
    @click.option("--torch/--no-torch", "with_torch", default=True, show_default=True, help="Also time PyTorch eager for the built models at small batches (when torch is installed).")
    @click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write the rows (with the run's context) as a JSON list.")
    def bench_cmd(cpu, model_paths, shipped, archs, variants, with_int8, batches, threads, seconds, with_torch, json_path):
        """CPU speed of the full refine() path (crop + inference + compose): the shipped refiners beside the paper's
        networks, fp32 and INT8 (with the training package: also PyTorch eager, and each row next to its roofline
        bound measured interleaved with the models)."""
        if 0 in batches:
            raise click.BadParameter("batch sizes must be >= 1", param_hint="--batch")
        if max(batches) > MAX_BATCH:
            raise click.BadParameter(f"batch sizes must be at most {MAX_BATCH} (RefinerSession's MAX_BATCH crops per call)",
                                     param_hint="--batch")
        if json_path:
            from refiner_rt.cli import prepare_output

            prepare_output(json_path, "'--json'")  # the CLI's one output rule, before minutes of timing
        machine = extension.machine_info(machine_info())

        def echo(msg):
            click.echo(msg, err=True)

        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="refiner-rt-bench-") as tmp:
            bench_models, weights = _prepare_models(model_paths, shipped, archs, variants, with_int8, Path(tmp), echo,
                                                     extension)
            also = extension.start(bench_models, with_torch, echo)
            echo(
                f"Timing refine() on a {FRAME_W}x{FRAME_H} frame: {len(bench_models)} model(s), batches {batches}, "
                f"threads {[t or 'all' for t in threads]}, ~{seconds:g} s per model and cell" + also
            )
            # A bar on a terminal only: elsewhere click prints its bare label, a stray "cells" line in the output.
            stream = contextlib.nullcontext(sys.stderr) if sys.stderr.isatty() else open(os.devnull, "w")  # noqa: SIM115
            with stream as bar_stream, click.progressbar(length=len(threads) * len(batches),
                                                         label="timing cells (threads x batches)",
                                                         file=bar_stream) as bar:
                try:
                    rows = run_bench(bench_models, batches, threads, seconds, extension,
                                     progress=lambda: bar.update(1))
                except ModelError as exc:  # a model that loaded but fails when it runs
                    raise click.ClickException(str(exc)) from None
        wall = time.perf_counter() - t0
        click.echo("")
        click.echo(f"Machine: {machine['cpu']}, {machine['cores']} cores, vector flags {' '.join(machine['cpu_flags']) or '?'}"
                   f" (torch dispatch: {machine['cpu_capability'] or 'n/a'}), onnxruntime {machine['onnxruntime']}, "
                   f"torch {machine['torch']}")
        click.echo(f"Weights: {weights}. Full refine() path, medians over interleaved rounds; wall {wall:.0f} s.")
        for line in extension.summary(rows, bench_models):
            click.echo(line)
        click.echo(format_table(rows))
        if json_path:
            # A list of rows (what machines read); each row carries the run's context.
            context = {"machine": machine, "weights_note": weights, "frame": [FRAME_W, FRAME_H],
                       "seconds_per_cell": seconds, "wall_s": wall}
            json_path.write_text(json.dumps([{**asdict(r), **context} for r in rows], indent=2))
            click.echo(f"Wrote {json_path}")

    return bench_cmd


def _prepare_models(model_paths, shipped, archs: str, variants, with_int8: bool, workdir: Path, echo,
                    extension: BenchExtension) -> tuple[list, str]:
    """The models to time and a note on their weights: the given files; or the shipped models and random-weight
    builds (and their INT8) by ``extension``."""
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
        echo(f"Building random-weight models {labels} (speed does not depend on weight values)...")
        built = extension.build_models(specs, workdir, int8=with_int8, echo=echo)
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
