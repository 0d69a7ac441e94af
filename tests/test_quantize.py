"""export.quantize: INT8 models keep the contract, record the scheme, load in the runtime and stay close to fp32."""

from click.testing import CliRunner
import numpy as np
import onnx
import pytest
import torch

from export import quantize as q8
import export
from export.parity import random_inputs
import models
from refiner_rt import RefinerSession
from refiner_rt import quaternion as rq
from refiner_rt.cli import main as cli_main
from refiner_rt.metadata import parse_metadata
from tests.cube_dataset import make_cube_dataset

# Small but not degenerate widths: per-tensor int8 on 8-wide layers is not what ships.
CONFIGS = {
    "shallow": {"input_size": 32, "conv_channels": [4, 8], "pose_widths": [16, 128], "head_widths": [64, 16]},
    "fusion": {"input_size": 32, "conv_channels": [8, 8], "fuse_width": 128, "pose_widths": [32, 128], "head_widths": [64, 32]},
}
INFO = {"objects": ["003_cracker_box"], "train_noise": "uniform:0:30"}


def _props(path):
    return {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}


@pytest.fixture(scope="module")
def fp32_models(tmp_path_factory):
    """{arch: fp32 ONNX path} of small random-weight refiners, exported through checkpoints."""
    d = tmp_path_factory.mktemp("fp32")
    out = {}
    for arch, cfg in CONFIGS.items():
        torch.manual_seed(0)
        ckpt = models.save_checkpoint(models.build_refiner(arch, **cfg), d / f"{arch}.pt", **INFO)
        out[arch] = export.export_checkpoint(ckpt).path
    return out


# static-qdq-int8-conv (and its float-pose variant) needs 16-channel convs or 64k-weight layers, which these tiny
# networks lack (it refuses them); tests/test_quantize_conv.py checks both on a five-block network.
@pytest.mark.parametrize("scheme", [s for s in q8.SCHEMES if not s.startswith("static-qdq-int8-conv")])
@pytest.mark.parametrize("arch", sorted(CONFIGS))
def test_int8_model_records_scheme_keeps_contract_and_is_close_to_fp32(fp32_models, tmp_path, arch, scheme):
    fp32 = fp32_models[arch]
    report = q8.quantize_model(fp32, tmp_path / "m.int8.onnx", scheme=scheme)
    assert report.path.is_file() and report.scheme == scheme
    assert report.size_bytes < report.fp32_size_bytes
    # Metadata: the scheme, and every fp32 key unchanged.
    before, after = _props(fp32), _props(report.path)
    assert after["quantization"] == scheme and before["quantization"] == "none"
    assert {k: v for k, v in after.items() if k not in ("quantization", "int8_calibration")} == {
        k: v for k, v in before.items() if k != "quantization"
    }
    assert ("int8_calibration" in after) == (scheme in q8.CALIBRATED_SCHEMES)
    # Agreement reported and within the stated bound.
    a = report.agreement
    assert a.enforced and a.passed and a.n_inputs == 64
    assert 0 < a.mean_deg <= a.max_deg <= q8.MAX_MAX_DEG and a.mean_deg <= q8.MAX_MEAN_DEG
    assert "INT8 agreement OK" in report.summary() and str(report.path) in report.summary()
    # The runtime loads it and its refinements stay close to fp32 on fixed inputs.
    s = CONFIGS[arch]["input_size"]
    images, q_in = random_inputs(s, 16, seed=42)
    sess8, sess32 = RefinerSession(report.path), RefinerSession(fp32)
    assert sess8.contract.quantization == scheme and sess8.metadata["arch"] == arch
    r8, r32 = sess8.refine_crops(images, q_in), sess32.refine_crops(images, q_in)
    diff = rq.geodesic_angle(r8.q_refined, r32.q_refined)
    assert diff.mean() <= q8.MAX_MEAN_DEG and diff.max() <= q8.MAX_MAX_DEG
    assert np.all(diff > 0)  # it really is a different (quantised) model


