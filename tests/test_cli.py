"""The refiner-rt click group: every subcommand's --help, lazy imports, and the runtime subcommands."""

import json
import subprocess
import sys
from pathlib import Path

from click.testing import CliRunner
import pytest

from tests import onnx_fixtures as fx
from refiner_rt.cli import ENTRY_POINT_GROUP, RUNTIME_COMMANDS, main, plugged_commands

# Every subcommand: the runtime's own and those the training package plugs in (pyproject.toml's entry points).
COMMANDS = sorted(set(RUNTIME_COMMANDS) | set(plugged_commands()))


def test_group_help_lists_every_command_without_importing_them():
    res = CliRunner().invoke(main, ["--help"])
    assert res.exit_code == 0
    for name in COMMANDS:
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
    assert "'refiner-rt export' needs" in done.stderr and "pip install -e '.[train]'" in done.stderr


@pytest.mark.parametrize("name", ["train", "render", "export", "eval"])
def test_a_training_command_in_a_runtime_only_install_says_what_to_install(name):
    """The wheel carries refiner_rt alone (here: the training package made unimportable): one line, no
    traceback, naming the source checkout's install."""
    code = ("import sys; [sys.modules.__setitem__(m, None) for m in ('models', 'export', 'benchmarks')]; "
            f"from refiner_rt.cli import main; main([{name!r}, '--help'])")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert done.stderr.count("\n") == 1, done.stderr
    assert f"'refiner-rt {name}' is part of the training package" in done.stderr
    assert "source checkout" in done.stderr and "pip install -e '.[train]'" in done.stderr


def test_bench_in_a_runtime_only_install_times_the_shipped_models_or_says_why_not():
    """Without the training package, `bench` still runs (it lives in refiner_rt) and says what the paper's
    networks need."""
    code = ("import sys; [sys.modules.__setitem__(m, None) for m in ('models', 'export', 'benchmarks')]; "
            "from refiner_rt.cli import main; main(['bench', '--cpu', '--archs', 'shallow', '--shipped', 'none'])")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert "training package" in done.stderr and "--model" in done.stderr


@pytest.mark.parametrize("name", sorted(COMMANDS))
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


# ---------------------------------------------------------------- bad files: a one-line error, never a traceback
import numpy as np  # noqa: E402
from onnx import TensorProto, helper  # noqa: E402

from refiner_rt.metadata import INPUT_IMAGE, INPUT_QUATERNION, OUTPUT_QUATERNION  # noqa: E402


