"""Finding and loading the textured meshes the renderer draws: the YCB objects and your own.

Three layouts, each object named as its files name it:

* YCB-Video style: ``<dir>/<name>/textured_simple.obj`` (or ``textured.obj``) with ``texture_map.png``; the name
  is the folder's (``003_cracker_box``, ``my_widget``);
* loose files: ``<dir>/<name>.obj`` with ``<name>.png`` (or the ``map_Kd`` of its ``.mtl``), or ``<dir>/<name>.ply``
  with texture coordinates and a texture, or with vertex colours; the name is the file's stem;
* BOP ``models/``: ``<dir>/models_info.json`` and ``<dir>/obj_NNNNNN.ply`` (millimetres); the name is
  ``obj_NNNNNN`` and the BOP ``obj_id`` is ``NNNNNN``; ``symmetries_discrete`` / ``symmetries_continuous`` of
  ``models_info.json`` are kept with the mesh.

Units: metres unless declared (``unit="mm"``); BOP folders are millimetres. What pybullet cannot read directly (PLY,
vertex colours, millimetres) is written once as an OBJ in metres with a texture (vertex colours become one flat
colour per face) under ``cache_dir``, keyed by the source file's SHA-256, so every render of the same file uses
the same converted mesh. The YCB meshes are read as they are (their renders do not change).

Meshes are in their file's own frame: ground-truth rotations (object to camera) are relative to it.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from models.data.objects import YCBV_CLASSES
from refiner_rt.metadata import file_sha256

__all__ = ["Mesh", "MODEL_FILES", "TEXTURE_FILE", "OWN_OBJ_ID_START", "find_models", "list_models", "load_obj",
           "file_sha256"]

MODEL_FILES = ("textured_simple.obj", "textured.obj")
TEXTURE_FILE = "texture_map.png"
OWN_OBJ_ID_START = 1000  # BOP obj_id of your own objects (not YCB, not BOP): 1000, 1001, ... by sorted name
_BOP_NAME = re.compile(r"^obj_(\d{6})$")


@dataclass
class Mesh:
    """A triangle mesh in metres, in its file's frame: ``vertices (V, 3)``, ``faces (F, 3)`` int, and its files.

    Attributes:
        obj_id: the object's name (YCB id, folder or file name, or ``obj_NNNNNN``).
        obj_path: the OBJ file pybullet loads (the source, or its conversion in metres).
        texture_path: its texture image.
        number: the BOP ``obj_id`` written in ``scene_gt.json`` (YCB-V numbering for YCB ids).
        source: the file the mesh came from (its SHA-256 is recorded with the data and the models).
        unit: the source file's unit, ``"m"`` or ``"mm"``.
        symmetry: BOP ``symmetries_discrete`` / ``symmetries_continuous`` of the object, if any.
    """

    obj_id: str
    obj_path: Path
    texture_path: Path
    vertices: np.ndarray
    faces: np.ndarray
    number: int = 0
    source: Path | None = None
    unit: str = "m"
    symmetry: dict = field(default_factory=dict)

    def record(self) -> dict:
        """What a dataset and a model record of the mesh: ``{"obj_id", "mesh": {"file", "sha256", "unit"}}``."""
        src = Path(self.source or self.obj_path)
        out = {"obj_id": self.number, "mesh": {"file": src.name, "sha256": file_sha256(src), "unit": self.unit}}
        if self.symmetry:
            out["symmetry"] = self.symmetry
        return out



def load_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` and triangle faces ``(F, 3)`` (0-based) of a Wavefront OBJ file (polygons fan-split).

    Raises:
        ValueError: no vertices or faces, or a face index out of range (message names the file).
    """
    verts, faces = [], []
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                idx = [int(tok.split("/")[0]) for tok in line.split()[1:]]
                for k in range(1, len(idx) - 1):
                    faces.append([idx[0], idx[k], idx[k + 1]])
    v = np.asarray(verts, dtype=np.float64)
    fa = np.asarray(faces, dtype=np.int64)
    if len(v) == 0 or len(fa) == 0:
        raise ValueError(f"{path}: not a usable OBJ mesh: {len(v)} vertices, {len(fa)} faces")
    fa = np.where(fa > 0, fa - 1, len(v) + fa)  # OBJ indices are 1-based, negatives count from the end
    if fa.min() < 0 or fa.max() >= len(v):
        raise ValueError(f"{path}: face index out of range (1..{len(v)})")
    return v, fa


def _bop_info(models_dir: Path) -> dict[str, dict] | None:
    path = models_dir / "models_info.json"
    if not path.is_file():
        return None
    return json.loads(path.read_text())


