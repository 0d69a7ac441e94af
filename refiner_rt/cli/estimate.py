"""``refiner-rt estimate``: 6D poses (rotation and translation) from images and 2D boxes (torch-free).

For each box, :class:`refiner_rt.estimate.PoseEstimator` of its object finds the rotation from the crop alone and the
translation from the box, ``K`` and the object's shipped surface points (or from a depth image). Output: JSON with
``R`` (row-major 3x3, object to camera), ``q_wxyz``, ``t_m`` (metres, the shipped models' object frame, the YCB
google_16k scan frame) and ``score`` per box; optionally a picture with each pose drawn as an outline.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import click
import cv2
import numpy as np

from refiner_rt.cli import check_picture_path, prepare_output, write_picture
from refiner_rt.cli.demo import numbers_callback

__all__ = ["estimate_cmd", "read_depth"]


def read_depth(path: Path, shape: tuple[int, int], mm_per_unit: float) -> np.ndarray:
    """A depth image as ``H x W`` float32 metres: a 16-bit PNG or an integer ``.npy`` in sensor units
    (``mm_per_unit`` millimetres each), or a float ``.npy`` already in metres.

    Raises:
        click.BadParameter: unreadable, not one channel, or not the colour image's size.
    """
    if path.suffix.lower() == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise click.BadParameter(f"{path}: not a readable .npy array ({exc})", param_hint="'--depth'") from None
    else:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise click.BadParameter(f"{path}: not an image OpenCV can read", param_hint="'--depth'")
    if raw.ndim != 2 or raw.shape != tuple(shape):
        raise click.BadParameter(f"{path}: expected one channel of the colour image's size {shape[0]}x{shape[1]}; "
                                 f"got shape {raw.shape}", param_hint="'--depth'")
    if raw.dtype.kind == "f":
        return raw.astype(np.float32)
    if raw.dtype.kind not in "iu":
        raise click.BadParameter(f"{path}: expected integer millimetres or float metres; got dtype {raw.dtype}",
                                 param_hint="'--depth'")
    return raw.astype(np.float32) * np.float32(mm_per_unit / 1000.0)


def _detections(detections_path: Path | None, images: tuple[Path, ...], object_id, boxes) -> dict:
    """``{image index: [(object, box (4,)), ...]}`` from ``--detections`` or from ``--object`` and ``--box``."""
    if detections_path is None:
        if object_id is None or not boxes:
            raise click.UsageError("give --object and at least one --box (or --detections FILE.json)")
        return {i: [(object_id, b) for b in boxes] for i in range(len(images))}
    if object_id is not None or boxes:
        raise click.UsageError("--detections replaces --object and --box: give one or the other")
    try:
        doc = json.loads(detections_path.read_text())
    except (OSError, ValueError) as exc:
        raise click.BadParameter(f"{detections_path}: not readable JSON ({exc})", param_hint="'--detections'") from None
    if not isinstance(doc, dict):
        raise click.BadParameter(f"{detections_path}: expected an object {{image file name: [{{\"object\": ID, "
                                 "\"box\": [x1, y1, x2, y2]}, ...]}}", param_hint="'--detections'")
    out = {}
    for i, image in enumerate(images):
        entries = doc.get(image.name, [])
        rows = []
        for k, e in enumerate(entries):
            box = np.asarray(e.get("box", []) if isinstance(e, dict) else [], dtype=np.float64)
            if not isinstance(e, dict) or not isinstance(e.get("object"), str) or box.shape != (4,):
                raise click.BadParameter(f"{detections_path}: {image.name}[{k}] must be {{\"object\": ID, \"box\": "
                                         f"[x1, y1, x2, y2]}}; got {e!r}", param_hint="'--detections'")
            rows.append((e["object"], box))
        out[i] = rows
    stray = sorted(set(doc) - {image.name for image in images})
    if stray:  # a key that names no given image: a typo or another folder's file, said rather than ignored
        click.echo(f"Warning: {detections_path}: no image given for {', '.join(map(repr, stray[:5]))}"
                   f"{' ...' if len(stray) > 5 else ''} (its keys are image file names)", err=True)
    return out


def _picture(image: np.ndarray, K: np.ndarray, poses: list[dict]) -> np.ndarray:
    """The image with each box (grey) and each pose's outline and axes (green)."""
    from refiner_rt import draw
    from refiner_rt.demo import load_outlines

    outlines = load_outlines()
    canvas = image.copy()
    for p in poses:
        x1, y1, x2, y2 = p["box_xyxy"]
        cv2.rectangle(canvas, (int(round(x1)), int(round(y1))), (int(round(x2)) - 1, int(round(y2)) - 1),
                      (200, 200, 200), 1)
        outline = outlines.get(p["object"])
        R, t = np.asarray(p["R"]), np.asarray(p["t_m"])
        if outline is None or t[2] <= 0:
            continue
        uv, z = draw.project(outline.points_m, R, t, K)
        radius = 0.6 * outline.spacing_m * K[0, 0] / float((R @ outline.centroid_m + t)[2])
        draw.draw_outline(canvas, uv, z, radius, draw.POSE_COLOURS["refined"], 2)
        c = outline.centroid_m
        length = 0.4 * float(np.max(outline.points_m.max(axis=0) - outline.points_m.min(axis=0)))
        uv, _ = draw.project(np.vstack([c, c + length * np.eye(3)]), R, t, K)
        draw.draw_axes_projected(canvas, uv[0], uv[1:], 2, labels=True)
    return canvas


