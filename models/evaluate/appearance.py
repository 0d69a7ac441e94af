"""The appearance benchmark: how much real pixels cost the refiners, measured without the real frames kept aside.

The command is ``python -m benchmarks.appearance`` (its docstring describes what is measured and has the usage);
this module is what it runs.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np


# Camera effects at the strength a working camera gives (a webcam indoors to a robot's RGB-D colour stream): name,
# operation of models.data.augment, strength (the argument apply_op takes).
STRESS_CASES: tuple[tuple[str, str, object], ...] = (
    ("exposure -0.7 EV", "brightness", 0.6),
    ("exposure +0.5 EV", "brightness", 1.4),
    ("gamma 0.8", "gamma", 0.8),
    ("gamma 1.25", "gamma", 1.25),
    ("white balance warm", "white_balance", (0.8, 1.0, 1.2)),
    ("white balance cool", "white_balance", (1.2, 1.0, 0.85)),
    ("colour cast green", "white_balance", (0.95, 1.15, 0.95)),
    ("saturation 0.6", "colour", 0.6),
    ("saturation 1.5", "colour", 1.5),
    ("contrast 0.7", "contrast", 0.7),
    ("contrast 1.3", "contrast", 1.3),
    ("sharpening 1.0", "sharpness", 1.0),
    ("sensor noise 4", "sensor_noise", (4.0, True)),
    ("sensor noise 8", "sensor_noise", (8.0, True)),
    ("motion blur 5 px", "motion_blur", (5.0, 0.5)),
    ("defocus 1 px", "blur", 1.0),
    ("JPEG 50", "jpeg", 50),
    ("JPEG 30", "jpeg", 30),
    ("half resolution", "downscale", 0.5),
)
DEFAULT_WORK = Path(os.environ.get("REFINER_RT_CACHE", Path.home() / ".cache" / "refiner-rt")) / "appearance"
# The shipped INT8 models' record that the model card's appearance columns read (``benchmarks.appearance --card``).
CARD_JSON = Path(__file__).resolve().parents[2] / "benchmarks" / "results" / "appearance" / "card.json"
STRESS_SEED = 7


def case_slug(name: str) -> str:
    """A folder name for a stress case (``"exposure -0.7 EV"`` -> ``exposure_-0.7_EV``)."""
    return name.replace(" ", "_").replace("/", "-")


def stressed_copy(data: Path, out: Path, op: str, strength, seed: int = STRESS_SEED) -> Path:
    """A copy of the BOP folder ``data`` at ``out`` with every colour image put through ``op`` at ``strength``
    (:func:`models.data.augment.apply_op` on the whole frame, BGR); ground truth copied unchanged. Reused when ``out``
    holds a finished copy of the same input and case (its ``stress.json``)."""
    import cv2

    from models.data.augment import apply_op

    record = {"data": str(Path(data).resolve()), "op": op, "strength": strength, "seed": seed}
    stamp = out / "stress.json"

    def finished() -> bool:  # ``out`` holds a finished copy of this input and case (this run's or another's)
        return stamp.is_file() and json.loads(stamp.read_text()) == json.loads(json.dumps(record))

    if finished():
        return out
    work = out.with_name(f"{out.name}.tmp-{os.getpid()}")  # this process's own: two runs may make the same copy
    shutil.rmtree(work, ignore_errors=True)
    shutil.copytree(data, work, ignore=shutil.ignore_patterns("depth", "mask*"))
    for i, path in enumerate(sorted(work.glob("*/rgb/*"))):
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise SystemExit(f"{path}: not an image")
        rng = np.random.default_rng([seed, i])
        changed = np.clip(apply_op(op, image.astype(np.float32), strength, rng), 0, 255).round().astype(np.uint8)
        cv2.imwrite(str(path.with_suffix(".png")), changed)
        if path.suffix != ".png":
            path.unlink()
    (work / "stress.json").write_text(json.dumps(record))
    if finished():
        shutil.rmtree(work)  # another run finished the same copy meanwhile: keep its
        return out
    shutil.rmtree(out, ignore_errors=True)
    try:
        work.rename(out)
    except OSError:  # another run's copy landed between the check and the rename
        shutil.rmtree(work)
    return out


def _folder_key(data: Path) -> str:
    return hashlib.sha256(str(Path(data).resolve()).encode()).hexdigest()[:10]


def _score(models: dict[str, Path], data: Path, draws: int, seed: int) -> dict:
    """:func:`benchmarks.real.run` with the objects' means only (the record the tables read)."""
    from models.evaluate.real import run

    r = run(models, data, draws=draws, seed=seed)
    return {"mean_deg": r["mean_deg"], "drift_mean_deg": r["drift_mean_deg"], "instances": r["instances"],
            "objects": {o: {"mean_deg": v["mean_deg"], "drift_mean_deg": v["drift_mean_deg"],
                            "instances": v["instances"]} for o, v in r["objects"].items()}}


