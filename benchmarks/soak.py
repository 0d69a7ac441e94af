"""Soak test of the runtime: resident memory (RSS) over a long run of batch-1 ``refine()`` calls on one session.

A fresh Python process that imports only the runtime (numpy, OpenCV, onnxruntime) loads one refiner with
``RefinerSession`` and calls ``refine()`` ``--calls`` times (default 1,000,000) at batch 1 on the bench's synthetic
640x480 frame, sampling its RSS (``/proc/self/statm``, Linux) every ``--every`` calls. With ``--callers N`` the
calls are spread over N threads sharing the one session (each thread keeps its own crop buffers), as a
multi-threaded ROS 2 executor would. The growth is measured after ``--warmup`` calls (onnxruntime's arena and
memory pattern settle in the first few thousand; see ``benchmarks/memory.py``). The model is a random-weight
``--arch`` export (needs torch, in this process only) or ``--model``.

Usage (from the repository root)::

    python -m benchmarks.soak                              # fusion fp32, 1,000,000 calls (about 15 min on one core)
    python -m benchmarks.soak --calls 100000 --json benchmarks/results/soak/soak_100k.json
    python -m benchmarks.soak --model refiner.onnx --callers 4
    python -m benchmarks.soak --model refiner_rt/weights/003_cracker_box.int8.onnx   # a shipped (ray-frame) model

Written (``--json``): the command, the machine (CPU model and its vector-instruction flags, cores, versions),
the model, RSS at start / after imports / after loading / after warm-up / at the end, peak RSS (VmHWM), the growth
after warm-up and over the second half, the least-squares slope, the largest step, calls per second, and the
samples ``[call, RSS bytes]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from export.bench_models import build_random_model
from models.evaluate.memory import MB, rss_bytes, rss_record, summarize
from models.evaluate.record import REPO
from models.evaluate.record import write_json

DEFAULT_CALLS = 1_000_000


def child(model: str, calls: int, every: int, callers: int) -> dict:
    """The measured process: import the runtime, load, refine ``calls`` times from ``callers`` threads, sample RSS."""
    start = rss_bytes()
    from refiner_rt import RefinerSession
    from refiner_rt.bench import frame_K, synthetic_frame

    imported = rss_bytes()
    sess = RefinerSession(model, threads=1)
    loaded = rss_bytes()
    image, boxes, q_in = synthetic_frame(1)
    K = frame_K(sess)  # the bench's camera: ray-frame models need K
    expected = sess.refine(image, boxes, q_in, K=K).q_refined
    samples, lock, done = [], threading.Lock(), [0]
    mismatches = [0]

    def run(n: int) -> None:
        for _ in range(n):
            q = sess.refine(image, boxes, q_in, K=K).q_refined
            with lock:
                if not (q == expected).all():
                    mismatches[0] += 1
                done[0] += 1
                if done[0] % every == 0:
                    samples.append((done[0], rss_bytes()))

    t0 = time.perf_counter()
    shares = [calls // callers + (1 if i < calls % callers else 0) for i in range(callers)]
    if callers == 1:
        run(calls)
    else:
        pool = [threading.Thread(target=run, args=(n,)) for n in shares]
        for t in pool:
            t.start()
        for t in pool:
            t.join()
    seconds = time.perf_counter() - t0
    return {**rss_record(sess, start, imported, loaded, samples), "seconds": seconds, "calls_per_s": calls / seconds,
            "results_differing_from_the_first": mismatches[0]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, help="ONNX model (default: a random-weight export of --arch)")
    parser.add_argument("--arch", default="fusion", help="architecture to export when no --model is given")
    parser.add_argument("--calls", type=int, default=DEFAULT_CALLS, help="batch-1 refine() calls in all")
    parser.add_argument("--warmup", type=int, default=10_000, help="calls counted as warm-up")
    parser.add_argument("--every", type=int, default=1_000, help="sample RSS every this many calls")
    parser.add_argument("--callers", type=int, default=1, help="threads sharing the one session")
    parser.add_argument("--json", type=Path, help="write the result here")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.calls < 1 or args.every < 1 or args.callers < 1 or not 0 <= args.warmup < args.calls:
        parser.error("--calls, --every and --callers must be >= 1, and --warmup from 0 to below --calls")
    if args.calls - args.warmup < 2 * args.every:
        parser.error("need at least two RSS samples after warm-up: raise --calls or lower --warmup / --every")

    if args.child:
        print(json.dumps(child(str(args.model), args.calls, args.every, args.callers)))
        return 0
    with tempfile.TemporaryDirectory(prefix="refiner-rt-soak-") as tmp:
        model = args.model or build_random_model(Path(tmp), args.arch, int8=False)
        cmd = [sys.executable, "-m", "benchmarks.soak", "--child", "--model", str(model), "--calls", str(args.calls),
               "--warmup", str(args.warmup), "--every", str(args.every), "--callers", str(args.callers)]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=REPO).stdout
    result = json.loads(out.strip().splitlines()[-1])
    from export.bench import machine_info  # here, not in the measured process: it looks for torch's version

    result["machine"] = machine_info()
    s = summarize(result, args.warmup)
    model_label = str(args.model) if args.model else f"random-weight {args.arch} fp32"
    print(f"# refine() soak: {model_label} ({result['arch']}, {result['quantization']}), batch 1, "
          f"{args.calls:,} calls from {args.callers} thread(s) on one session, in a fresh process "
          f"(torch imported: {result['torch_imported']})")
    m = result["machine"]
    print(f"machine: {m['cpu']} ({', '.join(m['cpu_flags']) or 'flags unknown'}), {m['cores']} cores, "
          f"onnxruntime {m['onnxruntime']}; {result['calls_per_s']:,.0f} calls/s; load average "
          f"{os.getloadavg()[0]:.2f} at the end")
    print(f"RSS after imports {result['rss_imported'] / MB:.1f} MB, after loading {result['rss_loaded'] / MB:.1f} MB, "
          f"after {args.warmup:,} warm-up calls {s['rss_after_warmup'] / MB:.2f} MB, at the end {s['rss_end'] / MB:.2f} MB; "
          f"peak (VmHWM) {result['peak_rss'] / MB:.1f} MB")
    print(f"growth after warm-up: {s['growth_after_warmup'] / 1024:+.0f} KB (slope "
          f"{s['slope_bytes_per_1000_calls']:+.1f} bytes per 1000 calls); largest step {s['largest_step'] / 1024:+.0f} KB "
          f"by call {s['largest_step_at']:,}; over the second half (calls {s['second_half_from']:,}-{args.calls:,}): "
          f"{s['growth_second_half'] / 1024:+.0f} KB; results differing from the first call's: "
          f"{result['results_differing_from_the_first']}")
    if args.json:
        record = {
            "command": "python -m benchmarks.soak " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:])),
            "model": model_label,
            "calls": args.calls,
            "warmup": args.warmup,
            "every": args.every,
            "callers": args.callers,
            **{k: v for k, v in result.items() if k != "samples"},
            **s,
            "samples": result["samples"],
        }
        write_json(args.json, record)
        print(f"Wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
