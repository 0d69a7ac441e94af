"""One annotated object instance in one image (:class:`Sample`), and the checks loaders run on file values.

Both readers (:func:`models.data.load_ycbv`, :func:`models.data.load_bop`) produce ``Sample``
records, so splits, the crop cache, training and evaluation never see a file format.

Conventions (docs/design.md §2):
    * ``R`` maps object to camera coordinates (``x_cam = R @ x_obj + t``), like YCB-Video's
      ``poses[:, :3, i]`` and BOP's ``cam_R_m2c``; ``t`` is in **metres**;
    * quaternions are ``wxyz`` (scalar first), ``w >= 0`` (:attr:`Sample.q_gt`);
    * boxes are ``(x1, y1, x2, y2)`` in pixels, float, continuous coordinates (pixel ``i`` covers
      ``[i, i + 1)``);
    * ``K`` is the 3x3 pinhole intrinsic matrix in pixels, in the same continuous-coordinate
      convention as the file it came from.

Rotation matrices read from files are re-orthonormalised (the paper's Premerlani-Bizard step by
default, SVD on request: :func:`refiner_rt.quaternion.orthonormalize`); a matrix that is far from a
rotation is a broken file and raises instead of being repaired.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from models.data.objects import YCBV_CLASSES, validate_object_ids
from refiner_rt import quaternion as rq

__all__ = [
    "Sample",
    "ROTATION_TOLERANCE",
    "ROTATION_METHODS",
    "BOX_OUTSIDE_TOLERANCE_PX",
    "filter_samples",
    "check_filter_values",
    "read_image_size",
    "check_rotations",
    "check_intrinsics",
    "check_box",
    "sort_key",
]

# Largest |R^T R - I| entry a file's rotation may have and still be repaired (the repair is then
# exact to ~1e-4 with one Premerlani step, exact with SVD); beyond it the file is broken.
ROTATION_TOLERANCE = 1e-2
ROTATION_METHODS = ("premerlani", "svd")
# A visible (mask) box may overshoot the image border by this much (rounding in the writer).
BOX_OUTSIDE_TOLERANCE_PX = 1.0


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Sample:
    """One object instance in one image with its ground-truth pose (object to camera).

    Attributes:
        image_path: path of the colour image (PNG or JPEG; read with ``cv2.imread``, i.e. BGR).
        obj_id: YCB id string, e.g. ``"003_cracker_box"`` (:mod:`models.data.objects`).
        R: ``(3, 3)`` float64 rotation, object to camera (``x_cam = R @ x_obj + t``),
            re-orthonormalised by the loader. Read-only.
        t: ``(3,)`` float64 translation in **metres**, object origin in camera coordinates. Read-only.
        box_xyxy: ``(4,)`` float64 box ``(x1, y1, x2, y2)`` in pixels, continuous coordinates. Read-only.
        K: ``(3, 3)`` float64 camera intrinsics in pixels. Read-only.
        image_size: ``(width, height)`` of the image in pixels.
        scene_id: sequence / scene name as in the files (YCB-Video ``"0048"``, BOP ``"000048"``).
        frame_id: frame number within the scene (YCB-Video ``000001`` -> 1, BOP ``im_id``).
        visib_fract: visible fraction of the object in ``[0, 1]``, ``None`` when the format does
            not record it (YCB-Video native).
        dataset: the directory the scene was read from (YCB-Video ``root``, BOP ``split_dir``);
            ``(dataset, scene_id)`` identifies a sequence across several loaded datasets.
        instance: index of this instance in the frame's annotation (BOP ``scene_gt`` list index,
            YCB-Video column of ``poses``).
        box_source: where ``box_xyxy`` came from: ``"bop:bbox_visib"``, ``"bop:bbox_obj"`` or
            ``"ycbv:box.txt"``.
        mask_path: the image of the instance's visible pixels, ``""`` when the dataset has none
            (BOP ``mask_visib/<im_id>_<gt_idx>.png``; YCB-Video ``<frame>-label.png``).
        mask_value: the pixel value of this instance in ``mask_path``: ``0`` means any non-zero
            pixel (BOP), otherwise the label (YCB-Video: the 1-based class index).

    Construction checks shapes and finiteness and stores float64 read-only copies; it does not
    re-check that ``R`` is a rotation (the loaders do, with the file name in the message).
    """

    image_path: str
    obj_id: str
    R: np.ndarray
    t: np.ndarray
    box_xyxy: np.ndarray
    K: np.ndarray
    image_size: tuple[int, int]
    scene_id: str
    frame_id: int
    visib_fract: float | None = None
    dataset: str = ""
    instance: int = 0
    box_source: str = ""
    mask_path: str = ""
    mask_value: int = 0

    def __post_init__(self):
        for name, shape in (("R", (3, 3)), ("t", (3,)), ("box_xyxy", (4,)), ("K", (3, 3))):
            value = np.array(getattr(self, name), dtype=np.float64)
            if value.shape != shape:
                raise ValueError(f"Sample.{name} must have shape {shape}; got shape {value.shape}")
            if not np.all(np.isfinite(value)):
                raise ValueError(f"Sample.{name} must be finite; got {value.tolist()}")
            object.__setattr__(self, name, _readonly(value))
        if not isinstance(self.obj_id, str):
            raise TypeError(f"Sample.obj_id must be a YCB id string such as '003_cracker_box'; got {self.obj_id!r}")
        size = tuple(int(v) for v in self.image_size)
        if len(size) != 2 or min(size) <= 0:
            raise ValueError(f"Sample.image_size must be (width, height) > 0; got {self.image_size!r}")
        object.__setattr__(self, "image_size", size)
        object.__setattr__(self, "image_path", str(self.image_path))
        object.__setattr__(self, "scene_id", str(self.scene_id))
        object.__setattr__(self, "frame_id", int(self.frame_id))
        if self.visib_fract is not None:
            object.__setattr__(self, "visib_fract", float(self.visib_fract))
        object.__setattr__(self, "mask_path", str(self.mask_path))
        if isinstance(self.mask_value, bool) or not isinstance(self.mask_value, (int, np.integer)) or not (
            0 <= self.mask_value <= 255
        ):
            raise ValueError(
                f"Sample.mask_value must be an integer in [0, 255] (0: any non-zero pixel); got {self.mask_value!r}"
            )
        object.__setattr__(self, "mask_value", int(self.mask_value))

    @property
    def q_gt(self) -> np.ndarray:
        """Ground-truth rotation as a unit quaternion, ``(4,)`` float64, ``wxyz``, ``w >= 0``, object to camera."""
        return rq.from_matrix(self.R)

    @property
    def scene_key(self) -> tuple[str, str]:
        """``(dataset, scene_id)``: the unit the ``scenes`` split keeps together."""
        return (self.dataset, self.scene_id)

    @property
    def box_size(self) -> tuple[float, float]:
        """``(width, height)`` of ``box_xyxy`` in pixels."""
        x1, y1, x2, y2 = self.box_xyxy
        return float(x2 - x1), float(y2 - y1)

    def __repr__(self) -> str:
        box = ", ".join(f"{v:.1f}" for v in self.box_xyxy)
        return (
            f"Sample({self.obj_id}, scene={self.scene_id}, frame={self.frame_id}, instance={self.instance}, "
            f"box_xyxy=({box}), visib_fract={self.visib_fract}, image={self.image_path})"
        )


def sort_key(sample: Sample) -> tuple:
    """A total order on samples by where they come from (dataset, scene, frame, instance, object)."""
    return (sample.dataset, sample.scene_id, sample.frame_id, sample.instance, sample.obj_id)


def filter_samples(
    samples: Iterable[Sample],
    objects: Iterable[str] | None = None,
    min_visib: float = 0.0,
    min_box_size: float = 0.0,
) -> list[Sample]:
    """Keep the samples that pass all filters (the loaders apply the same ones while reading).

    Args:
        samples: the samples to filter.
        objects: YCB id strings to keep; ``None`` keeps every object.
        min_visib: keep ``visib_fract >= min_visib``. A sample whose ``visib_fract`` is unknown
            (``None``, YCB-Video native) cannot be judged: with ``min_visib > 0`` it raises.
        min_box_size: keep boxes whose longer side (the side that sets the crop window) is at least
            this many pixels.

    Returns:
        A new list, input order preserved.

    Raises:
        ValueError: bad filter values, or ``min_visib > 0`` with samples of unknown visibility.
    """
    samples = list(samples)
    wanted = validate_object_ids(objects, known=set(YCBV_CLASSES) | {s.obj_id for s in samples})
    check_filter_values(min_visib, min_box_size)
    kept = []
    for s in samples:
        if wanted is not None and s.obj_id not in wanted:
            continue
        if min_visib > 0.0:
            if s.visib_fract is None:
                raise ValueError(
                    f"min_visib={min_visib} needs visib_fract, which is unknown (None) for {s!r}; "
                    "YCB-Video native files do not record visibility: use min_visib=0"
                )
            if s.visib_fract < min_visib:
                continue
        if max(s.box_size) < min_box_size:
            continue
        kept.append(s)
    return kept


def check_filter_values(min_visib: float, min_box_size: float) -> None:
    """Validate the ``min_visib`` (in ``[0, 1]``) and ``min_box_size`` (pixels, ``>= 0``) filters."""
    if not (isinstance(min_visib, (int, float)) and 0.0 <= min_visib <= 1.0):
        raise ValueError(f"min_visib must be a fraction in [0, 1]; got {min_visib!r}")
    if not (isinstance(min_box_size, (int, float)) and np.isfinite(min_box_size) and min_box_size >= 0.0):
        raise ValueError(f"min_box_size must be a length in pixels >= 0; got {min_box_size!r}")


def check_rotations(R: np.ndarray, where: list[str], method: str = "premerlani") -> np.ndarray:
    """Validate rotation matrices read from a file and re-orthonormalise them.

    Args:
        R: ``(n, 3, 3)`` float64 matrices, object to camera.
        where: ``n`` strings naming each matrix's file and field, used in error messages.
        method: ``"premerlani"`` (the paper's, default) or ``"svd"``
            (:func:`refiner_rt.quaternion.orthonormalize`).

    Returns:
        ``(n, 3, 3)`` float64 re-orthonormalised rotations.

    Raises:
        ValueError: a non-finite matrix, one whose ``|R^T R - I|`` exceeds :data:`ROTATION_TOLERANCE`
            or with ``det(R) < 0`` (a reflection), naming the file and field; an unknown method.
    """
    if method not in ROTATION_METHODS:
        raise ValueError(f"rotation_method must be one of {ROTATION_METHODS}; got {method!r}")
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    finite = np.isfinite(R).all(axis=(1, 2))
    if not finite.all():
        i = int(np.argmin(finite))
        raise ValueError(f"{where[i]} must be a finite 3x3 rotation; got {R[i].ravel().tolist()}")
    err = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = (err > ROTATION_TOLERANCE) | (det < 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f"{where[i]} is not a rotation matrix: expected |R^T R - I| <= {ROTATION_TOLERANCE} and det(R) = +1; "
            f"got max |R^T R - I| = {err[i]:.3g}, det = {det[i]:.4g}, R = {np.round(R[i], 6).tolist()}"
        )
    return rq.orthonormalize(R, method=method)


def check_intrinsics(K, where: str) -> np.ndarray:
    """Validate a pinhole intrinsic matrix read from a file.

    Args:
        K: anything reshapeable to 3x3 (BOP ``cam_K`` is 9 numbers, row-major).
        where: file and field for error messages.

    Returns:
        ``(3, 3)`` float64.

    Raises:
        ValueError: not 9 finite numbers, non-positive focal lengths, or a last row other than
            ``(0, 0, 1)``.
    """
    K = np.asarray(K, dtype=np.float64)
    if K.size != 9:
        raise ValueError(f"{where} must be a 3x3 camera matrix (9 numbers, row-major); got shape {K.shape}")
    K = K.reshape(3, 3)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], (0.0, 0.0, 1.0)):
        raise ValueError(
            f"{where} must be a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0; got {K.tolist()}"
        )
    return K


def check_box(box_xyxy, image_size: tuple[int, int], where: str, inside: bool = False) -> np.ndarray:
    """Validate a box ``(x1, y1, x2, y2)`` (pixels, continuous) against its image.

    Args:
        box_xyxy: 4 numbers.
        image_size: ``(width, height)``.
        where: file and field for error messages.
        inside: require the box to lie inside the image (within
            :data:`BOX_OUTSIDE_TOLERANCE_PX`), as a box computed from a visibility mask must;
            otherwise it need only overlap the image (an amodal box of a truncated object
            extends past the border).

    Returns:
        ``(4,)`` float64.

    Raises:
        ValueError: not 4 finite numbers, empty (``x2 <= x1`` or ``y2 <= y1``), outside the image.
    """
    box = np.asarray(box_xyxy, dtype=np.float64).ravel()
    w, h = image_size
    if box.size != 4 or not np.all(np.isfinite(box)):
        raise ValueError(f"{where} must be 4 finite numbers (x1, y1, x2, y2) in pixels; got {box.tolist()}")
    x1, y1, x2, y2 = box
    if x2 <= x1 or y2 <= y1:
        raise ValueError(f"{where} is empty: expected x2 > x1 and y2 > y1 (xyxy pixels); got {box.tolist()}")
    if x2 <= 0 or y2 <= 0 or x1 >= w or y1 >= h:
        raise ValueError(
            f"{where} lies outside the {w}x{h} image: expected a box overlapping [0, {w}) x [0, {h}); got {box.tolist()}"
        )
    tol = BOX_OUTSIDE_TOLERANCE_PX
    if inside and (x1 < -tol or y1 < -tol or x2 > w + tol or y2 > h + tol):
        raise ValueError(
            f"{where} extends outside the {w}x{h} image: a visible box must lie within [0, {w}] x [0, {h}]; "
            f"got {box.tolist()}"
        )
    return box


def read_image_size(path: str) -> tuple[int, int]:
    """``(width, height)`` of an image file (decoded with ``cv2.imread``).

    Raises:
        ValueError: the file cannot be decoded as an image.
    """
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{path}: cannot be read as an image (expected a PNG or JPEG file)")
    return int(image.shape[1]), int(image.shape[0])
