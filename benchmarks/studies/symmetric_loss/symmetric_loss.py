"""Plain loss against the symmetry-aware loss on a rendered symmetric object (a banded cylinder or square prism).

A cylinder whose colours change only along its axis looks the same after any turn about that axis, so the part of
the label ``q_noise^-1`` about the axis cannot be seen in the crop: the plain loss asks the network for it anyway;
the symmetry-aware loss (``models.data.symmetry``) trains towards the closest equivalent label. Both networks are the
same recipe on the same rendered data and split, trained for the same steps, and measured on the same test crops
and coarse inputs with the symmetry-aware error (and the plain error, for reference).

    python -m benchmarks.studies.symmetric_loss.symmetric_loss --work runs/symmetric_loss \\
        --json benchmarks/studies/symmetric_loss/symmetric_loss.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from models.evaluate.record import provenance, write_json

NAME = "obj_000001"
SYMMETRIES = {
    # a cylinder: any turn about its axis
    "cylinder": {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]},
    # a square prism: quarter turns about its axis (BOP 4x4 row-major matrices, translation in mm)
    "prism": {"symmetries_discrete": [[c, -s, 0, 0, s, c, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
                                      for c, s in ((0, 1), (-1, 0), (0, -1))]},
}
NET = {"input_size": 48, "conv_channels": [8, 16, 32], "fuse_width": 256, "pose_widths": [32, 256],
       "head_widths": [128, 32]}


def write_object(models: Path, shape: str, radius_mm: float = 35.0, height_mm: float = 110.0) -> None:
    """A closed cylinder or square prism (BOP models/ folder, mm) with colour bands along its axis and distinct
    caps, so its only symmetries are :data:`SYMMETRIES`' ones."""
    import trimesh

    if shape == "cylinder":
        mesh = trimesh.creation.cylinder(radius=radius_mm, height=height_mm, sections=48)
    else:
        mesh = trimesh.creation.box(extents=(1.7 * radius_mm, 1.7 * radius_mm, height_mm))
    mesh = mesh.subdivide().subdivide().subdivide()
    z = mesh.vertices[:, 2] / height_mm + 0.5  # 0 at the bottom, 1 at the top
    bands = np.array([[200, 40, 40], [40, 180, 60], [40, 60, 200], [220, 200, 40], [150, 40, 160]])
    colours = bands[np.clip((z * 5).astype(int), 0, 4)]
    top = mesh.vertices[:, 2] > height_mm / 2 - 1e-6
    bottom = mesh.vertices[:, 2] < -height_mm / 2 + 1e-6
    colours[top] = [240, 240, 240]
    colours[bottom] = [30, 30, 30]
    rgba = np.concatenate([colours, np.full((len(colours), 1), 255)], axis=1).astype(np.uint8)
    models.mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_colors=rgba, process=False).export(models / f"{NAME}.ply")
    (models / "models_info.json").write_text(json.dumps({"1": {"diameter": 2 * radius_mm, **SYMMETRIES[shape]}}))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="folder for the meshes, renders, crops and checkpoints")
    p.add_argument("--shape", choices=sorted(SYMMETRIES), default="cylinder")
    p.add_argument("--noise", default="uniform:0:30", help="coarse-pose noise of training and test")
    p.add_argument("--frames", type=int, default=600)
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--train-crops", type=int, default=400)
    p.add_argument("--val", type=int, default=50)
    p.add_argument("--test", type=int, default=100)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)

    import models
    from models.data.render import RenderConfig, render_dataset
    from models.evaluate.errors import evaluate_errors, torch_predictor
    from models.data.pipeline import checkpoint_test_set
    from models.train.recipe import TrainRecipe

    t0 = time.perf_counter()
    write_object(args.work / "models", args.shape)
    symmetry = SYMMETRIES[args.shape]
    K = ((200.0, 0.0, 79.5), (0.0, 200.0, 59.5), (0.0, 0.0, 1.0))
    cfg = RenderConfig.for_layout("tabletop", width=160, height=120, K=K, frames_per_scene=20, objects=(NAME,), objects_per_scene=(1, 1),
                       distance=(0.45, 0.7))
    data = args.work / "data"
    render_dataset(data, args.frames, args.work / "models", cfg, seed=0, progress=False)
    base = TrainRecipe.from_dict(dict(
        data=str(data), objects=[NAME], split_mode="scenes", arch="fusion", arch_config=NET, rotation_frame="ray",
        base_per_object=args.train_crops, per_object=0, val_per_object=args.val, test_per_object=args.test, epochs_mse=1,
        epochs_geodesic=args.epochs - 1, noise=args.noise, lr=1e-3, lr_schedule="cosine", batch_size=32, augment=True,
        threads=args.threads, cache_root=str(args.work / "cache"), device="cpu", name="symmetric_loss study"))
    rows = {}
    for label, symmetries in (("plain loss", {NAME: {}}), ("symmetry-aware loss", {})):
        recipe = base.merged(symmetries=symmetries) if symmetries else base
        out = args.work / "runs" / f"{label.split()[0]}.pt"
        t1 = time.perf_counter()
        models.run_training(recipe, out=out, progress=False)
        net, info = models.load_checkpoint(out)
        test, _ = checkpoint_test_set(net, info, cache_root=args.work / "cache")
        row = {"train_s": round(time.perf_counter() - t1, 1), "best_epoch": info["best_epoch"],
               "symmetries_in_checkpoint": info.get("symmetries", {})}
        for measure, sym in (("symmetry_aware", {NAME: symmetry}), ("plain", None)):
            e = evaluate_errors(torch_predictor(net), test, args.noise, seed=2024, rotation_frame="ray",
                                symmetries=sym)
            row[measure] = {"mean_deg": float(e.err_out_deg.mean()), "median_deg": float(np.median(e.err_out_deg)),
                            "under_5_deg": float((e.err_out_deg < 5).mean()),
                            "input_mean_deg": float(e.err_in_deg.mean()), "n": int(len(e.err_out_deg))}
        rows[label] = row
        print(f"{label}: symmetry-aware test error {row['symmetry_aware']['mean_deg']:.2f} deg (median "
              f"{row['symmetry_aware']['median_deg']:.2f}, input {row['symmetry_aware']['input_mean_deg']:.2f}); "
              f"plain error {row['plain']['mean_deg']:.2f}", file=sys.stderr)
    doc = {"study": f"plain vs symmetry-aware loss on a rendered banded {args.shape} (symmetric about z)",
           "object": NAME, "shape": args.shape, "symmetry": symmetry, "frames": args.frames, "recipe": base.as_dict(), "rows": rows,
           "test_noise": args.noise, **provenance("benchmarks.studies.symmetric_loss.symmetric_loss", list(sys.argv[1:] if argv is None else argv),
                                                      args.threads),
           "wall_s": round(time.perf_counter() - t0, 1)}
    if args.json:
        write_json(args.json, doc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
