"""Export a refiner to a self-contained, parity-checked ONNX model carrying the refiner-rt metadata contract.

Graph (docs/design.md §4.1; names from :mod:`refiner_rt.metadata`):
    * input ``image``: ``(batch, S, S, 3)`` uint8, NHWC, in the model's channel order (BGR by default);
    * input ``q_in``: ``(batch, 4)`` float32, ``wxyz``, the coarse rotation object-to-camera;
    * output ``q_out``: ``(batch, 4)`` float32, ``wxyz``, unit norm; ``q_refined = q_in * q_out``.
Cast, scaling, mean/std and the NHWC -> NCHW transpose are inside the graph. The batch axis is dynamic.

Export is a test: ``onnx.checker.check_model(full_check=True)``, then onnxruntime vs PyTorch on at least 64
fixed-seed random inputs (:mod:`export.parity`). The model is written to a temporary file next to the target and
moved into place only if ``max |dq| <= tol`` (fp32 default 1e-4); otherwise :class:`ParityError` is raised and
nothing is written. The file is self-contained (weights inline, no external data file; limit 2 GB).

Decisions (for the runtime and for robot integrators):
    * Exporter: ``torch.onnx.export(..., dynamo=True)`` (the ``torch.export``-based exporter, default since
      PyTorch 2.9; the TorchScript path still exists in 2.13 but is deprecated). It emits opset 18 natively;
      lower opsets need a version conversion that fails for these graphs, so ``opset >= 18`` is required and
      the opset actually written is checked. Its optimiser folds eval-mode BatchNorm into the convolutions.
    * LRN (VGG-M): ``nn.LocalResponseNorm`` exports as whatever subgraph the exporter decomposes it into (with
      ``If`` nodes, which OpenCV's ``cv2.dnn`` rejects, on some exporter paths). :class:`models.nets.blocks.
      LocalResponseNorm` instead calls the custom op ``refiner_rt::local_response_norm`` while exporting, and
      this module chooses how it is written (``lrn=``):

      - ``"decomposed"`` (default): ``Mul``, ``Pad``, ``AveragePool`` over the channel window, ``Sqrt``, ``Div``
        (``d ** 0.75`` as ``sqrt(d) * sqrt(sqrt(d))``). Measured at 224x224, batch 1, 1 thread: VGG-M in
        onnxruntime about 1.8x faster than with the ONNX ``LRN`` op, whose CPU kernel takes ~30 ms for LRN1
        alone (vs ~3 ms decomposed); ``cv2.dnn`` loads it and agrees, about 15 % slower than with ``LRN``.
      - ``"LRN"``: the single ONNX ``LRN`` operator, which ``cv2.dnn`` runs fastest; choose it for models that
        will run in OpenCV only.

      onnxruntime is the project's runtime (``RefinerSession``, ``refiner-rt bench``), hence the default.
    * uint8 input in OpenCV: ``cv2.dnn`` of OpenCV 5 (the version this project tests against) reads the uint8
      ``image`` input and runs the in-graph ``Cast`` itself: pass the uint8 crop as is
      (``net.setInput(crops_uint8, "image")``). It checks the graph input type and refuses a float32 blob for
      ``image``, so there is nothing to convert and nothing to fix; one graph serves onnxruntime and OpenCV.
    * OpenCV 4.x (checked by hand with opencv-python-headless 4.14, not in CI): its importer rejects a graph input
      whose batch dimension is symbolic (a Concat shape check at load time fails). A copy whose declared batch
      dimension is fixed to 1 loads, takes uint8 or float32 crops, and agrees with onnxruntime for any batch size
      (OpenCV 4 reshapes at ``setInput``)::

          m = onnx.load("refiner.onnx")
          for i in m.graph.input:
              i.type.tensor_type.shape.dim[0].dim_value = 1
          onnx.save(m, "refiner_opencv4.onnx")   # for cv2.dnn 4.x only: onnxruntime would then insist on batch 1
"""

