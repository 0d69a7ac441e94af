"""Unit-quaternion maths for rotations, in numpy (float64), batched over leading axes.

Convention (the whole project uses it; see docs/design.md §2.1):
    * quaternions are ``wxyz`` (scalar first), shape ``(..., 4)``, Hamilton product;
    * a rotation maps object coordinates to camera coordinates (``x_cam = R @ x_obj + t``);
    * angles are in degrees unless a name ends in ``_rad``;
    * functions that return a rotation return the canonical sign ``w >= 0``.

``to_xyzw`` / ``from_xyzw`` are the only functions that speak the ``xyzw`` order (ROS
``geometry_msgs/Quaternion``, ``scipy.spatial.transform.Rotation.as_quat``).

Sources: Hamilton product and matrix conversion as in SciPy's ``Rotation``; the matrix-to-quaternion
branch choice is Shepperd's method; the Premerlani-Bizard re-orthonormalisation is from
"Direction Cosine Matrix IMU: Theory" (Premerlani & Bizard, 2009), as used by the paper
(Jain & Dellaert, "Fast 3D Pose Refinement with RGB Images").
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "as_quaternion",
    "canonical",
    "normalize",
    "normalize_rows",
    "multiply",
    "multiply_rows",
    "inverse",
    "inverse_rows",
    "MIN_NORM",
    "geodesic_angle",
    "geodesic_angle_rad",
    "mean",
    "from_axis_angle",
    "to_axis_angle",
    "to_matrix",
    "from_matrix",
    "orthonormalize",
    "sample_rotation_noise",
    "to_xyzw",
    "from_xyzw",
    "identity",
]


# A quaternion of a smaller norm is a zero quaternion: refused, never normalised.
MIN_NORM = 1e-12


def as_quaternion(q, name: str = "q") -> np.ndarray:
    """Validate a batch of quaternions and return it as float64.

    Args:
        q: array-like of shape ``(..., 4)``, ``wxyz`` order. Must be finite and non-zero.
        name: argument name used in error messages.

    Returns:
        ``np.ndarray`` of shape ``(..., 4)``, float64 (not normalised).

    Raises:
        ValueError: a ragged sequence, wrong shape, non-finite values or a zero-norm quaternion.
    """
    try:
        arr = np.asarray(q)
    except (ValueError, TypeError) as exc:  # ragged nested lists: numpy's "setting an array element with a sequence"
        raise ValueError(
            f"{name} must be a numeric array of shape (..., 4) in wxyz order; got a ragged sequence ({exc})"
        ) from None
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{name} must be a numeric array of shape (..., 4) in wxyz order; got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim == 0 or arr.shape[-1] != 4:
        raise ValueError(f"{name} must have shape (..., 4) in wxyz order; got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr).all(axis=-1))
        raise ValueError(f"{name} must be finite; got non-finite values at index {tuple(bad[0])}")
    with np.errstate(over="ignore"):  # components above ~1e154: the norm is inf (not zero), normalize() handles it
        norms = np.linalg.norm(arr, axis=-1)
    if np.any(norms < MIN_NORM):
        bad = np.argwhere(norms < MIN_NORM)
        raise ValueError(f"{name} must be non-zero quaternions (wxyz); got a zero quaternion at index {tuple(bad[0])}")
    return arr


def identity(shape: tuple[int, ...] = ()) -> np.ndarray:
    """Identity rotation(s), ``wxyz`` = ``(1, 0, 0, 0)``, shape ``(*shape, 4)``, float64."""
    out = np.zeros((*shape, 4), dtype=np.float64)
    out[..., 0] = 1.0
    return out


def canonical(q) -> np.ndarray:
    """Flip the sign of each quaternion so that ``w >= 0`` (``q`` and ``-q`` are the same rotation).

    Args:
        q: ``(..., 4)`` quaternions, ``wxyz``.

    Returns:
        ``(..., 4)`` float64, ``wxyz``, with ``w >= 0``. For ``w == 0`` the first non-zero of
        ``x, y, z`` is made positive, so the result is unique.
    """
    q = np.array(q, dtype=np.float64)
    # Sign key: w, then x, y, z for the w == 0 (180 degree) case.
    key = q[..., 0]
    for i in (1, 2, 3):
        key = np.where(key == 0.0, q[..., i], key)
    return np.where((key < 0.0)[..., None], -q, q)


def normalize(q) -> np.ndarray:
    """Scale quaternions to unit norm and canonical sign (``w >= 0``).

    Args:
        q: ``(..., 4)`` finite, non-zero quaternions, ``wxyz``.

    Returns:
        ``(..., 4)`` float64 unit quaternions, ``wxyz``, ``w >= 0``.

    Finite quaternions of any size are handled: where the sum of squares overflows (components above about
    1e154) the quaternion is first divided by its largest absolute component, which does not change the rotation.

    Raises:
        ValueError: non-finite or zero quaternions (never silently replaced).
    """
    q = as_quaternion(q)
    with np.errstate(over="ignore"):
        norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.isfinite(norm).all():  # finite components whose squares overflow: scale to max |component| = 1 first
        big = ~np.isfinite(norm)
        q = np.where(big, q / np.where(big, np.abs(q).max(axis=-1, keepdims=True), 1.0), q)
        norm = np.where(big, np.linalg.norm(q, axis=-1, keepdims=True), norm)
    return canonical(q / norm)


def normalize_rows(rows: list) -> list | None:
    """:func:`normalize`'s fast twin on Python floats: unit norm, canonical sign ``w >= 0``. For a few rows, where
    numpy's fixed cost per call exceeds the maths (the runtime's small batches and the tracker's per-track steps).

    Same IEEE operations in the same order as the numpy version (sequential sum of squares, ``sqrt``,
    division, sign key ``w``, then ``x``, ``y``, ``z`` when ``w == 0``), so the results are identical.

    Args:
        rows: ``N`` lists ``[w, x, y, z]`` of floats.

    Returns:
        ``N`` lists ``[w, x, y, z]``, or None when a row is non-finite, has a norm below 1e-12 or one whose
        square overflows (components above ~1e154) (the caller then takes the numpy path, which raises the
        detailed error or, for huge finite rows, scales them first).
    """
    sqrt = math.sqrt
    out = []
    for w, x, y, z in rows:
        norm = sqrt(w * w + x * x + y * y + z * z)
        if not MIN_NORM <= norm < math.inf:  # also False for nan (any non-finite component gives nan or inf)
            return None
        w, x, y, z = w / norm, x / norm, y / norm, z / norm
        key = w if w != 0.0 else x if x != 0.0 else y if y != 0.0 else z
        out.append([-w, -x, -y, -z] if key < 0.0 else [w, x, y, z])
    return out


def multiply(a, b) -> np.ndarray:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``: ``R(a*b) = R(a) @ R(b)``).

    Args:
        a: ``(..., 4)`` quaternions, ``wxyz``.
        b: ``(..., 4)`` quaternions, ``wxyz``; broadcast against ``a``.

    Returns:
        ``(..., 4)`` float64, ``wxyz``. The sign is *not* canonicalised, so the product is
        bilinear; use :func:`canonical` or :func:`normalize` for a canonical rotation.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def multiply_rows(a: list, b: list) -> list:
    """:func:`multiply`'s fast twin (Hamilton product ``a * b``, ``wxyz``) on Python floats, row by row: the same
    operations in the same order, so the results are identical (``N`` lists ``[w, x, y, z]`` each; not canonical)."""
    out = []
    for (aw, ax, ay, az), (bw, bx, by, bz) in zip(a, b):
        out.append([
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ])
    return out


def inverse(q) -> np.ndarray:
    """Inverse rotation of unit quaternions (the conjugate ``(w, -x, -y, -z)``), canonical sign.

    Args:
        q: ``(..., 4)`` unit quaternions, ``wxyz``.

    Returns:
        ``(..., 4)`` float64, ``wxyz``, ``w >= 0``.
    """
    q = np.asarray(q, dtype=np.float64)
    return canonical(q * np.array([1.0, -1.0, -1.0, -1.0]))


def inverse_rows(rows: list) -> list:
    """:func:`inverse`'s fast twin on Python floats: ``(w, -x, -y, -z)`` with canonical sign (same sign key as
    :func:`canonical`; negation is exact, so the results are identical)."""
    out = []
    for w, x, y, z in rows:
        x, y, z = -x, -y, -z
        key = w if w != 0.0 else x if x != 0.0 else y if y != 0.0 else z
        out.append([-w, -x, -y, -z] if key < 0.0 else [w, x, y, z])
    return out


def geodesic_angle_rad(a, b) -> np.ndarray:
    """Rotation angle of ``a^-1 * b`` in radians, in ``[0, pi]``.

    Numerically exact near 0 and pi: computed as ``2 * atan2(|v|, |w|)`` of the relative
    quaternion, never as ``acos`` of a value that may round past 1.

    Args:
        a: ``(..., 4)`` unit quaternions, ``wxyz``.
        b: ``(..., 4)`` unit quaternions, ``wxyz``; broadcast against ``a``.

    Returns:
        ``(...)`` float64 angles in radians.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    rel = multiply(a * np.array([1.0, -1.0, -1.0, -1.0]), b)
    return 2.0 * np.arctan2(np.linalg.norm(rel[..., 1:], axis=-1), np.abs(rel[..., 0]))


