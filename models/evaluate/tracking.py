"""The tracking harness, on rendered video: each frame refined from the previous frame's result, against the paper's
per-frame use.

The command is ``python -m benchmarks.tracking`` (its docstring describes what is measured and has the usage); this
module is its harness: the sequences of a rendered folder, one scene's run of every method, the summaries and the
report's table.
"""

from __future__ import annotations

import json
import os
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.cascade import DEFAULT_COARSE_VIEWS, DEFAULT_FINE_VIEWS
from refiner_rt.session import RefinerSession
from refiner_rt.tracker import RefinerTracker

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
