"""benchmarks/data_scaling.py on the tiny cube dataset: one split per mode, the same test crops for every size.

Runs are capped at a few steps: this checks the study's plumbing and bookkeeping, not accuracy.
"""

import json
from pathlib import Path

from click.testing import CliRunner
import pytest

import models
from refiner_rt.cli import main
from tests.bench_scripts import load_benchmark
from tests.cube_dataset import make_cube_dataset

WIDE = {"fuse_width": 1024, "pose_widths": [64, 1024]}


def _load():
    return load_benchmark("data_scaling")


def _parameters(model) -> int:
    return sum(p.numel() for p in model.parameters())


@pytest.fixture(scope="module")
def cubes(tmp_path_factory):
    root = tmp_path_factory.mktemp("scaling") / "cubes"
    make_cube_dataset(root, scenes=6, frames=20)
    return root


def _common(cubes, tmp_path, out) -> list[str]:
    """The arguments every study run here shares: the cube data, its cracker box, small parts, quiet."""
    return ["--data", str(cubes), "--object", "003_cracker_box", "--val", "10", "--test", "20",
            "--cache", str(tmp_path / "cache"), "--threads", "1", "--json", str(out), "--quiet"]


def test_study_writes_one_row_per_size_and_mode_on_fixed_test_sets(cubes, tmp_path, capsys):
    study = _load()
    out = tmp_path / "scaling.json"
    argv = [*_common(cubes, tmp_path, out), "--sizes", "40,10", "--samples", "128", "--epoch-samples", "64",
            "--augment", "--config", json.dumps(WIDE)]
    assert study.main(argv) == 0
    doc = json.loads(out.read_text())
    assert doc["config"] == WIDE
    wide, default = models.build_refiner("fusion", **WIDE), models.build_refiner("fusion")
    assert doc["parameters"] == _parameters(wide) != _parameters(default)
    rows = [(r["mode"], r["train_crops"], r["augment"]) for r in doc["rows"]]
    assert rows == [(m, n, a) for m in ("frames", "scenes") for n, a in ((10, False), (40, False), (40, True))]
    for mode in ("frames", "scenes"):
        tests = {r["n"] for r in doc["rows"] if r["mode"] == mode}
        assert len(tests) == 1 and tests.pop() > 0
    for r in doc["rows"]:
        # 128 samples in epochs of at most 64: 2 epochs of ceil(min(n, 64) / 64) steps of 64 samples.
        assert r["epochs"] == (128 + min(r["train_crops"], 64) - 1) // min(r["train_crops"], 64)
        assert r["mean_deg"] >= 0 and r["input_mean_deg"] > 0
    printed = capsys.readouterr().out
    assert "| scenes | 40 | yes |" in printed and f"fusion {json.dumps(WIDE)}, " in printed
    assert doc["command"].startswith("python -m benchmarks.data_scaling --data")
    assert study.main(["--table", str(out)]) == 0
    assert capsys.readouterr().out.count("| frames |") == 3


def test_bad_sizes_are_named():
    study = _load()
    with pytest.raises(SystemExit, match="--sizes: expected comma-separated integers"):
        study.main(["--data", "x", "--sizes", "10,many"])
    with pytest.raises(SystemExit, match="--sizes: expected positive integers"):
        study.main(["--data", "x", "--sizes", "0"])


def test_a_bad_noise_is_named_by_the_recipe():
    study = _load()
    with pytest.raises(SystemExit, match="twist noise needs 0 <= LOW <= HIGH"):
        study.main(["--data", "x", "--noise", "twist:30:5"])


def test_bad_config_is_named(capsys):
    study = _load()
    with pytest.raises(SystemExit):
        study.main(["--data", "x", "--config", "[1024]"])
    assert "--config: expected a JSON object" in capsys.readouterr().err
    with pytest.raises(SystemExit, match=r"--config \{\"fuse_width\": 1024\}: .*must end with fuse_width=1024"):
        study.main(["--data", "x", "--config", '{"fuse_width": 1024}'])


def test_augment_sizes_run_the_augmented_runs_at_each_size_on_one_split(cubes, tmp_path, capsys):
    study = _load()
    out = tmp_path / "scaling.json"
    common = [*_common(cubes, tmp_path, out), "--modes", "scenes", "--samples", "64", "--epoch-samples", "32",
              "--config", json.dumps(WIDE)]
    assert study.main([*common, "--sizes", "10,40", "--augment", "--skip-plain", "--augment-sizes", "10,40"]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["train_crops"], r["augment"]) for r in rows] == [(10, True), (40, True)]
    assert len({r["n"] for r in rows}) == 1
    with pytest.raises(SystemExit):
        study.main([*common, "--sizes", "10,40", "--augment", "--augment-sizes", "80"])
    assert "--augment-sizes: each must be at most the largest --sizes (40)" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="--augment-sizes: expected positive integers"):
        study.main([*common, "--augment", "--augment-sizes", "0"])


