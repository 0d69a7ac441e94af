"""The options of one training stage (:class:`TrainConfig`) and the rules they share with the recipe: checked here,
importable without torch.

A :class:`models.train.recipe.TrainRecipe` gives one :class:`TrainConfig` per stage; the loop
(:mod:`models.train.loop`) runs it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from models.data.augment import validate_probabilities
from models.data.noise import NoiseSpec

__all__ = ["TrainConfig", "RecipeError", "check_inplane_frame", "check_masks"]


class RecipeError(ValueError):
    """A recipe value that is out of range or contradicts another field; ``field`` names the offending field."""

    def __init__(self, field_name: str, message: str):
        super().__init__(message)
        self.field = field_name


def check_inplane_frame(inplane: float, rotation_frame: str, *, as_flags: bool = True) -> None:
    """In-plane turns of a crop are rotations about the viewing ray, so they need the ray frame.

    ``as_flags``: name the values as command-line flags (``--inplane 30``) rather than fields (``inplane``).
    """
    if inplane > 0 and rotation_frame != "ray":
        why = ("a crop turned about its centre shows the object turned about the viewing ray, not the camera axis")
        if as_flags:
            message = f"--inplane {inplane:g} needs --rotation-frame ray ({why}); got --rotation-frame {rotation_frame}"
        else:
            message = f"inplane needs rotation_frame='ray': {why}; got rotation_frame={rotation_frame!r}"
        raise RecipeError("inplane", message)


def check_masks(background: float, occlude: float, has_masks: bool, where: str, *, as_flags: bool = True) -> None:
    """New backgrounds and pasted occluders cut the object out by its instance mask: refuse them without masks."""
    spell = (lambda n, p: f"--{n} {p:g}") if as_flags else (lambda n, p: f"{n}={p}")
    wanted = [spell(name, p) for name, p in (("background", background), ("occlude", occlude)) if p > 0]
    if wanted and not has_masks:
        raise RecipeError("background" if background > 0 else "occlude",
                          f"{' '.join(wanted)} needs instance masks, but {where} has none "
                          "(BOP mask_visib/<im_id>_<gt_idx>.png or YCB-Video <frame>-label.png; `refiner-rt render` "
                          "writes mask_visib/)")


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
            U(-inplane, inplane), with the coarse pose turned to match (see :func:`models.data.augment.rotate_in_plane`): the object
            seen at rotations about the viewing ray that no training scene had. First of the crop changes; needs
            ``rotation_frame="ray"``. 0 = off.
        relight: probability that a training crop gets another scene's light and camera (a smooth shading field,
            light colour, gamma, blur and sensor noise; see :func:`models.data.augment.relight`), after ``occlude`` and before ``augment``.
        photometric: camera-like photometric augmentation, ``{operation: probability per crop}``
            (:mod:`models.data.augment`: blur, motion blur, sensor noise, white balance, brightness, contrast, colour,
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
