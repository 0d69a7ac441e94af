"""Some of a model's objects keep the model's split.

The scenes split gives each scene to test, validation or training by all the objects it holds, so the same data
split over a subset of the objects puts other scenes in test. Evaluating or fine-tuning a subset of a model's
objects must therefore use the split drawn over the model's objects (``DataSpec.split_objects``), and a fine-tuning
split whose validation or test crops the base network was trained on is refused.
"""

import json
import re

from click.testing import CliRunner
import pytest

from refiner_rt.cli import main
from tests.cube_dataset import make_cube_dataset

C, M = "003_cracker_box", "006_mustard_bottle"
SIZES = (20, 0, 10, 10)
SMALL = {"input_size": 32, "conv_channels": [8, 8], "fuse_width": 128, "pose_widths": [32, 128], "head_widths": [64, 32]}


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """Scenes 0-5 hold both cubes, scenes 6-11 only the cracker box; and a base checkpoint split over both."""
    import models
    from models.data.pipeline import DataSpec

    root = tmp_path_factory.mktemp("mixed")
    data = root / "data"
    make_cube_dataset(data, obj_ids=(2, 5), scenes=6, frames=10)
    make_cube_dataset(root / "alone", obj_ids=(2,), scenes=6, frames=10, seed=1)
    for s in range(6):
        (root / "alone" / f"{s:06d}").rename(data / f"{s + 6:06d}")
    spec = DataSpec(data=str(data), objects=[C, M], split_mode="scenes", sizes=SIZES)
    base = root / "base" / "cube.pt"
    base.parent.mkdir()
    models.save_checkpoint(models.build_refiner("fusion", **SMALL), base, objects=[C, M], stage="base",
                           rotation_frame="camera", data=spec.as_dict())
    return data, spec, base


def _scenes(samples):
    return {s.scene_key for s in samples}


def _keys(samples):
    return [(s.scene_key, s.frame_id, s.instance) for s in samples]


def test_split_objects_keeps_the_full_split_where_a_subset_alone_would_move_test_scenes(mixed):
    from models.data.pipeline import PARTS, DataSpec, load_splits

    data, spec, _ = mixed
    full = load_splits(spec)
    alone = load_splits(DataSpec(data=str(data), objects=[C], split_mode="scenes", sizes=SIZES))
    kept = load_splits(DataSpec(data=str(data), objects=[C], split_objects=[C, M], split_mode="scenes", sizes=SIZES))
    assert _scenes(alone.test) & _scenes(full.train_base)  # the hazard is real on this data
    for part in PARTS:
        assert _keys(kept.part(part)) == _keys(full.part(part, C)), part
    assert set(kept.sizes_per_object) == {C}
    with pytest.raises(ValueError, match=r"not among split_objects"):
        load_splits(DataSpec(data=str(data), objects=[C, M], split_objects=[C], split_mode="scenes", sizes=SIZES))


def test_split_objects_is_recorded_only_when_set(mixed):
    from models.data.pipeline import DataSpec

    _, spec, _ = mixed
    assert "split_objects" not in spec.as_dict()  # specs (and cache keys) from before the field are unchanged
    sub = DataSpec(data=spec.data, objects=[C], split_objects=[C, M], split_mode="scenes", sizes=SIZES)
    assert sub.as_dict()["split_objects"] == [C, M]
    assert DataSpec.from_dict(sub.as_dict()) == sub


def test_eval_of_one_object_tests_on_the_models_split(mixed, tmp_path):
    from models.data.pipeline import load_splits

    data, spec, base = mixed
    out = tmp_path / "eval.json"
    res = CliRunner().invoke(main, ["eval", str(base), "--data", str(data), "--objects", C, "--threads", "1",
                                    "--quiet", "--cache", str(tmp_path / "cache"), "--json", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["data"]["split_objects"] == [C, M] and doc["data"]["objects"] == [C]
    assert list(doc["objects"]) == [C]
    assert doc["objects"][C]["n"] == len(load_splits(spec).part("test", C))


def test_fine_tuning_one_object_of_a_scenes_base_keeps_its_split(mixed, tmp_path):
    import models
    from models.data.pipeline import DataSpec, load_splits

    data, spec, base = mixed
    common = ["train", "--data", str(data), "--base", str(base), "--arch", "fusion", "--split-mode", "scenes",
              "--base-per-object", "0", "--val-per-object", str(SIZES[2]), "--ft-epochs-mse", "0",
              "--ft-epochs-geodesic", "1", "--threads", "1", "--quiet", "--cache", str(tmp_path / "cache")]
    out = tmp_path / "ft" / "cube.pt"
    res = CliRunner().invoke(main, common + ["--out", str(out), "--objects", C, "--per-object", str(SIZES[0]),
                                             "--test-per-object", str(SIZES[3])])
    assert res.exit_code == 0, res.output
    _, info = models.load_checkpoint(out.with_name(f"cube.{C}.pt"))
    assert info["data"]["split_objects"] == [C, M]
    tuned = load_splits(DataSpec.from_dict(info["data"]))
    full = load_splits(spec)
    assert _keys(tuned.test) == _keys(full.part("test", C))
    assert not _scenes(tuned.val + tuned.test) & _scenes(full.train_base)

    # Another test size redraws the scenes: some of the new test scenes are ones the base network trained on.
    res = CliRunner().invoke(main, common + ["--out", str(tmp_path / "bad" / "cube.pt"), "--per-object",
                                             str(SIZES[0]), "--test-per-object", "20"])
    assert res.exit_code == 1, res.output
    assert "come from scenes the base network" in res.output
    assert "validation/test 10/10" in res.output and "validation/test 10/20" in res.output


def test_an_empty_split_part_says_how_many_scenes_each_part_got_and_which_flags_set_the_sizes(tmp_path):
    from models.data.pipeline import DataSpec, cropset_for, load_splits

    data = tmp_path / "small"
    make_cube_dataset(data, obj_ids=(2,), scenes=2, frames=4)
    spec = DataSpec(data=str(data), objects=[C], split_mode="scenes", sizes=(8, 0, 4, 4))
    splits = load_splits(spec)
    empty = next(p for p in ("val", "test", "train_base") if not getattr(splits, p))
    with pytest.raises(ValueError) as info:
        cropset_for(splits, empty, spec, 32, 1.2, cache_root=tmp_path / "c", progress=False)
    msg = str(info.value)
    assert f"split part {empty!r} is empty" in msg
    assert re.search(r"train_base \d+ samples from \d+ scenes, .*val \d+ samples from \d+ scenes", msg), msg
    assert "--val-per-object" in msg and "refiner-rt render --frames" in msg