from __future__ import annotations

import logging
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import onnx
import torch
from torch.export import Dim

import refiner_rt
from export.defaults import DEFAULT_LRN_LOWERING, DEFAULT_OPSET, MIN_OPSET  # torch-free: `export --help` reads them
from export.parity import DEFAULT_TOL, MIN_PARITY_INPUTS, PARITY_SEED, check_parity, random_inputs
from models.nets.blocks import Refiner
from models.train.checkpoint import file_sha256, load_checkpoint, new_temp_file_beside
from refiner_rt.metadata import INPUT_IMAGE, INPUT_QUATERNION, OUTPUT_QUATERNION, REQUIRED_KEYS, build_metadata

__all__ = [
    "DEFAULT_LRN_LOWERING",
    "DEFAULT_OPSET",
    "LRN_LOWERINGS",
    "MIN_OPSET",
    "ExportReport",
    "ParityError",
    "build_model_metadata",
    "export_checkpoint",
    "export_loaded_checkpoint",
    "export_model",
    "to_onnx_proto",
]

logger = logging.getLogger(__name__)

_MAX_PROTO_BYTES = 2**31 - 1  # protobuf limit of a self-contained model


class ParityError(RuntimeError):
    """onnxruntime disagrees with PyTorch beyond the tolerance; the model was not written.

    Attributes:
        max_abs_dq: the measured ``max |dq|``.
        tol: the tolerance.
    """

    def __init__(self, message: str, max_abs_dq: float, tol: float):
        super().__init__(message)
        self.max_abs_dq = max_abs_dq
        self.tol = tol


@dataclass(frozen=True)
class ExportReport:
    """What an export produced.

    Attributes:
        path: the ONNX file written.
        arch: architecture name.
        max_abs_dq: parity result, ``max |q_onnxruntime - q_torch|`` over all inputs and components.
        n_parity: number of random inputs of the parity check.
        tol: parity tolerance the model was held to.
        opset: ONNX opset of the default domain.
        size_bytes: file size.
        seconds: wall time of the whole export (trace, checks, parity, write).
    """

    path: Path
    arch: str
    max_abs_dq: float
    n_parity: int
    tol: float
    opset: int
    size_bytes: int
    seconds: float

    def summary(self) -> str:
        """Two human-readable lines: the parity result, then path, size, opset and time."""
        return (
            f"parity OK: max |dq| = {self.max_abs_dq:.3g} over {self.n_parity} random inputs "
            f"(onnxruntime vs PyTorch, tol {self.tol:g})\n"
            f"wrote {self.path} ({self.arch}, {self.size_bytes / 1e6:.1f} MB, opset {self.opset}) "
            f"in {self.seconds:.1f} s"
        )


def _lrn_as_onnx_op(x, size: int, alpha: float, beta: float, k: float):
    """``refiner_rt::local_response_norm`` as the single ONNX ``LRN`` operator (``lrn="LRN"``)."""
    from onnxscript import opset18 as op

    return op.LRN(x, size=size, alpha=alpha, beta=beta, bias=k)


