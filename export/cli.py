"""``refiner-rt export CKPT [-o OUT.onnx] [--opset N] [--lrn decomposed|LRN]``: checkpoint -> parity-checked ONNX model.

Registered lazily by :mod:`refiner_rt.cli` (``export.cli:export_cmd``), so torch is imported only when it runs.
"""

from __future__ import annotations

import logging
from pathlib import Path

import click

from export.onnx_export import (
    DEFAULT_LRN_LOWERING,
    DEFAULT_OPSET,
    LRN_LOWERINGS,
    MIN_OPSET,
    ParityError,
    checkpoint_metadata_extra,
    export_model,
)
from export.parity import DEFAULT_TOL, MIN_PARITY_INPUTS
from models.checkpoint import file_sha256, load_checkpoint

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
    type=click.Choice(sorted(LRN_LOWERINGS)),
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
def export_cmd(checkpoint: Path, output: Path | None, opset: int, lrn: str, per_object: bool) -> None:
    """Export CHECKPOINT (a refiner-rt .pt file) to a self-contained ONNX model.

    The graph takes image (batch, S, S, 3) uint8 NHWC in the model's channel order (BGR by default) and
    q_in (batch, 4) float32 wxyz, and returns q_out (batch, 4) float32 wxyz (q_refined = q_in * q_out);
    the metadata contract (arch, input size, channel order, crop context, objects...) is embedded.

    Export is a test: the ONNX checker, then onnxruntime against PyTorch on
    64 fixed-seed random inputs; the model is written only if max |dq| <= 1e-4.
    """
    for name in _NOISY_LOGGERS:
        logging.getLogger(name).setLevel(logging.ERROR)
    output = output if output is not None else checkpoint.with_suffix(".onnx")
    if not output.parent.is_dir():
        raise click.BadParameter(f"directory {output.parent} does not exist", param_hint="'-o' / '--output'")
    _export_one(checkpoint, output, opset, lrn)
    if per_object:
        from models.data.objects import YCBV_CLASSES

        for obj in YCBV_CLASSES:
            sibling = checkpoint.with_name(f"{checkpoint.stem}.{obj}{checkpoint.suffix}")
            if sibling.is_file():
                _export_one(sibling, output.with_name(f"{output.stem}.{obj}{output.suffix}"), opset, lrn)


def _export_one(checkpoint: Path, output: Path, opset: int, lrn: str) -> None:
    try:
        model, info = load_checkpoint(checkpoint)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'CHECKPOINT'") from exc
    click.echo(f"exporting {model.arch} ({model.input_size}x{model.input_size} {model.channel_order}) from {checkpoint}")
    try:
        report = export_model(
            model,
            output,
            opset=opset,
            info=info,
            metadata_extra=checkpoint_metadata_extra(info),
            checkpoint_sha256=file_sha256(checkpoint),
            n_parity=MIN_PARITY_INPUTS,
            tol=DEFAULT_TOL,
            lrn=lrn,
        )
    except ParityError as exc:
        raise click.ClickException(str(exc)) from exc
    except ValueError as exc:  # e.g. checkpoint info the metadata contract does not accept
        raise click.ClickException(f"cannot export {checkpoint}: {exc}") from exc
    click.echo(report.summary())
