"""Held-out error of one object's refiner against the number of training crops, on both split protocols.

The ``frames`` split (the paper's) tests on frames whose neighbours in the same video were trained on; the
``scenes`` split holds whole scenes out, which is what a robot in a new room sees. This study trains the same
network with the same number of optimisation steps on growing subsets of one object's training crops and
measures the test error on each protocol, so the gap between them, and how it shrinks with data, is measured
rather than guessed.

Usage (from the repository root)::

    python -m benchmarks.data_scaling --data DIR --object 003_cracker_box --sizes 1000,3000,10000 \\
        --samples 150000 [--augment] [--background 0.5] [--occlude 0.5] [--json benchmarks/results/data_scaling/data_scaling.json]

For each mode the split is made once with the largest size (so the test crops are the same for every size) and
each run trains on the first N crops of a seeded permutation of that split's training part. Every run draws
``--samples`` training samples (epochs of at most ``--epoch-samples``); the validation part picks the best epoch;
the reported error is on the test part with the inputs of ``refiner-rt eval`` (``uniform:0:30``, seed 2024).
``--augment`` adds a run with colour and box jitter at the largest size; ``--background P`` a run that replaces
the background of a crop with probability ``P``, ``--occlude P`` one that pastes another crop's object over it
(both with the jitter of ``--augment`` when given; both need instance masks: BOP ``mask_visib/``, which
``refiner-rt render`` writes). ``--augment-sizes`` runs those augmented runs at other sizes too, on the same split;
``--skip-jitter`` drops the run with jitter alone. ``--relight P`` gives every augmented run another scene's light and
camera on a crop with probability ``P`` (a smooth shading field, light colour, gamma, blur, noise).
``--train-scenes S,...`` makes the runs take every crop of the first S training scenes instead of the first N crops
(more scenes against fewer, with the same split and test crops; ``all``: every training scene, those of
``--extra-train`` included).
``--extra-train DIR`` (repeatable) adds every crop of another dataset folder to the training part after the split
is drawn, so the split and the test crops stay those of ``--data``; render its scenes as the next ones of ``--data``'s
seed (``refiner-rt render --first-scene``). ``--init CKPT`` starts every run from a checkpoint's weights (same
architecture, config and rotation frame) instead of a new network: more data for a trained model.
``--split-objects IDS`` draws the split over several objects (the scenes split of ``refiner-rt train`` on them) and
studies the object's part of it, to compare with such a model on the same test scenes. ``--table JSON`` prints
the table of a written result again; ``--table A.json B.json ...`` (one object each) prints one table of all of
them with the mean over the objects;
files of different studies (architecture, config, rotation frame, split) get a table each and a table comparing
them object by object, and ``--plot PNG`` draws that comparison (per-object mean and standard deviation).
``--iterations N`` also measures each model after 2..N refinement passes (the same test crops and coarse poses);
``--save DIR`` keeps each run's model as a checkpoint that ``refiner-rt eval`` and ``refiner-rt export`` take.
The checkpoint is written before the test split is scored; ``--resume`` scores a checkpoint that ``--save`` already
holds instead of training that run again (a run killed while scoring loses only the scoring).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.data.augment import PHOTOMETRIC_OPS
from models.evaluate.record import provenance, write_json
from models.train.recipe import RecipeError, add_recipe_argument, load_recipe, recipe_from_arguments

# The study's training options: flag -> (argparse dest, TrainRecipe field, help when the study's meaning needs its
# own words, else None: the field's). Their defaults are the named recipe "data-scaling"; each run's recipe is that
# recipe with the run's images and augmentations (see ``run``).
RECIPE_ARGUMENTS = {
    "--data": ("data", "data", "rendered or real dataset (BOP or YCB-Video layout)"),
    "--samples": ("samples", "samples", "training samples drawn by every run"),
    "--epoch-samples": ("epoch_samples", "epoch_samples", "samples per epoch at most (validation after each)"),
    "--val": ("val", "val_per_object", "validation crops"),
    "--test": ("test", "test_per_object", "test crops"),
    "--arch": ("arch", "arch", None),
    "--config": ("config", "arch_config", "JSON object of architecture config overrides, e.g. '{\"fuse_width\": 1024}'"),
    "--lr": ("lr", "lr", "peak learning rate of the cosine schedule"),
    "--noise": ("noise", "noise", "training coarse-pose noise (uniform:0:30, normal:10:5, or twist:0:30 about the "
                                  "object's z axis); the test crops always get uniform:0:30"),
    "--rotation-frame": ("rotation_frame", "rotation_frame", None),
    "--seed": ("seed", "seed", None),
    "--bf16": ("bf16", "bf16", None),
    "--ema": ("ema", "ema", None),
    "--inplane": ("inplane", "inplane", None),
    "--weight-decay": ("weight_decay", "weight_decay", None),
    "--split-seed": ("split_seed", "split_seed", None),
    "--split-objects": ("split_objects", "split_objects",
                        "draw the split over these objects (comma-separated, or 'paper' for the paper's nine; they "
                        "must include --object) and train and test --object on its part of it: the scenes split of "
                        "`refiner-rt train` on those objects, for a comparison on the same test scenes (default: "
                        "the split of --object alone)"),
    "--extra-train": ("extra_train", "extra_train", None),
    "--init": ("init", "init", "start each run from this checkpoint's weights (the same --arch, --config, "
                               "--rotation-frame and split of --data) instead of a new network"),
    **{f"--aug-{op.replace('_', '-')}": (f"aug_{op}", f"aug_{op}", None) for op in PHOTOMETRIC_OPS},
    "--cache": ("cache", "cache_root", "crop cache folder (default: DATA/.crops)"),
    "--threads": ("threads", "threads", None),
}


def study_recipe(args, mode: str, base_per_object: int):
    """The recipe of the study's runs in one split mode (before each run's augmentations): the parsed options over
    the named recipe "data-scaling", one object, ``base_per_object`` training images per object."""
    fields_by_dest = {dest: name for dest, name, _ in RECIPE_ARGUMENTS.values()}
    return recipe_from_arguments(args, fields_by_dest, args.recipe, objects=[args.object], split_mode=mode,
                                 base_per_object=base_per_object, per_object=0, name="data-scaling")


def _parse_sizes(text: str, flag: str = "--sizes") -> list[int]:
    try:
        sizes = sorted({int(s) for s in text.split(",") if s.strip()})
    except ValueError:
        raise SystemExit(f"{flag}: expected comma-separated integers like 1000,3000; got {text!r}") from None
    if not sizes or sizes[0] <= 0:
        raise SystemExit(f"{flag}: expected positive integers; got {text!r}")
    return sizes


def _parse_train_scenes(text: str) -> list[int | str]:
    """``--train-scenes``: scene counts, or ``all`` (every training scene of the split and of ``--extra-train``)."""
    return ["all"] if text.strip() == "all" else _parse_sizes(text, "--train-scenes")


def _parse_probabilities(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected probabilities like 0.5 or 0.5,1; got {text!r}") from None
    if not values or not all(0 < v <= 1 for v in values):
        raise argparse.ArgumentTypeError(f"expected probabilities in (0, 1], comma-separated; got {text!r}")
    return values


def _augment_label(row: dict) -> str:
    extra = [f"{name} {row[key]:g}" for key, name in
             (("background", "background"), ("occlude", "occluders"), ("relight", "relight")) if row.get(key)]
    extra += ["photometric"] if row.get("photometric") else []  # models.data.augment, the --aug-* probabilities
    if not extra:
        return "yes" if row["augment"] else "no"
    return " + ".join((["jitter"] if row["augment"] else []) + extra)


def checkpoint_path(args, row: dict, n: int, train_scenes) -> Path:
    """Where ``--save`` keeps a run's checkpoint: named by the object, mode, training crops (and scenes) and
    augmentation, so a rerun of the same command finds it (``--resume``)."""
    slug = re.sub(r"[^A-Za-z0-9.]+", "-", _augment_label(row))
    scenes_tag = f"_s{train_scenes}" if train_scenes else ""
    return args.save / f"{args.object}_{row['mode']}_n{n}{scenes_tag}_{slug}.pt"


def resumed_checkpoint(path: Path, obj: str, n: int, train_config: dict):
    """The model and info of a checkpoint this command saved earlier, checked to be this run's: the same object,
    training crops and training configuration (a run killed while scoring resumes at the scoring)."""
    import models

    model, info = models.load_checkpoint(path)
    saved = info.get("train_config")
    saved = json.loads(saved) if isinstance(saved, str) else json.loads(json.dumps(saved))
    found = {"objects": info.get("objects"), "train_crops": info.get("train_crops"),
             "train_config": saved}
    wanted = {"objects": [obj], "train_crops": n, "train_config": json.loads(json.dumps(train_config))}
    for key in wanted:
        if found[key] != wanted[key]:
            raise SystemExit(f"--resume: {path} was not saved by this run: its {key} is {found[key]!r}, this run's is "
                             f"{wanted[key]!r}; remove it or drop --resume")
    return model, info


def _wall(row: dict) -> str:
    return "training time not recorded (resumed)" if row.get("wall_s") is None else f"{row['wall_s']:.0f} s"


def _crops_label(row: dict) -> str:
    """A row's training crops, and the training scenes they came from when the run took whole scenes."""
    crops = str(row["train_crops"])
    return f"{crops} from {row['train_scenes']} scenes" if row.get("train_scenes") else crops


