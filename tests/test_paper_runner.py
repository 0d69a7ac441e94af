"""benchmarks/paper.py on the tiny cube dataset: JSON schema, the report, skipping finished experiments, option errors.

Every training is capped at 1 epoch per stage of 2 steps: this checks the runner's plumbing, not accuracy.
"""

import json

import pytest

from tests.bench_scripts import load_benchmark
from tests.cube_dataset import make_cube_dataset


def _load_runner():
    return load_benchmark("paper")


@pytest.fixture(scope="module")
def runner():
    return _load_runner()


@pytest.fixture(scope="module")
def ran(runner, tmp_path_factory):
    root = tmp_path_factory.mktemp("paper")
    make_cube_dataset(root / "cubes", scenes=4, frames=30)
    argv = ["--data", str(root / "cubes"), "--runs", str(root / "runs"), "--results", str(root / "results"),
            "--cache", str(root / "cache"), "--threads", "1", "--max-epochs", "1", "--max-steps-per-epoch", "2",
            "--only", "baseline,iterations,input_angle"]
    assert runner.main(argv) == 0
    return root, argv


def test_results_follow_the_eval_schema_with_both_models(ran):
    root, _ = ran
    for name in ("baseline", "iterations", "input_angle"):
        doc = json.loads((root / "results" / f"{name}.json").read_text())
        assert doc["experiment"] == name
        assert set(doc["objects"]) == {"003_cracker_box", "006_mustard_bottle"}
        assert doc["objects"]["003_cracker_box"]["mean_deg"] == doc["paper"]["objects"]["003_cracker_box"]["mean_deg"]
        assert "mean_deg" in doc["average"] and "input_mean_deg" in doc["average"]
        for model, arch in (("paper", "shallow"), ("improved", "fusion")):
            assert "average" in doc[model]
            assert doc["budget"][model]["arch"] == arch
            assert doc["budget"][model]["max_steps_per_epoch"] == 2
            # 1 epoch per stage: base MSE + geodesic, then MSE + geodesic fine-tuning for each of the 2 objects;
            # at most 2 steps of 64 crops each
            training = doc["budget"][model]["training"]
            assert training["epochs"] == 6 and training["seconds"] > 0 and 0 < training["samples"] <= 6 * 2 * 64
        assert doc["command"].startswith("python -m benchmarks.paper --data")
        assert "cpu" in doc["machine"] and doc["wall_s"] > 0
    baseline = json.loads((root / "results" / "baseline.json").read_text())
    assert baseline["paper_reference"]["average_mean_deg"] == 6.67
    assert baseline["paper"]["per_object_models"] and baseline["improved"]["per_object_models"]
    # The paper's network keeps the paper's 3000 + 2000; the improved one fine-tunes on IMPROVED_FINETUNE's size.
    assert baseline["budget"]["paper"]["images_per_object"] == {"base": 3000, "fine_tune": 2000}
    assert baseline["budget"]["improved"]["images_per_object"] == {"base": 3000, "fine_tune": 5000}
    iterations = json.loads((root / "results" / "iterations.json").read_text())
    assert set(iterations["settings"]) == {"1", "2", "3"}
    assert [iterations["settings"][k]["improved"]["iterations"] for k in "123"] == [1, 2, 3]
    # eval-only experiments evaluate the baseline's models on the same test inputs
    assert iterations["paper"]["average"] == pytest.approx(baseline["paper"]["average"])
    bins = json.loads((root / "results" / "input_angle.json").read_text())["bins"]
    for model in ("paper", "improved"):
        assert [(b["lo_deg"], b["hi_deg"]) for b in bins[model]] == [(k, k + 5) for k in range(0, 45, 5)]
        assert sum(b["n"] for b in bins[model]) == json.loads((root / "results" / "input_angle.json").read_text())[model]["average"]["n"]


def test_report_writes_tables_and_plots(runner, ran):
    root, _ = ran
    assert runner.main(["--report", "--results", str(root / "results")]) == 0
    md = (root / "results" / "tables.md").read_text()
    assert "## baseline" in md and "| **average** | 6.67 |" in md
    assert str(root) not in md and "Command: `python -m benchmarks.paper" in md  # no machine paths on the page
    assert "## size_5000" in md and "**not run**" in md
    for png in ("baseline.png", "input_angle.png"):
        assert (root / "results" / png).stat().st_size > 1000


