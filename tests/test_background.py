"""Instance masks from the dataset to the training batch: loaders, crop cache, CropSet, background replacement.

Masks are written in the real formats (BOP ``mask_visib/<im_id>_<gt_idx>.png``, YCB-Video
``<frame>-label.png``) and the cached mask crops are checked against the runtime's crop rule applied
to the mask image itself.
"""

from __future__ import annotations

import dataclasses
import json

from click.testing import CliRunner
import cv2
import numpy as np
import pytest
import torch

from models.data import CropCache, load_bop, load_ycbv
from models.data.augment import jitter_box_and_colour, paste_occluders, replace_background
from models.data.cache import samples_fingerprint
from models.data.cropset import CropSet
from models.train.config import TrainConfig
from models.train.loop import train_refiner
from refiner_rt.cli import main
from refiner_rt.preprocess import crop_to_square
from tests.bench_scripts import load_benchmark
from tests.cube_dataset import make_cube_dataset
from tests.data_fixtures import write_ycbv_frame

S = 32
TINY = json.dumps({"input_size": S, "conv_channels": [8, 8], "fuse_width": 64, "pose_widths": [16, 64],
                   "head_widths": [32, 16]})


@pytest.fixture(scope="module")
def cubes(tmp_path_factory):
    root = tmp_path_factory.mktemp("masks")
    make_cube_dataset(root / "masked", scenes=3, frames=8, masks=True)
    make_cube_dataset(root / "plain", scenes=3, frames=8)
    return root


def test_bop_loader_finds_mask_visib(cubes):
    samples = load_bop(cubes / "masked")
    assert samples and all(s.mask_path and s.mask_value == 0 for s in samples)
    for s in samples[:6]:
        info = json.loads((cubes / "masked" / s.scene_id / "scene_gt_info.json").read_text())
        mask = cv2.imread(s.mask_path, cv2.IMREAD_UNCHANGED)
        assert mask.shape == (120, 160)
        assert int((mask > 0).sum()) == info[str(s.frame_id)][s.instance]["px_count_visib"]
    assert all(s.mask_path == "" for s in load_bop(cubes / "plain"))


def test_ycbv_loader_finds_the_label_image(tmp_path):
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    objects = [(2, np.eye(3), [0, 0, 0.5], [10, 20, 110, 220]), (5, np.eye(3), [0.1, 0, 0.6], [300, 40, 400, 200])]
    write_ycbv_frame(tmp_path, "0001", "000001", objects, K)
    write_ycbv_frame(tmp_path, "0001", "000002", objects, K, seed=1)
    label = np.zeros((480, 640), np.uint8)
    label[20:220, 10:110], label[40:200, 300:400] = 2, 5
    cv2.imwrite(str(tmp_path / "data" / "0001" / "000001-label.png"), label)
    samples = load_ycbv(tmp_path)
    with_label = [s for s in samples if s.frame_id == 1]
    assert [(s.obj_id, s.mask_value) for s in with_label] == [("003_cracker_box", 2), ("006_mustard_bottle", 5)]
    assert all(s.mask_path.endswith("000001-label.png") for s in with_label)
    assert all(s.mask_path == "" and s.mask_value == 0 for s in samples if s.frame_id == 2)
    cache = CropCache.build_or_load(with_label, S, tmp_path / "cache", progress=False)
    # Each instance's mask holds only its own label: the box is fully covered, the other object never.
    assert cache.masks[0].mean() > 0.3 and cache.masks[1].mean() > 0.3
    assert cache.masks.sum() == sum(_reference_mask(s).sum() for s in with_label)


def _reference_mask(sample, size=S, context=1.2):
    """The runtime's crop rule on the mask drawn as a grey image, thresholded at one half."""
    raw = cv2.imread(sample.mask_path, cv2.IMREAD_UNCHANGED)
    on = raw != 0 if sample.mask_value == 0 else raw == sample.mask_value
    grey = np.repeat((on * 255).astype(np.uint8)[..., None], 3, axis=2)
    return (crop_to_square(grey, sample.box_xyxy, size, context)[..., 0] >= 128).astype(np.uint8)


def test_cached_masks_follow_the_crop_rule(cubes, tmp_path):
    samples = load_bop(cubes / "masked")
    cache = CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
    assert cache.masks.shape == (len(samples), S, S) and cache.masks.dtype == np.uint8
    assert cache.has_mask.all()
    np.testing.assert_array_equal(cache.masks, np.stack([_reference_mask(s) for s in samples]))
    # The mask marks the cube: its pixels are far from the grey background (90-120), most outside ones are not.
    crops = cache.crops.astype(int)
    spread = crops.max(axis=3) - crops.min(axis=3)
    assert spread[cache.masks == 1].mean() > 3 * spread[cache.masks == 0].mean()
    again = CropCache.build_or_load(samples, S, tmp_path / "c2", workers=2, progress=False)
    np.testing.assert_array_equal(again.masks, cache.masks)


