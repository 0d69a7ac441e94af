"""RefinerSession against closed-form test models (tests/onnx_fixtures.py) and SciPy's Rotation."""

import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from refiner_rt import RefinerSession
from refiner_rt import quaternion as rq
from refiner_rt.preprocess import crop_to_square, resize_crop, validate_boxes
from refiner_rt.geometry import MAX_VIEWS, VIEW_JITTER, ray_quaternion_rows, ray_quaternions, view_boxes
from tests import onnx_fixtures as fx

RNG = np.random.default_rng(0)
IMG = RNG.integers(0, 256, (48, 64, 3), dtype=np.uint8)
BOXES = np.array([[5.0, 6.0, 25.0, 30.0], [30.5, 10.0, 60.0, 40.0], [-4.0, 20.0, 10.0, 47.0]])


def scipy_q(q_wxyz):
    return Rotation.from_quat(rq.to_xyzw(q_wxyz))


def test_composition_is_q_in_times_q_out_checked_with_scipy():
    q_out = rq.from_axis_angle([0.2, -0.4, 0.9], 17.0)
    sess = RefinerSession(fx.constant_model(q_out))
    q_in = rq.from_xyzw(Rotation.random(3, random_state=1).as_quat())
    res = sess.refine(IMG, BOXES, q_in)
    ref = (scipy_q(q_in) * scipy_q(q_out)).as_matrix()
    np.testing.assert_allclose(rq.to_matrix(res.q_refined), ref, atol=1e-6)
    assert res.q_refined.dtype == np.float64 and res.q_refined.shape == (3, 4)
    assert np.all(res.q_refined[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(res.q_refined, axis=1), 1.0, atol=1e-12)


def test_iterations_apply_the_correction_k_times():
    q_out = rq.from_axis_angle([0, 0, 1], 10.0)
    sess = RefinerSession(fx.constant_model(q_out))
    res = sess.refine(IMG, BOXES[:1], rq.identity((1,)), iterations=3)
    np.testing.assert_allclose(rq.geodesic_angle(res.q_refined, rq.from_axis_angle([0, 0, 1], 30.0)), 0, atol=1e-4)


@pytest.mark.parametrize("views", [1, 3])
def test_settle_deg_keeps_a_later_pass_only_where_it_turns_by_more(views):
    """The echo model turns a rotation of angle a by a again (q -> q * q): from 1 degree a second pass turns by 2 and
    is not kept at settle_deg 5; from 10 degrees every pass turns by more and all are kept (SciPy's composition)."""
    sess = RefinerSession(fx.q_echo_model())
    axes = ([0.2, -0.4, 0.9], [1.0, 0.3, 0.0], [0.0, 1.0, 1.0])
    angles = [1.0, 10.0, 2.0]
    q_in = np.array([rq.from_axis_angle(a, d) for a, d in zip(axes, angles)])
    res = sess.refine(IMG, BOXES, q_in, iterations=3, views=views, settle_deg=5.0)
    kept = [1, 3, 1]  # passes kept: 1 -> 2 degrees (the next would turn by 2); 10 -> 20 -> 40 -> 80; 2 -> 4 (then 4)
    expect = [Rotation.from_rotvec(np.radians(d * 2 ** k) * np.array(a) / np.linalg.norm(a))
              for a, d, k in zip(axes, angles, kept)]
    got = [scipy_q(q) for q in res.q_refined]
    assert all((g * e.inv()).magnitude() < 1e-6 for g, e in zip(got, expect))
    # the 10-degree row went on every pass: as the plain iterations
    plain = sess.refine(IMG, BOXES, q_in, iterations=3, views=views)
    assert rq.geodesic_angle(plain.q_refined, res.q_refined)[1] < 1e-6  # the 10-degree row went on every pass


@pytest.mark.parametrize("value", [0, -1.0, float("nan"), float("inf"), 180.0, 181.0, 10**400, True, "2"])
def test_bad_settle_deg_is_named(value):
    sess = RefinerSession(fx.q_echo_model())
    with pytest.raises(ValueError, match=r"settle_deg must be a number of degrees in \(0, 180\)"):
        sess.refine(IMG, BOXES[:1], rq.identity((1,)), iterations=2, settle_deg=value)


def test_settle_deg_without_a_later_pass_is_refused():
    sess = RefinerSession(fx.q_echo_model())
    with pytest.raises(ValueError, match="give iterations=2 or more with it; got iterations=1"):
        sess.refine(IMG, BOXES[:1], rq.identity((1,)), settle_deg=2.0)


def test_view_boxes_are_the_box_then_fixed_small_jitters_of_it():
    views = view_boxes(BOXES, MAX_VIEWS, 1.2).reshape(len(BOXES), MAX_VIEWS, 4)
    np.testing.assert_array_equal(views[:, 0], BOXES)
    np.testing.assert_array_equal(view_boxes(BOXES, 3, 1.2).reshape(3, 3, 4), views[:, :3])  # a prefix, every call
    for box, v in zip(BOXES, views):
        size, centre = box[2:] - box[:2], 0.5 * (box[:2] + box[2:])
        window = 1.2 * size.max()
        shift = np.abs(0.5 * (v[:, :2] + v[:, 2:]) - centre) / window
        scale = (v[:, 2:] - v[:, :2]) / size
        assert shift.max() <= VIEW_JITTER + 1e-12 and np.abs(scale - 1).max() <= VIEW_JITTER + 1e-12
        np.testing.assert_allclose(scale[:, 0], scale[:, 1])  # the aspect ratio is kept
        assert len({tuple(np.round(b, 9)) for b in v}) == MAX_VIEWS  # all different
        assert shift[1:].max() > 0.6 * VIEW_JITTER  # and spread over the range, not bunched at the box


def test_views_average_the_corrections_of_the_jittered_crops():
    # The channel-mean model's correction depends on the crop, so each view gives its own; the result is their
    # chordal mean (SciPy's Rotation.mean), composed as q_in * q_out.
    sess = RefinerSession(fx.channel_mean_model(size=8))
    q_in = rq.from_xyzw(Rotation.random(3, random_state=4).as_quat())
    res = sess.refine(IMG, BOXES, q_in, views=5)
    per_view = sess.refine(IMG, view_boxes(BOXES, 5, 1.2), np.repeat(q_in, 5, axis=0)).q_out.reshape(3, 5, 4)
    assert rq.geodesic_angle(per_view[:, 0], per_view[:, 1]).max() > 0.1  # the views really differ
    for i in range(3):
        ref = rq.from_xyzw(scipy_q(per_view[i]).mean().as_quat())
        assert rq.geodesic_angle(res.q_out[i], ref) < 1e-4
    np.testing.assert_allclose(rq.geodesic_angle(res.q_refined, rq.multiply(q_in, res.q_out)), 0, atol=1e-6)
    assert sess.refine(IMG, np.zeros((0, 4)), np.zeros((0, 4)), views=3).q_refined.shape == (0, 4)
    # views=1 is the plain refine.
    np.testing.assert_array_equal(sess.refine(IMG, BOXES, q_in, views=1).q_out, sess.refine(IMG, BOXES, q_in).q_out)


def test_views_keep_the_ray_frame_and_iterations():
    K = np.array([[500.0, 0, 31.5], [0, 500.0, 23.5], [0, 0, 1]])
    sess = RefinerSession(fx.q_echo_model(props=fx.contract(rotation_frame="ray")))
    q_in = rq.from_xyzw(Rotation.random(3, random_state=2).as_quat())
    # Every view of a box gets the rotation in the frame of the box's own ray (the training's box jitter keeps the
    # label): the echo model returns it from each view, so the average is exactly that.
    res = sess.refine(IMG, BOXES, q_in, K=K, views=4)
    np.testing.assert_allclose(rq.geodesic_angle(res.q_out, sess.refine(IMG, BOXES, q_in, K=K).q_out), 0, atol=1e-4)
    q_out = rq.from_axis_angle([0, 0, 1], 10.0)
    const = RefinerSession(fx.constant_model(q_out))
    res = const.refine(IMG, BOXES[:1], rq.identity((1,)), iterations=3, views=3)
    np.testing.assert_allclose(rq.geodesic_angle(res.q_refined, rq.from_axis_angle([0, 0, 1], 30.0)), 0, atol=1e-4)


def test_crops_follow_the_crop_rule_and_channel_order():
    sess = RefinerSession(fx.channel_mean_model(size=8))
    res = sess.refine(IMG, BOXES, rq.identity((3,)))
    for i, box in enumerate(BOXES):
        crop = crop_to_square(IMG, box, 8, 1.2).astype(np.float64)
        m = crop.mean(axis=(0, 1)) / 255.0
        ref = np.concatenate([[1.0], m]) / np.linalg.norm(np.concatenate([[1.0], m]))
        np.testing.assert_allclose(res.q_out[i], ref, atol=1e-5)
    # An RGB model gets the channels reversed by the runtime.
    rgb = RefinerSession(fx.channel_mean_model(size=8, props=fx.contract(channel_order="RGB")))
    res_rgb = rgb.refine(IMG, BOXES, rq.identity((3,)))
    np.testing.assert_allclose(res_rgb.q_out[:, 1:], res.q_out[:, [3, 2, 1]], atol=1e-6)


def test_refine_crops_matches_refine_on_cut_out_windows():
    sess = RefinerSession(fx.channel_mean_model(size=8))
    crop16 = crop_to_square(IMG, BOXES[0], 16, 1.2)
    res = sess.refine_crops([crop16, crop_to_square(IMG, BOXES[0], 8, 1.2)], rq.identity((2,)))
    ref = sess.refine_crops(resize_crop(crop16, 8)[None], rq.identity((1,)))
    np.testing.assert_allclose(res.q_out[0], ref.q_out[0], atol=1e-6)
    assert res.q_refined.shape == (2, 4)


def test_ray_frame_model_gets_q_in_relative_to_the_viewing_ray():
    K = np.array([[500.0, 0, 31.5], [0, 500.0, 23.5], [0, 0, 1]])
    sess = RefinerSession(fx.q_echo_model(props=fx.contract(rotation_frame="ray")))
    q_in = rq.from_xyzw(Rotation.random(3, random_state=2).as_quat())
    res = sess.refine(IMG, BOXES, q_in, K=K)
    q_ray = ray_quaternions(K, BOXES)
    # the echo model returns what it was given: q_ray^-1 * q_in
    np.testing.assert_allclose(rq.geodesic_angle(res.q_out, rq.multiply(rq.inverse(q_ray), q_in)), 0, atol=1e-4)
    # and the refined rotation is still q_in * q_out
    np.testing.assert_allclose(rq.geodesic_angle(res.q_refined, rq.multiply(q_in, res.q_out)), 0, atol=1e-6)
    with pytest.raises(ValueError, match="K is required"):
        sess.refine(IMG, BOXES, q_in)


def test_ray_quaternion_points_the_optical_axis_along_the_ray():
    K = np.array([[600.0, 0, 320], [0, 610.0, 240], [0, 0, 1]])
    boxes = np.array([[0.0, 0, 40, 40], [300.5, 220.5, 340.5, 260.5], [600, 400, 640, 480]])
    q = ray_quaternions(K, boxes)
    centres = np.stack([(boxes[:, 0] + boxes[:, 2]) / 2 - 0.5, (boxes[:, 1] + boxes[:, 3]) / 2 - 0.5, np.ones(3)], 1)
    d = centres @ np.linalg.inv(K).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(rq.to_matrix(q) @ [0, 0, 1], d, atol=1e-12)
    np.testing.assert_allclose(rq.geodesic_angle(q[1], rq.identity()), 0.0, atol=1e-9)  # central box: no rotation


def test_ray_quaternions_of_any_intrinsics_form_agree_and_the_float_path_matches_bit_for_bit():
    rng = np.random.default_rng(11)
    boxes = np.sort(rng.uniform(-50, 700, (20, 2, 2)), axis=1).transpose(0, 2, 1).reshape(20, 4)[:, [0, 2, 1, 3]]
    K = np.array([[612.3, 1.7, 318.9], [0, 605.1, 243.2], [0, 0, 1]])  # with skew
    q = ray_quaternions(K, boxes)
    centres = np.stack([(boxes[:, 0] + boxes[:, 2]) / 2 - 0.5, (boxes[:, 1] + boxes[:, 3]) / 2 - 0.5, np.ones(20)], 1)
    d = centres @ np.linalg.inv(K).T
    np.testing.assert_allclose(rq.to_matrix(q) @ [0, 0, 1], d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-12)
    # a scaled K (not in pinhole form: K[2, 2] != 1) takes the general path and gives the same rays
    np.testing.assert_allclose(rq.geodesic_angle(ray_quaternions(3.0 * K, boxes), q), 0, atol=1e-9)
    # one K per box
    np.testing.assert_array_equal(ray_quaternions(np.stack([K] * 20), boxes), q)
    # the Python-float twin used by refine() for small batches
    np.testing.assert_array_equal(np.array(ray_quaternion_rows(K, boxes.tolist())), q)


def test_non_unit_q_in_is_normalised():
    sess = RefinerSession(fx.constant_model([1, 0, 0, 0]))
    res = sess.refine(IMG, BOXES[:1], [[2.0, 0, 0, 0]])
    np.testing.assert_allclose(res.q_refined, [[1, 0, 0, 0]])


def test_empty_batch_returns_empty_result():
    sess = RefinerSession(fx.constant_model([1, 0, 0, 0]))
    res = sess.refine(IMG, np.zeros((0, 4)), np.zeros((0, 4)))
    assert res.q_refined.shape == (0, 4) and len(res) == 0


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(image_bgr=IMG.astype(np.float32)), "image_bgr must have dtype uint8"),
        (dict(image_bgr=IMG[..., :2]), r"image_bgr must have shape \(H, W, 3\)"),
        (dict(boxes_xyxy=np.zeros((3, 5))), r"boxes_xyxy must have shape \(N, 4\)"),
        (dict(boxes_xyxy=[[5, 5, 5, 9]] * 3), r"boxes_xyxy\[0\] is empty"),
        (dict(boxes_xyxy=[[100, 100, 120, 120]] * 3), "outside the 64x48 image"),
        (dict(q_in_wxyz=np.ones((2, 4))), "q_in_wxyz has 2 rotations but boxes_xyxy has 3"),
        (dict(q_in_wxyz=np.zeros((3, 4))), "zero quaternion"),
        (dict(q_in_wxyz=np.full((3, 4), np.nan)), "finite"),
        (dict(q_in_wxyz=np.ones((3, 3))), r"q_in_wxyz has shape \(3, 3\): one rotation matrix.*R\[None\].*"
                                          r"quaternion\.from_matrix\(R\)"),
        (dict(boxes_xyxy=[[0.1, 0.2, 0.4, 0.6]] * 3), r"boxes_xyxy look normalised to 0\.\.1 .* the image is 64x48 "
                                                      r"pixels.*scale them by \(W, H, W, H\) = \(64, 48, 64, 48\)"),
        (dict(boxes_xyxy=[[5, 6, 25, 30], [10, 10, 11.5, 30], [5, 6, 25, 30]]),
         r"boxes_xyxy\[1\] is 1\.5 x 20 pixels: expected at least 2 x 2"),
        (dict(boxes_xyxy=[[5, 6, 25, 30], [5, 6, 25, 30], [50, 30, 90, 70]]),
         r"boxes_xyxy\[2\] lies mostly outside the 64x48 image: 15\.8% of its area is inside, expected at least 25%"),
        (dict(iterations=0), "iterations must be an integer from 1 to 16"),
        (dict(views=0), "views must be an integer from 1 to 16"),
        (dict(views=17), "views must be an integer from 1 to 16"),
        (dict(views=2.0), "views must be an integer from 1 to 16"),
        (dict(views=True), "views must be an integer from 1 to 16"),
        (dict(K=np.eye(2)), r"K must be a \(3, 3\)"),
        (dict(K=np.diag([500.0, 500.0, np.inf])), "K must be finite"),
        (dict(K=np.diag([-500.0, 500.0, 1.0])), "fx > 0 and fy > 0"),
        (dict(K=np.diag([500, 0, 1])), "fx > 0 and fy > 0"),
    ],
)
def test_bad_inputs_raise_clear_errors(kwargs, match):
    sess = RefinerSession(fx.constant_model([1, 0, 0, 0]))
    args = dict(image_bgr=IMG, boxes_xyxy=BOXES, q_in_wxyz=rq.identity((3,)))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        sess.refine(**args)