def _passes(rows: list[dict]) -> list[str]:
    """The numbers of refinement passes beyond one that every row measured (``--iterations``), ascending."""
    common = set.intersection(*(set(r.get("iterations", {})) for r in rows)) if rows else set()
    return sorted(common, key=int)


def _passes_cell(row: dict) -> str:
    return ", ".join(f"{k}: {v['mean_deg']:.2f}" for k, v in sorted(row.get("iterations", {}).items(),
                                                                     key=lambda kv: int(kv[0]))) or "-"


@dataclass(frozen=True)
class Run:
    """One training run of a split: its training crops and augmentations."""

    index: np.ndarray  # indices into the split's training crops
    train_scenes: int | None  # the number of whole training scenes they come from (--train-scenes), else None
    augment: bool
    background: float
    occlude: float
    relight: float


def _runs(args, mode: str, train_all, sizes: list[int], augment_sizes: list[int]) -> list[Run]:
    """The runs of one split.

    Without ``--train-scenes`` a run takes the first N crops of a seeded permutation of the training part (plain
    runs at each ``--sizes``, augmented ones at each ``--augment-sizes``); with it, every crop of the first S
    training scenes of a seeded permutation of the scenes, for every kind of run.
    """
    plain = [] if args.skip_plain else [(False, 0.0, 0.0, 0.0)]
    augmented = [(True, 0.0, 0.0, args.relight)] if args.augment and not args.skip_jitter else []
    augmented += [(args.augment, p, 0.0, args.relight) for p in args.background]
    augmented += [(args.augment, 0.0, p, args.relight) for p in args.occlude]
    runs = []
    if args.train_scenes:
        # More scenes, not more crops of the same scenes; the split (made with the one --sizes) and the test
        # crops stay the same.
        scene_ids = train_all.scene_ids.astype(str)
        scene_order = np.random.default_rng(args.seed).permutation(np.unique(scene_ids))
        for s in args.train_scenes:
            s = len(scene_order) if s == "all" else s
            if s > len(scene_order):
                print(f"{mode}: only {len(scene_order)} training scenes, skipping --train-scenes {s}", file=sys.stderr)
                continue
            index = np.flatnonzero(np.isin(scene_ids, scene_order[:s]))
            runs += [Run(index, s, *kind) for kind in plain + augmented]
        return runs
    order = np.random.default_rng(args.seed).permutation(len(train_all))
    for n, kinds in [(n, plain) for n in sizes] + [(n, augmented) for n in augment_sizes]:
        if not kinds:
            continue
        if n > len(train_all):
            if n != sizes[-1]:
                print(f"{mode}: only {len(train_all)} training crops, skipping size {n}", file=sys.stderr)
                continue
            # The largest size made the split, which already scaled down to what the object has: train on all of
            # it (the row records the real number of crops) rather than lose the run.
            print(f"{mode}: only {len(train_all)} training crops for size {n}; training on all of them",
                  file=sys.stderr)
            n = len(train_all)
        runs += [Run(np.sort(order[:n]), None, *kind) for kind in kinds]
    return runs