def test_samples_without_masks_mix_and_keep_their_fingerprint(cubes, tmp_path):
    samples = load_bop(cubes / "masked")[:6]
    plain = [dataclasses.replace(s, mask_path="") for s in samples]
    assert samples_fingerprint(plain) == samples_fingerprint([dataclasses.replace(s, mask_value=7) for s in plain])
    assert samples_fingerprint(plain) != samples_fingerprint(samples)
    mixed = plain[:3] + samples[3:]
    cache = CropCache.build_or_load(mixed, S, tmp_path / "c", progress=False)
    assert cache.has_mask.tolist() == [False] * 3 + [True] * 3
    assert not cache.masks[:3].any() and cache.masks[3:].any()
    none = CropCache.build_or_load(plain, S, tmp_path / "c", progress=False)  # rebuilt in place without masks
    assert none.masks is None and not none.has_mask.any()
    assert not (tmp_path / "c" / "masks.npy").exists()


def test_mask_of_the_wrong_size_is_named(cubes, tmp_path):
    s = load_bop(cubes / "masked")[0]
    bad = tmp_path / "bad.png"
    cv2.imwrite(str(bad), np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match=r"bad\.png: a mask must be one channel of 160x120"):
        CropCache.build_or_load([dataclasses.replace(s, mask_path=str(bad))], S, tmp_path / "c", progress=False)


def test_cropset_checks_and_subsets_masks():
    crops = np.zeros((4, 8, 8, 3), np.uint8)
    q = np.tile([1.0, 0, 0, 0], (4, 1))
    masks = np.arange(4 * 64, dtype=np.int64).reshape(4, 8, 8).astype(np.uint8) % 2
    cs = CropSet(crops, q, np.array(["a", "b", "a", "b"]), masks=masks, has_mask=[True, False, True, True])
    sub = cs.for_object("a")
    np.testing.assert_array_equal(sub.masks, masks[[0, 2]])
    assert sub.has_mask.tolist() == [True, True]
    with pytest.raises(ValueError, match=r"masks must be \(4, 8, 8\) uint8"):
        CropSet(crops, q, np.array(["a"] * 4), masks=masks[:, :4])
    with pytest.raises(ValueError, match="has_mask was given without masks"):
        CropSet(crops, q, np.array(["a"] * 4), has_mask=[True] * 4)


def test_background_is_replaced_outside_the_mask_only():
    gen = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (6, 16, 16, 3), dtype=torch.uint8)
    masks = torch.zeros(6, 16, 16, dtype=torch.uint8)
    masks[:, 4:12, 5:11] = 1
    masks[2] = 0  # a crop without a mask
    out = replace_background(images, masks, 1.0, gen)
    inside = masks.bool()
    assert torch.equal(out[inside], images[inside])
    assert torch.equal(out[2], images[2])
    changed = (out != images).any(dim=3)
    for i in (0, 1, 3, 4, 5):
        assert changed[i][~inside[i]].float().mean() > 0.9
    assert torch.equal(replace_background(images, masks, 0.0, gen), images)


def _replace_background_whole_batch(images, masks, p, gen):
    """The background replacement written the plain way: every crop's new background made, then chosen per crop."""
    import torch.nn.functional as F

    n, s = images.shape[0], images.shape[1]
    pick = (torch.rand(n, generator=gen) < p) & (masks.flatten(1) > 0).any(dim=1)
    if n == 0 or not pick.any():
        return images
    other = torch.roll(images, shifts=int(torch.randint(1, max(n, 2), (1,), generator=gen)), dims=0).float()
    grid = torch.rand(n, 3, 4, 4, generator=gen) * 255
    field = F.interpolate(grid, size=(s, s), mode="bicubic", align_corners=False).permute(0, 2, 3, 1)
    field = field + torch.randn(n, s, s, 3, generator=gen) * 8
    use_field = (torch.rand(n, generator=gen) < 0.5) | (n == 1)
    background = torch.where(use_field[:, None, None, None], field, other)
    keep = ((masks > 0) | ~pick[:, None, None])[..., None]
    return torch.where(keep, images.float(), background).clamp(0, 255).round().to(torch.uint8)


