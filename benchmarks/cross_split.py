"""Refiners trained on different splits or datasets, compared on the same held-out crops that none of them saw.

A model's test error is measured on its own split's test part, so two models trained on different data (a larger
rendered set, another split seed) are normally scored on different test scenes, and part of the difference is the
test scenes. This script scores every checkpoint on one set of crops: the test part of the first checkpoint's
recorded split, minus every crop whose scene any of the checkpoints trained or validated on.

Usage (from the repository root)::

    python -m benchmarks.cross_split CKPT [CKPT ...] [--cache DIR] [--threads N] [--json OUT]

Scenes are compared by their folder on disk with symbolic links resolved, so a dataset that links the scene
folders of another (a rendered set extended with more scenes, say) is recognised as holding the same scenes.
Inputs are those of ``refiner-rt eval`` (``uniform:0:30``, seed 2024, one pass): every model sees the same crops with
the same coarse rotations. Checkpoints come from ``refiner-rt train`` or ``data_scaling.py --save`` (they record
their split); each must cover the first checkpoint's objects.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from models.evaluate.record import checkpoint_parser, parse_checkpoint_args, provenance, write_json

SEEN_PARTS = ("train_base", "train_finetune", "val")


def scene_folder(sample) -> str:
    """The sample's scene folder with links resolved (the ancestor of its image named after its scene id)."""
    path = Path(sample.image_path)
    for parent in path.parents:
        if parent.name == sample.scene_id:
            return str(parent.resolve())
    return f"{Path(sample.dataset).resolve()}::{sample.scene_id}"  # a layout without scene folders


def _spec(path: Path, info: dict):
    from models.data.pipeline import DataSpec

    if not info.get("data"):
        raise SystemExit(f"{path}: the checkpoint records no split (info['data']); train it with refiner-rt train "
                         "or data_scaling.py --save")
    return DataSpec.from_dict(info["data"])


def compare(paths: list[Path], cache: Path | None) -> dict:
    """Every checkpoint's error on the first one's test crops from scenes none of them trained or validated on."""
    import models
    from models.evaluate.errors import evaluate_errors, torch_predictor
    from models.data.pipeline import cropset_for, load_splits

    loaded = [(p, *models.load_checkpoint(p)) for p in paths]
    objects = loaded[0][2].get("objects") or []
    for p, _, info in loaded[1:]:
        if objects and info.get("objects") and not set(objects) <= set(info["objects"]):
            raise SystemExit(f"{p}: its objects {info['objects']} do not cover the first checkpoint's {objects}")
    split_cache: dict[str, object] = {}

    def splits_of(spec):
        key = json.dumps(spec.as_dict(), sort_keys=True)
        if key not in split_cache:
            split_cache[key] = load_splits(spec)
        return split_cache[key]

    seen: set[str] = set()
    models_seen = []
    for p, _, info in loaded:
        own = set(info.get("objects") or [])
        splits = splits_of(_spec(p, info))
        scenes = {scene_folder(s) for part in SEEN_PARTS for s in getattr(splits, part) if not own or s.obj_id in own}
        models_seen.append(len(scenes))
        seen |= scenes

    spec0 = _spec(paths[0], loaded[0][2])
    test = splits_of(spec0).test
    if not test:
        raise SystemExit(f"{paths[0]}: its recorded split has no test part (sizes {spec0.sizes})")
    mine = np.array([not objects or s.obj_id in objects for s in test])
    folders = [scene_folder(s) for s in test]
    keep = mine & np.array([f not in seen for f in folders])
    if not keep.any():
        raise SystemExit(f"none of the {int(mine.sum())} test crops of {paths[0]} is from a scene that no checkpoint "
                         "trained or validated on")
    result = {"test_of": str(paths[0]), "objects": objects, "test_crops": int(mine.sum()),
              "test_scenes": len({f for f, m in zip(folders, mine) if m}), "kept_crops": int(keep.sum()),
              "kept_scenes": sorted({f for f, k in zip(folders, keep) if k}), "models": []}
    for (p, net, info), n_seen in zip(loaded, models_seen):
        crops = cropset_for(splits_of(spec0), "test", spec0, net.input_size, net.config["crop_context"],
                            cache_root=cache, progress=False, crop_filter=net.config["crop_filter"]).subset(np.flatnonzero(keep))
        errors = evaluate_errors(torch_predictor(net.eval()), crops, rotation_frame=info.get("rotation_frame", "camera"))
        spec = _spec(p, info)
        result["models"].append({"checkpoint": str(p), "data": spec.data, "split_mode": spec.split_mode,
                                 "train_crops": info.get("train_crops"), "seen_scenes": n_seen,
                                 **errors.summary()["pooled"]})
    return result


def markdown(r: dict) -> str:
    lines = [f"Test crops of {Path(r['test_of']).name} ({r['test_crops']} in {r['test_scenes']} scenes) from scenes no "
             f"model trained or validated on: {r['kept_crops']} in {len(r['kept_scenes'])} scenes; inputs U(0, 30).", "",
             "| checkpoint | trained on | split | train crops | scenes seen | mean | median | under 5 | input mean |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for m in r["models"]:
        lines.append(f"| {Path(m['checkpoint']).name} | {Path(m['data']).name} | {m['split_mode']} | "
                     f"{m['train_crops'] if m['train_crops'] is not None else '-'} | {m['seen_scenes']} | "
                     f"{m['mean_deg']:.2f} | {m['median_deg']:.2f} | {100 * m['under_5_deg']:.1f}% | "
                     f"{m['input_mean_deg']:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = checkpoint_parser(__doc__.splitlines()[0], data=False,
                          checkpoints_help="the first one's split gives the test crops")
    args = parse_checkpoint_args(p, argv)

    from models.train.loop import set_threads

    threads = set_threads(args.threads)
    result = compare(args.checkpoints, args.cache)
    print(markdown(result))
    if args.json:
        write_json(args.json, {"study": "checkpoints on the same test crops from scenes none of them saw", **result,
                               "test_noise": "uniform:0:30", **provenance("benchmarks.cross_split", argv, threads)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
