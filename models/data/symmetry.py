"""Symmetric objects: the rotations that leave an object looking the same, the closest symmetric label, the error.

A symmetry is given in BOP's ``models_info.json`` form (BOP toolkit, ``bop_toolkit_lib/misc.py``,
``get_symmetry_transformations``): ``symmetries_discrete``, a list of 4x4 row-major matrices (16 numbers, the
translation in mm; only the rotation matters here), and ``symmetries_continuous``, a list of ``{"axis": [x, y, z],
"offset": [x, y, z]}`` (a rotation about ``axis`` by any angle: sampled every ``360 / CONTINUOUS_STEPS`` degrees for the
training label, exact in the error).
The set is every product of a discrete one (or the identity) with a continuous one (or the identity), as the toolkit
combines them.

For an object rotation ``R`` (object to camera) and a symmetry ``S`` (in the object's frame), ``R S`` looks the same
as ``R``. So the refiner's target ``q_in^-1 q_gt`` is as good as ``q_in^-1 q_gt s`` for any ``s``: the training label
becomes the closest of ``q_label * s``, and the error ``min_s geodesic(q_refined, q_gt * s)`` (BOP's MSSD idea on
rotations). Quaternions ``wxyz``, angles in degrees.
"""

from __future__ import annotations

import numpy as np

from refiner_rt import quaternion as rq

__all__ = ["CONTINUOUS_STEPS", "symmetry_quaternions", "symmetry_table", "closest_label", "symmetric_error",
           "validate_symmetry", "describe_symmetry"]

CONTINUOUS_STEPS = 36  # samples of a continuous symmetry: every 10 degrees (the closest is at most 5 degrees off)


