"""Build the fine refiners that ship beside the coarse ones: trained for small input errors, for the cascade.

A coarse refiner (the shipped ``<id>.int8.onnx``) learnt corrections of up to 30 degrees; its output has a floor of
2-3 degrees, and it moves a perfect input by about as much. The fine refiner of an object is the same network, started
from the shipped coarse model's weights and trained further on small input errors only (:data:`FINE_STAGES`: the
errors the coarse refiner leaves, and the motion between video frames), so its capacity goes to the last degrees.
It ships as ``<id>.fine.onnx`` / ``<id>.fine.int8.onnx`` (``refiner_rt.pretrained.model_file_name(..., stage="fine")``)
and :class:`refiner_rt.RefinerCascade` runs it with the coarse one.

    python -m export.release.fine train --data data/ycb9_robot --extra-train data/ycb9_tabletop_s32_next \\
        --run runs/fine_v2 --objects 003_cracker_box,...       # resumable: a trained object is skipped
    python -m export.release.fine ship --run runs/fine_v2 --heldout data/ycb9_fresh_s21 \\
        --calibration data/ycb9_calib_s22 --objects ...        # export, INT8, evaluate, copy into the package

Training data: the coarse models' own (fine version 2, beside coarse version 6: the robot layout ``ycb9_robot`` with
every crop of ``ycb9_tabletop_s32_next`` joining; ``benchmarks/DATA.md``), the held-out-scenes split of the coarse build
(:mod:`export.release.coarse`'s recipe, whose network, ray frame, canonical roll, box and colour jitter and new
backgrounds it keeps), float32, one thread. Fine version 1 trained from the version-5 coarse models on their tabletop
sets (``--data data/ycb9_tabletop_s32``).
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import time
from pathlib import Path

from export.release.card import FINE_DIR, FINE_SCHEMA, metadata_props, publish, stamp
from export.release.coarse import (fresh_quantization, portable_recipe, quantize_for_shipping, recover_shipped,
                                   shipped_recipe, train_shipped)
from models.evaluate.cascade import measure_cascade
from models.evaluate.record import git_commit, machine
from refiner_rt.metadata import file_sha256
from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name

# Two stages, each a cosine schedule: from the coarse model's weights on inputs U(0, 6) degrees off, then on inputs
# whose angle is half-normal with a 3-degree scale (68% under 3, 95% under 6), which sharpens the last degree: on the
# cracker box's fresh renders that stage took the cascade's drift from 1.09 to 0.89 degrees (fp32, crops) and, with
# the gate at 2 degrees, its U(0, 30) mean from 2.48 to 2.40 (refiner_rt.cascade.DEFAULT_GATE_DEG).
FINE_STAGES = (("uniform:0:6", 3e-4, 80_000), ("normal:0:3", 1e-4, 60_000))  # (noise, peak lr, samples)
FINE_NOISE = FINE_STAGES[0][0]   # the widest inputs a fine refiner trained on: what its INT8 model is scored on
FINE_SAMPLES = FINE_STAGES[0][2]
RUN_SIZES = 16_000           # at most this many training crops (every crop of the sets, with --extra-train)
FINE_VERSION = "2"
RESULTS_DIR = FINE_DIR
SCHEMA = FINE_SCHEMA


def train_object(obj: str, data: Path, run: Path, cache: Path, samples: int, extra_train: list[Path]) -> dict:
    """Train ``obj``'s fine refiner from its shipped coarse model through :data:`FINE_STAGES`, each stage a run of
    the training API (:func:`export.release.coarse.shipped_recipe` with the stage's inputs, rate and budget, no
    photometric augmentation; :func:`export.release.coarse.train_shipped`) from the previous stage's network (a
    stage whose checkpoint exists is reused; ``samples`` replaces the first stage's budget): the record."""
    init, init_record = recover_shipped(obj, data, run / "init", cache, any_version=True)
    recipes, stages, t0 = [], [], time.perf_counter()
    for k, (noise, lr, budget) in enumerate(FINE_STAGES):
        name = obj if k == 0 else f"{obj}.stage{k + 1}"
        recipe = shipped_recipe(data, obj, samples if k == 0 else budget, RUN_SIZES, cache, init=init,
                                extra_train=extra_train, noise=noise, lr=lr, photometric={})
        init, row = train_shipped(recipe, run / name, obj)
        recipes.append(portable_recipe(recipe))
        stages.append({"noise": noise, "lr": lr, **{k2: row.get(k2) for k2 in (
            "train_crops", "samples", "epochs", "best_epoch", "val_mean_deg", "wall_s", "mean_deg", "median_deg")}})
    last = stages[-1]
    return {"object_id": obj, "checkpoint": str(init), "init_from": init_record, "recipes": recipes,
            "commands": [shlex.join(["python", "-m", "export.release.fine", "train", "--data", "DATA",
                                     *[a for f in extra_train for a in ("--extra-train", Path(f).name)],
                                     "--run", "RUN", "--objects", obj])],
            "stages": stages, "wall_s": round(time.perf_counter() - t0, 1),
            "train": {"train_crops": last["train_crops"], "samples": sum(st["samples"] for st in stages),
                      "wall_s": round(sum(st["wall_s"] or 0 for st in stages), 1),
                      "val_mean_deg": last["val_mean_deg"], "mean_deg": last["mean_deg"]}}


