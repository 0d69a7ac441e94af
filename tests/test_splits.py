"""Tests of the per-object splits (models/data/splits.py): disjoint, deterministic, sized, no scene leaks."""

from __future__ import annotations

import logging
import random
from collections import Counter

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from models.data import Sample, SplitSizes, make_splits
from models.data.splits import PARTS

OBJECTS = ("003_cracker_box", "006_mustard_bottle", "035_power_drill")


def synthetic_samples(n_scenes=30, frames=40, objects=OBJECTS, dataset="/data/renders", seed=0) -> list[Sample]:
    """Samples without files: every scene holds a random non-empty subset of ``objects`` in every frame."""
    rng = np.random.default_rng(seed)
    samples = []
    for scene in range(n_scenes):
        present = [o for o in objects if rng.random() < 0.7] or [objects[scene % len(objects)]]
        for frame in range(frames):
            for inst, obj in enumerate(present):
                samples.append(Sample(
                    image_path=f"{dataset}/{scene:06d}/rgb/{frame:06d}.jpg", obj_id=obj, R=np.eye(3),
                    t=[0.0, 0.0, 1.0], box_xyxy=[10.0, 10.0, 50.0, 60.0], K=np.eye(3), image_size=(640, 480),
                    scene_id=f"{scene:06d}", frame_id=frame, visib_fract=1.0, dataset=dataset, instance=inst,
                ))
    return samples


def ident(s: Sample) -> tuple:
    return (s.dataset, s.scene_id, s.frame_id, s.instance)


def part_ids(splits, name):
    return [ident(s) for s in getattr(splits, name)]


SMALL = SplitSizes(train_base=60, train_finetune=40, val=60, test=60)


def test_frames_parts_are_disjoint_and_sized_per_object():
    splits = make_splits(synthetic_samples(), mode="frames", sizes=SMALL, seed=0)
    seen = set()
    for name in PARTS:
        ids = part_ids(splits, name)
        assert len(ids) == len(set(ids))
        assert not seen & set(ids), f"{name} overlaps an earlier part"
        seen |= set(ids)
        counts = Counter(s.obj_id for s in getattr(splits, name))
        assert counts == {o: getattr(SMALL, name) for o in OBJECTS}
    assert len(splits.train) == 3 * 100


def test_frames_split_is_deterministic_and_independent_of_input_order():
    samples = synthetic_samples()
    a = make_splits(samples, mode="frames", sizes=SMALL, seed=3)
    shuffled = list(samples)
    random.Random(1).shuffle(shuffled)
    b = make_splits(shuffled, mode="frames", sizes=SMALL, seed=3)
    c = make_splits(samples, mode="frames", sizes=SMALL, seed=4)
    for name in PARTS:
        assert part_ids(a, name) == part_ids(b, name)
    assert part_ids(a, "test") != part_ids(c, "test")


def test_frames_test_set_does_not_move_when_training_grows():
    samples = synthetic_samples()
    a = make_splits(samples, mode="frames", sizes=SMALL, seed=0)
    b = make_splits(samples, mode="frames", sizes=SplitSizes(train_base=200, train_finetune=100, val=60, test=60), seed=0)
    assert part_ids(a, "test") == part_ids(b, "test")
    assert part_ids(a, "val") == part_ids(b, "val")


def test_frames_split_mixes_scenes_like_the_paper():
    splits = make_splits(synthetic_samples(), mode="frames", sizes=SMALL, seed=0)
    shared = {s.scene_key for s in splits.test} & {s.scene_key for s in splits.train}
    assert len(shared) > 10  # test frames have neighbours from the same video in training


def test_too_few_samples_scale_down_with_a_warning(caplog):
    samples = synthetic_samples(n_scenes=4, frames=10, objects=("003_cracker_box",))  # 40 samples
    sizes = SplitSizes(train_base=30, train_finetune=20, val=30, test=30)  # 110 asked
    with caplog.at_level(logging.WARNING, logger="models.data.splits"):
        splits = make_splits(samples, mode="frames", sizes=sizes, seed=0)
    assert "has 40 samples, fewer than the 110 requested" in caplog.text
    got = {name: len(getattr(splits, name)) for name in PARTS}
    assert sum(got.values()) == 40
    assert got == splits.sizes_per_object["003_cracker_box"].as_dict()
    assert got == {"train_base": 11, "train_finetune": 7, "val": 11, "test": 11}
    with pytest.raises(ValueError, match="has 40 samples, fewer than the 110 requested.*strict=False"):
        make_splits(samples, mode="frames", sizes=sizes, seed=0, strict=True)


def test_scaled_sizes_sum_to_the_available_count():
    sizes = SplitSizes()
    for available in (0, 1, 7, 1000, 10999, 11000, 20000):
        scaled = sizes.scaled_to(available)
        assert scaled.total == min(available, sizes.total)
    assert sizes.scaled_to(5500).as_dict() == {"train_base": 1500, "train_finetune": 1000, "val": 1500, "test": 1500}


def test_scenes_mode_never_puts_a_scene_in_two_parts():
    samples = synthetic_samples(n_scenes=40)
    splits = make_splits(samples, mode="scenes", sizes=SMALL, seed=0)
    owner = {}
    for name in PARTS:
        for s in getattr(splits, name):
            group = "train" if name.startswith("train") else name
            assert owner.setdefault(s.scene_key, group) == group, f"scene {s.scene_key} in {owner[s.scene_key]} and {group}"
    summary = splits.summary()
    assert summary["mode"] == "scenes"
    assert all(summary["parts"][p]["scenes"] > 0 for p in PARTS)


