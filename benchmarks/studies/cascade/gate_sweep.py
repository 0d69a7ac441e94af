"""How far the cascade's gates can trade its U(0, 30) mean for its drift: every object's gates chosen on the
calibration renders by ``mean + W * drift`` for several weights ``W``, over a wider grid than ``export/release/fine.py``
weighs, then scored on the card's renders.

``export/release/fine.py`` chooses each object's ``(gate_deg, coarse_gate_deg)`` on ``--calibration`` (rendered scenes the
card does not score) as the smallest ``mean + drift`` (``W = 1``). Both paths of the cascade are run for every
instance once (``models.evaluate.cascade.runtime_errors``, cached as ``.npz`` under ``--cache``), so every gate and weight is
read off the same arrays. ``--real`` adds the real frames (ten U(0, 30) inputs per instance; measuring only, nothing
is chosen there).

    python -m benchmarks.studies.cascade.gate_sweep --heldout data/ycb9_fresh_s21 --calibration data/ycb9_calib_s22 \\
        --cache runs/gate_sweep --json benchmarks/studies/cascade/gate_sweep.json
"""
import argparse
import time
from pathlib import Path

import numpy as np

from models.evaluate.cascade import objects_with_fine, runtime_errors, with_gate
from models.evaluate.record import data_name
from models.evaluate.record import write_json
from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name

FINE_GATES = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0)
COARSE_GATES = (4.0, 6.0, 8.0, 12.0, 16.0, 20.0, None)
WEIGHTS = (1.0, 1.5, 2.0, 3.0, 5.0, 10.0)


def arrays(obj: str, fine: Path, data: Path, cache: Path, tag: str, **kw) -> dict:
    """``runtime_errors`` of ``obj`` on ``data``, from ``cache`` when it holds them."""
    from refiner_rt.cascade import DEFAULT_COARSE_VIEWS, DEFAULT_FINE_VIEWS

    # the view counts in the name: arrays of other views (the cascade's defaults before) are not taken for these
    path = cache / f"{obj}.{tag}.c{DEFAULT_COARSE_VIEWS}f{DEFAULT_FINE_VIEWS}.npz"
    if path.is_file():
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    t0 = time.perf_counter()
    e = runtime_errors(obj, WEIGHTS_DIR / model_file_name(obj, int8=True), fine, data, **kw)
    e = {k: v for k, v in e.items() if isinstance(v, np.ndarray)}
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, **e)
    print(f"[{obj}] {tag}: {len(e['input'])} refinements in {time.perf_counter() - t0:.0f} s", flush=True)
    return e


def score(e: dict, gate: tuple) -> dict:
    """The cascade's and the coarse refiner's means with ``gate`` (inputs 0-3: NaN where no draw was that close)."""
    c = with_gate(e, gate)
    small = c["input"] < 3.0

    def under_3(a):
        return float(a[small].mean()) if small.any() else float("nan")

    return {"mean_deg": float(c["cascade"].mean()), "drift_mean_deg": float(c["cascade@0"].mean()),
            "input_0_3_mean_deg": under_3(c["cascade"]),
            "coarse_mean_deg": float(c["coarse"].mean()), "coarse_drift_mean_deg": float(c["coarse@0"].mean()),
            "coarse_input_0_3_mean_deg": under_3(c["coarse"])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--heldout", type=Path, required=True, help="the card's fresh renders")
    ap.add_argument("--calibration", type=Path, required=True, help="other fresh renders: the gates are chosen there")
    ap.add_argument("--real", type=Path, help="real frames (BOP), measuring only")
    ap.add_argument("--objects", help="comma-separated YCB ids (default: every object with a fine refiner)")
    ap.add_argument("--fine-dir", type=Path, help="fine refiners OBJ.fine.int8.onnx to use instead of the shipped")
    ap.add_argument("--cache", type=Path, required=True, help="folder for the per-object arrays (.npz)")
    ap.add_argument("--json", type=Path, required=True)
    args = ap.parse_args(argv)
    objects = objects_with_fine(args.objects, ap.error)
    gates = [(g, c) for g in FINE_GATES for c in COARSE_GATES]
    sets = {"calibration": (args.calibration, {"seed": 7}), "heldout": (args.heldout, {})}
    if args.real:
        sets["real"] = (args.real, {"draws": 10, "symmetric": True})
    data = {}
    for obj in objects:
        fine = (args.fine_dir or WEIGHTS_DIR) / model_file_name(obj, int8=True, stage="fine")
        data[obj] = {name: arrays(obj, fine, folder, args.cache, name, **kw) for name, (folder, kw) in sets.items()}
    cal = {obj: {g: score(data[obj]["calibration"], g) for g in gates} for obj in objects}  # once, for every W
    rows = []
    for w in WEIGHTS:
        chosen = {obj: min(gates, key=lambda g: cal[obj][g]["mean_deg"] + w * cal[obj][g]["drift_mean_deg"])
                  for obj in objects}
        row = {"weight": w, "gates": {o: list(g) for o, g in chosen.items()}}
        for name in sets:
            per = [score(data[o][name], chosen[o]) for o in objects]
            row[name] = {k: round(float(np.mean([p[k] for p in per])), 3) for k in per[0]}
        rows.append(row)
        print(f"W={w:g}: " + "; ".join(f"{n} mean {row[n]['mean_deg']:.2f} (coarse {row[n]['coarse_mean_deg']:.2f}) "
                                       f"drift {row[n]['drift_mean_deg']:.2f} 0-3 {row[n]['input_0_3_mean_deg']:.2f}"
                                       for n in sets), flush=True)
    write_json(args.json, {"objects": objects, "fine_gates": list(FINE_GATES), "coarse_gates": list(COARSE_GATES),
                           "sets": {n: data_name(f) for n, (f, _) in sets.items()}, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
