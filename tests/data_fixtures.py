"""Writers of tiny datasets in the real YCB-Video and BOP file formats, for the data tests.

The writers follow the formats' own tools: ``-meta.mat`` as MATLAB saves it (``scipy.io.savemat``:
``poses`` 3x4xN, 3x4 for one object; ``cls_indexes`` an N x 1 double column), BOP JSON files as
``bop_toolkit_lib/inout.py`` ``save_json`` writes them (one image id per line, sorted keys,
``cam_R_m2c`` / ``cam_K`` flattened row-major, ``cam_t_m2c`` in mm). They return the ground truth
they wrote so tests can check exact round trips.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import scipy.io
from scipy.spatial.transform import Rotation

from models.data.objects import YCBV_CLASSES

K_YCBV = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])
K_YCBV_LATE = np.array([[1077.836, 0.0, 323.7872], [0.0, 1078.189, 279.6921], [0.0, 0.0, 1.0]])  # seq >= 60


@dataclass
class Truth:
    """One instance as written: the values a loader must give back."""

    image_path: Path
    obj_id: str
    R: np.ndarray
    t_m: np.ndarray
    box_xyxy: np.ndarray
    K: np.ndarray
    scene_id: str
    frame_id: int
    instance: int
    visib_fract: float | None = None
    bbox_obj_xyxy: np.ndarray | None = None


def random_rotations(n: int, seed: int) -> np.ndarray:
    """``(n, 3, 3)`` float64 random rotations (SciPy, uniform on SO(3))."""
    return Rotation.random(n, random_state=seed).as_matrix()


def write_image(path: Path, width: int, height: int, seed: int) -> np.ndarray:
    """Write a random-texture BGR image (PNG lossless, JPEG quality 95) and return the pixels written."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, size=(height // 8 + 1, width // 8 + 1, 3), dtype=np.uint8)
    image = cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR)
    path.parent.mkdir(parents=True, exist_ok=True)
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if path.suffix.lower() in (".jpg", ".jpeg") else []
    if not cv2.imwrite(str(path), image, params):
        raise OSError(f"could not write {path}")
    return image


def bop_save_json(path: Path, content: dict) -> None:
    """Write a dict as ``bop_toolkit_lib.inout.save_json`` does (one top-level key per line)."""
    items = sorted(content.items(), key=lambda kv: kv[0])
    with open(path, "w") as f:
        f.write("{\n")
        for i, (k, v) in enumerate(items):
            f.write('  "{}": {}'.format(k, json.dumps(v, sort_keys=True)))
            if i != len(items) - 1:
                f.write(",")
            f.write("\n")
        f.write("}")


# --- YCB-Video ----------------------------------------------------------------------------------


def write_ycbv_frame(root: Path, seq: str, frame: str, objects, K, size=(640, 480), seed=0, poses_override=None):
    """Write ``data/<seq>/<frame>-color.png``, ``-meta.mat`` and ``-box.txt``.

    Args:
        objects: list of ``(class_index 1-based, R 3x3, t metres (3,), box xyxy (4,))``.
        poses_override: write this array as ``poses`` instead (for malformed-file tests).

    Returns:
        list of :class:`Truth`.
    """
    seq_dir = root / "data" / seq
    seq_dir.mkdir(parents=True, exist_ok=True)
    color = seq_dir / f"{frame}-color.png"
    write_image(color, size[0], size[1], seed)
    poses = np.zeros((3, 4, len(objects)))
    for i, (_, R, t, _) in enumerate(objects):
        poses[:, :3, i] = R
        poses[:, 3, i] = t
    if len(objects) == 1:
        poses = poses[:, :, 0]  # MATLAB stores a 3x4x1 array as 3x4
    mat = {
        "poses": poses if poses_override is None else poses_override,
        "cls_indexes": np.array([[float(c)] for c, *_ in objects]),
        "intrinsic_matrix": np.asarray(K, dtype=np.float64),
        "factor_depth": np.array([[10000.0]]),
        "center": np.zeros((len(objects), 2)),
    }
    scipy.io.savemat(seq_dir / f"{frame}-meta.mat", mat)
    with open(seq_dir / f"{frame}-box.txt", "w") as f:
        for c, _, _, box in objects:
            f.write(f"{YCBV_CLASSES[c - 1]} " + " ".join(repr(float(v)) for v in box) + "\n")
    return [
        Truth(color, YCBV_CLASSES[c - 1], np.asarray(R), np.asarray(t, dtype=float), np.asarray(box, dtype=float),
              np.asarray(K), seq, int(frame), i)
        for i, (c, R, t, box) in enumerate(objects)
    ]


