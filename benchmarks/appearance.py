"""The appearance benchmark: how much real pixels cost the refiners, measured without the real frames kept aside.

Three parts, each optional, one JSON (and a plot):

* ``gap``: the real frames (``--real``, a BOP folder such as ``real_ycbv_dev/test``) against the same frames with
  every annotated object re-drawn at its true pose by the training renderer (``benchmarks/real_rendered.py``). The
  views are the same, so the difference per object is what the real appearance costs.
* ``stress``: the real frames under one camera effect at a time (:data:`STRESS_CASES`: exposure, tone curve, white
  balance and colour cast, saturation, contrast, sharpening, sensor noise, motion and defocus blur, JPEG, a lower
  resolution), each at a strength a real camera gives, applied to the whole frame before the crop
  (:func:`models.data.augment.apply_op`, the training augmentation's own operations). A robust model moves little: the
  table is each case's error minus the clean frames' error.
* ``rendered``: any number of rendered BOP folders (``--rendered NAME=DIR``: e.g. a Blender Cycles validation set and
  TinyRenderer fresh renders of the same layout), scored the same way; the ratio of the first to the second is
  reported.

Every part scores every instance with ``visib_fract >= 0.3`` through the runtime as ``benchmarks/real.py`` does:
``--draws`` coarse inputs U(0, 30) degrees around the truth per instance, one pass, and the drift (the true pose
as the input). Real frames are for measuring only: choose checkpoints on the stress test and the rendered sets, never
on the real frames' own numbers.

Usage (from the repository root)::

    python -m benchmarks.appearance --real REAL [--rendered cycles=DIR --rendered tiny=DIR] \\
        [--model OBJ=PATH ...] --json benchmarks/results/appearance/v6.json --plot benchmarks/results/appearance/v6.png
    python -m benchmarks.appearance --real REAL --rendered cycles=data/ycb9_robot_cycles_val_s43 \\
        --rendered tiny=data/ycb9_robot_tiny_val_s43 --card     # the model card's appearance columns
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from models.evaluate.appearance import CARD_JSON, DEFAULT_WORK, run_gap, run_rendered, run_stress, table
from models.evaluate.record import write_json


def plot(doc: dict, path: Path) -> None:
    """Bars: each stress case's cost (degrees over the clean frames), and the appearance gap per object."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [k for k in ("stress", "gap") if k in doc]
    if not panels:
        return
    fig, axes = plt.subplots(1, len(panels), figsize=(6.5 * len(panels), 4.8), squeeze=False)
    for ax, key in zip(axes[0], panels):
        if key == "stress":
            rows = doc["stress"]["cases"]
            ax.barh([r["case"] for r in rows], [r["cost_deg"] for r in rows], color="tab:orange")
            ax.axvline(1.0, color="grey", ls="--", lw=1)
            ax.set_xlabel("error minus clean frames' (deg)")
            ax.set_title(f"stress test (clean {doc['stress']['clean_deg']:.2f} deg)")
            ax.invert_yaxis()
        else:
            objs = doc["gap"]["objects"]
            ax.barh(list(objs), [v["gap_deg"] for v in objs.values()], color="tab:blue")
            ax.set_xlabel("real minus re-drawn (deg)")
            ax.set_title(f"appearance gap (mean {doc['gap']['gap_deg']:+.2f} deg)")
            ax.invert_yaxis()
    fig.suptitle(f"{doc['models']}: U(0, 30) inputs, one pass", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)

def _named_folder(item: str) -> tuple[str, Path]:
    name, sep, folder = item.partition("=")
    if not sep or not name or not Path(folder).is_dir():
        raise argparse.ArgumentTypeError(f"expected NAME=DIR with DIR a BOP folder; got {item!r}")
    return name, Path(folder)

