"""A contact sheet of network crops with their ground-truth object axes drawn: a look at the data.

Samples are read back through the dataset loaders (``load_bop`` / ``load_ycbv``), cut with the
shared crop rule, and the object's axes (x red, y green, z blue, origin at the object frame's
origin) are projected with ``K``, ``R``, ``t`` and mapped into the crop by the crop rule's affine
matrix. If rotations or crops were wrong, the axes would not follow the objects.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from refiner_rt.preprocess import crop_matrix, crop_to_square

__all__ = ["draw_axes_crop", "contact_sheet"]


def draw_axes_crop(image: np.ndarray, sample, size: int = 128, context: float = 1.2, axis_len: float = 0.06) -> np.ndarray:
    """The sample's crop (``size x size`` BGR) with its ground-truth axes drawn.

    Args:
        image: the full BGR image of ``sample``.
        sample: a :class:`models.data.Sample` (``R`` object-to-camera, ``t`` metres, ``K``, ``box_xyxy``).
        size: crop side in pixels.
        context: crop-rule context factor.
        axis_len: axis length in metres.
    """
    crop = crop_to_square(image, sample.box_xyxy, size, context)
    pts = np.array([[0, 0, 0], [axis_len, 0, 0], [0, axis_len, 0], [0, 0, axis_len]], dtype=np.float64)
    cam = pts @ np.asarray(sample.R).T + np.asarray(sample.t)
    if np.any(cam[:, 2] <= 1e-6):
        return crop
    uv = cam[:, :2] / cam[:, 2:3] * [sample.K[0][0], sample.K[1][1]] + [sample.K[0][2], sample.K[1][2]]
    # crop_matrix maps crop indices -> image indices; invert it to go image -> crop.
    M = np.vstack([crop_matrix(sample.box_xyxy, size, context), [0, 0, 1]])
    uvc = (np.c_[uv, np.ones(4)] @ np.linalg.inv(M).T)[:, :2]
    o = tuple(np.round(uvc[0] * 16).astype(int))
    for k, colour in enumerate([(0, 0, 255), (0, 255, 0), (255, 0, 0)]):
        cv2.line(crop, o, tuple(np.round(uvc[k + 1] * 16).astype(int)), colour, 2, cv2.LINE_AA, shift=4)
    return crop


def contact_sheet(samples, out_path: Path, n: int = 36, cols: int = 6, size: int = 128, seed: int = 0) -> Path:
    """Write a PNG grid of ``n`` random samples' crops with axes and object labels; returns the path."""
    if not samples:
        raise ValueError("no samples to preview")
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(samples), size=min(n, len(samples)), replace=False)
    tiles = []
    cache: dict = {}
    for i in sorted(pick):
        s = samples[i]
        if s.image_path not in cache:
            cache = {s.image_path: cv2.imread(str(s.image_path), cv2.IMREAD_COLOR)}
        tile = draw_axes_crop(cache[s.image_path], s, size)
        cv2.putText(tile, s.obj_id[:14], (3, size - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[r : r + cols], axis=1) for r in range(0, len(tiles), cols)]
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_path), np.concatenate(rows, axis=0))
    return out_path
