"""Input checks at the runtime's public boundary, in one module: images, boxes, rotations, ``K``, ``D``, depth
images, counts.

Every public function of the runtime validates its arguments with these (and nothing else does the same check
another way): a bad value raises ``ValueError`` or ``TypeError`` naming the argument, what was expected and what was
given (docs/design.md §7, "Limits"). Inside, the runtime trusts the data.

A few checks have a fast twin on Python floats beside them (:func:`boxes_rows` beside :func:`validate_boxes`): for
up to :data:`SMALL_BATCH` rows numpy's fixed cost per call exceeds the work. The twin accepts exactly what its
reference accepts and returns None for anything else, so that the reference raises the detailed error.

Conventions (docs/design.md §2): quaternions ``wxyz``, rotations object-to-camera, images ``H x W x 3`` uint8 BGR,
boxes ``(x1, y1, x2, y2)`` in continuous pixels (pixel ``i`` covers ``[i, i + 1)``), ``K`` in pixels.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.geometry import MAX_VIEWS

__all__ = ["SMALL_BATCH", "MAX_BATCH", "MAX_ITERATIONS", "STARTS", "MAX_STARTS", "MAX_VIEWS", "MAX_BOX_COORDINATE",
           "MIN_BOX_SIDE", "MIN_INSIDE_FRACTION", "K_MIN_FOCAL", "K_MAX_ABS", "DISTORTION_LENGTHS", "Q_ORDERS",
           "validate_image", "validate_boxes", "boxes_rows", "inside_fraction", "validate_K",
           "check_principal_point", "validate_D", "as_wxyz", "validate_rotations", "validate_settle",
           "validate_iterations", "validate_views", "validate_starts", "check_batch", "validate_threads",
           "check_coarse_rows", "validate_depth", "MAX_DEPTH_M"]

log = logging.getLogger(__name__)

# Up to this many boxes, refine() validates and composes on Python floats (module docstring); below the measured
# crossover with the numpy path (benchmarks/studies/speed, "Choices in the runtime").
SMALL_BATCH = 32
# Crops per call (boxes x views). Memory grows linearly with it: the crop batch takes S * S * 3 bytes per crop
# (12 KB at 64 x 64, 147 KB at 224 x 224) and onnxruntime's activations most of the rest (the peak memory per crop
# is measured in benchmarks/studies/speed, "Choices in the runtime"). Split larger requests into several calls;
# large batches are not faster per box on a CPU.
MAX_BATCH = 1024
# iterations: each one is a network pass (the paper does 1); bounded so that a wrong value cannot run for hours.
MAX_ITERATIONS = 16
# RefinerTracker(starts=...): the last rotation alone, or with the four turns about a tetrahedron's axes, or with the
# eight about a cube's corners: counts whose turns balance, so that their mean does not lean one way
STARTS = (1, 5, 9)
MAX_STARTS = max(STARTS)
# Box coordinates beyond a million pixels (far past any camera) are refused: they would only make black crops, and
# past ~1e154 the window's and the viewing ray's arithmetic overflows to inf.
MAX_BOX_COORDINATE = 1e6
# Boxes the runtime refuses because no usable crop comes from them (validate_boxes; the session's fast path checks the
# same): a side under MIN_BOX_SIDE pixels (a sub-pixel box, or one normalised to 0..1), and a box with less than
# MIN_INSIDE_FRACTION of its area inside the image (its crop is mostly the zero fill: a box for another image size,
# or an object nearly out of view).
MIN_BOX_SIDE = 2.0
MIN_INSIDE_FRACTION = 0.25
# K: pinhole form, focal lengths in [K_MIN_FOCAL, K_MAX_ABS] pixels and |skew|, |cx|, |cy| <= K_MAX_ABS. With box
# coordinates within MAX_BOX_COORDINATE these keep the viewing-ray maths far from overflow.
K_MIN_FOCAL = 1e-3
K_MAX_ABS = 1e9

# The coefficient counts OpenCV's distortion model takes: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]].
DISTORTION_LENGTHS = (4, 5, 8, 12, 14)
# A depth image whose median valid value is above this is refused: the sign of millimetres passed as metres.
MAX_DEPTH_M = 20.0
_D_FORM = ("OpenCV's (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tau_x, tau_y]]]]): 4, 5, 8, 12 or 14 "
           "numbers (CameraInfo's d: plumb_bob 5, rational_polynomial 8)")


def validate_D(D, name: str = "D") -> np.ndarray | None:
    """``D`` as a float64 vector, or None when every coefficient is zero (the pinhole camera: no resampling).

    Raises:
        ValueError: not 4, 5, 8, 12 or 14 finite numbers.
    """
    if D is None:
        return None
    try:
        arr = np.asarray(D, dtype=np.float64).reshape(-1) if np.ndim(D) <= 2 else None
    except (ValueError, TypeError):
        arr = None
    if arr is None or arr.size not in DISTORTION_LENGTHS:
        got = f"shape {np.shape(D)}" if arr is not None or isinstance(D, np.ndarray) else type(D).__name__
        raise ValueError(f"{name} must be the distortion coefficients {_D_FORM}; got {got}")
    if not all(math.isfinite(v) for v in arr.tolist()):
        raise ValueError(f"{name} must be finite; got {arr.tolist()}")
    return None if not arr.any() else arr



def validate_image(image, name: str = "image") -> np.ndarray:
    """Check an ``H x W x 3`` ``uint8`` image and return it (C-contiguous, no copy when already so).

    Raises:
        TypeError: not a numpy array.
        ValueError: wrong dtype, number of dimensions or channels, or an empty image.
    """
    if not isinstance(image, np.ndarray):
        raise TypeError(f"{name} must be a numpy array of shape (H, W, 3), dtype uint8, BGR; got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise ValueError(f"{name} must have dtype uint8 (H x W x 3, BGR); got dtype {image.dtype}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"{name} must have shape (H, W, 3) with 3 colour channels (BGR); got shape {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"{name} must not be empty; got shape {image.shape}")
    return np.ascontiguousarray(image)


def validate_boxes(boxes, image_shape: tuple[int, ...] | None = None, name: str = "boxes") -> np.ndarray:
    """Check ``(N, 4)`` boxes ``(x1, y1, x2, y2)`` in pixels and return them as float64.

    Args:
        boxes: array-like ``(N, 4)`` (or a single ``(4,)`` box, returned as ``(1, 4)``; an empty sequence is
            ``(0, 4)``, no boxes).
        image_shape: ``(H, W, ...)``; when given, each box must have at least :data:`MIN_INSIDE_FRACTION` of its
            area inside the image, and boxes normalised to 0..1 are told apart (below).
        name: argument name used in error messages.

    Raises:
        ValueError: a ragged sequence, wrong shape, non-finite values, coordinates beyond
            ``+-MAX_BOX_COORDINATE``, empty boxes (``x2 <= x1`` or ``y2 <= y1``), boxes narrower or lower than
            :data:`MIN_BOX_SIDE` pixels, boxes normalised to 0..1 (every coordinate within ``[0, 1]`` while the image
            is larger: the message says to scale them by the image size), or boxes entirely or mostly outside the
            image (the message names the box and its share inside).
    """
    try:
        arr = np.asarray(boxes)
    except (ValueError, TypeError) as exc:  # ragged nested lists
        raise ValueError(
            f"{name} must be numeric (N, 4) boxes (x1, y1, x2, y2) in pixels; got a ragged sequence ({exc})"
        ) from None
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{name} must be numeric (N, 4) boxes (x1, y1, x2, y2) in pixels; got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if arr.ndim == 1 and arr.shape[0] == 4:
        arr = arr[None]
    elif arr.shape == (0,):  # [] : no boxes
        arr = arr.reshape(0, 4)
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise ValueError(f"{name} must have shape (N, 4) as (x1, y1, x2, y2) in pixels; got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        i = int(np.argwhere(~np.isfinite(arr).all(axis=1))[0, 0])
        raise ValueError(f"{name}[{i}] must be finite; got {arr[i].tolist()}")
    huge = np.abs(arr).max(axis=1) > MAX_BOX_COORDINATE
    if np.any(huge):
        i = int(np.argmax(huge))
        raise ValueError(
            f"{name}[{i}] must have coordinates within +-{MAX_BOX_COORDINATE:g} pixels; got {arr[i].tolist()}"
        )
    empty = (arr[:, 2] <= arr[:, 0]) | (arr[:, 3] <= arr[:, 1])
    if np.any(empty):
        i = int(np.argmax(empty))
        raise ValueError(
            f"{name}[{i}] is empty: expected x2 > x1 and y2 > y1 (xyxy pixels); got {arr[i].tolist()}"
        )
    if image_shape is not None:
        h, w = int(image_shape[0]), int(image_shape[1])
        if len(arr) and arr.min() >= 0.0 and arr.max() <= 1.0 and max(w, h) > MIN_BOX_SIDE:
            raise ValueError(
                f"{name} look normalised to 0..1 (every coordinate within [0, 1]) but the image is {w}x{h} pixels: "
                f"boxes are (x1, y1, x2, y2) in pixels; scale them by (W, H, W, H) = ({w}, {h}, {w}, {h})"
            )
    small = (arr[:, 2] - arr[:, 0] < MIN_BOX_SIDE) | (arr[:, 3] - arr[:, 1] < MIN_BOX_SIDE)
    if np.any(small):
        i = int(np.argmax(small))
        raise ValueError(
            f"{name}[{i}] is {arr[i, 2] - arr[i, 0]:.3g} x {arr[i, 3] - arr[i, 1]:.3g} pixels: expected at least "
            f"{MIN_BOX_SIDE:g} x {MIN_BOX_SIDE:g} (xyxy pixels, not normalised); got {arr[i].tolist()}"
        )
    if image_shape is not None:
        outside = (arr[:, 2] <= 0) | (arr[:, 3] <= 0) | (arr[:, 0] >= w) | (arr[:, 1] >= h)
        if np.any(outside):
            i = int(np.argmax(outside))
            raise ValueError(
                f"{name}[{i}] lies entirely outside the {w}x{h} image: expected a box overlapping "
                f"[0, {w}) x [0, {h}); got {arr[i].tolist()}"
            )
        inside = inside_fraction(arr, image_shape)
        mostly = inside < MIN_INSIDE_FRACTION
        if np.any(mostly):
            i = int(np.argmax(mostly))
            raise ValueError(
                f"{name}[{i}] lies mostly outside the {w}x{h} image: {100 * inside[i]:.3g}% of its area is inside, "
                f"expected at least {100 * MIN_INSIDE_FRACTION:g}% (a box for another image size?); got "
                f"{arr[i].tolist()}"
            )
    return arr


def inside_fraction(boxes: np.ndarray, image_shape: tuple[int, ...]) -> np.ndarray:
    """``(N,)`` share of each ``(N, 4)`` non-empty box's area (``x1, y1, x2, y2`` pixels) inside the ``H x W`` image."""
    h, w = image_shape[0], image_shape[1]
    iw = np.clip(np.minimum(boxes[:, 2], w) - np.maximum(boxes[:, 0], 0.0), 0.0, None)
    ih = np.clip(np.minimum(boxes[:, 3], h) - np.maximum(boxes[:, 1], 0.0), 0.0, None)
    return (iw / (boxes[:, 2] - boxes[:, 0])) * (ih / (boxes[:, 3] - boxes[:, 1]))



