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
    python benchmarks/tracking.py --data data/tracking_s555 --json benchmarks/results/tracking.json \\
        --plot benchmarks/results/tracking.png

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
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from refiner_rt import quaternion as rq  # noqa: E402
from refiner_rt.cascade import DEFAULT_COARSE_VIEWS, DEFAULT_FINE_VIEWS  # noqa: E402
from refiner_rt.metadata import file_sha256  # noqa: E402
from refiner_rt.session import RefinerSession  # noqa: E402
from refiner_rt.tracker import (  # noqa: E402
    DEFAULT_MOTION_WINDOW,
    DEFAULT_SCENE_MAX_CORRECTION_DEG,
    DEFAULT_SCENE_PREDICTION_WEIGHT,
    RefinerTracker,
)

METHODS = ("hold", "per_frame", "track", "track_predict", "track_redetect", "track_lost", "track_fuse",
           "track_scene", "per_frame_cascade", "track_cascade", "track_cascade_scene")
TRACKERS = ("track", "track_predict", "track_redetect", "track_lost", "track_fuse", "track_scene", "track_cascade",
            "track_cascade_scene")
# the views the cascades run with (RefinerCascade's defaults), recorded with the results
CASCADE_VIEWS = (DEFAULT_COARSE_VIEWS, DEFAULT_FINE_VIEWS)
CASCADE_METHODS = ("per_frame_cascade", "track_cascade", "track_cascade_scene")  # need every object's fine refiner
LABELS = {"hold": "(a) hold the initial coarse pose", "per_frame": "(b) refine each frame from U(0, 30)",
          "track": "(c) track from an initial U(0, 30)", "track_predict": "(c) + constant-velocity prediction",
          "track_redetect": "(c) + a detector's U(0, 30) pose every N frames",
          "track_lost": "(c) + loss-of-track check, detector only when lost",
          "track_fuse": "(c) + a detector's pose fused every N frames",
          "track_scene": "(c) + the scene's motion (a still scene, a moving camera)",
          "per_frame_cascade": "(b) with the cascade (coarse and fine refiners)",
          "track_cascade": "(c) with the cascade: coarse then fine on every update",
          "track_cascade_scene": "(c) with the cascade and the scene's motion"}
DIVERGED_DEG = 30.0


@dataclass
class Sequence:
    """One object along one scene's camera path: its scored frames, truth and boxes (frame id -> value)."""

    scene: str
    object_id: str
    K: np.ndarray
    q_gt: dict[int, np.ndarray] = field(default_factory=dict)  # (4,) wxyz object-to-camera
    boxes: dict[int, np.ndarray] = field(default_factory=dict)  # (4,) xyxy pixels
    images: dict[int, str] = field(default_factory=dict)


def load_sequences(data: Path, objects: set[str], min_visib: float, min_frames: int) -> tuple[list[Sequence], dict]:
    """The sequences of ``objects`` in a BOP folder, each with the frames where ``visib_fract >= min_visib``; those
    with fewer than ``min_frames`` such frames are left out (counted in the returned notes)."""
    from models.data import load_bop

    samples = load_bop(data, objects=sorted(objects), min_visib=min_visib)
    seqs: dict[tuple[str, str], Sequence] = {}
    for s in samples:
        key = (s.scene_id, s.obj_id)
        if key not in seqs:
            seqs[key] = Sequence(s.scene_id, s.obj_id, np.asarray(s.K))
        seq = seqs[key]
        seq.q_gt[s.frame_id] = rq.from_matrix(s.R)
        seq.boxes[s.frame_id] = np.asarray(s.box_xyxy, dtype=np.float64)
        seq.images[s.frame_id] = str(s.image_path)
    kept = [q for q in seqs.values() if len(q.q_gt) >= min_frames]
    return sorted(kept, key=lambda q: (q.scene, q.object_id)), {"too_short": len(seqs) - len(kept)}


def sequence_rng(seed: int, seq: Sequence) -> np.random.Generator:
    """A generator fixed by the run seed, the scene and the object (the same draws whatever else is measured)."""
    return np.random.default_rng([seed, int(seq.scene), sum(map(ord, seq.object_id))])


