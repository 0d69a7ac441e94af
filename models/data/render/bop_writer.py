"""The BOP writer: JSON files as the BOP toolkit writes them, boxes and the occlusion test behind ``visib_fract``, a
frame's ground truth from the renderer's segmentation, a finished scene folder."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from .camera import projected_bbox, silhouette


def _bop_json(path: Path, content: dict) -> None:
    """Write JSON as ``bop_toolkit_lib.inout.save_json`` does (one image id per line), atomically."""
    items = sorted(content.items(), key=lambda kv: int(kv[0]))
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w") as f:
        f.write("{\n")
        for i, (k, v) in enumerate(items):
            f.write(f'  "{k}": {json.dumps(v, sort_keys=True)}' + (",\n" if i < len(items) - 1 else "\n"))
        f.write("}")
    os.replace(tmp, path)


def may_be_occluded(vis: np.ndarray, seg: np.ndarray, b: int, box: np.ndarray, width: int, height: int) -> bool:
    """Whether body ``b`` can be partly hidden: its projection reaches the image border, or its visible
    pixels touch another object's (an occluder always borders what it hides). Otherwise its visible
    pixels are its whole silhouette."""
    x1, y1, x2, y2 = box
    if x1 < 1 or y1 < 1 or x2 > width - 2 or y2 > height - 2:
        return True
    x, y, w, h = cv2.boundingRect(vis.view(np.uint8))
    if w == 0:
        return True
    a0, a1 = max(y - 2, 0), min(y + h + 2, height)
    b0, b1 = max(x - 2, 0), min(x + w + 2, width)
    local = vis[a0:a1, b0:b1].astype(np.uint8)
    ring = cv2.dilate(local, np.ones((3, 3), np.uint8)) > local
    neighbours = seg[a0:a1, b0:b1][ring]
    return bool(np.any((neighbours >= 0) & (neighbours != b)))


def _bbox(mask: np.ndarray) -> list[int]:
    """BOP box ``[x, y, w, h]`` of a mask, ``[-1, -1, -1, -1]`` when empty (as the BOP toolkit writes it)."""
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))  # the tight box of the non-zero pixels; (0, 0, 0, 0) if none
    return [int(x), int(y), int(w), int(h)] if w else [-1, -1, -1, -1]


def frame_ground_truth(world, bodies: dict[int, str], poses_w: dict, R_cw: np.ndarray, t_cw: np.ndarray,
                       seg: np.ndarray, K: np.ndarray, W: int, H: int, mask_dir: Path, im: int
                       ) -> tuple[list[dict], list[dict], list[str]]:
    """One frame's BOP ground truth from the renderer's segmentation ``seg`` (body id per pixel, -1 for none):
    ``(scene_gt entries, scene_gt_info entries, objects with visib_fract >= 0.3)``; each instance's visible mask is
    written to ``mask_dir/<im>_<k>.png``. ``poses_w``: body -> its mesh frame's world pose ``(R_wo, t_wo)``."""
    gts, infos, seen = [], [], []
    for k, b in enumerate(bodies):
        R_wo, t_wo = poses_w[b]
        R, t = R_cw @ R_wo, R_cw @ t_wo + t_cw
        mesh = world.meshes[bodies[b]]
        vis = seg == b
        cv2.imwrite(str(mask_dir / f"{im:06d}_{k:06d}.png"), vis.astype(np.uint8) * 255)
        if may_be_occluded(vis, seg, b, projected_bbox(mesh, R, t, K), W, H):
            # BOP's visib_fract: the whole silhouette counts, the part beyond the image border included, so an
            # object cut in half by the border has about 0.5, as one half hidden by another object has.
            full = silhouette(mesh, R, t, K, W, H, known=vis, border=True)
            n_all, n_valid = int(full.sum()), int(full[H:2 * H, W:2 * W].sum())
            x, y, w, h = _bbox(full)
            bbox_obj = [x - W, y - H, w, h] if w > 0 else [-1, -1, -1, -1]
        else:  # nothing can hide it and it is inside the image: visible pixels are the silhouette
            n_all = n_valid = int(vis.sum())
            bbox_obj = _bbox(vis)
        n_vis = int(vis.sum())
        frac = float(n_vis / n_all) if n_all else 0.0
        gts.append({"cam_R_m2c": R.flatten().tolist(), "cam_t_m2c": (t * 1000.0).tolist(), "obj_id": mesh.number})
        infos.append({
            "bbox_obj": bbox_obj, "bbox_visib": _bbox(vis), "px_count_all": n_all, "px_count_valid": n_valid,
            "px_count_visib": n_vis, "visib_fract": min(frac, 1.0),
        })
        if frac >= 0.3:
            seen.append(bodies[b])
    return gts, infos, seen


def finish_scene(tmp: Path, final: Path, gt: dict, info: dict, cam: dict, meta: dict) -> None:
    """Write the scene's BOP files and its render record into ``tmp``, then put ``tmp`` in ``final``'s place."""
    _bop_json(tmp / "scene_gt.json", gt)
    _bop_json(tmp / "scene_gt_info.json", info)
    _bop_json(tmp / "scene_camera.json", cam)
    (tmp / "scene_render.json").write_text(json.dumps(meta, indent=1))
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)