def boxes_rows(boxes, image_shape) -> tuple[np.ndarray, list] | None:
    """Fast path of :func:`validate_boxes` for up to :data:`SMALL_BATCH` well-formed ``(N, 4)`` numeric boxes.

    Returns:
        ``(float64 (N, 4) array, N lists [x1, y1, x2, y2])`` when every box is finite, within
        ``+-MAX_BOX_COORDINATE``, at least ``MIN_BOX_SIDE`` pixels on each side and at least
        ``MIN_INSIDE_FRACTION`` inside the image (the rules of :func:`validate_boxes`); None otherwise (the caller
        then runs :func:`validate_boxes`, which raises or converts).
    """
    if isinstance(boxes, np.ndarray):
        arr = boxes
    else:
        try:
            arr = np.asarray(boxes)
        except (ValueError, TypeError):  # ragged: validate_boxes names it
            return None
    if arr.dtype.kind not in "fiu" or arr.ndim != 2 or arr.shape[1] != 4 or len(arr) > SMALL_BATCH:
        return None
    arr = arr.astype(np.float64, copy=False)
    rows = arr.tolist()
    h, w = image_shape[0], image_shape[1]
    lo, hi, side, share = -MAX_BOX_COORDINATE, MAX_BOX_COORDINATE, MIN_BOX_SIDE, MIN_INSIDE_FRACTION
    for x1, y1, x2, y2 in rows:
        # chained comparisons are False for nan and inf, so they check finiteness too
        if not (lo <= x1 < x2 <= hi and lo <= y1 < y2 <= hi and x2 - x1 >= side and y2 - y1 >= side and x2 > 0
                and y2 > 0 and x1 < w and y1 < h):
            return None
        if x1 < 0 or y1 < 0 or x2 > w or y2 > h:  # partly outside: enough of it inside?
            if ((min(x2, w) - max(x1, 0.0)) / (x2 - x1)) * ((min(y2, h) - max(y1, 0.0)) / (y2 - y1)) < share:
                return None
    return arr, rows



