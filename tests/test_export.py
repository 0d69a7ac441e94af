"""export: ONNX graph contract, metadata, parity (enforced), OpenCV cv2.dnn agreement, and `refiner-rt export`."""

import os
import stat
from pathlib import Path

from click.testing import CliRunner
import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from export import onnx_export, parity
import export
from export.defaults import LRN_LOWERING_NAMES
import models
from models.train.checkpoint import file_sha256
from refiner_rt import __version__
from refiner_rt.cli import main as cli_main
from refiner_rt.metadata import INPUT_IMAGE, INPUT_QUATERNION, OUTPUT_QUATERNION, parse_metadata
from tests.test_models import small_config

INFO = {"objects": ["003_cracker_box", "035_power_drill"], "train_noise": "uniform:0:30"}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """Both archs (small configs) exported once, VGG-M with both LRN lowerings: {key: (model, report, ckpt or None)}."""
    out = {}
    torch.manual_seed(0)
    # shallow: through a checkpoint, with the default output path.
    d = tmp_path_factory.mktemp("shallow")
    model = models.build_refiner("shallow", **small_config("shallow"))
    ckpt = models.save_checkpoint(model, d / "shallow.pt", **INFO)
    report = export.export_checkpoint(ckpt)
    loaded, _ = models.load_checkpoint(ckpt)
    out["shallow"] = (loaded, report, ckpt)
    # vggm: an in-memory model left in training mode (dropout on): export must evaluate it in eval mode.
    d = tmp_path_factory.mktemp("vggm")
    model = models.build_refiner("vggm", **{**small_config("vggm"), "input_size": 96}).train()
    report = export.export_model(model, d / "vggm.onnx", info={"rotation_frame": "ray"}, metadata_extra={"note": "test"})
    assert model.training, "export must restore the model's training mode"
    out["vggm"] = (model.eval(), report, None)
    d = tmp_path_factory.mktemp("vggm_lrn")
    out["vggm-LRN"] = (model, export.export_model(model, d / "vggm_lrn.onnx", lrn="LRN"), None)
    return out


ARCHS = ["shallow", "vggm", "vggm-LRN"]


@pytest.mark.parametrize("arch", ARCHS)
def test_report_and_enforced_parity(exported, arch):
    model, report, _ = exported[arch]
    assert report.path.is_file() and report.arch == arch.split("-")[0]
    assert report.max_abs_dq <= 1e-4 and report.tol == 1e-4
    assert report.n_parity >= 64 and report.opset == export.DEFAULT_OPSET
    assert report.size_bytes == report.path.stat().st_size
    assert "parity OK" in report.summary() and str(report.path) in report.summary()
    # Independent re-check on other inputs.
    result = export.check_parity(model, report.path, n=64, seed=123)
    assert result.passed, str(result)


@pytest.mark.parametrize("arch", ARCHS)
def test_graph_contract_dynamic_batch_self_contained(exported, arch):
    model, report, _ = exported[arch]
    proto = onnx.load(str(report.path), load_external_data=False)
    s = model.input_size

    def io(values):
        return [
            (v.name, v.type.tensor_type.elem_type, [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim])
            for v in values
        ]

    assert io(proto.graph.input) == [
        (INPUT_IMAGE, onnx.TensorProto.UINT8, ["batch", s, s, 3]),
        (INPUT_QUATERNION, onnx.TensorProto.FLOAT, ["batch", 4]),
    ]
    assert io(proto.graph.output) == [(OUTPUT_QUATERNION, onnx.TensorProto.FLOAT, ["batch", 4])]
    assert all(t.data_location != onnx.TensorProto.EXTERNAL for t in proto.graph.initializer)
    assert sorted(p.name for p in report.path.parent.iterdir() if p.suffix != ".pt") == [report.path.name]
    ops = [n.op_type for n in proto.graph.node]
    assert "If" not in ops
    assert ops.count("LRN") == {"shallow": 0, "vggm": 0, "vggm-LRN": 2}[arch]
    assert ops.count("Sqrt") == {"shallow": 0, "vggm": 4, "vggm-LRN": 0}[arch]
    # Any batch size runs.
    images, q = parity.random_inputs(s, 7, seed=3)
    sess = ort.InferenceSession(str(report.path), providers=["CPUExecutionProvider"])
    (q_out,) = sess.run([OUTPUT_QUATERNION], {INPUT_IMAGE: images, INPUT_QUATERNION: q})
    assert q_out.shape == (7, 4)
    np.testing.assert_allclose(np.linalg.norm(q_out, axis=1), 1.0, atol=1e-5)