def geodesic_angle(a, b) -> np.ndarray:
    """Geodesic distance between rotations ``a`` and ``b`` in degrees, in ``[0, 180]``.

    ``geodesic_angle(q, -q) == 0``: the sign ambiguity of quaternions is ignored.

    Args:
        a: ``(..., 4)`` unit quaternions, ``wxyz``.
        b: ``(..., 4)`` unit quaternions, ``wxyz``; broadcast against ``a``.

    Returns:
        ``(...)`` float64 angles in degrees.
    """
    return np.degrees(geodesic_angle_rad(a, b))


def mean(q, axis: int = 0) -> np.ndarray:
    """The rotation that averages unit quaternions along ``axis`` (the chordal L2 mean, as SciPy's
    ``Rotation.mean``): the eigenvector of the largest eigenvalue of ``sum q q^T``, so ``q`` and ``-q`` count the
    same.

    Args:
        q: ``(..., 4)`` unit quaternions, ``wxyz``, with at least one along ``axis``.
        axis: the axis to average over (not the last one, which holds the four components).

    Returns:
        The quaternions with ``axis`` removed, float64, ``wxyz``, ``w >= 0``.
    """
    q = as_quaternion(q)
    if q.ndim < 2:
        raise ValueError(f"q must have an axis to average over besides the last (4 components); got shape {q.shape}")
    axis = axis % q.ndim
    if axis == q.ndim - 1:
        raise ValueError("axis must not be the last axis: it holds the quaternion components wxyz")
    if q.shape[axis] == 0:
        raise ValueError(f"nothing to average: q has no quaternions along axis {axis} (shape {q.shape})")
    q = np.moveaxis(q, axis, -2)
    outer = np.einsum("...ki,...kj->...ij", q, q)
    _, vectors = np.linalg.eigh(outer)  # eigenvalues ascending
    return canonical(vectors[..., :, -1])


