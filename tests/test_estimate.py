"""refiner_rt.estimate (PoseEstimator) and its CLI: geometry against SciPy, the API's checks, end to end on the
sample frames (rendered scenes with ground truth)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

import refiner_rt
from refiner_rt import quaternion as rq
from refiner_rt.cli import main
from refiner_rt.demo import SAMPLES_DIR, load_outlines, load_samples
from refiner_rt.checks import validate_depth
from refiner_rt.estimate import PoseEstimator, depth_translation, shape_disagreement, super_fibonacci
from refiner_rt.placement import fit_translation, load_extents, pixel_coordinates

K = np.array([[600.0, 0.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]])


def _cuboid(size=(0.08, 0.12, 0.04), n=12):
    """Points on the surface of an axis-aligned cuboid centred at the origin (metres)."""
    g = np.linspace(-0.5, 0.5, n)
    a, b = np.meshgrid(g, g)
    faces = []
    for axis in range(3):
        for side in (-0.5, 0.5):
            p = np.zeros((a.size, 3))
            others = [k for k in range(3) if k != axis]
            p[:, axis], p[:, others[0]], p[:, others[1]] = side, a.ravel(), b.ravel()
            faces.append(p * np.asarray(size))
    return np.unique(np.concatenate(faces), axis=0)


def _box_of(points, R, t):
    uv = pixel_coordinates(points @ R.T + t, K)
    return np.concatenate([uv.min(axis=0), uv.max(axis=0)])


def test_pixel_coordinates_are_opencvs_projection_half_a_pixel_on():
    """The placement's projection against OpenCV's (an independent one): OpenCV puts pixel centres at integers, the
    continuous box coordinates at half-integers, so the two differ by exactly 0.5 px. OpenCV reads no skew: a skewed
    K is held to the homogeneous product ``K @ p / z`` instead."""
    import cv2

    rng = np.random.default_rng(5)
    pts = rng.uniform(-0.1, 0.1, (50, 3)) + [0.02, -0.03, 0.9]
    ref = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, None)[0].reshape(-1, 2)
    np.testing.assert_allclose(pixel_coordinates(pts, K), ref + 0.5, atol=1e-9)
    Ks = K.copy()
    Ks[0, 1] = 3.5
    h = pts @ Ks.T
    np.testing.assert_allclose(pixel_coordinates(pts, Ks), h[:, :2] / h[:, 2:] + 0.5, atol=1e-9)


def test_super_fibonacci_spreads_unit_rotations_over_so3():
    q = super_fibonacci(512)
    assert q.shape == (512, 4) and np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    R = Rotation.from_quat(rq.to_xyzw(q)).as_matrix()  # SciPy: xyzw
    assert np.abs(R.mean(axis=0)).max() < 0.02  # the mean rotation matrix of a uniform set is 0
    nearest = np.sort(rq.geodesic_angle(q[:, None], q[None]), axis=1)[:, 1]
    assert nearest.min() > 15.0 and nearest.max() < 35.0  # no clumps, no holes (random draws: a few degrees)
    with pytest.raises(ValueError, match="positive integer"):
        super_fibonacci(0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fit_translation_recovers_a_known_translation(seed):
    rng = np.random.default_rng(seed)
    points = load_outlines()["003_cracker_box"].points_m
    R = Rotation.random(random_state=rng).as_matrix()
    t = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.15, 0.15), rng.uniform(0.6, 1.5)])
    got = fit_translation(R, points, _box_of(points, R, t), K, image_size=(480, 640))
    np.testing.assert_allclose(got, t, atol=1e-6)


@pytest.mark.parametrize("object_id", ["003_cracker_box", "011_banana", "035_power_drill"])
def test_shipped_extent_points_give_the_mesh_box(object_id):
    """The projected bounding box of the shipped extent points is the mesh's own, from any viewpoint."""
    from pathlib import Path

    from models.data.meshes import load_obj

    repo = Path(__file__).resolve().parents[1]
    vertices = load_obj(repo / "models" / "data" / "ycb_models" / object_id / "textured.obj")[0]
    extent = load_extents()[object_id]
    assert len(extent) < 1000
    rng = np.random.default_rng(4)
    for R in Rotation.random(20, random_state=rng).as_matrix():
        t = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(0.4, 1.2)])
        np.testing.assert_allclose(_box_of(extent, R, t), _box_of(vertices, R, t), atol=0.5)  # pixels


