"""The model card of the shipped refiners: ``refiner_rt/weights/models.json`` (what the runtime lists) and
``refiner_rt/weights/MODELS.md``, generated from the build records in ``benchmarks/results/pretrained/`` and
``benchmarks/results/fine/`` (and the real-frame record of ``python -m benchmarks.real``, the appearance record of
``python -m benchmarks.appearance --card``); the card's keys in each
ONNX file's metadata (:func:`stamp`); and :func:`publish`, which regenerates the card and the documents' tables after
a build and names the files that changed (committing them is the builder's step, not the code's).
"""

from __future__ import annotations

import fcntl
import json
import os
import shlex
from pathlib import Path

import numpy as np

from models.evaluate.appearance import CARD_JSON as APPEARANCE_JSON
from models.evaluate.real import DEFAULT_JSON as REAL_JSON
from models.evaluate.record import current_command
from models.evaluate.report import fine_table
from refiner_rt.metadata import file_sha256
from refiner_rt.pretrained import INDEX_FILE, INDEX_FORMAT, WEIGHTS_DIR, model_file_name

ROOT = Path(__file__).resolve().parents[2]
RESULTS_DIR = ROOT / "benchmarks" / "results" / "pretrained"
FINE_DIR = ROOT / "benchmarks" / "results" / "fine"
SCHEMA = "refiner-rt/pretrained-eval/1"
FINE_SCHEMA = "refiner-rt/fine-eval/1"
# What a build regenerates beside the weights: the card and the documents whose tables come from it.
# The accuracy an INT8 model may give up against its fp32 model (export.release.coarse.quantize_for_shipping).
MAX_INT8_COST_DEG = 0.2        # per object: INT8 held-out mean error at most this much above fp32's
MAX_MEAN_INT8_COST_DEG = 0.1   # goal over the shipped objects (reported by requantize)
CARD_FILES = (WEIGHTS_DIR / INDEX_FILE, WEIGHTS_DIR / "MODELS.md", ROOT / "README.md", ROOT / "benchmarks" / "RESULTS.md")


def metadata_props(path: Path) -> dict:
    """An ONNX file's ``metadata_props`` as a dict of strings."""
    import onnx

    return {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}


def stamp(path: Path, extra: dict) -> None:
    """Add model-card keys to an ONNX file's ``metadata_props`` (the weights are not touched)."""
    import onnx

    proto = onnx.load(str(path))
    props = {p.key: p.value for p in proto.metadata_props}
    props.update({k: v if isinstance(v, str) else json.dumps(v) for k, v in extra.items()})
    del proto.metadata_props[:]
    onnx.helper.set_model_props(proto, props)
    tmp = path.with_suffix(".tmp")
    onnx.save(proto, str(tmp))
    os.replace(tmp, path)


def load_results() -> list[dict]:
    """Every coarse model's build record (``benchmarks/results/pretrained/<id>.json``)."""
    docs = [json.loads(p.read_text()) for p in sorted(RESULTS_DIR.glob("*.json")) if not p.name.startswith("_")]
    return [d for d in docs if d.get("schema") == SCHEMA]


def _speed() -> dict:
    p = RESULTS_DIR / "_speed.json"
    return json.loads(p.read_text()) if p.is_file() else {}


def _real(real_json: Path = REAL_JSON) -> dict:
    """Per object, the real-frame record of ``python -m benchmarks.real`` (``real_json``) for the INT8 file that ships now
    (a record of another file, an older version's, is left out)."""
    if not real_json.is_file():
        return {}
    doc = json.loads(real_json.read_text())
    out = {}
    for obj, o in doc.get("objects", {}).items():
        shipped = WEIGHTS_DIR / model_file_name(obj, int8=True)
        if shipped.is_file() and o.get("sha256") == file_sha256(shipped):
            out[obj] = {**{k: round(o[k], 3) for k in ("mean_deg", "median_deg", "input_mean_deg", "drift_mean_deg",
                                                       "video_mean_deg", "under_5_deg")},
                        "instances": o["instances"], "videos": len(o["videos"]), "data": doc["data"],
                        "draws": doc["draws"], "symmetric": o.get("symmetric", False)}
    return out


