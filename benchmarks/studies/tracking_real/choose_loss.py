"""Choose the loss-of-track check's signal, smoothing and threshold on rendered video (``signals.py`` records).

A candidate flags a track at a frame when the exponential moving average (weight ``beta`` for the newest frame) of a
per-frame signal exceeds a threshold. Scored on the ``from_coarse`` chains of a signals file: ``recall``, the share of
chains ending above 30 degrees flagged at their last frame; ``false_end``, the share of chains ending below 15
degrees flagged there; ``false_frames``, the share of frames below 15 degrees flagged. The choice: the highest
``recall`` among the candidates with ``false_frames <= MAX_FALSE_FRAMES``, then the fewest false frames.

Usage::

    python -m benchmarks.studies.tracking_real.choose_loss SIGNALS.json [--scenes-below N]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

MAX_FALSE_FRAMES = 0.10
BETAS = (1.0, 0.5, 0.3, 0.2, 0.1)
THRESHOLDS = {"moved": (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0), "probe": (4, 6, 8, 10, 12, 15, 20),
              "spread": (2, 2.5, 3, 4, 5, 6, 8)}


def ema(x: np.ndarray, beta: float) -> np.ndarray:
    out = np.empty_like(x)
    acc = x[0]
    for i, v in enumerate(x):
        acc = v if i == 0 else beta * v + (1 - beta) * acc
        out[i] = acc
    return out


def score(chains: list[dict], signal: str, beta: float, thr: float) -> dict:
    far = near = far_hit = near_hit = frames_near = frames_hit = 0
    for c in chains:
        err = np.array(c["err"])
        flag = ema(np.array(c[signal]), beta) > thr
        if err[-1] > 30:
            far += 1
            far_hit += flag[-1]
        elif err[-1] < 15:
            near += 1
            near_hit += flag[-1]
        ok = err < 15
        frames_near += ok.sum()
        frames_hit += (flag & ok).sum()
    return {"signal": signal, "beta": beta, "threshold": thr, "ended_far": far,
            "recall": round(float(far_hit / far), 3) if far else None,
            "false_end": round(float(near_hit / max(near, 1)), 4),
            "false_frames": round(float(frames_hit / max(frames_near, 1)), 4)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("signals", nargs="+")
    p.add_argument("--scenes-below", type=int, default=None, help="only scenes with a number below this")
    a = p.parse_args(argv)
    chains = []
    for path in a.signals:
        for r in json.load(open(path))["records"]:
            if a.scenes_below is None or int(r["video"].split("/")[-1]) < a.scenes_below:
                chains += r["from_coarse"]
    rows = [score(chains, s, b, t) for s, ts in THRESHOLDS.items() for b in BETAS for t in ts]
    ok = [r for r in rows if r["recall"] is not None and r["false_frames"] <= MAX_FALSE_FRAMES]
    for r in sorted(ok, key=lambda r: (-r["recall"], r["false_frames"]))[:10]:
        print(r)
    print("chains", len(chains), "ending above 30:", rows[0]["ended_far"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
