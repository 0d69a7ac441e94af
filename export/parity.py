"""Parity between an exported ONNX refiner and its PyTorch model: onnxruntime (and OpenCV's cv2.dnn) vs torch.

The exporter treats export as a test (docs/design.md §4.4): the same fixed-seed random inputs (uint8 crops and unit
quaternions) go through PyTorch and onnxruntime, in batches of different sizes so the dynamic batch axis is
exercised, and the largest absolute difference of any ``q_out`` component, ``max |dq|``, must not exceed the
tolerance (fp32: 1e-4).

Conventions: images ``(N, S, S, 3)`` uint8 NHWC in the model's channel order (BGR by default); quaternions
``(N, 4)`` float32 ``wxyz``. Graph input/output names come from :mod:`refiner_rt.metadata`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from refiner_rt.metadata import INPUT_IMAGE, INPUT_QUATERNION, OUTPUT_QUATERNION

__all__ = [
    "DEFAULT_TOL",
    "MIN_PARITY_INPUTS",
    "PARITY_SEED",
    "ParityResult",
    "batch_slices",
    "check_parity",
    "onnxruntime_outputs",
    "opencv_dnn_outputs",
    "random_inputs",
    "torch_outputs",
]

logger = logging.getLogger(__name__)

DEFAULT_TOL = 1e-4  # fp32 max |dq| (docs/design.md §4.4)
MIN_PARITY_INPUTS = 64
PARITY_SEED = 0
_MAX_BATCH = 16


@dataclass(frozen=True)
class ParityResult:
    """Outcome of a parity check.

    Attributes:
        max_abs_dq: largest ``|q_onnx - q_torch|`` over all inputs and the 4 components.
        n_inputs: number of random inputs compared.
        tol: tolerance the check was held to.
    """

    max_abs_dq: float
    n_inputs: int
    tol: float

    @property
    def passed(self) -> bool:
        """``max_abs_dq <= tol`` (NaN never passes)."""
        return bool(self.max_abs_dq <= self.tol)

    def __str__(self) -> str:
        verdict = "OK" if self.passed else "FAILED"
        return f"parity {verdict}: max |dq| = {self.max_abs_dq:.3g} over {self.n_inputs} inputs (tol {self.tol:g})"


def random_inputs(input_size: int, n: int, seed: int = PARITY_SEED) -> tuple[np.ndarray, np.ndarray]:
    """Fixed-seed random test inputs.

    Args:
        input_size: crop side ``S``.
        n: number of inputs.
        seed: seed of the ``numpy.random.Generator``.

    Returns:
        ``(images, q_in)``: ``(n, S, S, 3)`` uint8 uniform in [0, 255] (NHWC; any channel order), and ``(n, 4)``
        float32 unit quaternions (``wxyz``, uniform on the sphere).
    """
    rng = np.random.default_rng(seed)
    images = rng.integers(0, 256, size=(n, input_size, input_size, 3), dtype=np.uint8)
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return images, q.astype(np.float32)


def batch_slices(n: int) -> list[slice]:
    """Split ``n`` inputs into batches of 1, 3, then up to 16, so several batch sizes are exercised."""
    slices, start = [], 0
    for size in (1, 3):
        if start < n:
            slices.append(slice(start, min(start + size, n)))
            start = slices[-1].stop
    while start < n:
        slices.append(slice(start, min(start + _MAX_BATCH, n)))
        start = slices[-1].stop
    return slices


def torch_outputs(model: torch.nn.Module, images: np.ndarray, q_in: np.ndarray) -> np.ndarray:
    """``q_out`` of a PyTorch refiner (evaluated as is: call ``model.eval()`` first for inference).

    Args:
        model: refiner with ``forward(image, q_in)``.
        images: ``(N, S, S, 3)`` uint8, NHWC, the model's channel order.
        q_in: ``(N, 4)`` float32, ``wxyz``.

    Returns:
        ``(N, 4)`` float32 ``q_out``, ``wxyz``.
    """
    outs = []
    with torch.no_grad():
        for sl in batch_slices(len(images)):
            outs.append(model(torch.from_numpy(images[sl]), torch.from_numpy(q_in[sl])).numpy())
    return np.concatenate(outs).astype(np.float32)


def onnxruntime_outputs(model_path, images: np.ndarray, q_in: np.ndarray) -> np.ndarray:
    """``q_out`` of an ONNX refiner in onnxruntime (CPU provider), in batches of several sizes.

    Args:
        model_path: ``.onnx`` file path, or the model's bytes.
        images: ``(N, S, S, 3)`` uint8, NHWC, the model's channel order.
        q_in: ``(N, 4)`` float32, ``wxyz``.

    Returns:
        ``(N, 4)`` float32 ``q_out``, ``wxyz``.
    """
    import onnxruntime as ort

    source = str(model_path) if isinstance(model_path, (str, Path)) else model_path
    session = ort.InferenceSession(source, providers=["CPUExecutionProvider"])
    outs = [
        session.run([OUTPUT_QUATERNION], {INPUT_IMAGE: images[sl], INPUT_QUATERNION: q_in[sl]})[0]
        for sl in batch_slices(len(images))
    ]
    return np.concatenate(outs).astype(np.float32)


def opencv_dnn_outputs(model_path, images: np.ndarray, q_in: np.ndarray) -> np.ndarray:
    """``q_out`` of an ONNX refiner in OpenCV's ``cv2.dnn``, in batches of several sizes.

    The uint8 ``image`` input is passed to ``cv2.dnn`` as uint8 (OpenCV 5 checks the graph input's type and
    rejects float32 for it).

    Args:
        model_path: ``.onnx`` file path.
        images: ``(N, S, S, 3)`` uint8, NHWC, the model's channel order.
        q_in: ``(N, 4)`` float32, ``wxyz``.

    Returns:
        ``(N, 4)`` float32 ``q_out``, ``wxyz``.
    """
    import cv2

    net = cv2.dnn.readNetFromONNX(str(model_path))
    outs = []
    for sl in batch_slices(len(images)):
        net.setInput(np.ascontiguousarray(images[sl]), INPUT_IMAGE)
        net.setInput(np.ascontiguousarray(q_in[sl]), INPUT_QUATERNION)
        outs.append(np.array(net.forward(OUTPUT_QUATERNION), dtype=np.float32).reshape(-1, 4))
    return np.concatenate(outs)


def check_parity(
    model: torch.nn.Module,
    onnx_model,
    *,
    n: int = MIN_PARITY_INPUTS,
    tol: float = DEFAULT_TOL,
    seed: int = PARITY_SEED,
) -> ParityResult:
    """Compare onnxruntime against PyTorch on ``n`` fixed-seed random inputs.

    Args:
        model: the PyTorch refiner (evaluated in eval mode; its mode is restored afterwards).
        onnx_model: the exported model, path or bytes.
        n: number of random inputs (at least 64).
        tol: tolerance on ``max |dq|``.
        seed: seed of the random inputs.

    Returns:
        :class:`ParityResult` (check ``.passed``; this function does not raise on a failed check).

    Raises:
        ValueError: ``n < 64`` or ``tol`` not positive.
    """
    if n < MIN_PARITY_INPUTS:
        raise ValueError(f"parity needs at least {MIN_PARITY_INPUTS} inputs; got n={n}")
    if not tol > 0:
        raise ValueError(f"parity tolerance must be > 0; got tol={tol}")
    images, q_in = random_inputs(model.input_size, n, seed)
    was_training = model.training
    model.eval()
    try:
        expected = torch_outputs(model, images, q_in)
    finally:
        model.train(was_training)
    got = onnxruntime_outputs(onnx_model, images, q_in)
    diff = np.abs(got.astype(np.float64) - expected.astype(np.float64))
    max_abs_dq = float(diff.max()) if np.all(np.isfinite(diff)) else float("nan")
    result = ParityResult(max_abs_dq=max_abs_dq, n_inputs=n, tol=float(tol))
    logger.info("%s", result)
    return result