def _fine() -> dict:
    """Per object, the fine refiner that ships (:mod:`export.release.fine`): its files, version and card, for records
    whose files are in the package and whose cascade was measured with the coarse INT8 file that ships now."""
    out = {}
    for path in sorted(FINE_DIR.glob("*.json")) if FINE_DIR.is_dir() else []:
        d = json.loads(path.read_text())
        obj = d.get("object_id")
        if d.get("schema") != FINE_SCHEMA or not all((WEIGHTS_DIR / f).is_file()
                                                                  for f in d["files"].values()):
            continue
        coarse = WEIGHTS_DIR / model_file_name(obj, int8=True)
        c = d["cascade"]
        if not coarse.is_file() or c.get("coarse_sha256") != file_sha256(coarse):
            continue
        out[obj] = {"files": d["files"], "version": d["fine_version"], "gate_deg": d.get("gate", {}).get("deg", 2.0),
                    "coarse_gate_deg": d.get("gate", {}).get("coarse_deg", 8.0),
                    "card": {"fine_int8_mean_deg": round(d["eval"]["int8"]["all"]["mean_deg"], 3),
                             "fine_noise": d["noise"], "int8_scheme": d["export"]["int8_scheme"],
                             "stages": [st["noise"] for st in d.get("stages", [])] or [d["noise"]],
                             "gate_on": d.get("gate", {}).get("chosen_on"),
                             "data": c["data"], "n": c["n"],
                             "cascade": {k: {m: (round(v, 3) if isinstance(v, float) else v)
                                             for m, v in c[k].items() if m != "floor_curve"}
                                         for k in ("coarse", "fine", "cascade")},
                             "train_command": d["train_command"], "train_wall_s": d["train"]["wall_s"]}}
    return out


def _appearance(appearance_json: Path = APPEARANCE_JSON) -> dict:
    """Per object, the card's appearance columns (:func:`models.evaluate.appearance.per_object`) from the record of
    ``python -m benchmarks.appearance --card``, for the INT8 file that ships now (a record of another file is left
    out, as :func:`_real` does)."""
    from models.evaluate.appearance import per_object

    if not appearance_json.is_file():
        return {}
    doc = json.loads(appearance_json.read_text())
    shas = doc.get("model_sha256", {})
    out = {}
    for obj, cols in per_object(doc).items():
        shipped = WEIGHTS_DIR / model_file_name(obj, int8=True)
        if shipped.is_file() and shas.get(obj) == file_sha256(shipped):
            out[obj] = {**cols, "real": doc.get("real"), "draws": doc["draws"]}
    return out


def write_card(real_json: Path = REAL_JSON, appearance_json: Path = APPEARANCE_JSON) -> None:
    """``weights/models.json`` (what the runtime lists) and ``weights/MODELS.md`` from the evaluation JSON (and the
    real-frame record of ``python -m benchmarks.real``, ``real_json``; the appearance record of ``python -m
    benchmarks.appearance --card``, ``appearance_json``; the fine refiners of :mod:`export.release.fine`)."""
    docs, speed, real, fine = load_results(), _speed(), _real(real_json), _fine()
    appearance = _appearance(appearance_json)
    models = {}
    for d in docs:
        obj = d["object_id"]
        sp = speed.get("models", {}).get(obj, {})
        models[obj] = {
            "arch": d["recipe"]["arch"], "config": d["recipe"]["config"], "version": d["model_version"],
            "files": d["files"], "heldout": d["heldout"], **({"real": real[obj]} if obj in real else {}),
            **({"appearance": appearance[obj]} if obj in appearance else {}),
            **({"fine": fine[obj]} if obj in fine else {}),
            "card": {"fp32_heldout_mean_deg": d["eval"]["fp32"]["all"]["mean_deg"],
                     "heldout_data": d["eval"]["split"].get("data"),
                     "fp32_training_split_mean_deg": d.get("eval_training_split", {}).get("fp32", {}).get(
                         "all", {}).get("mean_deg"),
                     "inside_image": d["eval"]["int8"]["inside_image"], "cut_by_border": d["eval"]["int8"]["cut_by_border"],
                     "int8_refinements_per_s": sp.get("int8"), "fp32_refinements_per_s": sp.get("fp32"),
                     "int8_scheme": d["export"].get("int8_scheme", "dynamic-int8"),
                     "recipe": d["recipe"]["name"], "train_command": d["train_command"],
                     "train_wall_s": d["train"]["wall_s"], "train_crops": d["train"]["train_crops"],
                     "train_samples": d["train"]["samples"], "mesh": d["metadata"]["mesh"],
                     "object_frame": d["metadata"]["object_frame"], "machine": d["machine"]},
        }
    WEIGHTS_DIR.mkdir(exist_ok=True)
    (WEIGHTS_DIR / INDEX_FILE).write_text(json.dumps({"format": INDEX_FORMAT, "models": models}, indent=1) + "\n")
    (WEIGHTS_DIR / "MODELS.md").write_text(card_markdown(docs, speed, real) + appearance_markdown(appearance)
                                           + fine_markdown(fine))


