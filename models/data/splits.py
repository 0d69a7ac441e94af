"""Per-object train / validation / test splits of samples, in the paper's ``frames`` protocol or by whole ``scenes``.

The paper (Jain & Dellaert, "Fast 3D Pose Refinement with RGB Images", section "Training Data")
draws, per object, 5000 training images (3000 for the base network, 2000 more for per-object
fine-tuning), 3000 validation and 3000 test images from YCB-Video's frames at random
(docs/design.md §6.6). Two modes:

* ``"frames"``: each object's samples are shuffled and cut into parts. Consecutive video frames
  are near-duplicates, so test frames have close neighbours in training (the paper's protocol).
* ``"scenes"``: whole scenes (YCB-Video sequences, BOP scenes, rendered sequences) are held out
  for validation and test, **for all objects at once**: a scene belongs to exactly one part, so
  no test crop shares a room, arrangement or trajectory with any training crop of any object.

Both are deterministic for a given ``seed`` and independent of the order of the input list.
"""

from __future__ import annotations

import logging
import zlib
from collections import Counter, defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from models.data.sample import Sample, sort_key

__all__ = ["SplitSizes", "Splits", "make_splits", "PARTS", "SPLIT_MODES"]

log = logging.getLogger(__name__)

PARTS = ("train_base", "train_finetune", "val", "test")
SPLIT_MODES = ("frames", "scenes")


@dataclass(frozen=True)
class SplitSizes:
    """Samples per object in each part (the paper's sizes by default).

    Attributes:
        train_base: base-network training samples per object (paper: 3000).
        train_finetune: additional per-object fine-tuning samples (paper: 2000), disjoint from
            ``train_base``.
        val: validation samples per object (paper: 3000).
        test: test samples per object (paper: 3000).
    """

    train_base: int = 3000
    train_finetune: int = 2000
    val: int = 3000
    test: int = 3000

    def __post_init__(self):
        for name in PARTS:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"SplitSizes.{name} must be an integer >= 0; got {value!r}")

    @property
    def total(self) -> int:
        """Samples per object over all parts."""
        return self.train_base + self.train_finetune + self.val + self.test

    def as_dict(self) -> dict[str, int]:
        """``{part: size}`` in :data:`PARTS` order."""
        return {name: int(getattr(self, name)) for name in PARTS}

    def scaled_to(self, available: int) -> "SplitSizes":
        """Sizes scaled down proportionally so that they sum to at most ``available``.

        Each part gets ``floor(size * available / total)``, then the remainder goes to the parts
        with the largest fractional parts (test first on ties, then val, train_base,
        train_finetune), so the parts sum to exactly ``available``.
        """
        if available >= self.total:
            return self
        exact = {name: size * available / self.total for name, size in self.as_dict().items()}
        sizes = {name: int(np.floor(v)) for name, v in exact.items()}
        order = sorted(PARTS, key=lambda n: (-(exact[n] - sizes[n]), ("test", "val", "train_base", "train_finetune").index(n)))
        for name in order[: available - sum(sizes.values())]:
            sizes[name] += 1
        return SplitSizes(**sizes)


