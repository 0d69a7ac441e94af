"""Run by tests/test_train.py under torchrun: a few DDP training steps, then each rank saves its weights."""

import sys

import numpy as np
import torch

import models
from models.data.cropset import CropSet
from models.train.config import TrainConfig
from models.train.loop import train_refiner
from models.train.run import init_distributed
from refiner_rt import quaternion as rq


def main(out_dir: str) -> None:
    rank, world = init_distributed("cpu")
    torch.set_num_threads(1)
    torch.manual_seed(0)  # same initial weights on every rank (DDP also broadcasts rank 0's)
    rng = np.random.default_rng(0)
    n = 64
    crops = rng.integers(0, 256, (n, 16, 16, 3), dtype=np.uint8)
    data = CropSet(crops, rq.sample_rotation_noise(n, "uniform", 0, 90, rng), np.array(["003_cracker_box"] * n))
    model = models.build_refiner("fusion", input_size=16, conv_channels=[4], fuse_width=16, pose_widths=[16], head_widths=[8])
    cfg = TrainConfig(epochs_mse=1, epochs_geodesic=1, batch_size=16, lr=1e-3)
    train_refiner(model, data, None, cfg, progress=False)
    torch.save(model.state_dict(), f"{out_dir}/rank{rank}.pt")
    assert world == 2, world
    torch.distributed.barrier()  # as train_cli does: no rank tears gloo down while the other still uses it
    torch.distributed.destroy_process_group()


if __name__ == "__main__":
    main(sys.argv[1])
