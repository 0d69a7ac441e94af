"""Where an object sits when only its box is known: the translation that puts the projected bounding box of the
posed object on the box (:func:`fit_translation`, docs/pose6d.md "Translation"), and the shipped extent points it
fits (:func:`load_extents`, ``weights/extents.json``: per object the mesh vertices farthest along 1,024 directions,
whose projected bounding box is the mesh's own from any viewpoint).

One fit for the whole runtime: :class:`refiner_rt.estimate.PoseEstimator` places its poses with it, and the drawings
(:func:`refiner_rt.draw.annotate_poses`, the demo's picture of your image) place an outline whose translation is not
known with it. numpy only.

Conventions: rotations object to camera (``x_cam = R @ x_obj + t``), translations in metres, the shipped models'
object frame (the YCB google_16k scan frame); boxes ``(x1, y1, x2, y2)`` pixels, continuous coordinates (pixel ``i``
covers ``[i, i+1)``); ``K`` the ``(3, 3)`` pinhole matrix with OpenCV's pixel centres at integers.
"""

from __future__ import annotations

import json
from functools import lru_cache

import numpy as np

from refiner_rt.pretrained import WEIGHTS_DIR

__all__ = ["fit_translation", "load_extents", "pixel_coordinates", "sides_clear_of_border", "BORDER_PX",
           "EXTENTS_FILE", "EXTENTS_FORMAT"]

# A box side within this many pixels of the image border is taken to be cut by the border (the object goes on
# beyond it): the translation fit does not use it.
BORDER_PX = 2.0
_FIT_STEPS = 10  # at most; each step cuts the error about twentyfold, and it stops once converged
EXTENTS_FORMAT = "refiner-rt/extents/1"
EXTENTS_FILE = WEIGHTS_DIR / "extents.json"


@lru_cache(maxsize=1)
def load_extents() -> dict[str, np.ndarray]:
    """``{object id: (P, 3) metres}``: the shipped extent points per object (the shipped models' object frame).

    Raises:
        FileNotFoundError / ValueError: the file is missing or of another format.
    """
    doc = json.loads(EXTENTS_FILE.read_text())
    if doc.get("format") != EXTENTS_FORMAT:
        raise ValueError(f"{EXTENTS_FILE}: format {doc.get('format')!r} is not {EXTENTS_FORMAT!r}")
    return {obj: np.asarray(o["points_mm"], dtype=np.float64) / 1000.0 for obj, o in doc["objects"].items()}


def pixel_coordinates(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``(..., P, 2)`` continuous pixel coordinates of camera-frame points (K's pixel centres at integers)."""
    z = points_cam[..., 2]
    u = (K[0, 0] * points_cam[..., 0] + K[0, 1] * points_cam[..., 1]) / z + K[0, 2] + 0.5
    v = K[1, 1] * points_cam[..., 1] / z + K[1, 2] + 0.5
    return np.stack([u, v], axis=-1)


def sides_clear_of_border(box: np.ndarray, image_size: tuple[int, int] | None) -> np.ndarray:
    """``(4,)`` bools: which sides ``x1, y1, x2, y2`` of a box are not at the image border (``BORDER_PX``)."""
    if image_size is None:
        return np.ones(4, dtype=bool)
    h, w = image_size
    return np.array([box[0] > BORDER_PX, box[1] > BORDER_PX, box[2] < w - BORDER_PX, box[3] < h - BORDER_PX])


def fit_translation(R, points_m, box_xyxy, K, image_size: tuple[int, int] | None = None) -> np.ndarray:
    """The translation that puts the bounding box of the projected, posed points on ``box_xyxy``.

    The rule for boxes smaller than the object's projection (docs/pose6d.md, "Translation"):

    * a side at the image border (within :data:`BORDER_PX`; needs ``image_size``) is cut there and is not used;
    * the distance comes from the box dimension (width or height, of those with both sides usable) that gives the
      *nearer* distance, i.e. the larger ratio of box to model extent: an occluder only ever shrinks the visible
      box, so the less shrunk dimension is the truer one (no usable dimension: both are used the same way);
    * the position across the ray matches the box centre along an axis with both sides usable, else the one usable
      side (neither: the centre).

    Solved by a fixed-point iteration (the projected box at the current ``t``, a scale step for the distance and a
    shift for the position); for an uncut, unoccluded box it converges to the exact translation.

    Args:
        R: ``(3, 3)`` rotation, object to camera.
        points_m: ``(P, 3)`` object points, metres, object frame: the shipped extent points
            (:func:`load_extents`), whose projected box is the mesh's own, or surface points.
        box_xyxy: ``(4,)`` box ``(x1, y1, x2, y2)`` in pixels, continuous coordinates.
        K: ``(3, 3)`` pinhole intrinsics (pixels, OpenCV's pixel centres).
        image_size: ``(H, W)`` of the image, for the border rule; None: every side is used.

    Returns:
        ``(3,)`` float64 metres: ``t`` with ``x_cam = R @ x_obj + t``.
    """
    R = np.asarray(R, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    box = np.asarray(box_xyxy, dtype=np.float64)
    rotated = np.asarray(points_m, dtype=np.float64) @ R.T
    trusted = sides_clear_of_border(box, image_size)
    use_w, use_h = bool(trusted[0] and trusted[2]), bool(trusted[1] and trusted[3])
    if not (use_w or use_h):
        use_w = use_h = True
    size = max(float(np.ptp(rotated[:, 0])), float(np.ptp(rotated[:, 1])), 1e-6)
    # Start on the ray through the box centre at the distance where the object's size fills the box.
    f = 0.5 * (K[0, 0] + K[1, 1])
    z0 = f * size / max(box[2] - box[0], box[3] - box[1])
    centre = np.array([0.5 * (box[0] + box[2]) - 0.5, 0.5 * (box[1] + box[3]) - 0.5, 1.0])
    ray = np.linalg.solve(K, centre)
    t = ray * z0 - rotated.mean(axis=0)
    for _ in range(_FIT_STEPS):
        uv = pixel_coordinates(rotated + t, K)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        ratios = []
        if use_w:
            ratios.append((box[2] - box[0]) / max(hi[0] - lo[0], 1e-9))
        if use_h:
            ratios.append((box[3] - box[1]) / max(hi[1] - lo[1], 1e-9))
        scale = max(ratios)  # the larger box/model ratio: the nearer distance (the less occluded dimension)
        c = rotated.mean(axis=0) + t
        c = c / scale  # move the centroid along its ray: the projection grows by about `scale`
        t = c - rotated.mean(axis=0)
        uv = pixel_coordinates(rotated + t, K)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        shift = np.zeros(2)
        for axis, (a, b) in enumerate(((0, 2), (1, 3))):
            if trusted[a] and trusted[b]:
                shift[axis] = 0.5 * (box[a] + box[b]) - 0.5 * (lo[axis] + hi[axis])
            elif trusted[a]:
                shift[axis] = box[a] - lo[axis]
            elif trusted[b]:
                shift[axis] = box[b] - hi[axis]
            else:
                shift[axis] = 0.5 * (box[a] + box[b]) - 0.5 * (lo[axis] + hi[axis])
        z = c[2]
        dy = shift[1] * z / K[1, 1]
        dx = (shift[0] * z - K[0, 1] * dy) / K[0, 0]
        t_next = t + np.array([dx, dy, 0.0])
        if abs(scale - 1.0) < 1e-9 and abs(dx) + abs(dy) < 1e-9:
            return t_next
        t = t_next
    return t
