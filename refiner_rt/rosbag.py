"""ROS 2 bags in and out without a ROS install: ``refiner-rt track --bag IN -o OUT``.

Reading and writing go through ``rosbags`` (``pip install 'refiner-rt[ros]'``): pure Python, it reads both rosbag2
storages, MCAP (``.mcap``, the default since ROS 2 Iron) and SQLite (``.db3``), as a bag folder (with its
``metadata.yaml``) or a bare file, deserialises messages from its own type store without ROS, and writes MCAP bags.
(``mcap`` with ``mcap-ros2-support`` reads MCAP only.)

The input bag holds an image topic (``sensor_msgs/Image`` or ``CompressedImage``), its ``sensor_msgs/CameraInfo`` and
``vision_msgs/Detection2DArray`` detections; each topic is found by its type when the bag has one of it, else named
with ``--image-topic`` and the like. Detections are matched to images by ``header.stamp`` (approximate time sync):
each image takes the detection message nearest in time within ``sync_tolerance_ms`` (default
:data:`SYNC_TOLERANCE_MS`, for a 30 Hz camera), nearest pairs first, one message per image and one image per
message. Matches that are not exact are counted (``refiner-rt track`` warns); when no image has a match the bag is
refused with the counts and the closest offset seen, before anything is written. Each matched image goes through
:class:`refiner_rt.ros.RosRefiner` (the function a live node calls; its docstring has the no-pose rule and the
instance ids), and the output bag (MCAP, a rosbag2 folder that Foxglove and ``ros2 bag play`` open) gets, at the
image's time:

* ``/refiner_rt/pose/<instance>`` (``geometry_msgs/PoseStamped``, one topic per instance, :func:`pose_topic`; the
  image's header: stamp and camera frame): the refined rotation, the detection's position;
* ``/tf`` (``tf2_msgs/TFMessage``): one transform per refined instance that has a position, from the image's
  ``header.frame_id`` (the camera's optical frame) to the frame :func:`object_frame` names: the refined rotation and
  the detection's position, passed through (the refiners correct the rotation only);
* ``/refiner_rt/detections`` (``vision_msgs/Detection2DArray``): the input detections with the refined poses in
  their hypotheses (an empty ``Detection2D.id`` of one of several instances gets its number, ``1``, ``2``...);
* ``/refiner_rt/detections3d`` (``vision_msgs/Detection3DArray``): per refined instance its class id, the refined
  pose and the refinement's confidence (``RefineResult.score``, in ``(0, 1]``; calibrated for two passes, see
  docs/ros2.md) as the hypothesis score;
* ``/refiner_rt/lost`` (``vision_msgs/Detection2DArray``, in ``"track"`` mode with ``lost_deg``, at every matched
  image, empty when none): the detections whose track the loss-of-track check flagged in that frame;
* ``/refiner_rt/overlay/compressed`` (``sensor_msgs/CompressedImage``, JPEG): the image with each object's box, its
  outline at the refined rotation (green; red when its track is lost) and at the detection's coarse rotation where the
  frame gives one (cyan), placed at the detection's position (else from the box), labels with the refinement's score,
  and a legend (:func:`refiner_rt.draw.annotate_poses`; a pinhole projection, lens distortion not drawn).
"""

from __future__ import annotations

import bisect
import logging
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from refiner_rt.ros import VISION_MSGS, RefinedPose, RosRefiner, stamp_ns

__all__ = ["refine_bag", "typestore", "BagSummary", "OUTPUT_PREFIX", "SYNC_TOLERANCE_MS", "pose_topic",
           "object_frame", "match_stamps"]

log = logging.getLogger(__name__)

