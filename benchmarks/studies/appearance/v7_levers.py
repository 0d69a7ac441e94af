"""Version 7 pilot: does a training lever make the shipped refiner robust to appearance? Three seeds per row.

Every row continues one object's version-6 model (its fp32 file in the package, recovered as
``export/release/coarse.py build`` does) for ``--samples`` samples on the robot-layout renders with the version-6
recipe (``robot-roll-v6``: the fusion network with the canonical roll, box and colour jitter, new backgrounds for half
the crops, float32, one thread), changing one thing:

===========  ===================================================================================================
lever        training
===========  ===================================================================================================
``control``  the version-6 recipe as it is: the same amount of further training, so a lever's gain is not the
             gain of training longer
``photo``    plus camera-like photometric augmentation at the probabilities the BOP winners use
             (:data:`PHOTO`: CosyPose's and GDRNPP's lists, the strengths of models.data.augment)
``aa``       the network's crop filter ``antialias`` (block averages before the crop's bilinear shrink,
             docs/design.md §3) in training as at run time; version 6 had it at run time only
``norm``     the network's input normalisation ``per_crop`` (each crop by its own per-channel mean and spread,
             inside the graph: a gain and an offset per channel, such as exposure and white balance, cancel)
``photo_norm`` ``photo`` and ``norm`` together
``photo_half_norm`` ``norm`` with ``photo`` at half its probabilities (:data:`PHOTO_HALF`): does a milder
             augmentation keep the Cycles set's gain without ``photo``'s cost on the TinyRenderer renders?
===========  ===================================================================================================

Each row is trained with ``--seeds`` (three by default: a seed alone moves a row by up to 3 degrees at this size),
exported (fp32) and scored where appearance is the problem, which is where the choice is made:

- the photometric stress test of :mod:`benchmarks.appearance` on the real dev frames (19 camera effects, the cost
  against the clean frames; the frames only measure, the cost is what is compared),
- the Cycles validation set and its TinyRenderer twin (``--cycles``, ``--tiny``: the ratio), and fresh robot-layout
  renders (``--fresh``), one coarse input per instance for the renders, 10 per instance for the frames;
- the real dev frames (``--real``) are reported beside, never chosen on.

Usage (from the repository root; resumable: a finished row is kept in the JSON, a trained checkpoint is reused; a
rendered set left out, e.g. while it renders, is scored on the next run that names it, from the rows' models in
``--run``)::

    python -m benchmarks.studies.appearance.v7_levers --robot data/ycb9_robot --real REAL \\
        --cycles data/ycb9_robot_cycles_val_s43 --tiny data/ycb9_robot_tiny_val_s43 \\
        --fresh data/ycb9_robot_fresh_s41 --objects 006_mustard_bottle,011_banana \\
        --run ~/.cache/refiner-rt/runs/v7_levers --samples 60000 \\
        --json benchmarks/studies/appearance/v7_levers.json
    python -m benchmarks.studies.appearance.v7_levers --table benchmarks/studies/appearance/v7_levers.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from models.evaluate.record import write_json

# CosyPose trains on renders with blur (p 0.4), sharpness, contrast and colour (0.3 each) and brightness (0.5);
# GDRNPP adds noise, JPEG-like degradation and colour casts at about 0.3 each. models.data.augment's strengths are a
# working camera's (narrower than theirs); the probabilities are theirs.
PHOTO = {"downscale": 0.2, "motion_blur": 0.2, "blur": 0.4, "sensor_noise": 0.3, "white_balance": 0.3,
         "brightness": 0.5, "gamma": 0.3, "contrast": 0.3, "colour": 0.3, "sharpness": 0.3, "jpeg": 0.3}
PHOTO_HALF = {name: p / 2 for name, p in PHOTO.items()}
LEVERS = {"control": {}, "photo": PHOTO, "aa": {}, "norm": {}, "photo_norm": PHOTO, "photo_half_norm": PHOTO_HALF}
CONFIG = {"aa": {"crop_filter": "antialias"}, "norm": {"input_norm": "per_crop"},
          "photo_norm": {"input_norm": "per_crop"},
          "photo_half_norm": {"input_norm": "per_crop"}}  # network config keys a lever sets


def row_folder(run: Path, lever: str, seed: int) -> Path:
    return run / f"{lever}_seed{seed}"


def train_row(lever: str, obj: str, data: Path, run: Path, samples: int, sizes: int, seed: int) -> tuple[Path, dict]:
    """Train ``obj`` for ``lever`` with ``seed`` (reusing its checkpoint when there) and export it (fp32)."""
    from export.release.coarse import card_command, data_scaling_command, recover_shipped, run_training_command
    from export.onnx_export import export_checkpoint

    folder = row_folder(run, lever, seed)
    folder.mkdir(parents=True, exist_ok=True)
    cache = run / "cache"
    weights = None
    if CONFIG.get(lever, {}).get("crop_filter"):  # the shipped weights with the lever's crop filter to start from
        from export.crop_filter import with_crop_filter
        from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name

        weights = run / f"shipped_{CONFIG[lever]['crop_filter']}"
        weights.mkdir(parents=True, exist_ok=True)
        name = model_file_name(obj, int8=False)
        if not (weights / name).is_file():
            with_crop_filter(WEIGHTS_DIR / name, weights / name, CONFIG[lever]["crop_filter"])
    init_dir = run / ("init" if weights is None else f"init_{weights.name}")
    init_dir.mkdir(exist_ok=True)
    init, _ = recover_shipped(obj, data, init_dir, cache, weights=weights, any_version=True)
    # the version-6 split of the same set (its validation and test scenes stay out of training)
    cmd = data_scaling_command(data, obj, folder, samples, sizes, cache, init=init,
                        photometric=LEVERS[lever], seed=seed)
    if lever in CONFIG:
        at = cmd.index("--config") + 1
        cmd[at] = json.dumps({**json.loads(cmd[at]), **CONFIG[lever]})
    t0 = time.perf_counter()
    ckpt = run_training_command(cmd, folder / obj, folder / f"{obj}.log", obj)
    train_s = time.perf_counter() - t0
    onnx = folder / f"{obj}.onnx"
    if not onnx.is_file():
        export_checkpoint(ckpt, onnx)
    row = json.loads((folder / f"{obj}.train.json").read_text())["rows"][-1]
    return onnx, {"command": card_command(cmd), "train_s": round(train_s, 1),
                  **{k: row.get(k) for k in ("train_crops", "samples", "val_mean_deg", "wall_s")}}


def score(onnx: Path, obj: str, real: Path, rendered: dict[str, Path], work: Path) -> dict:
    """The stress test on ``real`` (clean, worst and mean cost), and each rendered set's mean and drift."""
    from models.evaluate.appearance import run_stress

    stress = run_stress({obj: onnx}, real, work, draws=10, seed=2024, progress=False)
    out = {"real": {"mean_deg": round(stress["clean_deg"], 3), "drift_mean_deg": round(stress["clean_drift_deg"], 3)},
           "stress": {"worst_case": stress["worst_case"], "worst_cost_deg": round(stress["worst_cost_deg"], 3),
                      "mean_cost_deg": round(stress["mean_cost_deg"], 3),
                      "cases": {c["case"]: round(c["cost_deg"], 3) for c in stress["cases"]}}}
    return {**out, **score_rendered(onnx, obj, rendered)}


