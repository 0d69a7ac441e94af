"""export/release: the shipped models are built on the product's path (a named TrainRecipe through
``models.run_training``), that path is the run the shipped models' records name, and a tiny build runs end to end."""

import json
import shlex
from pathlib import Path

import pytest

from export.release import coarse
from models.train.recipe import load_recipe
from tests.cube_dataset import make_cube_dataset

ROOT = Path(__file__).resolve().parent.parent
TINY = {"input_size": 32, "conv_channels": [8, 8], "fuse_width": 64, "pose_widths": [32, 64], "head_widths": [32, 16],
        "roll": "canonical"}
# Fields in which the two recipes may differ without changing a weight: the name, the device (data_scaling trained
# on the CPU, train_refiner's default; the release says "cpu"), and the symmetries (data_scaling gave the loss none;
# the release turns a dataset's recorded symmetry off, for the same plain loss).
NOT_COMPARED = ("name", "device", "symmetries")


def data_scaling_recipe(argv: list[str]):
    """The recipe ``benchmarks/data_scaling.py`` trains its one run of ``argv`` with (the build's options: one size,
    ``--skip-plain --skip-jitter``, one ``--background``)."""
    from benchmarks import data_scaling

    base = load_recipe("data-scaling")
    args = data_scaling.build_parser(base).parse_args(argv)
    args.recipe = base
    assert args.skip_plain and args.skip_jitter and len(args.background) == 1 and not args.occlude
    recipe = data_scaling.study_recipe(args, args.modes, int(args.sizes))
    return recipe.merged(augment=args.augment, background=args.background[0], occlude=0.0, relight=args.relight)


def comparable(recipe) -> dict:
    return {k: v for k, v in recipe.as_dict().items() if k not in NOT_COMPARED}


def test_the_release_recipe_is_the_data_scaling_run(tmp_path):
    """The command that built versions 1-6 and the recipe the release trains with now are the same run, for the
    options a build varies (initial network, extra sets, inputs, rate, augmentations, turns)."""
    data, run, cache = tmp_path / "data", tmp_path / "run", tmp_path / "cache"
    cases = [dict(),
             dict(init=run / "a.init.pt", extra_train=[tmp_path / "more", tmp_path / "more2"]),
             dict(noise="twist:0:30", lr=1e-3, seed=3),
             dict(init=run / "a.pt", photometric={}, noise="normal:0:3", lr=1e-4),
             dict(photometric={"blur": 0.3, "jpeg": 0.2}, inplane=22.5, roll="none")]
    for kw in cases:
        cmd = coarse.data_scaling_command(data, "003_cracker_box", run, 450_000, 16_000, cache, **kw)
        assert cmd[1:3] == ["-m", "benchmarks.data_scaling"]
        mine = coarse.shipped_recipe(data, "003_cracker_box", 450_000, 16_000, cache, **kw)
        assert comparable(mine) == comparable(data_scaling_recipe(cmd[3:])), kw
        assert mine.name == coarse.RECIPE_NAME and mine.device == "cpu"
        assert mine.symmetries == {"003_cracker_box": {}}


def test_version_7_is_version_6_with_the_pilots_chosen_lever():
    """The recipe of model version 7 is version 6's with the version-7 pilot's chosen row (benchmarks/studies/appearance,
    ``norm``): the lever's network config and photometric probabilities (none), at version 6's own budget; nothing
    else differs, and it is what ships."""
    from benchmarks.studies.appearance.v7_levers import CONFIG, LEVERS

    v6, v7 = load_recipe("robot-roll-v6").as_dict(), load_recipe("robot-appearance-v7").as_dict()
    lever = "norm"
    assert {k[len("aug_"):]: p for k, p in v7.items() if k.startswith("aug_") and p} == LEVERS[lever]
    assert v7["arch_config"] == {**v6["arch_config"], **CONFIG[lever]}
    assert v7["samples"] == v6["samples"] == 450_000
    changed = {k for k in v6 if v6[k] != v7[k]} - {"name", "arch_config"}
    assert changed == {f"aug_{op}" for op in LEVERS[lever]}  # nothing else moved
    assert (coarse.RECIPE_NAME, coarse.MODEL_VERSION) == ("robot-appearance-v7", "7")  # what ships


