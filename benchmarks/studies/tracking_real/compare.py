"""Tracking from a first-frame pose against refining every frame from its own detector pose, per video.

Each video (:func:`models.evaluate.tracking_video.load_videos`: one scene, all its objects tracked together, the shipped INT8 coarse refiners, one
pass per object and frame, one thread) is run from ``--seeds`` draws of coarse poses, U(0, 30) degrees around the
truth (docs/design.md §1), the draws of ``benchmarks/tracking.py`` (``sequence_rng``):

* ``per_frame``: every frame refined once from its own fresh U(0, 30) draw (a detector on every frame);
* each tracker of ``TRACKERS``: started from the first frame's draw, no detector after it; per frame its error, its
  score (:attr:`refiner_rt.RefinerTracker.scores`) and whether it flags the object lost.

Errors are geodesic angles, the master chef can's to the closest turn about its axis (``error_deg``). Reported per
video and method: the mean error over frames and seeds, the mean last-frame error, the worst frame, and
the sequences that end above 30 degrees, with how many of those the tracker flags lost at their last frame.

Usage (from the repository root; REAL: the real dev frames' BOP folder, ``real_ycbv_dev/test``)::

    python -m benchmarks.studies.tracking_real.compare --data REAL --max-frames 20 \\
        --seeds 10 --json benchmarks/studies/tracking_real/real.json --plot benchmarks/studies/tracking_real/real.png
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from models.evaluate.tracking import cpu_record
from models.evaluate.tracking_video import TRACKERS, run, table

def plot(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(doc["videos"])
    cols = min(len(names), 4)
    rows = (len(names) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False, sharey=True)
    for ax, name in zip(axes.flat, names):
        for m, c in doc["videos"][name]["curves"].items():
            y = np.array([np.nan if x is None else x for x in c])
            ax.plot(np.arange(len(y)), y, label=m, lw=1.2)
        ax.set_title(f"{name} ({', '.join(o.split('_', 1)[1] for o in doc['videos'][name]['objects'])})", fontsize=7)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(names):]:
        ax.axis("off")
    axes[0][0].set_ylabel("mean rotation error (deg)")
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"{doc['data']}: mean over {doc['seeds']} coarse draws per frame", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, help="a BOP split folder of videos (real or rendered)")
    p.add_argument("--max-frames", type=int, default=100, help="frames per video from its first (default 100)")
    p.add_argument("--seeds", type=int, default=3, help="coarse-pose draws per video (default 3)")
    p.add_argument("--scenes", help="comma-separated scene folders (default: all)")
    p.add_argument("--trackers", help=f"comma-separated, of {', '.join(TRACKERS)} (default: all; per_frame always runs)")
    p.add_argument("--json", type=Path)
    p.add_argument("--plot", type=Path)
    p.add_argument("--report", type=Path, metavar="JSON", help="print the Markdown table of a results file and exit")
    a = p.parse_args(argv)
    if a.report:
        print(table(json.loads(a.report.read_text())))
        return 0
    trackers = TRACKERS
    if a.trackers:
        names = [n.strip() for n in a.trackers.split(",") if n.strip()]
        bad = [n for n in names if n not in TRACKERS]
        if bad or not names:
            p.error(f"--trackers: unknown {bad}; expected of {', '.join(TRACKERS)}")
        trackers = {n: TRACKERS[n] for n in names}
    t0 = time.time()
    doc = run(a.data, a.max_frames, a.seeds, a.scenes.split(",") if a.scenes else None, trackers)
    doc["wall_s"] = round(time.time() - t0, 1)
    doc["machine"] = cpu_record()
    print(json.dumps(doc["summary"], indent=1))
    print(f"wall {doc['wall_s']} s")
    if a.json:
        a.json.write_text(json.dumps(doc, indent=1) + "\n")
    if a.plot:
        plot(doc, a.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
