"""Memory of the runtime, measured: peak RSS of a fresh process that loads one refiner and runs many refinements, and
whether its RSS grows after warm-up (it should not: buffers are reused, nothing accumulates).

The model is exported first (random-weight ``shallow`` by default, in this process, which needs torch); the
measurement runs in a fresh Python process that imports only the runtime (numpy, OpenCV, onnxruntime), loads
the model with ``RefinerSession``, and calls ``refine()`` on the bench's synthetic 640x480 frame, sampling its
resident set size (``/proc/self/statm``, Linux) every ``--every`` calls.

The command is ``python -m benchmarks.memory`` (and ``python -m benchmarks.soak`` for long runs); this module is the
measured process's side.

Reported: RSS after the imports, after loading the model, after warm-up and at the end; peak RSS (VmHWM); the
growth from the end of warm-up to the end, the least-squares slope of RSS over the calls after warm-up, the largest
step between two samples, and the growth over the second half of the run. (Measured: onnxruntime's ``run`` takes
one step of about 0.7 MB after a few thousand calls, in a bare ``session.run`` loop too, and is flat after it
for at least 40,000 calls: a late warm-up, not a leak.)
"""

from __future__ import annotations

import os
import sys

MB = 2**20


def rss_bytes() -> int:
    """This process's resident set size (``/proc/self/statm``, Linux), bytes."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def peak_rss_bytes() -> int:
    """This process's peak resident set size (``VmHWM``, Linux), bytes."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("VmHWM not found in /proc/self/status")


def child(model: str, calls: int, every: int, batch: int, threads: int) -> dict:
    """The measured process: import the runtime, load, refine ``calls`` times, sample RSS every ``every`` calls."""
    start = rss_bytes()
    from refiner_rt import RefinerSession
    from refiner_rt.bench import frame_K, synthetic_frame

    imported = rss_bytes()
    sess = RefinerSession(model, threads=threads)
    loaded = rss_bytes()
    image, boxes, q_in = synthetic_frame(batch)
    K = frame_K(sess)  # the bench's camera: ray-frame models need K
    samples = []
    for i in range(1, calls + 1):
        sess.refine(image, boxes, q_in, K=K)
        if i % every == 0:
            samples.append((i, rss_bytes()))
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
        "peak_rss": peak_rss_bytes(),
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
