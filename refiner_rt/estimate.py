"""PoseEstimator: a 6D pose (rotation and translation) from a 2D box, with no coarse rotation given.

A 2D detector gives a box and a class; the shipped refiners need a coarse rotation within about 30 degrees. This
module finds one by search (docs/pose6d.md):

1. **Rotation hypotheses over all of SO(3)**: ``hypotheses`` rotations spread evenly over SO(3) by the
   super-Fibonacci spiral (Alexa, *Super-Fibonacci Spirals: Fast, Low-Discrepancy Sampling of SO(3)*, CVPR 2022),
   relative to the box's viewing ray (docs/design.md §2), so every resting face and every roll about the ray is
   covered. The object's crop is cut once; all hypotheses run through the coarse refiner in one batch.
2. **Refinement and ranking**: each hypothesis is refined ``passes`` times (one batched call per pass), then
   checked by one more pass and ranked by how far that pass moves it from where it was (``ranking``):

   * ``"return"``: the check pass starts from the hypothesis turned by :data:`RETURN_TURN_DEG` (about a fixed
     axis per hypothesis) and the residual is how far from the hypothesis it lands. The refiner, trained on inputs
     around the true rotation, brings a turned true rotation back; at a wrong rotation it has no way back.
   * ``"residual"``: the fixed-point residual, the check pass starts from the hypothesis itself. (On rendered
     scenes wrong rotations far outside the refiner's training range are often fixed points too, so this ranks
     worse: docs/pose6d.md.)
   * ``"return+shape"``: the return residual plus :data:`SHAPE_WEIGHT_DEG` times the hypothesis's box-shape
     disagreement (:func:`shape_disagreement`): a rotation whose projected box has another width-to-height ratio
     than the detected box is less likely (no network pass; boxes cut by the image border are not judged).
3. **Polish**: the winner is refined once more by the object's fine refiner (docs/design.md §8), when one ships.
4. **Translation** from the box, ``K`` and the object's extent points (``weights/extents.json``: the mesh vertices
   farthest along 1,024 directions, whose projected bounding box is the mesh's own from any viewpoint): the posed
   points' projected bounding box is fitted to the box (:func:`refiner_rt.placement.fit_translation`, the fit the
   drawings use too); with a depth image, the depth of the box's centre region sets the distance
   (:func:`depth_translation`, with the surface points of ``samples/outlines.json``).

Conventions: rotations object to camera (``x_cam = R @ x_obj + t``), translations in metres, the shipped models'
object frame (the YCB google_16k scan frame, :mod:`refiner_rt.frames`); quaternions ``wxyz``; images ``H x W x 3``
uint8 BGR; boxes ``(x1, y1, x2, y2)`` pixels, continuous coordinates (pixel ``i`` covers ``[i, i+1)``); depth
``H x W`` float metres, 0 or non-finite where unknown.

Example:
    >>> est = PoseEstimator.pretrained("003_cracker_box")
    >>> res = est.estimate(image_bgr, boxes_xyxy, K=K)          # res.R (N, 3, 3), res.t (N, 3) metres, res.score (N,)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.geometry import ray_quaternions
from refiner_rt.checks import validate_boxes, validate_depth, validate_image, validate_K
from refiner_rt.placement import fit_translation, load_extents, pixel_coordinates, sides_clear_of_border
from refiner_rt.preprocess import crop_to_square
from refiner_rt.session import RefinerSession

__all__ = ["PoseEstimator", "PoseEstimate", "super_fibonacci", "return_turns", "depth_translation",
           "shape_disagreement", "ranking_residual", "DEFAULT_HYPOTHESES", "DEFAULT_PASSES", "DEFAULT_RANKING",
           "RANKINGS", "RETURN_TURN_DEG", "SHAPE_WEIGHT_DEG"]

# The search's defaults, chosen on rendered scenes (benchmarks/pose6d.py --choose; docs/pose6d.md).
DEFAULT_HYPOTHESES = 3
DEFAULT_PASSES = 5
DEFAULT_RANKING = "return+shape"
RANKINGS = ("return", "residual", "return+shape")
# "return+shape": degrees of ranking residual per unit of box-shape disagreement (shape_disagreement); 30 lies
# between the two best weights of 5-160 tried on rendered scenes (docs/pose6d.md, "Choosing the search").
SHAPE_WEIGHT_DEG = 30.0
# The check pass's turn of each hypothesis for the "return" ranking, within the refiner's 30-degree training range
# (15 ranked better than 25 and 40 on rendered scenes: docs/pose6d.md).
RETURN_TURN_DEG = 15.0
# The central share of the box (each side) whose valid depths give the object's distance.
DEPTH_CENTRE_SHARE = 0.5
_DEPTH_GRID = 6  # cells per side of the model's coarse z-buffer over the depth region (depth_translation)


def super_fibonacci(n: int) -> np.ndarray:
    """``(n, 4)`` wxyz unit quaternions spread evenly over SO(3) (the super-Fibonacci spiral, Alexa 2022,
    Algorithm 1), ``w >= 0``. Deterministic."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer; got {n!r}")
    phi, psi = math.sqrt(2.0), 1.533751168755204288118041
    s = np.arange(n, dtype=np.float64) + 0.5
    r, big_r = np.sqrt(s / n), np.sqrt(1.0 - s / n)
    alpha, beta = 2.0 * np.pi * s / phi, 2.0 * np.pi * s / psi
    xyzw = np.stack([r * np.sin(alpha), r * np.cos(alpha), big_r * np.sin(beta), big_r * np.cos(beta)], axis=1)
    return rq.canonical(rq.from_xyzw(xyzw))


