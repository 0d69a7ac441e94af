"""Drawing a rotation on an image: an object's outline (from a few hundred surface points) or its axes, projected
with the camera intrinsics, for ``refiner-rt demo``.

Conventions: rotations ``R`` map object coordinates to camera coordinates (``x_cam = R @ x_obj + t``, metres);
``K`` is the ``(3, 3)`` pinhole matrix in OpenCV's pixel convention (pixel centres at integers); boxes are
``(x1, y1, x2, y2)`` in continuous pixel coordinates; images are ``H x W x 3`` ``uint8`` BGR.

An outline is drawn from points only (no mesh is needed at run time): the projected points are drawn as discs
about as wide as their spacing on the surface, the discs are merged by a morphological closing, and the outer
contour of the result is drawn. It is a silhouette up to about half a point spacing (a few millimetres).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.preprocess import crop_matrix

AXIS_COLOURS = ((0, 0, 255), (0, 200, 0), (255, 80, 0))  # BGR of the x, y, z axes: red, green, blue

__all__ = ["AXIS_COLOURS", "draw_axes_projected", "project", "centroid_translation", "translation_from_box", "outline_mask", "draw_outline", "draw_axes",
           "crop_view", "annotate"]


def project(points_m: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``(N, 2)`` (OpenCV convention) and depths ``(N,)`` of object points ``(N, 3)`` (metres)."""
    cam = points_m @ np.asarray(R).T + np.asarray(t)
    uvw = cam @ np.asarray(K, dtype=np.float64).T
    z = cam[:, 2]
    return uvw[:, :2] / np.where(np.abs(uvw[:, 2:]) > 1e-9, uvw[:, 2:], 1e-9), z


def centroid_translation(centroid_m: np.ndarray, R_true: np.ndarray, t_true: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The translation that puts the object's centroid where it is under the true pose ``(R_true, t_true)``, with
    rotation ``R`` instead: ``t = t_true + R_true c - R c``. The refiner estimates rotation only, so a coarse and a
    refined rotation are drawn about the object's centre rather than about its frame's origin (the YCB scan frame
    has its origin near the base)."""
    c = np.asarray(centroid_m, dtype=np.float64)
    return np.asarray(t_true, dtype=np.float64) + np.asarray(R_true) @ c - np.asarray(R) @ c


def translation_from_box(points_m: np.ndarray, R: np.ndarray, K: np.ndarray, box_xyxy) -> np.ndarray:
    """A translation for drawing when none is known: the object's centroid on the viewing ray through the box centre,
    at the depth where its projected extent matches the box's larger side (a weak-perspective estimate)."""
    K = np.asarray(K, dtype=np.float64)
    x1, y1, x2, y2 = (float(v) for v in box_xyxy)
    ray = np.linalg.solve(K, [0.5 * (x1 + x2) - 0.5, 0.5 * (y1 + y2) - 0.5, 1.0])  # OpenCV pixel centre of the box
    c = points_m.mean(axis=0)
    t1 = ray - np.asarray(R) @ c  # centroid at depth 1 m
    uv, _ = project(points_m, R, t1, K)
    extent = float(np.max(uv.max(axis=0) - uv.min(axis=0)))
    z = extent / max(x2 - x1, y2 - y1)
    return ray * z - np.asarray(R) @ c


def outline_mask(uv: np.ndarray, z: np.ndarray, radius_px: float, shape: tuple[int, int]) -> np.ndarray:
    """``H x W`` uint8 mask (255 inside) of the silhouette traced by projected points ``uv`` (in front of the camera)."""
    mask = np.zeros(shape, np.uint8)
    r = max(1, int(round(radius_px)))
    for u, v in np.round(uv[z > 1e-6]).astype(int):
        if -r <= u < shape[1] + r and -r <= v < shape[0] + r:
            cv2.circle(mask, (int(u), int(v)), r, 255, -1)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    return cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (r + 1 | 1, r + 1 | 1)))


HALO = (20, 20, 20)  # BGR of the dark edge under every drawn line: it stays visible on any object's colour


def draw_outline(canvas: np.ndarray, uv: np.ndarray, z: np.ndarray, radius_px: float, colour, thickness: int = 2):
    """Draw the outer contour of the points' silhouette on ``canvas`` (in place, over a dark halo) and return it."""
    mask = outline_mask(uv, z, radius_px, canvas.shape[:2])
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(canvas, contours, -1, HALO, thickness + 2, cv2.LINE_AA)
    cv2.drawContours(canvas, contours, -1, colour, thickness, cv2.LINE_AA)
    return canvas