def test_fit_translation_ignores_sides_cut_by_the_image_border():
    points = load_outlines()["004_sugar_box"].points_m
    R = Rotation.from_euler("xyz", [20, -30, 40], degrees=True).as_matrix()
    t = np.array([-0.45, 0.02, 0.9])
    box = _box_of(points, R, t)
    assert box[0] < 0  # the object runs off the left edge
    cut = box.copy()
    cut[0] = 0.0
    np.testing.assert_allclose(fit_translation(R, points, cut, K, image_size=(480, 640)), t, atol=1e-6)
    # Without the image size every side is trusted: the distance still comes from the whole height (the larger
    # ratio), but the cut box's centre pulls the object to the right.
    blind = fit_translation(R, points, cut, K)
    assert blind[2] == pytest.approx(t[2], rel=1e-6) and blind[0] - t[0] > 1e-3


def test_fit_translation_trusts_the_less_occluded_dimension():
    points = _cuboid()
    R, t = np.eye(3), np.array([0.05, -0.03, 0.8])
    box = _box_of(points, R, t)
    occluded = box.copy()
    occluded[3] -= 0.4 * (box[3] - box[1])  # the lower 40% hidden by something in front
    got = fit_translation(R, points, occluded, K, image_size=(480, 640))
    assert got[2] == pytest.approx(t[2], rel=1e-6)  # the distance from the width, which is whole
    assert got[0] == pytest.approx(t[0], abs=1e-6)


def test_depth_translation_puts_the_front_surface_at_the_measured_depth():
    points = _cuboid(n=20)
    R, t = np.eye(3), np.array([0.02, 0.01, 0.9])
    box = _box_of(points, R, t)
    depth = np.zeros((480, 640), dtype=np.float32)
    x1, y1, x2, y2 = box.astype(int)
    depth[y1:y2, x1:x2] = t[2] - 0.02  # the cuboid's front face (half depth 2 cm), seen face on
    t_box = t * 1.15  # a box fit 15% too far, along the ray through the centroid (at the origin here)
    got = depth_translation(R, points, t_box, box, K, depth)
    np.testing.assert_allclose(got, t, atol=1e-6)
    assert depth_translation(R, points, t_box, box, K, np.zeros_like(depth)) is None  # no valid depth


def test_shape_disagreement_prefers_the_rotation_that_made_the_box():
    extent = load_extents()["003_cracker_box"]
    rng = np.random.default_rng(5)
    R = Rotation.random(6, random_state=rng).as_matrix()
    t = np.array([0.05, -0.04, 0.9])
    boxes = np.array([_box_of(extent, r, t) for r in R])
    q = rq.from_matrix(R)
    own = shape_disagreement(q, extent, boxes, K, (480, 640))
    assert own.shape == (6,) and np.all((own >= 0) & (own < 0.02))  # near 0 (weak perspective off the axis)
    other = shape_disagreement(q[[1, 2, 3, 4, 5, 0]], extent, boxes, K, (480, 640))
    assert np.mean(other) > 5 * np.mean(own)
    cut = boxes.copy()
    cut[:, 0] = 0.0  # every box at the left border: no shape to judge
    assert np.all(shape_disagreement(q[[1, 2, 3, 4, 5, 0]], extent, cut, K, (480, 640)) == 0.0)


def test_validate_depth_refuses_millimetres_and_wrong_shapes():
    shape = (480, 640, 3)
    with pytest.raises(TypeError, match="float metres"):
        validate_depth(np.ones((480, 640), dtype=np.uint16), shape)
    with pytest.raises(ValueError, match="shape"):
        validate_depth(np.ones((240, 320), dtype=np.float32), shape)
    with pytest.raises(ValueError, match="millimetres"):
        validate_depth(np.full((480, 640), 850.0, dtype=np.float32), shape)
    with pytest.raises(TypeError, match="numpy array"):
        validate_depth([[1.0]], shape)
    d = np.full((480, 640), 0.85, dtype=np.float32)
    assert validate_depth(d, shape) is d


