"""INT8 quantisation of an exported refiner ONNX model, with the metadata contract kept and the scheme recorded.

    from export.quantize import quantize_model
    report = quantize_model("refiner.onnx", "refiner.int8.onnx")    # raises QuantizationError instead of
    print(report.summary())                                         # writing a model that disagrees with fp32

Schemes (the value written to the metadata key ``quantization``; every other key is copied unchanged):
    * ``"dynamic-int8"`` (default): ``onnxruntime.quantization.quantize_dynamic`` on ``MatMul``/``Gemm`` only.
      The fully connected layers (nearly all the weight bytes) get int8 weights (per tensor, symmetric); their
      input activations are quantised to uint8 per call, from that call's own min/max, so no calibration data
      is needed. The convolutions stay fp32.
    * ``"static-qdq-int8"``: ``quantize_static`` in QDQ format (uint8 activations, int8 weights: onnxruntime's
      choice for x86 with VNNI) on ``MatMul``/``Gemm`` too, with activation ranges calibrated (min/max) on
      crops: from a dataset's training split through the shared crop rule and the crop cache
      (:func:`dataset_calibration`), or random crops (:func:`random_calibration`).
    * ``"static-qdq-int8-conv"``: for networks whose convolutions are the cost (the shipped five-block refiner):
      static QDQ with per-channel int8 weights on the convolutions with at least :data:`CONV_MIN_CHANNELS` input
      channels and the ReLU / max-pool of their blocks (:func:`wide_conv_chain`; onnxruntime runs each as a
      ``QLinearConv`` in NHWC with a uint8 ``NhwcMaxPool``, so the chain stays in uint8), plus dynamic INT8 on the
      fully connected layers with at least :data:`CONV_SCHEME_FC_MIN_WEIGHTS` weights
      (:func:`large_fully_connected`). The first convolution (3 input channels) and the small FC layers (the
      quaternion's quadratic form, the pose input, the ``q_out`` layer) stay fp32. Weights are 7-bit
      (``reduce_range``), which keeps onnxruntime's u8s8 kernels from saturating on CPUs without VNNI. Calibrate
      it on a dataset's training crops for a model that will be used. Measured in
      ``benchmarks/studies/int8_convs`` (speed, per-operator profile and held-out accuracy of the shipped models).
    * ``"static-qdq-int8-conv-float-pose"``: ``"static-qdq-int8-conv"`` with every layer that ``q_in`` reaches
      (:func:`pose_dependent`: the head, where the pose features join the image's) left fp32, so only the image
      stage is quantised and the output moves with ``q_in`` as smoothly as fp32's; the shipped refiners' head's first
      layer is then an fp32 ``MatMul`` (``benchmarks/studies/int8_smooth``: smoothness, speed and held-out error).

Why dynamic is the default for ``refiner-rt export --int8`` without a dataset (measured for the two-block refiners
on an earlier 2-core EPYC with AVX-512 VNNI, onnxruntime 1.31; speed: bare ``session.run`` at batch 1 on 1 thread, interleaved medians, random-weight
default configs; agreement: geodesic angle between INT8 and fp32 ``q_out``, mean / max in degrees):

    =========================  =========  =========  ====================  ====================
    scheme (ops quantised)     shallow    fusion     agreement, parity     agreement, held-out
                               run (us)   run (us)   inputs (s / f)        cube crops (s / f)
    =========================  =========  =========  ====================  ====================
    fp32                       1589       332        0                     0
    dynamic (MatMul, Gemm)     434        251        0.13/0.42, 0.25/0.50  0.33/0.70, 0.52/0.97
    dynamic (all, incl. Conv)  2277       1846       0.18/0.41, 0.28/0.50
    static QDQ (MatMul, Gemm)  399        278        0.41/0.93, 0.52/1.30  0.59/3.53, 0.71/1.55
    static QDQ (+ Conv)        553        348        0.43/1.14, 0.61/1.61
    =========================  =========  =========  ====================  ====================

(held-out cube crops: models trained on the tiny cube dataset of ``tests/cube_dataset.py``, static QDQ calibrated
on 256 of its training crops.) Quantising the convolutions never pays here: ``ConvInteger`` (dynamic) is several
times slower than the fp32 conv, and ``QLinearConv`` (static) is no faster than fp32 for 3- and 16-channel
convs while its quantise/dequantise nodes add time. On the fully connected layers static and dynamic run at the
same speed within this shared machine's noise, and dynamic agrees with fp32 better, even against a static model
calibrated on the very data it is checked on: it takes each call's exact activation range. A static model
also clips whatever lies outside its calibration range: calibrated on cube crops, it differs from fp32 by
5.6 (shallow) and 10.4 (fusion) degrees on average on the random parity inputs. On the cube test split
(200 crops x 5 coarse poses, mean error in degrees) the costs were: shallow fp32 6.717, dynamic 6.750,
static (dataset) 6.747, static (random) 6.822; fusion fp32 5.336, dynamic 5.389, static (dataset) 5.436,
static (random) 5.476. Static QDQ stays available for runtimes that want a fixed-range graph.

Bound: the fp32 parity tolerance (1e-4) does not apply to INT8. The exporter reports the INT8-vs-fp32
geodesic difference of ``q_out`` on the parity inputs and refuses to write a model whose mean difference
exceeds :data:`MAX_MEAN_DEG` (2 degrees) or whose largest difference exceeds :data:`MAX_MAX_DEG` (15 degrees).
Working INT8 models measured 0.1-0.7 degrees mean and at most 3.5 degrees; broken ones (a static model fed
inputs outside its calibration range) 5-12 degrees mean and 12-30 degrees max. For a model calibrated on a
dataset the bound is enforced on held-out crops of that dataset (the inputs it is meant for), and the
parity-input figure is reported only. The change of a sample's error is at most its difference (triangle
inequality), so these figures bound the accuracy cost from above; the cost itself (goal: mean error within
0.1 degree of fp32) is measured with ``refiner-rt eval`` on the rendered test split.

Portability: the dynamic scheme's weights are range-reduced to 7 bits (``reduce_range=True``). On x86 CPUs without
VNNI (AVX2 only) onnxruntime's u8s8 kernels add pairs of uint8 x int8 products in 16 bits, which saturate with
full 8-bit weights; the shipped five-block refiners then lost up to 1.5 degrees on held-out rendered scenes
(mustard bottle: fp32 4.19, 8-bit weights 5.65, 7-bit 4.30; cracker box 3.99 / 4.25 / 4.11; per-channel 8-bit
weights were worse still, 9.6 and 6.3), measured on an AVX2-only machine. 7-bit weights give the same model on
every CPU, VNNI or not, at a small cost where VNNI would not have saturated.

Conventions: images ``(N, S, S, 3)`` uint8 NHWC in the model's channel order; quaternions ``(N, 4)`` ``wxyz``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
from onnxruntime.quantization import (
    CalibrationDataReader,
    CalibrationMethod,
    QuantFormat,
    QuantType,
    quantize_dynamic,
    quantize_static,
)

from export.defaults import (  # torch-free: `export --help` reads them
    CALIBRATED_SCHEMES,
    CONV_MIN_CHANNELS,
    CONV_SCHEME_FC,
    CONV_SCHEME_FC_MIN_WEIGHTS,
    CONV_SCHEME_REDUCE_RANGE,
    DEFAULT_SCHEME,
    MAX_MAX_DEG,
    MAX_MEAN_DEG,
    SCHEMES,
)
from export.parity import MIN_PARITY_INPUTS, PARITY_SEED, onnxruntime_outputs, random_inputs
from models.train.checkpoint import new_temp_file_beside
from refiner_rt import quaternion as rq
from refiner_rt.metadata import INPUT_IMAGE, INPUT_QUATERNION, ModelContract, parse_metadata

__all__ = [
    "CALIBRATED_SCHEMES",
    "CALIBRATION_SIZE",
    "CONV_MIN_CHANNELS",
    "DEFAULT_SCHEME",
    "MAX_MAX_DEG",
    "MAX_MEAN_DEG",
    "QUANTIZED_OP_TYPES",
    "SCHEMES",
    "AgreementResult",
    "Calibration",
    "QuantizationError",
    "QuantizeReport",
    "calibrated_scheme_for",
    "dataset_calibration",
    "int8_agreement",
    "int8_path_for",
    "quantize_model",
    "large_fully_connected",
    "pose_dependent",
    "random_calibration",
    "wide_conv_chain",
]

logger = logging.getLogger(__name__)

QUANTIZED_OP_TYPES = ("MatMul", "Gemm")  # the fully connected layers; convs stay fp32 (see the module docstring)
# in the dynamic and static-qdq schemes
CALIBRATION_SIZE = 256  # crops used to calibrate static QDQ activation ranges
CALIBRATION_SEED = 1  # differs from PARITY_SEED: the agreement is measured on inputs the calibration never saw
_CALIBRATION_BATCH = 16


class QuantizationError(RuntimeError):
    """The INT8 model disagrees with fp32 beyond the bound; it was not written.

    Attributes:
        agreement: the enforced :class:`AgreementResult` that failed.
    """

    def __init__(self, message: str, agreement: "AgreementResult"):
        super().__init__(message)
        self.agreement = agreement


@dataclass(frozen=True)
class Calibration:
    """Inputs for static calibration, and optionally held-out inputs of the same kind for the agreement check.

    Attributes:
        images: ``(N, S, S, 3)`` uint8 NHWC crops in the model's channel order.
        q_in: ``(N, 4)`` float32 coarse rotations, ``wxyz``, in the model's rotation frame.
        source: where they came from (recorded in the metadata as ``int8_calibration``).
        check_images: ``(M, S, S, 3)`` uint8 held-out crops from the same source (not used to calibrate), or
            None. When given, the agreement bound is enforced on them instead of on the parity inputs: a
            model calibrated on real crops is meant for real crops.
        check_q_in: ``(M, 4)`` float32 ``wxyz`` for ``check_images``.
    """

    images: np.ndarray
    q_in: np.ndarray
    source: str
    check_images: np.ndarray | None = None
    check_q_in: np.ndarray | None = None

    def __post_init__(self):
        for name, images, q in (("", self.images, self.q_in), ("check_", self.check_images, self.check_q_in)):
            if name and images is None and q is None:
                continue
            if images is None or q is None:
                raise ValueError(f"{name}images and {name}q_in must be given together")
            if images.ndim != 4 or images.shape[3] != 3 or images.dtype != np.uint8:
                raise ValueError(
                    f"calibration {name}images must be (N, S, S, 3) uint8; got shape {images.shape}, dtype {images.dtype}"
                )
            if q.shape != (len(images), 4):
                raise ValueError(f"calibration {name}q_in must have shape ({len(images)}, 4) wxyz; got {q.shape}")
            if len(images) == 0:
                raise ValueError(f"calibration {name}images must hold at least one crop; got 0")


@dataclass(frozen=True)
class AgreementResult:
    """INT8 vs fp32 geodesic difference of ``q_out`` (degrees) on fixed inputs.

    Attributes:
        mean_deg: mean geodesic angle between the two models' ``q_out``.
        max_deg: largest geodesic angle.
        n_inputs: number of inputs compared.
        inputs: what the inputs were (``"parity inputs"``, ``"held-out calibration crops"``).
        enforced: whether the bounds below decide if the model is written.
        max_mean_deg: bound on ``mean_deg``.
        max_max_deg: bound on ``max_deg``.
    """

    mean_deg: float
    max_deg: float
    n_inputs: int
    inputs: str = "parity inputs"
    enforced: bool = True
    max_mean_deg: float = MAX_MEAN_DEG
    max_max_deg: float = MAX_MAX_DEG

    @property
    def passed(self) -> bool:
        """Both bounds hold (NaN never passes)."""
        return bool(self.mean_deg <= self.max_mean_deg and self.max_deg <= self.max_max_deg)

    def __str__(self) -> str:
        if self.enforced:
            verdict = "OK" if self.passed else "FAILED"
            bounds = f"(bounds: mean <= {self.max_mean_deg:g}, max <= {self.max_max_deg:g} deg)"
        else:
            verdict, bounds = "reported", "(not enforced)"
        return (
            f"INT8 agreement {verdict}: geodesic difference of q_out vs fp32 mean {self.mean_deg:.3f} deg, "
            f"max {self.max_deg:.3f} deg over {self.n_inputs} {self.inputs} {bounds}"
        )


@dataclass(frozen=True)
class QuantizeReport:
    """What a quantisation produced.

    Attributes:
        path: the INT8 ONNX file written.
        scheme: one of :data:`SCHEMES` (``"dynamic-int8"``, ``"static-qdq-int8"``, ``"static-qdq-int8-conv"``; also in
            the metadata ``quantization``).
        agreement: INT8 vs fp32 on the parity inputs (always measured).
        heldout_agreement: INT8 vs fp32 on held-out crops of the calibration dataset (dataset calibration only).
        size_bytes: INT8 file size.
        fp32_size_bytes: size of the fp32 model it came from.
        calibration: calibration source (static scheme) or None.
        seconds: wall time (quantise, checks, agreement, write).
    """

    path: Path
    scheme: str
    agreement: AgreementResult
    heldout_agreement: AgreementResult | None
    size_bytes: int
    fp32_size_bytes: int
    calibration: str | None
    seconds: float

    @property
    def enforced(self) -> AgreementResult:
        """The agreement whose bounds were enforced."""
        return self.heldout_agreement if self.heldout_agreement is not None else self.agreement

    def summary(self) -> str:
        """Human-readable lines: the agreement(s), then path, scheme, size and time."""
        calib = f", calibrated on {self.calibration}" if self.calibration else ""
        lines = [str(self.agreement)]
        if self.heldout_agreement is not None:
            lines.append(str(self.heldout_agreement))
        lines.append(
            f"wrote {self.path} ({self.scheme}{calib}, {self.size_bytes / 1e6:.1f} MB from "
            f"{self.fp32_size_bytes / 1e6:.1f} MB fp32) in {self.seconds:.1f} s"
        )
        return "\n".join(lines)


def int8_path_for(fp32_path) -> Path:
    """Where the INT8 sibling of an fp32 model goes: ``OUT.onnx`` -> ``OUT.int8.onnx``."""
    p = Path(fp32_path)
    return p.with_name(f"{p.stem}.int8{p.suffix}")


def random_calibration(input_size: int, n: int = CALIBRATION_SIZE, seed: int = CALIBRATION_SEED) -> Calibration:
    """Uniform random uint8 crops and uniform random rotations (when no dataset is at hand).

    Args:
        input_size: crop side ``S``.
        n: number of crops.
        seed: seed (differs from the parity inputs' by default).

    Returns:
        :class:`Calibration` (``source="random:<n>"``, no held-out crops: the parity inputs are of the same kind).
    """
    images, q_in = random_inputs(input_size, n, seed)
    return Calibration(images=images, q_in=q_in, source=f"random:{n}")


def dataset_calibration(
    data_dir,
    contract: ModelContract,
    n: int = CALIBRATION_SIZE,
    n_check: int = MIN_PARITY_INPUTS,
    seed: int = CALIBRATION_SEED,
    *,
    cache_root=None,
    spec=None,
) -> Calibration:
    """Crops of a dataset's training split, cut by the shared crop rule, with coarse poses as in training.

    The split is rebuilt from the data spec recorded in the model's metadata (``data``, as ``refiner-rt train``
    writes it; its extra training folders left out) when present, else from the defaults, and crops come through
    the crop cache (:func:`models.data.pipeline.cropset_for`, reused when training built it). ``n + n_check``
    distinct crops of ``train_base`` are drawn with ``seed`` (never the test split): ``n`` to calibrate,
    ``n_check`` held out for the agreement check (a quarter of the split each way when it is smaller). Their
    coarse rotations are ``q_gt * q_noise`` in the model's rotation frame with the model's ``train_noise``
    (``uniform:0:30`` when that is not a noise spec).

    Args:
        data_dir: BOP split folder or YCB-Video root.
        contract: the fp32 model's parsed metadata.
        n: number of calibration crops.
        n_check: number of held-out crops.
        seed: sampling seed.
        cache_root: where crop caches live (default ``<data_dir>/.crops``).
        spec: a :class:`models.data.pipeline.DataSpec` whose ``train_base`` part to draw from instead of the recorded
            one (e.g. a folder of calibration scenes rendered apart from the training set: every instance of
            it in ``train_base``); its ``data`` is replaced by ``data_dir``.

    Returns:
        :class:`Calibration` in the model's channel order, as the graph takes them (for a model with the canonical
        roll, each crop and rotation turned as the runtime turns them) (``source="dataset:<folder name>:train_base:<n>"``: the
        folder's name only, since the source goes into the model's metadata and a model must not carry the paths of
        the machine that made it).

    Raises:
        FileNotFoundError / ValueError: not a dataset, or a training split with fewer than 2 crops.
    """
    from models.data.noise import NoiseSpec, perturb
    from models.data.pipeline import DataSpec, cropset_for, load_splits

    if spec is not None:
        spec = DataSpec.from_dict({**spec.as_dict(), "data": str(data_dir)})
    else:
        recorded = contract.extra.get("data")
        recorded = json.loads(recorded) if isinstance(recorded, str) else None
        # The recorded split without its extra training folders: they only add training crops, a shipped model
        # names them by folder name alone, and the split's own training part of data_dir is enough to draw from.
        spec = (DataSpec.from_dict({**recorded, "data": str(data_dir), "extra_train": None}) if recorded
                else DataSpec(data=str(data_dir)))
    crops = cropset_for(
        load_splits(spec), "train_base", spec, contract.input_size, contract.crop_context,
        cache_root=cache_root, progress=False, crop_filter=contract.crop_filter,
    )
    if len(crops) < 2:
        raise ValueError(f"{data_dir}: the training split has {len(crops)} crop(s); calibration needs at least 2")
    if len(crops) < n + n_check:
        n_check = max(1, len(crops) // 4)
        n = len(crops) - n_check
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(crops))
    try:
        noise = NoiseSpec.parse(contract.train_noise)
    except ValueError:
        noise = NoiseSpec.parse("uniform:0:30")

    def draw(index):
        part = crops.subset(index)
        q_in, _ = perturb(part.q_gt_in(contract.rotation_frame), noise, rng)
        images = part.crops if contract.channel_order == "BGR" else np.ascontiguousarray(part.crops[..., ::-1])
        return images, q_in.astype(np.float32)

    images, q_in = draw(order[:n])
    check_images, check_q_in = draw(order[n : n + n_check])
    if contract.roll != "none":  # what the graph sees: the runtime turns each crop before it
        from refiner_rt.preprocess import ROLL_TURNS

        turn = ROLL_TURNS[contract.roll]
        (images, q_in), (check_images, check_q_in) = ((im, q.astype(np.float32)) for im, q in (
            turn(images, q_in), turn(check_images, check_q_in)))
    return Calibration(
        images=images, q_in=q_in, source=f"dataset:{Path(data_dir).resolve().name}:train_base:{n}",
        check_images=check_images, check_q_in=check_q_in,
    )


def int8_agreement(
    fp32_model, int8_model, images: np.ndarray, q_in: np.ndarray, *, inputs: str = "parity inputs", enforced: bool = True
) -> AgreementResult:
    """Geodesic difference between the ``q_out`` of two ONNX refiners on the same inputs.

    Args:
        fp32_model: reference model (path or bytes).
        int8_model: quantised model (path or bytes).
        images: ``(N, S, S, 3)`` uint8 NHWC crops in the models' channel order.
        q_in: ``(N, 4)`` float32 ``wxyz``.
        inputs: what the inputs are (for the report).
        enforced: whether the default bounds decide the export.

    Returns:
        :class:`AgreementResult` (NaN when the INT8 model outputs non-finite or zero quaternions).
    """
    ref = onnxruntime_outputs(fp32_model, images, q_in).astype(np.float64)
    got = onnxruntime_outputs(int8_model, images, q_in).astype(np.float64)
    n = len(images)
    if not (np.all(np.isfinite(got)) and np.all(np.linalg.norm(got, axis=1) > 0)):
        return AgreementResult(float("nan"), float("nan"), n, inputs, enforced)
    angle = rq.geodesic_angle(rq.normalize(got), rq.normalize(ref))
    return AgreementResult(float(angle.mean()), float(angle.max()), n, inputs, enforced)


class _CalibrationReader(CalibrationDataReader):
    """onnxruntime's calibration reader over a :class:`Calibration`, in batches."""

    def __init__(self, calibration: Calibration):
        c = calibration
        self._batches = iter(
            {INPUT_IMAGE: c.images[i : i + _CALIBRATION_BATCH], INPUT_QUATERNION: c.q_in[i : i + _CALIBRATION_BATCH]}
            for i in range(0, len(c.images), _CALIBRATION_BATCH)
        )

    def get_next(self):
        return next(self._batches, None)