def test_the_recorded_build_command_names_a_budget_other_than_the_recipe_s(tmp_path):
    """A build record's command reproduces the run: ``--samples`` / ``--sizes`` appear exactly when they differ from
    the named recipe's (the first 450,000-sample version-7 builds, against a recipe of 60,000, recorded none),
    ``--extra-train`` by folder name."""
    named = coarse.NAMED_RECIPES[coarse.RECIPE_NAME]
    data, extra = tmp_path / "ycb9_robot", [tmp_path / "x" / "ycb9_tabletop_s32_next"]
    plain = shlex.split(coarse.release_command("011_banana", data, extra, named["samples"], named["base_per_object"]))
    assert "--samples" not in plain and "--sizes" not in plain and str(tmp_path) not in " ".join(plain)
    assert plain[plain.index("--extra-train") + 1] == "ycb9_tabletop_s32_next"
    samples, sizes = named["samples"] // 2, named["base_per_object"] // 2
    argv = shlex.split(coarse.release_command("011_banana", data, extra, samples, sizes))
    assert argv[argv.index("--samples") + 1] == str(samples) and argv[argv.index("--sizes") + 1] == str(sizes)
    assert argv[argv.index("--objects") + 1] == "011_banana"


def test_each_shipped_model_record_names_the_release_recipe(tmp_path):
    """Every build record of the current model version: its recorded training command reproduces the recipe that made
    the shipped weights. Versions up to 6 recorded the data_scaling run (the same run as
    :func:`export.release.coarse.shipped_recipe` gives for the same object, sets and budget); later ones the release
    build's own command, whose options give the recorded ``train_recipe``."""
    records = [json.loads(p.read_text()) for p in sorted((ROOT / "benchmarks/results/pretrained").glob("0*.json"))]
    current = [d for d in records if d.get("model_version") == coarse.MODEL_VERSION]
    if not current:
        pytest.skip("no model of the current version ships")
    for d in current:
        assert d["recipe"] == {**coarse.RECIPE, "split_objects": d["recipe"]["split_objects"]}, d["object_id"]
        argv = shlex.split(d["train_command"])
        value = lambda flag, default=None: argv[argv.index(flag) + 1] if flag in argv else default  # noqa: E731
        extra = [Path(argv[i + 1]) for i, a in enumerate(argv) if a == "--extra-train"]
        if argv[:4] == ["python", "-m", "export.release.coarse", "build"]:
            named = coarse.NAMED_RECIPES[coarse.RECIPE_NAME]
            assert value("--objects") == d["object_id"]
            mine = coarse.portable_recipe(coarse.shipped_recipe(
                Path(d["train_recipe"]["data"]), d["object_id"], int(value("--samples", named["samples"])),
                int(value("--sizes", named["base_per_object"])), tmp_path, extra_train=extra,
                init=Path(d["train_recipe"]["init"]) if d["train_recipe"]["init"] else None))
            assert mine == d["train_recipe"], d["object_id"]
            continue
        assert argv[:2] == ["python", "benchmarks/data_scaling.py"]
        argv = argv[2:]
        init = Path(value("--init")) if "--init" in argv else None
        mine = coarse.shipped_recipe(Path(value("--data")), d["object_id"], int(value("--samples")),
                                     int(value("--sizes")), Path(value("--cache")), init=init, extra_train=extra)
        theirs = data_scaling_recipe(argv)
        assert comparable(mine) == comparable(theirs), d["object_id"]