def _axis(canvas, o, tip, colour, thickness: int, label: str | None, arrow: bool) -> None:
    line = cv2.arrowedLine if arrow else cv2.line
    kw = {"tipLength": 0.15} if arrow else {}
    for c, t in ((HALO, thickness + 2), (colour, thickness)):
        line(canvas, o, tip, c, t, cv2.LINE_AA, **kw)
    if label:
        d = np.subtract(tip, o)
        at = tuple(int(round(v)) for v in np.add(tip, 7 * d / max(np.hypot(*d), 1e-6) - (4, -4)))
        cv2.putText(canvas, label, at, cv2.FONT_HERSHEY_SIMPLEX, 0.4, HALO, 3, cv2.LINE_AA)
        cv2.putText(canvas, label, at, cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1, cv2.LINE_AA)


def draw_axes_projected(canvas: np.ndarray, uv_origin, uv_tips, thickness: int = 2, colour=None, labels: bool = False):
    """Draw axes x, y, z from the projected origin ``uv_origin`` to the projected tips ``(3, 2)``: red, green, blue,
    or all in ``colour`` (the colour of the pose they belong to) with ``labels`` x, y, z at their tips."""
    o = tuple(int(round(v)) for v in uv_origin)
    for k, tip in enumerate(uv_tips):
        _axis(canvas, o, tuple(int(round(v)) for v in tip), AXIS_COLOURS[k] if colour is None else colour, thickness,
              "xyz"[k] if labels else None, arrow=False)
    return canvas


def draw_axes(canvas: np.ndarray, origin_uv, R: np.ndarray, length_px: float, thickness: int = 2, colour=None,
              labels: bool = False):
    """Draw the object's x, y, z axes from ``origin_uv``, in orthographic projection (a rotation alone, when no
    translation is known): the first two rows of ``R`` scaled to ``length_px``; red, green, blue, or all in
    ``colour`` with ``labels`` x, y, z at their tips."""
    o = np.asarray(origin_uv, dtype=np.float64)
    for k in range(3):
        tip = o + length_px * np.asarray(R)[:2, k]
        _axis(canvas, tuple(int(round(v)) for v in o), tuple(int(round(v)) for v in tip),
              AXIS_COLOURS[k] if colour is None else colour, thickness, "xyz"[k] if labels else None, arrow=True)
    return canvas


def crop_view(image: np.ndarray, box_xyxy, size: int, context: float) -> tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """A ``size x size`` view of the square window around a box (side ``max(w, h) * context``, the crop rule's window)
    and the function mapping image pixel coordinates ``(N, 2)`` into it."""
    m = crop_matrix(box_xyxy, size, context)
    view = cv2.warpAffine(image, m, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=(40, 40, 40))
    scale, offset = m[0, 0], m[:, 2]

    def to_view(uv: np.ndarray) -> np.ndarray:
        return (np.asarray(uv, dtype=np.float64) - offset) / scale

    return view, to_view


def annotate(image: np.ndarray, boxes: dict, rotations: dict) -> np.ndarray:
    """A copy of ``image`` (BGR) with each object's box and its rotation's axes drawn at the box centre.

    The axes are the columns of the object-to-camera rotation matrix, drawn orthographically (camera ``x`` right,
    ``y`` down) with half the box's shorter side as length: x red, y green, z blue.
    """
    out = image.copy()
    for object_id, q in rotations.items():
        x1, y1, x2, y2 = boxes[object_id]
        cv2.rectangle(out, (int(x1), int(y1)), (int(x2), int(y2)), (255, 255, 255), 1, cv2.LINE_AA)
        centre = np.array([(x1 + x2) / 2, (y1 + y2) / 2])
        length = 0.5 * min(x2 - x1, y2 - y1)
        R = rq.to_matrix(q)
        for axis in np.argsort(R[2])[::-1]:  # the axis pointing farthest away first, so nearer ones stay on top
            tip = centre + length * R[:2, axis]
            cv2.line(out, tuple(np.round(centre).astype(int)), tuple(np.round(tip).astype(int)),
                     AXIS_COLOURS[axis], 2, cv2.LINE_AA)
        cv2.putText(out, object_id, (int(x1), max(int(y1) - 4, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (255, 255, 255), 1, cv2.LINE_AA)
    return out