@click.command("estimate")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--K", "K", required=True, callback=numbers_callback(4, "fx,fy,cx,cy", positive=(0, 1)), metavar="FX,FY,CX,CY",
              help="The camera intrinsics in pixels (OpenCV's pixel centres).")
@click.option("--object", "object_id", metavar="YCB_ID", help="The object in every --box, e.g. 003_cracker_box.")
@click.option("--box", "boxes", multiple=True, callback=lambda c, p, v: [numbers_callback(4, "x1,y1,x2,y2")(c, p, b) for b in v],
              metavar="X1,Y1,X2,Y2", help="A box in pixels (repeat for several); the same boxes in every image.")
@click.option("--detections", "detections_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help='Instead of --object/--box: JSON {"<image file name>": [{"object": ID, "box": [x1, y1, x2, y2]}]}.')
@click.option("--depth", "depths", multiple=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="A depth image registered to the colour image, one per image in order: 16-bit PNG or integer "
                   ".npy in --depth-unit-mm, or float .npy in metres.")
@click.option("--depth-unit-mm", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True,
              help="Millimetres per unit of an integer depth image (YCB-Video's PNGs: 0.1).")
@click.option("--out", "-o", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the JSON here (default: print it).")
@click.option("--overlay", type=click.Path(dir_okay=False, path_type=Path),
              help="Write a picture of the poses (PNG); with several images, one per image: NAME_<image stem>.png.")
@click.option("--hypotheses", type=click.IntRange(1, 1024), default=None,
              help="Rotations tried per box (default: the estimator's, chosen on rendered scenes).")
@click.option("--threads", type=click.IntRange(0), default=1, show_default=True, help="Threads per model (0: every core).")
def estimate_cmd(images, K, object_id, boxes, detections_path, depths, depth_unit_mm, out, overlay, hypotheses, threads):
    """Estimate the 6D pose of the object in each box, from the image alone (or with depth).

    No coarse rotation is needed: rotations spread over every orientation are refined by the object's shipped
    refiners and ranked (docs/pose6d.md). The translation comes from the box, K and the object's size, or from
    --depth. Prints (or writes with --out) JSON: per image, per box, R (3x3 row-major, object to camera), q_wxyz,
    t_m (metres, the shipped models' object frame: the YCB google_16k scan frame) and score (0-1, higher is
    better; it orders poses and is not a probability).
    """
    from refiner_rt import quaternion as rq
    from refiner_rt.estimate import PoseEstimator
    from refiner_rt.pretrained import pretrained_models

    if depths and len(depths) != len(images):
        raise click.UsageError(f"--depth given {len(depths)} time{'s' if len(depths) != 1 else ''} for {len(images)} images: one per image, in order")
    if overlay is not None:
        check_picture_path(overlay)
    K3 = np.array([[K[0], 0.0, K[2]], [0.0, K[1], K[3]], [0.0, 0.0, 1.0]])
    wanted = _detections(detections_path, images, object_id, boxes)
    shipped = sorted(m.object_id for m in pretrained_models())
    unknown = sorted({o for rows in wanted.values() for o, _ in rows} - set(shipped))
    if unknown:
        raise click.BadParameter(f"no shipped model for {', '.join(map(repr, unknown))}; shipped: "
                                 f"{', '.join(shipped)}", param_hint="'--object'")
    for path, option in ((out, "'--out'"), (overlay, "'--overlay'")):
        if path is not None:
            prepare_output(path, option)
    kwargs = {} if hypotheses is None else {"hypotheses": hypotheses}
    estimators: dict = {}
    t0 = time.perf_counter()
    result = {"format": "refiner-rt/estimate/1", "K": K3.tolist(),
              "conventions": "R object to camera (x_cam = R @ x_obj + t), q wxyz, t metres in the YCB google_16k "
                             "scan frame, boxes x1,y1,x2,y2 pixels", "images": []}
    for i, path in enumerate(images):
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise click.BadParameter(f"{path} is not an image OpenCV can read", param_hint="'IMAGES'")
        depth = read_depth(depths[i], image.shape[:2], depth_unit_mm) if depths else None
        poses = []
        for obj in dict.fromkeys(o for o, _ in wanted[i]):
            obj_boxes = np.array([b for o, b in wanted[i] if o == obj])
            if obj not in estimators:
                estimators[obj] = PoseEstimator.pretrained(obj, threads=threads, **kwargs)
            try:
                res = estimators[obj].estimate(image, obj_boxes, K=K3, depth=depth)
            except (ValueError, TypeError) as exc:
                raise click.ClickException(f"{path.name}, {obj}: {exc}") from None
            for k in range(len(res)):
                poses.append({"object": obj, "box_xyxy": obj_boxes[k].tolist(), "R": res.R[k].round(6).tolist(),
                              "q_wxyz": rq.canonical(res.q[k]).round(6).tolist(), "t_m": res.t[k].round(5).tolist(),
                              "score": round(float(res.score[k]), 4)})
        result["images"].append({"image": str(path), "depth": str(depths[i]) if depths else None, "poses": poses})
        if overlay is not None:
            target = overlay if len(images) == 1 else overlay.with_name(f"{overlay.stem}_{path.stem}.png")
            write_picture(target, _picture(image, K3, poses))
    result["wall_s"] = round(time.perf_counter() - t0, 3)
    text = json.dumps(result, indent=1)
    if out is None:
        click.echo(text)
    else:
        out.write_text(text + "\n")
        n = sum(len(im["poses"]) for im in result["images"])
        click.echo(f"Wrote {out}: {n} poses in {len(images)} image{'s' if len(images) != 1 else ''} "
                   f"({result['wall_s']:.2f} s).")
