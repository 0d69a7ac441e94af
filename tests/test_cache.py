"""Tests of the crop cache (models/data/cache.py): crops equal the shared crop rule, hits, and every rebuild trigger."""

from __future__ import annotations

import logging
import os
import pickle

import cv2
import numpy as np
import pytest

from models.data import CropCache, load_bop
from models.data import cache as cache_module
from refiner_rt.preprocess import crop_to_square
from tests.data_fixtures import make_bop

S = 32


@pytest.fixture(scope="module")
def samples(tmp_path_factory):
    split = tmp_path_factory.mktemp("bop") / "test"
    make_bop(split)
    return load_bop(split)


def reference_crops(samples, size=S, context=1.2):
    return np.stack([crop_to_square(cv2.imread(s.image_path), s.box_xyxy, size, context) for s in samples])


def built(caplog) -> bool:
    return "building" in caplog.text


def test_crops_and_index_equal_the_crop_rule_and_the_samples(samples, tmp_path):
    cache = CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
    assert len(cache) == len(samples) == 5
    assert cache.crops.shape == (5, S, S, 3) and cache.crops.dtype == np.uint8
    assert isinstance(cache.crops, np.memmap) and not cache.crops.flags.writeable
    np.testing.assert_array_equal(cache.crops, reference_crops(samples))
    np.testing.assert_array_equal(cache.q_gt, np.stack([s.q_gt for s in samples]))
    np.testing.assert_array_equal(cache.R, np.stack([s.R for s in samples]))
    np.testing.assert_array_equal(cache.K, np.stack([s.K for s in samples]))
    np.testing.assert_array_equal(cache.boxes_xyxy, np.stack([s.box_xyxy for s in samples]))
    assert cache.obj_ids.tolist() == [s.obj_id for s in samples]
    assert cache.scene_ids.tolist() == [s.scene_id for s in samples]
    assert cache.frame_ids.tolist() == [s.frame_id for s in samples]
    assert cache.image_paths.tolist() == [s.image_path for s in samples]
    np.testing.assert_array_equal(cache.visib_fract, [s.visib_fract for s in samples])
    assert cache.manifest["channel_order"] == "BGR" and cache.manifest["n_images"] == 3
    crops, q = cache.get_batch([4, 0])
    np.testing.assert_array_equal(crops, reference_crops([samples[4], samples[0]]))
    np.testing.assert_array_equal(q, cache.q_gt[[4, 0]])


def test_context_and_size_follow_the_arguments(samples, tmp_path):
    cache = CropCache.build_or_load(samples, 20, tmp_path / "c", context=1.5, progress=False)
    assert (cache.size, cache.context) == (20, 1.5)
    np.testing.assert_array_equal(cache.crops, reference_crops(samples, 20, 1.5))


def test_second_call_is_a_hit(samples, tmp_path, caplog):
    first = CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
    inode = os.stat(tmp_path / "c" / "crops.npy").st_ino
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="models.data.cache"):
        second = CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
    assert not built(caplog) and "up to date" in caplog.text
    assert os.stat(tmp_path / "c" / "crops.npy").st_ino == inode
    assert second.manifest == first.manifest


@pytest.mark.parametrize(
    "change, reason",
    [
        (lambda ss, p: dict(samples=ss[:-1]), "n, samples_fingerprint"),
        (lambda ss, p: dict(samples=ss[::-1]), "samples_fingerprint"),
        (lambda ss, p: dict(size=S + 8), "size"),
        (lambda ss, p: dict(context=1.3), "context"),
    ],
    ids=["fewer samples", "other order", "size", "context"],
)
def test_changed_inputs_rebuild(samples, tmp_path, caplog, change, reason):
    CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
    kwargs = dict(samples=samples, size=S, context=1.2)
    kwargs.update(change(samples, tmp_path))
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="models.data.cache"):
        cache = CropCache.build_or_load(kwargs.pop("samples"), cache_dir=tmp_path / "c", progress=False, **kwargs)
    assert f"changed: {reason}" in caplog.text
    assert len(cache) == cache.manifest["n"] and cache.size == kwargs["size"]


