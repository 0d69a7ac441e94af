"""How far each test crop's rotation is from the nearest training rotation of its object, per split protocol.

The refiner learns appearance -> rotation from its training crops; a test crop whose rotation (in the network's
viewing-ray frame) is close to a training crop's can be answered by near-recall, one far from all of them must be
interpolated. The ``frames`` split (the paper's) draws test frames from the same smooth camera paths as the
training frames; the ``scenes`` split holds whole scenes out. This measures the gap between the two protocols in
the data itself, without training anything: for every test sample, the geodesic angle to the nearest training
sample of the same object (``train_base + train_finetune``), using the ground-truth rotations and boxes only (no
images are read).

Usage (from the repository root)::

    python -m benchmarks.pose_coverage --data DIR [--sizes 3000,5000,3000,3000] [--modes frames,scenes] \\
        [--json benchmarks/results/pose_coverage/pose_coverage.json]
    python -m benchmarks.pose_coverage --data DIR [--data DIR2 ...] --query REAL [--json PATH]

With ``--query`` (a BOP folder of other images, e.g. real frames) nothing is split: every instance of the query
(``visib_fract >= 0.3``) is measured against every instance of each ``--data`` folder, twice: the nearest rotation,
and the nearest *viewing direction* (the direction from the object to the camera in the object's frame, which a
turn about the viewing ray leaves unchanged: the nearest rotation once a training crop may be turned in the image
plane by any angle, ``refiner-rt train --inplane 180``), with the number of training instances within 10 degrees
of each (median). A query whose nearest rotation is far while its nearest direction is close shows the object rolled
about the ray as no training scene had it (leaning, or a tilted camera).

``--sizes`` are the per-object ``train_base,train_finetune,val,test`` of the split (default: the improved
refiner's baseline and scenes experiments); the split is ``make_splits`` with ``--split-seed``, as in training.
Symmetries are not folded in (nor are they by the error metric).
"""

from __future__ import annotations

import argparse
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from models.evaluate.record import write_json
from refiner_rt import quaternion as rq
from refiner_rt.geometry import ray_quaternions

THRESHOLDS_DEG = (2.0, 5.0, 10.0)
NEIGHBOUR_DEG = 10.0  # --query: reference instances this near a query instance are counted


def ray_frame_rotations(samples) -> np.ndarray:
    """``(N, 4)`` wxyz ground-truth rotations in each sample's viewing-ray frame (``q_ray^-1 * q_gt``)."""
    if not samples:
        return np.zeros((0, 4))
    K = np.stack([s.K for s in samples])
    boxes = np.stack([s.box_xyxy for s in samples])
    q_gt = np.stack([s.q_gt for s in samples])
    return rq.normalize(rq.multiply(rq.inverse(ray_quaternions(K, boxes)), q_gt))


def nearest_angles(query: np.ndarray, reference: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Geodesic angle (degrees) from every ``query`` rotation to its nearest ``reference`` rotation.

    Args:
        query: ``(N, 4)`` unit quaternions (wxyz).
        reference: ``(M, 4)`` unit quaternions, ``M >= 1``.
        chunk: query rows per matrix product (bounds memory at ``chunk * M`` floats).
    """
    query = np.asarray(query, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    for name, q in (("query", query), ("reference", reference)):
        if q.ndim != 2 or q.shape[1] != 4:
            raise ValueError(f"{name} must be (N, 4) wxyz quaternions; got shape {q.shape}")
    if len(reference) == 0:
        raise ValueError("reference holds no rotations: there is nothing to be near")
    best = np.empty(len(query))
    for i in range(0, len(query), chunk):
        dots = np.abs(query[i:i + chunk] @ reference.T)  # |<q, r>| = cos(angle / 2), sign-free (q ~ -q)
        best[i:i + chunk] = dots.max(axis=1)
    return np.degrees(2.0 * np.arccos(np.clip(best, 0.0, 1.0)))


def viewing_directions(q_ray: np.ndarray) -> np.ndarray:
    """``(N, 3)`` unit vectors from the object to the camera in the object's frame, from ray-frame rotations ``(N,
    4)`` (object to ray frame, wxyz): ``R^T (0, 0, -1)``, unchanged by a turn about the ray."""
    return -rq.to_matrix(q_ray)[:, 2, :]


def nearest_direction_angles(query: np.ndarray, reference: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Angle (degrees) from every ``query`` unit vector ``(N, 3)`` to its nearest ``reference`` vector ``(M, 3)``."""
    if len(reference) == 0:
        raise ValueError("reference holds no directions: there is nothing to be near")
    best = np.empty(len(query))
    for i in range(0, len(query), chunk):
        best[i:i + chunk] = (query[i:i + chunk] @ reference.T).max(axis=1)
    return np.degrees(np.arccos(np.clip(best, -1.0, 1.0)))