@dataclass
class Splits:
    """The result of :func:`make_splits`: four disjoint lists of samples.

    Attributes:
        train_base: base training samples (all objects).
        train_finetune: per-object fine-tuning samples, disjoint from ``train_base``.
        val: validation samples.
        test: test samples.
        mode: ``"frames"`` or ``"scenes"`` (every reported number names it).
        seed: the seed the split was drawn with.
        sizes: the requested per-object sizes.
        sizes_per_object: the sizes actually used per object (smaller when an object had fewer
            samples than requested).
    """

    train_base: list[Sample]
    train_finetune: list[Sample]
    val: list[Sample]
    test: list[Sample]
    mode: str
    seed: int
    sizes: SplitSizes
    sizes_per_object: dict[str, SplitSizes] = field(default_factory=dict)

    @property
    def train(self) -> list[Sample]:
        """``train_base + train_finetune`` (the paper's 5000 training images per object)."""
        return self.train_base + self.train_finetune

    def part(self, name: str, obj_id: str | None = None) -> list[Sample]:
        """One part (:data:`PARTS` or ``"train"``), optionally only one object's samples.

        Raises:
            ValueError: an unknown part name.
        """
        if name not in PARTS and name != "train":
            raise ValueError(f"part must be one of {PARTS + ('train',)}; got {name!r}")
        samples = getattr(self, name)
        return samples if obj_id is None else [s for s in samples if s.obj_id == obj_id]

    def summary(self) -> dict:
        """JSON-ready description: mode, seed, requested sizes, and per part and object the sample
        and scene counts (e.g. for a checkpoint's ``info`` or a results table)."""
        parts = {}
        for name in PARTS:
            samples = getattr(self, name)
            parts[name] = {
                "samples": len(samples),
                "scenes": len({s.scene_key for s in samples}),
                "per_object": dict(sorted(Counter(s.obj_id for s in samples).items())),
            }
        return {"mode": self.mode, "seed": self.seed, "requested_per_object": self.sizes.as_dict(), "parts": parts}


def _object_rng(seed: int, obj_id: str, salt: str) -> np.random.Generator:
    # crc32, not hash(): Python salts str hashes per process.
    return np.random.default_rng([int(seed), zlib.crc32(obj_id.encode()), zlib.crc32(salt.encode())])


def _sizes_for(obj_id: str, available: int, sizes: SplitSizes, strict: bool) -> SplitSizes:
    if available >= sizes.total:
        return sizes
    message = (
        f"object {obj_id!r} has {available} samples, fewer than the {sizes.total} requested "
        f"({sizes.as_dict()})"
    )
    if strict:
        raise ValueError(message + "; pass strict=False to scale the parts down proportionally")
    scaled = sizes.scaled_to(available)
    log.warning("%s: scaling down to %s", message, scaled.as_dict())
    return scaled


def make_splits(
    samples: Iterable[Sample],
    mode: str = "frames",
    sizes: SplitSizes | None = None,
    seed: int = 0,
    *,
    strict: bool = False,
) -> Splits:
    """Split samples per object into train_base / train_finetune / val / test.

    ``frames`` mode: per object, shuffle all samples (seeded by ``seed`` and the object id) and
    take the test part first, then val, train_base, train_finetune; so growing the training
    sizes never changes the test set.

    ``scenes`` mode: every scene (``Sample.scene_key``) goes whole to one of test, val or train,
    the same for all objects. Scenes are visited in a seeded random order and each goes to the part
    whose per-object targets are least filled, measured on the objects the scene contains; the
    targets are each part's share of the requested sizes applied to the object's available
    samples. Each part then draws its per-object size at random from its scenes; a part whose
    scenes hold fewer samples than asked keeps them all (logged). train_base and train_finetune
    come from the same training scenes, disjoint samples.

    Args:
        samples: samples of any number of objects and datasets.
        mode: ``"frames"`` (the paper's protocol) or ``"scenes"`` (whole scenes held out).
        sizes: requested samples per object (default the paper's 3000 + 2000, 3000, 3000).
        seed: random seed; the same seed and samples give the same split.
        strict: raise instead of scaling down when an object has fewer samples than requested
            (or, in ``scenes`` mode, when a part's scenes cannot supply its size).

    Returns:
        :class:`Splits`; each part is sorted by (dataset, scene, frame, instance).

    Raises:
        ValueError: an unknown mode, duplicated samples, or (``strict``) too few samples.
        TypeError: ``sizes`` is not a :class:`SplitSizes`.
    """
    if mode not in SPLIT_MODES:
        raise ValueError(f"mode must be one of {SPLIT_MODES}; got {mode!r}")
    sizes = SplitSizes() if sizes is None else sizes
    if not isinstance(sizes, SplitSizes):
        raise TypeError(f"sizes must be a SplitSizes(train_base, train_finetune, val, test); got {type(sizes).__name__}")
    samples = sorted(samples, key=sort_key)
    keys = [(s.dataset, s.scene_id, s.frame_id, s.instance) for s in samples]
    if len(set(keys)) != len(keys):
        dup = next(k for k, n in Counter(keys).items() if n > 1)
        raise ValueError(f"samples contain duplicates (same dataset, scene, frame, instance): {dup}")

    by_object: dict[str, list[Sample]] = defaultdict(list)
    for s in samples:
        by_object[s.obj_id].append(s)
    per_object = {obj: _sizes_for(obj, len(items), sizes, strict) for obj, items in sorted(by_object.items())}

    if mode == "frames":
        parts = _split_frames(by_object, per_object, seed)
    else:
        parts = _split_scenes(by_object, per_object, seed, strict)
    result = Splits(**{name: sorted(parts[name], key=sort_key) for name in PARTS}, mode=mode, seed=seed, sizes=sizes,
                    sizes_per_object=per_object)
    log.info("make_splits(mode=%s, seed=%d): %s", mode, seed, {n: len(getattr(result, n)) for n in PARTS})
    return result


