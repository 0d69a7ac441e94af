"""Building blocks shared by every refiner: in-graph input normalisation, the pose stage, the refinement head,
an ONNX-friendly local response norm, and the :class:`Refiner` base class that wires them together.

The network follows Jain & Dellaert, "Fast 3D Pose Refinement with RGB Images", section "Network Architecture"
(docs/design.md §1): a CNN feature stage on the crop, a pose stage that expands the coarse quaternion to a
feature vector, and a refinement head on their concatenation whose 4 outputs are unit-normalised.

Conventions (docs/design.md §2):
    * quaternions are ``wxyz`` (scalar first), Hamilton product; ``q_in`` is the coarse rotation
      object-to-camera, the output ``q_out`` the correction with ``q_refined = q_in * q_out``;
    * the image input is ``(N, S, S, 3)`` ``uint8`` NHWC in the model's ``channel_order`` (default ``"BGR"``,
      what ``cv2.imread`` gives). Cast, scaling to ``[0, 1]``, mean/std normalisation and NHWC -> NCHW happen
      inside :meth:`Refiner.forward`, so they are part of the exported ONNX graph.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from refiner_rt.metadata import CHANNEL_ORDERS, MAX_CROP_CONTEXT, MAX_INPUT_SIZE
from refiner_rt.preprocess import CROP_FILTERS, DEFAULT_CONTEXT

__all__ = [
    "IMAGENET_MEAN_RGB",
    "IMAGENET_STD_RGB",
    "InputNormalization",
    "LocalResponseNorm",
    "PoseStage",
    "RefinementHead",
    "Refiner",
    "mlp",
    "unit_normalize",
    "validate_float_triple",
    "validate_int_list",
]

# ImageNet statistics, in RGB order and [0, 1] units (torchvision's values). The model reorders them to its
# channel_order, so a config never holds statistics in one order and pixels in another.
IMAGENET_MEAN_RGB = (0.485, 0.456, 0.406)
IMAGENET_STD_RGB = (0.229, 0.224, 0.225)

# Guard against 0/0 in the output normalisation; a trained head never produces a raw norm this small.
_NORM_EPS = 1e-12


def unit_normalize(q: torch.Tensor) -> torch.Tensor:
    """Scale quaternions to unit norm (the sign is kept; ``q`` and ``-q`` are the same rotation).

    Args:
        q: ``(N, 4)`` float quaternions, ``wxyz``.

    Returns:
        ``(N, 4)`` unit quaternions, ``wxyz``. A raw norm below 1e-12 is divided by 1e-12 instead (no NaN).
    """
    return q / torch.linalg.vector_norm(q, dim=1, keepdim=True).clamp_min(_NORM_EPS)


def mlp(widths: Sequence[int], *, relu_last: bool) -> nn.Sequential:
    """Fully connected layers ``widths[0] -> widths[1] -> ... -> widths[-1]`` with ReLU between them.

    Args:
        widths: layer widths including input and output, at least two entries.
        relu_last: whether a ReLU follows the last layer too.

    Returns:
        ``nn.Sequential`` of ``len(widths) - 1`` ``nn.Linear`` layers (and their ReLUs).
    """
    layers: list[nn.Module] = []
    for i, (w_in, w_out) in enumerate(zip(widths[:-1], widths[1:])):
        layers.append(nn.Linear(w_in, w_out))
        if relu_last or i < len(widths) - 2:
            layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


PER_CROP_EPS = 0.02  # [0, 1] units: below a grey level's spread of 5, a crop's contrast is not amplified further


class InputNormalization(nn.Module):
    """uint8 NHWC image -> normalised float NCHW tensor, inside the graph.

    Computes ``(image / 255 - mean) / std`` per channel as one multiply-add (``image * scale + shift``), after
    the NHWC -> NCHW transpose (done on uint8, four times less memory traffic than on float).

    Args:
        channel_order: ``"BGR"`` or ``"RGB"``: the order of the image's channels.
        mean_rgb: per-channel mean in RGB order, ``[0, 1]`` units.
        std_rgb: per-channel standard deviation in RGB order, ``[0, 1]`` units, all > 0.
        per_crop: normalise each crop by its own per-channel mean and standard deviation instead of
            ``mean_rgb``/``std_rgb`` (the network config's ``input_norm: "per_crop"``).

    Shape:
        - input: ``(N, S, S, 3)`` uint8, NHWC, ``channel_order``.
        - output: ``(N, 3, S, S)`` float32, NCHW, same channel order.
    """

    def __init__(self, channel_order: str, mean_rgb: Sequence[float], std_rgb: Sequence[float], per_crop: bool = False):
        super().__init__()
        self.per_crop = bool(per_crop)
        mean = torch.tensor(mean_rgb, dtype=torch.float32)
        std = torch.tensor(std_rgb, dtype=torch.float32)
        if channel_order == "BGR":
            mean, std = mean.flip(0), std.flip(0)
        # Derived from the config, so not saved in the state dict: the config stays the single source of truth.
        self.register_buffer("scale", (1.0 / (255.0 * std)).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("shift", (-mean / std).view(1, 3, 1, 1), persistent=False)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = image.permute(0, 3, 1, 2).to(self.scale.dtype)
        if not self.per_crop:
            return x * self.scale + self.shift
        # Per crop and channel: (x - mean) / (std + eps), in [0, 1] units. Invariant to a per-channel gain and offset
        # (exposure, white balance, contrast, brightness) up to clipping; eps keeps a flat crop finite.
        x = x * (1.0 / 255.0)
        mean = x.mean(dim=(2, 3), keepdim=True)
        centred = x - mean
        std = (centred * centred).mean(dim=(2, 3), keepdim=True).sqrt()
        return centred / (std + PER_CROP_EPS)


@torch.library.custom_op("refiner_rt::local_response_norm", mutates_args=())
def _lrn_op(x: torch.Tensor, size: int, alpha: float, beta: float, k: float) -> torch.Tensor:
    # Used only while exporting (see LocalResponseNorm): the exporter maps it to the ONNX LRN operator.
    return F.local_response_norm(x, size, alpha, beta, k)


@_lrn_op.register_fake
def _lrn_op_fake(x, size, alpha, beta, k):
    return torch.empty_like(x)


class LocalResponseNorm(nn.Module):
    """Cross-channel local response normalisation that exports as the single ONNX ``LRN`` operator.

    Same maths as ``nn.LocalResponseNorm`` and ONNX ``LRN``:
    ``y = x / (k + alpha / size * sum_{c' in window(c)} x_{c'}^2) ** beta``. ``nn.LocalResponseNorm`` exports
    as whatever subgraph the exporter decomposes it into (with ``If`` nodes, which OpenCV's ``cv2.dnn``
    rejects, on some exporter paths); while ``torch.export`` traces, this module calls the custom op
    ``refiner_rt::local_response_norm`` instead, which :mod:`export.onnx_export` writes either as the ONNX
    ``LRN`` operator or as a decomposition chosen for speed. In eager mode (training) it is
    ``F.local_response_norm`` with its autograd.

    Args:
        size: number of neighbouring channels summed over (odd).
        alpha: scale (divided by ``size``, as in Caffe, PyTorch and ONNX).
        beta: exponent.
        k: additive bias.

    Shape:
        - input / output: ``(N, C, H, W)`` float.
    """

    def __init__(self, size: int, alpha: float, beta: float, k: float):
        super().__init__()
        if not isinstance(size, int) or size <= 0 or size % 2 == 0:
            # PyTorch and ONNX LRN centre an even window differently; odd windows agree exactly.
            raise ValueError(f"LocalResponseNorm size must be a positive odd int; got {size!r}")
        self.size, self.alpha, self.beta, self.k = int(size), float(alpha), float(beta), float(k)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.compiler.is_exporting():
            return torch.ops.refiner_rt.local_response_norm(x, self.size, self.alpha, self.beta, self.k)
        return F.local_response_norm(x, self.size, self.alpha, self.beta, self.k)

    def extra_repr(self) -> str:
        return f"size={self.size}, alpha={self.alpha}, beta={self.beta}, k={self.k}"


class PoseStage(nn.Module):
    """The paper's pose input stage: fully connected layers expanding the unit quaternion ``q_in`` (ReLU after each).

    Args:
        widths: hidden and output widths after the 4 inputs; paper default ``(64, 512, 4096)`` (3 FC layers,
            4 -> 64 -> 512 -> 4096).

    Shape:
        - input: ``(N, 4)`` float32, ``wxyz``.
        - output: ``(N, widths[-1])`` float32, non-negative.
    """

    def __init__(self, widths: Sequence[int]):
        super().__init__()
        self.out_features = int(widths[-1])
        self.layers = mlp([4, *widths], relu_last=True)

    def forward(self, q_in: torch.Tensor) -> torch.Tensor:
        return self.layers(q_in)


class RefinementHead(nn.Module):
    """The paper's refinement stage: fully connected layers from the concatenated features down to 4, unit-normalised.

    Args:
        in_features: image features + pose features (paper: 4096 + 4096 = 8192).
        widths: hidden widths; paper default ``(1024, 256, 64)`` (4 FC layers, 8192 -> 1024 -> 256 -> 64 -> 4).

    Shape:
        - input: ``(N, in_features)`` float32.
        - output: ``(N, 4)`` float32 unit quaternions, ``wxyz``.
    """

    def __init__(self, in_features: int, widths: Sequence[int]):
        super().__init__()
        self.layers = mlp([in_features, *widths, 4], relu_last=False)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return unit_normalize(self.layers(features))


def validate_int_list(config: dict, key: str, *, min_len: int = 1) -> list[int]:
    """``config[key]`` as a list of positive ints (for subclasses' ``resolve_config``).

    Raises:
        ValueError: not a list/tuple of at least ``min_len`` positive ints; the message shows the value.
    """
    value = config[key]
    if (
        not isinstance(value, (list, tuple))
        or len(value) < min_len
        or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
    ):
        raise ValueError(f"config[{key!r}] must be a list of at least {min_len} positive ints; got {value!r}")
    return [int(v) for v in value]


def validate_float_triple(config: dict, key: str, *, positive: bool) -> list[float]:
    """``config[key]`` as 3 floats (RGB order), optionally all > 0.

    Raises:
        ValueError: not 3 numbers (or not all positive when ``positive``); the message shows the value.
    """
    value = config[key]
    ok = isinstance(value, (list, tuple)) and len(value) == 3
    ok = ok and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    if not ok or (positive and not all(v > 0 for v in value)):
        kind = "positive numbers" if positive else "numbers"
        raise ValueError(f"config[{key!r}] must be 3 {kind} in RGB order; got {value!r}")
    return [float(v) for v in value]


class Refiner(nn.Module):
    """Base class of every refiner: normalisation -> feature stage, pose stage -> refinement head.

    A subclass sets ``DEFAULT_CONFIG`` (its own keys; the common keys below are added) and implements
    :meth:`build_feature_stage`; registering it with :func:`models.nets.registry.register_refiner` makes it buildable
    by name. Subclasses that need a different forward keep its signature and contract.

    Common config keys (defaults in ``COMMON_CONFIG``):
        * ``input_size`` (int, 1 to ``MAX_INPUT_SIZE`` = 1024): side ``S`` of the square crop (set per architecture).
        * ``channel_order`` (str): ``"BGR"`` (default, cv2's order) or ``"RGB"``: order of the image input.
        * ``mean_rgb``, ``std_rgb`` (3 floats, RGB order, [0, 1] units): normalisation; ImageNet by default.
        * ``crop_context`` (float from 1 to ``MAX_CROP_CONTEXT`` = 4): crop-rule context factor the model is
          trained with (default 1.2); written to the ONNX metadata.
        * ``crop_filter`` (str): the crop rule's filter, ``"none"`` (default: every model before the key) or
          ``"antialias"`` (:func:`refiner_rt.preprocess.crop_to_square`); the training crops are cut with it and the
          ONNX metadata tells the runtime.
        * ``pose_widths`` (list of int): pose stage widths after the 4 inputs; default ``[64, 512, 4096]``.
        * ``head_widths`` (list of int): refinement head hidden widths; default ``[1024, 256, 64]``.

    Attributes:
        arch: registry name.
        config: the complete config (JSON-able; ``build_refiner(arch, **config)`` rebuilds the model).
        input_size: side ``S`` of the input crop.
        channel_order: ``"BGR"`` or ``"RGB"``.
    """

    arch: str = ""
    COMMON_CONFIG: dict = {
        "input_size": 64,
        "channel_order": "BGR",
        "mean_rgb": list(IMAGENET_MEAN_RGB),
        "std_rgb": list(IMAGENET_STD_RGB),
        "crop_context": DEFAULT_CONTEXT,
        "crop_filter": "none",
        "pose_widths": [64, 512, 4096],
        "head_widths": [1024, 256, 64],
    }
    DEFAULT_CONFIG: dict = {}
    # Keys used only to initialise weights (e.g. a pretrained-weights file): ignored when a checkpoint's own
    # state dict is loaded over the model, so a checkpoint does not depend on files of the machine it came from.
    INIT_ONLY_KEYS: frozenset = frozenset()

    @classmethod
    def default_config(cls) -> dict:
        """The complete default config of this architecture (a fresh, JSON-able dict)."""
        return copy.deepcopy({**cls.COMMON_CONFIG, **cls.DEFAULT_CONFIG})

    @classmethod
    def resolve_config(cls, config: dict) -> dict:
        """Merge ``config`` over the defaults and validate the common keys.

        Raises:
            ValueError: an unknown key (the message lists the known ones) or an invalid value.
        """
        defaults = cls.default_config()
        unknown = sorted(set(config) - set(defaults))
        if unknown:
            raise ValueError(
                f"unknown config key(s) {unknown} for refiner {cls.arch!r}; known keys: {sorted(defaults)}"
            )
        cfg = {**defaults, **copy.deepcopy(config)}
        size = cfg["input_size"]
        if not isinstance(size, int) or isinstance(size, bool) or not 1 <= size <= MAX_INPUT_SIZE:
            raise ValueError(f"config['input_size'] must be an int from 1 to {MAX_INPUT_SIZE}; got {size!r}")
        if cfg["channel_order"] not in CHANNEL_ORDERS:
            raise ValueError(f"config['channel_order'] must be one of {CHANNEL_ORDERS}; got {cfg['channel_order']!r}")
        cfg["mean_rgb"] = validate_float_triple(cfg, "mean_rgb", positive=False)
        cfg["std_rgb"] = validate_float_triple(cfg, "std_rgb", positive=True)
        context = cfg["crop_context"]
        if not isinstance(context, (int, float)) or isinstance(context, bool) or not 1.0 <= context <= MAX_CROP_CONTEXT:
            raise ValueError(f"config['crop_context'] must be a number from 1 to {MAX_CROP_CONTEXT:g}; got {context!r}")
        cfg["crop_context"] = float(context)
        if cfg["crop_filter"] not in CROP_FILTERS:
            raise ValueError(f"config['crop_filter'] must be one of {CROP_FILTERS}; got {cfg['crop_filter']!r}")
        cfg["pose_widths"] = validate_int_list(cfg, "pose_widths")
        cfg["head_widths"] = validate_int_list(cfg, "head_widths", min_len=0)
        return cfg

    def __init__(self, **config):
        super().__init__()
        cfg = self.resolve_config(config)
        self.config = cfg
        self.input_size = cfg["input_size"]
        self.channel_order = cfg["channel_order"]
        self.normalize = InputNormalization(cfg["channel_order"], cfg["mean_rgb"], cfg["std_rgb"])
        self.features, n_image_features = self.build_feature_stage(cfg)
        self.pose = PoseStage(cfg["pose_widths"])
        self.head = RefinementHead(n_image_features + self.pose.out_features, cfg["head_widths"])

    def build_feature_stage(self, config: dict) -> tuple[nn.Module, int]:
        """The CNN feature stage: a module mapping ``(N, 3, S, S)`` normalised float to ``(N, F)`` features.

        Args:
            config: the resolved config.

        Returns:
            ``(module, F)``: the module and its number of output features.
        """
        raise NotImplementedError(f"{type(self).__name__} must implement build_feature_stage")

    def forward(self, image: torch.Tensor, q_in: torch.Tensor) -> torch.Tensor:
        """Predict the rotation correction ``q_out`` (``q_refined = q_in * q_out``).

        Args:
            image: ``(N, S, S, 3)`` uint8 crops, NHWC, in ``self.channel_order`` (default BGR), cut with the
                crop rule of :mod:`refiner_rt.preprocess`.
            q_in: ``(N, 4)`` float coarse rotations, ``wxyz``, object-to-camera, unit norm.

        Returns:
            ``(N, 4)`` unit quaternions ``q_out``, ``wxyz``, same dtype as the model (float32 by default).

        Raises:
            ValueError: ``image`` is not uint8 ``(N, S, S, 3)`` or ``q_in`` not floating ``(N, 4)`` with the same N.
        """
        self._check_inputs(image, q_in)
        image_features = self.features(self.normalize(image))
        pose_features = self.pose(q_in)
        return self.head(torch.cat([image_features, pose_features], dim=1))

    def _check_inputs(self, image: torch.Tensor, q_in: torch.Tensor) -> None:
        s = self.input_size
        if image.dtype != torch.uint8:
            raise ValueError(f"image must be a uint8 tensor (N, {s}, {s}, 3) NHWC; got dtype {image.dtype}")
        if image.dim() != 4 or tuple(image.shape[1:]) != (s, s, 3):
            raise ValueError(f"image must have shape (N, {s}, {s}, 3) NHWC {self.channel_order}; got {tuple(image.shape)}")
        if not q_in.is_floating_point() or q_in.dim() != 2 or q_in.shape[1] != 4:
            raise ValueError(f"q_in must be a float tensor (N, 4) wxyz; got {q_in.dtype} {tuple(q_in.shape)}")
        if image.shape[0] != q_in.shape[0]:
            raise ValueError(f"image and q_in must have the same N; got {image.shape[0]} and {q_in.shape[0]}")

    def num_parameters(self) -> int:
        """Number of trainable parameters."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)
