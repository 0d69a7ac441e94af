"""What ``refiner-rt demo`` computes: the shipped refiners on the sample frames, and the picture of the result.

The sample frames (``refiner_rt/samples/``, package data) are rendered scenes that no shipped model trained on, with
ground truth; ``benchmarks/demo_samples.py`` wrote them. For every object instance a coarse rotation is drawn
``U(0, 30)`` degrees around the truth (``q_in = q_gt * q_noise``, the paper's protocol, docs/design.md §1), refined
by the object's shipped model with the camera intrinsics, and compared with the truth (geodesic angle, degrees).

Conventions: quaternions ``wxyz`` (Hamilton), rotations object to camera, boxes ``(x1, y1, x2, y2)`` pixels,
images ``H x W x 3`` uint8 BGR, translations in metres, angles in degrees. The samples' object frame is the YCB
google_16k scan frame, the frame the shipped models were trained in.
"""

from __future__ import annotations

import json
import logging
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from refiner_rt import draw
from refiner_rt import quaternion as rq
from refiner_rt.placement import fit_translation

__all__ = ["SAMPLES_DIR", "SampleObject", "SampleFrame", "Outline", "Refinement", "load_samples", "load_outlines",
           "coarse_rotations", "refine_samples", "demo_picture", "image_picture", "COLOURS"]

logger = logging.getLogger(__name__)

SAMPLES_DIR = Path(__file__).resolve().parent / "samples"
SAMPLES_FORMAT = "refiner-rt/samples/1"
OUTLINES_FORMAT = "refiner-rt/outlines/1"
NOISE_DEG = (0.0, 30.0)  # the range the shipped models were trained and evaluated on
TIMED_CALLS = 20  # refine() calls timed per instance (after one warm-up call per model); the median is reported

# BGR colours of the picture: the truth, the coarse input and the refined rotation. Cyan and green, not red: many
# YCB objects are red or yellow. Every line has a dark halo (refiner_rt.draw.HALO), and each pose's axes are drawn in
# its own colour with x, y, z at their tips, so no axis colour is confused with an outline.
COLOURS = draw.POSE_COLOURS
PANEL = 192  # side of one view of an object in the picture (pixels); a tile shows two, coarse and refined
TILE_CONTEXT = 1.7  # the views' window around the box: wider than the crop rule's 1.2, so a coarse outline fits


@dataclass(frozen=True)
class SampleObject:
    """One object instance of a sample frame: YCB id, visible box, ground-truth rotation and translation."""

    object_id: str
    box_xyxy: np.ndarray  # (4,) x1, y1, x2, y2 in pixels
    q_gt: np.ndarray  # (4,) wxyz, object to camera
    t_m: np.ndarray  # (3,) metres, object origin in the camera frame
    visib_fract: float


@dataclass(frozen=True)
class SampleFrame:
    """A sample frame: its JPEG file, intrinsics ``K`` (3x3, pixels) and object instances."""

    path: Path
    K: np.ndarray
    objects: tuple[SampleObject, ...]

    def image(self) -> np.ndarray:
        """The frame, ``H x W x 3`` uint8 BGR."""
        img = cv2.imread(str(self.path), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"{self.path}: not a readable image")
        return img


@dataclass(frozen=True)
class Outline:
    """Surface points of an object (metres, YCB scan frame) and their typical spacing (metres), for drawing."""

    points_m: np.ndarray  # (N, 3)
    spacing_m: float

    @property
    def centroid_m(self) -> np.ndarray:
        return self.points_m.mean(axis=0)


@dataclass(frozen=True)
class Refinement:
    """One refined instance: inputs, result, errors against the truth (degrees) and time per ``refine()`` call."""

    frame: int  # index into the frames given
    instance: int  # index into that frame's objects
    object_id: str
    q_gt: np.ndarray
    q_in: np.ndarray
    q_refined: np.ndarray
    input_error_deg: float
    refined_error_deg: float
    ms_per_refinement: float