def _split_frames(by_object, per_object, seed) -> dict[str, list[Sample]]:
    parts = {name: [] for name in PARTS}
    for obj, items in sorted(by_object.items()):
        order = _object_rng(seed, obj, "frames").permutation(len(items))
        start = 0
        for name in ("test", "val", "train_base", "train_finetune"):
            n = getattr(per_object[obj], name)
            parts[name].extend(items[i] for i in order[start : start + n])
            start += n
    return parts


def _split_scenes(by_object, per_object, seed, strict) -> dict[str, list[Sample]]:
    groups = ("test", "val", "train")
    # Per object, the share of its available samples each scene group should receive.
    goal = {}
    for obj, items in by_object.items():
        s = per_object[obj]
        want = {"test": s.test, "val": s.val, "train": s.train_base + s.train_finetune}
        total = sum(want.values())
        goal[obj] = {g: (len(items) * want[g] / total if total else 0.0) for g in groups}

    scene_counts: dict[tuple, Counter] = defaultdict(Counter)
    for obj, items in by_object.items():
        for s in items:
            scene_counts[s.scene_key][obj] += 1
    scenes = sorted(scene_counts)
    order = np.random.default_rng([int(seed), zlib.crc32(b"scenes")]).permutation(len(scenes))

    filled = {obj: dict.fromkeys(groups, 0) for obj in by_object}
    scene_group = {}
    for i in order:
        key = scenes[i]
        counts = scene_counts[key]
        best, best_score = None, -np.inf
        for g in groups:  # ties go to test, then val, then train
            # Remaining fraction of each object's target in group g, weighted by the scene's samples
            # of that object; an object g should receive none of counts against g.
            score, usable = 0.0, False
            for obj, n in counts.items():
                target = goal[obj][g]
                if target > 0:
                    score += n * (target - filled[obj][g]) / target
                    usable = True
                else:
                    score -= n
            if usable and score > best_score:
                best, best_score = g, score
        best = best or "train"
        scene_group[key] = best
        for obj, n in counts.items():
            filled[obj][best] += n

    parts = {name: [] for name in PARTS}
    for obj, items in sorted(by_object.items()):
        pools = {g: [s for s in items if scene_group[s.scene_key] == g] for g in groups}
        s = per_object[obj]
        for g, names in (("test", ("test",)), ("val", ("val",)), ("train", ("train_base", "train_finetune"))):
            pool = pools[g]
            wanted = sum(getattr(s, n) for n in names)
            if len(pool) < wanted:
                message = (
                    f"scenes split: object {obj!r} has {len(pool)} samples in its {g} scenes, fewer than the "
                    f"{wanted} asked"
                )
                if strict:
                    raise ValueError(message + " (scenes are indivisible); pass strict=False to accept fewer")
                log.warning("%s; using all %d", message, len(pool))
            order = _object_rng(seed, obj, "scenes-" + g).permutation(len(pool))
            start = 0
            for name in names:
                n = getattr(s, name)
                parts[name].extend(pool[i] for i in order[start : start + n])
                start += n
    return parts