def run_scene(seqs: list[Sequence], sessions: dict[str, RefinerSession], steps: list[int], seed: int,
              n_frames: int, timing: dict, methods=METHODS, redetect: int = 10, lost_deg: float = 1.5,
              detections: dict | None = None, detector_weight: float = 0.5, fuse_every: int = 1,
              cascades: dict | None = None, motion_window: int | None = None, prediction_weight: float | None = None,
              max_correction_deg: float | None = None) -> dict:
    """Errors (degrees, NaN where not scored) per method, step and sequence, indexed by frames since the start."""
    rng = {s.object_id: sequence_rng(seed, s) for s in seqs}
    start_noise = {s.object_id: rq.sample_rotation_noise(1, "uniform", 0, 30, rng[s.object_id])[0] for s in seqs}
    frame_noise = {s.object_id: rq.sample_rotation_noise(n_frames, "uniform", 0, 30, rng[s.object_id]) for s in seqs}
    frames = sorted({f for s in seqs for f in s.images})
    # Every frame of the path from the first scored one is read (a frame with no scored object still counts as an
    # update without boxes, so the prediction knows how much time passed).
    any_path = Path(next(iter(seqs[0].images.values())))
    images = {f: cv2.imread(str(any_path.with_name(f"{f:06d}{any_path.suffix}")), cv2.IMREAD_COLOR)
              for f in range(frames[0], frames[-1] + 1)}
    missing = [f for f, im in images.items() if im is None]
    if missing:
        raise FileNotFoundError(f"{any_path.parent}: cannot read frames {missing[:5]}")
    K = seqs[0].K
    out = {m: {st: {} for st in steps} for m in methods}

    # (b) per frame, every visible frame once (each step scores its own frames from these).
    per_frame = {}
    for name in [m for m in ("per_frame", "per_frame_cascade") if m in methods]:
        refiners = sessions if name == "per_frame" else cascades
        for s in seqs:
            err = {}
            for f in sorted(s.images):
                q_in = rq.multiply(s.q_gt[f], frame_noise[s.object_id][f % n_frames])[None]
                t0, c0 = time.perf_counter(), time.process_time()
                res = refiners[s.object_id].refine(images[f], s.boxes[f][None], q_in, K=K)
                timing[name]["seconds"] += time.perf_counter() - t0
                timing[name]["cpu_seconds"] += time.process_time() - c0
                timing[name]["updates"] += 1
                timing[name]["refinements"] += 1
                err[f] = float(rq.geodesic_angle(res.q_refined[0], s.q_gt[f]))
            per_frame[name, s.object_id] = err

    for step in steps:
        grid = [f for f in range(frames[0], frames[-1] + 1) if f % step == 0]
        start = {s.object_id: next((f for f in grid if f in s.images), None) for s in seqs}
        live = [s for s in seqs if start[s.object_id] is not None]
        q_start = {s.object_id: rq.multiply(s.q_gt[start[s.object_id]], start_noise[s.object_id]) for s in live}
        for s in live:
            f0 = start[s.object_id]
            for m in methods:
                out[m][step][s.object_id] = np.full(n_frames, np.nan)
            for f in grid:
                if f >= f0 and f in s.images:
                    out["hold"][step][s.object_id][f - f0] = rq.geodesic_angle(q_start[s.object_id], s.q_gt[f])
                    for name in ("per_frame", "per_frame_cascade"):
                        if name in methods:
                            out[name][step][s.object_id][f - f0] = per_frame[name, s.object_id][f]
        for method in [m for m in TRACKERS if m in methods]:
            refiners = cascades if method in CASCADE_METHODS else sessions
            scene = method.endswith("_scene")
            tracker = RefinerTracker({s.object_id: refiners[s.object_id] for s in live}, K, {},
                                     predict="scene" if scene else method == "track_predict",
                                     motion_window=motion_window if scene else None,
                                     prediction_weight=prediction_weight if scene else None,
                                     max_correction_deg=max_correction_deg if scene else None,
                                     lost_deg=lost_deg if method == "track_lost" else None,
                                     detector_weight=detector_weight if method == "track_fuse" else None)
            key = f"{method}_step{step}"
            last_detection = {}
            for f in grid:
                for s in live:
                    if start[s.object_id] == f:
                        tracker.add(s.object_id, q_start[s.object_id])
                        last_detection[s.object_id] = f
                    elif (method == "track_redetect" and s.object_id in tracker and f in s.images
                          and f - last_detection[s.object_id] >= redetect):
                        # a detector's pose: the same fresh draw around the truth as per_frame's on this frame
                        tracker.reset(s.object_id, rq.multiply(s.q_gt[f], frame_noise[s.object_id][f % n_frames]))
                        last_detection[s.object_id] = f
                boxes = {s.object_id: s.boxes[f] for s in live if s.object_id in tracker and f in s.images}
                # a detector's pose (that frame's fresh draw): asked for only by track_lost's lost objects, or
                # fused by track_fuse every fuse_every updates after each track's start
                detector = None
                if method in ("track_lost", "track_fuse"):
                    detector = {s.object_id: rq.multiply(s.q_gt[f], frame_noise[s.object_id][f % n_frames])
                                for s in live if s.object_id in boxes and (method == "track_lost" or (
                                    f != start[s.object_id] and (f - start[s.object_id]) % (fuse_every * step) == 0))}
                t0, c0 = time.perf_counter(), time.process_time()
                before = tracker.redetections
                q = tracker.update(images[f], boxes, detector=detector)
                if detections is not None:
                    detections[key] = detections.get(key, 0) + tracker.redetections - before + (
                        sum(1 for s in live if s.object_id in boxes and last_detection.get(s.object_id) == f
                            and f != start[s.object_id])) + (len(detector) if method == "track_fuse" else 0)
                timing[key]["seconds"] += time.perf_counter() - t0
                timing[key]["cpu_seconds"] += time.process_time() - c0
                timing[key]["updates"] += 1
                timing[key]["refinements"] += len(q)
                for s in live:
                    if s.object_id in q:
                        out[method][step][s.object_id][f - start[s.object_id]] = rq.geodesic_angle(
                            q[s.object_id], s.q_gt[f])
    return out