def _initial_model(args, spec, config: dict):
    """The ``--init`` checkpoint's network, refused unless it is the study's network on the same split (or the same
    network but for the fusion network's ``roll``, which changes no weight).

    Its own training crops may be any of the study's training crops, but none of its validation or test crops: the
    checkpoint's recorded split must be ``spec``'s without the extra training folders. ``config``: the study's
    network's full config.
    """
    import models
    from models.data.pipeline import checkpoint_spec

    model, info = models.load_checkpoint(args.init)
    if model.arch == args.arch:
        from models.nets.fusion import with_roll

        model = with_roll(model, config)  # the same weights with another input turn may go on
    if model.arch != args.arch or model.config != config:
        raise SystemExit(f"--init {args.init}: a {model.arch} network with config {json.dumps(model.config)}; the study "
                         f"trains --arch {args.arch} --config {json.dumps(args.config)}")
    if info.get("rotation_frame", "camera") != args.rotation_frame:
        raise SystemExit(f"--init {args.init}: trained in the {info.get('rotation_frame', 'camera')} rotation frame; the "
                         f"study uses --rotation-frame {args.rotation_frame}")
    try:
        recorded = checkpoint_spec(info)
    except ValueError as exc:
        raise SystemExit(f"--init {args.init}: {exc}") from None
    mine, theirs = spec.held_out().as_dict(), recorded.held_out().as_dict()
    theirs_name, mine_name = Path(str(theirs.get("data"))).name, Path(str(mine.get("data"))).name
    if theirs_name != mine_name:
        # Trained on another set: the rule below has nothing to compare. What matters then is that it never trained
        # on this set's test scenes, which the checkpoint cannot show (a copy of its set under another name would
        # pass any name check): the caller says so with --init-other-set, e.g. for a set grown with `render
        # --first-scene` (the scenes after the other set's).
        if not args.init_other_set:
            raise SystemExit(f"--init {args.init}: trained on the set {theirs_name!r}, not on {mine_name!r}, so its "
                             "training scenes may be this set's test scenes; if this set's scenes are new to it (a set "
                             "grown with `refiner-rt render --first-scene`), pass --init-other-set")
        print(f"--init {args.init}: trained on the set {theirs_name!r}, not on {mine_name!r} (--init-other-set: "
              "this set's scenes are new to it)", file=sys.stderr)
        return model.train()
    # The same set: by its folder's name, as a shipped model records it (no build machine's folder), the rest exactly.
    mine, theirs = {**mine, "data": mine_name}, {**theirs, "data": theirs_name}
    differ = [k for k in sorted(set(mine) | set(theirs)) if mine.get(k) != theirs.get(k)]
    if differ:
        raise SystemExit(f"--init {args.init}: trained on another split ({', '.join(f'{k} {theirs.get(k)!r}' for k in differ)}"
                         f"; here {', '.join(repr(mine.get(k)) for k in differ)}), so its validation or test crops may be "
                         "in this study's training crops")
    return model.train()


