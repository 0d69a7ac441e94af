"""Averaging a refiner's corrections on held-out crops: box-jittered views of each crop, and ensembles of models.

A refiner's correction ``q_out`` is noisy. Two ways to average it cost network passes, not training or data:
*views* refine each test crop and ``K - 1`` box-jittered copies of it (the windows of
``RefinerSession.refine(views=K)``: the centre shifted and the side scaled by up to 5% of the window, a fixed pattern,
as the training's box jitter; here one affine resample of the cached crop) and average the ``K`` corrections; an *ensemble* averages the corrections of several models (trained on the same split), with one
view or ``K``. The average is the chordal mean of the rotations (``refiner_rt.quaternion.mean``, SciPy's
``Rotation.mean``), composed as ``q_in * q_out`` like one pass.

Usage (from the repository root)::

    python -m benchmarks.averaging CKPT [CKPT ...] [--views 4,8] [--runtime] [--cache DIR] [--data DIR] [--json OUT]

``--runtime`` also measures each model's views end to end, the way robot code runs them: the checkpoint exported to
ONNX (``refiner-rt export``, parity-checked) and ``RefinerSession.refine(image, box, q_in, K=K, views=K)`` on the full
frames of the test crops, with the same coarse poses (so one view there is the exported model on the runtime's own
crops, and the views see real pixels where a window leaves the cached crop).

Every checkpoint must record the same split (``refiner-rt train`` or ``data_scaling.py --save``; training folders added
with ``--extra-train`` change no held-out crops, so such models may be mixed with the others); they are tested
on its test crops of their objects with the inputs of ``refiner-rt eval`` (``uniform:0:30``, seed 2024), so every
row sees the same crops and coarse poses. Each row states its network passes per object (views x models): the
averaging's price in speed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from models.evaluate.record import checkpoint_parser, parse_checkpoint_args, provenance, write_json


def jittered_views(crops: np.ndarray, views: int) -> list[np.ndarray]:
    """``crops`` (uint8 NHWC, each the crop window of its box) and ``views - 1`` copies of them seen through the
    windows of ``RefinerSession.refine(views=...)`` (``refiner_rt.session.view_offsets``): one affine resample of the
    cached crop each, zeros where the window leaves the crop (the runtime re-crops the image there)."""
    import torch
    import torch.nn.functional as F

    from refiner_rt.geometry import view_offsets

    x = torch.from_numpy(np.array(crops)).permute(0, 3, 1, 2).float()
    out = [np.asarray(crops)]
    for dx, dy, ds in view_offsets(views)[1:]:
        # affine_grid units: the window spans [-1, 1], so a shift of dx windows is 2 * dx.
        theta = torch.tensor([[1 + ds, 0.0, 2 * dx], [0.0, 1 + ds, 2 * dy]], dtype=torch.float32).expand(len(x), 2, 3)
        grid = F.affine_grid(theta, list(x.shape), align_corners=False)
        y = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        out.append(y.clamp(0, 255).round().to(torch.uint8).permute(0, 2, 3, 1).contiguous().numpy())
    return out


def averaged_predictor(nets: list, views: int):
    """A predictor (``models.evaluate.errors``) that averages the corrections of ``nets`` over ``views`` views."""
    from models.train.loop import predict
    from refiner_rt import quaternion as rq

    def run(crops, q_in):
        outs = [predict(net, v, q_in) for v in jittered_views(crops, views) for net in nets]
        return rq.mean(np.stack(outs), axis=0)

    return run


def load_models(paths: list[Path], data: Path | None, cache: Path | None):
    """The nets, their shared test crops (of their objects) and rotation frame; refuses checkpoints of other splits."""
    import models
    from models.data.pipeline import checkpoint_spec, checkpoint_test_set

    loaded = [models.load_checkpoint(p) for p in paths]
    first = loaded[0][1]
    for p, (_, info) in zip(paths, loaded):
        if not info.get("data"):
            raise SystemExit(f"{p}: the checkpoint records no split (info['data']); train it with refiner-rt train "
                             "or data_scaling.py --save")
    split = checkpoint_spec(first).held_out()  # models trained on more folders (extra_train) test on the same crops
    for p, (net, info) in zip(paths, loaded):
        for key, what in (("data", "split"), ("rotation_frame", "rotation frame"), ("objects", "objects")):
            differs = checkpoint_spec(info).held_out() != split if key == "data" else info.get(key) != first.get(key)
            if differs:
                raise SystemExit(f"{p}: its {what} ({info.get(key)}) is not that of {paths[0]} ({first.get(key)}); "
                                 "averaging compares models on the same test crops: give checkpoints of one split, "
                                 "frame and object set")
        if (net.input_size, net.config["crop_context"]) != (loaded[0][0].input_size,
                                                             loaded[0][0].config["crop_context"]):
            raise SystemExit(f"{p}: its crops (input size, context) differ from those of {paths[0]}")
    try:  # one load of the split gives both the crops and their samples (frames, boxes)
        test, _, samples = checkpoint_test_set(loaded[0][0], first, data=data, cache_root=cache, with_samples=True)
    except ValueError as e:
        raise SystemExit(f"{paths[0]}: {e}") from None
    objects = first.get("objects") or None
    keep = np.flatnonzero(np.isin(test.obj_ids, objects)) if objects else np.arange(len(test))
    test = test.subset(keep)
    if len(test) == 0:
        raise SystemExit(f"{paths[0]}: its recorded split has no test crops of its objects {objects}")
    samples = [samples[i] for i in keep]
    return [m.eval() for m, _ in loaded], test, first.get("rotation_frame", "camera"), samples


def runtime_errors(ckpt: Path, test, frame: str, samples: list, views: list[int], workdir: Path) -> dict[int, dict]:
    """``{K: pooled summary}`` of ``RefinerSession.refine(views=K)`` on the full frames of ``test`` (``samples``: its
    frames and boxes), with the coarse poses of ``models.evaluate.errors.evaluate_errors`` (seed 2024, ``uniform:0:30``),
    for the checkpoint exported to ONNX."""
    import cv2

    from export.onnx_export import export_checkpoint
    from models.evaluate.metrics import summarize_errors
    from models.data.noise import NoiseSpec, perturb
    from refiner_rt import RefinerSession
    from refiner_rt import quaternion as rq

    q_gt = np.array([rq.from_matrix(s.R) for s in samples])
    assert rq.geodesic_angle(q_gt, test.q_gt).max() < 1e-6, "the crops and samples of one split load disagree"
    onnx = workdir / f"{ckpt.stem}.onnx"
    export_checkpoint(ckpt, onnx)
    sess = RefinerSession(onnx, threads=1)
    rng = np.random.default_rng(2024)  # evaluate_errors' coarse poses: the same inputs as the other rows
    q_in, _ = perturb(test.q_gt_in(frame), NoiseSpec.parse("uniform:0:30"), rng)
    if frame == "ray":
        q_in = rq.multiply(test.q_ray, q_in)  # the ray frame's input back in the camera frame refine() takes
    err_in = rq.geodesic_angle(q_in, q_gt)
    counts = [1, *views]
    refined = {k: np.zeros_like(q_gt) for k in counts}
    for i, s in enumerate(samples):  # each frame read once, for all the view counts
        image = cv2.imread(s.image_path, cv2.IMREAD_COLOR)
        if image is None:
            raise SystemExit(f"{ckpt}: cannot read the test frame {s.image_path} (a missing or unreadable image)")
        for k in counts:
            res = sess.refine(image, s.box_xyxy[None], q_in[i : i + 1], K=s.K if frame == "ray" else None, views=k)
            refined[k][i] = res.q_refined[0]
    return {k: summarize_errors(test.obj_ids, rq.geodesic_angle(refined[k], q_gt), err_in)["pooled"] for k in counts}


def run(paths: list[Path], views: list[int], data: Path | None, cache: Path | None, runtime: bool = False) -> list[dict]:
    import tempfile

    from models.evaluate.errors import evaluate_errors

    nets, test, frame, samples = load_models(paths, data, cache)
    names = [p.name for p in paths]
    if len(set(names)) < len(names):  # e.g. data_scaling.py --save of two runs in two folders: add the folder
        names = [f"{p.parent.name}/{p.name}" for p in paths]
    if len(set(names)) < len(names):
        names = [str(p) for p in paths]
    rows = []
    groups = [[i] for i in range(len(nets))] + ([list(range(len(nets)))] if len(nets) > 1 else [])
    for group in groups:
        for k in [1, *views]:
            errors = evaluate_errors(averaged_predictor([nets[i] for i in group], k), test, rotation_frame=frame)
            row = {"models": [names[i] for i in group], "views": k, "passes": k * len(group),
                   **errors.summary()["pooled"]}
            rows.append(row)
            print(f"{' + '.join(row['models'])}, {k} view(s): {row['mean_deg']:.2f} deg (median {row['median_deg']:.2f})",
                  file=sys.stderr)
    if runtime:
        with tempfile.TemporaryDirectory() as tmp:
            for path, name in zip(paths, names):
                for k, summary in runtime_errors(path, test, frame, samples, views, Path(tmp)).items():
                    rows.append({"models": [name], "views": k, "passes": k, "path": "runtime", **summary})
                    print(f"{name}, {k} view(s), RefinerSession on the full frames: {summary['mean_deg']:.2f} deg "
                          f"(median {summary['median_deg']:.2f})", file=sys.stderr)
    return rows


def markdown(rows: list[dict]) -> str:
    lines = ["Mean geodesic error (deg) on the test crops, inputs U(0, 30); path: the cached crops in PyTorch, or the "
             "exported model in RefinerSession on the full frames (runtime):", "",
             "| models | views | network passes | path | mean | median | under 5 deg |",
             "|---|---:|---:|---|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {' + '.join(r['models'])} | {r['views']} | {r['passes']} | {r.get('path', 'crops')} | "
                     f"{r['mean_deg']:.2f} | {r['median_deg']:.2f} | {100 * r['under_5_deg']:.0f}% |")
    return "\n".join(lines)


def _parse_views(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or any(v < 2 for v in values):
        raise argparse.ArgumentTypeError(f"expected view counts >= 2, comma-separated (one view is always measured); "
                                         f"got {text!r}")
    return sorted(set(values))


def main(argv: list[str] | None = None) -> int:
    p = checkpoint_parser(__doc__.splitlines()[0], json_help="write the rows and the command here")
    p.add_argument("--views", type=_parse_views, default=[4, 8], metavar="K[,K...]",
                   help="view counts to measure besides one (default: 4,8)")
    p.add_argument("--runtime", action="store_true",
                   help="also measure each model's views end to end: exported to ONNX and run by "
                        "RefinerSession.refine(views=K) on the full frames, with the same coarse poses")
    args = parse_checkpoint_args(p, argv)

    from models.train.loop import set_threads

    threads = set_threads(args.threads)
    rows = run(args.checkpoints, args.views, args.data, args.cache, runtime=args.runtime)
    print(markdown(rows))
    if args.json:
        write_json(args.json, {"study": "corrections averaged over box-jittered views and over models", "rows": rows,
                               "test_noise": "uniform:0:30", "checkpoints": [str(c) for c in args.checkpoints],
                               **provenance("benchmarks.averaging", argv, threads)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