def _lrn_decomposed(x, size: int, alpha: float, beta: float, k: float):
    """``refiner_rt::local_response_norm`` as elementwise ops and a channel-window average (``lrn="decomposed"``).

    ``y = x / (k + alpha * mean_window(x^2)) ** beta``, the window of ``size`` channels padded with zeros as
    PyTorch does (``size // 2`` before, ``(size - 1) // 2`` after). The power ``0.75`` (VGG-M's) is computed as
    ``sqrt(d) * sqrt(sqrt(d))`` and ``0.5`` as ``sqrt(d)``: onnxruntime's ``Pow`` and ``LRN`` kernels evaluate a
    scalar ``pow`` per element and are several times slower. No ``If`` nodes: ``cv2.dnn`` loads it.
    """
    from onnxscript import opset18 as op

    before, after = size // 2, (size - 1) // 2
    squared = op.Unsqueeze(op.Mul(x, x), op.Constant(value_ints=[1]))  # (N, 1, C, H, W)
    padded = op.Pad(squared, op.Constant(value_ints=[0, 0, before, 0, 0, 0, 0, after, 0, 0]))
    mean = op.Squeeze(op.AveragePool(padded, kernel_shape=[size, 1, 1], strides=[1, 1, 1]), op.Constant(value_ints=[1]))
    d = op.Add(op.Mul(mean, op.Constant(value_float=alpha)), op.Constant(value_float=k))
    if beta == 0.75:
        root = op.Sqrt(d)
        denominator = op.Mul(root, op.Sqrt(root))
    elif beta == 0.5:
        denominator = op.Sqrt(d)
    else:
        denominator = op.Pow(d, op.Constant(value_float=beta))
    return op.Div(x, denominator)


# How refiner_rt::local_response_norm (VGG-M's LRN) is written into the graph; see the module docstring.
LRN_LOWERINGS = {"decomposed": _lrn_decomposed, "LRN": _lrn_as_onnx_op}


def _custom_translations(lrn: str) -> dict:
    # The op is registered by importing models.nets.blocks (imported above for Refiner).
    return {torch.ops.refiner_rt.local_response_norm.default: LRN_LOWERINGS[lrn]}


def _check_model(model) -> None:
    if not isinstance(model, Refiner):
        raise ValueError(f"model must be a refiner built by models.build_refiner; got {type(model).__name__}")


def to_onnx_proto(model: Refiner, opset: int = DEFAULT_OPSET, *, lrn: str = DEFAULT_LRN_LOWERING) -> onnx.ModelProto:
    """Trace ``model`` (in eval mode) into an ONNX graph with the contract's input/output names and a dynamic batch.

    No metadata, checks or parity here: :func:`export_model` adds them.

    Args:
        model: a registered refiner; its train/eval mode is restored afterwards.
        opset: ONNX opset, at least 18.
        lrn: how local response norms are written: ``"decomposed"`` (default, fast in onnxruntime) or ``"LRN"``
            (the single ONNX operator, fast in OpenCV); see the module docstring.

    Returns:
        The ``onnx.ModelProto`` (weights inline).

    Raises:
        ValueError: ``model`` is not a refiner, ``opset < 18`` or an unknown ``lrn``.
        RuntimeError: the exporter produced another opset or other input/output names than requested.
    """
    _check_model(model)
    if not isinstance(opset, int) or opset < MIN_OPSET:
        raise ValueError(f"opset must be an int >= {MIN_OPSET} (the exporter's native opset); got {opset!r}")
    if lrn not in LRN_LOWERINGS:
        raise ValueError(f"lrn must be one of {sorted(LRN_LOWERINGS)}; got {lrn!r}")
    images, q_in = random_inputs(model.input_size, 2)
    batch = Dim("batch")
    was_training = model.training
    model.eval()
    try:
        with warnings.catch_warnings():
            # Two warnings from torch's own internals, not actionable here: the shared batch Dim *is* named
            # "batch" in the graph, and LeafSpec is used inside torch.export.
            warnings.filterwarnings("ignore", message=r"# The axis name: batch will not be used", category=UserWarning)
            warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\)", category=FutureWarning)
            program = torch.onnx.export(
                model,
                (torch.from_numpy(images), torch.from_numpy(q_in)),
                dynamo=True,
                opset_version=opset,
                input_names=[INPUT_IMAGE, INPUT_QUATERNION],
                output_names=[OUTPUT_QUATERNION],
                dynamic_shapes=({0: batch}, {0: batch}),
                custom_translation_table=_custom_translations(lrn),
                optimize=True,
                verbose=False,
            )
    finally:
        model.train(was_training)
    proto = program.model_proto
    # The exporter's per-node trace (source file paths and line numbers of the machine that exported, FX names):
    # nothing the runtime reads, and a shipped model should not carry the build machine's folders.
    for node in [*proto.graph.node, *(n for f in proto.functions for n in f.node)]:
        del node.metadata_props[:]
    written = {o.domain: o.version for o in proto.opset_import}.get("", None)
    if written != opset:
        raise RuntimeError(f"the exporter wrote opset {written} instead of the requested {opset}")
    inputs = [i.name for i in proto.graph.input]
    outputs = [o.name for o in proto.graph.output]
    if inputs != [INPUT_IMAGE, INPUT_QUATERNION] or outputs != [OUTPUT_QUATERNION]:
        raise RuntimeError(
            f"exported graph has inputs {inputs} and outputs {outputs}; "
            f"expected {[INPUT_IMAGE, INPUT_QUATERNION]} and {[OUTPUT_QUATERNION]}"
        )
    return proto


