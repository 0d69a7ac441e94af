"""Scoring every instance of a folder (real frames): `refiner-rt eval --all`, `benchmarks/real.py`, the crop cache of a
read-only folder. Models with known outputs (an identity correction, a fixed turn) give the expected errors in closed
form; SciPy draws the reference angles."""

import json
from pathlib import Path

from click.testing import CliRunner
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from refiner_rt.cli import main
from tests.data_fixtures import make_bop
from tests.onnx_fixtures import constant_model, contract


@pytest.fixture(scope="module")
def real_folder(tmp_path_factory):
    split = tmp_path_factory.mktemp("real") / "test"
    truths = make_bop(split)
    return split, truths


def _model(tmp_path: Path, q_out, obj="003_cracker_box") -> Path:
    path = tmp_path / f"{obj}.onnx"
    path.write_bytes(constant_model(q_out, props=contract(objects=[obj])))
    return path


def _visible(truths, obj):
    return [t for t in truths if t.obj_id == obj and t.visib_fract >= 0.3]


def test_all_scores_every_visible_instance_and_the_drift_of_a_fixed_turn(real_folder, tmp_path):
    split, truths = real_folder
    turn = Rotation.from_rotvec(np.radians(12.0) * np.array([0.0, 0.6, 0.8]))  # 12 deg about a unit axis
    x, y, z, w = turn.as_quat()
    model = _model(tmp_path, [w, x, y, z])
    out = tmp_path / "r.json"
    res = CliRunner().invoke(main, ["eval", str(model), "--data", str(split), "--all", "--draws", "4",
                                    "--json", str(out), "--cache", str(tmp_path / "cache"), "--quiet"])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    o = doc["objects"]["003_cracker_box"]
    assert o["instances"] == len(_visible(truths, "003_cracker_box")) == 2
    assert o["n"] == 2 * 4  # four draws per instance
    assert o["drift_mean_deg"] == pytest.approx(12.0, abs=1e-3)  # the true pose turned by the model's fixed 12 deg
    assert set(o["videos"]) == {"000048"}
    assert "drift" in res.output and "003_cracker_box" in res.output


def test_identity_model_leaves_the_input_error(real_folder, tmp_path):
    split, _ = real_folder
    model = _model(tmp_path, [1.0, 0.0, 0.0, 0.0], obj="009_gelatin_box")
    from models.evaluate.cli import run_eval_all

    r = run_eval_all(model, split, draws=5, threads=1, progress=False, cache_root=tmp_path / "c")
    o = r["objects"]["009_gelatin_box"]
    assert o["mean_deg"] == pytest.approx(o["input_mean_deg"], abs=1e-4)
    assert o["drift_mean_deg"] == pytest.approx(0.0, abs=1e-3)
    assert 0.0 < o["input_mean_deg"] < 30.0


def test_the_master_chef_can_is_scored_up_to_turns_about_its_axis(tmp_path):
    from tests.data_fixtures import K_YCBV, bop_instance, write_bop_scene

    R = Rotation.from_euler("xyz", [20, -30, 50], degrees=True).as_matrix()
    write_bop_scene(tmp_path / "test", 1, {1: [bop_instance(1, R, [0.0, 0.0, 800.0], [280, 200, 80, 100], 1.0)]},
                    K_YCBV)
    turn = Rotation.from_rotvec([0.0, 0.0, np.radians(45.0)])  # about the can's z axis only, between samples
    x, y, z, w = turn.as_quat()
    model = _model(tmp_path, [w, x, y, z], obj="002_master_chef_can")
    from models.evaluate.cli import run_eval_all

    r = run_eval_all(model, tmp_path / "test", draws=1, threads=1, progress=False, cache_root=tmp_path / "c")
    assert r["objects"]["002_master_chef_can"]["drift_mean_deg"] == pytest.approx(0.0, abs=1e-3)
    assert "002_master_chef_can" in r["protocol"]["symmetries"]


def test_all_refuses_split_options_and_names_a_missing_object(real_folder, tmp_path):
    split, _ = real_folder
    model = _model(tmp_path, [1.0, 0.0, 0.0, 0.0])
    res = CliRunner().invoke(main, ["eval", str(model), "--data", str(split), "--all", "--split-mode", "frames"])
    assert res.exit_code != 0 and "--all" in res.output and "--split-mode" in res.output
    res = CliRunner().invoke(main, ["eval", str(model), "--data", str(split), "--all", "--objects", "011_banana",
                                    "--cache", str(tmp_path / "c")])
    assert res.exit_code != 0 and "011_banana" in res.output and "Traceback" not in res.output


def test_a_read_only_folder_caches_its_crops_in_the_users_cache(tmp_path, monkeypatch):
    import models.data.pipeline as pipeline

    data = tmp_path / "shared" / "test"
    data.mkdir(parents=True)
    monkeypatch.setattr(pipeline.os, "access", lambda path, mode: False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    root = pipeline.writable_cache_root(data)
    assert root.is_relative_to(tmp_path / "home" / ".cache" / "refiner-rt" / "crops")
    assert root.name.startswith("test-")
    assert pipeline.writable_cache_root(data, tmp_path / "mine") == tmp_path / "mine"


def test_real_benchmark_scores_the_given_models_and_skips_absent_objects(real_folder, tmp_path, capsys, monkeypatch):
    split, truths = real_folder
    from benchmarks import real

    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    a = _model(tmp_path, [1.0, 0.0, 0.0, 0.0], obj="003_cracker_box")
    b = _model(tmp_path, [1.0, 0.0, 0.0, 0.0], obj="011_banana")
    out = tmp_path / "real.json"
    assert real.main(["--data", str(split), "--model", f"003_cracker_box={a}", "--model", f"011_banana={b}",
                      "--draws", "2", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert list(doc["objects"]) == ["003_cracker_box"] and "011_banana" in doc["skipped"]
    assert doc["mean_deg"] == pytest.approx(doc["objects"]["003_cracker_box"]["mean_deg"])
    assert "mean of objects" in capsys.readouterr().out
