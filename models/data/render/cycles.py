"""The Blender Cycles engine: physically based images of the same scenes, written as the same BOP scenes.

The arrangement is the TinyRenderer engine's for the same seed and scene (:func:`models.data.render.tiny.start_scene`:
pybullet settles the objects), seen along a camera path of the same kind (drawn next, so not the same path), and the
ground truth comes from the same place: pybullet's segmentation of the objects at the camera's pose gives the visible
masks, boxes and BOP ``visib_fract`` (:func:`frame_ground_truth`).
Only the colour image changes: Blender's path tracer (CPU, a few samples, OpenImageDenoise) renders the textured
meshes with glossy or rough materials on a textured table, lit by one of the HDR environment maps that ``bpy``
ships (``datafiles/studiolights/world``: light and background) and one or two area lights of random colour and
size (soft shadows, objects shadowing each other). The image is rendered at ``cycles_scale`` of its size (the crops
need no more) and resized, then gets the camera's sensor noise and JPEG as the TinyRenderer engine's images do.

With ``cycles_region`` the frame is rendered twice over: the whole frame at ``cycles_scale`` (the backdrop), then each
object's region alone (Blender's render border, cropped to it) at the scale where the region's side is
:data:`REGION_PIXELS` pixels: the refiner's crop (64 pixels of 1.2 times the box, box jitter aside) sampled from
about 1.3 times its resolution, as sharp for a far, small object as for a near one. Each region is warped back into
the frame at its exact place (the border snapped to the scaled image's pixels) over the backdrop, the finer
regions last. The object's appearance (``object_appearance``): a texture gain per object, multiplied into the
base colour.

``bpy`` requires ``numpy < 2`` and cannot share an environment with refiner-rt's OpenCV, so it runs in an
interpreter of its own: :data:`BLENDER_PYTHON_ENV` or ``--blender-python`` names it, and ``cycles_worker.py`` is run
there as a script, one process per scene. Install it with
``python3.11 -m venv .venv-blender && .venv-blender/bin/pip install bpy``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np

from .bop_writer import finish_scene, frame_ground_truth
from .camera import camera_path, projection_matrix_gl, view_matrix_gl
from .config import TABLE_HALF, RenderConfig
from .scene import World, object_appearance
from .tiny import random_texture, start_scene

BLENDER_PYTHON_ENV = "REFINER_RT_BLENDER_PYTHON"
WORKER = Path(__file__).with_name("cycles_worker.py")
# The HDR environment maps of bpy's datafiles/studiolights/world (bpy 4.x and 5.x ship these eight).
WORLDS = ("city.exr", "courtyard.exr", "forest.exr", "interior.exr", "night.exr", "studio.exr", "sunrise.exr",
          "sunset.exr")


# cycles_region: a region's side is REGION_SPAN times the object's projected box's larger side (the crop's 1.2 and
# room for the training's box jitter), rendered REGION_PIXELS pixels wide: the 64-pixel crop of 1.2 / 1.6 of it is then
# sampled from about 1.3 times its resolution.
REGION_SPAN = 1.6
REGION_PIXELS = 112


class BlenderError(RuntimeError):
    """No usable Blender Python, or Blender failed on a scene (the message says which and how to fix it)."""


def find_blender_python(given: str | os.PathLike | None = None) -> Path:
    """The interpreter that has ``bpy``: ``given``, else ``$REFINER_RT_BLENDER_PYTHON``, else ``.venv-blender`` in the
    current directory; checked by importing ``bpy`` in it.

    Raises:
        BlenderError: none found, or ``bpy`` does not import there (the message says how to install it).
    """
    how = ("the cycles engine needs Blender as a Python module in an interpreter of its own (bpy needs numpy < 2): "
           "python3.11 -m venv .venv-blender && .venv-blender/bin/pip install bpy, then pass --blender-python "
           f".venv-blender/bin/python or set {BLENDER_PYTHON_ENV}")
    candidate = given or os.environ.get(BLENDER_PYTHON_ENV)
    if candidate is None:
        local = Path(".venv-blender") / "bin" / "python"
        if not local.is_file():
            raise BlenderError(f"no Blender Python found; {how}")
        candidate = local
    path = Path(candidate)
    if not path.is_file():
        raise BlenderError(f"Blender Python {path} not found; {how}")
    try:
        probe = subprocess.run([str(path), "-c", "import bpy; print(bpy.app.version_string)"], capture_output=True,
                               text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise BlenderError(f"{path} could not be run to check for bpy ({exc}); {how}") from None
    if probe.returncode != 0:
        raise BlenderError(f"{path} cannot import bpy ({probe.stderr.strip().splitlines()[-1:] or '?'}); {how}")
    return path


def _die_with_parent() -> None:
    """In the Blender child, before it starts (Linux): be sent SIGTERM when the render worker that started it dies,
    so a stopped render (Ctrl-C, ``kill``) leaves no Blender running. Elsewhere nothing."""
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _matrix(R: np.ndarray, t: np.ndarray) -> list[list[float]]:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M.tolist()


def _look_from(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rotation of a Blender light or camera at ``position`` pointing its -z axis at ``target`` (world z up)."""
    back = position - target
    back /= np.linalg.norm(back)
    side = np.cross([0.0, 0.0, 1.0], back)
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else np.array([1.0, 0.0, 0.0])
    return np.stack([side, np.cross(back, side), back], axis=1)