def run_gap(models: dict[str, Path], real: Path, work: Path, draws: int, seed: int) -> dict:
    """Real frames against the same frames re-drawn at the true pose: per object and the nine-object means."""
    from models.data.render.rerender import rerender_folder
    from models.data.render import default_models_dir

    redrawn = work / f"redrawn_{_folder_key(real)}"
    if not (redrawn / "redrawn.json").is_file():
        rerender_folder(real, redrawn, default_models_dir(), "real", progress=False)
        (redrawn / "redrawn.json").write_text(json.dumps({"data": str(Path(real).resolve())}))
    a, b = _score(models, real, draws, seed), _score(models, redrawn, draws, seed)
    objects = {o: {"real_deg": a["objects"][o]["mean_deg"], "redrawn_deg": b["objects"][o]["mean_deg"],
                   "gap_deg": a["objects"][o]["mean_deg"] - b["objects"][o]["mean_deg"],
                   "instances": a["objects"][o]["instances"]} for o in a["objects"] if o in b["objects"]}
    return {"real_deg": a["mean_deg"], "redrawn_deg": b["mean_deg"], "gap_deg": a["mean_deg"] - b["mean_deg"],
            "real_drift_deg": a["drift_mean_deg"], "redrawn_drift_deg": b["drift_mean_deg"], "objects": objects}


def run_stress(models: dict[str, Path], real: Path, work: Path, draws: int, seed: int,
               cases=STRESS_CASES, progress: bool = True) -> dict:
    """Every stress case against the clean frames: the nine-object mean and drift, and their change."""
    clean = _score(models, real, draws, seed)
    rows = []
    for name, op, strength in cases:
        t0 = time.perf_counter()
        folder = stressed_copy(real, work / f"stress_{_folder_key(real)}" / case_slug(name), op, strength)
        s = _score(models, folder, draws, seed)
        rows.append({"case": name, "op": op, "strength": strength, "mean_deg": s["mean_deg"],
                     "drift_mean_deg": s["drift_mean_deg"], "cost_deg": s["mean_deg"] - clean["mean_deg"],
                     "drift_cost_deg": s["drift_mean_deg"] - clean["drift_mean_deg"],
                     "objects": {o: v["mean_deg"] for o, v in s["objects"].items()}})
        if progress:
            print(f"  {name:<22} {s['mean_deg']:6.2f} deg ({rows[-1]['cost_deg']:+.2f}), "
                  f"{time.perf_counter() - t0:.1f} s", file=sys.stderr)
    costs = [r["cost_deg"] for r in rows]
    return {"clean_deg": clean["mean_deg"], "clean_drift_deg": clean["drift_mean_deg"],
            "clean_objects": {o: v["mean_deg"] for o, v in clean["objects"].items()}, "cases": rows,
            "worst_case": rows[int(np.argmax(costs))]["case"] if rows else None,
            "worst_cost_deg": max(costs) if rows else None, "mean_cost_deg": float(np.mean(costs)) if rows else None}