def load_samples(folder: Path = SAMPLES_DIR) -> list[SampleFrame]:
    """The sample frames listed in ``folder/samples.json``.

    Raises:
        FileNotFoundError: the folder has no ``samples.json``.
        ValueError: the file is of another format.
    """
    path = Path(folder) / "samples.json"
    if not path.is_file():
        raise FileNotFoundError(f"no sample frames: {path} is missing")
    doc = json.loads(path.read_text())
    if doc.get("format") != SAMPLES_FORMAT:
        raise ValueError(f"{path}: format {doc.get('format')!r} is not {SAMPLES_FORMAT!r}")
    frames = []
    for f in doc["frames"]:
        objects = tuple(SampleObject(o["object_id"], np.asarray(o["box_xyxy"], dtype=np.float64),
                                     rq.canonical(np.asarray(o["q_gt_wxyz"], dtype=np.float64)),
                                     np.asarray(o["t_m"], dtype=np.float64), float(o["visib_fract"]))
                        for o in f["objects"])
        frames.append(SampleFrame(Path(folder) / f["file"], np.asarray(f["K"], dtype=np.float64), objects))
    return frames


def load_outlines(folder: Path = SAMPLES_DIR) -> dict[str, Outline]:
    """Outline points per YCB id from ``folder/outlines.json`` (empty when the file is missing)."""
    path = Path(folder) / "outlines.json"
    if not path.is_file():
        return {}
    doc = json.loads(path.read_text())
    if doc.get("format") != OUTLINES_FORMAT:
        raise ValueError(f"{path}: format {doc.get('format')!r} is not {OUTLINES_FORMAT!r}")
    return {obj: Outline(np.asarray(o["points_mm"], dtype=np.float64) / 1000.0, o["spacing_mm"] / 1000.0)
            for obj, o in doc["objects"].items()}


def coarse_rotations(frames: list[SampleFrame], seed: int) -> list[np.ndarray]:
    """Per frame, ``(N, 4)`` coarse rotations ``q_gt * q_noise`` with angles ``U(0, 30)`` degrees about uniform axes.

    One noise draw per instance of every frame, in file order, whether or not its object has a model, so an
    instance's coarse rotation depends only on ``seed``, not on which models ship."""
    rng = np.random.default_rng(seed)
    out = []
    for f in frames:
        q_gt = np.array([o.q_gt for o in f.objects]).reshape(-1, 4)
        noise = rq.sample_rotation_noise(len(f.objects), "uniform", *NOISE_DEG, rng=rng)
        out.append(rq.canonical(rq.multiply(q_gt, noise)))
    return out


def refine_samples(frames: list[SampleFrame], sessions: dict, seed: int = 0,
                   timed_calls: int = TIMED_CALLS) -> list[Refinement]:
    """Refine every instance whose object has a session (``{ycb id: RefinerSession}``), one box per call, with ``K``.

    Time per refinement: the median of ``timed_calls`` calls of ``refine()`` on that instance (crop, network and
    composition; batch 1), after one untimed call per session.
    """
    warm = set()
    out = []
    for i, (frame, q_in_all) in enumerate(zip(frames, coarse_rotations(frames, seed))):
        image = frame.image()
        for k, (obj, q_in) in enumerate(zip(frame.objects, q_in_all)):
            sess = sessions.get(obj.object_id)
            if sess is None:
                continue
            box, q = obj.box_xyxy[None], q_in[None]
            if obj.object_id not in warm:
                sess.refine(image, box, q, K=frame.K)
                warm.add(obj.object_id)
            times = []
            for _ in range(max(1, timed_calls)):
                t0 = time.perf_counter()
                res = sess.refine(image, box, q, K=frame.K)
                times.append(time.perf_counter() - t0)
            q_ref = res.q_refined[0]
            out.append(Refinement(i, k, obj.object_id, obj.q_gt, q_in, q_ref,
                                  float(rq.geodesic_angle(q_in, obj.q_gt)), float(rq.geodesic_angle(q_ref, obj.q_gt)),
                                  1000.0 * statistics.median(times)))
    return out