def appearance_markdown(appearance: dict) -> str:
    """The card's appearance section: per object the worst camera effect of the stress test on the real dev frames,
    the dev appearance gap, and the Cycles validation set against its TinyRenderer twin ("" when not measured)."""
    if not appearance:
        return ""
    a0 = next(iter(appearance.values()))
    cy0 = next((a["cycles"] for a in appearance.values() if "cycles" in a), {})
    lines = ["", "## Appearance", "",
             f"How much the pixels of a real camera or a physically based renderer cost each INT8 refiner, written by "
             f"`python -m benchmarks.appearance --real REAL --rendered cycles=DIR --rendered tiny=DIR --card` "
             f"(`benchmarks/results/appearance/card.json`; {a0['draws']} coarse inputs U(0, 30) per instance, one "
             "pass). Stress test: the real dev frames under one camera effect at a time at a working camera's "
             "strength (exposure, gamma, white balance, saturation, contrast, sharpening, noise, blur, JPEG, half "
             "resolution); the worst effect's error minus the clean frames'. Gap: the real dev frames minus the same "
             "frames with the object re-drawn at its true pose by the training renderer. Cycles: "
             "`" + cy0.get("data", "?") + "`, robot-layout scenes rendered by Blender Cycles under varied light and "
             "materials (no model trained on them), against the same arrangements rendered by the training renderer "
             "(`" + cy0.get("tiny_data", "?") + "`). The real frames are for measuring only.",
             "",
             "| object | stress test: worst effect (cost) | dev gap: real - re-drawn (instances) | Cycles val mean | renderer twin "
             "mean | Cycles / twin |",
             "|---|---|---:|---:|---:|---:|"]
    for obj, a in sorted(appearance.items()):
        sw, cy = a.get("stress_worst"), a.get("cycles")
        lines.append(f"| {obj} | " + (f"{sw['case']} ({sw['cost_deg']:+.2f})" if sw else "-")
                     + (f" | {a['gap_deg']:+.2f} ({a['real_instances']})" if "gap_deg" in a else " | -")
                     + (f" | {cy['mean_deg']:.2f} | {cy['tiny_mean_deg']:.2f} | {cy['ratio']:.2f}x |" if cy
                        else " | - | - | - |"))
    return "\n".join(lines) + "\n"


def fine_markdown(fine: dict) -> str:
    """The card's section on the fine refiners and the cascade (empty when none ships)."""
    if not fine:
        return ""
    f0 = next(iter(fine.values()))["card"]
    lines = ["", "## Fine refiners and the cascade", "",
             "A fine refiner ships beside the coarse one for these objects (`<id>.fine.int8.onnx`, "
             "`RefinerSession.pretrained(obj, stage=\"fine\")`; `RefinerCascade.pretrained(obj)` runs both). Each "
             "continued the object's coarse model on small input errors only (`python -m export.release.fine`): "
             + ", then ".join(f"`{n}`" for n in f0["stages"]) + " degrees (`normal:0:3`: half-normal angles, a 3-degree "
             "scale). Its INT8 file is scored on `" + f0["fine_noise"] + "` inputs. Measured through the runtime on the "
             "full frames of every instance in "
             f"`{f0['data']}` (fresh renders no model trained on; one U(0, 30) input per instance, and the true pose "
             "for the drift), INT8, the cascade as `RefinerCascade.pretrained` runs it (the fine refiner and the coarse "
             "refiner, four box-jittered views each; the fine result where both corrections are within the object's gates, "
             "else the fine refiner from the coarse one's result; the gates chosen on other rendered scenes, `"
             + (f0.get("gate_on") or "?") + "`, for the smallest mean of the U(0, 30) mean and the drift):", "",
             *fine_table(fine)]
    return "\n".join(lines) + "\n"


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.0f}%"


def _deg(s: dict, key: str = "mean_deg") -> str:
    return "-" if not s.get("n") else f"{s[key]:.2f}"


