"""The crop rule: the single source of truth for turning (image, box) into a network input.

Training (``models/``) and the runtime (:class:`refiner_rt.RefinerSession`) both call these
functions, so a crop seen at run time is produced exactly as the crops the network was trained on.

Rule (docs/design.md §3): a square window centred on the box centre with side
``max(w, h) * context``, resampled to ``size x size`` in one affine warp (bilinear), parts outside
the image filled with zeros. With ``crop_filter="antialias"`` (a model's metadata says which) the
window's pixels are first averaged over blocks of ``f x f``, ``f`` the largest power of two not above
the shrink ``scale = side / size`` (:func:`prefiltered_region`; nothing when ``scale < 2``), so that
the bilinear warp shrinks by less than 2: bilinear sampling alone reads 4 of the ``scale**2`` pixels
each crop pixel covers, and a sharp camera image then aliases into the crop (the crop depends on the
image's fine texture and on sub-pixel shifts of the box).

Conventions:
    * images are ``H x W x 3`` ``uint8`` (any channel order: the pixels are only moved, never mixed
      across channels; the runtime passes BGR);
    * boxes are ``(x1, y1, x2, y2)`` in pixels, float, continuous coordinates: pixel ``i`` covers
      ``[i, i + 1)``, so a box ``(0, 0, W, H)`` is the whole image.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from refiner_rt.checks import (  # noqa: F401  (the box and image checks, re-exported under their old home)
    MAX_BOX_COORDINATE,
    MIN_BOX_SIDE,
    MIN_INSIDE_FRACTION,
    inside_fraction,
    validate_boxes,
    validate_image,
)

__all__ = [
    "DEFAULT_CONTEXT",
    "CROP_FILTERS",
    "prefiltered_region",
    "MAX_BOX_COORDINATE",
    "MIN_BOX_SIDE",
    "MIN_INSIDE_FRACTION",
    "crop_window",
    "crop_matrix",
    "crop_to_square",
    "crop_to_square_reference",
    "crop_batch",
    "resize_crop",
    "roll_angle",
    "roll_angles",
    "canonical_roll",
    "quarter_roll",
    "ROLL_TURNS",
    "ROLL_STEP_DEG",
    "validate_image",
    "validate_boxes",
]

DEFAULT_CONTEXT = 1.2
# How the window's pixels are filtered before the warp: "none" (bilinear only: every model before the metadata key
# crop_filter) or "antialias" (block averages matched to the shrink, above).
CROP_FILTERS = ("none", "antialias")


def prefiltered_region(image: np.ndarray, x_lo: float, y_lo: float, x_hi: float, y_hi: float,
                       scale: float) -> tuple[np.ndarray, int, int, int]:
    """The part of ``image`` that a crop samples (source pixel indices ``[x_lo, x_hi] x [y_lo, y_hi]``, widened by
    a block), averaged over blocks of ``f x f`` pixels, ``f`` the largest power of two not above ``scale`` (halved
    ``log2(f)`` times by ``cv2.INTER_AREA``, OpenCV's fast path; the blocks aligned on the first crop pixel's
    footprint), so that the bilinear warp after it shrinks by less than 2. Returns ``(region, x0, y0, f)``: region
    pixel ``(i, j)`` averages the image's pixels ``[x0 + i f, x0 + (i + 1) f) x [y0 + j f, y0 + (j + 1) f)``, so an
    image index ``x`` is region index ``(x - x0 + 0.5) / f - 0.5``. ``f = 1`` (no change) when ``scale < 2``; an empty
    overlap with the image returns an empty region."""
    h, w = image.shape[:2]
    f = 1 << max(0, int(math.floor(math.log2(scale)))) if scale >= 2.0 else 1
    # the first crop pixel's footprint starts half a shrink before its sample point
    x0 = int(math.floor(x_lo - 0.5 * scale + 0.5)) - f
    y0 = int(math.floor(y_lo - 0.5 * scale + 0.5)) - f
    x0, y0 = x0 % f if x0 < 0 else x0, y0 % f if y0 < 0 else y0  # inside the image, still on the blocks
    x1 = min(w - (w - x0) % f, x0 + f * -(-(int(math.ceil(x_hi)) + 2 * f - x0) // f))  # whole blocks, inside
    y1 = min(h - (h - y0) % f, y0 + f * -(-(int(math.ceil(y_hi)) + 2 * f - y0) // f))
    if x1 <= x0 or y1 <= y0:
        return image[:0, :0], 0, 0, 1
    region = image[y0:y1, x0:x1]
    while region.shape[0] % 2 == 0 and region.shape[1] % 2 == 0 and (x1 - x0) // region.shape[1] < f:
        region = cv2.resize(region, (region.shape[1] // 2, region.shape[0] // 2), interpolation=cv2.INTER_AREA)
    return region, x0, y0, f


def crop_window(box_xyxy, context: float = DEFAULT_CONTEXT) -> tuple[float, float, float]:
    """Square crop window of one box: ``(cx, cy, side)`` in continuous pixel coordinates.

    Args:
        box_xyxy: ``(x1, y1, x2, y2)`` in pixels.
        context: side = ``max(w, h) * context``.
    """
    x1, y1, x2, y2 = (float(v) for v in box_xyxy)
    return 0.5 * (x1 + x2), 0.5 * (y1 + y2), max(x2 - x1, y2 - y1) * float(context)


def crop_matrix(box_xyxy, size: int, context: float = DEFAULT_CONTEXT) -> np.ndarray:
    """2x3 affine matrix mapping output pixel indices to source pixel indices (OpenCV convention).

    Pixel index ``u`` of the ``size x size`` output has its centre at continuous ``u + 0.5``; it
    samples the source at continuous ``x0 + (u + 0.5) * side / size``, i.e. source index
    ``x0 + (u + 0.5) * scale - 0.5``. Use with ``cv2.WARP_INVERSE_MAP``.

    Args:
        box_xyxy: ``(x1, y1, x2, y2)`` in pixels.
        size: output side ``S`` in pixels.
        context: window side = ``max(w, h) * context``.

    Returns:
        ``(2, 3)`` float64 matrix ``M`` with ``src = M @ (u, v, 1)``.
    """
    cx, cy, side = crop_window(box_xyxy, context)
    scale = side / size
    x0, y0 = cx - 0.5 * side, cy - 0.5 * side
    return np.array(
        [[scale, 0.0, x0 + 0.5 * scale - 0.5], [0.0, scale, y0 + 0.5 * scale - 0.5]], dtype=np.float64
    )


def crop_to_square(image: np.ndarray, box_xyxy, size: int, context: float = DEFAULT_CONTEXT, out=None,
                   crop_filter: str = "none") -> np.ndarray:
    """Cut one box out of an image by the crop rule.

    Args:
        image: ``H x W x 3`` ``uint8`` (channel order preserved).
        box_xyxy: ``(x1, y1, x2, y2)`` in pixels, continuous coordinates.
        size: output side ``S``.
        context: window side = ``max(w, h) * context``.
        out: optional preallocated ``S x S x 3`` ``uint8`` C-contiguous array to write into.
        crop_filter: ``"none"`` (bilinear) or ``"antialias"`` (the window low-passed first; module docstring).

    Returns:
        ``S x S x 3`` ``uint8`` crop, zeros where the window leaves the image.
    """
    m = crop_matrix(box_xyxy, size, context)
    if crop_filter not in CROP_FILTERS:
        raise ValueError(f"crop_filter must be one of {CROP_FILTERS}; got {crop_filter!r}")
    if crop_filter == "antialias" and m[0, 0] > 1.0:
        last = m[0, 0] * (size - 1)  # the last sample's offset from the first, in source pixels
        region, x0, y0, f = prefiltered_region(image, m[0, 2], m[1, 2], m[0, 2] + last, m[1, 2] + last, m[0, 0])
        if region.size and f > 1:  # the same sample points, in the region's pixels
            image = region
            m = np.array([[m[0, 0] / f, 0.0, (m[0, 2] - x0 + 0.5) / f - 0.5],
                          [0.0, m[1, 1] / f, (m[1, 2] - y0 + 0.5) / f - 0.5]])
    return cv2.warpAffine(
        image,
        m,
        (size, size),
        dst=out,
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(0, 0, 0),
    )


def crop_to_square_reference(image: np.ndarray, box_xyxy, size: int, context: float = DEFAULT_CONTEXT) -> np.ndarray:
    """:func:`crop_to_square`'s reference (``crop_filter="none"``): the crop rule written out, one pixel at a time,
    bilinear sampling in float64. Slow; for tests, which check the fast OpenCV warp against it (OpenCV's bilinear
    weights are fixed-point, 1/32 steps: the two agree within a few grey levels).

    Args:
        image: ``H x W x C`` array (any dtype; read as float).
        box_xyxy: ``(x1, y1, x2, y2)`` in pixels, continuous coordinates.
        size: output side ``S``.
        context: window side = ``max(w, h) * context``.

    Returns:
        ``S x S x C`` float64 crop, zeros where the window leaves the image.
    """
    x1, y1, x2, y2 = box_xyxy
    side = max(x2 - x1, y2 - y1) * context
    x0, y0 = (x1 + x2) / 2 - side / 2, (y1 + y2) / 2 - side / 2
    h, w = image.shape[:2]
    out = np.zeros((size, size, image.shape[2]))
    for v in range(size):
        for u in range(size):
            # continuous sample point -> index coordinates (pixel i centred at i + 0.5)
            xs = x0 + (u + 0.5) * side / size - 0.5
            ys = y0 + (v + 0.5) * side / size - 0.5
            xi, yi = int(np.floor(xs)), int(np.floor(ys))
            fx, fy = xs - xi, ys - yi
            acc = np.zeros(image.shape[2])
            for dy, wy in ((0, 1 - fy), (1, fy)):
                for dx, wx in ((0, 1 - fx), (1, fx)):
                    yy, xx = yi + dy, xi + dx
                    if 0 <= yy < h and 0 <= xx < w:
                        acc += wy * wx * image[yy, xx]
            out[v, u] = acc
    return out


def crop_batch(image: np.ndarray, boxes_xyxy, size: int, context: float = DEFAULT_CONTEXT, out=None,
               crop_filter: str = "none") -> np.ndarray:
    """Cut ``N`` boxes out of one image: one ``cv2.warpAffine`` per box into a ``(N, S, S, 3)`` batch.

    Args:
        image: ``H x W x 3`` ``uint8``.
        boxes_xyxy: ``(N, 4)`` float boxes ``(x1, y1, x2, y2)`` in pixels (already validated).
        size: output side ``S``.
        context: window side = ``max(w, h) * context``.
        out: optional preallocated C-contiguous ``(>= N, S, S, 3)`` ``uint8`` buffer; the first ``N``
            entries are written and returned as a view.
        crop_filter: as :func:`crop_to_square`.

    Returns:
        ``(N, S, S, 3)`` ``uint8``.
    """
    n = len(boxes_xyxy)
    if out is None:
        out = np.empty((n, size, size, 3), dtype=np.uint8)
    batch = out[:n]
    for i in range(n):
        crop_to_square(image, boxes_xyxy[i], size, context, out=batch[i], crop_filter=crop_filter)
    return batch


def resize_crop(crop: np.ndarray, size: int, out=None, crop_filter: str = "none") -> np.ndarray:
    """Resample an already cut-out crop to ``S x S`` with the crop rule's warp.

    The crop is treated as the crop window itself (``context = 1``, box = the whole crop); a
    non-square crop keeps its aspect ratio and is padded with zeros on the short side.

    Args:
        crop: ``h x w x 3`` ``uint8``.
        size: output side ``S``.
        out: optional preallocated ``S x S x 3`` ``uint8`` array.
        crop_filter: as :func:`crop_to_square`.

    Returns:
        ``S x S x 3`` ``uint8``.
    """
    h, w = crop.shape[:2]
    return crop_to_square(crop, (0.0, 0.0, float(w), float(h)), size, context=1.0, out=out, crop_filter=crop_filter)


# --------------------------------------------------------------------------------------------- the canonical roll
# A model whose metadata says ``roll = "canonical"`` (refiner_rt.metadata) was trained with each crop turned about its
# centre so that the coarse pose's object z axis points up in the image (its x axis where the z axis lies within 30
# degrees of the viewing ray), and the coarse pose turned with it (models.nets.fusion.canonical_roll, the training's
# definition in PyTorch). Its ONNX graph is the network alone: the runtime makes the turn here, one small warp per
# crop, before each pass.
_AXIS_NEAR_RAY = 0.25  # sin(30 deg) ** 2: the z axis's image length below which the x axis is used
# The runtime turns each crop by the roll angle rounded to this many degrees (the rotation turned by the same rounded
# angle, so crop and rotation still agree). Turned by the exact angle, the crop is resampled at every change of the
# coarse pose, however small, and its uint8 pixels step by whole grey levels: a 1e-4-degree change of q_in moved the
# shipped INT8 refiners' output by 0.08 degrees on average (fp32: 0.0014), 0.29 at most. Rounded, a small change of
# q_in leaves the crop as it was and reaches the network through its rotation input only, where both move the output
# by about the change itself; the crop changes when the angle crosses a step. The network then sees the axis up to half
# a step off up, which it did not train on; the held-out error did not change (benchmarks/studies/int8_smooth).
ROLL_STEP_DEG = 1.0


def roll_angle(w: float, x: float, y: float, z: float) -> float:
    """The image angle (radians, clockwise from up, x right and y down) of the object's z axis under the unit rotation
    ``(w, x, y, z)`` (object to the viewing-ray frame), or of its x axis where the z axis lies within 30 degrees of
    the ray. The runtime's twin of ``models.nets.fusion.roll_angle`` (plain floats: one crop at a time is the common case,
    where numpy's per-call cost would exceed the maths)."""
    zx, zy = 2.0 * (x * z + w * y), 2.0 * (y * z - w * x)  # R's third column: the object z axis
    if zx * zx + zy * zy > _AXIS_NEAR_RAY:
        return math.atan2(zx, -zy)
    return math.atan2(1.0 - 2.0 * (y * y + z * z), -2.0 * (x * y + w * z))  # R's first column: the x axis


