"""The paper's metric and its tables: per-object geodesic error of ``q_in * q_out`` against ground truth.

Paper (Jain & Dellaert, Table 1): per object the mean and standard deviation of the geodesic angle
in degrees, and their average over objects. We add the median, the input (coarse) error and the
share of samples under 5 and 10 degrees. numpy only, so ONNX evaluation needs no torch.
"""

from __future__ import annotations

import numpy as np

from refiner_rt import quaternion as rq

__all__ = ["summarize_errors", "format_table", "format_markdown", "swing_twist_deg"]


def _stats(err: np.ndarray, err_in: np.ndarray) -> dict:
    return {
        "mean_deg": float(err.mean()),
        "std_deg": float(err.std()),
        "median_deg": float(np.median(err)),
        "input_mean_deg": float(err_in.mean()),
        "input_median_deg": float(np.median(err_in)),
        "under_5_deg": float((err < 5).mean()),
        "under_10_deg": float((err < 10).mean()),
        "n": int(len(err)),
    }


def summarize_errors(obj_ids, err_out_deg, err_in_deg) -> dict:
    """Per-object and averaged statistics of refined and input errors.

    Args:
        obj_ids: ``(N,)`` YCB ids of the samples.
        err_out_deg: ``(N,)`` geodesic error after refinement, degrees.
        err_in_deg: ``(N,)`` geodesic error of the coarse input, degrees.

    Returns:
        ``{"objects": {id: {mean_deg, std_deg, median_deg, input_mean_deg, input_median_deg,
        under_5_deg, under_10_deg, n}}, "average": {...}, "pooled": {...}}``. ``average`` is the
        mean over objects of each per-object statistic (the paper's "average" row); ``pooled``
        treats all samples as one set.
    """
    obj_ids = np.asarray(obj_ids).astype(str)
    err_out = np.asarray(err_out_deg, dtype=np.float64)
    err_in = np.asarray(err_in_deg, dtype=np.float64)
    if not (len(obj_ids) == len(err_out) == len(err_in)):
        raise ValueError(f"obj_ids, err_out_deg and err_in_deg must have equal lengths; got {len(obj_ids)}, {len(err_out)}, {len(err_in)}")
    if len(obj_ids) == 0:
        raise ValueError("no samples to summarise")
    objects = {o: _stats(err_out[obj_ids == o], err_in[obj_ids == o]) for o in sorted(set(obj_ids.tolist()))}
    keys = [k for k in next(iter(objects.values())) if k != "n"]
    average = {k: float(np.mean([v[k] for v in objects.values()])) for k in keys}
    average["n"] = int(len(err_out))
    return {"objects": objects, "average": average, "pooled": _stats(err_out, err_in)}


def format_table(summary: dict, title: str = "") -> str:
    """The paper's Table 1 layout (object, mean, std) plus median, input error and shares, as plain text."""
    head = f"{'object':<22}{'mean':>8}{'std':>8}{'median':>8}{'input':>8}{'<5deg':>8}{'<10deg':>8}{'n':>7}"
    lines = ([title] if title else []) + [head, "-" * len(head)]
    rows = list(summary["objects"].items()) + [("average", summary["average"])]
    for name, s in rows:
        if name == "average":
            lines.append("-" * len(head))
        lines.append(
            f"{name:<22}{s['mean_deg']:>8.2f}{s['std_deg']:>8.2f}{s['median_deg']:>8.2f}{s['input_mean_deg']:>8.2f}"
            f"{100 * s['under_5_deg']:>7.1f}%{100 * s['under_10_deg']:>7.1f}%{s['n']:>7}"
        )
    return "\n".join(lines)


def format_markdown(summary: dict) -> str:
    """The same table in Markdown (degrees)."""
    lines = [
        "| object | mean | std | median | input mean | < 5 deg | < 10 deg | n |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    rows = list(summary["objects"].items()) + [("**average**", summary["average"])]
    for name, s in rows:
        lines.append(
            f"| {name} | {s['mean_deg']:.2f} | {s['std_deg']:.2f} | {s['median_deg']:.2f} | {s['input_mean_deg']:.2f} | "
            f"{100 * s['under_5_deg']:.1f}% | {100 * s['under_10_deg']:.1f}% | {s['n']} |"
        )
    return "\n".join(lines)


def swing_twist_deg(q, axis=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Split rotations into a twist about ``axis`` and a swing about an axis perpendicular to it.

    ``q = swing * twist``: the twist (about ``axis``) is applied first, then the swing. For the error rotation of a
    refiner in the viewing-ray frame (``q_refined * q_true^-1``, ``axis`` the ray), the twist is the part in the
    image plane and the swing the part out of it, which the crop's appearance shows far less directly.

    Args:
        q: ``(..., 4)`` unit quaternions, ``wxyz``.
        axis: the twist axis (3 numbers, normalised here).

    Returns:
        ``(swing_deg, twist_deg)``, each ``(...)`` in ``[0, 180]``.
    """
    q = np.asarray(q, dtype=np.float64)
    a = np.asarray(axis, dtype=np.float64)
    norm = np.linalg.norm(a)
    if a.shape != (3,) or not np.isfinite(norm) or norm == 0:
        raise ValueError(f"axis must be 3 finite numbers, not all zero; got {axis!r}")
    a = a / norm
    w, v = q[..., 0], q[..., 1:]
    along = v @ a  # the vector part projected on the axis: the twist is (w, along * a), normalised
    t = np.hypot(w, along)[..., None]
    twist_q = np.where(t > 0, np.concatenate([w[..., None], along[..., None] * a], axis=-1) / np.where(t > 0, t, 1.0),
                       np.array([1.0, 0.0, 0.0, 0.0]))
    swing_q = rq.multiply(q, twist_q * np.array([1.0, -1.0, -1.0, -1.0]))  # q * twist^-1
    angle = lambda u: np.degrees(2.0 * np.arctan2(np.linalg.norm(u[..., 1:], axis=-1), np.abs(u[..., 0])))  # noqa: E731
    return angle(swing_q), angle(twist_q)
