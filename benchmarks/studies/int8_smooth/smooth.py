"""How far the shipped refiners' output moves when the coarse rotation moves a little: fp32 against INT8, before and
after the fixes, with each suspect isolated. Render-free: the package's sample frames (refiner_rt/samples).

    python -m benchmarks.studies.int8_smooth.smooth --calibration data/ycb9_calib_s22 \\
        --heldout data/ycb9_robot_fresh_s41 --out benchmarks/studies/int8_smooth/results.json

Sweep: every sample instance of each shipped object, refined by that object's model from DRAWS coarse rotations
``q_gt * U(0, 30)``; each coarse rotation is turned by STEPS degrees about a random axis and the refined rotation's
movement (geodesic, degrees) recorded. Models: the shipped fp32 and INT8 files, and the INT8 model quantised again
from the fp32 file with ``static-qdq-int8-conv-float-pose`` (calibrated as the shipped one, on ``--calibration``);
each with the crop turned by the exact roll angle (``roll_step_deg=0``, the runtime before) and by the rounded one
(``refiner_rt.preprocess.ROLL_STEP_DEG``, the runtime now).

Isolation (shipped INT8, exact roll, network level): the crop turned as for the unchanged rotation while the network's
rotation input moves (``q only``), and the crop turned as for the moved rotation while the rotation input stays
(``crop only``).

``--heldout``: mean error of each model and roll step on every instance of each object in a folder of rendered scenes
no shipped model trained on (one pass, inputs U(0, 30)), as export/release/coarse.py scores the card. Speed: median
``refine()`` time at batch 1 on 1 thread, the three models interleaved in one run.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from refiner_rt import RefinerSession
from refiner_rt import quaternion as rq
from refiner_rt.demo import load_samples
from refiner_rt.geometry import ray_quaternions
from refiner_rt.metadata import INPUT_IMAGE, INPUT_QUATERNION
from refiner_rt.preprocess import ROLL_STEP_DEG, canonical_roll, crop_to_square, roll_angle
from refiner_rt.pretrained import WEIGHTS_DIR, pretrained_models

STEPS = (1e-4, 1e-3, 1e-2, 0.1, 0.6)
DRAWS = 16
SEED = 0
NEW_SCHEME = "static-qdq-int8-conv-float-pose"


def float_pose_model(obj: str, calibration: Path, out: Path, cache: Path) -> Path:
    """The object's shipped fp32 file quantised with :data:`NEW_SCHEME`, calibrated as the shipped INT8 file was
    (every instance of ``obj`` in ``calibration``, ``export/release/coarse.py``'s ``fresh_quantization``)."""
    from export.quantize import dataset_calibration, quantize_model
    from export.release.card import metadata_props
    from models.data.pipeline import whole_folder_spec
    from refiner_rt.metadata import parse_metadata

    fp32 = WEIGHTS_DIR / f"{obj}.onnx"
    c = parse_metadata(metadata_props(fp32))
    cal = dataset_calibration(calibration, c, cache_root=cache, spec=whole_folder_spec(calibration, obj, "train_base"))
    dst = out / f"{obj}.{NEW_SCHEME}.onnx"
    quantize_model(fp32, dst, scheme=NEW_SCHEME, calibration=cal)
    return dst


def _net(sess: RefinerSession, crop: np.ndarray, q_ray: np.ndarray, q_roll: np.ndarray) -> np.ndarray:
    """The network's ``q_out`` (wxyz, unit) for ``crop`` turned by the exact roll of ``q_roll`` and the rotation input
    ``q_ray`` turned by that same angle (the network level of one refine() pass)."""
    turned, q_turned = canonical_roll(crop[None], q_roll[None], step_deg=0)
    turn = rq.multiply(q_turned[0], rq.inverse(q_roll))  # q_z(-psi)
    q_net = rq.multiply(turn, q_ray)[None].astype(np.float32)
    out = sess._session.run(None, {INPUT_IMAGE: turned, INPUT_QUATERNION: q_net})[0]
    return rq.normalize(out[0].astype(np.float64))


def sweep(objects: list[str], paths: dict[str, dict[str, Path]]) -> dict:
    rng = np.random.default_rng(SEED)
    frames = load_samples()
    images = [f.image() for f in frames]
    moves: dict = {}
    isolation: dict = {"q only": {}, "crop only": {}}
    n_instances = 0
    crossings: dict = {}  # changes of the rounded roll angle (the crop then changes under roll_step_deg too)
    for obj in objects:
        sessions = {(name, step): RefinerSession(path, roll_step_deg=step)
                    for name, path in paths[obj].items() for step in (0.0, ROLL_STEP_DEG)}
        for f, image in zip(frames, images):
            for o in f.objects:
                if o.object_id != obj:
                    continue
                n_instances += 1
                box = o.box_xyxy[None]
                q_frame = ray_quaternions(f.K, box)[0]
                crop = crop_to_square(image, o.box_xyxy, 64, 1.2)
                for _ in range(DRAWS):
                    q = rq.multiply(o.q_gt, rq.sample_rotation_noise(1, "uniform", 0, 30, rng=rng)[0])
                    for step in STEPS:
                        axis = rng.standard_normal(3)
                        q2 = rq.multiply(q, rq.from_axis_angle(axis / np.linalg.norm(axis), step))
                        for (name, roll), s in sessions.items():
                            a = s.refine(image, box, q[None], K=f.K).q_refined[0]
                            b = s.refine(image, box, q2[None], K=f.K).q_refined[0]
                            moves.setdefault(f"{name}, roll step {roll:g}", {}).setdefault(
                                f"{step:g}", []).append(float(rq.geodesic_angle(a, b)))
                        s = sessions[("int8", 0.0)]
                        qr, qr2 = rq.multiply(rq.inverse(q_frame), q), rq.multiply(rq.inverse(q_frame), q2)
                        bins = [round(math.degrees(roll_angle(*x)) / ROLL_STEP_DEG) for x in (qr, qr2)]
                        crossings[f"{step:g}"] = crossings.get(f"{step:g}", 0) + int(bins[0] != bins[1])
                        base = _net(s, crop, qr, qr)
                        isolation["q only"].setdefault(f"{step:g}", []).append(
                            float(rq.geodesic_angle(base, _net(s, crop, qr2, qr))))
                        isolation["crop only"].setdefault(f"{step:g}", []).append(
                            float(rq.geodesic_angle(base, _net(s, crop, qr, qr2))))

    def summary(d):
        return {k: {"mean_deg": float(np.mean(v)), "p95_deg": float(np.percentile(v, 95)), "max_deg": float(np.max(v)),
                    "n": len(v)} for k, v in d.items()}

    return {"instances": n_instances, "draws_per_instance": DRAWS,
            "movement": {k: summary(v) for k, v in moves.items()},
            "rounded_roll_changes": crossings,
            "isolation_int8_exact_roll": {k: summary(v) for k, v in isolation.items()}}


def heldout(objects: list[str], paths: dict[str, dict[str, Path]], folder: Path, cache: Path) -> dict:
    """Mean error per object, model and roll step on every instance of the object in ``folder``."""
    from export.release.coarse import evaluate_fresh

    out = {}
    for obj in objects:
        for step in (0.0, ROLL_STEP_DEG):
            # the scorer builds its own sessions: the constructor's default is the one to set
            init = RefinerSession.__init__
            RefinerSession.__init__ = lambda self, *a, _init=init, _step=step, **k: _init(
                self, *a, **{**k, "roll_step_deg": _step})
            try:
                ev = evaluate_fresh(paths[obj], obj, folder, cache, "ray", 64, 1.2)
            finally:
                RefinerSession.__init__ = init
            out.setdefault(obj, {})[f"roll step {step:g}"] = {
                name: round(ev[name]["all"]["mean_deg"], 4) for name in paths[obj]}
            out[obj]["n"] = ev["fp32"]["all"]["n"]
    return out


def speed(objects: list[str], paths: dict[str, dict[str, Path]], calls: int = 200, rounds: int = 5) -> dict:
    """Median refine() time (us) per model at batch 1, 1 thread, models interleaved round by round."""
    f = load_samples()[0]
    image, o = f.image(), f.objects[0]
    times: dict = {}
    for obj in objects[:3]:
        sessions = {name: RefinerSession(p) for name, p in paths[obj].items()}
        for s in sessions.values():
            for _ in range(20):
                s.refine(image, o.box_xyxy[None], o.q_gt[None], K=f.K)
        for _ in range(rounds):
            for name, s in sessions.items():
                t0 = time.perf_counter()
                for _ in range(calls):
                    s.refine(image, o.box_xyxy[None], o.q_gt[None], K=f.K)
                times.setdefault(name, []).append((time.perf_counter() - t0) / calls * 1e6)
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"refine_us": {k: round(v, 1) for k, v in med.items()},
            "ratio_to_int8": {k: round(v / med["int8"], 3) for k, v in med.items()},
            "objects": objects[:3], "calls": calls, "rounds": rounds}


