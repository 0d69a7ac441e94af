"""``refiner-rt train``: a :class:`models.train.recipe.TrainRecipe` from ``--recipe NAME|FILE``, flags over it, then
:func:`models.train.run.run_training`.

The options are generated from the recipe's fields (one definition: name, help, section); only the click type of
each lives here. A flag not given keeps the recipe's value; ``--print-recipe`` prints the resolved recipe as JSON
(a file ``--recipe`` reads back). Outputs: see :mod:`models.train.run`; the resolved recipe is saved beside every
checkpoint as ``<stem>.recipe.json``.

With ``--base BASE.pt`` the base stage is skipped: BASE (a trained base checkpoint) is copied to ``CKPT`` and only
the per-object fine-tuning runs, e.g. to fine-tune on more images, or on an object the base never saw.

Runs data-parallel under ``torchrun --nproc_per_node N`` (PyTorch DDP: NCCL when the model is on a CUDA device,
gloo otherwise).
"""

from __future__ import annotations

import json
import logging
from dataclasses import fields
from pathlib import Path

import click

from models.data.augment import PHOTOMETRIC_OPS
from models.train.recipe import (NAMED_RECIPES, SECTIONS, RecipeError, TrainRecipe, field_default, object_names,
                                 load_recipe, parse_json_object)
from models.train.run import write_logs  # noqa: F401  (re-exported: the epoch logs of a run)

log = logging.getLogger(__name__)


def _noise(ctx, param, value):
    if value is None:
        return None
    from models.data.noise import NoiseSpec

    try:
        return str(NoiseSpec.parse(value))
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def _names(ctx, param, value):
    """Comma-separated object names (YCB ids, your own objects' names; ``paper`` for the paper's nine)."""
    if not value:
        return None
    try:
        return object_names(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def _json_config(ctx, param, value):
    """``--config``: the recipe's JSON-object parser, its error as click's."""
    import argparse

    if value is None:
        return None
    try:
        return parse_json_object(value)
    except argparse.ArgumentTypeError as exc:
        raise click.BadParameter(str(exc)) from None


_DIR = click.Path(exists=True, file_okay=False)
_FILE = click.Path(exists=True, dir_okay=False)
_PROB = click.FloatRange(0, 1)
# The click type (and callback) of every field that has a command-line option; the rest of each option (its name,
# help and section) comes from the field itself.
CLICK_TYPES: dict[str, dict] = {
    "data": {"type": _DIR}, "fmt": {"type": click.Choice(["auto", "bop", "ycbv"])},
    "objects": {"callback": _names}, "split_objects": {"callback": _names},
    "split_mode": {"type": click.Choice(["frames", "scenes"])}, "split_seed": {"type": int},
    "base_per_object": {"type": click.IntRange(0)}, "per_object": {"type": click.IntRange(0)},
    "val_per_object": {"type": click.IntRange(1)}, "test_per_object": {"type": click.IntRange(1)},
    "min_visib": {"type": _PROB}, "extra_train": {"type": _DIR, "multiple": True},
    "arch": {"type": str}, "arch_config": {"callback": _json_config},
    "rotation_frame": {"type": click.Choice(["camera", "ray"])}, "init": {"type": _FILE}, "base_ckpt": {"type": _FILE},
    "epochs_mse": {"type": click.IntRange(0)}, "epochs_geodesic": {"type": click.IntRange(0)},
    "ft_epochs_mse": {"type": click.IntRange(0)}, "ft_epochs_geodesic": {"type": click.IntRange(0)},
    "samples": {"type": click.IntRange(0)}, "epoch_samples": {"type": click.IntRange(1)},
    "noise": {"callback": _noise}, "lr": {"type": click.FloatRange(0, min_open=True)},
    "ft_lr": {"type": click.FloatRange(0, min_open=True)}, "lr_schedule": {"type": click.Choice(["constant", "cosine"])},
    "batch_size": {"type": click.IntRange(1)}, "max_steps_per_epoch": {"type": click.IntRange(0)}, "seed": {"type": int},
    "bf16": {"bool": True}, "ema": {"type": click.FloatRange(0, 1, max_open=True)},
    "weight_decay": {"type": click.FloatRange(0)}, "augment": {"bool": True}, "background": {"type": _PROB},
    "occlude": {"type": _PROB}, "relight": {"type": _PROB}, **{f"aug_{op}": {"type": _PROB} for op in PHOTOMETRIC_OPS}, "inplane": {"type": click.FloatRange(0, 180)},
    "device": {"type": str}, "threads": {"type": click.IntRange(0)}, "workers": {"type": click.IntRange(1)},
    "cache_root": {"type": click.Path(file_okay=False)},
}


def flag_of(name: str) -> str:
    """The command-line flag of a recipe field (``arch_config`` -> ``--config``)."""
    f = next((f for f in fields(TrainRecipe) if f.name == name), None)
    if f is None:
        return name
    return f.metadata.get("flag") or "--" + name.replace("_", "-")


class SectionOption(click.Option):
    """An option shown under a section heading of ``--help``."""

    def __init__(self, *args, section: str = "run", **kwargs):
        super().__init__(*args, **kwargs)
        self.section = section


class SectionedCommand(click.Command):
    """A command whose ``--help`` lists its options in sections (data, model, optimisation, augmentation, run)."""

    def format_options(self, ctx, formatter):
        by_section: dict[str, list] = {}
        for param in self.get_params(ctx):
            record = param.get_help_record(ctx)
            if record is not None:
                by_section.setdefault(getattr(param, "section", "run"), []).append(record)
        for section in (*SECTIONS, *[s for s in by_section if s not in SECTIONS]):
            if by_section.get(section):
                with formatter.section(f"{section.capitalize()} options"):
                    formatter.write_dl(by_section[section])


def recipe_options(func):
    """Decorate ``func`` with one option per recipe field that has one (``default=None``: not given)."""
    for f in reversed(fields(TrainRecipe)):
        if not f.metadata.get("cli", True):
            continue
        spec = dict(CLICK_TYPES[f.name])
        default = field_default(f)
        flag = flag_of(f.name)
        shown = json.dumps(default) if isinstance(default, (dict, list)) else default
        help_text = f"{f.metadata['help']} [paper: {shown}]" if default not in (None, [], {}) else f.metadata["help"]
        if spec.pop("bool", False):
            decls = [f"{flag}/--no-{flag[2:]}", f.name]
        else:
            decls = [flag, f.name]
        func = click.option(*decls, cls=SectionOption, section=f.metadata["section"], default=None, help=help_text,
                            **spec)(func)
    return func


def _given(opts: dict) -> dict:
    """The recipe fields given on the command line, as JSON-able values."""
    out = {}
    for name, value in opts.items():
        if value is None or value == ():
            continue
        if isinstance(value, Path):
            value = str(value)
        elif isinstance(value, tuple):
            value = [str(v) for v in value]
        out[name] = value
    return out


@click.command("train", cls=SectionedCommand)
@click.option("--recipe", "recipe_source", cls=SectionOption, section="run", metavar="NAME|FILE",
              help=f"The recipe to start from: a named recipe ({', '.join(NAMED_RECIPES)}) or a .json/.toml file "
                   "(e.g. one --print-recipe wrote); the flags below override it. Default: paper.")
@click.option("--print-recipe", is_flag=True, cls=SectionOption, section="run",
              help="Print the resolved recipe as JSON and exit (nothing is trained).")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), cls=SectionOption, section="run",
              help="Base checkpoint path (CKPT.pt); per-object ones, logs and CKPT.recipe.json go beside it.")