def _quantize_dynamic(src: Path, dst: Path, calibration: Calibration | None, *, reduce_range: bool = True,
                      fc_min_weights: int = 0, float_pose: bool = False) -> None:
    """Dynamic INT8 on ``MatMul``/``Gemm``: all of them, or those with at least ``fc_min_weights`` weights
    (:func:`large_fully_connected`). ``reduce_range`` (default): 7-bit weights, since 8-bit ones saturate the 16-bit
    pair sums of AVX2's u8s8 kernels (see Portability above)."""
    nodes = None
    if fc_min_weights:
        # onnxruntime's dynamic quantiser first rewrites each Gemm as a MatMul named "<gemm>_MatMul" (plus an Add)
        # and then selects nodes by name: both names are given.
        proto = onnx.load(str(src))
        chosen = large_fully_connected(proto, fc_min_weights)
        if float_pose:
            chosen = [n for n in chosen if n not in pose_dependent(proto)]
        nodes = [m for n in chosen for m in (n, f"{n}_MatMul")]
    quantize_dynamic(src, dst, op_types_to_quantize=list(QUANTIZED_OP_TYPES), weight_type=QuantType.QInt8,
                     reduce_range=reduce_range, nodes_to_quantize=nodes)


def large_fully_connected(proto: onnx.ModelProto, min_weights: int = CONV_SCHEME_FC_MIN_WEIGHTS) -> list[str]:
    """Names of the ``MatMul``/``Gemm`` nodes whose weight (a 2-D initializer) has at least ``min_weights`` elements.

    In the refiners these hold nearly all the weight bytes (the image features' and the head's first layer); the
    small ones are the precision-critical ends: the pose input (the coarse rotation as a matrix, and the quadratic
    form that computes it from ``q_in``) and the output layer that writes ``q_out``.
    """
    weights = {t.name: list(t.dims) for t in proto.graph.initializer}
    return [n.name for n in proto.graph.node
            if n.op_type in QUANTIZED_OP_TYPES and len(n.input) > 1 and len(weights.get(n.input[1], [])) == 2
            and weights[n.input[1]][0] * weights[n.input[1]][1] >= min_weights]