@pytest.mark.parametrize("arch", ARCHS)
def test_nodes_carry_no_trace_of_the_exporting_machine(exported, arch):
    # The exporter's per-node stack traces name the source files of the machine that exported.
    _, report, _ = exported[arch]
    proto = onnx.load(str(report.path), load_external_data=False)
    assert all(len(n.metadata_props) == 0 for n in proto.graph.node)
    assert str(Path(models.__file__).resolve().parent) not in report.path.read_bytes().decode("latin-1")


def test_metadata_contract(exported):
    model, report, ckpt = exported["shallow"]
    proto = onnx.load(str(report.path), load_external_data=False)
    contract = parse_metadata({p.key: p.value for p in proto.metadata_props})
    assert contract.arch == "shallow" and contract.input_size == model.input_size
    assert contract.channel_order == "BGR" and contract.crop_context == 1.2
    assert contract.rotation_frame == "camera" and contract.quantization == "none"
    assert contract.objects == tuple(INFO["objects"]) and contract.train_noise == INFO["train_noise"]
    assert contract.checkpoint_sha256 == file_sha256(ckpt)
    assert contract.version == __version__
    assert report.path == ckpt.with_suffix(".onnx")

    vggm_proto = onnx.load(str(exported["vggm"][1].path), load_external_data=False)
    vggm = parse_metadata({p.key: p.value for p in vggm_proto.metadata_props})
    assert vggm.arch == "vggm" and vggm.rotation_frame == "ray" and vggm.objects == ()
    assert vggm.train_noise == "unknown" and vggm.checkpoint_sha256 == "none" and vggm.extra["note"] == "test"


@pytest.mark.parametrize("arch", ARCHS)
def test_opencv_dnn_agrees_with_torch_on_uint8_input(exported, arch):
    model, report, _ = exported[arch]
    images, q = parity.random_inputs(model.input_size, 64, seed=7)
    got = parity.opencv_dnn_outputs(report.path, images, q)
    expected = parity.torch_outputs(model, images, q)
    assert np.abs(got - expected).max() <= 1e-4


def test_exporter_refuses_on_parity_failure(monkeypatch, tmp_path):
    real = parity.onnxruntime_outputs
    monkeypatch.setattr(parity, "onnxruntime_outputs", lambda *a, **k: real(*a, **k) + np.float32(3e-3))
    model = models.build_refiner("shallow", **small_config("shallow"))
    out = tmp_path / "bad.onnx"
    with pytest.raises(export.ParityError, match=r"refusing to write .*bad.onnx.*max \|dq\| = 0.003") as err:
        export.export_model(model, out)
    assert err.value.max_abs_dq == pytest.approx(3e-3, rel=1e-3) and err.value.tol == 1e-4
    assert list(tmp_path.iterdir()) == [], "nothing (not even a temp file) may be left behind"


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"opset": 17}, r"opset must be an int >= 18"),
        ({"lrn": "fast"}, r"lrn must be one of \['LRN', 'decomposed'\]"),
        ({"n_parity": 10}, r"n_parity must be at least 64"),
        ({"tol": 0.0}, r"tol must be > 0"),
        ({"metadata_extra": {"arch": "x"}}, r"must not redefine contract key\(s\) \['arch'\]"),
        ({"info": {"objects": "003_cracker_box"}}, r"'objects' must be a JSON list"),
    ],
)
def test_export_argument_errors(tmp_path, kwargs, match):
    model = models.build_refiner("shallow", **small_config("shallow"))
    with pytest.raises(ValueError, match=match):
        export.export_model(model, tmp_path / "m.onnx", **kwargs)
    assert not (tmp_path / "m.onnx").exists()


