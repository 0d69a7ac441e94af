"""Memory of the runtime: peak RSS of a fresh process that loads one refiner and runs many refinements, and
whether its RSS grows after warm-up (it should not: buffers are reused, nothing accumulates).

The model is exported first (random-weight ``shallow`` by default, in this process, which needs torch); the
measurement runs in a fresh Python process that imports only the runtime (numpy, OpenCV, onnxruntime), loads
the model with ``RefinerSession``, and calls ``refine()`` on the bench's synthetic 640x480 frame, sampling its
resident set size (``/proc/self/statm``, Linux) every ``--every`` calls.

Usage (from the repository root)::

    python benchmarks/memory.py                       # shallow fp32, batch 1, 10,000 refinements
    python benchmarks/memory.py --int8 --batch 8      # its dynamic-INT8 export, 8 boxes per call
    python benchmarks/memory.py --model refiner.onnx --calls 50000

Reported: RSS after the imports, after loading the model, after warm-up and at the end; peak RSS (VmHWM); the
growth from the end of warm-up to the end, the least-squares slope of RSS over the calls after warm-up, the largest
step between two samples, and the growth over the second half of the run. (Measured: onnxruntime's ``run`` takes
one step of about 0.7 MB after a few thousand calls, in a bare ``session.run`` loop too, and is flat after it
for at least 40,000 calls: a late warm-up, not a leak.)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

MB = 2**20


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _peak_rss_bytes() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("VmHWM not found in /proc/self/status")


def child(model: str, calls: int, every: int, batch: int, threads: int) -> dict:
    """The measured process: import the runtime, load, refine ``calls`` times, sample RSS every ``every`` calls."""
    start = _rss_bytes()
    from refiner_rt import RefinerSession
    from refiner_rt.bench import frame_K, synthetic_frame

    imported = _rss_bytes()
    sess = RefinerSession(model, threads=threads)
    loaded = _rss_bytes()
    image, boxes, q_in = synthetic_frame(batch)
    K = frame_K(sess)  # the bench's camera: ray-frame models need K
    samples = []
    for i in range(1, calls + 1):
        sess.refine(image, boxes, q_in, K=K)
        if i % every == 0:
            samples.append((i, _rss_bytes()))
    return rss_record(sess, start, imported, loaded, samples)


def rss_record(sess, start: int, imported: int, loaded: int, samples: list) -> dict:
    """What a measured child process reports: RSS at start, after imports and after loading ``sess``, the samples
    ``[call, RSS]``, the peak, whether torch was imported, and the model's kind."""
    return {
        "torch_imported": "torch" in sys.modules,
        "rss_start": start,
        "rss_imported": imported,
        "rss_loaded": loaded,
        "samples": samples,
        "peak_rss": _peak_rss_bytes(),
        "quantization": sess.contract.quantization,
        "arch": sess.contract.arch,
    }


def summarize(result: dict, warmup: int) -> dict:
    """Growth after warm-up: the last sample minus the first sample at or after ``warmup`` calls; also the growth
    over the second half of the run, the slope (least squares) and the largest step between two samples."""
    after = [(i, r) for i, r in result["samples"] if i >= warmup]
    if len(after) < 2:
        raise ValueError(f"need at least 2 samples after {warmup} warm-up calls; got {len(after)}")
    x = [i for i, _ in after]
    y = [r for _, r in after]
    mx, my = sum(x) / len(x), sum(y) / len(y)
    slope = sum((a - mx) * (b - my) for a, b in zip(x, y)) / sum((a - mx) ** 2 for a in x)
    half = after[len(after) // 2 :]
    steps = [(after[k + 1][0], after[k + 1][1] - after[k][1]) for k in range(len(after) - 1)]
    step_at, step = max(steps, key=lambda s: abs(s[1]))
    return {
        "rss_after_warmup": after[0][1],
        "rss_end": after[-1][1],
        "growth_after_warmup": after[-1][1] - after[0][1],
        "growth_second_half": half[-1][1] - half[0][1],
        "second_half_from": half[0][0],
        "largest_step": step,
        "largest_step_at": step_at,
        "slope_bytes_per_1000_calls": slope * 1000,
    }


def build_model(workdir: Path, arch: str, int8: bool) -> Path:
    """A random-weight model of ``arch`` exported to ``workdir`` (INT8 with export.quantize's default scheme)."""
    import torch

    import models
    from export import export_model

    torch.manual_seed(0)
    path = workdir / f"{arch}.onnx"
    export_model(models.build_refiner(arch).eval(), path, checkpoint_sha256="random-weights")
    if int8:
        from export.quantize import quantize_model

        path = quantize_model(path).path
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, help="ONNX model (default: a random-weight export of --arch)")
    parser.add_argument("--arch", default="shallow")
    parser.add_argument("--int8", action="store_true", help="quantise the built model (export.quantize default scheme)")
    parser.add_argument("--calls", type=int, default=10_000)
    parser.add_argument("--warmup", type=int, default=1_000, help="calls counted as warm-up")
    parser.add_argument("--every", type=int, default=100, help="sample RSS every this many calls")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.child:
        print(json.dumps(child(str(args.model), args.calls, args.every, args.batch, args.threads)))
        return 0
    with tempfile.TemporaryDirectory(prefix="refiner-rt-memory-") as tmp:
        model = args.model or build_model(Path(tmp), args.arch, args.int8)
        cmd = [sys.executable, __file__, "--child", "--model", str(model), "--calls", str(args.calls),
               "--every", str(args.every), "--batch", str(args.batch), "--threads", str(args.threads)]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    result = json.loads(out.strip().splitlines()[-1])
    s = summarize(result, args.warmup)
    print(f"# refine() memory: {result['arch']} ({result['quantization']}), batch {args.batch}, threads {args.threads}, "
          f"{args.calls:,} calls in a fresh process (torch imported: {result['torch_imported']})")
    print(f"RSS at start {result['rss_start'] / MB:.1f} MB, after imports {result['rss_imported'] / MB:.1f} MB, "
          f"after loading the model {result['rss_loaded'] / MB:.1f} MB")
    print(f"RSS after {args.warmup:,} warm-up calls {s['rss_after_warmup'] / MB:.2f} MB, at the end {s['rss_end'] / MB:.2f} MB; "
          f"peak RSS (VmHWM) {result['peak_rss'] / MB:.1f} MB")
    print(f"growth after warm-up: {s['growth_after_warmup'] / 1024:+.0f} KB (slope {s['slope_bytes_per_1000_calls'] / 1024:+.2f} "
          f"KB per 1000 calls); largest step {s['largest_step'] / 1024:+.0f} KB by call {s['largest_step_at']:,}; "
          f"growth over the second half (calls {s['second_half_from']:,}-{args.calls:,}): {s['growth_second_half'] / 1024:+.0f} KB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
