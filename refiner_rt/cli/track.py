"""``refiner-rt track``: run a :class:`~refiner_rt.tracker.RefinerTracker` over a folder of frames (torch-free).

Input: a folder of images (``.png`` / ``.jpg``, taken in file-name order) and a detections file (JSON)::

    {
      "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
      "frames": {
        "000000.png": {"003_cracker_box": {"box": [x1, y1, x2, y2], "q": [w, x, y, z]}},
        "000001.png": {"003_cracker_box": [x1, y1, x2, y2]}
      }
    }

A detection is a box, or a box with a coarse rotation ``q`` (a detector's pose): ``q`` starts tracking the object,
or re-initialises it (with ``--detector-weight W``: is refined beside the track and fused with it, weight ``W``).
Frames without an entry have no detections (the tracked objects keep their rotations).
Output: the refined rotation of every object in every frame where it had a box, as JSON
``{"frames": {"000000.png": {"003_cracker_box": [w, x, y, z]}}, ...}``.

Conventions (docs/design.md §2): quaternions ``wxyz`` (scalar first), object-to-camera; boxes ``(x1, y1, x2,
y2)`` in pixels, continuous coordinates; ``K`` in pixels (OpenCV convention).
"""

from __future__ import annotations

import functools
import json
import sys
import time
from pathlib import Path

import click
import cv2
import numpy as np

from refiner_rt import draw
from refiner_rt.checks import MAX_ITERATIONS, MAX_VIEWS, STARTS
from refiner_rt.cli import prepare_output

__all__ = ["track_cmd", "read_detections", "frame_files", "annotate", "OUTPUT_FORMAT"]

OUTPUT_FORMAT = "refiner-rt/track/1"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
VIDEO_CODECS = {".mp4": "mp4v", ".avi": "MJPG"}
STRIP_SUFFIXES = (".png", ".jpg")
STRIP_WIDTH = 320  # pixels per frame in an image strip


def frame_files(folder: Path) -> list[Path]:
    """The images in ``folder`` (``.png``, ``.jpg``, ``.jpeg``), sorted by file name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def read_detections(path: Path) -> tuple[np.ndarray | None, dict[str, dict[str, dict]]]:
    """Parse a detections file (module docstring).

    Returns:
        ``(K or None, {frame file name: {object id: {"box": (4,) float64, "q": (4,) float64 wxyz or None}}})``.

    Raises:
        ValueError: not JSON, or an entry of the wrong form (the message names the file and the entry).
    """
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable JSON detections file ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), dict):
        raise ValueError(f"{path}: expected an object with \"frames\": {{frame file name: {{object id: box}}}}")
    K = doc.get("K")
    frames = {}
    for frame, detections in doc["frames"].items():
        if not isinstance(detections, dict):
            raise ValueError(f"{path}: frames[{frame!r}] must map object ids to boxes; got {type(detections).__name__}")
        frames[frame] = {}
        for object_id, det in detections.items():
            where = f"{path}: frames[{frame!r}][{object_id!r}]"
            q = None
            if isinstance(det, dict):
                unknown = sorted(set(det) - {"box", "q"})
                if unknown or "box" not in det:
                    raise ValueError(f"{where} must be [x1, y1, x2, y2] or {{\"box\": [...], \"q\": [w, x, y, z]}}; "
                                     f"got keys {sorted(det)}")
                box, q = det["box"], det.get("q")
            else:
                box = det
            frames[frame][object_id] = {"box": _numbers(box, 4, f"{where} box (x1, y1, x2, y2)"),
                                        "q": None if q is None else _numbers(q, 4, f"{where} q (w, x, y, z)")}
    return (None if K is None else _numbers(K, (3, 3), f"{path}: K")), frames


def _numbers(value, shape, what: str) -> np.ndarray:
    shape = (shape,) if isinstance(shape, int) else shape
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be numbers of shape {shape}; got {value!r}") from None
    if arr.shape != shape:
        raise ValueError(f"{what} must have shape {shape}; got {value!r}")
    return arr


def annotate(image: np.ndarray, K: np.ndarray, objects: list) -> np.ndarray:
    """A copy of ``image`` (BGR) with each object's outline at its refined rotation (and at the detector's input,
    where the frame gives one), its box and its label, and a legend: :func:`refiner_rt.draw.annotate_poses` with the
    package's outline points (``objects``: :class:`refiner_rt.draw.PoseOverlay`)."""
    return draw.annotate_poses(image, K, objects, _outlines())