_K_FORM = "[[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels"
Q_ORDERS = ("wxyz", "xyzw")


def as_wxyz(q, q_order: str, name: str = "q_in_wxyz"):
    """``q`` (quaternions in ``q_order``, or ``(N, 3, 3)`` rotation matrices) as ``wxyz`` quaternions for
    :meth:`RefinerSession._q_in` (and the tracker); ``wxyz`` quaternions pass through untouched (the fast path).
    Errors name the argument ``name``."""
    if q_order not in Q_ORDERS:
        raise ValueError(f"q_order must be one of {', '.join(map(repr, Q_ORDERS))}; got {q_order!r}")
    shape = np.shape(q) if isinstance(q, np.ndarray) else None
    if shape is None:
        try:
            shape = np.shape(q)
        except (ValueError, TypeError):  # ragged: _q_in names it
            return q
    if tuple(shape) == (3, 3):
        raise ValueError(f"{name} has shape (3, 3): one rotation matrix, not (N, 4) quaternions; pass matrices as "
                         "(N, 3, 3) (R[None] for one box), or convert it with refiner_rt.quaternion.from_matrix(R) "
                         "(wxyz, object to camera)")
    if len(shape) == 3 and shape[1:] == (3, 3):
        R = np.asarray(q, dtype=np.float64)
        if not np.all(np.isfinite(R)):
            raise ValueError(f"{name} as rotation matrices (N, 3, 3) must be finite")
        err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2)) if len(R) else np.zeros(0)
        bad = np.flatnonzero((err > 1e-3) | (np.linalg.det(R) < 0)) if len(R) else []
        if len(bad):
            raise ValueError(f"{name}[{bad[0]}] is not a rotation matrix (orthonormal within 1e-3, determinant "
                             f"+1): R R^T differs from I by {err[bad[0]]:.3g}, det {np.linalg.det(R[bad[0]]):.3g}")
        return rq.from_matrix(rq.orthonormalize(R, method="svd"))
    if q_order == "xyzw":
        if len(shape) < 1 or shape[-1] != 4:
            raise ValueError(f"{name} with q_order='xyzw' must have shape (N, 4); got shape {tuple(shape)}")
        return rq.from_xyzw(np.asarray(q, dtype=np.float64))
    return q



