"""Error of a refiner binned by the angle of the crop's viewing ray off the optical axis.

A crop does not show where in the image it was cut, so a model that reads the rotation from the crop's appearance
is wrong in the camera frame by about that angle unless it works in the viewing-ray frame; a model whose error
does not grow with the angle has not learned to use the appearance yet (see ``benchmarks/studies/paper_protocol/README.md``).

Usage (from the repository root)::

    python -m benchmarks.ray_angle runs/fusion.pt [--cache DIR] [--bin 4]

Evaluates the checkpoint (base network only) on its own test split, with the inputs of ``refiner-rt eval``
(``uniform:0:30``, seed 2024), and prints one Markdown row per bin: crops, mean output error, mean input error.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", type=Path)
    p.add_argument("--cache", type=Path, help="crop cache folder (default: DATA/.crops)")
    p.add_argument("--bin", type=float, default=4.0, help="bin width in degrees")
    p.add_argument("--threads", type=int, default=0)
    args = p.parse_args(argv)

    import models
    from models.evaluate.errors import evaluate_errors, torch_predictor
    from models.data.pipeline import checkpoint_test_set
    from models.train.loop import set_threads
    from refiner_rt import quaternion as rq

    set_threads(args.threads)
    net, info = models.load_checkpoint(args.checkpoint)
    test, spec = checkpoint_test_set(net, info, cache_root=args.cache)
    if test.q_ray is None:
        raise SystemExit(f"{spec.data}: the test crops have no intrinsics K, so no viewing ray")
    errors = evaluate_errors(torch_predictor(net.eval()), test, rotation_frame=info.get("rotation_frame", "camera"))
    ray_deg = rq.geodesic_angle(test.q_ray, np.broadcast_to([1.0, 0.0, 0.0, 0.0], test.q_ray.shape))
    print(f"{args.checkpoint} ({info.get('rotation_frame', 'camera')} frame): mean error {errors.err_out_deg.mean():.2f} deg "
          f"(input {errors.err_in_deg.mean():.2f}) on {len(test)} test crops")
    print("| ray angle (deg) | crops | mean error (deg) | mean input error (deg) |\n|---|---:|---:|---:|")
    for lo in np.arange(0.0, ray_deg.max() + args.bin, args.bin):
        m = (ray_deg >= lo) & (ray_deg < lo + args.bin)
        if m.any():
            print(f"| {lo:g}-{lo + args.bin:g} | {m.sum()} | {errors.err_out_deg[m].mean():.2f} | {errors.err_in_deg[m].mean():.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
