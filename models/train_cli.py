"""``refiner-rt train``: base training on all objects, then per-object fine-tuning, as in the paper.

Outputs, next to ``--out CKPT`` (e.g. ``runs/shallow.pt``):
    * ``CKPT``: the base network (all objects);
    * ``<stem>.<ycb id>.pt``: one fine-tuned network per object (unless ``--per-object 0``);
    * ``<stem>.log.jsonl`` / ``<stem>.log.csv``: every epoch of every stage (loss, validation error,
      learning rate, samples/s);
    * ``<stem>.png``: loss and validation-error curves;
    * ``<stem>.state/``: resumable training state (used by ``--resume``).

With ``--base BASE.pt`` the base stage is skipped: BASE (a trained base checkpoint) is copied to ``CKPT`` and only
the per-object fine-tuning runs, e.g. to fine-tune on more images, or on an object the base never saw.

Runs data-parallel under ``torchrun --nproc_per_node N`` (PyTorch DDP; gloo on CPU, nccl on GPUs).
"""

from __future__ import annotations

import csv
import json
import logging
import os
import shutil
import time
from pathlib import Path

import click

log = logging.getLogger(__name__)

PAPER_SIZES = (3000, 2000, 3000, 3000)


def _noise(ctx, param, value):
    from models.noise import NoiseSpec

    try:
        return str(NoiseSpec.parse(value))
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def _objects(ctx, param, value):
    if not value:
        return None
    from models.data.objects import YCBV_CLASSES

    ids = [v.strip() for v in value.split(",") if v.strip()]
    unknown = [i for i in ids if i not in YCBV_CLASSES]
    if unknown:
        raise click.BadParameter(f"unknown YCB id(s) {unknown}; expected ids like 003_cracker_box (one of {list(YCBV_CLASSES)})")
    return ids


def _json_config(ctx, param, value):
    if not value:
        return {}
    try:
        cfg = json.loads(value)
    except json.JSONDecodeError as exc:
        raise click.BadParameter(f"expected a JSON object, e.g. '{{\"head_widths\": [512, 64]}}'; {exc}") from None
    if not isinstance(cfg, dict):
        raise click.BadParameter(f"expected a JSON object; got {type(cfg).__name__}")
    return cfg


def _init_distributed() -> tuple[int, int]:
    """Initialise torch.distributed when launched by torchrun; returns (rank, world_size)."""
    import torch

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    if not torch.distributed.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        torch.distributed.init_process_group(backend=backend)
    return torch.distributed.get_rank(), world


def write_logs(history: list[dict], stem: Path) -> None:
    """The epoch history as CSV and a PNG of loss and validation error per stage."""
    if not history:
        return
    fields = list(dict.fromkeys(k for row in history for k in row))  # a resumed run's older rows may lack newer keys
    with open(f"{stem}.log.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(history)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ModuleNotFoundError:
        log.warning("matplotlib not installed: no training plot written")
        return
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    stages = list(dict.fromkeys(r["stage"] for r in history))
    for stage in stages:
        rows = [r for r in history if r["stage"] == stage]
        ep = [r["epoch"] for r in rows]
        alpha = 1.0 if stage == "base" else 0.5
        ax1.plot(ep, [r["train_loss"] for r in rows], label=stage, alpha=alpha)
        ax2.plot(ep, [r["val_mean_deg"] for r in rows], label=stage, alpha=alpha)
    ax1.set(xlabel="epoch", ylabel="training loss (MSE, then geodesic rad)", yscale="log", title="loss")
    ax2.set(xlabel="epoch", ylabel="validation mean error (deg)", title="validation error")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(f"{stem}.png", dpi=110)
    plt.close(fig)


@click.command("train")
@click.option("--data", required=True, type=click.Path(exists=True, file_okay=False, path_type=Path), help="Dataset: a BOP split folder (scene folders) or a YCB-Video root.")
@click.option("--format", "fmt", type=click.Choice(["auto", "bop", "ycbv"]), default="auto", show_default=True, help="Dataset layout.")
@click.option("--arch", default="shallow", show_default=True, help="Registered architecture: shallow (paper), vggm (paper), fusion (ours).")
@click.option("--config", "arch_config", callback=_json_config, help="JSON object of architecture config overrides, e.g. '{\"head_widths\": [512, 64]}'.")
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="Base checkpoint path (CKPT.pt); per-object ones go beside it.")
@click.option("--objects", callback=_objects, help="Comma-separated YCB ids (default: the paper's nine).")
@click.option("--base", "base_ckpt", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="A trained base checkpoint: skip base training and fine-tune it per object (needs --per-object > 0; "
                   "--arch and --rotation-frame must be the checkpoint's).")
