"""ROS 2 messages in, refined poses out, without a ROS install: the one path that bags and live nodes share.

:class:`RosRefiner` takes one frame's messages, ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage``,
``sensor_msgs/CameraInfo`` and ``vision_msgs/Detection2DArray`` (ROS 2 Humble's vision_msgs 4: each detection's box,
its ``results[0].hypothesis.class_id`` naming the object and ``results[0].pose.pose`` its coarse pose), and returns
the refined pose of every detected object it has a refiner for. It reads messages by their field names only, so
the same call serves the messages of ``rclpy`` (a live node: ``examples/ros2_node.py``) and those ``rosbags``
deserialises from a bag (``refiner-rt track --bag``, :mod:`refiner_rt.rosbag`).

Conventions: ROS quaternions are ``xyzw`` (``geometry_msgs/Quaternion``); :class:`RefinedPose` gives both orders.
A pose is object to camera in the image's ``header.frame_id`` (the camera's optical frame). The refiners correct the
rotation only: the position is the detection's, passed through (``None`` when the detection has none).
Camera: ``k`` and ``d`` of ``CameraInfo`` (``plumb_bob`` or ``rational_polynomial``; an empty model is a pinhole
camera); ``rectified=True`` for a rectified image topic (``image_rect``): ``p``'s left 3x3 and no distortion.

No pose (the one rule, :func:`coarse_rotation`): a box-only detection carries no usable coarse rotation. Its
``results[0].pose.pose.orientation`` is then all zeros, or ``(0, 0, 0, 1)`` (or ``(0, 0, 0, -1)``): the message's
default, what an rclpy node publishes when it never sets the field; non-finite values count as none too. Both are "no pose" unless
``identity_is_pose=True`` (``--identity-is-pose``), for a detector that really outputs the identity rotation. Any
other orientation must be a unit quaternion (norm within :data:`QUATERNION_NORM_TOLERANCE` of 1): one further off
is refused with an error naming the detection, never normalised in silence.

Instances (:func:`detections_from_msg`): each detection gets an instance id, the object id it is tracked and
published under: ``<object id>#<Detection2D.id>`` when the detector sets ``id``; without one, an object detected
once in the frame keeps its object id, and several detections of one object are numbered by their boxes' left edge,
left to right: ``<object id>#1``, ``<object id>#2``... (set ``Detection2D.id`` for identities that hold when
objects cross). Two detections with the same instance id in one frame: the later ones are skipped.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, replace

import cv2
import numpy as np

from refiner_rt import quaternion as rq

__all__ = ["RosRefiner", "RefinedPose", "Detection", "image_from_msg", "camera_from_info", "detections_from_msg",
           "coarse_rotation", "stamp_ns", "VISION_MSGS", "DISTORTION_MODELS", "QUATERNION_NORM_TOLERANCE"]

log = logging.getLogger(__name__)

# A detection's orientation must have a norm within this of 1 (a float32 detector's round-off is about 1e-7);
# one further off is an error, not renormalised (module docstring, "No pose").
QUATERNION_NORM_TOLERANCE = 1e-3
INSTANCE_SEPARATOR = "#"  # as refiner_rt.tracker.INSTANCE_SEPARATOR (not imported here: the tracker loads lazily)

# CameraInfo distortion models this runtime undistorts through (OpenCV's model); "" is a pinhole camera.
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "")

# vision_msgs (ROS 2 Humble, version 4) definitions, for reading and writing bags without a ROS install
# (rosbags' typestores carry the core packages but not vision_msgs).
VISION_MSGS = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": ("vision_msgs/ObjectHypothesis hypothesis\n"
                                                 "geometry_msgs/PoseWithCovariance pose\n"),
    "vision_msgs/msg/Detection2D": ("std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
                                    "vision_msgs/BoundingBox2D bbox\nstring id\n"),
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nvision_msgs/Detection2D[] detections\n",
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": ("std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
                                    "vision_msgs/BoundingBox3D bbox\nstring id\n"),
    "vision_msgs/msg/Detection3DArray": "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n",
}

_CONVERSIONS = {"bgr8": None, "rgb8": cv2.COLOR_RGB2BGR, "bgra8": cv2.COLOR_BGRA2BGR, "rgba8": cv2.COLOR_RGBA2BGR,
                "mono8": cv2.COLOR_GRAY2BGR, "8UC3": None, "8UC1": cv2.COLOR_GRAY2BGR}
_CHANNELS = {"bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4, "mono8": 1, "8UC3": 3, "8UC1": 1}


def stamp_ns(header) -> int:
    """A ``std_msgs/Header``'s stamp in nanoseconds (``builtin_interfaces/Time``: ``sec``, ``nanosec``)."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def image_from_msg(msg) -> np.ndarray:
    """A ``sensor_msgs/Image`` (8-bit: ``bgr8``, ``rgb8``, ``bgra8``, ``rgba8``, ``mono8``) or
    ``sensor_msgs/CompressedImage`` (JPEG, PNG) as an ``H x W x 3`` ``uint8`` BGR array.

    Raises:
        ValueError: an encoding this runtime does not read, a data size that does not match the header, or
            compressed bytes OpenCV cannot decode.
    """
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if hasattr(msg, "format"):  # CompressedImage
        image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
        if image is None:
            raise ValueError(f"a CompressedImage of format {msg.format!r} that OpenCV cannot decode ({data.size} "
                             "bytes); expected JPEG or PNG")
        return image
    encoding = str(msg.encoding)
    if encoding not in _CONVERSIONS:
        raise ValueError(f"an Image of encoding {encoding!r}: expected one of {', '.join(_CONVERSIONS)} (8-bit "
                         "colour or grey)")
    h, w, step, c = int(msg.height), int(msg.width), int(msg.step), _CHANNELS[encoding]
    if h <= 0 or w <= 0 or step < w * c or data.size < h * step:
        raise ValueError(f"an Image of {w}x{h} {encoding} with step {step} holds {data.size} bytes; expected "
                         f"height x step = {h * step} with step >= {w * c}")
    image = data[: h * step].reshape(h, step)[:, : w * c].reshape(h, w, c)
    code = _CONVERSIONS[encoding]
    return np.ascontiguousarray(image) if code is None else cv2.cvtColor(image, code)


