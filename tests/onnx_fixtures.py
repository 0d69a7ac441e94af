"""Tiny hand-built ONNX graphs that satisfy the refiner-rt model contract, for runtime tests.

They need only the ``onnx`` package (no torch) and have outputs known in closed form, so the runtime's
cropping, channel handling and composition can be checked against independent computations.
"""

from __future__ import annotations

import numpy as np
from onnx import TensorProto, helper
import onnx

from refiner_rt.metadata import INPUT_IMAGE, INPUT_QUATERNION, OUTPUT_QUATERNION, build_metadata


def contract(**overrides) -> dict[str, str]:
    """Metadata props for a test model (overridable per key)."""
    kw = dict(
        arch="test",
        input_size=8,
        channel_order="BGR",
        crop_context=1.2,
        rotation_frame="camera",
        objects=["003_cracker_box"],
        train_noise="uniform:0:30",
        checkpoint_sha256="0" * 64,
        version="0.1.0",
    )
    kw.update(overrides)
    return build_metadata(**kw)


def _model(nodes, initializers, size: int, props: dict[str, str] | None, image_type=TensorProto.UINT8) -> bytes:
    graph = helper.make_graph(
        nodes,
        "test_refiner",
        [
            helper.make_tensor_value_info(INPUT_IMAGE, image_type, ["batch", size, size, 3]),
            helper.make_tensor_value_info(INPUT_QUATERNION, TensorProto.FLOAT, ["batch", 4]),
        ],
        [helper.make_tensor_value_info(OUTPUT_QUATERNION, TensorProto.FLOAT, ["batch", 4])],
        initializer=initializers,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    for k, v in (props or {}).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    onnx.checker.check_model(model, full_check=True)
    return model.SerializeToString()


def constant_model(q_out_wxyz, size: int = 8, props: dict[str, str] | None = None) -> bytes:
    """A model whose output is the same unit quaternion ``q_out_wxyz`` for every input row."""
    q = np.asarray(q_out_wxyz, dtype=np.float32)
    zero = helper.make_tensor("zero", TensorProto.FLOAT, [1], [0.0])
    const = helper.make_tensor("const", TensorProto.FLOAT, [4], q.tolist())
    nodes = [
        helper.make_node("Mul", [INPUT_QUATERNION, "zero"], ["zeros"]),
        helper.make_node("Add", ["zeros", "const"], [OUTPUT_QUATERNION]),
    ]
    return _model(nodes, [zero, const], size, contract(input_size=size) if props is None else props)


def channel_mean_model(size: int = 8, props: dict[str, str] | None = None) -> bytes:
    """A model with ``q_out = normalize(1, m0, m1, m2)``, ``m_c`` the mean of input channel ``c`` / 255.

    The output reveals exactly which pixels (and in which channel order) reached the graph.
    """
    axes = helper.make_tensor("axes", TensorProto.INT64, [2], [1, 2])
    scale = helper.make_tensor("scale", TensorProto.FLOAT, [1], [1.0 / 255.0])
    nodes = [
        helper.make_node("Cast", [INPUT_IMAGE], ["imgf"], to=TensorProto.FLOAT),
        helper.make_node("ReduceMean", ["imgf", "axes"], ["means"], keepdims=0),
        helper.make_node("Mul", ["means", "scale"], ["m"]),
        helper.make_node("Slice", [INPUT_QUATERNION, "s0", "s1", "s_axis"], ["q0"]),
        helper.make_node("Mul", ["q0", "zero"], ["z"]),
        helper.make_node("Add", ["z", "one"], ["ones"]),
        helper.make_node("Concat", ["ones", "m"], ["q"], axis=1),
        helper.make_node("ReduceL2", ["q", "last"], ["n"], keepdims=1),
        helper.make_node("Div", ["q", "n"], [OUTPUT_QUATERNION]),
    ]
    inits = [
        axes,
        scale,
        helper.make_tensor("s0", TensorProto.INT64, [1], [0]),
        helper.make_tensor("s1", TensorProto.INT64, [1], [1]),
        helper.make_tensor("s_axis", TensorProto.INT64, [1], [1]),
        helper.make_tensor("zero", TensorProto.FLOAT, [1], [0.0]),
        helper.make_tensor("one", TensorProto.FLOAT, [1], [1.0]),
        helper.make_tensor("last", TensorProto.INT64, [1], [1]),
    ]
    return _model(nodes, inits, size, contract(input_size=size) if props is None else props)


def q_echo_model(size: int = 8, props: dict[str, str] | None = None) -> bytes:
    """A model with ``q_out = q_in`` (reveals the rotation the graph was given, e.g. in the ray frame)."""
    nodes = [helper.make_node("Identity", [INPUT_QUATERNION], [OUTPUT_QUATERNION])]
    return _model(nodes, [], size, contract(input_size=size) if props is None else props)


def random_weight_model(size: int = 8, hidden: int = 16, seed: int = 0, props: dict[str, str] | None = None) -> bytes:
    """A small network with fixed random weights: ``q_out = normalize(q_in + tanh(x W1 + q_in W2) W3)``, ``x`` the
    crop's pixels / 255 flattened.

    Every pixel and every ``q_in`` component reaches the output through float matrix products (onnxruntime's MLAS
    kernels, as in the real refiners), so a crop or rotation mixed up between two calls changes the result.
    """
    rng = np.random.default_rng(seed)
    n_pix = size * size * 3
    w1 = (rng.standard_normal((n_pix, hidden)) / np.sqrt(n_pix)).astype(np.float32)
    w2 = rng.standard_normal((4, hidden)).astype(np.float32)
    w3 = (0.3 * rng.standard_normal((hidden, 4))).astype(np.float32)
    inits = [
        helper.make_tensor("flat", TensorProto.INT64, [2], [0, -1]),
        helper.make_tensor("scale", TensorProto.FLOAT, [1], [1.0 / 255.0]),
        helper.make_tensor("w1", TensorProto.FLOAT, list(w1.shape), w1.ravel().tolist()),
        helper.make_tensor("w2", TensorProto.FLOAT, list(w2.shape), w2.ravel().tolist()),
        helper.make_tensor("w3", TensorProto.FLOAT, list(w3.shape), w3.ravel().tolist()),
        helper.make_tensor("last", TensorProto.INT64, [1], [1]),
    ]
    nodes = [
        helper.make_node("Cast", [INPUT_IMAGE], ["imgf"], to=TensorProto.FLOAT),
        helper.make_node("Reshape", ["imgf", "flat"], ["x0"]),
        helper.make_node("Mul", ["x0", "scale"], ["x"]),
        helper.make_node("MatMul", ["x", "w1"], ["h_img"]),
        helper.make_node("MatMul", [INPUT_QUATERNION, "w2"], ["h_q"]),
        helper.make_node("Add", ["h_img", "h_q"], ["h_sum"]),
        helper.make_node("Tanh", ["h_sum"], ["h"]),
        helper.make_node("MatMul", ["h", "w3"], ["dq"]),
        helper.make_node("Add", [INPUT_QUATERNION, "dq"], ["q"]),
        helper.make_node("ReduceL2", ["q", "last"], ["n"], keepdims=1),
        helper.make_node("Div", ["q", "n"], [OUTPUT_QUATERNION]),
    ]
    return _model(nodes, inits, size, contract(input_size=size) if props is None else props)


def graph_model(nodes, inputs, outputs, initializers=(), props: dict[str, str] | None = None) -> bytes:
    """A model with any inputs and outputs, each ``(name, TensorProto type, shape)``: for contract-breaking tests.

    ``props`` defaults to a valid contract for ``input_size=8``.
    """
    graph = helper.make_graph(
        nodes,
        "test_graph",
        [helper.make_tensor_value_info(n, t, s) for n, t, s in inputs],
        [helper.make_tensor_value_info(n, t, s) for n, t, s in outputs],
        initializer=list(initializers),
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    for k, v in (contract() if props is None else props).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    return model.SerializeToString()
