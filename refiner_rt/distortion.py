"""Lens distortion: crops of a calibrated camera's raw image, sampled as the pinhole camera of ``K`` would see them.

The refiners were trained on pinhole renders. A real camera's image is distorted (OpenCV's model: ``plumb_bob``,
five coefficients ``k1 k2 p1 p2 k3``, or ``rational_polynomial``, eight, as ``sensor_msgs/CameraInfo`` gives them in
``d``), so a crop cut straight out of it shows the object bent, and the viewing ray through its box centre is off.
With ``D``, the runtime instead:

1. maps the box (given in the raw image, as a detector on the raw image gives it) into the undistorted pinhole image
   of ``K``, each side through its undistorted midpoint (:func:`undistort_boxes`);
2. cuts the crop by the crop rule in that pinhole image, each crop pixel sampled from the raw image through the
   distortion (:func:`crop_undistorted`): only the crop's pixels are computed, never a whole undistorted frame;
3. takes the viewing ray through the undistorted box's centre (:func:`refiner_rt.geometry.ray_quaternions`).

Conventions: ``K`` in pixels with OpenCV's pixel centres at integers; boxes ``(x1, y1, x2, y2)`` in continuous pixels
(pixel ``i`` covers ``[i, i + 1)``), as everywhere in the runtime.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from refiner_rt.checks import DISTORTION_LENGTHS, validate_D  # noqa: F401  (re-exported under their old home)
from refiner_rt.preprocess import CROP_FILTERS, crop_matrix, prefiltered_region

__all__ = ["DISTORTION_LENGTHS", "validate_D", "undistort_boxes", "crop_undistorted"]

def _undistort_points(points: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Raw-image pixel indices ``(M, 2)`` -> the pinhole image's (same ``K``), iterated to convergence."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
    src = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 1, 2)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
        out = cv2.undistortPointsIter(src, K, D, None, K, criteria)
    else:  # OpenCV 5 folded the criteria into undistortPoints
        out = cv2.undistortPoints(src, K, D, None, None, K, criteria)
    return out.reshape(-1, 2)


def undistort_boxes(boxes_xyxy, K, D) -> np.ndarray:
    """Boxes of the raw (distorted) image -> boxes of the undistorted pinhole image of ``K``, ``(N, 4)`` float64.

    Each side goes through the undistorted midpoint of that side (the left side's x is the undistorted x of the
    left side's midpoint, and so on). A detector's box touches the object's silhouette somewhere along each side;
    the midpoint is that place on average, and it keeps the box as tight as it was: the bounding box of the
    undistorted outline would add the side's bend to the box at every step.

    Args:
        boxes_xyxy: ``(N, 4)`` boxes in the raw image's continuous pixels (validated).
        K: ``(3, 3)`` validated intrinsics; D: coefficients from :func:`validate_D` (not None).
    """
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    if len(boxes) == 0:
        return boxes.copy()
    x1, y1, x2, y2 = boxes.T
    cx, cy = 0.5 * (x1 + x2), 0.5 * (y1 + y2)
    mid = np.stack([np.stack([x1, cy], 1), np.stack([cx, y1], 1), np.stack([x2, cy], 1), np.stack([cx, y2], 1)], 1)
    # continuous coordinates -> OpenCV pixel indices (centres at integers) and back
    und = (_undistort_points(mid.reshape(-1, 2) - 0.5, K, D) + 0.5).reshape(len(boxes), 4, 2)
    return np.stack([und[:, 0, 0], und[:, 1, 1], und[:, 2, 0], und[:, 3, 1]], axis=1)


def crop_undistorted(image: np.ndarray, box_xyxy, size: int, context: float, K: np.ndarray, D: np.ndarray,
                     out=None, crop_filter: str = "none") -> np.ndarray:
    """Cut one crop by the crop rule in the undistorted pinhole image of ``K``, sampling the raw ``image``.

    Args:
        image: the raw ``H x W x 3`` ``uint8`` image.
        box_xyxy: the box in the **undistorted** image (:func:`undistort_boxes`).
        size, context: the crop rule's (``refiner_rt.preprocess``).
        K, D: validated intrinsics and distortion coefficients.
        out: optional ``S x S x 3`` ``uint8`` array to write into.
        crop_filter: as :func:`refiner_rt.preprocess.crop_to_square` (the raw pixels the crop samples are low-passed
            for the window's shrink at its centre).

    Returns:
        ``S x S x 3`` ``uint8``: what the crop rule cuts from a pinhole image of the scene; zeros outside the image.
    """
    m = crop_matrix(box_xyxy, size, context)
    u = np.arange(size, dtype=np.float64)
    src_x = m[0, 0] * u + m[0, 2]  # pinhole pixel indices of the crop's pixel centres (separable: no skew)
    src_y = m[1, 1] * u + m[1, 2]
    fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    yn = (src_y - cy) / fy
    gx, gy = np.meshgrid(src_x, yn)
    xn = (gx - cx - s * gy) / fx
    pts = np.stack([xn, gy, np.ones_like(xn)], axis=-1).reshape(-1, 1, 3)
    raw, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, D)
    maps = raw.reshape(size, size, 2).astype(np.float32)
    if crop_filter not in CROP_FILTERS:
        raise ValueError(f"crop_filter must be one of {CROP_FILTERS}; got {crop_filter!r}")
    if crop_filter == "antialias" and m[0, 0] > 1.0:
        inside = np.isfinite(maps).all(axis=-1)
        if inside.any():
            lo, hi = maps[inside].min(axis=0), maps[inside].max(axis=0)
            region, x0, y0, f = prefiltered_region(image, lo[0], lo[1], hi[0], hi[1], m[0, 0])
            if region.size and f > 1:  # the same sample points, in the region's pixels
                image = region
                maps = ((maps - np.array([x0, y0], np.float32) + 0.5) / np.float32(f) - 0.5).astype(np.float32)
    return cv2.remap(image, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, dst=out,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
