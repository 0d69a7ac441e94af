"""Where a refiner's error is: on crops it trained on against held-out ones, and in the image plane against out of it.

Two questions decide what lowers a held-out error. Does the model fit its own training crops much better than new
ones (then more varied data or regularisation, not capacity, is the lever)? And is the remaining error a rotation
about the line of sight, which the crop shows directly, or a tilt out of the image plane, which only shading and
foreshortening reveal?

Usage (from the repository root)::

    python -m benchmarks.error_breakdown CKPT [CKPT ...] [--cache DIR] [--data DIR] [--json OUT]

Each checkpoint (``refiner-rt train``, its per-object fine-tuned models, or ``data_scaling.py --save``) is evaluated
on its own objects' crops in the training (base and fine-tuning; for a ``--train-scenes`` run of ``data_scaling.py``,
the training crops of its scenes only), validation and test parts of its recorded split,
with the inputs of ``refiner-rt eval`` (``uniform:0:30``, seed 2024, one pass, no augmentation). The test error
rotation ``q_refined * q_true^-1``, taken in the viewing-ray frame, is split into its twist about the ray (in the
image plane) and the swing perpendicular to it (out of the plane), and the coarse inputs' error the same way for
reference (:func:`models.evaluate.metrics.swing_twist_deg`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.evaluate.record import checkpoint_parser, parse_checkpoint_args, provenance, write_json

PARTS = ("train_base", "train_finetune", "val", "test")


def breakdown(path: Path, data: Path | None, cache: Path | None) -> dict:
    """One checkpoint's errors on each part of its split and its test error split about the viewing ray."""
    import models
    from models.evaluate.errors import evaluate_errors, torch_predictor
    from models.evaluate.metrics import swing_twist_deg
    from models.data.pipeline import checkpoint_spec, cropset_for, load_splits
    from refiner_rt import quaternion as rq

    net, info = models.load_checkpoint(path)
    if not info.get("data"):
        raise SystemExit(f"{path}: the checkpoint records no split (info['data']); train it with refiner-rt train "
                         "or data_scaling.py --save")
    spec = checkpoint_spec(info, data)
    splits = load_splits(spec)
    frame = info.get("rotation_frame", "camera")
    predictor = torch_predictor(net.eval())
    result = {"checkpoint": str(path), "objects": info.get("objects", []), "rotation_frame": frame,
              "split_mode": spec.split_mode, "train_crops": info.get("train_crops"), "parts": {}}
    objects = info.get("objects") or None
    for part in PARTS:
        if not getattr(splits, part):  # e.g. no fine-tuning part
            continue
        crops = cropset_for(splits, part, spec, net.input_size, net.config["crop_context"], cache_root=cache,
                            progress=False, crop_filter=net.config["crop_filter"])
        if objects:  # a per-object model of a split over more objects: its own object's crops only
            crops = crops.subset(np.isin(crops.obj_ids, objects))
            if len(crops) == 0:
                raise SystemExit(f"{path}: the {part} part of its split has no crops of its objects {objects}")
        if part == "train_base" and info.get("train_scene_ids"):  # data_scaling.py --train-scenes: its scenes only
            crops = crops.subset(np.isin(crops.scene_ids.astype(str), info["train_scene_ids"]))
        errors = evaluate_errors(predictor, crops, rotation_frame=frame)
        result["parts"][part] = {**errors.summary()["pooled"],
                                 "scenes": len(set(crops.scene_ids.tolist())) if crops.scene_ids is not None else None}
        if part == "test":
            test, test_errors = crops, errors
    if "test" not in result["parts"]:
        raise SystemExit(f"{path}: its recorded split has no test part (sizes {spec.sizes})")
    # The test error rotations about the viewing ray (about the optical axis when the crops have no intrinsics K).
    if test.q_ray is None:
        to_ray, axis = (lambda q: q), "optical axis (no intrinsics)"
    elif frame == "ray":
        to_ray, axis = (lambda q: q), "viewing ray"
    else:
        to_ray, axis = (lambda q: rq.multiply(rq.inverse(test.q_ray), q)), "viewing ray"
    true = to_ray(test_errors.q_true)
    for name, q in (("refined", test_errors.q_refined), ("input", test_errors.q_in)):
        swing, twist = swing_twist_deg(rq.multiply(to_ray(q), rq.inverse(true)))
        result[f"test_{name}"] = {"in_plane_mean_deg": float(twist.mean()),
                                  "in_plane_median_deg": float(np.median(twist)),
                                  "out_of_plane_mean_deg": float(swing.mean()),
                                  "out_of_plane_median_deg": float(np.median(swing))}
    result["twist_axis"] = axis
    return result


def markdown(results: list[dict]) -> str:
    lines = ["Mean geodesic error (deg), inputs U(0, 30); test error split about the viewing ray (mean / median):", "",
             "| checkpoint | split | train (base / fine-tune part) | val | test | test median | test in-plane | "
             "test out-of-plane | input in-plane | input out-of-plane |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        p, ref, inp = r["parts"], r["test_refined"], r["test_input"]
        train = " / ".join(f"{p[k]['mean_deg']:.2f}" if k in p else "-" for k in ("train_base", "train_finetune")
                           if k in p or "train_finetune" in p)
        lines.append(f"| {Path(r['checkpoint']).name} | {r['split_mode']} | {train} | "
                     f"{p['val']['mean_deg']:.2f} | {p['test']['mean_deg']:.2f} | {p['test']['median_deg']:.2f} | "
                     f"{ref['in_plane_mean_deg']:.2f} / {ref['in_plane_median_deg']:.2f} | "
                     f"{ref['out_of_plane_mean_deg']:.2f} / {ref['out_of_plane_median_deg']:.2f} | "
                     f"{inp['in_plane_mean_deg']:.2f} | {inp['out_of_plane_mean_deg']:.2f} |")
    if len(results) > 1:
        m = lambda f: float(np.mean([f(r) for r in results]))  # noqa: E731
        train = lambda r: r["parts"].get("train_finetune", r["parts"].get("train_base"))["mean_deg"]  # noqa: E731
        lines.append(f"| **mean of {len(results)}** | | {m(train):.2f} | "
                     f"{m(lambda r: r['parts']['val']['mean_deg']):.2f} | "
                     f"**{m(lambda r: r['parts']['test']['mean_deg']):.2f}** | "
                     f"{m(lambda r: r['parts']['test']['median_deg']):.2f} | "
                     f"{m(lambda r: r['test_refined']['in_plane_mean_deg']):.2f} | "
                     f"{m(lambda r: r['test_refined']['out_of_plane_mean_deg']):.2f} | "
                     f"{m(lambda r: r['test_input']['in_plane_mean_deg']):.2f} | "
                     f"{m(lambda r: r['test_input']['out_of_plane_mean_deg']):.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = checkpoint_parser(__doc__.splitlines()[0])
    args = parse_checkpoint_args(p, argv)

    from models.train.loop import set_threads

    threads = set_threads(args.threads)
    results = [breakdown(c, args.data, args.cache) for c in args.checkpoints]
    print(markdown(results))
    if args.json:
        write_json(args.json, {"study": "error on train/val/test parts, test error in and out of the image plane",
                               "results": results, "test_noise": "uniform:0:30",
                               **provenance("benchmarks.error_breakdown", argv, threads)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
