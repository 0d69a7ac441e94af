"""Camera-like photometric augmentation of training crops, as the BOP challenge's winners train on renders (CosyPose's
and GDRNPP's image augmentations): what a real camera does to the object's pixels that a renderer does not.

Each operation is applied to a crop with its own probability (a recipe field ``aug_<name>``, 0 = off) and a strength
drawn per crop from a fixed range, in a camera's order: the optics blur, then the sensor's noise, then the camera's
processing (white balance, exposure, contrast, saturation, sharpening) and the JPEG encoder.

=================  =====================================================================================
operation          per crop, when picked
=================  =====================================================================================
``motion_blur``    a line kernel of 3 to 9 px at a random angle (a moving camera or object)
``blur``           Gaussian blur, sigma in [0.3, 1.5] px (defocus)
``sensor_noise``   Gaussian noise, std in [2, 12] grey levels, half the time per channel, else the same on all
``white_balance``  per-channel gains in [0.75, 1.25] (a camera's colour temperature)
``brightness``     a gain in [0.5, 1.6]
``contrast``       a contrast factor in [0.5, 1.6] about the crop's mean
``colour``         saturation factor in [0.3, 2.0] (towards grey, or more vivid)
``sharpness``      an unsharp mask of amount [0.5, 2.5] (a camera's sharpening halo)
``jpeg``           JPEG at quality [30, 90]
=================  =====================================================================================

:func:`photometric` takes and returns a ``uint8`` NHWC batch (BGR) and seeds its draws from a ``torch.Generator``,
so a run's crops depend only on its seed. Each crop is changed with OpenCV (a few microseconds per operation on a
64 x 64 crop). The module needs no torch to import: the recipe reads :data:`PHOTOMETRIC_OPS` without it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    import torch

__all__ = ["PHOTOMETRIC_OPS", "photometric", "validate_probabilities"]

# The operations in the order they are applied, with what each does (the recipe's help text).
PHOTOMETRIC_OPS: dict[str, str] = {
    "motion_blur": "line-kernel motion blur of 3-9 px at a random angle",
    "blur": "Gaussian blur, sigma 0.3-1.5 px",
    "sensor_noise": "Gaussian sensor noise, std 2-12 grey levels",
    "white_balance": "per-channel gains 0.75-1.25",
    "brightness": "a gain of 0.5-1.6",
    "contrast": "a contrast factor of 0.5-1.6",
    "colour": "a saturation factor of 0.3-2.0",
    "sharpness": "an unsharp mask of amount 0.5-2.5",
    "jpeg": "JPEG compression at quality 30-90",
}


def validate_probabilities(probs: dict[str, float]) -> dict[str, float]:
    """``probs`` checked: names among :data:`PHOTOMETRIC_OPS`, values in [0, 1]; returns it.

    Raises:
        ValueError: naming the operation and what was expected.
    """
    for name, p in probs.items():
        if name not in PHOTOMETRIC_OPS:
            raise ValueError(f"unknown photometric augmentation {name!r}; expected one of {', '.join(PHOTOMETRIC_OPS)}")
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0.0 <= float(p) <= 1.0:
            raise ValueError(f"aug_{name} must be a probability in [0, 1]; got {p!r}")
    return probs


def _motion_kernel(rng: np.random.Generator, size: int = 9) -> np.ndarray:
    """A normalised ``size x size`` line kernel: length 3-9 px, angle uniform (a pixel's weight falls linearly with
    its distance from the segment, to zero at one pixel)."""
    length, angle = rng.uniform(3.0, 9.0), rng.uniform(0.0, np.pi)
    r = np.arange(size, dtype=np.float32) - size // 2
    yy, xx = np.meshgrid(r, r, indexing="ij")
    along = xx * np.cos(angle) + yy * np.sin(angle)
    across = -xx * np.sin(angle) + yy * np.cos(angle)
    beyond = np.maximum(np.abs(along) - length / 2, 0.0)
    w = np.maximum(1.0 - np.sqrt(across**2 + beyond**2), 0.0).astype(np.float32)
    return w / w.sum()


def _apply(name: str, crop: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Operation ``name`` on one ``S x S x 3`` float32 BGR crop (values may leave [0, 255] until the end)."""
    if name == "motion_blur":
        return cv2.filter2D(crop, -1, _motion_kernel(rng), borderType=cv2.BORDER_REPLICATE)
    if name == "blur":
        return cv2.GaussianBlur(crop, (0, 0), rng.uniform(0.3, 1.5), borderType=cv2.BORDER_REPLICATE)
    if name == "sensor_noise":
        std = rng.uniform(2.0, 12.0)
        if rng.uniform() < 0.5:  # the same noise on the three channels (a grey sensor pattern)
            return crop + std * rng.standard_normal(crop.shape[:2], dtype=np.float32)[..., None]
        return crop + std * rng.standard_normal(crop.shape, dtype=np.float32)
    if name == "white_balance":
        return crop * rng.uniform(0.75, 1.25, 3).astype(np.float32)
    if name == "brightness":
        return crop * np.float32(rng.uniform(0.5, 1.6))
    if name == "contrast":
        mean = crop.mean()
        return (crop - mean) * np.float32(rng.uniform(0.5, 1.6)) + mean
    if name == "colour":
        grey = crop @ np.array([0.114, 0.587, 0.299], np.float32)  # BGR luma
        return grey[..., None] + (crop - grey[..., None]) * np.float32(rng.uniform(0.3, 2.0))
    if name == "sharpness":
        soft = cv2.GaussianBlur(crop, (0, 0), 1.0, borderType=cv2.BORDER_REPLICATE)
        return crop + (crop - soft) * np.float32(rng.uniform(0.5, 2.5))
    if name == "jpeg":
        ok, buf = cv2.imencode(".jpg", np.clip(crop, 0, 255).round().astype(np.uint8),
                               [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(30, 91))])
        return cv2.imdecode(buf, cv2.IMREAD_COLOR).astype(np.float32) if ok else crop
    raise ValueError(f"unknown photometric augmentation {name!r}; expected one of {', '.join(PHOTOMETRIC_OPS)}")


def photometric(images: "torch.Tensor", probs: dict[str, float], gen: "torch.Generator") -> "torch.Tensor":
    """The operations of ``probs`` (name -> probability per crop, :data:`PHOTOMETRIC_OPS`) on a ``uint8`` NHWC batch,
    in the table's order; each crop draws its own strength. Returns ``uint8`` NHWC (the input when nothing is
    picked). One draw from ``gen`` seeds the batch's choices, so a run's crops depend only on its seed."""
    import torch

    n = images.shape[0]
    active = [(name, float(probs[name])) for name in PHOTOMETRIC_OPS if probs.get(name, 0) > 0]
    if n == 0 or not active:
        return images
    rng = np.random.default_rng(int(torch.randint(0, 2**62, (1,), generator=gen)))
    picks = np.stack([rng.uniform(size=n) < p for _, p in active], axis=1)  # (n, ops)
    rows = np.flatnonzero(picks.any(axis=1))
    if len(rows) == 0:
        return images
    out = images.numpy().copy()
    for i in rows:
        crop = out[i].astype(np.float32)
        for (name, _), on in zip(active, picks[i]):
            if on:
                crop = _apply(name, crop, rng)
        out[i] = np.clip(crop, 0, 255).round().astype(np.uint8)
    return torch.from_numpy(out)