def _fixed_batch_model() -> bytes:
    """A refiner whose batch axis is fixed to 1: it loads in onnxruntime but breaks the contract."""
    graph = helper.make_graph(
        [helper.make_node("Identity", [INPUT_QUATERNION], [OUTPUT_QUATERNION])],
        "fixed_batch",
        [helper.make_tensor_value_info(INPUT_IMAGE, TensorProto.UINT8, [1, 8, 8, 3]),
         helper.make_tensor_value_info(INPUT_QUATERNION, TensorProto.FLOAT, [1, 4])],
        [helper.make_tensor_value_info(OUTPUT_QUATERNION, TensorProto.FLOAT, [1, 4])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    helper.set_model_props(model, fx.contract())
    return model.SerializeToString()


@pytest.fixture(scope="module")
def bad_files(tmp_path_factory):
    """Corrupt inputs of every kind a subcommand reads: ``{name: path}`` (and an empty dataset folder)."""
    d = tmp_path_factory.mktemp("bad")
    rng = np.random.default_rng(39)
    files = {
        "random.onnx": rng.integers(0, 256, 4096, dtype=np.uint8).tobytes(),
        "empty.onnx": b"",
        "truncated.onnx": fx.constant_model([1, 0, 0, 0])[:200],
        "fixed_batch.onnx": _fixed_batch_model(),
        "random.pt": rng.integers(0, 256, 4096, dtype=np.uint8).tobytes(),
    }
    out = {}
    for name, data in files.items():
        out[name] = d / name
        out[name].write_bytes(data)
    out["data"] = d / "data"
    out["data"].mkdir()
    scene = d / "bop" / "000000"  # a BOP split whose ground truth is not JSON
    scene.mkdir(parents=True)
    (scene / "scene_gt.json").write_text("{not json")
    out["bop"] = scene.parent
    mesh = d / "meshes" / "003_cracker_box"  # a YCB-Video-style mesh folder whose mesh is random bytes
    mesh.mkdir(parents=True)
    (mesh / "textured_simple.obj").write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
    out["meshes"] = mesh.parent
    out["tmp"] = d
    return out


# (subcommand arguments with {placeholders}, the file the error line must name)
BAD_INVOCATIONS = [
    (["info", "{random.onnx}"], "random.onnx"),
    (["info", "{empty.onnx}"], "empty.onnx"),
    (["info", "{truncated.onnx}"], "truncated.onnx"),
    (["info", "{random.pt}"], "random.pt"),
    (["info", "{fixed_batch.onnx}"], "fixed_batch.onnx"),
    (["bench", "--model", "{random.onnx}", "--batch", "1", "--threads", "1", "--seconds", "0.05", "--no-torch"],
     "random.onnx"),
    (["bench", "--model", "{fixed_batch.onnx}", "--batch", "1", "--threads", "1", "--seconds", "0.05", "--no-torch"],
     "fixed_batch.onnx"),
    (["eval", "{random.onnx}", "--data", "{data}"], "random.onnx"),
    (["eval", "{truncated.onnx}", "--data", "{data}"], "truncated.onnx"),
    (["eval", "{random.pt}", "--data", "{data}"], "random.pt"),
    (["export", "{random.pt}"], "random.pt"),
    (["track", "{data}", "{random.pt}", "-o", "{tmp}/r.json"], "random.pt"),
    (["train", "--data", "{data}", "--out", "{tmp}/o.pt", "--base", "{random.pt}"], "random.pt"),
    (["train", "--data", "{bop}", "--out", "{tmp}/o.pt"], "scene_gt.json"),
    (["render", "--preview", "{tmp}/p.png", "--data", "{bop}"], "scene_gt.json"),
    (["demo", "--image", "{random.onnx}", "--box", "1,1,5,5", "--q", "1,0,0,0", "--K", "500,500,32,24", "--object",
      "003_cracker_box"], "random.onnx"),
    (["estimate", "{random.onnx}", "--K", "500,500,32,24", "--object", "003_cracker_box", "--box", "1,1,5,5"],
     "random.onnx"),
    (["render", "--out", "{tmp}/scenes", "--frames", "1", "--models", "{meshes}", "--objects", "003_cracker_box",
      "--width", "64", "--height", "48", "--quiet"], "textured_simple.obj"),
]


@pytest.mark.parametrize("args,names", BAD_INVOCATIONS, ids=lambda v: " ".join(v[:2]) if isinstance(v, list) else v)
def test_every_subcommand_fed_a_bad_file_fails_with_one_error_line(bad_files, args, names):
    argv = []
    for a in args:
        for key, path in bad_files.items():
            a = a.replace("{" + key + "}", str(path))
        argv.append(a)
    res = CliRunner().invoke(main, argv)
    assert res.exit_code != 0, res.output
    assert isinstance(res.exception, SystemExit), f"uncaught {type(res.exception).__name__}: {res.exception}"
    assert "Traceback" not in res.output
    errors = [line for line in res.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and names in errors[0], res.output


# Subcommands that read no file of the user's; their bad-input tests live beside their module's tests.
NO_USER_FILE = {"models"}  # the package's own index: tests/test_pretrained.py feeds it a corrupt one


def test_every_subcommand_is_covered_by_a_bad_file_test():
    assert {args[0] for args, _ in BAD_INVOCATIONS} == set(COMMANDS) - NO_USER_FILE


def test_the_training_commands_are_plugged_in_by_entry_points_not_named_by_the_runtime():
    """The runtime's command table names no training module; pyproject.toml declares the training commands, and the
    installed metadata lists the same (else `pip install -e .` must be rerun)."""
    import importlib.util
    import tomllib
    from pathlib import Path

    declared = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"][
        "entry-points"][ENTRY_POINT_GROUP]
    assert set(declared) == {"export", "train", "render", "eval", "bench"}
    installed = {name: ep.value for name, ep in plugged_commands().items()}
    assert installed == declared, "the installed metadata is stale: rerun pip install -e ."
    assert not any(c.target.split(".")[0] in ("models", "export", "benchmarks") for c in RUNTIME_COMMANDS.values())
    for value in declared.values():  # each names a torch-free LazyCommand in the training package
        module = value.split(":")[0]
        assert importlib.util.find_spec(module) is not None, module


@pytest.mark.parametrize("args", [
    ["demo", "--out", "{tmp}/demo.txt"],
    ["estimate", "{frame}", "--K", "1066.8,1067.5,313,241.3", "--object", "035_power_drill",
     "--box", "438,202,636,368", "--overlay", "{tmp}/overlay.txt"],
    ["track", "--bag", "{tmp}", "-o", "{tmp}/out_bag"],
], ids=["demo --out", "estimate --overlay", "track --bag"])
def test_a_picture_or_bag_path_the_command_cannot_use_is_one_error_line(tmp_path, args):
    """A picture suffix OpenCV does not write, and a folder that is no bag: named in one line, no traceback."""
    pytest.importorskip("rosbags")
    frame = Path(__file__).resolve().parents[1] / "refiner_rt" / "samples" / "000002_000001.jpg"
    argv = [a.replace("{tmp}", str(tmp_path)).replace("{frame}", str(frame)) for a in args]
    res = CliRunner().invoke(main, argv)
    assert res.exit_code == 1, res.output
    assert "Traceback" not in res.output and res.output.startswith("Error: ") and str(tmp_path) in res.output
    if args[0] != "track":
        assert ".png" in res.output  # what is expected


def test_prepare_output_makes_the_missing_folders_of_an_output_and_names_the_option_when_it_cannot(tmp_path):
    import click

    from refiner_rt.cli import prepare_output

    out = prepare_output(str(tmp_path / "a" / "b" / "poses.json"), "'--out'")
    assert out == tmp_path / "a" / "b" / "poses.json" and out.parent.is_dir() and not out.exists()
    assert prepare_output(Path("poses.json"), "'--out'") == Path("poses.json")  # the working folder: nothing to make
    (tmp_path / "file").write_text("x")
    with pytest.raises(click.BadParameter, match="cannot create the folder .*file") as err:
        prepare_output(tmp_path / "file" / "poses.json", "'--out'")
    assert err.value.param_hint == "'--out'"


@pytest.mark.parametrize("args, option", [
    (["demo", "--out", "{file}/demo.png"], "--out"),
    (["estimate", "{frame}", "--K", "1066.8,1067.5,313,241.3", "--object", "035_power_drill",
      "--box", "438,202,636,368", "--out", "{file}/poses.json"], "--out"),
    (["estimate", "{frame}", "--K", "1066.8,1067.5,313,241.3", "--object", "035_power_drill",
      "--box", "438,202,636,368", "--overlay", "{file}/poses.png"], "--overlay"),
    (["track", "{frames}", "{dets}", "-o", "{file}/rotations.json"], "--out"),
    (["track", "--bag", "{tmp}", "-o", "{file}/out_bag"], "--out"),
], ids=["demo --out", "estimate --out", "estimate --overlay", "track -o", "track --bag -o"])
def test_every_command_makes_a_missing_output_folder_by_one_rule(tmp_path, args, option):
    """demo, estimate and track treat an output's folder alike (refiner_rt.cli.prepare_output): a missing one is
    made (each command's own tests write into new folders), and one that cannot be made (a file in its way) is one
    error line naming the option, before any work."""
    from refiner_rt import pretrained_models

    if "--object" in args and "035_power_drill" not in {m.object_id for m in pretrained_models()}:
        pytest.skip("the shipped power-drill model is not in this checkout")
    file = tmp_path / "not_a_folder"
    file.write_text("{}")
    frame = Path(__file__).resolve().parents[1] / "refiner_rt" / "samples" / "000002_000001.jpg"
    frames, dets = tmp_path / "frames", tmp_path / "detections.json"  # readable inputs: the output is what is wrong
    frames.mkdir()
    (frames / frame.name).write_bytes(frame.read_bytes())
    dets.write_text(json.dumps({"K": [[1066.8, 0, 313.0], [0, 1067.5, 241.3], [0, 0, 1]], "frames": {frame.name: {
        "035_power_drill": {"box": [438, 202, 636, 368], "q": [1.0, 0.0, 0.0, 0.0]}}}}))
    if "{dets}" in args and "035_power_drill" not in {m.object_id for m in pretrained_models()}:
        pytest.skip("the shipped power-drill model is not in this checkout")
    argv = [a.replace("{tmp}", str(tmp_path)).replace("{file}", str(file)).replace("{frame}", str(frame))
            .replace("{frames}", str(frames)).replace("{dets}", str(dets)) for a in args]
    res = CliRunner().invoke(main, argv)
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and "cannot create the folder" in res.output and option in res.output