@pytest.fixture(scope="module")
def sample():
    """The sample frame 000008_000000 (rendered, ground truth) and its cracker box and sugar box."""
    frame = next(f for f in load_samples() if f.path.name == "000008_000000.jpg")
    objects = {o.object_id: o for o in frame.objects}
    return frame, frame.image(), objects


@pytest.fixture(scope="module")
def estimator():
    return PoseEstimator.pretrained("003_cracker_box")


def test_estimate_end_to_end_on_a_rendered_frame(sample, estimator):
    frame, image, objects = sample
    obj = objects["003_cracker_box"]
    res = estimator.estimate(image, obj.box_xyxy[None], K=frame.K)
    assert res.R.shape == (1, 3, 3) and res.t.shape == (1, 3) and res.score.shape == (1,) and len(res) == 1
    np.testing.assert_allclose(res.R[0] @ res.R[0].T, np.eye(3), atol=1e-9)
    assert np.linalg.det(res.R[0]) == pytest.approx(1.0)
    np.testing.assert_allclose(Rotation.from_quat(rq.to_xyzw(res.q)).as_matrix(), res.R, atol=1e-9)
    assert rq.geodesic_angle(res.q[0], obj.q_gt) < 10.0
    # The object's centre within 5 cm of the truth (translation from the box alone, at about 1 m).
    c = load_outlines()["003_cracker_box"].centroid_m
    R_gt = rq.to_matrix(obj.q_gt)
    assert np.linalg.norm((res.R[0] @ c + res.t[0]) - (R_gt @ c + obj.t_m)) < 0.05
    assert 0.0 < res.score[0] <= 1.0


def test_estimate_batches_boxes_as_single_calls_do(sample, estimator):
    frame, image, objects = sample
    box = objects["003_cracker_box"].box_xyxy
    other = box + np.array([-40.0, 10.0, -40.0, 10.0])
    both = estimator.estimate(image, np.stack([box, other]), K=frame.K)
    for i, b in enumerate((box, other)):
        one = estimator.estimate(image, b[None], K=frame.K)
        # INT8 kernels may round differently at another batch size: the same answer within a fraction of a degree.
        assert rq.geodesic_angle(both.q[i], one.q[0]) < 0.5
        np.testing.assert_allclose(both.t[i], one.t[0], atol=0.005)


def test_estimate_with_depth_uses_it(sample, estimator):
    frame, image, objects = sample
    obj = objects["003_cracker_box"]
    rgb = estimator.estimate(image, obj.box_xyxy[None], K=frame.K)
    depth = np.full(image.shape[:2], 2.0, dtype=np.float32)  # everything 2 m away: the object must move back
    with_depth = estimator.estimate(image, obj.box_xyxy[None], K=frame.K, depth=depth)
    np.testing.assert_allclose(with_depth.R, rgb.R)
    assert with_depth.t[0, 2] > 1.9 > rgb.t[0, 2]
    holes = estimator.estimate(image, obj.box_xyxy[None], K=frame.K, depth=np.zeros_like(depth))
    np.testing.assert_allclose(holes.t, rgb.t)  # no valid depth in the box: the box fit stands


