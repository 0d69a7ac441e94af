"""The training loop: the paper's recipe (MSE to the label, then the geodesic loss; Adam) on CropSets.

Paper (Jain & Dellaert, section "Training"): coarse inputs ``q_in = q_gt * q_noise`` with a fresh
``q_noise`` every epoch, label ``q_noise^-1``; MSE for the first 5 epochs then the geodesic angle
``2 * atan2(|v|, |w|)`` of ``q_out * q_label^-1`` for 10 more; Adam. Beyond the paper: a learning-rate
schedule (constant, or cosine decay with linear warm-up), optional crop augmentation (colour
jitter, a box jitter that imitates a detector; new backgrounds, occluders, relighting and in-plane
turns), the viewing-ray rotation frame, mixed precision, AdamW decay, a moving average of the weights,
best-epoch selection on validation, resumable state and data-parallel training under ``torchrun``.

Conventions: quaternions ``wxyz``, object-to-camera; crops ``(N, S, S, 3)`` uint8 BGR; angles in degrees.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import os
import sys
import time
import types
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from models.augment import photometric, validate_probabilities
from models.cropset import CropSet
from models.losses import geodesic_loss
from models.noise import NoiseSpec, perturb
from models.recipe import check_inplane_frame, check_masks
from models.symmetry import closest_label, symmetric_error, symmetry_table
from refiner_rt import quaternion as rq

__all__ = ["TrainConfig", "TrainResult", "train_refiner", "predict", "set_threads"]

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    """Hyper-parameters of one training stage (base training or one object's fine-tuning).

    Attributes:
        epochs_mse: epochs with the MSE loss to the label (paper: 5).
        epochs_geodesic: epochs with the geodesic loss after those (paper: 10).
        batch_size: samples per optimisation step.
        lr: Adam learning rate (peak rate for the cosine schedule).
        lr_schedule: ``"constant"`` (paper) or ``"cosine"`` (linear warm-up, cosine decay to ``lr * lr_min_ratio``).
        warmup_epochs: warm-up length for ``"cosine"`` (fractional epochs allowed).
        lr_min_ratio: final learning rate as a fraction of ``lr`` for ``"cosine"``.
        weight_decay: Adam weight decay: an L2 term added to the gradient, or with ``decoupled_weight_decay``
            a shrink of the weights by ``lr * weight_decay`` every step (AdamW).
        decoupled_weight_decay: apply ``weight_decay`` the AdamW way (decoupled from the gradient's scale).
        ema: decay of an exponential moving average of the weights (and batch-norm statistics) updated every
            step, e.g. 0.999 (about the last 1,000 steps); 0 = off. When on, validation, best-epoch selection and
            the returned model use the averaged weights, and each history row also holds the raw weights'
            validation error (``val_raw_mean_deg``). The average starts at the weights training starts from and
            ramps its decay as ``min(ema, (1 + t) / (10 + t))`` over the first steps.
        noise: coarse-pose noise, e.g. ``"uniform:0:30"`` (degrees).
        rotation_frame: ``"camera"`` (paper) or ``"ray"`` (rotation relative to the viewing ray).
        augment: colour jitter + box jitter on the crops (off in the paper presets).
        box_jitter: with ``augment``, maximum shift of the crop centre and change of its side, as a
            fraction of the side.
        background: probability that a training crop with a mask gets a new background (its pixels
            outside the instance's visible mask replaced by another crop of the batch or by a random
            smooth colour field, half each), before ``augment``; needs masks (``CropSet.masks``).
        occlude: probability that a training crop gets an occluder: another crop's object (its masked
            pixels), shifted by up to 60% of the side, pasted over it, after ``background`` and before
            ``augment``; needs masks.
        inplane: maximum angle (degrees) of an in-plane turn of every training crop about its centre, drawn from
            U(-inplane, inplane), with the coarse pose turned to match (see ``_rotate_in_plane``): the object
            seen at rotations about the viewing ray that no training scene had. First of the crop changes; needs
            ``rotation_frame="ray"``. 0 = off.
        relight: probability that a training crop gets another scene's light and camera (a smooth shading field,
            light colour, gamma, blur and sensor noise; see ``_relight``), after ``occlude`` and before ``augment``.
        photometric: camera-like photometric augmentation, ``{operation: probability per crop}``
            (:mod:`models.augment`: blur, motion blur, sensor noise, white balance, brightness, contrast, colour,
            sharpness, JPEG), last of the crop changes; ``{}`` = off.
        seed: seed of the noise, shuffling and augmentation.
        val_seed: seed of the fixed validation noise (the same inputs every epoch).
        max_steps_per_epoch: cap on optimisation steps per epoch (0 = one full pass).
        bf16: mixed precision: the training forward pass runs under ``torch.autocast`` in bfloat16 (its
            backward follows); the weights, the optimiser and the loss stay float32, and validation, prediction
            and export run in float32. About 1.7x the network's step rate on a CPU with AVX-512 BF16
            (measured on a five-block fusion step, batch 64, one thread); ``benchmarks/train_speed.py`` measures
            both precisions on other machines.
    """

    epochs_mse: int = 5
    epochs_geodesic: int = 10
    batch_size: int = 64
    lr: float = 1e-4
    lr_schedule: str = "constant"
    warmup_epochs: float = 1.0
    lr_min_ratio: float = 0.01
    weight_decay: float = 0.0
    decoupled_weight_decay: bool = False
    ema: float = 0.0
    noise: str = "uniform:0:30"
    rotation_frame: str = "camera"
    augment: bool = False
    box_jitter: float = 0.05
    background: float = 0.0
    occlude: float = 0.0
    relight: float = 0.0
    inplane: float = 0.0
    photometric: dict = field(default_factory=dict)
    seed: int = 0
    val_seed: int = 12345
    max_steps_per_epoch: int = 0
    bf16: bool = False

    def __post_init__(self):
        NoiseSpec.parse(self.noise)
        if self.epochs_mse < 0 or self.epochs_geodesic < 0 or self.epochs_mse + self.epochs_geodesic == 0:
            raise ValueError(
                f"epochs must be >= 0 with at least one in total; got epochs_mse={self.epochs_mse}, epochs_geodesic={self.epochs_geodesic}"
            )
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1; got {self.batch_size}")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0; got {self.lr}")
        if self.lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"lr_schedule must be 'constant' or 'cosine'; got {self.lr_schedule!r}")
        for name in ("background", "occlude", "relight"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1]; got {getattr(self, name)}")
        if self.rotation_frame not in ("camera", "ray"):
            raise ValueError(f"rotation_frame must be 'camera' or 'ray'; got {self.rotation_frame!r}")
        if not 0.0 <= self.inplane <= 180.0:
            raise ValueError(f"inplane must be an angle in [0, 180] degrees; got {self.inplane}")
        check_inplane_frame(self.inplane, self.rotation_frame, as_flags=False)
        validate_probabilities(self.photometric)
        for name in ("bf16", "decoupled_weight_decay"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be True or False; got {getattr(self, name)!r}")
        if not self.weight_decay >= 0:
            raise ValueError(f"weight_decay must be >= 0; got {self.weight_decay}")
        if not 0.0 <= self.ema < 1.0:
            raise ValueError(f"ema must be a decay in [0, 1) (0 = off, e.g. 0.999); got {self.ema}")

    @property
    def epochs(self) -> int:
        return self.epochs_mse + self.epochs_geodesic


@dataclass
class TrainResult:
    """Outcome of :func:`train_refiner`.

    Attributes:
        model: the model with the best validation epoch's weights loaded.
        best_epoch: 1-based epoch with the lowest validation mean error (the last epoch without validation data).
        best_val_deg: that epoch's validation mean geodesic error (degrees), NaN without validation data.
        history: one dict per epoch: ``epoch``, ``loss_kind``, ``train_loss``, ``val_mean_deg``,
            ``val_median_deg``, ``lr``, ``samples``, ``samples_per_s``, ``seconds`` (training only, not validation);
            with ``ema`` also ``val_raw_mean_deg`` and ``val_raw_median_deg`` (the raw weights).
    """

    model: torch.nn.Module
    best_epoch: int
    best_val_deg: float
    history: list[dict] = field(default_factory=list)


def set_threads(threads: int | None) -> int:
    """Set torch's intra-op threads (``None``/0 = every available core) and return the count."""
    if not threads:
        try:
            threads = len(os.sched_getaffinity(0))
        except AttributeError:
            threads = os.cpu_count() or 1
    torch.set_num_threads(int(threads))
    return int(threads)


