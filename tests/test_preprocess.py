"""The crop rule against its slow reference (refiner_rt.preprocess.crop_to_square_reference), a direct implementation
of its definition."""

import numpy as np
import pytest

from refiner_rt.preprocess import (
    crop_batch,
    crop_matrix,
    crop_to_square,
    crop_to_square_reference,
    crop_window,
    resize_crop,
    validate_boxes,
    validate_image,
)

RNG = np.random.default_rng(0)


def test_pixel_aligned_box_is_an_exact_copy():
    img = RNG.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    crop = crop_to_square(img, (10, 5, 26, 21), 16, context=1.0)
    np.testing.assert_array_equal(crop, img[5:21, 10:26])


def test_matches_naive_rule_with_context_and_borders():
    img = RNG.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    for box, size, ctx in [((3.2, 4.7, 20.1, 12.3), 12, 1.2), ((-5, -3, 12, 25), 9, 1.5), ((30, 20, 45, 35), 10, 1.2)]:
        fast = crop_to_square(img, box, size, ctx).astype(float)
        ref = crop_to_square_reference(img, box, size, ctx)
        # OpenCV's bilinear weights are fixed-point (1/32 steps): allow a couple of grey levels.
        assert np.abs(fast - ref).max() <= 3.0, (box, np.abs(fast - ref).max())


def test_outside_is_zero_and_window_is_square_on_box_centre():
    img = np.full((20, 20, 3), 200, dtype=np.uint8)
    crop = crop_to_square(img, (0, 0, 10, 20), 20, context=2.0)  # window 40x40 centred at (5, 10)
    assert crop[:, :2].max() == 0 and crop[:, -2:].max() == 0  # left/right beyond the image
    assert crop[10, 10].tolist() == [200, 200, 200]
    assert crop_window((0, 0, 10, 20), 2.0) == (5.0, 10.0, 40.0)


def test_batch_equals_single_crops_and_uses_buffer():
    img = RNG.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    boxes = np.array([[1, 2, 30, 40], [40.5, 10.5, 70.5, 50.5]])
    buf = np.zeros((4, 16, 16, 3), dtype=np.uint8)
    batch = crop_batch(img, boxes, 16, 1.2, out=buf)
    assert batch.base is buf or np.shares_memory(batch, buf)
    for i, b in enumerate(boxes):
        np.testing.assert_array_equal(batch[i], crop_to_square(img, b, 16, 1.2))


def test_resize_crop_identity_and_padding():
    crop = RNG.integers(0, 256, (16, 16, 3), dtype=np.uint8)
    np.testing.assert_array_equal(resize_crop(crop, 16), crop)
    wide = RNG.integers(1, 256, (8, 16, 3), dtype=np.uint8)
    out = resize_crop(wide, 16)
    assert out[:4].max() == 0 and out[-4:].max() == 0
    np.testing.assert_array_equal(out[4:12], wide)


def test_crop_matrix_maps_output_centre_to_box_centre():
    m = crop_matrix((10, 20, 30, 60), 64, 1.2)
    # output continuous centre (32, 32) = index (31.5, 31.5) -> source continuous (20, 40) = index (19.5, 39.5)
    np.testing.assert_allclose(m @ [31.5, 31.5, 1.0], [19.5, 39.5])


def test_validation_errors_name_what_was_wrong():
    img = np.zeros((10, 10, 3), np.uint8)
    with pytest.raises(ValueError, match="dtype uint8.*float32"):
        validate_image(img.astype(np.float32))
    with pytest.raises(ValueError, match=r"\(H, W, 3\).*\(10, 10, 4\)"):
        validate_image(np.zeros((10, 10, 4), np.uint8))
    with pytest.raises(TypeError, match="numpy array"):
        validate_image([[0]])
    with pytest.raises(ValueError, match=r"shape \(N, 4\)"):
        validate_boxes(np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"boxes\[1\] is empty"):
        validate_boxes([[0, 0, 5, 5], [3, 3, 3, 8]])
    with pytest.raises(ValueError, match=r"boxes\[0\] lies entirely outside the 10x10 image"):
        validate_boxes([[12, 0, 20, 5]], img.shape)
    with pytest.raises(ValueError, match="finite"):
        validate_boxes([[0, 0, np.inf, 5]])
    assert validate_boxes([1, 2, 3, 4]).shape == (1, 4)
