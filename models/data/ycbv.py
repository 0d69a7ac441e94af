"""Reader for the YCB-Video dataset in its native layout, producing :class:`models.data.Sample` records.

Format (Xiang et al., "PoseCNN", RSS 2018; the dataset's own README and ``classes.txt``), as
summarised in docs/design.md §6.2::

    <root>/data/<seq>/<frame>-color.png    640x480 colour image
    <root>/data/<seq>/<frame>-meta.mat     MATLAB file: poses 3x4xN (3x4 when N = 1), object to camera,
                                           metres; cls_indexes (N, 1-based into the 21 classes);
                                           intrinsic_matrix 3x3 (per frame: it changes from seq 60 on);
                                           factor_depth (depth scale, not used here)
    <root>/data/<seq>/<frame>-box.txt      one line per object: "<class name> x1 y1 x2 y2"
    <root>/data/<seq>/<frame>-label.png    optional: per-pixel 1-based class index (0 background);
                                           used by background augmentation
    <root>/image_sets/<name>.txt           frame lists, one "<seq>/<frame>" per line ("0048/000001")

Conventions of the produced samples: ``R`` object to camera (``poses[:, :3, i]``), ``t`` metres
(``poses[:, 3, i]``), ``box_xyxy`` the ``-box.txt`` numbers taken as continuous pixel
coordinates ``(x1, y1, x2, y2)`` as written, ``visib_fract`` ``None`` (the format does not record it).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from models.data.objects import YCBV_CLASSES, validate_object_ids
from models.data.sample import (
    Sample,
    check_box,
    check_filter_values,
    check_intrinsics,
    check_rotations,
    read_image_size,
)

__all__ = ["load_ycbv", "read_image_set", "read_meta", "read_box_file"]

log = logging.getLogger(__name__)

_META_FIELDS = ("poses", "cls_indexes", "intrinsic_matrix")


def read_image_set(path: str | os.PathLike) -> list[tuple[str, str]]:
    """Read a YCB-Video image-set file (lines ``"0048/000001"``).

    Args:
        path: the ``.txt`` file.

    Returns:
        ``[(seq, frame), ...]`` as strings, in file order (blank lines skipped).

    Raises:
        ValueError: a line that is not ``<seq>/<frame>`` with numeric parts, naming file and line.
    """
    frames = []
    with open(path, encoding="utf-8") as f:
        for lineno, line in enumerate(f, start=1):
            line = line.strip()
            if not line:
                continue
            parts = line.split("/")
            if len(parts) != 2 or not all(p.isdigit() for p in parts):
                raise ValueError(
                    f"{path}:{lineno}: expected a frame as '<seq>/<frame>' with numeric parts (e.g. '0048/000001'); "
                    f"got {line!r}"
                )
            frames.append((parts[0], parts[1]))
    return frames


def read_meta(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read the fields of a ``-meta.mat`` file this project needs.

    Args:
        path: the ``<frame>-meta.mat`` file.

    Returns:
        ``(poses, cls_indexes, K)``: ``(N, 3, 4)`` float64 object-to-camera poses ``[R | t]``
        (metres), ``(N,)`` int 1-based class indices, ``(3, 3)`` float64 intrinsics.

    Raises:
        ValueError: an unreadable file, a missing field, or a field of the wrong shape or values,
            naming the file and the field.
    """
    import scipy.io

    try:
        # variable_names skips the large fields (vertmap, center, ...) without decompressing them.
        mat = scipy.io.loadmat(str(path), variable_names=list(_META_FIELDS))
    except Exception as exc:  # scipy raises several types for corrupt files
        raise ValueError(f"{path}: cannot be read as a MATLAB .mat file ({type(exc).__name__}: {exc})") from exc
    for name in _META_FIELDS:
        if name not in mat:
            raise ValueError(f"{path}: missing field {name!r} (YCB-Video -meta.mat needs {', '.join(_META_FIELDS)})")

    poses = np.asarray(mat["poses"])
    if poses.dtype.kind not in "fiu":
        raise ValueError(f"{path}: field 'poses' must be numeric; got dtype {poses.dtype}")
    poses = poses.astype(np.float64)
    if poses.shape == (3, 4):  # MATLAB drops the trailing singleton axis when N = 1
        poses = poses[:, :, None]
    if poses.ndim != 3 or poses.shape[:2] != (3, 4):
        raise ValueError(f"{path}: field 'poses' must have shape 3x4xN (or 3x4 for one object); got {poses.shape}")
    poses = np.moveaxis(poses, 2, 0)

    cls = np.asarray(mat["cls_indexes"])
    if cls.dtype.kind not in "fiu":
        raise ValueError(f"{path}: field 'cls_indexes' must be numeric; got dtype {cls.dtype}")
    cls = cls.ravel().astype(np.float64)
    if cls.size != poses.shape[0]:
        raise ValueError(
            f"{path}: field 'cls_indexes' must have one entry per pose: expected {poses.shape[0]} (poses is "
            f"3x4x{poses.shape[0]}); got {cls.size}"
        )
    if not np.all(np.isfinite(cls)) or np.any(cls != np.round(cls)) or np.any((cls < 1) | (cls > len(YCBV_CLASSES))):
        raise ValueError(
            f"{path}: field 'cls_indexes' must hold 1-based class indices in 1..{len(YCBV_CLASSES)}; got {cls.tolist()}"
        )
    if len(np.unique(cls)) != cls.size:
        raise ValueError(f"{path}: field 'cls_indexes' lists a class twice; got {cls.astype(int).tolist()}")

    K = np.asarray(mat["intrinsic_matrix"])
    if K.shape != (3, 3) or K.dtype.kind not in "fiu":
        raise ValueError(f"{path}: field 'intrinsic_matrix' must be a numeric 3x3 matrix; got shape {K.shape}, dtype {K.dtype}")
    K = check_intrinsics(K, f"{path}: field 'intrinsic_matrix'")
    return poses, cls.astype(int), K


