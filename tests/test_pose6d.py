"""models.evaluate.pose6d: ADD, ADD-S, ADD(-S) and the AUC against brute-force references and SciPy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from models.evaluate.pose6d import (AUC_MAX_M, add, add_or_add_s, add_s, auc, mesh_points, rotation_error_deg)


def _poses(rng, n):
    R = Rotation.random(n, random_state=rng).as_matrix()
    t = rng.normal(0.0, 0.2, (n, 3)) + np.array([0.0, 0.0, 1.0])
    return R, t


def _add_naive(Re, te, Rg, tg, pts):
    return np.mean([np.linalg.norm((Re @ p + te) - (Rg @ p + tg)) for p in pts])


def _add_s_naive(Re, te, Rg, tg, pts):
    est = [Re @ p + te for p in pts]
    return np.mean([min(np.linalg.norm((Rg @ p + tg) - e) for e in est) for p in pts])


def test_add_and_add_s_match_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.normal(0.0, 0.05, (60, 3))
    Re, te = _poses(rng, 5)
    Rg, tg = _poses(rng, 5)
    got_add, got_add_s = add(Re, te, Rg, tg, pts), add_s(Re, te, Rg, tg, pts)
    assert got_add.shape == got_add_s.shape == (5,)
    for i in range(5):
        assert got_add[i] == pytest.approx(_add_naive(Re[i], te[i], Rg[i], tg[i], pts), rel=1e-12)
        assert got_add_s[i] == pytest.approx(_add_s_naive(Re[i], te[i], Rg[i], tg[i], pts), rel=1e-12)
    assert np.all(got_add_s <= got_add + 1e-15)


def test_add_s_forgives_a_symmetry_that_add_does_not():
    angles = np.radians(np.arange(0, 360, 10))
    ring = np.stack([0.05 * np.cos(angles), 0.05 * np.sin(angles), np.zeros_like(angles)], axis=1)
    Rg, tg = np.eye(3), np.array([0.0, 0.0, 1.0])
    Re = Rotation.from_euler("z", 30, degrees=True).as_matrix()  # a turn onto the ring's own samples
    assert add_s(Re, tg, Rg, tg, ring) == pytest.approx(0.0, abs=1e-12)
    assert add(Re, tg, Rg, tg, ring) > 0.02
    assert add_or_add_s("024_bowl", Re, tg, Rg, tg, ring) == pytest.approx(0.0, abs=1e-12)  # YCB-V symmetric
    assert add_or_add_s("003_cracker_box", Re, tg, Rg, tg, ring) == pytest.approx(add(Re, tg, Rg, tg, ring))


def test_auc_is_the_area_under_the_accuracy_threshold_curve():
    rng = np.random.default_rng(1)
    d = np.concatenate([rng.uniform(0.0, 0.15, 200), [np.inf]])
    thresholds = np.linspace(0.0, AUC_MAX_M, 200001)
    accuracy = (d[None, :] < thresholds[:, None]).mean(axis=1)
    reference = np.trapezoid(accuracy, thresholds) / AUC_MAX_M
    assert auc(d) == pytest.approx(reference, abs=1e-4)
    # PoseCNN's VOCap (steps at their right ends) is at most 1/n above it.
    s = np.sort(d[d < AUC_MAX_M])
    rec = np.concatenate([[0.0], s, [AUC_MAX_M]])
    prec = np.concatenate([[0.0], np.arange(1, len(s) + 1) / len(d), [len(s) / len(d)]])
    vocap = np.sum(np.diff(rec) * prec[1:]) / AUC_MAX_M
    assert 0.0 <= vocap - auc(d) <= 1.0 / len(d)
    assert auc([0.0, 0.0]) == 1.0 and auc([0.1, 0.2]) == 0.0 and auc([0.05]) == pytest.approx(0.5)


def test_auc_refuses_bad_input():
    with pytest.raises(ValueError, match="at least one"):
        auc([])
    with pytest.raises(ValueError, match=">= 0"):
        auc([-0.01])
    with pytest.raises(ValueError, match="max_m"):
        auc([0.01], max_m=0.0)


def test_rotation_error_matches_scipy():
    rng = np.random.default_rng(2)
    a, b = Rotation.random(20, random_state=rng), Rotation.random(20, random_state=rng)
    want = np.degrees((a.inv() * b).magnitude())
    np.testing.assert_allclose(rotation_error_deg(a.as_matrix(), b.as_matrix()), want, atol=1e-6)


def test_shapes_are_checked():
    with pytest.raises(ValueError, match="R"):
        add(np.eye(3), np.zeros(2), np.eye(3), np.zeros(3), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="points"):
        add(np.eye(3), np.zeros(3), np.eye(3), np.zeros(3), np.zeros((4, 2)))


def test_mesh_points_draws_vertices(tmp_path):
    obj = tmp_path / "m.obj"
    v = np.random.default_rng(3).normal(size=(50, 3))
    obj.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v) + "f 1 2 3\n")
    pts = mesh_points(obj, n=20)
    assert pts.shape == (20, 3)
    assert all(any(np.allclose(p, w) for w in v) for p in pts)
    assert mesh_points(obj, n=100).shape == (50, 3)
