"""Symmetric objects: the symmetry set (BOP form), the closest symmetric label, the symmetry-aware error and loss."""

import json

import numpy as np
import pytest
import torch

from models.data.symmetry import closest_label, symmetric_error, symmetry_quaternions, symmetry_table, validate_symmetry
from refiner_rt import quaternion as rq

HALF_TURN_X = [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]  # BOP symmetries_discrete entry (mm translation)
ABOUT_Z = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}


def test_symmetry_sets_in_bop_form():
    q = symmetry_quaternions({"symmetries_discrete": [HALF_TURN_X]})
    np.testing.assert_allclose(q, [[1, 0, 0, 0], [0, 1, 0, 0]], atol=1e-12)
    q = symmetry_quaternions(ABOUT_Z, steps=4)
    angles = rq.geodesic_angle(q, np.array([1.0, 0, 0, 0]))
    np.testing.assert_allclose(angles, [0, 90, 180, 90], atol=1e-9)
    both = symmetry_quaternions({"symmetries_discrete": [HALF_TURN_X], **ABOUT_Z}, steps=4)
    assert both.shape == (8, 4)
    assert symmetry_quaternions(None).shape == (1, 4)
    for bad, words in (({"symmetries_discrete": [[1, 2]]}, "16 numbers"), ({"axis": [0, 0, 1]}, "unknown key"),
                       ({"symmetries_continuous": [{"axis": [0, 0, 0]}]}, "non-zero axis")):
        with pytest.raises(ValueError, match=words):
            validate_symmetry(bad)


def test_symmetric_error_is_zero_on_an_equivalent_pose_and_plain_otherwise():
    rng = np.random.default_rng(0)
    q_gt = rq.sample_rotation_noise(6, "uniform", 0, 180, rng)
    s = rq.from_axis_angle([0, 0, 1], 70.0)
    est = rq.multiply(q_gt, np.broadcast_to(s, q_gt.shape))
    ids = np.array(["can"] * 3 + ["box"] * 3)
    err = symmetric_error(est, q_gt, ids, {"can": ABOUT_Z})
    np.testing.assert_allclose(err[:3], 0.0, atol=1e-6)  # a continuous symmetry is exact, not sampled
    np.testing.assert_allclose(err[3:], 70.0, atol=1e-9)  # no symmetry: the plain geodesic error
    table, index = symmetry_table(ids, {"can": ABOUT_Z})
    assert table.shape == (2, 36, 4) and index.tolist() == [0, 0, 0, 1, 1, 1]
    assert symmetry_table(ids, {"other": ABOUT_Z}) == (None, None)


def test_continuous_symmetric_error_is_the_minimum_over_every_turn():
    """Against a brute-force minimum over turns every 0.01 degrees about the axis (SciPy composes the rotations),
    with and without a discrete half turn besides."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    q_gt = rq.sample_rotation_noise(8, "uniform", 0, 180, rng)
    est = rq.multiply(q_gt, rq.sample_rotation_noise(8, "uniform", 0, 40, rng))
    axis = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
    turns = Rotation.from_rotvec(np.radians(np.arange(0, 360, 0.01))[:, None] * axis)
    for sym, extra in (({"symmetries_continuous": [{"axis": axis.tolist(), "offset": [0, 0, 0]}]}, [np.eye(3)]),
                       ({"symmetries_continuous": [{"axis": axis.tolist(), "offset": [0, 0, 0]}],
                         "symmetries_discrete": [HALF_TURN_X]}, [np.eye(3), np.diag([1.0, -1.0, -1.0])])):
        err = symmetric_error(est, q_gt, np.array(["o"] * 8), {"o": sym})
        for i in range(8):
            R_gt = Rotation.from_quat(rq.to_xyzw(q_gt[i]))
            R_est = Rotation.from_quat(rq.to_xyzw(est[i]))
            brute = min((R_est.inv() * R_gt * Rotation.from_matrix(d) * turns).magnitude().min() for d in extra)
            assert err[i] == pytest.approx(np.degrees(brute), abs=2e-3)


def test_closest_label_picks_the_symmetric_label_nearest_the_prediction():
    labels = torch.tensor([[[1.0, 0, 0, 0], [0, 1.0, 0, 0]]])
    q_out = torch.tensor([[0.1, -0.99, 0, 0]])  # near the second label, with the opposite sign
    assert torch.equal(closest_label(q_out, labels), labels[0, 1:2])


def test_training_with_a_symmetry_records_it_and_evaluates_with_it(tmp_path):
    import models
    from tests.cube_dataset import make_cube_dataset
    from models.train.recipe import RecipeError, TrainRecipe

    make_cube_dataset(tmp_path / "cubes", scenes=3, frames=8)
    tiny = {"input_size": 32, "conv_channels": [8, 8], "fuse_width": 64, "pose_widths": [32, 64],
            "head_widths": [32, 16]}
    recipe = TrainRecipe.from_dict(dict(
        data=str(tmp_path / "cubes"), objects=["003_cracker_box"], arch="fusion", arch_config=tiny,
        base_per_object=8, per_object=0, val_per_object=4, test_per_object=4, epochs_mse=1, epochs_geodesic=1,
        batch_size=8, threads=1, cache_root=str(tmp_path / "cache"), symmetries={"003_cracker_box": ABOUT_Z}))
    out = tmp_path / "sym.pt"
    models.run_training(recipe, out=out, progress=False)
    _, info = models.load_checkpoint(out)
    assert info["symmetries"] == {"003_cracker_box": ABOUT_Z}
    from models.evaluate.cli import run_eval

    result = run_eval(out, tmp_path / "cubes", cache_root=tmp_path / "cache", threads=1, progress=False)
    assert result["error"].startswith("symmetry-aware") and result["symmetries"] == info["symmetries"]
    with pytest.raises(RecipeError, match="non-zero axis"):
        recipe.merged(symmetries={"003_cracker_box": {"symmetries_continuous": [{"axis": [0, 0, 0]}]}})
    json.dumps(result)
