"""Which INT8 scheme makes the shipped five-block refiner fast on a CPU, and what it costs in accuracy.

For each shipped object: its fp32 model (``refiner_rt/weights/<obj>.onnx``) quantised with each candidate scheme,
static ones calibrated on crops the scoring never sees (the object's *training* split with ``--data/--run``, or a
folder of other fresh scenes with ``--calibration``); then, in one run:

1. the optimised graph onnxruntime builds from each (which operators it really runs: ``QLinearConv`` from the QDQ
   pairs, ``FusedConv`` from Conv + ReLU, NCHWc / NHWC layouts);
2. onnxruntime's profiler: kernel time per operator type, per call (batch 1, one thread);
3. speed of the full ``refine()`` path with K (batch 1, one thread, a 640x480 frame), candidates interleaved call
   by call over several rounds, medians; ratios only within this run;
4. session options on the fastest candidate (graph optimisation level, denormals as zero, spinning with 2 threads);
5. accuracy through the runtime on the object's held-out test scenes (``export/release/coarse.py``'s ``evaluate``)
   or on every instance of a folder of fresh scenes (``evaluate_fresh``, ``--heldout``), as the change of the mean
   error against fp32;
6. onnxruntime's QDQPropagationTransformer on and off for the shipped conv scheme (bare ``session.run`` and profile).

Usage (from the repository root; DATA is the rendered dataset, RUN the build's run folder with the checkpoints; or,
without checkpoints, HELDOUT and CALIB: rendered scenes of seeds no model trained on, benchmarks/DATA.md)::

    python -m benchmarks.studies.int8_convs.study --data DATA --run RUN --json benchmarks/studies/int8_convs/results.json
    python -m benchmarks.studies.int8_convs.study --heldout HELDOUT --calibration CALIB \\
        --json benchmarks/studies/int8_convs/results_vnni.json
    python -m benchmarks.studies.int8_convs.study --report benchmarks/studies/int8_convs/results.json   # the tables

Candidates (``static-qdq-int8-conv`` variants differ in which convolutions are quantised, by input channels, and
in whether the fully connected layers are quantised statically or dynamically):
"""

from __future__ import annotations

import argparse
import collections
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort

from refiner_rt import RefinerSession
from export.bench import machine_info
from refiner_rt.bench import FRAME_K, frame_K, synthetic_frame
from refiner_rt.metadata import INPUT_IMAGE, INPUT_QUATERNION, parse_metadata
from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name, pretrained_models
from refiner_rt.session import DISABLED_OPTIMIZERS, default_session_options

# name -> (scheme written to the metadata, quantiser options); "fp32" and the two older schemes take none.
_BIG = 65536  # weights of a "large" fully connected layer (export.quantize.large_fully_connected)
BASE = "dynamic-int8, 8-bit (the first shipped files)"
_OLD_BASE = "dynamic-int8, 8-bit (the shipped files)"  # BASE's name in results.json (written before the rename)
CANDIDATES = {
    "fp32": ("none", {}),
    BASE: ("dynamic-int8", {"reduce_range": False}),
    "dynamic-int8 (7-bit)": ("dynamic-int8", {}),
    "dynamic-int8, large FC only (7-bit)": ("dynamic-int8", {"fc_min_weights": _BIG}),
    "qdq conv>=16 + large FC dynamic (7-bit)": ("static-qdq-int8-conv", {}),
    "qdq conv>=16 + large FC dynamic, 8-bit": ("static-qdq-int8-conv", {"reduce_range": False}),
    "qdq conv>=16 + all FC dynamic (7-bit)": ("static-qdq-int8-conv", {"fc_min_weights": 0}),
    "qdq conv>=16 + large FC static (7-bit)": ("static-qdq-int8-conv", {"fc": "static"}),
    "qdq conv>=1 + large FC dynamic (7-bit)": ("static-qdq-int8-conv", {"min_channels": 1}),
    "qdq conv>=32 + large FC dynamic (7-bit)": ("static-qdq-int8-conv", {"min_channels": 32}),
}
__doc__ += "\n".join(f"    * {k}: {v[0]} {v[1] or ''}" for k, v in CANDIDATES.items()) + "\n"