def query_coverage(query, references: dict) -> dict:
    """Per reference folder and object of ``query``: the nearest rotation and the nearest viewing direction of every
    query instance among all the reference's instances of that object, summarised (objects it lacks are left out)."""
    out = {}
    q_query = ray_frame_rotations(query)
    objects = np.array([s.obj_id for s in query])
    for name, samples in references.items():
        q_ref = ray_frame_rotations(samples)
        ref_objects = np.array([s.obj_id for s in samples])
        per_object = {}
        for obj in sorted(set(objects)):
            mine, theirs = q_query[objects == obj], q_ref[ref_objects == obj]
            if not len(theirs):
                continue
            rotation = nearest_angles(mine, theirs)
            d_mine, d_theirs = viewing_directions(mine), viewing_directions(theirs)
            direction = nearest_direction_angles(d_mine, d_theirs)
            # How many reference instances lie within NEIGHBOUR_DEG of each query instance (median over the query).
            half = np.cos(np.radians(NEIGHBOUR_DEG) / 2)
            near_rot = (np.abs(mine @ theirs.T) > half).sum(axis=1)
            near_dir = (d_mine @ d_theirs.T > np.cos(np.radians(NEIGHBOUR_DEG))).sum(axis=1)
            per_object[obj] = {"n": int(len(mine)), "reference": int(len(theirs)),
                               "rotation": {**summarize(rotation), "neighbours_median": float(np.median(near_rot))},
                               "direction": {**summarize(direction), "neighbours_median": float(np.median(near_dir))}}
        out[name] = per_object
    return out


def summarize(angles: np.ndarray) -> dict:
    """Mean, median, 90th percentile and the fraction under each of :data:`THRESHOLDS_DEG`."""
    if len(angles) == 0:
        raise ValueError("no angles to summarise")
    out = {"n": int(len(angles)), "mean_deg": float(angles.mean()), "median_deg": float(np.median(angles)),
           "p90_deg": float(np.percentile(angles, 90)), "max_deg": float(angles.max())}
    out.update({f"under_{t:g}_deg": float((angles < t).mean()) for t in THRESHOLDS_DEG})
    return out


def split_coverage(splits) -> dict:
    """Per object: the test part's nearest-training-rotation angles summarised, with the parts' scene counts."""
    per_object = {}
    for obj in sorted({s.obj_id for s in splits.test}):
        train = splits.part("train", obj)
        test = splits.part("test", obj)
        if not train:
            raise ValueError(f"{obj}: the training part is empty, so its test crops have no neighbours")
        angles = nearest_angles(ray_frame_rotations(test), ray_frame_rotations(train))
        per_object[obj] = {**summarize(angles), "train": len(train),
                           "train_scenes": len({s.scene_key for s in train}),
                           "test_scenes": len({s.scene_key for s in test})}
    return per_object


def _average(per_object: dict) -> dict:
    keys = [k for k in next(iter(per_object.values())) if k.endswith("_deg") or k.startswith("under_")]
    return {k: float(np.mean([row[k] for row in per_object.values()])) for k in keys}


def _parse_sizes(text: str) -> tuple[int, int, int, int]:
    try:
        sizes = tuple(int(s) for s in text.split(","))
    except ValueError:
        sizes = ()
    if len(sizes) != 4 or min(sizes) < 0 or sizes[3] == 0 or sizes[0] + sizes[1] == 0:
        raise SystemExit(f"--sizes: expected train_base,train_finetune,val,test per object like 3000,5000,3000,3000 "
                         f"(some training and some test); got {text!r}")
    return sizes


def run_query(args, argv: list[str]) -> dict:
    from models.data import load_bop

    t0 = time.perf_counter()
    objects = args.objects.split(",") if args.objects else None

    def load(folder: Path) -> list:
        try:
            samples = load_bop(folder, min_visib=0.3)
        except (FileNotFoundError, ValueError) as exc:
            raise SystemExit(f"{folder}: {exc}") from None
        samples = [s for s in samples if objects is None or s.obj_id in objects]
        if not samples:
            raise SystemExit(f"{folder}: no instance with visib_fract >= 0.3" + (f" of {objects}" if objects else ""))
        return samples

    query = load(args.query)
    references = {folder.name: load(folder) for folder in args.data}
    from models.evaluate.record import data_name

    # The query (real frames) is named as the folder's dataset, REAL in the command: no machine path is recorded.
    argv = ["REAL" if Path(a) == args.query else a for a in argv]
    return {"query": data_name(args.query), "data": [str(d) for d in args.data], "min_visib": 0.3,
            "coverage": query_coverage(query, references),
            "command": "python -m benchmarks.pose_coverage " + shlex.join(argv),
            "wall_s": round(time.perf_counter() - t0, 1),
            "machine": {"python": platform.python_version(), "platform": platform.platform()}}