@pytest.mark.parametrize("n,p", [(1, 1.0), (2, 0.5), (7, 0.5), (32, 0.5), (32, 1.0)])
def test_background_matches_the_whole_batch_formula_to_the_byte(n, p):
    """Making the new background for the picked crops only gives the same bytes and leaves the generator in the
    same state as making it for every crop (the training runs before this change stay reproducible)."""
    g_ref, g = torch.Generator().manual_seed(n), torch.Generator().manual_seed(n)
    data = torch.Generator().manual_seed(100 + n)
    for _ in range(10):
        images = torch.randint(0, 256, (n, 24, 24, 3), dtype=torch.uint8, generator=data)
        masks = (torch.rand(n, 24, 24, generator=data) > 0.6).to(torch.uint8)
        masks[::3] = 0  # some crops without a mask
        assert torch.equal(replace_background(images, masks, p, g), _replace_background_whole_batch(images, masks, p, g_ref))
    assert torch.equal(g.get_state(), g_ref.get_state())


def _augment_with_affine_grid(images, cfg, gen):
    """The colour and box jitter written with ``F.affine_grid`` and out-of-place arithmetic (the earlier code)."""
    import torch.nn.functional as F

    n = images.shape[0]
    x = images.permute(0, 3, 1, 2).float()
    scale = 1 + (torch.rand(n, generator=gen) * 2 - 1) * cfg.box_jitter
    shift = (torch.rand(n, 2, generator=gen) * 2 - 1) * cfg.box_jitter * 2
    theta = torch.zeros(n, 2, 3)
    theta[:, 0, 0], theta[:, 1, 1], theta[:, :, 2] = scale, scale, shift
    x = F.grid_sample(x, F.affine_grid(theta, list(x.shape), align_corners=False), mode="bilinear",
                      padding_mode="zeros", align_corners=False)
    brightness = (torch.rand(n, 1, 1, 1, generator=gen) * 2 - 1) * 25
    contrast = 1 + (torch.rand(n, 1, 1, 1, generator=gen) * 2 - 1) * 0.2
    gain = 1 + (torch.rand(n, 3, 1, 1, generator=gen) * 2 - 1) * 0.1
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = ((x - mean) * contrast + mean) * gain + brightness
    return x.clamp(0, 255).round().to(torch.uint8).permute(0, 2, 3, 1).contiguous()


@pytest.mark.parametrize("n,s,jitter", [(1, 16, 0.05), (7, 24, 0.05), (64, 64, 0.05), (16, 64, 0.2)])
def test_augment_matches_the_affine_grid_formula_to_the_byte(n, s, jitter):
    """The written-out sampling grid gives the same bytes and generator state as ``F.affine_grid``, so training runs
    made before the change stay reproducible to the digit."""
    cfg = TrainConfig(augment=True, box_jitter=jitter)
    g_ref, g = torch.Generator().manual_seed(n), torch.Generator().manual_seed(n)
    data = torch.Generator().manual_seed(200 + n)
    for _ in range(20):
        images = torch.randint(0, 256, (n, s, s, 3), dtype=torch.uint8, generator=data)
        assert torch.equal(jitter_box_and_colour(images, cfg.box_jitter, g), _augment_with_affine_grid(images, cfg, g_ref))
    assert torch.equal(g.get_state(), g_ref.get_state())


def test_background_comes_from_other_crops_and_from_colour_fields():
    """Over a few batches both kinds appear: another crop's pixels exactly, or something no crop holds."""
    images = torch.randint(0, 256, (4, 16, 16, 3), dtype=torch.uint8)
    masks = torch.zeros(4, 16, 16, dtype=torch.uint8)
    masks[:, 6:10, 6:10] = 1
    outside = ~masks[0].bool()
    kinds = set()
    gen = torch.Generator().manual_seed(1)
    for _ in range(12):
        out = replace_background(images, masks, 1.0, gen)
        for i in range(4):
            donor = [j for j in range(4) if j != i and torch.equal(out[i][outside], images[j][outside])]
            kinds.add("crop" if donor else "field")
    assert kinds == {"crop", "field"}


