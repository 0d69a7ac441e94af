"""Probe: update rules for tracking on the cascade, side by side on one rendered video (no detector after the start).

Every rule keeps its own estimate per sequence; all rules of one object and frame are refined in one batched
``RefinerCascade.refine`` call. The draws are those of ``benchmarks/tracking.py`` (same seed rule), so ``per_frame``
here is that benchmark's per-frame refinement from a detector's pose, and ``base`` its ``track_cascade``.

Rules (``q``: the track's estimate, ``r``: the refined rotation for this update):

* ``base``: ``r`` = coarse then fine from ``q`` (what ``RefinerTracker`` does with a cascade); ``q = r``;
* ``gated``: ``r`` = the cascade's own gated path from ``q``; ``q = r``;
* ``smooth<a>``: ``q`` moves a fraction ``a`` of the way to ``r`` (base's ``r``);
* ``clamp<c>``: ``q`` moves toward ``r`` by at most ``c`` degrees per frame of step;
* ``ab<a>``: an alpha-beta filter: the constant-velocity prediction ``p``, ``r`` from ``p``, ``q`` moves ``a`` of the
  way from ``p`` to ``r``, and the velocity is smoothed toward the change.

``--ego``: the scene's motion (what became ``RefinerTracker(predict="scene")``), per scene, all objects at once; the
variants in ``EGO`` (window in updates, share of the prediction kept, a limit from it, outliers left out). This is a
re-implementation for speed, close to but not the tracker itself: ``benchmarks/tracking.py`` measures the tracker.

Usage::

    python -m benchmarks.studies.cascade.track_probe [--ego] --data data/tracking_calib_s556 --json OUT.json \
        [--scenes A:B] [--steps 1,2,4] [--rules R | --variants V]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]

from refiner_rt import RefinerCascade
from refiner_rt import quaternion as rq
from models.evaluate.tracking import DIVERGED_DEG, load_sequences, sequence_rng


def toward(q: np.ndarray, r: np.ndarray, frac: float | None = None, max_deg: float | None = None) -> np.ndarray:
    """``q`` turned toward ``r`` along the shortest arc: a fraction of the way, or by at most ``max_deg``."""
    step = rq.canonical(rq.normalize(rq.multiply(r, rq.inverse(q))))
    axis, angle = rq.to_axis_angle(step)
    if frac is not None:
        angle = angle * frac
    if max_deg is not None:
        angle = min(float(angle), max_deg)
    return rq.canonical(rq.normalize(rq.multiply(rq.from_axis_angle(axis, angle), q)))


def power(q: np.ndarray, t: float) -> np.ndarray:
    axis, angle = rq.to_axis_angle(q)
    return rq.from_axis_angle(axis, angle * t)


RULES = {
    "base": dict(kind="base"),
    "gated": dict(kind="gated"),
    "smooth0.5": dict(kind="smooth", frac=0.5),
    "smooth0.7": dict(kind="smooth", frac=0.7),
    "clamp1": dict(kind="clamp", deg=1.0),
    "clamp2": dict(kind="clamp", deg=2.0),
    "clamp4": dict(kind="clamp", deg=4.0),
    "ab0.5": dict(kind="ab", frac=0.5, beta=0.3),
    "ab0.7": dict(kind="ab", frac=0.7, beta=0.3),
    "ab0.85": dict(kind="ab", frac=0.85, beta=0.3),
    "gapvel": dict(kind="base", window=12, gap_predict=True),
    "gapsettle": dict(kind="base", gap_settle=True),
    "gapvel_settle": dict(kind="base", window=12, gap_predict=True, gap_settle=True),
    "vel12": dict(kind="base", window=12, predict=True),
    "vel12_settle": dict(kind="base", window=12, predict=True, gap_settle=True),
}


def window_velocity(history: list, window: int) -> np.ndarray | None:
    """Rotation change per frame in the camera frame over the refined estimates of the last ``window`` frames."""
    if len(history) < 2:
        return None
    f_now, q_now = history[-1]
    old = [(f, q) for f, q in history[:-1] if f_now - f <= window]
    if not old:
        return None
    f_old, q_old = old[0]
    change = rq.canonical(rq.normalize(rq.multiply(q_now, rq.inverse(q_old))))
    return power(change, 1.0 / (f_now - f_old))


def run_sequence(seq, cascade: RefinerCascade, images: dict, step: int, seed: int, n_frames: int,
                 rules: dict, settled: RefinerCascade | None = None) -> dict:
    rng = sequence_rng(seed, seq)
    start_noise = rq.sample_rotation_noise(1, "uniform", 0, 30, rng)[0]
    rq.sample_rotation_noise(n_frames, "uniform", 0, 30, rng)  # per-frame draws, as tracking.py (not used here)
    frames = sorted(seq.images)
    grid = [f for f in range(frames[0], frames[-1] + 1) if f % step == 0 and f in seq.images]
    f0 = grid[0]
    q = {k: rq.multiply(seq.q_gt[f0], start_noise) for k in rules}
    vel = {k: np.array([1.0, 0, 0, 0]) for k in rules}
    last = {k: None for k in rules}
    err = {k: [] for k in rules}
    history = {k: [] for k in rules}
    prev_f = f0
    for f in grid:
        gap = max(1, (f - prev_f) // step)
        frames_since = f - prev_f
        prev_f = f
        q_in, forced, settle = [], [], []
        for k, rule in rules.items():
            v = window_velocity(history[k], rule["window"]) if "window" in rule else None
            if rule["kind"] == "ab" and last[k] is not None:
                q_in.append(rq.canonical(rq.normalize(rq.multiply(power(vel[k], gap), q[k]))))
            elif v is not None and (rule.get("predict") or (rule.get("gap_predict") and gap > 1)):
                q_in.append(rq.canonical(rq.normalize(rq.multiply(power(v, frames_since), q[k]))))
            else:
                q_in.append(q[k])
            forced.append(rule["kind"] != "gated" or last[k] is None)
            settle.append(bool(rule.get("gap_settle")) and gap > 1)
        box = seq.boxes[f][None].repeat(len(rules), 0)
        settle = np.array(settle)
        res = np.zeros((len(rules), 4))
        if (~settle).any():
            res[~settle] = cascade.refine(images[f], box[~settle], np.array(q_in)[~settle], K=seq.K,
                                          coarse=np.array(forced)[~settle]).q_refined
        if settle.any():
            res[settle] = settled.refine(images[f], box[settle], np.array(q_in)[settle], K=seq.K,
                                         coarse=np.ones(int(settle.sum()), dtype=bool)).q_refined
        for (k, rule), p, r in zip(rules.items(), q_in, res):
            kind = rule["kind"]
            first = last[k] is None
            if first or kind in ("base", "gated"):
                new = r
            elif kind == "smooth":
                new = toward(q[k], r, frac=rule["frac"])
            elif kind == "clamp":
                new = toward(q[k], r, max_deg=rule["deg"] * step * gap)
            else:  # ab
                new = toward(p, r, frac=rule["frac"])
                change = rq.canonical(rq.normalize(rq.multiply(new, rq.inverse(q[k]))))
                vel[k] = toward(vel[k], power(change, 1.0 / gap), frac=rule["beta"])
            last[k] = q[k]
            q[k] = rq.canonical(rq.normalize(new))
            history[k] = (history[k] + [(f, q[k])])[-64:]
            err[k].append(float(rq.geodesic_angle(q[k], seq.q_gt[f])))
    return err


def scene_images(scene_seqs) -> dict:
    """Every frame of one scene's path, from its first scored frame to its last (frame id -> BGR image)."""
    any_path = Path(next(iter(scene_seqs[0].images.values())))
    lo = min(min(s.images) for s in scene_seqs)
    hi = max(max(s.images) for s in scene_seqs)
    return {f: cv2.imread(str(any_path.with_name(f"{f:06d}{any_path.suffix}")), cv2.IMREAD_COLOR)
            for f in range(lo, hi + 1)}


