"""The crop rule's anti-aliasing filter (metadata ``crop_filter``): against a whole-image Gaussian from SciPy and the
rule's naive bilinear sampling, what it removes (aliasing of fine texture), where it does nothing (a window not
shrunk), and that every path that cuts crops honours the model's choice: the runtime, the undistorted crop, the crop
cache and the exporter's metadata tool."""

import numpy as np
import onnx
import pytest
from scipy.ndimage import gaussian_filter

from refiner_rt import RefinerSession
from refiner_rt.metadata import parse_metadata
from refiner_rt.preprocess import crop_matrix, crop_to_square, crop_to_square_reference, prefiltered_region, resize_crop
from tests.onnx_fixtures import contract, random_weight_model


RNG = np.random.default_rng(3)


def test_an_integer_shrink_averages_each_crop_pixels_block():
    """A window shrunk exactly 4 times on the pixel grid: each crop pixel is the mean of the 4 x 4 image pixels it
    covers (numpy's block mean), where bilinear sampling alone reads 4 of them."""
    img = RNG.integers(0, 256, (200, 240, 3), dtype=np.uint8)
    box, size = (40.0, 48.0, 104.0, 112.0), 16  # 64 px into 16, the window on whole pixels
    blocks = img[48:112, 40:104].astype(float).reshape(16, 4, 16, 4, 3).mean(axis=(1, 3))
    fast = crop_to_square(img, box, size, 1.0, crop_filter="antialias").astype(float)
    assert np.abs(fast - blocks).max() <= 1.0  # uint8 rounding
    assert np.abs(crop_to_square(img, box, size, 1.0).astype(float) - blocks).mean() > 10


def test_a_shrink_between_powers_of_two_is_near_an_ideal_low_pass():
    """5.4x: blocks of 4, then bilinear at 1.35x; the crop is near a Gaussian low-pass of the whole shrink (SciPy)
    followed by the plain rule, and far from the plain rule on the sharp image."""
    img = RNG.integers(0, 256, (200, 240, 3), dtype=np.uint8)
    box, size = (40.0, 48.0, 126.4, 134.4), 16
    assert crop_matrix(box, size, 1.0)[0, 0] == pytest.approx(5.4)
    a = crop_to_square(img, box, size, 1.0, crop_filter="antialias").astype(float)
    sigma = 5.4 / np.sqrt(12)  # the box filter of the footprint's width
    ideal = crop_to_square_reference(np.stack([gaussian_filter(img[..., c].astype(float), sigma, mode="nearest")
                                 for c in range(3)], -1), box, size, 1.0)
    plain = crop_to_square(img, box, size, 1.0).astype(float)
    assert np.abs(a - ideal).mean() < 0.5 * np.abs(plain - ideal).mean()


def test_a_window_not_shrunk_is_the_plain_rule():
    img = RNG.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    for box, size in (((10, 5, 26, 21), 16), ((3.5, 2.25, 9.5, 8.25), 20)):
        np.testing.assert_array_equal(crop_to_square(img, box, size, 1.0, crop_filter="antialias"),
                                      crop_to_square(img, box, size, 1.0))
    assert prefiltered_region(img, 3.0, 3.0, 20.0, 20.0, 1.9)[3] == 1  # under 2x: no blocks


