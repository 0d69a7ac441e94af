"""Build the coarse refiners that ship in ``refiner_rt/weights/``: train, export, evaluate on held-out scenes, write
the card.

One complete, rerunnable command per shipped model (the way torchvision's ``references/`` hold one per weight; the
commands of every version are in ``export/release/README.md``). Each object is one chunk: it is trained through the
training API (:func:`models.run_training` with :func:`shipped_recipe`, the named recipe :data:`RECIPE_NAME` on that
object), exported to fp32 and INT8 ONNX (parity-checked), evaluated through the runtime on the scenes held out from
its training, stamped with its model-card metadata and copied into the package; the card and the documents' tables
are then regenerated and the files to commit are listed (committing is yours). A rerun skips the objects already
shipped as this model version, so an interrupted build resumes at the object it was on, and that object's training
at its last finished epoch (the training state in ``RUN/<id>/model.state/``, taken only with the recipe it began
with).

    python -m export.release.coarse build --data data/ycb9_robot --extra-train data/ycb9_tabletop_s32_next \\
        --run runs/v6 --cache CACHE --objects ... --heldout data/ycb9_fresh_s21 --calibration data/ycb9_calib_s22 \\
        --real REAL                                              # version 6 (each object's real-frame column too)
    python -m export.release.coarse speed                        # INT8/fp32 speed of every shipped model
    python -m export.release.coarse card                         # models.json and MODELS.md from the JSON
    python -m export.release.coarse requantize --data data/ycb9_v1 --run runs/v1   # INT8 again from the shipped fp32
    python -m export.release.coarse requantize --heldout data/ycb9_fresh_s21 --calibration data/ycb9_calib_s22
                                                                 # the same without checkpoints (the shipped files)

INT8 scheme: each object's INT8 model is quantised with every scheme of :data:`INT8_SCHEMES_FASTEST_FIRST` and
evaluated beside fp32 on held-out crops; the fastest whose mean error stays within :data:`MAX_INT8_COST_DEG` of
fp32's ships (the scheme is in the model's metadata ``quantization``), or, when none does, the one that costs least.
Static schemes are calibrated on crops the scoring never sees: the object's training crops (``build``, ``requantize
--data/--run``) or a second folder of fresh scenes (``requantize --calibration``). ``requantize`` redoes this from the
shipped fp32 files (no training), e.g. after a faster scheme was added.

Errors are measured on rendered images (``refiner-rt render``), instances with BOP ``visib_fract >= 0.3`` (the
silhouette beyond the image border counted), coarse inputs U(0, 30) degrees around the truth, one network pass: by
``build`` (and ``requantize --data/--run``) on scenes held out whole from the training set (``scenes`` split drawn
over the nine objects, so every object's test scenes are the same); by ``requantize --heldout`` on every instance of
a folder of scenes rendered with another seed, which then becomes the card's evaluation (the training split's is
kept as ``eval_training_split``).
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from export.release.card import (MAX_INT8_COST_DEG, MAX_MEAN_INT8_COST_DEG, RESULTS_DIR, ROOT, SCHEMA, load_results,
                                 metadata_props, portable_command, publish, stamp, write_card)
from models.data.objects import PAPER_OBJECTS, SCAN_FRAME_SYMMETRIES, object_names
from models.data.pipeline import whole_folder_spec
from models.evaluate.real import DEFAULT_JSON as REAL_JSON
from models.evaluate.record import git_commit, machine
from models.train.recipe import NAMED_RECIPES, TrainRecipe, load_recipe
from refiner_rt.metadata import file_sha256
from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name

MESHES_DIR = ROOT / "models" / "data" / "ycb_models"
OBJECT_FRAME = ("YCB google_16k scan frame (models/data/ycb_models/<id>/textured.obj, metres, origin near the base); "
                "axes as the YCB-Video model frame's, origin offset per object (refiner_rt.frames)")

# The held-out-scenes recipe of the shipped models, as this build names its options: a view of the one definition,
# ``heldout-scenes-v3`` in models/train/recipe.py (v1, the best measured for unseen scenes in
# benchmarks/studies/heldout_scenes, "Five conv blocks on all nine objects", and benchmarks/studies/scene_count; v2 on
# a four times larger rendered set; v3, v4 and v5 continue each object's shipped model on new scenes). Model version 1
# was trained with heldout-scenes-v1 (3,500 crops per object from ycb9_v1's 2,362 scenes), version 2 with
# heldout-scenes-v2 (ycb9_v2's 10,000 scenes), version 3 with heldout-scenes-v3 from version 2 on ycb9_v3's 8,000 new
# scenes, version 4 with the same recipe from version 3 on ycb9_v4's 8,000 new scenes, every crop of ycb9_v3 joining
# the training part (``build --extra-train``), version 5 likewise from version 4 on ycb9_v5's 5,000 new scenes, every
# crop of ycb9_v3 and ycb9_v4 joining. Version 6 continues each version-5 model with ``robot-roll-v6`` (the same
# network with the canonical roll, the same rates, float32) on scenes of the robot layout (ycb9_robot: objects resting
# on every face, cameras where a robot's would be) with tabletop scenes joining (``build --extra-train
# ycb9_tabletop_s32_next``): benchmarks/studies/real_levers, "The views the training scenes lack". Version 7 continues
# each version-6 model with ``robot-appearance-v7`` (the per-crop input normalisation, 450,000 samples, the same sets),
# chosen in benchmarks/studies/appearance and shipped through its release gate ("Version 7 with the tabletop scenes");
# two earlier builds of it were held back there (60,000 samples; 450,000 samples without the tabletop scenes).
RECIPE_NAME = "robot-appearance-v7"
MODEL_VERSION = "7"
# Versions 3 to 5 start each object from the model that ships now (its fp32 file, turned back into a checkpoint by
# export.recover); the build refuses to start from a model of this same version (that would be training twice).
INIT_FROM_SHIPPED = True
_NAMED = NAMED_RECIPES[RECIPE_NAME]
RECIPE = {
    "name": RECIPE_NAME,
    "arch": _NAMED["arch"],
    "config": _NAMED["arch_config"],
    "rotation_frame": _NAMED["rotation_frame"],
    "lr": _NAMED["lr"],
    "augment": _NAMED["augment"],
    "background": _NAMED["background"],
    "split_mode": _NAMED["split_mode"],
    "split_objects": ",".join(_NAMED["split_objects"]),
    "val": _NAMED["val_per_object"],
    "test": _NAMED["test_per_object"],
    "seed": _NAMED["seed"],
    "bf16": _NAMED.get("bf16", False),
    "init_from_shipped": INIT_FROM_SHIPPED,
    "photometric": {k[len("aug_"):]: v for k, v in _NAMED.items() if k.startswith("aug_")},
    "inplane": _NAMED.get("inplane", 0.0),
}

# INT8 schemes in the order of their speed on the shipped architecture, fastest first (benchmarks/studies/int8_convs:
# full refine() path, batch 1, one thread, interleaved medians). With onnxruntime's QDQPropagationTransformer off
# (RefinerSession does that, refiner_rt.session.DISABLED_OPTIMIZERS) the conv scheme's first max-pool stays in fp32
# NCHWc and its integer convolutions run 2.5-3x faster than the fp32 ones on AVX-512 VNNI: 1.59x the dynamic
# scheme's refine() speed (results_vnni.json). With the transformer on, the uint8 max-pool it creates cost more than
# the integer convs saved (0.7-0.8x on an AVX2-only EPYC, results.json). Then the accuracy an INT8 model may give up.
INT8_SCHEMES_FASTEST_FIRST = ("static-qdq-int8-conv", "dynamic-int8")

# The shipped objects' symmetries (models.data.objects): the card's error stays the plain geodesic one; the
# symmetry-aware error (to the closest turn about the can's axis) is scored beside it, the inputs' too.
SYMMETRIES = SCAN_FRAME_SYMMETRIES


# Objects trained from scratch in two stages instead of from the shipped model: a first stage whose coarse inputs are
# turns about the object's own axis alone (models.data.noise twist), then the recipe's stage from that network. The can's
# networks trained on random-axis inputs never learnt the turn about its axis, though its label shows it: the refined
# turn was the input's (benchmarks/studies/can_twist); a first stage on turns teaches it. That made the can's version
# 5 ({"002_master_chef_can": {"noise": "twist:0:30", "lr": 1e-3, "samples": 200_000}}); version 6 continues it, as
# every other object, from the shipped model.
FIRST_STAGE: dict = {}


def shipped_recipe(data: Path, obj: str, samples: int, sizes: int, cache: Path, val: int | None = None,
                   test: int | None = None, init: Path | None = None, extra_train: list[Path] = (), *,
                   noise: str | None = None, lr: float | None = None, photometric: dict | None = None,
                   seed: int | None = None, inplane: float | None = None, roll: str | None = None) -> TrainRecipe:
    """The :class:`models.train.recipe.TrainRecipe` of ``obj``'s shipped model: the named recipe :data:`RECIPE_NAME`
    on one object, ``samples`` training samples on the split drawn with ``sizes`` training crops per object (every
    crop of the ``extra_train`` folders joining its training part), from ``init`` when given. ``noise``, ``lr``,
    ``photometric`` (``{operation: probability}``, models.data.augment), ``seed`` (the training run's, not the
    split's), ``inplane`` (the largest turn of a training crop about the viewing ray, degrees, 0: none) and ``roll``
    (the fusion network's input turn, ``"canonical"`` or ``"none"``) replace the recipe's.

    The options the shipped recipe leaves open are those of the named recipe ``data-scaling`` (its budget per epoch,
    schedule and validation), with which models up to version 6 were trained; the same run as
    :func:`data_scaling_command` (a test holds the two recipes equal). The plain loss for every object, as those
    models had (``symmetries`` turns a dataset's recorded symmetry off).
    """
    r = {**RECIPE, **({"val": val} if val else {}), **({"test": test} if test else {}), **({"lr": lr} if lr else {}),
         **({"seed": seed} if seed is not None else {})}
    aug = r["photometric"] if photometric is None else photometric
    inplane = r["inplane"] if inplane is None else inplane
    config = r["config"] if roll is None else {**r["config"], "roll": roll}
    return load_recipe("data-scaling").merged(
        name=r["name"], data=str(data), objects=[obj], split_mode=r["split_mode"], base_per_object=sizes, per_object=0,
        val_per_object=r["val"], test_per_object=r["test"], split_objects=_split_objects(r["split_objects"]),
        arch=r["arch"], arch_config=config, rotation_frame=r["rotation_frame"], lr=r["lr"],
        **({"noise": noise} if noise else {}), seed=r["seed"], augment=True, background=r["background"],
        **{f"aug_{op}": p for op, p in aug.items()}, inplane=inplane, samples=samples, cache_root=str(cache),
        threads=1, bf16=r["bf16"], device="cpu", init=None if init is None else str(init),
        extra_train=[str(f) for f in extra_train], symmetries={obj: {}},
    )


def _split_objects(text: str) -> list[str]:
    """``--split-objects`` as data_scaling's command line read it: ``paper`` is the paper's nine objects."""
    return list(PAPER_OBJECTS) if text.strip() == "paper" else object_names(text)


def train_shipped(recipe: TrainRecipe, save: Path, obj: str) -> tuple[Path, dict]:
    """``(checkpoint, record)``: ``recipe`` trained by :func:`models.run_training` into ``save/model.pt`` (reused when
    it exists; an interrupted training of the same recipe and starting weights resumes after its last finished epoch),
    and its record: training crops and scenes, samples, epochs, best epoch, validation error, wall time (a resumed
    run's: this process's, plus the earlier epochs' own),
    and the error on the split's test crops (inputs U(0, 30), one pass)."""
    import models
    from models.data.pipeline import checkpoint_test_set
    from models.evaluate.errors import evaluate_errors, torch_predictor
    from models.train.loop import set_threads

    ckpt = save / "model.pt"
    began = save / "model.building.json"  # the run's recipe and starting weights, from its start until it ends
    wall, resumed_at = None, None
    if not ckpt.is_file() or began.is_file():  # model.pt is written before a recipe's later stages: not done yet
        mine = json.dumps({"recipe": recipe.as_dict(), "starts_from": {
            k: file_sha256(Path(f)) if f and Path(f).is_file() else f for k, f in (
                ("init", recipe.init), ("base_ckpt", recipe.base_ckpt))}}, sort_keys=True, default=str)
        state, earlier = save / "model.state" / "base.pt", []  # earlier: the epochs an interrupted run finished
        if began.is_file() and began.read_text() == mine and state.is_file():
            import torch

            earlier = torch.load(state, map_location="cpu", weights_only=True)["history"]
            resumed_at = len(earlier)
        else:  # a new run, or another recipe or start than the interrupted one: none of its state is taken
            shutil.rmtree(save / "model.state", ignore_errors=True)
            (save / "model.log.jsonl").unlink(missing_ok=True)
        save.mkdir(parents=True, exist_ok=True)
        began.write_text(mine)
        print(f"[{obj}] training: recipe {recipe.name} ({recipe.samples:,} samples) -> {ckpt}"
              + (f" (resuming after epoch {resumed_at})" if resumed_at is not None else ""), flush=True)
        t0 = time.perf_counter()
        models.run_training(recipe, ckpt, resume=resumed_at is not None, progress=False,
                            echo=lambda m: print(f"[{obj}] {m}", flush=True))
        # a resumed run's earlier epochs by their own time (its interrupted process's set-up is not counted)
        wall = round(time.perf_counter() - t0 + sum(r["seconds"] for r in earlier), 1)
        began.unlink()
    set_threads(recipe.threads)
    net, info = models.load_checkpoint(ckpt)
    test, _ = checkpoint_test_set(net, info, cache_root=Path(recipe.cache_root) if recipe.cache_root else None)
    pooled = evaluate_errors(torch_predictor(net.eval()), test, rotation_frame=recipe.rotation_frame).summary()["pooled"]
    cfg, parts = info["train_config"], info["split"]["parts"]
    row = {"train_crops": parts["train_base"]["samples"], "samples": cfg["epochs_mse"] + cfg["epochs_geodesic"],
           "epochs": cfg["epochs_mse"] + cfg["epochs_geodesic"], "best_epoch": info["best_epoch"],
           "val_mean_deg": info["val_mean_deg"], "wall_s": wall,
           **({"resumed_after_epoch": resumed_at} if resumed_at else {}),
           "scenes": {p: parts[p]["scenes"] for p in ("train_base", "val", "test")}, **pooled}
    row["samples"] = row["epochs"] * cfg["max_steps_per_epoch"] * cfg["batch_size"]
    return ckpt, row


def portable_recipe(recipe: TrainRecipe) -> dict:
    """``recipe`` as the card records it: the dataset by its folder's name (a set of benchmarks/DATA.md), no folder
    of the build machine."""
    d = recipe.as_dict()
    d["data"] = Path(d["data"]).resolve().name if d.get("data") else None
    d["extra_train"] = [Path(f).name for f in d.get("extra_train") or []]
    d["init"] = Path(d["init"]).name if d.get("init") else None
    d["cache_root"] = None
    return d


def release_command(obj: str, data: Path, extra_train: list[Path] = (), samples: int | None = None,
                    sizes: int | None = None) -> str:
    """The command that builds ``obj``'s shipped model, as the card records it (no folder of the build machine):
    ``--samples`` and ``--sizes`` where they are not the recipe's own."""
    budget = [*(["--samples", str(samples)] if samples not in (None, _NAMED["samples"]) else []),
              *(["--sizes", str(sizes)] if sizes not in (None, _NAMED["base_per_object"]) else [])]
    return shlex.join(["python", "-m", "export.release.coarse", "build", "--data", "DATA",
                       *[a for f in extra_train for a in ("--extra-train", Path(f).name)], "--run", "RUN",
                       *budget, "--objects", obj])


def data_scaling_command(data: Path, obj: str, run: Path, samples: int, sizes: int, cache: Path,
                         val: int | None = None, test: int | None = None, init: Path | None = None,
                         extra_train: list[Path] = (), *, noise: str | None = None, lr: float | None = None,
                         name: str | None = None, other_set: bool = True, photometric: dict | None = None,
                         seed: int | None = None, inplane: float | None = None, roll: str | None = None) -> list[str]:
    """The ``python -m benchmarks.data_scaling`` command of the same run as :func:`shipped_recipe` (the way models
    up to version 6 were trained, as their cards record it; the studies that vary it run it): from ``init`` when
    given, a model of another set unless ``other_set`` is False; ``name`` (default ``obj``) names the outputs in
    ``run``; the other arguments as :func:`shipped_recipe`'s."""
    r = {**RECIPE, **({"val": val} if val else {}), **({"test": test} if test else {}), **({"lr": lr} if lr else {}),
         **({"seed": seed} if seed is not None else {})}
    name = name or obj
    aug = r["photometric"] if photometric is None else photometric
    inplane = r["inplane"] if inplane is None else inplane
    config = r["config"] if roll is None else {**r["config"], "roll": roll}
    return [sys.executable, "-m", "benchmarks.data_scaling", "--data", str(data), "--object", obj,
            "--modes", r["split_mode"], "--sizes", str(sizes), "--val", str(r["val"]), "--test", str(r["test"]),
            "--split-objects", r["split_objects"], "--arch", r["arch"], "--config", json.dumps(config),
            "--rotation-frame", r["rotation_frame"], "--lr", str(r["lr"]), *(["--noise", noise] if noise else []),
            "--seed", str(r["seed"]),
            "--augment", "--background", str(r["background"]), "--skip-plain", "--skip-jitter",
            *[a for op, p in aug.items() for a in (f"--aug-{op.replace('_', '-')}", str(p))],
            *(["--inplane", f"{inplane:g}"] if inplane else []),
            "--samples", str(samples), "--cache", str(cache), "--threads", "1",
            *(["--bf16"] if r["bf16"] else []),
            # the shipped model trained on another set (DATA is the scenes after it: benchmarks/DATA.md)
            *(["--init", str(init), *(["--init-other-set"] if other_set else [])] if init is not None else []),
            # more sets: each run trains on every crop of the split's training part and of theirs
            *[a for folder in extra_train for a in ("--extra-train", str(folder))],
            *(["--train-scenes", "all"] if extra_train else []),
            "--save", str(run / name), "--json", str(run / f"{name}.train.json")]


def recover_shipped(obj: str, data: Path, run: Path, cache: Path, weights: Path | None = None,
                    any_version: bool = False) -> tuple[Path, dict]:
    """``(checkpoint, its recovered_from record)``: the shipped fp32 model of ``obj`` as a trainable checkpoint
    (``RUN/<obj>.init.pt``, :func:`export.recover.checkpoint_from_onnx`), its BatchNorm statistics rebuilt from 320 of
    ``data``'s training crops (the split the model recorded, drawn on ``data``). Reused when it exists. ``weights``:
    a folder holding the fp32 file to start from instead of the package's (a copy of an earlier version).
    ``any_version``: start from the shipped model whatever its version (the fine refiners start from the coarse model
    that ships now; a coarse build starts from the version before its own)."""
    import models
    from export.quantize import dataset_calibration
    from export.recover import RecoverError, checkpoint_from_onnx
    from refiner_rt.metadata import parse_metadata

    out = run / f"{obj}.init.pt"
    src = (weights or WEIGHTS_DIR) / model_file_name(obj, int8=False)
    if out.is_file():  # reused only when it was recovered from the file this build starts from
        _, info = models.load_checkpoint(out)
        if src.is_file() and info.get("recovered_from", {}).get("sha256") != file_sha256(src):
            raise SystemExit(f"[{obj}] {out} was recovered from another file than {src}: remove it, or use another "
                             "--run")
    else:
        if not src.is_file():
            raise SystemExit(f"[{obj}] no shipped fp32 model to start from ({src})")
        props = metadata_props(src)
        if not any_version and props.get("model_version") == MODEL_VERSION:
            where = "the shipped model" if weights is None else f"{src}"
            raise SystemExit(f"[{obj}] {where} is already version {MODEL_VERSION}; version {MODEL_VERSION} "
                             "starts from the version before it (--from-weights: a folder of that version's files)")
        try:
            cal = dataset_calibration(data, parse_metadata(props), cache_root=cache)
        except (FileNotFoundError, ValueError) as exc:
            raise SystemExit(f"[{obj}] crops of {data} to start from the shipped model: {exc}") from None
        images = np.concatenate([cal.images, cal.check_images])
        q_in = np.concatenate([cal.q_in, cal.check_q_in])
        try:
            checkpoint_from_onnx(src, out, images, q_in)
        except RecoverError as exc:
            raise SystemExit(f"[{obj}] {exc}") from None
    _, info = models.load_checkpoint(out)
    return out, {**info["recovered_from"], "max_abs_dq": info["recover_max_abs_dq"]}


def _cut_by_border(samples) -> np.ndarray:
    """Per test sample: whether its whole silhouette (BOP ``bbox_obj``) reaches past the image border."""
    infos: dict[Path, dict] = {}
    out = []
    for s in samples:
        path = Path(s.dataset) / s.scene_id / "scene_gt_info.json"
        if path not in infos:
            infos[path] = json.loads(path.read_text())
        x, y, w, h = infos[path][str(s.frame_id)][s.instance]["bbox_obj"]
        W, H = s.image_size
        out.append(x < 0 or y < 0 or x + w > W or y + h > H)
    return np.asarray(out, bool)


def _stats(err_out: np.ndarray, err_in: np.ndarray) -> dict:
    if len(err_out) == 0:
        return {"n": 0}
    return {"n": int(len(err_out)), "mean_deg": float(err_out.mean()), "std_deg": float(err_out.std()),
            "median_deg": float(np.median(err_out)), "under_5_deg": float((err_out < 5).mean()),
            "under_10_deg": float((err_out < 10).mean()), "input_mean_deg": float(err_in.mean())}


def _score(onnx_paths: dict[str, Path], test, samples, rotation_frame: str, noise: str = "uniform:0:30") -> dict:
    """Errors of each ONNX model on the crops ``test`` (``samples`` in the same order), through
    ``RefinerSession.refine_crops``: overall, inside the image and cut by its border; the same coarse inputs for all
    (``noise`` about the truth). Objects with a :data:`SYMMETRIES` entry are also scored to the closest symmetric
    pose (``symmetric``)."""
    from models.evaluate.errors import evaluate_errors, onnx_predictor
    from models.data.symmetry import symmetric_error

    q_samples = np.array([s.q_gt for s in samples])
    if len(samples) != len(test) or not np.allclose(np.abs(np.sum(q_samples * test.q_gt, axis=1)), 1.0, atol=1e-6):
        raise RuntimeError("the test crops and the test samples are not in the same order")
    cut = _cut_by_border(samples)
    out = {}
    for name, path in onnx_paths.items():
        errors = evaluate_errors(onnx_predictor(path, threads=1), test, noise, seed=2024,
                                 rotation_frame=rotation_frame)
        out[name] = {"all": _stats(errors.err_out_deg, errors.err_in_deg),
                     "inside_image": _stats(errors.err_out_deg[~cut], errors.err_in_deg[~cut]),
                     "cut_by_border": _stats(errors.err_out_deg[cut], errors.err_in_deg[cut])}
        if set(test.objects) & set(SYMMETRIES):  # the same refinements, measured to the closest symmetric pose
            sym_out = symmetric_error(errors.q_refined, errors.q_true, errors.obj_ids, SYMMETRIES)
            sym_in = symmetric_error(errors.q_in, errors.q_true, errors.obj_ids, SYMMETRIES)
            out[name]["symmetric"] = {**_stats(sym_out, sym_in), "symmetry": SYMMETRIES}
    return out


def _scenes(test) -> int:
    """How many scenes the crops ``test`` come from."""
    return len(set(test.scene_ids.astype(str).tolist()))


def evaluate(onnx_paths: dict[str, Path], ckpt: Path, data: Path, cache: Path) -> dict:
    """Held-out-scene errors of each ONNX model on the test split its checkpoint was trained against
    (:func:`_score`)."""
    import models
    from models.data.pipeline import checkpoint_test_set

    net, info = models.load_checkpoint(ckpt)
    test, spec, samples = checkpoint_test_set(net, info, data=data, cache_root=cache, with_samples=True)
    return {"test_scenes": _scenes(test), "split": spec.as_dict(),
            **_score(onnx_paths, test, samples, info.get("rotation_frame", "camera"))}


def evaluate_fresh(onnx_paths: dict[str, Path], obj: str, data: Path, cache: Path, rotation_frame: str,
                   input_size: int, crop_context: float, noise: str = "uniform:0:30", crop_filter: str = "none") -> dict:
    """Errors of each ONNX model on every instance of ``obj`` in ``data``, a folder of rendered scenes that no
    shipped model trained on (``refiner-rt render`` with a seed other than the training set's) (:func:`_score`)."""
    from models.data.pipeline import cropset_for, load_splits

    spec = whole_folder_spec(data, obj, "test")
    splits = load_splits(spec)
    test = cropset_for(splits, "test", spec, input_size, crop_context, cache_root=cache, progress=False,
                       crop_filter=crop_filter)
    folder_scenes = sum(1 for p in Path(data).iterdir() if (p / "scene_gt.json").is_file())  # BOP scenes
    return {"test_scenes": _scenes(test), "folder_scenes": folder_scenes,
            "split": {**spec.as_dict(), "data": data.resolve().name},
            **_score(onnx_paths, test, list(splits.test), rotation_frame, noise)}


def run_training_command(cmd: list[str], save: Path, log_path: Path, obj: str) -> Path:
    """The one checkpoint ``cmd`` (:func:`data_scaling_command`) saves in ``save``: run it from the repository root
    (output to ``log_path``) unless it is already there."""
    ckpts = sorted(save.glob("*.pt")) if save.is_dir() else []
    if not ckpts:
        print(f"[{obj}] training: {shlex.join(cmd)}", flush=True)
        with open(log_path, "w") as log:
            subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        ckpts = sorted(save.glob("*.pt"))
    if len(ckpts) != 1:
        raise RuntimeError(f"expected one checkpoint in {save}; found {[p.name for p in ckpts]}")
    return ckpts[0]


def card_command(cmd: list[str]) -> str:
    """A :func:`data_scaling_command` as a record prints it: ``python -m benchmarks.data_scaling ...`` without the
    build machine's interpreter or folders (:func:`export.release.card.portable_command`)."""
    return portable_command(shlex.join(["python", "-m", "benchmarks.data_scaling", *cmd[3:]]))


def ship_object(obj: str, data: Path, run: Path, cache: Path, samples: int, sizes: int,
                val: int | None = None, test: int | None = None, extra_train: list[Path] = (),
                from_weights: Path | None = None) -> dict:
    """Train ``obj``'s model (:func:`shipped_recipe`, :func:`train_shipped`), export it to fp32 and INT8 ONNX
    (:func:`quantize_for_shipping`), evaluate it on its held-out scenes, stamp its card keys, copy both files into
    the package and regenerate the card (:func:`export.release.card.publish`): the build record. ``from_weights``:
    a folder holding the fp32 file of the version before, to start from instead of the package's (to build again a
    version that ships already, :func:`recover_shipped`)."""
    import logging

    logging.getLogger("torch.onnx._internal.exporter._registration").setLevel(logging.ERROR)  # torchvision ops: n/a
    from export.onnx_export import export_checkpoint

    result_json = RESULTS_DIR / f"{obj}.json"
    t0 = time.perf_counter()
    first = FIRST_STAGE.get(obj)
    first_recipe = None
    if first:  # from scratch: the first stage, then the recipe's stage from its network (same split)
        first_recipe = shipped_recipe(data, obj, first["samples"], sizes, cache, val, test, None, extra_train,
                                      noise=first["noise"], lr=first["lr"])
        init, init_record = train_shipped(first_recipe, run / f"{obj}.stage1", obj)[0], None
    else:
        init, init_record = (recover_shipped(obj, data, run, cache, weights=from_weights)
                             if RECIPE["init_from_shipped"] else (None, None))
    recipe = shipped_recipe(data, obj, samples, sizes, cache, val, test, init, extra_train)
    ckpt, row = train_shipped(recipe, run / obj, obj)
    fp32, int8 = run / model_file_name(obj, int8=False), run / model_file_name(obj, int8=True)
    exp = export_checkpoint(ckpt, fp32)
    scheme, ev, tried = quantize_for_shipping(fp32, int8, *_checkpoint_quantization(fp32, ckpt, data, cache))
    print(f"[{obj}] exported: max |dq| {exp.max_abs_dq:.2g}; INT8 {scheme}", flush=True)
    mesh = MESHES_DIR / obj / "textured.obj"
    # Nothing shipped names a folder of the build machine: the JSON's split says DATA (as the card's command does),
    # and the models' `data` metadata names the rendered set by its folder's name (benchmarks/DATA.md lists the sets).
    ev["split"]["data"] = "DATA"
    data_meta = json.loads(metadata_props(fp32)["data"])
    data_meta["data"] = data.resolve().name
    if data_meta.get("extra_train"):
        data_meta["extra_train"] = [Path(x).resolve().name for x in data_meta["extra_train"]]
    heldout = {**{k: ev["int8"]["all"][k] for k in ("mean_deg", "median_deg", "under_5_deg", "under_10_deg",
                                                    "input_mean_deg", "n")},
               "split": "held-out scenes"}
    card_meta = {
        "object_id": obj, "model_version": MODEL_VERSION, "recipe": RECIPE["name"],
        "mesh": {"file": f"models/data/ycb_models/{obj}/textured.obj", "sha256": file_sha256(mesh)},
        "object_frame": OBJECT_FRAME, "data": data_meta,
        **({"init_from": {k: init_record[k] for k in ("file", "sha256", "model_version", "recipe")}}
           if init_record else {}),
        **({"first_stage": first} if first else {}),
        "heldout_error_deg": {"int8_mean": round(ev["int8"]["all"]["mean_deg"], 3),
                              "fp32_mean": round(ev["fp32"]["all"]["mean_deg"], 3),
                              "split": BUILD_SPLIT},
    }
    for p in (fp32, int8):
        stamp(p, card_meta)
    WEIGHTS_DIR.mkdir(exist_ok=True)
    for p in (fp32, int8):
        shutil.copyfile(p, WEIGHTS_DIR / p.name)
    doc = {
        "schema": SCHEMA, "object_id": obj, "model_version": MODEL_VERSION, "recipe": RECIPE,
        "train_command": release_command(obj, data, extra_train, samples, sizes),
        "train_recipe": portable_recipe(recipe),
        **({"first_stage": {**first, "recipe": portable_recipe(first_recipe)}} if first else {}),
        "train": {k: row.get(k) for k in ("train_crops", "samples", "epochs", "best_epoch", "val_mean_deg", "wall_s",
                                          "scenes", "mean_deg", "median_deg")},
        "export": {"max_abs_dq": exp.max_abs_dq, "int8_scheme": scheme, "int8_candidates": tried},
        "eval": ev, "heldout": heldout, "metadata": card_meta,
        "files": {"int8": int8.name, "fp32": fp32.name},
        **({"init_from": init_record} if init_record else {}),
        "sizes_bytes": {"int8": int8.stat().st_size, "fp32": fp32.stat().st_size},
        "checkpoint_sha256": file_sha256(ckpt), "machine": machine(), "git_commit": git_commit(),
        "build_s": round(time.perf_counter() - t0, 1),
    }
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    result_json.write_text(json.dumps(doc, indent=1) + "\n")
    publish([WEIGHTS_DIR / fp32.name, WEIGHTS_DIR / int8.name, result_json],
            f"[{obj}] held-out scenes: INT8 {ev['int8']['all']['mean_deg']:.2f} deg (fp32 "
            f"{ev['fp32']['all']['mean_deg']:.2f}, input {ev['int8']['all']['input_mean_deg']:.2f}); version "
            f"{MODEL_VERSION} of its refiner")
    return doc


def quantize_for_shipping(fp32: Path, int8: Path, score, calibrate, schemes=INT8_SCHEMES_FASTEST_FIRST
                          ) -> tuple[str, dict, dict]:
    """Write ``int8`` with the fastest scheme that holds accuracy: ``(scheme, evaluation, candidates)``.

    Every scheme of ``schemes`` (fastest first) quantises ``fp32``, static ones calibrated on ``calibrate()``'s
    crops (training crops, never test crops); all are scored with fp32 on the same held-out crops and coarse inputs
    by ``score(paths)`` (:func:`evaluate` or :func:`evaluate_fresh`). The first whose mean error is at most
    :data:`MAX_INT8_COST_DEG` above fp32's is written to ``int8``; when none is, the one with the smallest cost.
    ``evaluation`` has the scorer's form with the chosen model under ``"int8"``; ``candidates`` maps each scheme to
    its mean error and its cost (degrees).
    """
    from export.defaults import CALIBRATED_SCHEMES
    from export.quantize import QuantizationError, quantize_model

    calibration = None
    paths = {}
    for scheme in schemes:
        if scheme in CALIBRATED_SCHEMES and calibration is None:
            calibration = calibrate()
        out = int8.with_name(f"{int8.stem}.{scheme}.onnx")
        try:
            quantize_model(fp32, out, scheme=scheme, calibration=calibration if scheme in CALIBRATED_SCHEMES else None)
        except QuantizationError as exc:  # disagrees with fp32 beyond the exporter's bound: not a candidate
            print(f"  {scheme}: {exc}", flush=True)
            continue
        paths[scheme] = out
    if not paths:
        raise RuntimeError(f"{fp32}: no INT8 scheme of {schemes} passed the exporter's agreement check")
    schemes = [sc for sc in schemes if sc in paths]
    try:
        ev = score({**paths, "fp32": fp32})
        fp = ev["fp32"]["all"]["mean_deg"]
        tried = {sc: {"mean_deg": ev[sc]["all"]["mean_deg"], "cost_deg": ev[sc]["all"]["mean_deg"] - fp,
                      "cost_largest_group_deg": max(ev[sc][g]["mean_deg"] - ev["fp32"][g]["mean_deg"]
                                                    for g in ("inside_image", "cut_by_border") if ev[sc][g]["n"])}
                 for sc in paths}
        holding = [sc for sc in schemes if tried[sc]["cost_deg"] <= MAX_INT8_COST_DEG]
        chosen = holding[0] if holding else min(schemes, key=lambda sc: tried[sc]["cost_deg"])
        os.replace(paths[chosen], int8)
    finally:
        for p in paths.values():
            p.unlink(missing_ok=True)
    evaluation = {k: v for k, v in ev.items() if k not in paths}
    evaluation["int8"] = ev[chosen]
    return chosen, evaluation, tried


def _checkpoint_quantization(fp32: Path, ckpt: Path, data: Path, cache: Path) -> tuple:
    """``(score, calibrate)`` for :func:`quantize_for_shipping` from a build's checkpoint: its own held-out test
    split, and calibration on its training split."""
    from export.quantize import dataset_calibration
    from refiner_rt.metadata import parse_metadata

    contract = parse_metadata(metadata_props(fp32))
    return (lambda paths: evaluate(paths, ckpt, data, cache),
            lambda: dataset_calibration(data, contract, cache_root=cache))


def fresh_quantization(fp32: Path, obj: str, heldout: Path, calibration: Path, cache: Path,
                        noise: str = "uniform:0:30") -> tuple:
    """``(score, calibrate)`` for :func:`quantize_for_shipping` without a checkpoint: every instance of ``obj`` in
    ``heldout`` (scenes no model trained on), and calibration on every instance in ``calibration`` (other such
    scenes)."""
    from export.quantize import dataset_calibration
    from refiner_rt.metadata import parse_metadata

    c = parse_metadata(metadata_props(fp32))
    return (lambda paths: evaluate_fresh(paths, obj, heldout, cache, c.rotation_frame, c.input_size, c.crop_context,
                                         noise, crop_filter=c.crop_filter),
            lambda: dataset_calibration(calibration, c, cache_root=cache,
                                        spec=whole_folder_spec(calibration, obj, "train_base")))


def scoring_mode(ap: argparse.ArgumentParser, args) -> bool:
    """Check the two ways to score INT8 candidates (``--data`` and ``--run``, or ``--heldout`` and ``--calibration``)
    on parsed ``args``; True for the fresh folders. ``ap.error`` names what is missing or mixed."""
    by_checkpoints = args.data is not None or args.run is not None
    by_folders = args.heldout is not None or args.calibration is not None
    if by_checkpoints == by_folders:
        ap.error("give either --data and --run (the build's checkpoints) or --heldout and --calibration")
    if by_checkpoints and (args.data is None or args.run is None):
        ap.error("--data and --run go together (the dataset, and the build's checkpoints that name its split)")
    if by_folders and (args.heldout is None or args.calibration is None):
        ap.error("--heldout and --calibration go together (two folders of fresh scenes)")
    if by_folders and args.heldout.resolve() == args.calibration.resolve():
        ap.error("--calibration must be another folder than --heldout: calibrating on the scored crops would "
                 "hide what quantisation costs")
    return by_folders


FRESH_SPLIT = "rendered scenes of a set no shipped model trained on, visib_fract >= 0.3, inputs U(0, 30)"
BUILD_SPLIT = "scenes held out whole, rendered, visib_fract >= 0.3, inputs U(0, 30)"


def requantize(data: Path | None, run: Path | None, cache: Path | None, objects=None,
               schemes=INT8_SCHEMES_FASTEST_FIRST, heldout: Path | None = None,
               calibration: Path | None = None) -> dict:
    """Quantise every shipped object's INT8 model again from its shipped fp32 file (:func:`quantize_for_shipping`),
    update its evaluation JSON and metadata, and regenerate the card. The fp32 files' weights are not changed.

    Two ways to score the candidates: the build's checkpoints (``run``) rebuild each model's own test split of
    ``data``; or, without them, ``heldout`` and ``calibration``: folders of scenes rendered with seeds the training
    set did not use, every instance of the object in ``heldout`` scored and every one in ``calibration`` used to
    calibrate. The second way replaces the card's evaluation (``eval``) with the fresh scenes' and keeps the
    previous one, the training set's own test scenes, as ``eval_training_split`` (its ``int8`` entry is the
    previous INT8 file's).
    """
    from refiner_rt.pretrained import pretrained_models

    fresh = heldout is not None
    docs = {d["object_id"]: d for d in load_results()}
    chosen = [m.object_id for m in pretrained_models() if objects is None or m.object_id in objects]
    missing = sorted(set(objects or ()) - set(chosen))
    if missing:
        raise SystemExit(f"not shipped: {', '.join(missing)}")
    costs, changed = {}, []
    for obj in chosen:
        doc = docs[obj]
        fp32, int8 = WEIGHTS_DIR / doc["files"]["fp32"], WEIGHTS_DIR / doc["files"]["int8"]
        if fresh:
            tools = fresh_quantization(fp32, obj, heldout, calibration, cache or heldout / ".crops")
        else:
            ckpts = sorted((run / obj).glob("*.pt")) if (run / obj).is_dir() else []
            if len(ckpts) != 1:
                raise SystemExit(f"{obj}: expected one checkpoint in {run / obj} (its test split comes from it); "
                                 f"found {[p.name for p in ckpts]}")
            tools = _checkpoint_quantization(fp32, ckpts[0], data, cache or data / ".crops")
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="requantize-") as work:
            tmp = Path(work) / int8.name
            scheme, ev, tried = quantize_for_shipping(fp32, tmp, *tools, schemes)
            shutil.copyfile(tmp, int8)
        split_text = BUILD_SPLIT
        if not fresh:
            # The build's own test split again: the card's evaluation is that split's, as after `build`.
            doc.pop("eval_training_split", None)
            ev["split"]["data"] = "DATA"
        else:
            if "eval_training_split" not in doc:
                doc["eval_training_split"] = {**doc["eval"], "int8_file": "the previous INT8 file ("
                                              + doc["export"].get("int8_scheme", "dynamic-int8") + ")"}
            ev["calibration"] = {"data": calibration.resolve().name,
                                 "crops": "three quarters of the object's instances (the rest check the agreement)"}
            split_text = FRESH_SPLIT
        doc["eval"] = ev
        doc["heldout"] = {**{k: ev["int8"]["all"][k] for k in ("mean_deg", "median_deg", "under_5_deg", "under_10_deg",
                                                                "input_mean_deg", "n")},
                          "split": "fresh held-out scenes" if fresh else "held-out scenes"}
        doc["export"] = {**doc["export"], "int8_scheme": scheme, "int8_candidates": tried,
                         "int8_machine": machine()}
        held = {"int8_mean": round(ev["int8"]["all"]["mean_deg"], 3), "fp32_mean": round(ev["fp32"]["all"]["mean_deg"], 3),
                "split": split_text}
        if fresh:
            held["data"] = ev["split"]["data"]
            held["fp32_mean_training_split"] = round(doc["eval_training_split"]["fp32"]["all"]["mean_deg"], 3)
        doc["metadata"]["heldout_error_deg"] = held
        for p in (fp32, int8):
            stamp(p, {"heldout_error_deg": held})
        doc["sizes_bytes"] = {"int8": int8.stat().st_size, "fp32": fp32.stat().st_size}
        (RESULTS_DIR / f"{obj}.json").write_text(json.dumps(doc, indent=1) + "\n")
        costs[obj] = tried[scheme]["cost_deg"]
        changed += [fp32, int8, RESULTS_DIR / f"{obj}.json"]
        print(f"[{obj}] INT8 {scheme}: {ev['int8']['all']['mean_deg']:.3f} deg, fp32 {ev['fp32']['all']['mean_deg']:.3f} "
              f"(cost {costs[obj]:+.3f}; candidates " + ", ".join(f"{sc} {t['cost_deg']:+.3f}" for sc, t in tried.items())
              + f") in {time.perf_counter() - t0:.0f} s", flush=True)
    mean_cost = float(np.mean(list(costs.values()))) if costs else 0.0
    held = mean_cost <= MAX_MEAN_INT8_COST_DEG and all(c <= MAX_INT8_COST_DEG for c in costs.values())
    print(f"INT8 cost over {len(costs)} objects: mean {mean_cost:+.3f} deg (goal <= {MAX_MEAN_INT8_COST_DEG}), "
          f"largest {max(costs.values(), default=0):+.3f} (goal <= {MAX_INT8_COST_DEG}): "
          f"{'held' if held else 'NOT held'}", flush=True)
    schemes_used = sorted({docs[o]["export"]["int8_scheme"] for o in costs})
    publish(changed, f"the INT8 models of {', '.join(costs)} quantised again ({', '.join(schemes_used)}), mean cost "
            f"{mean_cost:+.3f} deg against fp32 on " + ("fresh rendered scenes" if fresh else "held-out scenes"))
    return {"costs_deg": costs, "mean_cost_deg": mean_cost, "held": held}


def _built(doc: dict) -> bool:
    """Whether a result JSON is this build's: the model version and recipe it would ship."""
    return doc.get("model_version") == MODEL_VERSION and doc.get("recipe", {}).get("name") == RECIPE["name"]


# -------------------------------------------------------------------------------------------- speed
def measure_speed(rounds: int = 7, calls: int = 300) -> dict:
    """Refinements/s of every shipped model, INT8 and fp32, batch 1, one thread, full ``refine()`` path with K,
    models interleaved round by round; medians."""
    import cv2

    from refiner_rt import RefinerSession
    from refiner_rt.pretrained import pretrained_models

    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    image = cv2.GaussianBlur(image, (0, 0), 2)
    K = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])
    box = np.array([[260.0, 180.0, 380.0, 330.0]])
    q = np.array([[0.9, 0.1, -0.3, 0.2]])
    sessions = {(m.object_id, k): RefinerSession(m.path(int8=(k == "int8")), threads=1)
                for m in pretrained_models() for k in ("int8", "fp32") if m.files.get(k)}
    times: dict = {key: [] for key in sessions}
    for s in sessions.values():
        for _ in range(20):
            s.refine(image, box, q, K=K)
    for _ in range(rounds):
        for key, s in sessions.items():
            t0 = time.perf_counter()
            for _ in range(calls):
                s.refine(image, box, q, K=K)
            times[key].append((time.perf_counter() - t0) / calls)
    out: dict = {}
    for (obj, kind), ts in times.items():
        out.setdefault(obj, {})[kind] = round(1.0 / float(np.median(ts)), 1)
    return {"schema": "refiner-rt/pretrained-speed/1", "rounds": rounds, "calls_per_round": calls, "models": out,
            "machine": machine(), "git_commit": git_commit(),
            "command": "python -m export.release.coarse speed"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build", help="train, export, evaluate and ship objects (resumable)")
    b.add_argument("--data", type=Path, required=True, help="rendered dataset folder (refiner-rt render --out)")
    b.add_argument("--run", type=Path, required=True, help="scratch folder for checkpoints and logs (not committed)")
    b.add_argument("--objects", required=True, help="comma-separated YCB ids, built in this order")
    b.add_argument("--samples", type=int, default=_NAMED["samples"], help="training samples per object (default: the recipe's)")
    b.add_argument("--sizes", type=int, default=_NAMED["base_per_object"],
                   help="training crops per object the split is drawn with (default: the recipe's)")
    b.add_argument("--cache", type=Path, help="crop cache folder (default DATA/.crops)")
    b.add_argument("--force", action="store_true", help="rebuild objects that already ship")
    b.add_argument("--from-weights", type=Path, metavar="FOLDER",
                   help="start each object from the fp32 file <id>.onnx in FOLDER (the version before this one, "
                        "e.g. taken from the git history) instead of the package's; with --force this builds a "
                        "shipped version again")
    b.add_argument("--val", type=int, help=f"validation crops per object (default {RECIPE['val']}; smaller for smoke tests)")
    b.add_argument("--test", type=int, help=f"test crops per object (default {RECIPE['test']})")
    b.add_argument("--heldout", type=Path, help="then score each new model on this folder of fresh scenes and "
                   "quantise it again calibrated on --calibration, as `requantize --heldout` does (the card's evaluation)")
    b.add_argument("--calibration", type=Path, help="with --heldout: the folder of other fresh scenes to calibrate on")
    b.add_argument("--real", type=Path, help="then score each new model on this folder of real frames (measuring only: "
                   "python -m benchmarks.real) and record it in the card")
    b.add_argument("--extra-train", type=Path, action="append", default=[], metavar="FOLDER",
                   help="another rendered set whose every crop joins the training part (its scene ids must differ "
                        "from --data's: the scenes rendered before them with --first-scene); repeatable")
    sub.add_parser("card", help="regenerate weights/models.json and weights/MODELS.md from the JSON")
    r = sub.add_parser("requantize", help="quantise the shipped INT8 models again from their fp32 files with the "
                       "fastest scheme that holds accuracy, re-evaluate, regenerate the card")
    r.add_argument("--data", type=Path, help="the rendered dataset the models were trained on (with --run)")
    r.add_argument("--run", type=Path, help="the build's run folder (RUN/<obj>/*.pt names the test split)")
    r.add_argument("--heldout", type=Path, help="instead of --data/--run: a rendered folder of scenes no model "
                   "trained on (another --seed); every instance is scored")
    r.add_argument("--calibration", type=Path, help="with --heldout: another such folder, for the static schemes' "
                   "calibration")
    r.add_argument("--cache", type=Path, help="crop cache folder (default DATA/.crops or HELDOUT/.crops)")
    r.add_argument("--objects", help="comma-separated YCB ids (default: every shipped object)")
    r.add_argument("--schemes", default=",".join(INT8_SCHEMES_FASTEST_FIRST),
                   help="candidate INT8 schemes, fastest first (default: %(default)s)")
    sub.add_parser("restamp", help="write the descriptive card keys (object_frame) into every shipped file and its "
                   "JSON again, as this build states them now (the weights are not touched)")
    s = sub.add_parser("speed", help="measure every shipped model's speed (run on a quiet machine)")
    s.add_argument("--rounds", type=int, default=7)
    args = ap.parse_args(argv)
    if args.cmd == "card":
        write_card()
        return 0
    if args.cmd == "restamp":
        for d in load_results():
            d["metadata"]["object_frame"] = OBJECT_FRAME
            for name in d["files"].values():
                stamp(WEIGHTS_DIR / name, {"object_frame": OBJECT_FRAME})
            d["sizes_bytes"] = {k: (WEIGHTS_DIR / d["files"][k]).stat().st_size for k in d["files"]}
            (RESULTS_DIR / f"{d['object_id']}.json").write_text(json.dumps(d, indent=1) + "\n")
        write_card()
        return 0
    if args.cmd == "requantize":
        from export.defaults import SCHEMES

        schemes = tuple(x.strip() for x in args.schemes.split(",") if x.strip())
        bad = [x for x in schemes if x not in SCHEMES]
        if bad or not schemes:
            ap.error(f"--schemes: unknown INT8 scheme(s) {bad}; known: {', '.join(SCHEMES)}")
        objects = [o.strip() for o in args.objects.split(",") if o.strip()] if args.objects else None
        scoring_mode(ap, args)
        out = requantize(args.data, args.run, args.cache, objects, schemes, args.heldout, args.calibration)
        return 0 if out["held"] else 1
    if args.cmd == "speed":
        doc = measure_speed(args.rounds)
        RESULTS_DIR.mkdir(parents=True, exist_ok=True)
        (RESULTS_DIR / "_speed.json").write_text(json.dumps(doc, indent=1) + "\n")
        print(json.dumps(doc["models"], indent=1))
        publish([RESULTS_DIR / "_speed.json"], "the shipped models' speed, measured interleaved on one core")
        return 0
    if (args.heldout is None) != (args.calibration is None):
        ap.error("--heldout and --calibration go together (two folders of fresh scenes)")
    if args.real is not None:
        from models.data.pipeline import detect_format

        try:  # checked before hours of training, not after
            detect_format(args.real)
        except (FileNotFoundError, ValueError) as exc:
            ap.error(f"--real: {exc}")
    if args.from_weights is not None:
        if not args.from_weights.is_dir():
            ap.error(f"--from-weights: expected a folder holding <id>.onnx fp32 files; {args.from_weights} is not a "
                     "folder")
        objects = [o.strip() for o in args.objects.split(",") if o.strip()]
        lacking = [o for o in objects
                   if not (args.from_weights / model_file_name(o, int8=False)).is_file()]
        if lacking:  # checked before hours of training, not after
            ap.error(f"--from-weights: {args.from_weights} holds no fp32 file of {', '.join(lacking)} "
                     f"(expected {model_file_name(lacking[0], int8=False)})")
        if set(FIRST_STAGE) & set(objects):
            ap.error(f"--from-weights: {', '.join(sorted(FIRST_STAGE))} train from scratch (FIRST_STAGE)")
    for folder in args.extra_train:
        if not folder.is_dir():
            ap.error(f"--extra-train: expected a rendered dataset folder; {folder} is not a folder")
    args.run.mkdir(parents=True, exist_ok=True)
    cache = args.cache or args.data / ".crops"
    for obj in [o.strip() for o in args.objects.split(",") if o.strip()]:
        done = RESULTS_DIR / f"{obj}.json"
        if done.is_file() and not args.force:
            d = json.loads(done.read_text())
            if _built(d) and (WEIGHTS_DIR / d["files"]["int8"]).is_file():
                print(f"[{obj}] already ships as version {MODEL_VERSION}; skipped (--force rebuilds)", flush=True)
                continue
        # Builds side by side share one object list: each object is built by whichever build holds its lock.
        with open(args.run / f"{obj}.lock", "w") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                print(f"[{obj}] being built by another process; skipped", flush=True)
                continue
            if done.is_file() and not args.force and _built(json.loads(done.read_text())):
                continue  # finished by the other build while this one waited
            ship_object(obj, args.data, args.run, cache, args.samples, args.sizes, args.val, args.test,
                        args.extra_train, args.from_weights)
            if args.heldout is not None:
                requantize(None, None, None, [obj], INT8_SCHEMES_FASTEST_FIRST, args.heldout, args.calibration)
            if args.real is not None:
                score_real(obj, args.real)
    return 0


def score_real(obj: str, real: Path) -> None:
    """The shipped INT8 model of ``obj`` on the real frames in ``real`` (:func:`models.evaluate.real.update`), merged
    into :data:`REAL_JSON`; then the card. Measuring only: nothing is chosen on them."""
    from models.evaluate.real import update

    doc = update(REAL_JSON, {obj: WEIGHTS_DIR / model_file_name(obj, int8=True)}, real)
    o = doc["objects"][obj]
    print(f"[{obj}] real frames: {o['mean_deg']:.2f} deg (input {o['input_mean_deg']:.2f}), drift "
          f"{o['drift_mean_deg']:.2f}, {o['instances']} instances", flush=True)
    publish([REAL_JSON], f"{obj}: its version-{MODEL_VERSION} refiner on the real dev frames")


if __name__ == "__main__":
    raise SystemExit(main())