def per_frame(seq, coarse, images: dict, seed: int, n_frames: int) -> dict[int, float]:
    rng = sequence_rng(seed, seq)
    rq.sample_rotation_noise(1, "uniform", 0, 30, rng)
    noise = rq.sample_rotation_noise(n_frames, "uniform", 0, 30, rng)
    out = {}
    for f in sorted(seq.images):
        q_in = rq.multiply(seq.q_gt[f], noise[f % n_frames])[None]
        r = coarse.refine(images[f], seq.boxes[f][None], q_in, K=seq.K).q_refined[0]
        out[f] = float(rq.geodesic_angle(r, seq.q_gt[f]))
    return out


# --------------------------------------------------------------------- a still scene, a moving camera: shared motion
EGO = {
    "ego1.0": dict(frac=1.0, window=12),
    "ego0.7": dict(frac=0.7, window=12),
    "ego0.5": dict(frac=0.5, window=12),
    "ego1.0_w24": dict(frac=1.0, window=24),
    "ego1.0_settle": dict(frac=1.0, window=12, gap_settle=True),
    "ego0.7_w4": dict(frac=0.7, window=4),
    "ego0.7_c1": dict(frac=0.7, window=4, clamp=1.0),
    "ego0.7_c2": dict(frac=0.7, window=4, clamp=2.0),
    "ego0.7_c4": dict(frac=0.7, window=4, clamp=4.0),
    "ego0.7_w4_rob": dict(frac=0.7, window=4, robust=True),
    "ego0.7_w8_rob": dict(frac=0.7, window=8, robust=True),
    "ego0.7_w4_rob_c2": dict(frac=0.7, window=4, robust=True, clamp=2.0),
    "ego0.7_w4_rob_c2t": dict(frac=0.7, window=4, robust=True, clamp=2.0, clamp_after_turn=True),
    "ego0.7_w4_rob_c3t": dict(frac=0.7, window=4, robust=True, clamp=3.0, clamp_after_turn=True),
}