def pose_dependent(proto: onnx.ModelProto) -> set[str]:
    """Names of the nodes whose output depends on the graph input ``q_in`` (the coarse rotation): the pose input
    stage and everything after the point where it joins the image features (in the refiners, the head).

    Quantising any of them makes the output a staircase in ``q_in``: a dynamically quantised layer rounds its input
    (pose features included) to a grid set by each call's own range, so a change of ``q_in`` by a thousandth of a
    degree moves the output by nothing or by a whole step (up to 0.08 degrees in the shipped refiners, whose head's
    first layer is quantised so; ``benchmarks/studies/int8_smooth``).
    """
    depends = {INPUT_QUATERNION}
    names = set()
    for node in proto.graph.node:  # ONNX graphs are topologically sorted
        if any(name in depends for name in node.input):
            names.add(node.name)
            depends.update(node.output)
    return names


def _quantize_static_qdq(src: Path, dst: Path, calibration: Calibration) -> None:
    quantize_static(
        src,
        dst,
        _CalibrationReader(calibration),
        quant_format=QuantFormat.QDQ,
        op_types_to_quantize=list(QUANTIZED_OP_TYPES),
        activation_type=QuantType.QUInt8,
        weight_type=QuantType.QInt8,
        calibrate_method=CalibrationMethod.MinMax,
    )


