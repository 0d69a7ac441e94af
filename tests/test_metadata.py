"""The ONNX metadata contract: written by build_metadata, read and validated by parse_metadata; the graph half
checked by check_graph."""

import json

import pytest

from refiner_rt.metadata import (
    MAX_CROP_CONTEXT,
    MAX_INPUT_SIZE,
    REQUIRED_KEYS,
    build_metadata,
    check_graph,
    parse_metadata,
)


def props(**kw):
    base = dict(
        arch="shallow",
        input_size=64,
        channel_order="BGR",
        crop_context=1.2,
        rotation_frame="camera",
        objects=["003_cracker_box", "011_banana"],
        train_noise="uniform:0:30",
        checkpoint_sha256="ab" * 32,
        version="0.1.0",
    )
    base.update(kw)
    return build_metadata(**base)


def test_round_trip():
    p = props(extra={"num_parameters": 123})
    c = parse_metadata(p)
    assert (c.arch, c.input_size, c.channel_order, c.crop_context, c.rotation_frame) == ("shallow", 64, "BGR", 1.2, "camera")
    assert c.objects == ("003_cracker_box", "011_banana")
    assert c.quantization == "none"
    assert c.extra == {"num_parameters": "123"}
    assert c.as_dict()["quaternion_order"] == "wxyz"
    assert all(isinstance(v, str) for v in p.values())


@pytest.mark.parametrize("key", REQUIRED_KEYS)
def test_missing_key_is_named(key):
    p = props()
    del p[key]
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        parse_metadata(p)


@pytest.mark.parametrize(
    "key,value",
    [
        ("refiner_rt.format", "other/2"),
        ("quaternion_order", "xyzw"),
        ("input_size", "sixty-four"),
        ("input_size", "0"),
        ("channel_order", "GRAY"),
        ("crop_context", "0.5"),
        ("rotation_frame", "world"),
        ("objects", json.dumps([1, 2])),
        ("objects", "not json"),
        ("quantization", "int4"),
    ],
)
def test_unknown_values_are_refused_naming_the_key(key, value):
    p = props()
    p[key] = value
    with pytest.raises(ValueError, match=f"'{key}'"):
        parse_metadata(p)


@pytest.mark.parametrize(
    "key,value",
    [
        ("crop_context", "inf"),
        ("crop_context", "1e308"),
        ("crop_context", "nan"),
        ("crop_context", "4.5"),
        ("crop_context", "0.99"),
        ("input_size", "100000"),
        ("input_size", "-3"),
        ("objects", "[" * 100_000),
    ],
)
def test_values_out_of_their_sane_range_are_refused_naming_the_key(key, value):
    p = props()
    p[key] = value
    with pytest.raises(ValueError, match=f"'{key}'"):
        parse_metadata(p)


def test_range_limits_are_inclusive_and_shared_with_build_metadata():
    assert parse_metadata(props(crop_context=1.0)).crop_context == 1.0
    assert parse_metadata(props(crop_context=MAX_CROP_CONTEXT, input_size=MAX_INPUT_SIZE)).input_size == MAX_INPUT_SIZE
    with pytest.raises(ValueError, match="'crop_context'"):
        props(crop_context=MAX_CROP_CONTEXT * 1.01)


# ---------------------------------------------------------------- the graph half of the contract
from types import SimpleNamespace  # noqa: E402


def arg(name, type_, shape):
    return SimpleNamespace(name=name, type=type_, shape=shape)


def graph(**changes):
    """Inputs and outputs of a contract-abiding graph with S = 8, with ``changes`` as ``name=(type, shape)`` (None
    removes the entry)."""
    spec = {
        "image": ("tensor(uint8)", ["batch", 8, 8, 3]),
        "q_in": ("tensor(float)", ["batch", 4]),
        "q_out": ("tensor(float)", ["batch", 4]),
    }
    spec.update(changes)
    inputs = [arg(n, *spec[n]) for n in spec if n != "q_out" and spec[n] is not None]
    outputs = [arg("q_out", *spec["q_out"])] if spec["q_out"] is not None else []
    return inputs, outputs


def test_a_contract_abiding_graph_passes_with_any_symbolic_batch_name():
    check_graph(*graph(), 8)
    check_graph(*graph(image=("tensor(uint8)", [None, 8, 8, 3]), q_out=("tensor(float)", ["N", "four"])), 8)
    inputs, outputs = graph()
    check_graph(inputs, outputs + [arg("debug", "tensor(double)", [2])], 8)  # extra outputs are not fetched


@pytest.mark.parametrize(
    "changes,match",
    [
        (dict(image=None), r"lacks \['image'\]"),
        (dict(q_out=None), r"lacks \['q_out'\]"),
        (dict(mask=("tensor(uint8)", ["batch", 8, 8])), r"inputs \['mask'\] that the runtime does not feed"),
        (dict(image=("tensor(float)", ["batch", 8, 8, 3])), r"input 'image' must be tensor\(uint8\)"),
        (dict(image=("tensor(uint8)", ["batch", 8, 8, 4])), r"input 'image' must have shape \(batch, 8, 8, 3\)"),
        (dict(image=("tensor(uint8)", ["batch", 3, 8, 8])), r"input 'image' must have shape"),
        (dict(image=("tensor(uint8)", ["batch", 16, 16, 3])), "input_size=8 expects"),
        (dict(image=("tensor(uint8)", [1, 8, 8, 3])), "input 'image' must have a dynamic batch axis"),
        (dict(q_in=("tensor(float)", ["batch", 3])), r"input 'q_in' must have shape \(batch, 4\)"),
        (dict(q_in=("tensor(double)", ["batch", 4])), r"input 'q_in' must be tensor\(float\)"),
        (dict(q_in=("tensor(float)", ["batch", 4, 1])), r"input 'q_in' must have shape \(batch, 4\)"),
        (dict(q_in=("tensor(float)", [1, 4])), "input 'q_in' must have a dynamic batch axis"),
        (dict(q_out=("tensor(float)", ["batch", 3])), r"output 'q_out' must have shape \(batch, 4\)"),
        (dict(q_out=("tensor(float16)", ["batch", 4])), r"output 'q_out' must be tensor\(float\)"),
        (dict(q_out=("tensor(float)", [1, 4])), "output 'q_out' must have a dynamic batch axis"),
    ],
)
def test_graph_contract_violations_are_named(changes, match):
    with pytest.raises(ValueError, match=match):
        check_graph(*graph(**changes), 8)
