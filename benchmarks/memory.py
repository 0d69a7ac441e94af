"""Memory of the runtime: peak RSS of a fresh process that loads one refiner and runs many refinements, and
whether its RSS grows after warm-up (it should not: buffers are reused, nothing accumulates).

The model is exported first (random-weight ``shallow`` by default, in this process, which needs torch); the
measurement runs in a fresh Python process that imports only the runtime (numpy, OpenCV, onnxruntime), loads
the model with ``RefinerSession``, and calls ``refine()`` on the bench's synthetic 640x480 frame, sampling its
resident set size (``/proc/self/statm``, Linux) every ``--every`` calls.

Usage (from the repository root)::

    python -m benchmarks.memory                       # shallow fp32, batch 1, 10,000 refinements
    python -m benchmarks.memory --int8 --batch 8      # its dynamic-INT8 export, 8 boxes per call
    python -m benchmarks.memory --model refiner.onnx --calls 50000

Reported: RSS after the imports, after loading the model, after warm-up and at the end; peak RSS (VmHWM); the
growth from the end of warm-up to the end, the least-squares slope of RSS over the calls after warm-up, the largest
step between two samples, and the growth over the second half of the run. (Measured: onnxruntime's ``run`` takes
one step of about 0.7 MB after a few thousand calls, in a bare ``session.run`` loop too, and is flat after it
for at least 40,000 calls: a late warm-up, not a leak.)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from export.bench_models import build_random_model
from models.evaluate.memory import MB, child, summarize
from models.evaluate.record import REPO


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
        model = args.model or build_random_model(Path(tmp), args.arch, args.int8)
        cmd = [sys.executable, "-m", "benchmarks.memory", "--child", "--model", str(model), "--calls", str(args.calls),
               "--every", str(args.every), "--batch", str(args.batch), "--threads", str(args.threads)]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=REPO).stdout
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
