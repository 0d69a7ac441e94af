"""export.quantize's "static-qdq-int8-conv" scheme: which layers it quantises, what onnxruntime makes of them, and
that the model stays a refiner close to fp32."""

import collections

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from export import quantize as q8
import export
from export.parity import random_inputs
import models
from refiner_rt import RefinerSession
from refiner_rt import quaternion as rq

# Five conv blocks like the shipped refiner, narrower: input channels per conv 3, 8, 16, 16, 32.
CONFIG = {"input_size": 32, "conv_channels": [8, 16, 16, 32, 32], "fuse_width": 64, "pose_widths": [32, 64],
          "head_widths": [64, 32]}
INFO = {"objects": ["003_cracker_box"], "train_noise": "uniform:0:30"}
SCHEME = "static-qdq-int8-conv"


@pytest.fixture(scope="module")
def fp32(tmp_path_factory):
    d = tmp_path_factory.mktemp("fp32")
    torch.manual_seed(0)
    ckpt = models.save_checkpoint(models.build_refiner("fusion", **CONFIG), d / "fusion.pt", **INFO)
    return export.export_checkpoint(ckpt).path


def _conv_inputs_from_config(min_channels):
    """Independent reference: the input channels of each conv block, from the network's configuration."""
    c_in = [3] + CONFIG["conv_channels"][:-1]
    return [c for c in c_in if c >= min_channels]


@pytest.mark.parametrize("min_channels", [1, 16, 32, 64])
def test_wide_conv_chain_picks_the_convs_with_enough_input_channels(fp32, min_channels):
    proto = onnx.load(str(fp32))
    chosen = q8.wide_conv_chain(proto, min_channels)
    nodes = {n.name: n for n in proto.graph.node}
    weights = {t.name: list(t.dims) for t in proto.graph.initializer}
    convs = [nodes[n] for n in chosen if nodes[n].op_type == "Conv"]
    assert [weights[c.input[1]][1] for c in convs] == _conv_inputs_from_config(min_channels)
    # Each chosen conv comes with the ReLU and max-pool of its block, in that order.
    kinds = [nodes[n].op_type for n in chosen]
    assert kinds == ["Conv", "Relu", "MaxPool"] * len(convs)


def _runtime_ops(path, tmp_path):
    o = ort.SessionOptions()
    o.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    o.optimized_model_filepath = str(tmp_path / "optimized.onnx")
    ort.InferenceSession(str(path), o, providers=["CPUExecutionProvider"])
    return collections.Counter(n.op_type for n in onnx.load(o.optimized_model_filepath).graph.node)


def test_conv_scheme_quantises_wide_convs_per_channel_and_onnxruntime_fuses_them(fp32, tmp_path):
    report = q8.quantize_model(fp32, tmp_path / "m.int8.onnx", scheme=SCHEME)
    assert report.scheme == SCHEME and report.agreement.passed and report.calibration.startswith("random:")
    proto = onnx.load(str(report.path))
    props = {p.key: p.value for p in proto.metadata_props}
    assert props["quantization"] == SCHEME and props["int8_calibration"] == report.calibration
    # Per-channel weights: the DequantizeLinear feeding each quantised conv has one scale per output channel.
    inits = {t.name: onnx.numpy_helper.to_array(t) for t in proto.graph.initializer}
    producers = {o: n for n in proto.graph.node for o in n.output}
    wide = _conv_inputs_from_config(q8.CONV_MIN_CHANNELS)
    quantised = 0
    for conv in (n for n in proto.graph.node if n.op_type == "Conv"):
        dq = producers.get(conv.input[1])
        if dq is None:
            continue
        quantised += 1
        weight, scale = inits[dq.input[0]], inits[dq.input[1]]
        assert weight.dtype == np.int8 and scale.shape == (weight.shape[0],)
    assert quantised == len(wide)
    # onnxruntime runs the quantised convs as integer convolutions, the narrow first one in fp32.
    ops = _runtime_ops(report.path, tmp_path)
    assert ops["QLinearConv"] == len(wide), ops
    assert sum(ops[k] for k in ("Conv", "FusedConv")) == len(CONFIG["conv_channels"]) - len(wide), ops


