"""Random-weight refiners exported to ONNX (and INT8) for ``refiner-rt bench`` when no ``--model`` is given.

The runtime's benchmark (:mod:`refiner_rt.bench`) never imports training code; this module, on the training side,
builds the networks and hands the files to it (``refiner-rt bench`` imports :func:`build_default_models` from here
when it needs it: a source checkout's training package).
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import click

from refiner_rt.bench import BenchModel
from refiner_rt.errors import TRAINING_INSTALL

__all__ = ["build_default_models"]


def _disk_needed(model, int8: bool) -> int:
    """Bytes of disk that exporting ``model`` (and quantising it) writes at most, with a margin.

    The fp32 file holds every weight in 4 bytes; quantisation writes a pre-processed fp32 copy and the INT8 file.
    """
    weights = 4 * sum(p.numel() for p in model.parameters())
    return int(weights * (3 if int8 else 1) * 1.2) + (16 << 20)


def _space_message(workdir: Path, need: int, label: str) -> str:
    free = shutil.disk_usage(workdir).free
    return (f"not enough free disk space in {workdir} for {label}'s ONNX files: they need about {need / 1e6:.0f} MB, "
            f"{free / 1e6:.0f} MB is free; free some space or point TMPDIR at a folder with more")


def _check_free_space(workdir: Path, need: int, label: str) -> None:
    """Raise a ClickException naming the folder and the sizes when ``need`` bytes do not fit in ``workdir``."""
    if shutil.disk_usage(workdir).free < need:
        raise click.ClickException(_space_message(workdir, need, label))


class _disk_full_is_clear:
    """Context manager: an error while writing model files becomes a clear disk-space error when the disk is full.

    A file cut short by a full disk otherwise surfaces later as an unrelated parse error
    (onnx's ``DecodeError: Wire format was corrupt``) from the step that reads it back.
    """

    def __init__(self, workdir: Path, need: int, label: str):
        self.workdir, self.need, self.label = workdir, need, label

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc is None or isinstance(exc, click.ClickException):
            return False
        if shutil.disk_usage(self.workdir).free < self.need:
            message = _space_message(self.workdir, self.need, self.label)
            raise click.ClickException(f"{message} ({exc_type.__name__}: {exc})") from exc
        return False


def build_default_models(specs, workdir: Path, int8: bool = True, echo=None) -> list[BenchModel]:
    """Random-weight networks exported to ONNX in ``workdir`` (and their INT8 versions).

    Args:
        specs: ``(label, arch, config overrides)`` triples.
        workdir: where the ONNX files go.
        int8: also quantise each with :data:`export.quantize.DEFAULT_SCHEME`.
        echo: optional callable for progress lines.

    Returns:
        The fp32 models (with their PyTorch networks), then the INT8 ones.
    """
    try:
        import torch

        import models
        from export import export_model
        from export.onnx_export import model_roll
        from export.quantize import DEFAULT_SCHEME, quantize_model
    except ModuleNotFoundError as exc:
        raise click.ClickException(
            f"building the default benchmark models needs {exc.name!r} ({TRAINING_INSTALL}); "
            "or pass exported models with --model"
        ) from exc
    fp32, quantized = [], []
    for i, (label, arch, config) in enumerate(specs):
        torch.manual_seed(0)
        try:
            model = models.build_refiner(arch, **config).eval()
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="'--archs' / '--variant'") from exc
        path = workdir / f"model{i}.onnx"
        need = _disk_needed(model, int8)
        _check_free_space(workdir, need, label)
        t0 = time.perf_counter()
        with _disk_full_is_clear(workdir, need, label):
            # a network with the canonical roll turns crops about the viewing ray: it exists in the ray frame only
            info = {"rotation_frame": "ray"} if model_roll(model) != "none" else None
            export_model(model, path, info=info, checkpoint_sha256="random-weights")
        line = f"  {label}: exported in {time.perf_counter() - t0:.1f} s"
        fp32.append(BenchModel(label, path, model, config))
        if int8:
            # Random weights: the agreement says nothing about a trained model's accuracy, so it is shown, not enforced.
            with _disk_full_is_clear(workdir, need, label):
                report = quantize_model(path, workdir / f"model{i}.int8.onnx", scheme=DEFAULT_SCHEME, enforce=False)
            a = report.agreement
            line += (f", {DEFAULT_SCHEME} in {report.seconds:.1f} s (vs fp32 with random weights: mean {a.mean_deg:.3f}, "
                     f"max {a.max_deg:.3f} deg)")
            quantized.append(BenchModel(label, report.path, None, config))
        if echo:
            echo(line)
    return fp32 + quantized


def build_random_model(workdir: Path, arch: str, int8: bool) -> Path:
    """A random-weight model of ``arch`` exported to ``workdir`` (INT8 with export.quantize's default scheme)."""
    import torch

    import models
    from export import export_model

    torch.manual_seed(0)
    path = workdir / f"{arch}.onnx"
    export_model(models.build_refiner(arch).eval(), path, checkpoint_sha256="random-weights")
    if int8:
        from export.quantize import quantize_model

        path = quantize_model(path).path
    return path
