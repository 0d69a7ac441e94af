"""ROS 2 bags in and out without a ROS install: ``refiner-rt track --bag IN -o OUT``.

Reading and writing go through ``rosbags`` (``pip install 'refiner-rt[ros]'``): pure Python, it reads both rosbag2
storages, MCAP (``.mcap``, the default since ROS 2 Iron) and SQLite (``.db3``), as a bag folder (with its
``metadata.yaml``) or a bare file, deserialises messages from its own type store without ROS, and writes MCAP bags.
(``mcap`` with ``mcap-ros2-support`` reads MCAP only.)

The input bag holds an image topic (``sensor_msgs/Image`` or ``CompressedImage``), its ``sensor_msgs/CameraInfo`` and
``vision_msgs/Detection2DArray`` detections whose ``header.stamp`` is the image's (what a detector node publishes);
each topic is found by its type when the bag has one of it, else named with ``--image-topic`` and the like. Each image
with detections goes through :class:`refiner_rt.ros.RosRefiner` (the function a live node calls), and the output bag
(MCAP, a rosbag2 folder that Foxglove and ``ros2 bag play`` open) gets, at the image's time:

* ``/refiner_rt/pose/<object>`` (``geometry_msgs/PoseStamped``, one topic per object; the image's header: stamp and
  camera frame): the refined rotation, the detection's position;
* ``/refiner_rt/detections`` (``vision_msgs/Detection2DArray``): the input detections with the refined poses in
  their hypotheses;
* ``/refiner_rt/overlay/compressed`` (``sensor_msgs/CompressedImage``, JPEG): the image with each object's box and
  refined axes drawn (x red, y green, z blue).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from refiner_rt.ros import VISION_MSGS, RefinedPose, RosRefiner, stamp_ns

__all__ = ["refine_bag", "typestore", "BagSummary", "OUTPUT_PREFIX", "pose_topic"]

OUTPUT_PREFIX = "/refiner_rt"
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
DETECTIONS_TYPE = "vision_msgs/msg/Detection2DArray"
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


def pose_topic(object_id: str) -> str:
    """The output topic of an object's poses: ROS 2 name tokens may not start with a digit, so ``003_cracker_box``
    becomes ``/refiner_rt/pose/ycb_003_cracker_box`` (``#2`` -> ``_2``)."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", object_id)
    return f"{OUTPUT_PREFIX}/pose/{'ycb_' + token if token[:1].isdigit() else token}"


@dataclass
class BagSummary:
    """What :func:`refine_bag` did: topics read, frames, poses written, detections skipped (by class id)."""

    image_topic: str
    info_topic: str
    detections_topic: str
    images: int = 0
    frames_with_detections: int = 0
    poses: int = 0
    objects: dict = field(default_factory=dict)  # object id -> poses written
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


def refine_bag(bag: Path, out: Path, refiner: RosRefiner, *, image_topic: str | None = None,
               info_topic: str | None = None, detections_topic: str | None = None, overlay: bool = True,
               progress: Callable[[int], None] | None = None, total: Callable[[int], None] | None = None
               ) -> BagSummary:
    """Run ``refiner`` over every image of ``bag`` that has detections and write the results to the MCAP bag
    ``out`` (module docstring). ``total(n)`` is told the number of images first, ``progress(1)`` after each.

    Raises:
        ValueError: a topic that is missing or ambiguous, an image before any CameraInfo, or a message the runtime
            cannot read (named with its topic and time).
        FileExistsError: ``out`` exists.
        ModuleNotFoundError: ``rosbags`` is not installed.
    """
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.rosbag2 import StoragePlugin, Writer
    except ModuleNotFoundError:
        raise ModuleNotFoundError(ROSBAGS_MISSING, name="rosbags") from None
    from refiner_rt.track_cli import annotate

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
        detections = {}
        for conn, _, raw in reader.messages(connections=by_topic[summary.detections_topic]):
            msg = reader.deserialize(raw, conn.msgtype)
            detections[stamp_ns(msg.header)] = msg
        n_images = sum(c.msgcount for c in by_topic[summary.image_topic])
        if total:
            total(n_images)
        Compressed = store.types["sensor_msgs/msg/CompressedImage"]
        writer = Writer(out, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
        with writer:
            out_conns = {}

            def write(topic: str, msgtype: str, msg, t: int) -> None:
                if topic not in out_conns:
                    out_conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
                    summary.output_topics.append(topic)
                writer.write(out_conns[topic], t, store.serialize_cdr(msg, msgtype))

            info = None
            wanted = by_topic[summary.info_topic] + by_topic[summary.image_topic]
            for conn, t, raw in reader.messages(connections=wanted):
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic == summary.info_topic:
                    info = msg
                    continue
                summary.images += 1
                det = detections.get(stamp_ns(msg.header))
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
                    summary.poses += len(poses)
                    write(f"{OUTPUT_PREFIX}/detections", DETECTIONS_TYPE, _refined_detections(det, poses), t)
                    if overlay:
                        from refiner_rt.ros import image_from_msg

                        drawn = annotate(image_from_msg(msg), {p.object_id: p.box for p in poses},
                                         {p.object_id: p.q_wxyz for p in poses})
                        ok, jpeg = cv2.imencode(".jpg", drawn, [cv2.IMWRITE_JPEG_QUALITY, 90])
                        write(f"{OUTPUT_PREFIX}/overlay/compressed", "sensor_msgs/msg/CompressedImage",
                              Compressed(header=msg.header, format="jpeg", data=np.frombuffer(jpeg.tobytes(), np.uint8)),
                              t)
                if progress:
                    progress(1)
    summary.skipped = dict(refiner.skipped)
    return summary


def _pose_msg(store, header, p: RefinedPose):
    T = store.types
    x, y, z, w = (float(v) for v in p.q_xyzw)
    pos = p.position if p.position is not None else np.zeros(3)
    point = T["geometry_msgs/msg/Point"](x=float(pos[0]), y=float(pos[1]), z=float(pos[2]))
    pose = T["geometry_msgs/msg/Pose"](position=point, orientation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))
    return T["geometry_msgs/msg/PoseStamped"](header=header, pose=pose)


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
        o = d.results[0].pose.pose.orientation
        o.x, o.y, o.z, o.w = x, y, z, w
        kept.append(d)
    out.detections = kept
    return out
