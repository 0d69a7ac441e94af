"""Build the package data of ``refiner-rt demo`` (a shipped artefact): a few rendered sample frames with ground truth, and outline points.

The demo must run without torch, without the training meshes and on scenes no shipped model trained on (those
train on renders of seed 11), so this script writes what it needs into ``refiner_rt/samples/``:

* ``<scene>_<image>.jpg``: frames of a render with seed 777, copied byte for byte (the renderer's JPEGs), chosen
  greedily so that together they show each of the paper's nine objects at least once with BOP ``visib_fract >= 0.5``;
* ``samples.json``: per frame the intrinsics ``K`` and, per instance of the nine objects with ``visib_fract >= 0.5``,
  the YCB id, the visible box ``(x1, y1, x2, y2)`` (BOP ``bbox_visib`` ``[x, y, w, h]`` converted), the
  ground-truth rotation ``q_gt`` (wxyz, object to camera, from ``cam_R_m2c`` by
  :func:`refiner_rt.quaternion.from_matrix`) and the translation in metres (for drawing only);
* ``outlines.json``: per object a few hundred points on its mesh surface (millimetres, integers, in the YCB scan
  frame of ``models/data/ycb_models/<id>/textured.obj``): area-weighted random surface samples thinned by
  farthest-point sampling, so they cover the surface evenly. The demo projects them to draw an object's outline.

Commands (about half a minute of rendering on one core):

    refiner-rt render --out DATA --frames 40 --frames-per-scene 4 --seed 777 --layout tabletop --quiet
    python -m export.release.samples --data DATA --out refiner_rt/samples
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from models.data.objects import PAPER_OBJECTS, YCBV_CLASSES
from models.data.render import YCB_MODELS_DIR, load_obj
from refiner_rt import quaternion as rq

SAMPLES_FORMAT = "refiner-rt/samples/1"
OUTLINES_FORMAT = "refiner-rt/outlines/1"
SEED = 777
MIN_VISIB = 0.5
MIN_BOX_SIDE = 32.0  # pixels: smaller instances make unreadable tiles
FRAMES = 5  # the cover first (three frames of this render), then the frames that best even out the objects' counts
OUTLINE_POINTS = 400
OBJECT_FRAME = ("YCB google_16k scan frame (models/data/ycb_models/<id>/textured.obj, origin near the base); "
                "axes as the YCB-Video model frame's, origin offset per object (refiner_rt.frames)")


def _instances(scene: Path) -> dict[int, list[dict]]:
    """Per image id: the instances of the paper's nine objects with ``visib_fract >= MIN_VISIB``."""
    gt = json.loads((scene / "scene_gt.json").read_text())
    info = json.loads((scene / "scene_gt_info.json").read_text())
    cam = json.loads((scene / "scene_camera.json").read_text())
    out = {}
    for key, gts in gt.items():
        K = np.asarray(cam[key]["cam_K"], dtype=float).reshape(3, 3)
        rows = []
        for g, i in zip(gts, info[key]):
            obj = YCBV_CLASSES[g["obj_id"] - 1]
            x, y, w, h = i["bbox_visib"]
            if obj not in PAPER_OBJECTS or i["visib_fract"] < MIN_VISIB or max(w, h) < MIN_BOX_SIDE:
                continue
            R = rq.orthonormalize(np.asarray(g["cam_R_m2c"], dtype=float).reshape(3, 3))
            rows.append({"object_id": obj, "obj_id": g["obj_id"], "box_xyxy": [x, y, x + w, y + h],
                         "q_gt_wxyz": [round(v, 8) for v in rq.from_matrix(R).tolist()],
                         "t_m": [round(v / 1000.0, 6) for v in g["cam_t_m2c"]],
                         "visib_fract": round(i["visib_fract"], 3)})
        out[int(key)] = (K, rows)
    return out