def build_candidate(fp32: Path, out: Path, name: str, calibration) -> Path:
    """``fp32`` quantised as candidate ``name`` into ``out``, with the fp32 metadata and the scheme."""
    from export import quantize as q8

    scheme, options = CANDIDATES[name]
    if scheme == "none":
        return fp32
    proto = onnx.load(str(fp32))
    with tempfile.TemporaryDirectory() as work:
        src, dst = Path(work) / "fp32.onnx", Path(work) / "int8.onnx"
        onnx.save(q8._without_value_info(proto), str(src))
        with q8._without_preprocess_advice():
            q8._QUANTIZERS[scheme](src, dst, None if scheme == "dynamic-int8" else calibration, **options)
        quantized = onnx.load(str(dst))
    props = {p.key: p.value for p in proto.metadata_props}
    props["quantization"] = scheme
    if scheme != "dynamic-int8":
        props["int8_calibration"] = calibration.source
    del quantized.metadata_props[:]
    onnx.helper.set_model_props(quantized, props)
    onnx.save(quantized, str(out))
    RefinerSession(out)  # the runtime's contract
    return out


def shallow_models(work: Path) -> dict:
    """The paper's shallow network and the default two-block ``fusion`` refiner (the architectures `refiner-rt
    train` builds by default) with random weights: fp32 and each INT8 scheme, the static ones calibrated on random
    crops (for speed only: which scheme ``export --int8 --calib`` should pick for them)."""
    import torch

    import models
    from export import export_model
    from export.quantize import quantize_model

    out = {}
    for arch, label in (("shallow", "paper shallow"), ("fusion", "default fusion (2 blocks)")):
        torch.manual_seed(0)
        path = work / f"{arch}.onnx"
        export_model(models.build_refiner(arch).eval(), path, checkpoint_sha256="random-weights")
        out[f"{label}, fp32"] = path
        for scheme in ("dynamic-int8", "static-qdq-int8", "static-qdq-int8-conv"):
            out[f"{label}, {scheme}"] = quantize_model(path, work / f"{arch}.{scheme}.onnx", scheme=scheme,
                                                       enforce=False).path
    return out


def session_options(threads: int = 1, level=ort.GraphOptimizationLevel.ORT_ENABLE_ALL, **configs) -> ort.SessionOptions:
    """RefinerSession's defaults (:func:`refiner_rt.session.default_session_options`), with ``level`` and extra
    ``add_session_config_entry`` settings."""
    o = default_session_options(threads, **configs)
    o.graph_optimization_level = level
    return o


def optimized_ops(path: Path, disabled=DISABLED_OPTIMIZERS) -> dict:
    """Operator counts of the graph onnxruntime runs (after its optimisations, at level ALL, with the transformers
    ``disabled``: RefinerSession's by default)."""
    with tempfile.TemporaryDirectory() as work:
        o = session_options()
        o.optimized_model_filepath = str(Path(work) / "opt.onnx")
        ort.InferenceSession(str(path), o, providers=["CPUExecutionProvider"], disabled_optimizers=list(disabled))
        g = onnx.load(o.optimized_model_filepath)
    return dict(collections.Counter(f"{n.domain + '.' if n.domain else ''}{n.op_type}" for n in g.graph.node))


def _feed(path: Path):
    image, boxes, q_in = synthetic_frame(1)
    s = RefinerSession(path)
    from refiner_rt.preprocess import crop_to_square

    crop = crop_to_square(image, boxes[0], s.input_size, s.contract.crop_context)[None]
    return {INPUT_IMAGE: np.ascontiguousarray(crop), INPUT_QUATERNION: q_in.astype(np.float32)}


