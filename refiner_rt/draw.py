"""Drawing a rotation on an image: an object's outline (from a few hundred surface points) or its axes, projected
with the camera intrinsics, for ``refiner-rt demo``.

Conventions: rotations ``R`` map object coordinates to camera coordinates (``x_cam = R @ x_obj + t``, metres);
``K`` is the ``(3, 3)`` pinhole matrix in OpenCV's pixel convention (pixel centres at integers); boxes are
``(x1, y1, x2, y2)`` in continuous pixel coordinates; images are ``H x W x 3`` ``uint8`` BGR.

An outline is drawn from points only (no mesh is needed at run time): the projected points are drawn as discs
about as wide as their spacing on the surface, the discs are merged by a morphological closing, and the outer
contour of the result is drawn. It is a silhouette up to about half a point spacing (a few millimetres). An object
whose translation is not known is placed on its box by the fit the estimator places its poses with
(:func:`refiner_rt.placement.fit_translation`, the object's shipped extent points: :func:`placement_points`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.placement import fit_translation, load_extents
from refiner_rt.preprocess import crop_matrix

AXIS_COLOURS = ((0, 0, 255), (0, 200, 0), (255, 80, 0))  # BGR of the x, y, z axes: red, green, blue
# BGR colours of the poses drawn: the truth, the coarse (detector's) input and the refined rotation. Cyan and green,
# not red: many YCB objects are red or yellow. LOST_COLOUR marks a track flagged lost.
POSE_COLOURS = {"truth": (255, 255, 255), "coarse": (255, 215, 0), "refined": (60, 225, 60)}
LOST_COLOUR = (40, 40, 255)

__all__ = ["AXIS_COLOURS", "POSE_COLOURS", "LOST_COLOUR", "PoseOverlay", "annotate_poses", "draw_axes_projected", "project", "centroid_translation", "placement_points", "outline_mask", "draw_outline", "draw_axes",
           "crop_view"]


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


def placement_points(object_id: str, outline) -> np.ndarray:
    """``(P, 3)`` metres: the points whose projected box :func:`refiner_rt.placement.fit_translation` puts on an
    object's box when its translation is not known (the estimator's fit, with its border and occlusion rules): the
    object's shipped extent points (``weights/extents.json``), else its outline points (``outline``, a
    :class:`refiner_rt.demo.Outline`). ``object_id`` may carry a ``#instance`` suffix."""
    extent = load_extents().get(object_id.split("#", 1)[0])
    return outline.points_m if extent is None else extent


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


@dataclass(frozen=True)
class PoseOverlay:
    """One object to draw on a frame by :func:`annotate_poses`.

    Attributes:
        object_id: the instance id (``"003_cracker_box"``, ``"003_cracker_box#2"``): its label, and its outline's.
        box: ``(4,)`` box ``(x1, y1, x2, y2)`` in pixels.
        q_refined: ``(4,)`` refined object-to-camera rotation, ``wxyz``.
        q_input: ``(4,)`` the detector's coarse rotation given in this frame (``wxyz``), or None.
        t: ``(3,)`` the object frame's origin in the camera frame (metres), or None: placed from the box
            (:func:`refiner_rt.placement.fit_translation` of :func:`placement_points`).
        lost: the loss-of-track check flagged the track in this frame (drawn in :data:`LOST_COLOUR`).
        score: the refinement's confidence (:attr:`refiner_rt.RefineResult.score`), printed in the label, or None.
    """

    object_id: str
    box: np.ndarray
    q_refined: np.ndarray
    q_input: np.ndarray | None = None
    t: np.ndarray | None = None
    lost: bool = False
    score: float | None = None

    @property
    def label(self) -> str:
        return self.object_id + ("" if self.score is None else f" {self.score:.2f}") + (" LOST" if self.lost else "")


LABEL_FONT, LABEL_SCALE = cv2.FONT_HERSHEY_SIMPLEX, 0.42