def test_model_without_contract_is_refused(tmp_path):
    with pytest.raises(ValueError, match="missing required key"):
        RefinerSession(fx.constant_model([1, 0, 0, 0], props={}))
    p = fx.contract()
    p["rotation_frame"] = "world"
    with pytest.raises(ValueError, match="'rotation_frame'"):
        RefinerSession(fx.constant_model([1, 0, 0, 0], props=p))
    with pytest.raises(ValueError, match="input_size=16 expects"):
        RefinerSession(fx.constant_model([1, 0, 0, 0], size=8, props=fx.contract(input_size=16)))
    with pytest.raises(FileNotFoundError):
        RefinerSession(tmp_path / "missing.onnx")
    with pytest.raises(ModelError, match="model file not found: .*missing.onnx"):  # the README's promise
        RefinerSession(tmp_path / "missing.onnx")
    with pytest.raises(ValueError, match="provider 'NoSuchProvider'"):
        RefinerSession(fx.constant_model([1, 0, 0, 0]), providers=["NoSuchProvider"])
    with pytest.raises(ValueError, match="threads"):
        RefinerSession(fx.constant_model([1, 0, 0, 0]), threads=-1)


def test_loads_from_path_and_reports_metadata(tmp_path):
    path = tmp_path / "m.onnx"
    path.write_bytes(fx.constant_model([1, 0, 0, 0]))
    sess = RefinerSession(path, threads=1)
    assert sess.metadata["arch"] == "test" and sess.metadata["quaternion_order"] == "wxyz"
    assert sess.input_size == 8 and "CPUExecutionProvider" in sess.providers
    assert "m.onnx" in repr(sess)