def run(args) -> dict:
    import torch

    import models
    from models.evaluate.errors import evaluate_errors, torch_predictor
    from models.data.pipeline import cropset_for, load_splits
    from models.train.recipe import check_masks
    from models.train.loop import set_threads, train_refiner

    try:  # the training options' ranges and rules, checked by the recipe before any crops are cut
        study_recipe(args, args.modes.split(",")[0], _parse_sizes(args.sizes)[-1])
    except RecipeError as exc:
        raise SystemExit(str(exc)) from None
    threads = set_threads(args.threads)
    sizes = _parse_sizes(args.sizes)
    augment_sizes = args.augment_sizes or [sizes[-1]]
    try:
        probe = models.build_refiner(args.arch, **args.config)
    except ValueError as exc:
        raise SystemExit(f"--arch {args.arch} --config {json.dumps(args.config)}: {exc}") from None
    size, context = probe.input_size, probe.config["crop_context"]
    rows = []
    t_all = time.perf_counter()
    for mode in args.modes.split(","):
        recipe = study_recipe(args, mode, sizes[-1])
        spec = recipe.data_spec()
        try:
            splits = load_splits(spec)
        except ValueError as exc:
            raise SystemExit(f"{mode} split: {exc}") from None
        parts = {p: cropset_for(splits, p, spec, size, context, cache_root=args.cache, progress=not args.quiet,
                                crop_filter=probe.config["crop_filter"])
                 for p in ("train_base", "val", "test")}
        train_all, val, test = parts["train_base"], parts["val"], parts["test"]
        try:
            check_masks(max(args.background, default=0.0), max(args.occlude, default=0.0),
                        train_all.masks is not None, str(args.data))
        except RecipeError as exc:
            raise SystemExit(str(exc)) from None
        scenes = {p: len(set(parts[p].scene_ids.tolist())) for p in parts}
        for r in _runs(args, mode, train_all, sizes, augment_sizes):
            n = len(r.index)
            train = train_all.subset(r.index)
            run_recipe = recipe.merged(augment=r.augment, background=r.background, occlude=r.occlude,
                                       relight=r.relight)
            cfg = run_recipe.stage_config("base", n)
            epochs = cfg.epochs
            row = {"mode": mode, "train_crops": n, **({"train_scenes": r.train_scenes} if r.train_scenes else {}),
                   **({"init": str(args.init)} if args.init else {}),
                   "augment": r.augment, "background": r.background, "occlude": r.occlude,
                   **({"relight": r.relight} if r.relight else {}),
                   **({"photometric": cfg.photometric} if cfg.photometric else {}), "epochs": epochs,
                   "samples": epochs * cfg.max_steps_per_epoch * cfg.batch_size}
            path = checkpoint_path(args, row, n, r.train_scenes) if args.save else None
            if args.resume and path.is_file():
                model, info = resumed_checkpoint(path, args.object, n, vars(cfg))
                row.update(best_epoch=info["best_epoch"], val_mean_deg=info["val_mean_deg"], scenes=scenes,
                           wall_s=info.get("wall_s"), resumed=True)
                print(f"--resume: scoring the checkpoint {path} (not trained again)", file=sys.stderr)
            else:
                torch.manual_seed(args.seed)
                model = (_initial_model(args, spec, probe.config) if args.init
                         else models.build_refiner(args.arch, **args.config))
                t0 = time.perf_counter()
                res = train_refiner(model, train, val, cfg, progress=not args.quiet, desc=f"{mode} n={n}")
                model, wall = res.model, round(time.perf_counter() - t0, 1)
                row.update(best_epoch=res.best_epoch, val_mean_deg=res.best_val_deg, scenes=scenes, wall_s=wall)
                # Saved before the test split is scored: hours of training must not hang on the evaluation after it.
                if path is not None:
                    models.save_checkpoint(model, path, objects=[args.object], stage="data_scaling",
                                           train_config=vars(cfg), best_epoch=res.best_epoch,
                                           val_mean_deg=res.best_val_deg, train_noise=cfg.noise,
                                           rotation_frame=args.rotation_frame, data=spec.as_dict(),
                                           split=splits.summary(), train_crops=n, wall_s=wall,
                                           **({"init": str(args.init)} if args.init else {}),
                                           **({"train_scene_ids": sorted(set(train.scene_ids.astype(str).tolist()))}
                                              if r.train_scenes else {}))
            if path is not None:
                row["checkpoint"] = str(path)
            predictor = torch_predictor(model.eval())
            errors = evaluate_errors(predictor, test, rotation_frame=args.rotation_frame)
            pooled = errors.summary()["pooled"]
            tail = ("scenes", "wall_s", "resumed", "checkpoint")
            row = {**{k: v for k, v in row.items() if k not in tail}, **pooled, **{k: row[k] for k in tail if k in row}}
            if args.iterations > 1:
                # The same test crops and coarse poses, refined again from each pass's output (RefinerSession's
                # ``iterations``); one pass is the row's own error.
                row["iterations"] = {
                    str(k): evaluate_errors(predictor, test, iterations=k,
                                            rotation_frame=args.rotation_frame).summary()["pooled"]
                    for k in range(2, args.iterations + 1)}
            rows.append(row)
            scenes_note = f" scenes={r.train_scenes}" if r.train_scenes else ""
            print(f"{mode:6s} n={n:6d}{scenes_note} augment={r.augment!s:5s} background={r.background:.2f} "
                  f"occlude={r.occlude:.2f}{f' relight={r.relight:.2f}' if r.relight else ''}"
                  f"{' photometric' if cfg.photometric else ''}: "
                  f"test {row['mean_deg']:.2f} deg "
                  f"(median {row['median_deg']:.2f}, input {row['input_mean_deg']:.2f}), val {row['val_mean_deg']:.2f}, "
                  f"{_wall(row)}", file=sys.stderr)
    return {
        "study": "held-out error vs training crops, frames and scenes splits",
        "object": args.object, "arch": args.arch, "config": args.config,
        **({"split_objects": args.split_objects} if args.split_objects else {}),
        "parameters": sum(p.numel() for p in probe.parameters()), "rotation_frame": args.rotation_frame, "lr": args.lr,
        "lr_schedule": "cosine", **({"bf16": True} if args.bf16 else {}),
        **({"ema": args.ema} if args.ema else {}), **({"inplane_deg": args.inplane} if args.inplane else {}),
        **({"adamw_weight_decay": args.weight_decay} if args.weight_decay else {}),
        "test_noise": "uniform:0:30", "rows": rows,
        **provenance("benchmarks.data_scaling", args.argv, threads),
        "wall_s": round(time.perf_counter() - t_all, 1),
    }


