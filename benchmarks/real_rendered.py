"""Real frames with their objects re-drawn: what the view costs on real frames, apart from the appearance.

Writes a copy of a BOP folder of real frames in which every annotated object is replaced by a render of its mesh
at its true pose (pybullet's TinyRenderer, the training renderer, one fixed light), over the real image
(``--background real``) or over flat grey (``--background grey``). Score the copy as the real frames are scored
(``benchmarks/real.py --data OUT``): an object whose error stays high on its renders at the true pose fails on its
view (a pose its training scenes lack, ``benchmarks/pose_coverage.py --query``), not on how real pixels look; the
difference to the real frames' score is what the appearance costs. Annotated objects occlude each other as in the
frame; objects that are not annotated are not drawn, so where one hid an annotated object the render shows it.

Real frames are for measuring only: never train, calibrate or choose a checkpoint on them or on this copy.

Usage (from the repository root)::

    python -m benchmarks.real_rendered --data REAL --out data/real_rendered/test [--background grey]
    python -m benchmarks.real --data data/real_rendered/test --json benchmarks/results/real/rendered_real.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from models.data.render.rerender import rerender_folder


def main(argv=None) -> int:
    from models.data.render import default_models_dir

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="a BOP split folder of real frames (real_ycbv_dev/test)")
    ap.add_argument("--out", type=Path, required=True, help="the copy to write (replaced if it exists)")
    ap.add_argument("--background", choices=("real", "grey"), default="real",
                    help="what lies behind the re-drawn objects: the real image, or flat grey (default: real)")
    ap.add_argument("--models", type=Path, default=None, help="models folder (default: the shipped YCB meshes)")
    args = ap.parse_args(argv)
    if not args.data.is_dir():
        ap.error(f"--data {args.data}: no such folder")
    if args.out.resolve() == args.data.resolve():
        ap.error("--out must not be --data: the copy replaces its folder")
    record = rerender_folder(args.data, args.out, args.models or default_models_dir(), args.background)
    print(f"re-drew {record['instances']} instances in {record['frames']} frames into {args.out} "
          f"({record['wall_s']} s)")
    return 0

if __name__ == "__main__":
    sys.exit(main())