def profile_ops(path: Path, calls: int = 300, disabled=DISABLED_OPTIMIZERS) -> dict:
    """onnxruntime's profiler: microseconds of kernel time per call, by operator type (batch 1, one thread), with the
    transformers ``disabled`` (RefinerSession's by default)."""
    feed = _feed(path)
    with tempfile.TemporaryDirectory() as work:
        o = session_options()
        o.enable_profiling = True
        o.profile_file_prefix = str(Path(work) / "prof")
        sess = ort.InferenceSession(str(path), o, providers=["CPUExecutionProvider"], disabled_optimizers=list(disabled))
        for _ in range(30):
            sess.run(None, feed)
        for _ in range(calls):
            sess.run(None, feed)
        events = json.loads(Path(sess.end_profiling()).read_text())
    per_op: dict = collections.defaultdict(list)
    runs = []
    for e in events:
        if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time"):
            per_op[e["args"]["op_name"]].append(e["dur"])
        elif e.get("cat") == "Session" and e.get("name") == "model_run":
            runs.append(e["dur"])
    total_calls = len(runs) or 1
    timed = runs[-calls:]
    ops = {op: sum(d) / total_calls for op, d in per_op.items()}
    return {"us_per_call_by_op": dict(sorted(ops.items(), key=lambda kv: -kv[1])),
            "kernel_us_per_call": sum(ops.values()), "model_run_us_median": statistics.median(timed) if timed else None}


def time_interleaved(runners: dict, rounds: int = 9, calls: int = 200) -> dict:
    """Median seconds per call of each runner: rounds of ``calls`` calls each, runners taking turns."""
    for fn in runners.values():
        for _ in range(20):
            fn()
    per_round = {k: [] for k in runners}
    for _ in range(rounds):
        for k, fn in runners.items():
            t0 = time.perf_counter()
            for _ in range(calls):
                fn()
            per_round[k].append((time.perf_counter() - t0) / calls)
    return {k: statistics.median(v) for k, v in per_round.items()}


def refine_speed(paths: dict, threads: int = 1, rounds: int = 9, calls: int = 200, options=None) -> dict:
    """Refinements/s of the full refine() path with K, batch 1, interleaved; ``options`` overrides the sessions'."""
    image, boxes, q_in = synthetic_frame(1)
    runners = {}
    for name, path in paths.items():
        s = RefinerSession(path, threads=threads, session_options=options() if options else None)
        runners[name] = (lambda s=s, K=frame_K(s): s.refine(image, boxes, q_in, K=K))
    return {k: 1.0 / v for k, v in time_interleaved(runners, rounds, calls).items()}


def propagation_speed(path: Path, rounds: int = 9, calls: int = 300) -> dict:
    """Bare ``session.run`` (batch 1, one thread) of one model with onnxruntime's QDQPropagationTransformer on (its
    default) and off (RefinerSession's), interleaved: microseconds per call, and each way's profile."""
    feed = _feed(path)
    ways = {"QDQ propagation on (onnxruntime's default)": (), "QDQ propagation off (RefinerSession)": DISABLED_OPTIMIZERS}
    runners = {}
    for label, disabled in ways.items():
        sess = ort.InferenceSession(str(path), session_options(), providers=["CPUExecutionProvider"],
                                    disabled_optimizers=list(disabled))
        runners[label] = (lambda sess=sess: sess.run(None, feed))
    us = {k: 1e6 * v for k, v in time_interleaved(runners, rounds, calls).items()}
    return {"run_us": us, "profile": {k: profile_ops(path, disabled=d) for k, d in ways.items()},
            "optimized_graph_ops": {k: optimized_ops(path, d) for k, d in ways.items()}}


