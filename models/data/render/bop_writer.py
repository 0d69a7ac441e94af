"""The BOP writer: JSON files as the BOP toolkit writes them, boxes and the occlusion test behind ``visib_fract``."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np


def _bop_json(path: Path, content: dict) -> None:
    """Write JSON as ``bop_toolkit_lib.inout.save_json`` does (one image id per line), atomically."""
    items = sorted(content.items(), key=lambda kv: int(kv[0]))
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w") as f:
        f.write("{\n")
        for i, (k, v) in enumerate(items):
            f.write(f'  "{k}": {json.dumps(v, sort_keys=True)}' + (",\n" if i < len(items) - 1 else "\n"))
        f.write("}")
    os.replace(tmp, path)


def _may_be_occluded(vis: np.ndarray, seg: np.ndarray, b: int, box: np.ndarray, width: int, height: int) -> bool:
    """Whether body ``b`` can be partly hidden: its projection reaches the image border, or its visible
    pixels touch another object's (an occluder always borders what it hides). Otherwise its visible
    pixels are its whole silhouette."""
    x1, y1, x2, y2 = box
    if x1 < 1 or y1 < 1 or x2 > width - 2 or y2 > height - 2:
        return True
    x, y, w, h = cv2.boundingRect(vis.view(np.uint8))
    if w == 0:
        return True
    a0, a1 = max(y - 2, 0), min(y + h + 2, height)
    b0, b1 = max(x - 2, 0), min(x + w + 2, width)
    local = vis[a0:a1, b0:b1].astype(np.uint8)
    ring = cv2.dilate(local, np.ones((3, 3), np.uint8)) > local
    neighbours = seg[a0:a1, b0:b1][ring]
    return bool(np.any((neighbours >= 0) & (neighbours != b)))


def _bbox(mask: np.ndarray) -> list[int]:
    """BOP box ``[x, y, w, h]`` of a mask, ``[-1, -1, -1, -1]`` when empty (as the BOP toolkit writes it)."""
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))  # the tight box of the non-zero pixels; (0, 0, 0, 0) if none
    return [int(x), int(y), int(w), int(h)] if w else [-1, -1, -1, -1]