@click.option("--base-per-object", default=PAPER_SIZES[0], show_default=True, type=click.IntRange(0),
              help="Base-training images per object (0 only with --base: the fine-tuning images then start where "
                   "the base images would, right after the validation ones).")
@click.option("--per-object", default=PAPER_SIZES[1], show_default=True, type=click.IntRange(0), help="Fine-tuning images per object (0: no fine-tuning).")
@click.option("--val-per-object", default=PAPER_SIZES[2], show_default=True, type=click.IntRange(1), help="Validation images per object.")
@click.option("--test-per-object", default=PAPER_SIZES[3], show_default=True, type=click.IntRange(1), help="Test images per object (held out; used by eval).")
@click.option("--split-mode", type=click.Choice(["frames", "scenes"]), default="frames", show_default=True, help="frames: paper's random frame split; scenes: whole scenes held out.")
@click.option("--split-seed", default=0, show_default=True, type=int)
@click.option("--extra-train", multiple=True, type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="Another dataset folder whose images all join the base-training images, after --data is split "
                   "(repeatable): the validation and test images stay those of --data. Its scene ids must be new, "
                   "e.g. the next scenes of --data's seed (refiner-rt render --first-scene N).")
@click.option("--min-visib", default=0.3, show_default=True, type=click.FloatRange(0, 1), help="Minimum visible fraction of an instance.")
@click.option("--epochs-mse", default=5, show_default=True, type=click.IntRange(0), help="Epochs with the MSE loss (paper: 5).")
@click.option("--epochs-geodesic", default=10, show_default=True, type=click.IntRange(0), help="Epochs with the geodesic loss after those (paper: 10).")
@click.option("--ft-epochs-mse", type=click.IntRange(0), help="Fine-tuning MSE epochs (default: --epochs-mse).")
@click.option("--ft-epochs-geodesic", type=click.IntRange(0), help="Fine-tuning geodesic epochs (default: --epochs-geodesic).")
@click.option("--noise", default="uniform:0:30", show_default=True, callback=_noise, help="Coarse-pose noise: uniform:LOW:HIGH or normal:MEAN:STD (degrees).")
@click.option("--lr", default=1e-4, show_default=True, type=click.FloatRange(0, min_open=True), help="Adam learning rate (base training).")
@click.option("--ft-lr", type=click.FloatRange(0, min_open=True), help="Fine-tuning learning rate (default: --lr / 3).")
@click.option("--lr-schedule", type=click.Choice(["constant", "cosine"]), default="constant", show_default=True)
@click.option("--batch-size", default=64, show_default=True, type=click.IntRange(1))
@click.option("--augment/--no-augment", default=False, show_default=True, help="Colour and detector-like box jitter (off in the paper's recipe).")
@click.option("--background", default=0.0, show_default=True, type=click.FloatRange(0, 1),
              help="Probability of giving a training crop a new background (another crop or a random colour field) "
                   "outside its instance mask; needs masks (BOP mask_visib/, YCB-Video -label.png).")
@click.option("--occlude", default=0.0, show_default=True, type=click.FloatRange(0, 1),
              help="Probability of pasting another training crop's object (its masked pixels, shifted) over a crop; "
                   "needs masks like --background.")
@click.option("--relight", default=0.0, show_default=True, type=click.FloatRange(0, 1),
              help="Probability of giving a training crop another scene's light and camera: a smooth shading field, "
                   "light colour, gamma, blur and sensor noise (no masks needed).")
@click.option("--inplane", default=0.0, show_default=True, type=click.FloatRange(0, 180),
              help="Turn every training crop about its centre by up to this many degrees, the coarse pose with it "
                   "(new rotations about the viewing ray); needs --rotation-frame ray. 0: off.")
@click.option("--rotation-frame", type=click.Choice(["camera", "ray"]), default="camera", show_default=True, help="camera: paper; ray: rotation relative to the viewing ray (needs K at run time).")
@click.option("--max-steps-per-epoch", default=0, show_default=True, type=click.IntRange(0), help="Cap optimisation steps per epoch (0: full pass).")
@click.option("--seed", default=0, show_default=True, type=int, help="Seed of initialisation, noise and shuffling.")
@click.option("--bf16/--no-bf16", default=False, show_default=True,
              help="Mixed precision: the training forward pass in bfloat16 (torch.autocast); weights, loss, validation "
                   "and export stay float32. Faster on CPUs with AVX-512 BF16 (benchmarks/train_speed.py measures it).")
