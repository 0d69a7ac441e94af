"""Where on rendered scenes a network with an input turn loses or gains against one without: the error per bin of
the true pose's roll about the viewing ray (the image angle of the object's z axis, the turn's own rule,
``refiner_rt.preprocess.roll_angle``) and of the angle between the object's z axis and the ray.

Every model is scored on the same crops and coarse poses (every instance of the object in ``--data``, U(0, 30) inputs,
``--draws`` per instance, one pass, through the runtime), so the bins compare like with like.

Usage (from the repository root)::

    python -m benchmarks.studies.real_levers.roll_bins --data data/ycb9_fresh_s21 --object 037_scissors \\
        --model v5=runs/v5_shipped/037_scissors.onnx --model roll=runs/levers/mix-long_roll/037_scissors.onnx \\
        --json benchmarks/studies/real_levers/roll_bins_037_scissors.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]

from models.evaluate.record import data_name
from models.evaluate.record import write_json

ROLL_BINS = ((0, 15), (15, 45), (45, 90), (90, 180.01))  # |roll|, degrees
AXIS_BINS = ((0, 20), (20, 30), (30, 40), (40, 60), (60, 90.01))  # z axis to the ray, degrees


def bins(q_true: np.ndarray) -> dict[str, np.ndarray]:
    """Per instance: ``roll`` (|roll angle|, degrees) and ``axis`` (angle between the object's z axis and the viewing
    ray, degrees, 0-90) of the true rotations ``q_true`` (``(N, 4)`` wxyz, ray frame)."""
    from refiner_rt.preprocess import roll_angles

    w, x, y, z = q_true.T
    zx, zy, zz = 2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)  # the object z axis
    return {"roll": np.abs(np.degrees(roll_angles(q_true))),
            "axis": np.degrees(np.arctan2(np.hypot(zx, zy), np.abs(zz)))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="a folder of rendered scenes (BOP)")
    ap.add_argument("--object", required=True, help="YCB id")
    ap.add_argument("--model", action="append", required=True, metavar="NAME=ONNX", help="a model to score (repeatable)")
    ap.add_argument("--draws", type=int, default=2, help="coarse poses per instance (default 2)")
    ap.add_argument("--cache", type=Path, help="crop cache folder (default DATA/.crops)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    models = {}
    for spec in args.model:
        name, sep, path = spec.partition("=")
        if not sep or not name or not Path(path).is_file():
            ap.error(f"--model: expected NAME=ONNX with an existing file; got {spec!r}")
        models[name] = Path(path)
    from models.data.pipeline import whole_folder_spec
    from models.evaluate.errors import evaluate_errors, onnx_predictor
    from models.data.pipeline import cropset_for, load_splits

    t0 = time.perf_counter()
    spec = whole_folder_spec(args.data, args.object, "test")
    test = cropset_for(load_splits(spec), "test", spec, 64, 1.2, cache_root=args.cache or args.data / ".crops",
                       progress=False)
    errors = {name: evaluate_errors(onnx_predictor(path, threads=1), test, rotation_frame="ray", resample=args.draws)
              for name, path in models.items()}
    first = next(iter(errors.values()))
    where = bins(first.q_true)
    table = {"all": {"n": len(first.err_out_deg), **{m: round(float(e.err_out_deg.mean()), 3)
                                                      for m, e in errors.items()}}}
    for key, edges in (("roll", ROLL_BINS), ("axis", AXIS_BINS)):
        for lo, hi in edges:
            sel = (where[key] >= lo) & (where[key] < hi)
            table[f"{key} {lo}-{min(hi, 180 if key == 'roll' else 90):g}"] = {
                "n": int(sel.sum()), **{m: round(float(e.err_out_deg[sel].mean()), 3) if sel.any() else None
                                        for m, e in errors.items()}}
    names = list(models)
    print("| bin (degrees) | instances x draws | " + " | ".join(names) + " |")
    print("|---|---:|" + "---:|" * len(names))
    for label, row in table.items():
        print(f"| {label} | {row['n']} | " + " | ".join("-" if row[m] is None else f"{row[m]:.2f}" for m in names)
              + " |")
    if args.json:
        write_json(args.json, {"data": data_name(args.data), "object": args.object, "draws": args.draws,
                               "models": {m: str(p.resolve().relative_to(ROOT)) if p.resolve().is_relative_to(ROOT) else p.name
                                          for m, p in models.items()},
                               "bins": table, "wall_s": round(time.perf_counter() - t0, 1)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
