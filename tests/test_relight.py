"""Another scene's light and camera on a training crop (``TrainConfig.relight``, ``--relight``)."""

from __future__ import annotations

import json

from click.testing import CliRunner
import numpy as np
import pytest
import torch

import models
from models.data.augment import relight
from models.train.config import TrainConfig
from refiner_rt.cli import main
from tests.bench_scripts import load_benchmark
from tests.cube_dataset import make_cube_dataset

S = 32
TINY = json.dumps({"input_size": S, "conv_channels": [8, 8], "fuse_width": 64, "pose_widths": [16, 64],
                   "head_widths": [32, 16]})


def _batch(n: int = 64, s: int = 48, seed: int = 0) -> torch.Tensor:
    """Textured crops: a random 6x6 colour checker per crop, nearest-upsampled (sharp edges to blur)."""
    rng = np.random.default_rng(seed)
    cells = rng.integers(40, 216, (n, 6, 6, 3), dtype=np.uint8)
    return torch.from_numpy(np.ascontiguousarray(cells.repeat(s // 6, axis=1).repeat(s // 6, axis=2)))


def test_relight_changes_the_picked_crops_only_and_is_seeded():
    x = _batch()
    same = relight(x, 0.0, torch.Generator().manual_seed(0))
    assert torch.equal(same, x)
    a = relight(x, 0.5, torch.Generator().manual_seed(1))
    b = relight(x, 0.5, torch.Generator().manual_seed(1))
    assert torch.equal(a, b) and a.dtype == torch.uint8 and a.shape == x.shape
    unchanged = [bool(torch.equal(a[i], x[i])) for i in range(len(x))]
    assert 16 <= sum(unchanged) <= 48  # about half of 64 picked
    changed = [i for i, u in enumerate(unchanged) if not u]
    diff = (a[changed].float() - x[changed].float()).abs().mean(dim=(1, 2, 3))
    assert bool((diff > 1.0).all())


def test_relight_is_a_smooth_gain_not_a_new_image():
    """The crop's content stays: relit crops correlate with their originals, and the large-scale ratio
    relit/original varies smoothly (a shading field), while a blur removes some edge energy."""
    x = _batch(n=32)
    y = relight(x, 1.0, torch.Generator().manual_seed(3)).float()
    xf = x.float()
    for i in range(len(x)):
        gx, gy = xf[i].mean(dim=2).flatten(), y[i].mean(dim=2).flatten()
        corr = torch.corrcoef(torch.stack([gx, gy]))[0, 1]
        assert corr > 0.6, f"crop {i}: relit crop does not follow the original (r={corr:.2f})"
    edges = lambda im: (im[:, :, 1:] - im[:, :, :-1]).abs().mean()  # noqa: E731
    # Gains and gamma change the contrast too; normalise by each image's spread before comparing sharpness.
    sharp_x = edges(xf) / xf.std()
    smooth_y = edges(y) / y.std()
    assert smooth_y < sharp_x * 1.2
    flat = torch.full((8, 48, 48, 3), 128, dtype=torch.uint8)
    lit = relight(flat, 1.0, torch.Generator().manual_seed(5)).float().mean(dim=3)
    # A flat grey crop gets a shading field: a spread across the crop, but no jumps between neighbours
    # beyond the sensor noise (std <= 4 grey levels).
    assert bool(((lit.amax(dim=(1, 2)) - lit.amin(dim=(1, 2))) > 10).all())
    assert float((lit[:, :, 1:] - lit[:, :, :-1]).abs().mean()) < 8


def test_relight_needs_a_probability():
    with pytest.raises(ValueError, match="relight must be a probability"):
        TrainConfig(relight=1.5)


@pytest.fixture(scope="module")
def cubes(tmp_path_factory):
    root = tmp_path_factory.mktemp("relight")
    make_cube_dataset(root, scenes=3, frames=8)
    return root


def test_train_cli_and_data_scaling_take_relight(cubes, tmp_path, capsys):
    out = tmp_path / "r.pt"
    args = ["train", "--data", str(cubes), "--out", str(out), "--objects", "003_cracker_box", "--base-per-object",
            "8", "--per-object", "0", "--val-per-object", "4", "--test-per-object", "4", "--epochs-mse", "1",
            "--epochs-geodesic", "0", "--arch", "fusion", "--config", TINY, "--cache", str(tmp_path / "cache"),
            "--relight", "0.5", "--quiet", "--threads", "1"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert models.load_checkpoint(out)[1]["train_config"]["relight"] == 0.5
    bad = CliRunner().invoke(main, args[:-5] + ["--relight", "2", "--quiet"])
    assert bad.exit_code != 0 and "--relight" in bad.output

    study = load_benchmark("data_scaling")
    js = tmp_path / "s.json"
    common = ["--data", str(cubes), "--object", "003_cracker_box", "--modes", "frames", "--sizes", "8", "--samples",
              "16", "--epoch-samples", "8", "--val", "4", "--test", "4", "--config", TINY, "--cache",
              str(tmp_path / "cache"), "--threads", "1", "--json", str(js), "--quiet"]
    assert study.main([*common, "--augment", "--relight", "0.5"]) == 0
    rows = json.loads(js.read_text())["rows"]
    assert [(r["augment"], r.get("relight", 0.0)) for r in rows] == [(False, 0.0), (True, 0.5)]
    assert "| jitter + relight 0.5 |" in study.markdown(json.loads(js.read_text()))
    capsys.readouterr()
    with pytest.raises(SystemExit):
        study.main([*common, "--relight", "0.5"])
    assert "--relight applies to the augmented runs" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        study.main([*common, "--augment", "--relight", "1.5"])
    assert "--relight: expected a probability in [0, 1]" in capsys.readouterr().err