def object_regions(world: World, bodies: dict[int, str], R_cw: np.ndarray, t_cw: np.ndarray, K: np.ndarray,
                   width: int, height: int) -> list[dict]:
    """``cycles_region``: per object in front of the camera whose region meets the image, the region to render
    alone: ``{"body", "percentage", "border": [x0, y0, x1, y1]}``, the border in the pixels of the image scaled by
    ``percentage`` (Blender's integer sizes: ``percentage * width // 100``), top-left origin, clipped to it."""
    out = []
    for b, obj in sorted(bodies.items()):
        R_wo, t_wo = world.mesh_pose(b)
        v = world.meshes[obj].vertices[::16] @ (R_cw @ R_wo).T + (R_cw @ t_wo + t_cw)
        v = v[v[:, 2] > 0.02]
        if len(v) < 4:
            continue
        uv = v[:, :2] / v[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        (x0, y0), (x1, y1) = uv.min(axis=0), uv.max(axis=0)
        side = max(x1 - x0, y1 - y0) * REGION_SPAN
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        x0, x1 = max(cx - side / 2, 0.0), min(cx + side / 2, float(width))
        y0, y1 = max(cy - side / 2, 0.0), min(cy + side / 2, float(height))
        if x1 - x0 < 2 or y1 - y0 < 2:
            continue
        pct = int(np.clip(np.ceil(100.0 * REGION_PIXELS / max(side, 1.0)), 1, 100))
        fx, fy = (pct * width // 100) / width, (pct * height // 100) / height
        border = [int(np.floor(x0 * fx)), int(np.floor(y0 * fy)), int(np.ceil(x1 * fx)), int(np.ceil(y1 * fy))]
        out.append({"body": b, "percentage": pct, "border": border})
    return out


def paste_region(frame: np.ndarray, region: np.ndarray, border: list[int], percentage: int) -> None:
    """Warp ``region`` (the image rendered inside ``border`` at ``percentage``, :func:`object_regions`) into
    ``frame`` (full size, float32) at its exact place, in place."""
    H, W = frame.shape[:2]
    fx, fy = (percentage * W // 100) / W, (percentage * H // 100) / H
    bx0, by0 = border[0], border[1]
    # region pixel centre (u, v) -> frame pixel (x, y): x = (bx0 + u + 0.5) / fx - 0.5
    M = np.array([[1 / fx, 0.0, (bx0 + 0.5) / fx - 0.5], [0.0, 1 / fy, (by0 + 0.5) / fy - 0.5]])
    warped = cv2.warpAffine(region.astype(np.float32), M, (W, H), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE).reshape(H, W, *region.shape[2:])
    inside = cv2.warpAffine(np.ones(region.shape[:2], np.uint8), M, (W, H), flags=cv2.INTER_NEAREST,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0
    frame[inside] = warped[inside]


def cycles_job(world: World, cfg: RenderConfig, bodies: dict[int, str], centre: np.ndarray, K: np.ndarray,
               poses: list, rng: np.random.Generator, work: Path, threads: int, seed: int = 0, scene: int = 0) -> dict:
    """The worker's job for one scene (see ``cycles_worker.py``); the table texture is written into ``work``.
    ``seed`` and ``scene`` draw the objects' appearance (``cfg.object_appearance``).

    Raises:
        ValueError: ``K``'s pixels are not square (Blender's camera has one focal length).
    """
    if abs(K[0, 0] / K[1, 1] - 1.0) > 2e-3:
        raise ValueError(f"the cycles engine needs square pixels (fx = fy within 0.2%); got fx {K[0, 0]:g}, "
                         f"fy {K[1, 1]:g}")
    work.mkdir(parents=True, exist_ok=True)
    table = work / "table.png"
    cv2.imwrite(str(table), random_texture(rng, 512))
    objects = []
    looks = object_appearance(cfg.object_appearance, seed, scene, bodies)
    for b, obj in bodies.items():
        R_wo, t_wo = world.mesh_pose(b)
        objects.append({"obj": str(world.meshes[obj].obj_path), "texture": str(world.meshes[obj].texture_path),
                        "matrix": _matrix(R_wo, t_wo),
                        "roughness": float(rng.uniform(0.2, 0.8)), "specular": float(rng.uniform(0.2, 0.7)),
                        **({"gain_rgb": looks[b]["gain_bgr"][::-1]} if b in looks else {})})
    lights = []
    for i in range(int(rng.integers(1, 3))):
        az, el = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(30, 80))
        pos = centre + rng.uniform(0.8, 2.0) * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        tinted = rng.uniform() < cfg.light_tint
        colour = rng.uniform(0.5 if tinted else 0.85, 1.0, 3)
        lights.append({"matrix": _matrix(_look_from(pos, centre), pos), "size": float(rng.uniform(0.1, 1.0)),
                       "power": float(np.exp(rng.uniform(np.log(5.0), np.log(60.0)))),
                       "colour": (colour / colour.max()).tolist()})
    flip = np.diag([1.0, -1.0, -1.0])  # OpenCV camera (y down, z forward) -> Blender camera (y up, looking down -z)
    frames = [{"cam_to_world": _matrix(R_cw.T @ flip, -R_cw.T @ t_cw),
               **({"regions": object_regions(world, bodies, R_cw, t_cw, K, cfg.width, cfg.height)}
                  if cfg.cycles_region else {})} for R_cw, t_cw in poses]
    return {
        "objects": objects,
        "table": {"half": TABLE_HALF, "texture": str(table), "roughness": float(rng.uniform(0.3, 0.9))},
        "world": {"hdr": str(rng.choice(WORLDS)), "strength": float(np.exp(rng.uniform(np.log(0.15), np.log(0.8)))),
                  "rotation": float(rng.uniform(0, 2 * np.pi))},
        "lights": lights,
        "camera": {"K": K.tolist(), "width": cfg.width, "height": cfg.height, "scale": cfg.cycles_scale},
        "frames": frames, "samples": cfg.cycles_samples, "seed": int(rng.integers(1 << 31)), "threads": threads,
        "out": str(work / "frames"),
    }


def render_scene_cycles(world: World, cfg: RenderConfig, seed: int, scene: int, out_dir: Path, blender: Path,
                        threads: int = 0) -> dict:
    """Render one BOP scene with Cycles into ``out_dir/<scene:06d>`` (see the module doc); returns what
    :func:`models.data.render.tiny.render_scene` returns.

    Raises:
        BlenderError: the Blender worker failed (its last lines of output in the message).
    """
    pb, c = world.pb, world.client
    t0 = time.perf_counter()
    rng, final, tmp, bodies, centre, K = start_scene(world, cfg, seed, scene, out_dir)
    W, H = cfg.width, cfg.height
    poses = camera_path(cfg, rng, centre, cfg.frames_per_scene)
    work = tmp / "cycles"
    job = cycles_job(world, cfg, bodies, centre, K, poses, rng, work, threads or os.cpu_count() or 1, seed, scene)
    (work / "job.json").write_text(json.dumps(job))
    run = subprocess.run([str(blender), str(WORKER), str(work / "job.json")], capture_output=True, text=True,
                         preexec_fn=_die_with_parent)
    if run.returncode != 0:
        tail = "\n".join((run.stdout + run.stderr).strip().splitlines()[-8:])
        raise BlenderError(f"Blender failed on scene {scene} (exit {run.returncode}):\n{tail}")
    cv2.setRNGSeed(int(rng.integers(1 << 31)))
    noise_std = rng.uniform(*cfg.noise_std)
    proj = projection_matrix_gl(K, W, H)
    poses_w = {b: world.mesh_pose(b) for b in bodies}
    gt, info, cam, visible = {}, {}, {}, {}
    for im, (R_cw, t_cw) in enumerate(poses):
        img = cv2.imread(str(work / "frames" / f"{im:06d}.png"), cv2.IMREAD_COLOR)
        if img is None:
            raise BlenderError(f"Blender wrote no image for frame {im} of scene {scene}")
        if img.shape[:2] != (H, W):
            img = cv2.resize(img, (W, H), interpolation=cv2.INTER_LINEAR)
        img = img.astype(np.float32)
        for k, reg in sorted(enumerate(job["frames"][im].get("regions", ())), key=lambda kr: kr[1]["percentage"]):
            part = cv2.imread(str(work / "frames" / f"{im:06d}_r{k}.png"), cv2.IMREAD_COLOR)
            if part is None:
                raise BlenderError(f"Blender wrote no image for region {k} of frame {im} of scene {scene}")
            paste_region(img, part, reg["border"], reg["percentage"])
        noise = np.empty(img.shape, np.float32)
        cv2.randn(noise, 0.0, float(noise_std))
        cv2.imwrite(str(tmp / "rgb" / f"{im:06d}.jpg"), np.clip(img + noise, 0, 255).astype(np.uint8),
                    [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])
        # The masks from pybullet's segmentation of the same objects at the same pose (the TinyRenderer engine's).
        _, _, _, _, seg = pb.getCameraImage(W, H, view_matrix_gl(R_cw, t_cw), proj, renderer=pb.ER_TINY_RENDERER,
                                            physicsClientId=c)
        seg = np.asarray(seg).reshape(H, W)
        gts, infos, seen = frame_ground_truth(world, bodies, poses_w, R_cw, t_cw, seg, K, W, H, tmp / "mask_visib", im)
        for obj in seen:
            visible[obj] = visible.get(obj, 0) + 1
        gt[im], info[im] = gts, infos
        cam[im] = {"cam_K": K.flatten().tolist(), "depth_scale": 1.0}
    meta = {"seed": seed, "scene": scene, "engine": "cycles", "objects": sorted(set(bodies.values())),
            "world": job["world"], "lights": job["lights"], "samples": cfg.cycles_samples, "scale": cfg.cycles_scale,
            **({"regions": sum(len(f.get("regions", ())) for f in job["frames"])} if cfg.cycles_region else {}),
            **({"object_appearance": [{"object": bodies[b], **look} for b, look in
                                      object_appearance(cfg.object_appearance, seed, scene, bodies).items()]}
               if cfg.object_appearance else {}),
            "noise_std": noise_std, "blender": run.stdout.strip().splitlines()[-1] if run.stdout.strip() else "",
            "meshes": {o: str(m.obj_path) for o, m in world.meshes.items() if o in bodies.values()}}
    shutil.rmtree(work, ignore_errors=True)
    finish_scene(tmp, final, gt, info, cam, meta)
    return {"frames": len(gt), "instances": sum(len(v) for v in gt.values()), "visible_instances": visible,
            "seconds": time.perf_counter() - t0}