def wide_conv_chain(proto: onnx.ModelProto, min_channels: int = CONV_MIN_CHANNELS) -> list[str]:
    """Names of the nodes the conv scheme quantises in the image stage: every ``Conv`` whose input has at least
    ``min_channels`` channels, with the ``Relu`` and ``MaxPool`` that follow it (so that consecutive quantised
    convolutions pass uint8 from one to the next, and onnxruntime fuses each into a ``QLinearConv``).

    The input channel count is read from the weight initializer, shape ``(C_out, C_in / group, kH, kW)``.
    """
    weights = {t.name: list(t.dims) for t in proto.graph.initializer}
    consumers: dict[str, list] = {}
    for node in proto.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    chosen = []
    for node in proto.graph.node:
        if node.op_type != "Conv" or len(node.input) < 2 or node.input[1] not in weights:
            continue
        group = next((a.i for a in node.attribute if a.name == "group"), 1)
        if weights[node.input[1]][1] * group < min_channels:
            continue
        chosen.append(node.name)
        out = node.output[0]
        for op in ("Relu", "MaxPool"):  # conv -> relu -> maxpool, as the image stages write it
            following = consumers.get(out, [])
            if len(following) != 1 or following[0].op_type != op:
                break
            chosen.append(following[0].name)
            out = following[0].output[0]
    return chosen