def test_occluders_are_other_crops_objects_pasted_whole():
    """Flat-coloured crops: every changed pixel of a crop takes the colour of one other crop, and no more pixels
    change than that crop's mask holds; without masks nothing is pasted."""
    n, s = 8, 20
    images = (torch.arange(n, dtype=torch.uint8) * 30 + 5)[:, None, None, None].expand(n, s, s, 3).contiguous()
    masks = torch.zeros(n, s, s, dtype=torch.uint8)
    masks[:, 5:15, 6:14] = 1
    gen = torch.Generator().manual_seed(3)
    out = paste_occluders(images, masks, 1.0, gen)
    pasted = 0
    for i in range(n):
        changed = (out[i] != images[i]).any(dim=2)
        if changed.any():
            colours = out[i][changed][:, 0].unique()
            assert len(colours) == 1 and colours.item() != images[i, 0, 0, 0].item()
            assert changed.sum() <= masks[0].sum()
            pasted += 1
    assert pasted >= n // 2
    assert torch.equal(paste_occluders(images, masks, 0.0, gen), images)
    assert torch.equal(paste_occluders(images, torch.zeros_like(masks), 1.0, gen), images)


def test_training_with_background_needs_masks():
    import models

    model = models.build_refiner("fusion", **json.loads(TINY))
    crops = np.zeros((4, S, S, 3), np.uint8)
    train = CropSet(crops, np.tile([1.0, 0, 0, 0], (4, 1)), np.array(["003_cracker_box"] * 4))
    with pytest.raises(ValueError, match="background=0.5 needs instance masks"):
        train_refiner(model, train, None, TrainConfig(epochs_mse=1, epochs_geodesic=0, background=0.5), progress=False)
    with pytest.raises(ValueError, match=r"background must be a probability in \[0, 1\]"):
        TrainConfig(background=1.5)
    with pytest.raises(ValueError, match=r"occlude must be a probability in \[0, 1\]"):
        TrainConfig(occlude=-0.1)
    with pytest.raises(ValueError, match="occlude=1.0 needs instance masks"):
        train_refiner(model, train, None, TrainConfig(epochs_mse=1, epochs_geodesic=0, occlude=1.0), progress=False)


def test_train_cli_uses_masks_and_names_data_without_them(cubes, tmp_path):
    import models

    common = ["--arch", "fusion", "--config", TINY, "--base-per-object", "12", "--per-object", "0",
              "--val-per-object", "4", "--test-per-object", "4", "--epochs-mse", "1", "--epochs-geodesic", "1",
              "--batch-size", "8", "--threads", "1", "--quiet", "--cache", str(tmp_path / "cache"),
              "--background", "0.5"]
    out = tmp_path / "masked.pt"
    res = CliRunner().invoke(main, ["train", "--data", str(cubes / "masked"), "--out", str(out), *common])
    assert res.exit_code == 0, res.output
    _, info = models.load_checkpoint(out)
    assert info["train_config"]["background"] == 0.5
    res = CliRunner().invoke(main, ["train", "--data", str(cubes / "plain"), "--out", str(tmp_path / "p.pt"), *common])
    assert res.exit_code != 0 and "--background 0.5 needs instance masks" in res.output
    occlude = [*common[:-2], "--occlude", "0.25"]
    res = CliRunner().invoke(main, ["train", "--data", str(cubes / "plain"), "--out", str(tmp_path / "p.pt"), *occlude])
    assert res.exit_code != 0 and "--occlude 0.25 needs instance masks" in res.output


def test_data_scaling_adds_background_and_occluder_runs(cubes, tmp_path, capsys):
    study = load_benchmark("data_scaling")
    out = tmp_path / "s.json"
    common = ["--object", "003_cracker_box", "--modes", "frames", "--sizes", "8", "--samples", "16",
              "--epoch-samples", "8", "--val", "4", "--test", "4", "--config", TINY, "--cache", str(tmp_path / "cache"),
              "--threads", "1", "--json", str(out), "--quiet"]
    argv = ["--data", str(cubes / "masked"), *common, "--background", "1", "--occlude", "0.5"]
    assert study.main(argv) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["augment"], r["background"], r["occlude"]) for r in rows] == [(False, 0.0, 0.0), (False, 1.0, 0.0),
                                                                              (False, 0.0, 0.5)]
    table = study.markdown(json.loads(out.read_text()))
    assert "| background 1 |" in table and "| occluders 0.5 |" in table
    capsys.readouterr()
    with pytest.raises(SystemExit):
        study.main(["--data", str(cubes / "masked"), *common, "--occlude", "1.5"])
    assert "--occlude: expected probabilities in (0, 1]" in capsys.readouterr().err
    assert study.main(["--data", str(cubes / "masked"), *common, "--occlude", "0.5", "--skip-plain"]) == 0
    assert [(r["augment"], r["occlude"]) for r in json.loads(out.read_text())["rows"]] == [(False, 0.5)]
    with pytest.raises(SystemExit):
        study.main(["--data", str(cubes / "masked"), *common, "--skip-plain"])
    assert "--skip-plain leaves no run" in capsys.readouterr().err
    argv = ["--data", str(cubes / "masked"), *common, "--augment", "--background", "1", "--skip-plain", "--skip-jitter"]
    assert study.main(argv) == 0
    assert [(r["augment"], r["background"]) for r in json.loads(out.read_text())["rows"]] == [(True, 1.0)]
    with pytest.raises(SystemExit):
        study.main(["--data", str(cubes / "masked"), *common, "--augment", "--skip-jitter"])
    assert "--skip-jitter needs --augment with --background or --occlude" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="--background 1 needs instance masks"):
        study.main(["--data", str(cubes / "plain"), *common, "--background", "1"])
    with pytest.raises(SystemExit, match="--occlude 1 needs instance masks"):
        study.main(["--data", str(cubes / "plain"), *common, "--occlude", "1"])


