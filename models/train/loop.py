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
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from models.data.augment import (jitter_box_and_colour, paste_occluders, photometric, relight, replace_background,
                                 rotate_in_plane)
from models.data.cropset import CropSet
from models.data.noise import NoiseSpec, perturb
from models.data.symmetry import closest_label, symmetric_error, symmetry_table
from models.train.config import TrainConfig, check_masks
from models.train.losses import geodesic_loss
from refiner_rt import quaternion as rq

__all__ = ["TrainConfig", "TrainResult", "train_refiner", "predict", "set_threads"]

log = logging.getLogger(__name__)


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
        symmetries: object name -> symmetry (BOP ``models_info.json`` form, see :mod:`models.data.symmetry`); those
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
        if log_path is not None and Path(log_path).is_file():  # this stage's log as the state has it: a run stopped
            # between the two writes neither logs an epoch twice nor loses one
            rows = [line for line in Path(log_path).read_text().splitlines() if json.loads(line).get("stage") != desc]
            Path(log_path).write_text("".join(f"{line}\n" for line in rows + [json.dumps(r) for r in history]))

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
                images, masks, q_turn = rotate_in_plane(images, masks, cfg.inplane, gen)
                q_in = rq.multiply(q_turn, q_in)
            if masks is not None:
                if cfg.background > 0:
                    images = replace_background(images, masks, cfg.background, gen)
                if cfg.occlude > 0:
                    images = paste_occluders(images, masks, cfg.occlude, gen)
            if cfg.relight > 0:
                images = relight(images, cfg.relight, gen)
            if cfg.augment:
                images = jitter_box_and_colour(images, cfg.box_jitter, gen)
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