@click.option("--ema", default=0.0, show_default=True, type=click.FloatRange(0, 1, max_open=True),
              help="Decay of a moving average of the weights updated every step (e.g. 0.999); validation, the kept "
                   "epoch and the saved model use the average. 0: off.")
@click.option("--weight-decay", default=0.0, show_default=True, type=click.FloatRange(0),
              help="AdamW weight decay: the weights shrink by lr * weight-decay every step. 0: off.")
@click.option("--threads", default=0, show_default=True, type=click.IntRange(0), help="Torch threads (0: all cores, shared between torchrun ranks).")
@click.option("--workers", default=1, show_default=True, type=click.IntRange(1), help="Processes that build the crop cache.")
@click.option("--cache", "cache_root", type=click.Path(file_okay=False, path_type=Path), help="Crop cache folder (default: DATA/.crops).")
@click.option("--resume", is_flag=True,
              help="Continue from OUT's .state folder: an interrupted run, or a finished one given more epochs "
                   "(each stage and object goes on from its last epoch with the options given now).")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def train_cmd(**opts):
    """Train a refiner: base network on all objects, then per-object fine-tuning (the paper's recipe).

    Coarse poses q_in = q_gt * q_noise are drawn afresh every epoch; the label is q_noise^-1;
    MSE for the first epochs, then the geodesic loss; Adam. The best validation epoch is kept.
    """
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    run_training(**opts)


def load_base(o: dict):
    """``(model, info)`` of the trained base network of ``--base`` (``o["base_ckpt"]``), checked against the
    options; ``(None, None)`` without it."""
    path = o.get("base_ckpt")
    if path is None:
        if o["base_per_object"] == 0:
            raise click.BadParameter("0 needs --base (a trained base network); without it the base stage trains "
                                     "on these images", param_hint="--base-per-object")
        return None, None
    import models

    if not o["per_object"]:
        raise click.BadParameter("--base skips the base stage, so there must be fine-tuning: pass --per-object > 0",
                                 param_hint="--base")
    try:
        model, info = models.load_checkpoint(path)
    except (OSError, ValueError, KeyError) as exc:
        message = str(exc) if str(exc).startswith(str(path)) else f"{path}: {exc}"
        raise click.BadParameter(message, param_hint="--base") from None
    stage = info.get("stage")
    if stage != "base":
        raise click.BadParameter(f"{path} is a {stage!r} checkpoint; expected a base network (stage 'base', the "
                                 "CKPT that `refiner-rt train` writes, not a per-object sibling)", param_hint="--base")
    if o["arch"] != model.arch:
        raise click.BadParameter(f"{path} is a {model.arch!r} network; pass --arch {model.arch} (got {o['arch']!r})",
                                 param_hint="--base/--arch")
    if o["arch_config"] and any(model.config.get(k) != v for k, v in o["arch_config"].items()):
        raise click.BadParameter(f"--config {json.dumps(o['arch_config'])} differs from the base checkpoint's "
                                 f"config; leave --config out (the checkpoint's is used)", param_hint="--base/--config")
    frame = info.get("rotation_frame", "camera")
    if o["rotation_frame"] != frame:
        raise click.BadParameter(f"{path} was trained in the {frame!r} rotation frame; pass --rotation-frame {frame} "
                                 f"(got {o['rotation_frame']!r})", param_hint="--base/--rotation-frame")
    return model, info


def _base_spec(spec, base_info: dict | None):
    """The base network's recorded data spec when it was split from the same dataset as ``spec``, else None."""
    from models.pipeline import DataSpec

    recorded = (base_info or {}).get("data")
    if not recorded or Path(recorded["data"]).resolve() != Path(spec.data).resolve():
        return None  # no record (an older checkpoint) or other data: there is no split to share
    return DataSpec.from_dict(recorded)


def split_like_base(spec, base_info: dict | None):
    """``spec``, drawing a ``scenes`` split over the base network's objects when fine-tuning a subset of them.

    The scenes split gives each scene to test, validation or training by all the objects it holds, so a subset
    split alone would test on scenes the base network was trained on.
    """
    base = _base_spec(spec, base_info)
    if base is not None and spec.split_mode == "scenes":
        spec.split_objects = base.split_objects_for(spec.object_ids)
    return spec


