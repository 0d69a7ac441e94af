"""The floor curve: output error against input error for the coarse refiner, the fine refiner and the cascade.

For every object with a shipped fine refiner, every instance of it in each folder is refined through the runtime on
its full frame (``export/release/fine.py``'s ``runtime_errors``: the INT8 files that ship, ``RefinerCascade`` with its
defaults) from U(0, 30) inputs (``--draws`` per instance) and from the true pose (the drift); the output error is
averaged in 1-degree bins of the input error. Rendered folders are scored with the plain geodesic error (as the model
card); real frames (``--real``) as ``refiner-rt eval --all`` scores them (the can up to turns about its axis).
The real frames only measure: nothing is chosen on them.

Usage (from the repository root)::

    python -m benchmarks.studies.cascade.cascade --fresh data/ycb9_fresh_s21 --real REAL \\
        --json benchmarks/studies/cascade/cascade.json --plot benchmarks/studies/cascade/floor.png
    python -m benchmarks.studies.cascade.cascade --table benchmarks/studies/cascade/cascade.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from models.evaluate.cascade import FLOOR_BINS, objects_with_fine, runtime_errors, summarise
from models.evaluate.record import data_name
from models.evaluate.record import write_json

STAGES = ("coarse", "fine", "cascade")


def measure(objects: list[str], folder: Path, draws: int, symmetric: bool, gates: dict | None = None) -> dict:
    """Per object and pooled over objects (instances weighted alike): :func:`models.evaluate.cascade.summarise`. ``gates``:
    ``{object: (gate_deg, coarse_gate_deg)}`` in place of the shipped ones."""
    from refiner_rt.pretrained import pretrained_model

    per, pooled = {}, {}
    for obj in objects:
        m = pretrained_model(obj)
        t0 = time.perf_counter()
        e = runtime_errors(obj, m.path(int8=True), m.path(int8=True, stage="fine"), folder, draws=draws,
                           symmetric=symmetric, gate=(gates or {}).get(obj))
        per[obj] = {**summarise(e), "wall_s": round(time.perf_counter() - t0, 1)}
        for k, v in e.items():
            if isinstance(v, np.ndarray):  # the arrays; not the gates
                pooled.setdefault(k, []).append(v)
        print(f"  {obj}: {per[obj]['n']} instances, coarse {per[obj]['coarse']['mean_deg']:.2f} -> cascade "
              f"{per[obj]['cascade']['mean_deg']:.2f}, drift {per[obj]['coarse']['drift_mean_deg']:.2f} -> "
              f"{per[obj]['cascade']['drift_mean_deg']:.2f} ({per[obj]['wall_s']:.0f} s)", flush=True)
    return {"objects": per, "pooled": summarise({k: np.concatenate(v) for k, v in pooled.items()})}


def table(doc: dict) -> str:
    """Markdown: per folder and object, the mean from U(0, 30), the drift and inputs 0-3 for each stage."""
    lines = ["| images | object | refinements | coarse: U(0, 30) | cascade: U(0, 30) | coarse: inputs 0-3 | "
             "cascade: inputs 0-3 | coarse: drift | fine alone: drift | cascade: drift | through coarse |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, res in doc["sets"].items():
        rows = list(res["objects"].items())
        means = {k: np.mean([r[k.split(".")[0]][k.split(".")[1]] for _, r in rows if
                             r[k.split(".")[0]][k.split(".")[1]] is not None])
                 for k in ("coarse.mean_deg", "cascade.mean_deg", "coarse.input_0_3_mean_deg",
                           "cascade.input_0_3_mean_deg", "coarse.drift_mean_deg", "fine.drift_mean_deg",
                           "cascade.drift_mean_deg")}
        for obj, r in rows + [(f"**mean of {len(rows)}**", None)]:
            if r is None:
                vals = [means[k] for k in means]
                n, through = "", ""
            else:
                vals = [r["coarse"]["mean_deg"], r["cascade"]["mean_deg"], r["coarse"]["input_0_3_mean_deg"],
                        r["cascade"]["input_0_3_mean_deg"], r["coarse"]["drift_mean_deg"], r["fine"]["drift_mean_deg"],
                        r["cascade"]["drift_mean_deg"]]
                n, through = str(r["n"]), f"{100 * r['cascade']['coarse_used']:.0f}%"
            lines.append(f"| {res['label']} | {obj} | {n} | " + " | ".join("-" if v is None else f"{v:.2f}" for v in vals)
                         + f" | {through} |")
    return "\n".join(lines)


def plot(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = list(doc["sets"].items())
    fig, axes = plt.subplots(1, len(sets), figsize=(5.2 * len(sets), 4.2), squeeze=False)
    colours = {"coarse": "tab:red", "fine": "tab:orange", "cascade": "black"}
    x = np.arange(FLOOR_BINS) + 0.5
    for ax, (name, res) in zip(axes[0], sets):
        p = res["pooled"]
        for k in STAGES:
            y = np.array([np.nan if v is None else v for v in p[k]["floor_curve"]])
            ax.plot(x, y, color=colours[k], lw=1.5, label=f"{k} (drift {p[k]['drift_mean_deg']:.2f})")
        ax.plot([0, FLOOR_BINS], [0, FLOOR_BINS], color="0.7", lw=0.8, ls=":", label="output = input")
        ax.set_xlim(0, FLOOR_BINS)
        ax.set_ylim(0, 12 if "real" not in name else 25)
        ax.set_xlabel("input error (deg, 1-degree bins)")
        ax.set_ylabel("output error, mean (deg)")
        ax.set_title(f"{res['label']}: {p['n']} refinements, {len(res['objects'])} objects", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fresh", type=Path, help="rendered scenes no model trained on (the card's ycb9_fresh_s21)")
    ap.add_argument("--real", type=Path, help="a BOP folder of real frames (measuring only)")
    ap.add_argument("--objects", help="comma-separated YCB ids (default: every object with a fine refiner)")
    ap.add_argument("--draws", type=int, default=1, help="U(0, 30) inputs per rendered instance (default 1)")
    ap.add_argument("--real-draws", type=int, default=10, help="U(0, 30) inputs per real instance (default 10)")
    ap.add_argument("--gate-on", type=Path, metavar="FOLDER", help="choose each object's gates on this folder of "
                    "rendered scenes (fine.py's rule) instead of using the shipped ones")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--plot", type=Path)
    ap.add_argument("--table", type=Path, metavar="JSON", help="print the Markdown table of a results file and stop")
    args = ap.parse_args(argv)
    if args.table:
        print(table(json.loads(args.table.read_text())))
        return 0
    objects = objects_with_fine(args.objects, ap.error)
    if args.fresh is None and args.real is None:
        ap.error("give --fresh and/or --real")
    t0 = time.perf_counter()
    gates = None
    if args.gate_on is not None:
        from models.evaluate.cascade import choose_gate
        from refiner_rt.pretrained import pretrained_model

        gates = {}
        for obj in objects:
            m = pretrained_model(obj)
            gates[obj], _ = choose_gate(runtime_errors(obj, m.path(int8=True), m.path(int8=True, stage="fine"),
                                                       args.gate_on, seed=7))
            print(f"  {obj}: gates {gates[obj][0]:g} / {gates[obj][1]:g} deg, chosen on {data_name(args.gate_on)}",
                  flush=True)
    sets = {}
    for folder, draws, real in ((args.fresh, args.draws, False), (args.real, args.real_draws, True)):
        if folder is None:
            continue
        name = data_name(folder)
        print(f"{name}:", flush=True)
        sets[name] = {"label": ("real frames, " if real else "fresh renders, ") + name, "draws": draws,
                      "real": real, **measure(objects, folder, draws, symmetric=real, gates=gates)}
    doc = {"objects": objects, "sets": sets, "floor_bins_deg": 1, "wall_s": round(time.perf_counter() - t0, 1),
           "gates": "shipped" if gates is None else {"chosen_on": data_name(args.gate_on),
                                                     **{o: list(g) for o, g in gates.items()}}}
    print(table(doc))
    if args.json:
        write_json(args.json, doc)
    if args.plot:
        plot(doc, args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
