"""Real frames with their objects re-drawn: what the view costs on real frames, apart from the appearance.

The command is ``python -m benchmarks.real_rendered`` (its docstring describes what is measured and has the usage);
this module is what it runs.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np


GREY = 128
# One light for every frame: from above the camera's right shoulder, the renderer's mid-range coefficients.
LIGHT = dict(lightDirection=[0.3, -1.0, -1.5], lightColor=[1.0, 1.0, 1.0], lightAmbientCoeff=0.5,
             lightDiffuseCoeff=0.6, lightSpecularCoeff=0.2, shadow=0)


def render_objects(world, names: list[str], poses: list[tuple[np.ndarray, np.ndarray]], K: np.ndarray,
                   width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The meshes ``names`` at ``poses`` (object to camera, metres) seen by the camera ``K``: ``(BGR image, mask of
    the objects' pixels)``, both ``height x width``."""
    from scipy.spatial.transform import Rotation

    from models.data.render import projection_matrix_gl, view_matrix_gl

    world.clear()
    for name, (R, t) in zip(names, poses):
        world.add_object(name, np.asarray(t, float).tolist(), Rotation.from_matrix(R).as_quat().tolist())
    pb = world.pb
    _, _, rgba, _, seg = pb.getCameraImage(width, height, view_matrix_gl(np.eye(3), np.zeros(3)),
                                           projection_matrix_gl(K, width, height), renderer=pb.ER_TINY_RENDERER,
                                           physicsClientId=world.client, **LIGHT)
    rgb = np.asarray(rgba, np.uint8).reshape(height, width, 4)[..., :3]
    return np.ascontiguousarray(rgb[..., ::-1]), np.asarray(seg).reshape(height, width) >= 0


def rerender_folder(data: Path, out: Path, models_dir: Path, background: str = "real", progress: bool = True) -> dict:
    """Copy the BOP folder ``data`` to ``out`` with every annotated object re-drawn at its true pose; returns a
    record (frames, instances, wall time)."""
    import cv2
    from tqdm import tqdm

    from models.data.meshes import find_models
    from models.data.objects import obj_id_map_for
    from models.data.render import World

    scenes = sorted(d for d in data.iterdir() if (d / "scene_gt.json").is_file())
    if not scenes:
        raise SystemExit(f"--data {data}: no BOP scene (a folder with scene_gt.json) in it")
    names = obj_id_map_for(data)
    gts = {d.name: json.loads((d / "scene_gt.json").read_text()) for d in scenes}
    used = sorted({names[a["obj_id"]] for gt in gts.values() for anns in gt.values() for a in anns
                   if a["obj_id"] in names})
    try:
        meshes = find_models(models_dir, used)
    except (FileNotFoundError, ValueError) as exc:
        raise SystemExit(f"--models {models_dir}: {exc}") from None
    t0 = time.perf_counter()
    frames = instances = 0
    work = out.with_name(out.name + ".tmp")
    shutil.rmtree(work, ignore_errors=True)
    world = World(meshes, work / ".textures")
    bar = tqdm(total=sum(len(g) for g in gts.values()), unit="frame", disable=not progress, desc="re-draw")
    for d in scenes:
        shutil.copytree(d, work / d.name)
        cams = json.loads((d / "scene_camera.json").read_text())
        for key, anns in gts[d.name].items():
            anns = [a for a in anns if a["obj_id"] in names]
            path = next((work / d.name / "rgb").glob(f"{int(key):06d}.*"))
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            K = np.asarray(cams[key]["cam_K"], float).reshape(3, 3)
            poses = [(np.asarray(a["cam_R_m2c"], float).reshape(3, 3), np.asarray(a["cam_t_m2c"], float) / 1000.0)
                     for a in anns]
            drawn, mask = render_objects(world, [names[a["obj_id"]] for a in anns], poses, K,
                                         image.shape[1], image.shape[0])
            base = image if background == "real" else np.full_like(image, GREY)
            cv2.imwrite(str(path.with_suffix(".png")), np.where(mask[..., None], drawn, base))
            if path.suffix != ".png":
                path.unlink()
            frames += 1
            instances += len(anns)
            bar.update()
    bar.close()
    shutil.rmtree(work / ".textures", ignore_errors=True)
    for name in ("objects.json",):
        if (data / name).is_file():
            shutil.copy2(data / name, work / name)
    shutil.rmtree(out, ignore_errors=True)
    work.rename(out)
    return {"data": str(data), "out": str(out), "background": background, "frames": frames, "instances": instances,
            "wall_s": round(time.perf_counter() - t0, 1)}
