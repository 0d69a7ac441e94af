"""The object vocabulary: YCB ids of the 21 YCB-Video classes and the paper's nine objects.

Every loader names objects by their YCB id string (``"003_cracker_box"``); this module maps the
numeric ids the file formats use to those strings:

* YCB-Video ``-meta.mat`` ``cls_indexes`` are **1-based** indices into the 21 classes below, in the
  order of YCB-Video's ``classes.txt`` (Xiang et al., "PoseCNN", RSS 2018);
* BOP's YCB-V ``obj_id`` uses the same numbers (BOP toolkit, ``bop_toolkit_lib/dataset_params.py``,
  ``ycbv``: objects 1..21 in the YCB-Video order), and so do the project's rendered BOP scenes.

The paper's nine objects (Jain & Dellaert, "Fast 3D Pose Refinement with RGB Images", Table 1)
are listed in docs/design.md §6.1.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

__all__ = [
    "YCBV_CLASSES",
    "PAPER_OBJECTS",
    "PAPER_NAMES",
    "ycb_id_from_class_index",
    "class_index_from_ycb_id",
    "BOP_YCBV_OBJ_IDS",
    "validate_object_ids",
    "SCAN_FRAME_SYMMETRIES",
    "OBJECT_NAME_PATTERN",
    "object_names",
]

# An object's name: a YCB id, a mesh folder or file name, or ``obj_NNNNNN`` of a BOP models/ folder.
OBJECT_NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_+-]*$")

# YCB-Video classes.txt, in order: class index i (1-based) is YCBV_CLASSES[i - 1].
YCBV_CLASSES: tuple[str, ...] = (
    "002_master_chef_can",
    "003_cracker_box",
    "004_sugar_box",
    "005_tomato_soup_can",
    "006_mustard_bottle",
    "007_tuna_fish_can",
    "008_pudding_box",
    "009_gelatin_box",
    "010_potted_meat_can",
    "011_banana",
    "019_pitcher_base",
    "021_bleach_cleanser",
    "024_bowl",
    "025_mug",
    "035_power_drill",
    "036_wood_block",
    "037_scissors",
    "040_large_marker",
    "051_large_clamp",
    "052_extra_large_clamp",
    "061_foam_brick",
)

# The paper's nine objects: YCB id -> the name the paper's tables use (docs/design.md §6.1).
PAPER_NAMES: dict[str, str] = {
    "002_master_chef_can": "Tin Can",
    "003_cracker_box": "Crackers",
    "004_sugar_box": "Sugar Box",
    "006_mustard_bottle": "Mustard",
    "009_gelatin_box": "Gelatin",
    "011_banana": "Banana",
    "021_bleach_cleanser": "Bleach",
    "035_power_drill": "Drill",
    "037_scissors": "Scissors",
}
PAPER_OBJECTS: tuple[str, ...] = tuple(PAPER_NAMES)

# BOP's symmetry of the paper's objects that have one (YCB-Video's models_info.json: the master chef can turns about
# its axis; the other eight have none), in the scan frame of models/data/ycb_models, where the can's axis is z (its
# side is a cylinder of radius 49.8 mm about x = -17.1, y = -9.7 mm, the fitted centre moving under 0.1 mm over 60 mm
# of height). Scoring uses it (the error to the closest turn about the axis, models.data.symmetry); the real YCB-Video
# frames also need it, their can annotations being unreliable about that axis.
SCAN_FRAME_SYMMETRIES = {
    "002_master_chef_can": {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [-17.1, -9.7, 0]}]},
}

# BOP YCB-V obj_id -> YCB id (same numbering as YCB-Video's 1-based class index).
BOP_YCBV_OBJ_IDS: dict[int, str] = {i + 1: name for i, name in enumerate(YCBV_CLASSES)}


def ycb_id_from_class_index(index: int) -> str:
    """YCB id of a YCB-Video class index.

    Args:
        index: 1-based class index as stored in ``-meta.mat`` ``cls_indexes`` (1..21).

    Returns:
        The YCB id string, e.g. ``2 -> "003_cracker_box"``.

    Raises:
        ValueError: an index outside 1..21.
    """
    if int(index) != index or not 1 <= index <= len(YCBV_CLASSES):
        raise ValueError(f"YCB-Video class index must be an integer in 1..{len(YCBV_CLASSES)}; got {index!r}")
    return YCBV_CLASSES[int(index) - 1]


def class_index_from_ycb_id(ycb_id: str) -> int:
    """1-based YCB-Video class index (= BOP YCB-V obj_id) of a YCB id string.

    Raises:
        ValueError: a name that is not one of the 21 YCB-Video classes.
    """
    try:
        return YCBV_CLASSES.index(ycb_id) + 1
    except ValueError:
        raise ValueError(f"unknown YCB id {ycb_id!r}; expected one of {', '.join(YCBV_CLASSES)}") from None


def validate_object_ids(objects: Iterable[str] | None, known: Iterable[str] = YCBV_CLASSES) -> frozenset[str] | None:
    """Check an object filter and return it as a set (``None`` = no filter, all objects).

    Args:
        objects: YCB id strings (``"003_cracker_box"``), or ``None``. A single string is refused,
            so ``"003_cracker_box"`` is not read as a set of characters.
        known: the ids the caller can produce.

    Raises:
        TypeError: a bare string or non-string entries.
        ValueError: an empty filter or an unknown id (the message lists the known ids).
    """
    if objects is None:
        return None
    if isinstance(objects, str):
        raise TypeError(f"objects must be a list of YCB id strings, not one string; got {objects!r} (use [{objects!r}])")
    chosen = list(objects)
    if not chosen:
        raise ValueError("objects must name at least one YCB id (or be None for all objects); got an empty list")
    known = tuple(sorted(known))
    for name in chosen:
        if not isinstance(name, str):
            raise TypeError(f"objects must be YCB id strings such as '003_cracker_box'; got {name!r} ({type(name).__name__})")
        if name not in known:
            raise ValueError(f"unknown object {name!r}; expected YCB ids from: {', '.join(known)}")
    return frozenset(chosen)


OBJECTS_FILE = "objects.json"  # a rendered dataset's record of its objects, beside its scene folders


def dataset_objects(data) -> dict[str, dict]:
    """The objects a rendered dataset records in ``<data>/objects.json``: name -> ``{"obj_id": int, "mesh":
    {"file", "sha256", "unit"}, "symmetry": {...}}``; ``{}`` for a dataset without that file (real data, or
    renders of the YCB objects from before the file existed, which use the YCB-V numbering)."""
    import json
    from pathlib import Path

    path = Path(data) / OBJECTS_FILE
    if not path.is_file():
        return {}
    record = json.loads(path.read_text())
    if not isinstance(record, dict) or not all(isinstance(v, dict) and isinstance(v.get("obj_id"), int)
                                               for v in record.values()):
        raise ValueError(f"{path}: expected an object of name -> {{\"obj_id\": int, ...}}")
    return record


def obj_id_map_for(data) -> dict[int, str]:
    """BOP ``obj_id`` -> object name of a dataset: its ``objects.json`` record over the YCB-V numbering."""
    ids = dict(BOP_YCBV_OBJ_IDS)
    ids.update({v["obj_id"]: name for name, v in dataset_objects(data).items()})
    return ids


def object_names(text: str) -> list[str]:
    """Comma-separated object names (each :data:`OBJECT_NAME_PATTERN`): the one parser of ``--objects`` lists.

    Raises:
        ValueError: an empty list or a name with other characters, the text quoted.
    """
    names = [v.strip() for v in text.split(",") if v.strip()]
    if not names or not all(OBJECT_NAME_PATTERN.match(n) for n in names):
        raise ValueError(f"expected comma-separated object names like 003_cracker_box,my_widget (letters, digits, "
                         f"_ + -); got {text!r}")
    return names