def test_the_report_shows_commands_without_machine_paths(runner):
    shown = runner.shown_command("python -m benchmarks.paper --data /mnt/me/proj/data/ycb9 --runs /srv/runs/paper_exp "
                                 "--cache /mnt/x/cache --only baseline")
    assert shown == "python -m benchmarks.paper --data data/ycb9 --runs runs/paper_exp --cache cache --only baseline"
    assert runner.shown_command("x --data=/data/alice/proj/data/ycb9 --runs=/opt/a/runs/x --n=3") == (
        "x --data=data/ycb9 --runs=runs/x --n=3")
    # records written before the python -m layout name the script by its path: printed as the command run now
    assert runner.shown_command("python benchmarks/paper.py --data /srv/data/ycb9 --only baseline") == (
        "python -m benchmarks.paper --data data/ycb9 --only baseline")


def test_second_invocation_skips_finished_experiments(runner, ran, capsys):
    root, argv = ran
    before = {p.name: p.stat().st_mtime_ns for p in (root / "results").glob("*.json")}
    assert runner.main(argv) == 0
    out = capsys.readouterr().out
    assert out.count("skipped") == 3
    assert {p.name: p.stat().st_mtime_ns for p in (root / "results").glob("*.json")} == before


def test_reevaluate_rewrites_the_json_without_retraining(runner, ran, capsys):
    root, argv = ran
    model = root / "runs" / "baseline" / "paper" / "shallow.pt"
    trained_at = model.stat().st_mtime_ns
    doc = json.loads((root / "results" / "baseline.json").read_text())
    assert runner.main([*argv[:-1], "baseline", "--reevaluate"]) == 0
    out = capsys.readouterr().out
    assert "trained (reused)" in out and "skipped" not in out
    assert model.stat().st_mtime_ns == trained_at
    again = json.loads((root / "results" / "baseline.json").read_text())
    assert again["paper"]["average"] == pytest.approx(doc["paper"]["average"])  # same models, same test inputs
    assert again["command"].endswith("--reevaluate")


def test_finished_trainings_leave_no_resumable_state(ran):
    root, _ = ran
    for model, arch in (("paper", "shallow"), ("improved", "fusion")):
        d = root / "runs" / "baseline" / model
        assert (d / f"{arch}.done").is_file() and (d / f"{arch}.pt").is_file()
        assert not (d / f"{arch}.state").exists()


def test_unknown_experiment_lists_the_valid_ones(runner, capsys):
    with pytest.raises(SystemExit):
        runner.main(["--only", "baseline,nope", "--list"])
    err = capsys.readouterr().err
    assert "unknown experiment(s) ['nope']" in err and "input_angle" in err


def test_continued_fine_tuning_extends_every_objects_schedule(runner, tmp_path, monkeypatch):
    make_cube_dataset(tmp_path / "cubes", scenes=4, frames=30)
    recipe = {**runner.RECIPES["improved"], "lr_schedule": "constant", "epochs_mse": 1, "epochs_geodesic": 0, "ft_epochs_mse": 1,
              "ft_epochs_geodesic": 1, "ft_continue": {"ft_epochs_geodesic": 3, "ft_lr": 1e-5}}
    monkeypatch.setitem(runner.RECIPES, "improved", recipe)
    argv = ["--data", str(tmp_path / "cubes"), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "results"),
            "--cache", str(tmp_path / "cache"), "--threads", "1", "--max-steps-per-epoch", "1",
            "--only", "baseline", "--models", "improved"]
    assert runner.main(argv) == 0
    rows = [json.loads(line) for line in (tmp_path / "runs" / "baseline" / "improved" / "fusion.log.jsonl").open()]
    for obj in ("003_cracker_box", "006_mustard_bottle"):
        # 1 MSE + 1 geodesic epoch, then resumed to 1 + 3 at the new rate: epochs 3 and 4 continue the same state.
        assert [r["epoch"] for r in rows if r["stage"] == obj] == [1, 2, 3, 4]
    doc = json.loads((tmp_path / "results" / "baseline.json").read_text())
    assert doc["budget"]["improved"]["epochs"]["fine_tune_continued"] == {"ft_epochs_geodesic": 3, "ft_lr": 1e-5}
    assert [r["lr"] for r in rows if r["stage"] == "003_cracker_box"][2:] == [1e-5, 1e-5]


