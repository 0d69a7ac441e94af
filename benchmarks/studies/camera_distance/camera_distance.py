"""How often rendered objects are cut by the image border, per camera distance range.

Renders the same scenes (seed, scene ids) with each camera distance range and counts, over the instances with any
visible pixel, the share cut by the border (``bbox_obj``, the whole silhouette, reaching past the image), the share
kept by ``--min-visib 0.3`` (BOP ``visib_fract``, border counted) and the median visible box height. Used to choose
``RenderConfig.distance``.

    python -m benchmarks.studies.camera_distance.camera_distance --scenes 60 --workers 2 \
        --json benchmarks/studies/camera_distance/camera_distance.json
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from models.data.render import RenderConfig, default_models_dir, render_dataset
from models.evaluate.record import write_json


def cut_stats(out: Path, width: int, height: int) -> dict:
    cut, kept, kept_cut, n, heights = 0, 0, 0, 0, []
    for info_path in sorted(out.glob("*/scene_gt_info.json")):
        for insts in json.loads(info_path.read_text()).values():
            for i in insts:
                if i["px_count_visib"] <= 0:
                    continue
                n += 1
                x, y, w, h = i["bbox_obj"]
                is_cut = x < 0 or y < 0 or x + w > width or y + h > height
                cut += is_cut
                if i["visib_fract"] >= 0.3:
                    kept += 1
                    kept_cut += is_cut
                    heights.append(i["bbox_visib"][3])
    return {"instances": n, "cut_by_border": cut / max(n, 1), "kept_min_visib_0.3": kept / max(n, 1),
            "cut_among_kept": kept_cut / max(kept, 1), "median_box_height_px": float(np.median(heights)) if heights else None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=60)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--ranges", default="0.5-1.2,0.7-1.4,0.8-1.6,1.0-1.8", help="comma-separated min-max, metres")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rows = []
    for r in args.ranges.split(","):
        lo, hi = map(float, r.split("-"))
        cfg = RenderConfig.for_layout("tabletop", frames_per_scene=4, distance=(lo, hi))
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            render_dataset(Path(tmp), args.scenes * 4, default_models_dir(), cfg, seed=args.seed, workers=args.workers,
                           progress=False)
            row = {"distance_m": [lo, hi], **cut_stats(Path(tmp), cfg.width, cfg.height),
                   "seconds": time.perf_counter() - t0}
        rows.append(row)
        print(json.dumps(row))
    if args.json:
        write_json(args.json, {"scenes": args.scenes, "seed": args.seed, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
