"""RefinerCascade: an object's coarse refiner and its fine refiner, run in turn, for results below the coarse floor.

A coarse refiner corrects inputs up to 30 degrees off but has a floor: an input already better than a few degrees
comes out no better, and a perfect input is moved by the refiner's drift (docs/design.md §8; the measured floor is in
``benchmarks/studies/cascade``). A fine refiner (``RefinerSession.pretrained(obj, stage="fine")``,
``benchmarks/fine.py``) is the same network trained further on inputs a few degrees off only; it is sharper there
and blind far away (from an input far off it moves little). The cascade uses each where it is good:

1. both refiners look at every input, each averaging box-jittered views (``RefinerSession.refine(views=...)``):
   the coarse one ``coarse_views``, the fine one ``fine_views``;
2. where the fine correction is at most ``gate_deg`` and the coarse one at most ``coarse_gate_deg``, the input was
   already close: the fine result stands (a good input is not handed to the coarse refiner's floor; the coarse
   refiner's verdict catches the far inputs the fine one cannot see);
3. elsewhere (and for the rows given in ``coarse``, e.g. a detector's pose), the fine refiner from the coarse one's
   result; with ``settle_deg``, the coarse refiner first runs a second pass on those rows, kept where it turns the
   result by more than ``settle_deg`` (``RefinerSession.refine(settle_deg=...)``: a coarse pose 30-60 degrees off,
   beyond the range the coarse refiner trained on, is brought within the fine refiner's range; docs/design.md §7).

Each step is one batched call per refiner. Cost per object: ``coarse_views + fine_views`` network passes when the
gate holds, ``coarse_views + 2 * fine_views`` otherwise, and ``coarse_views`` more with ``settle_deg`` (``refiner-rt
bench --cpu`` times both beside the single model). ``gate_deg=None`` always runs coarse then fine. The shipped
objects' gates were chosen on rendered scenes (:func:`shipped_gate`). Safe across threads, as the sessions are (the
cascade keeps no state).

Example:
    >>> cascade = RefinerCascade.pretrained("003_cracker_box")
    >>> res = cascade.refine(image_bgr, boxes, q_in, K=K)   # res.q_refined: (N, 4) wxyz; res.coarse_used: (N,)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.checks import MAX_BATCH, MAX_VIEWS, check_coarse_rows, validate_settle
from refiner_rt.session import RefineResult, RefinerSession, settle_keeps

__all__ = ["RefinerCascade", "CascadeResult", "DEFAULT_GATE_DEG", "DEFAULT_COARSE_GATE_DEG", "DEFAULT_COARSE_VIEWS",
           "DEFAULT_FINE_VIEWS", "shipped_gate", "long_way"]

# The defaults (benchmarks/fine.py chooses each shipped object's gates on rendered scenes the card does not score,
# with these view counts): a fine correction of at most 2 degrees, and a coarse one of at most 8, mean the input was
# within the fine refiner's sharp range; four views for each refiner were chosen among view pairs on rendered scenes
# (benchmarks/studies/cascade, "Views: four for the coarse refiner too").
DEFAULT_GATE_DEG = 2.0
DEFAULT_COARSE_GATE_DEG = 8.0
DEFAULT_COARSE_VIEWS = 4
DEFAULT_FINE_VIEWS = 4


def shipped_gate(object_id: str) -> tuple[float, float]:
    """``(gate_deg, coarse_gate_deg)`` shipped with an object's fine refiner (``models.json``; chosen per object on
    rendered scenes the card does not score, ``benchmarks/fine.py gate``, for the default view counts), else the
    defaults."""
    from refiner_rt.pretrained import pretrained_models

    m = next((m for m in pretrained_models() if m.object_id == object_id), None)
    fine = m.fine if m is not None else {}
    return (float(fine.get("gate_deg", DEFAULT_GATE_DEG)),
            float(fine.get("coarse_gate_deg", DEFAULT_COARSE_GATE_DEG)))


def long_way(fine_move, coarse_move, gate_deg: float | None, coarse_gate_deg: float | None) -> np.ndarray:
    """The cascade's path rule, the one definition: which inputs go the long way (the fine refiner again from the
    coarse result), from each refiner's correction of the input (degrees). ``gate_deg`` None: all of them."""
    fine_move = np.asarray(fine_move, dtype=np.float64)
    if gate_deg is None:
        return np.ones(fine_move.shape, dtype=bool)
    far = fine_move > gate_deg
    if coarse_gate_deg is not None:
        far |= np.asarray(coarse_move, dtype=np.float64) > coarse_gate_deg
    return far


