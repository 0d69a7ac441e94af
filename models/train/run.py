"""``models.run_training(recipe, out=...)``: a whole training run from a :class:`models.train.recipe.TrainRecipe`.

Outputs, next to ``out`` (e.g. ``runs/shallow.pt``):
    * ``out``: the base network (all objects), and ``<stem>.recipe.json``: the resolved recipe;
    * ``<stem>.<object>.pt``: one fine-tuned network per object (unless ``per_object == 0``), each with its
      ``.recipe.json``;
    * ``<stem>.log.jsonl`` / ``<stem>.log.csv``: every epoch of every stage; ``<stem>.png``: the curves;
    * ``<stem>.state/``: resumable training state (used by ``resume=True`` and by the recipe's ``stages``).

Runs data-parallel under ``torchrun --nproc_per_node N`` (PyTorch DDP: NCCL when the model is on a CUDA device,
gloo otherwise).
"""

from __future__ import annotations

import copy
import csv
import json
import logging
import os
import shutil
import time
from dataclasses import replace
from pathlib import Path

from models.train.paths import per_object_path, recipe_path_for
from models.train.recipe import RecipeError, TrainRecipe, check_masks

__all__ = ["run_training", "resolve_device", "init_distributed", "distributed_backend", "write_logs", "load_base", "load_init",
           "split_like_base", "check_base_split"]

log = logging.getLogger(__name__)


def resolve_device(device: str = "auto", rank: int = 0):
    """A ``torch.device`` from ``"auto"`` (CUDA, then MPS, then the CPU), ``"cpu"``, ``"cuda[:N]"`` or ``"mps"``.

    Under ``torchrun`` a bare ``"cuda"`` means the rank's own GPU (``LOCAL_RANK``).

    Raises:
        RecipeError: the device is not available on this machine.
    """
    import torch

    if device == "auto":
        if torch.cuda.is_available():
            device = "cuda"
        elif getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
            device = "mps"
        else:
            device = "cpu"
    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise RecipeError("device", f"device {device!r}: CUDA is not available here (torch "
                              f"{torch.__version__}, {'a CUDA build' if torch.version.cuda else 'a CPU-only build'})")
        if device == "cuda":
            device = f"cuda:{int(os.environ.get('LOCAL_RANK', rank)) % torch.cuda.device_count()}"
    if device == "mps" and not (getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available()):
        raise RecipeError("device", "device 'mps': Apple's Metal backend is not available here")
    return torch.device(device)


def init_distributed(device) -> tuple[int, int]:
    """Initialise torch.distributed when launched by torchrun; returns ``(rank, world_size)``.

    The backend follows where the tensors are: NCCL only for a CUDA device, gloo for the CPU (a machine with a GPU
    training on its CPU must not pick NCCL, which cannot reduce CPU tensors).
    """
    import torch

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    if not torch.distributed.is_initialized():
        torch.distributed.init_process_group(backend=distributed_backend(device))
    return torch.distributed.get_rank(), world


def distributed_backend(device) -> str:
    """``"nccl"`` for a CUDA device, ``"gloo"`` for every other."""
    return "nccl" if str(device).startswith("cuda") else "gloo"


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


def load_base(recipe: TrainRecipe):
    """``(model, info)`` of the trained base network ``recipe.base_ckpt``, checked against the recipe;
    ``(None, None)`` without one."""
    import models

    path = recipe.base_ckpt
    if path is None:
        return None, None
    try:
        model, info = models.load_checkpoint(path)
    except (OSError, ValueError, KeyError) as exc:
        message = str(exc) if str(exc).startswith(str(path)) else f"{path}: {exc}"
        raise RecipeError("base_ckpt", message) from None
    stage = info.get("stage")
    if stage != "base":
        raise RecipeError("base_ckpt", f"{path} is a {stage!r} checkpoint; expected a base network (stage 'base', the "
                          "CKPT that `refiner-rt train` writes, not a per-object sibling)")
    _check_same_network(recipe, model, info, path, "base_ckpt", "--base")
    return model, info


def load_init(recipe: TrainRecipe):
    """The network of ``recipe.init`` (weights to start the base stage from), checked against the recipe."""
    import models

    try:
        model, info = models.load_checkpoint(recipe.init)
    except (OSError, ValueError, KeyError) as exc:
        message = str(exc) if str(exc).startswith(str(recipe.init)) else f"{recipe.init}: {exc}"
        raise RecipeError("init", message) from None
    if recipe.arch_config and model.arch == recipe.arch:
        from models.nets.fusion import with_roll

        model = with_roll(model, {**model.config, **recipe.arch_config})  # going on with another input turn
    _check_same_network(recipe, model, info, recipe.init, "init", "--init")
    return model.train()


