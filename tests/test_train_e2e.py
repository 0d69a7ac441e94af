"""End to end on a tiny learnable dataset: train -> export -> evaluate through the runtime.

Checks that training lowers the error on its own data, that the checkpoint and the exported ONNX
model give the same evaluation, and that the per-object fine-tuned models are found and used.
"""

import json

from click.testing import CliRunner
import pytest

from refiner_rt.cli import main
from tests.cube_dataset import make_cube_dataset

ARCH = "fusion"
SMALL = json.dumps({"input_size": 32, "conv_channels": [8, 8], "fuse_width": 128, "pose_widths": [32, 128], "head_widths": [64, 32]})


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    data = root / "cubes"
    make_cube_dataset(data, scenes=4, frames=30)
    out = root / "run" / "cube.pt"
    args = ["train", "--data", str(data), "--arch", ARCH, "--config", SMALL, "--out", str(out),
            "--base-per-object", "80", "--per-object", "20", "--val-per-object", "10", "--test-per-object", "10",
            "--epochs-mse", "2", "--epochs-geodesic", "40", "--ft-epochs-mse", "0", "--ft-epochs-geodesic", "2",
            "--lr", "1e-3", "--batch-size", "32", "--threads", "1", "--quiet", "--cache", str(root / "cache")]
    res = CliRunner().invoke(main, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return root, data, out


def test_training_lowers_the_error_on_training_data(trained):
    import models
    from models.evaluate.errors import evaluate_errors, torch_predictor
    from models.data.pipeline import DataSpec, cropset_for, load_splits

    root, data, out = trained
    model, info = models.load_checkpoint(out)
    spec = DataSpec.from_dict(info["data"])
    train = cropset_for(load_splits(spec), "train_base", spec, 32, 1.2, cache_root=root / "cache", progress=False)
    s = evaluate_errors(torch_predictor(model), train, "uniform:0:30", seed=1).summary()["average"]
    assert s["mean_deg"] < 0.8 * s["input_mean_deg"], s
    fresh = models.build_refiner(ARCH, **json.loads(SMALL))
    s0 = evaluate_errors(torch_predictor(fresh), train, "uniform:0:30", seed=1).summary()["average"]
    assert s["mean_deg"] < s0["mean_deg"]
    rows = [json.loads(line) for line in open(out.with_suffix(".log.jsonl"))]
    base = [r for r in rows if r["stage"] == "base"]
    assert len(base) == 42 and base[-1]["train_loss"] < base[2]["train_loss"]
    assert out.with_suffix(".png").is_file() and out.with_suffix(".log.csv").is_file()


def test_checkpoint_and_onnx_evaluations_agree(trained):
    root, data, out = trained
    runner = CliRunner()
    res = runner.invoke(main, ["export", str(out)], catch_exceptions=False)  # also exports the per-object siblings
    assert res.exit_code == 0, res.output
    for obj in ("003_cracker_box", "006_mustard_bottle"):
        assert out.with_name(f"cube.{obj}.onnx").is_file()
    results = {}
    for model in (out, out.with_suffix(".onnx")):
        path = root / f"{model.suffix[1:]}.json"
        res = runner.invoke(main, ["eval", str(model), "--data", str(data), "--json", str(path), "--quiet",
                                   "--cache", str(root / "cache"), "--threads", "1"], catch_exceptions=False)
        assert res.exit_code == 0, res.output
        assert "average" in res.output
        results[model.suffix] = json.loads(path.read_text())
    pt, ox = results[".pt"], results[".onnx"]
    assert pt["runtime"] == "torch" and ox["runtime"] == "onnxruntime"
    assert set(pt["per_object_models"]) == {"003_cracker_box", "006_mustard_bottle"}
    assert set(ox["per_object_models"]) == set(pt["per_object_models"])
    for obj, s in pt["objects"].items():
        assert s["n"] == 10
        assert ox["objects"][obj]["mean_deg"] == pytest.approx(s["mean_deg"], abs=1e-3)
        assert ox["objects"][obj]["input_mean_deg"] == pytest.approx(s["input_mean_deg"], abs=1e-9)
    for key in ("mean_deg", "std_deg", "input_mean_deg"):
        assert key in pt["average"]
    # --base-only ignores the fine-tuned siblings
    res = runner.invoke(main, ["eval", str(out), "--data", str(data), "--base-only", "--quiet", "--json", str(root / "b.json"),
                               "--cache", str(root / "cache"), "--threads", "1"], catch_exceptions=False)
    assert res.exit_code == 0 and json.loads((root / "b.json").read_text())["per_object_models"] == {}


def test_logs_of_a_resumed_run_keep_every_column(tmp_path):
    # A run resumed by a newer version mixes epoch rows without a column (here "samples") with rows that have it.
    import csv

    from models.train.cli import write_logs

    old = {"stage": "base", "epoch": 1, "train_loss": 0.5, "seconds": 2.0, "val_mean_deg": 9.0}
    new = {"stage": "base", "epoch": 2, "train_loss": 0.4, "samples": 128, "seconds": 2.0, "val_mean_deg": 8.0}
    write_logs([old, new], tmp_path / "run")
    with open(tmp_path / "run.log.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["epoch"] for r in rows] == ["1", "2"]
    assert rows[0]["samples"] == "" and rows[1]["samples"] == "128"


def test_fine_tuning_a_given_base_network(trained):
    # --base skips base training: the base network is copied unchanged and only the per-object stage runs, here on
    # the images that followed the validation ones (--base-per-object 0), i.e. the base run's base + fine-tune images.
    import torch

    import models

    root, data, out = trained
    new = root / "ft" / "cube.pt"
    common = ["train", "--data", str(data), "--out", str(new), "--val-per-object", "10", "--test-per-object", "10",
              "--threads", "1", "--quiet", "--cache", str(root / "cache")]
    args = common + ["--base", str(out), "--arch", ARCH, "--base-per-object", "0", "--per-object", "100",
                     "--ft-epochs-mse", "0", "--ft-epochs-geodesic", "1", "--epochs-geodesic", "1", "--lr", "1e-3"]
    res = CliRunner().invoke(main, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert new.read_bytes() == out.read_bytes()
    base, _ = models.load_checkpoint(out)
    for obj in ("003_cracker_box", "006_mustard_bottle"):
        tuned, info = models.load_checkpoint(new.with_name(f"cube.{obj}.pt"))
        assert info["stage"] == "finetune" and info["objects"] == [obj]
        parts = info["split"]["parts"]
        assert info["data"]["sizes"][:2] == [0, 100] and parts["train_base"]["samples"] == 0
        assert parts["train_finetune"]["per_object"][obj] > 20  # more than the base run's 20 fine-tuning images
        changed = [k for k, v in tuned.state_dict().items() if v.is_floating_point()
                   and not torch.equal(v, base.state_dict()[k])]
        assert changed  # the fine-tuning moved the weights
    rows = [json.loads(line) for line in open(new.with_suffix(".log.jsonl"))]
    assert {r["stage"] for r in rows} == {"003_cracker_box", "006_mustard_bottle"}  # no base epochs

    bad = {
        "--base-per-object": common + ["--base-per-object", "0", "--per-object", "10"],
        "--per-object > 0": common + ["--base", str(out), "--arch", ARCH, "--per-object", "0"],
        "--arch fusion": common + ["--base", str(out), "--arch", "shallow"],
        "stage 'base'": common + ["--base", str(new.with_name("cube.003_cracker_box.pt")), "--arch", ARCH],
        "--rotation-frame camera": common + ["--base", str(out), "--arch", ARCH, "--rotation-frame", "ray"],
    }
    for expected, argv in bad.items():
        res = CliRunner().invoke(main, argv)
        assert res.exit_code == 2 and expected in res.output, (expected, res.output)


def test_extra_train_folders_add_base_images_and_keep_the_held_out_ones(tmp_path):
    import shutil

    import models

    make_cube_dataset(tmp_path / "cubes", scenes=6, frames=10)
    (tmp_path / "more").mkdir()
    for s in ("000004", "000005"):  # the set's next scenes, as `refiner-rt render --first-scene 4` writes them
        shutil.move(tmp_path / "cubes" / s, tmp_path / "more" / s)
    out = tmp_path / "run" / "cube.pt"
    common = ["train", "--data", str(tmp_path / "cubes"), "--arch", ARCH, "--config", SMALL,
              "--base-per-object", "10", "--per-object", "0", "--val-per-object", "5", "--test-per-object", "5",
              "--split-mode", "scenes", "--epochs-mse", "0", "--epochs-geodesic", "1", "--batch-size", "32",
              "--threads", "1", "--quiet", "--cache", str(tmp_path / "cache")]
    res = CliRunner().invoke(main, [*common, "--out", str(out), "--extra-train", str(tmp_path / "more")],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    alone = tmp_path / "alone" / "cube.pt"
    assert CliRunner().invoke(main, [*common, "--out", str(alone)], catch_exceptions=False).exit_code == 0
    (_, grown), (_, plain) = models.load_checkpoint(out), models.load_checkpoint(alone)
    assert grown["data"]["extra_train"] == [str(tmp_path / "more")] and "extra_train" not in plain["data"]
    g, p = grown["split"]["parts"], plain["split"]["parts"]
    assert g["train_base"]["scenes"] == p["train_base"]["scenes"] + 2
    assert g["train_base"]["samples"] == p["train_base"]["samples"] + 2 * 10 * 2  # 2 scenes x 10 frames x 2 cubes
    assert g["val"] == p["val"] and g["test"] == p["test"]
    res = CliRunner().invoke(main, [*common, "--out", str(out), "--extra-train", str(tmp_path / "cubes")])
    assert res.exit_code != 0 and "the extra scenes must be new ones" in res.output
