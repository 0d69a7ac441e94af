"""Evaluation: coarse poses drawn with a fixed seed, refined by a model, scored with the paper's metric.

A *predictor* maps ``(crops (N, S, S, 3) uint8 BGR, q_in (N, 4) wxyz)`` to ``q_out (N, 4) wxyz``.
ONNX models are evaluated through :class:`refiner_rt.RefinerSession` (the deployed runtime, no
torch); checkpoints through PyTorch. Both see identical crops and identical coarse poses, so their
numbers are directly comparable. Angles in degrees.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.data.cropset import CropSet
from models.evaluate.metrics import summarize_errors
from models.data.noise import NoiseSpec, perturb
from models.data.symmetry import symmetric_error
from refiner_rt import quaternion as rq
# Imported with the module, not when a long training run first scores its test split: a process that started before
# the runtime's files changed on disk must not fail at its end on a mix of the old and the new.
from refiner_rt.checks import validate_settle
from refiner_rt.session import settle_keeps

__all__ = ["EvalErrors", "evaluate_errors", "evaluate_folder", "folder_cropset", "onnx_predictor", "torch_predictor"]

Predictor = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass
class EvalErrors:
    """Per-sample errors (degrees) of one evaluation; ``summary()`` gives the paper's table."""

    obj_ids: np.ndarray
    err_in_deg: np.ndarray
    err_out_deg: np.ndarray
    #: ``(N, 4)`` ground truth, coarse inputs and refined rotations in the evaluated rotation frame (for analyses
    #: beyond the angle, e.g. ``benchmarks/error_breakdown.py``).
    q_true: np.ndarray | None = None
    q_in: np.ndarray | None = None
    q_refined: np.ndarray | None = None

    def summary(self) -> dict:
        return summarize_errors(self.obj_ids, self.err_out_deg, self.err_in_deg)


def evaluate_errors(
    predictor: Predictor | dict[str, Predictor],
    data: CropSet,
    noise: str | NoiseSpec = "uniform:0:30",
    *,
    seed: int = 2024,
    resample: int = 1,
    iterations: int = 1,
    rotation_frame: str = "camera",
    symmetries: dict | None = None,
    settle_deg: float | None = None,
) -> EvalErrors:
    """Refine ``data`` from coarse poses ``q_gt * q_noise`` and measure the geodesic error.

    Args:
        predictor: one predictor, or ``{obj_id: predictor}`` (per-object fine-tuned models; every
            object in ``data`` must have one).
        data: test crops with ground truth.
        noise: coarse-pose noise (``"uniform:0:30"`` ...).
        seed: seed of the coarse poses (the same seed gives the same inputs to every model).
        resample: evaluate each crop with this many different coarse poses (the paper's over-fitting test).
        iterations: refinement iterations (``q <- q * q_out`` repeated).
        rotation_frame: the models' frame, ``"camera"`` or ``"ray"``. Errors are frame-independent.
        symmetries: object name -> symmetry (BOP ``models_info.json`` form); those objects' errors are to the
            closest symmetric pose (:func:`models.data.symmetry.symmetric_error`), the inputs' too.
        settle_deg: with ``iterations >= 2``, a later iteration is kept only for the samples it turns by more than
            this many degrees, and the others stop (:meth:`refiner_rt.RefinerSession.refine`'s ``settle_deg``).

    Returns:
        :class:`EvalErrors` with ``N * resample`` samples.
    """
    if resample < 1 or iterations < 1:
        raise ValueError(f"resample and iterations must be >= 1; got {resample}, {iterations}")
    settle_deg = validate_settle(settle_deg, iterations)
    noise = NoiseSpec.parse(noise) if isinstance(noise, str) else noise
    rng = np.random.default_rng(seed)
    q_gt = data.q_gt_in(rotation_frame)
    if isinstance(predictor, dict):
        missing = sorted(set(data.objects) - set(predictor))
        if missing:
            raise ValueError(f"no model for object(s) {missing}; models given for {sorted(predictor)}")
    ids, e_in, e_out, qs_in, qs_out = [], [], [], [], []
    for _ in range(resample):
        q_in, _ = perturb(q_gt, noise, rng)
        q = q_in
        going = np.ones(len(q), dtype=bool)  # samples whose iterations go on (settle_deg stops the others)
        for k in range(iterations):
            if isinstance(predictor, dict):
                q_out = np.zeros_like(q)
                for obj, fn in predictor.items():
                    m = (data.obj_ids == obj) & going
                    if m.any():
                        q_out[m] = fn(data.crops[np.flatnonzero(m)], q[m])
            else:
                q_out = np.zeros_like(q)
                q_out[going] = predictor(data.crops[np.flatnonzero(going)] if not going.all() else data.crops,
                                         q[going])
            q_next = q.copy()
            q_next[going] = rq.normalize(rq.multiply(q[going], q_out[going]))
            if k > 0 and settle_deg is not None:
                going &= settle_keeps(q, q_next, settle_deg)
                q = np.where(going[:, None], q_next, q)
            else:
                q = q_next
            if not going.any():
                break
        ids.append(data.obj_ids)
        e_in.append(symmetric_error(q_in, q_gt, data.obj_ids, symmetries))
        e_out.append(symmetric_error(q, q_gt, data.obj_ids, symmetries))
        qs_in.append(q_in)
        qs_out.append(q)
    return EvalErrors(np.concatenate(ids), np.concatenate(e_in), np.concatenate(e_out),
                      q_true=np.concatenate([q_gt] * resample), q_in=np.concatenate(qs_in),
                      q_refined=np.concatenate(qs_out))


