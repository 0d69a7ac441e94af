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

import math
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    import torch

__all__ = ["PHOTOMETRIC_OPS", "apply_op", "draw_strength", "motion_kernel", "photometric", "validate_probabilities",
           "rotate_in_plane", "replace_background", "paste_occluders", "relight", "jitter_box_and_colour"]

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


# The crop changes of the training loop, in the order it applies them: an in-plane turn, a new background, pasted
# occluders, another scene's light, colour and box jitter; then the photometric operations above.


def rotate_in_plane(
    images: "torch.Tensor", masks: "torch.Tensor | None", max_deg: float, gen: "torch.Generator"
) -> "tuple[torch.Tensor, torch.Tensor | None, np.ndarray]":
    """Rotate every crop about its centre by an angle from U(-max_deg, max_deg): uint8 NHWC in and out.

    A crop centred on the box shows the object around the viewing ray, so turning the image by ``phi`` (a pixel
    offset ``(dx, dy)`` -> ``R(phi) (dx, dy)`` with x right and y down) shows the object turned by ``phi`` about
    that ray: in the ray frame ``q_gt -> q_z(phi) * q_gt``, and since the coarse pose is ``q_gt * q_noise`` the
    input becomes ``q_z(phi) * q_in`` with the same label. Corners the turn uncovers are filled by reflection;
    masks are turned with nearest sampling and zeros outside.

    Returns:
        the turned images, the turned masks (None without masks), and ``q_z(phi)`` per crop ``(N, 4)`` wxyz float64.
    """
    import torch
    import torch.nn.functional as F

    from models.nets.fusion import turn_grid

    n = images.shape[0]
    phi = (torch.rand(n, generator=gen, dtype=torch.float64) * 2 - 1) * math.radians(max_deg)
    # The grid F.affine_grid would give, written out: its batched matrix product is the slow part.
    grid = turn_grid(phi.float(), images.shape[1])
    x = images.permute(0, 3, 1, 2).float()
    x = F.grid_sample(x, grid, mode="bilinear", padding_mode="reflection", align_corners=False)
    out = x.clamp(0, 255).round().to(torch.uint8).permute(0, 2, 3, 1).contiguous()
    if masks is not None:
        m = F.grid_sample(masks[:, None].float(), grid, mode="nearest", padding_mode="zeros", align_corners=False)
        masks = m[:, 0].round().to(masks.dtype)
    half = phi.numpy() / 2
    q_turn = np.stack([np.cos(half), np.zeros(n), np.zeros(n), np.sin(half)], axis=1)
    return out, masks, q_turn


def replace_background(images: "torch.Tensor", masks: "torch.Tensor", p: float, gen: "torch.Generator") -> "torch.Tensor":
    """Give each crop with a mask, with probability ``p``, a new background: uint8 NHWC in and out.

    ``masks`` is ``(N, S, S)`` uint8, 1 on the instance's visible pixels (all zeros: no mask, left as is).
    The new background is, half the time each, another crop of the batch (real clutter, other objects)
    or a smooth random colour field (a 4x4 colour grid, bicubic upsampled, plus pixel noise).
    """
    import torch
    import torch.nn.functional as F

    n, s = images.shape[0], images.shape[1]
    has = (masks.flatten(1) > 0).any(dim=1)
    pick = (torch.rand(n, generator=gen) < p) & has
    if n == 0 or not pick.any():
        return images
    roll = int(torch.randint(1, max(n, 2), (1,), generator=gen))
    grid = torch.rand(n, 3, 4, 4, generator=gen) * 255
    noise = torch.randn(n, s, s, 3, generator=gen)
    use_field = (torch.rand(n, generator=gen) < 0.5) | (n == 1)  # a batch of one has no other crop
    # Only the picked crops change: the field is made for those that take it and the rest are copied, which
    # gives the same bytes as making every crop's background (the random draws above are the same) in about
    # half the time (1.8x, batch 64 of 64 px).
    idx = torch.nonzero(pick).flatten()
    background = torch.roll(images, shifts=roll, dims=0)[idx].float()
    f_idx = torch.nonzero(use_field[idx]).flatten()
    if len(f_idx):
        rows = idx[f_idx]
        field = F.interpolate(grid[rows], size=(s, s), mode="bicubic", align_corners=False).permute(0, 2, 3, 1)
        background[f_idx] = field + noise[rows] * 8
    out = images.clone()
    keep = (masks[idx] > 0)[..., None]
    out[idx] = torch.where(keep, images[idx].float(), background).clamp(0, 255).round().to(torch.uint8)
    return out


def paste_occluders(images: "torch.Tensor", masks: "torch.Tensor", p: float, gen: "torch.Generator") -> "torch.Tensor":
    """With probability ``p`` per crop, paste another crop's object (the pixels of its mask) over it, shifted
    by a random offset of up to 60% of the side in x and y; uint8 NHWC in and out (``masks`` as in
    :func:`replace_background`; donors without a mask paste nothing)."""
    import torch

    n, s = images.shape[0], images.shape[1]
    pick = torch.rand(n, generator=gen) < p
    if n < 2 or not pick.any():
        return images
    shift = int(torch.randint(1, n, (1,), generator=gen))
    donors, donor_masks = torch.roll(images, shift, dims=0), torch.roll(masks, shift, dims=0) > 0
    offsets = ((torch.rand(n, 2, generator=gen) * 2 - 1) * 0.6 * s).round().long().tolist()
    out = images.clone()
    for i in torch.nonzero(pick).flatten().tolist():
        dy, dx = offsets[i]
        # Destination rows/columns [y0, y1) x [x0, x1) receive the donor's [y0 - dy, y1 - dy) x [x0 - dx, x1 - dx).
        y0, y1, x0, x1 = max(dy, 0), min(s + dy, s), max(dx, 0), min(s + dx, s)
        if y1 <= y0 or x1 <= x0:
            continue
        src = donors[i, y0 - dy : y1 - dy, x0 - dx : x1 - dx]
        m = donor_masks[i, y0 - dy : y1 - dy, x0 - dx : x1 - dx, None]
        out[i, y0:y1, x0:x1] = torch.where(m, src, out[i, y0:y1, x0:x1])
    return out