def _net_label(doc: dict, default: str = "") -> str:
    """The network of a result file: its architecture and config overrides (``default`` when it has none)."""
    return doc["arch"] + (f" {json.dumps(doc['config'])}" if doc.get("config") else default)


def markdown(doc: dict) -> str:
    arch = _net_label(doc)
    if "parameters" in doc:
        arch += f", {doc['parameters'] / 1e6:.1f} M parameters"
    lines = [f"{doc['object']}, {arch} ({doc['rotation_frame']} frame), same number of samples per run:", "",
             "| split | training crops | augment | test mean (deg) | median | under 5 deg | input mean | best epoch | "
             "train/val/test scenes |",
             "|---|---:|---|---:|---:|---:|---:|---:|---|"]
    more = any("iterations" in r for r in doc["rows"])
    if more:  # a column of the means after more passes (--iterations)
        lines[2] += " mean after more passes (passes: deg) |"
        lines[3] += "---|"
    for r in doc["rows"]:
        s = r["scenes"]
        lines.append(f"| {r['mode']} | {_crops_label(r)} | {_augment_label(r)} | {r['mean_deg']:.2f} | "
                     f"{r['median_deg']:.2f} | {100 * r['under_5_deg']:.0f}% | {r['input_mean_deg']:.2f} | "
                     f"{r['best_epoch']} of {r['epochs']} | {s['train_base']}/{s['val']}/{s['test']} |"
                     + (f" {_passes_cell(r)} |" if more else ""))
    return "\n".join(lines)