def test_export_rejects_non_refiner_and_missing_directory(tmp_path):
    with pytest.raises(ValueError, match="models.build_refiner"):
        export.export_model(torch.nn.Linear(4, 4), tmp_path / "m.onnx")
    model = models.build_refiner("shallow", **small_config("shallow"))
    with pytest.raises(ValueError, match="directory does not exist"):
        export.export_model(model, tmp_path / "no" / "m.onnx")


def test_parity_helpers():
    slices = parity.batch_slices(64)
    assert [s.stop - s.start for s in slices][:3] == [1, 3, 16]
    assert np.array_equal(np.concatenate([np.arange(64)[s] for s in slices]), np.arange(64))
    a_img, a_q = parity.random_inputs(8, 5, seed=1)
    b_img, b_q = parity.random_inputs(8, 5, seed=1)
    assert a_img.dtype == np.uint8 and a_img.shape == (5, 8, 8, 3) and a_q.dtype == np.float32
    np.testing.assert_array_equal(a_img, b_img)
    np.testing.assert_allclose(np.linalg.norm(a_q, axis=1), 1.0, atol=1e-6)
    assert not parity.ParityResult(float("nan"), 64, 1e-4).passed


# ---------------------------------------------------------------- CLI
def test_cli_export_help():
    result = CliRunner().invoke(cli_main, ["export", "--help"])
    assert result.exit_code == 0, result.output
    for text in ("CHECKPOINT", "--output", "--opset", "--lrn", "uint8", "wxyz", "1e-4"):
        assert text in result.output
    assert "--int8" in result.output  # INT8 export is implemented


def test_cli_export_default_shallow(tmp_path):
    torch.manual_seed(0)
    previous = os.umask(0o022)
    try:
        ckpt = models.save_checkpoint(models.build_refiner("shallow"), tmp_path / "paper.pt", **INFO)
        out = tmp_path / "paper_fp32.onnx"
        result = CliRunner().invoke(cli_main, ["export", str(ckpt), "-o", str(out), "--opset", "18"])
    finally:
        os.umask(previous)
    assert result.exit_code == 0, result.output
    # written with the user's umask, as any new file (tempfile.mkstemp's 0600 would leave them private)
    assert stat.S_IMODE(out.stat().st_mode) == 0o644 and stat.S_IMODE(ckpt.stat().st_mode) == 0o644
    assert "parity OK: max |dq| = " in result.output and str(out) in result.output and " MB" in result.output
    proto = onnx.load(str(out), load_external_data=False)
    contract = parse_metadata({p.key: p.value for p in proto.metadata_props})
    assert (contract.arch, contract.input_size) == ("shallow", 64)


def test_cli_export_errors(tmp_path):
    runner = CliRunner()
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"definitely not a checkpoint")
    result = runner.invoke(cli_main, ["export", str(junk)])
    assert result.exit_code == 2 and "Invalid value for 'CHECKPOINT'" in result.output
    assert "not a refiner-rt checkpoint" in result.output

    result = runner.invoke(cli_main, ["export", str(tmp_path / "missing.pt")])
    assert result.exit_code == 2 and "does not exist" in result.output

    ckpt = models.save_checkpoint(models.build_refiner("shallow", **small_config("shallow")), tmp_path / "s.pt")
    result = runner.invoke(cli_main, ["export", str(ckpt), "--opset", "13"])
    assert result.exit_code == 2 and "13 is not in the range x>=18" in result.output

    result = runner.invoke(cli_main, ["export", str(ckpt), "-o", str(junk / "m.onnx")])  # a file in the folder's way
    assert result.exit_code == 2 and "cannot create the folder" in result.output and "Traceback" not in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.pt", "s.pt"]


