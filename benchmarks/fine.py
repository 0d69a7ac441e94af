"""Build the fine refiners that ship beside the coarse ones: trained for small input errors, for the cascade.

A coarse refiner (the shipped ``<id>.int8.onnx``) learnt corrections of up to 30 degrees; its output has a floor of
2-3 degrees, and it moves a perfect input by about as much. The fine refiner of an object is the same network, started
from the shipped coarse model's weights and trained further on small input errors only (:data:`FINE_STAGES`: the
errors the coarse refiner leaves, and the motion between video frames), so its capacity goes to the last degrees.
It ships as ``<id>.fine.onnx`` / ``<id>.fine.int8.onnx`` (``refiner_rt.pretrained.model_file_name(..., stage="fine")``)
and :class:`refiner_rt.RefinerCascade` runs it with the coarse one.

    python benchmarks/fine.py train --data data/ycb9_robot --extra-train data/ycb9_tabletop_s32_next \\
        --run runs/fine_v2 --objects 003_cracker_box,...       # resumable: a trained object is skipped
    python benchmarks/fine.py ship --run runs/fine_v2 --heldout data/ycb9_fresh_s21 --calibration data/ycb9_calib_s22 \\
        --objects ... [--commit]                               # export, INT8, evaluate, copy into the package

Training data: the coarse models' own (fine version 2, beside coarse version 6: the robot layout ``ycb9_robot`` with
every crop of ``ycb9_tabletop_s32_next`` joining; ``benchmarks/DATA.md``), the held-out-scenes split of the coarse build
(``benchmarks/pretrained.py``'s recipe, whose network, ray frame, canonical roll, box and colour jitter and new
backgrounds it keeps), float32, one thread. Fine version 1 trained from the version-5 coarse models on their tabletop
sets (``--data data/ycb9_tabletop_s32``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.pretrained import (_card_command, _commit, _fresh_quantization, _git_commit, _metadata,  # noqa: E402
                                   _run_training, machine, quantize_for_shipping, recover_shipped, stamp,
                                   train_command, whole_folder_spec, write_card)
from refiner_rt.metadata import file_sha256  # noqa: E402
from refiner_rt.pretrained import INDEX_FILE, WEIGHTS_DIR, model_file_name  # noqa: E402

# Two stages, each a cosine schedule: from the coarse model's weights on inputs U(0, 6) degrees off, then on inputs
# whose angle is half-normal with a 3-degree scale (68% under 3, 95% under 6), which sharpens the last degree: on the
# cracker box's fresh renders that stage took the cascade's drift from 1.09 to 0.89 degrees (fp32, crops) and, with
# the gate at 2 degrees, its U(0, 30) mean from 2.48 to 2.40 (refiner_rt.cascade.DEFAULT_GATE_DEG).
FINE_STAGES = (("uniform:0:6", 3e-4, 80_000), ("normal:0:3", 1e-4, 60_000))  # (noise, peak lr, samples)
FINE_NOISE = FINE_STAGES[0][0]   # the widest inputs a fine refiner trained on: what its INT8 model is scored on
FINE_SAMPLES = FINE_STAGES[0][2]
RUN_SIZES = 16_000           # at most this many training crops (every crop of the sets, with --extra-train)
FINE_VERSION = "2"
RESULTS_DIR = ROOT / "benchmarks" / "results" / "fine"
SCHEMA = "refiner-rt/fine-eval/1"
FLOOR_BINS = 30              # the floor curve: output error in 1-degree bins of input error, 0 to 30


def objects_with_fine(objects: str | None, error) -> list[str]:
    """The objects a cascade study runs on: ``objects`` (comma-separated YCB ids), default every object whose fine
    refiner ships; ``error(message)`` (``ArgumentParser.error``) for one without."""
    from refiner_rt.pretrained import pretrained_models

    with_fine = [m.object_id for m in pretrained_models() if "fine" in m.stages]
    chosen = [o.strip() for o in objects.split(",")] if objects else with_fine
    missing = sorted(set(chosen) - set(with_fine))
    if missing or not chosen:
        error(f"no fine refiner ships for {missing or 'any object'}")
    return chosen


def train_object(obj: str, data: Path, run: Path, cache: Path, samples: int, extra_train: list[Path]) -> dict:
    """Train ``obj``'s fine refiner from its shipped coarse model through :data:`FINE_STAGES` (a stage whose
    checkpoint exists is reused; ``samples`` replaces the first stage's budget): the record of the last stage."""
    init, init_record = recover_shipped(obj, data, run / "init", cache, any_version=True)
    commands, stages, t0 = [], [], time.perf_counter()
    for k, (noise, lr, budget) in enumerate(FINE_STAGES):
        name = obj if k == 0 else f"{obj}.stage{k + 1}"
        cmd = train_command(data, obj, run, samples if k == 0 else budget, RUN_SIZES, cache, init=init,
                            extra_train=extra_train, noise=noise, lr=lr, photometric={}, other_set=k == 0, name=name)
        init = _run_training(cmd, run / name, run / f"{name}.log", obj)
        row = json.loads((run / f"{name}.train.json").read_text())["rows"][-1]
        commands.append(_card_command(cmd))
        stages.append({"noise": noise, "lr": lr, **{k2: row.get(k2) for k2 in (
            "train_crops", "samples", "epochs", "best_epoch", "val_mean_deg", "wall_s", "mean_deg", "median_deg")}})
    last = stages[-1]
    return {"object_id": obj, "checkpoint": str(init), "init_from": init_record, "commands": commands,
            "stages": stages, "wall_s": round(time.perf_counter() - t0, 1),
            "train": {"train_crops": last["train_crops"], "samples": sum(st["samples"] for st in stages),
                      "wall_s": round(sum(st["wall_s"] or 0 for st in stages), 1),
                      "val_mean_deg": last["val_mean_deg"], "mean_deg": last["mean_deg"]}}


