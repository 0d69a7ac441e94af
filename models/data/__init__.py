"""Training and evaluation data: YCB-Video and BOP readers, per-object splits, and the crop cache.

Importable without torch (ONNX evaluation uses it). Submodules load on first use, so
``from models.data import synth`` (the renderer) does not pull in the loaders and vice versa.

Conventions (docs/design.md §2): rotations object to camera, quaternions ``wxyz``, translations
in metres, boxes ``(x1, y1, x2, y2)`` in continuous pixel coordinates, images BGR.

Example::

    from models.data import load_bop, make_splits, CropCache, PAPER_OBJECTS
    samples = load_bop("renders/", objects=PAPER_OBJECTS, min_visib=0.3)
    splits = make_splits(samples, mode="frames", seed=0)
    cache = CropCache.build_or_load(splits.train_base, 64, "renders/.crops/train_base_64")
"""

from __future__ import annotations

import importlib

__all__ = [
    "Sample",
    "filter_samples",
    "load_ycbv",
    "load_bop",
    "make_splits",
    "Splits",
    "SplitSizes",
    "CropCache",
    "YCBV_CLASSES",
    "PAPER_OBJECTS",
    "PAPER_NAMES",
]

# public name -> defining submodule
_EXPORTS = {
    "Sample": "sample",
    "filter_samples": "sample",
    "load_ycbv": "ycbv",
    "load_bop": "bop",
    "make_splits": "splits",
    "Splits": "splits",
    "SplitSizes": "splits",
    "CropCache": "cache",
    "YCBV_CLASSES": "objects",
    "PAPER_OBJECTS": "objects",
    "PAPER_NAMES": "objects",
}


def __getattr__(name):
    if name in _EXPORTS:
        module = importlib.import_module(f"{__name__}.{_EXPORTS[name]}")
        return getattr(module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
