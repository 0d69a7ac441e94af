"""Viewing-ray frame and view jitter: the torch-free geometry that the runtime and training share.

A crop shows the object's rotation relative to the ray through the box centre (docs/design.md §2.7, "The
viewing-ray frame"); :func:`ray_quaternions` gives that ray's rotation from the camera frame. :func:`view_boxes`
gives the fixed jittered windows of ``RefinerSession.refine(views=K)``. numpy only: ``models`` imports it from here,
so training never imports the ONNX session.

Conventions: quaternions ``wxyz`` (scalar first), float64; boxes ``(x1, y1, x2, y2)`` in continuous pixels;
``K`` in pixels with OpenCV's pixel centres at integers.
"""

from __future__ import annotations

import math

import numpy as np

from refiner_rt import quaternion as rq

__all__ = ["MAX_VIEWS", "VIEW_JITTER", "ray_quaternions", "ray_quaternion_rows", "is_pinhole", "view_boxes",
           "view_offsets"]

# refine(views=K): the largest K, and the box jitter of the extra views as a fraction of the crop window (the
# training's --augment box jitter, models.train.config.TrainConfig.box_jitter).
MAX_VIEWS = 16
VIEW_JITTER = 0.05


def _halton(index: int, base: int) -> float:
    """The ``index``-th element (from 1) of the van der Corput sequence in ``base``: in (0, 1), evenly spread."""
    f, r = 1.0, 0.0
    while index > 0:
        f /= base
        r += f * (index % base)
        index //= base
    return r


# View v >= 1 shifts the window's centre by (dx, dy) and scales it by (1 + ds), each in [-1, 1] x VIEW_JITTER:
# a fixed 3-D Halton pattern, so every call and every box get the same views. View 0 is the box itself.
_VIEW_OFFSETS = np.array([[2 * _halton(v, b) - 1 for b in (2, 3, 5)] for v in range(1, MAX_VIEWS)])


def view_offsets(views: int) -> np.ndarray:
    """``(views, 3)``: each view's window shift ``(dx, dy)`` as a fraction of the window side and its scale change
    ``ds`` (side ``* (1 + ds)``); view 0 is the box itself (zeros)."""
    return np.vstack([np.zeros((1, 3)), _VIEW_OFFSETS[: views - 1]]) * VIEW_JITTER


def view_boxes(boxes_xyxy: np.ndarray, views: int, context: float) -> np.ndarray:
    """``(N * views, 4)`` boxes, object-major: each box, then ``views - 1`` fixed jitters of it (see ``refine``)."""
    b = np.asarray(boxes_xyxy, dtype=np.float64)
    centre = 0.5 * (b[:, :2] + b[:, 2:])
    half = 0.5 * (b[:, 2:] - b[:, :2])
    window = context * 2 * half.max(axis=1)
    offsets = view_offsets(views)
    c = centre[:, None, :] + offsets[None, :, :2] * window[:, None, None]
    h = half[:, None, :] * (1 + offsets[None, :, 2:])
    return np.concatenate([c - h, c + h], axis=2).reshape(-1, 4)



def ray_quaternions(K, boxes_xyxy) -> np.ndarray:
    """Rotations from the camera frame to the viewing-ray frame of each box centre.

    The ray frame is the camera frame rotated by the smallest rotation that takes the optical
    axis ``(0, 0, 1)`` onto the ray through the box centre, ``d = K^-1 (cx, cy, 1)``. A crop shows
    the object's rotation relative to that ray: ``q_ray_frame = q_ray^-1 * q_camera``.

    Args:
        K: ``(3, 3)`` camera intrinsics (pixels), ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, or
            ``(N, 3, 3)``, one per box.
        boxes_xyxy: ``(N, 4)`` boxes ``(x1, y1, x2, y2)`` in pixels.

    Returns:
        ``(N, 4)`` float64 ``wxyz`` unit quaternions ``q_ray`` (``R(q_ray) @ (0, 0, 1) = d / |d|``).
    """
    K = np.asarray(K, dtype=np.float64)
    boxes = np.asarray(boxes_xyxy, dtype=np.float64)
    # Continuous pixel centre -> the projection model's coordinates (pixel i centred at i + 0.5 in
    # continuous coordinates; K follows OpenCV's convention of pixel centres at integers).
    u = 0.5 * (boxes[:, 0] + boxes[:, 2]) - 0.5
    v = 0.5 * (boxes[:, 1] + boxes[:, 3]) - 0.5
    if is_pinhole(K):
        # d = K^-1 (u, v, 1) by back-substitution, the operations ray_quaternion_rows repeats on Python floats.
        fx, s, cx, fy, cy = K[..., 0, 0], K[..., 0, 1], K[..., 0, 2], K[..., 1, 1], K[..., 1, 2]
        y = (v - cy) / fy
        x = (u - cx - s * y) / fx
        z = np.ones_like(x)
    else:
        d = np.einsum("...ij,...j->...i", np.linalg.inv(K), np.stack([u, v, np.ones_like(u)], axis=-1))
        x, y, z = d[..., 0], d[..., 1], d[..., 2]
    # Half-way quaternion: with n = |d|, q ~ (n + d_z, z x d) = (n + d_z, -d_y, d_x, 0) rotates z onto d
    # (d never opposite z here). Sums in a fixed order so that ray_quaternion_rows matches bit for bit.
    a = np.sqrt(x * x + y * y + z * z) + z
    m = np.sqrt(a * a + y * y + x * x)
    q = np.stack([a / m, -y / m, x / m, np.zeros_like(a)], axis=-1)
    return rq.canonical(q)


def is_pinhole(K: np.ndarray) -> bool:
    """Whether ``K`` (``(3, 3)`` or ``(N, 3, 3)``) has the pinhole form ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``."""
    if K.ndim == 2:  # on Python floats: ~50x cheaper than three np.all calls at this size (timeit)
        rows = K.tolist()
        return rows[1][0] == 0.0 and rows[2] == [0.0, 0.0, 1.0]
    return bool(np.all(K[..., 1, 0] == 0.0) and np.all(K[..., 2, :2] == 0.0) and np.all(K[..., 2, 2] == 1.0))


def ray_quaternion_rows(K: np.ndarray, rows: list) -> list:
    """:func:`ray_quaternions`' fast twin on Python floats for a pinhole ``K`` (``(3, 3)``) and ``N`` boxes given as
    lists ``[x1, y1, x2, y2]``: the same operations in the same order, so the results are identical.
    ``w = a / m > 0`` always, so no sign flip is needed."""
    (fx, s, cx), (_, fy, cy) = K[0].tolist(), K[1].tolist()
    sqrt = math.sqrt
    out = []
    for x1, y1, x2, y2 in rows:
        y = (0.5 * (y1 + y2) - 0.5 - cy) / fy
        x = (0.5 * (x1 + x2) - 0.5 - cx - s * y) / fx
        a = sqrt(x * x + y * y + 1.0) + 1.0
        m = sqrt(a * a + y * y + x * x)
        out.append([a / m, -y / m, x / m, 0.0])
    return out
