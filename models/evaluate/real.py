"""The shipped refiners on real camera frames: every instance of a BOP or YCB-Video folder, one JSON.

Each shipped model (INT8 by default, ``--fp32`` for the fp32 files, or ``--model OBJ=PATH`` for candidates) scores
every instance of its object in ``--data`` with ``visib_fract >= 0.3`` and its visible box: ``--draws`` coarse inputs
U(0, 30) degrees around the truth per instance, one pass, and the drift (the true pose given as the input); the
master chef can to the closest turn about its axis (``refiner-rt eval --all``, the same code). The nine-object mean
is the mean of the per-object means, as the model card's; the per-video mean averages each object's videos first
(20 frames of one video are nearly one view).

Real frames are for measuring only: never train, calibrate or choose a checkpoint on them. The command is
``python -m benchmarks.real``; the model card's real-frame column comes from :func:`update`.
"""

from __future__ import annotations

import json
from pathlib import Path

from models.evaluate.record import data_name, machine, write_json

# The shipped INT8 models' record on the real dev frames: the model card's real-frame column.
DEFAULT_JSON = Path(__file__).resolve().parents[2] / "benchmarks" / "results" / "real" / "real_ycbv_dev.json"


def shipped_paths(int8: bool = True) -> dict[str, Path]:
    """``{object: ONNX path}`` of the shipped refiners."""
    from refiner_rt.pretrained import pretrained_models

    return {m.object_id: Path(m.path(int8=int8)) for m in pretrained_models()}


def chosen_models(items: list[str], fp32: bool, error) -> dict[str, Path]:
    """``{object: ONNX path}`` from ``--model OBJ=PATH`` items, else the shipped files (fp32 or INT8); ``error``
    (``ArgumentParser.error``) is called with the message for a malformed item or a missing file."""
    if not items:
        return shipped_paths(int8=not fp32)
    models = {}
    for item in items:
        obj, sep, path = item.partition("=")
        if not sep or not Path(path).is_file():
            error(f"--model expects OBJ=PATH to an ONNX file; got {item!r}")
        models[obj] = Path(path)
    return models


def run(models: dict[str, Path], data: Path, draws: int = 10, seed: int = 2024, threads: int = 1,
        progress: bool = False) -> dict:
    """Every model on its object's instances in ``data``; objects with no instance there are listed as skipped.

    Raises:
        ValueError: a model fails on its object's instances, or no model's object has an instance in ``data``.
    """
    from models.evaluate.cli import run_eval_all
    from refiner_rt.metadata import file_sha256

    per_object, skipped = {}, {}
    for obj, path in models.items():
        try:
            r = run_eval_all(path, data, draws=draws, seed=seed, objects=[obj], threads=threads, progress=progress)
        except ValueError as exc:
            if "no samples of" not in str(exc):  # anything but "no instance of obj with visib_fract >= 0.3 here"
                raise ValueError(f"[{obj}] {path.name} on {data}: {exc}") from None
            skipped[obj] = str(exc)
            continue
        per_object[obj] = {**r["objects"][obj], "model": path.name, "sha256": file_sha256(path),
                           "eval_s": round(r["eval_s"], 2), "symmetric": bool(r["protocol"]["symmetries"])}
    if not per_object:
        raise ValueError(f"{data}: no instance of {sorted(models)} with visib_fract >= 0.3")
    return summarise(per_object, skipped, data, draws, seed)


def summarise(per_object: dict, skipped: dict, data: Path, draws: int, seed: int) -> dict:
    """The record of ``per_object`` (object -> its :func:`models.evaluate.cli.run_eval_all` entry): the means over
    objects, over instances and per video."""
    mean = lambda key: sum(o[key] for o in per_object.values()) / len(per_object)  # noqa: E731
    instances = sum(o["instances"] for o in per_object.values())
    return {
        "data": data_name(data), "objects": dict(sorted(per_object.items())), "skipped": skipped,
        "mean_deg": mean("mean_deg"), "input_mean_deg": mean("input_mean_deg"), "drift_mean_deg": mean("drift_mean_deg"),
        "video_mean_deg": mean("video_mean_deg"),
        "instance_mean_deg": sum(o["mean_deg"] * o["instances"] for o in per_object.values()) / instances,
        "instances": instances, "draws": draws, "seed": seed, "noise": "uniform:0:30",
    }


def update(path: Path, models: dict[str, Path], data: Path, draws: int = 10, seed: int = 2024) -> dict:
    """Score ``models`` and merge them into the record at ``path`` (its other objects kept); returns the record."""
    old = json.loads(path.read_text()) if path.is_file() else {"objects": {}}
    new = run(models, data, draws=draws, seed=seed)
    doc = summarise({**old.get("objects", {}), **new["objects"]}, {}, data, draws, seed)
    doc.update(models="shipped INT8", command="python -m benchmarks.real --data REAL --card", machine=machine())
    write_json(path, doc)
    return doc


def table(result: dict) -> str:
    """The record of :func:`run` as a plain-text table, one row per object and the means."""
    head = f"{'object':<22}{'n':>5}{'videos':>8}{'input':>8}{'refined':>9}{'median':>8}{'<5deg':>7}{'drift':>8}"
    lines = [head, "-" * len(head)]
    for obj, o in result["objects"].items():
        lines.append(f"{obj:<22}{o['instances']:>5}{len(o['videos']):>8}{o['input_mean_deg']:>8.2f}{o['mean_deg']:>9.2f}"
                     f"{o['median_deg']:>8.2f}{100 * o['under_5_deg']:>6.0f}%{o['drift_mean_deg']:>8.2f}")
    lines += ["-" * len(head),
              f"{'mean of objects':<22}{result['instances']:>5}{'':>8}{result['input_mean_deg']:>8.2f}"
              f"{result['mean_deg']:>9.2f}{'':>8}{'':>7}{result['drift_mean_deg']:>8.2f}",
              f"per-video mean {result['video_mean_deg']:.2f} deg, over instances {result['instance_mean_deg']:.2f} deg"]
    return "\n".join(lines)