def roll_angles(q_wxyz) -> np.ndarray:
    """``(N,)`` :func:`roll_angle` of each row of ``q_wxyz`` (``(N, 4)``)."""
    return np.array([roll_angle(*row) for row in np.asarray(q_wxyz, dtype=np.float64).tolist()])


def canonical_roll(crops: np.ndarray, q_wxyz, out: np.ndarray | None = None,
                   step_deg: float = ROLL_STEP_DEG) -> tuple[np.ndarray, np.ndarray]:
    """Each ``S x S`` crop turned about its centre so that the axis of :func:`roll_angle` points up (to within half of
    ``step_deg``), and its rotation turned about the viewing ray with it: ``(crops (N, S, S, 3) uint8, q (N, 4) float64
    wxyz)``.

    The turn is the training's (``models.nets.fusion.canonical_roll``): bilinear, corners filled by reflection about the
    crop's edges, the output pixel at offset ``d`` from the centre taking the input at ``R(psi) d``, ``psi`` the roll
    angle rounded to a multiple of ``step_deg`` degrees (:data:`ROLL_STEP_DEG`; ``0``: the exact angle, as in
    training); the rotation becomes ``q_z(-psi) * q``, so the turned crop and rotation agree whatever the rounding.
    Here in uint8, with OpenCV's fixed-point weights: within one grey level of the float turn. ``out``: an optional
    preallocated ``(N, S, S, 3)`` uint8 array.
    """
    crops = np.asarray(crops)
    out = np.empty_like(crops) if out is None else out
    size = crops.shape[1]
    centre = (size - 1) / 2.0
    # Reflected once into a border wide enough for any turn (a corner reaches centre * (sqrt(2) - 1) past an edge),
    # then warped with no border rule: twice as fast as OpenCV's reflecting warp, the same pixels within a grey level.
    pad = math.ceil(centre * (math.sqrt(2.0) - 1.0)) + 2
    padded = np.empty((size + 2 * pad, size + 2 * pad, crops.shape[3]), dtype=crops.dtype)
    q_turned = []
    step = math.radians(step_deg)
    for i, (w, x, y, z) in enumerate(np.asarray(q_wxyz, dtype=np.float64).tolist()):
        psi = roll_angle(w, x, y, z)
        if step:
            psi = round(psi / step) * step
        c, s = math.cos(psi), math.sin(psi)
        m = np.array([[c, -s, centre * (1.0 - c + s) + pad], [s, c, centre * (1.0 - s - c) + pad]])
        cv2.copyMakeBorder(crops[i], pad, pad, pad, pad, cv2.BORDER_REFLECT, dst=padded)
        cv2.warpAffine(padded, m, (size, size), dst=out[i], flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                       borderMode=cv2.BORDER_REPLICATE)
        hw, hz = math.cos(psi / 2.0), -math.sin(psi / 2.0)  # q_z(-psi) * q
        q_turned.append((hw * w - hz * z, hw * x - hz * y, hw * y + hz * x, hw * z + hz * w))
    return out, np.array(q_turned, dtype=np.float64).reshape(-1, 4)