def validate_settle(value, iterations: int | None = None) -> float | None:
    """``settle_deg`` checked (None passes): degrees in ``(0, 180)``, and with ``iterations`` (the passes it would
    choose among) at least two of them."""
    if value is None:
        return None
    try:
        ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating)) and (
            0 < float(value) < 180)
    except OverflowError:  # an int too large for a float
        ok = False
    if not ok:
        raise ValueError(f"settle_deg must be a number of degrees in (0, 180), or None; got {value!r}")
    if iterations is not None and iterations < 2:
        raise ValueError(f"settle_deg keeps a later pass where it turns the result by more than that: give "
                         f"iterations=2 or more with it; got iterations={iterations}")
    return float(value)


def validate_K(K) -> np.ndarray:
    """``K`` as a float64 ``(3, 3)`` pinhole matrix, or a ValueError naming ``K`` (see :data:`K_MAX_ABS`)."""
    try:
        arr = np.asarray(K)
    except (ValueError, TypeError):  # ragged nested lists
        raise ValueError(f"K must be a (3, 3) numeric intrinsics matrix {_K_FORM}; got a ragged sequence") from None
    if arr.dtype.kind not in "fiu" or arr.shape != (3, 3):
        raise ValueError(
            f"K must be a (3, 3) numeric intrinsics matrix {_K_FORM}; got shape {arr.shape}, dtype {arr.dtype}"
        )
    arr = arr.astype(np.float64, copy=False)  # read only from here on
    values = arr.ravel().tolist()  # checked on Python floats: a few times cheaper than numpy at 9 values
    fx, s, cx, k10, fy, cy, k20, k21, k22 = values
    if not all(map(math.isfinite, values)):
        raise ValueError(f"K must be finite, {_K_FORM}; got {arr.tolist()}")
    if not (fx > 0 and fy > 0):
        raise ValueError(f"K must have focal lengths fx > 0 and fy > 0, {_K_FORM}; got {arr.tolist()}")
    if k10 != 0.0 or k20 != 0.0 or k21 != 0.0 or k22 != 1.0:
        raise ValueError(f"K must have the pinhole form {_K_FORM} (an invertible camera matrix); got {arr.tolist()}")
    if not (K_MIN_FOCAL <= fx <= K_MAX_ABS and K_MIN_FOCAL <= fy <= K_MAX_ABS and abs(s) <= K_MAX_ABS
            and abs(cx) <= K_MAX_ABS and abs(cy) <= K_MAX_ABS):
        raise ValueError(
            f"K must have fx, fy in [{K_MIN_FOCAL:g}, {K_MAX_ABS:g}] pixels and |s|, |cx|, |cy| <= {K_MAX_ABS:g}; "
            f"got {arr.tolist()}"
        )
    return arr