def annotate_poses(image: np.ndarray, K: np.ndarray, objects: list[PoseOverlay], outlines: Mapping) -> np.ndarray:
    """A copy of ``image`` (``H x W x 3`` uint8 BGR) with each object's outline at its refined rotation (and at the
    detector's input rotation, where given), its box, a label that overlaps no other label, and a legend.

    Args:
        image: the frame, BGR.
        K: ``(3, 3)`` intrinsics in pixels (a pinhole projection: lens distortion is not drawn).
        objects: what to draw, one :class:`PoseOverlay` per object.
        outlines: ``{YCB id: Outline}`` (:func:`refiner_rt.demo.load_outlines`, the points the package ships); an
            object without outline points (or with a ``#instance`` suffix of one) gets axes from its box centre.
    """
    out = image.copy()
    K = np.asarray(K, dtype=np.float64)
    for o in objects:
        refined = LOST_COLOUR if o.lost else POSE_COLOURS["refined"]
        x1, y1, x2, y2 = (float(v) for v in o.box)
        cv2.rectangle(out, (int(x1), int(y1)), (int(x2), int(y2)), (200, 200, 200), 1, cv2.LINE_AA)
        outline = outlines.get(o.object_id.split("#", 1)[0])
        poses = [(o.q_input, POSE_COLOURS["coarse"], 1)] if o.q_input is not None else []
        poses.append((o.q_refined, refined, 2))
        for q, colour, width in poses:
            R = rq.to_matrix(rq.normalize(np.asarray(q, dtype=np.float64)))
            if outline is None:
                draw_axes(out, (0.5 * (x1 + x2), 0.5 * (y1 + y2)), R, 0.4 * min(x2 - x1, y2 - y1), width, colour)
                continue
            t = (fit_translation(R, placement_points(o.object_id, outline), o.box, K, out.shape[:2]) if o.t is None
                 else np.asarray(o.t, float))
            uv, z = project(outline.points_m, R, t, K)
            depth = float((R @ outline.centroid_m + t)[2])
            radius = 0.6 * outline.spacing_m * K[0, 0] / max(depth, 1e-3)
            draw_outline(out, uv, z, radius, colour, width)
    legend_box = _legend(out, any(o.q_input is not None for o in objects), any(o.lost for o in objects))
    placed = [legend_box]
    for o in objects:
        text = o.label
        (w, h), base = cv2.getTextSize(text, LABEL_FONT, LABEL_SCALE, 1)
        rect = _free_spot(o.box, w, h + base, placed, out.shape)
        placed.append(rect)
        x, y = rect[0], rect[3] - base
        cv2.putText(out, text, (x, y), LABEL_FONT, LABEL_SCALE, HALO, 3, cv2.LINE_AA)
        cv2.putText(out, text, (x, y), LABEL_FONT, LABEL_SCALE, LOST_COLOUR if o.lost else (255, 255, 255), 1,
                    cv2.LINE_AA)
    return out


def _legend(canvas: np.ndarray, with_input: bool, with_lost: bool) -> tuple[int, int, int, int]:
    """Draw the legend in the top-left corner (in place); returns its rectangle ``(x1, y1, x2, y2)``."""
    items = [("refined", POSE_COLOURS["refined"])]
    if with_input:
        items.append(("detector input", POSE_COLOURS["coarse"]))
    if with_lost:
        items.append(("lost", LOST_COLOUR))
    width = 36 + max(cv2.getTextSize(t, LABEL_FONT, LABEL_SCALE, 1)[0][0] for t, _ in items)
    height = 6 + 16 * len(items)
    cv2.rectangle(canvas, (0, 0), (width, height), (24, 24, 24), -1)
    for k, (text, colour) in enumerate(items):
        y = 14 + 16 * k
        cv2.line(canvas, (6, y - 4), (26, y - 4), colour, 2, cv2.LINE_AA)
        cv2.putText(canvas, text, (32, y), LABEL_FONT, LABEL_SCALE, (230, 230, 230), 1, cv2.LINE_AA)
    return 0, 0, width, height


def _free_spot(box, w: int, h: int, placed: list, shape) -> tuple[int, int, int, int]:
    """A ``w x h`` label rectangle near ``box`` (above it, below it, then inside it, stepping down) that overlaps
    none of ``placed`` and stays in the image; the first candidate when none is free."""
    x1, y1, x2, y2 = (int(round(v)) for v in box)
    H, W = shape[:2]
    starts = [(x1, y1 - h - 2), (x1, y2 + 2)] + [(x1, y1 + 2 + k * (h + 2)) for k in range(12)] + [
        (x1, y2 + 2 + k * (h + 2)) for k in range(1, 12)]
    candidates = []
    for x, y in starts:
        x, y = min(max(x, 0), max(W - w, 0)), min(max(y, 0), max(H - h, 0))
        candidates.append((x, y, x + w, y + h))
    for rect in candidates:
        if not any(rect[0] < r[2] and r[0] < rect[2] and rect[1] < r[3] and r[1] < rect[3] for r in placed):
            return rect
    return candidates[0]
