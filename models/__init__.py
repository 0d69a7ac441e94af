"""PyTorch side of refiner-rt: the refiner networks, their registry, checkpoints and losses.

    import models
    model = models.build_refiner("shallow")              # or "vggm"; **config overrides the defaults
    q_out = model(images_uint8_bgr_nhwc, q_in_wxyz)      # (N, 4) unit quaternions, q_refined = q_in * q_out
    models.save_checkpoint(model, "ckpt.pt", objects=["003_cracker_box"], train_noise="uniform:0:30")
    model, info = models.load_checkpoint("ckpt.pt")
    recipe = models.load_recipe("paper").merged(data="renders/", objects=["003_cracker_box"])
    models.run_training(recipe, out="runs/paper.pt")  # a whole run: base, per-object fine-tuning, continuations

Sub-packages, one job each (docs/design.md §11): ``models.nets`` (the networks and their registry),
``models.data`` (datasets, splits, crops, noise, augmentation, symmetries, the renderer), ``models.train``
(recipes, the training loop, checkpoints, losses) and ``models.evaluate`` (errors, metrics, real-frame scoring).

Conventions (docs/design.md §2): quaternions ``wxyz``, rotations object-to-camera, images ``(N, S, S, 3)``
uint8 NHWC in the model's channel order (BGR by default).
"""

from __future__ import annotations

import importlib

# Lazy: `models.data` (loaders, splits, crop cache) must import without torch, and the crop-cache worker
# processes should not pay torch's start-up; the networks load on first use of a name below (the registry
# imports the built-in architectures on its first lookup).
_EXPORTS = {
    "CHECKPOINT_FORMAT": "models.train.checkpoint",
    "load_checkpoint": "models.train.checkpoint",
    "save_checkpoint": "models.train.checkpoint",
    "Refiner": "models.nets.blocks",
    "build_refiner": "models.nets.registry",
    "get_refiner_class": "models.nets.registry",
    "list_refiners": "models.nets.registry",
    "register_refiner": "models.nets.registry",
    "run_training": "models.train.run",
    "TrainRecipe": "models.train.recipe",
    "load_recipe": "models.train.recipe",
    "NAMED_RECIPES": "models.train.recipe",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'models' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