def cpu() -> str:
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    except OSError:
        return platform.processor()
    name = next((line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("Model name")), "?")
    flags = next((line for line in text.splitlines() if line.startswith("Flags")), "")
    isa = "AVX-512 VNNI" if "avx512_vnni" in flags else "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "?"
    return f"{name}, {isa}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calibration", type=Path, required=True, help="rendered folder the shipped INT8 files were "
                    "calibrated on (data/ycb9_calib_s22)")
    ap.add_argument("--heldout", type=Path, help="rendered folder of scenes no shipped model trained on, for the "
                    "held-out error (omit to skip)")
    ap.add_argument("--objects", help="comma-separated YCB ids (default: every shipped object)")
    ap.add_argument("--out", type=Path, default=Path(__file__).with_name("results.json"))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    objects = args.objects.split(",") if args.objects else [m.object_id for m in pretrained_models()]
    with tempfile.TemporaryDirectory(prefix="int8-smooth-") as work:
        work = Path(work)
        paths = {obj: {"fp32": WEIGHTS_DIR / f"{obj}.onnx", "int8": WEIGHTS_DIR / f"{obj}.int8.onnx",
                       "int8 float pose": float_pose_model(obj, args.calibration, work, work / "crops")}
                 for obj in objects}
        shown = f"--calibration data/{args.calibration.resolve().name}" + (
            f" --heldout data/{args.heldout.resolve().name}" if args.heldout is not None else "") + (
            f" --objects {args.objects}" if args.objects else "")  # folder names only: no machine paths
        doc = {"command": f"python -m benchmarks.studies.int8_smooth.smooth {shown}",
               "cpu": cpu(), "roll_step_deg": ROLL_STEP_DEG, "steps_deg": list(STEPS), "objects": objects,
               "sweep": sweep(objects, paths)}
        if args.heldout is not None:
            doc["heldout"] = {"data": args.heldout.resolve().name,
                              "errors_deg": heldout(objects, paths, args.heldout, work / "crops")}
        doc["speed"] = speed(objects, paths)
    doc["seconds"] = round(time.perf_counter() - t0, 1)
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(json.dumps({k: doc[k] for k in ("sweep", "speed", "seconds")}, indent=1)[:6000])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