_PRINCIPAL_POINT_WARNED: set = set()  # (cx, cy, W, H) already warned about (at most 64: no growth without bound)


def check_principal_point(K: np.ndarray, image_shape) -> None:
    """Log a warning (once per principal point and image size) when ``K``'s principal point lies outside the
    image's central half: the sign of a ``K`` for another resolution (one calibrated at twice the size puts it at
    the image's corner, or beyond). Not refused: the ``K`` of a cropped image (a region of interest) may put it
    anywhere, and is right."""
    h, w = image_shape[0], image_shape[1]
    cx, cy = K[0, 2], K[1, 2]
    if abs(cx - 0.5 * w) <= 0.25 * w and abs(cy - 0.5 * h) <= 0.25 * h:
        return
    key = (float(cx), float(cy), w, h)
    if key in _PRINCIPAL_POINT_WARNED or len(_PRINCIPAL_POINT_WARNED) >= 64:
        return
    _PRINCIPAL_POINT_WARNED.add(key)
    log.warning("K's principal point (cx, cy) = (%g, %g) lies outside the central half of the %dx%d image: is K "
                "for another resolution? Scale fx, fy, cx, cy by the image's size over the calibration's (a cropped "
                "image's K may lie there: then this is expected)", float(cx), float(cy), w, h)




def validate_rotations(q, n: int, other: str) -> np.ndarray:
    """``q_in_wxyz`` (``wxyz`` quaternions, one per entry of the argument named ``other``, of which there are ``n``)
    as ``(n, 4)`` float64 unit quaternions, ``w >= 0``. ``[]`` is no rotations; a single ``(4,)`` one is ``(1, 4)``.
    :meth:`refiner_rt.RefinerSession.refine` takes the fast path on Python floats first
    (:func:`refiner_rt.quaternion.normalize_rows`) and this for anything unusual, which it names."""
    if isinstance(q, (list, tuple, np.ndarray)) and len(q) == 0 and np.ndim(q) == 1:
        q = np.zeros((0, 4))  # [] : no rotations (as boxes_xyxy=[] is no boxes)
    q = rq.as_quaternion(q, "q_in_wxyz")
    if q.ndim == 1:
        q = q[None]
    if q.ndim != 2:
        raise ValueError(f"q_in_wxyz must have shape (N, 4), wxyz; got shape {q.shape}")
    if len(q) != n:
        raise ValueError(f"q_in_wxyz has {len(q)} rotations but {other} has {n}: expected one rotation per box")
    return rq.normalize(q)


