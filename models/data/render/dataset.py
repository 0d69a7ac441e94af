"""Data sets: scenes rendered in worker processes, resumable, with their record (``render_config.json``,
``objects.json``)."""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from pathlib import Path

from models.data.meshes import Mesh, find_models
from models.data.objects import OBJECTS_FILE

from .config import RenderConfig
from .scene import World
from .tiny import render_scene

_WORKER: dict = {}


def _worker_init(models: dict[str, Mesh], tmp_root: str, blender: str | None = None, threads: int = 0):
    tmp = Path(tmp_root) / f"w{os.getpid()}"
    tmp.mkdir(parents=True, exist_ok=True)
    _WORKER.update(world=World(models, tmp), blender=blender, threads=threads)


def _worker_render(args):
    cfg, seed, scene, out_dir = args
    if cfg.engine == "cycles":
        from .cycles import render_scene_cycles

        return scene, render_scene_cycles(_WORKER["world"], cfg, seed, scene, Path(out_dir), Path(_WORKER["blender"]),
                                          threads=_WORKER["threads"])
    return scene, render_scene(_WORKER["world"], cfg, seed, scene, Path(out_dir))


def render_dataset(out_dir: Path, frames: int, models_dir: Path, cfg: RenderConfig | None = None, seed: int = 0,
                   workers: int = 1, progress: bool = True, first_scene: int = 0, mesh_unit: str | None = None,
                   blender_python: str | os.PathLike | None = None) -> dict:
    """Render ``ceil(frames / frames_per_scene)`` BOP scenes into ``out_dir``; finished scenes are kept (resumable).

    The scenes are numbered from ``first_scene``. A set's splits are drawn from its own scenes, so a set
    is grown by rendering the next scenes of the same seed and config into a second folder
    (``first_scene`` = the first set's scene count) rather than into the first.

    Args:
        out_dir: output folder; scene folders go directly under it (``load_bop(out_dir)`` reads them).
        frames: total frames (at least one scene).
        models_dir: models folder: YCB-Video style, loose OBJ/PLY files or BOP ``models/`` (see
            :func:`models.data.meshes.find_models`).
        cfg: what to render (defaults: 640x480, YCB-Video's K, 100 frames per scene, 3-6 objects).
        seed: the dataset seed; scene ``i`` depends only on ``(seed, i)``, so results are deterministic
            and independent of ``workers``.
        workers: parallel processes (each with its own pybullet world).
        progress: tqdm progress bar with frames/s.
        first_scene: index of the first scene (folder ``<first_scene:06d>``).
        mesh_unit: the meshes' unit, ``"m"`` or ``"mm"`` (None: millimetres for a BOP folder, else metres).
        blender_python: with ``cfg.engine == "cycles"``, the interpreter that has ``bpy``
            (:func:`models.data.render.cycles.find_blender_python`; default: found as it says).

    The objects' names, BOP ``obj_id`` numbers, mesh files (name, SHA-256, unit) and symmetries are written to
    ``out_dir/objects.json``, which the loaders read to name your own objects.

    Returns:
        Summary: scenes rendered and skipped, frames, visible instances per object (``visib_fract >= 0.3``)
        over the scenes rendered in this call, seconds.
    """
    cfg = cfg or RenderConfig()
    if frames < 1:
        raise ValueError(f"frames must be >= 1; got {frames}")
    if isinstance(first_scene, bool) or not isinstance(first_scene, int) or first_scene < 0:
        raise ValueError(f"first_scene must be an int >= 0; got {first_scene!r}")
    blender, threads = None, 0
    if cfg.engine == "cycles":
        from .cycles import find_blender_python

        blender = str(find_blender_python(blender_python))
        threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    meshes = find_models(models_dir, cfg.objects, unit=mesh_unit, cache_dir=out_dir / ".meshes")
    objects_record = json.dumps({o: m.record() for o, m in meshes.items()}, indent=1)
    n_scenes = math.ceil(frames / cfg.frames_per_scene)
    record = {"format": "refiner-rt/render/1", "seed": seed, "models_dir": str(Path(models_dir).resolve()), "config": cfg.as_dict()}
    rec_path = out_dir / "render_config.json"
    if rec_path.is_file():
        old = json.loads(rec_path.read_text())
        same = json.loads(json.dumps({k: record[k] for k in ("seed", "config")}))  # tuples -> lists, as stored
        if {k: old.get(k) for k in ("seed", "config")} != same:
            raise ValueError(f"{out_dir} holds scenes rendered with another seed or config ({rec_path}); use a new --out")
    else:
        rec_path.write_text(json.dumps(record, indent=1))
    (out_dir / OBJECTS_FILE).write_text(objects_record)
    todo = [s for s in range(first_scene, first_scene + n_scenes)
            if not (out_dir / f"{s:06d}" / "scene_gt_info.json").is_file()]
    t0 = time.perf_counter()
    visible: dict[str, int] = {}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(todo) * cfg.frames_per_scene, unit="frame", desc="render", dynamic_ncols=True)
    tmp_root = out_dir / ".work"
    jobs = [(cfg, seed, s, str(out_dir)) for s in todo]
    try:
        if workers <= 1:
            _worker_init(meshes, str(tmp_root), blender, threads)
            results = map(_worker_render, jobs)
            for _, r in results:
                _accumulate(visible, r, bar)
        else:
            import multiprocessing as mp

            with mp.get_context("spawn").Pool(workers, initializer=_worker_init, initargs=(meshes, str(tmp_root), blender, threads)) as pool:
                for _, r in pool.imap_unordered(_worker_render, jobs):
                    _accumulate(visible, r, bar)
    finally:
        if bar is not None:
            bar.close()
        shutil.rmtree(tmp_root, ignore_errors=True)
    return {"scenes": n_scenes, "rendered": len(todo), "skipped": n_scenes - len(todo),
            "frames": len(todo) * cfg.frames_per_scene, "visible_instances": dict(sorted(visible.items())),
            "seconds": time.perf_counter() - t0}


def _accumulate(visible: dict, r: dict, bar) -> None:
    for o, n in r["visible_instances"].items():
        visible[o] = visible.get(o, 0) + n
    if bar is not None:
        bar.update(r["frames"])