def test_estimate_checks_its_inputs(sample, estimator):
    frame, image, objects = sample
    box = objects["003_cracker_box"].box_xyxy[None]
    with pytest.raises(ValueError, match="K is required"):
        estimator.estimate(image, box, K=None)
    with pytest.raises(ValueError, match="K must"):
        estimator.estimate(image, box, K=np.eye(2))
    with pytest.raises(ValueError, match="boxes_xyxy"):
        estimator.estimate(image, np.zeros((1, 3)), K=frame.K)
    with pytest.raises(ValueError, match="image_bgr"):
        estimator.estimate(image[..., 0], box, K=frame.K)
    with pytest.raises(ValueError, match="depth must have the image's shape"):
        estimator.estimate(image, box, K=frame.K, depth=np.ones((2, 2), dtype=np.float32))
    with pytest.raises(ValueError, match="at most 1024"):
        estimator.estimate(image, np.repeat(box, 1024 // estimator.hypotheses + 1, axis=0), K=frame.K)
    empty = estimator.estimate(image, np.zeros((0, 4)), K=frame.K)
    assert empty.R.shape == (0, 3, 3) and empty.t.shape == (0, 3)


def test_constructor_and_pretrained_checks(estimator):
    with pytest.raises(ValueError, match="hypotheses"):
        PoseEstimator(estimator.coarse, estimator.points_m, hypotheses=0)
    with pytest.raises(ValueError, match="passes"):
        PoseEstimator(estimator.coarse, estimator.points_m, passes=0)
    with pytest.raises(ValueError, match="ranking"):
        PoseEstimator(estimator.coarse, estimator.points_m, ranking="best")
    with pytest.raises(ValueError, match=r"points_m must be \(P, 3\)"):
        PoseEstimator(estimator.coarse, np.zeros((5, 2)))
    with pytest.raises(TypeError, match="RefinerSession"):
        PoseEstimator("model.onnx", estimator.points_m)
    with pytest.raises(ValueError, match="no surface or extent points ship"):
        PoseEstimator.pretrained("999_unknown")


def test_exported_from_the_package():
    assert refiner_rt.PoseEstimator is PoseEstimator
    assert "PoseEstimator" in refiner_rt.__all__


def test_cli_help():
    result = CliRunner().invoke(main, ["estimate", "--help"])
    assert result.exit_code == 0, result.output
    assert "--box" in result.output and "--depth" in result.output
    assert "estimate" in CliRunner().invoke(main, ["--help"]).output


def test_cli_run_writes_json_and_overlay(tmp_path, sample):
    frame, image, objects = sample
    obj = objects["003_cracker_box"]
    out, overlay = tmp_path / "json" / "poses.json", tmp_path / "pictures" / "poses.png"  # folders made
    fx, fy, cx, cy = frame.K[0, 0], frame.K[1, 1], frame.K[0, 2], frame.K[1, 2]
    args = ["estimate", str(frame.path), "--K", f"{fx},{fy},{cx},{cy}", "--object", "003_cracker_box",
            "--box", ",".join(f"{v:g}" for v in obj.box_xyxy), "--out", str(out), "--overlay", str(overlay)]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    doc = json.loads(out.read_text())
    pose = doc["images"][0]["poses"][0]
    assert pose["object"] == "003_cracker_box" and len(pose["t_m"]) == 3 and 0 < pose["score"] <= 1
    assert rq.geodesic_angle(np.array(pose["q_wxyz"]), obj.q_gt) < 10.0
    np.testing.assert_allclose(rq.to_matrix(np.array(pose["q_wxyz"])), np.array(pose["R"]), atol=1e-4)
    assert cv2.imread(str(overlay)).shape == image.shape


def test_cli_errors_are_messages(tmp_path, sample):
    frame, _, _ = sample
    base = ["estimate", str(frame.path), "--K", "600,600,320,240"]
    r = CliRunner().invoke(main, [*base, "--object", "999_thing", "--box", "1,1,50,50"])
    assert r.exit_code == 2 and "no shipped model" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(main, [*base, "--object", "003_cracker_box"])
    assert r.exit_code == 2 and "--box" in r.output
    r = CliRunner().invoke(main, [*base, "--object", "003_cracker_box", "--box", "1,2,3"])
    assert r.exit_code == 2 and "x1,y1,x2,y2" in r.output
    bad = tmp_path / "d.npy"
    np.save(bad, np.zeros((4, 4), dtype=np.uint16))
    r = CliRunner().invoke(main, [*base, "--object", "003_cracker_box", "--box", "300,100,400,300", "--depth", str(bad)])
    assert r.exit_code == 2 and "colour image's size" in r.output
    assert (SAMPLES_DIR / frame.path.name).is_file()