def test_touched_source_image_rebuilds(samples, tmp_path, caplog):
    CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
    st = os.stat(samples[0].image_path)
    try:
        os.utime(samples[0].image_path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
        with caplog.at_level(logging.INFO, logger="models.data.cache"):
            CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
        assert "changed: sources_fingerprint" in caplog.text
    finally:
        os.utime(samples[0].image_path, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_new_crop_rule_version_rebuilds(samples, tmp_path, caplog, monkeypatch):
    CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
    monkeypatch.setattr(cache_module, "crop_rule_version", lambda: "a-new-rule")
    with caplog.at_level(logging.INFO, logger="models.data.cache"):
        cache = CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
    assert "changed: crop_rule_version" in caplog.text
    assert cache.manifest["crop_rule_version"] == "a-new-rule"


def test_incomplete_cache_rebuilds_and_cannot_be_opened(samples, tmp_path, caplog):
    CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
    (tmp_path / "c" / "manifest.json").unlink()  # e.g. a build killed before its last step
    with pytest.raises(FileNotFoundError, match="manifest.json: missing; not a \\(complete\\) crop cache"):
        CropCache.open(tmp_path / "c")
    with caplog.at_level(logging.INFO, logger="models.data.cache"):
        cache = CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
    assert "building (no manifest)" in caplog.text
    np.testing.assert_array_equal(cache.crops, reference_crops(samples))


def test_each_image_is_decoded_once(samples, tmp_path, monkeypatch):
    calls = []
    real_imread = cv2.imread

    def counting_imread(path, *args):
        calls.append(path)
        return real_imread(path, *args)

    monkeypatch.setattr(cache_module.cv2, "imread", counting_imread)
    CropCache.build_or_load(samples, S, tmp_path / "c", progress=False)
    assert sorted(calls) == sorted({s.image_path for s in samples})  # 5 samples, 3 images


def test_worker_processes_give_the_same_cache(samples, tmp_path):
    cache = CropCache.build_or_load(samples, S, tmp_path / "c", workers=2, progress=False)
    np.testing.assert_array_equal(cache.crops, reference_crops(samples))
    assert cache.manifest["workers"] == 2


def test_pickles_without_copying_the_crops(samples, tmp_path):
    cache = CropCache.build_or_load(samples * 40, S, tmp_path / "c", progress=False)
    blob = pickle.dumps(cache)
    assert len(blob) < cache.crops.nbytes / 4
    clone = pickle.loads(blob)
    assert isinstance(clone.crops, np.memmap)
    np.testing.assert_array_equal(clone.crops, cache.crops)


def test_image_of_another_size_is_named(samples, tmp_path):
    wrong = samples[0].__class__(**{**samples[0].__dict__, "image_size": (320, 240)})
    with pytest.raises(ValueError, match=r"image is 640x480, but its samples expect 320x240"):
        CropCache.build_or_load([wrong], S, tmp_path / "c", progress=False)
    assert not list((tmp_path / "c").glob("crops*.npy"))  # the half-built file is removed


def test_missing_image_is_named(samples, tmp_path):
    gone = samples[0].__class__(**{**samples[0].__dict__, "image_path": str(tmp_path / "gone.png")})
    with pytest.raises(FileNotFoundError, match="gone.png: image missing"):
        CropCache.build_or_load([gone], S, tmp_path / "c", progress=False)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(size=0), "size must be a positive integer"),
        (dict(size=32.0), "size must be a positive integer"),
        (dict(context=0), "context must be a positive number"),
        (dict(workers=0), "workers must be an integer >= 1 or None"),
    ],
)
def test_bad_arguments_are_refused(samples, tmp_path, kwargs, message):
    args = dict(size=S, cache_dir=tmp_path / "c", progress=False)
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        CropCache.build_or_load(samples, **args)
    with pytest.raises(ValueError, match="samples must not be empty"):
        CropCache.build_or_load([], S, tmp_path / "c")


def test_data_modules_import_without_torch():
    # The data package serves ONNX evaluation too, which must not need torch. Checked with torch made
    # unimportable and the `models` package stubbed, so only models.data's own imports are tested.
    import subprocess
    import sys
    from pathlib import Path

    models_dir = Path(cache_module.__file__).resolve().parents[1]
    code = (
        "import sys, types\n"
        "sys.modules['torch'] = None\n"
        f"pkg = types.ModuleType('models'); pkg.__path__ = [{str(models_dir)!r}]; sys.modules['models'] = pkg\n"
        "import models.data\n"
        "from models.data import Sample, load_bop, load_ycbv, make_splits, CropCache, PAPER_OBJECTS\n"
        "import models.data.cache, models.data.splits, models.data.bop, models.data.ycbv\n"
        "print('ok', len(PAPER_OBJECTS))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok 9"
