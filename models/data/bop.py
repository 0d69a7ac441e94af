"""Reader for BOP-format datasets (BOP's YCB-V and the project's rendered scenes), producing :class:`Sample` records.

Format (BOP toolkit, ``docs/bop_datasets_format.md`` and ``bop_toolkit_lib/inout.py``), as
summarised in docs/design.md §6.3::

    <split_dir>/<scene:06d>/rgb/<im_id:06d>.png|.jpg
    <split_dir>/<scene:06d>/scene_gt.json        {"<im_id>": [{"cam_R_m2c": 9 numbers row-major,
                                                  "cam_t_m2c": 3 numbers in mm, "obj_id": int}, ...]}
    <split_dir>/<scene:06d>/scene_gt_info.json   {"<im_id>": [{"bbox_obj": [x, y, w, h],
                                                  "bbox_visib": [x, y, w, h], "visib_fract": float,
                                                  "px_count_*": int}, ...]}  (same order as scene_gt)
    <split_dir>/<scene:06d>/scene_camera.json    {"<im_id>": {"cam_K": 9 numbers row-major,
                                                  "depth_scale": float}}
    <split_dir>/<scene:06d>/mask_visib/<im_id:06d>_<gt_idx:06d>.png   optional: the instance's visible
                                                  pixels (non-zero); used by background augmentation

Conventions of the produced samples: ``R`` object to camera (``cam_R_m2c``), ``t`` in **metres**
(``cam_t_m2c / 1000``), ``box_xyxy = (x, y, x + w, y + h)`` in continuous pixel coordinates.
BOP ids map to YCB id strings with :data:`models.data.objects.BOP_YCBV_OBJ_IDS` (YCB-V numbering,
also used by the renderer) unless another map is given.

Box choice: by default the **visible** box ``bbox_visib``, because that is what a 2D detector
gives a refiner at run time (detectors are trained on modal, visible-extent boxes); ``box="obj"``
uses the amodal ``bbox_obj`` (the projection of the whole object, which may extend past the image).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from models.data.objects import obj_id_map_for, validate_object_ids
from models.data.sample import (
    Sample,
    check_box,
    check_filter_values,
    check_intrinsics,
    check_rotations,
    read_image_size,
)

__all__ = ["load_bop", "BOX_FIELDS", "list_scenes", "read_json"]

log = logging.getLogger(__name__)

# box argument of load_bop -> scene_gt_info.json field
BOX_FIELDS = {"visib": "bbox_visib", "obj": "bbox_obj"}
_IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


def read_json(path: Path) -> dict:
    """Read one of a scene's JSON files as a dict keyed by ``im_id`` string.

    Raises:
        FileNotFoundError: the file is missing.
        ValueError: invalid JSON, or not an object keyed by integer image ids.
    """
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing (every BOP scene needs scene_gt.json, scene_gt_info.json, scene_camera.json)")
    try:
        with open(path, encoding="utf-8") as f:
            content = json.load(f)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: invalid JSON ({exc})") from exc
    if not isinstance(content, dict):
        raise ValueError(f"{path}: expected a JSON object keyed by image id; got {type(content).__name__}")
    for key in content:
        if not key.isdigit():
            raise ValueError(f"{path}: keys must be integer image ids; got key {key!r}")
    return content


def list_scenes(split_dir: str | os.PathLike) -> list[Path]:
    """Scene folders of a BOP split: sub-folders holding a ``scene_gt.json``, sorted by name.

    Raises:
        FileNotFoundError: ``split_dir`` does not exist.
        ValueError: no scene folder in it.
    """
    split_dir = Path(split_dir)
    if not split_dir.is_dir():
        raise FileNotFoundError(f"{split_dir}: no such folder (expected a BOP split such as ycbv/test)")
    scenes = sorted(p for p in split_dir.iterdir() if p.is_dir() and (p / "scene_gt.json").is_file())
    if not scenes:
        hint = " (it is itself a scene folder: pass its parent)" if (split_dir / "scene_gt.json").is_file() else ""
        raise ValueError(f"{split_dir}: no BOP scene folders (sub-folders with scene_gt.json){hint}")
    return scenes


def _numbers(value, n: int, where: str) -> np.ndarray:
    """A JSON list of ``n`` finite numbers as float64, or a ValueError naming ``where``."""
    ok = isinstance(value, list) and len(value) == n
    ok = ok and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    if not ok:
        got = f"a list of {len(value)}" if isinstance(value, list) and len(value) > 12 else repr(value)
        raise ValueError(f"{where} must be a list of {n} numbers; got {got}")
    out = np.array(value, dtype=np.float64)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{where} must be finite; got {out.tolist()}")
    return out


def _field(entry, key: str, where: str):
    if not isinstance(entry, dict):
        raise ValueError(f"{where} must be a JSON object; got {type(entry).__name__}")
    if key not in entry:
        raise ValueError(f"{where}: missing field {key!r}")
    return entry[key]


def _image_path(scene: Path, listing: set[str], im_id: int) -> Path:
    for ext in _IMAGE_EXTENSIONS:
        name = f"{im_id:06d}{ext}"
        if name in listing:
            return scene / "rgb" / name
    raise FileNotFoundError(f"{scene / 'rgb' / f'{im_id:06d}'}.png|.jpg: missing image for im_id {im_id}")


def _read_scene(scene: Path, id_map, wanted, box, min_visib, min_box_size, records, matrices, where_R) -> int:
    """Append the kept instances of one scene folder to ``records``, their ``cam_R_m2c`` to
    ``matrices`` and its file/field label to ``where_R``; return the number of invisible instances."""
    box_field = BOX_FIELDS[box]
    gt_path, info_path, cam_path = (scene / n for n in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"))
    scene_gt, scene_info, scene_cam = read_json(gt_path), read_json(info_path), read_json(cam_path)
    listing = set(os.listdir(scene / "rgb")) if (scene / "rgb").is_dir() else set()
    masks = set(os.listdir(scene / "mask_visib")) if (scene / "mask_visib").is_dir() else set()
    size = None  # (width, height), read from the first image used: a scene is one camera
    n_invisible = 0
    for key in sorted(scene_gt, key=int):
        im_id = int(key)
        gts = scene_gt[key]
        if not isinstance(gts, list):
            raise ValueError(f"{gt_path}: image {key}: expected a list of instances; got {type(gts).__name__}")
        if key not in scene_info:
            raise ValueError(f"{info_path}: missing image {key} (listed in {gt_path.name})")
        infos = scene_info[key]
        if not isinstance(infos, list) or len(infos) != len(gts):
            got = len(infos) if isinstance(infos, list) else type(infos).__name__
            raise ValueError(
                f"{info_path}: image {key}: expected {len(gts)} entries, one per instance in {gt_path.name}; got {got}"
            )
        K = None
        for inst, (gt, info) in enumerate(zip(gts, infos)):
            where_gt = f"{gt_path}: image {key}, instance {inst}"
            where_info = f"{info_path}: image {key}, instance {inst}"
            obj = _field(gt, "obj_id", where_gt)
            if isinstance(obj, bool) or not isinstance(obj, int) or obj not in id_map:
                raise ValueError(f"{where_gt}: field 'obj_id' must be one of {sorted(id_map)}; got {obj!r}")
            name = id_map[obj]
            if wanted is not None and name not in wanted:
                continue
            R = _numbers(_field(gt, "cam_R_m2c", where_gt), 9, f"{where_gt}: field 'cam_R_m2c'").reshape(3, 3)
            t = _numbers(_field(gt, "cam_t_m2c", where_gt), 3, f"{where_gt}: field 'cam_t_m2c'") / 1000.0
            visib = _numbers([_field(info, "visib_fract", where_info)], 1, f"{where_info}: field 'visib_fract'")[0]
            if not 0.0 <= visib <= 1.0:
                raise ValueError(f"{where_info}: field 'visib_fract' must be in [0, 1]; got {visib}")
            xywh_visib = _numbers(_field(info, "bbox_visib", where_info), 4, f"{where_info}: field 'bbox_visib'")
            if visib <= 0.0 or xywh_visib[2] <= 0 or xywh_visib[3] <= 0:
                n_invisible += 1
                continue
            if visib < min_visib:
                continue
            xywh = xywh_visib if box == "visib" else _numbers(
                _field(info, box_field, where_info), 4, f"{where_info}: field {box_field!r}"
            )
            if K is None:
                cam = scene_cam.get(key)
                if cam is None:
                    raise ValueError(f"{cam_path}: missing image {key} (listed in {gt_path.name})")
                where_K = f"{cam_path}: image {key}: field 'cam_K'"
                K = check_intrinsics(_numbers(_field(cam, "cam_K", f"{cam_path}: image {key}"), 9, where_K), where_K)
            image = _image_path(scene, listing, im_id)
            if size is None:
                size = read_image_size(image)
            xyxy = np.array([xywh[0], xywh[1], xywh[0] + xywh[2], xywh[1] + xywh[3]])
            xyxy = check_box(xyxy, size, f"{where_info}: field {box_field!r} (as x1, y1, x2, y2)", inside=box == "visib")
            if max(xyxy[2] - xyxy[0], xyxy[3] - xyxy[1]) < min_box_size:
                continue
            mask = f"{im_id:06d}_{inst:06d}.png"
            mask = str(scene / "mask_visib" / mask) if mask in masks else ""
            records.append((scene.name, im_id, inst, name, t, xyxy, K, visib, image, size, mask))
            matrices.append(R)
            where_R.append(f"{where_gt}: field 'cam_R_m2c'")
    return n_invisible


def load_bop(
    split_dir: str | os.PathLike,
    objects: Iterable[str] | None = None,
    min_visib: float = 0.0,
    *,
    box: str = "visib",
    min_box_size: float = 0.0,
    rotation_method: str = "premerlani",
    obj_id_map: Mapping[int, str] | None = None,
) -> list[Sample]:
    """Load the annotated object instances of a BOP split as samples.

    Instances with no visible pixel (``visib_fract == 0`` or an empty ``bbox_visib``, which BOP
    writes as ``[-1, -1, -1, -1]``) are always skipped: their crop would show only the occluder.

    Args:
        split_dir: folder holding the scene folders (e.g. BOP's ``ycbv/test``, or the output of
            ``refiner-rt render``).
        objects: YCB id strings to keep; ``None`` keeps every object.
        min_visib: keep instances with ``visib_fract >= min_visib`` (``[0, 1]``).
        box: ``"visib"`` (default: ``bbox_visib``, the visible extent, what a detector gives) or
            ``"obj"`` (``bbox_obj``, the amodal extent of the whole object).
        min_box_size: drop boxes whose longer side (the side that sets the crop window) is
            shorter than this, in pixels.
        rotation_method: re-orthonormalisation of ``cam_R_m2c``: ``"premerlani"`` (the paper's)
            or ``"svd"``.
        obj_id_map: BOP ``obj_id`` -> object name; default the split folder's ``objects.json`` record (a render of
            your own objects) over the YCB-V numbering (:func:`models.data.objects.obj_id_map_for`).

    Returns:
        Samples in (scene, im_id, instance) order: ``R`` object to camera (float64,
        re-orthonormalised), ``t`` metres, ``box_xyxy`` continuous pixels ``(x, y, x + w, y + h)``,
        ``K`` from ``cam_K``, ``visib_fract`` from ``scene_gt_info.json``, ``scene_id`` the scene
        folder name, ``frame_id`` the ``im_id``, ``dataset`` the absolute ``split_dir``.

    Raises:
        FileNotFoundError: a missing split folder, JSON file or image.
        ValueError: malformed files (missing key, wrong length, unknown ``obj_id``, a matrix that
            is not a rotation, a box outside the image, annotation lists that disagree), naming the
            file and the field; bad arguments.
    """
    if box not in BOX_FIELDS:
        raise ValueError(f"box must be one of {sorted(BOX_FIELDS)} (bbox_visib / bbox_obj); got {box!r}")
    check_filter_values(min_visib, min_box_size)
    id_map = dict(obj_id_map_for(split_dir) if obj_id_map is None else obj_id_map)
    wanted = validate_object_ids(objects, known=id_map.values())
    split_dir = Path(split_dir).absolute()

    records, matrices, where_R = [], [], []  # one entry per kept instance; matrices checked together below
    n_invisible = 0
    scenes = list_scenes(split_dir)
    for scene in scenes:
        n_invisible += _read_scene(scene, id_map, wanted, box, min_visib, min_box_size, records, matrices, where_R)

    if not records:
        log.warning(
            "load_bop(%s): no samples left after filters (objects=%s, min_visib=%s, min_box_size=%s)",
            split_dir, objects, min_visib, min_box_size,
        )
        return []
    rotations = check_rotations(np.stack(matrices), where_R, method=rotation_method)
    samples = [
        Sample(
            image_path=str(image),
            obj_id=name,
            R=rotations[i],
            t=t,
            box_xyxy=xyxy,
            K=K,
            image_size=size,
            scene_id=scene_name,
            frame_id=im_id,
            visib_fract=visib,
            dataset=str(split_dir),
            instance=inst,
            box_source=f"bop:{BOX_FIELDS[box]}",
            mask_path=mask,
        )
        for i, (scene_name, im_id, inst, name, t, xyxy, K, visib, image, size, mask) in enumerate(records)
    ]
    log.info(
        "load_bop(%s): %d samples from %d scenes (%d invisible instances skipped)",
        split_dir, len(samples), len(scenes), n_invisible,
    )
    return samples