def read_box_file(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a ``-box.txt`` file (``"<class name> x1 y1 x2 y2"`` per line).

    Returns:
        ``{class name: (4,) float64 box (x1, y1, x2, y2) in pixels}``.

    Raises:
        ValueError: a malformed line, an unknown class name or a class listed twice, naming file and line.
    """
    boxes: dict[str, np.ndarray] = {}
    with open(path, encoding="utf-8") as f:
        for lineno, line in enumerate(f, start=1):
            parts = line.split()
            if not parts:
                continue
            where = f"{path}:{lineno}"
            if len(parts) != 5:
                raise ValueError(f"{where}: expected '<class name> x1 y1 x2 y2'; got {line.strip()!r}")
            name = parts[0]
            if name not in YCBV_CLASSES:
                raise ValueError(f"{where}: unknown class name {name!r}; expected one of the 21 YCB-Video classes")
            if name in boxes:
                raise ValueError(f"{where}: class {name!r} listed twice")
            try:
                boxes[name] = np.array([float(v) for v in parts[1:]], dtype=np.float64)
            except ValueError:
                raise ValueError(f"{where}: box of {name!r} must be 4 numbers x1 y1 x2 y2; got {parts[1:]}") from None
    return boxes


def _resolve_image_set(root: Path, image_set: str | os.PathLike) -> Path:
    candidate = Path(image_set)
    if candidate.is_file():
        return candidate
    named = root / "image_sets" / f"{image_set}.txt"
    if named.is_file():
        return named
    available = sorted(p.stem for p in (root / "image_sets").glob("*.txt")) if (root / "image_sets").is_dir() else []
    raise ValueError(
        f"image_set {str(image_set)!r} is neither a file nor a name in {root / 'image_sets'}; "
        f"available names: {available or 'none'}"
    )


def _all_frames(data: Path) -> list[tuple[str, str]]:
    frames = []
    for seq in sorted(p.name for p in data.iterdir() if p.is_dir()):
        for name in sorted(os.listdir(data / seq)):
            if name.endswith("-meta.mat"):
                frames.append((seq, name[: -len("-meta.mat")]))
    return frames


def load_ycbv(
    root: str | os.PathLike,
    image_set: str | os.PathLike | None = None,
    objects: Iterable[str] | None = None,
    *,
    min_box_size: float = 0.0,
    rotation_method: str = "premerlani",
) -> list[Sample]:
    """Load YCB-Video (native layout) annotations as samples, one per object instance.

    Args:
        root: dataset folder holding ``data/`` and ``image_sets/``.
        image_set: which frames: ``None`` for every frame with a ``-meta.mat`` under ``data/``,
            a name such as ``"keyframe"`` or ``"train"`` (``<root>/image_sets/<name>.txt``), or the
            path of an image-set file (lines ``"0048/000001"``).
        objects: YCB id strings to keep (e.g. :data:`models.data.objects.PAPER_OBJECTS`);
            ``None`` keeps all 21 classes.
        min_box_size: drop boxes whose longer side (the side that sets the crop window) is
            shorter than this, in pixels.
        rotation_method: re-orthonormalisation of ``poses[:, :3, i]``: ``"premerlani"`` (the
            paper's) or ``"svd"``.

    Returns:
        Samples in (sequence, frame, pose column) order. ``R`` object to camera (float64,
        re-orthonormalised), ``t`` metres, ``box_xyxy`` continuous pixels as in ``-box.txt``,
        ``K`` the frame's ``intrinsic_matrix``, ``visib_fract`` ``None``, ``scene_id`` the
        sequence (``"0048"``), ``frame_id`` the frame number, ``dataset`` the absolute ``root``.

    Raises:
        FileNotFoundError: a missing ``data/`` folder or a frame's colour, meta or box file.
        ValueError: malformed files (missing field, wrong shape, class index out of range, a pose
            that is not a rotation, a box outside the image), naming the file and the field;
            bad arguments.
    """
    root = Path(root).absolute()
    data = root / "data"
    if not data.is_dir():
        raise FileNotFoundError(f"{data}: no such folder; a YCB-Video root must hold data/<seq>/<frame>-meta.mat")
    wanted = validate_object_ids(objects)
    check_filter_values(0.0, min_box_size)
    frames = _all_frames(data) if image_set is None else read_image_set(_resolve_image_set(root, image_set))
    if not frames:
        raise ValueError(f"{root}: no frames found (image_set={image_set!r})")

    records = []  # (seq, frame, column, class name, R, t, box, K, image path, label path, class index)
    where_R = []
    listings: dict[str, set[str]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    for seq, frame in frames:
        seq_dir = data / seq
        if seq not in listings:
            listings[seq] = set(os.listdir(seq_dir)) if seq_dir.is_dir() else set()
        for suffix in ("-color.png", "-meta.mat", "-box.txt"):
            if frame + suffix not in listings[seq]:
                raise FileNotFoundError(f"{seq_dir / (frame + suffix)}: missing (frame {seq}/{frame})")
        color = seq_dir / f"{frame}-color.png"
        if seq not in sizes:  # one decode per sequence: a sequence is one camera
            sizes[seq] = read_image_size(color)
        meta_path = seq_dir / f"{frame}-meta.mat"
        box_path = seq_dir / f"{frame}-box.txt"
        poses, cls, K = read_meta(meta_path)
        boxes = read_box_file(box_path)
        for col, index in enumerate(cls):
            name = YCBV_CLASSES[index - 1]
            if wanted is not None and name not in wanted:
                continue
            if name not in boxes:
                raise ValueError(f"{box_path}: no line for class {name!r}, which {meta_path} lists in 'cls_indexes'")
            box = check_box(boxes[name], sizes[seq], f"{box_path}: box of {name!r}")
            if max(box[2] - box[0], box[3] - box[1]) < min_box_size:
                continue
            label = str(seq_dir / f"{frame}-label.png") if f"{frame}-label.png" in listings[seq] else ""
            records.append((seq, frame, col, name, poses[col, :, :3], poses[col, :, 3], box, K, color, label, index))
            where_R.append(f"{meta_path}: field 'poses'[:, :3, {col}] ({name})")

    if not records:
        log.warning("load_ycbv(%s): no samples left after filters (objects=%s, min_box_size=%s)", root, objects, min_box_size)
        return []
    rotations = check_rotations(np.stack([r[4] for r in records]), where_R, method=rotation_method)
    samples = [
        Sample(
            image_path=str(color),
            obj_id=name,
            R=rotations[i],
            t=t,
            box_xyxy=box,
            K=K,
            image_size=sizes[seq],
            scene_id=seq,
            frame_id=int(frame),
            visib_fract=None,
            dataset=str(root),
            instance=col,
            box_source="ycbv:box.txt",
            mask_path=label,
            mask_value=index if label else 0,
        )
        for i, (seq, frame, col, name, _, t, box, K, color, label, index) in enumerate(records)
    ]
    log.info("load_ycbv(%s): %d samples from %d frames", root, len(samples), len(frames))
    return samples