def scene_velocity(hist: dict, window: int, robust: bool = False) -> np.ndarray | None:
    """The camera-frame rotation per frame that every still object shares (the camera's own turn, inverted): the
    mean over objects of each one's change across its refined estimates of the last ``window`` frames."""
    rates = []
    for h in hist.values():
        f_now, q_now = h[-1]
        old = [(f, q) for f, q in h[:-1] if f_now - f <= window]
        if not old or f_now - old[0][0] < window // 2:
            continue
        f_old, q_old = old[0]
        rates.append(power(rq.canonical(rq.normalize(rq.multiply(q_now, rq.inverse(q_old)))), 1.0 / (f_now - f_old)))
    if not rates:
        return None
    m = rq.canonical(rq.normalize(rq.mean(np.array(rates))))
    if robust and len(rates) >= 3:  # leave out the tracks whose change is far from the others' (a drifting track)
        d = rq.geodesic_angle(np.array(rates), m)
        keep = d <= max(0.2, 2.0 * float(np.median(d)))
        m = rq.canonical(rq.normalize(rq.mean(np.array(rates)[keep])))
    return m


def run_scene_ego(seqs, cascades: dict, settled: dict, images: dict, step: int, seed: int, n_frames: int,
                  variants: dict) -> dict:
    """Errors per variant and sequence (one list per sequence, its scored frames in order)."""
    start_noise = {}
    for s in seqs:
        rng = sequence_rng(seed, s)
        start_noise[s.object_id] = rq.sample_rotation_noise(1, "uniform", 0, 30, rng)[0]
    lo = min(min(s.images) for s in seqs)
    hi = max(max(s.images) for s in seqs)
    grid = [f for f in range(lo, hi + 1) if f % step == 0]
    q = {k: {} for k in variants}  # variant -> object -> (last frame refined, q)
    hist = {k: {} for k in variants}
    err = {k: {s.object_id: [] for s in seqs} for k in variants}
    for f in grid:
        vel = {k: scene_velocity(hist[k], v["window"] * step, v.get("robust", False)) for k, v in variants.items()}
        for s in seqs:
            if f not in s.images:
                continue
            o = s.object_id
            q_in, settle, fresh = [], [], []
            for k, v in variants.items():
                if o not in q[k]:
                    q_in.append(rq.multiply(s.q_gt[f], start_noise[o]))
                    fresh.append(True)
                    settle.append(False)
                    continue
                f_last, q_last = q[k][o]
                p = q_last if vel[k] is None else rq.canonical(rq.normalize(rq.multiply(power(vel[k], f - f_last),
                                                                                          q_last)))
                q_in.append(p)
                fresh.append(False)
                settle.append(bool(v.get("gap_settle")) and f - f_last > step)
            settle = np.array(settle)
            box = s.boxes[f][None].repeat(len(variants), 0)
            res = np.zeros((len(variants), 4))
            q_arr = np.array(q_in)
            if (~settle).any():
                res[~settle] = cascades[o].refine(images[f], box[~settle], q_arr[~settle], K=s.K,
                                                  coarse=np.ones(int((~settle).sum()), dtype=bool)).q_refined
            if settle.any():
                res[settle] = settled[o].refine(images[f], box[settle], q_arr[settle], K=s.K,
                                                coarse=np.ones(int(settle.sum()), dtype=bool)).q_refined
            for (k, v), p, r, new in zip(variants.items(), q_arr, res, fresh):
                clamp = v.get("clamp") if vel[k] is not None or not v.get("clamp_after_turn") else None
                out = r if new else toward(p, r, frac=v["frac"], max_deg=clamp)
                q[k][o] = (f, out)
                hist[k].setdefault(o, []).append((f, out))
                hist[k][o] = hist[k][o][-64:]
                err[k][o].append(float(rq.geodesic_angle(out, s.q_gt[f])))
    return err


