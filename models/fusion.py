"""The project's improved refiner: the paper's shallow CNN with a rotation-matrix pose input and multiplicative fusion.

Differences from the paper's design (``models.shallow``), each chosen by measurement (see
``benchmarks/RESULTS.md``):
    * the coarse rotation enters the pose stage as its 3x3 rotation matrix (9 numbers, continuous
      in the rotation and free of the ``q ~ -q`` ambiguity) instead of the raw quaternion;
    * image and pose features are projected to the same width ``d`` and fused as
      ``concat[a, b, a * b]`` (the product lets the head compare appearance with the claimed pose
      directly) instead of a plain 4096 + 4096 concatenation;
    * the head is narrower (``3d -> 256 -> 64 -> 4``), so the model is about 4x smaller than the
      paper's and faster on a CPU.

Contract unchanged (design.md section 5): ``forward(image (N, S, S, 3) uint8 NHWC BGR, q_in (N, 4)
wxyz) -> q_out (N, 4)`` unit ``wxyz``, ``q_refined = q_in * q_out``; the quaternion-to-matrix
conversion happens inside the graph.
"""

from __future__ import annotations

import torch
from torch import nn

from models.blocks import InputNormalization, RefinementHead, Refiner, mlp, validate_int_list
from models.registry import register_refiner

__all__ = ["FusionRefiner", "quaternion_to_matrix_flat"]


def _quadratic_form_matrix() -> torch.Tensor:
    """``M`` with ``R.flatten() = (q outer q).flatten() @ M`` for unit ``wxyz`` quaternions ``q``."""
    m = torch.zeros(4, 4, 9)
    # R = (w^2 - |v|^2) I + 2 v v^T + 2 w [v]x, each entry a quadratic form in (w, x, y, z).
    w, x, y, z = range(4)
    entries = {
        0: [(w, w, 1), (x, x, 1), (y, y, -1), (z, z, -1)],
        1: [(x, y, 2), (w, z, -2)],
        2: [(x, z, 2), (w, y, 2)],
        3: [(x, y, 2), (w, z, 2)],
        4: [(w, w, 1), (x, x, -1), (y, y, 1), (z, z, -1)],
        5: [(y, z, 2), (w, x, -2)],
        6: [(x, z, 2), (w, y, -2)],
        7: [(y, z, 2), (w, x, 2)],
        8: [(w, w, 1), (x, x, -1), (y, y, -1), (z, z, 1)],
    }
    for k, terms in entries.items():
        for i, j, c in terms:
            m[i, j, k] += c
    return m.reshape(16, 9)


_QUADRATIC_FORM = _quadratic_form_matrix()


def quaternion_to_matrix_flat(q: torch.Tensor) -> torch.Tensor:
    """Row-major rotation matrices of unit quaternions.

    Computed as one constant matrix product of the outer product ``q q^T`` (every entry of ``R`` is a
    quadratic form in ``q``): in the exported graph that is 4 nodes instead of about 40 elementwise ones,
    which measured as a quarter of the fusion model's INT8 inference time at batch 1.

    Args:
        q: ``(N, 4)`` float unit quaternions, ``wxyz`` (object-to-camera).

    Returns:
        ``(N, 9)`` float: ``R`` row-major, ``x_cam = R @ x_obj``.
    """
    outer = (q.unsqueeze(2) * q.unsqueeze(1)).flatten(1)
    return outer @ _QUADRATIC_FORM.to(dtype=q.dtype, device=q.device)