def _check_gate(value, name: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and 0 < value <= 30):
        raise ValueError(f"{name} must be a number of degrees in (0, 30], or None; got {value!r}")
    return float(value)


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
        gate_deg: the fine result stands where the fine correction is at most this many degrees (and the coarse one
            at most ``coarse_gate_deg``); a number in ``(0, 30]``, or ``None``: always coarse then fine.
        coarse_gate_deg: the coarse correction above which an input counts as far whatever the fine refiner says;
            a number in ``(0, 30]``, or ``None``: no such check.
        coarse_views: box-jittered views the coarse refiner averages (``1`` to ``MAX_VIEWS``).
        fine_views: box-jittered views the fine refiner averages (``1`` to ``MAX_VIEWS``).
        settle_deg: on the long way, a second coarse pass, kept where it turns the coarse result by more than this
            many degrees (:data:`refiner_rt.session.SETTLE_DEG` is the measured value): for coarse poses that may be
            more than 30 degrees off. A number in ``(0, 180)``, or None (default): one coarse pass.

    Raises:
        TypeError / ValueError: not sessions, sessions whose crop contracts differ, or a bad gate or view count.
    """

    #: :class:`refiner_rt.Refiner`'s capability: the passes and views are fixed here, not per :meth:`refine` call.
    per_call_passes = False

    def __init__(self, coarse: RefinerSession, fine: RefinerSession, *, gate_deg: float | None = DEFAULT_GATE_DEG,
                 coarse_gate_deg: float | None = DEFAULT_COARSE_GATE_DEG, coarse_views: int = DEFAULT_COARSE_VIEWS,
                 fine_views: int = DEFAULT_FINE_VIEWS, settle_deg: float | None = None):
        for name, s in (("coarse", coarse), ("fine", fine)):
            if not isinstance(s, RefinerSession):
                raise TypeError(f"{name} must be a RefinerSession; got {type(s).__name__}")
        a, b = coarse.contract, fine.contract
        if (a.input_size, a.crop_context, a.rotation_frame) != (b.input_size, b.crop_context, b.rotation_frame):
            raise ValueError("coarse and fine must cut the same crops: input_size, crop_context and rotation_frame "
                             f"differ ({a.input_size}, {a.crop_context}, {a.rotation_frame!r} against "
                             f"{b.input_size}, {b.crop_context}, {b.rotation_frame!r})")
        gate_deg, coarse_gate_deg = _check_gate(gate_deg, "gate_deg"), _check_gate(coarse_gate_deg, "coarse_gate_deg")
        for name, views in (("coarse_views", coarse_views), ("fine_views", fine_views)):
            if type(views) is not int or not 1 <= views <= MAX_VIEWS:
                raise ValueError(f"{name} must be an int in [1, {MAX_VIEWS}]; got {views!r}")
        self.coarse, self.fine = coarse, fine
        self.gate_deg, self.coarse_gate_deg = gate_deg, coarse_gate_deg
        self.coarse_views, self.fine_views = coarse_views, fine_views
        self.settle_deg = validate_settle(settle_deg)  # its second coarse pass is the cascade's own

    @classmethod
    def pretrained(cls, object_id: str, int8: bool = True, threads: int = 1, **kwargs) -> "RefinerCascade":
        """The cascade of the refiners shipped for ``object_id`` (``refiner-rt models`` lists the objects with a
        fine refiner), with the gates chosen for that object (:func:`shipped_gate`). ``kwargs``: ``gate_deg``,
        ``coarse_gate_deg``, ``coarse_views``, ``fine_views`` and ``settle_deg``.

        Raises:
            ValueError: no model, or no fine refiner, ships for ``object_id``.
        """
        coarse = RefinerSession.pretrained(object_id, int8=int8, threads=threads)
        fine = RefinerSession.pretrained(object_id, int8=int8, threads=threads, stage="fine")
        gate, coarse_gate = shipped_gate(object_id)
        kwargs.setdefault("gate_deg", gate)
        kwargs.setdefault("coarse_gate_deg", coarse_gate)
        return cls(coarse, fine, **kwargs)

    @property
    def contract(self):
        """The crop contract both refiners share (the coarse model's :class:`refiner_rt.metadata.ModelContract`)."""
        return self.coarse.contract

    def refine(self, image_bgr, boxes_xyxy, q_in_wxyz, *, K=None, D=None, q_order: str = "wxyz",
               coarse=None) -> CascadeResult:
        """Refine ``N`` objects of one image, as :meth:`RefinerSession.refine` (the same arguments, keyword-only
        after ``q_in_wxyz``, and the same checks; the passes and views were fixed when the cascade was built, so
        ``iterations``, ``views`` and ``settle_deg`` are not among them: :attr:`per_call_passes` is False).
        Each refiner's call crops ``N`` times its views: ``N`` is at most ``MAX_BATCH // max(coarse_views,
        fine_views)`` (256 with the defaults).

        Args:
            coarse: ``(N,)`` bools, or None: rows to send through the coarse refiner whatever the gate says (a
                detector's pose, known to be coarse).

        Returns:
            :class:`CascadeResult`.
        """
        views = max(self.coarse_views, self.fine_views)
        shape = np.shape(boxes_xyxy)
        if len(shape) == 2 and shape[1] == 4 and shape[0] * views > MAX_BATCH:  # other shapes: the session's checks
            raise ValueError(f"boxes_xyxy has {shape[0]} entries: a cascade with coarse_views={self.coarse_views} and "
                             f"fine_views={self.fine_views} takes at most MAX_BATCH // {views} = "
                             f"{MAX_BATCH // views} boxes per call (MAX_BATCH={MAX_BATCH} crops); split them over "
                             "several calls")
        mid = self.coarse.refine(image_bgr, boxes_xyxy, q_in_wxyz, K=K, q_order=q_order, D=D,
                                 views=self.coarse_views)
        n = len(mid)
        forced = np.zeros(n, dtype=bool) if coarse is None else check_coarse_rows(coarse, n)
        q_in = mid.q_in
        if n == 0:
            return CascadeResult(q_refined=q_in.copy(), q_out=q_in.copy(), q_in=q_in, coarse_used=forced)
        boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
        far = forced.copy() if self.gate_deg is not None else np.ones(n, dtype=bool)
        q = np.zeros_like(q_in)
        if not far.all():
            first = self.fine.refine(image_bgr, boxes[~far], q_in[~far], K=K, views=self.fine_views, D=D).q_refined
            near = ~long_way(rq.geodesic_angle(q_in[~far], first), rq.geodesic_angle(q_in[~far], mid.q_refined[~far]),
                             self.gate_deg, self.coarse_gate_deg)
            rows = np.flatnonzero(~far)
            q[rows[near]] = first[near]
            far[rows[~near]] = True
        if far.any():
            start = mid.q_refined[far]
            if self.settle_deg is not None:  # RefinerSession.refine(iterations=2, settle_deg=...) from mid's pass
                again = self.coarse.refine(image_bgr, boxes[far], start, K=K, D=D, views=self.coarse_views).q_refined
                moved = settle_keeps(start, again, self.settle_deg)
                start[moved] = again[moved]
            q[far] = self.fine.refine(image_bgr, boxes[far], start, K=K, views=self.fine_views, D=D).q_refined
        q_out = rq.canonical(rq.normalize(rq.multiply(rq.inverse(q_in), q)))
        return CascadeResult(q_refined=q, q_out=q_out, q_in=q_in, coarse_used=far)

    def __repr__(self) -> str:
        return (f"RefinerCascade(coarse={self.coarse.model_path}, fine={self.fine.model_path}, "
                f"gate_deg={self.gate_deg}, coarse_gate_deg={self.coarse_gate_deg}, coarse_views={self.coarse_views}, "
                f"fine_views={self.fine_views}, settle_deg={self.settle_deg})")
