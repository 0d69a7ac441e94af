"""RefinerCascade: an object's coarse refiner and its fine refiner, run in turn, for results below the coarse floor.

A coarse refiner corrects inputs up to 30 degrees off but has a floor: an input better than about 3 degrees comes
out worse, and a perfect input is moved by 2-3 degrees. A fine refiner (``RefinerSession.pretrained(obj,
stage="fine")``, ``benchmarks/fine.py``) is the same network trained further on inputs a few degrees off only; it is
sharper there and useless far away. The cascade uses each where it is good:

1. the fine refiner first, on every input, averaging ``fine_views`` box-jittered views (``RefinerSession.refine
   (views=...)``): when its correction is at most ``gate_deg`` the input was already close, and that is the result
   (a good input is not handed to the coarse refiner, which would move it by its floor);
2. for the others (and the rows given in ``coarse``, e.g. a detector's pose), the coarse refiner from the input,
   then the fine refiner from its output.

Each step is one batched call per refiner. Cost per object: ``fine_views`` network passes when the gate holds,
``1 + 2 * fine_views`` otherwise (``refiner-rt bench --cpu`` times it beside the single model). ``gate_deg=None``
always runs coarse then fine. Safe across threads, as the sessions are (the cascade keeps no state).

Example:
    >>> cascade = RefinerCascade.pretrained("003_cracker_box")
    >>> res = cascade.refine(image_bgr, boxes, q_in, K=K)   # res.q_refined: (N, 4) wxyz; res.coarse_used: (N,)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.geometry import MAX_VIEWS
from refiner_rt.session import RefineResult, RefinerSession

__all__ = ["RefinerCascade", "CascadeResult", "DEFAULT_GATE_DEG", "DEFAULT_FINE_VIEWS"]

# The gate and the fine refiner's views, chosen on the cracker box's fresh renders (crops, fp32; benchmarks/fine.py):
# a fine correction of at most 2 degrees means the input was within the fine refiner's sharp range (3 degrees let
# inputs 10-20 degrees off through: 2.69 against 2.40 from U(0, 30)); four views took a sixth to a fifth off its
# error from the true pose (1.25 -> 1.04, one view against four, before its second stage).
DEFAULT_GATE_DEG = 2.0
DEFAULT_FINE_VIEWS = 4


@dataclass(frozen=True)
class CascadeResult(RefineResult):
    """Output of :meth:`RefinerCascade.refine`: a :class:`RefineResult` (``q_out`` is the whole correction,
    ``q_refined = q_in * q_out``) and ``coarse_used``, ``(N,)`` bool: which objects went through the coarse
    refiner (the gate did not hold, or the caller asked)."""

    coarse_used: np.ndarray = None


class RefinerCascade:
    """An object's coarse and fine refiners, run in turn (module docstring).

    Args:
        coarse: the coarse :class:`RefinerSession` (inputs up to 30 degrees off).
        fine: the fine :class:`RefinerSession` of the same object (same crop contract).
        gate_deg: accept the fine refiner's result alone when its correction is at most this many degrees; a number
            in ``(0, 30]``, or ``None``: always coarse then fine.
        fine_views: box-jittered views the fine refiner averages (``1`` to ``MAX_VIEWS``).

    Raises:
        TypeError / ValueError: not sessions, sessions whose crop contracts differ, or a bad ``gate_deg`` /
            ``fine_views``.
    """

    def __init__(self, coarse: RefinerSession, fine: RefinerSession, *, gate_deg: float | None = DEFAULT_GATE_DEG,
                 fine_views: int = DEFAULT_FINE_VIEWS):
        for name, s in (("coarse", coarse), ("fine", fine)):
            if not isinstance(s, RefinerSession):
                raise TypeError(f"{name} must be a RefinerSession; got {type(s).__name__}")
        a, b = coarse.contract, fine.contract
        if (a.input_size, a.crop_context, a.rotation_frame) != (b.input_size, b.crop_context, b.rotation_frame):
            raise ValueError("coarse and fine must cut the same crops: input_size, crop_context and rotation_frame "
                             f"differ ({a.input_size}, {a.crop_context}, {a.rotation_frame!r} against "
                             f"{b.input_size}, {b.crop_context}, {b.rotation_frame!r})")
        if gate_deg is not None:
            if isinstance(gate_deg, bool) or not isinstance(gate_deg, (int, float)) or not (
                    math.isfinite(gate_deg) and 0 < gate_deg <= 30):
                raise ValueError(f"gate_deg must be a number of degrees in (0, 30], or None; got {gate_deg!r}")
            gate_deg = float(gate_deg)
        if type(fine_views) is not int or not 1 <= fine_views <= MAX_VIEWS:
            raise ValueError(f"fine_views must be an int in [1, {MAX_VIEWS}]; got {fine_views!r}")
        self.coarse, self.fine = coarse, fine
        self.gate_deg, self.fine_views = gate_deg, fine_views

    @classmethod
    def pretrained(cls, object_id: str, int8: bool = True, threads: int = 1, **kwargs) -> "RefinerCascade":
        """The cascade of the refiners shipped for ``object_id`` (``refiner-rt models`` lists the objects with a
        fine refiner). ``kwargs``: ``gate_deg`` and ``fine_views``.

        Raises:
            ValueError: no model, or no fine refiner, ships for ``object_id``.
        """
        coarse = RefinerSession.pretrained(object_id, int8=int8, threads=threads)
        fine = RefinerSession.pretrained(object_id, int8=int8, threads=threads, stage="fine")
        return cls(coarse, fine, **kwargs)

    @property
    def contract(self):
        """The crop contract both refiners share (the coarse model's :class:`refiner_rt.metadata.Contract`)."""
        return self.coarse.contract

    def refine(self, image_bgr, boxes_xyxy, q_in_wxyz, K=None, *, q_order: str = "wxyz", D=None,
               coarse=None) -> CascadeResult:
        """Refine ``N`` objects of one image, as :meth:`RefinerSession.refine` (same arguments, same checks).

        Args:
            coarse: ``(N,)`` bools, or None: rows to send through the coarse refiner whatever the gate says (a
                detector's pose, known to be coarse).

        Returns:
            :class:`CascadeResult`.
        """
        first = self.fine.refine(image_bgr, boxes_xyxy, q_in_wxyz, K=K, views=self.fine_views, q_order=q_order, D=D)
        n = len(first)
        forced = np.zeros(n, dtype=bool)
        if coarse is not None:
            forced = np.asarray(coarse)
            if forced.dtype != bool or forced.shape != (n,):
                raise ValueError(f"coarse must be None or ({n},) bools, one per box; got "
                                 f"{'dtype ' + str(forced.dtype) if forced.dtype != bool else 'shape'} "
                                 f"{forced.shape}")
        q_in, q = first.q_in, first.q_refined.copy()
        far = forced | (True if self.gate_deg is None else rq.geodesic_angle(q_in, q) > self.gate_deg)
        far = np.broadcast_to(far, (n,)).copy()
        if far.any():
            boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)[far]
            mid = self.coarse.refine(image_bgr, boxes, q_in[far], K=K, D=D)
            q[far] = self.fine.refine(image_bgr, boxes, mid.q_refined, K=K, views=self.fine_views, D=D).q_refined
        q_out = rq.canonical(rq.normalize(rq.multiply(rq.inverse(q_in), q))) if n else q.copy()
        return CascadeResult(q_refined=q, q_out=q_out, q_in=q_in, coarse_used=far)

    def __repr__(self) -> str:
        return (f"RefinerCascade(coarse={self.coarse.model_path}, fine={self.fine.model_path}, "
                f"gate_deg={self.gate_deg}, fine_views={self.fine_views})")