def test_importing_runtime_does_not_import_torch():
    code = "import sys, refiner_rt; from refiner_rt import RefinerSession, quaternion, cli, bench; from refiner_rt.cli import info; assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


# ---------------------------------------------------------------- lean refine() path
import onnxruntime as ort  # noqa: E402
from onnx import TensorProto, helper  # noqa: E402

import refiner_rt.checks as checks_module  # noqa: E402
import refiner_rt.session as session_module  # noqa: E402
from refiner_rt.metadata import INPUT_IMAGE, INPUT_QUATERNION, OUTPUT_QUATERNION  # noqa: E402


def mix_model(size: int = 8, props=None) -> bytes:
    """``q_out = normalize(q_in + 0.5 * (0, m_0, m_1, m_2))``, ``m_c`` the mean of input channel ``c`` / 255.

    Depends on the crop's pixels, their channel order and on ``q_in``, so any difference between two refine()
    implementations in cropping, channel handling, frames or composition shows in the output.
    """
    inits = [
        helper.make_tensor("axes", TensorProto.INT64, [2], [1, 2]),
        helper.make_tensor("scale", TensorProto.FLOAT, [1], [0.5 / 255.0]),
        helper.make_tensor("pads", TensorProto.INT64, [4], [0, 1, 0, 0]),
        helper.make_tensor("last", TensorProto.INT64, [1], [1]),
    ]
    nodes = [
        helper.make_node("Cast", [INPUT_IMAGE], ["imgf"], to=TensorProto.FLOAT),
        helper.make_node("ReduceMean", ["imgf", "axes"], ["means"], keepdims=0),
        helper.make_node("Mul", ["means", "scale"], ["m"]),
        helper.make_node("Pad", ["m", "pads"], ["m4"]),
        helper.make_node("Add", [INPUT_QUATERNION, "m4"], ["q"]),
        helper.make_node("ReduceL2", ["q", "last"], ["n"], keepdims=1),
        helper.make_node("Div", ["q", "n"], [OUTPUT_QUATERNION]),
    ]
    return fx._model(nodes, inits, size, fx.contract(input_size=size) if props is None else props)


def reference_refine(model: bytes, image, boxes, q_in, iterations=1, K=None, size=8, context=1.2, rgb=False, ray=False):
    """The straightforward refine(): crop_to_square per box, session.run, rq.multiply; float64 numpy throughout."""
    sess = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    boxes = np.asarray(boxes, dtype=np.float64)
    crops = np.stack([crop_to_square(image, b, size, context) for b in boxes])
    if rgb:
        crops = np.ascontiguousarray(crops[..., ::-1])
    q_in = rq.normalize(np.asarray(q_in, dtype=np.float64))
    q_frame = ray_quaternions(K, boxes) if ray else None
    q = q_in
    for _ in range(iterations):
        q_net = q if q_frame is None else rq.multiply(rq.inverse(q_frame), q)
        out = sess.run([OUTPUT_QUATERNION], {INPUT_IMAGE: crops, INPUT_QUATERNION: q_net.astype(np.float32)})[0]
        q_out = rq.normalize(out.astype(np.float64))
        q = rq.normalize(rq.multiply(q, q_out))
    return q, q_out, q_in


K_TEST = np.array([[500.0, 0, 31.5], [0, 500.0, 23.5], [0, 0, 1]])


@pytest.mark.parametrize("n", [1, 3, session_module.SMALL_BATCH, session_module.SMALL_BATCH + 7])
@pytest.mark.parametrize("frame,order", [("camera", "BGR"), ("ray", "BGR"), ("camera", "RGB")])
@pytest.mark.parametrize("iterations", [1, 3])
def test_lean_refine_is_bit_identical_to_the_reference(n, frame, order, iterations):
    rng = np.random.default_rng(n)
    side = rng.uniform(6, 30, n)
    cx, cy = rng.uniform(4, 60, n), rng.uniform(6, 42, n)  # at least a quarter of each box inside
    boxes = np.stack([cx - side / 2, cy - side / 2, cx + side / 2, cy + side * 0.3], axis=1)
    q_in = rng.standard_normal((n, 4)) * 3  # non-unit: normalised by both
    model = mix_model(props=fx.contract(rotation_frame=frame, channel_order=order))
    K = K_TEST if frame == "ray" else None
    res = RefinerSession(model).refine(IMG, boxes, q_in, iterations=iterations, K=K)
    ref = reference_refine(model, IMG, boxes, q_in, iterations, K, rgb=order == "RGB", ray=frame == "ray")
    for got, want in zip((res.q_refined, res.q_out, res.q_in), ref):
        assert got.dtype == np.float64 and got.shape == (n, 4)
        np.testing.assert_array_equal(got, want)


def test_python_float_and_numpy_paths_agree_exactly(monkeypatch):
    rng = np.random.default_rng(5)
    q_in = rng.standard_normal((3, 4))
    q_in[1] = [0.0, -0.5, 0.5, 0.5]  # w == 0: the sign key falls through to x
    q_in[2, 0] = -2.0  # flipped to w >= 0
    sess = RefinerSession(mix_model())
    small = sess.refine(IMG, BOXES, q_in, iterations=2)
    monkeypatch.setattr(session_module, "SMALL_BATCH", 0)  # the quaternion rows
    monkeypatch.setattr(checks_module, "SMALL_BATCH", 0)  # the box rows
    vectorised = sess.refine(IMG, BOXES, q_in, iterations=2)
    for a, b in zip((small.q_refined, small.q_out, small.q_in), (vectorised.q_refined, vectorised.q_out, vectorised.q_in)):
        np.testing.assert_array_equal(a, b)
    assert np.all(small.q_in[:, 0] >= 0) and small.q_in[1, 1] > 0


def test_results_do_not_alias_the_reused_buffers():
    sess = RefinerSession(mix_model())
    first = sess.refine(IMG, BOXES, rq.identity((3,)))
    kept = [a.copy() for a in (first.q_refined, first.q_out, first.q_in)]
    sess.refine(255 - IMG, BOXES, rq.from_axis_angle([1, 0, 0], [10.0, 20.0, 30.0]))
    for a, b in zip((first.q_refined, first.q_out, first.q_in), kept):
        np.testing.assert_array_equal(a, b)
    crops = sess.refine_crops(np.stack([crop_to_square(IMG, b, 8, 1.2) for b in BOXES]), rq.identity((3,)))
    np.testing.assert_array_equal(crops.q_out, first.q_out)