@pytest.fixture(scope="module")
def small_result(cubes, tmp_path_factory):
    """The JSON of one tiny scenes run of the study (two passes measured, model kept), for the tests of ``--table``."""
    tmp = tmp_path_factory.mktemp("small_result")
    out = tmp / "a.json"
    argv = [*_common(cubes, tmp, out), "--modes", "scenes", "--sizes", "10", "--samples", "32", "--epoch-samples", "32",
            "--iterations", "2", "--save", str(tmp / "models")]
    assert _load().main(argv) == 0
    return json.loads(out.read_text())


def _as_shallow(doc: dict) -> dict:
    """The same result as if another network (the paper's) had made it, with its own errors."""
    return {**doc, "arch": "shallow", "rows": [{**r, "mean_deg": 9.5, "std_deg": 1.0} for r in doc["rows"]]}


def test_more_passes_and_the_saved_model_agree_with_refiner_rt_eval(small_result, cubes, tmp_path, capsys):
    # The kept checkpoint records the split, so `refiner-rt eval` rebuilds the same test crops and coarse poses on
    # its own: its one- and two-pass errors must be the study's.
    row = small_result["rows"][0]
    ckpt = Path(row["checkpoint"])
    assert ckpt.name == "003_cracker_box_scenes_n10_no.pt" and set(row["iterations"]) == {"2"}
    for passes, expected in ((1, row), (2, row["iterations"]["2"])):
        out = tmp_path / f"eval{passes}.json"
        res = CliRunner().invoke(main, ["eval", str(ckpt), "--data", str(cubes), "--iterations", str(passes),
                                        "--json", str(out), "--cache", str(tmp_path / "cache"), "--threads", "1",
                                        "--quiet"], catch_exceptions=False)
        assert res.exit_code == 0, res.output
        measured = json.loads(out.read_text())["objects"]["003_cracker_box"]
        assert measured["n"] == expected["n"] == row["n"]
        assert measured["mean_deg"] == pytest.approx(expected["mean_deg"], abs=1e-4)
        assert measured["input_mean_deg"] == pytest.approx(row["input_mean_deg"], abs=1e-9)
    assert row["iterations"]["2"]["mean_deg"] != pytest.approx(row["mean_deg"], abs=1e-6)  # a second pass ran
    # --settle-deg: a second pass kept where it turns by more than 179 degrees is never kept (one pass), one kept
    # where it turns by more than 1e-6 always is (two passes); without --iterations 2 it is a usage error
    for settle, expected in (("179", row), ("1e-6", row["iterations"]["2"])):
        out = tmp_path / f"settle{settle}.json"
        res = CliRunner().invoke(main, ["eval", str(ckpt), "--data", str(cubes), "--iterations", "2", "--settle-deg",
                                        settle, "--json", str(out), "--cache", str(tmp_path / "cache"), "--threads",
                                        "1", "--quiet"], catch_exceptions=False)
        assert res.exit_code == 0, res.output
        doc = json.loads(out.read_text())
        assert doc["settle_deg"] == float(settle)
        assert doc["objects"]["003_cracker_box"]["mean_deg"] == pytest.approx(expected["mean_deg"], abs=1e-4)
    for bad in (["--settle-deg", "2"], ["--settle-deg", "2", "--iterations", "2", "--all"]):
        res = CliRunner().invoke(main, ["eval", str(ckpt), "--data", str(cubes), *bad])
        assert res.exit_code == 2 and "--settle-deg" in res.output and "Traceback" not in res.output
    doc_path = tmp_path / "a.json"
    doc_path.write_text(json.dumps(small_result))
    capsys.readouterr()
    assert _load().main(["--table", str(doc_path)]) == 0
    assert f"| 2: {row['iterations']['2']['mean_deg']:.2f} |" in capsys.readouterr().out


def test_bad_iterations_are_named(capsys):
    with pytest.raises(SystemExit):
        _load().main(["--data", "x", "--iterations", "0"])
    assert "--iterations: expected a number of refinement passes >= 1; got 0" in capsys.readouterr().err


