"""Tests of the YCB-Video native reader (models/data/ycbv.py) on fixtures written in the real format."""

from __future__ import annotations

import re

import numpy as np
import pytest
import scipy.io
from scipy.spatial.transform import Rotation

from models.data import PAPER_OBJECTS, Sample, load_ycbv
from models.data.ycbv import read_meta
from refiner_rt import quaternion as rq
from tests.data_fixtures import K_YCBV, K_YCBV_LATE, make_ycbv, random_rotations, write_ycbv_frame


@pytest.fixture(scope="module")
def ycbv(tmp_path_factory):
    root = tmp_path_factory.mktemp("ycbv")
    return root, make_ycbv(root)


def one_frame(root, objects=None, **kwargs):
    """A one-frame dataset (seq 0001, frame 000001) with a valid cracker box unless objects are given."""
    if objects is None:
        objects = [(2, random_rotations(1, 5)[0], [0.0, 0.0, 0.8], [100.0, 100.0, 200.0, 250.0])]
    write_ycbv_frame(root, "0001", "000001", objects, K_YCBV, **kwargs)
    return root / "data" / "0001"


def test_round_trip_poses_boxes_ids_exactly(ycbv):
    root, truths = ycbv
    samples = load_ycbv(root)
    assert len(samples) == len(truths) == 8
    for s, t in zip(samples, truths):
        assert isinstance(s, Sample)
        assert s.image_path == str(t.image_path)
        assert s.obj_id == t.obj_id
        np.testing.assert_allclose(s.R, t.R, rtol=0, atol=1e-12)  # only the re-orthonormalisation's rounding
        np.testing.assert_array_equal(s.t, t.t_m)
        np.testing.assert_array_equal(s.box_xyxy, t.box_xyxy)
        np.testing.assert_array_equal(s.K, t.K)
        assert (s.scene_id, s.frame_id, s.instance) == (t.scene_id, t.frame_id, t.instance)
        assert s.image_size == (640, 480)
        assert s.visib_fract is None
        assert s.box_source == "ycbv:box.txt"
        assert s.R.dtype == np.float64 and s.t.dtype == np.float64
        assert s.dataset == str(root.absolute())


def test_intrinsics_are_read_per_frame(ycbv):
    root, _ = ycbv
    by_seq = {s.scene_id: s.K for s in load_ycbv(root)}
    np.testing.assert_array_equal(by_seq["0048"], K_YCBV)
    np.testing.assert_array_equal(by_seq["0060"], K_YCBV_LATE)


def test_q_gt_matches_scipy_in_wxyz(ycbv):
    root, truths = ycbv
    for s, t in zip(load_ycbv(root), truths):
        x, y, z, w = Rotation.from_matrix(t.R).as_quat()
        assert rq.geodesic_angle(s.q_gt, [w, x, y, z]) < 1e-6
        assert s.q_gt[0] >= 0


def test_single_object_frame_has_3x4_poses_and_loads(ycbv):
    root, _ = ycbv
    raw = scipy.io.loadmat(root / "data" / "0048" / "000002-meta.mat")
    assert raw["poses"].shape == (3, 4)  # the N = 1 case as MATLAB stores it
    poses, cls, _ = read_meta(root / "data" / "0048" / "000002-meta.mat")
    assert poses.shape == (1, 3, 4) and cls.tolist() == [2]


def test_image_set_by_name_and_by_path(ycbv):
    root, _ = ycbv
    key = load_ycbv(root, image_set="keyframe")
    assert sorted({(s.scene_id, s.frame_id) for s in key}) == [("0048", 1), ("0060", 1)]
    assert len(key) == 5
    by_path = load_ycbv(root, image_set=root / "image_sets" / "keyframe.txt")
    assert [s.image_path for s in by_path] == [s.image_path for s in key]
    assert len(load_ycbv(root, image_set="train")) == 8


def test_unknown_image_set_lists_available_names(ycbv):
    root, _ = ycbv
    with pytest.raises(ValueError, match=r"available names: \['keyframe', 'train'\]"):
        load_ycbv(root, image_set="val")


def test_object_filter(ycbv):
    root, _ = ycbv
    samples = load_ycbv(root, objects=["003_cracker_box"])
    assert [s.obj_id for s in samples] == ["003_cracker_box"] * 2
    paper = load_ycbv(root, objects=PAPER_OBJECTS)
    assert {s.obj_id for s in paper} <= set(PAPER_OBJECTS) and len(paper) == 8  # all fixture objects are paper objects


def test_object_filter_rejects_bad_ids(ycbv):
    root, _ = ycbv
    with pytest.raises(ValueError, match="unknown object '003_crackers'"):
        load_ycbv(root, objects=["003_crackers"])
    with pytest.raises(TypeError, match="not one string"):
        load_ycbv(root, objects="003_cracker_box")


def test_min_box_size_uses_the_longer_side(ycbv):
    root, _ = ycbv
    kept = load_ycbv(root, min_box_size=75)
    # scissors 20x70 and gelatin 50x50 go; banana 100x70 stays (its longer side is 100)
    assert {s.obj_id for s in kept} == {"003_cracker_box", "006_mustard_bottle", "035_power_drill", "011_banana",
                                         "021_bleach_cleanser"}
    assert len(kept) == 6