def test_lean_path_accepts_lists_and_other_numeric_dtypes():
    sess = RefinerSession(mix_model())
    ref = sess.refine(IMG, BOXES, np.array([[1.0, 0, 0, 0]] * 3))
    for boxes, q in [
        (BOXES.tolist(), [[1, 0, 0, 0]] * 3),
        (BOXES.astype(np.float32).astype(np.float64), np.array([[2, 0, 0, 0]] * 3, dtype=np.int32)),
        (BOXES, np.array([[1, 0, 0, 0]] * 3, dtype=np.float32)),
    ]:
        res = sess.refine(IMG, boxes, q, iterations=np.int64(1))
        np.testing.assert_array_equal(res.q_refined, ref.q_refined)
    np.testing.assert_array_equal(sess.refine(IMG, BOXES[0], [1, 0, 0, 0]).q_refined, ref.q_refined[:1])


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(boxes_xyxy=[[5, 6, np.inf, 30]] * 3), r"boxes_xyxy\[0\] must be finite"),
        (dict(boxes_xyxy=[[5, 6, 25, 30], [5, 6, 25, np.nan], [5, 6, 25, 30]]), r"boxes_xyxy\[1\] must be finite"),
        (dict(boxes_xyxy=[[5, 6, 25, 30], [5, 6, 25, 30], [64, 6, 70, 30]]), r"boxes_xyxy\[2\] lies entirely outside"),
        (dict(q_in_wxyz=[[1, 0, 0, 0], [1, 0, 0, np.inf], [1, 0, 0, 0]]), "finite"),
        (dict(q_in_wxyz=[[1, 0, 0, 0], [0, 0, 0, 1e-13], [1, 0, 0, 0]]), "zero quaternion"),
        (dict(q_in_wxyz=np.array([[True, False, False, False]] * 3)), "numeric"),
        (dict(iterations=1.0), "iterations must be an integer from 1 to 16"),
        (dict(iterations=True), "iterations must be an integer from 1 to 16"),
    ],
)
def test_fast_paths_fall_back_to_the_detailed_errors(kwargs, match):
    sess = RefinerSession(fx.constant_model([1, 0, 0, 0]))
    args = dict(image_bgr=IMG, boxes_xyxy=BOXES, q_in_wxyz=rq.identity((3,)))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        sess.refine(**args)


def test_non_finite_model_output_is_an_error():
    sess = RefinerSession(fx.constant_model([float("nan"), 0, 0, 0]))
    with pytest.raises(ValueError, match="finite"):
        sess.refine(IMG, BOXES, rq.identity((3,)))


def _os_threads() -> int:
    return len(os.listdir("/proc/self/task"))


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="counts OS threads through /proc (Linux)")
def test_threads_does_what_it_says():
    model = fx.constant_model([1, 0, 0, 0])
    before = _os_threads()
    one = RefinerSession(model, threads=1)
    assert one.threads == 1 and _os_threads() == before  # 1 thread: no onnxruntime pool, calls run on the caller
    assert one._session.get_session_options().intra_op_num_threads == 1
    two = RefinerSession(model, threads=2)
    assert two.threads == 2 and _os_threads() == before + 1  # the caller plus one pool thread
    every = RefinerSession(model, threads=0)
    assert every.threads == session_module.available_cores() == len(os.sched_getaffinity(0))
    assert every._session.get_session_options().intra_op_num_threads == every.threads
    assert "threads=" in repr(every)
    options = ort.SessionOptions()
    options.intra_op_num_threads = 3
    assert RefinerSession(model, threads=1, session_options=options).threads == 3
    del one, two, every


# ---------------------------------------------------------------- one session shared by many threads
import threading  # noqa: E402


def _thread_calls(count: int, seed: int, ray: bool) -> list[tuple]:
    """``count`` distinct calls: mostly batch 1 (the fast path), some 3 boxes with 2 iterations, 37 boxes (the
    numpy path), 3 views, and refine_crops on crops of other sizes; each with its own image, boxes and rotations."""
    rng = np.random.default_rng(seed)
    K = K_TEST if ray else None
    calls = []
    for i in range(count):
        image = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
        kind = i % 10
        n = {7: 3, 8: session_module.SMALL_BATCH + 5}.get(kind, 1 if kind != 9 else 2)
        side = rng.uniform(6, 30, n)
        cx, cy = rng.uniform(4, 60, n), rng.uniform(6, 42, n)  # at least a quarter of each box inside
        boxes = np.stack([cx - side / 2, cy - side / 2, cx + side / 2, cy + side * 0.4], axis=1)
        q_in = rng.standard_normal((n, 4))
        if kind == 9:
            crops = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for h, w in rng.integers(4, 20, (n, 2))]
            calls.append(("refine_crops", (crops, q_in), {}))
        elif kind == 6:
            calls.append(("refine", (image, boxes, q_in), dict(K=K, views=3)))
        else:
            calls.append(("refine", (image, boxes, q_in), dict(K=K, iterations=2 if kind == 7 else 1)))
    return calls


@pytest.mark.parametrize("frame,order", [("camera", "BGR"), ("ray", "RGB")])
def test_one_session_shared_by_8_threads_gives_the_serial_results_bit_for_bit(frame, order):
    sess = RefinerSession(fx.random_weight_model(size=16, props=fx.contract(input_size=16, rotation_frame=frame,
                                                                                channel_order=order)))
    calls = _thread_calls(400, seed=3, ray=frame == "ray")
    serial = [getattr(sess, name)(*args, **kwargs) for name, args, kwargs in calls]
    threads, results, errors = 8, [None] * len(calls), []
    start = threading.Barrier(threads)

    def worker(t):
        try:
            start.wait()
            for _ in range(2):  # twice: the second round runs on buffers grown by the first
                for i in range(t, len(calls), threads):
                    name, args, kwargs = calls[i]
                    results[i] = getattr(sess, name)(*args, **kwargs)
        except Exception as exc:  # surfaced below, with the thread's traceback kept in the exception
            errors.append(exc)

    pool = [threading.Thread(target=worker, args=(t,)) for t in range(threads)]
    for th in pool:
        th.start()
    for th in pool:
        th.join()
    assert not errors, errors[0]
    for i, (got, want) in enumerate(zip(results, serial)):
        for a, b in zip((got.q_refined, got.q_out, got.q_in), (want.q_refined, want.q_out, want.q_in)):
            np.testing.assert_array_equal(a, b, err_msg=f"call {i}: {calls[i][0]} {calls[i][2]}")


# ---------------------------------------------------------------- models that cannot be used: one error type
from refiner_rt import ModelError  # noqa: E402

U8, F32, F64 = TensorProto.UINT8, TensorProto.FLOAT, TensorProto.DOUBLE


def _regroup(width: int) -> list:
    """Nodes ``q_out = reshape(reshape(q_in, (-1, width)), (-1, 4))``: shape inference cannot see that this fails
    unless ``4 * batch`` is a multiple of ``width`` (needs the initializers ``w{width}`` and ``w4``)."""
    return [helper.make_node("Reshape", [INPUT_QUATERNION, f"w{width}"], ["grouped"]),
            helper.make_node("Reshape", ["grouped", "w4"], [OUTPUT_QUATERNION])]


def _shape_inits() -> list:
    return [helper.make_tensor("one_row", TensorProto.INT64, [2], [1, 4])] + [
        helper.make_tensor(n, TensorProto.INT64, [1], [v]) for n, v in (("s0", 0), ("s3", 3), ("s1", 1))] + [
        helper.make_tensor(f"w{w}", TensorProto.INT64, [2], [-1, w]) for w in (4, 8, 12)]
IMAGE_IN = (INPUT_IMAGE, U8, ["batch", 8, 8, 3])
Q_IN = (INPUT_QUATERNION, F32, ["batch", 4])
Q_OUT = (OUTPUT_QUATERNION, F32, ["batch", 4])
ECHO = [helper.make_node("Identity", [INPUT_QUATERNION], [OUTPUT_QUATERNION])]


