"""The project's improved refiner: the paper's shallow CNN with a rotation-matrix pose input and multiplicative fusion.

Differences from the paper's design (``models.nets.shallow``), each chosen by measurement (see
``benchmarks/studies/paper_protocol/README.md``):
    * the coarse rotation enters the pose stage as its 3x3 rotation matrix (9 numbers, continuous
      in the rotation and free of the ``q ~ -q`` ambiguity) instead of the raw quaternion;
    * image and pose features are projected to the same width ``d`` and fused as
      ``concat[a, b, a * b]`` (the product lets the head compare appearance with the claimed pose
      directly) instead of a plain 4096 + 4096 concatenation;
    * 3x3 convolutions instead of 5x5: the convolutions are most of the INT8 model's time at batch 1, and
      3x3 cuts their FLOPs 2.8x (1.7x faster refine() on one core) with no loss of accuracy in training;
    * the head is narrower (``3d -> 256 -> 64 -> 4``), so the model is about 4x smaller than the
      paper's and faster on a CPU.

Contract unchanged (docs/design.md §4.1): ``forward(image (N, S, S, 3) uint8 NHWC BGR, q_in (N, 4)
wxyz) -> q_out (N, 4)`` unit ``wxyz``, ``q_refined = q_in * q_out``; the quaternion-to-matrix
conversion happens inside the graph.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from models.nets.blocks import InputNormalization, RefinementHead, Refiner, mlp, unit_normalize, validate_int_list
from models.nets.quaternion import quat_multiply
from models.nets.registry import register_refiner

__all__ = ["FusionRefiner", "quaternion_to_matrix_flat", "matrix_from_6d", "correction_from_matrices", "roll_angle",
           "turn_grid", "canonical_roll", "quarter_roll", "ROLLS", "with_roll"]


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

INPUT_NORMS = ("dataset", "per_crop")


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


def matrix_from_6d(x: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from 6 numbers by Gram-Schmidt (Zhou et al., CVPR 2019: continuous, unlike quaternions).

    Args:
        x: ``(N, 6)`` float, two 3-vectors ``a1, a2`` (need not be unit or orthogonal).

    Returns:
        ``(N, 3, 3)`` float rotation matrices with columns ``b1 = a1/|a1|``, ``b2`` (``a2`` made orthogonal
        to ``b1``, unit), ``b3 = b1 x b2``.
    """
    a1, a2 = x[:, :3], x[:, 3:]
    b1 = a1 / torch.linalg.vector_norm(a1, dim=1, keepdim=True).clamp_min(1e-8)
    a2 = a2 - (b1 * a2).sum(dim=1, keepdim=True) * b1
    b2 = a2 / torch.linalg.vector_norm(a2, dim=1, keepdim=True).clamp_min(1e-8)
    b3 = torch.cross(b1, b2, dim=1)
    return torch.stack([b1, b2, b3], dim=2)


def correction_from_matrices(r_in: torch.Tensor, r_abs: torch.Tensor) -> torch.Tensor:
    """``q_out`` (``wxyz``, ``w >= 0``) of ``R_out = R_in^T R_abs``, the correction that takes ``R_in`` to ``R_abs``.

    Uses ``w = sqrt(1 + trace) / 2``: exact and well conditioned for corrections up to well past 90 degrees
    (a refiner's corrections are small); near 180 degrees, where ``w -> 0``, the clamp keeps it finite and the
    unit normalisation keeps the result a rotation.

    Args:
        r_in: ``(N, 3, 3)`` input rotations; r_abs: ``(N, 3, 3)`` estimated rotations (same frame).

    Returns:
        ``(N, 4)`` unit quaternions, ``wxyz``, ``w >= 0``.
    """
    r = r_in.transpose(1, 2) @ r_abs
    trace = r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]
    w4 = 2.0 * torch.sqrt((1.0 + trace).clamp_min(1e-6))  # 4 w
    q = torch.stack([w4 / 4.0, (r[:, 2, 1] - r[:, 1, 2]) / w4, (r[:, 0, 2] - r[:, 2, 0]) / w4, (r[:, 1, 0] - r[:, 0, 1]) / w4], dim=1)
    return unit_normalize(q)


def roll_angle(q: torch.Tensor) -> torch.Tensor:
    """``(N,)`` image angle (radians, clockwise from up, x right and y down) of the object's z axis under the
    rotations ``q`` (``(N, 4)`` wxyz, object to the viewing-ray frame), or of its x axis where the z axis lies
    within 30 degrees of the ray (its image direction is then ill-defined; the x axis is at least 60 degrees off)."""
    r = quaternion_to_matrix_flat(q).view(-1, 3, 3)
    z, x = r[:, :, 2], r[:, :, 0]
    use_z = (z[:, 0] * z[:, 0] + z[:, 1] * z[:, 1]) > 0.25  # sin(30 deg)^2
    axis = torch.where(use_z[:, None], z, x)
    return torch.atan2(axis[:, 0], -axis[:, 1])


