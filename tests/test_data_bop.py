"""Tests of the BOP reader (models/data/bop.py) on scenes written as the BOP toolkit writes them."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from models.data import Sample, load_bop
from refiner_rt import quaternion as rq
from tests.data_fixtures import K_YCBV, bop_instance, make_bop, random_rotations, write_bop_scene


@pytest.fixture(scope="module")
def bop(tmp_path_factory):
    split = tmp_path_factory.mktemp("bop") / "test"
    return split, make_bop(split)


def one_scene(split, instance=None, size=(640, 480), **kwargs):
    """A one-image scene 000001 with one cracker box, or the given instance dict."""
    if instance is None:
        instance = bop_instance(2, random_rotations(1, 3)[0], [0.0, 0.0, 900.0], [100, 100, 80, 120], 0.8)
    scene, _ = write_bop_scene(split, 1, {0: [instance]}, K_YCBV, size=size, **kwargs)
    return scene


def test_round_trip_poses_boxes_ids_exactly(bop):
    split, truths = bop
    samples = load_bop(split)
    assert len(samples) == len(truths) == 5
    for s, t in zip(samples, truths):
        assert isinstance(s, Sample)
        assert s.image_path == str(t.image_path)
        assert s.obj_id == t.obj_id
        np.testing.assert_allclose(s.R, t.R, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(s.t, t.t_m)  # mm -> metres
        np.testing.assert_array_equal(s.box_xyxy, t.box_xyxy)  # [x, y, w, h] -> [x, y, x + w, y + h]
        np.testing.assert_array_equal(s.K, t.K)
        assert (s.scene_id, s.frame_id, s.instance) == (t.scene_id, t.frame_id, t.instance)
        assert s.visib_fract == t.visib_fract
        assert s.image_size == (640, 480)
        assert s.box_source == "bop:bbox_visib"
        assert s.dataset == str(split.absolute())


def test_png_and_jpg_images_are_found(bop):
    split, _ = bop
    suffixes = {s.scene_id: s.image_path.rsplit(".", 1)[1] for s in load_bop(split)}
    assert suffixes == {"000048": "png", "000050": "jpg"}


def test_translation_is_converted_from_mm_to_metres(bop):
    split, _ = bop
    first = load_bop(split)[0]
    np.testing.assert_allclose(first.t, [0.0125, -0.020, 0.81225], rtol=0, atol=1e-15)


def test_amodal_box_option(bop):
    split, truths = bop
    samples = load_bop(split, box="obj")
    assert [s.box_source for s in samples] == ["bop:bbox_obj"] * 5
    for s, t in zip(samples, truths):
        np.testing.assert_array_equal(s.box_xyxy, t.bbox_obj_xyxy)
    with pytest.raises(ValueError, match=r"box must be one of \['obj', 'visib'\].*got 'amodal'"):
        load_bop(split, box="amodal")


def test_invisible_instances_are_skipped(bop):
    split, _ = bop
    # scene 50 image 7 instance 1 (mustard, visib_fract 0, bbox_visib [-1, -1, -1, -1]) never appears
    for box in ("visib", "obj"):
        assert "006_mustard_bottle" not in {s.obj_id for s in load_bop(split, box=box)}


def test_min_visib_filter(bop):
    split, _ = bop
    assert len(load_bop(split, min_visib=0.3)) == 4  # scissors at 0.25 goes
    assert {s.obj_id for s in load_bop(split, min_visib=0.5)} == {"003_cracker_box", "009_gelatin_box"}
    with pytest.raises(ValueError, match=r"min_visib must be a fraction in \[0, 1\]; got 30"):
        load_bop(split, min_visib=30)


def test_object_and_box_size_filters(bop):
    split, _ = bop
    assert [s.frame_id for s in load_bop(split, objects=["003_cracker_box"])] == [1, 2]
    kept = load_bop(split, min_box_size=100)
    assert sorted(s.obj_id for s in kept) == ["003_cracker_box", "003_cracker_box", "035_power_drill"]


def test_custom_obj_id_map(tmp_path):
    one_scene(tmp_path)
    (s,) = load_bop(tmp_path, obj_id_map={2: "my_box"})
    assert s.obj_id == "my_box"


def test_q_gt_is_wxyz_of_cam_R_m2c(bop):
    split, truths = bop
    for s, t in zip(load_bop(split), truths):
        np.testing.assert_allclose(rq.to_matrix(s.q_gt), t.R, atol=1e-12)


@pytest.mark.parametrize("field, file", [("cam_R_m2c", "scene_gt.json"), ("obj_id", "scene_gt.json"),
                                         ("bbox_visib", "scene_gt_info.json"), ("visib_fract", "scene_gt_info.json")])
def test_missing_key_names_file_and_field(tmp_path, field, file):
    inst = bop_instance(2, np.eye(3), [0.0, 0.0, 900.0], [100, 100, 80, 120], drop=(field,))
    scene = one_scene(tmp_path, inst)
    with pytest.raises(ValueError, match=re.escape(f"{scene / file}: image 0, instance 0: missing field {field!r}")):
        load_bop(tmp_path)


def test_wrong_length_is_named(tmp_path):
    inst = bop_instance(2, np.eye(3), [0.0, 900.0], [100, 100, 80, 120])
    scene = one_scene(tmp_path, inst)
    with pytest.raises(ValueError, match=re.escape(f"{scene / 'scene_gt.json'}: image 0, instance 0: field 'cam_t_m2c' must be a list of 3 numbers; got [0.0, 900.0]")):
        load_bop(tmp_path)


def test_non_rotation_is_named(tmp_path):
    scene = one_scene(tmp_path, bop_instance(2, 2.0 * np.eye(3), [0.0, 0.0, 900.0], [100, 100, 80, 120]))
    with pytest.raises(ValueError, match=re.escape(f"{scene / 'scene_gt.json'}: image 0, instance 0: field 'cam_R_m2c' is not a rotation matrix")):
        load_bop(tmp_path)


def test_small_rotation_error_is_repaired(tmp_path):
    R = random_rotations(1, 4)[0]
    one_scene(tmp_path, bop_instance(2, np.round(R, 4), [0.0, 0.0, 900.0], [100, 100, 80, 120]))
    (s,) = load_bop(tmp_path)
    assert np.abs(s.R.T @ s.R - np.eye(3)).max() < 1e-7
    assert rq.geodesic_angle(s.q_gt, rq.from_matrix(R)) < 0.02


def test_visible_box_past_the_border_is_named(tmp_path):
    scene = one_scene(tmp_path, bop_instance(2, np.eye(3), [0.0, 0.0, 900.0], [600, 100, 80, 120]))
    with pytest.raises(ValueError, match=re.escape(f"{scene / 'scene_gt_info.json'}: image 0, instance 0: field 'bbox_visib' (as x1, y1, x2, y2) extends outside the 640x480 image")):
        load_bop(tmp_path)


def test_box_entirely_outside_is_named(tmp_path):
    inst = bop_instance(2, np.eye(3), [0.0, 0.0, 900.0], [100, 100, 80, 120], bbox_obj=[700, 100, 50, 50])
    one_scene(tmp_path, inst)
    with pytest.raises(ValueError, match=r"field 'bbox_obj' \(as x1, y1, x2, y2\) lies outside the 640x480 image"):
        load_bop(tmp_path, box="obj")
    assert len(load_bop(tmp_path, box="visib")) == 1  # the visible box is fine


def test_unknown_obj_id_is_named(tmp_path):
    scene = one_scene(tmp_path, bop_instance(99, np.eye(3), [0.0, 0.0, 900.0], [100, 100, 80, 120]))
    with pytest.raises(ValueError, match=re.escape(f"{scene / 'scene_gt.json'}: image 0, instance 0: field 'obj_id' must be one of [1, 2,")):
        load_bop(tmp_path)


def test_annotation_lists_must_agree(tmp_path):
    scene = one_scene(tmp_path)
    info = json.loads((scene / "scene_gt_info.json").read_text())
    info["0"].append(info["0"][0])
    (scene / "scene_gt_info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"scene_gt_info.json: image 0: expected 1 entries, one per instance in scene_gt.json; got 2"):
        load_bop(tmp_path)


def test_missing_camera_entry_and_bad_K_are_named(tmp_path):
    scene = one_scene(tmp_path)
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": [1, 0, 0, 0, 1, 0, 0, 0]}}))
    with pytest.raises(ValueError, match=re.escape(f"{scene / 'scene_camera.json'}: image 0: field 'cam_K' must be a list of 9 numbers")):
        load_bop(tmp_path)
    (scene / "scene_camera.json").write_text(json.dumps({"5": {"cam_K": K_YCBV.ravel().tolist()}}))
    with pytest.raises(ValueError, match=re.escape(f"{scene / 'scene_camera.json'}: missing image 0")):
        load_bop(tmp_path)


def test_missing_files_are_named(tmp_path):
    scene = one_scene(tmp_path)
    (scene / "rgb" / "000000.png").unlink()
    with pytest.raises(FileNotFoundError, match=re.escape(f"{scene / 'rgb' / '000000'}.png|.jpg: missing image")):
        load_bop(tmp_path)
    (scene / "scene_gt_info.json").unlink()
    with pytest.raises(FileNotFoundError, match=re.escape(f"{scene / 'scene_gt_info.json'}: missing")):
        load_bop(tmp_path)


def test_invalid_json_is_named(tmp_path):
    scene = one_scene(tmp_path)
    (scene / "scene_gt.json").write_text('{\n  "0": [{"obj_id": 2,}]\n}')
    with pytest.raises(ValueError, match=re.escape(f"{scene / 'scene_gt.json'}: invalid JSON")):
        load_bop(tmp_path)


def test_visib_fract_out_of_range_is_named(tmp_path):
    one_scene(tmp_path, bop_instance(2, np.eye(3), [0.0, 0.0, 900.0], [100, 100, 80, 120], visib_fract=1.5))
    with pytest.raises(ValueError, match=r"scene_gt_info.json: image 0, instance 0: field 'visib_fract' must be in \[0, 1\]; got 1.5"):
        load_bop(tmp_path)


def test_split_folder_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such folder"):
        load_bop(tmp_path / "nope")
    scene = one_scene(tmp_path)
    with pytest.raises(ValueError, match=r"no BOP scene folders .* \(it is itself a scene folder: pass its parent\)"):
        load_bop(scene)