def _bad_bytes() -> dict[str, bytes]:
    rng = np.random.default_rng(39)
    good = fx.constant_model([1, 0, 0, 0])
    return {
        "empty": b"",
        "random": rng.integers(0, 256, 4096, dtype=np.uint8).tobytes(),
        "truncated": good[: len(good) // 2],
        "text": b"this is not an onnx model\n" * 10,
        "one byte": b"\x08",
    }


@pytest.mark.parametrize("kind", list(_bad_bytes()))
@pytest.mark.parametrize("as_file", [False, True])
def test_unreadable_models_raise_model_error_naming_the_file(kind, as_file, tmp_path):
    data = _bad_bytes()[kind]
    source = data
    if as_file:
        source = tmp_path / f"{kind.replace(' ', '_')}.onnx"
        source.write_bytes(data)
    with pytest.raises(ModelError) as info:
        RefinerSession(source)
    assert type(info.value) is ModelError and isinstance(info.value, ValueError)
    assert str(source if as_file else "<model bytes>") in str(info.value)
    assert "\n" not in str(info.value)


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads files whatever their mode")
def test_a_model_file_without_read_permission_is_a_model_error(tmp_path):
    path = tmp_path / "m.onnx"
    path.write_bytes(fx.constant_model([1, 0, 0, 0]))
    path.chmod(0)
    with pytest.raises(ModelError, match="cannot read"):
        RefinerSession(path)


@pytest.mark.parametrize(
    "nodes,inputs,outputs,match",
    [
        (ECHO, [(INPUT_IMAGE, U8, ["batch", 8, 8, 4]), Q_IN], [Q_OUT], r"'image' must have shape \(batch, 8, 8, 3\)"),
        (ECHO, [(INPUT_IMAGE, F32, ["batch", 8, 8, 3]), Q_IN], [Q_OUT], r"'image' must be tensor\(uint8\)"),
        (ECHO, [(INPUT_IMAGE, U8, [1, 8, 8, 3]), (INPUT_QUATERNION, F32, [1, 4])],
         [(OUTPUT_QUATERNION, F32, [1, 4])], "'image' must have a dynamic batch axis"),
        ([helper.make_node("Identity", [INPUT_QUATERNION], [OUTPUT_QUATERNION])], [IMAGE_IN, (INPUT_QUATERNION, F32,
         ["batch", 3])], [(OUTPUT_QUATERNION, F32, ["batch", 3])], r"'q_in' must have shape \(batch, 4\)"),
        (ECHO, [IMAGE_IN, (INPUT_QUATERNION, F64, ["batch", 4])], [(OUTPUT_QUATERNION, F64, ["batch", 4])],
         r"'q_in' must be tensor\(float\)"),
        ([helper.make_node("Slice", [INPUT_QUATERNION, "s0", "s3", "s1"], [OUTPUT_QUATERNION])], [IMAGE_IN, Q_IN],
         [(OUTPUT_QUATERNION, F32, ["batch", 3])], r"'q_out' must have shape \(batch, 4\)"),
        (ECHO, [IMAGE_IN, Q_IN, ("mask", U8, ["batch", 8, 8])], [Q_OUT], r"inputs \['mask'\]"),
        ([helper.make_node("Identity", [INPUT_QUATERNION], ["out"])], [IMAGE_IN, Q_IN],
         [("out", F32, ["batch", 4])], r"lacks \['q_out'\]"),
        # a batch axis fixed inside the graph: onnxruntime's shape inference shows it
        ([helper.make_node("Reshape", [INPUT_QUATERNION, "one_row"], [OUTPUT_QUATERNION])], [IMAGE_IN, Q_IN],
         [Q_OUT], "'q_out' must have a dynamic batch axis"),
        # a graph that only works for batches of 3, 6, ...: the trial run on two crops finds it
        (_regroup(12), [IMAGE_IN, Q_IN], [Q_OUT], "fails on a trial batch of 2 black 8x8 crops"),
        # declared (batch, 4) but gives three components
        ([helper.make_node("Slice", [INPUT_QUATERNION, "s0", "s3", "s1"], [OUTPUT_QUATERNION])], [IMAGE_IN, Q_IN],
         [Q_OUT], r"must be \(batch, 4\) float32; a trial batch of 2 gave shape \(2, 3\)"),
    ],
)
def test_contract_breaking_graphs_are_refused_on_load_naming_the_input_or_output(nodes, inputs, outputs, match):
    with pytest.raises(ModelError, match=match) as info:
        RefinerSession(fx.graph_model(nodes, inputs, outputs, _shape_inits()))
    assert type(info.value) is ModelError


@pytest.mark.parametrize("key,value", [("crop_context", "inf"), ("crop_context", "1e308"), ("input_size", "0"),
                                       ("quaternion_order", "xyzw")])
def test_metadata_out_of_range_is_refused_on_load(key, value):
    props = fx.contract()
    props[key] = value
    with pytest.raises(ModelError, match=f"'{key}'"):
        RefinerSession(fx.constant_model([1, 0, 0, 0], props=props))


def test_a_network_that_fails_at_run_time_raises_model_error_not_an_onnxruntime_type():
    # works for even batches only: it passes the trial run on two crops and fails on one or three
    sess = RefinerSession(fx.graph_model(_regroup(8), [IMAGE_IN, Q_IN], [Q_OUT], _shape_inits()))
    sess.refine(IMG, BOXES[:2], rq.identity((2,)))
    with pytest.raises(ModelError, match="the network failed on a batch of 3") as info:
        sess.refine(IMG, BOXES, rq.identity((3,)))
    assert type(info.value) is ModelError
    nan = RefinerSession(fx.constant_model([float("nan"), 0, 0, 0]))
    for n in (1, 40):  # the Python-float path and the numpy path
        with pytest.raises(ModelError, match=r"returned q_out\[0\] = \[nan, 0.0, 0.0, 0.0\]"):
            nan.refine(IMG, np.tile(BOXES[:1], (n, 1)), rq.identity((n,)))
    with pytest.raises(ModelError, match="q_out"):
        RefinerSession(fx.constant_model([0, 0, 0, 0])).refine(IMG, BOXES, rq.identity((3,)), views=2)


# ---------------------------------------------------------------- every bad input named, every result finite
@pytest.mark.parametrize("n,views", [(3, 1), (40, 1), (3, 2)])  # the Python-float path, the numpy path, views
def test_huge_finite_q_in_gives_the_rotation_of_its_direction(n, views):
    sess = RefinerSession(mix_model())
    rng = np.random.default_rng(n)
    direction = rng.standard_normal((n, 4))
    boxes = np.tile(BOXES[:1], (n, 1))
    ref = sess.refine(IMG, boxes, direction, views=views)
    for scale in (1e154, 1e200, 1e308 / 4):
        res = sess.refine(IMG, boxes, direction * scale, views=views)
        assert np.isfinite(res.q_refined).all() and res.q_refined.dtype == np.float64
        np.testing.assert_allclose(np.linalg.norm(res.q_refined, axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(res.q_refined, ref.q_refined, atol=1e-6)


K_RAY = K_TEST


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(boxes_xyxy=[[5, 6, 25, 30], [30.5, 10, 60], [-4, 20, 10, 47]]), r"boxes_xyxy must be numeric.*ragged"),
        (dict(boxes_xyxy=[["a", "b", "c", "d"]] * 3), "boxes_xyxy must be numeric"),
        (dict(boxes_xyxy=[[5, 6, 25, 2e6]] * 3), r"boxes_xyxy\[0\] must have coordinates within \+-1e\+06"),
        (dict(boxes_xyxy=[[-1e300, 6, 25, 30]] * 3), r"boxes_xyxy\[0\] must have coordinates within"),
        (dict(q_in_wxyz=[[1, 0, 0, 0], [1, 0, 0], [1, 0, 0, 0]]), r"q_in_wxyz must be .*ragged"),
        (dict(q_in_wxyz=np.array([[1, 0, 0, 0]] * 3, dtype=object)), "q_in_wxyz must be a numeric"),
        (dict(q_in_wxyz=[[1, 0, 0, 0]] * 3 + [[1, 0, 0, 0]]), "q_in_wxyz has 4 rotations but boxes_xyxy has 3"),
        (dict(q_in_wxyz=np.full((3, 4), 1e-200)), "zero quaternion"),
        (dict(iterations=17), "iterations must be an integer from 1 to 16"),
        (dict(iterations=10**9), "iterations must be an integer from 1 to 16"),
        (dict(iterations=np.int64(-1)), "iterations must be an integer from 1 to 16"),
        (dict(K=[[500, 0, 31.5], [0, 500, 23.5], [0, 0]]), r"K must be a \(3, 3\).*ragged"),
        (dict(K=np.zeros((3, 3))), "K must have focal lengths fx > 0 and fy > 0"),
        (dict(K=[[500, 0, 31.5], [0, 500, 23.5], [0, 0, 0]]), "K must have the pinhole form"),
        (dict(K=[[500, 0, 31.5], [0, 500, 23.5], [0, 0, 3]]), "K must have the pinhole form"),
        (dict(K=[[500, 0, 31.5], [7, 500, 23.5], [0, 0, 1]]), "K must have the pinhole form"),
        (dict(K=np.diag([1e-300, 500, 1])), r"K must have fx, fy in \[0.001, 1e\+09\]"),
        (dict(K=[[500, 0, 1e300], [0, 500, 23.5], [0, 0, 1]]), r"\|cx\|, \|cy\| <= 1e\+09"),
        (dict(K=[["500", 0, 1], [0, 500, 1], [0, 0, 1]]), r"K must be a \(3, 3\) numeric"),
        (dict(image_bgr=IMG.tolist()), "image_bgr must be a numpy array"),
        (dict(image_bgr=np.zeros((0, 5, 3), np.uint8)), "image_bgr must not be empty"),
    ],
)
def test_more_bad_inputs_are_named_with_expected_and_got(kwargs, match):
    sess = RefinerSession(fx.q_echo_model(props=fx.contract(rotation_frame="ray")))
    args = dict(image_bgr=IMG, boxes_xyxy=BOXES, q_in_wxyz=rq.identity((3,)), K=K_RAY)
    args.update(kwargs)
    with pytest.raises((ValueError, TypeError), match=match) as info:
        sess.refine(**args)
    assert not isinstance(info.value, ModelError)


