"""refiner_rt.quaternion against SciPy's Rotation (independent reference) and maths identities."""

from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from refiner_rt import quaternion as rq

RNG = np.random.default_rng(0)


def random_q(n, rng=RNG):
    return rq.canonical(rq.from_xyzw(Rotation.random(n, random_state=int(rng.integers(1 << 31))).as_quat()))


def same_rotation(a, b, atol=1e-9):
    """True where a and b are the same rotation (q ~ -q)."""
    return np.all(np.minimum(np.abs(a - b).max(-1), np.abs(a + b).max(-1)) < atol)


unit_quats = arrays(np.float64, 4, elements=st.floats(-1, 1, allow_nan=False)).filter(
    lambda v: np.linalg.norm(v) > 1e-3
).map(lambda v: v / np.linalg.norm(v))


# ---------------------------------------------------------------- known values
def test_known_value_wxyz_order():
    # 90 degrees about z: wxyz = (cos45, 0, 0, sin45); SciPy's xyzw puts w last.
    q = rq.from_axis_angle([0, 0, 1], 90.0)
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-15)
    np.testing.assert_allclose(rq.to_matrix(q), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(rq.to_xyzw(q), Rotation.from_euler("z", 90, degrees=True).as_quat(), atol=1e-15)


def test_xyzw_round_trip_and_scipy():
    q = random_q(50)
    np.testing.assert_array_equal(rq.from_xyzw(rq.to_xyzw(q)), q)
    np.testing.assert_allclose(Rotation.from_quat(rq.to_xyzw(q)).as_matrix(), rq.to_matrix(q), atol=1e-12)


# ---------------------------------------------------------------- against SciPy
def test_multiply_matches_scipy_composition():
    a, b = random_q(200), random_q(200)
    ref = (Rotation.from_quat(rq.to_xyzw(a)) * Rotation.from_quat(rq.to_xyzw(b))).as_quat()
    assert same_rotation(rq.multiply(a, b), rq.from_xyzw(ref))
    # R(a*b) = R(a) @ R(b): b is applied first.
    np.testing.assert_allclose(rq.to_matrix(rq.multiply(a, b)), rq.to_matrix(a) @ rq.to_matrix(b), atol=1e-12)


def test_inverse_matches_scipy():
    q = random_q(100)
    ref = rq.from_xyzw(Rotation.from_quat(rq.to_xyzw(q)).inv().as_quat())
    assert same_rotation(rq.inverse(q), ref)
    assert np.all(rq.inverse(q)[:, 0] >= 0)


def test_matrix_conversions_match_scipy():
    q = random_q(500)
    R = Rotation.from_quat(rq.to_xyzw(q)).as_matrix()
    np.testing.assert_allclose(rq.to_matrix(q), R, atol=1e-12)
    assert same_rotation(rq.from_matrix(R), q, atol=1e-12)
    assert np.all(rq.from_matrix(R)[:, 0] >= 0)


def test_from_matrix_near_180_degrees():
    # w close to 0: the trace branch is unstable, Shepperd's largest-pivot branch is not.
    axes = RNG.normal(size=(100, 3))
    q = rq.from_axis_angle(axes, 180.0 - 1e-7)
    R = rq.to_matrix(q)
    assert same_rotation(rq.from_matrix(R), q, atol=1e-9)


def test_axis_angle_matches_scipy():
    axes = RNG.normal(size=(100, 3))
    angles = RNG.uniform(0, 180, size=100)
    q = rq.from_axis_angle(axes, angles)
    unit = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    ref = Rotation.from_rotvec(unit * np.radians(angles)[:, None]).as_quat()
    assert same_rotation(q, rq.from_xyzw(ref))
    axis2, angle2 = rq.to_axis_angle(q)
    np.testing.assert_allclose(angle2, angles, atol=1e-9)
    np.testing.assert_allclose(axis2, unit, atol=1e-9)


def test_geodesic_matches_scipy_magnitude():
    a, b = random_q(300), random_q(300)
    ref = (Rotation.from_quat(rq.to_xyzw(a)).inv() * Rotation.from_quat(rq.to_xyzw(b))).magnitude()
    np.testing.assert_allclose(rq.geodesic_angle(a, b), np.degrees(ref), atol=1e-9)


def test_geodesic_exact_near_zero_and_180():
    axis = np.array([0.3, -0.5, 0.8])
    for angle in (1e-9, 1e-6, 1e-3):
        assert rq.geodesic_angle(rq.identity(), rq.from_axis_angle(axis, angle)) == pytest.approx(angle, rel=1e-6)
    for angle in (180.0 - 1e-6, 180.0 - 1e-3, 180.0):
        assert rq.geodesic_angle(rq.identity(), rq.from_axis_angle(axis, angle)) == pytest.approx(angle, rel=1e-12)
    q = random_q(10)
    assert np.all(rq.geodesic_angle(q, q) < 1e-9)


def test_identity_angle_from_slightly_non_unit_input_is_not_nan():
    q = np.array([1.0 + 1e-15, 0, 0, 0])
    assert rq.geodesic_angle(q, rq.identity()) == 0.0


# ---------------------------------------------------------------- property tests
@settings(max_examples=200, deadline=None)
@given(unit_quats, unit_quats, unit_quats)
def test_associativity(a, b, c):
    np.testing.assert_allclose(rq.multiply(rq.multiply(a, b), c), rq.multiply(a, rq.multiply(b, c)), atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(unit_quats)
def test_inverse_gives_identity(q):
    assert rq.geodesic_angle(rq.multiply(q, rq.inverse(q)), rq.identity()) < 1e-6
    assert rq.geodesic_angle(rq.multiply(rq.inverse(q), q), rq.identity()) < 1e-6


@settings(max_examples=200, deadline=None)
@given(unit_quats, unit_quats)
def test_geodesic_sign_invariance_and_symmetry(a, b):
    assert rq.geodesic_angle(a, -a) < 1e-9
    assert rq.geodesic_angle(a, b) == pytest.approx(rq.geodesic_angle(-a, b), abs=1e-9)
    assert rq.geodesic_angle(a, b) == pytest.approx(rq.geodesic_angle(b, a), abs=1e-9)
    assert 0.0 <= rq.geodesic_angle(a, b) <= 180.0


@settings(max_examples=200, deadline=None)
@given(unit_quats)
def test_round_trips(q):
    assert same_rotation(rq.from_matrix(rq.to_matrix(q)), q, atol=1e-9)
    axis, angle = rq.to_axis_angle(q)
    assert same_rotation(rq.from_axis_angle(axis, angle), q, atol=1e-9)
    np.testing.assert_allclose(rq.from_xyzw(rq.to_xyzw(q)), q)


# ---------------------------------------------------------------- orthonormalize
def test_orthonormalize_svd_is_exact_and_premerlani_first_order():
    R = rq.to_matrix(random_q(100))
    noisy = R + RNG.normal(scale=1e-3, size=R.shape)
    for method, tol in (("svd", 1e-12), ("premerlani", 1e-4)):
        out = rq.orthonormalize(noisy, method=method)
        err = np.abs(np.swapaxes(out, -1, -2) @ out - np.eye(3)).max()
        assert err < tol, (method, err)
        np.testing.assert_allclose(np.linalg.det(out), 1.0, atol=tol)
        assert rq.geodesic_angle(rq.from_matrix(rq.orthonormalize(out, "svd")), rq.from_matrix(R)).max() < 0.5


def test_orthonormalize_premerlani_known_formula():
    # An exact rotation is a fixed point of the paper's step.
    R = rq.to_matrix(random_q(5))
    np.testing.assert_allclose(rq.orthonormalize(R, "premerlani"), R, atol=1e-14)


def test_orthonormalize_rejects_bad_input():
    with pytest.raises(ValueError, match="shape"):
        rq.orthonormalize(np.eye(4))
    with pytest.raises(ValueError, match="method"):
        rq.orthonormalize(np.eye(3), method="gram")
    with pytest.raises(ValueError, match="reflection"):
        rq.orthonormalize(np.diag([1.0, 1.0, -1.0]), method="svd")


# ---------------------------------------------------------------- noise sampling
def test_sample_rotation_noise_uniform_angles_and_axes():
    rng = np.random.default_rng(1)
    q = rq.sample_rotation_noise(20000, "uniform", 0, 30, rng)
    angles = rq.geodesic_angle(q, rq.identity())
    assert angles.min() >= 0 and angles.max() <= 30 + 1e-9
    assert angles.mean() == pytest.approx(15.0, abs=0.2)
    axis, _ = rq.to_axis_angle(q)
    # Axes uniform on the sphere (the canonical sign folds them onto w >= 0, not the axis itself).
    np.testing.assert_allclose(axis.mean(axis=0), 0.0, atol=0.03)
    np.testing.assert_allclose((axis**2).mean(axis=0), 1 / 3, atol=0.02)


def test_sample_rotation_noise_normal_and_seed():
    q1 = rq.sample_rotation_noise(10000, "normal", 30, 5, np.random.default_rng(7))
    q2 = rq.sample_rotation_noise(10000, "normal", 30, 5, np.random.default_rng(7))
    np.testing.assert_array_equal(q1, q2)
    angles = rq.geodesic_angle(q1, rq.identity())
    assert angles.mean() == pytest.approx(30.0, abs=0.3)
    assert angles.std() == pytest.approx(5.0, abs=0.3)


def test_sample_rotation_noise_errors():
    with pytest.raises(ValueError, match="distribution"):
        rq.sample_rotation_noise(3, "cauchy")
    with pytest.raises(ValueError, match="low <= high"):
        rq.sample_rotation_noise(3, "uniform", 30, 0)
    with pytest.raises(ValueError, match="std"):
        rq.sample_rotation_noise(3, "normal", 10, -1)
    assert rq.sample_rotation_noise(0).shape == (0, 4)


# ---------------------------------------------------------------- validation
def test_invalid_quaternions_are_rejected_with_clear_errors():
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 4\).*got shape \(3,\)"):
        rq.normalize([1, 0, 0])
    with pytest.raises(ValueError, match="finite"):
        rq.normalize([np.nan, 0, 0, 0])
    with pytest.raises(ValueError, match="zero quaternion"):
        rq.normalize([[1, 0, 0, 0], [0, 0, 0, 0]])
    with pytest.raises(ValueError, match="non-zero"):
        rq.from_axis_angle([0, 0, 0], 10)


def test_normalize_and_canonical():
    q = rq.normalize([[-2.0, 0, 0, 0], [0, -1.0, 0, 0]])
    np.testing.assert_array_equal(q, [[1, 0, 0, 0], [0, 1, 0, 0]])


def test_mean_matches_scipy_and_ignores_signs():
    for spread in (5.0, 40.0, 180.0):
        centre = random_q(1)[0]
        q = rq.multiply(centre, rq.sample_rotation_noise(7, "uniform", 0.0, spread, np.random.default_rng(int(spread))))
        q = rq.normalize(q)
        ref = rq.from_xyzw(Rotation.from_quat(rq.to_xyzw(q)).mean().as_quat())
        assert same_rotation(rq.mean(q), ref, atol=1e-9)
        flipped = q * np.array([1, -1, 1, -1, 1, -1, 1])[:, None]  # q and -q are one rotation
        assert same_rotation(rq.mean(flipped), ref, atol=1e-9)
    # Batched over other axes: (views, N, 4) averaged over the views, and over axis 1 of (N, views, 4).
    q = random_q(12).reshape(3, 4, 4)
    by_view = rq.mean(q, axis=0)
    assert by_view.shape == (4, 4) and np.all(by_view[:, 0] >= 0)
    for i in range(4):
        ref = rq.from_xyzw(Rotation.from_quat(rq.to_xyzw(q[:, i])).mean().as_quat())
        assert same_rotation(by_view[i], ref)
    assert np.allclose(rq.mean(np.swapaxes(q, 0, 1), axis=1), by_view)
    assert same_rotation(rq.mean(q[:1], axis=0), rq.canonical(q[0]))


def test_mean_rejects_what_it_cannot_average():
    with pytest.raises(ValueError, match="axis to average over"):
        rq.mean(np.array([1.0, 0, 0, 0]))
    with pytest.raises(ValueError, match="must not be the last axis"):
        rq.mean(random_q(3), axis=-1)
    with pytest.raises(ValueError, match="nothing to average"):
        rq.mean(np.zeros((0, 4)))


def test_the_python_float_twins_equal_their_numpy_references_bit_for_bit():
    """normalize_rows, multiply_rows and inverse_rows (the runtime's small-batch fast paths) against normalize,
    multiply and inverse: the same operations in the same order, so equal exactly, w == 0 sign keys included."""
    rng = np.random.default_rng(11)
    a, b = rng.standard_normal((64, 4)), rng.standard_normal((64, 4))
    a[0] = [0.0, -0.5, 0.5, 0.5]
    a[1] = [0.0, 0.0, -1.0, 2.0]
    a[2, 0] = -3.0
    np.testing.assert_array_equal(np.array(rq.normalize_rows(a.tolist())), rq.normalize(a))
    np.testing.assert_array_equal(np.array(rq.multiply_rows(a.tolist(), b.tolist())), rq.multiply(a, b))
    unit = rq.normalize(a)
    np.testing.assert_array_equal(np.array(rq.inverse_rows(unit.tolist())), rq.inverse(unit))
    assert rq.normalize_rows([[0.0, 0.0, 0.0, 0.0]]) is None and rq.normalize_rows([[np.nan, 0, 0, 1]]) is None