def test_dynamic_weights_are_seven_bit_so_avx2_kernels_cannot_saturate(fp32_models, tmp_path):
    # AVX2's u8s8 kernels sum pairs of products in int16: |w| <= 64 keeps 2 * 255 * 64 below 32767.
    report = q8.quantize_model(fp32_models["fusion"], tmp_path / "d.int8.onnx", scheme="dynamic-int8")
    graph = onnx.load(str(report.path)).graph
    consumers = {name for n in graph.node if n.op_type == "MatMulInteger" for name in n.input}
    weights = [onnx.numpy_helper.to_array(t) for t in graph.initializer
               if t.data_type == onnx.TensorProto.INT8 and t.name in consumers and len(t.dims) == 2]  # not zero points
    assert weights
    assert max(int(np.abs(w.astype(np.int32)).max()) for w in weights) <= 64
    assert max(int(np.abs(w.astype(np.int32)).max()) for w in weights) >= 32  # the range is used, not collapsed


def test_default_output_path_and_scheme(fp32_models):
    report = q8.quantize_model(fp32_models["fusion"])
    assert report.path == fp32_models["fusion"].with_name(fp32_models["fusion"].stem + ".int8.onnx")
    assert report.scheme == q8.DEFAULT_SCHEME == "dynamic-int8" and report.calibration is None


def test_refuses_bad_arguments(fp32_models, tmp_path):
    fp32 = fp32_models["shallow"]
    with pytest.raises(ValueError, match="scheme must be one of"):
        q8.quantize_model(fp32, tmp_path / "a.onnx", scheme="int4")
    with pytest.raises(ValueError, match="takes none"):
        q8.quantize_model(fp32, tmp_path / "a.onnx", calibration=q8.random_calibration(32, n=4))
    with pytest.raises(ValueError, match="input_size"):
        q8.quantize_model(fp32, tmp_path / "a.onnx", scheme="static-qdq-int8", calibration=q8.random_calibration(16, n=4))
    int8 = q8.quantize_model(fp32, tmp_path / "b.onnx").path
    with pytest.raises(ValueError, match="already quantised"):
        q8.quantize_model(int8, tmp_path / "c.onnx")
    assert not (tmp_path / "a.onnx").exists() and not (tmp_path / "c.onnx").exists()


def test_refuses_to_write_a_model_beyond_the_bound(fp32_models, tmp_path):
    # Calibrated on black crops only, static ranges clip everything the parity inputs contain.
    s = CONFIGS["shallow"]["input_size"]
    black = q8.Calibration(np.zeros((16, s, s, 3), np.uint8), np.tile([1, 0, 0, 0], (16, 1)).astype(np.float32), "black")
    out = tmp_path / "bad.int8.onnx"
    with pytest.raises(q8.QuantizationError, match="refusing to write") as err:
        q8.quantize_model(fp32_models["shallow"], out, scheme="static-qdq-int8", calibration=black)
    assert not err.value.agreement.passed
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == []


def test_enforce_false_reports_the_agreement_and_writes(fp32_models, tmp_path):
    # The same out-of-bound model: measured and reported, not acted on (speed benchmarks of random weights).
    s = CONFIGS["shallow"]["input_size"]
    black = q8.Calibration(np.zeros((16, s, s, 3), np.uint8), np.tile([1, 0, 0, 0], (16, 1)).astype(np.float32), "black")
    report = q8.quantize_model(fp32_models["shallow"], tmp_path / "bad.int8.onnx", scheme="static-qdq-int8",
                               calibration=black, enforce=False)
    assert report.path.is_file() and not report.agreement.passed and not report.agreement.enforced
    assert "reported" in str(report.agreement) and "not enforced" in str(report.agreement)


@pytest.fixture(scope="module")
def cubes(tmp_path_factory):
    data = tmp_path_factory.mktemp("cubes") / "data"
    make_cube_dataset(data, scenes=2, frames=40)
    return data


def test_dataset_calibration_uses_held_out_training_crops(fp32_models, cubes, tmp_path):
    contract = parse_metadata(_props(fp32_models["fusion"]))
    cal = q8.dataset_calibration(cubes, contract, n=16, n_check=8, cache_root=tmp_path / "cache")
    assert cal.images.shape == (16, 32, 32, 3) and cal.check_images.shape == (8, 32, 32, 3)
    assert cal.q_in.dtype == np.float32 and cal.source.endswith("train_base:16")
    np.testing.assert_allclose(np.linalg.norm(cal.q_in, axis=1), 1, atol=1e-6)
    # Calibration and check crops are distinct training crops (cubes on a noisy background differ).
    assert not any(np.array_equal(a, b) for a in cal.images for b in cal.check_images)
    report = q8.quantize_model(fp32_models["fusion"], tmp_path / "c.int8.onnx", scheme="static-qdq-int8", calibration=cal)
    assert report.heldout_agreement is not None and report.heldout_agreement.passed
    assert report.enforced is report.heldout_agreement and not report.agreement.enforced
    assert _props(report.path)["int8_calibration"] == cal.source