def validate_symmetry(sym: dict, where: str = "symmetry") -> dict:
    """Check a BOP-style symmetry dict; returns it with only the two known keys.

    Raises:
        ValueError: an unknown key, a discrete entry that is not 16 numbers with a rotation part, or a continuous
            entry without a non-zero 3-vector ``axis``.
    """
    if not isinstance(sym, dict):
        raise ValueError(f"{where} must be an object with symmetries_discrete and/or symmetries_continuous; got "
                         f"{type(sym).__name__}")
    unknown = sorted(set(sym) - {"symmetries_discrete", "symmetries_continuous"})
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; expected symmetries_discrete and/or "
                         "symmetries_continuous (BOP models_info.json)")
    for i, m in enumerate(sym.get("symmetries_discrete", [])):
        a = np.asarray(m, float)
        if a.size != 16:
            raise ValueError(f"{where}: symmetries_discrete[{i}] must be 16 numbers (a 4x4 matrix, row-major); got "
                             f"{a.size}")
        R = a.reshape(4, 4)[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
            raise ValueError(f"{where}: symmetries_discrete[{i}]'s 3x3 part is not a rotation")
    for i, c in enumerate(sym.get("symmetries_continuous", [])):
        axis = np.asarray(c.get("axis", []) if isinstance(c, dict) else [], float)
        if axis.shape != (3,) or not np.linalg.norm(axis) > 0:
            raise ValueError(f"{where}: symmetries_continuous[{i}] must be {{\"axis\": [x, y, z], \"offset\": "
                             f"[x, y, z]}} with a non-zero axis; got {c!r}")
    return {k: sym[k] for k in ("symmetries_discrete", "symmetries_continuous") if sym.get(k)}


def symmetry_quaternions(sym: dict | None, steps: int = CONTINUOUS_STEPS) -> np.ndarray:
    """The object's symmetry rotations as ``(K, 4)`` wxyz quaternions (``w >= 0``), the identity first.

    Args:
        sym: BOP-style symmetry dict, or None / empty for an object without symmetry (``K = 1``).
        steps: samples of each continuous symmetry over the full turn.
    """
    sym = validate_symmetry(sym) if sym else {}
    discrete = [np.array([1.0, 0.0, 0.0, 0.0])]
    for m in sym.get("symmetries_discrete", []):
        R = rq.orthonormalize(np.asarray(m, float).reshape(4, 4)[:3, :3], method="svd")
        discrete.append(rq.from_matrix(R))
    continuous = [np.array([1.0, 0.0, 0.0, 0.0])]
    for c in sym.get("symmetries_continuous", []):
        axis = np.asarray(c["axis"], float)
        for k in range(1, steps):
            continuous.append(rq.from_axis_angle(axis / np.linalg.norm(axis), 360.0 * k / steps))
    out = [rq.multiply(d, c) for d in discrete for c in continuous]
    q = np.array(out)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def symmetry_table(obj_ids: np.ndarray, symmetries: dict | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Per-sample symmetry sets: ``(table (n_objects, K, 4), index (N,))`` so sample ``i``'s set is
    ``table[index[i]]`` (shorter sets padded with the identity); ``(None, None)`` when no object of ``obj_ids`` is
    symmetric (the plain loss then runs unchanged)."""
    names = list(dict.fromkeys(np.asarray(obj_ids).astype(str).tolist()))
    if not symmetries or not any(symmetries.get(o) for o in names):
        return None, None
    sets = [symmetry_quaternions(symmetries.get(o)) for o in names]
    k = max(len(s) for s in sets)
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    table = np.stack([np.concatenate([s, np.repeat(identity[None], k - len(s), 0)]) for s in sets])
    position = {o: i for i, o in enumerate(names)}
    return table, np.array([position[o] for o in np.asarray(obj_ids).astype(str).tolist()], dtype=np.int64)


def closest_label(q_out, labels):
    """The label of ``labels`` (``(B, K, 4)`` torch, wxyz) closest in angle to ``q_out`` (``(B, 4)``): ``(B, 4)``."""
    import torch

    dots = torch.einsum("bkq,bq->bk", labels, q_out).abs()
    return labels[torch.arange(len(labels), device=labels.device), dots.argmax(dim=1)]


def symmetric_error(q_est: np.ndarray, q_gt: np.ndarray, obj_ids: np.ndarray, symmetries: dict | None) -> np.ndarray:
    """Geodesic error (degrees) of ``q_est`` to the closest symmetric pose ``q_gt * s`` of each sample's object.

    Objects without a symmetry get the plain ``geodesic_angle(q_est, q_gt)``. A single continuous symmetry is exact:
    for ``r = (q_gt d)^-1 q_est = (w, v)`` (``d`` each discrete symmetry or the identity), the closest turn about the
    unit axis ``a`` leaves ``2 atan2(|v - (v . a) a|, sqrt(w^2 + (v . a)^2))``; several continuous axes are sampled (the loss's table).
    """
    q_est, q_gt = np.asarray(q_est, float), np.asarray(q_gt, float)
    ids = np.asarray(obj_ids).astype(str)
    out = rq.geodesic_angle(q_est, q_gt)
    for obj in set(ids.tolist()):
        sym = validate_symmetry(symmetries[obj]) if symmetries and symmetries.get(obj) else {}
        if not sym:
            continue
        m = ids == obj
        continuous = sym.get("symmetries_continuous", [])
        if len(continuous) == 1:
            axis = np.asarray(continuous[0]["axis"], float)
            axis /= np.linalg.norm(axis)
            discrete = symmetry_quaternions({k: v for k, v in sym.items() if k == "symmetries_discrete"})
            r = rq.multiply(rq.inverse(rq.multiply(q_gt[m][:, None, :], discrete[None])), q_est[m][:, None, :])
            along = r[..., 1:] @ axis
            cos_half = np.sqrt(r[..., 0] ** 2 + along**2)
            sin_half = np.linalg.norm(r[..., 1:] - along[..., None] * axis, axis=-1)  # atan2: exact near zero
            out[m] = np.degrees(2.0 * np.arctan2(sin_half, cos_half)).min(axis=1)
        else:
            candidates = rq.multiply(q_gt[m][:, None, :], symmetry_quaternions(sym)[None])  # (n, K, 4)
            out[m] = rq.geodesic_angle(q_est[m][:, None, :], candidates).min(axis=1)
    return out


def describe_symmetry(sym: dict | None) -> str:
    """One line for the model card: what the refined rotation means for this object."""
    if not sym:
        return "none"
    parts = []
    if sym.get("symmetries_discrete"):
        parts.append(f"{len(sym['symmetries_discrete'])} discrete")
    for c in sym.get("symmetries_continuous", []):
        parts.append(f"continuous about axis {list(c['axis'])}")
    return (", ".join(parts) + ": the refined rotation is one of the equivalent poses, measured to the closest "
            "(symmetry-aware error)")