def onnx_predictor(model: str | Path | bytes, threads: int = 0, batch_size: int = 256) -> Predictor:
    """A predictor running an exported model through :class:`refiner_rt.RefinerSession.refine_crops`."""
    from refiner_rt import RefinerSession

    sess = RefinerSession(model, threads=threads)

    def run(crops: np.ndarray, q_in: np.ndarray) -> np.ndarray:
        out = [
            sess.refine_crops(np.ascontiguousarray(crops[i : i + batch_size]), q_in[i : i + batch_size]).q_out
            for i in range(0, len(crops), batch_size)
        ]
        return np.concatenate(out) if out else np.zeros((0, 4))

    run.session = sess
    return run


def torch_predictor(model, batch_size: int = 256) -> Predictor:
    """A predictor running a PyTorch refiner in eval mode."""
    from models.train.loop import predict

    return lambda crops, q_in: predict(model, crops, q_in, batch_size)


def folder_cropset(data: str | Path, objects: list[str], size: int, context: float, *, min_visib: float = 0.3,
                   min_box_size: float = 16.0, cache_root: str | Path | None = None, progress: bool = False,
                   crop_filter: str = "none"):
    """Every instance of ``objects`` in a BOP or YCB-Video folder (no split: real frames, or rendered scenes no
    model trained on) with ``visib_fract >= min_visib`` and a visible box of ``min_box_size`` px or more, cropped
    by the crop rule (with the model's ``crop_filter``): ``(CropSet, samples)`` in the same order.

    The crops are cached under ``cache_root`` (default: ``<data>/.crops``, or the user's cache folder when ``data``
    is read-only).

    Raises:
        ValueError: no such instance in ``data`` (the message names the folder, the objects and the filter).
    """
    from models.data import CropCache
    from models.data.pipeline import DataSpec, load_samples, writable_cache_root
    from refiner_rt.geometry import ray_quaternions

    spec = DataSpec(data=str(data), objects=list(objects), split_mode="scenes", sizes=(0, 0, 0, 0),
                    min_visib=min_visib, min_box_size=min_box_size)
    samples = load_samples(spec)
    key = json.dumps({**spec.as_dict(), "part": "all", "size": size, "context": context,
                      **({"crop_filter": crop_filter} if crop_filter != "none" else {})}, sort_keys=True)
    folder = writable_cache_root(Path(data), cache_root) / f"all_{size}_{hashlib.sha1(key.encode()).hexdigest()[:10]}"
    cache = CropCache.build_or_load(samples, size, folder, context=context, progress=progress,
                                    crop_filter=crop_filter)
    crops = CropSet(crops=cache.crops, q_gt=cache.q_gt, obj_ids=cache.obj_ids,
                    q_ray=ray_quaternions(cache.K, cache.boxes_xyxy), scene_ids=np.asarray(cache.scene_ids))
    return crops, samples


def evaluate_folder(
    predictor: Predictor | dict[str, Predictor],
    crops: CropSet,
    *,
    rotation_frame: str,
    noise: str = "uniform:0:30",
    draws: int = 10,
    seed: int = 2024,
    symmetries: dict | None = None,
) -> dict:
    """Score every instance of ``crops`` (see :func:`folder_cropset`): ``draws`` coarse inputs each, and the drift
    from the ground truth (the true pose given as the input: how far a perfect pose is moved).

    Errors of the objects in ``symmetries`` are to the closest symmetric pose. Returns the JSON-ready result:
    ``objects`` (per object: mean, median, shares, input mean, ``drift_mean_deg``, ``videos`` and
    ``video_mean_deg``, the mean of its per-video means), ``mean_deg`` (the mean over objects), ``pooled_mean_deg``
    (over instances), ``drift_mean_deg`` (mean over objects), ``video_mean_deg`` (mean over objects of their
    per-video means), and the protocol.
    """
    errors = evaluate_errors(predictor, crops, noise, seed=seed, resample=draws, rotation_frame=rotation_frame,
                             symmetries=symmetries)
    drift = evaluate_errors(predictor, crops, "uniform:0:0", seed=seed, rotation_frame=rotation_frame,
                            symmetries=symmetries)
    summary = errors.summary()
    scenes = np.concatenate([crops.scene_ids.astype(str)] * draws)
    objects = {}
    for obj, stats in summary["objects"].items():
        keep = errors.obj_ids == obj
        videos = {v: float(errors.err_out_deg[keep & (scenes == v)].mean()) for v in sorted(set(scenes[keep]))}
        objects[obj] = {**stats, "instances": int((crops.obj_ids == obj).sum()),
                        "drift_mean_deg": float(drift.err_out_deg[drift.obj_ids == obj].mean()),
                        "videos": videos, "video_mean_deg": float(np.mean(list(videos.values())))}
    mean = lambda key: float(np.mean([o[key] for o in objects.values()]))  # noqa: E731
    return {
        "objects": objects,
        "mean_deg": mean("mean_deg"),
        "input_mean_deg": mean("input_mean_deg"),
        "drift_mean_deg": mean("drift_mean_deg"),
        "video_mean_deg": mean("video_mean_deg"),
        "pooled_mean_deg": float(errors.err_out_deg.mean()),
        "instances": int(len(crops)),
        "protocol": {"noise": str(noise), "draws": draws, "seed": seed, "drift": "input = the true pose",
                     "symmetries": symmetries or {}, "error": "geodesic, to the closest symmetric pose for "
                     "the objects in symmetries", "mean_deg": "mean over objects of the per-object mean"},
    }