def test_dataset_calibration_leaves_out_the_recorded_extra_training_folders(fp32_models, cubes, tmp_path):
    # A shipped model records its extra training folders by name only (no machine paths), so they cannot be found
    # from another folder: calibration draws from the recorded split's own training part of the data given.
    import json

    from models.data.pipeline import DataSpec

    props = _props(fp32_models["fusion"])
    spec = DataSpec(data="a_set").as_dict()
    plain = parse_metadata({**props, "data": json.dumps(spec)})
    named = parse_metadata({**props, "data": json.dumps({**spec, "extra_train": ["a_set_rendered_elsewhere"]})})
    a = q8.dataset_calibration(cubes, plain, n=8, n_check=4, cache_root=tmp_path / "cache")
    b = q8.dataset_calibration(cubes, named, n=8, n_check=4, cache_root=tmp_path / "cache")
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.q_in, b.q_in)


def test_cli_export_help_mentions_int8():
    result = CliRunner().invoke(cli_main, ["export", "--help"])
    assert result.exit_code == 0
    for option in ("--int8", "--int8-scheme", "--calib", "dynamic-int8", "static-qdq-int8"):
        assert option in result.output


def test_cli_export_int8(tmp_path, cubes):
    torch.manual_seed(0)
    model = models.build_refiner("fusion", **CONFIGS["fusion"])
    ckpt = models.save_checkpoint(model, tmp_path / "f.pt", **INFO)
    models.save_checkpoint(model, tmp_path / "f.003_cracker_box.pt", **INFO)  # a per-object fine-tuned sibling
    runner = CliRunner()
    result = runner.invoke(cli_main, ["export", str(ckpt), "--int8"])
    assert result.exit_code == 0, result.output
    assert "parity OK" in result.output and "INT8 agreement OK" in result.output
    fp32, int8 = tmp_path / "f.onnx", tmp_path / "f.int8.onnx"
    assert _props(fp32)["quantization"] == "none" and _props(int8)["quantization"] == "dynamic-int8"
    assert RefinerSession(int8).contract.quantization == "dynamic-int8"
    # Siblings sit where `refiner-rt eval` looks for them next to either base model.
    assert _props(tmp_path / "f.003_cracker_box.onnx")["quantization"] == "none"
    assert _props(tmp_path / "f.int8.003_cracker_box.onnx")["quantization"] == "dynamic-int8"
    # --calib selects static QDQ calibrated on the dataset's training crops.
    out = tmp_path / "g.onnx"
    result = runner.invoke(cli_main, ["export", str(ckpt), "-o", str(out), "--int8", "--calib", str(cubes)])
    assert result.exit_code == 0, result.output
    assert "held-out calibration crops" in result.output
    assert _props(tmp_path / "g.int8.onnx")["quantization"] == "static-qdq-int8"  # two 3/8-channel convs: FC only
    # A network with two or more convolutions of 16+ input channels gets the conv scheme from --calib alone.
    torch.manual_seed(0)
    wide = models.build_refiner("fusion", **{**CONFIGS["fusion"], "conv_channels": [8, 16, 16, 16]})
    wide_ckpt = models.save_checkpoint(wide, tmp_path / "w.pt", **INFO)
    result = runner.invoke(cli_main, ["export", str(wide_ckpt), "--int8", "--calib", str(cubes)])
    assert result.exit_code == 0, result.output
    assert _props(tmp_path / "w.int8.onnx")["quantization"] == "static-qdq-int8-conv"
    # Option combinations that make no sense are refused.
    result = runner.invoke(cli_main, ["export", str(ckpt), "--calib", str(cubes)])
    assert result.exit_code != 0 and "add --int8" in result.output
    result = runner.invoke(cli_main, ["export", str(ckpt), "--int8", "--int8-scheme", "dynamic-int8", "--calib", str(cubes)])
    assert result.exit_code != 0 and "takes no calibration data" in result.output