def make_ycbv(root: Path) -> list[Truth]:
    """A 3-sequence YCB-Video folder: seq 0048 (2 frames, 3 and 1 objects), 0059, 0060 (other K).

    Also writes ``image_sets/keyframe.txt`` (0048/000001 and 0060/000001) and ``train.txt`` (all).
    """
    Rs = random_rotations(8, seed=1)
    truths = []
    truths += write_ycbv_frame(root, "0048", "000001", [
        (2, Rs[0], [0.01, -0.02, 0.8], [100.5, 120.25, 220.75, 300.0]),
        (5, Rs[1], [-0.1, 0.05, 0.95], [300.0, 100.0, 380.0, 260.0]),
        (15, Rs[2], [0.12, 0.0, 1.1], [400.0, 200.0, 560.0, 330.0]),
    ], K_YCBV, seed=1)
    truths += write_ycbv_frame(root, "0048", "000002", [(2, Rs[3], [0.01, -0.02, 0.81], [101.0, 121.0, 221.0, 301.0])],
                               K_YCBV, seed=2)
    truths += write_ycbv_frame(root, "0059", "000007", [
        (17, Rs[4], [0.0, 0.1, 0.7], [10.0, 20.0, 30.0, 90.0]),
        (10, Rs[5], [0.2, 0.1, 0.9], [500.0, 400.0, 600.0, 470.0]),
    ], K_YCBV, seed=3)
    truths += write_ycbv_frame(root, "0060", "000001", [
        (12, Rs[6], [0.0, 0.0, 1.0], [200.0, 100.0, 280.0, 330.0]),
        (8, Rs[7], [0.05, 0.05, 0.6], [250.0, 300.0, 300.0, 350.0]),
    ], K_YCBV_LATE, seed=4)
    sets = root / "image_sets"
    sets.mkdir(parents=True, exist_ok=True)
    (sets / "keyframe.txt").write_text("0048/000001\n0060/000001\n")
    (sets / "train.txt").write_text("0048/000001\n0048/000002\n0059/000007\n0060/000001\n")
    return truths


# --- BOP ----------------------------------------------------------------------------------------


