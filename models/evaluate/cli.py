"""``refiner-rt eval MODEL --data DIR``: the paper's metric on a dataset's test split; with ``--all``, on every
instance of a folder (real frames, or rendered scenes no model trained on).

MODEL is a checkpoint (``.pt``, run in PyTorch) or an exported model (``.onnx``, run through
``refiner_rt.RefinerSession``, the deployed path). When per-object fine-tuned siblings exist
(``<stem>.<ycb id>.pt`` / ``.onnx``, as ``refiner-rt train`` and ``refiner-rt export`` write them),
each object is evaluated with its own network, as in the paper; ``--base-only`` turns that off.
The split (mode, seed, sizes, objects) defaults to the one recorded in a checkpoint, so the test
set is the one held out in training.
"""

from __future__ import annotations

import json
import logging
import shlex
import sys
import time
from pathlib import Path

import click

log = logging.getLogger(__name__)


def _siblings(model: Path) -> dict[str, Path]:
    """Per-object fine-tuned models next to ``model``: ``{object: path}``."""
    from models.train.paths import per_object_siblings

    return per_object_siblings(model)


def _load(model: Path, threads: int, device: str = "auto"):
    """``(predictor, contract dict)`` for a checkpoint or an ONNX file."""
    from models.evaluate.errors import onnx_predictor, torch_predictor

    if model.suffix == ".onnx":
        pred = onnx_predictor(model, threads=threads)
        meta = pred.session.metadata
        return pred, {
            "input_size": meta["input_size"],
            "crop_context": meta["crop_context"],
            "crop_filter": meta.get("crop_filter", "none"),
            "rotation_frame": meta["rotation_frame"],
            "objects": meta["objects"],
            "data": json.loads(meta["data"]) if "data" in meta else None,
            "runtime": "onnxruntime",
            "arch": meta["arch"],
            "symmetries": json.loads(meta["symmetries"]) if meta.get("symmetries") else {},
        }
    import models
    from models.train.loop import set_threads

    from models.train.run import resolve_device

    set_threads(threads)
    net, info = models.load_checkpoint(model)
    net.to(resolve_device(device))
    return torch_predictor(net), {
        "input_size": net.input_size,
        "crop_context": net.config["crop_context"],
        "crop_filter": net.config.get("crop_filter", "none"),
        "rotation_frame": info.get("rotation_frame", "camera"),
        "objects": info.get("objects", []),
        "data": info.get("data"),
        "runtime": "torch",
        "arch": net.arch,
        "symmetries": info.get("symmetries") or {},
    }


def run_eval(
    model: Path,
    data: Path,
    *,
    noise: str = "uniform:0:30",
    resample: int = 1,
    iterations: int = 1,
    settle_deg: float | None = None,
    seed: int = 2024,
    base_only: bool = False,
    split_mode: str | None = None,
    split_seed: int | None = None,
    test_per_object: int | None = None,
    objects: list[str] | None = None,
    threads: int = 0,
    cache_root: Path | None = None,
    workers: int = 1,
    progress: bool = True,
    device: str = "auto",
) -> dict:
    """Evaluate ``model`` on the test split of ``data``; returns the JSON-ready result (see the module doc)."""
    from models.evaluate.errors import evaluate_errors
    from models.data.pipeline import DataSpec, cropset_for, load_splits

    t0 = time.perf_counter()
    predictor, c = _load(model, threads, device)
    per_object = {} if base_only else _siblings(model)
    recorded = c["data"] or {}
    spec = DataSpec.from_dict({**recorded, "data": str(data)}) if recorded else DataSpec(data=str(data))
    spec = spec.held_out()  # the test part only: the folders of extra training crops are not needed
    if split_mode:
        spec.split_mode = split_mode
    if split_seed is not None:
        spec.split_seed = split_seed
    if test_per_object:
        spec.sizes = (*spec.sizes[:3], test_per_object)
    if objects:
        # The model's scenes split, not one drawn over these objects alone (which would hold out other scenes).
        spec.split_objects = spec.split_objects_for(objects)
        spec.objects = objects
    splits = load_splits(spec)
    test = cropset_for(splits, "test", spec, int(c["input_size"]), float(c["crop_context"]),
                       cache_root=cache_root, workers=workers, progress=progress, crop_filter=c["crop_filter"])
    if per_object:
        preds = {obj: _load(p, threads, device)[0] for obj, p in per_object.items() if obj in test.objects}
        for obj in test.objects:
            preds.setdefault(obj, predictor)
        predictor_used = preds
    else:
        predictor_used = predictor
    errors = evaluate_errors(predictor_used, test, noise, seed=seed, resample=resample, iterations=iterations,
                             rotation_frame=c["rotation_frame"], symmetries=c["symmetries"], settle_deg=settle_deg)
    summary = errors.summary()
    return {
        **summary,
        **({"symmetries": c["symmetries"], "error": "symmetry-aware (closest symmetric pose)"}
           if c["symmetries"] else {}),
        "model": str(model),
        "arch": c["arch"],
        "runtime": c["runtime"],
        "per_object_models": {k: str(v) for k, v in per_object.items() if k in test.objects},
        "rotation_frame": c["rotation_frame"],
        "data": spec.as_dict(),
        "split_mode": spec.split_mode,
        "noise": noise,
        "resample": resample,
        "iterations": iterations,
        "settle_deg": settle_deg,
        "seed": seed,
        "eval_s": time.perf_counter() - t0,
    }


