"""CPU speed benchmark behind ``refiner-rt bench --cpu``: the full ``refine()`` path, architectures side by side.

What is timed is what robot code pays per call: crop every box out of a 640x480 BGR frame with the
shared crop rule, run the network, compose ``q_in * q_out`` in float64. Architectures are measured
interleaved (round-robin, several rounds) so that drift of a shared machine hits all of them alike,
and every ratio comes from one run. Reported: median (p50) and p90 latency per call and
refinements per second (``batch / p50``).

With no ``--model``, the registered architectures are built with random weights and exported
(speed does not depend on the weight values); this needs the training extra (torch). When torch is
installed the same networks are also timed in PyTorch eager mode for the onnxruntime/PyTorch ratio.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import statistics
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import click
import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.preprocess import crop_batch, validate_boxes

log = logging.getLogger(__name__)

FRAME_W, FRAME_H = 640, 480


@dataclass
class BenchRow:
    """One measured cell: an architecture on a runtime at a batch size and thread count."""

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
    ratio_shallow_over_vggm: float | None = None
    ratio_onnxruntime_over_torch: float | None = None


def machine_info() -> dict:
    """CPU model, core count and library versions of this machine."""
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


def available_cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def synthetic_frame(batch: int, seed: int = 0):
    """A 640x480 BGR frame, ``batch`` boxes of varied size and ``batch`` coarse rotations (wxyz)."""
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (FRAME_H, FRAME_W, 3), dtype=np.uint8)
    side = rng.uniform(60, 200, size=batch)
    cx = rng.uniform(100, FRAME_W - 100, size=batch)
    cy = rng.uniform(100, FRAME_H - 100, size=batch)
    boxes = np.stack([cx - side / 2, cy - side / 2, cx + side / 2, cy + side * 0.4], axis=1)
    q_in = rq.sample_rotation_noise(batch, "uniform", 0, 180, rng)
    return image, boxes, q_in


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


def measure_interleaved(runners: dict[str, callable], seconds: float, rounds: int = 5, warmup: int = 3) -> dict[str, list[float]]:
    """Per-call latencies (s) of several callables, measured round-robin.

    Each runner gets about ``seconds`` of calls in total, split over ``rounds`` rounds; within a
    round the runners take turns, so slow drift of the machine is shared by all.
    """
    per_call = {}
    for name, fn in runners.items():
        warm = _time_calls(fn, warmup)
        per_call[name] = max(statistics.median(warm), 1e-6)
    calls = {name: max(1, int(seconds / rounds / t)) for name, t in per_call.items()}
    lat = {name: [] for name in runners}
    for _ in range(rounds):
        for name, fn in runners.items():
            lat[name].extend(_time_calls(fn, calls[name]))
    return lat


def _percentile(values, q):
    return float(np.percentile(np.asarray(values), q))


def build_default_models(archs, workdir: Path) -> dict[str, tuple[Path, object]]:
    """Random-weight networks of ``archs`` exported to ONNX in ``workdir``: ``{arch: (onnx_path, torch_model)}``."""
    try:
        import torch

        import models
        from export import export_model
    except ModuleNotFoundError as exc:
        raise click.ClickException(
            f"building the default benchmark models needs {exc.name!r} (pip install 'refiner-rt[train]'); "
            "or pass exported models with --model"
        ) from exc
    out = {}
    for arch in archs:
        torch.manual_seed(0)
        model = models.build_refiner(arch).eval()
        path = workdir / f"{arch}.onnx"
        export_model(model, path, checkpoint_sha256="random-weights")
        out[arch] = (path, model)
    return out


def run_bench(
    onnx_models: dict[str, Path],
    torch_models: dict[str, object] | None = None,
    batches=(1, 8),
    threads=(1, 0),
    seconds: float = 3.0,
    progress=None,
) -> list[BenchRow]:
    """Measure every (batch, threads) cell for every model; returns the rows with ratios filled in.

    Args:
        onnx_models: ``{label: path}`` of refiner-rt ONNX models (the label is the row's ``arch``).
        torch_models: ``{label: nn.Module}`` timed in PyTorch eager mode, or None.
        batches: boxes per call.
        threads: intra-op thread counts; ``0`` means all available cores.
        seconds: approximate time spent per model and cell.
        progress: optional callable advanced by one after each cell.
    """
    from refiner_rt.session import RefinerSession

    torch_models = torch_models or {}
    rows: list[BenchRow] = []
    for nthreads in threads:
        n = nthreads or available_cores()
        sessions = {label: RefinerSession(path, threads=n) for label, path in onnx_models.items()}
        torch_runners = {label: TorchRefiner(m, n) for label, m in torch_models.items()}
        if torch_runners:
            import torch

            torch.set_num_threads(n)
        for batch in batches:
            image, boxes, q_in = synthetic_frame(batch)
            runners = {}
            for label, sess in sessions.items():
                runners[("onnxruntime", label)] = lambda s=sess: s.refine(image, boxes, q_in)
            for label, tr in torch_runners.items():
                runners[("torch", label)] = lambda r=tr: r.refine(image, boxes, q_in)
            lat = measure_interleaved(runners, seconds)
            for (runtime, label), values in lat.items():
                p50 = _percentile(values, 50)
                quant = sessions[label].contract.quantization if runtime == "onnxruntime" else "none"
                arch = sessions[label].contract.arch if label in sessions else label
                rows.append(
                    BenchRow(
                        arch=arch,
                        runtime=runtime,
                        threads=n,
                        batch=batch,
                        fps=batch / p50,
                        p50_ms=p50 * 1e3,
                        p90_ms=_percentile(values, 90) * 1e3,
                        calls=len(values),
                        model=label,
                        quantization=quant,
                    )
                )
            if progress:
                progress()
    _fill_ratios(rows)
    return rows


def _fill_ratios(rows: list[BenchRow]) -> None:
    """Same-run ratios: shallow/VGG-M speed per (runtime, threads, batch), and onnxruntime/torch per arch."""
    index = {(r.runtime, r.model, r.threads, r.batch): r for r in rows}
    for r in rows:
        vggm = next(
            (o for o in rows if o.arch == "vggm" and (o.runtime, o.threads, o.batch, o.quantization) == (r.runtime, r.threads, r.batch, r.quantization)),
            None,
        )
        if r.arch == "shallow" and vggm is not None:
            r.ratio_shallow_over_vggm = r.fps / vggm.fps
        if r.runtime == "onnxruntime":
            t = index.get(("torch", r.model, r.threads, r.batch))
            if t is not None:
                r.ratio_onnxruntime_over_torch = r.fps / t.fps


def format_table(rows: list[BenchRow]) -> str:
    """A Markdown table of the rows (what the CLI prints and the README quotes)."""
    head = "| arch | runtime | quant | threads | batch | refinements/s | p50 ms | p90 ms | shallow/VGG-M | ORT/torch |"
    sep = "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"
    lines = [head, sep]
    for r in sorted(rows, key=lambda r: (r.threads, r.batch, r.runtime, r.arch)):
        ratio = f"{r.ratio_shallow_over_vggm:.1f}x" if r.ratio_shallow_over_vggm else ""
        ort_t = f"{r.ratio_onnxruntime_over_torch:.1f}x" if r.ratio_onnxruntime_over_torch else ""
        lines.append(
            f"| {r.arch} | {r.runtime} | {r.quantization} | {r.threads} | {r.batch} | {r.fps:,.0f} | "
            f"{r.p50_ms:.3f} | {r.p90_ms:.3f} | {ratio} | {ort_t} |"
        )
    return "\n".join(lines)


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


@click.command("bench")
@click.option("--cpu", "cpu", is_flag=True, default=True, help="Benchmark on the CPU (the only device supported; default).")
@click.option(
    "--model",
    "model_paths",
    multiple=True,
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="An exported refiner-rt ONNX model (repeatable). Default: random-weight shallow and VGG-M models.",
)
@click.option("--archs", default="shallow,vggm", show_default=True, help="Registered architectures to build when no --model is given.")
@click.option("--batch", "batches", default="1,8", show_default=True, callback=_int_list, help="Boxes per refine() call.")
@click.option("--threads", "threads", default="1,all", show_default=True, callback=_threads_list, help="Intra-op thread counts ('all' = every core).")
@click.option("--seconds", default=3.0, show_default=True, type=click.FloatRange(0.1, 600), help="Measuring time per model and cell.")
@click.option("--torch/--no-torch", "with_torch", default=True, show_default=True, help="Also time PyTorch eager for the built-in random-weight models (when torch is installed).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write the rows and machine info as JSON.")
def bench_cmd(cpu, model_paths, archs, batches, threads, seconds, with_torch, json_path):
    """CPU speed of the full refine() path (crop + inference + compose), architectures side by side."""
    if 0 in batches:
        raise click.BadParameter("batch sizes must be >= 1", param_hint="--batch")
    machine = machine_info()
    with tempfile.TemporaryDirectory(prefix="refiner-rt-bench-") as tmp:
        torch_models = {}
        if model_paths:
            onnx_models = {}
            for p in model_paths:
                label = p.stem if p.stem not in onnx_models else str(p)
                onnx_models[label] = p
            weights = "user-supplied models"
        else:
            arch_list = [a.strip() for a in archs.split(",") if a.strip()]
            click.echo(f"Building random-weight models {arch_list} (speed does not depend on weight values)...", err=True)
            built = build_default_models(arch_list, Path(tmp))
            onnx_models = {a: p for a, (p, _) in built.items()}
            if with_torch:
                torch_models = {a: m for a, (_, m) in built.items()}
            weights = "random weights (speed does not depend on weight values)"
        n_cells = len(threads) * len(batches)
        click.echo(
            f"Timing refine() on a {FRAME_W}x{FRAME_H} frame: {len(onnx_models)} model(s), batches {batches}, "
            f"threads {[t or 'all' for t in threads]}, ~{seconds:g} s per model and cell",
            err=True,
        )
        t0 = time.perf_counter()
        with click.progressbar(length=n_cells, label="cells", file=click.get_text_stream("stderr")) as bar:
            rows = run_bench(onnx_models, torch_models, batches, threads, seconds, progress=lambda: bar.update(1))
        wall = time.perf_counter() - t0
    click.echo("")
    click.echo(f"Machine: {machine['cpu']}, {machine['cores']} cores, onnxruntime {machine['onnxruntime']}, torch {machine['torch']}")
    click.echo(f"Weights: {weights}. Full refine() path, medians over interleaved rounds; wall {wall:.0f} s.")
    click.echo(format_table(rows))
    if json_path:
        # A list of rows (what machines read); each row carries the run's context.
        context = {"machine": machine, "weights": weights, "frame": [FRAME_W, FRAME_H], "seconds_per_cell": seconds, "wall_s": wall}
        json_path.write_text(json.dumps([{**asdict(r), **context} for r in rows], indent=2))
        click.echo(f"Wrote {json_path}")