def check_base_split(spec, splits, base_info: dict | None, base_path) -> None:
    """Refuse a fine-tuning split whose validation or test crops come from what the base network trained on.

    Those crops would be seen by the network before it is validated and tested on them. In ``scenes`` mode the
    unit is the scene (an unseen scene is the point of the split), otherwise the frame. Splits that are the
    same by construction (same mode, seed, filters, validation and test sizes; in ``scenes`` mode also the same
    objects and training total) are not recomputed.
    """
    from models.pipeline import load_splits

    base = _base_spec(spec, base_info)
    if base is None:
        return
    same = [getattr(spec, k) == getattr(base, k) for k in ("fmt", "split_mode", "split_seed", "min_visib",
                                                             "min_box_size", "image_set")]
    same.append(tuple(spec.sizes[2:]) == tuple(base.sizes[2:]))
    if spec.split_mode == "scenes":
        same.append(sum(spec.sizes[:2]) == sum(base.sizes[:2]))
        same.append(set(spec.drawn_objects) == set(base.drawn_objects))
    if all(same):
        return
    unit = "scene" if base.split_mode == "scenes" else "frame"

    def key(s):
        return s.scene_key if unit == "scene" else (s.scene_key, s.frame_id)

    trained = {key(s) for s in load_splits(base).train_base}
    held = splits.val + splits.test
    leaked = sum(key(s) in trained for s in held)
    if leaked:

        def described(d):
            text = (f"--split-mode {d.split_mode} --split-seed {d.split_seed} --min-visib {d.min_visib}, "
                    f"validation/test {d.sizes[2]}/{d.sizes[3]} per object")
            if d.split_mode == "scenes":
                text += f", {sum(d.sizes[:2])} training images per object over {len(d.drawn_objects)} objects"
            return text

        raise click.ClickException(
            f"{leaked} of the {len(held)} validation and test crops of this split come from {unit}s the base "
            f"network {base_path} was trained on, so they would not be held out. The base was split with "
            f"{described(base)}; this run asks for {described(spec)} (training images: --base-per-object + "
            "--per-object). Use the base's values."
        )