def _distributed() -> tuple[int, int]:
    """(rank, world_size) when running under torchrun with an initialised process group, else (0, 1)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


def _average_buffers(model: torch.nn.Module, world: int) -> None:
    """Average floating buffers (batch-norm running statistics) over DDP ranks, so every rank holds the same model.

    DDP keeps parameters identical; each rank's BN statistics, though, follow its own shard of the data.
    """
    for buf in model.buffers():
        if buf.is_floating_point():
            torch.distributed.all_reduce(buf, op=torch.distributed.ReduceOp.SUM)
            buf.div_(world)


class _WeightAverage:
    """Exponential moving average of a model's state (parameters and floating buffers; counters are copied)."""

    def __init__(self, model: torch.nn.Module, decay: float):
        self.decay = decay
        self.steps = 0
        self.state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        self._floats = [k for k, v in self.state.items() if v.is_floating_point()]
        self._counters = [k for k, v in self.state.items() if not v.is_floating_point()]

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        d = min(self.decay, (1 + self.steps) / (10 + self.steps))
        current = model.state_dict()
        torch._foreach_lerp_([self.state[k] for k in self._floats], [current[k] for k in self._floats], 1.0 - d)
        for k in self._counters:
            self.state[k].copy_(current[k])
        self.steps += 1

    def average_buffers(self, model: torch.nn.Module, world: int) -> None:
        """Average the floating buffers' averages over DDP ranks (the parameters' are identical already)."""
        names = {name for name, _ in model.named_buffers()}
        for k, v in self.state.items():
            if k in names and v.is_floating_point():
                torch.distributed.all_reduce(v, op=torch.distributed.ReduceOp.SUM)
                v.div_(world)