def test_table_of_several_objects_prints_each_row_and_the_mean(small_result, tmp_path, capsys):
    study = _load()
    doc = small_result
    out = tmp_path / "a.json"
    out.write_text(json.dumps(doc))
    other = {**doc, "object": "005_tomato_soup_can",
             "rows": [{**r, "mean_deg": r["mean_deg"] + 2.0, "n": 30} for r in doc["rows"]]}
    (tmp_path / "b.json").write_text(json.dumps(other))
    capsys.readouterr()
    assert study.main(["--table", str(out), str(tmp_path / "b.json")]) == 0
    printed = capsys.readouterr().out
    first = doc["rows"][0]
    assert f"| 003_cracker_box | scenes | 10 | no | {first['samples']} | {first['mean_deg']:.2f} |" in printed
    assert f"| 005_tomato_soup_can | scenes | 10 | no | {first['samples']} | {first['mean_deg'] + 2:.2f} |" in printed
    assert f"| **mean of 2** | scenes | 10 | no | {first['samples']} | **{first['mean_deg'] + 1:.2f}** |" in printed
    assert f"| {first['n'] + 30} | 2: **{first['iterations']['2']['mean_deg']:.2f}** |" in printed  # both 2-pass
    with pytest.raises(SystemExit, match="--table: the files are of different studies"):
        study.markdown_objects([doc, _as_shallow(doc)])


def test_table_of_several_studies_compares_them_per_object_and_plots(small_result, tmp_path, capsys):
    study = _load()
    doc = small_result
    out = tmp_path / "a.json"
    out.write_text(json.dumps(doc))
    (tmp_path / "b.json").write_text(json.dumps({**doc, "object": "005_tomato_soup_can"}))
    (tmp_path / "c.json").write_text(json.dumps(_as_shallow(doc)))
    png = tmp_path / "compare.png"
    capsys.readouterr()
    files = [str(out), str(tmp_path / "b.json"), str(tmp_path / "c.json")]
    assert study.main(["--table", *files, "--plot", str(png)]) == 0
    printed = capsys.readouterr().out
    mean = doc["rows"][0]["mean_deg"]
    # only what differs between the series names them
    assert "| object | fusion (default config) | shallow (default config) |" in printed
    assert f"| 003_cracker_box | {mean:.2f} | 9.50 |" in printed
    assert f"| 005_tomato_soup_can | {mean:.2f} | - |" in printed
    assert f"| **mean of 1** | **{mean:.2f}** | **9.50** |" in printed  # the objects every series has
    assert "2 objects, fusion" in printed  # the fusion study's own table with its mean
    assert png.stat().st_size > 0 and png.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(SystemExit, match="two results for 003_cracker_box"):
        study.main(["--table", str(out), str(out), str(tmp_path / "c.json")])
    with pytest.raises(SystemExit):
        study.main(["--plot", str(png)])
    assert "--plot draws the results of --table" in capsys.readouterr().err


def test_split_objects_trains_and_tests_on_the_objects_part_of_the_larger_split(cubes, tmp_path, capsys):
    from models.data.pipeline import DataSpec, load_splits

    study = _load()
    out = tmp_path / "split.json"
    both = ["003_cracker_box", "006_mustard_bottle"]
    argv = [*_common(cubes, tmp_path, out), "--modes", "scenes", "--sizes", "40", "--samples", "64",
            "--epoch-samples", "64", "--split-objects", ",".join(both)]
    assert study.main(argv) == 0
    doc = json.loads(out.read_text())
    assert doc["split_objects"] == both
    spec = DataSpec(data=str(cubes), objects=["003_cracker_box"], split_mode="scenes", sizes=(40, 0, 10, 20),
                    split_objects=both)
    splits = load_splits(spec)
    (row,) = doc["rows"]
    assert row["n"] == len(splits.test)
    assert row["scenes"]["test"] == len({s.scene_key for s in splits.test})
    with pytest.raises(SystemExit):
        study.main([*argv[:-1], "006_mustard_bottle"])
    assert "--split-objects must include --object 003_cracker_box" in capsys.readouterr().err


