"""The cascade measured through the runtime: per instance of a folder, the coarse refiner, the fine refiner and
:class:`refiner_rt.RefinerCascade` with any gates from the same runs (:func:`runtime_errors`, :func:`with_gate`),
the gates chosen on scenes the card does not score (:func:`choose_gate`), and the card's numbers with the floor curve
(:func:`summarise`). The fine refiners' build (``export.release.fine``) and the cascade studies use it.

Conventions: quaternions ``wxyz``, rotations object to camera, errors in degrees.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from models.data.objects import SCAN_FRAME_SYMMETRIES as SYMMETRIES

__all__ = ["FLOOR_BINS", "GATES", "objects_with_fine", "runtime_errors", "with_gate", "choose_gate", "summarise",
           "measure_cascade"]

FLOOR_BINS = 30              # the floor curve: output error in 1-degree bins of input error, 0 to 30


def objects_with_fine(objects: str | None, error) -> list[str]:
    """The objects a cascade study runs on: ``objects`` (comma-separated YCB ids), default every object whose fine
    refiner ships; ``error(message)`` (``ArgumentParser.error``) for one without."""
    from refiner_rt.pretrained import pretrained_models

    with_fine = [m.object_id for m in pretrained_models() if "fine" in m.stages]
    chosen = [o.strip() for o in objects.split(",")] if objects else with_fine
    missing = sorted(set(chosen) - set(with_fine))
    if missing or not chosen:
        error(f"no fine refiner ships for {missing or 'any object'}")
    return chosen


def runtime_errors(obj: str, coarse: Path, fine: Path, data: Path, seed: int = 2024, symmetric: bool = False,
                   draws: int = 1, gate: tuple | None = None, coarse_views: int | None = None,
                   fine_views: int | None = None) -> dict:
    """Per instance of ``obj`` in ``data`` (every one: ``visib_fract >= 0.3``, the box of the loader), through the
    runtime on the full frames: the coarse refiner alone (``coarse``: one pass, as ``RefinerSession.refine`` runs it
    by default; ``coarse_cascade``: the cascade's views), the fine refiner alone (the cascade's views), the cascade's
    coarse pass then the fine refiner, and :class:`refiner_rt.RefinerCascade` with gates ``gate`` (``(gate_deg,
    coarse_gate_deg)``; default: the object's shipped gates), from U(0, 30) inputs and from the true pose
    (the drift). The cascade's two paths are each run for every instance, so :func:`with_gate` gives the cascade of
    any other gates from the same arrays; ``cascade`` here is the one of ``gate`` (exactly what
    ``RefinerCascade.refine`` returns: the same calls). ``draws``: U(0, 30) inputs per instance (seeds ``seed``,
    ``seed + 1``...; the arrays hold them one draw after the other). ``symmetric``: errors to the closest symmetric
    pose of ``models.data.objects``' symmetries (the can's turns), as ``refiner-rt eval --all`` scores real frames.
    ``coarse_views`` / ``fine_views``: box-jittered views each refiner averages (default ``RefinerCascade``'s,
    ``DEFAULT_COARSE_VIEWS`` and ``DEFAULT_FINE_VIEWS``). Returns the error arrays (degrees) by key, and
    ``fine_move`` and ``coarse_move`` (``@0``): the corrections of the fine refiner and of the cascade's coarse pass,
    degrees."""
    import cv2

    from models.data.noise import NoiseSpec, perturb
    from models.data.pipeline import load_splits, whole_folder_spec
    from models.data.symmetry import symmetric_error
    from refiner_rt import RefinerSession
    from refiner_rt import quaternion as rq
    from refiner_rt.cascade import DEFAULT_COARSE_VIEWS, DEFAULT_FINE_VIEWS, shipped_gate

    samples = list(load_splits(whole_folder_spec(data, obj, "test")).test)
    q_gt = np.array([rq.from_matrix(s.R) for s in samples])
    q_ins = [perturb(q_gt, NoiseSpec.parse("uniform:0:30"), np.random.default_rng(seed + k))[0] for k in range(draws)]
    c_sess, f_sess = RefinerSession(coarse, threads=1), RefinerSession(fine, threads=1)
    views = DEFAULT_FINE_VIEWS if fine_views is None else fine_views
    coarse_views = DEFAULT_COARSE_VIEWS if coarse_views is None else coarse_views
    by_image = defaultdict(list)
    for i, s in enumerate(samples):
        by_image[s.image_path].append(i)
    n = len(samples)
    out = {k + suffix: np.zeros((n * (draws if not suffix else 1), 4))
           for k in ("coarse", "coarse_cascade", "fine", "coarse_fine") for suffix in ("", "@0")}
    for path, idx in by_image.items():
        image = cv2.imread(path, cv2.IMREAD_COLOR)
        if image is None:
            raise FileNotFoundError(f"cannot read the frame {path}")
        boxes = np.array([samples[i].box_xyxy for i in idx])
        K = samples[idx[0]].K
        starts = [("", [i + k * n for i in idx], q_in[idx]) for k, q_in in enumerate(q_ins)] + [("@0", idx, q_gt[idx])]
        for suffix, rows, start in starts:
            mid = c_sess.refine(image, boxes, start, K=K, views=coarse_views).q_refined
            out["coarse_cascade" + suffix][rows] = mid
            out["coarse" + suffix][rows] = mid if coarse_views == 1 else c_sess.refine(image, boxes, start,
                                                                                       K=K).q_refined
            out["fine" + suffix][rows] = f_sess.refine(image, boxes, start, K=K, views=views).q_refined
            out["coarse_fine" + suffix][rows] = f_sess.refine(image, boxes, mid, K=K, views=views).q_refined
    truth = {"": np.tile(q_gt, (draws, 1)), "@0": q_gt}
    starts = {"": np.concatenate(q_ins), "@0": q_gt}

    def err(q, key):
        t = truth["@0" if "@" in key else ""]
        ids = np.array([obj] * len(t))
        return symmetric_error(q, t, ids, SYMMETRIES) if symmetric and obj in SYMMETRIES else rq.geodesic_angle(q, t)

    e = {"input": err(starts[""], ""), **{k: err(v, k) for k, v in out.items()},
         **{f"{k}_move{suffix}": rq.geodesic_angle(starts[suffix], out[k2 + suffix])
            for k, k2 in (("fine", "fine"), ("coarse", "coarse_cascade")) for suffix in ("", "@0")}}
    return with_gate(e, shipped_gate(obj) if gate is None else gate)


def with_gate(e: dict, gate: tuple) -> dict:
    """``e`` (:func:`runtime_errors`) with ``cascade``, ``cascade@0`` and their ``_coarse_used`` for the gates
    ``(gate_deg, coarse_gate_deg)`` (either ``None``: no such check; ``gate_deg`` None: always the coarse refiner
    then the fine one), as ``RefinerCascade`` picks its path."""
    from refiner_rt.cascade import long_way

    out = dict(e)
    for suffix in ("", "@0"):
        far = long_way(e["fine_move" + suffix], e["coarse_move" + suffix], *gate)
        out["cascade" + suffix] = np.where(far, e["coarse_fine" + suffix], e["fine" + suffix])
        out[f"cascade{suffix}_coarse_used"] = far
    out["gate"] = list(gate)
    return out


# The gates choose_gate weighs: the fine correction's and the coarse one's (degrees).
GATES = tuple((g, c) for g in (1.0, 1.5, 2.0, 2.5, 3.0, 4.0) for c in (4.0, 6.0, 8.0, 12.0))


def choose_gate(e: dict, gates=GATES) -> tuple[tuple, dict]:
    """The gates of ``gates`` with the smallest mean of the cascade's U(0, 30) mean and its drift (the two things a
    cascade is for, weighed alike), on :func:`runtime_errors`' arrays of scenes the card does not score:
    ``((gate_deg, coarse_gate_deg), {gates: [U(0, 30) mean, drift]})``."""
    scores = {}
    for g in gates:
        c = with_gate(e, g)
        scores[g] = [float(c["cascade"].mean()), float(c["cascade@0"].mean())]
    return min(gates, key=lambda g: sum(scores[g])), scores


def summarise(e: dict) -> dict:
    """The card's numbers from :func:`runtime_errors`' arrays: means, medians, the 0-3 degree inputs, the floor
    curve (mean output error per 1-degree input bin, ``None`` where a bin is empty)."""
    small = e["input"] < 3.0
    bins = np.minimum((e["input"]).astype(int), FLOOR_BINS - 1)
    out = {"n": int(len(e["input"])), "input_mean_deg": float(e["input"].mean()), "input_0_3_n": int(small.sum())}
    for k in [k for k in ("coarse", "coarse_cascade", "fine", "cascade") if k in e]:  # coarse_cascade: views > 1
        out[k] = {"mean_deg": float(e[k].mean()), "median_deg": float(np.median(e[k])),
                  "drift_mean_deg": float(e[k + "@0"].mean()), "drift_median_deg": float(np.median(e[k + "@0"])),
                  "input_0_3_mean_deg": float(e[k][small].mean()) if small.any() else None,
                  "floor_curve": [float(e[k][bins == b].mean()) if (bins == b).any() else None
                                  for b in range(FLOOR_BINS)]}
    out["gate"] = e.get("gate")
    out["cascade"]["coarse_used"] = float(e["cascade_coarse_used"].mean())
    out["cascade"]["coarse_used_at_truth"] = float(e["cascade@0_coarse_used"].mean())
    out["floor_curve_n"] = [int((bins == b).sum()) for b in range(FLOOR_BINS)]
    return out


def measure_cascade(obj: str, coarse: Path, fine: Path, heldout: Path, calibration: Path) -> tuple[dict, dict]:
    """The object's gate, chosen on ``calibration`` (:func:`choose_gate`: rendered scenes the card does not score),
    and the cascade with it on ``heldout`` (:func:`summarise`): ``(gate record, summary)``."""
    from refiner_rt.cascade import DEFAULT_COARSE_VIEWS, DEFAULT_FINE_VIEWS

    gate, scores = choose_gate(runtime_errors(obj, coarse, fine, calibration, seed=7))
    record = {"deg": gate[0], "coarse_deg": gate[1], "chosen_on": calibration.resolve().name, "seed": 7,
              "coarse_views": DEFAULT_COARSE_VIEWS, "fine_views": DEFAULT_FINE_VIEWS,
              "scores": {f"{g[0]:g}/{g[1]:g}": {"mean_deg": round(v[0], 3), "drift_mean_deg": round(v[1], 3)}
                         for g, v in scores.items()},
              "rule": "the smallest mean of the cascade's U(0, 30) mean and its drift"}
    return record, summarise(runtime_errors(obj, coarse, fine, heldout, gate=gate))