def test_cli_export_makes_a_missing_output_folder(tmp_path):
    """The CLI's output rule (refiner_rt.cli.prepare_output): -o into a folder that does not exist yet makes it."""
    ckpt = models.save_checkpoint(models.build_refiner("shallow", **small_config("shallow")), tmp_path / "s.pt")
    out = tmp_path / "new" / "deeper" / "m.onnx"
    result = CliRunner().invoke(cli_main, ["export", str(ckpt), "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert out.is_file() and out.stat().st_size > 0


def test_cli_export_into_an_unwritable_folder_is_one_error_line(monkeypatch, tmp_path):
    runner = CliRunner()
    ckpt = models.save_checkpoint(models.build_refiner("shallow", **small_config("shallow")), tmp_path / "s.pt")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with monkeypatch.context() as m:
            if os.access(locked, os.W_OK):  # root writes anywhere: let the check see the folder as others do
                real = os.access
                m.setattr(os, "access", lambda path, mode, **kw: str(path) != str(locked) and real(path, mode, **kw))
            result = runner.invoke(cli_main, ["export", str(ckpt), "-o", str(locked / "m.onnx")])
        assert result.exit_code == 2 and "is not writable" in result.output, result.output
        assert "Traceback" not in result.output and list(locked.iterdir()) == []
    finally:
        locked.chmod(0o700)

    def refuse(path):
        raise PermissionError(13, "Permission denied", str(path))

    # the folder passes the check but the write fails (a read-only mount, a race): still one line, exit 1
    monkeypatch.setattr(onnx_export, "new_temp_file_beside", refuse)
    result = runner.invoke(cli_main, ["export", str(ckpt), "-o", str(tmp_path / "m.onnx")])
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit), result.output
    assert "Traceback" not in result.output and "cannot write" in result.output and "Permission denied" in result.output


def test_cli_export_parity_failure_exits_nonzero(monkeypatch, tmp_path):
    real = parity.onnxruntime_outputs
    monkeypatch.setattr(parity, "onnxruntime_outputs", lambda *a, **k: real(*a, **k) + np.float32(1e-2))
    ckpt = models.save_checkpoint(models.build_refiner("shallow", **small_config("shallow")), tmp_path / "s.pt")
    result = CliRunner().invoke(cli_main, ["export", str(ckpt)])
    assert result.exit_code == 1 and "refusing to write" in result.output and "0.01" in result.output
    assert not ckpt.with_suffix(".onnx").exists()


@pytest.mark.parametrize("beta", [0.75, 0.5, 0.6])
def test_lrn_lowerings_match_torch(tmp_path, beta):
    """Both LRN lowerings (and the decomposition's sqrt / pow branches) equal F.local_response_norm."""

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.lrn = models.nets.blocks.LocalResponseNorm(5, 1e-2, beta, 2.0)

        def forward(self, x):
            return self.lrn(x)

    x = torch.rand(2, 11, 6, 6) * 20
    expected = torch.nn.functional.local_response_norm(x, 5, 1e-2, beta, 2.0).numpy()
    assert sorted(export.LRN_LOWERINGS) == sorted(LRN_LOWERING_NAMES)  # what `export --lrn` offers
    for name, lowering in export.LRN_LOWERINGS.items():
        program = torch.onnx.export(
            Net().eval(), (x,), dynamo=True, verbose=False, input_names=["x"],
            custom_translation_table={torch.ops.refiner_rt.local_response_norm.default: lowering},
        )
        path = tmp_path / f"{name}.onnx"
        program.save(str(path))
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        np.testing.assert_allclose(sess.run(None, {"x": x.numpy()})[0], expected, rtol=1e-5, atol=1e-6, err_msg=name)