def test_limits_are_documented_constants_and_hold_at_their_edge():
    sess = RefinerSession(fx.constant_model([1, 0, 0, 0]))
    one = BOXES[:1]
    assert sess.refine(IMG, one, rq.identity((1,)), iterations=session_module.MAX_ITERATIONS).q_refined.shape == (1, 4)
    edge = session_module.MAX_BATCH
    boxes = np.tile(one, (edge, 1))
    assert len(sess.refine(IMG, boxes, rq.identity((edge,)))) == edge
    with pytest.raises(ValueError, match=f"boxes_xyxy has {edge + 1} entries: at most MAX_BATCH={edge}"):
        sess.refine(IMG, np.tile(one, (edge + 1, 1)), rq.identity((edge + 1,)))
    half = edge // 2 + 1
    with pytest.raises(ValueError, match=f"boxes_xyxy has {half} entries x views=2 = {2 * half} crops"):
        sess.refine(IMG, np.tile(one, (half, 1)), rq.identity((half,)), views=2)
    crops = np.zeros((edge + 1, 8, 8, 3), np.uint8)
    with pytest.raises(ValueError, match=f"crops_bgr has {edge + 1} entries"):
        sess.refine_crops(crops, rq.identity((edge + 1,)))
    with pytest.raises(ValueError, match="iterations must be an integer from 1 to 16"):
        sess.refine_crops(crops[:1], rq.identity((1,)), iterations=17)
    # the widest boxes and K the limits allow still give finite unit viewing-ray rotations, and refine() does with
    # the widest box the image allows (a quarter of it inside) and that K
    ray = RefinerSession(fx.q_echo_model(props=fx.contract(rotation_frame="ray")))
    big = checks_module.MAX_BOX_COORDINATE
    K = np.array([[session_module.K_MIN_FOCAL, session_module.K_MAX_ABS, session_module.K_MAX_ABS],
                  [0, session_module.K_MIN_FOCAL, -session_module.K_MAX_ABS], [0, 0, 1]])
    for boxes in ([[-big, -big, big, big]], [[-big, -big, 1, 1]] * 40):
        q = ray_quaternions(K, np.array(boxes, dtype=np.float64))
        assert np.isfinite(q).all()
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    for boxes in ([[-32.0, -24.0, 96.0, 72.0]], [[-32.0, -24.0, 96.0, 72.0]] * 40):
        res = ray.refine(IMG, boxes, rq.identity((len(boxes),)), K=K, views=2 if len(boxes) == 1 else 1)
        assert np.isfinite(res.q_refined).all()
        np.testing.assert_allclose(np.linalg.norm(res.q_refined, axis=1), 1.0, atol=1e-12)


# ---------------------------------------------------------------- property fuzzing: a finite unit rotation or a named error
import re  # noqa: E402
import warnings  # noqa: E402

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