@pytest.mark.slow
def test_a_tiny_build_trains_through_the_recipe_path(tmp_path):
    """A few steps of the release's training on the cube dataset: models.run_training with the shipped recipe (a
    tiny network), the recipe saved with the checkpoint, and the record the build writes into the card."""
    import models

    data = tmp_path / "cubes"
    make_cube_dataset(data, obj_ids=(2, 5), scenes=6, frames=8, masks=True)
    recipe = coarse.shipped_recipe(data, "003_cracker_box", 40, 10, tmp_path / "cache", val=4, test=4).merged(
        split_objects=["003_cracker_box", "006_mustard_bottle"], arch_config=TINY, epoch_samples=20)
    ckpt, row = coarse.train_shipped(recipe, tmp_path / "run" / "003_cracker_box", "003_cracker_box")
    assert ckpt.is_file() and ckpt.with_name("model.recipe.json").is_file()
    _, info = models.load_checkpoint(ckpt)
    assert info["recipe"]["name"] == coarse.RECIPE_NAME and info["recipe"]["samples"] == 40
    assert row["samples"] >= 40 and row["train_crops"] > 0 and row["wall_s"] is not None
    assert 0 <= row["mean_deg"] <= 180 and row["epochs"] >= 1
    # a rerun reuses the checkpoint (a build resumes at the object it was on) and scores the same crops alike
    again, row2 = coarse.train_shipped(recipe, tmp_path / "run" / "003_cracker_box", "003_cracker_box")
    assert again == ckpt and row2["wall_s"] is None and row2["mean_deg"] == row["mean_deg"]
    portable = coarse.portable_recipe(recipe)
    assert portable["data"] == "cubes" and portable["cache_root"] is None
    assert str(tmp_path) not in json.dumps(portable)


@pytest.mark.slow
def test_an_interrupted_build_resumes_at_its_last_epoch(tmp_path, capsys):
    """A build stopped in its second epoch (logged, its state not yet written) goes on after the first with the same
    recipe and ends with the weights of a build never stopped, each epoch logged once; with a changed recipe it starts
    again."""
    import os
    from unittest import mock

    import torch

    import models

    data = tmp_path / "cubes"
    make_cube_dataset(data, obj_ids=(2, 5), scenes=6, frames=8, masks=True)
    recipe = coarse.shipped_recipe(data, "003_cracker_box", 60, 10, tmp_path / "cache", val=4, test=4).merged(
        split_objects=["003_cracker_box", "006_mustard_bottle"], arch_config=TINY, epoch_samples=20, threads=1)
    whole, _ = coarse.train_shipped(recipe, tmp_path / "whole", "003_cracker_box")

    real_replace, saved = os.replace, []

    def stop_in_second_epoch(src, dst):
        if str(dst).endswith(".state/base.pt"):
            saved.append(dst)
            if len(saved) == 2:  # the session ending after epoch 2 was logged, before its state landed
                raise KeyboardInterrupt
        real_replace(src, dst)

    save = tmp_path / "stopped"
    with mock.patch("models.train.loop.os.replace", stop_in_second_epoch), pytest.raises(KeyboardInterrupt):
        coarse.train_shipped(recipe, save, "003_cracker_box")
    assert len(saved) == 2 and not (save / "model.pt").exists()
    capsys.readouterr()
    trained = []  # the epochs the second call trains: a state lands after each

    def count(src, dst):
        real_replace(src, dst)
        if str(dst).endswith(".state/base.pt"):
            trained.append(dst)

    with mock.patch("models.train.loop.os.replace", count):
        resumed, row = coarse.train_shipped(recipe, save, "003_cracker_box")
    assert "resuming after epoch 1" in capsys.readouterr().out

    def epochs(run):
        return [json.loads(line)["epoch"] for line in (run / "model.log.jsonl").read_text().splitlines()]

    # epoch 1 not trained again, epoch 2 once more, and logged once
    assert epochs(save) == epochs(tmp_path / "whole") == list(range(1, len(epochs(save)) + 1))
    assert len(epochs(save)) > 2 and len(trained) == len(epochs(save)) - 1
    assert row["resumed_after_epoch"] == 1 and row["wall_s"] > json.loads(
        (save / "model.log.jsonl").read_text().splitlines()[0])["seconds"]
    a, b = models.load_checkpoint(whole)[0].state_dict(), models.load_checkpoint(resumed)[0].state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not (save / "model.building.json").exists()

    other = tmp_path / "changed"  # stopped, then started again with another recipe: no resume
    saved.clear()
    with mock.patch("models.train.loop.os.replace", stop_in_second_epoch), pytest.raises(KeyboardInterrupt):
        coarse.train_shipped(recipe, other, "003_cracker_box")
    capsys.readouterr()
    trained.clear()
    with mock.patch("models.train.loop.os.replace", count):
        coarse.train_shipped(recipe.merged(lr=recipe.lr / 2), other, "003_cracker_box")
    assert "resuming" not in capsys.readouterr().out and len(trained) == len(epochs(save))
    assert epochs(other) == epochs(save)  # the stopped run's epoch dropped, every epoch trained anew