def test_conv_scheme_model_refines_close_to_fp32(fp32, tmp_path):
    report = q8.quantize_model(fp32, tmp_path / "m.int8.onnx", scheme=SCHEME)
    images, q_in = random_inputs(CONFIG["input_size"], 32, seed=42)
    r8, r32 = RefinerSession(report.path).refine_crops(images, q_in), RefinerSession(fp32).refine_crops(images, q_in)
    diff = rq.geodesic_angle(r8.q_refined, r32.q_refined)
    assert diff.mean() <= q8.MAX_MEAN_DEG and diff.max() <= q8.MAX_MAX_DEG
    assert np.all(diff > 0)  # really quantised
    np.testing.assert_allclose(np.linalg.norm(r8.q_refined, axis=1), 1.0, atol=1e-9)


def test_conv_scheme_refuses_a_model_it_would_leave_fp32(tmp_path):
    torch.manual_seed(0)
    cfg = {**CONFIG, "conv_channels": [4, 8]}  # input channels 3 and 4, and no fully connected layer of 64k weights
    ckpt = models.save_checkpoint(models.build_refiner("fusion", **cfg), tmp_path / "n.pt", **INFO)
    fp32 = export.export_checkpoint(ckpt).path
    with pytest.raises(ValueError, match="has neither.*use dynamic-int8"):
        q8.quantize_model(fp32, tmp_path / "n.int8.onnx", scheme=SCHEME)
    assert not (tmp_path / "n.int8.onnx").exists()


def test_large_fully_connected_keeps_the_small_ends_in_fp32(fp32):
    # Reference from the configuration: the Linear layers' in x out sizes (the quaternion's quadratic form, 16 x 9,
    # is a MatMul with a constant and never large).
    side = CONFIG["input_size"] // 2 ** len(CONFIG["conv_channels"])
    d = CONFIG["fuse_width"]
    linear = [CONFIG["conv_channels"][-1] * side * side * d, 9 * CONFIG["pose_widths"][0],
              CONFIG["pose_widths"][0] * CONFIG["pose_widths"][1], 3 * d * CONFIG["head_widths"][0],
              CONFIG["head_widths"][0] * CONFIG["head_widths"][1], CONFIG["head_widths"][1] * 4]
    proto = onnx.load(str(fp32))
    for threshold in (1, 2048, 12288, 10**9):
        chosen = q8.large_fully_connected(proto, threshold)
        assert len(chosen) == sum(n >= threshold for n in linear) + (16 * 9 >= threshold), threshold


def test_conv_scheme_refuses_a_bad_fc_mode(fp32, tmp_path):
    with pytest.raises(ValueError, match="fc must be 'static' or 'dynamic'"):
        q8._quantize_static_qdq_conv(fp32, tmp_path / "x.onnx", q8.random_calibration(CONFIG["input_size"], n=4),
                                     fc="sometimes")


def test_conv_scheme_quantises_the_large_fully_connected_layers_dynamically(fp32, tmp_path):
    # With a lower threshold the tiny model's head input layer (192 x 64 = 12,288 weights) counts as large: it must
    # come out as a dynamic integer MatMul (onnxruntime renames Gemm nodes while quantising them), the others fp32.
    src = tmp_path / "src.onnx"
    onnx.save(q8._without_value_info(onnx.load(str(fp32))), str(src))
    out = tmp_path / "m.onnx"
    q8._quantize_static_qdq_conv(src, out, q8.random_calibration(CONFIG["input_size"], n=8), fc_min_weights=12288)
    ops = collections.Counter(n.op_type for n in onnx.load(str(out)).graph.node)
    assert ops["MatMulInteger"] == 1 and ops["DynamicQuantizeLinear"] == 1, ops
    runtime = _runtime_ops(out, tmp_path)
    assert runtime["QLinearConv"] == len(_conv_inputs_from_config(q8.CONV_MIN_CHANNELS)), runtime


def _runtime_graph(path, tmp_path, disabled=()):
    o = ort.SessionOptions()
    o.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    o.optimized_model_filepath = str(tmp_path / "optimized.onnx")
    ort.InferenceSession(str(path), o, providers=["CPUExecutionProvider"], disabled_optimizers=list(disabled))
    return onnx.load(o.optimized_model_filepath).graph


def _pools_on_uint8(graph):
    """Max-pools that read a QuantizeLinear's output (uint8): onnxruntime's plain NCHW pool on integers."""
    producers = {o: n for n in graph.node for o in n.output}
    return [n.name for n in graph.node if n.op_type == "MaxPool" and n.input[0] in producers
            and producers[n.input[0]].op_type == "QuantizeLinear"]


