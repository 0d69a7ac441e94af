"""refiner_rt.bench (the runtime's timer) and export.bench (its training side: operation counts and roofline bounds,
PyTorch eager rows): interleaved timing, variants, and `refiner-rt bench` rows."""

import json

import click
from click.testing import CliRunner
import numpy as np
from onnx import TensorProto, helper, numpy_helper
import pytest

from tests import onnx_fixtures as fx
from tests.bench_scripts import load_benchmark
from export import bench as paper
from export import bench_models
from export.defaults import DEFAULT_SCHEME
from refiner_rt import bench
from refiner_rt import pretrained as pt
from refiner_rt.cli import RUNTIME_COMMANDS, main
from tests.test_pretrained import weights  # noqa: F401  (fixture: two constant-output models in place of the shipped ones)


def _graph_model(nodes, inits, inputs, outputs, path):
    graph = helper.make_graph(nodes, "g", inputs, outputs, initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    helper.set_model_props(model, fx.contract(input_size=8))
    path.write_bytes(model.SerializeToString())
    return path


def test_model_cost_counts_conv_and_gemm_in_fp32(tmp_path):
    w = np.zeros((6, 3, 5, 5), np.float32)   # conv 3 -> 6, 5x5, pad 2: 8x8 output
    g = np.zeros((10, 384), np.float32)      # Gemm transB: 384 -> 10
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"], pads=[2, 2, 2, 2]),
        helper.make_node("Flatten", ["c"], ["f"]),
        helper.make_node("Gemm", ["f", "g"], ["y"], transB=1),
    ]
    path = _graph_model(
        nodes, [numpy_helper.from_array(w, "w"), numpy_helper.from_array(g, "g")],
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["batch", 3, 8, 8])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["batch", 10])], tmp_path / "m.onnx",
    )
    cost = paper.model_cost(path)
    assert cost.weight_bytes == w.nbytes + g.nbytes
    assert cost.flops == 2 * (8 * 8 * 6 * 3 * 25 + 384 * 10)
    assert cost.int8_ops == 0 and cost.quantization == "none"


def test_model_cost_counts_quantised_layers_as_int8(tmp_path):
    b = np.zeros((64, 32), np.int8)
    nodes = [
        helper.make_node("DynamicQuantizeLinear", ["x"], ["xq", "xs", "xz"]),
        helper.make_node("MatMulInteger", ["xq", "b", "xz"], ["y"]),
    ]
    path = _graph_model(
        nodes, [numpy_helper.from_array(b, "b")],
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["batch", 64])],
        [helper.make_tensor_value_info("y", TensorProto.INT32, ["batch", 32])], tmp_path / "q.onnx",
    )
    cost = paper.model_cost(path)
    assert cost.int8_ops == 2 * 64 * 32 and cost.flops == 0 and cost.weight_bytes == b.nbytes


def test_roofline_bound_takes_the_slower_limit():
    limits = paper.MachineLimits(bandwidth=10e9, peak_fp32={1: 100e9}, peak_int8={1: 400e9})
    cost = paper.ModelCost(weight_bytes=10_000_000, flops=10e6, int8_ops=40e6)  # 1 ms memory; 0.2 ms per crop
    fps, limit = paper.roofline_bound(cost, 1, 1, limits)
    assert limit == "memory" and fps == pytest.approx(1000.0)
    fps, limit = paper.roofline_bound(cost, 10, 1, limits)  # 2 ms of compute for 10 crops
    assert limit == "compute" and fps == pytest.approx(10 / 2e-3)


def test_measured_limits_are_plausible():
    assert paper.measure_bandwidth(megabytes=16, repeats=2) > 1e8
    assert paper.measure_peak(int8=False, threads=1, size=128, repeats=2) > 1e8
    assert paper.measure_peak(int8=True, threads=1, size=128, repeats=2) > 1e8


def test_measure_interleaved_takes_turns_and_honours_min_calls():
    order = []
    runners = {name: (lambda n=name: order.append(n)) for name in ("a", "b")}
    lat = bench.measure_interleaved(runners, seconds=0.0, rounds=3, min_calls=3)
    assert {k: len(v) for k, v in lat.items()} == {"a": 3, "b": 3}
    timed = order[-6:]
    assert timed == ["a", "b"] * 3  # one call each per round, alternating


