"""RefinerTracker: refine each object's rotation frame after frame, its previous refined rotation as the coarse pose.

The paper refines one frame from a detector's coarse pose. In video the best coarse pose for frame ``t`` is
usually the refined pose of frame ``t - 1``: a detector's pose is needed once (and again only to recover), and
every later frame costs one network pass per object. ``benchmarks/tracking.py`` measures this on rendered video.

Conventions (docs/design.md §2):
    * quaternions are ``wxyz`` (scalar first, Hamilton product), float64, returned with ``w >= 0``;
    * rotations map object coordinates to camera coordinates (``x_cam = R @ x_obj + t``);
    * images are ``H x W x 3`` ``uint8`` **BGR** (what ``cv2.imread`` gives);
    * boxes are ``(x1, y1, x2, y2)`` in pixels, continuous coordinates (pixel ``i`` covers ``[i, i+1)``);
    * angles are in degrees.

Object ids are YCB ids (``"003_cracker_box"``), optionally with a ``#suffix`` that tells two instances of one
object apart (``"003_cracker_box#2"``); the part before ``#`` must be an object the session's model was trained for.

Constant-angular-velocity prediction (``predict=True``): the rotation change between an object's last two refined
rotations, taken in the camera frame, ``dq = q_t * q_{t-1}^-1`` per update, is applied once more before refining,
``q_in = dq * q_t`` (a camera turning steadily around a still object turns it at a constant rate in the camera
frame). Only refined rotations enter ``dq``: the correction of a coarse initial pose is not motion.

Scene-motion prediction (``predict="scene"``): for a camera moving over objects that stand still (a camera on a
robot's arm or head looking over a table). Every still object turns in the camera frame by the same rotation, the
camera's own turn inverted, so the tracker estimates that one turn from all its tracks at once: for each track, the
change between the refiner's results across the last ``motion_window`` updates, per update; their mean (without the
tracks far from the others: one drifting off, or an object that moved) is the scene's turn per update. Before each
update every refined track is turned by it, those without a box too: an object hidden for a while comes back where
the camera's motion took it, not where it was last seen (with ``predict=True`` or without prediction, a track held
through a long occlusion while the camera moves is far off when it returns). The mean over objects and updates is
much steadier than one object's last change. Objects that move by themselves (one being carried) break the
assumption: use ``predict=True`` or no prediction there.

Prediction weight (``prediction_weight``): once a prediction is made (the motion measured), the new rotation may
keep a share of it: ``q`` is taken that fraction of the way from the refined rotation back to the predicted one
(``0``: the refined rotation as is). A refinement's noise is then damped while the prediction carries the motion. With the scene's motion, once its turn is
measured, the new rotation also stays within ``max_correction_deg`` of the prediction: the camera's motion is
carried by the prediction, so a refinement that pulls further (a view the refiner misreads, frame after frame) is
followed only that far per update. Defaults with ``predict="scene"``: weight 0.3, 2 degrees, window 4 updates, chosen
on rendered video the tracking benchmark does not score (``benchmarks/studies/cascade``).

The temporal filter (no prediction, the default): the object is taken to hold still, so its last rotation is the
prediction from its second update on (not the coarse start): the new rotation keeps a quarter of it
(``prediction_weight=0.25``) and stays within 3 degrees of it (``max_correction_deg=3``). On the real frames a
refiner's correction from frame to frame is 1-3 degrees while the truth turns by less than 0.1; on rendered video a
refinement sometimes jumps into a wrong pose that later frames then hold (a view whose refinement has no fixed point
nearby). The limit follows a camera turning up to 3 degrees per update; ``prediction_weight=0, max_correction_deg=180``
turns the filter off. Both chosen on rendered robot-layout video (``benchmarks/studies/tracking_real``).

Several starts per update (``starts=N``): refined from its own last rotation alone, a track can settle on a view's
wrong fixed point and stay there, which refining every frame from a fresh detector pose avoids. With ``starts=N`` (5
or 9) each update refines the object from its last rotation and from ``N - 1`` rotations turned :data:`START_DEG`
degrees from it (about a tetrahedron's four axes, with 9 also the opposite four, in the object frame: turns that
balance, so their mean does not lean), each crop on its own fixed jitter of the box (``views``' jitters; the box
itself where a jitter falls mostly outside the image), and keeps their chordal mean
(:func:`refiner_rt.quaternion.mean`); the starts' spread about it adds to the score as the views' does. ``N``
network passes per object and update. With ``starts=5`` tracks from one first-frame pose and no detector after it
were 3.58 degrees off on the real dev videos against 4.78 for refining every frame from a detector's pose, and 4.12
against 4.02 on held-out rendered video, where hard views still take tracks on excursions
(``benchmarks/studies/tracking_real``, "Several starts per update"); wider turns (25-30 degrees) walked away on
rendered video.

Confidence: :attr:`RefinerTracker.scores` has each refined object's :attr:`refiner_rt.RefineResult.score` of the last
update (from its last rotation, one pass: a second opinion on it).

Loss-of-track check (``lost_deg``): a tracker that loses an object rarely finds it again, since the refiner is
trained on coarse poses within 30 degrees of the truth. The check needs no ground truth: the refined rotation is
refined once more (a second network pass in the same batched call per session), and an object whose rotation that
second pass moves by more than ``lost_deg`` degrees is flagged lost (the refiner does not agree with its own
output: near the truth it moves little). A flagged object is listed in :attr:`RefinerTracker.lost`; when
:meth:`RefinerTracker.update` is given a ``detector``, it is re-initialised from the detector's coarse pose and
refined from it in the same update, and :attr:`RefinerTracker.redetections` counts it.

Re-initialisation without a detector (``reinit=True``, with ``lost_deg``): a flagged object for which the detector
gives no pose is searched for on its box. Its rotation is refined :data:`REINIT_PASSES` more times; where that turns
it by more than :data:`REINIT_GATE_DEG` (the refiner pulls it elsewhere), the rotation search of
:class:`refiner_rt.PoseEstimator` runs on the box: :data:`REINIT_HYPOTHESES` rotations spread over SO(3) about the
box's viewing ray and the track's own, each refined :data:`REINIT_PASSES` times, ranked by the "return" residual
(plus the box-shape term for shipped objects; docs/pose6d.md); a start other than the track's own wins only by
:data:`REINIT_MARGIN_DEG`. The winner is taken, as a new start, only where one more pass moves it by at most
``lost_deg`` (the check would pass it); elsewhere the track is kept and stays in :attr:`RefinerTracker.lost`.
:attr:`RefinerTracker.reinits` counts the objects re-initialised. Cost: only on flagged objects,
:data:`REINIT_PASSES` network passes, and where the gate opens ``(REINIT_HYPOTHESES + 1) * (REINIT_PASSES + 1) - 2``
more. On rendered video it ends part of the excursions of tracks started 45-90 degrees off and leaves tracks started
within 30 degrees about as they were (``benchmarks/studies/tracking_real``, "Ending excursions"). What it cannot
end: a view whose refinement has a wrong fixed point (the search's passes settle there too) and a front-back flip
that agrees with itself (the check does not flag it).

A :class:`refiner_rt.RefinerCascade` in place of a session runs its coarse refiner, then its fine one, on every
update (its gate is for single refinements: from frame to frame the fine refiner alone let small errors add up on
rendered video), and its coarse refiner is the loss check's second opinion. It averages its own views
(``coarse_views`` and ``fine_views``; the tracker's ``iterations`` and ``views`` are for sessions): with the defaults
eight network passes per object and update, and eight more for the loss check or a fused detection.

Fusing a detector (``detector_weight``): when a detector gives poses in many frames (every frame, or every few), a
track need not choose between them and its own estimate. Each update then refines both, the tracked rotation and the
detector's pose (one batched network call, two rows per object), and keeps the rotation a fraction ``w`` of the way
from the refined track to the refined detection along the shortest arc (``q = (q_det * q_track^-1) ** w * q_track``).
The track carries what earlier frames saw, so a poor refinement in one frame moves it by only ``w`` of its error;
the detections pull a drifting track back (a turn the refiner cannot see, such as a can's about its own axis, is not
left to accumulate). ``w = 1`` is the paper's per-frame refinement; the frames without a detector pose are plain
tracking.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping

import numpy as np

from refiner_rt import quaternion as rq
from refiner_rt.distortion import undistort_boxes
from refiner_rt.estimate import ranking_residual, return_turns, super_fibonacci
from refiner_rt.geometry import ray_quaternions, view_boxes
from refiner_rt.placement import load_extents
from refiner_rt.checks import (MAX_BATCH, as_wxyz, boxes_rows, validate_boxes, validate_D,
                               validate_image, validate_iterations, validate_K, validate_settle, validate_starts,
                               validate_views)
from refiner_rt.quaternion import inverse_rows, multiply_rows, normalize_rows
from refiner_rt.refiner import Refiner, load
from refiner_rt.session import RefineResult

__all__ = ["RefinerTracker", "INSTANCE_SEPARATOR", "LOST_DEG", "REINIT_PASSES", "REINIT_GATE_DEG", "REINIT_HYPOTHESES",
           "REINIT_MARGIN_DEG", "START_DEG", "object_name"]

log = logging.getLogger(__name__)

PREDICTIONS = ("object", "scene")
# chosen on rendered video the benchmark does not score (benchmarks/studies/cascade, "Tracking with the scene's motion")
DEFAULT_MOTION_WINDOW = 4  # updates
DEFAULT_SCENE_PREDICTION_WEIGHT = 0.3
DEFAULT_SCENE_MAX_CORRECTION_DEG = 2.0
# without a motion prediction (the last rotation is the prediction): chosen on rendered robot-layout video
# (tracking_robot_s561, benchmarks/studies/tracking_real) among weights 0-0.65 and limits 3 degrees or none
DEFAULT_HOLD_PREDICTION_WEIGHT = 0.25
DEFAULT_HOLD_MAX_CORRECTION_DEG = 3.0
# the loss-of-track check's threshold to use (RefinerTracker(lost_deg=...), refiner-rt track --lost-deg): chosen on
# rendered robot-layout video (tracking_robot_s561, benchmarks/studies/tracking_real) with the temporal filter on,
# the largest share of tracks ending above 30 degrees flagged with at most 10% of good frames (below 15) flagged
LOST_DEG = 2.5
# re-initialising a flagged track from its box (reinit=True): chosen on rendered robot-layout video
# (tracking_robot_s561, benchmarks/studies/tracking_real, "Ending excursions"): the least error of tracks started 45-90
# degrees off among the variants that left tracks started within 30 degrees no worse
REINIT_PASSES = 3  # refinement passes from each start
REINIT_GATE_DEG = 15.0  # the search runs where those passes turn the track's own rotation by more than this
REINIT_HYPOTHESES = 8  # rotations over SO(3) searched besides the track's own
REINIT_MARGIN_DEG = 20.0  # another start replaces the track's own only with a ranking residual this much lower
# several starts per update (starts=N): the last rotation and N - 1 rotations turned START_DEG from it about fixed
# axes (a tetrahedron's, and with 9 the opposite one's too: turns that balance), each cropped from its own fixed box
# jitter; chosen on rendered robot-layout video (tracking_robot_s561, benchmarks/studies/tracking_real, "Several
# starts per update")
START_DEG = 15.0
_START_AXES = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1],
                        [-1, -1, -1], [-1, 1, 1], [1, -1, 1], [1, 1, -1]], dtype=np.float64) / math.sqrt(3.0)
TURN_OUTLIER_DEG = 0.2  # per update: a track's change further from the medoid than this and twice the median is left out
INSTANCE_SEPARATOR = "#"  # "003_cracker_box#2": the second cracker box, refined by the cracker box's model


def object_name(object_id: str) -> str:
    """The YCB id part of an object id (``"003_cracker_box#2"`` -> ``"003_cracker_box"``)."""
    return object_id.split(INSTANCE_SEPARATOR, 1)[0]


class _Track:
    """One tracked object: its session, current rotation and (for prediction) its last rotation change."""

    __slots__ = ("session", "q", "refined", "velocity", "missed", "history")

    def __init__(self, session: Refiner, q: np.ndarray):
        self.session = session
        self.q = q  # [w, x, y, z] Python floats, unit, w >= 0: the current estimate (coarse until the first update)
        self.refined = False  # whether q came from the refiner (only then does it count for the velocity)
        self.velocity = None  # [w, x, y, z]: rotation change per update in the camera frame, or None
        self.missed = 0  # updates since this object was last refined (it had no box)
        self.history: list[tuple[int, list]] = []  # (update index, the refiner's result): the scene turn's source


class RefinerTracker:
    """Track the rotations of objects through video with :class:`RefinerSession` refinements.

    Each :meth:`update` refines every object that has a box in the frame, starting from its previous refined
    rotation (or, right after construction, :meth:`add` or :meth:`reset`, from the coarse rotation given there).
    Objects that share a session are refined in one batched :meth:`RefinerSession.refine` call. An object without
    a box in a frame (not detected, hidden) keeps its rotation until it is seen again; with ``predict="scene"`` it
    turns with the camera.

    Args:
        session: the refiner(s). A :class:`RefinerSession` refines every object (each object id must be one of its
            model's objects); a string loads that shipped model with :func:`refiner_rt.load` (INT8, one
            thread) for every object; a mapping ``object id -> RefinerSession or pretrained name`` gives each object
            its own (a name is loaded once and shared by the objects that name it).
        K: ``(3, 3)`` camera intrinsics in pixels, ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` (the shipped models
            need it: they work in the viewing-ray frame).
        q0: ``{object id: (4,) coarse rotation}``, object-to-camera, ``wxyz`` (e.g. a detector's pose); finite and
            non-zero, normalised here. May be empty (add objects later with :meth:`add`).
        predict: the prediction made before each refinement (module docstring): ``False`` (default) none, ``True``
            or ``"object"`` each object's constant angular velocity, ``"scene"`` the camera's turn shared by still
            objects (estimated from every track; hidden objects are carried with it).
        motion_window: with ``predict="scene"``, the updates over which each track's change is measured (an int
            ``>= 2``); None (default): 4.
        prediction_weight: the share of the prediction kept in each new rotation, in ``[0, 1)`` (without
            ``predict`` the last rotation is the prediction: the temporal filter). None (default): 0.3 with
            ``predict="scene"``, 0.25 without a prediction, 0 with ``predict="object"``.
        max_correction_deg: the most degrees a new rotation may differ from its prediction (with
            ``predict="scene"`` once the scene's turn is measured), in ``(0, 180]`` (180: no limit). None
            (default): 2 with ``predict="scene"``, 3 without a prediction, no limit with ``predict="object"``.
        iterations: refinement passes per update (``>= 1``), as :meth:`RefinerSession.refine` (sessions only: a
            :class:`RefinerCascade` runs its own passes).
        views: crops averaged per object and update (``1`` to ``MAX_VIEWS``), as :meth:`RefinerSession.refine`
            (sessions only: a :class:`RefinerCascade` averages its own ``coarse_views`` and ``fine_views``).
        starts: refinements averaged per object and update, 1, 5 or 9 (:data:`refiner_rt.checks.STARTS`; module
            docstring): ``1`` (default) refines from the last rotation alone; ``N`` also from ``N - 1`` rotations turned
            :data:`START_DEG` (15) degrees from it, each on its own fixed jitter of the box, and keeps their average
            (``N`` network passes per object and update; ``5`` is the setting measured on video). Sessions only: a
            :class:`RefinerCascade` refines from the last rotation alone.
        lost_deg: the loss-of-track check (module docstring): flag an object lost when a second refinement of its
            refined rotation moves it by more than this many degrees; a finite number in ``(0, 180]``, or ``None``
            (default) for no check (one network pass per object and update; the check costs a second).
            :data:`LOST_DEG` (2.5) is the value chosen on rendered video.
        detector_weight: fuse the detector's poses given to :meth:`update` (module docstring): the weight ``w`` in
            ``(0, 1]`` of the refined detection against the refined track, or ``None`` (default): the detector is
            used only by the loss-of-track check. Fusing costs a second network pass per object with a detection.
        q_order: ``"wxyz"`` (default) or ``"xyzw"`` (ROS, SciPy): the order of every quaternion given to the
            tracker (``q0``, :meth:`add`, :meth:`reset`, detector poses); a ``(3, 3)`` rotation matrix is taken
            anywhere a rotation is. Rotations returned are ``wxyz``.
        D: the camera's lens distortion coefficients (OpenCV's model, ``CameraInfo.d``), as
            :meth:`RefinerSession.refine`: frames and boxes are then the raw camera's. None: a pinhole camera.
        settle_deg: with ``iterations >= 2``, each later pass of a :class:`RefinerSession` refinement is kept only
            where it turns the rotation by more than this many degrees, as :meth:`RefinerSession.refine` (for
            detector poses that may be more than 30 degrees off; :data:`refiner_rt.SETTLE_DEG`). A
            :class:`RefinerCascade` takes its own ``settle_deg``. None (default): every pass is kept.
        reinit: with ``lost_deg``, re-initialise a flagged object the detector has no pose for by a rotation search
            on its box (module docstring): costs nothing on objects not flagged. False (default): a flagged object
            keeps its track and is listed in :attr:`lost`.

    Raises:
        ValueError / TypeError: a bad argument, named, with what was expected and what was given.

    Not thread-safe: one tracker per camera stream, updated from one thread.

    Example:
        >>> tracker = RefinerTracker("003_cracker_box", K, {"003_cracker_box": q_detector})
        >>> for image, box in frames:                      # image: HxWx3 uint8 BGR, box: (x1, y1, x2, y2) pixels
        ...     q = tracker.update(image, {"003_cracker_box": box})["003_cracker_box"]   # (4,) wxyz
    """

    def __init__(self, session, K, q0: Mapping, *, predict: bool | str = False, iterations: int = 1, views: int = 1,
                 starts: int = 1, lost_deg: float | None = None, detector_weight: float | None = None,
                 q_order: str = "wxyz",
                 D=None, settle_deg: float | None = None, motion_window: int | None = None,
                 prediction_weight: float | None = None, max_correction_deg: float | None = None,
                 reinit: bool = False):
        self.K = validate_K(K).copy()
        self.D = validate_D(D)
        as_wxyz(np.zeros((0, 4)), q_order)  # checks q_order
        self.q_order = q_order
        if not isinstance(predict, (bool, str)):
            raise TypeError(f"predict must be False, True, 'object' or 'scene'; got {predict!r}")
        if predict is True:
            predict = "object"
        if predict is not False and predict not in PREDICTIONS:
            raise ValueError(f"predict must be False, True, 'object' or 'scene'; got {predict!r}")
        self.predict = predict or None  # None, "object" or "scene"
        if motion_window is not None and self.predict != "scene":
            raise ValueError(f"motion_window={motion_window!r} is the window of the scene's turn; it needs "
                             "predict='scene'")
        if motion_window is None:
            motion_window = DEFAULT_MOTION_WINDOW
        if isinstance(motion_window, bool) or not isinstance(motion_window, (int, np.integer)):
            raise TypeError(f"motion_window must be an int >= 2 (updates); got {motion_window!r}")
        if motion_window < 2:
            raise ValueError(f"motion_window must be an int >= 2 (updates); got {motion_window!r}")
        self.motion_window = int(motion_window)
        if prediction_weight is None:
            prediction_weight = {"scene": DEFAULT_SCENE_PREDICTION_WEIGHT, None: DEFAULT_HOLD_PREDICTION_WEIGHT}.get(
                self.predict, 0.0)
        if isinstance(prediction_weight, bool) or not isinstance(prediction_weight, (int, float, np.integer,
                                                                                    np.floating)):
            raise TypeError(f"prediction_weight must be a number in [0, 1) (the prediction's share) or None; got "
                            f"{prediction_weight!r}")
        if not 0.0 <= float(prediction_weight) < 1.0:
            raise ValueError(f"prediction_weight must be a number in [0, 1) (the prediction's share); got "
                             f"{prediction_weight!r}")
        self.prediction_weight = float(prediction_weight)
        if max_correction_deg is None and self.predict == "scene":
            max_correction_deg = DEFAULT_SCENE_MAX_CORRECTION_DEG
        if max_correction_deg is None and self.predict is None:
            max_correction_deg = DEFAULT_HOLD_MAX_CORRECTION_DEG
        self.max_correction_deg = _optional_in_range(max_correction_deg, "max_correction_deg", 180.0,
                                                     "a number of degrees", " degrees (180: no limit)")
        self._updates = 0  # update() calls so far: the clock of the scene motion
        self.lost_deg = _check_lost_deg(lost_deg)
        self.detector_weight = _check_detector_weight(detector_weight)
        if self.lost_deg is not None and self.detector_weight is not None:
            raise ValueError("lost_deg and detector_weight are two uses of a detector's poses (only when a track is "
                             "lost, or fused in every frame); choose one")
        if not isinstance(reinit, bool):
            raise TypeError(f"reinit must be True or False; got {reinit!r}")
        if reinit and self.lost_deg is None:
            raise ValueError(f"reinit=True needs lost_deg: the loss-of-track check picks the tracks to re-initialise "
                             f"(e.g. lost_deg={LOST_DEG}, refiner_rt.tracker.LOST_DEG)")
        self.reinit = reinit
        self.lost: list[str] = []  # objects the last update flagged lost (neither re-detected nor re-initialised)
        self.redetections = 0  # objects re-initialised from a detector's pose by update(), in all
        self.reinits = 0  # objects re-initialised by the rotation search on their box (reinit=True), in all
        self.reinitialised: list[str] = []  # the objects the last update re-initialised that way
        self.scores: dict[str, float] = {}  # the last update's RefineResult.score per refined object
        self.iterations = validate_iterations(iterations)
        self.views = validate_views(views)
        self.starts = validate_starts(starts)
        self.settle_deg = validate_settle(settle_deg, self.iterations)
        self._loaded: dict[str, Refiner] = {}  # pretrained name -> session, loaded once
        self._default: Refiner | None = None
        self._per_object: dict[str, Refiner] = {}
        if isinstance(session, Mapping):
            for object_id, s in session.items():
                self._check_id(object_id, "session")
                self._per_object[object_id] = self._session_of(s, f"session[{object_id!r}]")
        else:
            self._default = self._session_of(session, "session")
        if not isinstance(q0, Mapping):
            raise TypeError(
                f"q0 must be a mapping {{object id: (4,) wxyz rotation}}, e.g. {{'003_cracker_box': q}}; "
                f"got {type(q0).__name__}"
            )
        self._tracks: dict[str, _Track] = {}
        for object_id, q in q0.items():
            self._add(object_id, q, None, f"q0[{object_id!r}]")
        missing = sorted(set(self._per_object) - set(self._tracks))
        if missing:
            log.debug("sessions given for objects without an initial rotation (add them later): %s", missing)

    # ------------------------------------------------------------------ objects
    @property
    def object_ids(self) -> list[str]:
        """The tracked object ids, in the order they were added."""
        return list(self._tracks)

    @property
    def rotations(self) -> dict[str, np.ndarray]:
        """``{object id: (4,) float64 wxyz, w >= 0}``: each object's current object-to-camera rotation (a copy)."""
        return {k: np.array(t.q) for k, t in self._tracks.items()}

    def __len__(self) -> int:
        return len(self._tracks)

    def __contains__(self, object_id) -> bool:
        return object_id in self._tracks

    def add(self, object_id: str, q, session=None) -> None:
        """Start tracking an object from a coarse rotation.

        Args:
            object_id: a YCB id, optionally with a ``#suffix`` (module docstring); not already tracked.
            q: ``(4,)`` coarse object-to-camera rotation, ``wxyz``; finite, non-zero (normalised here).
            session: a :class:`RefinerSession` or a pretrained name for this object; default the one given for it
                at construction, else the tracker's common session.

        Raises:
            ValueError / TypeError: an id already tracked or not a string, no session for it, a session whose model
                was not trained for the object, a bad ``q``.
        """
        self._add(object_id, q, session, "q")

    def _add(self, object_id, q, session, q_name: str) -> None:
        self._check_id(object_id, "object_id")
        if object_id in self._tracks:
            raise ValueError(f"object_id {object_id!r} is already tracked; use reset() to give it a new rotation")
        if session is not None:
            sess = self._session_of(session, "session")
        elif object_id in self._per_object:
            sess = self._per_object[object_id]
        elif self._default is not None:
            sess = self._default
        else:
            raise ValueError(
                f"no session for object_id {object_id!r}: the tracker's sessions are per object "
                f"({sorted(self._per_object)}); pass session= (a RefinerSession or a pretrained name)"
            )
        objects = list(sess.contract.objects)
        if object_name(object_id) not in objects:
            raise ValueError(
                f"object_id {object_id!r} is not an object its session's model was trained for (metadata objects: "
                f"{objects}); use that object's model, or name the object '<ycb id>' or '<ycb id>#<instance>'"
            )
        self._tracks[object_id] = _Track(sess, self._check_q(q, q_name))

    def drop(self, object_id: str) -> None:
        """Stop tracking an object.

        Raises:
            ValueError: the object is not tracked (the message lists those that are).
        """
        self._track(object_id)
        del self._tracks[object_id]

    def reset(self, object_id: str, q) -> None:
        """Re-initialise an object from a new coarse rotation (a detector's), forgetting its motion.

        Args:
            object_id: a tracked object id.
            q: ``(4,)`` coarse object-to-camera rotation, ``wxyz``; finite, non-zero (normalised here).

        Raises:
            ValueError: the object is not tracked, or a bad ``q``.
        """
        track = self._track(object_id)
        track.q = self._check_q(q, "q")
        track.refined, track.velocity, track.missed, track.history = False, None, 0, []

    # ------------------------------------------------------------------ tracking
    def update(self, image, boxes: Mapping, detector=None) -> dict[str, np.ndarray]:
        """Refine the tracked objects seen in one frame.

        Args:
            image: ``H x W x 3`` ``uint8`` image, **BGR** channel order.
            boxes: ``{object id: (4,) box (x1, y1, x2, y2)}`` in pixels (continuous coordinates), one per tracked
                object seen in this frame; each non-empty and overlapping the image. Tracked objects without a box
                keep their rotation (with ``predict="scene"``, turned with the camera); an id that is not tracked is
                an error.
            detector: a detector's coarse poses: a callable ``detector(object_id) -> (4,)`` or a mapping
                ``{object id: (4,)}``, object-to-camera ``wxyz`` rotations (e.g. your pose detector's); ``None`` or
                missing for an object it has no pose for. With ``lost_deg``, asked only for the objects this update
                flags lost; each is re-initialised from that pose and refined from it in this update (one more
                network pass), its motion forgotten, and one without a pose stays lost (see :attr:`lost`). With
                ``detector_weight``, asked for every object in ``boxes``; each pose is refined beside the track
                and fused with it. ``None`` (default): no detector in this frame.

        Returns:
            ``{object id: (4,) float64 wxyz, w >= 0}``: the refined object-to-camera rotation of each object in
            ``boxes`` (the others are in :attr:`rotations`).

        After the call, :attr:`lost` lists the objects of this update that were flagged lost and neither re-detected
        nor (``reinit=True``) re-initialised by the search on their box (always empty without ``lost_deg``);
        :attr:`redetections` and :attr:`reinits` have grown by the numbers re-detected and re-initialised.

        Raises:
            ValueError / TypeError: a bad image or box, a box for an object that is not tracked, a ``detector``
                that is neither callable nor a mapping, or a bad rotation from it (named with its object).
        """
        image = validate_image(image, "image")
        if detector is not None and not (callable(detector) or isinstance(detector, Mapping)):
            raise TypeError(f"detector must be a callable detector(object_id) -> (4,) wxyz rotation, a mapping "
                            f"{{object id: (4,) wxyz}} or None; got {type(detector).__name__}")
        if not isinstance(boxes, Mapping):
            raise TypeError(
                f"boxes must be a mapping {{object id: (4,) box (x1, y1, x2, y2) in pixels}}; got {type(boxes).__name__}"
            )
        groups: dict[int, tuple[Refiner, list[str], list[np.ndarray]]] = {}
        for object_id, box in boxes.items():
            track = self._track(object_id, name="boxes")
            row = _check_box(box, image.shape, f"boxes[{object_id!r}]")
            group = groups.get(id(track.session))
            if group is None:
                group = groups[id(track.session)] = (track.session, [], [])
            group[1].append(object_id)
            group[2].append(row)
        seen = set(boxes)
        # Refine (and check) every group first, then ask the detector, and change the tracks only once nothing
        # can fail any more: a bad pose from the detector leaves the tracker as it was.
        results = []
        turn = self._scene_turn() if self.predict == "scene" else None
        for sess, ids, rows in groups.values():
            q_in = [self._prediction(self._tracks[i], turn) for i in ids]
            fused = []  # (index into ids, the detector's pose) to refine and fuse
            if self.detector_weight is not None and detector is not None:
                for i, object_id in enumerate(ids):
                    q_det = self._ask(detector, object_id)
                    if q_det is not None:
                        fused.append((i, q_det))
            # a cascade runs its coarse refiner, then its fine one, on every update: with the fine refiner alone from
            # frame to frame its small errors added up (benchmarks/studies/cascade, "Tracking on the cascade")
            coarse = [True] * (len(ids) + len(fused))
            res = self._refine(sess, image, rows + [rows[i] for i, _ in fused],
                               np.array(q_in + [q for _, q in fused]), coarse)
            both = res.q_refined.tolist()
            score = res.score[: len(ids)].tolist()
            raw = both[: len(ids)]  # the refiner's own results: what it saw move (the scene's turn's source)
            tracked = list(raw)  # the refined tracks (the object velocity's source)
            predicted = [self._predicted(self._tracks[i], turn) for i in ids]
            if self.prediction_weight:  # keep a share of the prediction (not of a coarse start or the last rotation)
                tracked = [_blend(q, p, self.prediction_weight) if made else q
                           for q, p, made in zip(tracked, q_in, predicted)]
            if self.max_correction_deg is not None:  # within reach of the prediction
                tracked = [_within(q, p, self.max_correction_deg) if made else q
                           for q, p, made in zip(tracked, q_in, predicted)]
            refined = list(tracked)
            for (i, _), q_det in zip(fused, both[len(ids):]):
                refined[i] = _blend(tracked[i], q_det, self.detector_weight)
            results.append((sess, ids, rows, refined, tracked, raw, score,
                            self._flag_lost(sess, image, ids, rows, refined)))
        redetected, lost = {}, []  # redetected: object id -> (rotation, score) of a new start
        reinitialised = []
        for sess, ids, rows, refined, tracked, raw, score, flagged in results:
            found, poses, missing = [], [], []
            for i in flagged:
                q = self._ask(detector, ids[i])
                if q is None:
                    missing.append(i)
                else:
                    found.append(i)
                    poses.append(q)
            if found:
                again = self._refine(sess, image, [rows[i] for i in found], np.array(poses), [True] * len(found))
                redetected.update({ids[i]: (q, sc) for i, q, sc in zip(found, again.q_refined.tolist(),
                                                                       again.score.tolist())})
            starts = (self._search(sess, image, [ids[i] for i in missing], [rows[i] for i in missing],
                                   [refined[i] for i in missing]) if self.reinit and missing else [None] * len(missing))
            for i, start in zip(missing, starts):
                if start is None:
                    lost.append(ids[i])
                else:
                    redetected[ids[i]] = start
                    reinitialised.append(ids[i])
        out, scores = {}, {}
        for sess, ids, rows, refined, tracked, raw, score, flagged in results:
            for object_id, q, q_tracked, q_raw, sc in zip(ids, refined, tracked, raw, score):
                track = self._tracks[object_id]
                scores[object_id] = sc
                if object_id in redetected:  # a detector's pose refined, or the search's: a new start, not motion
                    (track.q, scores[object_id]), track.refined, track.velocity, track.missed = (
                        redetected[object_id], True, None, 0)
                    track.history = []
                    out[object_id] = np.array(track.q)
                    continue
                if self.predict == "scene":  # the refiner's result (not the prediction's share, nor a detection's
                    # pull) measures the motion: a turn measured from damped rotations would lag behind itself
                    track.history = [(t, h) for t, h in track.history if self._updates - t < self.motion_window]
                    track.history.append((self._updates, q_raw))
                elif self.predict and track.refined:
                    # camera-frame change over missed + 1 updates: q_new * q_old^-1 (Python floats: see session.py),
                    # from the refined track alone: a fused detection's pull is a correction, not motion
                    step = normalize_rows(multiply_rows([q_tracked], inverse_rows([track.q])))[0]
                    track.velocity = step if track.missed == 0 else _fraction(step, 1.0 / (track.missed + 1))
                track.q, track.refined, track.missed = q, True, 0
                out[object_id] = np.array(q)
        for object_id, track in self._tracks.items():
            if object_id not in seen:
                track.missed += 1
                if turn is not None and track.refined:  # the objects not seen in this frame turn with the camera
                    track.q = normalize_rows(multiply_rows([turn], [track.q]))[0]
        self._updates += 1
        self.lost = lost
        self.scores = scores
        self.redetections += len(redetected) - len(reinitialised)
        self.reinits += len(reinitialised)
        self.reinitialised = reinitialised
        return out

    def update_from_detector(self, image, boxes: Mapping, poses: Mapping, sessions: Mapping | None = None
                             ) -> dict[str, np.ndarray]:
        """One frame of a detector that gives every object's box and, in some frames, its coarse pose: the step
        ``refiner-rt track`` runs per frame, on a folder of frames and on a ROS 2 bag
        (:class:`refiner_rt.ros.RosRefiner`) alike.

        Each pose starts its object when it is not tracked yet (:meth:`add`, with ``sessions[object id]`` when
        given); for a tracked object it is fused with the track when the tracker has ``detector_weight`` (module
        docstring), else it re-initialises the object (:meth:`reset`). Then :meth:`update` with ``boxes``.

        Args:
            image: as :meth:`update`.
            boxes: ``{object id: (4,) box (x1, y1, x2, y2)}`` in pixels; an object not tracked needs a pose here.
            poses: ``{object id: (4,) coarse object-to-camera rotation}`` (``q_order``, or a ``(3, 3)`` matrix) for
                some of the objects in ``boxes``.
            sessions: ``{object id: RefinerSession, RefinerCascade or pretrained name}`` for the objects this frame
                starts (default: as :meth:`add`).

        Returns:
            As :meth:`update`; :attr:`lost` as after it.

        Raises:
            ValueError / TypeError: a pose without a box, a box of an object neither tracked nor given a pose, or
                anything :meth:`add`, :meth:`reset` and :meth:`update` refuse.
        """
        if not isinstance(poses, Mapping):
            raise TypeError(f"poses must be a mapping {{object id: (4,) rotation}}; got {type(poses).__name__}")
        missing = sorted(set(poses) - set(boxes))
        if missing:
            raise ValueError(f"poses names {missing}, which have no box in boxes: a detector's pose comes with its box")
        fused = {}
        for object_id, q in poses.items():
            if object_id not in self._tracks:
                self.add(object_id, q, session=None if sessions is None else sessions.get(object_id))
            elif self.detector_weight is not None:
                fused[object_id] = q
            else:
                self.reset(object_id, q)
        return self.update(image, boxes, detector=fused or None)

    def _refine(self, sess: Refiner, image, rows: list, q_in, coarse: list) -> RefineResult:
        passes = ({"iterations": self.iterations, "views": self.views, "settle_deg": self.settle_deg}
                  if sess.per_call_passes else {})  # a cascade runs the passes it was built with
        if self.starts > 1 and sess.per_call_passes:
            return self._refine_starts(sess, image, rows, q_in, coarse, passes)
        return sess.refine(image, np.array(rows), q_in, K=self.K, D=self.D, coarse=np.array(coarse, dtype=bool),
                           **passes)

    def _refine_starts(self, sess: Refiner, image, rows: list, q_in, coarse: list, passes: dict) -> RefineResult:
        """``starts > 1`` (module docstring): each row refined from ``starts`` rotations, each on its own box jitter,
        in calls of at most :data:`MAX_BATCH` crops; their chordal mean, its correction from ``q_in`` and the
        starts' spread about it (added to each row's views' spread) for the score."""
        m = self.starts
        q_in = rq.canonical(rq.normalize(np.asarray(q_in, dtype=np.float64)))
        turns = np.vstack([rq.identity()[None], rq.from_axis_angle(_START_AXES[: m - 1], START_DEG)])
        n = len(rows)
        q_starts = rq.multiply(np.repeat(q_in, m, axis=0), np.tile(turns, (n, 1)))  # object frame: q * turn
        boxes = self._start_boxes(sess, image, rows)
        flags = np.repeat(np.array(coarse, dtype=bool), m)
        per = max(1, MAX_BATCH // (m * self.views))  # objects per call
        results, last, spread = [], [], []
        for at in range(0, n, per):
            cut = slice(at * m, min(n, at + per) * m)
            r = sess.refine(image, boxes[cut], q_starts[cut], K=self.K, D=self.D, coarse=flags[cut], **passes)
            results.append(r.q_refined)
            last.append(r.q_out)
            spread.append(np.zeros(len(r)) if r.views_spread_deg is None else r.views_spread_deg)
        q_all = np.concatenate(results).reshape(n, m, 4)
        q_mean = rq.mean(q_all, axis=1)
        apart = rq.geodesic_angle(q_all, np.repeat(q_mean[:, None], m, axis=1)).mean(axis=1)
        views_spread = np.concatenate(spread).reshape(n, m).mean(axis=1)
        if self.iterations == 1:  # one pass: the update's own turn from the last rotation (a second opinion on it)
            q_out = rq.canonical(rq.multiply(rq.inverse(q_in), q_mean))
        else:  # several: the last pass's correction, as RefineResult.score is calibrated on; the starts' mean
            q_out = rq.mean(np.concatenate(last).reshape(n, m, 4), axis=1)
        return RefineResult(q_mean, q_out, q_in, apart + views_spread)

    def _start_boxes(self, sess: Refiner, image, rows: list) -> np.ndarray:
        """``(N * starts, 4)``: each box, then ``starts - 1`` fixed jitters of it (``views``' jitters); a jitter the
        runtime would refuse (mostly outside the image, too small) is replaced by the box itself, which update()
        has checked."""
        m = self.starts
        boxes = view_boxes(np.array(rows, dtype=np.float64), m, sess.contract.crop_context)
        for k in range(len(boxes)):
            if k % m:
                try:
                    validate_boxes(boxes[k][None], image.shape)
                except ValueError:
                    boxes[k] = rows[k // m]
        return boxes

    def _flag_lost(self, sess: Refiner, image, ids: list, rows: list, refined: list) -> list[int]:
        """Indices into ``ids`` of the objects the loss-of-track check flags (module docstring): refined from a
        tracked (not a coarse) rotation, and moved by more than ``lost_deg`` by one more refinement."""
        if self.lost_deg is None:
            return []
        checked = [i for i, object_id in enumerate(ids) if self._tracks[object_id].refined]
        if not checked:
            return []
        # one more pass; a cascade's coarse refiner gives the verdict (coarse=True): it sees drift the fine one follows
        passes = {"views": self.views} if sess.per_call_passes else {}
        again = sess.refine(image, np.array([rows[i] for i in checked]), np.array([refined[i] for i in checked]),
                            K=self.K, D=self.D, coarse=np.ones(len(checked), dtype=bool), **passes).q_refined
        moved = rq.geodesic_angle(np.array([refined[i] for i in checked]), again)
        return [i for i, m in zip(checked, moved) if m > self.lost_deg]

    def _search(self, sess: Refiner, image, ids: list, rows: list, q_track: list) -> list:
        """Per flagged object (``reinit``, module docstring): ``(rotation, score)`` of the start the search on its box
        found, or None where the track is kept: its own rotation refined :data:`REINIT_PASSES` times turned by at
        most :data:`REINIT_GATE_DEG`, or the search's winner would be flagged too."""
        boxes, q_track = np.array(rows, dtype=np.float64), np.array(q_track, dtype=np.float64)
        own = self._passes(sess, image, boxes, q_track, REINIT_PASSES)
        go = np.flatnonzero(rq.geodesic_angle(own, q_track) > REINIT_GATE_DEG)
        out = [None] * len(ids)
        if len(go) == 0:
            return out
        # in chunks that keep every call within the batch limit: REINIT_HYPOTHESES + 1 starts per object, each seen
        # by as many views as any of the calls takes (the check's, or a cascade's own)
        views = max(self.views or 1, getattr(sess, "coarse_views", 1) or 1, getattr(sess, "fine_views", 1) or 1)
        chunk = max(1, MAX_BATCH // ((REINIT_HYPOTHESES + 1) * views))
        for at in range(0, len(go), chunk):
            part = go[at:at + chunk]
            for i, found in zip(part, self._search_chunk(sess, image, [ids[i] for i in part], boxes[part], own[part])):
                out[i] = found
        return out

    def _search_chunk(self, sess: Refiner, image, ids: list, boxes: np.ndarray, own: np.ndarray) -> list:
        """:meth:`_search` on boxes whose own rotation turned too far: per box ``(rotation, score)`` or None."""
        h, m = REINIT_HYPOTHESES, REINIT_HYPOTHESES + 1  # per object: the hypotheses, then the track's own
        n = len(boxes)
        pinhole = boxes if self.D is None else undistort_boxes(boxes, self.K, self.D)
        searched = np.zeros((n * h, 4))
        if h:  # (0: the track's own rotation alone, refined further)
            starts = rq.multiply(np.repeat(ray_quaternions(self.K, pinhole), h, axis=0),
                                 np.tile(super_fibonacci(h), (n, 1)))
            searched = self._passes(sess, image, np.repeat(boxes, h, axis=0), starts, REINIT_PASSES)
        q = np.concatenate([searched.reshape(n, h, 4), own[:, None]], axis=1).reshape(-1, 4)
        rep = np.repeat(boxes, m, axis=0)
        back = sess.refine(image, rep, rq.multiply(q, np.tile(return_turns(m), (n, 1))), K=self.K, D=self.D,
                           coarse=np.ones(len(rep), dtype=bool)).q_refined
        residual = rq.geodesic_angle(back, q).reshape(n, m)
        extents = load_extents()
        winners = []
        for k in range(n):
            ranked = ranking_residual(residual[k], q[k * m:(k + 1) * m], extents.get(object_name(ids[k])),
                                      np.repeat(pinhole[k][None], m, axis=0), self.K, image.shape[:2])
            ranked[-1] -= REINIT_MARGIN_DEG
            winners.append(q[k * m + int(np.argmin(ranked))])
        winners = rq.canonical(np.array(winners))
        # the loss check's own pass (its views too), so that a winner taken is one the next check passes
        views = {"views": self.views} if sess.per_call_passes else {}
        check = sess.refine(image, boxes, winners, K=self.K, D=self.D, coarse=np.ones(n, dtype=bool), **views)
        moved = rq.geodesic_angle(check.q_refined, winners)
        return [(winners[k].tolist(), float(check.score[k])) if moved[k] <= self.lost_deg else None
                for k in range(n)]

    def _passes(self, sess: Refiner, image, boxes: np.ndarray, q: np.ndarray, passes: int) -> np.ndarray:
        """``q`` refined ``passes`` times (a session in one call, a cascade one call per pass)."""
        coarse = np.ones(len(boxes), dtype=bool)
        if sess.per_call_passes:
            return sess.refine(image, boxes, q, K=self.K, D=self.D, coarse=coarse, iterations=passes).q_refined
        for _ in range(passes):
            q = sess.refine(image, boxes, q, K=self.K, D=self.D, coarse=coarse).q_refined
        return q

    def _ask(self, detector, object_id: str) -> list | None:
        """The detector's coarse pose for an object (checked, unit), or None when it has none."""
        if detector is None:
            return None
        q = detector(object_id) if callable(detector) else detector.get(object_id)
        return None if q is None else self._check_q(q, f"detector pose for {object_id!r}")

    # ------------------------------------------------------------------ internals
    def _scene_turn(self) -> list | None:
        """The rotation per update that every still object shares in the camera frame (module docstring,
        ``predict="scene"``): the mean over the tracks of each one's change per update across the refiner's results
        of the last ``motion_window`` updates (those measured over at least ``motion_window // 2`` updates); with
        three or more, those further from the medoid (the rate closest to all the others) than
        :data:`TURN_OUTLIER_DEG` and twice the median distance are left out first. None before any track is
        measured."""
        rates = []
        for track in self._tracks.values():
            h = [(t, q) for t, q in track.history if self._updates - t <= self.motion_window]
            if len(h) < 2 or h[-1][0] - h[0][0] < max(1, self.motion_window // 2):
                continue
            change = normalize_rows(multiply_rows([h[-1][1]], inverse_rows([h[0][1]])))[0]
            rates.append(_fraction(change, 1.0 / (h[-1][0] - h[0][0])))
        if not rates:
            return None
        rates = np.array(rates)
        if len(rates) >= 3:  # leave out a track whose change is far from the others' (one drifting off, or moved)
            apart = np.degrees(2.0 * np.arccos(np.clip(np.abs(rates @ rates.T), 0.0, 1.0)))
            off = apart[np.argmin(apart.sum(axis=1))]  # from the medoid, which an outlier does not pull
            rates = rates[off <= max(TURN_OUTLIER_DEG, 2.0 * float(np.median(off)))]
        return rq.mean(rates).tolist()

    def _predicted(self, track: _Track, turn: list | None) -> bool:
        """Whether this update's coarse rotation for ``track`` is a prediction (motion measured, a refined track)."""
        if not track.refined:
            return False
        if self.predict is None:  # the object is taken to hold still: its last rotation is the prediction
            return True
        return turn is not None if self.predict == "scene" else track.velocity is not None

    def _prediction(self, track: _Track, turn: list | None = None) -> list:
        """The coarse rotation for this update: the last one, turned on by the velocity (``predict="object"``) or
        by the scene's turn (``predict="scene"``) when predicting."""
        if self.predict == "scene":
            if turn is None or not track.refined:
                return track.q
            return normalize_rows(multiply_rows([turn], [track.q]))[0]
        if not self.predict or track.velocity is None:
            return track.q
        step = track.velocity if track.missed == 0 else _fraction(track.velocity, track.missed + 1.0)
        return normalize_rows(multiply_rows([step], [track.q]))[0]

    def _session_of(self, value, name: str):
        if isinstance(value, Refiner):
            return value
        if isinstance(value, str):
            if value not in self._loaded:
                log.debug("loading the pretrained refiner %r", value)
                self._loaded[value] = load(value, int8=True, threads=1)
            return self._loaded[value]
        raise TypeError(f"{name} must be a RefinerSession, a RefinerCascade or a pretrained model name such as "
                        "'003_cracker_box'; "
                        f"got {type(value).__name__}")

    def _track(self, object_id, name: str = "object_id") -> _Track:
        try:
            return self._tracks[object_id]
        except (KeyError, TypeError):
            raise ValueError(f"{name} names {object_id!r}, which is not tracked (tracked: {list(self._tracks)}); "
                             f"add it with add(object_id, q)") from None

    @staticmethod
    def _check_id(object_id, name: str) -> None:
        if not isinstance(object_id, str) or not object_id:
            raise TypeError(f"{name}: object ids must be non-empty strings such as '003_cracker_box'; "
                            f"got {object_id!r}")

    def _check_q(self, q, name: str) -> list:
        """One rotation: a ``(3, 3)`` matrix or a ``(4,)`` quaternion in ``q_order``, as a unit ``wxyz`` list."""
        try:
            shape = np.shape(q)
        except (ValueError, TypeError):
            shape = None
        if shape == (3, 3):
            return rq.normalize(as_wxyz(np.asarray(q, dtype=np.float64)[None], "wxyz", name)[0]).tolist()
        arr = rq.as_quaternion(q, name)
        if arr.shape != (4,):
            raise ValueError(f"{name} must be one rotation: a (4,) quaternion ({self.q_order}) or a (3, 3) matrix; "
                             f"got shape {arr.shape}")
        if self.q_order == "xyzw":
            arr = rq.from_xyzw(arr)
        return rq.normalize(arr).tolist()

    def __repr__(self) -> str:
        return (f"RefinerTracker(objects={self.object_ids}, predict={self.predict or False!r}, "
                f"motion_window={self.motion_window}, prediction_weight={self.prediction_weight}, "
                f"max_correction_deg={self.max_correction_deg}, "
                f"iterations={self.iterations}, "
                f"lost_deg={self.lost_deg}, reinit={self.reinit}, detector_weight={self.detector_weight}, "
                f"settle_deg={self.settle_deg})")


def _optional_in_range(value, name: str, high: float, number: str, in_range: str) -> float | None:
    """``value`` as a float in ``(0, high]``, or None; the errors name ``name`` and what it means."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be {number} in (0, {high:g}] or None; got {value!r}")
    if not (0.0 < float(value) <= high):
        raise ValueError(f"{name} must be in (0, {high:g}]{in_range}; got {value!r}")
    return float(value)


def _check_lost_deg(value) -> float | None:
    return _optional_in_range(value, "lost_deg", 180.0, "a number of degrees", " degrees (or None for no check)")


def _check_detector_weight(value) -> float | None:
    return _optional_in_range(value, "detector_weight", 1.0, "a number",
                           " (the refined detection's share; None: no fusion)")


def _blend(q_track: list, q_det: list, w: float) -> list:
    """The rotation ``w`` of the way from ``q_track`` to ``q_det`` along the shortest arc, ``w >= 0`` canonical:
    ``(q_det * q_track^-1) ** w * q_track`` (unit ``[w, x, y, z]`` lists)."""
    step = normalize_rows(multiply_rows([q_det], inverse_rows([q_track])))[0]
    return normalize_rows(multiply_rows([_fraction(step, w)], [q_track]))[0]


def _within(q: list, p: list, max_deg: float) -> list:
    """``q``, or the rotation ``max_deg`` degrees from ``p`` toward it along the shortest arc where ``q`` is further
    (unit ``[w, x, y, z]`` lists, ``w >= 0``)."""
    step = normalize_rows(multiply_rows([q], inverse_rows([p])))[0]
    angle = math.degrees(2.0 * math.atan2(math.sqrt(step[1] ** 2 + step[2] ** 2 + step[3] ** 2), abs(step[0])))
    if angle <= max_deg:
        return q
    return normalize_rows(multiply_rows([_fraction(step, max_deg / angle)], [p]))[0]


def _fraction(q: list, power: float) -> list:
    """``q ** power`` for a unit quaternion ``[w, x, y, z]``: the same axis, ``power`` times the angle (of the
    shortest arc), ``w >= 0``. Python floats: called per track and update, where NumPy's per-call cost dominates."""
    w, x, y, z = q
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-15:
        return [1.0, 0.0, 0.0, 0.0]
    half = math.atan2(s, w) * power
    k = math.sin(half) / s
    out = [math.cos(half), x * k, y * k, z * k]
    return out if out[0] >= 0 else [-v for v in out]


def _check_box(box, image_shape, name: str) -> list:
    """One box ``(x1, y1, x2, y2)`` in pixels as a list of floats, checked by the session's rules (its fast path for a
    well-formed box, else :func:`refiner_rt.checks.validate_boxes`, which raises the detailed error)."""
    try:
        arr = np.asarray(box, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be one numeric box (x1, y1, x2, y2) in pixels; got {box!r}") from None
    if arr.shape != (4,):
        raise ValueError(f"{name} must be one box (x1, y1, x2, y2) in pixels, shape (4,); got shape {arr.shape}")
    fast = boxes_rows(arr[None], image_shape)
    if fast is not None:
        return fast[1][0]
    return validate_boxes(arr, image_shape, name)[0].tolist()