def _lr_at(cfg: TrainConfig, progress_epochs: float) -> float:
    if cfg.lr_schedule == "constant":
        return cfg.lr
    if progress_epochs < cfg.warmup_epochs:
        return cfg.lr * max(progress_epochs / max(cfg.warmup_epochs, 1e-9), 0.01)
    span = max(cfg.epochs - cfg.warmup_epochs, 1e-9)
    t = min((progress_epochs - cfg.warmup_epochs) / span, 1.0)
    return cfg.lr * (cfg.lr_min_ratio + (1 - cfg.lr_min_ratio) * 0.5 * (1 + math.cos(math.pi * t)))


def _rotate_in_plane(
    images: torch.Tensor, masks: torch.Tensor | None, max_deg: float, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor | None, np.ndarray]:
    """Rotate every crop about its centre by an angle from U(-max_deg, max_deg): uint8 NHWC in and out.

    A crop centred on the box shows the object around the viewing ray, so turning the image by ``phi`` (a pixel
    offset ``(dx, dy)`` -> ``R(phi) (dx, dy)`` with x right and y down) shows the object turned by ``phi`` about
    that ray: in the ray frame ``q_gt -> q_z(phi) * q_gt``, and since the coarse pose is ``q_gt * q_noise`` the
    input becomes ``q_z(phi) * q_in`` with the same label. Corners the turn uncovers are filled by reflection;
    masks are turned with nearest sampling and zeros outside.

    Returns:
        the turned images, the turned masks (None without masks), and ``q_z(phi)`` per crop ``(N, 4)`` wxyz float64.
    """
    from models.fusion import turn_grid

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


def _replace_background(images: torch.Tensor, masks: torch.Tensor, p: float, gen: torch.Generator) -> torch.Tensor:
    """Give each crop with a mask, with probability ``p``, a new background: uint8 NHWC in and out.

    ``masks`` is ``(N, S, S)`` uint8, 1 on the instance's visible pixels (all zeros: no mask, left as is).
    The new background is, half the time each, another crop of the batch (real clutter, other objects)
    or a smooth random colour field (a 4x4 colour grid, bicubic upsampled, plus pixel noise).
    """
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


def _paste_occluders(images: torch.Tensor, masks: torch.Tensor, p: float, gen: torch.Generator) -> torch.Tensor:
    """With probability ``p`` per crop, paste another crop's object (the pixels of its mask) over it, shifted
    by a random offset of up to 60% of the side in x and y; uint8 NHWC in and out (``masks`` as in
    :func:`_replace_background`; donors without a mask paste nothing)."""
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


