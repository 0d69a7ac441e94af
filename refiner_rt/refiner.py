"""The refiner interface (:class:`Refiner`) and :func:`load`, the one place that decides an object's shipped refiner.

A refiner is anything robot code calls ``refine(image_bgr, boxes_xyxy, q_in_wxyz, *, K=..., D=..., q_order=...,
coarse=...)`` on: a :class:`refiner_rt.RefinerSession` (one network) or a :class:`refiner_rt.RefinerCascade` (an
object's coarse and fine networks in turn). The tracker and the ROS 2 code take either through this protocol and ask
it what it can do (:attr:`Refiner.per_call_passes`), never which class it is (docs/design.md §10).

Conventions (docs/design.md §2): quaternions ``wxyz``, rotations object-to-camera, images ``H x W x 3`` uint8 BGR,
boxes ``(x1, y1, x2, y2)`` pixels, angles in degrees.

Example:
    >>> import refiner_rt
    >>> refiner = refiner_rt.load("003_cracker_box")                  # the shipped INT8 coarse refiner
    >>> res = refiner.refine(image_bgr, boxes_xyxy, q_in_wxyz, K=K)   # res.q_refined: (N, 4) wxyz
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Protocol, runtime_checkable

from refiner_rt.pretrained import STAGES, pretrained_model

if TYPE_CHECKING:
    from refiner_rt.metadata import ModelContract
    from refiner_rt.session import RefineResult

__all__ = ["Refiner", "load"]

log = logging.getLogger(__name__)


@runtime_checkable
class Refiner(Protocol):
    """What :class:`refiner_rt.RefinerSession` and :class:`refiner_rt.RefinerCascade` both are.

    Attributes:
        contract: the crop contract of the model(s) (:class:`refiner_rt.metadata.ModelContract`): its ``objects``
            say which objects it may refine.
        per_call_passes: True when ``iterations``, ``views`` and ``settle_deg`` are arguments of :meth:`refine`
            (a session); False when they were fixed when the refiner was built (a cascade: ``coarse_views``,
            ``fine_views``, ``settle_deg``) and :meth:`refine` takes none of them.
    """

    contract: ModelContract
    per_call_passes: bool

    def refine(self, image_bgr, boxes_xyxy, q_in_wxyz, *, K=None, D=None, q_order: str = "wxyz",
               coarse=None) -> RefineResult:
        """Refine ``N`` objects of one image.

        Args:
            image_bgr: ``H x W x 3`` uint8 image, BGR.
            boxes_xyxy: ``(N, 4)`` boxes ``(x1, y1, x2, y2)`` in pixels.
            q_in_wxyz: ``(N, 4)`` coarse object-to-camera rotations, ``wxyz`` (or ``q_order``), or ``(N, 3, 3)``
                rotation matrices.
            K: ``(3, 3)`` camera intrinsics in pixels (the shipped models need it).
            D: the camera's distortion coefficients (OpenCV's model), or None.
            q_order: ``"wxyz"`` or ``"xyzw"``: the order of ``q_in_wxyz``.
            coarse: ``(N,)`` bools or None: rows known to be coarse (a detector's pose), which must go through the
                coarse refiner (a session refines every row with its one network anyway).

        Returns:
            a :class:`refiner_rt.RefineResult` (``q_refined``: ``(N, 4)`` float64 ``wxyz``).
        """
        ...


def load(object_id: str, *, stage: str = "coarse", cascade: bool = False, int8: bool = True, threads: int = 1,
         settle_deg: float | None = None) -> Refiner:
    """The refiner shipped for ``object_id`` (package data; nothing is downloaded).

    Args:
        object_id: a YCB id such as ``"003_cracker_box"`` (``refiner-rt models`` and
            :func:`refiner_rt.pretrained_models` list them).
        stage: ``"coarse"`` (default: inputs up to 30 degrees off) or ``"fine"`` (inputs a few degrees off: the
            coarse refiner's output, the previous video frame's); a single :class:`refiner_rt.RefinerSession`.
        cascade: the object's :class:`refiner_rt.RefinerCascade` (coarse and fine refiners in turn, with the gates
            shipped for it) where a fine refiner ships; the coarse session where none does (``pretrained_models()``
            lists each object's stages). Only with ``stage="coarse"``.
        int8: the INT8 models (default, fastest) or the fp32 ones.
        threads: onnxruntime threads per network (``>= 1``; ``0``: every core this process may run on).
        settle_deg: a cascade's second coarse pass on the long way (:class:`refiner_rt.RefinerCascade`); only with
            ``cascade=True``, and unused where the coarse session stands in for the cascade.

    Returns:
        a :class:`Refiner`: a session or a cascade. The shipped models work in the viewing-ray frame: pass ``K`` to
        ``refine``.

    Raises:
        TypeError: ``object_id`` is not a string.
        ValueError: no model ships for ``object_id`` (the message lists those that do), an unknown stage,
            ``cascade=True`` with ``stage="fine"``, ``settle_deg`` without ``cascade``, or no fp32 file ships.
    """
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {', '.join(STAGES)}; got {stage!r}")
    if cascade and stage != "coarse":
        raise ValueError(f"cascade=True runs the coarse and the fine refiner in turn: leave stage='coarse'; got "
                         f"stage={stage!r}")
    if settle_deg is not None and not cascade:
        raise ValueError("settle_deg is a cascade's option here: give cascade=True, or pass settle_deg (with "
                         "iterations=2) to RefinerSession.refine")
    model = pretrained_model(object_id)  # raises for an unknown object
    if cascade and "fine" in model.stages:
        from refiner_rt.cascade import RefinerCascade

        return RefinerCascade.pretrained(object_id, int8=int8, threads=threads, settle_deg=settle_deg)
    if cascade:
        log.debug("%s: no fine refiner ships; loading its coarse refiner alone", object_id)
    from refiner_rt.session import RefinerSession

    return RefinerSession.pretrained(object_id, int8=int8, threads=threads, stage=stage)