@functools.lru_cache(maxsize=1)
def _outlines() -> dict:
    from refiner_rt.demo import load_outlines

    return load_outlines()


class _VideoOutput:
    """Annotated frames to a video file (``.mp4``, ``.avi``) or an image strip (``.png``, ``.jpg``)."""

    def __init__(self, path: Path, n_frames: int, strip_frames: int, fps: float):
        self.path, self.writer, self.tiles = path, None, []
        suffix = path.suffix.lower()
        if suffix not in VIDEO_CODECS and suffix not in STRIP_SUFFIXES:
            raise click.BadParameter(f"expected a .mp4 or .avi video or a .png or .jpg image strip; got {path.name!r}",
                                     param_hint="'--video'")
        self.strip = suffix in STRIP_SUFFIXES
        self.fps = fps
        count = max(1, min(strip_frames, n_frames))
        self.keep = set(np.round(np.linspace(0, n_frames - 1, count)).astype(int).tolist())

    def add(self, index: int, frame: np.ndarray) -> None:
        if self.strip:
            if index in self.keep:
                h, w = frame.shape[:2]
                self.tiles.append(cv2.resize(frame, (STRIP_WIDTH, max(1, round(h * STRIP_WIDTH / w))),
                                             interpolation=cv2.INTER_AREA))
            return
        if self.writer is None:
            h, w = frame.shape[:2]
            self.size = (w, h)
            fourcc = cv2.VideoWriter_fourcc(*VIDEO_CODECS[self.path.suffix.lower()])
            self.writer = cv2.VideoWriter(str(self.path), fourcc, self.fps, self.size)
            if not self.writer.isOpened():
                raise click.ClickException(f"OpenCV cannot write the video {self.path} (codec "
                                           f"{VIDEO_CODECS[self.path.suffix.lower()]}); write a .png image strip instead")
        if (frame.shape[1], frame.shape[0]) != self.size:
            frame = cv2.resize(frame, self.size)
        self.writer.write(frame)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.release()
        if self.strip and self.tiles:
            height = max(t.shape[0] for t in self.tiles)
            tiles = [cv2.copyMakeBorder(t, 0, height - t.shape[0], 0, 0, cv2.BORDER_CONSTANT) for t in self.tiles]
            if not cv2.imwrite(str(self.path), np.hstack(tiles)):
                raise click.ClickException(f"cannot write the image strip {self.path}")


def _sessions(object_ids, model_args, int8: bool, threads: int) -> dict:
    """``{object id: RefinerSession}``: an ``--model`` ONNX file trained for the object, else its shipped model."""
    from refiner_rt.refiner import load
    from refiner_rt.session import RefinerSession
    from refiner_rt.tracker import object_name

    files, names = [], set()
    for m in model_args:
        if m.lower().endswith(".onnx") or Path(m).is_file():
            files.append(RefinerSession(m, threads=threads))
        else:
            names.add(m)
    loaded, out = {}, {}
    for object_id in object_ids:
        name = object_name(object_id)
        sess = next((s for s in files if name in s.contract.objects), None)
        if sess is None:
            if names and name not in names:
                raise ValueError(f"no --model serves object {object_id!r}: the ONNX files given are trained for "
                                 f"{sorted({o for s in files for o in s.contract.objects})} and the names given are "
                                 f"{sorted(names)}")
            if name not in loaded:
                loaded[name] = load(name, int8=int8, threads=threads)
            sess = loaded[name]
        out[object_id] = sess
    return out


def _cascades(sessions: dict, int8: bool, threads: int, settle_deg: float | None = None) -> dict:
    """``--cascade``: each object's shipped :class:`refiner_rt.RefinerCascade` (with ``settle_deg``) in place of its
    coarse session (the session kept where no fine refiner ships, or where an ``--model`` file serves the object)."""
    from refiner_rt.pretrained import WEIGHTS_DIR
    from refiner_rt.refiner import load
    from refiner_rt.tracker import object_name

    out, built = {}, {}
    for object_id, sess in sessions.items():
        name = object_name(object_id)
        shipped = sess.model_path is not None and Path(sess.model_path).parent == WEIGHTS_DIR
        if shipped:
            if name not in built:  # the cascade where a fine refiner ships, else the coarse session
                built[name] = load(name, cascade=True, int8=int8, threads=threads, settle_deg=settle_deg)
            out[object_id] = built[name]
        else:
            out[object_id] = sess
    return out