def _study_key(doc: dict) -> tuple:
    """What makes two result files one study: the network, its config, the rotation frame and the split's objects."""
    return (doc["arch"], json.dumps(doc.get("config", {}), sort_keys=True), doc["rotation_frame"],
            ",".join(doc.get("split_objects") or []))


def markdown_objects(docs: list[dict]) -> str:
    """One table of several objects' results (one written ``--json`` each), with the mean over the objects.

    A mean is printed for each (split, training crops, augmentation, samples) that every object has; the files must
    share the architecture, its config, the rotation frame and the split's objects, or the mean would mix different
    networks or test crops (:func:`markdown_studies` takes files of several studies).
    """
    keys = {_study_key(d) for d in docs}
    if len(keys) != 1:
        raise SystemExit(f"--table: the files are of different studies (arch, config, rotation frame, split objects): "
                         f"{sorted(keys)}")
    arch = _net_label(docs[0])
    n_objects = len({d["object"] for d in docs})  # files of one object (other runs of it) count once
    lines = [f"{n_objects} object{'s' if n_objects > 1 else ''}, {arch} ({docs[0]['rotation_frame']} frame):", "",
             "| object | split | training crops | augment | samples | test mean (deg) | median | under 5 deg | "
             "input mean | test crops |",
             "|---|---|---:|---|---:|---:|---:|---:|---:|---:|"]
    groups: dict[tuple, list[dict]] = {}
    more = any("iterations" in r for d in docs for r in d["rows"])
    if more:  # a column of the means after more passes (--iterations)
        lines[2] += " mean after more passes (passes: deg) |"
        lines[3] += "---|"
    for d in docs:
        for r in d["rows"]:
            key = (r["mode"], _crops_label(r), _augment_label(r), r["samples"])
            groups.setdefault(key, []).append(r)
            lines.append(f"| {d['object']} | {r['mode']} | {key[1]} | {key[2]} | {r['samples']} | "
                         f"{r['mean_deg']:.2f} | {r['median_deg']:.2f} | {100 * r['under_5_deg']:.0f}% | "
                         f"{r['input_mean_deg']:.2f} | {r['n']} |" + (f" {_passes_cell(r)} |" if more else ""))
    for (mode, crops, label, samples), rows in groups.items():
        if len(rows) == len(docs):
            mean = lambda k: sum(r[k] for r in rows) / len(rows)  # noqa: E731
            passes = ", ".join(f"{k}: **{sum(r['iterations'][k]['mean_deg'] for r in rows) / len(rows):.2f}**"
                               for k in _passes(rows)) or "-"
            lines.append(f"| **mean of {len(rows)}** | {mode} | {crops} | {label} | {samples} | "
                         f"**{mean('mean_deg'):.2f}** | {mean('median_deg'):.2f} | "
                         f"{100 * mean('under_5_deg'):.0f}% | {mean('input_mean_deg'):.2f} | "
                         f"{sum(r['n'] for r in rows)} |" + (f" {passes} |" if more else ""))
    return "\n".join(lines)


def comparison_series(docs: list[dict]) -> dict[str, dict[str, dict]]:
    """The rows of several result files as series to compare: ``{label: {object: row}}``.

    A series is one (study, split, training crops, augmentation, samples); its label names only what differs between
    the series, so a table or plot of two networks on the same data reads "fusion (default config)" against
    "fusion {...}". Two rows of one object in one series are refused: they could not be told apart.
    """
    parts: list[tuple[tuple, str, dict]] = []
    for d in docs:
        net = _net_label(d, default=" (default config)")
        split = f"split over {len(d['split_objects'])} objects" if d.get("split_objects") else "own split"
        for r in d["rows"]:
            fields = (net, f"{d['rotation_frame']} frame", split, r["mode"], f"{_crops_label(r)} crops",
                      _augment_label(r), f"{r['samples']} samples")
            parts.append((fields, d["object"], r))
    varying = [i for i in range(7) if len({f[i] for f, _, _ in parts}) > 1]
    series: dict[str, dict[str, dict]] = {}
    for fields, obj, row in parts:
        label = ", ".join(fields[i] for i in varying) or fields[0]
        if obj in series.setdefault(label, {}):
            raise SystemExit(f"--table: two results for {obj} in the series {label!r}; pass one file per object "
                             "and study")
        series[label][obj] = row
    return series


