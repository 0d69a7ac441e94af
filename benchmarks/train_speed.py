"""Training speed: samples/s of ``train_refiner`` in float32 and in mixed precision (``--bf16``), on the same
synthetic crops, in one process.

The held-out-scenes models are limited by their training steps, so a step's cost is what bounds them. This runs the
real training loop (``models.train.loop.train_refiner``: crop pipeline, forward, loss, backward, Adam) on random crops with
random instance masks, with the augmentations the scene runs use (``--augment --background 0.5`` by default), and
reads each epoch's ``samples_per_s`` from its history. The variants alternate epoch by epoch, so load on the machine
falls on each alike; the first epoch of each is warm-up and is dropped. Reported: the median samples/s of each
variant and their ratio.

Usage (from the repository root)::

    python -m benchmarks.train_speed                       # five-block fusion, batch 64, one thread
    python -m benchmarks.train_speed --config '{}' --threads 2 --json benchmarks/results/train_speed/train_speed.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from models.evaluate.record import provenance, write_json
from models.train.recipe import parse_json_object as _parse_config

FIVE_BLOCKS = {"conv_channels": [16, 32, 64, 128, 128]}


def synthetic_crops(n: int, size: int, seed: int = 0):
    """``n`` random ``size`` px crops with random rotations, ray-frame rotations and a random blob mask each."""
    from models.data.cropset import CropSet
    from refiner_rt import quaternion as rq

    rng = np.random.default_rng(seed)
    crops = rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8)
    yy, xx = np.mgrid[:size, :size] / size
    centre = rng.uniform(0.3, 0.7, (n, 2, 1, 1))
    radius = rng.uniform(0.15, 0.35, (n, 1, 1))
    masks = (((yy - centre[:, 0]) ** 2 + (xx - centre[:, 1]) ** 2) < radius**2).astype(np.uint8)
    q = rq.sample_rotation_noise(n, "uniform", 0, 180, rng)
    q_ray = rq.sample_rotation_noise(n, "uniform", 0, 20, rng)
    return CropSet(crops, q, np.array(["003_cracker_box"] * n), q_ray=q_ray, masks=masks)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--arch", default="fusion", help="network (default fusion)")
    ap.add_argument("--config", type=_parse_config, default=FIVE_BLOCKS,
                    help=f"network config overrides as JSON (default the five-block stage, {json.dumps(FIVE_BLOCKS)})")
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--steps", type=int, default=40, help="optimisation steps per epoch (default 40)")
    ap.add_argument("--epochs", type=int, default=6, help="epochs per variant, the first one dropped (default 6)")
    ap.add_argument("--background", type=float, default=0.5, help="new-background probability (default 0.5)")
    ap.add_argument("--no-augment", dest="augment", action="store_false", help="without colour and box jitter")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    ap.add_argument("--json", type=Path, help="write the result here")
    args = ap.parse_args(argv)
    if args.epochs < 2 or args.steps < 1 or args.batch_size < 1:
        ap.error(f"--epochs must be >= 2 and --steps, --batch-size >= 1; got {args.epochs}, {args.steps}, {args.batch_size}")
    if not 0.0 <= args.background <= 1.0:
        ap.error(f"--background: expected a probability in [0, 1]; got {args.background}")

    import torch

    import models
    from models.train.config import TrainConfig
    from models.train.loop import set_threads, train_refiner

    set_threads(args.threads)
    torch.manual_seed(0)
    probe = models.build_refiner(args.arch, **args.config)
    data = synthetic_crops(args.batch_size * args.steps, probe.input_size)
    variants = {"float32": False, "bf16": True}
    nets = {}
    for name in variants:
        torch.manual_seed(0)
        nets[name] = models.build_refiner(args.arch, **args.config)
    rates = {name: [] for name in variants}
    t0 = time.perf_counter()
    for epoch in range(args.epochs):
        for name, bf16 in variants.items():
            cfg = TrainConfig(epochs_mse=0, epochs_geodesic=1, batch_size=args.batch_size, lr=1e-4, lr_schedule="cosine",
                              rotation_frame="ray", augment=args.augment, background=args.background, seed=epoch,
                              bf16=bf16)
            res = train_refiner(nets[name], data, None, cfg, progress=False, desc=name)
            nets[name] = res.model
            if epoch:  # the first epoch of each variant is warm-up
                rates[name].append(res.history[0]["samples_per_s"])
    med = {name: float(np.median(r)) for name, r in rates.items()}
    doc = {
        "study": "training samples/s, float32 against bf16 mixed precision",
        "arch": args.arch, "config": args.config, "parameters": sum(p.numel() for p in probe.parameters()),
        "batch_size": args.batch_size, "steps_per_epoch": args.steps, "epochs_measured": args.epochs - 1,
        "augment": args.augment, "background": args.background,
        "median_samples_per_s": med, "bf16_speedup": med["bf16"] / med["float32"],
        "samples_per_s": rates,
        **provenance("benchmarks.train_speed", argv, args.threads),
        "cpu_bf16": "avx512_bf16" in Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else None,
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    print(f"{args.arch} {json.dumps(args.config)}, batch {args.batch_size}, {args.threads} thread(s): "
          f"float32 {med['float32']:.0f} samples/s, bf16 {med['bf16']:.0f} ({doc['bf16_speedup']:.2f}x)")
    if args.json:
        write_json(args.json, doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
