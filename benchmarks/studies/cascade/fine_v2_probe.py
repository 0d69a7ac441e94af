"""A fine refiner trained from the shipped version-6 coarse model on the robot layout, against the shipped fine
refiner (version 1: from version 5, tabletop layout), each in the cascade with the shipped version-6 coarse INT8 model.

Both fine refiners in fp32; each one's gates chosen on ``--calibration`` (``models.evaluate.cascade.measure_cascade``: rendered
scenes the card does not score), then the card's renders (``--heldout``) and the real frames (``--real``, ten U(0, 30)
inputs per instance; measuring only). The trial's fine refiner is trained first with

    python -m export.release.fine train --data data/ycb9_robot --extra-train data/ycb9_tabletop_s32_next \\
        --run runs/fine_v2 --objects OBJ --cache CACHE

    python -m benchmarks.studies.cascade.fine_v2_probe --object OBJ --run runs/fine_v2 --heldout data/ycb9_fresh_s21 \\
        --calibration data/ycb9_calib_s22 --real REAL --json benchmarks/studies/cascade/fine_v2_OBJ.json
"""
import argparse
import json
import time
from pathlib import Path

from export.onnx_export import export_checkpoint
from models.evaluate.cascade import measure_cascade, runtime_errors, summarise
from models.evaluate.record import write_json
from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", required=True, help="YCB id")
    ap.add_argument("--run", type=Path, required=True, help="the fine.py train --run folder of the trial")
    ap.add_argument("--heldout", type=Path, required=True, help="the card's fresh renders")
    ap.add_argument("--calibration", type=Path, required=True, help="other fresh renders: the gates are chosen there")
    ap.add_argument("--real", type=Path, required=True, help="real frames (BOP), measuring only")
    ap.add_argument("--json", type=Path, required=True)
    args = ap.parse_args(argv)
    obj = args.object
    coarse = WEIGHTS_DIR / model_file_name(obj, int8=True)
    trial = args.run / f"{obj}.fine_v2.onnx"
    export_checkpoint(next((args.run / f"{obj}.stage2").glob("*.pt")), trial)
    rows = {}
    for name, fine in (("shipped fine (version 1)", WEIGHTS_DIR / model_file_name(obj, int8=False, stage="fine")),
                       ("trial: from version 6, robot layout", trial)):
        t0 = time.perf_counter()
        gate, card = measure_cascade(obj, coarse, fine, args.heldout, args.calibration)
        g = (gate["deg"], gate["coarse_deg"])
        real = summarise(runtime_errors(obj, coarse, fine, args.real, draws=10, gate=g))
        rows[name] = {"gate": list(g), **{f"{where}_{k}": {m: round(s[k][m], 3) for m in
                                                          ("mean_deg", "drift_mean_deg", "input_0_3_mean_deg")}
                                          for where, s in (("card", card), ("real", real))
                                          for k in ("coarse", "fine", "cascade")},
                      "wall_s": round(time.perf_counter() - t0, 1)}
        print(name, json.dumps(rows[name]), flush=True)
    write_json(args.json, {"object": obj, "coarse": coarse.name, "fine_precision": "fp32", "heldout":
                           args.heldout.resolve().name, "calibration": args.calibration.resolve().name,
                           "real": f"{args.real.resolve().parent.name}/{args.real.resolve().name}", "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