def write_detections(seqs: list[Sequence], seed: int, path: Path) -> None:
    """A ``refiner-rt track`` detections file for one scene: every scored box, and at each object's first frame the
    initial coarse pose the benchmark tracks from (the same draw), so the command reproduces the ``track`` rows."""
    frames: dict[str, dict] = defaultdict(dict)
    for s in seqs:
        noise = rq.sample_rotation_noise(1, "uniform", 0, 30, sequence_rng(seed, s))[0]
        first = min(s.images)
        for f in sorted(s.images):
            box = [round(v, 3) for v in s.boxes[f].tolist()]
            name = Path(s.images[f]).name
            frames[name][s.object_id] = box if f != first else {
                "box": box, "q": rq.multiply(s.q_gt[f], noise).tolist()}
    doc = {"K": seqs[0].K.tolist(), "frames": dict(sorted(frames.items()))}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1) + "\n")


def summarise(errors: list[np.ndarray]) -> dict:
    """Mean over scored frames, mean last-frame error, diverged share and counts for one method and step."""
    scored = np.concatenate([e[~np.isnan(e)] for e in errors])
    last = [e[~np.isnan(e)][-1] for e in errors]
    diverged = [bool(np.nanmax(e) > DIVERGED_DEG) for e in errors]
    return {"mean_deg": round(float(scored.mean()), 3), "median_deg": round(float(np.median(scored)), 3),
            "last_frame_mean_deg": round(float(np.mean(last)), 3), "diverged_share": round(float(np.mean(diverged)), 4),
            "diverged": int(sum(diverged)), "sequences": len(errors), "frames": int(scored.size)}


def curve(errors: list[np.ndarray], stat=np.mean) -> list[float | None]:
    """``stat`` (mean or median) of the error per frame index since the start, over the sequences scored there (None
    where none is)."""
    stack = np.stack(errors)
    out = []
    for column in stack.T:
        scored = column[~np.isnan(column)]
        out.append(round(float(stat(scored)), 3) if scored.size else None)
    return out


def cpu_record() -> dict:
    """The machine (:func:`refiner_rt.bench.machine_info`), its vector-instruction flags and the load average."""
    from refiner_rt.bench import cpu_flags, machine_info

    info = machine_info()
    return {"cpu": info["cpu"], "vector_flags": cpu_flags(), "cores": info["cores"], "python": info["python"],
            "onnxruntime": info["onnxruntime"], "load_average_1min_at_start": round(os.getloadavg()[0], 2)}



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


def report(doc: dict) -> str:
    """The Markdown table of a results file: one row per frame step and method."""
    scene = (f"window {doc.get('motion_window')}, weight {doc.get('prediction_weight')}, at most "
             f"{doc.get('max_correction_deg')} deg")
    short = {"hold": "(a) hold initial pose", "per_frame": "(b) refine each frame from U(0, 30)",
             "track": "(c) track", "track_predict": "(c) track + constant velocity",
             "track_redetect": f"(c) track + detector every {doc['redetect']} frames",
             "track_lost": f"(c) track + loss check ({doc.get('lost_deg')} deg), detector when lost",
             "track_fuse": f"(c) track + detector fused (weight {doc.get('detector_weight')}) every "
                           + ("frame" if doc.get("fuse_every", 1) == 1 else f"{doc.get('fuse_every')} frames"),
             "track_scene": f"(c) track + the scene's motion ({scene})",
             "per_frame_cascade": "(b) with the cascade", "track_cascade": "(c) track with the cascade",
             "track_cascade_scene": f"(c) track with the cascade + the scene's motion ({scene})"}
    lines = ["| step | method | mean | median | last frame | diverged (> 30 deg) | beats (b) per sequence "
             "| detector poses per frame | CPU ms per update |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for st in doc["steps"]:
        for m in [m for m in METHODS if m in doc["summary"]]:
            r = doc["summary"][m][str(st)]
            beats = "" if m == "per_frame" or "beats_per_frame_share" not in r else f"{100 * r['beats_per_frame_share']:.0f}%"
            share = r.get("detector_share")
            det = "" if share is None else f"{100 * share:.1f}%"
            cost = doc.get("cost", {}).get(m if m.startswith("per_frame") else f"{m}_step{st}", {})
            ms = "" if m == "hold" or cost.get("cpu_ms_per_update") is None else f"{cost['cpu_ms_per_update']:.2f}"
            lines.append(f"| {st} | {short[m]} | {r['mean_deg']:.2f} | {r['median_deg']:.2f} | "
                         f"{r['last_frame_mean_deg']:.2f} | {100 * r['diverged_share']:.1f}% ({r['diverged']}/{r['sequences']}) "
                         f"| {beats} | {det} | {ms} |")
    return "\n".join(lines)


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
        "command": shlex.join(["python", "benchmarks/tracking.py", *(sys.argv[1:] if argv is None else argv)]),
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