def option_speed(path: Path, rounds: int = 9, calls: int = 200) -> dict:
    """The same model under several session options, interleaved (refinements/s)."""
    L = ort.GraphOptimizationLevel
    one = {
        "1 thread, ALL (default)": lambda: session_options(1),
        "1 thread, EXTENDED": lambda: session_options(1, L.ORT_ENABLE_EXTENDED),
        "1 thread, BASIC": lambda: session_options(1, L.ORT_ENABLE_BASIC),
        "1 thread, ALL, denormals as zero": lambda: session_options(1, **{"session.set_denormal_as_zero": "1"}),
    }
    image, boxes, q_in = synthetic_frame(1)
    runners = {}
    for label, make in one.items():
        s = RefinerSession(path, session_options=make())
        runners[label] = (lambda s=s: s.refine(image, boxes, q_in, K=FRAME_K))
    out = {k: 1.0 / v for k, v in time_interleaved(runners, rounds, calls).items()}
    import os

    n = len(os.sched_getaffinity(0))
    if n > 1:
        two = {}
        for spin in ("1", "0"):
            s = RefinerSession(path, session_options=session_options(n, **{"session.intra_op.allow_spinning": spin}))
            two[f"{n} threads, ALL, spinning {'on' if spin == '1' else 'off'}"] = (
                lambda s=s: s.refine(image, boxes, q_in, K=FRAME_K))
        out.update({k: 1.0 / v for k, v in time_interleaved(two, rounds, calls).items()})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.int8_convs.study",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, help="rendered dataset (training crops calibrate, test crops score)")
    ap.add_argument("--run", type=Path, help="the build's run folder: RUN/<obj>/*.pt")
    ap.add_argument("--heldout", type=Path, help="instead of --data/--run: rendered scenes no model trained on, every "
                    "instance scored (export/release/coarse.py requantize --heldout)")
    ap.add_argument("--calibration", type=Path, help="with --heldout: other such scenes, every instance calibrates")
    ap.add_argument("--cache", type=Path, help="crop cache (default DATA/.crops or HELDOUT/.crops)")
    ap.add_argument("--objects", help="comma-separated YCB ids (default: every shipped object)")
    ap.add_argument("--candidates", help="semicolon-separated candidate names (default: all)")
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--skip-accuracy", action="store_true", help="only speed and profile")
    ap.add_argument("--skip-speed", action="store_true", help="only accuracy (the speed keys of --json are kept)")
    ap.add_argument("--json", type=Path, help="the results file (required unless --report); a rerun updates it")
    ap.add_argument("--report", type=Path, metavar="JSON", help="print the Markdown tables of this results file "
                    "(what the README quotes) and stop")
    args = ap.parse_args(argv)
    if args.report is not None:
        if not args.report.is_file():
            ap.error(f"--report: no such file: {args.report}")
        print(report(json.loads(args.report.read_text())))
        return 0
    if args.json is None:
        ap.error("--json is required (unless --report)")
    from export.quantize import dataset_calibration
    from export.release.coarse import evaluate, evaluate_fresh, scoring_mode
    from models.data.pipeline import whole_folder_spec

    fresh = scoring_mode(ap, args)
    cache = args.cache or (args.heldout if fresh else args.data) / ".crops"
    objects = args.objects.split(",") if args.objects else [m.object_id for m in pretrained_models()]
    names = [n.strip() for n in args.candidates.split(";")] if args.candidates else list(CANDIDATES)
    unknown = [n for n in names if n not in CANDIDATES]
    if unknown:
        ap.error(f"unknown candidates {unknown}; known: {list(CANDIDATES)}")
    t_start = time.perf_counter()
    # A rerun with --skip-speed or --skip-accuracy updates its own keys of an existing file and keeps the rest.
    doc = json.loads(args.json.read_text()) if args.json.is_file() else {}
    command = "python -m benchmarks.studies.int8_convs.study " + " ".join(
        a if not a.startswith("/") else Path(a).name for a in (argv or sys.argv[1:]))
    doc.update({"schema": "refiner-rt/study-int8-convs/1", "candidates": {k: [v[0], v[1]] for k, v in CANDIDATES.items()}})
    doc.setdefault("objects", {})
    doc.setdefault("runs", []).append({"command": command, "machine": machine_info(),
                                       "started": time.strftime("%Y-%m-%d %H:%M:%S")})
    with tempfile.TemporaryDirectory(prefix="int8-convs-") as work:
        work = Path(work)
        paths_by_object = {}
        for obj in objects if not args.skip_accuracy else objects[:1]:
            fp32 = WEIGHTS_DIR / model_file_name(obj, int8=False)
            contract = parse_metadata({p.key: p.value for p in onnx.load(str(fp32), load_external_data=False).metadata_props})
            t0 = time.perf_counter()
            if fresh:
                cal = dataset_calibration(args.calibration, contract, cache_root=cache,
                                          spec=whole_folder_spec(args.calibration, obj, "train_base"))
            else:
                cal = dataset_calibration(args.data, contract, cache_root=cache)
            print(f"[{obj}] calibration: {len(cal.images)} training crops in {time.perf_counter() - t0:.0f} s", flush=True)
            paths = {}
            for i, name in enumerate(names):
                paths[name] = build_candidate(fp32, work / f"{obj}.{i}.onnx", name, cal)
            paths_by_object[obj] = paths
            entry = doc["objects"].setdefault(obj, {})
            entry["sizes_bytes"] = {n: p.stat().st_size for n, p in paths.items()}
            if not args.skip_accuracy:
                t0 = time.perf_counter()
                if fresh:
                    ev = evaluate_fresh(paths, obj, args.heldout, cache, contract.rotation_frame, contract.input_size,
                                        contract.crop_context)
                else:
                    ev = evaluate(paths, sorted((args.run / obj).glob("*.pt"))[0], args.data, cache)
                fp = ev["fp32"]["all"]["mean_deg"] if "fp32" in ev else None
                entry["accuracy"] = {n: {"mean_deg": ev[n]["all"]["mean_deg"], "median_deg": ev[n]["all"]["median_deg"],
                                         "delta_vs_fp32_deg": None if fp is None else ev[n]["all"]["mean_deg"] - fp,
                                         "n": ev[n]["all"]["n"]} for n in paths}
                print(f"[{obj}] accuracy in {time.perf_counter() - t0:.0f} s: " + ", ".join(
                    f"{n} {a['mean_deg']:.3f}" for n, a in entry["accuracy"].items()), flush=True)
        if not args.skip_speed:
            # Speed and profile on the first object (every shipped model has the same graph, so the same speed),
            # beside the paper's shallow network (random weights: speed does not depend on them).
            speed(doc, {**paths_by_object[objects[0]], **shallow_models(work)}, args.rounds)
    doc["runs"][-1]["wall_s"] = time.perf_counter() - t_start
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {args.json} ({doc['runs'][-1]['wall_s']:.0f} s)")
    return 0