def runtime_errors(obj: str, coarse: Path, fine: Path, data: Path, seed: int = 2024, symmetric: bool = False,
                   draws: int = 1, gate: tuple | None = None, coarse_views: int | None = None,
                   fine_views: int | None = None) -> dict:
    """Per instance of ``obj`` in ``data`` (every one: ``visib_fract >= 0.3``, the box of the loader), through the
    runtime on the full frames: the coarse refiner alone (``coarse``: one pass, as ``RefinerSession.refine`` runs it
    by default; ``coarse_cascade``: the cascade's views), the fine refiner alone (the cascade's views), the cascade's
    coarse pass then the fine refiner, and :class:`refiner_rt.RefinerCascade` with gates ``gate`` (``(gate_deg,
    coarse_gate_deg)``; default: the object's shipped gates), from U(0, 30) inputs and from the true pose
    (the drift). The cascade's two paths are each run for every instance, so :func:`with_gate` gives the cascade of
    any other gates from the same arrays; ``cascade`` here is the one of ``gate`` (exactly what
    ``RefinerCascade.refine`` returns: the same calls). ``draws``: U(0, 30) inputs per instance (seeds ``seed``,
    ``seed + 1``...; the arrays hold them one draw after the other). ``symmetric``: errors to the closest symmetric
    pose of ``models.data.objects``' symmetries (the can's turns), as ``refiner-rt eval --all`` scores real frames.
    ``coarse_views`` / ``fine_views``: box-jittered views each refiner averages (default ``RefinerCascade``'s,
    ``DEFAULT_COARSE_VIEWS`` and ``DEFAULT_FINE_VIEWS``). Returns the error arrays (degrees) by key, and
    ``fine_move`` and ``coarse_move`` (``@0``): the corrections of the fine refiner and of the cascade's coarse pass,
    degrees."""
    import cv2

    from models.data.noise import NoiseSpec, perturb
    from models.data.pipeline import load_splits
    from models.data.symmetry import symmetric_error
    from benchmarks.pretrained import SYMMETRIES
    from refiner_rt import RefinerSession
    from refiner_rt import quaternion as rq
    from refiner_rt.cascade import DEFAULT_COARSE_VIEWS, DEFAULT_FINE_VIEWS, shipped_gate

    samples = list(load_splits(whole_folder_spec(data, obj, "test")).test)
    q_gt = np.array([rq.from_matrix(s.R) for s in samples])
    q_ins = [perturb(q_gt, NoiseSpec.parse("uniform:0:30"), np.random.default_rng(seed + k))[0] for k in range(draws)]
    c_sess, f_sess = RefinerSession(coarse, threads=1), RefinerSession(fine, threads=1)
    views = DEFAULT_FINE_VIEWS if fine_views is None else fine_views
    coarse_views = DEFAULT_COARSE_VIEWS if coarse_views is None else coarse_views
    by_image = defaultdict(list)
    for i, s in enumerate(samples):
        by_image[s.image_path].append(i)
    n = len(samples)
    out = {k + suffix: np.zeros((n * (draws if not suffix else 1), 4))
           for k in ("coarse", "coarse_cascade", "fine", "coarse_fine") for suffix in ("", "@0")}
    for path, idx in by_image.items():
        image = cv2.imread(path, cv2.IMREAD_COLOR)
        if image is None:
            raise SystemExit(f"cannot read the frame {path}")
        boxes = np.array([samples[i].box_xyxy for i in idx])
        K = samples[idx[0]].K
        starts = [("", [i + k * n for i in idx], q_in[idx]) for k, q_in in enumerate(q_ins)] + [("@0", idx, q_gt[idx])]
        for suffix, rows, start in starts:
            mid = c_sess.refine(image, boxes, start, K=K, views=coarse_views).q_refined
            out["coarse_cascade" + suffix][rows] = mid
            out["coarse" + suffix][rows] = mid if coarse_views == 1 else c_sess.refine(image, boxes, start,
                                                                                       K=K).q_refined
            out["fine" + suffix][rows] = f_sess.refine(image, boxes, start, K=K, views=views).q_refined
            out["coarse_fine" + suffix][rows] = f_sess.refine(image, boxes, mid, K=K, views=views).q_refined
    truth = {"": np.tile(q_gt, (draws, 1)), "@0": q_gt}
    starts = {"": np.concatenate(q_ins), "@0": q_gt}

    def err(q, key):
        t = truth["@0" if "@" in key else ""]
        ids = np.array([obj] * len(t))
        return symmetric_error(q, t, ids, SYMMETRIES) if symmetric and obj in SYMMETRIES else rq.geodesic_angle(q, t)

    e = {"input": err(starts[""], ""), **{k: err(v, k) for k, v in out.items()},
         **{f"{k}_move{suffix}": rq.geodesic_angle(starts[suffix], out[k2 + suffix])
            for k, k2 in (("fine", "fine"), ("coarse", "coarse_cascade")) for suffix in ("", "@0")}}
    return with_gate(e, shipped_gate(obj) if gate is None else gate)