def build_model_metadata(
    model: Refiner,
    *,
    info: dict | None = None,
    checkpoint_sha256: str = "none",
    metadata_extra: dict | None = None,
) -> dict[str, str]:
    """The ``metadata_props`` of an exported refiner (validated by :func:`refiner_rt.metadata.parse_metadata`).

    Args:
        model: the refiner: ``arch``, ``input_size``, ``channel_order`` and ``config["crop_context"]`` (default 1.2).
        info: checkpoint info: ``objects`` (list of object names, default ``[]``), ``train_noise`` (default
            ``"unknown"``), ``rotation_frame`` (``"camera"`` or ``"ray"``, default ``"camera"``); ``meshes`` and
            ``symmetries`` (recorded for rendered and symmetric objects) are copied as JSON when present.
        checkpoint_sha256: SHA-256 of the checkpoint file, ``"none"`` when exporting an in-memory model.
        metadata_extra: additional ``{key: value}`` pairs (non-strings stored as JSON); must not redefine a
            contract key.

    Returns:
        ``{key: str}``.

    Raises:
        ValueError: a value the contract does not accept, or ``metadata_extra`` redefining a contract key.
    """
    info = dict(info or {})
    objects = info.get("objects", [])
    if not isinstance(objects, (list, tuple)) or not all(isinstance(o, str) for o in objects):
        raise ValueError(f"checkpoint info 'objects' must be a JSON list of YCB id strings; got {objects!r}")
    train_noise = info.get("train_noise", "unknown")
    if not isinstance(train_noise, str):
        raise ValueError(f"checkpoint info 'train_noise' must be a string such as 'uniform:0:30'; got {train_noise!r}")
    extra = dict(metadata_extra or {})
    reserved = sorted(set(extra) & (set(REQUIRED_KEYS) | {"quantization", "roll", "crop_filter"}))
    if reserved:
        raise ValueError(f"metadata_extra must not redefine contract key(s) {reserved}; they are set by the exporter")
    # What a user's own object needs beside its name: the meshes it was rendered from (file, sha256, unit), and its
    # symmetry, so users know the refined rotation is one of the equivalent poses.
    for key in ("meshes", "symmetries"):
        if info.get(key):
            extra.setdefault(key, info[key])
    return build_metadata(
        arch=model.arch,
        input_size=model.input_size,
        channel_order=model.channel_order,
        crop_context=model.config.get("crop_context", 1.2),
        rotation_frame=info.get("rotation_frame", "camera"),
        objects=list(objects),
        train_noise=train_noise,
        checkpoint_sha256=checkpoint_sha256,
        version=refiner_rt.__version__,
        extra={"model_config": model.config, **extra},
        roll=model_roll(model),
        crop_filter=model.config["crop_filter"],
    )


def model_roll(model: Refiner) -> str:
    """The turn the runtime makes before ``model``'s graph: the fusion network's ``roll`` config (``"none"`` or
    ``"canonical"`` or ``"quarter"``; models.nets.fusion.ROLLS), ``"none"`` for every other network."""
    return model.config.get("roll", "none") if model.arch == "fusion" else "none"


