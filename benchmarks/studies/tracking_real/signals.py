"""Render-free diagnostics of frame-to-frame refinement, and the per-frame signals a loss check could use.

For each video (``video.load_videos``) and object, with the shipped INT8 coarse refiner, one thread:

* ``fixed_point``: on the object's first frame, the true pose refined again and again (15 passes on the same frame):
  the error after 1, 5 and 15 passes and the last passes' movement (where the refiner settles on this view);
* ``chain``: from the true pose of the first frame, each frame refined once from the previous frame's result (the
  tracker without a detector): the error and the correction per frame;
* ``from_coarse``: :class:`refiner_rt.RefinerTracker` (its defaults, the temporal filter) from ``--seeds`` draws of
  a U(0, 30)-degree start and as many of a U(45, 90)-degree start (a track already lost), with per frame the
  signals a loss check can compute without ground truth: ``moved`` (a second pass's movement, today's ``lost_deg`` check),
  ``probe`` (the mean distance back to the track of the results refined from the track turned by ``PROBE_DEG`` about
  four axes: near the truth the refiner pulls them back), ``spread`` (the spread of four box-jittered views).

Usage (from the repository root; REAL: the real dev frames' BOP folder, ``real_ycbv_dev/test``)::

    python -m benchmarks.studies.tracking_real.signals --data REAL --max-frames 20 \\
        --json benchmarks/studies/tracking_real/signals_real.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from models.evaluate.tracking_video import dataset_name, load_videos
from refiner_rt import quaternion as rq
from refiner_rt.session import RefinerSession
from refiner_rt.tracker import RefinerTracker

PROBE_DEG = 20.0
START_NEAR, START_FAR = (0, 30), (45, 90)  # U(0, 30): a detector's pose; U(45, 90): a track already lost
PROBE_AXES = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])


def probe_rotations() -> np.ndarray:
    return np.stack([rq.from_axis_angle(a, PROBE_DEG) for a in PROBE_AXES])


def run(data: Path, max_frames: int, seeds: int, scenes: list[str] | None) -> dict:
    videos = load_videos(data, scenes, max_frames)
    sessions: dict[str, RefinerSession] = {}
    probes = probe_rotations()
    out = []
    for v in videos:
        for s in v.seqs:
            sess = sessions.setdefault(s.object_id, RefinerSession.pretrained(s.object_id, int8=True, threads=1))
            frames = sorted(s.images)
            f0 = frames[0]
            im0, box0 = v.images[f0], s.boxes[f0][None]
            q, errs, moves = s.q_gt[f0][None], [], []
            for _ in range(15):
                r = sess.refine(im0, box0, q, K=v.K)
                moves.append(float(r.correction_deg[0]))
                q = r.q_refined
                errs.append(float(rq.geodesic_angle(q[0], s.q_gt[f0])))
            rec = {"video": v.name, "object": s.object_id, "frames": len(frames),
                   "truth_turn_deg": float(rq.geodesic_angle(s.q_gt[f0], s.q_gt[frames[-1]])),
                   "fixed_point": {"err_1": errs[0], "err_5": errs[4], "err_15": errs[-1],
                                   "last5_moved": float(np.mean(moves[-5:]))}}
            q, chain, corr = s.q_gt[f0][None], [], []
            for f in frames:
                r = sess.refine(v.images[f], s.boxes[f][None], q, K=v.K)
                corr.append(float(r.correction_deg[0]))
                q = r.q_refined
                chain.append(float(rq.geodesic_angle(q[0], s.q_gt[f])))
            rec["chain"] = {"err": chain, "correction": corr}
            runs = []
            for seed, (lo, hi) in [(k, START_NEAR) for k in range(seeds)] + [(k, START_FAR) for k in range(seeds)]:
                rng = np.random.default_rng([seed, int(s.scene), sum(map(ord, s.object_id)), lo])
                q = rq.multiply(s.q_gt[f0], rq.sample_rotation_noise(1, "uniform", lo, hi, rng)[0])[None]
                tracker = RefinerTracker(sess, v.K, {s.object_id: q[0]})  # its defaults: the temporal filter
                per = {k: [] for k in ("err", "correction", "moved", "probe", "spread")}
                for f in frames:
                    im, box = v.images[f], s.boxes[f][None]
                    q_prev = tracker.rotations[s.object_id]
                    q = tracker.update(im, {s.object_id: s.boxes[f]})[s.object_id][None]
                    per["err"].append(float(rq.geodesic_angle(q[0], s.q_gt[f])))
                    per["correction"].append(float(rq.geodesic_angle(q_prev, q[0])))
                    rows = np.concatenate([q, rq.multiply(q, probes)])
                    again = sess.refine(im, np.repeat(box, len(rows), 0), rows, K=v.K).q_refined
                    per["moved"].append(float(rq.geodesic_angle(again[0], q[0])))
                    per["probe"].append(float(np.mean(rq.geodesic_angle(again[1:], q))))
                    per["spread"].append(float(sess.refine(im, box, q, K=v.K, views=4).views_spread_deg[0]))
                runs.append({"start_deg": [lo, hi], **{k: [round(x, 3) for x in val] for k, val in per.items()}})
            rec["from_coarse"] = runs
            out.append(rec)
            fp = rec["fixed_point"]
            last = [r["err"][-1] for r in runs if r["start_deg"] == list(START_NEAR)]
            print(f"{v.name} {s.object_id:20s} truth turns {rec['truth_turn_deg']:4.1f} | fixed point "
                  f"{fp['err_1']:4.1f} {fp['err_5']:4.1f} {fp['err_15']:4.1f} | chain from truth mean "
                  f"{np.mean(chain):4.1f} last {chain[-1]:4.1f} corr {np.mean(corr):3.1f} | from U(0,30) last "
                  f"mean {np.mean(last):4.1f} max {np.max(last):4.1f}", flush=True)
    return {"data": dataset_name(data), "max_frames": max_frames, "seeds": seeds, "probe_deg": PROBE_DEG,
            "model": "shipped INT8 coarse refiners, one pass, one thread", "records": out}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--max-frames", type=int, default=100)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--scenes", help="comma-separated scene folders (default all)")
    p.add_argument("--json", type=Path)
    a = p.parse_args(argv)
    t0 = time.time()
    doc = run(a.data, a.max_frames, a.seeds, a.scenes.split(",") if a.scenes else None)
    doc["wall_s"] = round(time.time() - t0, 1)
    print(f"wall {doc['wall_s']} s")
    if a.json:
        a.json.write_text(json.dumps(doc) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