def _relight(images: torch.Tensor, p: float, gen: torch.Generator) -> torch.Tensor:
    """With probability ``p`` per crop, the light and camera of another scene: uint8 NHWC in and out.

    What the renderer draws anew for every scene, beyond the backdrop, redrawn on the crop: a smooth shading field
    across it (another light direction and ambient/diffuse balance: a 3x3 grid of gains in [0.6, 1.4], bicubic
    upsampled), a light colour (per-channel gains in [0.8, 1.2]), a gamma in [0.7, 1.4], a Gaussian blur (sigma in
    [0, 0.6] px of the crop: the renderer's blur of up to 1 px, shrunk with the object to the crop) and sensor noise
    (std in [0, 4] grey levels). The other crops are returned unchanged.
    """
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


def _augment(images: torch.Tensor, cfg: TrainConfig, gen: torch.Generator) -> torch.Tensor:
    """Colour jitter and a detector-like box jitter on a uint8 NHWC batch; returns uint8 NHWC."""
    n, s = images.shape[0], images.shape[1]
    x = images.permute(0, 3, 1, 2).float()
    # Box jitter: shift the crop centre and scale its side by up to box_jitter (one affine resample).
    j = cfg.box_jitter
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


@torch.no_grad()
def predict(model: torch.nn.Module, crops: np.ndarray, q_in: np.ndarray, batch_size: int = 256) -> np.ndarray:
    """Run a PyTorch refiner on crops: ``(N, S, S, 3)`` uint8 BGR and ``(N, 4)`` wxyz in, ``(N, 4)`` float64 q_out."""
    model.eval()
    device = next(model.parameters()).device
    out = []
    for i in range(0, len(crops), batch_size):
        img = torch.from_numpy(np.array(crops[i : i + batch_size])).to(device)  # a writable copy (crops may be a read-only memmap)
        q = torch.from_numpy(q_in[i : i + batch_size].astype(np.float32)).to(device)
        out.append(model(img, q).double().cpu().numpy())
    return np.concatenate(out) if out else np.zeros((0, 4))


def validation_errors(model, val: CropSet, cfg: TrainConfig, symmetries: dict | None = None) -> np.ndarray:
    """Geodesic errors (degrees) of ``q_in * q_out`` on ``val`` with fixed-seed noise (same inputs every epoch);
    for the objects in ``symmetries``, the error to the closest symmetric pose."""
    q_gt = val.q_gt_in(cfg.rotation_frame)
    q_in, _ = perturb(q_gt, NoiseSpec.parse(cfg.noise), np.random.default_rng(cfg.val_seed))
    q_out = predict(model, val.crops, q_in)
    return symmetric_error(rq.multiply(q_in, q_out), q_gt, val.obj_ids, symmetries)


def _progress(total: int, desc: str, enabled: bool):
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ModuleNotFoundError:
        return None
    return tqdm(total=total, desc=desc, unit="sample", unit_scale=True, dynamic_ncols=True, leave=False)