OUTPUT_PREFIX = "/refiner_rt"
TF_TOPIC = "/tf"
# A 30 Hz camera's frames are 33 ms apart; matching is one to one, nearest first, so a detection serves one image.
SYNC_TOLERANCE_MS = 20.0
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
DETECTIONS_TYPE = "vision_msgs/msg/Detection2DArray"
DETECTIONS_3D_TYPE = "vision_msgs/msg/Detection3DArray"
ROSBAGS_MISSING = ("reading ROS 2 bags needs the rosbags package: pip install 'refiner-rt[ros]' (or pip install "
                   "rosbags)")


def typestore():
    """A ``rosbags`` type store of ROS 2 Humble's messages plus vision_msgs (:data:`refiner_rt.ros.VISION_MSGS`)."""
    try:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    except ModuleNotFoundError:
        raise ModuleNotFoundError(ROSBAGS_MISSING, name="rosbags") from None
    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    for name, text in VISION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def _token(object_id: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", object_id)


def pose_topic(object_id: str) -> str:
    """The output topic of an instance's poses: ROS 2 name tokens may not start with a digit, so ``003_cracker_box``
    becomes ``/refiner_rt/pose/ycb_003_cracker_box`` (``#2`` -> ``_2``)."""
    token = _token(object_id)
    return f"{OUTPUT_PREFIX}/pose/{'ycb_' + token if token[:1].isdigit() else token}"


def object_frame(object_id: str) -> str:
    """The TF frame of an instance: its id with ``#`` (and anything but letters, digits and ``_``) as ``_``:
    ``003_cracker_box``, ``003_cracker_box_2``."""
    return _token(object_id)


@dataclass
class BagSummary:
    """What :func:`refine_bag` did: topics read, images and detection messages, how they matched (``approximate``:
    matches whose stamps differ, by up to ``max_offset_ms``), frames refined, poses written (per instance), lost
    flags and re-initialisations (instance -> frames), transforms written, detections skipped (by object id)."""

    image_topic: str
    info_topic: str
    detections_topic: str
    images: int = 0
    detection_messages: int = 0
    frames_with_detections: int = 0
    approximate: int = 0
    max_offset_ms: float = 0.0
    unmatched_detections: int = 0
    poses: int = 0
    transforms: int = 0
    objects: dict = field(default_factory=dict)  # instance id -> poses written
    lost: dict = field(default_factory=dict)  # instance id -> frames the loss-of-track check flagged it in
    reinitialised: dict = field(default_factory=dict)  # instance id -> frames its track was re-initialised in
    skipped: dict = field(default_factory=dict)
    output_topics: list = field(default_factory=list)


def _pick(connections, types, flag: str, given: str | None) -> str:
    topics = sorted({c.topic for c in connections if c.msgtype in types})
    if given is not None:
        if given not in {c.topic for c in connections}:
            raise ValueError(f"{flag} {given!r} is not a topic of the bag; its topics: "
                             + ", ".join(f"{c.topic} ({c.msgtype})" for c in connections))
        return given
    if len(topics) == 1:
        return topics[0]
    what = " or ".join(t.split("/")[-1] for t in types)
    if not topics:
        raise ValueError(f"the bag has no {what} topic; its topics: "
                         + (", ".join(f"{c.topic} ({c.msgtype})" for c in connections) or "none"))
    raise ValueError(f"the bag has several {what} topics ({', '.join(topics)}); choose one with {flag}")


def match_stamps(image_stamps: list[int], detection_stamps: list[int], tolerance_ns: int
                 ) -> tuple[dict[int, int], int | None]:
    """Approximate time sync: ``({image index: detection index}, closest offset in ns or None)``.

    Pairs whose stamps (ns) differ by at most ``tolerance_ns`` are matched nearest first, each image and each
    detection message at most once. The closest offset is the smallest ``|image - detection|`` over all images
    (matched or not; None without images or detections), for the message when nothing matched.
    """
    order = sorted(range(len(detection_stamps)), key=detection_stamps.__getitem__)
    sorted_stamps = [detection_stamps[j] for j in order]
    pairs, closest = [], None
    for i, t in enumerate(image_stamps):
        k = bisect.bisect_left(sorted_stamps, t)
        if sorted_stamps:
            near = min(abs(sorted_stamps[j] - t) for j in (k - 1, k) if 0 <= j < len(sorted_stamps))
            closest = near if closest is None else min(closest, near)
        lo = bisect.bisect_left(sorted_stamps, t - tolerance_ns)
        hi = bisect.bisect_right(sorted_stamps, t + tolerance_ns)
        pairs += [(abs(sorted_stamps[j] - t), i, order[j]) for j in range(lo, hi)]
    matched, used = {}, set()
    for _, i, j in sorted(pairs):
        if i not in matched and j not in used:
            matched[i] = j
            used.add(j)
    return matched, closest


def refine_bag(bag: Path, out: Path, refiner: RosRefiner, *, image_topic: str | None = None,
               info_topic: str | None = None, detections_topic: str | None = None, overlay: bool = True,
               sync_tolerance_ms: float = SYNC_TOLERANCE_MS, progress: Callable[[int], None] | None = None,
               total: Callable[[int], None] | None = None) -> BagSummary:
    """Run ``refiner`` over every image of ``bag`` that a detection message matches (within
    ``sync_tolerance_ms`` milliseconds, module docstring) and write the results to the MCAP bag ``out``.
    ``total(n)`` is told the number of images first, ``progress(1)`` after each. Approximate matches are counted in
    the summary (``approximate``, ``max_offset_ms``, ``unmatched_detections``: ``refiner-rt track`` prints them as
    a warning) and logged at INFO level.

    Raises:
        ValueError: a topic that is missing or ambiguous, no image matched by any detection message (the counts
            and the closest offset seen; nothing is written), an image before any CameraInfo, a negative
            tolerance, or a message the runtime cannot read (named with its topic and time).
        FileExistsError: ``out`` exists.
        ModuleNotFoundError: ``rosbags`` is not installed.
    """
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.rosbag2 import StoragePlugin, Writer
    except ModuleNotFoundError:
        raise ModuleNotFoundError(ROSBAGS_MISSING, name="rosbags") from None
    from refiner_rt.demo import load_outlines
    from refiner_rt.draw import PoseOverlay, annotate_poses
    from refiner_rt.ros import camera_from_info, image_from_msg

    if not np.isfinite(sync_tolerance_ms) or sync_tolerance_ms < 0:
        raise ValueError(f"sync_tolerance_ms must be a finite number of milliseconds >= 0; got {sync_tolerance_ms!r}")
    tolerance_ns = int(round(sync_tolerance_ms * 1e6))
    outlines = load_outlines() if overlay else {}  # the package's outline points, read once
    bag, out = Path(bag), Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists; the output bag must be a new folder")
    store = typestore()
    with AnyReader([bag], default_typestore=store) as reader:
        conns = reader.connections
        summary = BagSummary(image_topic=_pick(conns, IMAGE_TYPES, "--image-topic", image_topic),
                             info_topic=_pick(conns, (INFO_TYPE,), "--info-topic", info_topic),
                             detections_topic=_pick(conns, (DETECTIONS_TYPE,), "--detections-topic",
                                                    detections_topic))
        by_topic = {t: [c for c in conns if c.topic == t] for t in (summary.image_topic, summary.info_topic,
                                                                     summary.detections_topic)}
        detections = [reader.deserialize(raw, conn.msgtype)
                      for conn, _, raw in reader.messages(connections=by_topic[summary.detections_topic])]
        image_stamps = [stamp_ns(reader.deserialize(raw, conn.msgtype).header)
                        for conn, _, raw in reader.messages(connections=by_topic[summary.image_topic])]
        matched, closest = match_stamps(image_stamps, [stamp_ns(d.header) for d in detections], tolerance_ns)
        summary.detection_messages = len(detections)
        if not matched:
            seen = "no stamps to compare" if closest is None else f"the closest stamps {closest / 1e6:.3f} ms apart"
            raise ValueError(f"no detections matched an image within {sync_tolerance_ms:g} ms "
                             f"(--sync-tolerance-ms): {len(image_stamps)} images on {summary.image_topic}, "
                             f"{len(detections)} detection messages on {summary.detections_topic}, {seen}; "
                             "a detection must carry its image's header.stamp (give a larger tolerance if the "
                             "detector restamps)")
        offsets = [abs(image_stamps[i] - stamp_ns(detections[j].header)) for i, j in matched.items()]
        summary.approximate = sum(1 for o in offsets if o)
        summary.max_offset_ms = max(offsets) / 1e6
        summary.unmatched_detections = len(detections) - len(matched)
        if summary.approximate:
            log.info("%d of %d matched images have detections stamped up to %.3f ms apart (within %g ms)",
                        summary.approximate, len(matched), summary.max_offset_ms, sync_tolerance_ms)
        if total:
            total(len(image_stamps))
        Compressed = store.types["sensor_msgs/msg/CompressedImage"]
        TFMessage = store.types["tf2_msgs/msg/TFMessage"]
        writer = Writer(out, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
        with writer:
            out_conns = {}

            def write(topic: str, msgtype: str, msg, t: int) -> None:
                if topic not in out_conns:
                    out_conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
                    summary.output_topics.append(topic)
                writer.write(out_conns[topic], t, store.serialize_cdr(msg, msgtype))

            info = None
            index = -1
            wanted = by_topic[summary.info_topic] + by_topic[summary.image_topic]
            for conn, t, raw in reader.messages(connections=wanted):
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic == summary.info_topic:
                    info = msg
                    continue
                index += 1
                summary.images += 1
                det = detections[matched[index]] if index in matched else None
                if det is not None:
                    if info is None:
                        raise ValueError(f"{summary.image_topic} at {t} ns: an image before any CameraInfo on "
                                         f"{summary.info_topic}")
                    try:
                        poses = refiner.process(msg, info, det)
                    except ValueError as exc:
                        raise ValueError(f"{summary.image_topic} at {t} ns: {exc}") from None
                    summary.frames_with_detections += 1
                    for p in poses:
                        write(pose_topic(p.object_id), "geometry_msgs/msg/PoseStamped", _pose_msg(store, msg.header, p),
                              t)
                        summary.objects[p.object_id] = summary.objects.get(p.object_id, 0) + 1
                        if p.lost:
                            summary.lost[p.object_id] = summary.lost.get(p.object_id, 0) + 1
                        if p.reinitialised:
                            summary.reinitialised[p.object_id] = summary.reinitialised.get(p.object_id, 0) + 1
                    summary.poses += len(poses)
                    transforms = [_transform_msg(store, msg.header, p) for p in poses if p.position is not None]
                    if transforms:
                        write(TF_TOPIC, "tf2_msgs/msg/TFMessage", TFMessage(transforms=transforms), t)
                        summary.transforms += len(transforms)
                    write(f"{OUTPUT_PREFIX}/detections", DETECTIONS_TYPE, _refined_detections(det, poses), t)
                    write(f"{OUTPUT_PREFIX}/detections3d", DETECTIONS_3D_TYPE, _detections_3d(store, msg.header, poses),
                          t)
                    if refiner.checks_loss:
                        write(f"{OUTPUT_PREFIX}/lost", DETECTIONS_TYPE,
                              _refined_detections(det, [p for p in poses if p.lost]), t)
                    if overlay:
                        drawn = annotate_poses(image_from_msg(msg), camera_from_info(info, refiner.rectified)[0], [
                            PoseOverlay(p.object_id, p.box, p.q_wxyz, q_input=p.q_input_wxyz, t=p.position,
                                        lost=p.lost, score=p.refine_score) for p in poses], outlines)
                        ok, jpeg = cv2.imencode(".jpg", drawn, [cv2.IMWRITE_JPEG_QUALITY, 90])
                        write(f"{OUTPUT_PREFIX}/overlay/compressed", "sensor_msgs/msg/CompressedImage",
                              Compressed(header=msg.header, format="jpeg", data=np.frombuffer(jpeg.tobytes(), np.uint8)),
                              t)
                if progress:
                    progress(1)
    summary.skipped = dict(refiner.skipped)
    return summary


def _transform_msg(store, header, p: RefinedPose):
    """``geometry_msgs/TransformStamped`` from the camera frame (``header.frame_id``) to :func:`object_frame`."""
    T = store.types
    x, y, z, w = (float(v) for v in p.q_xyzw)
    translation = T["geometry_msgs/msg/Vector3"](x=float(p.position[0]), y=float(p.position[1]),
                                                 z=float(p.position[2]))
    transform = T["geometry_msgs/msg/Transform"](translation=translation,
                                                 rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))
    return T["geometry_msgs/msg/TransformStamped"](header=header, child_frame_id=object_frame(p.object_id),
                                                   transform=transform)


def _pose(store, p: RefinedPose):
    """``geometry_msgs/Pose``: the refined rotation and the detection's position (zeros without one)."""
    T = store.types
    x, y, z, w = (float(v) for v in p.q_xyzw)
    pos = p.position if p.position is not None else np.zeros(3)
    point = T["geometry_msgs/msg/Point"](x=float(pos[0]), y=float(pos[1]), z=float(pos[2]))
    return T["geometry_msgs/msg/Pose"](position=point, orientation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))