def quarter_roll(crops: np.ndarray, q_wxyz, out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`canonical_roll` in quarter turns (``models.nets.fusion.quarter_roll``): each crop turned by the multiple of 90
    degrees nearest to the canonical turn, so that the axis then points within 45 degrees of up, and its rotation
    with it. Pixels are moved, never resampled: equal to the training's turn. ``(crops, q)`` as there."""
    crops = np.asarray(crops)
    out = np.empty_like(crops) if out is None else out
    q_turned = []
    for i, (w, x, y, z) in enumerate(np.asarray(q_wxyz, dtype=np.float64).tolist()):
        k = round(roll_angle(w, x, y, z) / (math.pi / 2)) % 4  # quarter turns to undo, 0-3
        out[i] = np.rot90(crops[i], k, axes=(0, 1)) if k else crops[i]
        hw, hz = math.cos(k * math.pi / 4), -math.sin(k * math.pi / 4)  # q_z(-k * 90 deg) * q
        q_turned.append((hw * w - hz * z, hw * x - hz * y, hw * y + hz * x, hw * z + hz * w))
    return out, np.array(q_turned, dtype=np.float64).reshape(-1, 4)


# The turn the runtime makes before the graph, by the metadata's ``roll``.
ROLL_TURNS = {"canonical": canonical_roll, "quarter": quarter_roll}
