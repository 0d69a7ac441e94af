"""TrainRecipe: files, rules, named recipes, the generated CLI, and stages that give the same weights as calls."""

import json

from click.testing import CliRunner
import pytest
import torch

from refiner_rt.cli import main
from tests.cube_dataset import make_cube_dataset

TINY = {"input_size": 32, "conv_channels": [8, 8], "fuse_width": 64, "pose_widths": [32, 64], "head_widths": [32, 16]}


@pytest.fixture(scope="module")
def cubes(tmp_path_factory):
    root = tmp_path_factory.mktemp("recipe")
    make_cube_dataset(root / "cubes", scenes=4, frames=10, masks=True)
    return root


def _tiny(cubes, **changes):
    from models.train.recipe import TrainRecipe

    d = dict(data=str(cubes / "cubes"), arch="fusion", arch_config=TINY, base_per_object=10, per_object=6,
             val_per_object=4, test_per_object=4, epochs_mse=1, epochs_geodesic=1, batch_size=8, threads=1,
             cache_root=str(cubes / "cache"), lr=1e-3)
    return TrainRecipe.from_dict({**d, **changes})


def _weights(path):
    return torch.load(path, weights_only=True)["state_dict"]


def _same(a, b) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_named_recipes_are_valid_and_paper_is_the_defaults():
    from models.train.recipe import NAMED_RECIPES, TrainRecipe, load_recipe

    assert load_recipe("paper").as_dict() == {**TrainRecipe().as_dict(), "name": "paper"}
    held = load_recipe("heldout-scenes-v1")
    assert (held.arch, held.arch_config, held.rotation_frame, held.lr, held.lr_schedule) == (
        "fusion", {"conv_channels": [16, 32, 64, 128, 128]}, "ray", 1e-3, "cosine")
    assert (held.augment, held.background, held.split_mode, held.val_per_object, held.test_per_object) == (
        True, 0.5, "scenes", 300, 700)
    assert len(held.merged(data="x").data_spec().drawn_objects) == 9
    for name in NAMED_RECIPES:
        load_recipe(name)
    # the same values as the build script that trains the shipped models
    from export.release.coarse import RECIPE

    built = load_recipe(RECIPE["name"])
    assert (built.val_per_object, built.test_per_object, built.lr, built.background, built.seed, built.bf16) == (
        RECIPE["val"], RECIPE["test"], RECIPE["lr"], RECIPE["background"], RECIPE["seed"], RECIPE["bf16"])
    assert built.arch_config == RECIPE["config"]
    # the same network as heldout-scenes-v1's, but for the input turn that version 6 adds (models.nets.fusion roll)
    # and the per-crop input normalisation of version 7 (weightless: the same weights' shapes)
    assert {k: v for k, v in built.arch_config.items() if k not in ("roll", "input_norm")} == held.arch_config
    assert built.rotation_frame == RECIPE["rotation_frame"] == held.rotation_frame
    assert built.inplane == RECIPE["inplane"]


def test_recipe_files_round_trip_and_toml_reads(tmp_path):
    from models.train.recipe import TrainRecipe, load_recipe

    r = TrainRecipe(arch="fusion", arch_config={"fuse_width": 128}, objects=["003_cracker_box", "my_widget"],
                    stages=[{"ft_epochs_geodesic": 20}], rotation_frame="ray", inplane=15.0).validate()
    path = r.save(tmp_path / "r.json")
    assert load_recipe(path).as_dict() == {**r.as_dict(), "name": "r.json"}
    (tmp_path / "r.toml").write_text('arch = "fusion"\nlr = 0.001\nobjects = ["my_widget"]\n'
                                     '[arch_config]\nfuse_width = 128\n')
    t = load_recipe(tmp_path / "r.toml")
    assert (t.arch, t.lr, t.objects, t.arch_config, t.epochs_mse) == ("fusion", 1e-3, ["my_widget"],
                                                                       {"fuse_width": 128}, 5)