def turn_grid(phi: torch.Tensor, size: int) -> torch.Tensor:
    """``(N, size, size, 2)`` ``grid_sample`` grid (``align_corners=False``) that turns a square image about its centre
    by ``phi`` (``(N,)`` radians; a pixel offset ``d -> R(phi) d``, x right, y down): the output pixel at ``d`` samples
    the input at ``R(-phi) d``. The one rule for the training's in-plane turns and the network's canonical roll."""
    c, s = torch.cos(phi)[:, None, None], torch.sin(phi)[:, None, None]
    u = (torch.arange(size, dtype=phi.dtype, device=phi.device) * 2 + 1) / size - 1  # pixel centres in [-1, 1]
    x_out, y_out = u[None, None, :], u[None, :, None]
    return torch.stack([c * x_out + s * y_out, c * y_out - s * x_out], dim=-1)


def canonical_roll(image: torch.Tensor, q_in: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Turn each crop about its centre, and its coarse rotation about the viewing ray with it, so that the axis of
    :func:`roll_angle` points up: ``(image (N, C, S, S) float, q_in (N, 4))`` in and out.

    Turning the image by ``phi`` (a pixel offset ``d -> R(phi) d``, x right, y down) shows the object turned by
    ``q_z(phi)`` about the ray, so the turned crop goes with ``q_z(phi) * q_in``, and ``q_out = q_in^-1 q_gt`` is the
    same for both. Here ``phi = -roll_angle(q_in)``. Corners the turn uncovers are filled by reflection, as the
    training's in-plane turns fill them (bilinear, ``align_corners=False``).
    """
    psi = roll_angle(q_in)
    grid = turn_grid(-psi, image.shape[-1]).to(image.dtype)
    turned = torch.nn.functional.grid_sample(image, grid, mode="bilinear", padding_mode="reflection",
                                             align_corners=False)
    half = -psi / 2
    q_turn = torch.stack([torch.cos(half), torch.zeros_like(half), torch.zeros_like(half), torch.sin(half)], dim=1)
    return turned, quat_multiply(q_turn.to(q_in.dtype), q_in)


def quarter_roll(image: torch.Tensor, q_in: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`canonical_roll` in quarter turns: each crop turned by the multiple of 90 degrees nearest to the one that
    points the axis of :func:`roll_angle` up (so that it then points within 45 degrees of up), and the coarse rotation
    with it; ``(image (N, C, S, S), q_in (N, 4))`` in and out.

    A quarter turn moves pixels without resampling them and uncovers no corner, and a crop whose axis already points
    within 45 degrees of up (an object standing on a table under a level camera) is not turned at all: the network
    sees it as a network without the roll does, and only the views rolled further are turned.
    """
    k = torch.round(roll_angle(q_in) / (math.pi / 2)).remainder(4)  # quarter turns to undo, 0-3
    turned = image.clone()
    for quarter in (1, 2, 3):
        rows = k == quarter
        if bool(rows.any()):
            # a turn by -quarter * 90 degrees, clockwise positive (x right, y down): counter-clockwise on screen
            turned[rows] = torch.rot90(image[rows], quarter, dims=(2, 3))
    half = -k * (math.pi / 4)
    q_turn = torch.stack([torch.cos(half), torch.zeros_like(half), torch.zeros_like(half), torch.sin(half)], dim=1)
    return turned, quat_multiply(q_turn.to(q_in.dtype), q_in)


# The fusion network's input turns: none, the canonical roll (continuous), its quarter turns.
ROLLS = {"canonical": canonical_roll, "quarter": quarter_roll}


# Config keys of the fusion network that change no weight: a network may go on with another value of them.
WEIGHTLESS_KEYS = ("roll", "input_norm", "crop_filter")


def with_roll(model, config: dict):
    """``model`` rebuilt with ``config`` when the two differ only in the fusion network's weightless keys
    (:data:`WEIGHTLESS_KEYS`: the input turn ``roll``, the input normalisation ``input_norm`` and the crop rule's
    ``crop_filter``, which change no weight, so a network trained without them may go on with them, and back), its
    weights kept; else ``model`` as it is (the caller's own checks then refuse another network)."""
    mine = getattr(model, "config", None)
    if getattr(model, "arch", None) != "fusion" or not mine:
        return model
    mine = {**FusionRefiner.default_config(), **mine}  # a checkpoint from before a key existed has its default
    change = {k: config[k] for k in WEIGHTLESS_KEYS if k in config and config[k] != mine.get(k)}
    if not change or {**mine, **change} != {**mine, **config}:
        return model
    from models.nets.registry import build_refiner

    turned = build_refiner("fusion", **{**mine, **change})
    turned.load_state_dict(model.state_dict())
    return turned.train(model.training)


@register_refiner("fusion")
class FusionRefiner(Refiner):
    """Shallow CNN + rotation-matrix pose stage + multiplicative fusion ``concat[a, b, a*b]``.

    Config keys (beyond the common ones of :class:`models.nets.blocks.Refiner`):
        * ``conv_channels`` (list of ints, default ``[16, 16]``): one ``conv k x k - BN - ReLU - maxpool 2``
          block per entry.
        * ``kernel_size`` (odd int, default 3; the paper's network uses 5).
        * ``fuse_width`` (int, default 512): width ``d`` of the image and pose feature vectors.
        * ``pose_input`` (``"matrix"`` or ``"quaternion"``, default ``"matrix"``).
        * ``fusion`` (``"product"`` = ``concat[a, b, a*b]``, default; or ``"concat"`` = ``concat[a, b]``).
        * ``output`` (``"relative"``: the head predicts ``q_out`` directly, as the paper's; ``"absolute"``: the
          head predicts the rotation the crop shows, ``R_abs``, as 6 numbers (:func:`matrix_from_6d`), and the
          graph computes ``q_out`` from ``R_in^T R_abs`` (:func:`correction_from_matrices`), so the network
          never has to learn the composition of two rotations).
        * ``pose_widths`` (default ``[64, 512]``): pose MLP widths; the last must equal ``fuse_width``.
        * ``head_widths`` (default ``[256, 64]``).
        * ``roll`` (``"none"``, default; or ``"canonical"``): with ``"canonical"`` the graph first turns the crop
          about its centre so that the coarse pose's object z axis points up in it (its x axis where the z axis is
          within 30 degrees of the viewing ray), and the coarse pose with it (:func:`canonical_roll`). The network
          then sees every viewing direction at one roll, whatever the object's roll about the ray in the image (an
          object leaning on another, a tilted camera): rolls its training scenes lack cost nothing. ``q_out`` is
          unchanged by the turn, so the contract is the same. Ray frame only: the roll is about the viewing ray.
          ``"quarter"``: the same in quarter turns (:func:`quarter_roll`): views within 45 degrees of that roll are
          left as they are, the others turned by 90, 180 or 270 degrees without resampling.
        * ``input_norm`` (``"dataset"``, default: ``mean_rgb``/``std_rgb``; or ``"per_crop"``: each crop by its own
          per-channel mean and standard deviation, inside the graph, so a camera's exposure, white balance and
          contrast, which change a channel by a gain and an offset, do not reach the network; the runtime contract
          is unchanged).

    Shape:
        - image: ``(N, S, S, 3)`` uint8, NHWC, ``channel_order`` (default BGR).
        - q_in: ``(N, 4)`` float32, ``wxyz``.
        - output: ``(N, 4)`` float32 unit quaternions ``q_out``, ``wxyz``.
    """

    DEFAULT_CONFIG = {
        "input_size": 64,
        "conv_channels": [16, 16],
        "kernel_size": 3,
        "fuse_width": 512,
        "pose_input": "matrix",
        "fusion": "product",
        "output": "relative",
        "pose_widths": [64, 512],
        "head_widths": [256, 64],
        "roll": "none",
        "input_norm": "dataset",
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
        if cfg["output"] not in ("relative", "absolute"):
            raise ValueError(f"config['output'] must be 'relative' or 'absolute'; got {cfg['output']!r}")
        if cfg["fusion"] not in ("product", "concat"):
            raise ValueError(f"config['fusion'] must be 'product' or 'concat'; got {cfg['fusion']!r}")
        if cfg["roll"] not in ("none", *ROLLS):
            raise ValueError(f"config['roll'] must be one of {('none', *ROLLS)}; got {cfg['roll']!r}")
        if cfg["input_norm"] not in INPUT_NORMS:
            raise ValueError(f"config['input_norm'] must be one of {INPUT_NORMS}; got {cfg['input_norm']!r}")
        return cfg

    def __init__(self, **config):
        nn.Module.__init__(self)
        cfg = self.resolve_config(config)
        self.config = cfg
        self.input_size = cfg["input_size"]
        self.channel_order = cfg["channel_order"]
        self.normalize = InputNormalization(cfg["channel_order"], cfg["mean_rgb"], cfg["std_rgb"],
                                            per_crop=cfg["input_norm"] == "per_crop")
        self.features, _ = self.build_feature_stage(cfg)
        d = cfg["fuse_width"]
        n_pose_in = 9 if cfg["pose_input"] == "matrix" else 4
        self.pose = mlp([n_pose_in, *cfg["pose_widths"]], relu_last=True)
        n_fused = 3 * d if cfg["fusion"] == "product" else 2 * d
        if cfg["output"] == "relative":
            self.head = RefinementHead(n_fused, cfg["head_widths"])
        else:
            self.head = mlp([n_fused, *cfg["head_widths"], 6], relu_last=False)

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
        x = self.normalize(image)
        if self.config["roll"] != "none":
            x, q_in = ROLLS[self.config["roll"]](x, q_in)
        a = self.features(x)
        matrix_needed = self.config["pose_input"] == "matrix" or self.config["output"] == "absolute"
        r_in = quaternion_to_matrix_flat(q_in) if matrix_needed else None
        b = self.pose(r_in if self.config["pose_input"] == "matrix" else q_in)
        fused = torch.cat([a, b, a * b] if self.config["fusion"] == "product" else [a, b], dim=1)
        if self.config["output"] == "relative":
            return self.head(fused)
        # "absolute": the head estimates the rotation the crop shows; the correction is computed exactly.
        return correction_from_matrices(r_in.view(-1, 3, 3), matrix_from_6d(self.head(fused)))
