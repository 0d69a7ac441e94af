"""Does averaging more box-jittered views take the cascade to its render goals? For each ``COARSExFINE`` pair of
view counts, every object's gates are chosen on the calibration renders as ``export/release/fine.py gate`` chooses them
(the smallest U(0, 30) mean plus drift over ``models.evaluate.cascade.GATES``), then the cascade is scored on the card's
renders and, measuring only, on the real frames (ten U(0, 30) inputs per instance, the can up to its turns).

Both paths of the cascade are run for every instance once per pair (``models.evaluate.cascade.runtime_errors``, cached as
``.npz`` under ``--cache``), so objects can be run in separate processes and the table written by a last run that
finds every array cached.

    python -m benchmarks.studies.cascade.views_probe --heldout data/ycb9_fresh_s21 --calibration data/ycb9_calib_s22 \\
        --real REAL --views 1x4,4x4,1x8,4x8 --cache runs/views_probe --json benchmarks/studies/cascade/views_probe.json
"""
import argparse
import time
from pathlib import Path

import numpy as np

from models.evaluate.cascade import choose_gate, objects_with_fine, runtime_errors, with_gate
from models.evaluate.record import data_name
from models.evaluate.record import write_json
from refiner_rt.cascade import shipped_gate
from refiner_rt.geometry import MAX_VIEWS
from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name


def parse_views(text: str, error) -> list[tuple[int, int]]:
    """``"1x4,4x4"`` -> ``[(1, 4), (4, 4)]`` (coarse views x fine views, each 1 to ``MAX_VIEWS``)."""
    pairs = []
    for item in text.split(","):
        parts = item.strip().split("x")
        if len(parts) != 2 or not all(p.isdigit() and 1 <= int(p) <= MAX_VIEWS for p in parts):
            error(f"--views: {item!r} is not COARSExFINE, two view counts from 1 to {MAX_VIEWS} (e.g. 4x8)")
        pairs.append((int(parts[0]), int(parts[1])))
    return pairs


def arrays(obj: str, data: Path, cache: Path, tag: str, views: tuple[int, int], **kw) -> dict:
    """``runtime_errors`` of ``obj``'s shipped INT8 refiners on ``data`` with ``views``, from ``cache`` if there."""
    path = cache / f"{obj}.{tag}.c{views[0]}f{views[1]}.npz"
    if path.is_file():
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    t0 = time.perf_counter()
    e = runtime_errors(obj, WEIGHTS_DIR / model_file_name(obj, int8=True),
                       WEIGHTS_DIR / model_file_name(obj, int8=True, stage="fine"), data,
                       coarse_views=views[0], fine_views=views[1], **kw)
    e = {k: v for k, v in e.items() if isinstance(v, np.ndarray)}
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, **e)
    print(f"[{obj}] {tag} {views[0]}x{views[1]}: {len(e['input'])} refinements in {time.perf_counter() - t0:.0f} s",
          flush=True)
    return e


def score(e: dict, gate: tuple) -> dict:
    c = with_gate(e, gate)
    small = c["input"] < 3.0
    return {"coarse_mean_deg": float(c["coarse"].mean()), "coarse_drift_mean_deg": float(c["coarse@0"].mean()),
            "coarse_views_mean_deg": float(c["coarse_cascade"].mean()),
            "coarse_views_drift_mean_deg": float(c["coarse_cascade@0"].mean()),
            "mean_deg": float(c["cascade"].mean()), "drift_mean_deg": float(c["cascade@0"].mean()),
            "input_0_3_mean_deg": float(c["cascade"][small].mean()) if small.any() else float("nan")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--heldout", type=Path, required=True, help="the card's fresh renders")
    ap.add_argument("--calibration", type=Path, required=True, help="other fresh renders: the gates are chosen there")
    ap.add_argument("--real", type=Path, help="real frames (BOP), measuring only")
    ap.add_argument("--views", default="1x4,4x4,1x8,4x8", help="COARSExFINE view pairs, comma-separated")
    ap.add_argument("--objects", help="comma-separated YCB ids (default: every object with a fine refiner)")
    ap.add_argument("--cache", type=Path, required=True, help="folder for the per-object arrays (.npz)")
    ap.add_argument("--json", type=Path, help="the table (written once every object's arrays are there)")
    args = ap.parse_args(argv)
    objects = objects_with_fine(args.objects, ap.error)
    pairs = parse_views(args.views, ap.error)
    sets = {"calibration": (args.calibration, {"seed": 7}), "heldout": (args.heldout, {})}
    if args.real:
        sets["real"] = (args.real, {"draws": 10, "symmetric": True})
    rows = []
    for views in pairs:
        per_obj = {}
        for obj in objects:
            data = {name: arrays(obj, folder, args.cache, name, views, **kw) for name, (folder, kw) in sets.items()}
            chosen, _ = choose_gate(data["calibration"])
            per_obj[obj] = {"gate": list(chosen), **{name: score(data[name], chosen) for name in sets},
                            "shipped_gate": {name: score(data[name], shipped_gate(obj)) for name in sets}}
        row = {"coarse_views": views[0], "fine_views": views[1], "objects": per_obj}
        for key in (None, "shipped_gate"):
            for name in sets:
                per = [(p[key] if key else p)[name] for p in per_obj.values()]
                row[f"{name}{'_shipped_gate' if key else ''}"] = {
                    k: round(float(np.mean([q[k] for q in per])), 3) for k in per[0]}
        rows.append(row)
        print(f"{views[0]}x{views[1]}: " + "; ".join(
            f"{n} coarse {row[n]['coarse_mean_deg']:.2f} ({views[0]} views {row[n]['coarse_views_mean_deg']:.2f}) "
            f"cascade {row[n]['mean_deg']:.2f} "
            f"drift {row[n]['drift_mean_deg']:.2f} 0-3 {row[n]['input_0_3_mean_deg']:.2f}" for n in sets), flush=True)
    if args.json:
        write_json(args.json, {"objects": objects, "sets": {n: data_name(f) for n, (f, _) in sets.items()},
                               "gate_rule": "models.evaluate.cascade.choose_gate on the calibration set", "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
