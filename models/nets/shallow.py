"""The paper's shallow refiner: a two-layer CNN feature stage (Jain & Dellaert, section "Network Architecture").

CNN stage: ``conv(3 -> 16, 5x5, pad 2) - BN - ReLU - maxpool 2`` twice (the second conv 16 -> 16), flattened:
``16 x 16 x 16 = 4096`` features at the default 64x64 input, matching the paper's 4096-d image features.
Pose and refinement stages are the shared ones of :mod:`models.nets.blocks`.

Conventions: image ``(N, 64, 64, 3)`` uint8 NHWC BGR by default; quaternions ``wxyz``, object-to-camera;
``q_refined = q_in * q_out``.
"""

from __future__ import annotations

from torch import nn

from models.nets.blocks import Refiner, validate_int_list
from models.nets.registry import register_refiner

__all__ = ["ShallowRefiner"]


@register_refiner("shallow")
class ShallowRefiner(Refiner):
    """The paper's refiner with its shallow CNN feature stage.

    Config keys (beyond the common ones of :class:`models.nets.blocks.Refiner`):
        * ``input_size`` (int, default 64, multiple of 4).
        * ``conv_channels`` (2 ints, default ``[16, 16]``): output channels of the two conv layers.
        * ``kernel_size`` (odd int, default 5): conv kernel side ("same" padding).

    Image features: ``conv_channels[1] * (input_size / 4) ** 2`` (4096 by default).

    Shape:
        - image: ``(N, S, S, 3)`` uint8, NHWC, ``channel_order`` (default BGR).
        - q_in: ``(N, 4)`` float32, ``wxyz``.
        - output: ``(N, 4)`` float32 unit quaternions ``q_out``, ``wxyz``.

    Example:
        >>> model = build_refiner("shallow")   # doctest: +SKIP
        >>> q_out = model(images_uint8_bgr, q_in_wxyz)   # doctest: +SKIP
    """

    DEFAULT_CONFIG = {"input_size": 64, "conv_channels": [16, 16], "kernel_size": 5}

    @classmethod
    def resolve_config(cls, config: dict) -> dict:
        cfg = super().resolve_config(config)
        if cfg["input_size"] % 4:
            raise ValueError(f"config['input_size'] must be a multiple of 4 (two 2x max-pools); got {cfg['input_size']}")
        cfg["conv_channels"] = validate_int_list(cfg, "conv_channels", min_len=2)
        if len(cfg["conv_channels"]) != 2:
            raise ValueError(f"config['conv_channels'] must hold 2 ints (the paper's 2 conv layers); got {cfg['conv_channels']}")
        k = cfg["kernel_size"]
        if not isinstance(k, int) or isinstance(k, bool) or k <= 0 or k % 2 == 0:
            raise ValueError(f"config['kernel_size'] must be a positive odd int; got {k!r}")
        return cfg

    def build_feature_stage(self, config: dict) -> tuple[nn.Module, int]:
        c1, c2 = config["conv_channels"]
        k = config["kernel_size"]
        stage = nn.Sequential(
            nn.Conv2d(3, c1, k, padding=k // 2),
            nn.BatchNorm2d(c1),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(2),
            nn.Conv2d(c1, c2, k, padding=k // 2),
            nn.BatchNorm2d(c2),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(2),
            nn.Flatten(),
        )
        return stage, c2 * (config["input_size"] // 4) ** 2