@click.option("--resume", is_flag=True, cls=SectionOption, section="run",
              help="Continue from OUT's .state folder: an interrupted run, or a finished one given more epochs "
                   "(each stage and object goes on from its last epoch with the options given now).")
@click.option("--quiet", is_flag=True, cls=SectionOption, section="run", help="No progress bars.")
@recipe_options
def train_cmd(recipe_source, print_recipe, out, resume, quiet, **opts):
    """Train a refiner from a recipe: base network on all objects, then per-object fine-tuning (the paper's).

    Coarse poses q_in = q_gt * q_noise are drawn afresh every epoch; the label is q_noise^-1;
    MSE for the first epochs, then the geodesic loss; Adam. The best validation epoch is kept.
    Example: refiner-rt train --recipe paper --data DIR --out runs/paper.pt
    """
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        base = load_recipe(recipe_source or "paper")
        recipe = TrainRecipe.from_dict(_given(opts), base=base)
    except RecipeError as exc:
        hint = "--recipe" if exc.field == "recipe" else flag_of(exc.field)
        raise click.BadParameter(str(exc), param_hint=hint) from None
    if print_recipe:
        click.echo(recipe.to_json(), nl=False)
        return
    if out is None:
        raise click.UsageError("give --out CKPT.pt (or --print-recipe)")
    if recipe.data is None:
        raise click.BadParameter("the dataset folder is not set by the recipe: give --data DIR", param_hint="--data")
    run(recipe, out, resume=resume, quiet=quiet)


def run(recipe: TrainRecipe, out: Path, *, resume: bool = False, quiet: bool = False) -> dict:
    """:func:`models.train.run.run_training` with its errors as click errors (a bad value: exit 2; bad data: exit 1)."""
    from models.train.run import run_training

    try:
        return run_training(recipe, out, resume=resume, progress=not quiet, echo=lambda m: click.echo(m, err=True))
    except RecipeError as exc:
        raise click.BadParameter(str(exc), param_hint=flag_of(exc.field)) from None
    except ValueError as exc:  # the data does not give the split asked for (the message says why)
        raise click.ClickException(str(exc)) from None