def test_the_runtime_keeps_the_max_pool_before_the_integer_convs_in_fp32(fp32, tmp_path):
    # With onnxruntime's QDQPropagationTransformer on, the first QuantizeLinear moves above the max-pool before the
    # first integer conv (which then runs on uint8 in NCHW); RefinerSession turns that transformer off
    # (DISABLED_OPTIMIZERS), so that pool stays in fp32 after its conv.
    from refiner_rt.session import DISABLED_OPTIMIZERS

    path = q8.quantize_model(fp32, tmp_path / "m.int8.onnx", scheme=SCHEME).path
    assert len(_pools_on_uint8(_runtime_graph(path, tmp_path))) == 1
    assert _pools_on_uint8(_runtime_graph(path, tmp_path, DISABLED_OPTIMIZERS)) == []


@pytest.mark.parametrize("scheme", ["static-qdq-int8-conv", "static-qdq-int8"])
def test_turning_qdq_propagation_off_changes_no_output(fp32, tmp_path, scheme):
    # Max-pooling (and a reshape) commute with a monotonic quantisation, so RefinerSession (transformer off) must
    # agree bit for bit with a plain onnxruntime session (transformer on) on the same crops, for both static schemes.
    path = q8.quantize_model(fp32, tmp_path / "m.int8.onnx", scheme=scheme).path
    images, q_in = random_inputs(CONFIG["input_size"], 16, seed=7)
    plain = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    expected = plain.run(["q_out"], {"image": images, "q_in": q_in.astype(np.float32)})[0]
    sess = RefinerSession(path)
    got = sess._session.run(["q_out"], {"image": images, "q_in": q_in.astype(np.float32)})[0]
    np.testing.assert_array_equal(got, expected)


def test_float_pose_scheme_leaves_every_layer_that_q_in_reaches_in_fp32(fp32, tmp_path):
    """``static-qdq-int8-conv-float-pose``: the convolutions are quantised as in the conv scheme, but no integer or
    quantising node depends on q_in, so with the crop fixed a 1e-4-degree change of q_in moves q_out by about that
    much (the conv scheme with the head quantised moves it by nothing or by a whole step)."""
    scheme = "static-qdq-int8-conv-float-pose"
    src = tmp_path / "src.onnx"
    onnx.save(q8._without_value_info(onnx.load(str(fp32))), str(src))
    calibration = q8.random_calibration(CONFIG["input_size"], n=16)
    # The tiny head input layer (12,288 weights) counts as large at this threshold, as the shipped head's does at 64k.
    stepped, smooth = tmp_path / "conv.onnx", tmp_path / "float_pose.onnx"
    q8._quantize_static_qdq_conv(src, stepped, calibration, fc_min_weights=12288)
    q8._quantize_static_qdq_conv(src, smooth, calibration, fc_min_weights=12288, float_pose=True)
    quantising = {"DynamicQuantizeLinear", "MatMulInteger", "QuantizeLinear", "DequantizeLinear", "ConvInteger"}
    for path, expect_pose_quantised in ((stepped, True), (smooth, False)):
        proto = onnx.load(str(path))
        pose = q8.pose_dependent(proto)
        kinds = {n.op_type for n in proto.graph.node if n.name in pose}
        assert bool(kinds & quantising) == expect_pose_quantised, kinds
        assert sum(n.op_type == "QuantizeLinear" for n in proto.graph.node) > 0  # the convolutions still are
    # The scheme's name goes through quantize_model and into the metadata.
    report = q8.quantize_model(fp32, tmp_path / "m.int8.onnx", scheme=scheme, calibration=calibration)
    assert report.agreement.passed and RefinerSession(report.path).contract.quantization == scheme
    images, q_in = random_inputs(CONFIG["input_size"], 32, seed=3)
    rng = np.random.default_rng(0)
    axes = rng.standard_normal((32, 3))
    q2 = rq.multiply(q_in.astype(np.float64), rq.from_axis_angle(axes / np.linalg.norm(axes, axis=1, keepdims=True),
                                                                 1e-4)).astype(np.float32)
    for path, bound in ((smooth, 0.01), (report.path, 0.01)):
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        a, b = (sess.run(None, {"image": images, "q_in": q})[0].astype(np.float64) for q in (q_in, q2))
        assert rq.geodesic_angle(rq.normalize(a), rq.normalize(b)).max() < bound