ARGUMENT_NAMES = re.compile(r"\b(image_bgr|boxes_xyxy|q_in_wxyz|K|iterations|views|crops_bgr)\b")
# derandomize: the same examples every run (a fixed seed); a few seconds in all
FUZZ = settings(max_examples=300, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
_FUZZ_SESSIONS = {}


def fuzz_session(frame: str) -> RefinerSession:
    """One random-weight session per rotation frame, shared by all examples (the ray one takes RGB)."""
    if frame not in _FUZZ_SESSIONS:
        props = fx.contract(rotation_frame=frame, channel_order="RGB" if frame == "ray" else "BGR")
        _FUZZ_SESSIONS[frame] = RefinerSession(fx.random_weight_model(props=props))
    return _FUZZ_SESSIONS[frame]


# odd floats: extreme but finite, tiny, zero, non-finite
ODD_FLOAT = st.one_of(
    st.sampled_from([0.0, -0.0, 5e-324, 1e-200, 1e-13, 1e154, -1e200, 1e300, 1.7e308, -1.7e308, np.nan, np.inf]),
    st.floats(allow_nan=True, allow_infinity=True),
)
FORMS_OK = ["f64", "f32", "int", "list"]
FORMS_BAD = ["ragged", "object", "strings", "3 columns", "rows+1", "3-d", "scalar"]


def box_ints(boxes: np.ndarray) -> np.ndarray:
    """Boxes on whole pixels, grown outwards (so they stay non-empty and overlapping)."""
    return np.concatenate([np.floor(boxes[:, :2]), np.ceil(boxes[:, 2:])], axis=1).astype(np.int64)


def rotation_ints(q: np.ndarray) -> np.ndarray:
    """Quaternions as integers (scaled to a largest component of +-1000: the same rotations)."""
    return np.rint(q / np.abs(q).max(axis=1, keepdims=True) * 1000).astype(np.int64) if len(q) else q.astype(np.int64)


def as_form(arr: np.ndarray, form: str, to_int):
    """``arr`` (``(n, 4)`` float64) as a user might pass it: an array of some dtype (``to_int`` makes the integer
    one), a list, or a broken form."""
    with np.errstate(all="ignore"):
        if form == "f32":
            return arr.astype(np.float32)
        if form == "int":
            return to_int(arr)
    return {
        "f64": lambda: arr,
        "list": arr.tolist,
        "ragged": lambda: [r[: 4 - (i % 2)] for i, r in enumerate(arr.tolist())] or [[1.0, 2.0], [3.0]],
        "object": lambda: arr.astype(object),
        "strings": lambda: arr.astype(str),
        "3 columns": lambda: arr[:, :3],
        "rows+1": lambda: np.vstack([arr, np.ones((1, 4))]),
        "3-d": lambda: arr[None],
        "scalar": lambda: 1.0,
    }[form]()


@st.composite
def table(draw, valid: np.ndarray, bad: bool, to_int):
    """``valid`` as given in one of the accepted forms, or (``bad``) with an odd value or in a broken form."""
    arr = valid.copy()
    if bad and len(arr) and draw(st.booleans()):
        arr[draw(st.integers(0, len(arr) - 1)), draw(st.integers(0, 3))] = draw(ODD_FLOAT)
        return as_form(arr, draw(st.sampled_from(["f64", "list"])), to_int)
    if not valid.size or np.abs(valid).max() < 1e18:  # float32 and int64 cannot hold what is beyond
        forms = FORMS_OK
    else:
        forms = ["f64", "list"]
    return as_form(arr, draw(st.sampled_from(FORMS_BAD if bad else forms)), to_int)


@st.composite
def images(draw, bad: bool):
    h, w = draw(st.integers(3, 40)), draw(st.integers(2, 40))  # at least 2 x 2 after the [::2] view below
    image = draw(hnp.arrays(np.uint8, (h, w, 3), elements=st.integers(0, 255)))
    if not bad:
        return image if draw(st.integers(0, 3)) else image[::2, ::-1]  # non-contiguous views are fine
    kind = draw(st.sampled_from(["float", "gray", "rgba", "empty", "list", "bool"]))
    return {"float": lambda: image.astype(np.float32), "gray": lambda: image[..., 0],
            "rgba": lambda: np.dstack([image, image[..., :1]]), "empty": lambda: image[:0], "list": image.tolist,
            "bool": lambda: image > 127}[kind]()


@st.composite
def overlapping_boxes(draw, n: int, h: int, w: int) -> np.ndarray:
    """``(n, 4)`` boxes the runtime takes in an ``h x w`` image (``h, w >= 2``): from ``MIN_BOX_SIDE`` pixels to
    1.8 times the image, anywhere that keeps 52% of each side inside (27% of the area, above
    ``MIN_INSIDE_FRACTION``)."""
    def side(size):
        # from 2.01 (so that rounding keeps 2 pixels) to 1.8 times the image
        length = draw(hnp.arrays(np.float64, n, elements=st.floats(0, 1))) * (1.8 * size - 2.01) + 2.01
        start = draw(hnp.arrays(np.float64, n, elements=st.floats(0, 1)))
        low, high = 0.52 * length - length, size - 0.52 * length  # the first coordinate's range
        first = low + start * (high - low)
        return first, first + length
    x1, x2 = side(w)
    y1, y2 = side(h)
    return np.stack([x1, y1, x2, y2], axis=1).reshape(n, 4)


@st.composite
def rotations(draw, n: int) -> np.ndarray:
    """``(n, 4)`` finite non-zero quaternions of any norm, from 1e-6 to 1e300 (all valid)."""
    q = draw(hnp.arrays(np.float64, (n, 4), elements=st.floats(-2, 2)))
    q[np.linalg.norm(q, axis=1) < 1e-3] = [1.0, 0.0, 0.0, 0.0]
    return q * draw(st.sampled_from([1.0, 1.0, 1e-6, 1e154, 1e200, 1e300]))


@st.composite
def intrinsics(draw, bad: bool, needed: bool):
    pinhole = np.array([[draw(st.floats(0.5, 5000)), draw(st.floats(-5, 5)), draw(st.floats(-100, 100))],
                        [0.0, draw(st.floats(0.5, 5000)), draw(st.floats(-100, 100))], [0.0, 0.0, 1.0]])
    if not bad:
        edge = np.array([[session_module.K_MIN_FOCAL, session_module.K_MAX_ABS, -session_module.K_MAX_ABS],
                         [0.0, session_module.K_MAX_ABS, session_module.K_MAX_ABS], [0.0, 0.0, 1.0]])
        options = [pinhole, pinhole.tolist(), edge] + ([] if needed else [None])
        return draw(st.sampled_from(options))
    kind = draw(st.sampled_from(["odd entry", "any", "ragged", "2x2", "scaled"] + (["none"] if needed else [])))
    if kind == "odd entry":
        pinhole[draw(st.integers(0, 2)), draw(st.integers(0, 2))] = draw(ODD_FLOAT)
        return pinhole
    return {"any": lambda: draw(hnp.arrays(np.float64, (3, 3), elements=ODD_FLOAT)),
            "ragged": lambda: [[500.0, 0.0, 20.0], [0.0, 500.0], [0.0, 0.0, 1.0]],
            "2x2": lambda: np.eye(2), "scaled": lambda: 3.0 * pinhole, "none": lambda: None}[kind]()


def count(bad: bool):
    return st.sampled_from([0, -1, 17, 2.0, True, None, "1", 10**9]) if bad else st.sampled_from([1, 1, 2, np.int64(3)])


ARGS = ("image_bgr", "boxes_xyxy", "q_in_wxyz", "K", "iterations", "views")


def assert_finite_unit_or_named_error(call, bad: set) -> None:
    """The property: ``call()`` returns finite unit ``wxyz`` rotations with ``w >= 0``, or raises a ValueError or
    TypeError that names an argument (not a ModelError: the model is fine). numpy warnings count as failures.
    With no argument made bad, it must return."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            res = call()
        except (ValueError, TypeError) as exc:
            assert bad, f"valid arguments refused: {exc}"
            assert not isinstance(exc, ModelError), f"a good model reported as broken: {exc}"
            assert ARGUMENT_NAMES.search(str(exc)), f"the error does not name the argument: {exc}"
            return
    for q in (res.q_refined, res.q_out, res.q_in):
        assert q.dtype == np.float64 and q.ndim == 2 and q.shape == (len(res), 4)
        assert np.isfinite(q).all(), q
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-9)
        assert (q[:, 0] >= 0).all()


@FUZZ
@given(data=st.data())
def test_fuzz_refine_gives_a_finite_unit_rotation_or_names_the_argument(data):
    # Most examples make none or one argument bad (odd values, dtypes, shapes, ragged lists), some two.
    bad = data.draw(st.one_of(st.just(set()), st.sets(st.sampled_from(ARGS), min_size=1, max_size=2)))
    frame = data.draw(st.sampled_from(["camera", "ray"]))
    n = data.draw(st.sampled_from([1, 2, 5, session_module.SMALL_BATCH + 3, 0]))
    image = data.draw(images("image_bgr" in bad))
    h, w = (image.shape[:2]) if isinstance(image, np.ndarray) and image.ndim == 3 and image.size else (20, 20)
    boxes = data.draw(table(data.draw(overlapping_boxes(n, h, w)), "boxes_xyxy" in bad, box_ints))
    q_in = data.draw(table(data.draw(rotations(n)), "q_in_wxyz" in bad, rotation_ints))
    K = data.draw(intrinsics("K" in bad, needed=frame == "ray"))
    iterations, views = data.draw(count("iterations" in bad)), data.draw(count("views" in bad))
    sess = fuzz_session(frame)
    assert_finite_unit_or_named_error(
        lambda: sess.refine(image, boxes, q_in, iterations=iterations, K=K, views=views), bad)


@FUZZ
@given(data=st.data())
def test_fuzz_refine_crops_gives_a_finite_unit_rotation_or_names_the_argument(data):
    bad = data.draw(st.one_of(st.just(set()), st.sets(st.sampled_from(["crops_bgr", "q_in_wxyz", "iterations"]),
                                                      min_size=1, max_size=2)))
    n = data.draw(st.sampled_from([1, 3, session_module.SMALL_BATCH + 3, 0]))
    crops = [data.draw(images(False)) for _ in range(min(n, 4))] + [np.zeros((8, 8, 3), np.uint8)] * max(0, n - 4)
    form = data.draw(st.sampled_from(["list", "tuple", "array"]))
    if "crops_bgr" in bad:
        kind = data.draw(st.sampled_from(["one bad crop", "one crop, no batch", "generator", "dict", "5-d"]))
        if kind == "one bad crop" and n:
            crops[data.draw(st.integers(0, min(n, 4) - 1))] = data.draw(images(True))
        else:
            crops = {"one crop, no batch": lambda: np.zeros((5, 7, 3), np.uint8), "generator": lambda: iter(crops),
                     "dict": lambda: {0: crops}, "5-d": lambda: np.zeros((n, 1, 5, 7, 3), np.uint8),
                     "one bad crop": lambda: [np.zeros((5, 7), np.uint8)]}[kind]()
    elif form == "tuple":
        crops = tuple(crops)
    elif form == "array":
        crops = np.zeros((n, 5, 7, 3), np.uint8)
    q_in = data.draw(table(data.draw(rotations(n)), "q_in_wxyz" in bad, rotation_ints))
    iterations = data.draw(count("iterations" in bad))
    sess = fuzz_session(data.draw(st.sampled_from(["camera", "ray"])))
    assert_finite_unit_or_named_error(lambda: sess.refine_crops(crops, q_in, iterations=iterations), bad)


def test_default_session_options_are_the_sessions_own_plus_entries():
    from refiner_rt.session import default_session_options

    o = default_session_options(2, **{"session.intra_op.allow_spinning": "0"})
    assert o.intra_op_num_threads == 2 and o.inter_op_num_threads == 1
    assert o.graph_optimization_level == ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    assert o.get_session_config_entry("session.intra_op.allow_spinning") == "0"


def test_rotations_in_the_forms_robot_code_has_matrices_and_ros_order_against_scipy():
    """(N, 3, 3) matrices and xyzw quaternions (SciPy's and ROS's order) give what the same rotations in wxyz give;
    res.R is the refined rotation as SciPy's matrix. An identity correction makes the refined rotation the input."""
    from scipy.spatial.transform import Rotation

    sess = RefinerSession(fx.constant_model([1, 0, 0, 0]))
    rot = Rotation.random(3, random_state=7)
    image = np.full((120, 160, 3), 90, np.uint8)
    boxes = np.array([[10.0, 10.0, 60.0, 70.0], [50.0, 20.0, 120.0, 90.0], [30.0, 40.0, 80.0, 110.0]])
    wxyz = rq.from_xyzw(rot.as_quat())
    ref = sess.refine(image, boxes, wxyz)
    by_matrix = sess.refine(image, boxes, rot.as_matrix())
    by_xyzw = sess.refine(image, boxes, rot.as_quat(), q_order="xyzw")
    for res in (ref, by_matrix, by_xyzw):
        np.testing.assert_allclose(res.R, rot.as_matrix(), atol=1e-9)
        assert rq.geodesic_angle(res.q_refined, wxyz).max() < 1e-6
    crops = sess.refine_crops([image[10:70, 10:60]] * 3, rot.as_matrix())
    np.testing.assert_allclose(crops.R, rot.as_matrix(), atol=1e-9)
    with pytest.raises(ValueError, match="q_order must be one of 'wxyz', 'xyzw'"):
        sess.refine(image, boxes, wxyz, q_order="XYZW")
    with pytest.raises(ValueError, match=r"q_in_wxyz\[1\] is not a rotation matrix"):
        sess.refine(image, boxes, np.stack([np.eye(3), 2 * np.eye(3), np.eye(3)]))
    with pytest.raises(ValueError, match=r"has shape \(3, 3\): one rotation matrix"):
        sess.refine(image, boxes, np.zeros((3, 3)), q_order="xyzw")
    one = sess.refine(image, boxes[:1], rot.as_matrix()[:1])  # one matrix as (1, 3, 3), as the message says
    np.testing.assert_allclose(one.R[0], rot.as_matrix()[0], atol=1e-9)
    bad = rot.as_matrix()[:1].copy()
    bad[0, :, 0] *= -1  # a reflection: orthonormal, determinant -1
    with pytest.raises(ValueError, match=r"q_in_wxyz\[0\] is not a rotation matrix.*det -1"):
        sess.refine(image, boxes[:1], bad)


def test_silent_inputs_are_caught_at_the_boundary(caplog):
    """Boxes normalised to 0..1, sub-pixel boxes and boxes mostly outside the image are refused by name, on the fast
    path (a few boxes) and the numpy path (more than SMALL_BATCH) alike; a principal point far from the image's centre
    (K for another resolution) is logged once per K and image size, and the call still refines."""
    import logging

    sess = RefinerSession(fx.constant_model([1, 0, 0, 0]))
    image = np.zeros((480, 640, 3), np.uint8)
    for n in (1, session_module.SMALL_BATCH + 1):
        ok = np.tile([[100.0, 100.0, 200.0, 220.0]], (n, 1))
        with pytest.raises(ValueError, match=r"boxes_xyxy look normalised to 0\.\.1.*640x480"):
            sess.refine(image, np.tile([[0.15, 0.2, 0.3, 0.45]], (n, 1)), rq.identity((n,)))
        for bad, match in (([100, 100, 101.5, 220], rf"boxes_xyxy\[{n - 1}\] is 1\.5 x 120 pixels"),
                           ([-120, 400, 40, 520], rf"boxes_xyxy\[{n - 1}\] lies mostly outside the 640x480 image: "
                                                  r"16\.7% of its area is inside, expected at least 25%")):
            boxes = ok.copy()
            boxes[-1] = bad
            with pytest.raises(ValueError, match=match):
                sess.refine(image, boxes, rq.identity((n,)))
        boxes = ok.copy()
        boxes[-1] = [600, 100, 760, 220]  # exactly a quarter inside: taken
        assert len(sess.refine(image, boxes, rq.identity((n,)))) == n
    checks_module._PRINCIPAL_POINT_WARNED.clear()
    K_big = np.array([[1000.0, 0, 640.0], [0, 1000.0, 480.0], [0, 0, 1]])  # calibrated at 1280x960
    with caplog.at_level(logging.WARNING, logger="refiner_rt.session"):
        for _ in range(3):
            sess.refine(image, [[100.0, 100.0, 200.0, 220.0]], rq.identity((1,)), K=K_big)
        sess.refine(image, [[100.0, 100.0, 200.0, 220.0]], rq.identity((1,)), K=K_big / 2 + np.diag([0, 0, 0.5]))
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 1, warned
    assert "principal point (cx, cy) = (640, 480) lies outside the central half of the 640x480 image" in warned[0]


@FUZZ
@given(boxes=hnp.arrays(np.float64, (3, 4), elements=st.one_of(st.floats(-60, 120), st.integers(-60, 120).map(float),
                                                                st.floats(0, 1))),
       h=st.integers(2, 60), w=st.integers(2, 60))
def test_the_fast_box_path_takes_exactly_the_boxes_validate_boxes_takes(boxes, h, w):
    fast = checks_module.boxes_rows(boxes, (h, w, 3))
    try:
        validate_boxes(boxes, (h, w, 3))
    except ValueError:
        assert fast is None
    else:
        assert fast is not None


# ------------------------------------------------------------------------------ RefineResult.score
def test_score_falls_with_the_last_correction_and_the_spread_of_the_views():
    """score = exp(-(angle of q_out + views' spread) / SCORE_SCALE_DEG): known values on constant models, and a
    crop-dependent model whose views disagree scores below its own one-view refinement."""
    from refiner_rt.session import SCORE_SCALE_DEG

    image = np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    boxes = [[20.0, 30.0, 90.0, 100.0], [60.0, 10.0, 150.0, 110.0]]
    q_in = rq.from_axis_angle([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], [10.0, 40.0])
    scores = []
    for angle in (2.0, 20.0):
        sess = RefinerSession(fx.constant_model(rq.from_axis_angle([0.0, 1.0, 0.0], angle)))
        for views in (1, 4):
            res = sess.refine(image, boxes, q_in, views=views)
            np.testing.assert_allclose(res.correction_deg, angle, atol=1e-4)
            np.testing.assert_allclose(res.score, np.exp(-angle / SCORE_SCALE_DEG), rtol=1e-5)
            assert (res.views_spread_deg is None) == (views == 1)
        scores.append(res.score)
    assert np.all(scores[0] > scores[1])
    sess = RefinerSession(fx.channel_mean_model())
    one, four = sess.refine(image, boxes, q_in), sess.refine(image, boxes, q_in, views=4)
    assert np.all(four.views_spread_deg > 0) and np.all(four.score < np.exp(-four.correction_deg / SCORE_SCALE_DEG))
    assert one.score.shape == (2,) and np.all((0 < one.score) & (one.score <= 1))
    settled = sess.refine(image, boxes, q_in, views=4, iterations=3, settle_deg=1.0)
    assert settled.views_spread_deg.shape == (2,)


def test_score_orders_true_poses_above_poses_60_degrees_off_on_the_samples():
    """Shipped INT8 refiners, two passes, on the sample frames: from the true pose each instance scores higher than
    from a pose 60 degrees off, and the mean score follows the refined error down."""
    from refiner_rt.demo import load_samples

    rng = np.random.default_rng(0)
    good, bad, err_good, err_bad = [], [], [], []
    for frame in load_samples():
        image = frame.image()
        for obj in frame.objects:
            sess = RefinerSession.pretrained(obj.object_id)
            off = rq.multiply(obj.q_gt, rq.sample_rotation_noise(1, "uniform", 60, 60 + 1e-9, rng=rng)[0])
            for q, scores, errors in ((obj.q_gt, good, err_good), (off, bad, err_bad)):
                res = sess.refine(image, obj.box_xyxy[None], q[None], K=frame.K, iterations=2)
                scores.append(float(res.score[0]))
                errors.append(float(rq.geodesic_angle(res.q_refined, obj.q_gt[None])[0]))
    good, bad = np.array(good), np.array(bad)
    assert len(good) >= 25
    assert np.mean(good > bad) >= 0.9, (good, bad)
    assert good.mean() > bad.mean() and np.mean(err_good) < np.mean(err_bad)


def test_score_is_calibrated_on_rendered_frames():
    """Shipped INT8 refiners, two passes, on the sample frames (renders no model or the calibration saw), inputs
    U(0, 30) and U(30, 90) degrees off: a higher score means a lower error (Spearman), and the score reads as the
    probability of ending within SCORE_WITHIN_DEG of the truth: its mean is near the share that does, and the
    results scoring 0.8 or more end within it far more often than those scoring below 0.6."""
    from scipy.stats import spearmanr

    from refiner_rt.demo import load_samples
    from refiner_rt.session import SCORE_WITHIN_DEG

    rng = np.random.default_rng(0)
    score, err = [], []
    for frame in load_samples():
        image = frame.image()
        for obj in frame.objects:
            sess = RefinerSession.pretrained(obj.object_id)
            for lo, hi in ((0, 30), (30, 90)):
                q = rq.multiply(obj.q_gt, rq.sample_rotation_noise(1, "uniform", lo, hi, rng=rng)[0])
                res = sess.refine(image, obj.box_xyxy[None], q[None], K=frame.K, iterations=2)
                score.append(float(res.score[0]))
                err.append(float(rq.geodesic_angle(res.q_refined, obj.q_gt[None])[0]))
    score, within = np.array(score), np.array(err) < SCORE_WITHIN_DEG
    assert len(score) >= 50
    assert spearmanr(score, err)[0] < -0.4
    assert abs(score.mean() - within.mean()) < 0.1
    assert within[score >= 0.8].mean() > 0.85 and within[score < 0.6].mean() < 0.6