def graph_network(model: Refiner) -> Refiner:
    """The network an exported file holds: ``model`` itself, or for a network with a roll (models.nets.fusion.ROLLS) the same
    weights without it. The turn is a warp of each crop that the runtime makes before the graph
    (refiner_rt.preprocess.ROLL_TURNS; metadata ``roll``), a few microseconds there against as much time as the
    network itself as an ONNX GridSample."""
    from models.nets.fusion import with_roll

    return with_roll(model, {"roll": "none"}) if model_roll(model) != "none" else model


def export_model(
    model: Refiner,
    out_path,
    *,
    opset: int = DEFAULT_OPSET,
    info: dict | None = None,
    metadata_extra: dict | None = None,
    checkpoint_sha256: str = "none",
    n_parity: int = MIN_PARITY_INPUTS,
    tol: float = DEFAULT_TOL,
    lrn: str = DEFAULT_LRN_LOWERING,
) -> ExportReport:
    """Export ``model`` to ``out_path`` as a checked, parity-tested, self-contained ONNX file.

    Args:
        model: a refiner from :func:`models.build_refiner` or :func:`models.load_checkpoint`; exported in eval
            mode (its mode is restored).
        out_path: destination ``.onnx`` file; its directory must exist. Replaced only if the checks pass.
        opset: ONNX opset, at least 18 (default 18).
        info: checkpoint info for the metadata (``objects``, ``train_noise``, ``rotation_frame``).
        metadata_extra: additional metadata keys (see :func:`build_model_metadata`).
        checkpoint_sha256: SHA-256 of the source checkpoint (``"none"`` for an in-memory model).
        n_parity: number of fixed-seed random inputs of the parity check (at least 64).
        tol: parity tolerance on ``max |dq|`` (fp32: 1e-4).
        lrn: lowering of local response norms (VGG-M): ``"decomposed"`` (default) or ``"LRN"``.

    Returns:
        :class:`ExportReport`.

    Raises:
        ValueError: invalid arguments or metadata.
        onnx.checker.ValidationError: the graph fails the full ONNX check.
        ParityError: onnxruntime and PyTorch differ by more than ``tol``; nothing is written.
    """
    start = time.perf_counter()
    _check_model(model)
    out_path = Path(out_path)
    if not out_path.parent.is_dir():
        raise ValueError(f"out_path's directory does not exist: {out_path.parent}")
    if n_parity < MIN_PARITY_INPUTS:
        raise ValueError(f"n_parity must be at least {MIN_PARITY_INPUTS}; got {n_parity}")
    if not tol > 0:
        raise ValueError(f"tol must be > 0; got {tol}")
    if lrn not in LRN_LOWERINGS:
        raise ValueError(f"lrn must be one of {sorted(LRN_LOWERINGS)}; got {lrn!r}")
    props = build_model_metadata(model, info=info, checkpoint_sha256=checkpoint_sha256, metadata_extra=metadata_extra)
    network = graph_network(model)  # without its roll, which the runtime makes (metadata ``roll``)

    proto = to_onnx_proto(network, opset, lrn=lrn)
    onnx.helper.set_model_props(proto, props)
    proto.doc_string = (
        f"refiner-rt {model.arch} refiner: {INPUT_IMAGE} (batch, {model.input_size}, {model.input_size}, 3) uint8 "
        f"NHWC {model.channel_order}, {INPUT_QUATERNION} (batch, 4) float32 wxyz -> {OUTPUT_QUATERNION} (batch, 4) "
        f"float32 wxyz unit; q_refined = q_in * q_out"
        + ("; the runtime first turns each crop and its q_in about the viewing ray (metadata roll = "
           f"{props['roll']!r})" if "roll" in props else "")
    )
    if proto.ByteSize() > _MAX_PROTO_BYTES:
        raise ValueError(f"model is {proto.ByteSize() / 1e9:.2f} GB; a self-contained ONNX file is limited to 2 GB")
    onnx.checker.check_model(proto, full_check=True)
    data = proto.SerializeToString()

    tmp = new_temp_file_beside(out_path)  # the user's umask (0644 typically), not mkstemp's 0600
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        result = check_parity(network, tmp, n=n_parity, tol=tol, seed=PARITY_SEED)
        if not result.passed:
            raise ParityError(
                f"refusing to write {out_path}: onnxruntime differs from PyTorch by max |dq| = {result.max_abs_dq:.3g} "
                f"over {result.n_inputs} inputs (tol {tol:g})",
                result.max_abs_dq,
                tol,
            )
        os.replace(tmp, out_path)
    finally:
        tmp.unlink(missing_ok=True)
    report = ExportReport(
        path=out_path,
        arch=model.arch,
        max_abs_dq=result.max_abs_dq,
        n_parity=result.n_inputs,
        tol=float(tol),
        opset=opset,
        size_bytes=out_path.stat().st_size,
        seconds=time.perf_counter() - start,
    )
    logger.info("exported %s to %s (%d bytes, max |dq| %.3g)", model.arch, out_path, report.size_bytes, report.max_abs_dq)
    return report


