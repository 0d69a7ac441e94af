"""benchmarks/viewpoints.py: the camera's elevation above an object's own z axis, its distance and roll, against the
world-frame geometry they describe (SciPy draws the poses)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from benchmarks.viewpoints import viewpoints
from models.data.render import look_at


def test_elevation_distance_and_roll_match_the_world_geometry():
    rng = np.random.default_rng(0)
    R_wo = Rotation.random(20, random_state=1).as_matrix()
    p_wo = rng.uniform(-0.3, 0.3, (20, 3))
    eyes = rng.uniform(-1.5, 1.5, (20, 3)) + np.array([0.0, 0.0, 1.0])
    Rs, ts, expected = [], [], []
    for R, p, eye in zip(R_wo, p_wo, eyes):
        R_cw, t_cw = look_at(eye, p + rng.normal(0, 0.05, 3))
        Rs.append(R_cw @ R)
        ts.append(R_cw @ p + t_cw)
        to_eye = (eye - p) / np.linalg.norm(eye - p)
        expected.append((np.degrees(np.arcsin(to_eye @ R[:, 2])), np.linalg.norm(eye - p)))
    v = viewpoints(np.stack(Rs), np.stack(ts))
    np.testing.assert_allclose(v["elevation_deg"], [e for e, _ in expected], atol=1e-9)
    np.testing.assert_allclose(v["distance_m"], [d for _, d in expected], atol=1e-9)


def test_an_upright_object_seen_level_has_zero_elevation_and_roll():
    R_cw, t_cw = look_at([1.0, 0.0, 0.0], [0.0, 0.0, 0.0])  # camera at the object's height, looking at it
    v = viewpoints(R_cw[None], t_cw[None])
    assert v["elevation_deg"][0] == pytest.approx(0.0, abs=1e-9)
    assert v["roll_deg"][0] == pytest.approx(0.0, abs=1e-9)  # its z axis points up in the image
    R_cw, t_cw = look_at([0.6, 0.0, 0.6], [0.0, 0.0, 0.0])
    assert viewpoints(R_cw[None], t_cw[None])["elevation_deg"][0] == pytest.approx(45.0)
