"""RefinerSession against closed-form test models (tests/onnx_fixtures.py) and SciPy's Rotation."""

import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import onnx_fixtures as fx
from refiner_rt import RefinerSession
from refiner_rt import quaternion as rq
from refiner_rt.preprocess import crop_to_square, resize_crop
from refiner_rt.session import MAX_VIEWS, VIEW_JITTER, ray_quaternions, view_boxes

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
    np.testing.assert_array_equal(np.array(session_module._ray_rows(K, boxes.tolist())), q)


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
        (dict(q_in_wxyz=np.ones((3, 3))), r"shape \(\.\.\., 4\)"),
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
    code = "import sys, refiner_rt; from refiner_rt import RefinerSession, quaternion, cli, bench, info; assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


# ---------------------------------------------------------------- lean refine() path (issue 6)
import onnxruntime as ort  # noqa: E402
from onnx import TensorProto, helper  # noqa: E402

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
    cx, cy = rng.uniform(0, 64, n), rng.uniform(0, 48, n)
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
    monkeypatch.setattr(session_module, "SMALL_BATCH", 0)
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
        cx, cy = rng.uniform(0, 64, n), rng.uniform(0, 48, n)
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