@click.command("track")
@click.argument("frames", type=click.Path(exists=True, file_okay=False, path_type=Path), required=False)
@click.argument("detections", type=click.Path(exists=True, dir_okay=False, path_type=Path), required=False)
@click.option("-o", "--out", "out_path", type=click.Path(path_type=Path), required=True,
              help="Rotations file to write (JSON, wxyz object-to-camera per frame and object); with --bag, the "
                   "output bag (a new folder, MCAP).")
@click.option("--bag", "bag", type=click.Path(exists=True, path_type=Path),
              help="A ROS 2 bag (rosbag2 folder, .mcap or .db3) with images, CameraInfo and vision_msgs "
                   "Detection2DArray, instead of FRAMES and DETECTIONS: the refined poses go to the -o bag "
                   "(refiner_rt.rosbag). Needs pip install 'refiner-rt[ros]'.")
@click.option("--mode", type=click.Choice(["track", "refine"]), default="track", show_default=True,
              help="With --bag: track (a detection's pose starts an object, later frames refine from the previous "
                   "result) or refine (every detection with a pose refined from it).")
@click.option("--cascade", is_flag=True, help="Each object's coarse and fine refiners in turn (RefinerCascade) where "
              "a fine refiner ships: eight network passes per object and frame instead of one (with --bag --mode refine, "
              "twelve where an input goes the long way; more with --settle-deg or --lost-deg).")
@click.option("--rectified", is_flag=True, help="With --bag: the image topic is rectified: K from CameraInfo.p, "
              "no distortion.")
@click.option("--image-topic", help="With --bag: the image topic (default: the bag's one Image or CompressedImage "
              "topic).")
@click.option("--info-topic", help="With --bag: the CameraInfo topic (default: the bag's one).")
@click.option("--detections-topic", help="With --bag: the Detection2DArray topic (default: the bag's one).")
@click.option("--sync-tolerance-ms", type=click.FloatRange(0.0, 1000.0), default=None, metavar="MS",
              help="With --bag: match each image to the detection message nearest in stamp within this many "
                   "milliseconds (approximate matches are counted and reported; no match at all is an error). "
                   "Default: 20, for a 30 Hz camera; 0 for exact stamps only.")
@click.option("--identity-is-pose", is_flag=True,
              help="With --bag: a detection orientation of (0, 0, 0, 1) is the identity rotation. Default: it is "
                   "the message's default, a box-only detection (no pose), like all zeros.")
@click.option("--estimate-missing", is_flag=True,
              help="With --bag: a box-only detection gets a 6D pose from the object's PoseEstimator (rotation from "
                   "the crop alone, translation from the box): the output in --mode refine, a track's start in "
                   "--mode track. Default: box-only detections are skipped (refine) or wait for a pose (track).")
@click.option("--class-map", "class_map", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="With --bag: a JSON object mapping the detector's class ids to YCB ids (default: the class id "
                   "is the YCB id).")
@click.option("--model", "models", multiple=True,
              help="A refiner for some objects: an ONNX file (serves the objects in its metadata) or a shipped "
                   "model's name. Repeatable. Default: each object's shipped model.")
@click.option("--fp32", is_flag=True, help="Use the shipped fp32 models instead of INT8.")
@click.option("--K", "K_text", metavar="FX,FY,CX,CY", help="Camera intrinsics in pixels (instead of the file's \"K\").")
@click.option("--predict", is_flag=True, help="Predict each rotation with a constant angular velocity first.")
@click.option("--scene-motion", is_flag=True,
              help="The objects stand still and the camera moves (a camera on a robot's arm or head): predict every "
                   "rotation with the camera's turn, measured from all tracked objects, and carry hidden objects "
                   "with it (RefinerTracker(predict=\"scene\")). Not with --predict.")