def test_fine_texture_does_not_alias_and_a_sub_pixel_shift_changes_little():
    yy, xx = np.mgrid[0:480, 0:640]
    stripes = np.repeat((((xx + yy) // 1) % 2 * 255).astype(np.uint8)[..., None], 3, axis=-1)  # 1-px checkers
    box = (200.0, 150.0, 392.0, 342.0)  # 192 px: shrunk 3.6x into 64
    shifted = (200.4, 150.3, 392.4, 342.3)
    plain = [crop_to_square(stripes, b, 64).astype(float) for b in (box, shifted)]
    smooth = [crop_to_square(stripes, b, 64, crop_filter="antialias").astype(float) for b in (box, shifted)]
    assert smooth[0].std() < 0.25 * plain[0].std()  # the checkers average to grey instead of beating
    assert np.abs(smooth[0] - smooth[1]).mean() < 0.25 * np.abs(plain[0] - plain[1]).mean()


def test_unknown_filters_are_refused_by_name():
    img = np.zeros((10, 10, 3), np.uint8)
    with pytest.raises(ValueError, match="crop_filter must be one of"):
        crop_to_square(img, (0, 0, 5, 5), 4, crop_filter="lanczos")
    props = contract()
    props["crop_filter"] = "lanczos"
    with pytest.raises(ValueError, match="metadata key 'crop_filter'"):
        parse_metadata(props)


def test_metadata_round_trip_and_default():
    assert parse_metadata(contract()).crop_filter == "none"
    props = contract(crop_filter="antialias")
    assert props["crop_filter"] == "antialias" and parse_metadata(props).crop_filter == "antialias"
    assert parse_metadata(props).as_dict()["crop_filter"] == "antialias"
    assert "crop_filter" not in parse_metadata(props).extra


@pytest.mark.parametrize("crop_filter", ["none", "antialias"])
def test_the_session_cuts_crops_as_its_model_says(crop_filter):
    size = 16
    sess = RefinerSession(random_weight_model(size=size, props=contract(input_size=size, crop_filter=crop_filter)))
    img = RNG.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    box = np.array([[60.0, 40.0, 180.0, 170.0]])
    q = np.array([[0.9, 0.1, -0.3, 0.3]])
    q /= np.linalg.norm(q)
    full = sess.refine(img, box, q).q_refined
    for f in ("none", "antialias"):
        crop = crop_to_square(img, box[0], size, 1.2, crop_filter=f)
        via_crop = sess.refine_crops(crop[None], q).q_refined
        if f == crop_filter:
            np.testing.assert_allclose(full, via_crop, atol=1e-6)
        else:
            assert np.abs(full - via_crop).max() > 1e-4


def test_refine_crops_filters_a_crop_larger_than_the_input():
    big = RNG.integers(0, 256, (64, 64, 3), dtype=np.uint8)
    a = resize_crop(big, 16, crop_filter="antialias")
    np.testing.assert_array_equal(a, crop_to_square(big, (0, 0, 64, 64), 16, 1.0, crop_filter="antialias"))
    assert np.abs(a.astype(int) - resize_crop(big, 16).astype(int)).mean() > 5


def test_undistorted_crops_are_filtered_too():
    from refiner_rt.distortion import crop_undistorted

    img = RNG.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    D = np.zeros(5)
    box = (100.0, 60.0, 200.0, 160.0)
    for f in ("none", "antialias"):
        # with no distortion, the undistorted crop is the crop rule's (up to the remap's rounding)
        got = crop_undistorted(img, box, 16, 1.2, K, D, crop_filter=f).astype(int)
        assert np.abs(got - crop_to_square(img, box, 16, 1.2, crop_filter=f).astype(int)).max() <= 2


def test_the_crop_cache_records_and_uses_the_filter(tmp_path):
    import cv2

    from models.data import CropCache
    from models.data.sample import Sample

    img = RNG.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    path = tmp_path / "a.png"
    cv2.imwrite(str(path), img)
    s = Sample(image_path=str(path), obj_id="003_cracker_box", R=np.eye(3), t=np.array([0.0, 0.0, 1.0]),
               box_xyxy=np.array([20.0, 20.0, 100.0, 90.0]), K=np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]]),
               image_size=(160, 120), scene_id="000001", frame_id=1)
    plain = CropCache.build_or_load([s], 16, tmp_path / "c", progress=False)
    assert plain.crop_filter == "none"
    smooth = CropCache.build_or_load([s], 16, tmp_path / "c", progress=False, crop_filter="antialias")
    assert smooth.crop_filter == "antialias"  # the filter is part of the cache's key: rebuilt
    np.testing.assert_array_equal(smooth.crops[0], crop_to_square(img, s.box_xyxy, 16, crop_filter="antialias"))


def test_with_crop_filter_writes_a_copy_the_runtime_loads(tmp_path):
    from export.crop_filter import with_crop_filter

    src = tmp_path / "m.onnx"
    src.write_bytes(random_weight_model(size=8))
    dst = with_crop_filter(src, tmp_path / "aa.onnx", "antialias")
    assert RefinerSession(str(dst)).metadata["crop_filter"] == "antialias"
    a, b = onnx.load(str(src)), onnx.load(str(dst))
    assert [i.raw_data for i in a.graph.initializer] == [i.raw_data for i in b.graph.initializer]
    back = with_crop_filter(dst, tmp_path / "back.onnx", "none")
    assert "crop_filter" not in RefinerSession(str(back)).metadata
    with pytest.raises(ValueError, match="crop_filter must be one of"):
        with_crop_filter(src, tmp_path / "x.onnx", "box")


def test_a_network_config_names_the_filter_and_the_export_passes_it_on():
    import models
    from export.onnx_export import build_model_metadata

    net = models.build_refiner("shallow", crop_filter="antialias")
    assert net.config["crop_filter"] == "antialias"
    assert models.build_refiner("shallow").config["crop_filter"] == "none"
    props = build_model_metadata(net, info={"objects": ["003_cracker_box"], "train_noise": "uniform:0:30"})
    assert parse_metadata(props).crop_filter == "antialias"
    with pytest.raises(ValueError, match=r"config\['crop_filter'\] must be one of"):
        models.build_refiner("shallow", crop_filter="bicubic")