def portable_command(command: str) -> str:
    """``command`` as the model card prints it: a command to rerun (a script as its module,
    :func:`models.evaluate.record.current_command`) that names no folder of the build machine. The ``--data`` folder
    is written ``DATA`` and the folder holding ``--save`` ``RUN`` (paths inside them too); each ``--extra-train``
    folder by its name (a set of benchmarks/DATA.md); a ``--cache`` elsewhere ``CACHE`` (a crop cache, rebuilt where
    missing); an ``--init`` checkpoint elsewhere ``RUN/<name>.init.pt``, ``<name>`` the ``--save`` folder's (where
    :func:`export.release.coarse.recover_shipped` writes the shipped model a build starts from), ``INIT`` without
    ``--save``. So neither the card nor the JSON names a path outside the repository. Idempotent."""
    args = shlex.split(current_command(command))

    def value(flag: str) -> str | None:
        return args[args.index(flag) + 1] if flag in args[:-1] else None

    data, save = value("--data"), value("--save")
    folders = {**({data: "DATA"} if data else {}), **({str(Path(save).parent): "RUN"} if save else {})}

    def placed(a: str) -> str | None:
        for folder, name in folders.items():
            if a == folder or a.startswith(folder + "/"):
                return name + a[len(folder):]
        return None

    out = []
    for i, a in enumerate(args):
        flag = args[i - 1] if i else ""
        if flag == "--extra-train":
            a = Path(a).name
        elif flag == "--cache":
            a = placed(a) or "CACHE"
        elif flag == "--init":
            a = placed(a) or (f"RUN/{Path(save).name}.init.pt" if save else "INIT")
        else:
            a = placed(a) or a
        out.append(a)
    return shlex.join(out)


def _fresh(d: dict) -> bool:
    """Whether ``d``'s card evaluation is on fresh scenes (``requantize --heldout``) rather than its own test split."""
    return "eval_training_split" in d


def _symmetry_sentence(d: dict) -> str:
    """The card's sentence on an object scored with its symmetry too (``eval.int8.symmetric``)."""
    from models.data.symmetry import CONTINUOUS_STEPS

    sym = d["eval"]["int8"]["symmetric"]
    turns = [c["axis"] for s in sym["symmetry"].values() for c in s.get("symmetries_continuous", [])]
    what = "; ".join(f"any turn about the axis {axis} of the scan frame" for axis in turns) or "its discrete symmetries"
    return (f"`{d['object_id']}` scored with BOP's symmetry for it ({what} leaves it looking the same; the error is "
            f"to the closest such pose, turns sampled every {360 // CONTINUOUS_STEPS} degrees), on the same crops and "
            f"inputs: INT8 mean **{_deg(sym)}**, median {_deg(sym, 'median_deg')}, under 5 degrees "
            f"{_pct(sym['under_5_deg'])}, input mean {_deg(sym, 'input_mean_deg')}. The table keeps the plain geodesic "
            "error.")