@click.option("--lost-deg", type=click.FloatRange(0.0, 180.0, min_open=True), default=None,
              help="Loss-of-track check: flag an object lost when a second refinement moves its rotation by more "
                   "than this many degrees (one more pass per object and frame, N with --views N); the output's "
                   "\"lost\" lists those frames, for a detector's new \"q\" (with --bag: the /refiner_rt/lost "
                   "topic). 2.5 is the value chosen on rendered video (refiner_rt.tracker.LOST_DEG). Default: no "
                   "check.")
@click.option("--reinit", is_flag=True,
              help="With --lost-deg: re-initialise a flagged object that has no detector \"q\" in the frame from a "
                   "rotation search on its box (the pose estimator's, the track's own rotation one of the starts; "
                   "RefinerTracker(reinit=True), docs/tracking.md). Costs nothing on objects not flagged.")
@click.option("--detector-weight", type=click.FloatRange(0.0, 1.0, min_open=True), default=None,
              help="Fuse a tracked object's later detector poses (\"q\") instead of restarting from them: refine each "
                   "beside the track and keep the rotation this share of the way to it (0.5: the weight measured "
                   "best on rendered video, benchmarks/RESULTS.md; one more pass per pose, N with --views N). With "
                   "--bag, the detections' poses (--mode track). Not with --lost-deg. Default: a \"q\" re-initialises "
                   "the object.")
@click.option("--iterations", type=click.IntRange(1, MAX_ITERATIONS), default=1, show_default=True,
              help="Refinement passes per object and frame.")
@click.option("--views", type=click.IntRange(1, MAX_VIEWS), default=1, show_default=True,
              help="Box-jittered crops each refiner averages per object and frame, one network pass each: 4 took "
                   "the shipped refiners from 5.67 to 4.93 degrees on real YCB-Video frames (README, \"Below the "
                   "floor\"). Not with --cascade, which averages its own.")
@click.option("--starts", type=click.Choice([str(n) for n in STARTS]), default="1", show_default=True,
              help="Refinements averaged per object and frame: the last rotation alone (1), or with 4 or 8 rotations "
                   "turned 15 degrees from it, each on its own box jitter (RefinerTracker(starts=N), "
                   "docs/tracking.md): with 5, tracks without a detector were 3.58 degrees off on the real dev "
                   "videos against 4.78 for per-frame refinement (4.12 against 4.02 on held-out renders), at five "
                   "network passes. Not with --cascade.")
@click.option("--settle-deg", type=click.FloatRange(0.0, 180.0, min_open=True, max_open=True), default=None, metavar="DEG",
              help="For detector poses that may be more than 30 degrees off: each refinement runs a second coarse "
                   "pass, kept where it turns the result by more than DEG (2: the value measured on renders, "
                   "README \"Coarse poses far off\"); with --iterations N, N passes. Default: off.")
@click.option("--threads", type=click.IntRange(1, 256), default=1, show_default=True,
              help="Threads each network runs on.")
@click.option("--video", "video_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the frames annotated with each object's outline at its refined rotation (and the detector's "
                   "input), its label and score, and a legend: a .mp4/.avi video or a .png/.jpg "
                   "strip of --strip frames.")
@click.option("--strip", "strip_frames", type=click.IntRange(1, 64), default=8, show_default=True,
              help="Frames in a --video image strip, evenly spaced.")