def test_an_experiment_fine_tunes_another_ones_base_network(runner, ran, monkeypatch):
    # base_from: the baseline's trained base networks are copied, not retrained, and fine-tuned per object on the
    # images that follow the validation ones (base_per_object 0).
    root, argv = ran
    exp = runner.Experiment("fine-tuning the baseline's base networks", base_from="baseline",
                            train={**runner.BASELINE_DATA, "base_per_object": 0, "per_object": 40},
                            recipe={"paper": {"ft_continue": None}, "improved": {"ft_continue": None}})
    monkeypatch.setitem(runner.EXPERIMENTS, "ft_small", exp)
    only = argv.index("--only") + 1
    assert runner.main(argv[:only] + ["ft_small"] + argv[only + 1:]) == 0
    doc = json.loads((root / "results" / "ft_small.json").read_text())
    for model, arch in (("paper", "shallow"), ("improved", "fusion")):
        base = root / "runs" / "baseline" / model / f"{arch}.pt"
        tuned = root / "runs" / "ft_small" / model / f"{arch}.pt"
        assert tuned.read_bytes() == base.read_bytes()
        rows = [json.loads(line) for line in tuned.with_suffix(".log.jsonl").open()]
        assert {r["stage"] for r in rows} == {"003_cracker_box", "006_mustard_bottle"}  # no base stage
        budget = doc["budget"][model]
        assert budget["protocol"].startswith("baseline's base network (not retrained)")
        assert budget["images_per_object"]["fine_tune"] == 40 and "base_mse" not in budget["epochs"]
        assert budget["training"]["epochs"] == 4  # 1 MSE + 1 geodesic epoch for each of the 2 objects
        assert "average" in doc[model]


def test_every_experiments_training_options_are_train_options(runner, tmp_path):
    # A misspelt recipe key would only fail hours into a run; every key must be a `refiner-rt train` parameter
    # (ft_continue's too, since it is passed to a resumed training) and every arch a registered one.
    import models

    args = runner.parse_args(["--data", str(tmp_path), "--runs", str(tmp_path)])
    known = set(runner._train_defaults(tmp_path))
    for name, exp in runner.EXPERIMENTS.items():
        if exp.train is None:
            continue
        for model in runner.RECIPES:
            opts = runner.train_options(exp, model, args)
            cont = opts.pop("ft_continue", None) or {}
            assert set(opts) | set(cont) <= known, (name, model, (set(opts) | set(cont)) - known)
            models.get_refiner_class(opts["arch"])


def test_an_experiment_of_one_model_trains_only_that_model(runner, tmp_path, monkeypatch, capsys):
    # models=("improved",): asked for both, the runner trains and reports only the improved refiner; asked for the
    # paper net alone, it trains nothing and writes no JSON.
    make_cube_dataset(tmp_path / "cubes", scenes=4, frames=30)
    exp = runner.Experiment("one model only", train={**runner.BASELINE_DATA, "per_object": 0},
                            recipe={"improved": runner.DEEP5}, models=("improved",))
    monkeypatch.setitem(runner.EXPERIMENTS, "one_model", exp)
    argv = ["--data", str(tmp_path / "cubes"), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "results"),
            "--cache", str(tmp_path / "cache"), "--threads", "1", "--max-epochs", "1", "--max-steps-per-epoch", "1",
            "--only", "one_model"]
    assert runner.main(argv + ["--models", "paper"]) == 0
    assert "none of --models paper is one of one_model's models" in capsys.readouterr().out
    assert not (tmp_path / "results" / "one_model.json").exists() and not (tmp_path / "runs").exists()
    assert runner.main(argv) == 0
    doc = json.loads((tmp_path / "results" / "one_model.json").read_text())
    assert "paper" not in doc and "average" in doc["improved"]
    assert doc["budget"]["improved"]["arch_config"] == runner.DEEP5["arch_config"]
    assert not (tmp_path / "runs" / "one_model" / "paper").exists()
    assert runner.finished("one_model", runner.parse_args(argv))  # the paper net is not waited for