def return_turns(n: int) -> np.ndarray:
    """``(n, 4)`` wxyz unit quaternions: the "return" check's turn of each of ``n`` hypotheses, :data:`RETURN_TURN_DEG`
    about axes spread over the sphere (the vector parts of the last ``n`` of ``super_fibonacci(2 n)``). A hypothesis
    ``q`` is checked from ``q * turn`` (the turn in the object frame). Deterministic."""
    axes = super_fibonacci(2 * n)[n:, 1:]
    return rq.from_axis_angle(axes / np.linalg.norm(axes, axis=1, keepdims=True), RETURN_TURN_DEG)


@dataclass(frozen=True)
class PoseEstimate:
    """Output of :meth:`PoseEstimator.estimate`.

    Attributes:
        R: ``(N, 3, 3)`` float64: rotations, object to camera (``x_cam = R @ x_obj + t``).
        t: ``(N, 3)`` float64 metres: translations, the shipped models' object frame.
        score: ``(N,)`` float64 in ``(0, 1]``: confidence of the rotation, ``exp(-residual / 10 deg)`` with the
            residual the chosen hypothesis's ranking residual (degrees); orders poses, not calibrated.
        q: ``(N, 4)`` float64 ``wxyz`` (``w >= 0``): ``R`` as quaternions.
    """

    R: np.ndarray
    t: np.ndarray
    score: np.ndarray
    q: np.ndarray

    def __len__(self) -> int:
        return len(self.t)


def ranking_residual(residual_deg, q_cam, extent_m, boxes_xyxy, K, image_size: tuple[int, int]) -> np.ndarray:
    """``(M,)`` degrees: the ranking of rotation hypotheses, lower first: the return residual ``residual_deg`` plus,
    where the object's extent points are known (``extent_m`` not None), :data:`SHAPE_WEIGHT_DEG` times
    :func:`shape_disagreement`. The one rule of :class:`PoseEstimator` (``ranking="return+shape"``) and of
    :class:`refiner_rt.tracker.RefinerTracker`'s re-initialisation."""
    residual = np.asarray(residual_deg, dtype=np.float64)
    if extent_m is None:
        return residual.copy()
    return residual + SHAPE_WEIGHT_DEG * shape_disagreement(q_cam, extent_m, boxes_xyxy, K, image_size)