def with_gate(e: dict, gate: tuple) -> dict:
    """``e`` (:func:`runtime_errors`) with ``cascade``, ``cascade@0`` and their ``_coarse_used`` for the gates
    ``(gate_deg, coarse_gate_deg)`` (either ``None``: no such check; ``gate_deg`` None: always the coarse refiner
    then the fine one), as ``RefinerCascade`` picks its path."""
    from refiner_rt.cascade import long_way

    out = dict(e)
    for suffix in ("", "@0"):
        far = long_way(e["fine_move" + suffix], e["coarse_move" + suffix], *gate)
        out["cascade" + suffix] = np.where(far, e["coarse_fine" + suffix], e["fine" + suffix])
        out[f"cascade{suffix}_coarse_used"] = far
    out["gate"] = list(gate)
    return out


# The gates choose_gate weighs: the fine correction's and the coarse one's (degrees).
GATES = tuple((g, c) for g in (1.0, 1.5, 2.0, 2.5, 3.0, 4.0) for c in (4.0, 6.0, 8.0, 12.0))


def choose_gate(e: dict, gates=GATES) -> tuple[tuple, dict]:
    """The gates of ``gates`` with the smallest mean of the cascade's U(0, 30) mean and its drift (the two things a
    cascade is for, weighed alike), on :func:`runtime_errors`' arrays of scenes the card does not score:
    ``((gate_deg, coarse_gate_deg), {gates: [U(0, 30) mean, drift]})``."""
    scores = {}
    for g in gates:
        c = with_gate(e, g)
        scores[g] = [float(c["cascade"].mean()), float(c["cascade@0"].mean())]
    return min(gates, key=lambda g: sum(scores[g])), scores