def from_axis_angle(axis, angle_deg) -> np.ndarray:
    """Quaternion of a rotation by ``angle_deg`` degrees about ``axis`` (right-hand rule).

    Args:
        axis: ``(..., 3)`` rotation axes; normalised here, must be non-zero and finite.
        angle_deg: ``(...)`` angles in degrees, broadcast against ``axis[..., 0]``.

    Returns:
        ``(..., 4)`` float64 unit quaternions, ``wxyz``, ``w >= 0``.

    Raises:
        ValueError: wrong axis shape, zero or non-finite axis, non-finite angle.
    """
    axis = np.asarray(axis, dtype=np.float64)
    if axis.ndim == 0 or axis.shape[-1] != 3:
        raise ValueError(f"axis must have shape (..., 3); got shape {axis.shape}")
    angle = np.asarray(angle_deg, dtype=np.float64)
    if not (np.all(np.isfinite(axis)) and np.all(np.isfinite(angle))):
        raise ValueError("axis and angle_deg must be finite")
    n = np.linalg.norm(axis, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise ValueError("axis must be non-zero")
    half = np.radians(angle)[..., None] / 2.0
    axis, half = np.broadcast_arrays(axis / n, half)
    return canonical(np.concatenate([np.cos(half[..., :1]), np.sin(half) * axis], axis=-1))


def to_axis_angle(q) -> tuple[np.ndarray, np.ndarray]:
    """Axis and angle (degrees, in ``[0, 180]``) of unit quaternions.

    Args:
        q: ``(..., 4)`` unit quaternions, ``wxyz``.

    Returns:
        ``(axis, angle_deg)``: ``(..., 3)`` unit axes (``(1, 0, 0)`` for the identity) and
        ``(...)`` angles in degrees.
    """
    q = canonical(q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    angle = np.degrees(2.0 * np.arctan2(s, q[..., 0]))
    safe = np.where(s[..., None] > 0, v / np.where(s > 0, s, 1.0)[..., None], np.array([1.0, 0.0, 0.0]))
    return safe, angle


def to_matrix(q) -> np.ndarray:
    """Rotation matrices of unit quaternions.

    Args:
        q: ``(..., 4)`` quaternions, ``wxyz``; normalised here.

    Returns:
        ``(..., 3, 3)`` float64 rotation matrices ``R`` with ``x_cam = R @ x_obj``.
    """
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def from_matrix(R) -> np.ndarray:
    """Quaternions of rotation matrices (Shepperd's method: largest-diagonal branch, stable).

    The input must already be a rotation; re-orthonormalise noisy matrices first with
    :func:`orthonormalize`.

    Args:
        R: ``(..., 3, 3)`` rotation matrices, ``x_cam = R @ x_obj``.

    Returns:
        ``(..., 4)`` float64 unit quaternions, ``wxyz``, ``w >= 0``.

    Raises:
        ValueError: wrong shape or non-finite values.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3); got shape {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError("R must be finite")
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = m00 + m11 + m22
    # Four candidate (unnormalised) quaternions; pick the one with the largest pivot.
    cands = np.stack(
        [
            np.stack([1 + trace, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1),
            np.stack([R[..., 2, 1] - R[..., 1, 2], 1 + m00 - m11 - m22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], -1),
            np.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], 1 - m00 + m11 - m22, R[..., 1, 2] + R[..., 2, 1]], -1),
            np.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )
    pivots = np.stack([trace, m00, m11, m22], axis=-1)
    best = np.argmax(pivots, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    return canonical(q / np.linalg.norm(q, axis=-1, keepdims=True))


def orthonormalize(R, method: str = "premerlani") -> np.ndarray:
    """Project nearly-orthogonal matrices back onto rotations.

    Args:
        R: ``(..., 3, 3)`` nearly-orthonormal matrices (e.g. read from a file with few digits).
        method: ``"premerlani"`` (the paper's, Premerlani & Bizard 2009: split the dot-product
            error ``e = r0 . r1`` between the first two rows, ``r0' = r0 - e/2 r1``,
            ``r1' = r1 - e/2 r0``, ``r2' = r0' x r1'``, then scale each row by ``(3 - r.r)/2``)
            or ``"svd"`` (the exact nearest rotation in Frobenius norm, ``U diag(1, 1, det) V^T``).

    Returns:
        ``(..., 3, 3)`` float64 matrices. For ``"premerlani"`` the result is orthonormal to first
        order in the input error (one step, as in the paper); ``"svd"`` is exact.

    Raises:
        ValueError: wrong shape, non-finite values, unknown method, or (``"svd"``) a reflection
            or degenerate matrix that is not near any rotation.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3); got shape {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError("R must be finite")
    if method == "premerlani":
        r0, r1 = R[..., 0, :], R[..., 1, :]
        err = np.sum(r0 * r1, axis=-1, keepdims=True)
        x = r0 - 0.5 * err * r1
        y = r1 - 0.5 * err * r0
        z = np.cross(x, y)
        rows = [0.5 * (3.0 - np.sum(v * v, axis=-1, keepdims=True)) * v for v in (x, y, z)]
        return np.stack(rows, axis=-2)
    if method == "svd":
        u, s, vt = np.linalg.svd(R)
        det = np.linalg.det(u @ vt)
        if np.any(det < 0):
            raise ValueError("R is a reflection (det < 0), not near a rotation; cannot orthonormalize")
        return u @ vt
    raise ValueError(f"method must be 'premerlani' or 'svd'; got {method!r}")


def sample_rotation_noise(
    n: int,
    distribution: str = "uniform",
    a: float = 0.0,
    b: float = 30.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Random rotations about uniform random axes, with angles from a chosen distribution.

    The paper's sampling (section "Training Data"): axis
    ``n = (sqrt(1-s^2) cos t, sqrt(1-s^2) sin t, s)`` with ``t ~ U(0, 2pi)``, ``s ~ U(-1, 1)``
    (uniform on the sphere), angle from ``U(a, b)`` or ``N(a, b)`` degrees. For the normal
    distribution a negative draw is a rotation by ``|angle|`` about the opposite axis, which the
    same axis distribution already covers, so the angle is reported as drawn.

    Args:
        n: number of rotations (>= 0).
        distribution: ``"uniform"`` (``a`` = low, ``b`` = high, degrees) or ``"normal"``
            (``a`` = mean, ``b`` = standard deviation, degrees).
        a, b: distribution parameters in degrees.
        rng: ``numpy.random.Generator`` for reproducibility (a fresh unseeded one when None).

    Returns:
        ``(n, 4)`` float64 unit quaternions, ``wxyz``, ``w >= 0``.

    Raises:
        ValueError: negative ``n``, unknown distribution or invalid parameters.
    """
    if int(n) != n or n < 0:
        raise ValueError(f"n must be a non-negative integer; got {n!r}")
    n = int(n)
    if rng is None:
        rng = np.random.default_rng()
    if distribution == "uniform":
        if not (np.isfinite(a) and np.isfinite(b)) or b < a:
            raise ValueError(f"uniform noise needs finite low <= high (degrees); got low={a}, high={b}")
    elif distribution == "normal":
        if not (np.isfinite(a) and np.isfinite(b)) or b < 0:
            raise ValueError(f"normal noise needs a finite mean and std >= 0 (degrees); got mean={a}, std={b}")
    else:
        raise ValueError(f"distribution must be 'uniform' or 'normal'; got {distribution!r}")
    theta = rng.uniform(0.0, 2.0 * np.pi, size=n)
    s = rng.uniform(-1.0, 1.0, size=n)
    r = np.sqrt(1.0 - s * s)
    axis = np.stack([r * np.cos(theta), r * np.sin(theta), s], axis=-1)
    if distribution == "uniform":
        angle = rng.uniform(a, b, size=n)
    else:
        angle = rng.normal(a, b, size=n)
    if n == 0:
        return np.zeros((0, 4))
    return from_axis_angle(axis, angle)


def to_xyzw(q) -> np.ndarray:
    """Reorder ``wxyz`` quaternions to ``xyzw`` (ROS ``geometry_msgs/Quaternion``, SciPy ``as_quat``).

    Args:
        q: ``(..., 4)`` quaternions, ``wxyz``.

    Returns:
        ``(..., 4)`` float64, ``xyzw``. Values and sign are unchanged.
    """
    q = as_quaternion(q)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def from_xyzw(q) -> np.ndarray:
    """Reorder ``xyzw`` quaternions (ROS, SciPy) to this project's ``wxyz``.

    Args:
        q: ``(..., 4)`` quaternions, ``xyzw``.

    Returns:
        ``(..., 4)`` float64, ``wxyz``. Values and sign are unchanged.
    """
    q = as_quaternion(q)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)