def query_table(result: dict) -> str:
    """Markdown rows: one per reference folder and object, nearest rotation and nearest viewing direction."""
    lines = ["| training set | object | query instances | its instances | nearest rotation: median / max (deg) | "
             f"within {NEIGHBOUR_DEG:g} deg | nearest viewing direction: median / max (deg) | within {NEIGHBOUR_DEG:g} deg |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for name, per_object in result["coverage"].items():
        for obj, r in per_object.items():
            rot, d = r["rotation"], r["direction"]
            lines.append(f"| {name} | {obj} | {r['n']} | {r['reference']} | {rot['median_deg']:.1f} / "
                         f"{rot['max_deg']:.1f} | {rot['neighbours_median']:g} | {d['median_deg']:.1f} / "
                         f"{d['max_deg']:.1f} | {d['neighbours_median']:g} |")
    return "\n".join(lines)


def run(args) -> dict:
    from models.data import SplitSizes, make_splits
    from models.data.splits import SPLIT_MODES
    from models.data.pipeline import DataSpec, load_samples

    sizes = _parse_sizes(args.sizes)
    modes = [m for m in args.modes.split(",") if m]
    for mode in modes:
        if mode not in SPLIT_MODES:
            raise SystemExit(f"--modes {mode}: split mode must be one of {SPLIT_MODES}")
    t0 = time.perf_counter()
    spec = DataSpec(data=str(args.data), objects=args.objects.split(",") if args.objects else None)
    try:
        samples = load_samples(spec)  # read once, split once per mode
    except (FileNotFoundError, ValueError) as exc:
        raise SystemExit(f"--data {args.data}: {exc}") from None
    result = {"data": str(args.data), "sizes": list(sizes), "split_seed": args.split_seed, "modes": {}}
    for mode in modes:
        splits = make_splits(samples, mode=mode, sizes=SplitSizes(*sizes), seed=args.split_seed)
        per_object = split_coverage(splits)
        result["modes"][mode] = {"average": _average(per_object), "per_object": per_object}
    result.update(command="python " + shlex.join(sys.argv), wall_s=round(time.perf_counter() - t0, 1),
                  machine={"python": platform.python_version(), "platform": platform.platform()})
    return result


def table(result: dict) -> str:
    """Markdown rows: one per mode and object, then the mode's average."""
    lines = ["| split | object | test crops | train crops / scenes | nearest training rotation: mean | median | "
             "90% | under 2 / 5 / 10 deg |", "|---|---|---:|---:|---:|---:|---:|---|"]
    for mode, block in result["modes"].items():
        for obj, r in block["per_object"].items():
            lines.append(f"| {mode} | {obj} | {r['n']} | {r['train']} / {r['train_scenes']} | {r['mean_deg']:.2f} | "
                         f"{r['median_deg']:.2f} | {r['p90_deg']:.2f} | {r['under_2_deg']:.0%} / "
                         f"{r['under_5_deg']:.0%} / {r['under_10_deg']:.0%} |")
        a = block["average"]
        lines.append(f"| {mode} | **average** | | | **{a['mean_deg']:.2f}** | {a['median_deg']:.2f} | "
                     f"{a['p90_deg']:.2f} | {a['under_2_deg']:.0%} / {a['under_5_deg']:.0%} / "
                     f"{a['under_10_deg']:.0%} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, action="append",
                        help="dataset folder (BOP split folder or YCB-Video root); with --query, one or more "
                             "training sets, each given with its own --data")
    parser.add_argument("--query", type=Path, default=None,
                        help="a BOP folder of other images (real frames): measure its instances against every "
                             "instance of each --data, no split")
    parser.add_argument("--sizes", default="3000,5000,3000,3000",
                        help="per-object train_base,train_finetune,val,test (default: %(default)s)")
    parser.add_argument("--modes", default="frames,scenes", help="split modes, comma-separated (default: %(default)s)")
    parser.add_argument("--objects", default=None, help="YCB ids, comma-separated (default: the paper's nine)")
    parser.add_argument("--split-seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None, help="write the result here")
    args = parser.parse_args(argv)
    if args.query is not None:
        result = run_query(args, list(sys.argv[1:] if argv is None else argv))
        print(query_table(result))
    else:
        if len(args.data) > 1:
            parser.error("several --data folders need --query (the split protocols measure one folder)")
        args.data = args.data[0]
        result = run(args)
        print(table(result))
    if args.json:
        write_json(args.json, result)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
