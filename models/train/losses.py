"""The geodesic loss in PyTorch, for training the refiners (the quaternion maths: :mod:`models.nets.quaternion`).

The loss is the paper's geodesic angle between the predicted correction and its label,
``2 * acos(|w(q_pred * q_label^-1)|)`` (Jain & Dellaert, section "Training"), computed in the numerically safe
form ``2 * atan2(|v|, |w|)`` (as :func:`refiner_rt.quaternion.geodesic_angle_rad`): exact near 0 and pi, and with a
finite gradient at a perfect prediction, where ``acos`` has an infinite slope and ``|v|`` an undefined one.

Conventions (docs/design.md §2.1): quaternions ``wxyz`` (scalar first), Hamilton product, shape ``(..., 4)``;
``q`` and ``-q`` are the same rotation (the loss ignores the sign).
"""

from __future__ import annotations

import torch

from models.nets.quaternion import check_quaternions, quat_conjugate, quat_multiply

__all__ = ["geodesic_angle_rad", "geodesic_loss"]


def geodesic_angle_rad(q_a: torch.Tensor, q_b: torch.Tensor) -> torch.Tensor:
    """Angle of the rotation ``q_a * q_b^-1`` in radians, in ``[0, pi]``, per quaternion pair.

    Scale-invariant (``2 * atan2(|v|, |w|)`` of the relative quaternion), so the inputs need not be exactly unit;
    the sign of either input does not matter. The gradient is finite everywhere except at zero quaternions: at
    ``v = 0`` (identical rotations) the subgradient 0 is used for ``|v|``.

    Args:
        q_a: ``(..., 4)`` quaternions, ``wxyz``, non-zero.
        q_b: ``(..., 4)`` quaternions, ``wxyz``, non-zero; broadcast against ``q_a``.

    Returns:
        ``(...)`` angles in radians.
    """
    check_quaternions(q_a, "q_a")
    check_quaternions(q_b, "q_b")
    rel = quat_multiply(q_a, quat_conjugate(q_b))
    sq = (rel[..., 1:] ** 2).sum(dim=-1)
    positive = sq > 0
    # Double where: sqrt is evaluated only where its gradient is finite.
    v_norm = torch.where(positive, torch.sqrt(torch.where(positive, sq, torch.ones_like(sq))), torch.zeros_like(sq))
    return 2.0 * torch.atan2(v_norm, rel[..., 0].abs())


def geodesic_loss(q_pred: torch.Tensor, q_label: torch.Tensor) -> torch.Tensor:
    """Mean geodesic angle between predicted and label rotations, in radians (the paper's fine-tuning loss).

    Args:
        q_pred: ``(N, 4)`` predicted corrections ``q_out``, ``wxyz`` (unit norm from the model).
        q_label: ``(N, 4)`` labels ``q_noise^-1``, ``wxyz``.

    Returns:
        Scalar tensor: ``mean(2 * atan2(|v|, |w|))`` of ``q_pred * q_label^-1``.

    Raises:
        ValueError: shapes are not ``(..., 4)`` or differ.
    """
    check_quaternions(q_pred, "q_pred")
    check_quaternions(q_label, "q_label")
    if q_pred.shape != q_label.shape:
        raise ValueError(f"q_pred and q_label must have the same shape (N, 4); got {tuple(q_pred.shape)} and {tuple(q_label.shape)}")
    return geodesic_angle_rad(q_pred, q_label).mean()