def _pose_msg(store, header, p: RefinedPose):
    return store.types["geometry_msgs/msg/PoseStamped"](header=header, pose=_pose(store, p))


def _detections_3d(store, header, poses: list[RefinedPose]):
    """``vision_msgs/Detection3DArray``: per refined instance one ``Detection3D`` whose hypothesis is the object's
    class id, the refinement's confidence (:attr:`RefinedPose.refine_score`) as its ``score`` and the refined pose;
    ``bbox.center`` the same pose, ``bbox.size`` zeros (not measured); ``id`` the instance's (``#`` suffix)."""
    T = store.types
    out = []
    for p in poses:
        pose = _pose(store, p)
        covariance = np.zeros(36, dtype=np.float64)
        hypothesis = T["vision_msgs/msg/ObjectHypothesisWithPose"](
            hypothesis=T["vision_msgs/msg/ObjectHypothesis"](
                class_id=p.object_id.split("#", 1)[0],
                score=float("nan") if p.refine_score is None else float(p.refine_score)),
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=covariance))
        bbox = T["vision_msgs/msg/BoundingBox3D"](center=pose, size=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0))
        out.append(T["vision_msgs/msg/Detection3D"](header=header, results=[hypothesis], bbox=bbox,
                                                    id=p.object_id.split("#", 1)[1] if "#" in p.object_id else ""))
    return T["vision_msgs/msg/Detection3DArray"](header=header, detections=out)


def _refined_detections(det, poses: list[RefinedPose]):
    """The input ``Detection2DArray`` with each refined detection's hypothesis pose orientation replaced (matched
    by box), the others left out."""
    import copy

    out = copy.deepcopy(det)
    kept = []
    for d in out.detections:
        if not len(d.results):
            continue
        box = np.array([d.bbox.center.position.x - d.bbox.size_x / 2, d.bbox.center.position.y - d.bbox.size_y / 2,
                        d.bbox.center.position.x + d.bbox.size_x / 2, d.bbox.center.position.y + d.bbox.size_y / 2])
        match = next((p for p in poses if np.allclose(p.box, box)), None)
        if match is None:
            continue
        x, y, z, w = (float(v) for v in match.q_xyzw)
        if not d.id and "#" in match.object_id:  # one of several instances without an id: its number
            d.id = match.object_id.split("#", 1)[1]
        o = d.results[0].pose.pose.orientation
        o.x, o.y, o.z, o.w = x, y, z, w
        kept.append(d)
    out.detections = kept
    return out
