"""From a dataset folder to CropSets: format detection, loading, the per-object split and the crop caches.

Shared by ``refiner-rt train`` and ``refiner-rt eval`` so that both see the same split of the same
data (same seed, sizes and mode) and the same crops (the crop cache, built by the shared crop rule).

Conventions: rotations object-to-camera, quaternions ``wxyz``, crops BGR uint8, boxes xyxy pixels.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from models.data.cropset import CropSet
from refiner_rt.geometry import ray_quaternions

__all__ = ["DataSpec", "detect_format", "load_samples", "load_splits", "cropset_for", "checkpoint_spec",
           "checkpoint_test_set", "whole_folder_spec", "PARTS"]

log = logging.getLogger(__name__)

PARTS = ("train_base", "train_finetune", "val", "test")


@dataclass
class DataSpec:
    """Which data and which split: everything needed to rebuild the same CropSets elsewhere.

    Attributes:
        data: dataset folder (a BOP split folder holding scene folders, or a YCB-Video root).
        fmt: ``"bop"``, ``"ycbv"`` or ``"auto"`` (detected from the layout).
        objects: YCB ids to use, or None for the paper's nine objects.
        split_objects: the objects the split is drawn over, when that is a larger set than ``objects`` (None:
            ``objects``). The ``scenes`` split gives each scene to a part by all the objects it holds, so a
            subset of objects split alone puts other scenes in test than the full set did; evaluating or
            fine-tuning some objects of a model trained on more names the model's objects here.
        split_mode: ``"frames"`` (paper) or ``"scenes"`` (whole scenes held out).
        split_seed: seed of the split.
        sizes: per-object ``(train_base, train_finetune, val, test)``; the paper's ``(3000, 2000, 3000, 3000)``.
        min_visib: minimum visible fraction of an instance.
        min_box_size: minimum longer box side in pixels.
        image_set: YCB-Video image set name or file (YCB-Video only).
        extra_train: more dataset folders whose every sample (of the spec's objects, with the same filters)
            joins ``train_base`` after ``data`` is split. The split of ``data`` (and so its val and test
            parts) is unchanged, so a set grows without moving its test scenes: render its next scenes
            into a new folder (``refiner-rt render --first-scene``). Their scene ids must not occur in ``data``.
    """

    data: str
    fmt: str = "auto"
    objects: list[str] | None = None
    split_mode: str = "frames"
    split_seed: int = 0
    sizes: tuple[int, int, int, int] = (3000, 2000, 3000, 3000)
    min_visib: float = 0.3
    min_box_size: float = 16.0
    image_set: str | None = None
    split_objects: list[str] | None = None
    extra_train: list[str] | None = None

    def as_dict(self) -> dict:
        d = asdict(self)
        d["sizes"] = list(self.sizes)
        for name in ("split_objects", "extra_train"):
            if d[name] is None:
                del d[name]  # the key of every spec (and crop cache) from before the field existed
        return d

    def held_out(self) -> "DataSpec":
        """The spec without ``extra_train``: the one that draws the split, so it fixes every part but ``train_base``
        (two specs with the same ``held_out()`` validate and test on the same crops)."""
        return replace(self, extra_train=None)

    @property
    def object_ids(self) -> list[str]:
        """The objects used: ``objects``, or the paper's nine."""
        from models.data import PAPER_OBJECTS

        return list(self.objects or PAPER_OBJECTS)

    @property
    def drawn_objects(self) -> list[str]:
        """The objects the split is drawn over: ``split_objects``, else :attr:`object_ids`."""
        return list(self.split_objects or self.object_ids)

    def split_objects_for(self, objects: list[str]) -> list[str] | None:
        """``split_objects`` for using some of this spec's objects on its split: its drawn objects when
        ``objects`` are fewer of them in ``scenes`` mode, else None (the frames split is drawn per object)."""
        drawn = self.drawn_objects
        return drawn if self.split_mode == "scenes" and set(objects) < set(drawn) else None

    @classmethod
    def from_dict(cls, d: dict) -> "DataSpec":
        d = dict(d)
        d["sizes"] = tuple(d.get("sizes", (3000, 2000, 3000, 3000)))
        return cls(**d)


def detect_format(data: Path) -> str:
    """``"ycbv"`` for a YCB-Video root (``data/`` + ``image_sets/``), ``"bop"`` for a folder of BOP scenes.

    Raises:
        FileNotFoundError: the folder does not exist.
        ValueError: neither layout is recognised (the message says what was looked for).
    """
    data = Path(data)
    if not data.is_dir():
        raise FileNotFoundError(f"dataset folder not found: {data}")
    if (data / "data").is_dir() and (data / "image_sets").is_dir():
        return "ycbv"
    if any((p / "scene_gt.json").is_file() for p in data.iterdir() if p.is_dir()):
        return "bop"
    raise ValueError(
        f"{data}: not a dataset: expected a YCB-Video root (data/ and image_sets/) or a BOP split "
        "folder with scene folders holding scene_gt.json"
    )


def load_samples(spec: DataSpec, objects: list[str] | None = None) -> list:
    """The samples of ``spec.data`` (filtered by objects, visibility and box size).

    ``objects`` overrides ``spec.objects`` (default: ``spec.objects``, or the paper's nine).
    """
    from models.data import load_bop, load_ycbv

    fmt = detect_format(Path(spec.data)) if spec.fmt == "auto" else spec.fmt
    objects = list(objects or spec.object_ids)
    if fmt == "bop":
        samples = load_bop(spec.data, objects=objects, min_visib=spec.min_visib, min_box_size=spec.min_box_size)
    elif fmt == "ycbv":
        # YCB-Video's native files record no visible fraction: only the box-size filter applies.
        samples = load_ycbv(spec.data, image_set=spec.image_set, objects=objects, min_box_size=spec.min_box_size)
        if spec.min_visib > 0:
            log.info("YCB-Video records no visible fraction: min_visib=%g not applied", spec.min_visib)
    else:
        raise ValueError(f"format must be 'bop', 'ycbv' or 'auto'; got {spec.fmt!r}")
    if not samples:
        raise ValueError(f"{spec.data}: no samples of {objects} with visib_fract >= {spec.min_visib}")
    return samples


def whole_folder_spec(data: str | Path, obj: str, part: str) -> DataSpec:
    """A :class:`DataSpec` that puts every instance of ``obj`` in ``data`` (the usual filters:
    ``visib_fract >= 0.3``, boxes of 16 px or more) into one part, ``"train_base"`` or ``"test"``: for a folder of
    scenes rendered apart from any training set (calibration crops, or fresh held-out scenes).

    Raises:
        ValueError: ``data`` is not a dataset, or has no visible instance of ``obj``.
    """
    spec = DataSpec(data=str(data), objects=[obj], split_mode="scenes", sizes=(0, 0, 0, 0))
    try:
        n = len(load_samples(spec))
    except (FileNotFoundError, ValueError) as exc:  # not a dataset, or no visible instance of obj
        raise ValueError(f"{data}: {exc}") from None
    return DataSpec.from_dict({**spec.as_dict(), "sizes": (n, 0, 0, 0) if part == "train_base" else (0, 0, 0, n)})


def load_splits(spec: DataSpec):
    """Load and split ``spec.data``; returns :class:`models.data.Splits`.

    With ``spec.split_objects`` the split is drawn over those objects and each part then keeps ``spec.objects``.
    With ``spec.extra_train`` every sample of those folders is appended to ``train_base``.

    Raises:
        ValueError: an object outside ``split_objects``, or an ``extra_train`` folder sharing a scene id with
            ``data`` or with another extra folder (it could hold the same scenes, some of them test scenes).
    """
    from models.data import SplitSizes, make_splits

    samples = load_samples(spec, spec.split_objects)
    base, fine, val, test = spec.sizes
    sizes = SplitSizes(train_base=base, train_finetune=fine, val=val, test=test)
    splits = make_splits(samples, mode=spec.split_mode, sizes=sizes, seed=spec.split_seed)
    if spec.split_objects:
        keep = set(spec.object_ids)
        missing = keep - set(spec.split_objects)
        if missing:
            raise ValueError(f"objects {sorted(missing)} are not among split_objects {spec.split_objects}; the split "
                             "must be drawn over every object it is used for")
        splits = replace(
            splits, **{p: [s for s in getattr(splits, p) if s.obj_id in keep] for p in PARTS},
            sizes_per_object={o: n for o, n in splits.sizes_per_object.items() if o in keep})
    if spec.extra_train:
        splits = replace(splits, train_base=splits.train_base + _extra_train_samples(spec, samples))
    return splits


def _extra_train_samples(spec: DataSpec, samples: list) -> list:
    """The samples of ``spec.extra_train``'s folders, after checking that no scene id repeats one already seen."""
    if isinstance(spec.extra_train, (str, Path)):
        raise ValueError(f"extra_train must be a list of dataset folders; got the single value {spec.extra_train!r}")
    seen = {s.scene_id: str(spec.data) for s in samples}
    extra = []
    for folder in spec.extra_train:
        more = load_samples(replace(spec, data=str(folder), fmt="auto", split_objects=None, extra_train=None))
        scenes = {s.scene_id for s in more}
        clash = sorted(scenes & set(seen))
        if clash:
            raise ValueError(
                f"extra_train folder {folder} has scene id(s) {clash[:5]}{' ...' if len(clash) > 5 else ''} that "
                f"{seen[clash[0]]} has too; the extra scenes must be new ones (render the next scenes of the same "
                "seed with `refiner-rt render --first-scene N`, N = the first set's scene count)")
        seen.update({sid: str(folder) for sid in scenes})
        extra += more
    return extra


def writable_cache_root(data: Path, cache_root: str | Path | None = None) -> Path:
    """Where the crop caches of ``data`` go: ``cache_root`` if given, else ``<data>/.crops``, or, when ``data`` is
    read-only (a shared evaluation set), ``~/.cache/refiner-rt/crops/<data's name>-<hash of its path>``."""
    if cache_root:
        return Path(cache_root)
    data = Path(data)
    if os.access(data, os.W_OK) or (data / ".crops").is_dir() and os.access(data / ".crops", os.W_OK):
        return data / ".crops"
    tag = hashlib.sha1(str(data.resolve()).encode()).hexdigest()[:10]
    return Path.home() / ".cache" / "refiner-rt" / "crops" / f"{data.resolve().name}-{tag}"


def _cache_dir(spec: DataSpec, part: str, size: int, context: float, cache_root: Path | None,
               crop_filter: str = "none") -> Path:
    if part != "train_base":
        spec = spec.held_out()  # extra training folders change no other part: share its cache
    key = json.dumps({**spec.as_dict(), "part": part, "size": size, "context": context,
                      **({"crop_filter": crop_filter} if crop_filter != "none" else {})}, sort_keys=True)
    tag = hashlib.sha1(key.encode()).hexdigest()[:10]
    return writable_cache_root(Path(spec.data), cache_root) / f"{spec.split_mode}_{part}_{size}_{tag}"


def cropset_for(
    splits,
    part: str,
    spec: DataSpec,
    size: int,
    context: float,
    *,
    cache_root: Path | None = None,
    workers: int = 1,
    progress: bool = True,
    obj_id: str | None = None,
    crop_filter: str = "none",
) -> CropSet:
    """The CropSet of one split part (optionally one object), through the crop cache.

    Args:
        splits: the :class:`models.data.Splits` of ``spec``.
        part: one of :data:`PARTS`.
        spec: the data spec (names the cache folder).
        size: crop side ``S`` (the model's ``input_size``).
        context: crop-rule context (the model's ``crop_context``).
        cache_root: where caches live (default ``<data>/.crops``).
        workers: processes that build the cache.
        progress: progress bar while building.
        obj_id: only this object's samples.
        crop_filter: the crop rule's filter (the model's ``config["crop_filter"]``).
    """
    from models.data import CropCache

    if part not in PARTS:
        raise ValueError(f"part must be one of {PARTS}; got {part!r}")
    samples = getattr(splits, part)
    if not samples:
        parts = {p: getattr(splits, p) for p in PARTS}
        scenes = {p: len({(str(x.dataset), x.scene_id) for x in v}) for p, v in parts.items()}
        have = ", ".join(f"{p} {len(v)} samples from {scenes[p]} scenes" for p, v in parts.items())
        raise ValueError(
            f"split part {part!r} is empty ({spec.split_mode} split of {spec.data}, per-object sizes train_base, "
            f"train_finetune, val, test = {tuple(spec.sizes)}; got {have}). The {spec.split_mode} split gives each "
            "part its share of the data" + (" in whole scenes, so every part needs at least one scene of each object"
                                             if spec.split_mode == "scenes" else "")
            + ": render more scenes (refiner-rt render --frames), or ask for fewer crops per part (refiner-rt train "
            "--base-per-object, --per-object, --val-per-object, --test-per-object)")
    cache = CropCache.build_or_load(
        samples, size, _cache_dir(spec, part, size, context, cache_root, crop_filter), context=context, workers=workers,
        progress=progress, crop_filter=crop_filter,
    )
    cs = CropSet(
        crops=cache.crops,
        q_gt=cache.q_gt,
        obj_ids=cache.obj_ids,
        q_ray=ray_quaternions(cache.K, cache.boxes_xyxy),
        scene_ids=np.asarray(cache.scene_ids),
        masks=cache.masks,
        has_mask=None if cache.masks is None else cache.has_mask,
    )
    return cs if obj_id is None else cs.for_object(obj_id)


def checkpoint_spec(info: dict, data: str | Path | None = None) -> DataSpec:
    """The data spec a checkpoint recorded (its split), with ``data`` as the dataset folder if it moved since training.

    Raises:
        ValueError: the checkpoint records no data spec (``info['data']``).
    """
    if not info.get("data"):
        raise ValueError("the checkpoint records no training data spec (info['data']); evaluate it with refiner-rt eval --data")
    return DataSpec.from_dict({**info["data"], **({"data": str(data)} if data is not None else {})})


def checkpoint_test_set(
    model,
    info: dict,
    *,
    data: str | Path | None = None,
    cache_root: Path | None = None,
    progress: bool = False,
    with_samples: bool = False,
) -> tuple:
    """The test crops a checkpoint was trained against: its recorded data spec, cropped for the model.

    Args:
        model: the loaded refiner (gives ``input_size`` and ``config["crop_context"]``).
        info: the checkpoint's ``info`` (``models.load_checkpoint``); its ``data`` entry names the split.
        data: the dataset folder if it moved since training (default: the recorded one).
        cache_root: where crop caches live (default ``<data>/.crops``).
        progress: progress bar while the cache is built.
        with_samples: also return the test part's samples (frames, boxes, poses), in the crops' order.

    Returns:
        ``(test CropSet, DataSpec)``, or ``(test CropSet, DataSpec, samples)`` with ``with_samples``.

    Raises:
        ValueError: the checkpoint records no data spec, or its split has no test part.
    """
    spec = checkpoint_spec(info, data)
    splits = load_splits(spec.held_out())  # the split is drawn without extra training folders
    test = cropset_for(splits, "test", spec, model.input_size, model.config["crop_context"],
                       cache_root=cache_root, progress=progress, crop_filter=model.config.get("crop_filter", "none"))
    return (test, spec, list(splits.test)) if with_samples else (test, spec)