def test_small_rotation_error_is_repaired(tmp_path):
    R = random_rotations(1, 9)[0]
    noisy = R + 1e-4 * np.random.default_rng(0).standard_normal((3, 3))
    one_frame(tmp_path, [(2, noisy, [0, 0, 1.0], [10.0, 10.0, 50.0, 50.0])])
    for method in ("premerlani", "svd"):
        (s,) = load_ycbv(tmp_path, rotation_method=method)
        assert np.abs(s.R.T @ s.R - np.eye(3)).max() < 1e-7
        assert rq.geodesic_angle(s.q_gt, rq.from_matrix(R)) < 0.05  # degrees


@pytest.mark.parametrize(
    "matrix, what",
    [
        (np.diag([1.1, 1.0, 1.0]), r"not a rotation matrix.*\|R\^T R - I\| = 0\.21"),
        (np.diag([1.0, 1.0, -1.0]), r"not a rotation matrix.*det = -1"),
    ],
)
def test_non_rotation_is_rejected_naming_file_and_field(tmp_path, matrix, what):
    one_frame(tmp_path, [(2, matrix, [0, 0, 1.0], [10.0, 10.0, 50.0, 50.0])])
    with pytest.raises(ValueError, match=what) as err:
        load_ycbv(tmp_path)
    assert "000001-meta.mat: field 'poses'[:, :3, 0] (003_cracker_box)" in str(err.value)


def test_missing_field_is_named(tmp_path):
    seq = one_frame(tmp_path)
    mat = scipy.io.loadmat(seq / "000001-meta.mat")
    del mat["intrinsic_matrix"]
    scipy.io.savemat(seq / "000001-meta.mat", {k: v for k, v in mat.items() if not k.startswith("__")})
    with pytest.raises(ValueError, match=re.escape(f"{seq / '000001-meta.mat'}: missing field 'intrinsic_matrix'")):
        load_ycbv(tmp_path)


def test_wrong_pose_shape_is_named(tmp_path):
    seq = one_frame(tmp_path, poses_override=np.zeros((3, 3, 1)))
    with pytest.raises(ValueError, match=re.escape(f"{seq / '000001-meta.mat'}: field 'poses' must have shape 3x4xN")):
        load_ycbv(tmp_path)


def test_class_index_out_of_range_is_named(tmp_path):
    seq = one_frame(tmp_path)
    mat = scipy.io.loadmat(seq / "000001-meta.mat")
    mat["cls_indexes"] = np.array([[22.0]])
    scipy.io.savemat(seq / "000001-meta.mat", {k: v for k, v in mat.items() if not k.startswith("__")})
    with pytest.raises(ValueError, match=r"000001-meta.mat: field 'cls_indexes' must hold 1-based class indices in 1\.\.21; got \[22\.0\]"):
        load_ycbv(tmp_path)


def test_pose_count_mismatch_is_named(tmp_path):
    seq = one_frame(tmp_path, poses_override=np.zeros((3, 4, 2)))
    with pytest.raises(ValueError, match=r"field 'cls_indexes' must have one entry per pose: expected 2"):
        load_ycbv(tmp_path)
    assert seq.is_dir()


def test_box_outside_image_is_named(tmp_path):
    seq = one_frame(tmp_path, [(2, np.eye(3), [0, 0, 1.0], [700.0, 10.0, 760.0, 50.0])])
    with pytest.raises(ValueError, match=re.escape(f"{seq / '000001-box.txt'}: box of '003_cracker_box' lies outside the 640x480 image")):
        load_ycbv(tmp_path)


def test_empty_box_is_named(tmp_path):
    one_frame(tmp_path, [(2, np.eye(3), [0, 0, 1.0], [50.0, 10.0, 40.0, 50.0])])
    with pytest.raises(ValueError, match=r"000001-box.txt: box of '003_cracker_box' is empty"):
        load_ycbv(tmp_path)


def test_box_file_without_the_class_is_named(tmp_path):
    seq = one_frame(tmp_path)
    (seq / "000001-box.txt").write_text("006_mustard_bottle 1 2 3 4\n")
    with pytest.raises(ValueError, match=r"000001-box.txt: no line for class '003_cracker_box'"):
        load_ycbv(tmp_path)


def test_malformed_box_line_is_named(tmp_path):
    seq = one_frame(tmp_path)
    (seq / "000001-box.txt").write_text("003_cracker_box 1 2 3\n")
    with pytest.raises(ValueError, match=re.escape(f"{seq / '000001-box.txt'}:1: expected '<class name> x1 y1 x2 y2'")):
        load_ycbv(tmp_path)


def test_missing_image_is_named(tmp_path):
    seq = one_frame(tmp_path)
    (seq / "000001-color.png").unlink()
    with pytest.raises(FileNotFoundError, match=re.escape(str(seq / "000001-color.png"))):
        load_ycbv(tmp_path)


def test_bad_image_set_line_is_named(tmp_path):
    one_frame(tmp_path)
    bad = tmp_path / "bad.txt"
    bad.write_text("0001/000001\n0001-000002\n")
    with pytest.raises(ValueError, match=re.escape(f"{bad}:2: expected a frame as '<seq>/<frame>'")):
        load_ycbv(tmp_path, image_set=bad)


def test_corrupt_mat_file_is_named(tmp_path):
    seq = one_frame(tmp_path)
    (seq / "000001-meta.mat").write_bytes(b"not a mat file")
    with pytest.raises(ValueError, match=re.escape(f"{seq / '000001-meta.mat'}: cannot be read as a MATLAB .mat file")):
        load_ycbv(tmp_path)


def test_unknown_rotation_method_is_refused(tmp_path):
    one_frame(tmp_path)
    with pytest.raises(ValueError, match=r"rotation_method must be one of \('premerlani', 'svd'\); got 'qr'"):
        load_ycbv(tmp_path, rotation_method="qr")
