"""models.data.pipeline: format detection, loading through either loader, and split parts as CropSets."""

import numpy as np
import pytest

from models.data.pipeline import DataSpec, checkpoint_test_set, cropset_for, detect_format, load_samples, load_splits
from refiner_rt import quaternion as rq
from refiner_rt.session import ray_quaternions
from tests.data_fixtures import make_bop, make_ycbv


def test_detects_both_formats_and_rejects_others(tmp_path):
    make_ycbv(tmp_path / "ycbv")
    make_bop(tmp_path / "bop")
    assert detect_format(tmp_path / "ycbv") == "ycbv"
    assert detect_format(tmp_path / "bop") == "bop"
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="not a dataset"):
        detect_format(tmp_path / "empty")
    with pytest.raises(FileNotFoundError):
        detect_format(tmp_path / "missing")


def test_ycbv_loads_without_visibility_information(tmp_path):
    truths = make_ycbv(tmp_path / "ycbv")
    samples = load_samples(DataSpec(data=str(tmp_path / "ycbv"), min_visib=0.3, min_box_size=0))
    paper = {t.obj_id for t in truths} & {s.obj_id for s in samples}
    assert len(samples) == sum(1 for t in truths if t.obj_id in paper)


def test_cropset_of_a_split_part_carries_rays_and_ground_truth(tmp_path):
    make_bop(tmp_path / "bop")
    spec = DataSpec(data=str(tmp_path / "bop"), min_visib=0.0, min_box_size=0, sizes=(1, 0, 0, 1))
    splits = load_splits(spec)
    cs = cropset_for(splits, "train_base", spec, 16, 1.2, cache_root=tmp_path / "cache", progress=False)
    samples = splits.train_base
    assert len(cs) == len(samples) and cs.crops.shape[1:] == (16, 16, 3)
    np.testing.assert_allclose(cs.q_gt, np.stack([s.q_gt for s in samples]))
    ref = ray_quaternions(np.stack([s.K for s in samples]), np.stack([s.box_xyxy for s in samples]))
    np.testing.assert_allclose(rq.geodesic_angle(cs.q_ray, ref), 0, atol=1e-9)
    with pytest.raises(ValueError, match="part must be one of"):
        cropset_for(splits, "holdout", spec, 16, 1.2)


def test_checkpoint_test_set_rebuilds_the_recorded_test_split(tmp_path):
    make_bop(tmp_path / "bop")
    spec = DataSpec(data=str(tmp_path / "bop"), min_visib=0.0, min_box_size=0, sizes=(1, 0, 0, 1))

    class Net:
        input_size, config = 16, {"crop_context": 1.2}

    direct = cropset_for(load_splits(spec), "test", spec, 16, 1.2, cache_root=tmp_path / "cache", progress=False)
    test, got = checkpoint_test_set(Net(), {"data": spec.as_dict()}, cache_root=tmp_path / "cache")
    assert got == spec
    np.testing.assert_array_equal(test.crops, direct.crops)
    np.testing.assert_allclose(test.q_gt, direct.q_gt)
    again, _, samples = checkpoint_test_set(Net(), {"data": spec.as_dict()}, cache_root=tmp_path / "cache",
                                            with_samples=True)
    assert len(samples) == len(again)  # the samples in the crops' order: the frames runtime studies read again
    np.testing.assert_allclose(again.q_gt, np.stack([s.q_gt for s in samples]))
    np.testing.assert_array_equal(again.scene_ids, [s.scene_id for s in samples])
    with pytest.raises(ValueError, match="records no training data spec"):
        checkpoint_test_set(Net(), {}, cache_root=tmp_path / "cache")


def _grown_set(root):
    """A 5-scene cube set split in two folders as a grown render is: scenes 0-2 in ``first``, 3-4 in ``more``."""
    import shutil

    from tests.cube_dataset import make_cube_dataset

    make_cube_dataset(root / "all", scenes=5, frames=6)
    (root / "more").mkdir()
    for s in ("000003", "000004"):
        shutil.move(root / "all" / s, root / "more" / s)
    return root / "all", root / "more"


def test_extra_train_folders_join_the_training_part_and_leave_the_split_alone(tmp_path):
    first, more = _grown_set(tmp_path)
    kw = dict(objects=["003_cracker_box"], split_mode="scenes", sizes=(6, 0, 6, 6), min_box_size=0)
    plain = load_splits(DataSpec(data=str(first), **kw))
    grown_spec = DataSpec(data=str(first), extra_train=[str(more)], **kw)
    grown = load_splits(grown_spec)
    def keys(samples):
        return [(s.scene_id, s.frame_id, s.instance, s.obj_id) for s in samples]

    assert plain.val and plain.test and plain.train_base
    for part in ("train_finetune", "val", "test"):
        assert keys(getattr(grown, part)) == keys(getattr(plain, part))
    extra = load_samples(DataSpec(data=str(more), **kw))
    assert keys(grown.train_base) == keys(plain.train_base + extra)
    assert {s.scene_id for s in extra} == {"000003", "000004"}
    # The spec round-trips through a checkpoint's info; a spec without the field keeps its old key (and crop cache).
    assert DataSpec.from_dict(grown_spec.as_dict()) == grown_spec
    assert "extra_train" not in DataSpec(data=str(first), **kw).as_dict()
    cs = cropset_for(grown, "train_base", grown_spec, 16, 1.2, cache_root=tmp_path / "cache", progress=False)
    assert len(cs) == len(grown.train_base) and set(cs.scene_ids.tolist()) >= {"000003", "000004"}


def test_extra_train_refuses_scene_ids_it_has_seen(tmp_path):
    import shutil

    first, more = _grown_set(tmp_path)
    kw = dict(objects=["003_cracker_box"], split_mode="scenes", sizes=(6, 0, 6, 6), min_box_size=0)
    with pytest.raises(ValueError, match=r"scene id\(s\) \['000000', '000001', '000002'\].*--first-scene"):
        load_splits(DataSpec(data=str(first), extra_train=[str(first)], **kw))  # the set itself: its test scenes too
    with pytest.raises(ValueError, match=r"scene id\(s\) \['000003', '000004'\]"):
        load_splits(DataSpec(data=str(first), extra_train=[str(more), str(more)], **kw))
    shutil.copytree(more / "000003", tmp_path / "copy" / "000001")  # a scene id of the first set, other content
    with pytest.raises(ValueError, match=r"\['000001'\] that .*all has too"):
        load_splits(DataSpec(data=str(first), extra_train=[str(tmp_path / "copy")], **kw))
    with pytest.raises(ValueError, match="extra_train must be a list of dataset folders"):
        load_splits(DataSpec(data=str(first), extra_train=str(more), **kw))


def test_the_pipeline_does_not_import_the_onnx_session():
    # The ray frame lives in the torch-free refiner_rt.geometry, which training and the session both import.
    import subprocess
    import sys

    code = "import sys, models.data.pipeline; assert 'refiner_rt.session' not in sys.modules, 'session imported'"
    subprocess.run([sys.executable, "-c", code], check=True)
    from refiner_rt import geometry, session

    assert session.ray_quaternions is geometry.ray_quaternions and session.view_boxes is geometry.view_boxes
