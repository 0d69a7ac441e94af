"""Camera-like photometric augmentation of training crops, as the BOP challenge's winners train on renders (CosyPose's
and GDRNPP's image augmentations): what a real camera does to the object's pixels that a renderer does not.

Each operation is applied to a crop with its own probability (a recipe field ``aug_<name>``, 0 = off) and a strength
drawn per crop from a fixed range, in a camera's order: the sensor's resolution and the optics blur, then the
sensor's noise, then the camera's processing (white balance, exposure, tone curve, contrast, saturation, sharpening) and the JPEG encoder.

=================  =====================================================================================
operation          per crop, when picked
=================  =====================================================================================
``downscale``      a lower resolution: down to [0.35, 0.9] of the size (area), back up bilinearly
``motion_blur``    a line kernel of 3 to 9 px at a random angle (a moving camera or object)
``blur``           Gaussian blur, sigma in [0.3, 1.5] px (defocus)
``sensor_noise``   Gaussian noise, std in [2, 12] grey levels, half the time per channel, else the same on all
``white_balance``  per-channel gains in [0.75, 1.25] (a camera's colour temperature)
``brightness``     a gain in [0.5, 1.6]
``gamma``          a tone curve, gamma in [0.7, 1.4] on [0, 1] values
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

__all__ = ["PHOTOMETRIC_OPS", "apply_op", "draw_strength", "motion_kernel", "photometric", "validate_probabilities"]

# The operations in the order they are applied, with what each does (the recipe's help text).
PHOTOMETRIC_OPS: dict[str, str] = {
    "downscale": "a lower resolution: down to 0.35-0.9 of the size and back",
    "motion_blur": "line-kernel motion blur of 3-9 px at a random angle",
    "blur": "Gaussian blur, sigma 0.3-1.5 px",
    "sensor_noise": "Gaussian sensor noise, std 2-12 grey levels",
    "white_balance": "per-channel gains 0.75-1.25",
    "brightness": "a gain of 0.5-1.6",
    "gamma": "a tone curve: gamma 0.7-1.4",
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


def motion_kernel(length: float, angle_rad: float, size: int = 9) -> np.ndarray:
    """A normalised ``size x size`` line kernel of ``length`` px at ``angle_rad`` (a pixel's weight falls linearly
    with its distance from the segment, to zero at one pixel)."""
    r = np.arange(size, dtype=np.float32) - size // 2
    yy, xx = np.meshgrid(r, r, indexing="ij")
    along = xx * np.cos(angle_rad) + yy * np.sin(angle_rad)
    across = -xx * np.sin(angle_rad) + yy * np.cos(angle_rad)
    beyond = np.maximum(np.abs(along) - length / 2, 0.0)
    w = np.maximum(1.0 - np.sqrt(across**2 + beyond**2), 0.0).astype(np.float32)
    return w / w.sum()


def _motion_kernel(rng: np.random.Generator, size: int = 9) -> np.ndarray:
    """:func:`motion_kernel` with a random length of 3-9 px and a uniform angle."""
    length, angle = rng.uniform(3.0, 9.0), rng.uniform(0.0, np.pi)
    return motion_kernel(length, angle, size)


def draw_strength(name: str, rng: np.random.Generator):
    """The strength of operation ``name`` drawn from its training range (the table above); the argument
    :func:`apply_op` takes as ``strength``."""
    if name == "downscale":
        return float(rng.uniform(0.35, 0.9))
    if name == "motion_blur":
        return float(rng.uniform(3.0, 9.0)), float(rng.uniform(0.0, np.pi))
    if name == "blur":
        return float(rng.uniform(0.3, 1.5))
    if name == "sensor_noise":
        std = float(rng.uniform(2.0, 12.0))
        return std, bool(rng.uniform() >= 0.5)  # (std, per channel); else the same noise on the three channels
    if name == "white_balance":
        return tuple(float(g) for g in rng.uniform(0.75, 1.25, 3))
    if name == "brightness":
        return float(rng.uniform(0.5, 1.6))
    if name == "gamma":
        return float(rng.uniform(0.7, 1.4))
    if name == "contrast":
        return float(rng.uniform(0.5, 1.6))
    if name == "colour":
        return float(rng.uniform(0.3, 2.0))
    if name == "sharpness":
        return float(rng.uniform(0.5, 2.5))
    if name == "jpeg":
        return int(rng.integers(30, 91))
    raise ValueError(f"unknown photometric augmentation {name!r}; expected one of {', '.join(PHOTOMETRIC_OPS)}")


def apply_op(name: str, image: np.ndarray, strength, rng: np.random.Generator | None = None) -> np.ndarray:
    """Operation ``name`` at a given ``strength`` on one ``H x W x 3`` float32 BGR image (a crop in training, a
    whole frame in ``benchmarks/appearance.py``'s stress test); values may leave [0, 255] until the caller clips.

    ``strength`` per operation: ``downscale`` the resolution factor (down with area averaging, back up bilinearly);
    ``motion_blur`` ``(length_px, angle_rad)``; ``blur`` sigma in px; ``sensor_noise`` ``(std, per_channel)`` in grey
    levels; ``white_balance`` the ``(b, g, r)`` gains; ``brightness`` a gain; ``gamma`` the exponent on [0, 1]
    values; ``contrast`` a factor about the image's mean; ``colour`` a saturation factor about the luma;
    ``sharpness`` an unsharp-mask amount (sigma 1 px); ``jpeg`` the quality. ``rng`` draws the sensor noise.
    """
    if name == "downscale":
        h, w = image.shape[:2]
        small = cv2.resize(image, (max(1, round(w * strength)), max(1, round(h * strength))),
                           interpolation=cv2.INTER_AREA)
        return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    if name == "motion_blur":
        size = 9 if strength[0] <= 9 else 2 * int(np.ceil(strength[0] / 2)) + 1  # 9: the training range's kernel
        kernel = motion_kernel(*strength, size=size)
        return cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REPLICATE)
    if name == "blur":
        return cv2.GaussianBlur(image, (0, 0), strength, borderType=cv2.BORDER_REPLICATE)
    if name == "sensor_noise":
        std, per_channel = strength
        rng = rng if rng is not None else np.random.default_rng(0)
        if not per_channel:  # the same noise on the three channels (a grey sensor pattern)
            return image + std * rng.standard_normal(image.shape[:2], dtype=np.float32)[..., None]
        return image + std * rng.standard_normal(image.shape, dtype=np.float32)
    if name == "white_balance":
        return image * np.asarray(strength, np.float32)
    if name == "brightness":
        return image * np.float32(strength)
    if name == "gamma":
        return 255.0 * (np.clip(image, 0, 255) / 255.0) ** np.float32(strength)
    if name == "contrast":
        mean = image.mean()
        return (image - mean) * np.float32(strength) + mean
    if name == "colour":
        grey = image @ np.array([0.114, 0.587, 0.299], np.float32)  # BGR luma
        return grey[..., None] + (image - grey[..., None]) * np.float32(strength)
    if name == "sharpness":
        soft = cv2.GaussianBlur(image, (0, 0), 1.0, borderType=cv2.BORDER_REPLICATE)
        return image + (image - soft) * np.float32(strength)
    if name == "jpeg":
        ok, buf = cv2.imencode(".jpg", np.clip(image, 0, 255).round().astype(np.uint8),
                               [cv2.IMWRITE_JPEG_QUALITY, int(strength)])
        return cv2.imdecode(buf, cv2.IMREAD_COLOR).astype(np.float32) if ok else image
    raise ValueError(f"unknown photometric augmentation {name!r}; expected one of {', '.join(PHOTOMETRIC_OPS)}")


def _apply(name: str, crop: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Operation ``name`` on one ``S x S x 3`` float32 BGR crop at a strength drawn from its range."""
    return apply_op(name, crop, draw_strength(name, rng), rng)


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
