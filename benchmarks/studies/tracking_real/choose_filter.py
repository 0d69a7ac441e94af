"""Choose the tracker's temporal filter on rendered video: ``prediction_weight`` (the share of the last rotation kept
in each new one, with no motion prediction) and ``max_correction_deg`` (the most a rotation may move per update),
by the mean error over the chosen scenes' frames and seeds (``compare.run``).

Usage::

    python -m benchmarks.studies.tracking_real.choose_filter --data data/tracking_robot_s559 --scenes 0-14 \\
        --json benchmarks/studies/tracking_real/choose_filter.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from models.evaluate.tracking_video import run

WEIGHTS = (0.0, 0.25, 0.5, 0.65)
MAX_CORRECTIONS = (None, 3.0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--scenes", required=True, help="first-last scene numbers, e.g. 0-14")
    p.add_argument("--max-frames", type=int, default=100)
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--json", type=Path)
    a = p.parse_args(argv)
    lo, hi = (int(v) for v in a.scenes.split("-"))
    scenes = [f"{k:06d}" for k in range(lo, hi + 1)]
    grid = {f"w{w}_max{m}": {"prediction_weight": w, "max_correction_deg": m, "lost_deg": None}
            for w in WEIGHTS for m in MAX_CORRECTIONS}
    t0 = time.time()
    doc = run(a.data, a.max_frames, a.seeds, scenes, grid)
    rows = sorted(((v["mean_deg"], k, v) for k, v in doc["summary"].items()), key=lambda r: r[0])
    for mean, k, v in rows:
        print(f"{k:22s} mean {mean:6.3f} last {v['last_frame_mean_deg']:6.3f} ended>30 {v['ended_above_30']}")
    doc["wall_s"] = round(time.time() - t0, 1)
    if a.json:
        a.json.write_text(json.dumps({k: doc[k] for k in ("data", "seeds", "max_frames", "trackers", "summary",
                                                          "wall_s")}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