def list_models(models_dir) -> list[str]:
    """The object names a models folder offers (sorted): YCB-style folders, loose OBJ/PLY files, BOP objects."""
    models_dir = Path(models_dir)
    names = set()
    for p in models_dir.iterdir():
        if p.is_dir() and any((p / n).is_file() for n in MODEL_FILES):
            names.add(p.name)
        elif p.suffix.lower() in (".obj", ".ply") and p.is_file():
            names.add(p.stem)
    return sorted(names)


def _texture_of_obj(path: Path) -> Path | None:
    """The texture of a loose OBJ file: ``<stem>.png``, else the first ``map_Kd`` of its material library."""
    png = path.with_suffix(".png")
    if png.is_file():
        return png
    for line in path.read_text(errors="replace").splitlines():
        if line.startswith("mtllib "):
            mtl = path.parent / line.split(maxsplit=1)[1].strip()
            if mtl.is_file():
                for ml in mtl.read_text(errors="replace").splitlines():
                    if ml.strip().startswith("map_Kd "):
                        tex = mtl.parent / ml.strip().split(maxsplit=1)[1]
                        if tex.is_file():
                            return tex
    return None


def _write_obj(folder: Path, vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
               texture: np.ndarray) -> tuple[Path, Path]:
    """An OBJ (metres) with per-corner texture coordinates, its material and texture, written atomically."""
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / TEXTURE_FILE), texture)
    (folder / "textured.mtl").write_text(f"newmtl material_0\nKd 1 1 1\nmap_Kd {TEXTURE_FILE}\n")
    lines = ["mtllib textured.mtl", "usemtl material_0"]
    lines += [f"v {a:.7f} {b:.7f} {c:.7f}" for a, b, c in vertices]
    lines += [f"vt {a:.6f} {b:.6f}" for a, b in uv]
    lines += [f"f {a + 1}/{ta + 1} {b + 1}/{tb + 1} {c + 1}/{tc + 1}"
              for (a, b, c), (ta, tb, tc) in zip(faces, uv_faces)]
    tmp = folder / "textured.obj.tmp"
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, folder / "textured.obj")
    return folder / "textured.obj", folder / TEXTURE_FILE