def shape_disagreement(q_cam, extent_m, boxes_xyxy, K, image_size: tuple[int, int] | None = None) -> np.ndarray:
    """``(M,)`` in ``[0, 1)``: how far the projected box of each posed object disagrees in shape with its box,
    ``1 - min(rw, rh) / max(rw, rh)`` with ``rw, rh`` the box's width and height over the projection's (the object
    placed on the box's viewing ray at the distance its size suggests). 0 for a box with a side at the image border
    (:data:`refiner_rt.placement.BORDER_PX`; needs ``image_size``): its shape is the border's.

    Args:
        q_cam: ``(M, 4)`` wxyz rotations, object to camera. extent_m: ``(P, 3)`` extent points, metres.
        boxes_xyxy: ``(M, 4)`` pixels, continuous coordinates. K: ``(3, 3)`` pinhole intrinsics.
    """
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    K = np.asarray(K, dtype=np.float64)
    R = rq.to_matrix(np.asarray(q_cam, dtype=np.float64).reshape(-1, 4))
    pts = np.einsum("mij,pj->mpi", R, np.asarray(extent_m, dtype=np.float64))
    centre = np.stack([0.5 * (boxes[:, 0] + boxes[:, 2]) - 0.5, 0.5 * (boxes[:, 1] + boxes[:, 3]) - 0.5,
                       np.ones(len(boxes))], axis=1)
    rays = np.linalg.solve(K, centre.T).T
    side = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
    size = np.maximum(np.ptp(pts[..., 0], axis=1), np.ptp(pts[..., 1], axis=1))
    z = 0.5 * (K[0, 0] + K[1, 1]) * size / side
    uv = pixel_coordinates(pts - pts.mean(axis=1, keepdims=True) + (rays * z[:, None])[:, None, :], K)
    rw = (boxes[:, 2] - boxes[:, 0]) / np.maximum(np.ptp(uv[..., 0], axis=1), 1e-9)
    rh = (boxes[:, 3] - boxes[:, 1]) / np.maximum(np.ptp(uv[..., 1], axis=1), 1e-9)
    out = 1.0 - np.minimum(rw, rh) / np.maximum(rw, rh)
    if image_size is not None:
        cut = ~np.array([sides_clear_of_border(b, image_size).all() for b in boxes], dtype=bool)
        out[cut] = 0.0
    return out


def depth_translation(R, points_m, t_box, box_xyxy, K, depth) -> np.ndarray | None:
    """The translation with the distance taken from a depth image, or None where the box has no valid depth.

    The sensor sees the object's front surface: the median valid depth of the box's central
    :data:`DEPTH_CENTRE_SHARE` (each side) is compared with the same statistic of the posed model (rotation ``R``,
    translation ``t_box``): the front-most posed point in each cell of a :data:`_DEPTH_GRID` x :data:`_DEPTH_GRID` grid
    over that region (a coarse z-buffer), the median over cells. The model's centroid lies that far behind its
    front surface; ``t_box``'s centroid is moved along its ray until the two medians agree. Where no posed point
    falls in the region, half the object's depth along the optical axis is used as that offset.

    Args:
        R: ``(3, 3)`` rotation, object to camera. points_m: ``(P, 3)`` metres, object frame.
        t_box: ``(3,)`` metres, the box fit's translation. box_xyxy: ``(4,)`` pixels. K: ``(3, 3)``.
        depth: ``H x W`` float metres (:func:`refiner_rt.checks.validate_depth`).
    """
    box = np.asarray(box_xyxy, dtype=np.float64)
    h, w = depth.shape
    cx, cy = 0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3])
    hw, hh = 0.5 * DEPTH_CENTRE_SHARE * (box[2] - box[0]), 0.5 * DEPTH_CENTRE_SHARE * (box[3] - box[1])
    x1, x2 = int(np.clip(np.floor(cx - hw), 0, w)), int(np.clip(np.ceil(cx + hw), 0, w))
    y1, y2 = int(np.clip(np.floor(cy - hh), 0, h)), int(np.clip(np.ceil(cy + hh), 0, h))
    region = depth[y1:y2, x1:x2]
    valid = region[np.isfinite(region) & (region > 0)]
    if valid.size == 0:
        return None
    rotated = np.asarray(points_m, dtype=np.float64) @ np.asarray(R, dtype=np.float64).T
    centroid = rotated.mean(axis=0)
    posed = rotated + np.asarray(t_box, dtype=np.float64)
    c = centroid + np.asarray(t_box, dtype=np.float64)
    uv = pixel_coordinates(posed, np.asarray(K, dtype=np.float64))
    gx = np.floor((uv[:, 0] - (cx - hw)) / (2 * hw) * _DEPTH_GRID)
    gy = np.floor((uv[:, 1] - (cy - hh)) / (2 * hh) * _DEPTH_GRID)
    inside = (gx >= 0) & (gx < _DEPTH_GRID) & (gy >= 0) & (gy < _DEPTH_GRID)
    if inside.any():
        cell = (gy[inside] * _DEPTH_GRID + gx[inside]).astype(np.int64)
        front = np.full(_DEPTH_GRID * _DEPTH_GRID, np.inf)
        np.minimum.at(front, cell, posed[inside, 2])
        behind = c[2] - float(np.median(front[np.isfinite(front)]))
    else:
        behind = 0.5 * float(np.ptp(rotated[:, 2]))
    c = c * ((float(np.median(valid)) + behind) / c[2])
    return c - centroid


