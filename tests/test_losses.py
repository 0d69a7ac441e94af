"""models.train.losses against refiner_rt.quaternion (numpy) and SciPy's Rotation, plus gradient safety."""

from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
import torch

from models.nets import quaternion
from models.train import losses
from refiner_rt import quaternion as rq

RNG = np.random.default_rng(1)


def random_q(n: int) -> np.ndarray:
    return rq.from_xyzw(Rotation.random(n, random_state=int(RNG.integers(1 << 31))).as_quat())


unit_quats = arrays(np.float64, 4, elements=st.floats(-1, 1, allow_nan=False)).filter(
    lambda v: np.linalg.norm(v) > 1e-3
).map(lambda v: v / np.linalg.norm(v))


def test_quat_multiply_known_value_wxyz():
    # i * j = k in the Hamilton convention, wxyz order.
    i = torch.tensor([0.0, 1.0, 0.0, 0.0])
    j = torch.tensor([0.0, 0.0, 1.0, 0.0])
    torch.testing.assert_close(quaternion.quat_multiply(i, j), torch.tensor([0.0, 0.0, 0.0, 1.0]))


def test_quat_multiply_and_conjugate_match_numpy_and_scipy():
    a, b = random_q(100), random_q(100)
    got = quaternion.quat_multiply(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    np.testing.assert_allclose(got, rq.multiply(a, b), atol=1e-12)
    scipy_ab = (Rotation.from_quat(rq.to_xyzw(a)) * Rotation.from_quat(rq.to_xyzw(b))).as_matrix()
    np.testing.assert_allclose(rq.to_matrix(got), scipy_ab, atol=1e-12)
    conj = quaternion.quat_conjugate(torch.from_numpy(a)).numpy()
    np.testing.assert_allclose(rq.canonical(conj), rq.inverse(a), atol=1e-15)


def test_wxyz_splits_scalar_first():
    w, x, y, z = quaternion.wxyz(torch.tensor([[1.0, 2.0, 3.0, 4.0]]))
    assert (w.item(), x.item(), y.item(), z.item()) == (1.0, 2.0, 3.0, 4.0)


def test_geodesic_angle_matches_numpy_and_scipy():
    a, b = random_q(200), random_q(200)
    got = losses.geodesic_angle_rad(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    # a * b^-1 has the same angle as a^-1 * b.
    np.testing.assert_allclose(got, rq.geodesic_angle_rad(a, b), atol=1e-12)
    rel = Rotation.from_quat(rq.to_xyzw(a)) * Rotation.from_quat(rq.to_xyzw(b)).inv()
    np.testing.assert_allclose(got, rel.magnitude(), atol=1e-9)


def test_geodesic_loss_known_value_and_mean():
    q_label = torch.tensor([[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    q_pred = torch.from_numpy(rq.from_axis_angle([[0, 0, 1], [1, 0, 0]], [30.0, 90.0])).float()
    loss = losses.geodesic_loss(q_pred, q_label)
    assert loss.item() == pytest.approx(np.radians(60.0), abs=1e-6)


@settings(max_examples=50, deadline=None)
@given(unit_quats, unit_quats)
def test_geodesic_ignores_sign_and_is_symmetric(a, b):
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    d = losses.geodesic_angle_rad(ta, tb)
    torch.testing.assert_close(losses.geodesic_angle_rad(-ta, tb), d)
    torch.testing.assert_close(losses.geodesic_angle_rad(tb, ta), d)
    assert 0.0 <= d.item() <= np.pi + 1e-12


def test_gradient_finite_at_zero_error_and_near_it():
    q = torch.from_numpy(random_q(8)).float()
    for offset in (0.0, 1e-7, 1e-3):
        q_pred = (q + offset).requires_grad_(True)
        loss = losses.geodesic_loss(q_pred, q)
        loss.backward()
        assert torch.isfinite(q_pred.grad).all(), f"non-finite gradient at offset {offset}"
    assert losses.geodesic_loss(q, q).item() == pytest.approx(0.0, abs=1e-6)


def test_gradient_decreases_the_loss():
    torch.manual_seed(0)
    q_label = torch.from_numpy(random_q(16)).float()
    q_pred = torch.nn.functional.normalize(q_label + 0.3 * torch.randn(16, 4), dim=1).requires_grad_(True)
    loss = losses.geodesic_loss(q_pred, q_label)
    loss.backward()
    with torch.no_grad():
        stepped = q_pred - 0.05 * q_pred.grad
    assert losses.geodesic_loss(stepped, q_label).item() < loss.item()


def test_bad_shapes_raise_value_error():
    with pytest.raises(ValueError, match=r"\(\.\.\., 4\)"):
        losses.geodesic_loss(torch.zeros(3, 3), torch.zeros(3, 3))
    with pytest.raises(ValueError, match="same shape"):
        losses.geodesic_loss(torch.zeros(3, 4), torch.zeros(2, 4))
    with pytest.raises(TypeError, match="torch.Tensor"):
        quaternion.quat_conjugate(np.zeros(4))
