"""Set the crop filter a refiner model asks the runtime for (metadata ``crop_filter``), its weights unchanged.

The crop rule's filter (:data:`refiner_rt.preprocess.CROP_FILTERS`) is part of the model contract: the runtime cuts
crops the way the model's metadata says. A model trained before the key existed reads as ``"none"``; this writes a
copy whose metadata names another filter, for a model measured to do better with it (``benchmarks/appearance.py``
with ``--model``), and checks that the runtime loads the copy.
"""

from __future__ import annotations

from pathlib import Path

import onnx

from refiner_rt.metadata import parse_metadata
from refiner_rt.preprocess import CROP_FILTERS

__all__ = ["with_crop_filter"]


def with_crop_filter(src: str | Path, dst: str | Path, crop_filter: str) -> Path:
    """Copy the ONNX model ``src`` to ``dst`` with metadata ``crop_filter`` set; the graph and weights unchanged.

    Raises:
        ValueError: an unknown ``crop_filter``, or ``src`` is not a refiner model (its metadata fails the contract).
    """
    if crop_filter not in CROP_FILTERS:
        raise ValueError(f"crop_filter must be one of {CROP_FILTERS}; got {crop_filter!r}")
    model = onnx.load(str(src))
    props = {p.key: p.value for p in model.metadata_props}
    parse_metadata(props)  # refuses a file that is not a refiner model, naming the key
    props.pop("crop_filter", None)
    if crop_filter != "none":
        props["crop_filter"] = crop_filter
    parse_metadata(props)
    del model.metadata_props[:]
    for key, value in props.items():
        model.metadata_props.add(key=key, value=value)
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(dst))
    return dst
