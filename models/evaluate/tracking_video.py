"""Tracking on video, real or rendered: the frames of one scene with every object's truth and box, and the comparison of
trackers started from a first-frame pose against refining every frame (``benchmarks/studies/tracking_real``).

Real YCB-Video dev videos and rendered video alike are BOP folders; an object's sequence is its frames with
``visib_fract >= min_visib`` (:func:`models.evaluate.tracking.load_sequences`). A *video* here is one scene: its sequences
tracked together, as a robot's tracker would, over its first ``max_frames`` frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from models.data.objects import SCAN_FRAME_SYMMETRIES
from models.data.symmetry import symmetric_error
from models.evaluate.tracking import Sequence, load_sequences, sequence_rng
from refiner_rt import quaternion as rq
from refiner_rt.session import RefinerSession
from refiner_rt.tracker import LOST_DEG, RefinerTracker
from refiner_rt.pretrained import pretrained_models

SHIPPED = tuple(sorted(m.object_id for m in pretrained_models()))


@dataclass
class Video:
    """One scene: its consecutive frame ids, the images (BGR) and the sequences of its objects."""

    dataset: str
    scene: str
    frames: list[int]
    images: dict[int, np.ndarray]
    seqs: list[Sequence]

    @property
    def K(self) -> np.ndarray:
        return self.seqs[0].K

    @property
    def name(self) -> str:
        return f"{self.dataset}/{self.scene}"


def dataset_name(data: Path) -> str:
    """A BOP folder as the records name it: ``real_ycbv_dev/test`` for a split folder, else the folder's name."""
    data = Path(data).resolve()
    return f"{data.parent.name}/{data.name}" if data.name in ("test", "val", "train") else data.name


def load_videos(data: Path, scenes: list[str] | None = None, max_frames: int = 100, min_visib: float = 0.3,
                min_frames: int = 10) -> list[Video]:
    """The videos of ``data`` (a BOP split folder), each cut to its first ``max_frames`` consecutive frames."""
    seqs, _ = load_sequences(Path(data), set(SHIPPED), min_visib, 1)
    by_scene: dict[str, list[Sequence]] = {}
    for s in seqs:
        if scenes is None or s.scene in scenes:
            by_scene.setdefault(s.scene, []).append(s)
    videos = []
    for scene, group in sorted(by_scene.items()):
        first = min(min(s.images) for s in group)
        frames = list(range(first, first + max_frames))
        any_path = Path(next(iter(group[0].images.values())))
        images = {}
        for f in frames:
            im = cv2.imread(str(any_path.with_name(f"{f:06d}{any_path.suffix}")), cv2.IMREAD_COLOR)
            if im is None:
                break
            images[f] = im
        frames = [f for f in frames if f in images]
        kept = []
        for s in group:
            for table in (s.q_gt, s.boxes, s.images):
                for f in [f for f in table if f not in images]:
                    del table[f]
            if len(s.images) >= min_frames:
                kept.append(s)
        if kept:
            videos.append(Video(Path(data).resolve().parent.name if Path(data).name == "test" else Path(data).name,
                                scene, frames, images, kept))
    return videos


DIVERGED_DEG = 30.0


def error_deg(object_id: str, q: np.ndarray, q_gt: np.ndarray) -> float:
    """Rotation error in degrees; objects with a symmetry (the master chef can, about its axis: the real frames'
    annotation is not reliable about it) to the closest symmetric pose (``models.data.objects.SCAN_FRAME_SYMMETRIES``,
    as ``refiner-rt eval`` scores them)."""
    return float(symmetric_error(np.asarray(q)[None], np.asarray(q_gt)[None], np.array([object_id]),
                                 SCAN_FRAME_SYMMETRIES)[0])