def _quantize_static_qdq_conv(src: Path, dst: Path, calibration: Calibration, *,
                              min_channels: int = CONV_MIN_CHANNELS, fc: str = CONV_SCHEME_FC,
                              fc_min_weights: int = CONV_SCHEME_FC_MIN_WEIGHTS,
                              reduce_range: bool = CONV_SCHEME_REDUCE_RANGE, float_pose: bool = False) -> None:
    """Static QDQ (per-channel int8 weights, uint8 activations, min/max calibration) on the wide convolutions
    (:func:`wide_conv_chain`); the large fully connected layers (:func:`large_fully_connected`) ``fc="static"``
    in the same pass or ``fc="dynamic"`` (a dynamic pass over the result). ``reduce_range``: 7-bit weights
    (onnxruntime's remedy for the saturation of its u8s8 kernels on CPUs without VNNI). ``float_pose``: the fully
    connected layers that ``q_in`` reaches (:func:`pose_dependent`: the head, after the pose features join) stay
    fp32, so that only the image stage is quantised."""
    if fc not in ("static", "dynamic"):
        raise ValueError(f"fc must be 'static' or 'dynamic'; got {fc!r}")
    proto = onnx.load(str(src))
    nodes = wide_conv_chain(proto, min_channels)
    large_fc = large_fully_connected(proto, fc_min_weights)
    if float_pose:
        large_fc = [n for n in large_fc if n not in pose_dependent(proto)]
    if not nodes and not large_fc:
        raise ValueError(
            f"static-qdq-int8-conv quantises convolutions with at least {min_channels} input channels and fully "
            f"connected layers with at least {fc_min_weights} weights; this model has neither (a small network): "
            "use dynamic-int8"
        )
    op_types = ["Conv", "Relu", "MaxPool"]
    if fc == "static":
        nodes += large_fc
        op_types += list(QUANTIZED_OP_TYPES)
    if not nodes:  # no conv is wide enough: only the large fully connected layers, dynamically
        _quantize_dynamic(src, dst, None, reduce_range=reduce_range, fc_min_weights=fc_min_weights,
                          float_pose=float_pose)
        return
    if fc == "dynamic" and large_fc:
        # The dynamic pass first: after the static one, onnxruntime's dynamic quantiser leaves a graph with QDQ
        # nodes alone (its FC layers would stay fp32). Convolutions keep their names through it.
        mid = dst.with_name(dst.stem + ".dynamic.onnx")
        _quantize_dynamic(src, mid, None, reduce_range=reduce_range, fc_min_weights=fc_min_weights,
                          float_pose=float_pose)
        src = mid
    quantize_static(
        src,
        dst,
        _CalibrationReader(calibration),
        quant_format=QuantFormat.QDQ,
        op_types_to_quantize=op_types,
        nodes_to_quantize=nodes,
        per_channel=True,
        reduce_range=reduce_range,
        activation_type=QuantType.QUInt8,
        weight_type=QuantType.QInt8,
        calibrate_method=CalibrationMethod.MinMax,
    )


