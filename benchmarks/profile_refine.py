"""Where ``RefinerSession.refine()`` spends its time: Python work outside ``session.run`` vs inference.

For each model, at one batch size and thread count (default batch 1, 1 thread), on the bench's synthetic
640x480 BGR frame:

1. **Overhead in the loop**: ``refine()`` and a bare ``InferenceSession.run`` on the same session with the
   same, already-cropped feed, alternating call by call (so both see the same cache and machine state);
   medians. ``outside run = p50(refine) - p50(run)``: crop, validation, casts, quaternion composition, and
   the cache misses they take after the network has streamed its weights through the caches.
2. **Overhead with warm caches**: the same for a constant-output model with the same input size and
   contract (the network does no work, so nothing evicts the Python side): what the Python code itself costs.
3. **onnxruntime profiler**: the operators that take the most kernel time (the profiler adds a cost per
   node, so its ``model_run`` time is inflated: read it for the ranking).
4. **cProfile** of ``refine()``: the Python functions outside ``session.run``, per call (inflated likewise).

Usage (from the repository root)::

    python -m benchmarks.profile_refine                 # random-weight shallow + fusion, fp32 (needs torch)
    python -m benchmarks.profile_refine --int8          # ... and their dynamic-INT8 exports
    python -m benchmarks.profile_refine --model a.onnx --model b.onnx --batch 8 --threads 2

Speed does not depend on weight values, so random weights give the real timings. The machine is
shared: compare numbers from one run only, and note what else was running.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from refiner_rt import RefinerSession
from export.bench import machine_info
from refiner_rt.bench import frame_K, synthetic_frame
from refiner_rt.metadata import INPUT_IMAGE, INPUT_QUATERNION, OUTPUT_QUATERNION
from refiner_rt.preprocess import crop_to_square, validate_boxes
from refiner_rt.session import DISABLED_OPTIMIZERS


def build_models(archs: list[str], workdir: Path, int8: bool) -> dict[str, Path]:
    """Random-weight models of ``archs`` exported to ``workdir`` (and their INT8 versions): ``{label: path}``."""
    import torch

    import models
    from export import export_model

    out = {}
    for arch in archs:
        torch.manual_seed(0)
        model = models.build_refiner(arch).eval()
        path = workdir / f"{arch}.onnx"
        export_model(model, path, checkpoint_sha256="random-weights")
        out[arch] = path
        if int8:
            from export.quantize import quantize_model

            q_path = workdir / f"{arch}.int8.onnx"
            quantize_model(path, q_path)
            out[f"{arch}-int8"] = q_path
    return out


def overhead(sess: RefinerSession, image, boxes, q_in, seconds: float) -> dict:
    """p50 of ``refine()`` and of the bare ``InferenceSession.run`` on the same feed, alternating call by call (s)."""
    K = frame_K(sess)
    s = sess.input_size
    boxes = validate_boxes(boxes)
    crops = np.stack([crop_to_square(image, b, s, sess.contract.crop_context, crop_filter=sess.contract.crop_filter) for b in boxes])
    if sess.contract.channel_order == "RGB":
        crops = np.ascontiguousarray(crops[..., ::-1])
    feed = {INPUT_IMAGE: crops, INPUT_QUATERNION: q_in.astype(np.float32)}
    raw = sess._session  # the onnxruntime.InferenceSession refine() calls (private: benchmark only)
    perf = time.perf_counter
    for _ in range(20):
        raw.run([OUTPUT_QUATERNION], feed)
        sess.refine(image, boxes, q_in, K=K)
    t0 = perf()
    sess.refine(image, boxes, q_in, K=K)
    n = max(200, int(seconds / 2 / max(perf() - t0, 1e-6)))
    lat_run, lat_refine = [], []
    for _ in range(n):
        t0 = perf()
        raw.run([OUTPUT_QUATERNION], feed)
        t1 = perf()
        sess.refine(image, boxes, q_in, K=K)
        t2 = perf()
        lat_run.append(t1 - t0)
        lat_refine.append(t2 - t1)
    p_run, p_refine = statistics.median(lat_run), statistics.median(lat_refine)
    return {"run_p50": p_run, "refine_p50": p_refine, "outside": p_refine - p_run, "calls": n}


def constant_model(contract) -> bytes:
    """A model with ``sess``'s contract and input size whose output is the identity rotation (no work)."""
    from onnx import TensorProto, helper

    s = contract.input_size
    props = {k: (v if isinstance(v, str) else json.dumps(v)) for k, v in contract.as_dict().items()}
    props["input_size"], props["crop_context"] = str(s), repr(contract.crop_context)
    graph = helper.make_graph(
        [helper.make_node("Mul", [INPUT_QUATERNION, "zero"], ["z"]), helper.make_node("Add", ["z", "one"], [OUTPUT_QUATERNION])],
        "constant_refiner",
        [helper.make_tensor_value_info(INPUT_IMAGE, TensorProto.UINT8, ["batch", s, s, 3]),
         helper.make_tensor_value_info(INPUT_QUATERNION, TensorProto.FLOAT, ["batch", 4])],
        [helper.make_tensor_value_info(OUTPUT_QUATERNION, TensorProto.FLOAT, ["batch", 4])],
        initializer=[helper.make_tensor("zero", TensorProto.FLOAT, [1], [0.0]),
                     helper.make_tensor("one", TensorProto.FLOAT, [4], [1.0, 0.0, 0.0, 0.0])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    helper.set_model_props(model, props)
    return model.SerializeToString()


def ort_profile(sess: RefinerSession, image, boxes, q_in, calls: int, workdir: Path, top: int) -> dict:
    """onnxruntime's own profile of ``calls`` refine()-equivalent runs with the session's options."""
    options = sess._session.get_session_options()
    options.enable_profiling = True
    options.profile_file_prefix = str(workdir / "ort_profile")
    source = str(sess.model_path)
    prof = ort.InferenceSession(source, sess_options=options, providers=sess.providers,
                                disabled_optimizers=list(DISABLED_OPTIMIZERS))
    s = sess.input_size
    crops = np.stack([crop_to_square(image, b, s, sess.contract.crop_context, crop_filter=sess.contract.crop_filter) for b in validate_boxes(boxes)])
    feed = {INPUT_IMAGE: crops, INPUT_QUATERNION: q_in.astype(np.float32)}
    for _ in range(calls):
        prof.run([OUTPUT_QUATERNION], feed)
    events = json.loads(Path(prof.end_profiling()).read_text())
    runs = [e["dur"] for e in events if e.get("name") == "model_run"][5:]  # drop the first runs (warm-up)
    per_op: dict[str, float] = {}
    for e in events:
        if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time"):
            op = e.get("args", {}).get("op_name", "?")
            per_op[op] = per_op.get(op, 0.0) + e["dur"]
    total = sum(per_op.values()) or 1.0
    ops = sorted(per_op.items(), key=lambda kv: -kv[1])[:top]
    return {
        "model_run_p50": statistics.median(runs) * 1e-6 if runs else float("nan"),
        "ops": [(op, dur / total) for op, dur in ops],
    }


def python_profile(sess: RefinerSession, image, boxes, q_in, calls: int, top: int) -> list[tuple[str, float]]:
    """cProfile of ``calls`` refine() calls: ``(function, tottime per call in s)``, highest first."""
    K = frame_K(sess)
    for _ in range(20):
        sess.refine(image, boxes, q_in, K=K)
    prof = cProfile.Profile()
    prof.enable()
    for _ in range(calls):
        sess.refine(image, boxes, q_in, K=K)
    prof.disable()
    stats = pstats.Stats(prof).stats
    rows = []
    for (filename, line, func), (_, _, tottime, _, _) in stats.items():
        name = func if filename == "~" else f"{Path(filename).name}:{line}({func})"
        rows.append((name, tottime / calls))
    rows.sort(key=lambda r: -r[1])
    return rows[:top]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", action="append", type=Path, default=[], help="ONNX model (repeatable)")
    parser.add_argument("--archs", default="shallow,fusion", help="archs to build when no --model is given")
    parser.add_argument("--int8", action="store_true", help="also profile the dynamic-INT8 exports of the built archs")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seconds", type=float, default=4.0, help="timing budget per model for the overhead step")
    parser.add_argument("--calls", type=int, default=2000, help="calls profiled by cProfile and onnxruntime")
    parser.add_argument("--top", type=int, default=8)
    args = parser.parse_args(argv)

    m = machine_info()
    print(f"# refine() profile: batch {args.batch}, threads {args.threads}")
    print(f"machine: {m['cpu']}, {m['cores']} cores, onnxruntime {m['onnxruntime']}, numpy {m['numpy']}, "
          f"load average {os.getloadavg()[0]:.2f} at start")
    image, boxes, q_in = synthetic_frame(args.batch)
    with tempfile.TemporaryDirectory(prefix="profile-refine-") as tmp:
        tmp = Path(tmp)
        if args.model:
            paths = {p.stem: p for p in args.model}
        else:
            paths = build_models([a.strip() for a in args.archs.split(",") if a.strip()], tmp, args.int8)
        summary = []
        for label, path in paths.items():
            sess = RefinerSession(path, threads=args.threads)
            o = overhead(sess, image, boxes, q_in, args.seconds)
            warm = overhead(RefinerSession(constant_model(sess.contract), threads=args.threads), image, boxes, q_in, 1.0)
            op = ort_profile(sess, image, boxes, q_in, min(args.calls, 500), tmp, args.top)
            py = python_profile(sess, image, boxes, q_in, args.calls, args.top)
            share = o["outside"] / o["refine_p50"]
            summary.append((label, sess.contract.quantization, o, op, share, warm))
            print(f"\n## {label} ({sess.contract.arch}, quantization {sess.contract.quantization})")
            print(f"refine() p50 {o['refine_p50'] * 1e6:.1f} us | session.run p50 {o['run_p50'] * 1e6:.1f} us | "
                  f"outside run {o['outside'] * 1e6:.1f} us = {share:.1%} of refine()  ({o['calls']} calls each)")
            print(f"warm caches (constant-output model, same input size): refine() p50 {warm['refine_p50'] * 1e6:.1f} us, "
                  f"session.run p50 {warm['run_p50'] * 1e6:.1f} us, outside run {warm['outside'] * 1e6:.1f} us")
            print(f"onnxruntime profiler: model_run p50 {op['model_run_p50'] * 1e6:.1f} us (inflated by profiling); "
                  f"kernel time by operator: " + ", ".join(f"{k} {v:.0%}" for k, v in op["ops"]))
            print("cProfile, tottime per refine() call (inflated by the profiler):")
            for name, t in py:
                print(f"    {t * 1e6:8.1f} us  {name}")
        print("\n| model | quant | refine() p50 us | session.run p50 us | outside run us | outside share | "
              "outside, warm caches us | refinements/s |")
        print("|---|---|---:|---:|---:|---:|---:|---:|")
        for label, quant, o, _, share, warm in summary:
            print(f"| {label} | {quant} | {o['refine_p50'] * 1e6:.1f} | {o['run_p50'] * 1e6:.1f} | "
                  f"{o['outside'] * 1e6:.1f} | {share:.1%} | {warm['outside'] * 1e6:.1f} | {args.batch / o['refine_p50']:,.0f} |")
    print(f"load average {os.getloadavg()[0]:.2f} at end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