# tracker name -> RefinerTracker keyword arguments (besides the sessions, K and the start poses)
TRACKERS = {
    "track_plain": {"prediction_weight": 0.0, "max_correction_deg": 180.0},  # the tracker before: no filter
    "track": {},  # RefinerTracker's defaults: the temporal filter
    "track_lost": {"lost_deg": LOST_DEG},  # and the loss-of-track check at its chosen threshold
    "track_views4": {"views": 4, "lost_deg": LOST_DEG},  # four box-jittered views per update (best on s561)
    "track_reinit": {"lost_deg": LOST_DEG, "reinit": True},  # and a flagged track re-initialised by a search on its box
    "track_views4_reinit": {"views": 4, "lost_deg": LOST_DEG, "reinit": True},  # both
    "track_starts5": {"starts": 5},  # five starts per update, each on its own box jitter, averaged (best on s561)
    "track_starts5_reinit": {"starts": 5, "lost_deg": LOST_DEG, "reinit": True},  # and the re-initialisation
}


def draws(video: Video, seed: int, n_frames: int, start_deg: tuple[float, float] = (0.0, 30.0)) -> tuple[dict, dict]:
    """The start pose and the per-frame detector poses of every sequence of ``video`` for ``seed``: per-frame poses
    U(0, 30) degrees around the truth, the start U(``start_deg``) (other than U(0, 30), e.g. U(45, 90) for a track
    already lost, drawn from a generator of its own, ``signals.py``'s, so the per-frame poses stay the same)."""
    start, per_frame = {}, {}
    for s in video.seqs:
        rng = sequence_rng(seed, s)
        noise0 = rq.sample_rotation_noise(1, "uniform", 0, 30, rng)[0]
        noise = rq.sample_rotation_noise(n_frames, "uniform", 0, 30, rng)
        if tuple(start_deg) != (0.0, 30.0):
            lo, hi = start_deg
            own = np.random.default_rng([seed, int(s.scene), sum(map(ord, s.object_id)), int(lo)])
            noise0 = rq.sample_rotation_noise(1, "uniform", lo, hi, own)[0]
        f0 = min(s.images)
        start[s.object_id] = rq.multiply(s.q_gt[f0], noise0)
        per_frame[s.object_id] = {f: rq.multiply(s.q_gt[f], noise[i % n_frames]) for i, f in enumerate(video.frames)
                                  if f in s.q_gt}
    return start, per_frame


def run_video(video: Video, sessions: dict, seed: int, trackers: dict, start_deg: tuple[float, float] = (0.0, 30.0),
              tracker=RefinerTracker) -> dict:
    """Per method and object: per-frame errors (NaN where the object is not scored), scores and lost flags; the
    trackers (``tracker``: the class, :class:`RefinerTracker` or a subclass) start U(``start_deg``) off."""
    n = len(video.frames)
    index = {f: i for i, f in enumerate(video.frames)}
    start, det = draws(video, seed, n, start_deg)
    out = {}
    rec = {}
    for s in video.seqs:
        err = np.full(n, np.nan)
        for f in sorted(s.images):
            r = sessions[s.object_id].refine(video.images[f], s.boxes[f][None], det[s.object_id][f][None], K=video.K)
            err[index[f]] = error_deg(s.object_id, r.q_refined[0], s.q_gt[f])
        rec[s.object_id] = {"err": err}
    out["per_frame"] = rec
    for name, kwargs in trackers.items():
        track = tracker({s.object_id: sessions[s.object_id] for s in video.seqs}, video.K, {}, **kwargs)
        rec = {s.object_id: {"err": np.full(n, np.nan), "score": np.full(n, np.nan), "lost": np.zeros(n, bool)}
               for s in video.seqs}
        for f in video.frames:
            boxes = {}
            for s in video.seqs:
                if f in s.images:
                    if s.object_id not in track:
                        track.add(s.object_id, start[s.object_id])
                    boxes[s.object_id] = s.boxes[f]
            q = track.update(video.images[f], boxes)
            scores = getattr(track, "scores", {})
            for s in video.seqs:
                if s.object_id in q:
                    r = rec[s.object_id]
                    r["err"][index[f]] = error_deg(s.object_id, q[s.object_id], s.q_gt[f])
                    r["score"][index[f]] = scores.get(s.object_id, np.nan)
                    r["lost"][index[f]] = s.object_id in track.lost
        out[name] = rec
    return out