def summarise(e: dict) -> dict:
    """The card's numbers from :func:`runtime_errors`' arrays: means, medians, the 0-3 degree inputs, the floor
    curve (mean output error per 1-degree input bin, ``None`` where a bin is empty)."""
    small = e["input"] < 3.0
    bins = np.minimum((e["input"]).astype(int), FLOOR_BINS - 1)
    out = {"n": int(len(e["input"])), "input_mean_deg": float(e["input"].mean()), "input_0_3_n": int(small.sum())}
    for k in [k for k in ("coarse", "coarse_cascade", "fine", "cascade") if k in e]:  # coarse_cascade: views > 1
        out[k] = {"mean_deg": float(e[k].mean()), "median_deg": float(np.median(e[k])),
                  "drift_mean_deg": float(e[k + "@0"].mean()), "drift_median_deg": float(np.median(e[k + "@0"])),
                  "input_0_3_mean_deg": float(e[k][small].mean()) if small.any() else None,
                  "floor_curve": [float(e[k][bins == b].mean()) if (bins == b).any() else None
                                  for b in range(FLOOR_BINS)]}
    out["gate"] = e.get("gate")
    out["cascade"]["coarse_used"] = float(e["cascade_coarse_used"].mean())
    out["cascade"]["coarse_used_at_truth"] = float(e["cascade@0_coarse_used"].mean())
    out["floor_curve_n"] = [int((bins == b).sum()) for b in range(FLOOR_BINS)]
    return out


def measure_cascade(obj: str, coarse: Path, fine: Path, heldout: Path, calibration: Path) -> tuple[dict, dict]:
    """The object's gate, chosen on ``calibration`` (:func:`choose_gate`: rendered scenes the card does not score),
    and the cascade with it on ``heldout`` (:func:`summarise`): ``(gate record, summary)``."""
    from refiner_rt.cascade import DEFAULT_COARSE_VIEWS, DEFAULT_FINE_VIEWS

    gate, scores = choose_gate(runtime_errors(obj, coarse, fine, calibration, seed=7))
    record = {"deg": gate[0], "coarse_deg": gate[1], "chosen_on": calibration.resolve().name, "seed": 7,
              "coarse_views": DEFAULT_COARSE_VIEWS, "fine_views": DEFAULT_FINE_VIEWS,
              "scores": {f"{g[0]:g}/{g[1]:g}": {"mean_deg": round(v[0], 3), "drift_mean_deg": round(v[1], 3)}
                         for g, v in scores.items()},
              "rule": "the smallest mean of the cascade's U(0, 30) mean and its drift"}
    return record, summarise(runtime_errors(obj, coarse, fine, heldout, gate=gate))


def regate(obj: str, heldout: Path, calibration: Path, commit: bool) -> dict:
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
    write_card()
    c = cas
    print(f"[{obj}] gates {gate['deg']:g}/{gate['coarse_deg']:g} deg (on {gate['chosen_on']}); U(0, 30): coarse {c['coarse']['mean_deg']:.2f} -> "
          f"cascade {c['cascade']['mean_deg']:.2f}; drift {c['coarse']['drift_mean_deg']:.2f} -> "
          f"{c['cascade']['drift_mean_deg']:.2f}", flush=True)
    if commit:
        _commit([result, WEIGHTS_DIR / INDEX_FILE, WEIGHTS_DIR / "MODELS.md", ROOT / "README.md",
                 ROOT / "benchmarks" / "RESULTS.md"], regenerate=True,
                message=f"{obj}: its cascade's gates chosen on other rendered scenes (fine {gate['deg']:g}, coarse "
                f"{gate['coarse_deg']:g} deg); on fresh "
                f"renders {c['cascade']['mean_deg']:.2f} deg from U(0, 30) (coarse alone {c['coarse']['mean_deg']:.2f}), "
                f"a perfect pose moved {c['cascade']['drift_mean_deg']:.2f} (coarse {c['coarse']['drift_mean_deg']:.2f})")
    return doc