def test_parse_variant():
    assert bench.parse_variant('h512=shallow:{"head_widths": [512, 256, 64]}') == (
        "h512", "shallow", {"head_widths": [512, 256, 64]}
    )
    label, arch, config = bench.parse_variant('fusion:{"fuse_width": 256}')
    assert (label, arch, config) == ('fusion:{"fuse_width":256}', "fusion", {"fuse_width": 256})
    for bad in ("shallow", "shallow:[1]", "shallow:{oops", ':{"a": 1}'):
        with pytest.raises(Exception, match="ARCH:JSON"):
            bench.parse_variant(bad)


ROW_KEYS = ("arch", "runtime", "threads", "batch", "fps", "p50_ms", "p90_ms", "ratio_shallow_over_vggm", "quantization",
            "weights", "ratio_over_shallow", "config", "weight_bytes", "flops_per_call", "int8_ops_per_call", "bound_fps",
            "bound", "roofline_ratio", "roofline_note", "bandwidth_gbs", "peak_fp32_gflops", "peak_int8_gops")


def test_bench_json_rows_carry_quantization_and_roofline_fields(tmp_path):
    a, b = tmp_path / "shallow.onnx", tmp_path / "vggm.onnx"
    a.write_bytes(fx.constant_model([1, 0, 0, 0], size=16, props=fx.contract(input_size=16, arch="shallow")))
    b.write_bytes(fx.channel_mean_model(size=16, props=fx.contract(input_size=16, arch="vggm")))
    out = tmp_path / "bench.json"
    res = CliRunner().invoke(main, ["bench", "--model", str(a), "--model", str(b), "--seconds", "0.05",
                                    "--batch", "1,3", "--threads", "1", "--json", str(out)])
    assert res.exit_code == 0, res.output
    rows = json.loads(out.read_text())
    assert len(rows) == 4
    for r in rows:
        for key in ROW_KEYS:
            assert key in r
        assert r["quantization"] == "none" and r["bound"] in ("memory", "compute") and r["weights"] == "user-supplied"
        if r["roofline_note"] is None:
            assert r["roofline_ratio"] == pytest.approx(r["fps"] / r["bound_fps"]) and 0 < r["roofline_ratio"] <= 1
        else:
            assert r["roofline_ratio"] is None and r["fps"] > r["bound_fps"]
        assert r["bandwidth_gbs"] > 0 and r["peak_fp32_gflops"] > 0 and r["peak_int8_gops"] > 0
    assert "Roofline: measured in each of the 2 cells" in res.output and "of bound" in res.output


def test_a_row_faster_than_its_bound_gets_no_ratio():
    # A bound measured on a busy machine (or weights served from cache) can lie below what the model achieved: the
    # row then says so instead of reading as more than 100% of the hardware.
    cost = paper.ModelCost(weight_bytes=10_000_000, flops=10e6, int8_ops=0)
    limits = paper.MachineLimits(bandwidth=10e9, peak_fp32={1: 100e9}, peak_int8={1: 400e9})  # bound: 1,000/s
    fast = bench.BenchRow(arch="a", runtime="onnxruntime", threads=1, batch=1, fps=1500.0, p50_ms=0.67, p90_ms=0.7,
                          calls=10, model="a")
    paper._fill_roofline(fast, cost, limits)
    assert fast.bound_fps == pytest.approx(1000.0) and fast.roofline_ratio is None and "1.50x its bound" in fast.roofline_note
    slow = bench.BenchRow(arch="a", runtime="onnxruntime", threads=1, batch=1, fps=500.0, p50_ms=2.0, p90_ms=2.1,
                          calls=10, model="b")
    paper._fill_roofline(slow, cost, limits)
    assert slow.roofline_ratio == pytest.approx(0.5) and slow.roofline_note is None
    table = bench.format_table([fast, slow])
    assert "| 50% |" in table and "n/a*" in table and "150%" not in table


