"""Tracking on rendered video: each frame refined from the previous frame's result, against the paper's per-frame use.

A *sequence* is one object along one rendered camera path (``refiner-rt render --frames-per-scene 100``: a still
tabletop seen by a camera sweeping 60-180 degrees of azimuth). On every sequence and at frame steps 1, 2 and 4 (every
frame, every 2nd, every 4th: larger motion between updates), four estimates are scored against the ground truth:

* ``hold``: the initial coarse pose, drawn U(0, 30) degrees around the truth of the first frame, never updated;
* ``per_frame``: the paper's setting, every frame refined once from a fresh coarse pose drawn U(0, 30) around its truth;
* ``track``: :class:`refiner_rt.tracker.RefinerTracker` started from the ``hold`` pose, one refinement per frame,
  each from the previous frame's result;
* ``track_predict``: the same with the constant-angular-velocity prediction;
* ``track_redetect``: ``track`` with a detector's pose every ``--redetect`` frames (a slow detector and a fast
  tracker): :meth:`~refiner_rt.tracker.RefinerTracker.reset` to the same fresh draw ``per_frame`` refines there;
* ``track_lost``: ``track`` with the tracker's loss-of-track check (``lost_deg=--lost-deg``: a second refinement
  of each refined rotation; an object it moves by more than that is lost) and the detector asked only then, for the
  same fresh draw ``per_frame`` refines on that frame. Its re-detection rate is reported (detector poses per
  refined object and frame).
* ``track_fuse``: ``track`` with a detector's pose every ``--fuse-every`` frames (default every frame: the same
  fresh draw ``per_frame`` refines), refined beside the track and fused with it
  (``RefinerTracker(detector_weight=--detector-weight)``): the same detector input as ``per_frame`` at twice its
  network passes.

* ``per_frame_cascade`` and ``track_cascade`` (``--methods``; they need every object's fine refiner): ``per_frame``
  and ``track`` with :class:`refiner_rt.RefinerCascade` in place of the coarse refiner (the tracker runs the coarse
  refiner, then the fine one, on every update); ``--settle-deg`` gives their cascades ``settle_deg`` (a second coarse
  pass on the rows that go the long way, kept where it turns the result by more than that).
* ``track_scene`` and ``track_cascade_scene``: ``track`` and ``track_cascade`` with the scene's motion
  (``RefinerTracker(predict="scene")``, its defaults or ``--motion-window``, ``--prediction-weight`` and
  ``--max-correction-deg``): the camera's turn, estimated from every tracked object of the scene (they stand still),
  turns each track before its update and carries hidden objects through their occlusions.

Coarse poses follow docs/design.md §1 (``q_in = q_gt * q_noise``, uniform axis). A frame where the object's BOP
``visib_fract`` is below ``--min-visib`` gives the tracker no box (a missed detection) and is not scored. All objects
of a scene are tracked by one tracker, each with its own shipped model, one ``update()`` per frame. Reported per method
and step: mean error over all scored frames, the mean error at each sequence's last scored frame, the share of
sequences that diverge (error above 30 degrees at any scored frame), and the cost of an update; the plot shows the mean
error against the frame index since the track began.

Usage (from the repository root; the data is rendered with a seed no shipped model trained on)::

    refiner-rt render --out data/tracking_s555 --frames 7000 --frames-per-scene 100 --seed 555 --workers 2 \\
        --layout tabletop
    python -m benchmarks.tracking --data data/tracking_s555 --json benchmarks/results/tracking/tracking.json \\
        --plot benchmarks/results/tracking/tracking.png

``--model OBJ=FILE.onnx`` measures an ONNX file in place of a shipped model (default: every shipped model).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from models.evaluate.tracking import (CASCADE_METHODS, CASCADE_VIEWS, DIVERGED_DEG, LABELS, METHODS, TRACKERS,
                                      cpu_record, curve, load_sequences, report, run_scene, summarise, write_detections)
from refiner_rt.metadata import file_sha256
from refiner_rt.session import RefinerSession
from refiner_rt.tracker import DEFAULT_MOTION_WINDOW, DEFAULT_SCENE_MAX_CORRECTION_DEG, DEFAULT_SCENE_PREDICTION_WEIGHT


def plot(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = doc["steps"]
    fig, axes = plt.subplots(2, len(steps), figsize=(4.6 * len(steps), 6.6), sharey="row", squeeze=False)
    colours = {"hold": "0.6", "per_frame": "tab:blue", "track": "tab:red", "track_predict": "tab:orange",
               "track_redetect": "tab:green", "track_lost": "tab:purple", "track_fuse": "tab:brown",
               "track_scene": "tab:pink", "per_frame_cascade": "tab:cyan", "track_cascade": "black",
               "track_cascade_scene": "tab:olive"}
    for row, (key, stat) in enumerate((("curves", "mean"), ("curves_median", "median"))):
        for ax, step in zip(axes[row], steps):
            for m in [m for m in METHODS if m in doc[key]]:
                y = np.array([np.nan if v is None else v for v in doc[key][m][str(step)]])
                x = np.arange(len(y))
                ok = ~np.isnan(y)
                every = doc.get("fuse_every", 1) if m == "track_fuse" else doc["redetect"]
                label = LABELS[m].replace("every N frames", "every frame" if every == 1 else f"every {every} frames")
                ax.plot(x[ok], y[ok], color=colours[m], label=label, lw=1.3, ls="--" if m == "track_predict" else "-")
            if row == 0:
                ax.set_title({1: "step 1 (every frame)", 2: "step 2 (every 2nd frame)"}.get(
                    step, f"step {step} (every {step}th frame)"))
            else:
                ax.set_xlabel("frames since the track began")
            ax.set_ylim(0, 40 if row == 0 else 20)
            ax.grid(alpha=0.3)
        axes[row][0].set_ylabel(f"{stat} rotation error (deg)")
    axes[0][-1].legend(fontsize=7, loc="upper right")
    n = doc["summary"]["hold"][str(steps[0])]["sequences"]
    fig.suptitle(f"Tracking on rendered video: {n} sequences, {', '.join(doc['objects'])}", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)

def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, help="rendered BOP folder (refiner-rt render --out)")
    p.add_argument("--report", type=Path, metavar="JSON", help="print the Markdown table of a results file and exit")
    p.add_argument("--objects", help="comma-separated YCB ids (default: every object with a shipped model)")
    p.add_argument("--model", action="append", default=[], metavar="OBJ=FILE",
                   help="an ONNX file to measure for an object instead of its shipped model (repeatable)")
    p.add_argument("--fp32", action="store_true", help="the shipped fp32 models instead of INT8")
    p.add_argument("--steps", default="1,2,4", help="frame steps (default 1,2,4)")
    p.add_argument("--min-visib", type=float, default=0.3, help="BOP visib_fract below which a frame has no box")
    p.add_argument("--min-frames", type=int, default=20, help="leave out sequences with fewer visible frames")
    p.add_argument("--scenes", type=int, default=0, help="use only the first N scenes (0: all)")
    p.add_argument("--seed", type=int, default=0, help="seed of the coarse poses")
    p.add_argument("--methods", default=",".join(m for m in METHODS if m not in CASCADE_METHODS),
                   help=f"what to measure, of {','.join(METHODS)} (default: all but {', '.join(CASCADE_METHODS)}, which "
                   "need every object's fine refiner)")
    p.add_argument("--redetect", type=int, default=10,
                   help="track_redetect: frames between a detector's poses (default 10, e.g. 3 Hz in 30 Hz video)")
    p.add_argument("--lost-deg", type=float, default=1.5,
                   help="track_lost: the tracker's lost_deg (degrees a second refinement may move a rotation; default 1.5)")
    p.add_argument("--detector-weight", type=float, default=0.5,
                   help="track_fuse: the tracker's detector_weight (the refined detection's share; default 0.5)")
    p.add_argument("--fuse-every", type=int, default=1,
                   help="track_fuse: updates between a detector's poses (default 1: every update)")
    p.add_argument("--settle-deg", type=float, default=None, metavar="DEG",
                   help="the cascade methods: RefinerCascade(settle_deg=DEG), a second coarse pass on the rows that go "
                        "the long way, kept where it turns the result by more than DEG (default: off)")
    p.add_argument("--motion-window", type=int, default=None, metavar="N",
                   help="the _scene methods: RefinerTracker(motion_window=N), updates over which each track's change is "
                        "measured (default 4, the tracker's)")
    p.add_argument("--prediction-weight", type=float, default=None, metavar="W",
                   help="the _scene methods: RefinerTracker(prediction_weight=W), the prediction's share kept in each "
                        "new rotation, in [0, 1) (default: the tracker's, 0.3 with the scene's motion)")
    p.add_argument("--max-correction-deg", type=float, default=None, metavar="DEG",
                   help="the _scene methods: RefinerTracker(max_correction_deg=DEG), the most a new rotation may differ "
                        "from the scene's prediction, in (0, 180] (default: the tracker's, 2)")
    p.add_argument("--json", type=Path, help="write the results here")
    p.add_argument("--plot", type=Path, help="write the error-vs-frame plot here (PNG)")
    p.add_argument("--detections-out", type=Path, metavar="DIR",
                   help="also write DIR/<scene>.json, each scene's boxes and initial coarse poses as a "
                        "`refiner-rt track` detections file")
    args = p.parse_args(argv)
    if args.report:
        print(report(json.loads(args.report.read_text())))
        return 0
    steps = [int(v) for v in args.steps.split(",")]
    if args.data is None or not args.data.is_dir():
        p.error(f"--data {args.data}: no such folder")
    methods = tuple(m for m in METHODS if m in args.methods.split(","))
    if set(args.methods.split(",")) - set(METHODS) or "hold" not in methods:
        p.error(f"--methods must list some of {','.join(METHODS)}, hold included; got {args.methods!r}")
    if not 0 < args.lost_deg <= 180:
        p.error(f"--lost-deg must be in (0, 180] degrees; got {args.lost_deg}")
    if not 0 < args.detector_weight <= 1:
        p.error(f"--detector-weight must be in (0, 1]; got {args.detector_weight}")
    if args.fuse_every < 1:
        p.error(f"--fuse-every must be a positive integer; got {args.fuse_every}")
    if args.motion_window is not None and args.motion_window < 2:
        p.error(f"--motion-window must be an integer >= 2 (updates); got {args.motion_window}")
    scene_options = [f"--{k.replace('_', '-')}" for k in ("motion_window", "prediction_weight", "max_correction_deg")
                     if getattr(args, k) is not None]
    if scene_options and not any(m.endswith("_scene") for m in methods):
        p.error(f"{', '.join(scene_options)} apply to the _scene methods (track_scene, track_cascade_scene); "
                "--methods has neither")
    if args.max_correction_deg is not None and not 0 < args.max_correction_deg <= 180:
        p.error(f"--max-correction-deg must be in (0, 180] degrees; got {args.max_correction_deg}")
    if args.prediction_weight is not None and not 0 <= args.prediction_weight < 1:
        p.error(f"--prediction-weight must be in [0, 1); got {args.prediction_weight}")
    if any(s < 1 for s in steps):
        p.error(f"--steps must be positive integers; got {args.steps!r}")

    from refiner_rt.pretrained import pretrained_models

    files = {}
    for spec in args.model:
        obj, _, path = spec.partition("=")
        if not path or not Path(path).is_file():
            p.error(f"--model expects OBJ=FILE.onnx with an existing file; got {spec!r}")
        files[obj] = Path(path)
    shipped = {m.object_id: m for m in pretrained_models()}
    objects = [o.strip() for o in args.objects.split(",")] if args.objects else sorted(set(shipped) | set(files))
    missing = [o for o in objects if o not in files and o not in shipped]
    if missing or not objects:
        p.error(f"no model for {missing or 'any object'}: shipped {sorted(shipped)}; give --model OBJ=FILE.onnx")
    cascades = {}
    if any(m in CASCADE_METHODS for m in methods):
        from refiner_rt import RefinerCascade

        no_fine = [o for o in objects if o not in shipped or "fine" not in shipped[o].stages]
        if no_fine:
            p.error(f"{', '.join(CASCADE_METHODS)} need each object's fine refiner; none ships for {no_fine}")
        try:
            cascades = {o: RefinerCascade.pretrained(o, int8=not args.fp32, threads=1, settle_deg=args.settle_deg)
                        for o in objects}
        except ValueError as e:  # a bad --settle-deg, as RefinerCascade words it
            p.error(f"--settle-deg: {e}")
    elif args.settle_deg is not None:
        p.error(f"--settle-deg applies to {', '.join(CASCADE_METHODS)} only; --methods has neither")
    sessions, model_record = {}, {}
    for o in objects:
        if o in files:
            sessions[o] = RefinerSession(files[o], threads=1, object_id=o)
            model_record[o] = {"file": str(files[o]), "sha256": file_sha256(files[o])}
        else:
            sessions[o] = RefinerSession.pretrained(o, int8=not args.fp32, threads=1)
            model_record[o] = {"file": shipped[o].files["fp32" if args.fp32 else "int8"], "version": shipped[o].version,
                               "heldout_mean_deg": shipped[o].heldout.get("mean_deg"),
                               "sha256": file_sha256(shipped[o].path(int8=not args.fp32))}
            if o in cascades:
                fine = shipped[o].path(int8=not args.fp32, stage="fine")
                model_record[o]["fine"] = {"file": fine.name, "sha256": file_sha256(fine)}

    machine = cpu_record()
    seqs, notes = load_sequences(args.data, set(objects), args.min_visib, args.min_frames)
    scenes = sorted({s.scene for s in seqs})
    if args.scenes:
        scenes = scenes[: args.scenes]
        seqs = [s for s in seqs if s.scene in scenes]
    if not seqs:
        p.error(f"no sequence of {objects} in {args.data} with >= {args.min_frames} frames at visib >= {args.min_visib}")
    n_frames = max(max(s.images) for s in seqs) + 1
    timing = defaultdict(lambda: {"seconds": 0.0, "cpu_seconds": 0.0, "updates": 0, "refinements": 0})
    detections: dict[str, int] = {}  # method_step -> detector poses used after each track's start
    errors = {m: {st: [] for st in steps} for m in methods}
    per_sequence = []  # step 1 (the first step), one row per sequence: its mean and largest error per method
    per_object = {m: {st: defaultdict(list) for st in steps} for m in methods}
    t_start = time.perf_counter()
    for i, scene in enumerate(scenes):
        scene_seqs = [s for s in seqs if s.scene == scene]
        res = run_scene(scene_seqs, sessions, steps, args.seed, n_frames, timing, methods, args.redetect,
                        args.lost_deg, detections, args.detector_weight, args.fuse_every, cascades,
                        args.motion_window, args.prediction_weight, args.max_correction_deg)
        for s in scene_seqs:
            if s.object_id in res["hold"][steps[0]]:
                row = {"scene": scene, "object": s.object_id, "frames": len(s.images)}
                for m in methods:
                    e = res[m][steps[0]][s.object_id]
                    row[m] = {"mean_deg": round(float(np.nanmean(e)), 2), "max_deg": round(float(np.nanmax(e)), 2)}
                per_sequence.append(row)
        if args.detections_out:
            write_detections(scene_seqs, args.seed, args.detections_out / f"{scene}.json")
        for m in methods:
            for st in steps:
                for obj, e in res[m][st].items():
                    errors[m][st].append(e)
                    per_object[m][st][obj].append(e)
        print(f"scene {scene} ({i + 1}/{len(scenes)}): {len(scene_seqs)} sequences, "
              f"{time.perf_counter() - t_start:.0f} s", file=sys.stderr)

    summary = {m: {str(st): summarise(errors[m][st]) for st in steps} for m in methods}
    if "per_frame" in methods:  # per sequence: does the method's mean beat refining each frame from a fresh pose?
        for m in methods:
            for st in steps:
                better = [np.nanmean(a) < np.nanmean(b) for a, b in zip(errors[m][st], errors["per_frame"][st])]
                summary[m][str(st)]["beats_per_frame_share"] = round(float(np.mean(better)), 4)
    for m in TRACKERS:
        for st in steps:
            if m in methods:  # detector poses per scored frame after the start (per_frame: one on every frame)
                summary[m][str(st)]["detector_share"] = round(
                    detections.get(f"{m}_step{st}", 0) / summary[m][str(st)]["frames"], 4)
    for m in ("per_frame", "per_frame_cascade"):
        for st in steps if m in methods else []:
            summary[m][str(st)]["detector_share"] = 1.0
    objects_table = {m: {str(st): {o: summarise(v) for o, v in sorted(per_object[m][st].items())} for st in steps}
                     for m in methods}
    # CPU time of this process (threads=1: the network's own time) is the cost; wall time also counts the waits
    # for cores that other processes held, which on a shared machine can be most of it.
    cost = {}
    for key, t in sorted(timing.items()):
        cost[key] = {"cpu_ms_per_update": round(1e3 * t["cpu_seconds"] / t["updates"], 4) if t["updates"] else None,
                     "cpu_ms_per_refinement": round(1e3 * t["cpu_seconds"] / t["refinements"], 4)
                     if t["refinements"] else None,
                     "wall_ms_per_update": round(1e3 * t["seconds"] / t["updates"], 4) if t["updates"] else None,
                     **{k: (round(v, 3) if isinstance(v, float) else v) for k, v in t.items()}}
    machine["load_average_1min_at_end"] = round(os.getloadavg()[0], 2)
    render = args.data / "render_config.json"
    render_record = json.loads(render.read_text()) if render.is_file() else {}
    doc = {
        "format": "refiner-rt/bench/tracking/1",
        "command": shlex.join(["python", "-m", "benchmarks.tracking", *(sys.argv[1:] if argv is None else argv)]),
        "measured": (f"{len(seqs)} sequences ({len(scenes)} rendered scenes of up to {n_frames} frames, seed "
                     f"{render_record.get('seed', '?')}, camera sweep {render_record.get('config', {}).get('sweep_deg')} "
                     f"deg of azimuth per scene) of {len(objects)} object(s); frames with visib_fract >= "
                     f"{args.min_visib} scored, sequences with >= {args.min_frames} such frames; coarse poses U(0, 30) deg "
                     f"around the truth, seed {args.seed}; one network pass per object and update (track_lost: two, and one more "
                     f"per detector pose; track_fuse: one more per detector pose; the cascade: {CASCADE_VIEWS[0]} "
                     f"coarse views and {CASCADE_VIEWS[1]} fine views, {CASCADE_VIEWS[1]} more where it goes through "
                     f"the coarse refiner, as the trackers always do), threads=1"),
        "cascade_views": {"coarse": CASCADE_VIEWS[0], "fine": CASCADE_VIEWS[1]},
        "data": str(args.data), "render_seed": render_record.get("seed"), "scenes": len(scenes),
        "sequences_per_object": {o: len(v) for o, v in sorted(per_object["hold"][steps[0]].items())},
        "left_out_too_short": notes["too_short"], "objects": objects, "models": model_record, "steps": steps,
        "min_visib": args.min_visib, "diverged_above_deg": DIVERGED_DEG, "seed": args.seed, "redetect": args.redetect,
        "lost_deg": args.lost_deg, "detector_weight": args.detector_weight, "fuse_every": args.fuse_every,
        "settle_deg": args.settle_deg,
        "motion_window": DEFAULT_MOTION_WINDOW if args.motion_window is None else args.motion_window,
        "prediction_weight": (DEFAULT_SCENE_PREDICTION_WEIGHT if args.prediction_weight is None
                              else args.prediction_weight),
        "max_correction_deg": (DEFAULT_SCENE_MAX_CORRECTION_DEG if args.max_correction_deg is None
                               else args.max_correction_deg),
        "summary": summary, "per_object": objects_table, "per_sequence_first_step": per_sequence,
        "curves": {m: {str(st): curve(errors[m][st]) for st in steps} for m in methods},
        "curves_median": {m: {str(st): curve(errors[m][st], np.median) for st in steps} for m in methods},
        "cost": cost, "machine": machine, "wall_s": round(time.perf_counter() - t_start, 1),
    }
    for st in steps:
        row = "  ".join(f"{m} {summary[m][str(st)]['mean_deg']:6.2f} (last {summary[m][str(st)]['last_frame_mean_deg']:5.2f}, "
                        f"div {100 * summary[m][str(st)]['diverged_share']:4.1f}%)" for m in methods)
        print(f"step {st}: {row}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=1) + "\n")
    if args.plot:
        plot(doc, args.plot)
    return 0

if __name__ == "__main__":
    raise SystemExit(main())