def test_train_scenes_trains_on_every_crop_of_the_first_scenes_on_one_split(cubes, tmp_path, capsys):
    from models.data.pipeline import DataSpec, load_splits

    study = _load()
    out = tmp_path / "scenes.json"
    argv = [*_common(cubes, tmp_path, out), "--modes", "scenes", "--sizes", "40", "--samples", "32",
            "--epoch-samples", "32", "--train-scenes", "1,2,99", "--save", str(tmp_path / "models")]
    assert study.main(argv) == 0
    printed = capsys.readouterr()
    assert "only 3 training scenes, skipping --train-scenes 99" in printed.err
    doc = json.loads(out.read_text())
    # The crops of the split's training part (made with --sizes 40), by scene: each run takes all crops of its scenes.
    spec = DataSpec(data=str(cubes), objects=["003_cracker_box"], split_mode="scenes", sizes=(40, 0, 10, 20))
    train = [s.scene_id for s in load_splits(spec).train_base]
    per_scene = {s: train.count(s) for s in set(train)}
    assert len(per_scene) == 3
    assert [r["train_scenes"] for r in doc["rows"]] == [1, 2]
    assert len({r["n"] for r in doc["rows"]}) == 1
    first, second = doc["rows"]
    saved = [models.load_checkpoint(r["checkpoint"])[1] for r in doc["rows"]]
    chosen = [s["train_scene_ids"] for s in saved]
    assert len(chosen[0]) == 1 and len(chosen[1]) == 2 and set(chosen[0]) < set(chosen[1])
    assert first["train_crops"] == sum(per_scene[s] for s in chosen[0])
    assert second["train_crops"] == sum(per_scene[s] for s in chosen[1])
    assert f"| scenes | {second['train_crops']} from 2 scenes |" in printed.out
    # error_breakdown.py measures such a model's training error on the crops of its own scenes only.
    out = tmp_path / "breakdown.json"
    assert load_benchmark("error_breakdown").main([first["checkpoint"], "--cache", str(tmp_path / "cache"),
                                                   "--threads", "1", "--json", str(out)]) == 0
    parts = json.loads(out.read_text())["results"][0]["parts"]
    assert parts["train_base"]["n"] == first["train_crops"] and parts["train_base"]["scenes"] == 1
    assert parts["test"]["n"] == first["n"]
    with pytest.raises(SystemExit):
        study.main([*argv[:-2], "--sizes", "20,40"])
    assert "--train-scenes takes the runs' crops from whole scenes: give one --sizes" in capsys.readouterr().err


def test_extra_train_adds_new_scenes_and_init_starts_from_a_trained_model(tmp_path, capsys):
    import shutil

    from models.data.pipeline import DataSpec, checkpoint_test_set, load_splits

    study = _load()
    make_cube_dataset(tmp_path / "cubes", scenes=8, frames=12)
    (tmp_path / "more").mkdir()
    for s in ("000006", "000007"):  # the set's next scenes, as `refiner-rt render --first-scene 6` writes them
        shutil.move(tmp_path / "cubes" / s, tmp_path / "more" / s)
    first, more = tmp_path / "cubes", tmp_path / "more"
    common = ["--object", "003_cracker_box", "--val", "10", "--test", "20", "--modes", "scenes", "--sizes", "30",
              "--samples", "32", "--epoch-samples", "32", "--cache", str(tmp_path / "cache"), "--threads", "1",
              "--quiet", "--save", str(tmp_path / "models")]
    assert study.main(["--data", str(first), *common, "--json", str(tmp_path / "plain.json")]) == 0
    plain = json.loads((tmp_path / "plain.json").read_text())["rows"][0]
    argv = ["--data", str(first), *common, "--extra-train", str(more), "--train-scenes", "all",
            "--json", str(tmp_path / "grown.json")]
    spec = DataSpec(data=str(first), objects=["003_cracker_box"], split_mode="scenes", sizes=(30, 0, 10, 20),
                    extra_train=[str(more)])
    train_base = load_splits(spec).train_base
    train_scenes = len({s.scene_id for s in train_base})
    assert train_scenes == plain["scenes"]["train_base"] + 2
    argv += ["--init", plain["checkpoint"]]
    assert study.main(argv) == 0
    grown = json.loads((tmp_path / "grown.json").read_text())["rows"][0]
    assert grown["scenes"]["train_base"] == train_scenes and grown["init"] == plain["checkpoint"]
    # --train-scenes all: every crop of the split's training scenes and of the extra folder's
    assert grown["train_scenes"] == train_scenes and grown["train_crops"] == len(train_base) > plain["train_crops"]
    assert grown["scenes"]["test"] == plain["scenes"]["test"] and grown["input_mean_deg"] == plain["input_mean_deg"]
    model, info = models.load_checkpoint(grown["checkpoint"])
    assert {"000006", "000007"} <= set(info["train_scene_ids"]) and info["data"]["extra_train"] == [str(more)]
    # The recorded spec rebuilds the same test crops as the set alone.
    test, _ = checkpoint_test_set(model, info, cache_root=tmp_path / "cache")
    alone, _ = checkpoint_test_set(model, models.load_checkpoint(plain["checkpoint"])[1], cache_root=tmp_path / "cache")
    assert len(test) == grown["n"] and (test.crops == alone.crops).all()
    # --init is refused for another network or another split, and missing folders are named.
    for extra, message in ((["--config", '{"conv_channels": [8, 8]}'], "a fusion network with config"),
                           (["--split-seed", "3"], r"trained on another split \(split_seed 0; here 3\)")):
        with pytest.raises(SystemExit, match=message):
            study.main([*argv, *extra])
    # A shipped model records its set by the folder's name alone (no build machine's folder): the same split matches.
    model0, info0 = models.load_checkpoint(plain["checkpoint"])
    data0 = info0["data"] if isinstance(info0["data"], dict) else json.loads(info0["data"])
    named = tmp_path / "named.pt"
    models.save_checkpoint(model0, named, **{**info0, "data": {**data0, "data": first.name}})
    assert study.main([str(named) if a == plain["checkpoint"] else a for a in argv]) == 0
    capsys.readouterr()
    # A model trained on another set is refused (its training scenes may be this set's test scenes: here they are,
    # a copy under another name), unless the caller vouches with --init-other-set; the run then says so.
    shutil.copytree(first, tmp_path / "cubes_copy")
    other = ["--data", str(tmp_path / "cubes_copy"), *common, "--init", plain["checkpoint"],
             "--json", str(tmp_path / "copy.json")]
    with pytest.raises(SystemExit, match="trained on the set 'cubes', not on 'cubes_copy'.*--init-other-set"):
        study.main(other)
    assert study.main([*other, "--init-other-set"]) == 0
    assert "trained on the set 'cubes', not on 'cubes_copy' (--init-other-set" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        study.main([*argv, "--extra-train", str(tmp_path / "missing")])
    assert "--extra-train: not a folder" in capsys.readouterr().err