def test_build_refuses_a_from_weights_path_that_is_not_a_folder(tmp_path, capsys):
    """``build --from-weights`` (start from an earlier version's fp32 files, to build a shipped version again) names
    the option and what it expected, before any training."""
    (tmp_path / "data").mkdir()
    with pytest.raises(SystemExit) as exc:
        coarse.main(["build", "--data", str(tmp_path / "data"), "--run", str(tmp_path / "run"), "--objects",
                     "011_banana", "--from-weights", str(tmp_path / "missing")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--from-weights" in err and "not a folder" in err
    assert not (tmp_path / "run").exists()
    (tmp_path / "v5").mkdir()
    (tmp_path / "v5" / "011_banana.onnx").write_bytes(b"")
    with pytest.raises(SystemExit):
        coarse.main(["build", "--data", str(tmp_path / "data"), "--run", str(tmp_path / "run"), "--objects",
                     "011_banana,035_power_drill", "--from-weights", str(tmp_path / "v5")])
    err = capsys.readouterr().err
    assert "holds no fp32 file of 035_power_drill" in err and "011_banana," not in err
    assert not (tmp_path / "run").exists()


def test_a_recovered_start_is_reused_only_from_the_same_file(tmp_path):
    """``RUN/<id>.init.pt`` recovered from one fp32 file is not taken as the start of a build from another (e.g. a
    scratch folder of an earlier build with the package's model, then ``--from-weights``)."""
    from unittest import mock

    from refiner_rt.metadata import file_sha256

    (tmp_path / "v5").mkdir()
    src = tmp_path / "v5" / "011_banana.onnx"
    src.write_bytes(b"an earlier version")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "011_banana.init.pt").write_bytes(b"")  # its contents: the load_checkpoint below
    with mock.patch("models.load_checkpoint", return_value=(None, {"recovered_from": {"sha256": "0" * 64}})):
        with pytest.raises(SystemExit, match="recovered from another file"):
            coarse.recover_shipped("011_banana", tmp_path, tmp_path / "run", tmp_path, weights=tmp_path / "v5")
    assert file_sha256(src) != "0" * 64


def test_the_release_readme_builds_the_objects_that_ship():
    """Every ``--objects`` list of a coarse build in export/release/README.md names objects that ship; the version's
    build names all of them."""
    import re

    from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name, pretrained_models

    text = (ROOT / "export" / "release" / "README.md").read_text()
    shipped = {m.object_id for m in pretrained_models()}  # the card's list
    lists = [m.split(",") for m in re.findall(r"coarse build .*?--objects (\S+)", text, flags=re.S)]
    assert lists and shipped
    assert any(set(objects) == shipped for objects in lists)  # the version's build: all of them
    for objects in lists:
        assert set(objects) <= shipped, objects  # a rebuild: some of them
    assert all((WEIGHTS_DIR / model_file_name(o, int8=True)).is_file() for o in shipped)
