"""Tracking from a first-frame pose against refining every frame from its own detector pose, per video.

Each video (``video.load_videos``: one scene, all its objects tracked together, the shipped INT8 coarse refiners, one
pass per object and frame, one thread) is run from ``--seeds`` draws of coarse poses, U(0, 30) degrees around the
truth (docs/design.md §1), the draws of ``benchmarks/tracking.py`` (``sequence_rng``):

* ``per_frame``: every frame refined once from its own fresh U(0, 30) draw (a detector on every frame);
* each tracker of ``TRACKERS``: started from the first frame's draw, no detector after it; per frame its error, its
  score (:attr:`refiner_rt.RefinerTracker.scores`) and whether it flags the object lost.

Errors are geodesic angles, the master chef can's to the closest turn about its axis (``error_deg``). Reported per
video and method: the mean error over frames and seeds, the mean last-frame error, the worst frame, and
the sequences that end above 30 degrees, with how many of those the tracker flags lost at their last frame.

Usage (from the repository root; REAL: the real dev frames' BOP folder, ``real_ycbv_dev/test``)::

    python -m benchmarks.studies.tracking_real.compare --data REAL --max-frames 20 \\
        --seeds 10 --json benchmarks/studies/tracking_real/real.json --plot benchmarks/studies/tracking_real/real.png
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchmarks.studies.tracking_real.video import Video, dataset_name, load_videos
from benchmarks.tracking import cpu_record, sequence_rng
from models.data.objects import SCAN_FRAME_SYMMETRIES
from models.symmetry import symmetric_error
from refiner_rt import quaternion as rq
from refiner_rt.session import RefinerSession
from refiner_rt.tracker import LOST_DEG, RefinerTracker

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
}


def draws(video: Video, seed: int, n_frames: int) -> tuple[dict, dict]:
    """The start pose and the per-frame detector poses of every sequence of ``video`` for ``seed``."""
    start, per_frame = {}, {}
    for s in video.seqs:
        rng = sequence_rng(seed, s)
        noise0 = rq.sample_rotation_noise(1, "uniform", 0, 30, rng)[0]
        noise = rq.sample_rotation_noise(n_frames, "uniform", 0, 30, rng)
        f0 = min(s.images)
        start[s.object_id] = rq.multiply(s.q_gt[f0], noise0)
        per_frame[s.object_id] = {f: rq.multiply(s.q_gt[f], noise[i % n_frames]) for i, f in enumerate(video.frames)
                                  if f in s.q_gt}
    return start, per_frame


def run_video(video: Video, sessions: dict, seed: int, trackers: dict) -> dict:
    """Per method and object: per-frame errors (NaN where the object is not scored), scores and lost flags."""
    n = len(video.frames)
    index = {f: i for i, f in enumerate(video.frames)}
    start, det = draws(video, seed, n)
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
        tracker = RefinerTracker({s.object_id: sessions[s.object_id] for s in video.seqs}, video.K, {}, **kwargs)
        rec = {s.object_id: {"err": np.full(n, np.nan), "score": np.full(n, np.nan), "lost": np.zeros(n, bool)}
               for s in video.seqs}
        for f in video.frames:
            boxes = {}
            for s in video.seqs:
                if f in s.images:
                    if s.object_id not in tracker:
                        tracker.add(s.object_id, start[s.object_id])
                    boxes[s.object_id] = s.boxes[f]
            q = tracker.update(video.images[f], boxes)
            scores = getattr(tracker, "scores", {})
            for s in video.seqs:
                if s.object_id in q:
                    r = rec[s.object_id]
                    r["err"][index[f]] = error_deg(s.object_id, q[s.object_id], s.q_gt[f])
                    r["score"][index[f]] = scores.get(s.object_id, np.nan)
                    r["lost"][index[f]] = s.object_id in tracker.lost
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


def run(data: Path, max_frames: int, seeds: int, scenes: list[str] | None, trackers: dict) -> dict:
    videos = load_videos(data, scenes, max_frames)
    sessions: dict[str, RefinerSession] = {}
    for v in videos:
        for s in v.seqs:
            if s.object_id not in sessions:
                sessions[s.object_id] = RefinerSession.pretrained(s.object_id, int8=True, threads=1)
    methods = ["per_frame", *trackers]
    per_video, all_runs = {}, []
    for v in videos:
        runs = [run_video(v, sessions, seed, trackers) for seed in range(seeds)]
        all_runs += runs
        per_video[v.name] = {"objects": [s.object_id for s in v.seqs], "frames": len(v.frames),
                             "summary": {m: summarise(runs, m) for m in methods},
                             "curves": {m: curves(runs, m) for m in methods}}
        line = "  ".join(f"{m} {per_video[v.name]['summary'][m]['mean_deg']:5.2f}" for m in methods)
        print(f"{v.name} ({len(v.seqs)} objects): {line}", flush=True)
    return {"data": dataset_name(data), "max_frames": max_frames, "seeds": seeds, "noise": "uniform:0:30",
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


def plot(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(doc["videos"])
    cols = min(len(names), 4)
    rows = (len(names) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False, sharey=True)
    for ax, name in zip(axes.flat, names):
        for m, c in doc["videos"][name]["curves"].items():
            y = np.array([np.nan if x is None else x for x in c])
            ax.plot(np.arange(len(y)), y, label=m, lw=1.2)
        ax.set_title(f"{name} ({', '.join(o.split('_', 1)[1] for o in doc['videos'][name]['objects'])})", fontsize=7)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(names):]:
        ax.axis("off")
    axes[0][0].set_ylabel("mean rotation error (deg)")
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"{doc['data']}: mean over {doc['seeds']} coarse draws per frame", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, help="a BOP split folder of videos (real or rendered)")
    p.add_argument("--max-frames", type=int, default=100, help="frames per video from its first (default 100)")
    p.add_argument("--seeds", type=int, default=3, help="coarse-pose draws per video (default 3)")
    p.add_argument("--scenes", help="comma-separated scene folders (default: all)")
    p.add_argument("--json", type=Path)
    p.add_argument("--plot", type=Path)
    p.add_argument("--report", type=Path, metavar="JSON", help="print the Markdown table of a results file and exit")
    a = p.parse_args(argv)
    if a.report:
        print(table(json.loads(a.report.read_text())))
        return 0
    t0 = time.time()
    doc = run(a.data, a.max_frames, a.seeds, a.scenes.split(",") if a.scenes else None, TRACKERS)
    doc["wall_s"] = round(time.time() - t0, 1)
    doc["machine"] = cpu_record()
    print(json.dumps(doc["summary"], indent=1))
    print(f"wall {doc['wall_s']} s")
    if a.json:
        a.json.write_text(json.dumps(doc, indent=1) + "\n")
    if a.plot:
        plot(doc, a.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