def regate(obj: str, heldout: Path, calibration: Path) -> dict:
    """Choose a shipped fine refiner's gate again (:func:`measure_cascade`) and rewrite its card entry."""
    result = RESULTS_DIR / f"{obj}.json"
    doc = json.loads(result.read_text())
    coarse, fine = WEIGHTS_DIR / model_file_name(obj, True), WEIGHTS_DIR / doc["files"]["int8"]
    t0 = time.perf_counter()
    gate, cas = measure_cascade(obj, coarse, fine, heldout, calibration)
    doc["gate"] = gate
    doc["cascade"] = {**cas, "data": heldout.resolve().name, "seed": 2024, "coarse_file": coarse.name,
                      "coarse_sha256": file_sha256(coarse)}
    doc["gate_s"] = round(time.perf_counter() - t0, 1)
    result.write_text(json.dumps(doc, indent=1) + "\n")
    c = cas
    print(f"[{obj}] gates {gate['deg']:g}/{gate['coarse_deg']:g} deg (on {gate['chosen_on']}); U(0, 30): coarse {c['coarse']['mean_deg']:.2f} -> "
          f"cascade {c['cascade']['mean_deg']:.2f}; drift {c['coarse']['drift_mean_deg']:.2f} -> "
          f"{c['cascade']['drift_mean_deg']:.2f}", flush=True)
    publish([result], f"{obj}: its cascade's gates chosen on other rendered scenes (fine {gate['deg']:g}, coarse "
            f"{gate['coarse_deg']:g} deg)")
    return doc


