"""Object frames: the shipped models' YCB google_16k scan frame against the YCB-Video model frame.

The shipped refiners' rotations are relative to the scan frame of ``models/data/ycb_models/<id>/textured.obj``
(metres, origin near the object's base). Its axes coincide with the YCB-Video model frame's (an ICP fit of the
YCB-Video model points to the scan's vertices leaves 0.02-0.46 degrees of rotation), so **a rotation from YCB-Video
data applies as it is**; only the origin moves, by a per-object offset shipped in ``weights/frames.json``:
``X_scan = X_ycbv + offset``. For a pose ``x_cam = R @ X + t`` the translations differ by ``R @ offset``.

Conventions: ``R`` object to camera, ``(..., 3, 3)``; translations in metres, ``(..., 3)``.
"""

from __future__ import annotations

import json
from functools import lru_cache

import numpy as np

from refiner_rt.pretrained import WEIGHTS_DIR

__all__ = ["FRAMES_FILE", "ycbv_offset", "translation_from_ycbv", "translation_to_ycbv"]

FRAMES_FILE = WEIGHTS_DIR / "frames.json"


@lru_cache(maxsize=1)
def _offsets() -> dict[str, np.ndarray]:
    doc = json.loads(FRAMES_FILE.read_text())
    return {obj: np.asarray(d["ycbv_origin_in_scan_m"], dtype=np.float64) for obj, d in doc["objects"].items()}


def ycbv_offset(object_id: str) -> np.ndarray:
    """``(3,)`` metres: where the YCB-Video model frame's origin sits in the scan frame of ``object_id``.

    Raises:
        ValueError: no offset ships for ``object_id`` (the message lists the objects that have one).
    """
    offsets = _offsets()
    if object_id not in offsets:
        raise ValueError(f"no frame offset for object {object_id!r}; shipped for: {', '.join(sorted(offsets))}")
    return offsets[object_id].copy()


def _pose(R, t, what: str) -> tuple[np.ndarray, np.ndarray]:
    R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    if R.shape[-2:] != (3, 3) or t.shape[-1:] != (3,) or R.shape[:-2] != t.shape[:-1]:
        raise ValueError(f"{what}: expected R of shape (..., 3, 3) and t of shape (..., 3) with the same leading "
                         f"shape; got R {R.shape}, t {t.shape}")
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ValueError(f"{what}: R and t must be finite")
    return R, t


def translation_from_ycbv(object_id: str, R, t_ycbv) -> np.ndarray:
    """The translation of a YCB-Video pose ``(R, t_ycbv)`` for the shipped model's scan frame (metres):
    ``t_scan = t_ycbv - R @ offset``. The rotation ``R`` is the same in both frames."""
    R, t = _pose(R, t_ycbv, "translation_from_ycbv")
    return t - R @ ycbv_offset(object_id)


def translation_to_ycbv(object_id: str, R, t_scan) -> np.ndarray:
    """The translation of a scan-frame pose ``(R, t_scan)`` for the YCB-Video model frame (metres):
    ``t_ycbv = t_scan + R @ offset``."""
    R, t = _pose(R, t_scan, "translation_to_ycbv")
    return t + R @ ycbv_offset(object_id)
