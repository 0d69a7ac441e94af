"""Calibrate ``RefineResult.score`` on rendered frames: the scale of ``exp(-(degrees moved) / scale)`` that makes the
score the probability that the refined rotation is within ``WITHIN_DEG`` of the truth (least Brier score).

On up to ``--instances`` instances of a rendered BOP folder (``visib_fract >= 0.3``; the shipped INT8 coarse
refiners, one thread), each refined from a coarse pose U(0, 30) degrees around the truth and from one U(30, 90)
degrees off (a lost track's input), with one and with two passes (one view). Per setting: the Spearman correlation
of the score with the error, the error per score bin, and the Brier score of ``exp(-moved / scale)`` against
``error < WITHIN_DEG`` for each scale of ``SCALES``.

Usage (from the repository root)::

    python -m benchmarks.studies.score_calibration.calibrate --data data/ycb9_calib_s22 \\
        --json benchmarks/studies/score_calibration/calib_s22.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.stats import spearmanr

from models.evaluate.tracking_video import SHIPPED, dataset_name
from models.data.bop import load_bop
from refiner_rt import quaternion as rq
from refiner_rt.session import RefinerSession

WITHIN_DEG = 10.0
SCALES = (5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 40.0, 60.0)
BINS = (0.0, 0.2, 0.4, 0.6, 0.8, 0.9, 1.0001)
INPUTS = {"U(0, 30)": (0.0, 30.0), "U(30, 90)": (30.0, 90.0)}


def run(data: Path, instances: int, seed: int) -> dict:
    samples = load_bop(data, objects=list(SHIPPED), min_visib=0.3)
    rng = np.random.default_rng(seed)
    picked = rng.choice(len(samples), min(instances, len(samples)), replace=False)
    sessions: dict[str, RefinerSession] = {}
    rows = []  # (input, passes, error, moved)
    for i in picked:
        s = samples[int(i)]
        sess = sessions.setdefault(s.obj_id, RefinerSession.pretrained(s.obj_id, int8=True, threads=1))
        image = cv2.imread(str(s.image_path))
        q_gt = rq.from_matrix(s.R)
        for name, (lo, hi) in INPUTS.items():
            q_in = rq.multiply(q_gt, rq.sample_rotation_noise(1, "uniform", lo, hi, rng)[0])[None]
            for passes in (1, 2):
                r = sess.refine(image, np.asarray(s.box_xyxy)[None], q_in, K=s.K, iterations=passes)
                rows.append((name, passes, float(rq.geodesic_angle(r.q_refined[0], q_gt)), float(r.correction_deg[0])))
    out = {}
    for passes in (1, 2):
        for inputs in (["U(0, 30)"], ["U(0, 30)", "U(30, 90)"]):
            a = np.array([(e, m) for name, p, e, m in rows if p == passes and name in inputs])
            err, moved = a[:, 0], a[:, 1]
            good = (err < WITHIN_DEG).astype(float)
            brier = {str(sc): round(float(np.mean((np.exp(-moved / sc) - good) ** 2)), 5) for sc in SCALES}
            score = np.exp(-moved / min(SCALES, key=lambda sc: brier[str(sc)]))
            bins = []
            for lo, hi in zip(BINS[:-1], BINS[1:]):
                m = (score >= lo) & (score < hi)
                if m.any():
                    bins.append({"score": [lo, min(hi, 1.0)], "n": int(m.sum()), "mean_err_deg": round(float(err[m].mean()), 2),
                                 "share_within": round(float(good[m].mean()), 3), "mean_score": round(float(score[m].mean()), 3)})
            out[f"{passes} pass(es), inputs {' + '.join(inputs)}"] = {
                "n": len(a), "share_within": round(float(good.mean()), 3),
                "spearman_score_error": round(float(spearmanr(-moved, err)[0]), 3), "brier_by_scale": brier,
                "best_scale_deg": min(SCALES, key=lambda sc: brier[str(sc)]), "bins_at_best_scale": bins}
    return {"data": dataset_name(data), "instances": int(len(picked)), "seed": seed, "within_deg": WITHIN_DEG,
            "model": "shipped INT8 coarse refiners, one view, threads=1", "settings": out}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--instances", type=int, default=600)
    p.add_argument("--seed", type=int, default=5)
    p.add_argument("--json", type=Path)
    a = p.parse_args(argv)
    t0 = time.time()
    doc = run(a.data, a.instances, a.seed)
    doc["wall_s"] = round(time.time() - t0, 1)
    for k, v in doc["settings"].items():
        print(f"{k}: n {v['n']}, within {v['share_within']}, spearman {v['spearman_score_error']}, best scale "
              f"{v['best_scale_deg']}, brier {v['brier_by_scale']}")
        for b in v["bins_at_best_scale"]:
            print("   ", b)
    if a.json:
        a.json.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