def relight(images: "torch.Tensor", p: float, gen: "torch.Generator") -> "torch.Tensor":
    """With probability ``p`` per crop, the light and camera of another scene: uint8 NHWC in and out.

    What the renderer draws anew for every scene, beyond the backdrop, redrawn on the crop: a smooth shading field
    across it (another light direction and ambient/diffuse balance: a 3x3 grid of gains in [0.6, 1.4], bicubic
    upsampled), a light colour (per-channel gains in [0.8, 1.2]), a gamma in [0.7, 1.4], a Gaussian blur (sigma in
    [0, 0.6] px of the crop: the renderer's blur of up to 1 px, shrunk with the object to the crop) and sensor noise
    (std in [0, 4] grey levels). The other crops are returned unchanged.
    """
    import torch
    import torch.nn.functional as F

    n, s = images.shape[0], images.shape[1]
    pick = torch.rand(n, generator=gen) < p
    if n == 0 or not pick.any():
        return images
    x = images.permute(0, 3, 1, 2).float() / 255.0
    grid = 0.6 + 0.8 * torch.rand(n, 1, 3, 3, generator=gen)
    shading = F.interpolate(grid, size=(s, s), mode="bicubic", align_corners=True).clamp(0.5, 1.5)
    colour = 0.8 + 0.4 * torch.rand(n, 3, 1, 1, generator=gen)
    gamma = torch.exp(torch.empty(n, 1, 1, 1).uniform_(math.log(0.7), math.log(1.4), generator=gen))
    x = (x * shading * colour).clamp(0, 1) ** gamma
    # Per-crop Gaussian blur: one separable 7-tap kernel per crop, applied as a grouped convolution.
    sigma = (0.6 * torch.rand(n, generator=gen)).clamp_min(1e-3)
    taps = torch.arange(-3, 4, dtype=torch.float32)
    kernel = torch.exp(-0.5 * (taps[None] / sigma[:, None]) ** 2)
    kernel = (kernel / kernel.sum(dim=1, keepdim=True)).repeat_interleave(3, dim=0)  # (n * 3, 7)
    flat = F.pad(x.reshape(1, n * 3, s, s), (3, 3, 3, 3), mode="replicate")
    flat = F.conv2d(flat, kernel[:, None, None, :], groups=n * 3)
    flat = F.conv2d(flat, kernel[:, None, :, None], groups=n * 3)
    x = flat.reshape(n, 3, s, s) * 255.0
    x = x + torch.randn(x.shape, generator=gen) * (4.0 * torch.rand(n, 1, 1, 1, generator=gen))
    out = x.clamp(0, 255).round().to(torch.uint8).permute(0, 2, 3, 1)
    return torch.where(pick[:, None, None, None], out, images).contiguous()


def jitter_box_and_colour(images: "torch.Tensor", box_jitter: float, gen: "torch.Generator") -> "torch.Tensor":
    """Colour jitter and a detector-like box jitter (the crop centre shifted and its side scaled by up to
    ``box_jitter``, a fraction of the side) on a uint8 NHWC batch; returns uint8 NHWC."""
    import torch
    import torch.nn.functional as F

    n, s = images.shape[0], images.shape[1]
    x = images.permute(0, 3, 1, 2).float()
    # Box jitter: shift the crop centre and scale its side by up to box_jitter (one affine resample).
    j = box_jitter
    scale = 1 + (torch.rand(n, generator=gen) * 2 - 1) * j
    shift = (torch.rand(n, 2, generator=gen) * 2 - 1) * j * 2  # affine_grid units: the side is 2
    # F.affine_grid's grid for theta = [[scale, 0, shift_x], [0, scale, shift_y]], written out: its pixel centres
    # (linspace(-1, 1, s) * (s - 1) / s, in that order) scaled and shifted are the same floats, without its batched
    # matrix product, which cost more than the resample itself (a test holds the two equal).
    ls = (torch.linspace(-1, 1, s) * (s - 1) / s)[None, :] * scale[:, None]
    grid = torch.empty(n, s, s, 2)
    grid[..., 0] = (ls + shift[:, 0:1])[:, None, :]
    grid[..., 1] = (ls + shift[:, 1:2])[:, :, None]
    x = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    # Colour: brightness, contrast and per-channel gain (in place: the same arithmetic in the same order).
    brightness = (torch.rand(n, 1, 1, 1, generator=gen) * 2 - 1) * 25
    contrast = 1 + (torch.rand(n, 1, 1, 1, generator=gen) * 2 - 1) * 0.2
    gain = 1 + (torch.rand(n, 3, 1, 1, generator=gen) * 2 - 1) * 0.1
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = x.sub_(mean).mul_(contrast).add_(mean).mul_(gain).add_(brightness)
    return x.clamp_(0, 255).round_().to(torch.uint8).permute(0, 2, 3, 1).contiguous()