def test_limit_probe_takes_turns_with_the_models_and_keeps_the_best_round():
    probe = paper.LimitProbe(megabytes=4, size=64)
    order = []
    runners = {("onnxruntime", 0): lambda: order.append("model")}
    for key, fn in probe.runners(1).items():
        runners[key] = (lambda k=key, f=fn: (order.append(k), f()))
    lat = bench.measure_interleaved(runners, seconds=0.0, rounds=3, min_calls=3)
    assert order[-4:] == ["model", probe.BANDWIDTH, probe.FP32, probe.INT8]  # one round: models and limits in turn
    limits = probe.limits(1, lat)
    assert limits.bandwidth == pytest.approx(2 * 4 * 2**20 / min(lat[probe.BANDWIDTH]))
    assert limits.peak_fp32[1] == pytest.approx(2 * 64**3 / min(lat[probe.FP32])) and limits.peak_int8[1] > 0


def test_bench_times_a_viewing_ray_model(tmp_path):
    # Trained models use the viewing-ray frame, whose refine() needs the camera intrinsics: bench passes its frame's.
    ray = tmp_path / "ray.onnx"
    ray.write_bytes(fx.constant_model([1, 0, 0, 0], size=16, props=fx.contract(input_size=16, rotation_frame="ray")))
    out = tmp_path / "bench.json"
    res = CliRunner().invoke(main, ["bench", "--model", str(ray), "--seconds", "0.05", "--batch", "2",
                                    "--threads", "1", "--json", str(out)])
    assert res.exit_code == 0, res.output
    rows = json.loads(out.read_text())
    assert len(rows) == 1 and rows[0]["fps"] > 0


def test_profile_refine_runs_on_camera_and_viewing_ray_models(tmp_path, capsys):
    module = load_benchmark("profile_refine")
    paths = []
    for frame in ("camera", "ray"):
        path = tmp_path / f"{frame}.onnx"
        path.write_bytes(fx.q_echo_model(size=16, props=fx.contract(input_size=16, rotation_frame=frame)))
        paths += ["--model", str(path)]
    assert module.main(paths + ["--seconds", "0.05", "--calls", "20"]) == 0
    table = capsys.readouterr().out.split("| model |")[1]
    assert "| camera |" in table and "| ray |" in table


SMALL = {
    "shallow": {"input_size": 32, "conv_channels": [4, 8], "pose_widths": [16, 128], "head_widths": [64, 16]},
    "vggm": {"input_size": 64, "pose_widths": [8, 16], "head_widths": [16, 8], "fc_widths": [32, 32]},
}


def test_bench_builds_fp32_and_int8_rows_of_variants(tmp_path):
    out = tmp_path / "results" / "bench.json"  # a folder that does not exist yet: the CLI's output rule makes it
    args = ["bench", "--shipped", "none", "--archs", "", "--variant", f"shallow=shallow:{json.dumps(SMALL['shallow'])}",
            "--variant", f"vggm=vggm:{json.dumps(SMALL['vggm'])}", "--batch", "1", "--threads", "1",
            "--seconds", "0.05", "--json", str(out)]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    rows = json.loads(out.read_text())
    cells = {(r["model"], r["runtime"], r["quantization"]) for r in rows}
    assert cells == {(m, rt, q) for m in ("shallow", "vggm")
                     for rt, q in (("onnxruntime", "none"), ("onnxruntime", DEFAULT_SCHEME), ("torch", "none"))}
    for r in rows:
        assert r["config"] == SMALL[r["model"]] and r["bound_fps"] > 0 and r["weights"] == "random"
        if r["runtime"] == "onnxruntime":
            assert r["ratio_onnxruntime_over_torch"] > 0
        if r["model"] == "shallow":
            assert r["ratio_shallow_over_vggm"] > 0
    int8 = next(r for r in rows if r["model"] == "shallow" and r["quantization"] == DEFAULT_SCHEME)
    fp32 = next(r for r in rows if r["model"] == "shallow" and r["quantization"] == "none" and r["runtime"] == "onnxruntime")
    assert int8["weight_bytes"] < fp32["weight_bytes"] / 2 and int8["int8_ops_per_call"] > 0
    assert fp32["int8_ops_per_call"] == 0 and fp32["flops_per_call"] > int8["flops_per_call"]