def checkpoint_metadata_extra(info: dict) -> dict | None:
    """Extra metadata carried over from a checkpoint's info: the training data spec (``data``: dataset, split
    mode, seed and sizes), so ``refiner-rt eval`` can rebuild the held-out test split of an exported model."""
    return {"data": info["data"]} if isinstance(info.get("data"), dict) else None


def export_checkpoint(
    ckpt_path,
    out_path=None,
    *,
    opset: int = DEFAULT_OPSET,
    n_parity: int = MIN_PARITY_INPUTS,
    tol: float = DEFAULT_TOL,
    lrn: str = DEFAULT_LRN_LOWERING,
) -> ExportReport:
    """Load a checkpoint and export it (see :func:`export_model`), recording its SHA-256 and info in the metadata.

    Args:
        ckpt_path: checkpoint written by :func:`models.save_checkpoint`.
        out_path: destination; default: the checkpoint path with the suffix ``.onnx``.
        opset: ONNX opset, at least 18.
        n_parity: number of parity inputs (at least 64).
        tol: parity tolerance on ``max |dq|``.
        lrn: lowering of local response norms (VGG-M): ``"decomposed"`` (default) or ``"LRN"``.

    Returns:
        :class:`ExportReport`.

    Raises:
        FileNotFoundError: no checkpoint at ``ckpt_path``.
        ValueError: not a valid checkpoint (message names file and field) or invalid arguments.
        ParityError: parity failed; nothing is written.
    """
    ckpt_path = Path(ckpt_path)
    model, info = load_checkpoint(ckpt_path)
    out = Path(out_path) if out_path is not None else ckpt_path.with_suffix(".onnx")
    return export_loaded_checkpoint(model, info, ckpt_path, out, opset=opset, n_parity=n_parity, tol=tol, lrn=lrn)


def export_loaded_checkpoint(
    model: Refiner,
    info: dict,
    ckpt_path,
    out_path,
    *,
    opset: int = DEFAULT_OPSET,
    n_parity: int = MIN_PARITY_INPUTS,
    tol: float = DEFAULT_TOL,
    lrn: str = DEFAULT_LRN_LOWERING,
) -> ExportReport:
    """Export a checkpoint already loaded with :func:`models.load_checkpoint` (its info and SHA-256 go into the
    metadata); the one place that maps a checkpoint to :func:`export_model`'s arguments."""
    return export_model(
        model,
        Path(out_path),
        opset=opset,
        info=info,
        metadata_extra=checkpoint_metadata_extra(info),
        checkpoint_sha256=file_sha256(ckpt_path),
        n_parity=n_parity,
        tol=tol,
        lrn=lrn,
    )