def _check_same_network(recipe: TrainRecipe, model, info: dict, path, field_name: str, flag: str) -> None:
    if recipe.arch != model.arch:
        raise RecipeError(field_name, f"{path} is a {model.arch!r} network; pass --arch {model.arch} (got "
                          f"{recipe.arch!r})")
    if recipe.arch_config and any(model.config.get(k) != v for k, v in recipe.arch_config.items()):
        raise RecipeError(field_name, f"--config {json.dumps(recipe.arch_config)} differs from the {flag} "
                          "checkpoint's config; leave --config out (the checkpoint's is used)")
    frame = info.get("rotation_frame", "camera")
    if recipe.rotation_frame != frame:
        raise RecipeError(field_name, f"{path} was trained in the {frame!r} rotation frame; pass --rotation-frame "
                          f"{frame} (got {recipe.rotation_frame!r})")


def run_training(recipe: TrainRecipe, out: str | Path, *, resume: bool = False, progress: bool = True,
          echo=None) -> dict[str, str]:
    """Run ``recipe``: its first pass, then each of its ``stages`` continuing from the previous state.

    Args:
        recipe: the run (validated again here).
        out: the base checkpoint path (``CKPT.pt``); per-object ones, logs and recipes go beside it.
        resume: continue from ``out``'s ``.state`` folder (an interrupted run, or a finished one given more epochs).
        progress: progress bars (rank 0 only).
        echo: ``callable(str)`` for the run's progress lines (default: the module's logger).

    Returns:
        ``{"base": path, <object>: path, ...}``: the checkpoints written.

    Raises:
        RecipeError: a value out of range, a rule broken, or a checkpoint that does not fit (``.field`` names it).
        ValueError: data that cannot give the split asked for.
    """
    recipe.validate()
    first = replace(recipe, stages=[])
    outputs = _train_pass(first, Path(out), resume=resume, progress=progress, echo=echo or log.info, full=recipe)
    for i, changes in enumerate(recipe.stages):
        (echo or log.info)(f"stage {i + 2} of {len(recipe.stages) + 1}: continuing with {json.dumps(changes)}")
        stage = replace(first, **changes)
        outputs = _train_pass(stage.validate(), Path(out), resume=True, progress=progress, echo=echo or log.info,
                              full=recipe)
    return outputs