def camera_from_info(msg, rectified: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """``(K, D)`` of a ``sensor_msgs/CameraInfo``: ``k`` as ``(3, 3)``, ``d`` when the distortion model is
    ``plumb_bob`` or ``rational_polynomial`` (``None`` when it is empty or all zeros). ``rectified``: the
    projection ``p``'s left 3x3 and no distortion (for ``image_rect`` topics).

    Raises:
        ValueError: another distortion model (e.g. ``equidistant``: a fisheye lens; rectify it first) or a ``k``
            that is not nine numbers.
    """
    if rectified:
        P = np.asarray(msg.p, dtype=np.float64)
        if P.size != 12:
            raise ValueError(f"CameraInfo.p must hold 12 numbers; got {P.size}")
        return P.reshape(3, 4)[:, :3].copy(), None
    K = np.asarray(msg.k, dtype=np.float64)
    if K.size != 9:
        raise ValueError(f"CameraInfo.k must hold 9 numbers; got {K.size}")
    model = str(msg.distortion_model)
    D = np.asarray(msg.d, dtype=np.float64)
    if model not in DISTORTION_MODELS:
        raise ValueError(f"CameraInfo.distortion_model {model!r} is not one this runtime undistorts through "
                         f"(plumb_bob, rational_polynomial); rectify the images first (image_proc) and pass "
                         "rectified=True (--rectified)")
    return K.reshape(3, 3), (D if D.size and D.any() else None)


@dataclass(frozen=True)
class Detection:
    """One object of a ``vision_msgs/Detection2DArray``: ``object_id`` (its ``class_id``, mapped), ``box``
    ``(x1, y1, x2, y2)`` pixels, the coarse rotation ``q_wxyz`` (``None``: no pose, :func:`coarse_rotation`),
    ``position`` (metres, or ``None`` when all zeros or non-finite), ``score``, the tracking ``id``
    (``Detection2D.id``, may be empty) and ``instance``, the id it is refined and published under (module
    docstring, "Instances"); ``estimate_score``: where ``q_wxyz`` came from :class:`refiner_rt.PoseEstimator`
    (``RosRefiner(estimate_missing=True)``), that estimate's score, else None."""

    object_id: str
    box: np.ndarray
    q_wxyz: np.ndarray | None
    position: np.ndarray | None
    score: float
    id: str
    instance: str = ""
    estimate_score: float | None = None


def coarse_rotation(xyzw, identity_is_pose: bool = False, what: str = "orientation") -> np.ndarray | None:
    """A detection's coarse rotation by the no-pose rule (module docstring): ``(4,)`` wxyz unit, or ``None``.

    Args:
        xyzw: ``geometry_msgs/Quaternion`` components ``(x, y, z, w)``.
        identity_is_pose: take ``(0, 0, 0, 1)`` as the identity rotation (default: the message's default, no pose).
        what: names the detection in the error.

    Raises:
        ValueError: a finite, non-zero quaternion whose norm is further than :data:`QUATERNION_NORM_TOLERANCE`
            from 1.
    """
    q = np.asarray(xyzw, dtype=np.float64)
    if not np.isfinite(q).all() or not q.any():
        return None
    if not identity_is_pose and q[0] == 0.0 and q[1] == 0.0 and q[2] == 0.0 and abs(q[3]) == 1.0:
        return None
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise ValueError(f"{what} (x, y, z, w) = {q.tolist()} has norm {norm:.6g}: expected a unit quaternion (within "
                         f"{QUATERNION_NORM_TOLERANCE:g}), or all zeros or (0, 0, 0, 1) for a box-only detection")
    return rq.from_xyzw(q / norm)


def detections_from_msg(msg, class_map: Mapping | None = None, identity_is_pose: bool = False) -> list[Detection]:
    """The detections of a ``vision_msgs/Detection2DArray`` (ROS 2 Humble field names; the first hypothesis of
    each), with their instance ids (module docstring). ``class_map``: detector class id -> object id (default: the
    class id is the object id). ``identity_is_pose``: as :func:`coarse_rotation`.

    Raises:
        ValueError: an orientation that is not a unit quaternion (named by its index, class and id).
    """
    out = []
    for i, d in enumerate(msg.detections):
        if not len(d.results):
            continue
        hyp = d.results[0]
        class_id = str(hyp.hypothesis.class_id)
        object_id = str(class_map.get(class_id, class_id)) if class_map else class_id
        cx, cy = float(d.bbox.center.position.x), float(d.bbox.center.position.y)
        hw, hh = 0.5 * float(d.bbox.size_x), 0.5 * float(d.bbox.size_y)
        pose = hyp.pose.pose
        o = pose.orientation
        what = f"detections[{i}] (class_id {class_id!r}, id {str(d.id)!r}): results[0].pose.pose.orientation"
        q = coarse_rotation([o.x, o.y, o.z, o.w], identity_is_pose, what)
        p = np.array([pose.position.x, pose.position.y, pose.position.z], dtype=np.float64)
        out.append(Detection(object_id=object_id, box=np.array([cx - hw, cy - hh, cx + hw, cy + hh]), q_wxyz=q,
                             position=p if np.isfinite(p).all() and p.any() else None,
                             score=float(hyp.hypothesis.score), id=str(d.id)))
    return _with_instances(out)


def _with_instances(dets: list[Detection]) -> list[Detection]:
    """``dets`` with their ``instance`` ids (module docstring, "Instances"): ``<object>#<id>`` where ``id`` is set;
    without it, ``<object>`` for an object detected once, else ``<object>#1``, ``#2``... by the box's left edge."""
    taken = {f"{d.object_id}{INSTANCE_SEPARATOR}{d.id}" for d in dets if d.id}
    unnamed: dict[str, list[int]] = {}
    for i, d in enumerate(dets):
        if not d.id:
            unnamed.setdefault(d.object_id, []).append(i)
    names = {i: f"{d.object_id}{INSTANCE_SEPARATOR}{d.id}" for i, d in enumerate(dets) if d.id}
    for object_id, idx in unnamed.items():
        if len(idx) == 1 and object_id not in taken:
            names[idx[0]] = object_id
            continue
        k = 0
        for i in sorted(idx, key=lambda i: (dets[i].box[0], dets[i].box[1])):
            k += 1
            while f"{object_id}{INSTANCE_SEPARATOR}{k}" in taken:
                k += 1
            names[i] = f"{object_id}{INSTANCE_SEPARATOR}{k}"
    return [replace(d, instance=names[i]) for i, d in enumerate(dets)]


@dataclass(frozen=True)
class RefinedPose:
    """One refined object of a frame: ``object_id`` (the detection's instance id: the object id, with
    ``#<Detection2D.id>`` or ``#<n>`` for one of several instances, module docstring), ``q_wxyz`` (object to camera)
    and ``q_xyzw`` (the same, ROS order), ``position`` (the detection's, or ``None``), ``box`` and ``score`` (the
    detection's), ``refine_score``: the refinement's confidence in ``(0, 1]``, :attr:`refiner_rt.RefineResult.score`
    (in ``"track"`` mode the tracker's, :attr:`refiner_rt.RefinerTracker.scores`), ``lost``: the loss-of-track check
    flagged it in this frame (``lost_deg``; always False without it and in ``"refine"`` mode), ``reinitialised``: the
    tracker's rotation search on its box gave it a new start in this frame (``reinit``), and ``q_input_wxyz``:
    the detection's coarse rotation in this frame, or None."""

    object_id: str
    q_wxyz: np.ndarray
    position: np.ndarray | None
    box: np.ndarray
    score: float
    lost: bool = False
    refine_score: float | None = None
    reinitialised: bool = False
    q_input_wxyz: np.ndarray | None = None

    @property
    def q_xyzw(self) -> np.ndarray:
        return rq.to_xyzw(self.q_wxyz)


class RosRefiner:
    """Refine (or track) the detected objects of each frame's ROS 2 messages (module docstring).

    Args:
        mode: ``"refine"``: every detection with a coarse pose is refined from it (the paper's per-frame use);
            ``"track"``: a :class:`refiner_rt.RefinerTracker` per camera: a detection's pose starts an object, later
            frames refine from the previous result, so the detector's pose is needed once. A later pose of a
            tracked object re-initialises it, or with ``detector_weight`` is fused with the track
            (:meth:`refiner_rt.RefinerTracker.update_from_detector`, as ``refiner-rt track`` does for frames).
            Instances are told apart by their instance ids (module docstring).
        models: ``{object id: RefinerSession or RefinerCascade}`` (default: each detected object's shipped model,
            loaded on first sight; objects without one are skipped and counted in :attr:`skipped`).
        cascade: with the shipped models, use each object's :class:`refiner_rt.RefinerCascade` (coarse and fine)
            where a fine refiner ships.
        rectified, class_map: as :func:`camera_from_info` and :func:`detections_from_msg`.
        identity_is_pose: take an orientation of ``(0, 0, 0, 1)`` as the identity rotation, for a detector that
            really outputs it; by default it is the message's default and means no pose (:func:`coarse_rotation`).
        int8, threads: for the shipped models.
        settle_deg: for detector poses that may be more than 30 degrees off: each refinement by a
            :class:`refiner_rt.RefinerSession` runs two passes, the second kept where it turns the result by more
            than this (:meth:`refiner_rt.RefinerSession.refine`), and the shipped cascades take it too
            (:data:`refiner_rt.SETTLE_DEG` is the measured value). None (default): one pass.
        views: box-jittered crops each :class:`refiner_rt.RefinerSession` averages per object and frame
            (:meth:`refiner_rt.RefinerSession.refine`; ``1`` to ``MAX_VIEWS``, default 1): four took the shipped
            refiners from 5.67 to 4.93 degrees on the real dev frames, for four network passes. A cascade averages
            its own views: not with ``cascade=True``.
        estimate_missing: a box-only detection (no usable pose, :func:`coarse_rotation`) gets a 6D pose from
            :class:`refiner_rt.PoseEstimator` (the object's shipped refiners, rotation from the crop alone and
            translation from the box): in ``"refine"`` mode that pose is the output (its ``refine_score`` the
            estimator's, its ``position`` the estimate where the detection has none); in ``"track"`` mode it starts
            the object's track. Needs a pinhole camera (an empty distortion model, or ``rectified=True``). Default
            False: box-only detections are skipped (refine) or wait for a pose (track), and counted in :attr:`skipped`.
        tracker_kwargs: passed to :class:`refiner_rt.RefinerTracker` (``predict``, ``lost_deg``,
            ``detector_weight``...), checked here. With ``lost_deg`` each :class:`RefinedPose` says whether the
            check flagged it (``lost``).

    Not thread-safe in ``"track"`` mode (one tracker per camera stream).
    """

    def __init__(self, mode: str = "track", models: Mapping | None = None, *, cascade: bool = False,
                 rectified: bool = False, class_map: Mapping | None = None, identity_is_pose: bool = False,
                 int8: bool = True, threads: int = 1, settle_deg: float | None = None, views: int = 1,
                 estimate_missing: bool = False, **tracker_kwargs):
        if mode not in ("refine", "track"):
            raise ValueError(f"mode must be 'refine' or 'track'; got {mode!r}")
        from refiner_rt.checks import validate_settle, validate_views

        views = validate_views(views)
        if views != 1 and cascade:
            raise ValueError(f"views={views} is for single refiners; a cascade averages its own coarse_views and "
                             "fine_views (four each): give one of views and cascade")
        if tracker_kwargs and mode != "track":
            raise ValueError(f"{sorted(tracker_kwargs)} apply to mode='track' only")
        if "starts" in tracker_kwargs:
            from refiner_rt.checks import validate_starts

            validate_starts(tracker_kwargs["starts"])
            if tracker_kwargs["starts"] != 1 and cascade:
                raise ValueError(f"starts={tracker_kwargs['starts']!r} is for single refiners; a cascade refines each "
                                 "frame from the last rotation with its own views: give one of starts and cascade")
        self.mode, self.cascade, self.rectified = mode, bool(cascade), bool(rectified)
        self.class_map = dict(class_map or {})
        self.identity_is_pose = bool(identity_is_pose)
        self.int8, self.threads, self.tracker_kwargs = int8, threads, tracker_kwargs
        self.settle_deg = validate_settle(settle_deg)
        self.views = views
        if self.settle_deg is not None and mode == "track":
            self.tracker_kwargs = {"iterations": 2, **tracker_kwargs, "settle_deg": self.settle_deg}
        if mode == "track" and views != 1:
            self.tracker_kwargs = {**self.tracker_kwargs, "views": views}
        if mode == "track":  # the tracker's own checks, now rather than at the first frame
            from refiner_rt.tracker import RefinerTracker

            RefinerTracker({}, np.eye(3), {}, **self.tracker_kwargs)
        self.estimate_missing = bool(estimate_missing)
        self._estimators: dict = {}  # object id -> PoseEstimator or None (no shipped model), built on first need
        self._models = dict(models or {})
        self._given = models is not None
        self._tracker = None
        self.skipped: dict[str, int] = {}  # class id -> detections skipped (no refiner for it, or no pose to start)

    @property
    def checks_loss(self) -> bool:
        """Whether the tracker runs the loss-of-track check (``mode="track"`` with ``lost_deg``)."""
        return self.mode == "track" and self.tracker_kwargs.get("lost_deg") is not None

    def _model(self, object_id: str):
        if object_id in self._models:
            return self._models[object_id]
        if self._given:
            return None
        from refiner_rt.pretrained import pretrained_models
        from refiner_rt.refiner import load

        if object_id not in {m.object_id for m in pretrained_models()}:
            model = None
        else:
            model = load(object_id, cascade=self.cascade, int8=self.int8, threads=self.threads,
                         settle_deg=self.settle_deg if self.cascade else None)
        self._models[object_id] = model
        return model

    def _estimator(self, object_id: str):
        if object_id not in self._estimators:
            from refiner_rt.estimate import PoseEstimator
            from refiner_rt.pretrained import pretrained_models

            shipped = object_id in {m.object_id for m in pretrained_models()}
            self._estimators[object_id] = (PoseEstimator.pretrained(object_id, int8=self.int8, threads=self.threads)
                                           if shipped else None)
        return self._estimators[object_id]

    def _estimate(self, image, K, D, dets: list[Detection], needed) -> tuple[list[Detection], set]:
        """``dets`` with a pose estimated for each box-only detection that ``needed(d)`` says needs one
        (``estimate_missing``), and the instance ids whose pose was estimated."""
        todo: dict[str, list[int]] = {}
        for i, d in enumerate(dets):
            if d.q_wxyz is None and needed(d) and self._estimator(d.object_id) is not None:
                todo.setdefault(d.object_id, []).append(i)
        if not todo:
            return dets, set()
        if D is not None and np.any(D):
            raise ValueError("estimate_missing needs a pinhole camera: this CameraInfo has lens distortion (use a "
                             "rectified image topic with rectified=True, --rectified)")
        dets = list(dets)
        estimated = set()
        for object_id, idx in todo.items():
            est = self._estimator(object_id).estimate(image, np.array([dets[i].box for i in idx]), K=K)
            for i, q, t, score in zip(idx, est.q, est.t, est.score):
                d = dets[i]
                dets[i] = replace(d, q_wxyz=q, position=d.position if d.position is not None else t,
                                  estimate_score=float(score))
                estimated.add(d.instance)
        return dets, estimated

    def _skip(self, object_id: str) -> None:
        self.skipped[object_id] = self.skipped.get(object_id, 0) + 1

    def process(self, image_msg, info_msg, detections_msg) -> list[RefinedPose]:
        """The refined poses of one frame (its image, its camera's ``CameraInfo`` and its detections).

        Raises:
            ValueError: an image, camera or detection this runtime cannot use (named), e.g. an orientation that is
                not a unit quaternion (:func:`coarse_rotation`).
        """
        image = image_from_msg(image_msg)
        K, D = camera_from_info(info_msg, self.rectified)
        dets, names = [], set()
        for d in detections_from_msg(detections_msg, self.class_map, self.identity_is_pose):
            if self._model(d.object_id) is None:
                self._skip(d.object_id)  # no refiner for this class
            elif d.instance in names:  # a second detection under one instance id: not told apart
                self._skip(d.object_id)
            else:
                names.add(d.instance)
                dets.append(d)
        if self.mode == "refine":
            return self._refine(image, K, D, dets)
        return self._track(image, K, D, dets)

    def _refine(self, image, K, D, dets: list[Detection]) -> list[RefinedPose]:
        out = []
        by_object: dict[str, list[Detection]] = {}
        estimated: set = set()
        if self.estimate_missing:
            dets, estimated = self._estimate(image, K, D, dets, lambda d: True)
        for d in dets:
            if d.instance in estimated:  # the estimator's pose is already refined: the output as it is
                out.append(RefinedPose(d.instance, d.q_wxyz, d.position, d.box, d.score, refine_score=d.estimate_score))
                continue
            if d.q_wxyz is None:
                self._skip(d.object_id)
                continue
            by_object.setdefault(d.object_id, []).append(d)
        for object_id, group in by_object.items():
            model = self._model(object_id)
            passes = {} if not model.per_call_passes else {"views": self.views, **(
                {} if self.settle_deg is None else {"iterations": 2, "settle_deg": self.settle_deg})}
            res = model.refine(image, np.array([d.box for d in group]), np.array([d.q_wxyz for d in group]), K=K,
                               D=D, **passes)
            out += [RefinedPose(d.instance, q, d.position, d.box, d.score, refine_score=float(c), q_input_wxyz=d.q_wxyz)
                    for d, q, c in zip(group, res.q_refined, res.score)]
        return out

    def _track(self, image, K, D, dets: list[Detection]) -> list[RefinedPose]:
        from refiner_rt.tracker import RefinerTracker

        if self._tracker is None:
            self._tracker = RefinerTracker({}, K, {}, D=D, **self.tracker_kwargs)
        tracker = self._tracker
        if self.estimate_missing:  # a box-only detection of an object not tracked yet: a pose to start from
            dets, _ = self._estimate(image, K, D, dets, lambda d: d.instance not in tracker)
        boxes, poses, seen = {}, {}, {}
        for d in dets:
            if d.q_wxyz is None and d.instance not in tracker:
                self._skip(d.object_id)  # a box but no pose to start from yet
                continue
            boxes[d.instance], seen[d.instance] = d.box, d
            if d.q_wxyz is not None:
                poses[d.instance] = d.q_wxyz
        if not boxes:
            return []
        sessions = {key: self._model(seen[key].object_id) for key in poses if key not in tracker}
        refined = tracker.update_from_detector(image, boxes, poses, sessions=sessions)
        lost, again = set(tracker.lost), set(tracker.reinitialised)
        return [RefinedPose(key, q, seen[key].position, seen[key].box, seen[key].score, lost=key in lost,
                            refine_score=tracker.scores.get(key), q_input_wxyz=poses.get(key),
                            reinitialised=key in again)
                for key, q in refined.items()]
