"""The shipped refiners on real camera frames: every instance of a BOP or YCB-Video folder, one JSON.

Each shipped model (INT8 by default, ``--fp32`` for the fp32 files, or ``--model OBJ=PATH`` for candidates) scores
every instance of its object in ``--data`` with ``visib_fract >= 0.3`` and its visible box: ``--draws`` coarse inputs
U(0, 30) degrees around the truth per instance, one pass, and the drift (the true pose given as the input); the
master chef can to the closest turn about its axis (``refiner-rt eval --all``, the same code). The nine-object mean
is the mean of the per-object means, as the model card's; the per-video mean averages each object's videos first
(20 frames of one video are nearly one view).

Real frames are for measuring only: never train, calibrate or choose a checkpoint on them.

Usage (from the repository root)::

    python benchmarks/real.py --data REAL [--json PATH | --card]   # REAL: a BOP folder of real frames (real_ycbv_dev/test)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.study_cli import write_json  # noqa: E402

DEFAULT_JSON = REPO / "benchmarks" / "results" / "real" / "real_ycbv_dev.json"


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
    """Every model on its object's instances in ``data``; objects with no instance there are listed as skipped."""
    from models.evaluate.cli import run_eval_all
    from refiner_rt.metadata import file_sha256

    per_object, skipped = {}, {}
    for obj, path in models.items():
        try:
            r = run_eval_all(path, data, draws=draws, seed=seed, objects=[obj], threads=threads, progress=progress)
        except ValueError as exc:
            if "no samples of" not in str(exc):  # anything but "no instance of obj with visib_fract >= 0.3 here"
                raise SystemExit(f"[{obj}] {path.name} on {data}: {exc}") from None
            skipped[obj] = str(exc)
            continue
        per_object[obj] = {**r["objects"][obj], "model": path.name, "sha256": file_sha256(path),
                           "eval_s": round(r["eval_s"], 2), "symmetric": bool(r["protocol"]["symmetries"])}
    if not per_object:
        raise SystemExit(f"{data}: no instance of {sorted(models)} with visib_fract >= 0.3")
    return summarise(per_object, skipped, data, draws, seed)


def summarise(per_object: dict, skipped: dict, data: Path, draws: int, seed: int) -> dict:
    """The record of ``per_object`` (object -> its :func:`models.evaluate.cli.run_eval_all` entry): the means over
    objects, over instances and per video."""
    mean = lambda key: sum(o[key] for o in per_object.values()) / len(per_object)  # noqa: E731
    instances = sum(o["instances"] for o in per_object.values())
    return {
        "data": _data_name(data), "objects": dict(sorted(per_object.items())), "skipped": skipped,
        "mean_deg": mean("mean_deg"), "input_mean_deg": mean("input_mean_deg"), "drift_mean_deg": mean("drift_mean_deg"),
        "video_mean_deg": mean("video_mean_deg"),
        "instance_mean_deg": sum(o["mean_deg"] * o["instances"] for o in per_object.values()) / instances,
        "instances": instances, "draws": draws, "seed": seed, "noise": "uniform:0:30",
    }


def update(path: Path, models: dict[str, Path], data: Path, draws: int = 10, seed: int = 2024) -> dict:
    """Score ``models`` and merge them into the record at ``path`` (its other objects kept); returns the record."""
    from benchmarks.pretrained import machine

    old = json.loads(path.read_text()) if path.is_file() else {"objects": {}}
    new = run(models, data, draws=draws, seed=seed)
    doc = summarise({**old.get("objects", {}), **new["objects"]}, {}, data, draws, seed)
    doc.update(models="shipped INT8", command="python benchmarks/real.py --data REAL --card", machine=machine())
    write_json(path, doc)
    return doc


def _data_name(data: Path) -> str:
    """The folder's name as the card prints it: a BOP split folder by its dataset's name (``real_ycbv_dev/test``)."""
    data = Path(data).resolve()
    return f"{data.parent.name}/{data.name}" if data.name in ("test", "val", "train") else data.name


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1; got {text}")
    return value


def table(result: dict) -> str:
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="a BOP split folder or YCB-Video root of real frames")
    ap.add_argument("--fp32", action="store_true", help="the shipped fp32 files instead of the INT8 ones")
    ap.add_argument("--model", action="append", default=[], metavar="OBJ=PATH",
                    help="score this ONNX file for OBJ instead of the shipped one (repeat); only these objects")
    ap.add_argument("--draws", type=_positive_int, default=10, help="coarse inputs per instance (default 10)")
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, help=f"write the result (the shipped models' record: {DEFAULT_JSON.name})")
    ap.add_argument("--card", action="store_true",
                    help="the shipped INT8 models' record: write it to benchmarks/results/real/real_ycbv_dev.json, then "
                         "the model card, refiner_rt/weights/models.json and the README's tables from it")
    args = ap.parse_args(argv)
    if args.card:
        if args.model or args.fp32:
            ap.error("--card records the shipped INT8 models: it takes neither --model nor --fp32")
        args.json = args.json or DEFAULT_JSON
    if not args.data.is_dir():
        ap.error(f"--data {args.data}: no such folder")
    models = chosen_models(args.model, args.fp32, ap.error)
    from benchmarks.pretrained import machine

    t0 = time.perf_counter()
    result = run(models, args.data, draws=args.draws, seed=args.seed, threads=args.threads)
    result["models"] = "custom" if args.model else ("shipped fp32" if args.fp32 else "shipped INT8")
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    result["command"] = "python benchmarks/real.py " + " ".join(
        "REAL" if a == str(args.data) else a for a in (sys.argv[1:] if argv is None else argv))
    result["machine"] = machine()
    print(f"{result['models']} on every instance of {args.data} (visib_fract >= 0.3), U(0, 30) inputs x "
          f"{args.draws}, one pass; degrees")
    print(table(result))
    if args.json:
        write_json(args.json, result)
        print(f"Wrote {args.json}")
    if args.card:
        from benchmarks import pretrained, report

        pretrained.REAL_JSON = args.json
        pretrained.write_card()
        report.main([])
        print("Wrote refiner_rt/weights/models.json, MODELS.md and the README's tables")
    return 0


if __name__ == "__main__":
    sys.exit(main())