def main(argv=None) -> int:
    from models.evaluate.real import chosen_models
    from models.evaluate.record import machine, positive_int
    from refiner_rt.metadata import file_sha256

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--real", type=Path, help="a BOP folder of real frames (real_ycbv_dev/test): the gap and stress")
    ap.add_argument("--rendered", type=_named_folder, action="append", default=[], metavar="NAME=DIR",
                    help="a rendered BOP folder to score (repeat; the first two give the ratio)")
    ap.add_argument("--skip", action="append", default=[], choices=("gap", "stress"), help="leave a part out")
    ap.add_argument("--fp32", action="store_true", help="the shipped fp32 files instead of the INT8 ones")
    ap.add_argument("--model", action="append", default=[], metavar="OBJ=PATH",
                    help="score this ONNX file for OBJ instead of the shipped one (repeat); only these objects")
    ap.add_argument("--draws", type=positive_int, default=10, help="coarse inputs per instance (default 10)")
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--work", type=Path, default=DEFAULT_WORK,
                    help=f"cache of the re-drawn and stressed copies (default {DEFAULT_WORK})")
    ap.add_argument("--json", type=Path, help="write the record here")
    ap.add_argument("--plot", type=Path, help="write the bar plot here (PNG)")
    ap.add_argument("--card", action="store_true",
                    help="the shipped INT8 models' record for the model card's appearance columns: needs --real and "
                         "--rendered cycles=DIR --rendered tiny=DIR; writes benchmarks/results/appearance/card.json "
                         "(unless --json), then the card")
    args = ap.parse_args(argv)
    if args.real is None and not args.rendered:
        ap.error("nothing to measure: give --real and/or --rendered NAME=DIR")
    if args.card:
        if args.model or args.fp32:
            ap.error("--card records the shipped INT8 models: it takes neither --model nor --fp32")
        if args.real is None or {"cycles", "tiny"} - {name for name, _ in args.rendered} or args.skip:
            ap.error("--card needs --real REAL, --rendered cycles=DIR and --rendered tiny=DIR, and no --skip")
        if args.json is not None:
            ap.error(f"--card writes the card's record ({CARD_JSON.name}); leave --json out")
        args.json = CARD_JSON
    if args.real is not None and not args.real.is_dir():
        ap.error(f"--real {args.real}: no such folder")
    models = chosen_models(args.model, args.fp32, ap.error)
    t0 = time.perf_counter()
    doc: dict = {"models": "custom" if args.model else ("shipped fp32" if args.fp32 else "shipped INT8"),
                 "draws": args.draws, "seed": args.seed, "noise": "uniform:0:30"}
    if args.model:
        doc["model_files"] = {o: p.name for o, p in models.items()}
    doc["model_sha256"] = {o: file_sha256(p) for o, p in models.items()}
    if args.real is not None:
        doc["real"] = args.real.resolve().parent.name + "/" + args.real.name
        if "gap" not in args.skip:
            doc["gap"] = run_gap(models, args.real, args.work, args.draws, args.seed)
        if "stress" not in args.skip:
            doc["stress"] = run_stress(models, args.real, args.work, args.draws, args.seed)
    if args.rendered:
        doc["rendered"] = run_rendered(models, dict(args.rendered), args.draws, args.seed)
    doc["wall_s"] = round(time.perf_counter() - t0, 1)
    doc["command"] = "python -m benchmarks.appearance " + " ".join(
        "REAL" if args.real is not None and a == str(args.real) else a
        for a in (sys.argv[1:] if argv is None else argv))
    doc["machine"] = machine()
    print(table(doc))
    if args.json:
        write_json(args.json, doc)
        print(f"Wrote {args.json}")
    if args.plot:
        plot(doc, args.plot)
        print(f"Wrote {args.plot}")
    if args.card:
        from export.release.card import write_card
        from models.evaluate.report import write_docs

        write_card(appearance_json=args.json)
        write_docs()
        print("Wrote refiner_rt/weights/models.json, MODELS.md and the README's tables")
    return 0

if __name__ == "__main__":
    sys.exit(main())