def speed(doc: dict, first: dict, rounds: int) -> None:
    """Optimised graphs, profiles, refine() speed and session options of one object's candidates, into ``doc``."""
    doc["optimized_graph_ops"] = {n: optimized_ops(p) for n, p in first.items()}
    doc["profile"] = {n: profile_ops(p) for n, p in first.items()}
    for n, prof in doc["profile"].items():
        top = ", ".join(f"{op} {us:.0f}" for op, us in list(prof["us_per_call_by_op"].items())[:5])
        print(f"profile {n}: kernels {prof['kernel_us_per_call']:.0f} us/call ({top})", flush=True)
    doc["refine_per_s_1_thread"] = refine_speed(first, rounds=rounds)
    base = doc["refine_per_s_1_thread"].get(BASE)
    paper = doc["refine_per_s_1_thread"].get("paper shallow, dynamic-int8")
    for n, v in doc["refine_per_s_1_thread"].items():
        print(f"speed {n}: {v:,.0f}/s ({v / base:.2f}x the first shipped files, {v / paper:.2f}x paper shallow INT8)", flush=True)
    best = max((n for n in first if n != "fp32" and not n.startswith(("paper", "default"))),
               key=doc["refine_per_s_1_thread"].get)
    conv = "qdq conv>=16 + large FC dynamic (7-bit)"
    if conv in first:
        doc["propagation"] = propagation_speed(first[conv], rounds=rounds)
        for k, v in doc["propagation"]["run_us"].items():
            print(f"{conv}, {k}: session.run {v:.1f} us", flush=True)
    doc["options_model"] = best
    doc["options_per_s"] = option_speed(first[best], rounds=rounds)
    for k, v in doc["options_per_s"].items():
        print(f"options ({best}) {k}: {v:,.0f}/s", flush=True)