def card_markdown(docs: list[dict], speed: dict, real: dict | None = None) -> str:
    fresh_docs = [d for d in docs if _fresh(d)]
    fresh = bool(fresh_docs)  # the extra column; all docs fresh is what requantize --heldout leaves
    sets = sorted({d["eval"]["split"]["data"] for d in fresh_docs})
    if fresh:
        ev0 = fresh_docs[0]["eval"]
        scenes = f"{ev0['folder_scenes']:,} scenes" if len(sets) == 1 and ev0.get("folder_scenes") else "scenes"
        which = "" if len(fresh_docs) == len(docs) else (
            " for the objects with a value in the last column; the others on the scenes held out whole from their "
            "own training set")
        measured_on = (
            "measured on **rendered scenes of a set that no shipped model trained on** ("
            + ", ".join(f"`{x}`" for x in sets) + f": {scenes} rendered with another seed than the training set, "
            "every instance of each object scored; `benchmarks/DATA.md` has its command)" + which + ". The last column "
            "is the fp32 model on its training set's own held-out test scenes (the split is drawn over the nine objects)."
        )
    else:
        measured_on = ("measured on **rendered scenes held out whole** from its training (every object's test scenes "
                       "are the same: the split is drawn over the nine objects).")
    lines = [
        "# The shipped refiners",
        "",
        "Generated by `python -m export.release.coarse card` from `benchmarks/results/pretrained/*.json`; do not edit.",
        "",
        "One refiner per YCB object, trained on images rendered by `refiner-rt render` and " + measured_on + " "
        "Instances with BOP `visib_fract >= 0.3` (the silhouette beyond the image border counted), coarse "
        "inputs drawn U(0, 30) degrees around the truth, one network pass, errors in degrees (geodesic). "
        "Rotations are relative to the YCB google_16k scan frame of `models/data/ycb_models/<id>/textured.obj` "
        "(origin near the object's base). Its axes coincide with the YCB-Video model frame's, so YCB-Video rotations "
        "apply as they are; only the origin differs, by a per-object offset (`refiner_rt.frames` converts a "
        "translation).",
        "",
        "| object | INT8 mean | median | under 5 | under 10 | input mean | inside the image: mean (n) | cut by the border: "
        "mean (n) | INT8 - fp32 | INT8 refinements/s | test crops |" + (" fp32, training set's test scenes |" if fresh else "")
        + (" real frames: mean / drift (n) |" if real else ""),
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|" + ("---:|" if fresh else "") + ("---:|" if real else ""),
    ]
    real = real or {}
    means, inputs, own = [], [], []
    for d in docs:
        e, f = d["eval"]["int8"], d["eval"]["fp32"]
        sp = speed.get("models", {}).get(d["object_id"], {}).get("int8")
        means.append(e["all"]["mean_deg"])
        inputs.append(e["all"]["input_mean_deg"])
        extra = ""
        if _fresh(d):
            own.append(d["eval_training_split"]["fp32"]["all"]["mean_deg"])
            extra = f" {own[-1]:.2f} |"
        elif fresh:
            extra = " - |"
        if real:
            r = real.get(d["object_id"])
            extra += f" {r['mean_deg']:.2f} / {r['drift_mean_deg']:.2f} ({r['instances']}) |" if r else " - |"
        lines.append(
            f"| {d['object_id']} | **{_deg(e['all'])}** | {_deg(e['all'], 'median_deg')} | {_pct(e['all']['under_5_deg'])} "
            f"| {_pct(e['all']['under_10_deg'])} | {_deg(e['all'], 'input_mean_deg')} | "
            f"{_deg(e['inside_image'])} ({e['inside_image']['n']}) | {_deg(e['cut_by_border'])} ({e['cut_by_border']['n']}) | "
            f"{e['all']['mean_deg'] - f['all']['mean_deg']:+.3f} | {'-' if sp is None else f'{sp:,.0f}'} | {e['all']['n']} |"
            + extra)
    if docs:
        lines.append(f"| **mean of {len(docs)}** | **{np.mean(means):.2f}** | | | | {np.mean(inputs):.2f} | | | | | |"
                     + (f" {np.mean(own):.2f} |" if fresh and len(own) == len(docs) else " |" if fresh else "")
                     + (f" **{np.mean([r['mean_deg'] for r in real.values()]):.2f}** / "
                        f"{np.mean([r['drift_mean_deg'] for r in real.values()]):.2f} |" if real else ""))
    if real:
        r0 = next(iter(real.values()))
        lines += ["", f"Real frames: every instance of the object in `{r0['data']}` (real YCB-Video camera frames, "
                  f"`visib_fract >= 0.3`, the visible box), {r0['draws']} coarse inputs U(0, 30) each, one pass, INT8; "
                  "the master chef can up to turns about its axis (its real annotations are unreliable about it); "
                  "drift: the error when the input is the true pose. Written by `python -m benchmarks.real --data "
                  "REAL --card` (`benchmarks/results/real/real_ycbv_dev.json`). The real frames are for measuring "
                  "only: no model was trained, calibrated or chosen on them."]
    lines += [line for d in docs if "symmetric" in d["eval"]["int8"] for line in ("", _symmetry_sentence(d))]
    lines += ["", "## How each model was made", "",
              "Each training command names the build machine's folders `DATA` (the rendered set, benchmarks/DATA.md), "
              "`RUN` (the run's folder) and `CACHE` (the crop cache, made where missing).", ""]
    for d in docs:
        t = d["train"]
        lines += [f"- `{d['object_id']}` (version {d['model_version']}, recipe `{d['recipe']['name']}`): "
                  f"{t['train_crops']:,} training crops from {t['scenes']['train_base']:,} scenes, "
                  f"{t['samples']:,} samples, best epoch {t['best_epoch']} of {t['epochs']}, "
                  + (f"started from the version-{d['init_from']['model_version'] or '?'} model ({d['init_from']['recipe']}; "
                     f"`{d['init_from']['file']}` sha256 {d['init_from']['sha256'][:12]}, turned back into the "
                     "checkpoint `RUN/<object>.init.pt` by `export.recover`), " if d.get("init_from") else "")
                  + (f"from scratch: a first stage of {d['first_stage']['samples']:,} samples whose coarse inputs are "
                     f"turns about the object's axis alone (`{d['first_stage']['noise']}`, lr {d['first_stage']['lr']:g}, "
                     "the first command), then these samples from it, " if d.get("first_stage") else "")
                  + (f"training {t['wall_s']:,.0f} s" + (f" (resumed after epoch {t['resumed_after_epoch']})"
                                                         if t.get("resumed_after_epoch") else "")
                     if t.get("wall_s") is not None
                     else "training time not recorded (its run was killed after saving the checkpoint and scored "
                          "again with `--resume`)")
                  + f" on one thread of {d['machine']['cpu']} "
                  f"({', '.join(d['machine']['isa_flags']) or 'no AVX flags read'}); "
                  + (f"{d['eval_training_split']['int8']['all']['n']} test crops from "
                     f"{d['eval_training_split']['test_scenes']} held-out scenes of its training set; "
                     if _fresh(d) else "")
                  + f"{d['eval']['int8']['all']['n']} test crops from {d['eval']['test_scenes']} "
                  + ("fresh scenes that hold it." if _fresh(d) else "held-out scenes."),
                  "  ```bash\n"
                  + (f"  {portable_command(d['first_stage']['command'])}\n" if d.get("first_stage") else "")
                  + f"  {portable_command(d['train_command'])}\n  ```"]
    if docs:
        by_scheme: dict = {}
        for d in docs:
            by_scheme.setdefault(d["export"].get("int8_scheme", "dynamic-int8"), []).append(d["object_id"])
        schemes = "; ".join(f"{sc}: {', '.join(objs)}" for sc, objs in by_scheme.items())
        calib = sorted({d["eval"]["calibration"]["data"] for d in fresh_docs if "calibration" in d["eval"]})
        lines += ["", "Then, for each: `refiner-rt export CKPT -o OBJ.onnx` (the fp32 file) and the INT8 file, quantised "
                  "from it with the fastest scheme whose mean error on the scored crops stays within "
                  f"{MAX_INT8_COST_DEG} deg of fp32's ({schemes}). Static schemes calibrate on "
                  + ("three quarters of the object's instances in " + ", ".join(f"`{c}`" for c in calib)
                     + " (other fresh scenes; the rest check the agreement), by "
                     "`python -m export.release.coarse requantize --heldout HELDOUT --calibration CALIB`"
                     if calib else "the object's training crops, by `python -m export.release.coarse build`")
                  + (" (objects without a fresh evaluation: on their training crops, by `build`)"
                     if calib and len(fresh_docs) < len(docs) else "")
                  + "; every model is scored through `RefinerSession.refine_crops`."]
    if speed:
        m = speed.get("machine", {})
        lines += ["", "## Speed", "",
                  f"`{current_command(speed.get('command', 'python -m export.release.coarse speed'))}`: batch 1, one thread, the full "
                  f"`refine()` path with `K` (crop from a 640x480 frame, network, composition), median of "
                  f"{speed.get('rounds', '?')} interleaved rounds on {m.get('cpu', '?')} "
                  f"({', '.join(m.get('isa_flags', []))}). Compare rows, not machines."]
    return "\n".join(lines) + "\n"


def publish(paths: list[Path], summary: str) -> list[Path]:
    """After a build step: regenerate the card (:func:`write_card`) and the documents' generated tables
    (:func:`models.evaluate.report.write_docs`) under a lock (two builds side by side write one card), then print
    ``summary`` and the files to commit, ``paths`` and the card's. Returns those files."""
    from models.evaluate.report import write_docs

    with open(Path(os.environ.get("TMPDIR", "/tmp")) / "refiner-rt-release.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        write_card()
        write_docs()
    changed = [p for p in [*paths, *CARD_FILES] if p.exists()]
    print(f"{summary}\nTo commit: " + " ".join(shlex.quote(str(p.relative_to(ROOT))) for p in changed), flush=True)
    return changed