def _flat_colour_texture(face_colours: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A palette texture for per-face colours (BGR uint8 ``(F, 3)``): ``(texture, uv (C, 2), uv index per face)``.

    Each distinct colour gets a 4x4 px cell; a face's three corners all sample its cell's centre, so colours do
    not bleed across faces.
    """
    colours, index = np.unique(face_colours, axis=0, return_inverse=True)
    side = max(1, math.ceil(math.sqrt(len(colours))))
    cell = 4
    tex = np.zeros((side * cell, side * cell, 3), np.uint8)
    uv = np.zeros((len(colours), 2))
    for i, c in enumerate(colours):
        r, q = divmod(i, side)
        tex[r * cell:(r + 1) * cell, q * cell:(q + 1) * cell] = c
        uv[i] = ((q + 0.5) * cell / tex.shape[1], 1.0 - (r + 0.5) * cell / tex.shape[0])  # OBJ v points up
    return tex, uv, np.repeat(index.reshape(-1, 1), 3, axis=1)


def _convert(src: Path, scale: float, cache_dir: Path) -> tuple[Path, Path, np.ndarray, np.ndarray]:
    """``src`` (OBJ or PLY, texture or vertex colours) as an OBJ in metres with a texture, under ``cache_dir``."""
    import trimesh

    folder = Path(cache_dir) / f"{src.stem}-{file_sha256(src)[:16]}-{scale:g}"
    if (folder / "textured.obj").is_file() and (folder / TEXTURE_FILE).is_file():
        v, f = load_obj(folder / "textured.obj")
        return folder / "textured.obj", folder / TEXTURE_FILE, v, f
    mesh = trimesh.load(src, force="mesh", process=False)
    v = np.asarray(mesh.vertices, dtype=np.float64) * scale
    f = np.asarray(mesh.faces, dtype=np.int64)
    visual = mesh.visual
    uv = getattr(visual, "uv", None)
    image = getattr(getattr(visual, "material", None), "image", None)
    if image is None and getattr(visual, "material", None) is not None:
        image = getattr(visual.material, "baseColorTexture", None)
    if uv is not None and image is not None:
        tex = cv2.cvtColor(np.asarray(image.convert("RGB")), cv2.COLOR_RGB2BGR)
        obj, png = _write_obj(folder, v, f, np.asarray(uv, float), f, tex)
    elif getattr(visual, "kind", None) in ("vertex", "face"):
        rgb = np.asarray(visual.face_colors)[:, :3] if visual.kind == "face" else \
            np.asarray(visual.vertex_colors)[:, :3][f].mean(axis=1)
        tex, uv, uv_faces = _flat_colour_texture(np.round(rgb[:, ::-1]).astype(np.uint8))
        obj, png = _write_obj(folder, v, f, uv, uv_faces, tex)
    else:
        raise ValueError(f"{src}: the mesh has neither a texture (texture coordinates and an image) nor vertex "
                         "colours; the refiner learns from the object's appearance, so it needs one of them")
    return obj, png, v, f


def _object_number(name: str, own: list[str]) -> int:
    """The BOP obj_id written for ``name``: YCB-V numbering, ``obj_NNNNNN``'s NNNNNN, else 1000 + its rank."""
    if name in YCBV_CLASSES:
        return YCBV_CLASSES.index(name) + 1
    m = _BOP_NAME.match(name)
    if m:
        return int(m.group(1))
    return OWN_OBJ_ID_START + own.index(name)


def find_models(models_dir: Path, objects, *, unit: str | None = None, cache_dir: Path | None = None) -> dict[str, Mesh]:
    """Meshes of ``objects`` in a models folder (any of the three layouts of the module docstring).

    Args:
        models_dir: the folder.
        objects: object names (YCB ids, folder or file names, ``obj_NNNNNN``).
        unit: the meshes' unit, ``"m"`` or ``"mm"``; None: millimetres for a BOP folder, metres otherwise.
        cache_dir: where converted meshes go (default ``~/.cache/refiner-rt/meshes``).

    Raises:
        FileNotFoundError: the folder, an object's mesh or its texture is missing (the message lists
            what was looked for).
        ValueError: an unknown unit, or a mesh without texture or colours.
    """
    models_dir = Path(models_dir)
    if not models_dir.is_dir():
        raise FileNotFoundError(f"models folder not found: {models_dir} (expected <dir>/<name>/textured.obj + "
                                "texture_map.png, <dir>/<name>.obj|.ply, or a BOP models/ folder)")
    if unit not in (None, "m", "mm"):
        raise ValueError(f"unit must be 'm' or 'mm'; got {unit!r}")
    bop = _bop_info(models_dir)
    scale = {"m": 1.0, "mm": 1e-3}[unit or ("mm" if bop is not None else "m")]
    cache_dir = Path(cache_dir or Path.home() / ".cache" / "refiner-rt" / "meshes")
    own = sorted(o for o in objects if o not in YCBV_CLASSES and not _BOP_NAME.match(o))
    out = {}
    for obj in objects:
        folder = models_dir / obj
        symmetry = {}
        if folder.is_dir():  # YCB-Video style
            obj_path = next((folder / n for n in MODEL_FILES if (folder / n).is_file()), None)
            tex = folder / TEXTURE_FILE
            if obj_path is None or not tex.is_file():
                raise FileNotFoundError(
                    f"{folder}: missing {' or '.join(MODEL_FILES) if obj_path is None else TEXTURE_FILE}; expected the "
                    f"YCB-Video models layout <dir>/<name>/{{{', '.join(MODEL_FILES)}}} + {TEXTURE_FILE}"
                )
            source = obj_path
        else:
            source = next((models_dir / f"{obj}{ext}" for ext in (".obj", ".ply", ".OBJ", ".PLY")
                           if (models_dir / f"{obj}{ext}").is_file()), None)
            if source is None:
                raise FileNotFoundError(
                    f"{models_dir}: no mesh for object {obj!r}; expected {folder}/{{{', '.join(MODEL_FILES)}}} + "
                    f"{TEXTURE_FILE}, {models_dir / obj}.obj|.ply, or a BOP models/ folder with obj_NNNNNN.ply "
                    f"(available: {', '.join(list_models(models_dir)) or 'none'})")
            obj_path, tex = source, _texture_of_obj(source) if source.suffix.lower() == ".obj" else None
            m = _BOP_NAME.match(obj)
            if bop is not None and m:
                entry = bop.get(str(int(m.group(1)))) or {}
                symmetry = {k: entry[k] for k in ("symmetries_discrete", "symmetries_continuous") if entry.get(k)}
        if scale == 1.0 and tex is not None and obj_path.suffix.lower() == ".obj":
            v, f = load_obj(obj_path)
        else:
            obj_path, tex, v, f = _convert(source, scale, cache_dir)
        out[obj] = Mesh(obj, obj_path, tex, v, f, number=_object_number(obj, own), source=source,
                        unit="m" if scale == 1.0 else "mm", symmetry=symmetry)
    return out