def run_training(**o) -> dict:
    """The body of ``refiner-rt train`` (callable from Python with the same option names)."""
    import copy

    import torch

    import models
    from models.pipeline import DataSpec, cropset_for, load_splits
    from models.train import TrainConfig, set_threads, train_refiner

    if o["inplane"] and o["rotation_frame"] != "ray":
        raise click.ClickException(
            f"--inplane {o['inplane']:g} needs --rotation-frame ray (a crop turned about its centre shows the object "
            f"turned about the viewing ray); got --rotation-frame {o['rotation_frame']}"
        )
    rank, world = _init_distributed()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    set_threads(o["threads"] or max(1, cores // world))
    out: Path = o["out"]
    out.parent.mkdir(parents=True, exist_ok=True)
    stem = out.with_suffix("")
    state_dir = Path(f"{stem}.state")
    if rank == 0:
        state_dir.mkdir(exist_ok=True)
    if not o["resume"] and rank == 0:
        for p in list(state_dir.glob("*.pt")) + [Path(f"{stem}.log.jsonl")]:
            p.unlink(missing_ok=True)

    spec = DataSpec(
        data=str(o["data"]),
        fmt=o["fmt"],
        objects=o["objects"],
        split_mode=o["split_mode"],
        split_seed=o["split_seed"],
        sizes=(o["base_per_object"], max(o["per_object"], 0), o["val_per_object"], o["test_per_object"]),
        min_visib=o["min_visib"],
        extra_train=[str(d) for d in o["extra_train"]] or None,
    )
    t_start = time.perf_counter()
    base_model, base_info = load_base(o)
    spec = split_like_base(spec, base_info)
    try:
        splits = load_splits(spec)
    except ValueError as exc:  # the data does not give the split asked for (the message says why)
        raise click.ClickException(str(exc)) from None
    check_base_split(spec, splits, base_info, o.get("base_ckpt"))
    torch.manual_seed(o["seed"])
    model = base_model
    if model is None:
        try:
            model = models.build_refiner(o["arch"], **o["arch_config"])
        except (KeyError, ValueError) as exc:
            raise click.BadParameter(str(exc), param_hint="--arch/--config") from None
    size, context = model.input_size, model.config["crop_context"]
    progress = not o["quiet"]
    wanted = ["val"] + (["train_base"] if base_model is None else []) + (["train_finetune"] if o["per_object"] else [])
    parts = {p: cropset_for(splits, p, spec, size, context, cache_root=o["cache_root"], workers=o["workers"], progress=progress and rank == 0)
             for p in wanted}
    base_cfg = TrainConfig(
        epochs_mse=o["epochs_mse"],
        epochs_geodesic=o["epochs_geodesic"],
        batch_size=o["batch_size"],
        lr=o["lr"],
        lr_schedule=o["lr_schedule"],
        noise=o["noise"],
        rotation_frame=o["rotation_frame"],
        augment=o["augment"],
        background=o["background"],
        occlude=o["occlude"],
        relight=o["relight"],
        inplane=o["inplane"],
        seed=o["seed"],
        max_steps_per_epoch=o["max_steps_per_epoch"],
        bf16=o["bf16"],
        ema=o["ema"],
        weight_decay=o["weight_decay"],
        decoupled_weight_decay=True,
    )
    log_path = Path(f"{stem}.log.jsonl") if rank == 0 else None
    first = "train_base" if base_model is None else "train_finetune"
    masked = [f"--{k} {o[k]}" for k in ("background", "occlude") if o[k] > 0]
    if masked and any(parts[p].masks is None for p in parts if p != "val"):
        raise click.ClickException(
            f"{' '.join(masked)} needs instance masks, but {o['data']} has none for the training crops "
            "(BOP mask_visib/<im_id>_<gt_idx>.png or YCB-Video <frame>-label.png; "
            "`refiner-rt render` writes mask_visib/)"
        )
    click.echo(
        f"Training {o['arch']} ({model.num_parameters():,} parameters) on {len(parts[first])} crops of "
        f"{len(parts[first].objects)} objects, split {spec.split_mode}, {world} process(es)"
        + (f", fine-tuning the base network {o['base_ckpt']}" if base_model is not None else ""),
        err=True,
    )
    if base_model is None:
        res = train_refiner(model, parts["train_base"], parts["val"], base_cfg, state_path=state_dir / "base.pt",
                            log_path=log_path, progress=progress, desc="base")
    info_common = {
        "train_noise": o["noise"],
        "rotation_frame": o["rotation_frame"],
        "data": spec.as_dict(),
        "split": splits.summary(),
        "world_size": world,
    }
    outputs = {"base": str(out)}
    if base_model is not None:
        history = []
        if rank == 0 and out.resolve() != o["base_ckpt"].resolve():
            shutil.copyfile(o["base_ckpt"], out)  # the per-object checkpoints name their base network beside them
            click.echo(f"base: {o['base_ckpt']} (not retrained) -> {out}", err=True)
    else:
        if rank == 0:
            models.save_checkpoint(
                res.model, out, objects=parts["train_base"].objects, stage="base", train_config=vars(base_cfg),
                best_epoch=res.best_epoch, val_mean_deg=res.best_val_deg, **info_common,
            )
            click.echo(f"base: best epoch {res.best_epoch}, validation mean error {res.best_val_deg:.2f} deg -> {out}",
                       err=True)
        history = list(res.history)
    if o["per_object"]:
        ft_cfg = copy.deepcopy(base_cfg)
        ft_cfg.epochs_mse = o["ft_epochs_mse"] if o["ft_epochs_mse"] is not None else o["epochs_mse"]
        ft_cfg.epochs_geodesic = o["ft_epochs_geodesic"] if o["ft_epochs_geodesic"] is not None else o["epochs_geodesic"]
        ft_cfg.lr = o["ft_lr"] or o["lr"] / 3
        ft_cfg.__post_init__()
        base_state = copy.deepcopy(model.state_dict())
        for obj in parts["train_finetune"].objects:
            model.load_state_dict(base_state)
            ft = train_refiner(model, parts["train_finetune"].for_object(obj), parts["val"].for_object(obj), ft_cfg,
                               state_path=state_dir / f"{obj}.pt", log_path=log_path, progress=progress, desc=obj)
            history += ft.history
            path = Path(f"{stem}.{obj}.pt")
            if rank == 0:
                models.save_checkpoint(
                    ft.model, path, objects=[obj], stage="finetune", base_checkpoint=out.name, train_config=vars(ft_cfg),
                    best_epoch=ft.best_epoch, val_mean_deg=ft.best_val_deg, **info_common,
                )
                click.echo(f"{obj}: best epoch {ft.best_epoch}, validation mean error {ft.best_val_deg:.2f} deg -> {path}", err=True)
            outputs[obj] = str(path)
    if rank == 0:
        write_logs(history, stem)
        click.echo(f"Done in {time.perf_counter() - t_start:.0f} s. Logs: {stem}.log.csv, plot: {stem}.png", err=True)
    if world > 1:
        # Every rank reaches teardown before any destroys the group: a rank that tears gloo down while another
        # still talks to it can abort at exit ("terminate called without an active exception").
        torch.distributed.barrier()
        torch.distributed.destroy_process_group()
    return outputs