def ship_object(obj: str, run: Path, heldout: Path, calibration: Path, cache: Path) -> dict:
    """Export ``obj``'s trained fine refiner, quantise it (the fastest INT8 scheme within the build's bound, scored
    on :data:`FINE_NOISE` inputs of ``heldout``, calibrated on ``calibration``), measure the cascade with the shipped
    coarse refiner on ``heldout`` (:func:`runtime_errors`), stamp, copy into the package, write the card."""
    import logging

    logging.getLogger("torch.onnx._internal.exporter._registration").setLevel(logging.ERROR)
    from export.onnx_export import export_checkpoint

    t0 = time.perf_counter()
    record = run / f"{obj}.fine.json"
    if not record.is_file():
        raise SystemExit(f"[{obj}] no {record}: train it first (python -m export.release.fine train)")
    rec = json.loads(record.read_text())
    fp32, int8 = run / model_file_name(obj, False, "fine"), run / model_file_name(obj, True, "fine")
    exp = export_checkpoint(Path(rec["checkpoint"]), fp32)
    scheme, ev, tried = quantize_for_shipping(fp32, int8, *fresh_quantization(fp32, obj, heldout, calibration, cache,
                                                                              noise=FINE_NOISE))
    coarse = WEIGHTS_DIR / model_file_name(obj, True)
    gate, cas = measure_cascade(obj, coarse, int8, heldout, calibration)
    coarse_meta = metadata_props(coarse)
    card_meta = {"object_id": obj, "stage": "fine", "fine_version": FINE_VERSION,
                 "coarse_model": {"file": coarse.name, "sha256": file_sha256(coarse),
                                  "model_version": coarse_meta.get("model_version")},
                 "fine_noise": FINE_NOISE, "init_from": {k: rec["init_from"][k] for k in ("file", "sha256",
                                                                                          "model_version")},
                 "heldout_error_deg": {"int8_mean": round(ev["int8"]["all"]["mean_deg"], 3),
                                       "fp32_mean": round(ev["fp32"]["all"]["mean_deg"], 3),
                                       "split": f"fresh rendered scenes ({heldout.resolve().name}), inputs "
                                                f"{FINE_NOISE} degrees"}}
    for p in (fp32, int8):
        stamp(p, card_meta)
    for p in (fp32, int8):
        shutil.copyfile(p, WEIGHTS_DIR / p.name)
    doc = {"schema": SCHEMA, "object_id": obj, "stage": "fine", "fine_version": FINE_VERSION,
           "files": {"int8": int8.name, "fp32": fp32.name}, "train": rec["train"], "stages": rec["stages"],
           "train_command": " && ".join(rec["commands"]), **({"train_recipes": rec["recipes"]} if "recipes" in rec else {}), "noise": FINE_NOISE, "init_from": rec["init_from"],
           "export": {"max_abs_dq": exp.max_abs_dq, "int8_scheme": scheme, "int8_candidates": tried},
           "eval": {**ev, "noise": FINE_NOISE}, "gate": gate, "cascade": {**cas, "data": heldout.resolve().name, "seed": 2024,
                                                             "coarse_file": coarse.name,
                                                             "coarse_sha256": file_sha256(coarse)},
           "metadata": card_meta, "sizes_bytes": {"int8": int8.stat().st_size, "fp32": fp32.stat().st_size},
           "machine": machine(), "git_commit": git_commit(), "ship_s": round(time.perf_counter() - t0, 1)}
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    result = RESULTS_DIR / f"{obj}.json"
    result.write_text(json.dumps(doc, indent=1) + "\n")
    c = cas
    print(f"[{obj}] fine INT8 ({scheme}) {ev['int8']['all']['mean_deg']:.2f} deg on {FINE_NOISE}; U(0, 30): coarse "
          f"{c['coarse']['mean_deg']:.2f} -> cascade {c['cascade']['mean_deg']:.2f}; drift {c['coarse']['drift_mean_deg']:.2f}"
          f" -> {c['cascade']['drift_mean_deg']:.2f}; 0-3 deg inputs {c['coarse']['input_0_3_mean_deg']:.2f} -> "
          f"{c['cascade']['input_0_3_mean_deg']:.2f}", flush=True)
    publish([WEIGHTS_DIR / fp32.name, WEIGHTS_DIR / int8.name, result],
            f"the {obj} fine refiner (version {FINE_VERSION}); its cascade on fresh renders "
            f"{c['cascade']['mean_deg']:.2f} deg from U(0, 30) (coarse alone {c['coarse']['mean_deg']:.2f})")
    return doc


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train fine refiners from the shipped coarse ones (resumable)")
    t.add_argument("--data", type=Path, required=True, help="rendered dataset folder (refiner-rt render --out)")
    t.add_argument("--extra-train", type=Path, action="append", default=[], metavar="FOLDER",
                   help="another rendered set whose every crop joins the training part (scene ids new); repeatable")
    t.add_argument("--run", type=Path, required=True, help="scratch folder for checkpoints and logs (not committed)")
    t.add_argument("--objects", required=True, help="comma-separated YCB ids, trained in this order")
    t.add_argument("--samples", type=int, default=FINE_SAMPLES,
                   help="training samples of the first stage per object (default %(default)s)")
    t.add_argument("--cache", type=Path, help="crop cache folder (default DATA/.crops)")
    sh = sub.add_parser("ship", help="export, quantise, measure the cascade, copy into the package and write the card")
    sh.add_argument("--run", type=Path, required=True, help="the train command's --run folder")
    sh.add_argument("--heldout", type=Path, required=True, help="fresh rendered scenes (the card's ycb9_fresh_s21)")
    sh.add_argument("--calibration", type=Path, required=True, help="other fresh scenes, for INT8 calibration")
    sh.add_argument("--objects", required=True, help="comma-separated YCB ids")
    sh.add_argument("--cache", type=Path, help="crop cache folder (default HELDOUT/.crops)")
    g = sub.add_parser("gate", help="choose each shipped fine refiner's cascade gate again (on --calibration) and "
                       "measure the cascade with it (on --heldout); the card follows")
    g.add_argument("--heldout", type=Path, required=True, help="fresh rendered scenes (the card's ycb9_fresh_s21)")
    g.add_argument("--calibration", type=Path, required=True, help="other fresh scenes: the gate is chosen on them")
    g.add_argument("--objects", required=True, help="comma-separated YCB ids")
    args = ap.parse_args(argv)
    if args.cmd in ("ship", "gate") and args.heldout.resolve() == args.calibration.resolve():
        ap.error("--calibration must be another folder than --heldout")
    if args.cmd == "gate":
        for obj in [o.strip() for o in args.objects.split(",") if o.strip()]:
            regate(obj, args.heldout, args.calibration)
        return 0
    if args.cmd == "ship":
        for obj in [o.strip() for o in args.objects.split(",") if o.strip()]:
            ship_object(obj, args.run, args.heldout, args.calibration, args.cache or args.heldout / ".crops")
        return 0
    if args.cmd == "train":
        for folder in [args.data, *args.extra_train]:
            if not folder.is_dir():
                ap.error(f"expected a rendered dataset folder; {folder} is not a folder")
        args.run.mkdir(parents=True, exist_ok=True)
        (args.run / "init").mkdir(exist_ok=True)
        cache = args.cache or args.data / ".crops"
        for obj in [o.strip() for o in args.objects.split(",") if o.strip()]:
            rec = train_object(obj, args.data, args.run, cache, args.samples, args.extra_train)
            (args.run / f"{obj}.fine.json").write_text(json.dumps(rec, indent=1) + "\n")
            print(f"[{obj}] fine: val {rec['train']['val_mean_deg']:.2f} deg (inputs {FINE_STAGES[-1][0]}), test "
                  f"{rec['train']['mean_deg']:.2f} (U(0, 30)) in {rec['wall_s']:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