def run_rendered(models: dict[str, Path], sets: dict[str, Path], draws: int, seed: int) -> dict:
    """Each rendered set scored; ``ratio`` = the first set's mean over the second's (when two or more)."""
    out = {name: _score(models, folder, draws, seed) | {"data": folder.name} for name, folder in sets.items()}
    names = list(out)
    doc = {"sets": out}
    if len(names) >= 2:
        doc["ratio"] = {"of": names[0], "to": names[1],
                        "value": out[names[0]]["mean_deg"] / out[names[1]]["mean_deg"]}
    return doc


def table(doc: dict) -> str:
    """The record as plain-text tables (the README's and the study's source)."""
    lines = []
    if "gap" in doc:
        g = doc["gap"]
        lines += ["Appearance gap (real frames against the same frames re-drawn at the true pose), degrees:",
                  f"{'object':<22}{'n':>5}{'real':>8}{'re-drawn':>10}{'gap':>8}"]
        for o, v in g["objects"].items():
            lines.append(f"{o:<22}{v['instances']:>5}{v['real_deg']:>8.2f}{v['redrawn_deg']:>10.2f}{v['gap_deg']:>+8.2f}")
        lines += [f"{'mean of objects':<22}{'':>5}{g['real_deg']:>8.2f}{g['redrawn_deg']:>10.2f}{g['gap_deg']:>+8.2f}",
                  ""]
    if "stress" in doc:
        s = doc["stress"]
        lines += [f"Stress test on the real frames: clean {s['clean_deg']:.2f} deg (drift {s['clean_drift_deg']:.2f})",
                  f"{'case':<24}{'mean':>8}{'cost':>8}{'drift':>8}{'cost':>8}"]
        for r in s["cases"]:
            lines.append(f"{r['case']:<24}{r['mean_deg']:>8.2f}{r['cost_deg']:>+8.2f}{r['drift_mean_deg']:>8.2f}"
                         f"{r['drift_cost_deg']:>+8.2f}")
        lines += [f"worst: {s['worst_case']} ({s['worst_cost_deg']:+.2f}); mean cost {s['mean_cost_deg']:+.2f}", ""]
    if "rendered" in doc:
        r = doc["rendered"]
        lines.append("Rendered sets:")
        for name, v in r["sets"].items():
            lines.append(f"  {name:<12} {v['data']:<28} {v['mean_deg']:6.2f} deg, drift {v['drift_mean_deg']:.2f} "
                         f"({v['instances']} instances)")
        if "ratio" in r:
            lines.append(f"  {r['ratio']['of']} / {r['ratio']['to']}: {r['ratio']['value']:.2f}x")
    return "\n".join(lines)


def per_object(doc: dict) -> dict:
    """Per object, the card's appearance columns from an appearance record: the worst stress case at realistic
    strength (its name and its cost over the clean frames, degrees), the dev appearance gap (real minus re-drawn), and
    the Cycles validation set's mean with its ratio to the TinyRenderer twin (the rendered sets named ``cycles`` and
    ``tiny``). Parts the record lacks are left out."""
    out: dict = {}
    stress = doc.get("stress")
    if stress and "clean_objects" in stress:
        for obj, clean in stress["clean_objects"].items():
            costs = [(c["objects"][obj] - clean, c["case"]) for c in stress["cases"] if obj in c["objects"]]
            if costs:
                cost, case = max(costs)
                out.setdefault(obj, {})["stress_worst"] = {"case": case, "cost_deg": round(cost, 3)}
    for obj, g in (doc.get("gap") or {}).get("objects", {}).items():
        out.setdefault(obj, {}).update(gap_deg=round(g["gap_deg"], 3), real_instances=g["instances"])
    sets = (doc.get("rendered") or {}).get("sets", {})
    if "cycles" in sets and "tiny" in sets:
        for obj, c in sets["cycles"]["objects"].items():
            t = sets["tiny"]["objects"].get(obj)
            if t:
                out.setdefault(obj, {})["cycles"] = {"mean_deg": round(c["mean_deg"], 3),
                                                     "tiny_mean_deg": round(t["mean_deg"], 3),
                                                     "ratio": round(c["mean_deg"] / t["mean_deg"], 3),
                                                     "data": sets["cycles"]["data"],
                                                     "tiny_data": sets["tiny"]["data"]}
    return out
