"""The twist/swing split of the can-twist study, against SciPy's rotations."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.bench_scripts import load_benchmark

twist_study = load_benchmark("studies/can_twist/twist")


def _wxyz(r: Rotation) -> np.ndarray:
    x, y, z, w = r.as_quat().T
    return np.column_stack([w, x, y, z])


@pytest.mark.parametrize("axis", [[0, 0, 1], [1, 2, -0.5]])
def test_twist_and_swing_recover_the_rotations_they_were_composed_of(axis):
    rng = np.random.default_rng(3)
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    twist_deg = rng.uniform(-170, 170, 50)
    # a swing axis perpendicular to the twist axis, an angle under 90 degrees
    perp = np.cross(a, rng.normal(size=(50, 3)))
    perp /= np.linalg.norm(perp, axis=1, keepdims=True)
    swing_deg = rng.uniform(0, 80, 50)
    swing = Rotation.from_rotvec(perp * np.radians(swing_deg)[:, None])
    twist = Rotation.from_rotvec(np.outer(np.radians(twist_deg), a))
    q = _wxyz(swing * twist)  # the twist first, about the object's axis
    q[::2] *= -1  # both signs of each quaternion
    got_twist, got_swing = twist_study.twist_swing(q, axis)
    np.testing.assert_allclose(got_twist, twist_deg, atol=1e-6)
    np.testing.assert_allclose(got_swing, swing_deg, atol=1e-5)


def test_a_rotation_about_another_axis_is_all_swing():
    q = _wxyz(Rotation.from_rotvec([[0.3, 0.0, 0.0]]))
    twist, swing = twist_study.twist_swing(q, [0, 0, 1])
    assert abs(twist[0]) < 1e-9
    assert swing[0] == pytest.approx(np.degrees(0.3))
