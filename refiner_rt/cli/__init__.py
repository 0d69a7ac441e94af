"""The ``refiner-rt`` command line: a thin click group whose subcommands import lazily, one module per command.

The runtime's subcommands live in this package (:data:`RUNTIME_COMMANDS`: ``info``, ``models``, ``demo``,
``estimate``, ``track``, ``bench``) and need only numpy, OpenCV and onnxruntime. Other packages plug commands in through the entry
point group :data:`ENTRY_POINT_GROUP` (``pyproject.toml`` declares the training package's ``export``, ``train``,
``render`` and ``eval`` there): the runtime never names a training module. Each entry point names a
:class:`LazyCommand` (its target and one-line help) or a click command; nothing is imported until a command runs
except the module holding its :class:`LazyCommand`, so ``refiner-rt --help`` and the runtime path never import
torch. In a runtime-only install (the wheel) a plugged-in command whose package is absent says what to install.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from importlib.metadata import entry_points

import click

from refiner_rt import __version__
from refiner_rt.errors import TRAINING_INSTALL, ModelError

__all__ = ["main", "LazyGroup", "LazyCommand", "RUNTIME_COMMANDS", "ENTRY_POINT_GROUP", "plugged_commands",
           "check_picture_path", "write_picture", "PICTURE_SUFFIXES", "prepare_output",
           "missing_message"]

# Where other packages declare their subcommands (pyproject.toml, [project.entry-points."refiner_rt.commands"]).
ENTRY_POINT_GROUP = "refiner_rt.commands"


@dataclass(frozen=True)
class LazyCommand:
    """A subcommand known by its target, ``"module:attribute"`` of a click command, and its one-line help: the
    module is imported only when the command runs (:meth:`load`)."""

    target: str
    help: str

    def load(self) -> click.Command:
        module_name, attr = self.target.split(":")
        return getattr(importlib.import_module(module_name), attr)


# The runtime's own subcommands, one module each under refiner_rt/cli/. A new runtime command adds its line here.
RUNTIME_COMMANDS = {
    "info": LazyCommand("refiner_rt.cli.info:info_cmd", "Print a model's metadata contract, inputs/outputs and size."),
    "models": LazyCommand("refiner_rt.cli.models:models_cmd", "List the pretrained refiners that ship in the package."),
    "demo": LazyCommand("refiner_rt.cli.demo:demo_cmd",
                        "Refine sample frames (or your image) with the shipped models; draw it."),
    "estimate": LazyCommand("refiner_rt.cli.estimate:estimate_cmd",
                            "6D poses (rotation and translation) from images and 2D boxes alone."),
    "track": LazyCommand("refiner_rt.cli.track:track_cmd",
                         "Track object rotations through a folder of frames with boxes."),
    "bench": LazyCommand("refiner_rt.cli.bench:bench_cmd",
                         "CPU speed of the full refine() path: shallow, fusion and VGG-M, fp32 and INT8."),
}


PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")  # what the commands' pictures may be


def check_picture_path(path):
    """``path`` as a ``Path`` when its suffix is one of :data:`PICTURE_SUFFIXES`, else a one-line click error (a
    command checks its picture path before its work, then writes with :func:`write_picture`)."""
    from pathlib import Path

    path = Path(path)
    if path.suffix.lower() not in PICTURE_SUFFIXES:
        raise click.ClickException(f"cannot write a picture to {path}: expected a file ending in "
                                   f"{', '.join(PICTURE_SUFFIXES)}; got {path.suffix or 'no suffix'!r}")
    return path


def prepare_output(path, param_hint: str):
    """``path``, an output of a command (a file, or ``track --bag``'s new bag folder), as a ``Path`` whose missing
    parent folders have been created: the one rule of every ``refiner-rt`` output (``demo --out``, ``estimate
    --out/--overlay``, ``track -o/--video``), applied once the options are checked and before the work, so that a
    long run does not fail at its end. The output itself is not created here.

    Raises:
        click.BadParameter: the parent folder cannot be made (a file in its way, no permission), naming
            ``param_hint`` (the option, e.g. ``"'--out'"``).
    """
    from pathlib import Path

    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise click.BadParameter(f"cannot create the folder {path.parent} for {path.name}: {exc.strerror or exc}",
                                 param_hint=param_hint) from None
    return path


def write_picture(path, picture) -> None:
    """Write ``picture`` (``H x W x 3`` uint8 BGR) to ``path``, or a one-line click error naming what was wrong: a
    suffix OpenCV does not write as an image (one of :data:`PICTURE_SUFFIXES` expected), or a folder not writable."""
    import cv2
    from pathlib import Path

    path = check_picture_path(path)
    try:
        ok = cv2.imwrite(str(path), picture)
    except cv2.error:
        ok = False
    if not ok:
        raise click.ClickException(f"could not write {path} (is its folder there and writable?)")


def plugged_commands() -> dict:
    """``{name: entry point}`` of the commands other packages declare in :data:`ENTRY_POINT_GROUP` (not loaded)."""
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def missing_message(command: str, module: str | None, provider: str | None = None) -> str:
    """One line for a command that stopped at a missing module: the package that plugs the command in (``provider``,
    its top-level name: the training package, absent from a runtime-only install, since the wheel carries
    ``refiner_rt`` alone) or one of its dependencies (torch, onnx, pybullet...)."""
    if provider is not None and (module or "").split(".")[0] == provider:
        return f"'refiner-rt {command}' is part of the training package, which is not installed: {TRAINING_INSTALL}"
    return (f"'refiner-rt {command}' needs {module or 'a module'!r}, which is not installed; install the training "
            f"extra in the source checkout: pip install torch==2.13.0 && pip install -e '.[train]'")


class LazyGroup(click.Group):
    """A click group that imports a subcommand's module only when that subcommand runs: ``lazy_commands``
    (``{name: LazyCommand}``) and, with ``plugins``, the commands of :data:`ENTRY_POINT_GROUP`. A plugged-in command
    named like one of ``lazy_commands`` takes its place where its package is installed (the training package's
    ``bench`` is the runtime's with more rows), and the group's own runs where it is not."""

    def __init__(self, *args, lazy_commands: dict | None = None, plugins: bool = False, **kwargs):
        super().__init__(*args, **kwargs)
        self.lazy_commands = dict(lazy_commands or {})
        self.plugins = plugins

    def _plugged(self) -> dict:
        return plugged_commands() if self.plugins else {}

    def _names(self) -> set:
        return set(self.lazy_commands) | set(self._plugged())

    def _target(self, name: str):
        """What ``name`` runs, not loaded yet: a :class:`LazyCommand` (or a click command), None if unknown.

        Raises:
            ModuleNotFoundError: a plugged-in command whose package is not installed, with no command of the
                group's own by that name.
        """
        ep = self._plugged().get(name)
        if ep is not None:
            try:
                return ep.load()
            except ModuleNotFoundError:
                if name not in self.lazy_commands:
                    raise
        return self.lazy_commands.get(name)

    def _provider(self, name: str) -> str | None:
        """The top-level package that plugs command ``name`` in (None for the group's own commands)."""
        ep = self._plugged().get(name)
        return None if ep is None else ep.value.split(":")[0].split(".")[0]

    def list_commands(self, ctx):
        return sorted(set(super().list_commands(ctx)) | self._names())

    def get_command(self, ctx, cmd_name):
        if cmd_name not in self._names():
            return super().get_command(ctx, cmd_name)
        try:
            target = self._target(cmd_name)
            return target.load() if isinstance(target, LazyCommand) else target
        except ModuleNotFoundError as exc:
            raise click.ClickException(missing_message(cmd_name, exc.name, self._provider(cmd_name))) from exc

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
            raise click.ClickException(missing_message(name, exc.name, self._provider(name))) from None

    def _help_of(self, name: str) -> str:
        """A command's one-line help without importing its module: a :class:`LazyCommand`'s own (a plugged-in one's
        from a module of its package that imports nothing heavy)."""
        try:
            target = self._target(name)
        except ModuleNotFoundError as exc:
            return missing_message(name, exc.name, self._provider(name)).split(":")[0] + "."
        if isinstance(target, LazyCommand):
            return target.help
        return target.get_short_help_str() if isinstance(target, click.Command) else ""

    def format_commands(self, ctx, formatter):
        rows = [(name, self._help_of(name)) for name in sorted(self._names())]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


@click.group(cls=LazyGroup, lazy_commands=RUNTIME_COMMANDS, plugins=True)
@click.version_option(__version__, prog_name="refiner-rt")
def main():
    """refiner-rt: fast 3D pose refinement from RGB crops.

    Conventions: quaternions wxyz (scalar first), rotations object-to-camera,
    images HxWx3 uint8 BGR, boxes (x1, y1, x2, y2) in pixels, angles in degrees.
    Output files of demo, estimate and track: a missing folder of one is made.
    """
