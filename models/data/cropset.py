"""CropSet: network-ready crops with their ground-truth rotations, the unit that training and evaluation consume.

Crops are made once by the shared crop rule (``refiner_rt.preprocess``), usually through the crop
cache (``models.data.cache``), and held as a ``(N, S, S, 3)`` uint8 array or memmap.

Conventions: crops are BGR ``uint8`` NHWC; rotations are ``wxyz`` quaternions mapping object to
camera coordinates; ``q_ray`` rotates the camera frame onto the viewing-ray frame of each crop
(``refiner_rt.geometry.ray_quaternions``), so the rotation a crop shows is ``q_ray^-1 * q_gt``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from refiner_rt import quaternion as rq

__all__ = ["CropSet"]


@dataclass
class CropSet:
    """Crops and labels of ``N`` object instances.

    Attributes:
        crops: ``(N, S, S, 3)`` uint8, BGR, NHWC (array or read-only memmap).
        q_gt: ``(N, 4)`` float64 ``wxyz`` ground-truth object-to-camera rotations.
        obj_ids: ``(N,)`` YCB id strings (e.g. ``"003_cracker_box"``).
        q_ray: ``(N, 4)`` float64 ``wxyz`` camera-to-ray-frame rotations, or None when the
            intrinsics are unknown (then only the ``"camera"`` frame is possible).
        scene_ids: ``(N,)`` scene/sequence ids, or None.
        masks: ``(N, S, S)`` uint8, 1 on the instance's visible pixels, or None; with ``has_mask``
            ``(N,)`` bool saying which crops have one (a crop without a mask has zeros there).
    """

    crops: np.ndarray
    q_gt: np.ndarray
    obj_ids: np.ndarray
    q_ray: np.ndarray | None = None
    scene_ids: np.ndarray | None = None
    masks: np.ndarray | None = None
    has_mask: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.crops)
        if self.crops.ndim != 4 or self.crops.shape[3] != 3 or self.crops.dtype != np.uint8:
            raise ValueError(f"crops must be (N, S, S, 3) uint8 BGR; got shape {self.crops.shape}, dtype {self.crops.dtype}")
        self.q_gt = np.asarray(self.q_gt, dtype=np.float64)
        self.obj_ids = np.asarray(self.obj_ids).astype(str)
        if self.q_gt.shape != (n, 4):
            raise ValueError(f"q_gt must be ({n}, 4) wxyz; got shape {self.q_gt.shape}")
        if self.obj_ids.shape != (n,):
            raise ValueError(f"obj_ids must have shape ({n},); got {self.obj_ids.shape}")
        if self.q_ray is not None:
            self.q_ray = np.asarray(self.q_ray, dtype=np.float64)
            if self.q_ray.shape != (n, 4):
                raise ValueError(f"q_ray must be ({n}, 4) wxyz; got shape {self.q_ray.shape}")
        if self.scene_ids is not None:
            self.scene_ids = np.asarray(self.scene_ids)
        if self.masks is not None:
            s = self.crops.shape[1:3]
            if self.masks.shape != (n, *s) or self.masks.dtype != np.uint8:
                raise ValueError(f"masks must be ({n}, {s[0]}, {s[1]}) uint8 0/1; got shape {self.masks.shape}, "
                                 f"dtype {self.masks.dtype}")
            self.has_mask = np.ones(n, bool) if self.has_mask is None else np.asarray(self.has_mask, dtype=bool)
            if self.has_mask.shape != (n,):
                raise ValueError(f"has_mask must have shape ({n},); got {self.has_mask.shape}")
        elif self.has_mask is not None:
            raise ValueError("has_mask was given without masks")

    def __len__(self) -> int:
        return len(self.crops)

    @property
    def input_size(self) -> int:
        """Crop side ``S``."""
        return int(self.crops.shape[1])

    @property
    def objects(self) -> list[str]:
        """Sorted distinct YCB ids present."""
        return sorted(set(self.obj_ids.tolist()))

    def subset(self, index) -> "CropSet":
        """A CropSet of the given indices (boolean mask or integer array, taken in ascending order); crops are copied into memory."""
        index = np.asarray(index)
        # Sorted, so a memmap is read front to back.
        idx = np.flatnonzero(index) if index.dtype == bool else np.sort(index)
        return CropSet(
            crops=np.ascontiguousarray(self.crops[idx]),
            q_gt=self.q_gt[idx],
            obj_ids=self.obj_ids[idx],
            q_ray=None if self.q_ray is None else self.q_ray[idx],
            scene_ids=None if self.scene_ids is None else self.scene_ids[idx],
            masks=None if self.masks is None else np.ascontiguousarray(self.masks[idx]),
            has_mask=None if self.masks is None else self.has_mask[idx],
        )

    def for_object(self, obj_id: str) -> "CropSet":
        """The instances of one object."""
        mask = self.obj_ids == obj_id
        if not mask.any():
            raise ValueError(f"no crops of object {obj_id!r}; present: {self.objects}")
        return self.subset(mask)

    def q_gt_in(self, frame: str) -> np.ndarray:
        """Ground truth in the network's rotation frame: ``"camera"`` or ``"ray"`` (``q_ray^-1 * q_gt``)."""
        if frame == "camera":
            return self.q_gt
        if frame == "ray":
            if self.q_ray is None:
                raise ValueError("the 'ray' rotation frame needs the intrinsics K of every crop; this CropSet has none")
            return rq.normalize(rq.multiply(rq.inverse(self.q_ray), self.q_gt))
        raise ValueError(f"rotation frame must be 'camera' or 'ray'; got {frame!r}")
