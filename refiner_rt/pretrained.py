"""The refiners that ship inside the package: listing them, finding their files, and their model-card data.

Each shipped model refines one YCB object (the paper's design: one network per object). Its files live in
``refiner_rt/weights/`` (package data, nothing is downloaded): ``<ycb id>.int8.onnx`` (INT8) and
``<ycb id>.onnx`` (fp32). ``weights/models.json`` holds what the model card says about each (held-out-scene error,
speed, recipe, mesh, training time); it is generated from the evaluation JSON by ``benchmarks/pretrained.py``,
never written by hand.

Frames: the shipped models were trained on renders of the YCB google_16k meshes in their **original YCB scan frame**
(origin near the object's base). Its axes are the YCB-Video / BOP ycbv model frame's, so their rotations are used as
they are; only the origin differs, by a per-object offset (:mod:`refiner_rt.frames` converts a translation). A
rotation refined by a shipped model maps that frame to the camera (``x_cam = R @ x_obj + t``).

Example:
    >>> from refiner_rt import load, pretrained_models
    >>> [m.object_id for m in pretrained_models()]
    >>> sess = load("003_cracker_box", int8=True, threads=1)   # refiner_rt.refiner.load: session or cascade
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["WEIGHTS_DIR", "STAGES", "PretrainedModel", "pretrained_models", "pretrained_model", "model_file_name"]

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
INDEX_FILE = "models.json"
INDEX_FORMAT = "refiner-rt/pretrained/1"


# A shipped object has a coarse refiner (U(0, 30) degree inputs) and may have a fine one (small inputs: the
# coarse refiner's output, or the previous video frame's; benchmarks/fine.py), run in turn by refiner_rt.cascade.
STAGES = ("coarse", "fine")


def model_file_name(object_id: str, int8: bool, stage: str = "coarse") -> str:
    """The file name of a shipped model (the one naming rule): ``<ycb id>.int8.onnx`` or ``<ycb id>.onnx`` for the
    coarse refiner, ``<ycb id>.fine.int8.onnx`` or ``<ycb id>.fine.onnx`` for the fine one."""
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {', '.join(STAGES)}; got {stage!r}")
    stem = object_id if stage == "coarse" else f"{object_id}.{stage}"
    return f"{stem}.int8.onnx" if int8 else f"{stem}.onnx"


@dataclass(frozen=True)
class PretrainedModel:
    """One shipped refiner and its model-card data.

    Attributes:
        object_id: the YCB id it refines, e.g. ``"003_cracker_box"``.
        arch: network architecture (``models`` registry name) and ``config``: its configuration.
        version: the model's version (bumped whenever its weights change).
        files: ``{"int8": file name, "fp32": file name}`` in :data:`WEIGHTS_DIR` (fp32 may be absent).
        heldout: held-out-scene error of the INT8 model through the runtime (degrees; ``mean_deg``, ``median_deg``,
            ``under_5_deg``, ``under_10_deg``, ``input_mean_deg``, ``n``, the split named in ``split``).
        card: everything else the model card shows (fp32 error, inside / cut by the border, speed, recipe command,
            mesh and its sha256, training wall time and machine).
        real: the INT8 model on real camera frames (degrees; ``mean_deg``, ``median_deg``, ``input_mean_deg``,
            ``drift_mean_deg``: a perfect input pose moved by, ``instances``, ``videos``, the folder in ``data``),
            ``{}`` when not measured (``benchmarks/real.py``).
        fine: the object's fine refiner, ``{}`` when none ships: ``files`` (``{"int8": ..., "fp32": ...}``),
            ``version``, and its card (``cascade``: the coarse refiner alone and the cascade on the same fresh
            renders; ``benchmarks/fine.py``).
    """

    object_id: str
    arch: str
    version: str
    files: dict
    heldout: dict
    config: dict = field(default_factory=dict)
    card: dict = field(default_factory=dict)
    real: dict = field(default_factory=dict)
    fine: dict = field(default_factory=dict)

    @property
    def stages(self) -> list[str]:
        """The refiners that ship for this object: ``["coarse"]`` or ``["coarse", "fine"]``."""
        return ["coarse", "fine"] if self.fine.get("files") else ["coarse"]

    def path(self, int8: bool = True, stage: str = "coarse") -> Path:
        """The model's ONNX file (INT8 by default): the coarse refiner's, or the fine one's (``stage="fine"``).

        Raises:
            ValueError: an unknown stage, no fine refiner for this object, or the fp32 file was asked for but is not
                shipped.
        """
        if stage not in STAGES:
            raise ValueError(f"stage must be one of {', '.join(STAGES)}; got {stage!r}")
        files = self.files if stage == "coarse" else self.fine.get("files", {})
        if not files:
            raise ValueError(f"{self.object_id}: no fine refiner ships (refiner_rt.pretrained_models() lists each "
                             "object's stages)")
        key = "int8" if int8 else "fp32"
        name = files.get(key)
        if not name:
            what = key if stage == "coarse" else f"{key} {stage}"
            raise ValueError(f"{self.object_id}: no {what} model ships (files: {sorted(files)}); use int8=True")
        return WEIGHTS_DIR / name


def _index() -> dict:
    path = WEIGHTS_DIR / INDEX_FILE
    if not path.is_file():
        return {"format": INDEX_FORMAT, "models": {}}
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: the pretrained models' index is unreadable ({exc}); reinstall refiner-rt") from None
    if not isinstance(doc, dict) or doc.get("format") != INDEX_FORMAT or not isinstance(doc.get("models"), dict):
        raise ValueError(f"{path}: not a pretrained models' index of format {INDEX_FORMAT!r}; reinstall refiner-rt")
    return doc


def pretrained_models() -> list[PretrainedModel]:
    """The refiners shipped in this package, sorted by YCB id (empty when none ships)."""
    out = []
    for obj, m in sorted(_index()["models"].items()):
        out.append(PretrainedModel(object_id=obj, arch=m["arch"], version=str(m["version"]), files=dict(m["files"]),
                                   heldout=dict(m["heldout"]), config=dict(m.get("config", {})),
                                   card=dict(m.get("card", {})), real=dict(m.get("real", {})),
                                   fine=dict(m.get("fine", {}))))
    return out


def pretrained_model(object_id: str) -> PretrainedModel:
    """The shipped refiner of one object.

    Args:
        object_id: a YCB id string such as ``"003_cracker_box"``.

    Raises:
        TypeError: ``object_id`` is not a string.
        ValueError: no model ships for that object (the message lists the ones that do).
    """
    if not isinstance(object_id, str):
        raise TypeError(f"object_id must be a YCB id string such as '003_cracker_box'; got {type(object_id).__name__}")
    models = {m.object_id: m for m in pretrained_models()}
    if object_id not in models:
        shipped = ", ".join(sorted(models)) or "none"
        raise ValueError(f"no pretrained model for object {object_id!r}; shipped: {shipped}")
    return models[object_id]