def _pose_drawing(view, to_view, K, obj: SampleObject, outline: Outline | None, q, colour, scale: float) -> None:
    """Draw the truth (white outline, thin axes) and rotation ``q`` (outline in ``colour``, thick axes) on ``view``."""
    R_gt = rq.to_matrix(obj.q_gt)
    if outline is None:  # no outline points for this object: axes only, about the view's centre
        draw.draw_axes(view, (view.shape[1] / 2, view.shape[0] / 2), R_gt, view.shape[0] / 4, 1, COLOURS["truth"])
        draw.draw_axes(view, (view.shape[1] / 2, view.shape[0] / 2), rq.to_matrix(q), view.shape[0] / 4, 2, colour,
                       labels=True)
        return
    c = outline.centroid_m
    centre_z = float((R_gt @ c + obj.t_m)[2])
    radius = 0.6 * outline.spacing_m * K[0, 0] / centre_z * scale
    length = 0.4 * float(np.max(outline.points_m.max(axis=0) - outline.points_m.min(axis=0)))
    for R, line_colour, width in ((R_gt, COLOURS["truth"], 1), (rq.to_matrix(q), colour, 2)):
        t = draw.centroid_translation(c, R_gt, obj.t_m, R)
        uv, z = draw.project(outline.points_m, R, t, K)
        draw.draw_outline(view, to_view(uv), z, radius, line_colour, width)
    for R, width, axis_colour in ((R_gt, 1, COLOURS["truth"]), (rq.to_matrix(q), 2, colour)):
        t = draw.centroid_translation(c, R_gt, obj.t_m, R)
        uv, _ = draw.project(np.vstack([c, c + length * np.eye(3)]), R, t, K)
        draw.draw_axes_projected(view, to_view(uv[:1])[0], to_view(uv[1:]), width, axis_colour, labels=width == 2)


