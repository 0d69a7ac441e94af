"""Time per frame: the nine objects of one 640x480 frame, each refined by its own shipped model, on one core and on
all cores.

What robot code with one refiner per object pays per camera frame: for each of the nine objects, ``refine()`` of
its box with its own model (crop by the crop rule, network, composition, the frame's K for the viewing-ray frame),
batch 1, one iteration. Models of different objects cannot share a batch, so a frame is nine calls. Timed ways:

* ``one core``: one thread, the nine calls one after the other (sessions with ``threads=1``);
* ``all cores, objects in parallel``: a pool of one worker thread per core, each with single-threaded sessions,
  the nine calls spread over the workers (onnxruntime and OpenCV release the GIL while they compute);
* ``all cores, threads per call``: the nine calls one after the other, each session on every core (worker spinning
  off: nine sessions' spinning pools fought over the cores, 14-19 ms per frame on 2 cores).

The ways are measured interleaved (round by round, frames of each way in turn, with a 50 ms pause before each way
so that the previous one's spinning onnxruntime workers have parked) and the figure is the median frame time. Where fewer than nine objects ship, the missing ones are refined by copies of shipped models (a separate
session each, as a real object's would be; every shipped model has the same architecture, so the same speed) and
the output says so.

    python -m benchmarks.frame_speed --json benchmarks/results/frame_speed/frame_speed.json
    python -m benchmarks.frame_speed --model-dir DIR      # DIR/<obj>.int8.onnx instead of the shipped files
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from refiner_rt import RefinerSession
from export.bench import machine_info
from refiner_rt.bench import FRAME_K, synthetic_frame
from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name, pretrained_models
from refiner_rt.session import available_cores, default_session_options

PAUSE_S = 0.05  # between ways, in every round (see the loop)
PAPER_OBJECTS = ("002_master_chef_can", "003_cracker_box", "004_sugar_box", "006_mustard_bottle", "009_gelatin_box",
                 "011_banana", "021_bleach_cleanser", "035_power_drill", "037_scissors")


def frame_models(model_dir: Path | None, int8: bool) -> tuple[dict, dict]:
    """``({object: model path}, {object: the object whose model stands in for it})`` for the nine paper objects.

    From ``model_dir`` (``<obj>.int8.onnx`` / ``<obj>.onnx``) when given, else the shipped models; objects without a
    model get one of the available ones, in turn.
    """
    folder = model_dir or WEIGHTS_DIR
    if model_dir is None:
        have = [m.object_id for m in pretrained_models() if m.files.get("int8" if int8 else "fp32")]
    else:
        have = [o for o in PAPER_OBJECTS if (folder / model_file_name(o, int8)).is_file()]
    if not have:
        raise SystemExit(f"no {'INT8' if int8 else 'fp32'} model found in {folder}")
    paths, stand_in = {}, {}
    for i, obj in enumerate(PAPER_OBJECTS):
        src = obj if obj in have else have[i % len(have)]
        if src != obj:
            stand_in[obj] = src
        paths[obj] = folder / model_file_name(src, int8)
    return paths, stand_in


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model-dir", type=Path, help="folder of <obj>.int8.onnx / <obj>.onnx (default: the shipped models)")
    ap.add_argument("--fp32", action="store_true", help="the fp32 models instead of INT8")
    ap.add_argument("--rounds", type=int, default=9, help="interleaved rounds")
    ap.add_argument("--frames", type=int, default=50, help="frames per way and round")
    ap.add_argument("--json", type=Path, help="write the result here")
    args = ap.parse_args(argv)

    paths, stand_in = frame_models(args.model_dir, int8=not args.fp32)
    cores = available_cores()
    image, boxes, q_in = synthetic_frame(len(PAPER_OBJECTS), seed=3)
    objects = list(paths)
    one = {o: RefinerSession(paths[o], threads=1) for o in objects}
    own = {o: RefinerSession(paths[o], threads=1) for o in objects}  # the parallel way's: no session shared by ways
    # Worker spinning off: nine sessions each with a spinning pool fight over the cores between their calls (14-19 ms
    # per frame on 2 cores, and they slowed the other ways measured beside them).
    no_spin = {"session.intra_op.allow_spinning": "0"}
    every = {o: RefinerSession(paths[o], session_options=default_session_options(cores, **no_spin)) for o in objects}
    schemes = sorted({s.contract.quantization for s in one.values()})

    def call(sessions, i):
        s = sessions[objects[i]]
        return s.refine(image, boxes[i : i + 1], q_in[i : i + 1], K=FRAME_K if s.contract.rotation_frame == "ray" else None)

    def sequential(sessions):
        for i in range(len(objects)):
            call(sessions, i)

    pool = ThreadPoolExecutor(max_workers=cores)
    chunks = [list(range(w, len(objects), cores)) for w in range(cores)]

    def parallel():
        list(pool.map(lambda idx: [call(own, i) for i in idx], chunks))

    ways = {"one core": lambda: sequential(one)}
    if cores > 1:
        ways["all cores, objects in parallel"] = parallel
        ways["all cores, threads per call (spinning off)"] = lambda: sequential(every)
    for fn in ways.values():  # warm-up
        for _ in range(10):
            fn()
    times = {k: [] for k in ways}
    for _ in range(args.rounds):
        for k, fn in ways.items():
            # The previous way's onnxruntime workers spin for a while after its last call; let them park first, so
            # that they do not take the core from this way's first frames.
            time.sleep(PAUSE_S)
            for _ in range(args.frames):
                t0 = time.perf_counter()
                fn()
                times[k].append(time.perf_counter() - t0)
    pool.shutdown()
    result = {k: {"median_ms": 1e3 * statistics.median(v), "p90_ms": 1e3 * float(np.percentile(v, 90)),
                  "frames": len(v)} for k, v in times.items()}
    meta = one[objects[0]].contract
    doc = {
        "schema": "refiner-rt/frame-speed/1",
        "objects": objects,
        "stand_ins": stand_in,
        "models": "shipped" if args.model_dir is None else "from --model-dir",
        "precision": "fp32" if args.fp32 else "int8",
        "quantization": schemes,
        "arch": meta.arch,
        "cores": cores,
        "result": result,
        "target_ms_one_core": 2.0,
        "machine": machine_info(),
        "command": "python -m benchmarks.frame_speed " + " ".join(
            Path(a).name if a.startswith("/") else a for a in (argv if argv is not None else sys.argv[1:])),
        "rounds": args.rounds,
        "frames_per_round": args.frames,
    }
    if stand_in:
        print(f"{len(stand_in)} of the 9 objects have no {'fp32' if args.fp32 else 'INT8'} model here: refined by copies "
              f"of shipped models (own sessions): " + ", ".join(f"{o} <- {s}" for o, s in stand_in.items()))
    print(f"Nine objects of one 640x480 frame, each its own {meta.arch} model ({', '.join(schemes)}), batch 1 per "
          f"object; {doc['machine']['cpu']}, flags {' '.join(doc['machine']['cpu_flags'])}; medians of "
          f"{args.rounds} interleaved rounds x {args.frames} frames:")
    for k, r in result.items():
        print(f"  {k}: {r['median_ms']:.2f} ms per frame (p90 {r['p90_ms']:.2f}), {1e3 / r['median_ms']:.0f} frames/s")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
