"""A tiny learnable BOP dataset: colour-faced cubes whose appearance reveals their rotation.

Written with the BOP JSON writer of ``data_fixtures`` (as the BOP toolkit writes it) and drawn with
OpenCV (projected faces, back-face culling), so end-to-end tests need neither pybullet nor meshes.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from tests.data_fixtures import bop_save_json

# Cube of side 2 (object units: 5 cm): 8 corners, 6 faces (outward, counter-clockwise seen from outside).
_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float) * 0.025
_FACES = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
_COLOURS = [(40, 40, 220), (40, 220, 40), (220, 40, 40), (40, 220, 220), (220, 40, 220), (220, 220, 40)]


def draw_cube(image: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, colour_shift: int = 0) -> np.ndarray:
    """Draw the cube (object-to-camera ``R``, ``t`` metres) into ``image``; returns its mask (bool)."""
    cam = _CORNERS @ R.T + t
    uv = cam @ K.T
    uv = uv[:, :2] / uv[:, 2:3]
    mask = np.zeros(image.shape[:2], np.uint8)
    centre = cam.mean(axis=0)
    order = sorted(range(6), key=lambda f: -np.linalg.norm(cam[list(_FACES[f])].mean(0)))
    for f in order:
        idx = list(_FACES[f])
        normal = cam[idx].mean(0) - centre
        if normal @ cam[idx].mean(0) >= 0:  # facing away from the camera
            continue
        poly = np.round(uv[idx] * 16).astype(np.int32)
        colour = tuple(int((c + colour_shift) % 256) for c in _COLOURS[f])
        cv2.fillConvexPoly(image, poly, colour, lineType=cv2.LINE_AA, shift=4)
        cv2.fillConvexPoly(mask, poly, 1, shift=4)
    return mask.astype(bool)


def make_cube_dataset(split_dir: Path, obj_ids=(2, 5), scenes: int = 4, frames: int = 30, size=(160, 120), seed: int = 0,
                      max_angle: float = 60.0, masks: bool = False):
    """Write ``scenes`` BOP scenes of ``frames`` frames, each showing one cube per ``obj_ids`` entry.

    Object ``k`` is told apart by a colour shift. Rotations are random per frame, within ``max_angle``
    degrees of a fixed tilted view (like objects on a table); boxes come from the mask. With ``masks``,
    each instance's visible pixels are written as BOP ``mask_visib/<im_id>_<gt_idx>.png`` (0/255).
    """
    rng = np.random.default_rng(seed)
    w, h = size
    K = np.array([[220.0, 0, w / 2 - 0.5], [0, 220.0, h / 2 - 0.5], [0, 0, 1]])
    for s in range(scenes):
        scene = Path(split_dir) / f"{s:06d}"
        (scene / "rgb").mkdir(parents=True, exist_ok=True)
        if masks:
            (scene / "mask_visib").mkdir(exist_ok=True)
        gt, info, cam = {}, {}, {}
        for im in range(frames):
            image = np.full((h, w, 3), 90, np.uint8)
            image += rng.integers(0, 30, image.shape, dtype=np.uint8)
            gts, infos, drawn = [], [], []
            for k, obj in enumerate(obj_ids):
                axis = rng.normal(size=3)
                delta = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(rng.uniform(0, max_angle)))
                R = (Rotation.from_euler("xyz", [30, 40, 0], degrees=True) * delta).as_matrix()
                x = (k + 0.5) / len(obj_ids) * w
                t = np.linalg.inv(K) @ np.array([x, h / 2, 1.0]) * 0.45
                mask = draw_cube(image, K, R, t, colour_shift=60 * k)
                drawn.append(mask)
                ys, xs = np.nonzero(mask)
                box = [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]
                gts.append({"cam_R_m2c": R.flatten().tolist(), "cam_t_m2c": (t * 1000).tolist(), "obj_id": int(obj)})
                infos.append({"bbox_obj": box, "bbox_visib": box, "px_count_all": int(mask.sum()),
                              "px_count_valid": int(mask.sum()), "px_count_visib": int(mask.sum()), "visib_fract": 1.0})
            cv2.imwrite(str(scene / "rgb" / f"{im:06d}.png"), image)
            for k in range(len(drawn) if masks else 0):  # visible: not covered by a cube drawn later
                visible = drawn[k] & ~np.any(drawn[k + 1:], axis=0) if k + 1 < len(drawn) else drawn[k]
                cv2.imwrite(str(scene / "mask_visib" / f"{im:06d}_{k:06d}.png"), visible.astype(np.uint8) * 255)
            gt[im], info[im] = gts, infos
            cam[im] = {"cam_K": K.flatten().tolist(), "depth_scale": 1.0}
        bop_save_json(scene / "scene_gt.json", gt)
        bop_save_json(scene / "scene_gt_info.json", info)
        bop_save_json(scene / "scene_camera.json", cam)
    return K
