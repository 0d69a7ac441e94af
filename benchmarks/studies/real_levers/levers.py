"""What each lever gives on real camera frames: the scene layout, camera-like photometric augmentation, and both.

Every row continues one object's version-5 model (its fp32 file in ``--v5``, a copy of what shipped, recovered as
``export/release/coarse.py build`` does) for ``--samples`` samples with the build's recipe (``robot-real-v6``'s
network, rates and jitter: box and colour jitter, new backgrounds for half the crops, float32, one thread), with or
without its photometric augmentation, changing one thing:

=====================  ========================================================================================
lever                  training data, augmentation
=====================  ========================================================================================
``v5``                 no training: the version-5 model
``tabletop``           scenes of the earlier layout (``render --layout tabletop``), the recipe's augmentation
``tabletop+photo``     the same scenes, plus the photometric augmentation of ``robot-real-v6`` (models.data.augment)
``robot``              scenes of the robot layout (``render``'s default), the recipe's augmentation
``robot+photo``        the robot scenes plus the photometric augmentation: ``robot-real-v6``
``robot-long``         ``robot`` on every training crop of the set (about 5,000) for ``--long-samples`` samples
``mix-long``           ``robot-long`` with every crop of ``--mix`` (tabletop scenes of ids that the robot set
                       does not use) joining the training part
``cycles``             ``--cycles``: Blender Cycles renders of the robot set's arrangements (``render --engine
                       cycles`` with the robot set's seed, so scene i is the robot set's scene i seen along another
                       camera path), the recipe's augmentation
``robot-same-scenes``  the control for ``cycles``: the robot set's TinyRenderer images of the same scenes (the
                       scenes ``--cycles`` holds), split by the same rule with the same sizes
``tabletop+inplane``   ``tabletop`` with every training crop turned about the viewing ray by up to ``--inplane``
                       degrees, the coarse pose with it (``refiner-rt train --inplane``): rolls of the object about
                       the ray that no training scene had, as an object leaning on another or a tilted camera shows
``robot+inplane``      ``robot`` with the same turns
``mix-long+inplane``   ``mix-long`` with the same turns (``robot-long+inplane`` likewise)
``tabletop+roll``      ``tabletop`` with the network's canonical roll (``models.nets.fusion.canonical_roll``): every crop
                       is turned, inside the network, so that the coarse pose's object z axis points up in it, so the
                       network sees each viewing direction at one roll (``robot+roll``, ``mix-long+roll`` likewise)
``tabletop+quarter``   ``tabletop`` with the canonical roll in quarter turns (``models.nets.fusion.quarter_roll``): a crop
                       whose axis points within 45 degrees of up is left as it is, the others are turned by 90, 180
                       or 270 degrees (``mix-long+quarter`` likewise)
=====================  ========================================================================================

The ``tabletop`` row is the control: the same amount of further training on the kind of scenes the model already saw.
Each model (fp32, exported and parity-checked) is then scored on every instance of its object in the real frames
(``--real``: U(0, 30) inputs x 10 draws, one pass, and the drift from the true pose; ``refiner-rt eval --all``) and in
rendered scenes no model trained on (``--fresh``: the model card's ``ycb9_fresh_s21``, tabletop layout; ``--fresh-robot``,
robot layout), one draw each. The real frames only measure; nothing is chosen on them per model.

Usage (from the repository root; resumable: a finished row is kept in the JSON, a trained checkpoint is reused)::

    python -m benchmarks.studies.real_levers.levers --robot data/ycb9_robot --tabletop data/ycb9_tabletop_s32 \\
        --real REAL --fresh data/ycb9_fresh_s21 --fresh-robot data/ycb9_robot_fresh_s41 \\
        --objects 006_mustard_bottle,011_banana --run runs/levers --v5 runs/v5_shipped --samples 60000 \\
        --json benchmarks/studies/real_levers/levers.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from models.evaluate.record import data_name
from models.evaluate.record import write_json

LEVERS = ("v5", "tabletop", "tabletop+photo", "robot", "robot+photo", "robot-long", "mix-long", "cycles",
          "robot-same-scenes", "tabletop+inplane", "robot+inplane", "robot-long+inplane", "mix-long+inplane",
          "tabletop+roll", "robot+roll", "mix-long+roll", "tabletop+quarter", "mix-long+quarter")


def photometric() -> dict:
    """The photometric augmentation of the ``robot-real-v6`` recipe: ``{operation: probability}``."""
    from models.train.recipe import NAMED_RECIPES

    return {k[len("aug_"):]: v for k, v in NAMED_RECIPES["robot-real-v6"].items() if k.startswith("aug_")}


def row_folder(run: Path, lever: str, seed: int | None = None, inplane: float | None = None) -> Path:
    """Where a row trains (its checkpoint, log and fp32 ONNX file): ``run/<lever>[<inplane>][_seed<seed>]``."""
    return run / (lever.replace("+", "_") + ("" if inplane is None else f"{inplane:g}")
                  + ("" if seed is None else f"_seed{seed}"))


def score_redrawn(docs: list[dict], run: Path, v5: Path, redrawn: Path) -> dict:
    """Every row of ``docs`` scored again, as on the real frames (10 draws, the drift), on ``redrawn``: the real frames
    with their objects re-drawn at the true poses (``benchmarks/real_rendered.py``), so that a row's gain on the
    view can be told from its gain on the appearance. ``{label: {object: {"mean_deg", "drift_mean_deg"}}}``."""
    from models.evaluate.cli import run_eval_all
    from refiner_rt.pretrained import model_file_name

    out: dict = {}
    for row in (r for doc in docs for r in doc["rows"]):
        obj, lever = row["object"], row["lever"]
        onnx = (v5 / model_file_name(obj, int8=False) if lever == "v5"
                else row_folder(run, lever, row.get("seed"), row.get("inplane_deg")) / f"{obj}.onnx")
        if not onnx.is_file():
            raise SystemExit(f"{onnx}: the row's model is not there (--run and --v5 as when the rows were trained)")
        r = run_eval_all(onnx, redrawn, objects=[obj], draws=10, threads=1, progress=False)["objects"][obj]
        out.setdefault(_label(row), {})[obj] = {"mean_deg": round(r["mean_deg"], 3),
                                               "drift_mean_deg": round(r["drift_mean_deg"], 3)}
    return out


def redrawn_table(scores: dict, real_rows: list[dict]) -> str:
    """Markdown: per object and row, the real frames' mean beside the re-drawn frames' mean and drift."""
    real = {(r["object"], _label(r)): r["real"] for r in real_rows}
    lines = ["| object | lever | real frames: mean | re-drawn: mean | re-drawn: drift |", "|---|---|---:|---:|---:|"]
    for obj in sorted({o for per in scores.values() for o in per}):
        for label, per in scores.items():
            if obj in per:
                lines.append(f"| {obj} | `{label}` | {real[(obj, label)]['mean_deg']:.2f} | {per[obj]['mean_deg']:.2f} "
                             f"| {per[obj]['drift_mean_deg']:.2f} |")
    return "\n".join(lines)


def train_row(lever: str, obj: str, data: Path, run: Path, samples: int, sizes: int, v5: Path,
              extra_train: tuple = (), seed: int | None = None, inplane: float = 0.0) -> tuple[Path, dict]:
    """Train ``obj`` for ``lever`` (its checkpoint reused when it exists) and export it: ``(fp32 ONNX, record)``.
    ``seed``: the training run's seed (default: the recipe's), to see how much a row moves with it alone;
    ``inplane``: the largest in-plane turn of the ``+inplane`` levers (degrees)."""
    from export.release.coarse import card_command, data_scaling_command, recover_shipped, run_training_command
    from export.onnx_export import export_checkpoint

    turns = lever.endswith("+inplane")
    roll = {"+roll": "canonical", "+quarter": "quarter"}.get(lever[lever.rfind("+"):]) if "+" in lever else None
    folder = row_folder(run, lever, seed, inplane if turns else None)
    folder.mkdir(parents=True, exist_ok=True)
    cache = run / "cache"
    (run / data.name).mkdir(exist_ok=True)  # the version-5 checkpoint, its batch-norm statistics from data's crops
    init, _ = recover_shipped(obj, data, run / data.name, cache, weights=v5)
    # The split's validation and test parts are small: the rows are scored on the real frames and fresh renders.
    cmd = data_scaling_command(data, obj, folder, samples, sizes, cache, val=200, test=100, init=init, extra_train=extra_train,
                        photometric=photometric() if lever.endswith("+photo") else {}, seed=seed,
                        inplane=inplane if turns else 0.0, roll=roll)
    t0 = time.perf_counter()
    ckpt = run_training_command(cmd, folder / obj, folder / f"{obj}.log", obj)
    train_s = time.perf_counter() - t0
    onnx = folder / f"{obj}.onnx"
    if not onnx.is_file():
        export_checkpoint(ckpt, onnx)
    row = json.loads((folder / f"{obj}.train.json").read_text())["rows"][-1]
    from export.release.coarse import RECIPE_NAME

    return onnx, {"recipe": RECIPE_NAME, **({} if seed is None else {"seed": seed}),
                  **({"inplane_deg": inplane} if turns else {}), **({"roll": roll} if roll else {}),
                  "command": card_command(cmd),
                  "train_s": round(train_s, 1),
                  **{k: row.get(k) for k in ("train_crops", "samples", "val_mean_deg", "mean_deg", "wall_s")}}


def same_scenes(robot: Path, cycles: Path, run: Path) -> Path:
    """A folder in ``run`` of links to the scenes of ``robot`` that ``cycles`` rendered too (the same seed and scene
    ids: the same arrangements), so that a control row trains on the TinyRenderer images of exactly those scenes.

    Raises:
        SystemExit: the two sets were not rendered from the same seed, or ``robot`` lacks one of the scenes.
    """
    def seed(folder):
        return json.loads((folder / "render_config.json").read_text()).get("seed")

    if seed(robot) != seed(cycles):
        raise SystemExit(f"--cycles {cycles} was rendered with seed {seed(cycles)} and --robot {robot} with "
                         f"{seed(robot)}: the control needs the same arrangements (render --engine cycles --seed "
                         f"{seed(robot)})")
    out = run / f"{robot.name}_scenes_of_{cycles.name}"
    scenes = sorted(d.name for d in cycles.iterdir() if d.is_dir() and d.name.isdigit())
    if out.is_dir():
        if sorted(d.name for d in out.iterdir() if d.name.isdigit()) == scenes:
            return out
        shutil.rmtree(out)  # links only: --cycles has grown (a resumed render) since they were made
    missing = [s for s in scenes if not (robot / s).is_dir()]
    if missing:
        raise SystemExit(f"--robot {robot} lacks scenes {missing[:5]} of --cycles {cycles}")
    tmp = out.with_name(out.name + ".tmp")
    tmp.mkdir(parents=True, exist_ok=True)
    for name in scenes + ["objects.json", "render_config.json"]:
        if not (tmp / name).exists():
            (tmp / name).symlink_to((robot / name).resolve())
    tmp.rename(out)
    return out


def score(onnx: Path, obj: str, real: Path, fresh: list[Path]) -> dict:
    """Real-frame and fresh-render errors of ``onnx`` for ``obj``."""
    from models.evaluate.cli import run_eval_all

    r = run_eval_all(onnx, real, objects=[obj], draws=10, threads=1, progress=False)["objects"][obj]
    out = {"real": {k: round(r[k], 3) for k in ("mean_deg", "median_deg", "input_mean_deg", "drift_mean_deg",
                                                "video_mean_deg")} | {"instances": r["instances"]}}
    for folder in fresh:
        waited = 0
        while not folder.is_dir() or (folder / ".work").is_dir():  # still being rendered (`refiner-rt render` works there)
            if waited > 3 * 3600:
                raise SystemExit(f"{folder}: not there, or still being rendered after three hours")
            time.sleep(10)
            waited += 10
        f = run_eval_all(onnx, folder, objects=[obj], draws=1, threads=1, progress=False)["objects"][obj]
        out[folder.name] = {"mean_deg": round(f["mean_deg"], 3), "drift_mean_deg": round(f["drift_mean_deg"], 3),
                            "instances": f["instances"]}
    return out


def _label(row: dict) -> str:
    """A row's lever, with its largest in-plane turn, its training seed and a budget other than the study's where they
    were given (``cycles seed 1``, ``tabletop+inplane 180``, ``mix-long+roll (450k samples)``)."""
    return (row["lever"] + (f" {row['inplane_deg']:g}" if "inplane_deg" in row else "")
            + (f" seed {row['seed']}" if "seed" in row else "")
            + (f" ({row['long_samples'] // 1000}k samples)" if "long_samples" in row else ""))


def table(docs: list[dict]) -> str:
    """Markdown: a row per object and lever (real frames: mean and drift; fresh renders: mean), then per lever the
    change against ``v5`` averaged over the objects that lever ran on."""
    rows = [r for d in docs for r in d["rows"]]
    fresh = list(docs[0].get("fresh", []))
    lines = ["| object | lever | real: mean | real: drift | " + " | ".join(fresh) + " |",
             "|---|---|---:|---:|" + "---:|" * len(fresh)]
    by = {(r["object"], _label(r)): r for r in rows}
    labels = [x for lever in LEVERS for x in [lever] + sorted({_label(r) for r in rows if r["lever"] == lever} - {lever})]
    objects = sorted({r["object"] for r in rows})
    for obj in objects:
        for lever in labels:
            r = by.get((obj, lever))
            if r:
                lines.append(f"| {obj} | `{lever}` | {r['real']['mean_deg']:.2f} | {r['real']['drift_mean_deg']:.2f} | "
                             + " | ".join(f"{r[f]['mean_deg']:.2f}" if f in r else "-" for f in fresh) + " |")
    lines += ["", "| lever | objects | real: mean change against `v5` | real: drift change | "
              + " | ".join(f"{f}: change" for f in fresh) + " |", "|---|---|---:|---:|" + "---:|" * len(fresh)]
    for lever in labels[1:]:
        got = [o for o in objects if (o, lever) in by and (o, "v5") in by]
        if not got:
            continue
        def change(key):
            return sum(key(by[(o, lever)]) - key(by[(o, "v5")]) for o in got) / len(got)
        cells = [f"{change(lambda r: r['real']['mean_deg']):+.2f}", f"{change(lambda r: r['real']['drift_mean_deg']):+.2f}"]
        cells += [f"{change(lambda r, f=f: r[f]['mean_deg']):+.2f}" for f in fresh]
        lines.append(f"| `{lever}` | {len(got)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--table", type=Path, nargs="+", metavar="JSON", help="print the Markdown table of these results "
                    "(one or more --json files of this script) and stop")
    ap.add_argument("--robot", type=Path, help="training scenes, robot layout")
    ap.add_argument("--tabletop", type=Path, help="training scenes, tabletop layout")
    ap.add_argument("--real", type=Path, help="real frames (BOP), measured only")
    ap.add_argument("--fresh", type=Path, help="rendered scenes no model trained on (tabletop)")
    ap.add_argument("--fresh-robot", type=Path, help="rendered scenes no model trained on (robot layout)")
    ap.add_argument("--objects", help="comma-separated YCB ids")
    ap.add_argument("--levers", default=",".join(LEVERS), help=f"comma-separated, of {', '.join(LEVERS)}")
    ap.add_argument("--run", type=Path, help="scratch folder of checkpoints and crop caches")
    ap.add_argument("--v5", type=Path, help="folder holding the version-5 fp32 files (a copy of refiner_rt/weights "
                    "made before version 6 shipped)")
    ap.add_argument("--samples", type=int, default=60_000)
    ap.add_argument("--long-samples", type=int, default=150_000, help="samples of the robot-long and mix-long rows")
    ap.add_argument("--cycles", type=Path, help="cycles and robot-same-scenes: Cycles renders (robot layout) with "
                    "--robot's seed (render --engine cycles), finished scenes only")
    ap.add_argument("--mix", type=Path, help="mix-long: tabletop scenes whose ids the robot set does not use "
                    "(render --first-scene N, N >= its scene count)")
    ap.add_argument("--sizes", type=int, default=2_500,
                    help="training crops per object at most (the same for every lever: the tabletop set is smaller)")
    ap.add_argument("--seed", type=int, help="the training runs' seed (default: the recipe's); its rows train into "
                    "folders of their own and are labelled with it")
    ap.add_argument("--inplane", type=float, default=180.0, help="the +inplane levers: the largest turn of a training "
                    "crop about the viewing ray, degrees in (0, 180] (default: every roll)")
    ap.add_argument("--redrawn", type=Path, help="with --table: score every row of the tables again on this folder of "
                    "the real frames re-drawn at their true poses (benchmarks/real_rendered.py; needs --run and --v5)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if not 0.0 < args.inplane <= 180.0:
        ap.error(f"--inplane must be an angle in (0, 180] degrees; got {args.inplane:g}")
    if args.table:
        missing = [str(p) for p in args.table if not p.is_file()]
        if missing:
            ap.error(f"--table: no such file {', '.join(missing)} (the --json files of earlier runs)")
        docs = [json.loads(p.read_text()) for p in args.table]
        if args.redrawn:
            if not (args.run and args.v5):
                ap.error("--redrawn needs --run and --v5 (where the rows' models are)")
            scores = score_redrawn(docs, args.run, args.v5, args.redrawn)
            if args.json:
                write_json(args.json, {"redrawn": data_name(args.redrawn), "draws": 10, "scores": scores})
            print(redrawn_table(scores, [r for d in docs for r in d["rows"]]))
            return 0
        print(table(docs))
        return 0
    missing = [f"--{k}" for k in ("robot", "tabletop", "real", "fresh", "objects", "run", "json", "v5")
               if not getattr(args, k)]
    if missing:
        ap.error(f"missing {', '.join(missing)}")
    levers = [x for x in args.levers.split(",") if x]
    bad = [x for x in levers if x not in LEVERS]
    if bad:
        ap.error(f"--levers: unknown {bad}; expected some of {', '.join(LEVERS)}")
    fresh = [args.fresh] + ([args.fresh_robot] if args.fresh_robot else [])
    doc = json.loads(args.json.read_text()) if args.json.is_file() else {"rows": []}
    done = {(r["lever"], r["object"]) for r in doc["rows"]}
    for obj in args.objects.split(","):
        for lever in levers:
            if (lever, obj) in done:
                continue
            t0 = time.perf_counter()
            turns = args.inplane if lever.endswith("+inplane") else 0.0
            if lever == "v5":
                from refiner_rt.pretrained import model_file_name

                onnx, record = args.v5 / model_file_name(obj, int8=False), {}
            elif lever.startswith("mix-long"):
                if not args.mix:
                    ap.error(f"--levers {lever} needs --mix")
                onnx, record = train_row(lever, obj, args.robot, args.run, args.long_samples, 16_000, args.v5,
                                         extra_train=(args.mix,), seed=args.seed, inplane=turns)
            elif lever == "cycles":
                if not args.cycles:
                    ap.error("--levers cycles needs --cycles")
                onnx, record = train_row(lever, obj, args.cycles, args.run, args.samples, args.sizes, args.v5,
                                         seed=args.seed)
            elif lever == "robot-same-scenes":
                if not args.cycles:
                    ap.error("--levers robot-same-scenes needs --cycles")
                onnx, record = train_row(lever, obj, same_scenes(args.robot, args.cycles, args.run), args.run,
                                         args.samples, args.sizes, args.v5, seed=args.seed)
            elif lever.startswith("robot-long"):
                onnx, record = train_row(lever, obj, args.robot, args.run, args.long_samples, 16_000, args.v5,
                                         seed=args.seed, inplane=turns)
            else:
                data = args.robot if lever.startswith("robot") else args.tabletop
                onnx, record = train_row(lever, obj, data, args.run, args.samples, args.sizes, args.v5, seed=args.seed,
                                         inplane=turns)
            row = {"lever": lever, "object": obj, **record, **score(Path(onnx), obj, args.real, fresh),
                   "row_s": round(time.perf_counter() - t0, 1)}
            doc["rows"].append(row)
            doc.update(samples=args.samples, photometric=photometric(), real=data_name(args.real),
                       fresh=[f.name for f in fresh])
            write_json(args.json, doc)
            print(f"{obj:<22}{lever:<16} real {row['real']['mean_deg']:6.2f} (drift {row['real']['drift_mean_deg']:5.2f})"
                  + "".join(f"  {f.name} {row[f.name]['mean_deg']:5.2f}" for f in fresh), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
