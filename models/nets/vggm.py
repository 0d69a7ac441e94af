"""The VGG-M refiner: the paper's deep variant, VGG-M conv1..fc7 as the image feature stage.

VGG-M is the "M" network of Chatfield, Simonyan, Vedaldi & Zisserman, "Return of the Devil in the Details:
Delving Deep into Convolutional Nets" (BMVC 2014), Table 1, as in their Caffe model ``VGG_CNN_M``:

    conv1 96x7x7 /2, ReLU, LRN(5, 5e-4, 0.75, k=2), max-pool 3/2
    conv2 256x5x5 /2 pad 1, ReLU, LRN, max-pool 3/2
    conv3, conv4, conv5 512x3x3 pad 1, ReLU; max-pool 3/2           -> 6 x 6 x 512 at 224x224
    fc6 4096, ReLU, dropout; fc7 4096, ReLU, dropout                  -> 4096 image features

All three poolings round up (Caffe's rule, ``ceil_mode=True``), which gives the original 13x13 conv3..conv5 maps
and 6x6 after pool5 at 224x224. No ImageNet weights are downloaded (ever): the stage is trained from scratch or
initialised from a user-supplied state dict file (``init_state_dict``).

Conventions: image ``(N, 224, 224, 3)`` uint8 NHWC BGR by default; quaternions ``wxyz``, object-to-camera;
``q_refined = q_in * q_out``.
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from pathlib import Path

import torch
from torch import nn

from models.nets.blocks import LocalResponseNorm, Refiner, validate_int_list
from models.nets.registry import register_refiner

__all__ = ["MIN_INPUT_SIZE", "VGGMRefiner", "vggm_feature_size"]

logger = logging.getLogger(__name__)

LRN_PARAMS = {"size": 5, "alpha": 5e-4, "beta": 0.75, "k": 2.0}
CONV5_CHANNELS = 512


def _conv_out(size: int, kernel: int, stride: int, pad: int = 0, ceil: bool = False) -> int:
    """Output side of a conv/pool layer, with PyTorch's ceil-mode rule (last window starts inside the input)."""
    span = size + 2 * pad - kernel
    out = (math.ceil(span / stride) if ceil else span // stride) + 1
    if ceil and (out - 1) * stride >= size + pad:
        out -= 1
    return out


def vggm_feature_size(input_size: int) -> int:
    """Side of the pool5 map for a square ``input_size`` input (6 at 224); below 1 the input is too small."""
    s = _conv_out(input_size, 7, 2)
    s = _conv_out(s, 3, 2, ceil=True)
    s = _conv_out(s, 5, 2, pad=1)
    s = _conv_out(s, 3, 2, ceil=True)
    return _conv_out(s, 3, 2, ceil=True)


# Smallest input side with a non-empty pool5 map (41).
MIN_INPUT_SIZE = next(s for s in range(1, 512) if vggm_feature_size(s) >= 1)


@register_refiner("vggm")
class VGGMRefiner(Refiner):
    """The paper's refiner with a VGG-M (conv1..fc7) feature stage.

    Config keys (beyond the common ones of :class:`models.nets.blocks.Refiner`):
        * ``input_size`` (int, default 224; at least ``MIN_INPUT_SIZE`` = 41 so pool5 is non-empty).
        * ``fc_widths`` (2 ints, default ``[4096, 4096]``): widths of fc6 and fc7; fc7 is the image feature size.
        * ``dropout`` (float in [0, 1), default 0.5): dropout after fc6 and fc7 (training only).
        * ``init_state_dict`` (str or None, default None): path of a file saved with ``torch.save`` holding a
          state dict for the feature stage (keys ``conv1.weight``, ``conv1.bias``, ..., ``conv5.bias``,
          optionally ``fc6.*``, ``fc7.*``; a subset such as conv weights only is allowed and logged). Loaded with
          ``weights_only=True``. Used at build time only: a checkpoint's own weights take precedence.

    Shape:
        - image: ``(N, S, S, 3)`` uint8, NHWC, ``channel_order`` (default BGR).
        - q_in: ``(N, 4)`` float32, ``wxyz``.
        - output: ``(N, 4)`` float32 unit quaternions ``q_out``, ``wxyz``.
    """

    DEFAULT_CONFIG = {"input_size": 224, "fc_widths": [4096, 4096], "dropout": 0.5, "init_state_dict": None}
    INIT_ONLY_KEYS = frozenset({"init_state_dict"})

    @classmethod
    def resolve_config(cls, config: dict) -> dict:
        cfg = super().resolve_config(config)
        if vggm_feature_size(cfg["input_size"]) < 1:
            raise ValueError(
                f"config['input_size'] must be at least {MIN_INPUT_SIZE} for VGG-M (pool5 empty); got {cfg['input_size']}"
            )
        cfg["fc_widths"] = validate_int_list(cfg, "fc_widths", min_len=2)
        if len(cfg["fc_widths"]) != 2:
            raise ValueError(f"config['fc_widths'] must hold 2 ints (fc6, fc7); got {cfg['fc_widths']}")
        p = cfg["dropout"]
        if not isinstance(p, (int, float)) or isinstance(p, bool) or not 0.0 <= p < 1.0:
            raise ValueError(f"config['dropout'] must be a number in [0, 1); got {p!r}")
        cfg["dropout"] = float(p)
        init = cfg["init_state_dict"]
        if init is not None and not isinstance(init, str):
            raise ValueError(f"config['init_state_dict'] must be a file path (str) or None; got {init!r}")
        return cfg

    def __init__(self, **config):
        super().__init__(**config)
        if self.config["init_state_dict"] is not None:
            self._load_feature_weights(Path(self.config["init_state_dict"]))

    def build_feature_stage(self, config: dict) -> tuple[nn.Module, int]:
        fc6, fc7 = config["fc_widths"]
        side = vggm_feature_size(config["input_size"])
        stage = nn.Sequential(
            OrderedDict(
                [
                    ("conv1", nn.Conv2d(3, 96, 7, stride=2)),
                    ("relu1", nn.ReLU(inplace=True)),
                    ("norm1", LocalResponseNorm(**LRN_PARAMS)),
                    ("pool1", nn.MaxPool2d(3, 2, ceil_mode=True)),
                    ("conv2", nn.Conv2d(96, 256, 5, stride=2, padding=1)),
                    ("relu2", nn.ReLU(inplace=True)),
                    ("norm2", LocalResponseNorm(**LRN_PARAMS)),
                    ("pool2", nn.MaxPool2d(3, 2, ceil_mode=True)),
                    ("conv3", nn.Conv2d(256, 512, 3, padding=1)),
                    ("relu3", nn.ReLU(inplace=True)),
                    ("conv4", nn.Conv2d(512, 512, 3, padding=1)),
                    ("relu4", nn.ReLU(inplace=True)),
                    ("conv5", nn.Conv2d(512, CONV5_CHANNELS, 3, padding=1)),
                    ("relu5", nn.ReLU(inplace=True)),
                    ("pool5", nn.MaxPool2d(3, 2, ceil_mode=True)),
                    ("flatten", nn.Flatten()),
                    ("fc6", nn.Linear(CONV5_CHANNELS * side * side, fc6)),
                    ("relu6", nn.ReLU(inplace=True)),
                    ("drop6", nn.Dropout(config["dropout"])),
                    ("fc7", nn.Linear(fc6, fc7)),
                    ("relu7", nn.ReLU(inplace=True)),
                    ("drop7", nn.Dropout(config["dropout"])),
                ]
            )
        )
        return stage, fc7

    def _load_feature_weights(self, path: Path) -> None:
        """Copy a user-supplied state dict into the feature stage (see ``init_state_dict``)."""
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise ValueError(f"config['init_state_dict']: file not found: {path}") from None
        except Exception as exc:  # a corrupt or non-weights file: torch raises several types
            raise ValueError(f"config['init_state_dict']: {path} is not a weights-only torch state dict ({exc})") from None
        if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
            raise ValueError(f"config['init_state_dict']: {path} must hold a dict of name -> tensor; got {type(state).__name__}")
        own = self.features.state_dict()
        unexpected = sorted(set(state) - set(own))
        if unexpected:
            raise ValueError(
                f"config['init_state_dict']: {path} has unexpected key(s) {unexpected}; expected keys among {sorted(own)}"
            )
        for name, tensor in state.items():
            if tensor.shape != own[name].shape:
                raise ValueError(
                    f"config['init_state_dict']: {path} key {name!r} has shape {tuple(tensor.shape)}; "
                    f"expected {tuple(own[name].shape)}"
                )
        self.features.load_state_dict(state, strict=False)
        missing = sorted(set(own) - set(state))
        logger.info("VGG-M feature stage initialised from %s (%d tensors; left at random init: %s)", path, len(state), missing)