def score_rendered(onnx: Path, obj: str, rendered: dict[str, Path], row: dict | None = None) -> dict:
    """Each rendered set's mean and drift (one coarse input per instance), and the Cycles set's ratio to its
    TinyRenderer twin when both are scored (here or already in ``row``)."""
    from models.evaluate.appearance import run_rendered

    sets = run_rendered({obj: onnx}, rendered, draws=1, seed=2024)["sets"]
    out = {name: {"mean_deg": round(s["mean_deg"], 3), "drift_mean_deg": round(s["drift_mean_deg"], 3),
                  "instances": s["instances"]} for name, s in sets.items()}
    both = {**(row or {}), **out}
    if "cycles" in both and "tiny" in both:
        out["cycles_ratio"] = round(both["cycles"]["mean_deg"] / both["tiny"]["mean_deg"], 3)
    return out


METRICS = (("real", "mean_deg", "dev real"), ("real", "drift_mean_deg", "dev drift"),
           ("stress", "worst_cost_deg", "stress worst"), ("stress", "mean_cost_deg", "stress mean"),
           ("cycles", "mean_deg", "Cycles val"), ("tiny", "mean_deg", "tiny twin"),
           ("fresh", "mean_deg", "fresh robot"))


def table(doc: dict) -> str:
    """Markdown: per object and lever the median over seeds (min-max) of each measure, then per lever the change
    against ``control`` averaged over objects (medians over seeds)."""
    rows = doc["rows"]
    objects = sorted({r["object"] for r in rows})
    levers = [lv for lv in ("v6", *LEVERS) if any(r["lever"] == lv for r in rows)]
    head = "| object | lever | seeds | " + " | ".join(m[2] for m in METRICS) + " |"
    lines = [head, "|---|---|---:|" + "---:|" * len(METRICS)]
    med: dict = {}
    for obj in objects:
        for lv in levers:
            got = [r for r in rows if r["object"] == obj and r["lever"] == lv]
            if not got:
                continue
            cells = []
            for part, key, label in METRICS:
                vals = [r[part][key] for r in got if part in r]
                if not vals:
                    cells.append("-")
                    continue
                med[(obj, lv, label)] = statistics.median(vals)
                cells.append(f"{statistics.median(vals):.2f}" + (f" ({min(vals):.2f}-{max(vals):.2f})"
                                                                  if len(vals) > 1 else ""))
            lines.append(f"| {obj} | `{lv}` | {len(got)} | " + " | ".join(cells) + " |")
    lines += ["", "| lever | objects | " + " | ".join(f"{m[2]}: change" for m in METRICS) + " |",
              "|---|---:|" + "---:|" * len(METRICS)]
    for lv in levers:
        if lv == "control":
            continue
        got = [o for o in objects if (o, lv, METRICS[0][2]) in med and (o, "control", METRICS[0][2]) in med]
        if not got:
            continue
        cells = []
        for _, _, label in METRICS:
            d = [med[(o, lv, label)] - med[(o, "control", label)] for o in got
                 if (o, lv, label) in med and (o, "control", label) in med]
            cells.append(f"{sum(d) / len(d):+.2f}" if d else "-")
        lines.append(f"| `{lv}` | {len(got)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--table", type=Path, metavar="JSON", help="print the Markdown table of this record and stop")
    ap.add_argument("--robot", type=Path, help="training scenes, robot layout (what version 6 trained on)")
    ap.add_argument("--real", type=Path, help="real frames (BOP): the stress test; measured only")
    ap.add_argument("--cycles", type=Path, help="the Cycles validation set (robot layout, never trained on)")
    ap.add_argument("--tiny", type=Path, help="its TinyRenderer twin (the same arrangements)")
    ap.add_argument("--fresh", type=Path, help="fresh robot-layout renders no model trained on")
    ap.add_argument("--objects", default="006_mustard_bottle,011_banana", help="comma-separated YCB ids")
    ap.add_argument("--levers", default="v6," + ",".join(LEVERS),
                    help=f"comma-separated, of v6 (the shipped fp32 model, no training), {', '.join(LEVERS)}")
    ap.add_argument("--seeds", default="0,1,2", help="training seeds of every trained row (comma-separated)")
    ap.add_argument("--run", type=Path, help="scratch folder of checkpoints and crop caches (keep it outside the "
                    "work tree: a later session resumes from it)")
    ap.add_argument("--samples", type=int, default=60_000, help="training samples per row")
    ap.add_argument("--sizes", type=int, default=16_000, help="training crops per object the split is drawn with "
                    "(default: the recipe's, every crop of the robot set)")
    ap.add_argument("--work", type=Path, help="stressed copies of --real (default: benchmarks.appearance's cache)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if args.table:
        print(table(json.loads(args.table.read_text())))
        return 0
    missing = [f"--{k}" for k in ("robot", "real", "run", "json") if getattr(args, k) is None]
    if missing:
        ap.error(f"{', '.join(missing)} required (or --table JSON)")
    if not (args.cycles or args.tiny or args.fresh):
        ap.error("at least one rendered set to score: --cycles, --tiny or --fresh")
    from models.evaluate.appearance import DEFAULT_WORK
    from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name

    levers = args.levers.split(",")
    bad = [lv for lv in levers if lv not in ("v6", *LEVERS)]
    if bad:
        ap.error(f"--levers: unknown {bad}; expected of v6, {', '.join(LEVERS)}")
    seeds = [int(s) for s in args.seeds.split(",")]
    rendered = {k: v for k, v in {"cycles": args.cycles, "tiny": args.tiny, "fresh": args.fresh}.items() if v}
    doc = json.loads(args.json.read_text()) if args.json.is_file() else {"rows": []}
    doc.update(samples=args.samples, photo=PHOTO, robot=args.robot.name,
               rendered={**doc.get("rendered", {}), **{k: v.name for k, v in rendered.items()}})
    done = {(r["object"], r["lever"], r.get("seed")) for r in doc["rows"]}
    # a row scored before a set existed (e.g. the Cycles set still rendering) is scored on it now, from its model
    for row in doc["rows"]:
        later = {k: v for k, v in rendered.items() if k not in row}
        onnx = (WEIGHTS_DIR / model_file_name(row["object"], int8=False) if row["lever"] == "v6"
                else row_folder(args.run, row["lever"], row["seed"]) / f"{row['object']}.onnx")
        if later and onnx.is_file():
            row.update(score_rendered(onnx, row["object"], later, row))
            write_json(args.json, doc)
            print(f"[{row['object']}] {row['lever']} seed {row.get('seed')}: scored on {', '.join(later)}", flush=True)
    # seeds outermost: the first complete comparison (one seed of every lever) comes first
    plan = [(obj, "v6", None) for obj in args.objects.split(",") if "v6" in levers]
    plan += [(obj, lv, s) for s in seeds for obj in args.objects.split(",") for lv in levers if lv != "v6"]
    for obj, lever, seed in plan:
        if (obj, lever, seed) in done:
            continue
        t0 = time.perf_counter()
        if lever == "v6":
            onnx, record = WEIGHTS_DIR / model_file_name(obj, int8=False), {}
        else:
            onnx, record = train_row(lever, obj, args.robot, args.run, args.samples, args.sizes, seed)
        row = {"object": obj, "lever": lever, **({} if seed is None else {"seed": seed}), **record,
               **score(onnx, obj, args.real, rendered, args.work or DEFAULT_WORK)}
        row["row_s"] = round(time.perf_counter() - t0, 1)
        doc["rows"].append(row)
        write_json(args.json, doc)
        sets = ", ".join(f"{k} {row[k]['mean_deg']:.2f}" for k in rendered)
        print(f"[{obj}] {lever} seed {seed}: stress worst {row['stress']['worst_cost_deg']:+.2f}, {sets}, "
              f"dev {row['real']['mean_deg']:.2f} ({row['row_s']:.0f} s)", flush=True)
    print(table(doc))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