def train_refiner(
    model: torch.nn.Module,
    train: CropSet,
    val: CropSet | None,
    cfg: TrainConfig,
    *,
    state_path: Path | None = None,
    log_path: Path | None = None,
    progress: bool = True,
    desc: str = "train",
    device: str | torch.device = "cpu",
    symmetries: dict | None = None,
) -> TrainResult:
    """Train ``model`` on ``train`` with the paper's recipe and keep the best validation epoch.

    Args:
        model: a refiner from ``models.build_refiner`` (forward(image uint8 NHWC, q_in wxyz) -> q_out).
        train: training crops; a fresh coarse pose is drawn for every sample in every epoch.
        val: validation crops (fixed noise), or None (then the last epoch is kept).
        cfg: the stage's hyper-parameters.
        state_path: if given, the full training state (weights, optimiser, epoch, history, RNG) is
            written there after every epoch, and training resumes from it when it exists.
        log_path: if given, the epoch history is written there as JSON Lines after every epoch.
        progress: show a progress bar with loss, samples/s and ETA (rank 0 only).
        desc: label of the progress bar and log lines.
        device: where the model and the batches live (``"cpu"``, ``"cuda:0"``, ``"mps"``); the crops, their
            augmentation and the random draws stay on the CPU, so a run's samples do not depend on the device.
        symmetries: object name -> symmetry (BOP ``models_info.json`` form, see :mod:`models.symmetry`); those
            objects' samples are trained towards the closest of their symmetric labels and validated with the
            symmetry-aware error. None or empty: the plain loss (the paper's).

    Returns:
        :class:`TrainResult`. Under ``torchrun`` every rank trains on its shard of each batch
        (gradients averaged by DDP) and all ranks return identical weights.
    """
    if len(train) == 0:
        raise ValueError("the training CropSet is empty")
    if train.input_size != model.input_size:
        raise ValueError(f"crops are {train.input_size} px but the model takes {model.input_size} px")
    check_masks(cfg.background, cfg.occlude, train.masks is not None, "the training crops", as_flags=False)
    rank, world = _distributed()
    device = torch.device(device)
    model.to(device)
    noise = NoiseSpec.parse(cfg.noise)
    q_gt_all = train.q_gt_in(cfg.rotation_frame)
    sym_table, sym_index = symmetry_table(train.obj_ids, symmetries)
    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    # The fused kernel makes the optimiser step about 20% of a shallow-model step cheaper on the CPU (measured,
    # batch 64); it exists for CPU and CUDA tensors.
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay,
                           decoupled_weight_decay=cfg.decoupled_weight_decay, fused=device.type in ("cpu", "cuda"))
    ema = _WeightAverage(model, cfg.ema) if cfg.ema > 0 else None
    history: list[dict] = []
    best = (math.inf, 0, copy.deepcopy(model.state_dict()))
    start_epoch = 0
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed + 1)

    if state_path is not None and Path(state_path).exists():
        state = torch.load(state_path, map_location="cpu", weights_only=True)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        history = state["history"]
        best = (state["best_val"], state["best_epoch"], state["best_state"])
        if ema is not None:
            ema.state, ema.steps = state["ema"], state["ema_steps"]
        start_epoch = state["epoch"]
        rng.bit_generator.state = state["rng"]
        gen.set_state(state["gen"])
        log.info("%s: resumed from %s at epoch %d", desc, state_path, start_epoch)

    n = len(train)
    steps_per_epoch = math.ceil(n / cfg.batch_size)
    if cfg.max_steps_per_epoch:
        steps_per_epoch = min(steps_per_epoch, cfg.max_steps_per_epoch)
    for epoch in range(start_epoch, cfg.epochs):
        loss_kind = "mse" if epoch < cfg.epochs_mse else "geodesic"
        model.train()
        perm = rng.permutation(n)
        q_in_all, label_all = perturb(q_gt_all, noise, rng)
        t0 = time.perf_counter()
        total_loss, seen = 0.0, 0
        bar = _progress(steps_per_epoch * cfg.batch_size, f"{desc} {epoch + 1}/{cfg.epochs} ({loss_kind})", progress and rank == 0)
        for step in range(steps_per_epoch):
            idx = np.sort(perm[step * cfg.batch_size : (step + 1) * cfg.batch_size])
            if world > 1:
                idx = idx[rank::world]
            lr = _lr_at(cfg, epoch + step / steps_per_epoch)
            for g in opt.param_groups:
                g["lr"] = lr
            images = torch.from_numpy(np.ascontiguousarray(train.crops[idx]))
            q_in = q_in_all[idx]
            masks = None
            if cfg.background > 0 or cfg.occlude > 0:
                masks = torch.from_numpy(np.ascontiguousarray(train.masks[idx]))
            if cfg.inplane > 0:
                images, masks, q_turn = _rotate_in_plane(images, masks, cfg.inplane, gen)
                q_in = rq.multiply(q_turn, q_in)
            if masks is not None:
                if cfg.background > 0:
                    images = _replace_background(images, masks, cfg.background, gen)
                if cfg.occlude > 0:
                    images = _paste_occluders(images, masks, cfg.occlude, gen)
            if cfg.relight > 0:
                images = _relight(images, cfg.relight, gen)
            if cfg.augment:
                images = _augment(images, cfg, gen)
            if cfg.photometric:
                images = photometric(images, cfg.photometric, gen)
            label = label_all[idx]
            if sym_table is not None:  # every symmetric pose's label: (B, K, 4)
                label = rq.multiply(label[:, None, :], sym_table[sym_index[idx]])
            to = dict(device=device, non_blocking=device.type == "cuda")
            images = images.to(**to)
            q_in = torch.from_numpy(q_in.astype(np.float32)).to(**to)
            label = torch.from_numpy(label.astype(np.float32)).to(**to)
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=cfg.bf16):
                q_out = net(images, q_in)
            q_out = q_out.float()
            if sym_table is not None:
                label = closest_label(q_out.detach(), label)
            loss = F.mse_loss(q_out, label) if loss_kind == "mse" else geodesic_loss(q_out, label)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if ema is not None:
                ema.update(model)
            total_loss += loss.item() * len(idx)
            seen += len(idx)
            if bar is not None:
                bar.update(len(idx) * world)
                bar.set_postfix(loss=f"{total_loss / seen:.4f}", lr=f"{lr:.1e}")
        if bar is not None:
            bar.close()
        if world > 1:
            _average_buffers(model, world)
            if ema is not None:
                ema.average_buffers(model, world)
        seconds = time.perf_counter() - t0
        row = {
            "stage": desc,
            "epoch": epoch + 1,
            "loss_kind": loss_kind,
            "train_loss": total_loss / max(seen, 1),
            "lr": lr,
            "samples": seen * world,
            "samples_per_s": seen * world / seconds,
            "seconds": seconds,
            "val_mean_deg": float("nan"),
            "val_median_deg": float("nan"),
        }
        # The weights this epoch is judged by: the average when there is one, else the raw weights.
        kept = model.state_dict() if ema is None else ema.state
        if val is not None and len(val):
            if ema is not None:
                err = validation_errors(model, val, cfg, symmetries)
                row["val_raw_mean_deg"], row["val_raw_median_deg"] = float(err.mean()), float(np.median(err))
                raw = copy.deepcopy(model.state_dict())
                model.load_state_dict(ema.state)
                err = validation_errors(model, val, cfg, symmetries)
                model.load_state_dict(raw)
            else:
                err = validation_errors(model, val, cfg, symmetries)
            row["val_mean_deg"], row["val_median_deg"] = float(err.mean()), float(np.median(err))
            if row["val_mean_deg"] < best[0]:
                best = (row["val_mean_deg"], epoch + 1, copy.deepcopy(kept))
        else:
            best = (float("nan"), epoch + 1, copy.deepcopy(kept))
        history.append(row)
        if rank == 0:
            log.info(
                "%s epoch %d/%d %s loss %.4f val %.2f deg (median %.2f) %.0f samples/s",
                desc, epoch + 1, cfg.epochs, loss_kind, row["train_loss"], row["val_mean_deg"], row["val_median_deg"], row["samples_per_s"],
            )
            if log_path is not None:
                with open(log_path, "a") as f:
                    f.write(json.dumps(row) + "\n")
            if state_path is not None:
                tmp = Path(str(state_path) + ".tmp")
                torch.save(
                    {
                        "model": model.state_dict(),
                        "optimizer": opt.state_dict(),
                        "history": history,
                        "best_val": best[0],
                        "best_epoch": best[1],
                        "best_state": best[2],
                        "epoch": epoch + 1,
                        "rng": rng.bit_generator.state,
                        "gen": gen.get_state(),
                        "config": asdict(cfg),
                        **({"ema": ema.state, "ema_steps": ema.steps} if ema is not None else {}),
                    },
                    tmp,
                )
                os.replace(tmp, state_path)
    model.load_state_dict(best[2])
    return TrainResult(model=model, best_epoch=best[1], best_val_deg=best[0], history=history)


class _CallableModule(types.ModuleType):
    """``models.train`` is this module and also the run function: ``models.train(recipe, out=...)``.

    (``import models.train`` binds the module as the package attribute ``train``, so the documented call
    ``models.train(recipe, out=...)`` goes through the module's ``__call__`` to :func:`models.training.train`.)
    """

    def __call__(self, recipe, out, **kwargs):
        from models.training import train

        return train(recipe, out, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
