"""benchmarks/cross_split.py: models trained on a dataset and on that dataset extended by linked scenes, scored on
the same unseen test crops."""

import json

import pytest

from models.data.pipeline import DataSpec, load_splits
from tests.bench_scripts import load_benchmark
from tests.cube_dataset import make_cube_dataset


def _study(tmp, data, name):
    out = tmp / f"{name}.json"
    argv = ["--data", str(data), "--object", "003_cracker_box", "--modes", "scenes", "--sizes", "30", "--val", "10",
            "--test", "20", "--samples", "64", "--epoch-samples", "32", "--cache", str(tmp / "cache"),
            "--threads", "1", "--save", str(tmp / name), "--json", str(out), "--quiet"]
    assert load_benchmark("data_scaling").main(argv) == 0
    return json.loads(out.read_text())["rows"][0]["checkpoint"]


@pytest.fixture(scope="module")
def two_models(tmp_path_factory):
    """A model on twelve scenes, and one on those twelve (linked) plus twelve more."""
    tmp = tmp_path_factory.mktemp("cross")
    small, more, big = tmp / "small", tmp / "more", tmp / "big"
    make_cube_dataset(small, scenes=12, frames=5)
    make_cube_dataset(more, scenes=24, frames=5, seed=1)
    big.mkdir()
    for s in range(24):
        (big / f"{s:06d}").symlink_to((small if s < 12 else more) / f"{s:06d}", target_is_directory=True)
    return tmp, _study(tmp, small, "small"), _study(tmp, big, "big")


def _seen(ckpt):
    import models

    _, info = models.load_checkpoint(ckpt)
    splits = load_splits(DataSpec.from_dict(info["data"]))
    return {s.scene_id for part in ("train_base", "train_finetune", "val") for s in getattr(splits, part)
            if s.obj_id in info["objects"]}, splits


def test_one_model_is_scored_on_its_whole_test_part_as_error_breakdown_does(two_models):
    tmp, _, big = two_models
    out = tmp / "one.json"
    assert load_benchmark("cross_split").main([big, "--cache", str(tmp / "cache"), "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["kept_crops"] == r["test_crops"] == 20
    br = tmp / "breakdown.json"
    assert load_benchmark("error_breakdown").main([big, "--cache", str(tmp / "cache"), "--json", str(br)]) == 0
    test = json.loads(br.read_text())["results"][0]["parts"]["test"]
    assert r["models"][0]["mean_deg"] == pytest.approx(test["mean_deg"], abs=1e-9)
    assert r["models"][0]["n"] == test["n"]


def test_crops_from_scenes_either_model_saw_are_left_out(two_models, capsys):
    tmp, small, big = two_models
    out = tmp / "two.json"
    assert load_benchmark("cross_split").main([big, small, "--cache", str(tmp / "cache"), "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    seen_small, _ = _seen(small)
    seen_big, splits = _seen(big)
    test = [s for s in splits.test if s.obj_id == "003_cracker_box"]
    # Scene ids name the same scene in both datasets (0-11 are links to the small set's folders).
    unseen = [s for s in test if s.scene_id not in seen_small | seen_big]
    assert r["kept_crops"] == len(unseen) < r["test_crops"] == len(test)
    assert sorted(p.rsplit("/", 1)[1] for p in r["kept_scenes"]) == sorted({s.scene_id for s in unseen})
    assert [m["n"] for m in r["models"]] == [len(unseen)] * 2
    assert [m["seen_scenes"] for m in r["models"]] == [len(seen_big), len(seen_small)]
    assert f"| {big.rsplit('/', 1)[1]} | big | scenes | 30 |" in capsys.readouterr().out


def test_a_model_without_the_objects_is_refused(two_models, tmp_path, capsys):
    import torch

    tmp, small, big = two_models
    other = tmp_path / "other.pt"
    ckpt = torch.load(small, weights_only=False)
    ckpt["info"] = {**ckpt["info"], "objects": ["002_master_chef_can"]}
    torch.save(ckpt, other)
    with pytest.raises(SystemExit, match="do not cover the first checkpoint's"):
        load_benchmark("cross_split").main([big, str(other), "--cache", str(tmp / "cache")])