def _train_pass(recipe: TrainRecipe, out: Path, *, resume: bool, progress: bool, echo, full: TrainRecipe) -> dict:
    import torch

    import models
    from models.data.pipeline import cropset_for, load_splits
    from models.train.loop import set_threads, train_refiner

    device = resolve_device(recipe.device)
    rank, world = init_distributed(device)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    set_threads(recipe.threads or max(1, cores // world))
    out.parent.mkdir(parents=True, exist_ok=True)
    stem = out.with_suffix("")
    state_dir = Path(f"{stem}.state")
    if rank == 0:
        state_dir.mkdir(exist_ok=True)
    if not resume and rank == 0:
        for p in list(state_dir.glob("*.pt")) + [Path(f"{stem}.log.jsonl")]:
            p.unlink(missing_ok=True)

    spec = recipe.data_spec()
    t_start = time.perf_counter()
    base_model, base_info = load_base(recipe)
    spec = split_like_base(spec, base_info)
    splits = load_splits(spec)
    check_base_split(spec, splits, base_info, recipe.base_ckpt)
    torch.manual_seed(recipe.seed)
    model = base_model
    if model is None and recipe.init is not None:
        model = load_init(recipe)
    elif model is None:
        try:
            model = models.build_refiner(recipe.arch, **recipe.arch_config)
        except (KeyError, ValueError) as exc:
            raise RecipeError("arch", f"--arch {recipe.arch} --config {json.dumps(recipe.arch_config)}: {exc}") from None
    size, context = model.input_size, model.config["crop_context"]
    show = progress and rank == 0
    wanted = (["val"] + (["train_base"] if base_model is None else [])
              + (["train_finetune"] if recipe.per_object else []))
    parts = {p: cropset_for(splits, p, spec, size, context, cache_root=recipe.cache_root, workers=recipe.workers,
                            progress=show, crop_filter=model.config["crop_filter"]) for p in wanted}
    first = "train_base" if base_model is None else "train_finetune"
    check_masks(recipe.background, recipe.occlude,
                all(parts[p].masks is not None for p in parts if p != "val"),
                f"{recipe.data} for the training crops")
    symmetries = _symmetries(recipe, spec)
    echo(f"Training {recipe.arch} ({model.num_parameters():,} parameters) on {len(parts[first])} crops of "
         f"{len(parts[first].objects)} objects, split {spec.split_mode}, {world} process(es) on {device}"
         + (f", fine-tuning the base network {recipe.base_ckpt}" if base_model is not None else ""))
    log_path = Path(f"{stem}.log.jsonl") if rank == 0 else None
    info_common = {
        "train_noise": recipe.noise,
        "rotation_frame": recipe.rotation_frame,
        "data": spec.as_dict(),
        "split": splits.summary(),
        "world_size": world,
        **({"symmetries": symmetries} if symmetries else {}),
        **_object_records(spec),
    }
    outputs = {"base": str(out)}
    if base_model is None:
        base_cfg = recipe.stage_config("base", len(parts["train_base"]))
        res = train_refiner(model, parts["train_base"], parts["val"], base_cfg, state_path=state_dir / "base.pt",
                            log_path=log_path, progress=show, desc="base", device=device, symmetries=symmetries)
        if rank == 0:
            models.save_checkpoint(
                res.model, out, objects=parts["train_base"].objects, stage="base", train_config=vars(base_cfg),
                best_epoch=res.best_epoch, val_mean_deg=res.best_val_deg, recipe=full.as_dict(), **info_common,
            )
            full.save(recipe_path_for(out))
            echo(f"base: best epoch {res.best_epoch}, validation mean error {res.best_val_deg:.2f} deg -> {out}")
        history = list(res.history)
    else:
        history = []
        if rank == 0 and out.resolve() != Path(recipe.base_ckpt).resolve():
            shutil.copyfile(recipe.base_ckpt, out)  # the per-object checkpoints name their base network beside them
            echo(f"base: {recipe.base_ckpt} (not retrained) -> {out}")
    if recipe.per_object:
        base_state = copy.deepcopy(model.state_dict())
        for obj in parts["train_finetune"].objects:
            model.load_state_dict(base_state)
            train_obj = parts["train_finetune"].for_object(obj)
            ft_cfg = recipe.stage_config("finetune", len(train_obj))
            ft = train_refiner(model, train_obj, parts["val"].for_object(obj), ft_cfg,
                               state_path=state_dir / f"{obj}.pt", log_path=log_path, progress=show, desc=obj,
                               device=device, symmetries=symmetries)
            history += ft.history
            path = per_object_path(out, obj)
            if rank == 0:
                models.save_checkpoint(
                    ft.model, path, objects=[obj], stage="finetune", base_checkpoint=out.name,
                    train_config=vars(ft_cfg), best_epoch=ft.best_epoch, val_mean_deg=ft.best_val_deg,
                    recipe=full.as_dict(), **info_common,
                )
                full.save(recipe_path_for(path))
                echo(f"{obj}: best epoch {ft.best_epoch}, validation mean error {ft.best_val_deg:.2f} deg -> {path}")
            outputs[obj] = str(path)
    if rank == 0:
        write_logs(history, stem)
        echo(f"Done in {time.perf_counter() - t_start:.0f} s. Logs: {stem}.log.csv, plot: {stem}.png")
    if world > 1:
        # Every rank reaches teardown before any destroys the group: a rank that tears gloo down while another
        # still talks to it can abort at exit ("terminate called without an active exception").
        torch.distributed.barrier()
        torch.distributed.destroy_process_group()
    return outputs


def _symmetries(recipe: TrainRecipe, spec) -> dict:
    """Object name -> symmetry (BOP models_info form) of the objects trained: the dataset's record, then the
    recipe's ``symmetries`` over it (``{}`` for an object trains it with the plain loss)."""
    from models.data.objects import dataset_objects

    recorded = dataset_objects(spec.data)
    out = {o: recorded[o]["symmetry"] for o in spec.object_ids if recorded.get(o, {}).get("symmetry")}
    out.update({o: s for o, s in recipe.symmetries.items() if o in spec.object_ids})
    return {o: s for o, s in out.items() if s}  # an empty entry in the recipe turns a recorded symmetry off


def _object_records(spec) -> dict:
    """``{"meshes": {object: {"file", "sha256", "unit"}}}`` for the objects trained, from the dataset's record of
    the meshes it was rendered from (nothing for real data, which records none)."""
    from models.data.objects import dataset_objects

    recorded = dataset_objects(spec.data)
    meshes = {o: recorded[o]["mesh"] for o in spec.object_ids if recorded.get(o, {}).get("mesh")}
    return {"meshes": meshes} if meshes else {}


def _base_spec(spec, base_info: dict | None):
    """The base network's recorded data spec when it was split from the same dataset as ``spec``, else None."""
    from models.data.pipeline import DataSpec

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

    Raises:
        ValueError: some validation or test crops come from the base network's training scenes or frames.
    """
    from models.data.pipeline import load_splits

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

        raise ValueError(
            f"{leaked} of the {len(held)} validation and test crops of this split come from {unit}s the base "
            f"network {base_path} was trained on, so they would not be held out. The base was split with "
            f"{described(base)}; this run asks for {described(spec)} (training images: --base-per-object + "
            "--per-object). Use the base's values."
        )