def summarise(rows, steps, names) -> None:
    """Print, per step, per-frame refinement's mean (where measured) and each rule's mean, median and lost share."""
    for st in steps:
        line = f"step {st}"
        if "per_frame" in rows[0]:
            pf = [row["per_frame"][f] for row in rows for f in sorted(row["per_frame"]) if f % st == 0]
            line += f": per_frame {np.mean(pf):.2f} ({len(pf)} frames)"
        print(line)
        for k in names:
            e = [np.asarray(row["steps"][st][k]) for row in rows]
            flat = np.concatenate(e)
            lost = sum(int(x.max() > DIVERGED_DEG) for x in e)
            print(f"  {k:14s} mean {flat.mean():5.2f}  median {np.median(flat):5.2f}  diverged "
                  f"{100 * lost / len(e):4.1f}% ({lost}/{len(e)})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--ego", action="store_true", help="the scene's motion (EGO variants), all objects of a scene at once")
    ap.add_argument("--scenes", default="", help="first:last scene index slice, e.g. 0:15")
    ap.add_argument("--steps", default="1,2,4")
    ap.add_argument("--rules", default=",".join(RULES), help="per-object rules (without --ego)")
    ap.add_argument("--variants", default=",".join(EGO), help="scene-motion variants (with --ego)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    names = args.variants.split(",") if args.ego else args.rules.split(",")
    table = EGO if args.ego else RULES
    unknown = [k for k in names if k not in table]
    if unknown:
        ap.error(f"unknown {'variants' if args.ego else 'rules'} {unknown}; choose from {sorted(table)}")
    chosen = {k: table[k] for k in names}
    steps = [int(s) for s in args.steps.split(",")]
    from refiner_rt.pretrained import pretrained_models

    objects = sorted(m.object_id for m in pretrained_models())
    seqs, _ = load_sequences(args.data, set(objects), 0.3, 20)
    scenes = sorted({s.scene for s in seqs})
    if args.scenes:
        a, b = (int(v) for v in args.scenes.split(":"))
        scenes = scenes[a:b]
    cascades = {o: RefinerCascade.pretrained(o, int8=True, threads=1) for o in objects}
    settled = {o: RefinerCascade(c.coarse, c.fine, gate_deg=c.gate_deg, coarse_gate_deg=c.coarse_gate_deg,
                                 settle_deg=2.0) for o, c in cascades.items()}
    n_frames = max(max(s.images) for s in seqs) + 1
    rows = []
    t0 = time.perf_counter()
    for i, scene in enumerate(scenes):
        scene_seqs = [s for s in seqs if s.scene == scene]
        images = scene_images(scene_seqs)
        if args.ego:
            res = {st: run_scene_ego(scene_seqs, cascades, settled, images, st, args.seed, n_frames, chosen)
                   for st in steps}
            rows += [{"scene": scene, "object": s.object_id,
                      "steps": {st: {k: res[st][k][s.object_id] for k in chosen} for st in steps}}
                     for s in scene_seqs]
        else:
            for s in scene_seqs:
                o = s.object_id
                rows.append({"scene": scene, "object": o,
                             "per_frame": per_frame(s, cascades[o].coarse, images, args.seed, n_frames),
                             "steps": {st: run_sequence(s, cascades[o], images, st, args.seed, n_frames, chosen,
                                                        settled[o]) for st in steps}})
        print(f"scene {i + 1}/{len(scenes)} {time.perf_counter() - t0:.0f}s", flush=True)
    args.json.write_text(json.dumps({"variants" if args.ego else "rules": chosen, "steps": steps, "rows": rows}))
    summarise(rows, steps, list(chosen))
    return 0


if __name__ == "__main__":
    sys.exit(main())
