"""The shipped refiners on real camera frames: every instance of a BOP or YCB-Video folder, one JSON.

Each shipped model (INT8 by default, ``--fp32`` for the fp32 files, or ``--model OBJ=PATH`` for candidates) scores
every instance of its object in ``--data`` (:mod:`models.evaluate.real`). Real frames are for measuring only: never
train, calibrate or choose a checkpoint on them.

Usage (from the repository root)::

    python -m benchmarks.real --data REAL [--json PATH | --card]   # REAL: a BOP folder of real frames (real_ycbv_dev/test)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from models.evaluate.real import DEFAULT_JSON, chosen_models, run, table
from models.evaluate.record import machine, positive_int, write_json


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="a BOP split folder or YCB-Video root of real frames")
    ap.add_argument("--fp32", action="store_true", help="the shipped fp32 files instead of the INT8 ones")
    ap.add_argument("--model", action="append", default=[], metavar="OBJ=PATH",
                    help="score this ONNX file for OBJ instead of the shipped one (repeat); only these objects")
    ap.add_argument("--draws", type=positive_int, default=10, help="coarse inputs per instance (default 10)")
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
    t0 = time.perf_counter()
    try:
        result = run(models, args.data, draws=args.draws, seed=args.seed, threads=args.threads)
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    result["models"] = "custom" if args.model else ("shipped fp32" if args.fp32 else "shipped INT8")
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    result["command"] = "python -m benchmarks.real " + " ".join(
        "REAL" if a == str(args.data) else a for a in (sys.argv[1:] if argv is None else argv))
    result["machine"] = machine()
    print(f"{result['models']} on every instance of {args.data} (visib_fract >= 0.3), U(0, 30) inputs x "
          f"{args.draws}, one pass; degrees")
    print(table(result))
    if args.json:
        write_json(args.json, result)
        print(f"Wrote {args.json}")
    if args.card:
        from export.release.card import write_card
        from models.evaluate.report import write_docs

        write_card(real_json=args.json)
        write_docs()
        print("Wrote refiner_rt/weights/models.json, MODELS.md and the README's tables")
    return 0


if __name__ == "__main__":
    sys.exit(main())