def validate_iterations(iterations) -> int:
    """``iterations`` (refinement passes) as an int from 1 to :data:`MAX_ITERATIONS`."""
    if (isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer))
            or not 1 <= iterations <= MAX_ITERATIONS):
        raise ValueError(f"iterations must be an integer from 1 to {MAX_ITERATIONS}; got {iterations!r}")
    return int(iterations)


def validate_views(views) -> int:
    """``views`` (box-jittered crops averaged per object) as an int from 1 to :data:`MAX_VIEWS`."""
    if isinstance(views, bool) or not isinstance(views, (int, np.integer)) or not 1 <= views <= MAX_VIEWS:
        raise ValueError(f"views must be an integer from 1 to {MAX_VIEWS}; got {views!r}")
    return int(views)


def validate_starts(starts) -> int:
    """``starts`` (refinements a tracker averages per object and update) as an int, one of :data:`STARTS`."""
    if isinstance(starts, bool) or not isinstance(starts, (int, np.integer)) or starts not in STARTS:
        raise ValueError(f"starts must be 1, 5 or 9 (the last rotation alone, or with 4 or 8 turned starts whose turns "
                         f"balance; 5 is the setting measured on video); got {starts!r}")
    return int(starts)


def check_batch(n: int, views: int, name: str) -> None:
    """Refuse more than :data:`MAX_BATCH` crops in one call (``n`` entries of argument ``name`` times ``views``)."""
    if n * views > MAX_BATCH:
        per = f" x views={views} = {n * views} crops" if views > 1 else ""
        raise ValueError(
            f"{name} has {n} entries{per}: at most MAX_BATCH={MAX_BATCH} crops per call (boxes x views); "
            "split them over several calls"
        )


def validate_threads(threads) -> int:
    """``threads`` (onnxruntime intra-op threads) as an int ``>= 0`` (``0``: every core this process may run on)."""
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 0:
        raise ValueError(f"threads must be an integer >= 0 (0 = all cores); got {threads!r}")
    return int(threads)


def check_coarse_rows(coarse, n: int) -> np.ndarray:
    """``coarse`` (``refine(coarse=...)``: the rows known to be coarse) as ``(n,)`` bools, one per box."""
    forced = np.asarray(coarse)
    if forced.dtype != bool or forced.shape != (n,):
        raise ValueError(f"coarse must be None or ({n},) bools, one per box; got "
                         f"{'dtype ' + str(forced.dtype) if forced.dtype != bool else 'shape'} "
                         f"{forced.shape}")
    return forced


def validate_depth(depth, image_shape) -> np.ndarray:
    """Check a depth image: ``H x W`` float metres matching the colour image; 0 or non-finite where unknown.

    Raises:
        TypeError: not a numpy array, or an integer array (raw sensor millimetres: convert with ``depth_mm / 1000``).
        ValueError: a shape other than the image's ``(H, W)``, or values that look like millimetres (a median
            valid depth above :data:`MAX_DEPTH_M`).
    """
    if not isinstance(depth, np.ndarray):
        raise TypeError(f"depth must be a numpy array (H, W), float metres; got {type(depth).__name__}")
    if depth.dtype.kind != "f":
        raise TypeError(f"depth must be float metres (H, W); got dtype {depth.dtype} (a raw sensor image in "
                        "millimetres? pass depth_mm.astype(np.float32) / 1000)")
    if depth.shape != tuple(image_shape[:2]):
        raise ValueError(f"depth must have the image's shape (H, W) = {tuple(image_shape[:2])}, float metres; "
                         f"got shape {depth.shape}")
    valid = depth[np.isfinite(depth) & (depth > 0)]
    if valid.size and float(np.median(valid)) > MAX_DEPTH_M:
        raise ValueError(f"depth must be in metres; its median valid value is {float(np.median(valid)):.1f} "
                         f"(> {MAX_DEPTH_M:g} m: millimetres? divide by 1000)")
    return depth
