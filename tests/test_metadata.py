"""The ONNX metadata contract: written by build_metadata, read and validated by parse_metadata."""

import json

import pytest

from refiner_rt.metadata import REQUIRED_KEYS, build_metadata, parse_metadata


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