def choose_frames(data: Path) -> list[dict]:
    """``FRAMES`` frames, one per scene: first a greedy cover (each frame adds the most objects not yet shown, until all
    nine are), then the frames that add the most instances of the objects shown least often so far."""
    candidates = []
    for scene in sorted(p for p in data.iterdir() if (p / "scene_gt.json").is_file()):
        for im, (K, rows) in sorted(_instances(scene).items()):
            if rows:
                candidates.append({"scene": int(scene.name), "image": im, "path": scene / "rgb" / f"{im:06d}.jpg",
                                   "K": K, "objects": rows})
    chosen, missing = [], set(PAPER_OBJECTS)
    counts = dict.fromkeys(PAPER_OBJECTS, 0)

    def gain(c):
        new = {r["object_id"] for r in c["objects"]} & missing
        return (len(new), sum(1.0 / (1 + counts[r["object_id"]]) for r in c["objects"]))

    while len(chosen) < FRAMES:
        used = {x["scene"] for x in chosen}
        best = max((c for c in candidates if c["scene"] not in used), key=gain, default=None)
        if best is None:
            break
        chosen.append(best)
        missing -= {r["object_id"] for r in best["objects"]}
        for r in best["objects"]:
            counts[r["object_id"]] += 1
    if missing:
        raise SystemExit(f"{data}: no {FRAMES} frames show {sorted(missing)} with visib_fract >= {MIN_VISIB}; "
                         "render more scenes")
    return chosen


def outline_points(obj: str, n: int = OUTLINE_POINTS, seed: int = 0) -> dict:
    """``n`` evenly spread surface points of ``obj``'s mesh (mm) and their mean nearest-neighbour spacing (mm)."""
    v, f = load_obj(YCB_MODELS_DIR / obj / "textured.obj")
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(f), size=40 * n, p=area / area.sum())
    a, b = rng.random((2, len(pick), 1))
    flip = (a + b) > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    dense = tri[pick, 0] + a * (tri[pick, 1] - tri[pick, 0]) + b * (tri[pick, 2] - tri[pick, 0])
    chosen = [0]
    dist = np.linalg.norm(dense - dense[0], axis=1)
    for _ in range(n - 1):  # farthest-point sampling: each new point is the one farthest from those chosen
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(dense - dense[k], axis=1))
    pts = dense[chosen] * 1000.0
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return {"spacing_mm": round(float(d.min(axis=1).mean()), 1), "points_mm": np.round(pts).astype(int).tolist()}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, help=f"a render with --seed {SEED} and --frames-per-scene 4")
    p.add_argument("--out", type=Path, default=ROOT / "refiner_rt" / "samples")
    args = p.parse_args(argv)
    render = json.loads((args.data / "render_config.json").read_text())
    if render["seed"] != SEED:
        raise SystemExit(f"{args.data}: rendered with seed {render['seed']}; the samples come from seed {SEED}")
    frames = choose_frames(args.data)
    args.out.mkdir(parents=True, exist_ok=True)
    doc = {"format": SAMPLES_FORMAT, "object_frame": OBJECT_FRAME,
           "source": {"command": f"refiner-rt render --out DATA --frames 40 --frames-per-scene 4 --seed {SEED} --layout tabletop",
                      "seed": SEED, "min_visib_fract": MIN_VISIB,
                      "note": "rendered scenes no shipped model trained on (the shipped models train on seed 11)"},
           "frames": []}
    for c in frames:
        name = f"{c['scene']:06d}_{c['image']:06d}.jpg"
        shutil.copyfile(c["path"], args.out / name)
        doc["frames"].append({"file": name, "scene": c["scene"], "image": c["image"],
                              "K": [[round(x, 4) for x in row] for row in c["K"].tolist()], "objects": c["objects"]})
    (args.out / "samples.json").write_text(json.dumps(doc, indent=1) + "\n")
    outlines = {"format": OUTLINES_FORMAT, "units": "mm", "object_frame": OBJECT_FRAME,
                "source": f"{OUTLINE_POINTS} points per object: area-weighted samples of the mesh surface thinned by "
                          "farthest-point sampling (export/release/samples.py)",
                "objects": {obj: outline_points(obj) for obj in PAPER_OBJECTS}}
    text = json.dumps(outlines, separators=(",", ":"))
    (args.out / "outlines.json").write_text(text + "\n")
    size = sum(f.stat().st_size for f in args.out.iterdir() if f.is_file())
    shown = sorted({r["object_id"] for c in frames for r in c["objects"]})
    print(f"{len(frames)} frames ({sum(len(c['objects']) for c in frames)} instances of {len(shown)} objects), "
          f"{len(text) / 1e3:.0f} kB of outlines, {size / 1e6:.2f} MB in {args.out}")


if __name__ == "__main__":
    main()
