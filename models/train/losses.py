"""Quaternion helpers and the geodesic loss in PyTorch, for training the refiners.

The loss is the paper's geodesic angle between the predicted correction and its label,
``2 * acos(|w(q_pred * q_label^-1)|)`` (Jain & Dellaert, section "Training"), computed in the numerically safe
form ``2 * atan2(|v|, |w|)`` (as :func:`refiner_rt.quaternion.geodesic_angle_rad`): exact near 0 and pi, and with a
finite gradient at a perfect prediction, where ``acos`` has an infinite slope and ``|v|`` an undefined one.

Conventions (docs/design.md §2.1): quaternions ``wxyz`` (scalar first), Hamilton product, shape ``(..., 4)``;
``q`` and ``-q`` are the same rotation (the loss ignores the sign).
"""

from __future__ import annotations

import torch

__all__ = ["geodesic_angle_rad", "geodesic_loss", "quat_conjugate", "quat_multiply", "wxyz"]


def _check_quaternions(q: torch.Tensor, name: str) -> None:
    if not isinstance(q, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape (..., 4), wxyz; got {type(q).__name__}")
    if q.dim() == 0 or q.shape[-1] != 4:
        raise ValueError(f"{name} must have shape (..., 4), wxyz; got {tuple(q.shape)}")


def wxyz(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split quaternions into their components.

    Args:
        q: ``(..., 4)`` quaternions, ``wxyz``.

    Returns:
        ``(w, x, y, z)``, each of shape ``(...)``.
    """
    _check_quaternions(q, "q")
    return q[..., 0], q[..., 1], q[..., 2], q[..., 3]


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``), as :func:`refiner_rt.quaternion.multiply`.

    Args:
        a: ``(..., 4)`` quaternions, ``wxyz``.
        b: ``(..., 4)`` quaternions, ``wxyz``; broadcast against ``a``.

    Returns:
        ``(..., 4)`` quaternions, ``wxyz`` (sign not canonicalised).
    """
    _check_quaternions(b, "b")
    aw, ax, ay, az = wxyz(a)
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """Conjugate ``(w, -x, -y, -z)``: the inverse rotation of a unit quaternion.

    Args:
        q: ``(..., 4)`` quaternions, ``wxyz``.

    Returns:
        ``(..., 4)`` quaternions, ``wxyz``.
    """
    _check_quaternions(q, "q")
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


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
    _check_quaternions(q_a, "q_a")
    _check_quaternions(q_b, "q_b")
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
    _check_quaternions(q_pred, "q_pred")
    _check_quaternions(q_label, "q_label")
    if q_pred.shape != q_label.shape:
        raise ValueError(f"q_pred and q_label must have the same shape (N, 4); got {tuple(q_pred.shape)} and {tuple(q_label.shape)}")
    return geodesic_angle_rad(q_pred, q_label).mean()