def markdown_studies(docs: list[dict]) -> str:
    """Files of several studies: a table per study (:func:`markdown_objects`), then one comparing them per object.

    The comparison's mean row is over the objects every series has, so each column's mean is over the same objects.
    """
    groups: dict[tuple, list[dict]] = {}
    for d in docs:
        groups.setdefault(_study_key(d), []).append(d)
    tables = [markdown_objects(g) if len(g) > 1 else markdown(g[0]) for g in groups.values()]
    series = comparison_series(docs)
    objects = sorted({o for rows in series.values() for o in rows})
    common = [o for o in objects if all(o in rows for rows in series.values())]
    lines = ["Test mean (deg) per object:", "", "| object | " + " | ".join(series) + " |",
             "|---|" + "---:|" * len(series)]
    for o in objects:
        cells = [f"{rows[o]['mean_deg']:.2f}" if o in rows else "-" for rows in series.values()]
        lines.append(f"| {o} | " + " | ".join(cells) + " |")
    if common:
        means = [sum(rows[o]["mean_deg"] for o in common) / len(common) for rows in series.values()]
        lines.append(f"| **mean of {len(common)}** | " + " | ".join(f"**{m:.2f}**" for m in means) + " |")
    return "\n\n".join([*tables, "\n".join(lines)])


