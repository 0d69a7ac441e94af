"""How much of a refiner's error is a turn about one axis of the object: the master chef can's turn about its own axis.

Splits each rotation error (``q_true^-1 q``, in the object's frame) into its *twist* about ``--axis`` and the *swing*
that is left (``error = swing * twist``), for the coarse inputs and for the refined rotations, on every instance of
the object in a folder of fresh rendered scenes (the crops, filters and coarse inputs of the shipped models' card:
``visib_fract >= 0.3``, U(0, 30) degrees, seed 2024). The slope of the refined twist against the input twist says
how much of the turn the network corrects: 0 all of it, 1 none.

    python -m benchmarks.studies.can_twist.twist --heldout data/ycb9_fresh_s21 \\
        --json benchmarks/studies/can_twist/twist_v4.json                      # the shipped can, INT8 and fp32
    python -m benchmarks.studies.can_twist.twist --heldout data/ycb9_fresh_s21 --model runs/x/can.onnx
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from models.evaluate.record import provenance, write_json
from refiner_rt import quaternion as rq


def twist_swing(q_err: np.ndarray, axis) -> tuple[np.ndarray, np.ndarray]:
    """Signed twist angle about ``axis`` and unsigned swing angle (degrees) of rotations ``q_err`` (``(N, 4)``
    ``wxyz``), with ``q_err = swing * twist`` (the twist applied first, about the object's axis)."""
    q = np.asarray(q_err, float).reshape(-1, 4)
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    twist_rad = 2.0 * np.arctan2(q[:, 1:] @ a, q[:, 0])
    twist_rad = (twist_rad + np.pi) % (2 * np.pi) - np.pi
    twist_q = np.column_stack([np.cos(twist_rad / 2), np.outer(np.sin(twist_rad / 2), a)])
    swing = rq.geodesic_angle(q, twist_q)  # the angle of q * twist^-1
    return np.degrees(twist_rad), np.asarray(swing, float)


def _parts(q: np.ndarray, q_true: np.ndarray, axis) -> dict:
    err = rq.multiply(rq.inverse(q_true), q)
    twist, swing = twist_swing(err, axis)
    return {"mean_deg": float(rq.geodesic_angle(q_true, q).mean()), "twist_mean_deg": float(np.abs(twist).mean()),
            "swing_mean_deg": float(swing.mean())}, twist


def measure(model: Path, obj: str, heldout: Path, axis) -> dict:
    """The twist/swing split of ``model``'s errors on every instance of ``obj`` in ``heldout``."""
    from export.release.card import metadata_props
    from models.data.pipeline import whole_folder_spec
    from models.evaluate.errors import evaluate_errors, onnx_predictor
    from models.data.pipeline import cropset_for, load_splits

    meta = metadata_props(model)
    spec = whole_folder_spec(heldout, obj, "test")
    splits = load_splits(spec)
    test = cropset_for(splits, "test", spec, int(meta["input_size"]), float(meta["crop_context"]),
                       cache_root=heldout / ".crops", progress=False)
    e = evaluate_errors(onnx_predictor(model, threads=1), test, "uniform:0:30", seed=2024,
                        rotation_frame=meta.get("rotation_frame", "camera"))
    coarse, tw_in = _parts(e.q_in, e.q_true, axis)
    refined, tw_out = _parts(e.q_refined, e.q_true, axis)
    slope = float(np.polyfit(tw_in, tw_out, 1)[0])
    return {"model": model.name, "model_version": meta.get("model_version"), "n": int(len(tw_in)),
            "coarse": coarse, "refined": refined, "twist_slope": slope}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heldout", type=Path, required=True, help="a folder of rendered scenes no model trained on")
    ap.add_argument("--object", default="002_master_chef_can")
    ap.add_argument("--axis", default="0,0,1", help="the object-frame axis, x,y,z (default: the can's, z)")
    ap.add_argument("--model", type=Path, action="append",
                    help="ONNX model(s) (default: the shipped INT8 and fp32 files of --object)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    try:
        axis = [float(v) for v in args.axis.split(",")]
        if len(axis) != 3 or not np.linalg.norm(axis) > 0:
            raise ValueError
    except ValueError:
        ap.error(f"--axis must be three numbers x,y,z, not all zero; got {args.axis!r}")
    if args.model:
        models = args.model
    else:
        from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name

        models = [WEIGHTS_DIR / model_file_name(args.object, int8=i8) for i8 in (True, False)]
    rows = [measure(m, args.object, args.heldout, axis) for m in models]
    for r in rows:
        c, f = r["coarse"], r["refined"]
        print(f"{r['model']} (version {r['model_version']}, n={r['n']}): error {c['mean_deg']:.2f} -> "
              f"{f['mean_deg']:.2f}; twist {c['twist_mean_deg']:.2f} -> {f['twist_mean_deg']:.2f}; swing "
              f"{c['swing_mean_deg']:.2f} -> {f['swing_mean_deg']:.2f}; twist slope {r['twist_slope']:.3f}")
    if args.json:
        write_json(args.json, {"object": args.object, "axis": axis, "heldout": args.heldout.resolve().name,
                               "noise": "uniform:0:30", "seed": 2024, "rows": rows,
                               **provenance("benchmarks.studies.can_twist.twist", argv)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