def _tile(image: np.ndarray, K: np.ndarray, obj: SampleObject, r: Refinement, outline: Outline | None) -> np.ndarray:
    """One object's tile: the window around its box twice, the coarse rotation against the truth on the left and
    the refined one on the right, with a caption."""
    base, to_view = draw.crop_view(image, obj.box_xyxy, PANEL, TILE_CONTEXT)
    scale = PANEL / (TILE_CONTEXT * max(obj.box_xyxy[2] - obj.box_xyxy[0], obj.box_xyxy[3] - obj.box_xyxy[1]))
    panels = []
    for name, q, err in (("coarse", r.q_in, r.input_error_deg), ("refined", r.q_refined, r.refined_error_deg)):
        view = base.copy()
        _pose_drawing(view, to_view, K, obj, outline, q, COLOURS[name], scale)
        band = np.full((20, PANEL, 3), 24, np.uint8)
        cv2.putText(band, f"{name}: {err:.1f} deg", (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, COLOURS[name], 1,
                    cv2.LINE_AA)
        view = np.vstack([view, band])
        panels.append(view)
    panels.insert(1, np.full((panels[0].shape[0], 2, 3), 24, np.uint8))
    caption = np.full((22, 2 * PANEL + 2, 3), 24, np.uint8)
    cv2.putText(caption, obj.object_id, (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (230, 230, 230), 1, cv2.LINE_AA)
    return np.vstack([caption, np.hstack(panels)])


def demo_picture(frames: list[SampleFrame], refinements: list[Refinement], outlines: dict[str, Outline],
                 columns: int = 3) -> np.ndarray:
    """The demo's picture (BGR): one tile per object, its most visible refined instance, with a legend on top."""
    best: dict[str, tuple] = {}
    images: dict[int, np.ndarray] = {}
    for r in refinements:
        obj = frames[r.frame].objects[r.instance]
        key = (obj.visib_fract, float(np.prod(obj.box_xyxy[2:] - obj.box_xyxy[:2])))
        if r.object_id not in best or key > best[r.object_id][0]:
            best[r.object_id] = (key, obj, r)
    tiles = []
    for obj_id in sorted(best):
        _, obj, r = best[obj_id]
        if r.frame not in images:
            images[r.frame] = frames[r.frame].image()
        tiles.append(_tile(images[r.frame], frames[r.frame].K, obj, r, outlines.get(obj_id)))
    if not tiles:
        raise ValueError("nothing to draw: no refinements")
    columns = min(columns, len(tiles))
    rows = -(-len(tiles) // columns)
    gap = np.full((tiles[0].shape[0], 6, 3), 24, np.uint8)
    blank = np.full_like(tiles[0], 24)
    padded = tiles + [blank] * (rows * columns - len(tiles))
    grid = [np.hstack([x for t in padded[k * columns:(k + 1) * columns] for x in (t, gap)][:-1]) for k in range(rows)]
    header = legend(grid[0].shape[1], {"truth": "ground truth (thin)",
                                         "coarse": "coarse input, U(0, 30) deg around the truth",
                                         "refined": "refined by the shipped model"})
    return np.vstack([header, *grid])


def legend(width: int, items: dict) -> np.ndarray:
    """A dark band ``width`` pixels wide naming each pose's colour (``{"truth" | "coarse" | "refined": text}``) and
    saying how the axes are drawn."""
    band = np.full((34, width, 3), 24, np.uint8)
    x = 8
    for name, text in [*items.items(), (None, "axes: outline colour, x, y, z at the tips")]:
        if name is not None:
            cv2.line(band, (x, 17), (x + 22, 17), COLOURS[name], 2, cv2.LINE_AA)
        else:
            x -= 28
        cv2.putText(band, text, (x + 28, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.48, (230, 230, 230), 1, cv2.LINE_AA)
        x += 40 + int(cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.48, 1)[0][0])
    return band


def image_picture(image: np.ndarray, K: np.ndarray, box_xyxy, q_in: np.ndarray, q_refined: np.ndarray,
                  outline: Outline | None, object_id: str = "") -> np.ndarray:
    """A user's image (BGR) with the box, and the coarse and refined rotations drawn as outlines with axes, under a
    legend band, placed on the box by :func:`refiner_rt.placement.fit_translation` (the refiner estimates rotation
    only; the points fitted: :func:`refiner_rt.draw.placement_points` of ``object_id``), or as axes alone without an
    outline for the object."""
    canvas = image.copy()
    x1, y1, x2, y2 = (float(v) for v in box_xyxy)
    cv2.rectangle(canvas, (int(round(x1)), int(round(y1))), (int(round(x2)) - 1, int(round(y2)) - 1), (200, 200, 200),
                  1)
    side = max(x2 - x1, y2 - y1)
    for name, q in (("coarse", q_in), ("refined", q_refined)):
        R = rq.to_matrix(q)
        if outline is not None:
            t = fit_translation(R, draw.placement_points(object_id, outline), box_xyxy, K, image.shape[:2])
            uv, z = draw.project(outline.points_m, R, t, K)
            radius = 0.6 * outline.spacing_m * K[0, 0] / float((R @ outline.centroid_m + t)[2])
            draw.draw_outline(canvas, uv, z, radius, COLOURS[name], 2)
            c = outline.centroid_m
            length = 0.4 * float(np.max(outline.points_m.max(axis=0) - outline.points_m.min(axis=0)))
            uv, _ = draw.project(np.vstack([c, c + length * np.eye(3)]), R, t, K)
            draw.draw_axes_projected(canvas, uv[0], uv[1:], 2, COLOURS[name], labels=True)
        else:
            draw.draw_axes(canvas, (0.5 * (x1 + x2) - 0.5, 0.5 * (y1 + y2) - 0.5), R, 0.4 * side, 2, COLOURS[name],
                           labels=True)
    band = legend(max(canvas.shape[1], 560), {"coarse": "coarse input", "refined": "refined by the shipped model"})
    if band.shape[1] > canvas.shape[1]:  # a narrow image: the legend keeps its width, the image is padded
        canvas = cv2.copyMakeBorder(canvas, 0, 0, 0, band.shape[1] - canvas.shape[1], cv2.BORDER_CONSTANT, value=(24, 24, 24))
    return np.vstack([band, canvas])