def write_bop_scene(split_dir: Path, scene_id: int, frames, K, size=(640, 480), ext="png", seed=0):
    """Write one BOP scene folder.

    Args:
        frames: ``{im_id: [instance dict]}`` with keys ``obj_id``, ``R`` (3x3), ``t_mm`` (3,),
            ``bbox_obj`` and ``bbox_visib`` (``[x, y, w, h]``), ``visib_fract``; extra keys
            (``drop``: field names to leave out) serve malformed-file tests.
        ext: ``"png"`` or ``"jpg"`` for ``rgb/``.

    Returns:
        ``(scene_dir, truths)``.
    """
    scene = split_dir / f"{scene_id:06d}"
    (scene / "rgb").mkdir(parents=True, exist_ok=True)
    scene_gt, scene_info, scene_cam, truths = {}, {}, {}, []
    for im_id, instances in sorted(frames.items()):
        image = scene / "rgb" / f"{im_id:06d}.{ext}"
        write_image(image, size[0], size[1], seed * 1000 + im_id)
        gts, infos = [], []
        for inst, d in enumerate(instances):
            gt = {"cam_R_m2c": np.asarray(d["R"]).flatten().tolist(), "cam_t_m2c": np.asarray(d["t_mm"]).flatten().tolist(),
                  "obj_id": int(d["obj_id"])}
            # bop_toolkit's calc_gt_info writes boxes as ints
            info = {"bbox_obj": [int(v) for v in d["bbox_obj"]], "bbox_visib": [int(v) for v in d["bbox_visib"]],
                    "px_count_all": 1000, "px_count_valid": 1000, "px_count_visib": int(1000 * d["visib_fract"]),
                    "visib_fract": float(d["visib_fract"])}
            for name in d.get("drop", ()):
                gt.pop(name, None)
                info.pop(name, None)
            gts.append(gt)
            infos.append(info)
            x, y, w, h = d["bbox_visib"]
            bx, by, bw, bh = d["bbox_obj"]
            name = YCBV_CLASSES[d["obj_id"] - 1] if 1 <= d["obj_id"] <= len(YCBV_CLASSES) else str(d["obj_id"])
            truths.append(Truth(image, name, np.asarray(d["R"]), np.asarray(d["t_mm"]) / 1000.0,
                                np.array([x, y, x + w, y + h], dtype=float), np.asarray(K), f"{scene_id:06d}", im_id, inst,
                                float(d["visib_fract"]), np.array([bx, by, bx + bw, by + bh], dtype=float)))
        scene_gt[im_id] = gts
        scene_info[im_id] = infos
        scene_cam[im_id] = {"cam_K": np.asarray(K).flatten().tolist(), "depth_scale": 0.1}
    bop_save_json(scene / "scene_gt.json", scene_gt)
    bop_save_json(scene / "scene_gt_info.json", scene_info)
    bop_save_json(scene / "scene_camera.json", scene_cam)
    return scene, truths


def bop_instance(obj_id, R, t_mm, bbox_visib, visib_fract=0.9, bbox_obj=None, **extra) -> dict:
    """One instance dict for :func:`write_bop_scene` (``bbox_obj`` defaults to ``bbox_visib`` grown 10 px)."""
    if bbox_obj is None:
        x, y, w, h = bbox_visib
        bbox_obj = [x - 5, y - 5, w + 10, h + 10]
    return dict(obj_id=obj_id, R=R, t_mm=t_mm, bbox_visib=list(bbox_visib), bbox_obj=list(bbox_obj),
                visib_fract=visib_fract, **extra)


def make_bop(split_dir: Path, size=(640, 480)) -> list[Truth]:
    """A 2-scene BOP split: scene 48 (PNG, 2 frames), scene 50 (JPEG, 1 frame, one invisible instance)."""
    Rs = random_rotations(7, seed=2)
    truths = []
    _, t1 = write_bop_scene(split_dir, 48, {
        1: [bop_instance(2, Rs[0], [12.5, -20.0, 812.25], [100, 120, 80, 150], 0.95),
            bop_instance(15, Rs[1], [-100.0, 50.0, 950.0], [300, 100, 120, 90], 0.4)],
        2: [bop_instance(2, Rs[2], [13.0, -21.0, 815.0], [102, 121, 79, 150], 0.93)],
    }, K_YCBV, size=size, ext="png", seed=48)
    _, t2 = write_bop_scene(split_dir, 50, {
        7: [bop_instance(17, Rs[3], [0.0, 100.0, 700.0], [10, 20, 20, 70], 0.25),
            bop_instance(5, Rs[4], [0.0, 0.0, 1000.0], [-1, -1, -1, -1], 0.0, bbox_obj=[200, 200, 40, 60]),
            bop_instance(8, Rs[5], [50.0, 50.0, 600.0], [250, 300, 50, 50], 1.0)],
    }, K_YCBV_LATE, size=size, ext="jpg", seed=50)
    truths = [t for t in t1 + t2 if t.visib_fract > 0]
    return truths
