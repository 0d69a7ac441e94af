"""Render speed: the renderer's textures decoded once per worker and read back as BMPs (what ``refiner-rt render``
does) against each scene loading the PNG textures (as the renderer did before), on the same scenes, and whether the
two write the same bytes.

Each scene is rendered once each way, the two interleaved so that load on the machine falls on both alike; one
process, one core. Reported: the median seconds per scene each way, their ratio, frames/s of one worker, and the
number of files that differ between the two outputs (0: the BMPs change no pixel or label).

Usage (from the repository root)::

    python -m benchmarks.render_speed                                  # 20 four-frame scenes of the shipped YCB meshes
    python -m benchmarks.render_speed --scenes 40 --json benchmarks/results/render_speed/render_speed.json
"""

from __future__ import annotations

import argparse
import filecmp
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from models.data.render import RenderConfig, default_models_dir, World, find_models, render_scene
from models.evaluate.record import provenance, write_json


class _PngTextureWorld(World):
    """The world as it was: every body's texture loaded from the mesh's PNG."""

    def _texture(self, obj: str) -> Path:
        return self.meshes[obj].texture_path


def differing_files(a: Path, b: Path) -> tuple[int, list[str]]:
    """``(files compared, relative paths of the files under a and b that are missing on one side or differ)``."""
    files_a = {p.relative_to(a) for p in a.rglob("*") if p.is_file()}
    files_b = {p.relative_to(b) for p in b.rglob("*") if p.is_file()}
    differ = files_a ^ files_b
    differ |= {p for p in files_a & files_b if not filecmp.cmp(a / p, b / p, shallow=False)}
    return len(files_a | files_b), sorted(map(str, differ))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models-dir", type=Path, default=default_models_dir(),
                    help="YCB-Video-style models folder (default: the meshes in models/data/ycb_models)")
    ap.add_argument("--scenes", type=int, default=20, help="scenes rendered each way (default 20)")
    ap.add_argument("--frames-per-scene", type=int, default=4, help="frames per scene (default 4, as the scene sets)")
    ap.add_argument("--seed", type=int, default=2, help="dataset seed (default 2, as the scene sets)")
    ap.add_argument("--first-scene", type=int, default=0, help="first scene index (default 0)")
    ap.add_argument("--json", type=Path, help="write the result here")
    args = ap.parse_args(argv)
    if args.scenes < 1 or args.frames_per_scene < 1:
        ap.error(f"--scenes and --frames-per-scene must be >= 1; got {args.scenes} and {args.frames_per_scene}")
    cfg = RenderConfig.for_layout("tabletop", frames_per_scene=args.frames_per_scene)  # as its results were
    meshes = find_models(args.models_dir, cfg.objects)
    from tqdm import tqdm

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        worlds = {"bmp_textures": World(meshes, tmp / "bmp"), "png_textures": _PngTextureWorld(meshes, tmp / "png")}
        times: dict[str, list[float]] = {name: [] for name in worlds}
        for name, world in worlds.items():
            (tmp / name).mkdir()
            render_scene(world, cfg, args.seed, args.first_scene, tmp / "warmup")  # loads the libraries and the textures
        scenes = range(args.first_scene, args.first_scene + args.scenes)
        for scene in tqdm(scenes, desc="render_speed", unit="scene", dynamic_ncols=True):
            for name, world in worlds.items():
                t0 = time.perf_counter()
                render_scene(world, cfg, args.seed, scene, tmp / name)
                times[name].append(time.perf_counter() - t0)
        compared, differ = differing_files(tmp / "bmp_textures", tmp / "png_textures")
    med = {name: float(np.median(t)) for name, t in times.items()}
    doc = {
        **provenance("benchmarks.render_speed", argv, processes=1),
        "scenes": args.scenes, "frames_per_scene": args.frames_per_scene, "seed": args.seed,
        "first_scene": args.first_scene, "image": [cfg.width, cfg.height],
        "median_s_per_scene": med,
        "frames_per_s_one_worker": {name: args.frames_per_scene / m for name, m in med.items()},
        "speedup": med["png_textures"] / med["bmp_textures"],
        "files_compared": compared,
        "files_differing": differ,
    }
    print(f"{args.scenes} scenes of {args.frames_per_scene} frames, one core: median {med['bmp_textures']:.3f} s per "
          f"scene with the BMP textures, {med['png_textures']:.3f} s loading the PNGs ({doc['speedup']:.2f}x); "
          f"{len(differ)} of {compared} files differ")
    if args.json:
        write_json(args.json, doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