def test_train_cli_and_data_scaling_take_bf16_ema_weight_decay_and_inplane(cubes, tmp_path):
    import models

    out = tmp_path / "b.pt"
    args = ["train", "--data", str(cubes / "masked"), "--out", str(out), "--objects", "003_cracker_box",
            "--base-per-object", "8", "--per-object", "0", "--val-per-object", "4", "--test-per-object", "4",
            "--epochs-mse", "1", "--epochs-geodesic", "0", "--arch", "fusion", "--config", TINY, "--cache",
            str(tmp_path / "cache"), "--bf16", "--ema", "0.99", "--weight-decay", "0.05", "--quiet", "--threads", "1"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    model, meta = models.load_checkpoint(out)
    assert meta["train_config"]["bf16"] is True and meta["train_config"]["ema"] == 0.99
    assert meta["train_config"]["weight_decay"] == 0.05 and meta["train_config"]["decoupled_weight_decay"] is True
    assert all(v.dtype == torch.float32 for v in model.state_dict().values() if v.is_floating_point())

    res = CliRunner().invoke(main, args + ["--inplane", "30"])  # the camera frame: refused before any work
    assert res.exit_code != 0 and "--inplane 30 needs --rotation-frame ray" in res.output
    study = load_benchmark("data_scaling")
    with pytest.raises(SystemExit, match="--inplane 30 needs --rotation-frame ray"):
        study.main(["--data", str(cubes / "masked"), "--rotation-frame", "camera", "--inplane", "30"])
    with pytest.raises(SystemExit, match="ema must be a decay in"):
        study.main(["--data", str(cubes / "masked"), "--ema", "1.5"])
    js = tmp_path / "s.json"
    assert study.main(["--data", str(cubes / "masked"), "--object", "003_cracker_box", "--modes", "frames", "--sizes",
                       "8", "--samples", "16", "--epoch-samples", "8", "--val", "4", "--test", "4", "--config", TINY,
                       "--cache", str(tmp_path / "cache"), "--threads", "1", "--skip-plain", "--background", "0.5",
                       "--inplane", "20",
                       "--bf16", "--ema", "0.99", "--weight-decay", "0.05", "--json", str(js), "--quiet"]) == 0
    doc = json.loads(js.read_text())
    assert doc["ema"] == 0.99 and doc["adamw_weight_decay"] == 0.05 and doc["inplane_deg"] == 20
    assert doc["bf16"] is True and [r["background"] for r in doc["rows"]] == [0.5]


def test_train_speed_benchmark_measures_both_precisions(tmp_path):
    bench = load_benchmark("train_speed")
    data = bench.synthetic_crops(6, 16)
    assert data.masks.shape == (6, 16, 16) and set(np.unique(data.masks)) <= {0, 1} and data.masks.any()
    js = tmp_path / "speed.json"
    assert bench.main(["--config", json.dumps({"input_size": 16, "conv_channels": [4], "fuse_width": 16,
                                               "pose_widths": [16], "head_widths": [8]}),
                       "--batch-size", "4", "--steps", "2", "--epochs", "3", "--json", str(js)]) == 0
    doc = json.loads(js.read_text())
    assert [len(doc["samples_per_s"][k]) for k in ("float32", "bf16")] == [2, 2]
    assert all(v > 0 for v in doc["median_samples_per_s"].values())
    assert doc["bf16_speedup"] == pytest.approx(doc["median_samples_per_s"]["bf16"] / doc["median_samples_per_s"]["float32"])
    with pytest.raises(SystemExit):
        bench.main(["--config", "[1]"])
