"""6D pose metrics as the field reports them on YCB-Video: ADD, ADD-S, ADD(-S) and their AUC.

Definitions (Hinterstoisser et al., ACCV 2012, for ADD / ADD-S; Xiang et al., *PoseCNN*, RSS 2018, Section V-A, for
the AUC on YCB-Video):

* ADD: the mean distance between the model points under the estimated and the true pose,
  ``mean_i |(R_e x_i + t_e) - (R_g x_i + t_g)|``;
* ADD-S: the mean distance from each point under the true pose to the *closest* point under the estimated pose,
  ``mean_i min_j |(R_g x_i + t_g) - (R_e x_j + t_e)|`` (for symmetric objects: no penalty for a symmetric turn);
* ADD(-S): ADD-S for the objects YCB-Video counts as symmetric (:data:`YCBV_SYMMETRIC`), ADD for the others;
* AUC: the area under the accuracy-threshold curve (the share of instances whose distance is below the threshold)
  for thresholds from 0 to :data:`AUC_MAX_M` (10 cm), normalised to 1. The integral has a closed form: the mean of
  ``max(0, 1 - d / AUC_MAX_M)``. (PoseCNN's ``VOCap`` sums the same curve by steps taken at their right ends,
  which can exceed this by at most ``1 / n``.)

Distances in metres; rotations ``(..., 3, 3)`` object to camera (``x_cam = R @ x_obj + t``); model points
``(P, 3)`` metres in the same object frame as both poses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["AUC_MAX_M", "YCBV_SYMMETRIC", "add", "add_s", "add_or_add_s", "auc", "mesh_points", "rotation_error_deg"]

AUC_MAX_M = 0.10

# YCB-Video's symmetric objects for ADD(-S) (PoseCNN's evaluation): none of the nine shipped objects is among them;
# the package's own symmetry of the master chef can (models.data.objects.SCAN_FRAME_SYMMETRIES) scores its rotation
# error, not ADD(-S), so that numbers stay comparable with the published ones.
YCBV_SYMMETRIC = frozenset({"024_bowl", "036_wood_block", "051_large_clamp", "052_extra_large_clamp",
                            "061_foam_brick"})


def _posed(R, t, points) -> np.ndarray:
    R, t, p = (np.asarray(a, dtype=np.float64) for a in (R, t, points))
    if R.shape[-2:] != (3, 3) or t.shape[-1:] != (3,) or R.shape[:-2] != t.shape[:-1]:
        raise ValueError(f"expected R (..., 3, 3) and t (..., 3) with the same leading shape; got R {R.shape}, "
                         f"t {t.shape}")
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"points must be (P, 3) metres with P >= 1; got shape {p.shape}")
    return np.einsum("...ij,pj->...pi", R, p) + t[..., None, :]


def add(R_est, t_est, R_gt, t_gt, points) -> np.ndarray:
    """ADD (metres), ``(...)``: mean distance between corresponding model points under the two poses."""
    return np.linalg.norm(_posed(R_est, t_est, points) - _posed(R_gt, t_gt, points), axis=-1).mean(axis=-1)


def add_s(R_est, t_est, R_gt, t_gt, points) -> np.ndarray:
    """ADD-S (metres), ``(...)``: mean distance from each true-posed point to the closest estimated-posed point
    (a k-d tree per pose, :class:`scipy.spatial.cKDTree`)."""
    from scipy.spatial import cKDTree

    est, gt = _posed(R_est, t_est, points), _posed(R_gt, t_gt, points)
    lead = est.shape[:-2]
    est, gt = est.reshape(-1, *est.shape[-2:]), gt.reshape(-1, *gt.shape[-2:])
    out = np.array([cKDTree(e).query(g, k=1)[0].mean() for e, g in zip(est, gt)])
    return out.reshape(lead)


def add_or_add_s(object_id: str, R_est, t_est, R_gt, t_gt, points) -> np.ndarray:
    """ADD(-S): :func:`add_s` for the objects in :data:`YCBV_SYMMETRIC`, :func:`add` for the others."""
    fn = add_s if object_id in YCBV_SYMMETRIC else add
    return fn(R_est, t_est, R_gt, t_gt, points)


def auc(distances_m, max_m: float = AUC_MAX_M) -> float:
    """Area under the accuracy-threshold curve for thresholds 0 to ``max_m``, normalised to ``[0, 1]`` (module
    docstring): ``mean(max(0, 1 - d / max_m))``. Non-finite distances (failures) count as misses.

    Raises:
        ValueError: no distances, negative ones, or ``max_m <= 0``.
    """
    d = np.asarray(distances_m, dtype=np.float64).ravel()
    if d.size == 0:
        raise ValueError("auc needs at least one distance")
    if not max_m > 0:
        raise ValueError(f"max_m must be > 0 metres; got {max_m!r}")
    if np.any(d[np.isfinite(d)] < 0):
        raise ValueError("distances must be >= 0")
    d = np.where(np.isfinite(d), d, np.inf)
    return float(np.clip(1.0 - d / max_m, 0.0, 1.0).mean())


def rotation_error_deg(R_est, R_gt) -> np.ndarray:
    """Geodesic angle (degrees) between rotations, ``(...)``."""
    R_est, R_gt = np.asarray(R_est, dtype=np.float64), np.asarray(R_gt, dtype=np.float64)
    cos = (np.einsum("...ij,...ij->...", R_est, R_gt) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def mesh_points(obj_path: str | Path, n: int = 2000, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` metres: model points for the metrics, ``n`` of the mesh's vertices drawn without replacement
    (fixed seed; all of them when it has fewer). YCB-Video's own point files hold 2,620 points per object."""
    from models.data.meshes import load_obj

    vertices = np.asarray(load_obj(Path(obj_path))[0], dtype=np.float64)
    if len(vertices) <= n:
        return vertices
    return vertices[np.sort(np.random.default_rng(seed).choice(len(vertices), n, replace=False))]