def test_scenes_mode_reaches_the_sizes_when_data_suffices():
    splits = make_splits(synthetic_samples(n_scenes=40), mode="scenes", sizes=SMALL, seed=0)
    for name in PARTS:
        assert Counter(s.obj_id for s in getattr(splits, name)) == {o: getattr(SMALL, name) for o in OBJECTS}


def test_scenes_mode_holds_out_roughly_the_target_share_of_scenes():
    # 60 scenes of 40 frames, 2200 of 2400 samples asked: test's share is 600 / 2200 of the scenes (16.4),
    # enough for its 600 samples (15 scenes), and val's the same; train gets the rest.
    samples = synthetic_samples(n_scenes=60, objects=("003_cracker_box",))
    sizes = SplitSizes(train_base=600, train_finetune=400, val=600, test=600)
    splits = make_splits(samples, mode="scenes", sizes=sizes, seed=0)
    for name in ("test", "val"):
        assert 16 <= len({s.scene_key for s in getattr(splits, name)}) <= 18
        assert len(getattr(splits, name)) == 600
    assert len(splits.train) == 1000


def test_scenes_mode_is_deterministic_and_seeded():
    samples = synthetic_samples(n_scenes=40)
    a = make_splits(samples, mode="scenes", sizes=SMALL, seed=5)
    b = make_splits(list(reversed(samples)), mode="scenes", sizes=SMALL, seed=5)
    c = make_splits(samples, mode="scenes", sizes=SMALL, seed=6)
    for name in PARTS:
        assert part_ids(a, name) == part_ids(b, name)
    assert {s.scene_key for s in a.test} != {s.scene_key for s in c.test}


def test_scenes_mode_short_part_warns_or_raises(caplog):
    samples = synthetic_samples(n_scenes=3, frames=10, objects=("003_cracker_box",))  # 3 scenes of 10
    sizes = SplitSizes(train_base=5, train_finetune=5, val=5, test=5)  # 20 asked of 30
    with caplog.at_level(logging.WARNING, logger="models.data.splits"):
        splits = make_splits(samples, mode="scenes", sizes=sizes, seed=0)
    assert len(splits.test) == 5 and len(splits.val) == 5 and len(splits.train) == 10
    assert len({s.scene_key for s in splits.test + splits.val + splits.train}) == 3
    samples = synthetic_samples(n_scenes=2, frames=10, objects=("003_cracker_box",))  # 2 scenes for 3 groups
    with pytest.raises(ValueError, match="fewer than the .* asked \\(scenes are indivisible\\)"):
        make_splits(samples, mode="scenes", sizes=sizes, seed=0, strict=True)


def test_scenes_from_two_datasets_with_the_same_names_stay_apart():
    samples = synthetic_samples(n_scenes=10, dataset="/data/a") + synthetic_samples(n_scenes=10, dataset="/data/b", seed=1)
    splits = make_splits(samples, mode="scenes", sizes=SplitSizes(20, 10, 20, 20), seed=0)
    assert len({s.scene_key for s in splits.test}) < len({s.scene_key for s in samples})
    assert not {s.scene_key for s in splits.test} & {s.scene_key for s in splits.train}


def test_part_accessor_and_summary():
    splits = make_splits(synthetic_samples(), mode="frames", sizes=SMALL, seed=0)
    assert len(splits.part("test", "003_cracker_box")) == 60
    assert len(splits.part("train")) == 300
    summary = splits.summary()
    assert summary["requested_per_object"] == SMALL.as_dict()
    assert summary["parts"]["val"]["per_object"] == {o: 60 for o in OBJECTS}
    with pytest.raises(ValueError, match="part must be one of"):
        splits.part("training")


def test_bad_arguments_are_refused():
    samples = synthetic_samples(n_scenes=2, frames=2)
    with pytest.raises(ValueError, match=r"mode must be one of \('frames', 'scenes'\); got 'random'"):
        make_splits(samples, mode="random")
    with pytest.raises(TypeError, match="sizes must be a SplitSizes"):
        make_splits(samples, sizes=(5000, 3000, 3000))
    with pytest.raises(ValueError, match="SplitSizes.val must be an integer >= 0; got -1"):
        SplitSizes(val=-1)
    with pytest.raises(ValueError, match="samples contain duplicates"):
        make_splits(samples + samples[:1])


@settings(max_examples=25, deadline=None)
@given(
    sizes=st.tuples(*[st.integers(0, 40)] * 4),
    n_scenes=st.integers(1, 12),
    seed=st.integers(0, 2**31),
    mode=st.sampled_from(["frames", "scenes"]),
)
def test_property_disjoint_bounded_and_no_scene_leak(sizes, n_scenes, seed, mode):
    samples = synthetic_samples(n_scenes=n_scenes, frames=8, seed=seed % 1000)
    requested = SplitSizes(*sizes)
    splits = make_splits(samples, mode=mode, sizes=requested, seed=seed)
    all_ids = [i for name in PARTS for i in part_ids(splits, name)]
    assert len(all_ids) == len(set(all_ids))
    for name in PARTS:
        for obj, n in Counter(s.obj_id for s in getattr(splits, name)).items():
            assert n <= getattr(requested, name)
    if mode == "scenes":
        groups = {}
        for name in PARTS:
            for s in getattr(splits, name):
                groups.setdefault(s.scene_key, set()).add("train" if name.startswith("train") else name)
        assert all(len(g) == 1 for g in groups.values())