def summarise(runs: list[dict], method: str) -> dict:
    """Mean error, mean last-frame error, worst frame, sequences ending above 30 deg and those of them flagged lost."""
    errs, last, ended_far, flagged, false_flags = [], [], 0, 0, 0
    for run in runs:
        for r in run[method].values():
            e = r["err"]
            scored = ~np.isnan(e)
            errs.append(e[scored])
            i = np.flatnonzero(scored)[-1]
            last.append(e[i])
            if e[i] > DIVERGED_DEG:
                ended_far += 1
                flagged += bool(r.get("lost", np.zeros_like(scored))[i])
            elif "lost" in r and r["lost"][i]:
                false_flags += 1
    allerr = np.concatenate(errs)
    return {"mean_deg": round(float(allerr.mean()), 3), "median_deg": round(float(np.median(allerr)), 3),
            "last_frame_mean_deg": round(float(np.mean(last)), 3), "max_deg": round(float(allerr.max()), 2),
            "sequences": len(last), "ended_above_30": ended_far, "ended_above_30_flagged_lost": flagged,
            "flagged_lost_at_end_below_30": false_flags}


def curves(runs: list[dict], method: str) -> list[float | None]:
    stack = np.stack([r["err"] for run in runs for r in run[method].values()])
    return [None if np.all(np.isnan(c)) else round(float(np.nanmean(c)), 3) for c in stack.T]


def run(data: Path, max_frames: int, seeds: int, scenes: list[str] | None, trackers: dict,
        start_deg: tuple[float, float] = (0.0, 30.0), tracker=RefinerTracker, first_seed: int = 0) -> dict:
    videos = load_videos(data, scenes, max_frames)
    sessions: dict[str, RefinerSession] = {}
    for v in videos:
        for s in v.seqs:
            if s.object_id not in sessions:
                sessions[s.object_id] = RefinerSession.pretrained(s.object_id, int8=True, threads=1)
    methods = ["per_frame", *trackers]
    per_video, all_runs = {}, []
    for v in videos:
        runs = [run_video(v, sessions, seed, trackers, start_deg, tracker)
                for seed in range(first_seed, first_seed + seeds)]
        all_runs += runs
        per_video[v.name] = {"objects": [s.object_id for s in v.seqs], "frames": len(v.frames),
                             "summary": {m: summarise(runs, m) for m in methods},
                             "curves": {m: curves(runs, m) for m in methods}}
        line = "  ".join(f"{m} {per_video[v.name]['summary'][m]['mean_deg']:5.2f}" for m in methods)
        print(f"{v.name} ({len(v.seqs)} objects): {line}", flush=True)
    return {"data": dataset_name(data), "max_frames": max_frames, "seeds": seeds, "noise": "uniform:0:30",
            **({"start": f"uniform:{start_deg[0]:g}:{start_deg[1]:g}"} if tuple(start_deg) != (0.0, 30.0) else {}),
            **({"first_seed": first_seed} if first_seed else {}),
            "model": "shipped INT8 coarse refiners, one pass per object and frame, threads=1",
            "trackers": trackers, "summary": {m: summarise(all_runs, m) for m in methods}, "videos": per_video}


def table(doc: dict) -> str:
    """The Markdown table of a results file: per video and method the mean and last-frame error, the worst frame,
    and the sequences ending above 30 degrees (flagged lost / all), then all videos together."""
    lines = ["| video | objects | method | mean | last frame | worst frame | ended > 30 deg (flagged) | flagged, ended < 30 |",
             "|---|---|---|---:|---:|---:|---:|---:|"]
    rows = [(name, ", ".join(o.split("_", 1)[1] for o in v["objects"]), v["summary"]) for name, v in doc["videos"].items()]
    rows.append(("all", "", doc["summary"]))
    for name, objects, summary in rows:
        for m, r in summary.items():
            lines.append(f"| {name.split('/')[-1]} | {objects} | {m} | {r['mean_deg']:.2f} | {r['last_frame_mean_deg']:.2f} | "
                         f"{r['max_deg']:.1f} | {r['ended_above_30']} ({r['ended_above_30_flagged_lost']}) | "
                         f"{r['flagged_lost_at_end_below_30']} |")
    return "\n".join(lines)