def calibrated_scheme_for(fp32_path) -> str:
    """The static scheme ``refiner-rt export --int8 --calib`` uses when none is named: ``"static-qdq-int8-conv"``
    for a model with at least two convolutions of :data:`CONV_MIN_CHANNELS` or more input channels
    (:func:`wide_conv_chain`), a deep image stage such as the shipped five-block refiner's (1.6x the dynamic
    scheme's speed and within 0.05 degree of fp32 on AVX-512 VNNI, ``benchmarks/studies/int8_convs``); else
    ``"static-qdq-int8"`` (the fully connected layers only), as before for the two-block defaults, whose one wide
    convolution was not measured under this scheme against it."""
    proto = onnx.load(str(fp32_path), load_external_data=False)
    nodes = {n.name: n.op_type for n in proto.graph.node}
    wide_convs = [name for name in wide_conv_chain(proto) if nodes[name] == "Conv"]
    return "static-qdq-int8-conv" if len(wide_convs) >= 2 else "static-qdq-int8"


_QUANTIZERS = {"dynamic-int8": _quantize_dynamic, "static-qdq-int8": _quantize_static_qdq,
               "static-qdq-int8-conv": _quantize_static_qdq_conv,
               "static-qdq-int8-conv-float-pose": lambda src, dst, calibration: _quantize_static_qdq_conv(
                   src, dst, calibration, float_pose=True)}


