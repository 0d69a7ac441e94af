"""``refiner-rt export CKPT [-o OUT.onnx] [--opset N] [--lrn decomposed|LRN] [--int8 [--int8-scheme S] [--calib DATA]]``.

Checkpoint -> parity-checked fp32 ONNX model, and with ``--int8`` its INT8 sibling ``OUT.int8.onnx``
(:mod:`export.quantize`: scheme, agreement bound, why dynamic is the default).

Registered lazily by :mod:`refiner_rt.cli` (``export.cli:export_cmd``). The options come from the torch-free
:mod:`export.defaults` and the exporter is imported when the command runs, so ``export --help`` answers without
importing torch.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import click

from export.defaults import (
    DEFAULT_LRN_LOWERING,
    DEFAULT_OPSET,
    DEFAULT_SCHEME,
    LRN_LOWERING_NAMES,
    MAX_MAX_DEG,
    MAX_MEAN_DEG,
    MIN_OPSET,
    SCHEMES,
)
from models.train.paths import per_object_path, per_object_siblings
from refiner_rt.cli import prepare_output

__all__ = ["export_cmd"]

# torch.onnx warns at import about optional torchvision ops it cannot register; irrelevant to refiners.
_NOISY_LOGGERS = ("torch.onnx._internal.exporter._registration",)


@click.command("export")
@click.argument("checkpoint", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="ONNX file to write  [default: CHECKPOINT with the suffix .onnx]",
)
@click.option(
    "--opset",
    type=click.IntRange(min=MIN_OPSET),
    default=DEFAULT_OPSET,
    show_default=True,
    help=f"ONNX opset of the exported graph (>= {MIN_OPSET}).",
)
@click.option(
    "--lrn",
    type=click.Choice(sorted(LRN_LOWERING_NAMES)),
    default=DEFAULT_LRN_LOWERING,
    show_default=True,
    help="How VGG-M's local response norms are written: 'decomposed' is fastest in onnxruntime, "
    "'LRN' (one ONNX operator) in OpenCV cv2.dnn. No effect on the shallow model.",
)
@click.option(
    "--per-object/--no-per-object",
    default=True,
    show_default=True,
    help="Also export the per-object fine-tuned siblings CKPT_STEM.<ycb id>.pt (as `refiner-rt train` writes them) "
    "to OUT_STEM.<ycb id>.onnx.",
)
@click.option(
    "--int8",
    is_flag=True,
    help="Also write an INT8 model OUT_STEM.int8.onnx (per-object siblings: OUT_STEM.int8.<ycb id>.onnx), quantised "
    "from the parity-checked fp32 model; the scheme is recorded in its metadata ('quantization').",
)
@click.option(
    "--int8-scheme",
    type=click.Choice(SCHEMES),
    default=None,
    help=f"INT8 scheme: dynamic-int8 (MatMul/Gemm, activations quantised per call; no calibration), "
    f"static-qdq-int8 (MatMul/Gemm with calibrated activation ranges), static-qdq-int8-conv (also the convolutions "
    f"with 16+ input channels, per-channel 7-bit weights: the fast one for deep image stages such as the shipped "
    f"five-block refiner; give --calib) or static-qdq-int8-conv-float-pose (the same with the layers that q_in "
    f"reaches left fp32: outputs that move smoothly with q_in).  [default: {DEFAULT_SCHEME}; with --calib static-qdq-int8-conv for a "
    f"model with two or more such convolutions, else static-qdq-int8]",
)
@click.option(
    "--calib",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    default=None,
    help="Dataset (BOP split folder or YCB-Video root) whose training-split crops calibrate the static schemes and, "
    "held out, check them; implies a static scheme (static-qdq-int8-conv where the model has two or more "
    "convolutions of 16+ input channels, else static-qdq-int8) unless --int8-scheme names one. Without it the static schemes calibrate "
    "on random crops.",
)
def export_cmd(
    checkpoint: Path,
    output: Path | None,
    opset: int,
    lrn: str,
    per_object: bool,
    int8: bool,
    int8_scheme: str | None,
    calib: Path | None,
) -> None:
    """Export CHECKPOINT (a refiner-rt .pt file) to a self-contained ONNX model.

    The graph takes image (batch, S, S, 3) uint8 NHWC in the model's channel order (BGR by default) and
    q_in (batch, 4) float32 wxyz, and returns q_out (batch, 4) float32 wxyz (q_refined = q_in * q_out);
    the metadata contract (arch, input size, channel order, crop context, objects...) is embedded.

    Export is a test: the ONNX checker, then onnxruntime against PyTorch on
    64 fixed-seed random inputs; the model is written only if max |dq| <= 1e-4.

    With --int8 the INT8 model's q_out is compared with fp32 on the same inputs
    (geodesic difference, degrees); it is written only if the mean is <= 2 and
    the max <= 15 degrees (on held-out dataset crops when calibrated with --calib).
    """
    from export.quantize import int8_path_for  # the exporter's modules (torch, onnx) load only when it runs

    for name in _NOISY_LOGGERS:
        logging.getLogger(name).setLevel(logging.ERROR)
    if (int8_scheme or calib) and not int8:
        raise click.BadParameter("--int8-scheme and --calib configure the INT8 model: add --int8", param_hint="'--int8'")
    if calib is not None and int8_scheme == "dynamic-int8":
        raise click.BadParameter(
            "dynamic-int8 quantises activations per call and takes no calibration data; "
            "drop --int8-scheme (--calib then picks a static scheme) or drop --calib",
            param_hint="'--calib'",
        )
    # With --calib and no scheme named, each model gets the fastest static scheme it has layers for
    # (export.quantize.calibrated_scheme_for); without --calib, the dynamic scheme, which needs no data.
    scheme = int8_scheme or (None if calib is not None else DEFAULT_SCHEME)
    output = output if output is not None else checkpoint.with_suffix(".onnx")
    output = prepare_output(output, "'-o' / '--output'")  # the CLI's one output rule: a missing folder is made
    if not os.access(output.parent, os.W_OK | os.X_OK):
        raise click.BadParameter(f"directory {output.parent} is not writable", param_hint="'-o' / '--output'")
    # (checkpoint, fp32 output, INT8 output): per-object siblings are named so that `refiner-rt eval` finds them
    # next to either base model (OUT.<id>.onnx beside OUT.onnx, OUT.int8.<id>.onnx beside OUT.int8.onnx).
    int8_output = int8_path_for(output)
    jobs = [(checkpoint, output, int8_output)]
    if per_object:
        for obj, sibling in per_object_siblings(checkpoint).items():
            jobs.append((sibling, per_object_path(output, obj), per_object_path(int8_output, obj)))
    for ckpt, out, out_int8 in jobs:
        try:
            _export_one(ckpt, out, opset, lrn)
            if int8:
                _quantize_one(out, out_int8, scheme, calib)
        except OSError as exc:  # e.g. the folder became read-only or the disk is full
            raise click.ClickException(f"cannot write {exc.filename or out}: {exc.strerror or exc}") from None


def _quantize_one(fp32: Path, out: Path, scheme: str | None, calib: Path | None) -> None:
    """Write the INT8 model ``out`` from the fp32 model ``fp32`` (see :func:`export.quantize.quantize_model`)."""
    from export.quantize import QuantizationError, calibrated_scheme_for, dataset_calibration, quantize_model

    scheme = scheme or calibrated_scheme_for(fp32)
    calibration = None
    if calib is not None:
        from refiner_rt.session import RefinerSession

        try:
            calibration = dataset_calibration(calib, RefinerSession(fp32).contract)
        except (FileNotFoundError, ValueError) as exc:
            raise click.BadParameter(str(exc), param_hint="'--calib'") from exc
    click.echo(f"quantising {fp32} ({scheme})")
    try:
        report = quantize_model(fp32, out, scheme=scheme, calibration=calibration)
    except QuantizationError as exc:
        raise click.ClickException(f"{exc} (bounds {MAX_MEAN_DEG:g} / {MAX_MAX_DEG:g} deg)") from exc
    click.echo(report.summary())


def _export_one(checkpoint: Path, output: Path, opset: int, lrn: str) -> None:
    from export.onnx_export import ParityError, export_loaded_checkpoint
    from models.train.checkpoint import load_checkpoint

    try:
        model, info = load_checkpoint(checkpoint)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'CHECKPOINT'") from exc
    click.echo(f"exporting {model.arch} ({model.input_size}x{model.input_size} {model.channel_order}) from {checkpoint}")
    try:
        report = export_loaded_checkpoint(model, info, checkpoint, output, opset=opset, lrn=lrn)
    except ParityError as exc:
        raise click.ClickException(str(exc)) from exc
    except ValueError as exc:  # e.g. checkpoint info the metadata contract does not accept
        raise click.ClickException(f"cannot export {checkpoint}: {exc}") from exc
    click.echo(report.summary())