@click.option("--fps", type=click.FloatRange(min=0.1), default=15.0, show_default=True, help="Frame rate of --video.")
def track_cmd(frames, detections, out_path, bag, mode, cascade, rectified, image_topic, info_topic, detections_topic,
              sync_tolerance_ms, identity_is_pose, estimate_missing, class_map, models, fp32, K_text, predict,
              scene_motion, lost_deg, reinit,
              detector_weight, iterations, views, starts, settle_deg, threads, video_path, strip_frames, fps):
    """Track object rotations through a folder of frames (FRAMES, file-name order) from a DETECTIONS file.

    DETECTIONS is JSON: {"K": [[fx,0,cx],[0,fy,cy],[0,0,1]], "frames": {"<image file>": {"<object id>": [x1,y1,x2,y2]
    or {"box": [...], "q": [w,x,y,z]}}}}. A "q" (a detector's coarse rotation) starts or re-initialises an object;
    later frames refine from the previous frame's result. Object ids are YCB ids, "#<n>" telling instances apart.
    Quaternions wxyz object-to-camera, boxes in pixels.
    """
    from refiner_rt.tracker import RefinerTracker

    if predict and scene_motion:
        raise click.UsageError("--predict (each object's own velocity) and --scene-motion (the camera's turn, shared by "
                               "still objects) are two predictions; choose one")
    prediction = "scene" if scene_motion else predict  # RefinerTracker(predict=...)
    if views != 1 and cascade:
        raise click.UsageError("--views is for single refiners; --cascade averages its own views (four for each of "
                               "its refiners): give one of them")

    starts = int(starts)
    if starts != 1 and cascade:
        raise click.UsageError("--starts is for single refiners; --cascade refines each frame from the last rotation "
                               "with its own views: give one of them")
    if reinit and lost_deg is None:
        raise click.UsageError("--reinit re-initialises the tracks the loss-of-track check flags: give --lost-deg "
                               "too (2.5, refiner_rt.tracker.LOST_DEG)")
    if lost_deg is not None and detector_weight is not None:
        raise click.UsageError("--lost-deg and --detector-weight are two uses of the detections' \"q\" (restart a "
                               "lost track, or fuse every pose); give one")
    bag_only = {"--mode": mode != "track", "--rectified": rectified,
                "--image-topic": image_topic, "--info-topic": info_topic, "--detections-topic": detections_topic,
                "--sync-tolerance-ms": sync_tolerance_ms is not None, "--identity-is-pose": identity_is_pose,
                "--estimate-missing": estimate_missing, "--class-map": class_map}
    if bag is not None:
        if frames is not None or detections is not None:
            raise click.UsageError("give either --bag BAG or FRAMES DETECTIONS, not both")
        # what a bag gives instead of each option of the frames path
        instead = {"--K": (K_text, "the bag's CameraInfo gives the camera"),
                   "--video": (video_path, "the output bag has the overlay, /refiner_rt/overlay/compressed"),
                   "--model": (models, "each object's shipped model refines it"),
                   "--iterations": (iterations != 1, "one pass per object and frame; --settle-deg adds a second")}
        unused = [f"{flag} ({why})" for flag, (value, why) in instead.items() if value]
        if unused:
            raise click.UsageError(f"not with --bag, only with FRAMES DETECTIONS: {'; '.join(unused)}")
        return _track_bag(bag, out_path, mode, cascade, rectified, image_topic, info_topic, detections_topic,
                          class_map, fp32, prediction, lost_deg, threads, settle_deg, views, detector_weight,
                          sync_tolerance_ms, identity_is_pose, estimate_missing, reinit, starts)
    if frames is None or detections is None:
        raise click.UsageError("give FRAMES and DETECTIONS (a folder of images and a detections file), or --bag BAG")
    used = [flag for flag, value in bag_only.items() if value]
    if used:
        raise click.UsageError(f"{', '.join(used)} {'applies' if len(used) == 1 else 'apply'} to --bag only")
    if out_path.suffix.lower() != ".json":
        raise click.BadParameter(f"expected a .json file for the rotations (a video or image strip goes to --video); "
                                 f"got {out_path.name!r}", param_hint="'-o' / '--out'")
    try:
        K, dets = read_detections(detections)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    if K_text is not None:
        try:
            fx, fy, cx, cy = (float(v) for v in K_text.split(","))
        except ValueError:
            raise click.BadParameter(f"expected four numbers FX,FY,CX,CY; got {K_text!r}", param_hint="'--K'") from None
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if K is None:
        raise click.UsageError("no camera intrinsics: give \"K\" in the detections file or --K FX,FY,CX,CY")
    files = frame_files(frames)
    if not files:
        raise click.ClickException(f"{frames}: no .png or .jpg frames")
    unknown = sorted(set(dets) - {p.name for p in files})
    if unknown:
        raise click.ClickException(f"{detections}: frames {unknown[:5]} are not images in {frames}")
    object_ids = sorted({o for d in dets.values() for o in d})
    try:
        sessions = _sessions(object_ids, models, int8=not fp32, threads=threads)
        refiners = _cascades(sessions, int8=not fp32, threads=threads, settle_deg=settle_deg) if cascade else sessions
        if settle_deg is not None:
            iterations = max(iterations, 2)
        tracker = RefinerTracker(refiners, K, {}, predict=prediction, iterations=iterations, views=views,
                                 starts=starts, lost_deg=lost_deg, detector_weight=detector_weight,
                                 settle_deg=settle_deg, reinit=reinit)
    except (ValueError, TypeError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None

    prepare_output(out_path, "'-o' / '--out'")  # once the inputs are read: a refused run leaves no folder behind
    video = _VideoOutput(video_path, len(files), strip_frames, fps) if video_path else None
    if video is not None:
        prepare_output(video_path, "'--video'")
    results, scores, lost, reinitialised, refined, seconds = {}, {}, {}, {}, 0, 0.0
    for index, path in enumerate(files):
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise click.ClickException(f"{path}: OpenCV cannot read this image")
        frame_dets = dets.get(path.name, {})
        t0 = time.perf_counter()
        try:
            for object_id, det in frame_dets.items():
                if det["q"] is None and object_id not in tracker:
                    raise ValueError(f"{object_id!r} has a box but no rotation to start from: give its first "
                                     f"detection as {{\"box\": [...], \"q\": [w, x, y, z]}}")
            boxes = {o: d["box"] for o, d in frame_dets.items()}
            out = tracker.update_from_detector(image, boxes, {o: d["q"] for o, d in frame_dets.items()
                                                              if d["q"] is not None})
        except (ValueError, TypeError) as exc:
            raise click.ClickException(f"{path.name}: {exc}") from None
        seconds += time.perf_counter() - t0
        refined += len(out)
        results[path.name] = {o: [round(v, 9) for v in q.tolist()] for o, q in out.items()}
        scores[path.name] = {o: round(float(tracker.scores[o]), 4) for o in out if o in tracker.scores}
        if tracker.lost:
            lost[path.name] = list(tracker.lost)
        if tracker.reinitialised:
            reinitialised[path.name] = list(tracker.reinitialised)
        if video is not None:
            video.add(index, annotate(image, K, [
                draw.PoseOverlay(o, np.asarray(boxes[o], dtype=np.float64), q, q_input=frame_dets[o]["q"],
                                 lost=o in tracker.lost, score=tracker.scores.get(o)) for o, q in out.items()]))
    if video is not None:
        video.close()
    out_path.write_text(json.dumps({
        "format": OUTPUT_FORMAT,
        "conventions": "quaternions wxyz (scalar first, Hamilton), object-to-camera; boxes x1,y1,x2,y2 pixels",
        "K": K.tolist(), "predict": predict, "scene_motion": scene_motion, "iterations": iterations,
        "views": None if cascade else views, "starts": starts, "settle_deg": settle_deg, "lost_deg": lost_deg,
        "reinit": reinit, "reinits": tracker.reinits,  # tracks re-initialised by the search on their box, in all
        "detector_weight": detector_weight,
        "models": {o: str(s.model_path) if s.model_path else "<bytes>" for o, s in sessions.items()},
        "cascade": {o: str(r.fine.model_path) for o, r in refiners.items() if r is not sessions[o]},
        "frames": results,
        "scores": scores,  # frame -> object -> RefineResult.score of its refinement there (docs/tracking.md)
        "lost": lost,  # frame -> objects the loss-of-track check flagged there (docs/tracking.md; empty without --lost-deg)
        "reinitialised": reinitialised,  # frame -> objects the search on their box gave a new start there (--reinit)
    }, indent=1))
    per_frame = 1e3 * seconds / len(files)
    click.echo(f"{len(files)} frames, {len(object_ids)} objects, {refined} refinements: {per_frame:.2f} ms per frame "
               f"(tracker only, image reading excluded) -> {out_path}" + (f", {video_path}" if video_path else ""))


def _track_bag(bag, out_path, mode, cascade, rectified, image_topic, info_topic, detections_topic, class_map, fp32,
               predict, lost_deg, threads, settle_deg, views, detector_weight=None, sync_tolerance_ms=None,
               identity_is_pose=False, estimate_missing=False, reinit=False, starts=1):
    """``track --bag``: :func:`refiner_rt.rosbag.refine_bag` with a progress bar and one-line errors; approximate
    stamp matches and lost tracks are reported on stderr."""
    from refiner_rt.ros import RosRefiner

    try:
        from refiner_rt.rosbag import SYNC_TOLERANCE_MS, refine_bag
        mapping = None
        if class_map is not None:
            try:
                mapping = json.loads(class_map.read_text())
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise ValueError(f"{class_map}: not a readable JSON object ({exc})") from None
            if not isinstance(mapping, dict) or not all(isinstance(v, str) for v in mapping.values()):
                raise ValueError(f"{class_map}: expected a JSON object {{detector class id: YCB id}}")
        extra = {k: v for k, v in {"predict": predict, "lost_deg": lost_deg, "reinit": reinit,
                                   "detector_weight": detector_weight, "starts": starts != 1 and starts}.items() if v}
        if extra and mode != "track":
            flags = ["--scene-motion" if k == "predict" and v == "scene" else "--" + k.replace("_", "-")
                     for k, v in extra.items()]
            raise click.UsageError(f"{', '.join(flags)} apply to --mode track")
        refiner = RosRefiner(mode, cascade=cascade, rectified=rectified, class_map=mapping, int8=not fp32,
                             identity_is_pose=identity_is_pose, estimate_missing=estimate_missing,
                             settle_deg=settle_deg, views=views, threads=threads,
                             **extra)
        prepare_output(out_path, "'-o' / '--out'")  # once the options are checked: a refused run leaves no folder
        tolerance = SYNC_TOLERANCE_MS if sync_tolerance_ms is None else sync_tolerance_ms
        t0 = time.perf_counter()
        with _LazyBar("frames") as bar:
            summary = refine_bag(bag, out_path, refiner, image_topic=image_topic, info_topic=info_topic,
                                 detections_topic=detections_topic, sync_tolerance_ms=tolerance, total=bar.start,
                                 progress=bar.update)
    except ModuleNotFoundError as exc:
        raise click.ClickException(str(exc) if exc.name == "rosbags" else f"needs {exc.name!r}") from None
    except (ValueError, TypeError, FileExistsError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    except Exception as exc:  # rosbags' own errors (a damaged bag, an unknown message type): named, one line
        if type(exc).__module__.startswith("rosbags"):
            raise click.ClickException(f"{bag}: {type(exc).__name__}: {exc}") from None
        raise
    skipped = f"; skipped detections: {summary.skipped}" if summary.skipped else ""
    if summary.approximate:
        click.echo(f"warning: {summary.approximate} of {summary.frames_with_detections} images matched detections "
                   f"stamped up to {summary.max_offset_ms:.3f} ms apart (approximate sync within {tolerance:g} ms)",
                   err=True)
    if summary.unmatched_detections:
        click.echo(f"warning: {summary.unmatched_detections} of {summary.detection_messages} detection messages "
                   f"matched no image within {tolerance:g} ms", err=True)
    if summary.lost:
        click.echo(f"lost (the loss-of-track check, frames per instance; on /refiner_rt/lost): {summary.lost}",
                   err=True)
    if summary.reinitialised:
        click.echo(f"re-initialised (--reinit: the search on the box, frames per instance): {summary.reinitialised}",
                   err=True)
    click.echo(f"{summary.images} images ({summary.image_topic}), {summary.frames_with_detections} with detections "
               f"({summary.detections_topic}), {summary.poses} poses of {len(summary.objects)} objects in "
               f"{time.perf_counter() - t0:.1f} s -> {out_path} (topics: {', '.join(summary.output_topics)}){skipped}")


class _LazyBar:
    """A click progress bar on stderr whose length is known only once work starts (``start(n)``); on a terminal
    only (elsewhere click would print its bare label)."""

    def __init__(self, label: str):
        self.label, self.bar = label, None

    def start(self, n: int) -> None:
        if sys.stderr.isatty():
            self.bar = click.progressbar(length=n, label=self.label, file=sys.stderr)
            self.bar.__enter__()

    def update(self, k: int) -> None:
        if self.bar is not None:
            self.bar.update(k)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.__exit__(*exc)
        return False
