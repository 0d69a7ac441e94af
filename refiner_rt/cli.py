"""The ``refiner-rt`` command line: a thin click group whose heavy subcommands import lazily.

The runtime subcommands (``info``, ``models``, ``demo``, ``bench`` of ONNX files) need only numpy, OpenCV and
onnxruntime; ``export``, ``train``, ``render`` and ``eval`` live in the training package and are imported only when
invoked, so ``refiner-rt --help`` and the runtime path never import torch.
"""

from __future__ import annotations

import importlib

import click

from refiner_rt import __version__
from refiner_rt.errors import TRAINING_INSTALL, ModelError

# name -> ("module:attribute", one-line help shown by `refiner-rt --help` without importing the module)
LAZY_COMMANDS = {
    "export": ("export.cli:export_cmd", "Export a checkpoint to ONNX (parity-checked against PyTorch)."),
    "info": ("refiner_rt.info:info_cmd", "Print a model's metadata contract, inputs/outputs and size."),
    "models": ("refiner_rt.models_cli:models_cmd", "List the pretrained refiners that ship in the package."),
    "demo": ("refiner_rt.demo_cli:demo_cmd", "Refine sample frames (or your image) with the shipped models; draw it."),
    "estimate": ("refiner_rt.estimate_cli:estimate_cmd", "6D poses (rotation and translation) from images and 2D boxes alone."),
    "track": ("refiner_rt.track_cli:track_cmd", "Track object rotations through a folder of frames with boxes."),
    "bench": ("refiner_rt.bench:bench_cmd", "CPU speed of the full refine() path: shallow, fusion and VGG-M, fp32 and INT8."),
    "render": ("models.data.render:render_cmd", "Render BOP-format training scenes of YCB objects on the CPU."),
    "train": ("models.train_cli:train_cmd", "Train a refiner (paper recipe: base, then per-object fine-tuning)."),
    "eval": ("models.eval_cli:eval_cmd", "Evaluate a checkpoint or ONNX model on a dataset's test split."),
}


# The training package's top-level modules: present in a source checkout (pip install -e), never in the wheel.
TRAINING_PACKAGES = ("models", "export", "benchmarks")


def missing_message(command: str, module: str | None) -> str:
    """One line for a command that stopped at a missing module: the training package itself (a runtime-only
    install: the wheel carries ``refiner_rt`` alone) or one of its dependencies (torch, onnx, pybullet...)."""
    top = (module or "").split(".")[0]
    if top in TRAINING_PACKAGES:
        return f"'refiner-rt {command}' is part of the training package, which is not installed: {TRAINING_INSTALL}"
    return (f"'refiner-rt {command}' needs {module or 'a module'!r}, which is not installed; install the training "
            f"extra in the source checkout: pip install torch==2.13.0 && pip install -e '.[train]'")


class LazyGroup(click.Group):
    """A click group that imports a subcommand's module only when that subcommand runs."""

    def __init__(self, *args, lazy_commands: dict | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.lazy_commands = dict(lazy_commands or {})

    def list_commands(self, ctx):
        return sorted(set(super().list_commands(ctx)) | set(self.lazy_commands))

    def get_command(self, ctx, cmd_name):
        if cmd_name in self.lazy_commands:
            target, _ = self.lazy_commands[cmd_name]
            module_name, attr = target.split(":")
            try:
                module = importlib.import_module(module_name)
            except ModuleNotFoundError as exc:
                raise click.ClickException(missing_message(cmd_name, exc.name)) from exc
            return getattr(module, attr)
        return super().get_command(ctx, cmd_name)

    def invoke(self, ctx):
        # Safety nets, so that no subcommand prints a traceback for these: a model that cannot be used; and a
        # training command run in a runtime-only install, which stops at its first import of a training dependency
        # (torch, onnx, pybullet, tqdm...): name the module and the extra to install.
        try:
            return super().invoke(ctx)
        except ModelError as exc:
            raise click.ClickException(str(exc)) from None
        except ModuleNotFoundError as exc:
            name = ctx.invoked_subcommand or "this command"  # set by the group's invoke once the command is found
            raise click.ClickException(missing_message(name, exc.name)) from None

    def format_commands(self, ctx, formatter):
        rows = [(name, self.lazy_commands[name][1]) for name in sorted(self.lazy_commands)]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


@click.group(cls=LazyGroup, lazy_commands=LAZY_COMMANDS)
@click.version_option(__version__, prog_name="refiner-rt")
def main():
    """refiner-rt: fast 3D pose refinement from RGB crops.

    Conventions: quaternions wxyz (scalar first), rotations object-to-camera,
    images HxWx3 uint8 BGR, boxes (x1, y1, x2, y2) in pixels, angles in degrees.
    """


if __name__ == "__main__":
    main()