@pytest.mark.parametrize("changes, field, words", [
    ({"inplane": 10.0}, "inplane", "--inplane 10 needs --rotation-frame ray"),
    ({"arch": "fusion", "arch_config": {"roll": "canonical"}}, "arch_config", "roll 'canonical' needs --rotation-frame ray"),
    ({"base_per_object": 0}, "base_per_object", "0 needs --base"),
    ({"lr": 0.0}, "lr", "lr must be a number > 0"),
    ({"background": 1.5}, "background", "background must be a number in [0, 1]"),
    ({"device": "tpu"}, "device", "device must be auto, cpu, cuda"),
    ({"stages": [{"nope": 1}]}, "stages", "unknown or not continuable"),
    ({"objects": ["a b"]}, "objects", "objects must be a non-empty list of object names"),
])
def test_cross_field_rules_name_the_field(changes, field, words):
    from models.train.recipe import RecipeError, TrainRecipe

    with pytest.raises(RecipeError, match=words.replace("[", r"\[").replace("]", r"\]")) as info:
        TrainRecipe.from_dict(changes)
    assert info.value.field == field
    with pytest.raises(RecipeError, match="unknown recipe field"):
        TrainRecipe.from_dict({"learning_rate": 1e-3})


def test_print_recipe_round_trips_through_a_file_and_flags_override(tmp_path):
    runner = CliRunner()
    res = runner.invoke(main, ["train", "--recipe", "heldout-scenes-v1", "--objects", "003_cracker_box", "--lr",
                               "0.002", "--no-augment", "--print-recipe"], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    printed = json.loads(res.output)
    assert printed["lr"] == 0.002 and printed["augment"] is False and printed["objects"] == ["003_cracker_box"]
    assert printed["arch"] == "fusion" and printed["name"] == "heldout-scenes-v1"
    (tmp_path / "r.json").write_text(res.output)
    again = runner.invoke(main, ["train", "--recipe", str(tmp_path / "r.json"), "--print-recipe"])
    assert again.exit_code == 0 and json.loads(again.output) == printed
    bad = runner.invoke(main, ["train", "--recipe", "nope", "--print-recipe"])
    assert bad.exit_code == 2 and "heldout-scenes-v1" in bad.output
    bad = runner.invoke(main, ["train", "--inplane", "10", "--print-recipe"])
    assert bad.exit_code == 2 and "--inplane 10 needs --rotation-frame ray" in bad.output


def test_train_help_is_grouped_in_sections():
    res = CliRunner().invoke(main, ["train", "--help"])
    assert res.exit_code == 0
    heads = [h for h in ("Data options:", "Model options:", "Optimisation options:", "Augmentation options:",
                         "Run options:") if h in res.output]
    assert len(heads) == 5
    assert res.output.index("--split-mode") < res.output.index("Model options:") < res.output.index("--arch")
    for flag in ("--base-per-object", "--ft-lr", "--background", "--inplane", "--cache", "--device", "--recipe"):
        assert flag in res.output


def test_a_multi_stage_recipe_gives_the_weights_of_the_same_calls_in_sequence(cubes, tmp_path):
    # Base, per-object fine-tuning, then a continuation of the fine-tuning at a lower rate: one recipe, or two
    # calls (the second resuming), write the same weights.
    import models

    staged = _tiny(cubes, stages=[{"ft_epochs_geodesic": 2, "ft_lr": 1e-4}])
    out = models.run_training(staged, out=tmp_path / "staged" / "m.pt", progress=False)
    first = _tiny(cubes)
    calls = tmp_path / "calls" / "m.pt"
    models.run_training(first, out=calls, progress=False)
    models.run_training(first.merged(ft_epochs_geodesic=2, ft_lr=1e-4), out=calls, resume=True, progress=False)
    assert set(out) == {"base", "003_cracker_box", "006_mustard_bottle"}
    for key, path in out.items():
        other = calls if key == "base" else calls.with_name(f"m.{key}.pt")
        assert _same(_weights(path), _weights(other)), key
    rows = [json.loads(line) for line in open(tmp_path / "staged" / "m.log.jsonl")]
    assert [r["epoch"] for r in rows if r["stage"] == "003_cracker_box"] == [1, 2, 3]
    # the resolved recipe beside every checkpoint, stages included
    saved = json.loads((tmp_path / "staged" / "m.recipe.json").read_text())
    assert saved["stages"] == [{"ft_epochs_geodesic": 2, "ft_lr": 1e-4}]
    assert json.loads((tmp_path / "staged" / "m.003_cracker_box.recipe.json").read_text()) == saved
    assert models.load_checkpoint(out["base"])[1]["recipe"] == saved


def test_the_heldout_recipe_reproduces_the_data_scaling_command(cubes, tmp_path):
    # Models up to version 6 were trained by benchmarks/data_scaling.py; `refiner-rt train --recipe heldout-scenes-v1`
    # with the same images, budget and network writes the same weights.
    from benchmarks import data_scaling

    common = ["--val", "4", "--test", "4", "--samples", "40", "--epoch-samples", "20", "--threads", "1",
              "--config", json.dumps(TINY)]
    argv = ["--data", str(cubes / "cubes"), "--object", "003_cracker_box", "--modes", "scenes", "--sizes", "10",
            "--split-objects", "003_cracker_box,006_mustard_bottle", "--arch", "fusion", "--rotation-frame", "ray",
            "--lr", "0.001", "--seed", "0", "--augment", "--background", "0.5", "--skip-plain", "--skip-jitter",
            *common, "--cache", str(tmp_path / "c1"), "--save", str(tmp_path / "study"), "--quiet"]
    assert data_scaling.main(argv) == 0
    study = next((tmp_path / "study").glob("*.pt"))
    cli = ["train", "--recipe", "heldout-scenes-v1", "--data", str(cubes / "cubes"), "--objects", "003_cracker_box",
           "--split-objects", "003_cracker_box,006_mustard_bottle", "--base-per-object", "10", "--val-per-object",
           "4", "--test-per-object", "4", "--samples", "40", "--epoch-samples", "20", "--threads", "1", "--config",
           json.dumps(TINY), "--cache", str(tmp_path / "c2"), "--out", str(tmp_path / "cli" / "m.pt"), "--quiet"]
    res = CliRunner().invoke(main, cli, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert _same(_weights(study), _weights(tmp_path / "cli" / "m.pt"))


def test_devices_and_the_ddp_backend_follow_the_tensors():
    from models.train.recipe import RecipeError
    from models.train.run import distributed_backend, resolve_device

    assert resolve_device("cpu").type == "cpu"
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else resolve_device("auto").type)
    assert distributed_backend(torch.device("cuda:0")) == "nccl"
    assert distributed_backend(torch.device("cpu")) == "gloo" and distributed_backend("mps") == "gloo"
    if not torch.cuda.is_available():
        with pytest.raises(RecipeError, match="CUDA is not available"):
            resolve_device("cuda")
        res = CliRunner().invoke(main, ["train", "--data", ".", "--out", "x.pt", "--device", "cuda:0"])
        assert res.exit_code == 2 and "--device" in res.output


def test_training_on_a_device_saves_device_free_checkpoints(cubes, tmp_path):
    # On a machine with CUDA this trains there; everywhere the checkpoint's tensors are on the CPU.
    import models
    from models.train.run import resolve_device

    device = resolve_device("auto")
    r = _tiny(cubes, per_object=0, device=str(device))
    out = models.run_training(r, out=tmp_path / "d.pt", progress=False)
    state = _weights(out["base"])
    assert all(v.device.type == "cpu" for v in state.values())
    model, _ = models.load_checkpoint(out["base"])
    assert next(model.parameters()).device.type == "cpu"