def report(doc: dict) -> str:
    """Markdown tables of a results file (what the README quotes)."""
    out = []
    objs = doc.get("objects", {})
    names = [n for n in [_OLD_BASE, *CANDIDATES] if any(n in o.get("accuracy", {}) for o in objs.values())]
    if names:
        out += ["| candidate | " + " | ".join(objs) + " | mean cost | largest cost |",
                "|---|" + "---:|" * (len(objs) + 2)]
        for n in names:
            costs = [objs[o]["accuracy"][n]["delta_vs_fp32_deg"] for o in objs if n in objs[o].get("accuracy", {})]
            cells = [f"{objs[o]['accuracy'][n]['mean_deg']:.3f} ({objs[o]['accuracy'][n]['delta_vs_fp32_deg']:+.3f})"
                     if n in objs[o].get("accuracy", {}) else "" for o in objs]
            out.append(f"| {n} | " + " | ".join(cells) + f" | {np.mean(costs):+.3f} | {max(costs):+.3f} |")
        out.append("")
    speed = doc.get("refine_per_s_1_thread", {})
    if speed:
        base, paper = speed.get(BASE) or speed.get(_OLD_BASE), speed.get("paper shallow, dynamic-int8")
        out += ["| model | refine()/s, 1 thread | over the first shipped files | over paper shallow INT8 | kernel us/call "
                "(profiler) | top operators (us/call) |", "|---|---:|---:|---:|---:|---|"]
        for n, v in speed.items():
            prof = doc.get("profile", {}).get(n, {})
            top = ", ".join(f"{op} {us:.0f}" for op, us in list(prof.get("us_per_call_by_op", {}).items())[:6])
            out.append(f"| {n} | {v:,.0f} | {v / base:.2f}x | {v / paper:.2f}x | {prof.get('kernel_us_per_call', 0):.0f} "
                       f"| {top} |")
        out.append("")
    prop = doc.get("propagation")
    if prop:
        out += ["| qdq conv>=16 + large FC dynamic (7-bit), bare session.run | us/call | kernel us/call (profiler) | "
                "top operators (us/call) |", "|---|---:|---:|---|"]
        for k, v in prop["run_us"].items():
            pr = prop["profile"][k]
            top = ", ".join(f"{op} {us:.0f}" for op, us in list(pr["us_per_call_by_op"].items())[:6])
            out.append(f"| {k} | {v:.1f} | {pr['kernel_us_per_call']:.0f} | {top} |")
        out.append("")
    opts = doc.get("options_per_s", {})
    if opts:
        out += [f"Session options ({doc.get('options_model')}):", "", "| options | refine()/s |", "|---|---:|"]
        out += [f"| {k} | {v:,.0f} |" for k, v in opts.items()]
        out.append("")
    graphs = doc.get("optimized_graph_ops", {})
    if graphs:
        out += ["| candidate | operators onnxruntime runs (level ALL) |", "|---|---|"]
        out += [f"| {n} | " + ", ".join(f"{k} {v}" for k, v in sorted(ops.items())) + " |" for n, ops in graphs.items()]
    return "\n".join(out)


if __name__ == "__main__":
    raise SystemExit(main())
