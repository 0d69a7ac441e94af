"""The refiner-rt click group: every subcommand's --help, lazy imports, and the runtime subcommands."""

import json
import subprocess
import sys

import pytest
from click.testing import CliRunner

import onnx_fixtures as fx
from refiner_rt.cli import LAZY_COMMANDS, main


def test_group_help_lists_every_command_without_importing_them():
    res = CliRunner().invoke(main, ["--help"])
    assert res.exit_code == 0
    for name in LAZY_COMMANDS:
        assert name in res.output
    # Listing commands must not import torch (the runtime path stays light).
    code = "import sys; from click.testing import CliRunner; from refiner_rt.cli import main; CliRunner().invoke(main, ['--help']); assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("name", ["export", "info", "models", "bench", "demo"])
def test_runtime_and_export_help_do_not_import_torch(name):
    """`--help` of these answers at once: torch (seconds to import) is loaded only when a command needs it."""
    code = ("import sys; from click.testing import CliRunner; from refiner_rt.cli import main; "
            f"r = CliRunner().invoke(main, [{name!r}, '--help']); assert r.exit_code == 0, r.output; "
            "assert 'torch' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_missing_training_dependency_is_named_not_a_traceback(tmp_path):
    """In a runtime-only install (here: torch and onnx made unimportable) `export` says what to install."""
    ckpt = tmp_path / "m.pt"
    ckpt.write_bytes(b"x")
    code = ("import sys; sys.modules['torch'] = None; sys.modules['onnx'] = None; "
            f"from refiner_rt.cli import main; main(['export', {str(ckpt)!r}])")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert "'refiner-rt export' needs" in done.stderr and "pip install 'refiner-rt[train]'" in done.stderr


@pytest.mark.parametrize("name", sorted(LAZY_COMMANDS))
def test_every_subcommand_help(name):
    res = CliRunner().invoke(main, [name, "--help"])
    assert res.exit_code == 0, res.output
    assert "Usage:" in res.output and name in res.output


def test_info_prints_the_contract(tmp_path):
    path = tmp_path / "m.onnx"
    path.write_bytes(fx.constant_model([1, 0, 0, 0]))
    res = CliRunner().invoke(main, ["info", str(path)])
    assert res.exit_code == 0, res.output
    assert "quaternion_order" in res.output and "wxyz" in res.output and "q_out" in res.output
    res = CliRunner().invoke(main, ["info", str(path), "--json"])
    d = json.loads(res.output)
    assert d["metadata"]["arch"] == "test" and d["parameters"] == 5 and d["inputs"][0]["name"] == "image"


def test_info_on_a_file_that_is_not_onnx_is_one_line(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("not a model")
    res = CliRunner().invoke(main, ["info", str(path)])
    assert res.exit_code == 1
    assert res.output.count("\n") == 1 and "Traceback" not in res.output
    assert str(path) in res.output  # the message names the file, whichever layer reports it


def test_info_refuses_a_model_without_contract(tmp_path):
    path = tmp_path / "bad.onnx"
    path.write_bytes(fx.constant_model([1, 0, 0, 0], props={}))
    res = CliRunner().invoke(main, ["info", str(path)])
    assert res.exit_code != 0 and "missing required key" in res.output


def test_bench_with_given_models_writes_json_rows(tmp_path):
    a, b = tmp_path / "shallow.onnx", tmp_path / "vggm.onnx"
    a.write_bytes(fx.constant_model([1, 0, 0, 0], size=16, props=fx.contract(input_size=16, arch="shallow")))
    b.write_bytes(fx.channel_mean_model(size=16, props=fx.contract(input_size=16, arch="vggm")))
    out = tmp_path / "bench.json"
    res = CliRunner().invoke(main, ["bench", "--cpu", "--model", str(a), "--model", str(b), "--seconds", "0.1",
                                    "--batch", "1,2", "--threads", "1", "--json", str(out)])
    assert res.exit_code == 0, res.output
    rows = json.loads(out.read_text())
    assert len(rows) == 4
    for r in rows:
        for key in ("arch", "runtime", "threads", "batch", "fps", "p50_ms", "p90_ms", "ratio_shallow_over_vggm"):
            assert key in r
        assert r["fps"] > 0 and r["p90_ms"] >= r["p50_ms"]
    shallow = [r for r in rows if r["arch"] == "shallow"]
    assert all(r["ratio_shallow_over_vggm"] > 0 for r in shallow)
    assert "refinements/s" in res.output


def test_bench_rejects_bad_options():
    res = CliRunner().invoke(main, ["bench", "--batch", "0"])
    assert res.exit_code != 0 and "batch" in res.output
    res = CliRunner().invoke(main, ["bench", "--threads", "many"])
    assert res.exit_code != 0 and "thread counts" in res.output