class PoseEstimator:
    """Rotation and translation of one object from boxes alone (module docstring).

    Args:
        coarse: the object's coarse :class:`RefinerSession` (runs every hypothesis).
        points_m: ``(P, 3)`` the object's surface points, metres, in the refiner's object frame (the depth rule).
        extent_m: ``(Q, 3)`` points whose projected bounding box is the object's (for the box fit), metres, same
            frame; None: ``points_m``.
        fine: the object's fine refiner, run once on the winning hypothesis, or None.
        hypotheses: rotations tried per box (``1`` to ``1024``).
        passes: coarse passes over every hypothesis before the check pass (``1`` to ``32``).
        ranking: ``"return+shape"`` (default), ``"return"`` or ``"residual"`` (module docstring): how the check pass
            ranks the hypotheses.

    Cost per box: ``hypotheses * (passes + 1)`` coarse network passes (one batched call per pass) and one fine pass.
    """

    def __init__(self, coarse: RefinerSession, points_m, fine: RefinerSession | None = None, *, extent_m=None,
                 hypotheses: int = DEFAULT_HYPOTHESES, passes: int = DEFAULT_PASSES, ranking: str = DEFAULT_RANKING):
        if not isinstance(coarse, RefinerSession) or not (fine is None or isinstance(fine, RefinerSession)):
            raise TypeError("coarse must be a RefinerSession and fine a RefinerSession or None; got "
                            f"{type(coarse).__name__}, {type(fine).__name__}")
        if coarse.contract.rotation_frame != "ray":
            raise ValueError("PoseEstimator needs a refiner trained in the viewing-ray frame (metadata "
                             f"rotation_frame='ray'); got {coarse.contract.rotation_frame!r}")
        pts = np.asarray(points_m, dtype=np.float64)
        ext = pts if extent_m is None else np.asarray(extent_m, dtype=np.float64)
        for name, a in (("points_m", pts), ("extent_m", ext)):
            if a.ndim != 2 or a.shape[1] != 3 or len(a) < 4 or not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be (P, 3) finite metres, P >= 4; got shape {a.shape}")
        if isinstance(hypotheses, bool) or not isinstance(hypotheses, (int, np.integer)) or not 1 <= hypotheses <= 1024:
            raise ValueError(f"hypotheses must be an integer from 1 to 1024; got {hypotheses!r}")
        if isinstance(passes, bool) or not isinstance(passes, (int, np.integer)) or not 1 <= passes <= 32:
            raise ValueError(f"passes must be an integer from 1 to 32; got {passes!r}")
        if ranking not in RANKINGS:
            raise ValueError(f"ranking must be one of {', '.join(RANKINGS)}; got {ranking!r}")
        self.coarse, self.fine, self.points_m, self.extent_m = coarse, fine, pts, ext
        self.hypotheses, self.passes, self.ranking = int(hypotheses), int(passes), ranking
        self._q_hyp = super_fibonacci(self.hypotheses)
        self._q_turn = return_turns(self.hypotheses)  # one fixed turn per hypothesis for the "return" check

    @classmethod
    def pretrained(cls, object_id: str, int8: bool = True, threads: int = 1, fine: bool = True,
                   **kwargs) -> "PoseEstimator":
        """The estimator of a shipped object: its coarse (and fine) refiner, its shipped surface points
        (``samples/outlines.json``) and extent points (``weights/extents.json``). ``kwargs``: ``hypotheses``,
        ``passes``, ``ranking``.

        Raises:
            ValueError: no model or no surface points ship for ``object_id``.
        """
        from refiner_rt.demo import load_outlines
        from refiner_rt.pretrained import pretrained_models

        outlines, extents = load_outlines(), load_extents()
        if object_id not in outlines or object_id not in extents:
            raise ValueError(f"no surface or extent points ship for object {object_id!r}; shipped for: "
                             f"{', '.join(sorted(set(outlines) & set(extents)))}")
        coarse = RefinerSession.pretrained(object_id, int8=int8, threads=threads)
        fine_session = None
        if fine and any(m.object_id == object_id and m.fine for m in pretrained_models()):
            fine_session = RefinerSession.pretrained(object_id, int8=int8, threads=threads, stage="fine")
        return cls(coarse, outlines[object_id].points_m, fine_session, extent_m=extents[object_id], **kwargs)

    def rotations(self, image_bgr, boxes_xyxy, K) -> tuple[np.ndarray, np.ndarray]:
        """The rotation search alone (checked inputs): ``(q (N, 4) wxyz, residual_deg (N,))``."""
        image = validate_image(image_bgr, "image_bgr")
        boxes = validate_boxes(boxes_xyxy, image.shape, "boxes_xyxy")
        K = validate_K(K)
        return self._rotations(image, boxes, K)

    def _rotations(self, image: np.ndarray, boxes: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(q (N, 4) wxyz object to camera, ranking residual (N,) degrees)`` of the chosen hypotheses."""
        n, h = len(boxes), self.hypotheses
        if n == 0:
            return np.zeros((0, 4)), np.zeros(0)
        c = self.coarse.contract
        crops = np.empty((n * h, c.input_size, c.input_size, 3), dtype=np.uint8)
        for i, box in enumerate(boxes):
            crop_to_square(image, box, c.input_size, c.crop_context, out=crops[i * h], crop_filter=c.crop_filter)
            crops[i * h + 1:(i + 1) * h] = crops[i * h]
        q = np.tile(self._q_hyp, (n, 1))  # in each box's viewing-ray frame: the network's own frame
        for _ in range(self.passes):
            q = self.coarse.refine_crops(crops, q).q_refined
        start = q if self.ranking == "residual" else rq.multiply(q, np.tile(self._q_turn, (n, 1)))
        residual = rq.geodesic_angle(self.coarse.refine_crops(crops, start).q_refined, q)
        q_ray_box = ray_quaternions(K, boxes)
        if self.ranking == "return+shape":
            q_all = rq.multiply(np.repeat(q_ray_box, h, axis=0), q)
            residual = ranking_residual(residual, q_all, self.extent_m, np.repeat(boxes, h, axis=0), K,
                                        image.shape[:2])
        best = residual.reshape(n, h).argmin(axis=1)
        rows = np.arange(n) * h + best
        q_ray = q[rows]
        if self.fine is not None:
            q_ray = self.fine.refine_crops(crops[rows], q_ray).q_refined
        q_cam = rq.canonical(rq.normalize(rq.multiply(q_ray_box, q_ray)))
        return q_cam, residual[rows]

    def estimate(self, image_bgr, boxes_xyxy, K, depth=None) -> PoseEstimate:
        """The 6D pose of the object in each box.

        Args:
            image_bgr: ``H x W x 3`` ``uint8`` image, **BGR**.
            boxes_xyxy: ``(N, 4)`` boxes ``(x1, y1, x2, y2)`` in pixels (continuous coordinates), one per instance
                of this object (:func:`refiner_rt.checks.validate_boxes`'s rules); ``N * hypotheses`` at most
                1024.
            K: ``(3, 3)`` pinhole intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels (required).
            depth: optional ``H x W`` float depth image in **metres** registered to ``image_bgr`` (0 or non-finite
                where unknown; :func:`refiner_rt.checks.validate_depth`). A box with no valid depth in its centre
                keeps the box fit.

        Returns:
            :class:`PoseEstimate`.

        Raises:
            ValueError / TypeError: a bad argument, named with what was expected and what was given.
        """
        image = validate_image(image_bgr, "image_bgr")
        boxes = validate_boxes(boxes_xyxy, image.shape, "boxes_xyxy")
        if K is None:
            raise ValueError("K is required: (3, 3) camera intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels")
        K = validate_K(K)
        if len(boxes) * self.hypotheses > 1024:
            raise ValueError(f"boxes_xyxy has {len(boxes)} boxes x {self.hypotheses} hypotheses = "
                             f"{len(boxes) * self.hypotheses} crops: at most 1024 per call; split the boxes")
        if depth is not None:
            depth = validate_depth(depth, image.shape)
        q, residual = self._rotations(image, boxes, K)
        R = rq.to_matrix(q) if len(q) else np.zeros((0, 3, 3))
        t = np.zeros((len(boxes), 3))
        for i, box in enumerate(boxes):
            t[i] = fit_translation(R[i], self.extent_m, box, K, image.shape[:2])
            if depth is not None:
                t_depth = depth_translation(R[i], self.points_m, t[i], box, K, depth)
                if t_depth is not None:
                    t[i] = t_depth
        return PoseEstimate(R=R, t=t, score=np.exp(-residual / 10.0), q=q)

    def __repr__(self) -> str:
        return (f"PoseEstimator(coarse={self.coarse.model_path}, fine={getattr(self.fine, 'model_path', None)}, "
                f"hypotheses={self.hypotheses}, passes={self.passes}, ranking={self.ranking!r}, points={len(self.points_m)})")