def ship_object(obj: str, run: Path, heldout: Path, calibration: Path, cache: Path, commit: bool) -> dict:
    """Export ``obj``'s trained fine refiner, quantise it (the fastest INT8 scheme within the build's bound, scored
    on :data:`FINE_NOISE` inputs of ``heldout``, calibrated on ``calibration``), measure the cascade with the shipped
    coarse refiner on ``heldout`` (:func:`runtime_errors`), stamp, copy into the package, write the card."""
    import logging

    logging.getLogger("torch.onnx._internal.exporter._registration").setLevel(logging.ERROR)
    from export.onnx_export import export_checkpoint

    t0 = time.perf_counter()
    record = run / f"{obj}.fine.json"
    if not record.is_file():
        raise SystemExit(f"[{obj}] no {record}: train it first (benchmarks/fine.py train)")
    rec = json.loads(record.read_text())
    fp32, int8 = run / model_file_name(obj, False, "fine"), run / model_file_name(obj, True, "fine")
    exp = export_checkpoint(Path(rec["checkpoint"]), fp32)
    scheme, ev, tried = quantize_for_shipping(fp32, int8, *_fresh_quantization(fp32, obj, heldout, calibration, cache,
                                                                              noise=FINE_NOISE))
    coarse = WEIGHTS_DIR / model_file_name(obj, True)
    gate, cas = measure_cascade(obj, coarse, int8, heldout, calibration)
    coarse_meta = _metadata(coarse)
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
           "train_command": " && ".join(rec["commands"]), "noise": FINE_NOISE, "init_from": rec["init_from"],
           "export": {"max_abs_dq": exp.max_abs_dq, "int8_scheme": scheme, "int8_candidates": tried},
           "eval": {**ev, "noise": FINE_NOISE}, "gate": gate, "cascade": {**cas, "data": heldout.resolve().name, "seed": 2024,
                                                             "coarse_file": coarse.name,
                                                             "coarse_sha256": file_sha256(coarse)},
           "metadata": card_meta, "sizes_bytes": {"int8": int8.stat().st_size, "fp32": fp32.stat().st_size},
           "machine": machine(), "git_commit": _git_commit(), "ship_s": round(time.perf_counter() - t0, 1)}
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    result = RESULTS_DIR / f"{obj}.json"
    result.write_text(json.dumps(doc, indent=1) + "\n")
    write_card()
    c = cas
    print(f"[{obj}] fine INT8 ({scheme}) {ev['int8']['all']['mean_deg']:.2f} deg on {FINE_NOISE}; U(0, 30): coarse "
          f"{c['coarse']['mean_deg']:.2f} -> cascade {c['cascade']['mean_deg']:.2f}; drift {c['coarse']['drift_mean_deg']:.2f}"
          f" -> {c['cascade']['drift_mean_deg']:.2f}; 0-3 deg inputs {c['coarse']['input_0_3_mean_deg']:.2f} -> "
          f"{c['cascade']['input_0_3_mean_deg']:.2f}", flush=True)
    if commit:
        _commit([WEIGHTS_DIR / fp32.name, WEIGHTS_DIR / int8.name, result, WEIGHTS_DIR / INDEX_FILE,
                 WEIGHTS_DIR / "MODELS.md", ROOT / "README.md", ROOT / "benchmarks" / "RESULTS.md"], regenerate=True,
                message=f"weights: the {obj} fine refiner (version {FINE_VERSION}); its cascade on fresh renders "
                f"{c['cascade']['mean_deg']:.2f} deg from U(0, 30) (coarse alone {c['coarse']['mean_deg']:.2f}), a "
                f"perfect pose moved {c['cascade']['drift_mean_deg']:.2f} (coarse {c['coarse']['drift_mean_deg']:.2f})")
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
    sh.add_argument("--commit", action="store_true", help="git-commit each shipped fine refiner as it is done")
    g = sub.add_parser("gate", help="choose each shipped fine refiner's cascade gate again (on --calibration) and "
                       "measure the cascade with it (on --heldout); the card follows")
    g.add_argument("--heldout", type=Path, required=True, help="fresh rendered scenes (the card's ycb9_fresh_s21)")
    g.add_argument("--calibration", type=Path, required=True, help="other fresh scenes: the gate is chosen on them")
    g.add_argument("--objects", required=True, help="comma-separated YCB ids")
    g.add_argument("--commit", action="store_true", help="git-commit each object's card entry")
    args = ap.parse_args(argv)
    if args.cmd in ("ship", "gate") and args.heldout.resolve() == args.calibration.resolve():
        ap.error("--calibration must be another folder than --heldout")
    if args.cmd == "gate":
        for obj in [o.strip() for o in args.objects.split(",") if o.strip()]:
            regate(obj, args.heldout, args.calibration, args.commit)
        return 0
    if args.cmd == "ship":
        for obj in [o.strip() for o in args.objects.split(",") if o.strip()]:
            ship_object(obj, args.run, args.heldout, args.calibration, args.cache or args.heldout / ".crops",
                        args.commit)
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
