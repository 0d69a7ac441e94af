"""The file-naming rules of a training run's outputs: each built here, and nowhere else."""

from __future__ import annotations

from pathlib import Path

__all__ = ["per_object_path", "per_object_siblings", "recipe_path_for"]


def per_object_path(base: str | Path, obj: str) -> Path:
    """The per-object sibling of a base file: ``runs/x.pt`` -> ``runs/x.<obj>.pt``, ``runs/x.int8.onnx`` ->
    ``runs/x.int8.<obj>.onnx`` (checkpoints, exported models and their INT8 versions alike)."""
    base = Path(base)
    return base.with_name(f"{base.stem}.{obj}{base.suffix}")


def recipe_path_for(ckpt: str | Path) -> Path:
    """Where the resolved recipe of a checkpoint is saved: ``<ckpt stem>.recipe.json`` beside it."""
    ckpt = Path(ckpt)
    return ckpt.with_name(f"{ckpt.stem}.recipe.json")


def per_object_siblings(base: str | Path) -> dict[str, Path]:
    """The per-object files beside ``base`` (:func:`per_object_path` of each object that has one): ``{object: path}``.

    Found by name, so your own objects' models are found like the YCB ones; ``x.int8.onnx`` beside ``x.onnx`` is
    the INT8 model, not an object's.
    """
    import glob

    from models.data.objects import OBJECT_NAME_PATTERN

    base = Path(base)
    out = {}
    for p in sorted(base.parent.glob(f"{glob.escape(base.stem)}.*{glob.escape(base.suffix)}")):
        obj = p.name[len(base.stem) + 1 : len(p.name) - len(base.suffix)]
        if obj != "int8" and OBJECT_NAME_PATTERN.match(obj) and p.is_file():
            out[obj] = p
    return out