def run_eval_all(model: Path, data: Path, *, noise: str = "uniform:0:30", draws: int = 10, seed: int = 2024,
                 objects: list[str] | None = None, threads: int = 0, cache_root: Path | None = None,
                 progress: bool = True, device: str = "auto", base_only: bool = False) -> dict:
    """Evaluate ``model`` on every instance of ``data`` (``visib_fract >= 0.3``, the visible box, boxes of 16 px
    or more): ``draws`` coarse inputs per instance and the drift from the true pose
    (:func:`models.evaluate.errors.evaluate_folder`). Objects with a symmetry (the model's, or
    :data:`models.data.objects.SCAN_FRAME_SYMMETRIES`) are scored to the closest symmetric pose."""
    from models.data.objects import SCAN_FRAME_SYMMETRIES
    from models.evaluate.errors import evaluate_folder, folder_cropset

    t0 = time.perf_counter()
    predictor, c = _load(model, threads, device)
    per_object = {} if base_only else _siblings(model)
    objects = list(objects or c["objects"] or [])
    if not objects:
        raise ValueError(f"{model} records no objects: give --objects")
    crops, _ = folder_cropset(data, objects, int(c["input_size"]), float(c["crop_context"]), cache_root=cache_root,
                              progress=progress, crop_filter=c["crop_filter"])
    if per_object:
        predictor = {obj: (_load(per_object[obj], threads, device)[0] if obj in per_object else predictor)
                     for obj in crops.objects}
    symmetries = {**{o: s for o, s in SCAN_FRAME_SYMMETRIES.items() if o in crops.objects}, **c["symmetries"]}
    result = evaluate_folder(predictor, crops, rotation_frame=c["rotation_frame"], noise=noise, draws=draws,
                             seed=seed, symmetries=symmetries)
    return {**result, "model": str(model), "arch": c["arch"], "runtime": c["runtime"], "data": str(data),
            "rotation_frame": c["rotation_frame"], "eval_s": time.perf_counter() - t0}


def format_all_table(result: dict, title: str = "") -> str:
    """The ``--all`` result as plain text: per object, refined and input error, drift from the true pose, videos."""
    head = f"{'object':<22}{'mean':>8}{'median':>8}{'input':>8}{'<5deg':>8}{'drift':>8}{'videos':>8}{'n':>6}"
    lines = ([title] if title else []) + [head, "-" * len(head)]
    for name, s in result["objects"].items():
        lines.append(f"{name:<22}{s['mean_deg']:>8.2f}{s['median_deg']:>8.2f}{s['input_mean_deg']:>8.2f}"
                     f"{100 * s['under_5_deg']:>7.1f}%{s['drift_mean_deg']:>8.2f}{len(s['videos']):>8}"
                     f"{s['instances']:>6}")
    lines += ["-" * len(head),
              f"{'mean of objects':<22}{result['mean_deg']:>8.2f}{'':>8}{result['input_mean_deg']:>8.2f}{'':>8}"
              f"{result['drift_mean_deg']:>8.2f}{'':>8}{result['instances']:>6}",
              f"Per-video mean (each object's videos averaged first): {result['video_mean_deg']:.2f} deg; over "
              f"instances: {result['pooled_mean_deg']:.2f} deg. drift: error when the input is the true pose."]
    return "\n".join(lines)


@click.command("eval")
@click.argument("model", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--data", required=True, type=click.Path(exists=True, file_okay=False, path_type=Path), help="Dataset folder (BOP split or YCB-Video root).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help="Write the result as JSON.")
@click.option("--markdown", "md_path", type=click.Path(dir_okay=False, path_type=Path), help="Write the table as Markdown.")
@click.option("--noise", default="uniform:0:30", show_default=True, help="Coarse-pose noise of the test inputs (uniform:LOW:HIGH or normal:MEAN:STD, degrees).")
@click.option("--resample", default=1, show_default=True, type=click.IntRange(1), help="Coarse poses per test image (the paper's over-fitting test).")
@click.option("--iterations", default=1, show_default=True, type=click.IntRange(1), help="Refinement iterations (beyond the paper).")
@click.option("--settle-deg", type=click.FloatRange(0.0, 180.0, min_open=True, max_open=True), default=None,
              metavar="DEG", help="With --iterations 2 or more: a later iteration is kept only where it turns the "
                                  "result by more than DEG (RefinerSession.refine's settle_deg; README \"Coarse poses "
                                  "far off\").")