def _not_preprocess_advice(record: logging.LogRecord) -> bool:
    # onnxruntime's quantisers log "Please consider (to run) pre-processing before quantization" on the root
    # logger for every model. Its pre-processing (quant_pre_process) fails on these graphs and the shape inference
    # it stands for is done by the quantiser anyway, so the advice is not actionable here.
    return not record.getMessage().startswith("Please consider")


@contextlib.contextmanager
def _without_preprocess_advice():
    """Drop only that advice, only while quantising (a filter on the root logger, removed afterwards)."""
    root = logging.getLogger()
    root.addFilter(_not_preprocess_advice)
    try:
        yield
    finally:
        root.removeFilter(_not_preprocess_advice)


def _without_value_info(proto: onnx.ModelProto) -> onnx.ModelProto:
    # The torch exporter records shapes of every tensor, weights included. onnxruntime's dynamic quantiser
    # rewrites Gemm as MatMul with a transposed weight of the same name, and ONNX shape inference then fails on
    # the stale recorded shape ("Inferred shape and existing shape differ"). Shapes are re-inferred anyway.
    out = onnx.ModelProto()
    out.CopyFrom(proto)
    del out.graph.value_info[:]
    return out


def quantize_model(
    fp32_path,
    out_path=None,
    *,
    scheme: str = DEFAULT_SCHEME,
    calibration: Calibration | None = None,
    n_check: int = MIN_PARITY_INPUTS,
    enforce: bool = True,
) -> QuantizeReport:
    """Quantise an exported fp32 refiner to INT8, check it against fp32, and write it with the scheme in its metadata.

    Args:
        fp32_path: an fp32 refiner-rt ONNX model (metadata ``quantization`` = ``"none"``).
        out_path: destination; default :func:`int8_path_for` (``OUT.int8.onnx``). Its directory must exist;
            replaced only if the checks pass.
        scheme: ``"dynamic-int8"`` (default), ``"static-qdq-int8"`` or ``"static-qdq-int8-conv"`` (see the module
            docstring).
        calibration: crops for the static schemes (default: :func:`random_calibration`); not accepted with
            the dynamic scheme, which needs none.
        n_check: number of parity inputs of the agreement check (at least 64).
        enforce: refuse to write a model beyond the agreement bounds (default). ``False`` measures and reports the
            agreement without acting on it: for speed benchmarks of untrained networks, whose outputs are
            arbitrary rotations that quantisation noise can swing far; never for a model that will be used.

    Returns:
        :class:`QuantizeReport`.

    Raises:
        ValueError: unknown scheme, calibration given to the dynamic scheme, a model that is not an fp32
            refiner-rt model, or a missing output directory.
        QuantizationError: the INT8 model disagrees with fp32 beyond the bounds (``enforce``); nothing is written.
    """
    start = time.perf_counter()
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}; got {scheme!r}")
    if calibration is not None and scheme == "dynamic-int8":
        raise ValueError(
            f"calibration crops calibrate the static schemes {CALIBRATED_SCHEMES}; 'dynamic-int8' quantises "
            "activations at run time and takes none"
        )
    if n_check < MIN_PARITY_INPUTS:
        raise ValueError(f"n_check must be at least {MIN_PARITY_INPUTS}; got {n_check}")
    fp32_path = Path(fp32_path)
    out_path = Path(out_path) if out_path is not None else int8_path_for(fp32_path)
    if not out_path.parent.is_dir():
        raise ValueError(f"out_path's directory does not exist: {out_path.parent}")
    proto = onnx.load(str(fp32_path))
    props = {p.key: p.value for p in proto.metadata_props}
    contract = parse_metadata(props)
    if contract.quantization != "none":
        raise ValueError(
            f"{fp32_path} is already quantised (metadata quantization={contract.quantization!r}); expected an fp32 "
            "model (quantization='none')"
        )
    if scheme in CALIBRATED_SCHEMES and calibration is None:
        calibration = random_calibration(contract.input_size)
    if calibration is not None and calibration.images.shape[1:3] != (contract.input_size, contract.input_size):
        raise ValueError(
            f"calibration crops must be {contract.input_size}x{contract.input_size} (the model's input_size); "
            f"got {calibration.images.shape[1]}x{calibration.images.shape[2]}"
        )

    data = _quantized_proto(proto, scheme, calibration).SerializeToString()
    tmp = new_temp_file_beside(out_path)  # the user's umask (0644 typically), not mkstemp's 0600
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        _check_loads(tmp, scheme)
        agreement, heldout_agreement = _agreements(fp32_path, tmp, contract.input_size, calibration, n_check, enforce)
        enforced = heldout_agreement if heldout_agreement is not None else agreement
        if enforce and not enforced.passed:
            raise QuantizationError(f"refusing to write {out_path}: {enforced}", enforced)
        os.replace(tmp, out_path)
    finally:
        tmp.unlink(missing_ok=True)
    report = QuantizeReport(
        path=out_path,
        scheme=scheme,
        agreement=agreement,
        heldout_agreement=heldout_agreement,
        size_bytes=out_path.stat().st_size,
        fp32_size_bytes=fp32_path.stat().st_size,
        calibration=calibration.source if calibration is not None else None,
        seconds=time.perf_counter() - start,
    )
    logger.info("quantised %s to %s (%s, %d bytes)", fp32_path, out_path, scheme, report.size_bytes)
    return report