def plot_comparison(docs: list[dict], path: Path) -> None:
    """Per-object test mean with the standard deviation as error bars, one bar per series (like the paper's figures)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series = comparison_series(docs)
    objects = sorted({o for rows in series.values() for o in rows})
    x = np.arange(len(objects))
    width = 0.8 / len(series)
    fig, ax = plt.subplots(figsize=(max(6, 0.9 * len(objects) + 2), 4))
    for k, (label, rows) in enumerate(series.items()):
        means = [rows[o]["mean_deg"] if o in rows else np.nan for o in objects]
        stds = [rows[o]["std_deg"] if o in rows else 0.0 for o in objects]
        ax.bar(x + (k - (len(series) - 1) / 2) * width, means, width, yerr=stds, capsize=3, label=label)
    ax.set_xticks(x, objects, rotation=30, ha="right", fontsize=8)
    ax.set(ylabel="geodesic error (deg), mean ± std", title="held-out error per object")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))  # beside the axes, never over a bar
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def build_parser(base=None) -> argparse.ArgumentParser:
    """The command's options; the training ones default to ``base`` (the named recipe "data-scaling")."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    base = base or load_recipe("data-scaling")
    for flag, (dest, name, help_text) in RECIPE_ARGUMENTS.items():
        add_recipe_argument(p, flag, name, base, dest=dest, help=help_text)
    p.add_argument("--table", type=Path, nargs="+", metavar="JSON",
                   help="print the Markdown table of a written --json and exit; with several files (one object "
                        "each), one table of all of them with the mean over the objects; files of several "
                        "studies (arch, config, frame, split objects) get a table each and a comparison table")
    p.add_argument("--plot", type=Path, metavar="PNG",
                   help="with --table: draw the per-object comparison of the files (mean and standard deviation)")
    p.add_argument("--object", default="003_cracker_box", help="YCB id of the object to study")
    p.add_argument("--sizes", default="1000,3000,10000", help="training crops per run, comma-separated")
    p.add_argument("--modes", default="frames,scenes", help="split protocols, comma-separated")
    p.add_argument("--augment", action="store_true",
                   help="add a run with colour and box jitter at the largest size (or at each --augment-sizes)")
    p.add_argument("--background", type=_parse_probabilities, default=[], metavar="P[,P...]",
                   help="add a run per probability of background replacement at the largest size (or at each "
                        "--augment-sizes; with the jitter of --augment when given); needs instance masks in the "
                        "dataset (BOP mask_visib/)")
    p.add_argument("--occlude", type=_parse_probabilities, default=[], metavar="P[,P...]",
                   help="add a run per probability of pasting another crop's object over a crop at the largest size "
                        "(or at each --augment-sizes; with the jitter of --augment when given); needs instance masks")
    p.add_argument("--relight", type=float, default=0.0, metavar="P",
                   help="with probability P, give a crop of every augmented run (--augment, --background, --occlude) "
                        "another scene's light and camera: a smooth shading field, light colour, gamma, blur and "
                        "sensor noise")
    p.add_argument("--augment-sizes", type=lambda t: _parse_sizes(t, "--augment-sizes"), metavar="N[,N...]",
                   help="training crops of the --augment/--background/--occlude runs (default: the largest of --sizes;"
                        " each at most that, since the split is made with it)")
    p.add_argument("--train-scenes", type=_parse_train_scenes, metavar="S[,S...]|all",
                   help="train each run on every crop of the first S training scenes (a seeded permutation of the "
                        "split's training scenes) instead of the first N crops: more scenes against fewer, on one "
                        "split made with the one --sizes; 'all': every training scene (with --extra-train, theirs "
                        "too)")
    p.add_argument("--skip-plain", action="store_true",
                   help="skip the runs without augmentation (one per size), e.g. when an earlier result has them")
    p.add_argument("--skip-jitter", action="store_true",
                   help="skip the run with --augment's jitter alone (keep the jitter in the --background/--occlude "
                        "runs)")
    p.add_argument("--iterations", type=int, default=1, metavar="N",
                   help="also measure the test error after 2..N refinement passes (default: one pass only)")
    p.add_argument("--init-other-set", action="store_true",
                   help="accept an --init checkpoint trained on another dataset folder: you vouch that none of "
                        "--data's scenes were in its training (e.g. --data grown with render --first-scene)")
    p.add_argument("--save", type=Path, metavar="DIR",
                   help="write each run's model here as a checkpoint (`refiner-rt eval` and `export` take it)")
    p.add_argument("--resume", action="store_true",
                   help="score a run's checkpoint that --save already holds instead of training it again (e.g. "
                        "after a run killed while scoring); it must be this command's run (object, crops, "
                        "configuration)")
    p.add_argument("--json", type=Path, help="write the rows and the command here")
    p.add_argument("--quiet", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    base = load_recipe("data-scaling")
    p = build_parser(base)
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    args.recipe = base
    if args.plot and not args.table:
        p.error("--plot draws the results of --table JSON ...: give the files to compare with --table")
    if args.table:
        docs = [json.loads(t.read_text()) for t in args.table]
        if len({_study_key(d) for d in docs}) > 1:
            print(markdown_studies(docs))
        else:
            print(markdown(docs[0]) if len(docs) == 1 else markdown_objects(docs))
        if args.plot:
            plot_comparison(docs, args.plot)
            print(f"\nwrote {args.plot}")
        return 0
    if args.data is None:
        p.error("--data is required (or --table JSON)")
    for folder in args.extra_train or []:
        if not folder.is_dir():
            p.error(f"--extra-train: not a folder: {folder}")
    if args.init and not args.init.is_file():
        p.error(f"--init: checkpoint not found: {args.init}")
    if args.init_other_set and not args.init:
        p.error("--init-other-set needs --init CKPT")
    if args.iterations < 1:
        p.error(f"--iterations: expected a number of refinement passes >= 1; got {args.iterations}")
    if args.resume and not args.save:
        p.error("--resume needs --save DIR (the folder that holds the checkpoints)")
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
    if args.split_objects and args.object not in args.split_objects:
        p.error(f"--split-objects must include --object {args.object}; got {','.join(args.split_objects)}")
    if args.skip_jitter and not (args.augment and (args.background or args.occlude)):
        p.error("--skip-jitter needs --augment with --background or --occlude (it skips the run with jitter alone)")
    if args.skip_plain and not (args.augment or args.background or args.occlude):
        p.error("--skip-plain leaves no run: add --augment, --background or --occlude")
    if not 0.0 <= args.relight <= 1.0:
        p.error(f"--relight: expected a probability in [0, 1]; got {args.relight}")
    if args.relight and not (args.augment or args.background or args.occlude):
        p.error("--relight applies to the augmented runs: add --augment, --background or --occlude")
    if args.augment_sizes and max(args.augment_sizes) > max(_parse_sizes(args.sizes)):
        p.error(f"--augment-sizes: each must be at most the largest --sizes ({max(_parse_sizes(args.sizes))}), "
                f"which makes the split; got {max(args.augment_sizes)}")
    if args.train_scenes and (len(_parse_sizes(args.sizes)) > 1 or args.augment_sizes):
        p.error(f"--train-scenes takes the runs' crops from whole scenes: give one --sizes (the split's training "
                f"crops) and no --augment-sizes; got --sizes {args.sizes}")
    for m in args.modes.split(","):
        if m not in ("frames", "scenes"):
            p.error(f"--modes: expected frames and/or scenes; got {m!r}")
    doc = run(args)
    print(markdown(doc))
    if args.json:
        write_json(args.json, doc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