@click.option("--seed", default=2024, show_default=True, type=int, help="Seed of the test coarse poses.")
@click.option("--all", "all_instances", is_flag=True,
              help="Score every instance of DIR (no split: real frames, or rendered scenes no model trained on): "
                   "visib_fract >= 0.3, the visible box, --draws coarse inputs each, and the drift from the true pose; "
                   "symmetric objects to the closest symmetric pose.")
@click.option("--draws", default=10, show_default=True, type=click.IntRange(1),
              help="With --all: coarse inputs drawn per instance.")
@click.option("--base-only", is_flag=True, help="Ignore per-object fine-tuned siblings of MODEL.")
@click.option("--split-mode", type=click.Choice(["frames", "scenes"]), help="Override the split recorded in the checkpoint.")
@click.option("--split-seed", type=int, help="Override the split seed.")
@click.option("--test-per-object", type=click.IntRange(1), help="Override the test size per object.")
@click.option("--objects", help="Comma-separated object names: YCB ids or your own objects' (default: the model's).")
@click.option("--device", default="auto", show_default=True,
              help="Where a .pt checkpoint runs: auto (cuda, then mps, then cpu), cpu, cuda, cuda:N or mps. ONNX models "
                   "run on onnxruntime's CPU provider.")
@click.option("--threads", default=0, show_default=True, type=click.IntRange(0), help="Threads (0: all cores).")
@click.option("--cache", "cache_root", type=click.Path(file_okay=False, path_type=Path), help="Crop cache folder (default: DATA/.crops, or the user's cache folder when DATA is read-only).")
@click.option("--workers", default=1, show_default=True, type=click.IntRange(1), help="Processes that build the crop cache.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def eval_cmd(model, data, json_path, md_path, noise, resample, iterations, settle_deg, seed, all_instances, draws,
             base_only, split_mode, split_seed, test_per_object, objects, device, threads, cache_root, workers, quiet):
    """Evaluate MODEL (.pt checkpoint or .onnx) on the test split: per-object mean/std geodesic error (degrees).

    With --all, on every instance of DIR instead (a folder of real frames: `refiner-rt eval M --data
    real_ycbv_dev/test --all`)."""
    from models.evaluate.metrics import format_markdown, format_table
    from models.data.noise import NoiseSpec

    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    try:
        noise = str(NoiseSpec.parse(noise))
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--noise") from None
    obj_list = [o.strip() for o in objects.split(",")] if objects else None
    if all_instances:
        clash = [name for name, given in (("--split-mode", split_mode), ("--split-seed", split_seed),
                                          ("--test-per-object", test_per_object), ("--md", md_path)) if given]
        clash += ["--resample"] * (resample != 1) + ["--iterations"] * (iterations != 1) + (
            ["--settle-deg"] * (settle_deg is not None))
        if clash:
            raise click.UsageError(f"--all scores every instance with --draws inputs each, one pass; it takes none of "
                                   f"{', '.join(clash)}")
        try:
            result = run_eval_all(model, data, noise=noise, draws=draws, seed=seed, objects=obj_list, threads=threads,
                                  cache_root=cache_root, progress=not quiet, device=device, base_only=base_only)
        except (ValueError, FileNotFoundError) as exc:
            raise click.ClickException(str(exc)) from None
        result["command"] = "refiner-rt " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        click.echo(format_all_table(result, f"{model.name} ({result['arch']}, {result['runtime']}) on every instance "
                                            f"of {data}, noise {noise}, {draws} draws; errors in degrees"))
        if json_path:
            json_path.write_text(json.dumps(result, indent=2))
            click.echo(f"Wrote {json_path}")
        return
    if settle_deg is not None and iterations < 2:
        raise click.UsageError("--settle-deg keeps a later iteration where it turns the result by more than DEG: "
                               "give --iterations 2 or more with it")
    try:
        result = run_eval(model, data, noise=noise, resample=resample, iterations=iterations, settle_deg=settle_deg,
                          seed=seed, base_only=base_only,
                          split_mode=split_mode, split_seed=split_seed, test_per_object=test_per_object, objects=obj_list,
                          threads=threads, cache_root=cache_root, workers=workers, progress=not quiet,
                          device=device)
    except (ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    result["command"] = "refiner-rt " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    title = (f"{model.name} ({result['arch']}, {result['runtime']}), split {result['split_mode']}, noise {noise}, "
             f"resample {resample}, iterations {iterations}"
             + (f", settle_deg {settle_deg:g}" if settle_deg is not None else "") + "; errors in degrees")
    click.echo(format_table(result, title))
    if json_path:
        json_path.write_text(json.dumps(result, indent=2))
        click.echo(f"Wrote {json_path}")
    if md_path:
        md_path.write_text(f"{title}\n\n{format_markdown(result)}\n")
        click.echo(f"Wrote {md_path}")
