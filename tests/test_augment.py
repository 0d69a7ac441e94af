"""Camera-like photometric augmentation (models.data.augment): each operation against an independent computation of what
it should do, determinism, untouched crops, and the recipe's validation of the probabilities."""

import cv2
import numpy as np
import pytest
import torch

from models.data.augment import PHOTOMETRIC_OPS, _apply, _motion_kernel, photometric, validate_probabilities
from models.train.recipe import RecipeError, TrainRecipe


def _batch(n=6, s=32, seed=0):
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (n, 4, 4, 3), dtype=np.uint8)
    return torch.from_numpy(np.stack([cv2.resize(c, (s, s), interpolation=cv2.INTER_CUBIC) for c in small]))


@pytest.mark.parametrize("op", list(PHOTOMETRIC_OPS))
def test_each_operation_changes_every_picked_crop_and_keeps_shape_and_dtype(op):
    x = _batch()
    y = photometric(x, {op: 1.0}, torch.Generator().manual_seed(1))
    assert y.shape == x.shape and y.dtype == torch.uint8
    changed = (y.int() - x.int()).abs().reshape(len(x), -1).amax(dim=1)
    assert bool((changed > 0).all()), op


def test_probability_zero_and_unpicked_crops_are_untouched():
    x = _batch(n=64)
    assert photometric(x, {op: 0.0 for op in PHOTOMETRIC_OPS}, torch.Generator()) is x
    y = photometric(x, {"white_balance": 0.5}, torch.Generator().manual_seed(3))
    same = (y == x).reshape(len(x), -1).all(dim=1)
    assert 10 < int(same.sum()) < 54  # about half picked


def test_the_same_seed_gives_the_same_crops():
    probs = {op: 0.5 for op in PHOTOMETRIC_OPS}
    a = photometric(_batch(), probs, torch.Generator().manual_seed(7))
    b = photometric(_batch(), probs, torch.Generator().manual_seed(7))
    c = photometric(_batch(), probs, torch.Generator().manual_seed(8))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_gains_and_saturation_match_their_formulas():
    crop = _batch(n=1)[0].numpy().astype(np.float32)
    rng, ref = np.random.default_rng(5), np.random.default_rng(5)
    np.testing.assert_allclose(_apply("white_balance", crop, rng), crop * ref.uniform(0.75, 1.25, 3), rtol=1e-6)
    np.testing.assert_allclose(_apply("brightness", crop, rng), crop * ref.uniform(0.5, 1.6), rtol=1e-6)
    out = _apply("colour", crop, rng)
    s = ref.uniform(0.3, 2.0)
    grey = 0.114 * crop[..., 0] + 0.587 * crop[..., 1] + 0.299 * crop[..., 2]
    np.testing.assert_allclose(out, grey[..., None] + (crop - grey[..., None]) * s, rtol=1e-5, atol=1e-3)
    contrast = _apply("contrast", crop, rng)
    assert contrast.mean() == pytest.approx(crop.mean(), rel=1e-4)  # about the crop's mean


def test_motion_kernel_is_a_normalised_line_through_the_centre():
    for seed in range(5):
        k = _motion_kernel(np.random.default_rng(seed))
        assert k.sum() == pytest.approx(1.0, abs=1e-6) and k[4, 4] == k.max()
        np.testing.assert_allclose(k, k[::-1, ::-1], atol=1e-7)  # symmetric about its centre


def test_probabilities_are_validated_with_the_operation_named():
    with pytest.raises(ValueError, match="unknown photometric augmentation 'fog'"):
        validate_probabilities({"fog": 0.5})
    with pytest.raises(ValueError, match="aug_jpeg must be a probability"):
        validate_probabilities({"jpeg": 1.5})
    with pytest.raises(RecipeError, match="aug_blur"):
        TrainRecipe(data="x", aug_blur=2.0).validate()
    r = TrainRecipe(data="x", aug_blur=0.3, aug_jpeg=0.2).validate()
    assert r.photometric == {"blur": 0.3, "jpeg": 0.2}
    assert r.stage_config("base", 100).photometric == {"blur": 0.3, "jpeg": 0.2}


def test_gamma_and_downscale_match_their_formulas():
    from models.data.augment import apply_op

    crop = _batch(n=1, s=64)[0].numpy().astype(np.float32)
    np.testing.assert_allclose(apply_op("gamma", crop, 1.25), 255.0 * (crop / 255.0) ** 1.25, rtol=1e-5, atol=1e-3)
    small = cv2.resize(crop, (32, 32), interpolation=cv2.INTER_AREA)
    np.testing.assert_allclose(apply_op("downscale", crop, 0.5),
                               cv2.resize(small, (64, 64), interpolation=cv2.INTER_LINEAR), atol=1e-4)
    assert apply_op("downscale", crop, 1.0).shape == crop.shape


def test_fixed_strengths_are_the_drawn_ones():
    """apply_op at the strength draw_strength gives is what the training augmentation applies (one definition)."""
    from models.data.augment import apply_op, draw_strength

    crop = _batch(n=1, s=32)[0].numpy().astype(np.float32)
    for op in PHOTOMETRIC_OPS:
        rng, ref = np.random.default_rng(11), np.random.default_rng(11)
        expected = apply_op(op, crop, draw_strength(op, ref), ref)
        np.testing.assert_array_equal(_apply(op, crop, rng), expected)


def test_unknown_operations_are_refused_by_name():
    from models.data.augment import apply_op, draw_strength

    with pytest.raises(ValueError, match="unknown photometric augmentation 'vignette'"):
        apply_op("vignette", np.zeros((4, 4, 3), np.float32), 1.0)
    with pytest.raises(ValueError, match="expected one of"):
        draw_strength("vignette", np.random.default_rng(0))


def test_a_long_motion_blur_gets_a_kernel_that_holds_it():
    from models.data.augment import apply_op, motion_kernel

    k = motion_kernel(13.0, 0.0, size=15)
    assert k.sum() == pytest.approx(1.0, abs=1e-6) and (k[7] > 0).sum() >= 13  # a horizontal line of 13 px
    line = np.zeros((31, 31, 3), np.float32)
    line[15, 15] = 255.0
    spread = apply_op("motion_blur", line, (13.0, 0.0))
    assert (spread[15, :, 0] > 0).sum() >= 13