def test_bench_help_and_bad_options():
    res = CliRunner().invoke(main, ["bench", "--help"])
    assert res.exit_code == 0
    for text in ("--variant", "--int8", "--archs", "shallow,vggm", "--shipped", "1,8,32", "roofline"):
        assert text in res.output
    res = CliRunner().invoke(main, ["bench", "--variant", "shallow"])
    assert res.exit_code != 0 and "ARCH:JSON" in res.output
    res = CliRunner().invoke(main, ["bench", "--archs", "", "--shipped", "none"])
    assert res.exit_code != 0 and "nothing to benchmark" in res.output
    res = CliRunner().invoke(main, ["bench", "--shipped", "999_nothing"])
    assert res.exit_code == 2 and "999_nothing" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(main, ["bench", "--batch", "1,2000"])
    assert res.exit_code == 2 and "at most 1024" in res.output


def _disk_with_free(nbytes):
    import shutil

    real = shutil.disk_usage

    def usage(path):
        total, used, _ = real(path)
        return type(real(path))(total, used, nbytes)

    return usage


def test_bench_says_when_the_disk_cannot_hold_the_model_files(monkeypatch):
    monkeypatch.setattr(bench_models.shutil, "disk_usage", _disk_with_free(1 << 20))
    args = ["bench", "--shipped", "none", "--archs", "", "--variant", f"shallow=shallow:{json.dumps(SMALL['shallow'])}",
            "--seconds", "0.05"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code != 0 and isinstance(res.exception, SystemExit)
    assert "not enough free disk space" in res.output and "shallow's ONNX files" in res.output
    assert "1 MB is free" in res.output


def test_a_write_that_fails_on_a_full_disk_is_reported_as_such(tmp_path, monkeypatch):
    with pytest.raises(click.ClickException, match="not enough free disk space.*DecodeError: Wire format"):
        with bench_models._disk_full_is_clear(tmp_path, 1 << 40, "vggm"):
            raise type("DecodeError", (Exception,), {})("Wire format was corrupt")
    # With room left, the original error is not hidden.
    with pytest.raises(RuntimeError, match="unrelated"):
        with bench_models._disk_full_is_clear(tmp_path, 1, "vggm"):
            raise RuntimeError("unrelated")


def _without_torch(monkeypatch):
    """Make `bench` see a runtime-only install (no torch to build the default models with)."""
    real = bench.importlib.util.find_spec
    monkeypatch.setattr(bench.importlib.util, "find_spec", lambda name, *a: None if name == "torch" else real(name, *a))


def test_bench_times_a_shipped_model_beside_the_paper_network(weights, tmp_path):  # noqa: F811
    # By default: one representative shipped refiner (trained weights, INT8 and fp32) next to the paper's networks
    # (random weights), each row saying which weights it has, and its speed over the shallow network's.
    out = tmp_path / "bench.json"
    args = ["bench", "--archs", "", "--variant", f"shallow=shallow:{json.dumps(SMALL['shallow'])}", "--batch", "1",
            "--threads", "1", "--seconds", "0.05", "--no-torch", "--json", str(out)]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "shipped 003_cracker_box: trained weights, INT8 and fp32 (one representative of the 2" in res.output
    rows = json.loads(out.read_text())
    by_model = {(r["model"], r["quantization"] != "none"): r for r in rows if r["model"] != "shallow"}
    assert {r["model"] for r in rows} == {"003_cracker_box.int8", "003_cracker_box", "shallow"}
    shallow = {r["quantization"] != "none": r for r in rows if r["model"] == "shallow"}
    for r in by_model.values():
        assert r["weights"] == "trained"
        ref = shallow[r["quantization"] != "none"]
        assert r["ratio_over_shallow"] == pytest.approx(r["fps"] / ref["fps"])
    assert all(r["weights"] == "random" and r["ratio_over_shallow"] is None for r in shallow.values())
    res = CliRunner().invoke(main, ["bench", "--archs", "", "--shipped", "all", "--batch", "1", "--threads", "1",
                                    "--seconds", "0.05", "--json", str(out)])
    assert res.exit_code == 0, res.output
    assert {r["model"] for r in json.loads(out.read_text())} == {
        "003_cracker_box.int8", "003_cracker_box", "011_banana.int8", "011_banana"}


def test_bench_without_torch_times_the_shipped_models(weights, monkeypatch):  # noqa: F811
    _without_torch(monkeypatch)
    res = CliRunner().invoke(main, ["bench", "--seconds", "0.05", "--batch", "1", "--threads", "1", "--shipped", "all"])
    assert res.exit_code == 0, res.output
    assert "torch is not installed" in res.output and "timing only the shipped models" in res.output
    assert "003_cracker_box" in res.output and "011_banana" in res.output


def test_bench_without_torch_or_shipped_models_is_one_line(tmp_path, monkeypatch):
    _without_torch(monkeypatch)
    monkeypatch.setattr(pt, "WEIGHTS_DIR", tmp_path)
    res = CliRunner().invoke(main, ["bench", "--seconds", "0.05"])
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert "needs torch" in res.output and "pass exported models with --model" in res.output
    assert "no shipped model" in res.output
def test_the_runtime_bench_imports_no_training_code():
    # The random-weight models, PyTorch eager and the roofline are the training side's (export.bench), which plugs
    # its bench command in; the runtime's own times ONNX files, and the wheel carries it alone.
    import re
    from pathlib import Path

    source = Path(bench.__file__).read_text()
    assert not re.search(r"^\s*(import|from) (models|export|torch|onnx)\b", source, re.M)
    assert RUNTIME_COMMANDS["bench"].target == "refiner_rt.cli.bench:bench_cmd"
    assert callable(bench_models.build_default_models)
    assert paper.bench_cmd.name == "bench" and isinstance(paper.PaperBench(), bench.BenchExtension)


def test_machine_info_records_the_cpu_vector_flags():
    import torch

    info = paper.machine_info()
    flags = info["cpu_flags"]
    assert isinstance(flags, list) and all(f.startswith(bench._SIMD_FLAG_PREFIXES) for f in flags)
    assert info["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert bench.machine_info()["cpu_capability"] is None  # the runtime's own never imports torch


def test_soak_reports_rss_over_the_calls_from_threads_sharing_one_session(tmp_path, capsys):
    module = load_benchmark("soak")
    model = tmp_path / "m.onnx"
    model.write_bytes(fx.random_weight_model(size=16, props=fx.contract(input_size=16)))
    out = tmp_path / "soak.json"
    argv = ["--model", str(model), "--calls", "600", "--warmup", "200", "--every", "50", "--callers", "3",
            "--json", str(out)]
    assert module.main(argv) == 0
    assert "growth after warm-up" in capsys.readouterr().out
    d = json.loads(out.read_text())
    assert d["calls"] == 600 and d["callers"] == 3 and d["torch_imported"] is False
    assert d["results_differing_from_the_first"] == 0
    assert [i for i, _ in d["samples"]] == list(range(50, 601, 50))
    assert "cpu_flags" in d["machine"] and d["rss_end"] > 0 and d["peak_rss"] > 0
    for key in ("growth_after_warmup", "growth_second_half", "slope_bytes_per_1000_calls", "calls_per_s"):
        assert isinstance(d[key], (int, float))
    with pytest.raises(SystemExit):
        module.main(["--model", str(model), "--calls", "100", "--warmup", "100"])


def test_study_json_is_stamped_with_schema_version_and_commit(tmp_path):
    from models.evaluate.record import SCHEMA_VERSION, write_json

    path = tmp_path / "sub" / "r.json"
    write_json(path, {"rows": [1], "schema_version": SCHEMA_VERSION})
    d = json.loads(path.read_text())
    assert list(d)[:2] == ["schema_version", "git_commit"] and d["schema_version"] == SCHEMA_VERSION
    assert d["rows"] == [1]
    assert d["git_commit"] is None or len(d["git_commit"].removesuffix("-dirty")) == 40
