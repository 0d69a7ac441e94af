"""Quaternion maths in PyTorch for the networks and their losses: the Hamilton product and the conjugate, batched,
differentiable, with the checks every function applies.

Conventions (docs/design.md §2.1): quaternions ``wxyz`` (scalar first), Hamilton product, shape ``(..., 4)``;
``q`` and ``-q`` are the same rotation. The numpy twins are :mod:`refiner_rt.quaternion`'s.
"""

from __future__ import annotations

import torch

__all__ = ["check_quaternions", "quat_conjugate", "quat_multiply", "wxyz"]


def check_quaternions(q: torch.Tensor, name: str) -> None:
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
    check_quaternions(q, "q")
    return q[..., 0], q[..., 1], q[..., 2], q[..., 3]


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``), as :func:`refiner_rt.quaternion.multiply`.

    Args:
        a: ``(..., 4)`` quaternions, ``wxyz``.
        b: ``(..., 4)`` quaternions, ``wxyz``; broadcast against ``a``.

    Returns:
        ``(..., 4)`` quaternions, ``wxyz`` (sign not canonicalised).
    """
    check_quaternions(b, "b")
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
    check_quaternions(q, "q")
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)