@register_refiner("fusion")
class FusionRefiner(Refiner):
    """Shallow CNN + rotation-matrix pose stage + multiplicative fusion ``concat[a, b, a*b]``.

    Config keys (beyond the common ones of :class:`models.blocks.Refiner`):
        * ``conv_channels`` (list of ints, default ``[16, 16]``): one ``conv 5x5 - BN - ReLU - maxpool 2``
          block per entry.
        * ``kernel_size`` (odd int, default 5).
        * ``fuse_width`` (int, default 512): width ``d`` of the image and pose feature vectors.
        * ``pose_input`` (``"matrix"`` or ``"quaternion"``, default ``"matrix"``).
        * ``fusion`` (``"product"`` = ``concat[a, b, a*b]``, default; or ``"concat"`` = ``concat[a, b]``).
        * ``pose_widths`` (default ``[64, 512]``): pose MLP widths; the last must equal ``fuse_width``.
        * ``head_widths`` (default ``[256, 64]``).

    Shape:
        - image: ``(N, S, S, 3)`` uint8, NHWC, ``channel_order`` (default BGR).
        - q_in: ``(N, 4)`` float32, ``wxyz``.
        - output: ``(N, 4)`` float32 unit quaternions ``q_out``, ``wxyz``.
    """

    DEFAULT_CONFIG = {
        "input_size": 64,
        "conv_channels": [16, 16],
        "kernel_size": 5,
        "fuse_width": 512,
        "pose_input": "matrix",
        "fusion": "product",
        "pose_widths": [64, 512],
        "head_widths": [256, 64],
    }

    @classmethod
    def resolve_config(cls, config: dict) -> dict:
        cfg = super().resolve_config(config)
        cfg["conv_channels"] = validate_int_list(cfg, "conv_channels")
        k = cfg["kernel_size"]
        if not isinstance(k, int) or isinstance(k, bool) or k <= 0 or k % 2 == 0:
            raise ValueError(f"config['kernel_size'] must be a positive odd int; got {k!r}")
        pools = 2 ** len(cfg["conv_channels"])
        if cfg["input_size"] % pools:
            raise ValueError(
                f"config['input_size'] must be a multiple of {pools} ({len(cfg['conv_channels'])} 2x max-pools); got {cfg['input_size']}"
            )
        d = cfg["fuse_width"]
        if not isinstance(d, int) or isinstance(d, bool) or d <= 0:
            raise ValueError(f"config['fuse_width'] must be a positive int; got {d!r}")
        if cfg["pose_widths"][-1] != d:
            raise ValueError(f"config['pose_widths'] must end with fuse_width={d}; got {cfg['pose_widths']}")
        if cfg["pose_input"] not in ("matrix", "quaternion"):
            raise ValueError(f"config['pose_input'] must be 'matrix' or 'quaternion'; got {cfg['pose_input']!r}")
        if cfg["fusion"] not in ("product", "concat"):
            raise ValueError(f"config['fusion'] must be 'product' or 'concat'; got {cfg['fusion']!r}")
        return cfg

    def __init__(self, **config):
        nn.Module.__init__(self)
        cfg = self.resolve_config(config)
        self.config = cfg
        self.input_size = cfg["input_size"]
        self.channel_order = cfg["channel_order"]
        self.normalize = InputNormalization(cfg["channel_order"], cfg["mean_rgb"], cfg["std_rgb"])
        self.features, _ = self.build_feature_stage(cfg)
        d = cfg["fuse_width"]
        n_pose_in = 9 if cfg["pose_input"] == "matrix" else 4
        self.pose = mlp([n_pose_in, *cfg["pose_widths"]], relu_last=True)
        n_fused = 3 * d if cfg["fusion"] == "product" else 2 * d
        self.head = RefinementHead(n_fused, cfg["head_widths"])

    def build_feature_stage(self, config: dict) -> tuple[nn.Module, int]:
        k = config["kernel_size"]
        layers: list[nn.Module] = []
        c_in = 3
        for c in config["conv_channels"]:
            layers += [nn.Conv2d(c_in, c, k, padding=k // 2), nn.BatchNorm2d(c), nn.ReLU(inplace=True), nn.MaxPool2d(2)]
            c_in = c
        side = config["input_size"] // 2 ** len(config["conv_channels"])
        d = config["fuse_width"]
        layers += [nn.Flatten(), nn.Linear(c_in * side * side, d), nn.ReLU(inplace=True)]
        return nn.Sequential(*layers), d

    def forward(self, image: torch.Tensor, q_in: torch.Tensor) -> torch.Tensor:
        """Predict ``q_out`` (``q_refined = q_in * q_out``); same contract as :meth:`Refiner.forward`."""
        self._check_inputs(image, q_in)
        a = self.features(self.normalize(image))
        pose_in = quaternion_to_matrix_flat(q_in) if self.config["pose_input"] == "matrix" else q_in
        b = self.pose(pose_in)
        fused = torch.cat([a, b, a * b] if self.config["fusion"] == "product" else [a, b], dim=1)
        return self.head(fused)
