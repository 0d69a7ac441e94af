"""Evaluation: coarse poses drawn with a fixed seed, refined by a model, scored with the paper's metric.

A *predictor* maps ``(crops (N, S, S, 3) uint8 BGR, q_in (N, 4) wxyz)`` to ``q_out (N, 4) wxyz``.
ONNX models are evaluated through :class:`refiner_rt.RefinerSession` (the deployed runtime, no
torch); checkpoints through PyTorch. Both see identical crops and identical coarse poses, so their
numbers are directly comparable. Angles in degrees.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.cropset import CropSet
from models.metrics import summarize_errors
from models.noise import NoiseSpec, perturb
from models.symmetry import symmetric_error
from refiner_rt import quaternion as rq

__all__ = ["EvalErrors", "evaluate_errors", "onnx_predictor", "torch_predictor"]

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
            closest symmetric pose (:func:`models.symmetry.symmetric_error`), the inputs' too.

    Returns:
        :class:`EvalErrors` with ``N * resample`` samples.
    """
    if resample < 1 or iterations < 1:
        raise ValueError(f"resample and iterations must be >= 1; got {resample}, {iterations}")
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
        for _ in range(iterations):
            if isinstance(predictor, dict):
                q_out = np.zeros_like(q)
                for obj, fn in predictor.items():
                    m = data.obj_ids == obj
                    if m.any():
                        q_out[m] = fn(data.crops[np.flatnonzero(m)], q[m])
            else:
                q_out = predictor(data.crops, q)
            q = rq.normalize(rq.multiply(q, q_out))
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
    from models.train import predict

    return lambda crops, q_in: predict(model, crops, q_in, batch_size)