def test_the_network_is_saved_before_the_test_split_is_scored(cubes, tmp_path, monkeypatch):
    """A failure while scoring (after what may be hours of training) keeps the trained network on disk."""
    study = _load()

    def fail(*args, **kwargs):
        raise RuntimeError("scoring failed")

    monkeypatch.setattr("models.evaluate.errors.evaluate_errors", fail)  # the study imports it when it runs
    argv = [*_common(cubes, tmp_path, tmp_path / "a.json"), "--modes", "scenes", "--sizes", "10", "--samples", "32",
            "--epoch-samples", "32", "--save", str(tmp_path / "models")]
    with pytest.raises(RuntimeError, match="scoring failed"):
        study.main(argv)
    saved = list((tmp_path / "models").glob("*.pt"))
    assert len(saved) == 1
    model, info = models.load_checkpoint(saved[0])
    assert info["objects"] == ["003_cracker_box"]
    assert info["wall_s"] > 0  # the training time travels with the checkpoint, for a --resume

    # The rerun with --resume scores that network without training it again: the same weights, the same row.
    monkeypatch.undo()
    trained = []
    monkeypatch.setattr("models.train.loop.train_refiner", lambda *a, **k: trained.append(1))  # imported when it runs
    before = saved[0].stat().st_mtime_ns
    assert study.main([*argv, "--resume"]) == 0
    assert not trained and saved[0].stat().st_mtime_ns == before
    row = json.loads((tmp_path / "a.json").read_text())["rows"][0]
    assert row["resumed"] is True and row["wall_s"] == info["wall_s"]
    assert row["best_epoch"] == info["best_epoch"] and row["val_mean_deg"] == info["val_mean_deg"]
    assert row["checkpoint"] == str(saved[0]) and row["n"] > 0


def test_resume_refuses_a_checkpoint_of_another_run(cubes, tmp_path, capsys):
    """--resume scores only this command's own checkpoint: another configuration's file under the same name is named,
    not silently scored; and --resume without --save is refused."""
    study = _load()
    argv = [*_common(cubes, tmp_path, tmp_path / "a.json"), "--modes", "scenes", "--sizes", "10", "--samples", "32",
            "--epoch-samples", "32", "--save", str(tmp_path / "models")]
    assert study.main(argv) == 0
    with pytest.raises(SystemExit, match="was not saved by this run: its train_config"):
        study.main([*argv, "--samples", "64", "--resume"])
    with pytest.raises(SystemExit):
        study.main([a for a in argv if a not in ("--save", str(tmp_path / "models"))] + ["--resume"])
    assert "--resume needs --save DIR" in capsys.readouterr().err
