"""PyTorch side of refiner-rt: the refiner networks, their registry, checkpoints and losses.

    import models
    model = models.build_refiner("shallow")              # or "vggm"; **config overrides the defaults
    q_out = model(images_uint8_bgr_nhwc, q_in_wxyz)      # (N, 4) unit quaternions, q_refined = q_in * q_out
    models.save_checkpoint(model, "ckpt.pt", objects=["003_cracker_box"], train_noise="uniform:0:30")
    model, info = models.load_checkpoint("ckpt.pt")

Conventions (design.md section 2): quaternions ``wxyz``, rotations object-to-camera, images ``(N, S, S, 3)``
uint8 NHWC in the model's channel order (BGR by default).
"""

from __future__ import annotations

from models import losses
from models import shallow as _shallow  # noqa: F401  (registers "shallow")
from models import vggm as _vggm  # noqa: F401  (registers "vggm")
from models import fusion as _fusion  # noqa: F401  (registers "fusion", the project's improved refiner)
from models.blocks import Refiner
from models.checkpoint import CHECKPOINT_FORMAT, load_checkpoint, save_checkpoint
from models.registry import build_refiner, get_refiner_class, list_refiners, register_refiner

__all__ = [
    "CHECKPOINT_FORMAT",
    "Refiner",
    "build_refiner",
    "get_refiner_class",
    "list_refiners",
    "load_checkpoint",
    "losses",
    "register_refiner",
    "save_checkpoint",
]