def _quantized_proto(proto: onnx.ModelProto, scheme: str, calibration: Calibration | None) -> onnx.ModelProto:
    """Run onnxruntime's quantiser for ``scheme``; the result carries the fp32 metadata plus the scheme, and passes
    the full ONNX check."""
    with tempfile.TemporaryDirectory(prefix="refiner-rt-int8-") as work:
        src, dst = Path(work) / "fp32.onnx", Path(work) / "int8.onnx"
        onnx.save(_without_value_info(proto), str(src))
        with _without_preprocess_advice():
            _QUANTIZERS[scheme](src, dst, calibration)
        quantized = onnx.load(str(dst))
    props = {p.key: p.value for p in proto.metadata_props}
    props["quantization"] = scheme
    if calibration is not None:
        props["int8_calibration"] = calibration.source
    parse_metadata(props)
    del quantized.metadata_props[:]
    onnx.helper.set_model_props(quantized, props)
    quantized.doc_string = f"{proto.doc_string} [INT8: {scheme}]".strip()
    onnx.checker.check_model(quantized, full_check=True)
    return quantized


def _agreements(
    fp32_path: Path, int8_path: Path, input_size: int, calibration: Calibration | None, n_check: int, enforce: bool = True
):
    """``(on the parity inputs, on held-out calibration crops or None)``; the held-out one is enforced when present
    (neither when ``enforce`` is False)."""
    heldout = calibration is not None and calibration.check_images is not None
    images, q_in = random_inputs(input_size, n_check, PARITY_SEED)
    parity = int8_agreement(fp32_path, int8_path, images, q_in, enforced=enforce and not heldout)
    logger.info("%s", parity)
    if not heldout:
        return parity, None
    held = int8_agreement(
        fp32_path, int8_path, calibration.check_images, calibration.check_q_in, inputs="held-out calibration crops",
        enforced=enforce,
    )
    logger.info("%s", held)
    return parity, held


def _check_loads(path: Path, scheme: str) -> None:
    """The INT8 model loads in the runtime (contract, inputs, outputs) and declares its scheme."""
    from refiner_rt import RefinerSession

    sess = RefinerSession(path, threads=1)
    if sess.contract.quantization != scheme:
        raise RuntimeError(f"quantised model declares quantization={sess.contract.quantization!r}; expected {scheme!r}")
