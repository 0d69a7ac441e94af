"""The fusion network's canonical roll: the turn's geometry against SciPy and a pinhole projection, its agreement
with the training's in-plane turns, the unchanged contract, ONNX export parity, and a network going on from one
trained without it."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

import export
import models
from models.fusion import canonical_roll, roll_angle
from models.train import _rotate_in_plane

SMALL = {"conv_channels": [8, 8], "fuse_width": 32, "pose_widths": [16, 32], "head_widths": [16, 8]}


def _wxyz(r: Rotation) -> torch.Tensor:
    xyzw = np.atleast_2d(r.as_quat())
    return torch.tensor(np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1), dtype=torch.float32)


def _image_angle(axis_cam: np.ndarray) -> float:
    """Clockwise angle from image-up of a camera-frame direction at the optical axis (x right, y down): where a pinhole
    camera draws it, from the projection of a point a little along it from (0, 0, 1)."""
    p0, p1 = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]) + 1e-3 * axis_cam
    d = p1[:2] / p1[2] - p0[:2] / p0[2]
    return float(np.degrees(np.arctan2(d[0], -d[1])))


def test_roll_angle_is_where_the_object_z_axis_points_in_the_image():
    rots = Rotation.random(50, random_state=3)
    got = np.degrees(roll_angle(_wxyz(rots)).numpy())
    for r, angle in zip(rots, got):
        z, x = r.as_matrix()[:, 2], r.as_matrix()[:, 0]
        axis = z if np.hypot(z[0], z[1]) > 0.5 else x  # the x axis where z is within 30 deg of the ray
        assert abs((angle - _image_angle(axis) + 180) % 360 - 180) < 1e-3


def test_canonical_roll_points_the_axis_up_and_turns_the_pose_with_the_image():
    """After the turn the coarse pose's axis points up; the turn is about the ray (z), so q_out is unchanged; a bar
    drawn along the axis's image direction is turned upright with it."""
    r = Rotation.from_euler("xyz", [70, 10, 0], degrees=True) * Rotation.from_euler("z", 35, degrees=True)
    r = Rotation.from_euler("z", 50, degrees=True) * r  # rolled about the ray
    q = _wxyz(r)
    psi = float(roll_angle(q)[0])
    size = 64
    image = np.zeros((1, 1, size, size), np.float32)
    for t in np.linspace(0, 26, 200):  # a bar from the centre along the axis's image direction
        x, y = 31.5 + t * np.sin(psi), 31.5 - t * np.cos(psi)
        image[0, 0, int(round(y)), int(round(x))] = 1.0
    turned, q_turned = canonical_roll(torch.tensor(image), q)
    ys, xs = np.nonzero(turned[0, 0].numpy() > 0.3)
    assert xs.min() >= 29 and xs.max() <= 34 and ys.max() <= 33 and ys.min() <= 8  # upright, above the centre
    r_new = Rotation.from_quat(np.r_[q_turned[0, 1:].numpy(), q_turned[0, 0].numpy()])
    assert abs(_image_angle(r_new.as_matrix()[:, 2])) < 1e-2
    turn = r_new * r.inv()  # a turn about the ray by -psi
    np.testing.assert_allclose(turn.as_rotvec(), [0.0, 0.0, -psi], atol=1e-5)
    q_gt = r * Rotation.from_euler("y", 12, degrees=True)
    assert np.degrees(((r_new.inv() * (turn * q_gt)).inv() * (r.inv() * q_gt)).magnitude()) < 1e-3


def test_canonical_roll_turns_crops_as_the_training_in_plane_turn_does():
    """The graph's turn and train --inplane's turn are one rule: poses whose roll is -phi are turned by +phi, giving
    the pixels and the pose q_z(phi) * q that _rotate_in_plane gives for the same phi (it rounds to uint8)."""
    crops = torch.randint(0, 256, (6, 32, 32, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
    gen_seed, max_deg = 1, 170.0
    images, _, q_turn = _rotate_in_plane(crops, None, max_deg, torch.Generator().manual_seed(gen_seed))
    phi = ((torch.rand(6, generator=torch.Generator().manual_seed(gen_seed), dtype=torch.float64) * 2 - 1)
           * np.radians(max_deg)).numpy()  # the angles _rotate_in_plane drew
    upright = Rotation.from_euler("x", 90, degrees=True)  # the object z axis -> image up
    r = Rotation.from_euler("z", -phi[:, None]) * upright
    q = _wxyz(r)
    np.testing.assert_allclose(roll_angle(q).numpy(), -phi, atol=1e-5)
    turned, q_turned = canonical_roll(crops.permute(0, 3, 1, 2).float(), q)
    diff = turned.round().clamp(0, 255) - images.permute(0, 3, 1, 2).float()
    assert diff.abs().max() <= 1.0
    expected = Rotation.from_quat(np.c_[q_turn[:, 1:], q_turn[:, :1]]) * r
    got = Rotation.from_quat(np.c_[q_turned[:, 1:].numpy(), q_turned[:, :1].numpy()])
    assert np.degrees((got.inv() * expected).magnitude()).max() < 1e-3


def test_canonical_roll_network_keeps_the_contract_and_exports_with_parity(tmp_path):
    torch.manual_seed(0)
    model = models.build_refiner("fusion", input_size=32, roll="canonical", **SMALL).eval()
    assert model.config["roll"] == "canonical"
    image = torch.randint(0, 256, (5, 32, 32, 3), dtype=torch.uint8)
    q = torch.nn.functional.normalize(torch.randn(5, 4), dim=1)
    out = model(image, q)
    assert out.shape == (5, 4) and torch.allclose(out.norm(dim=1), torch.ones(5), atol=1e-5)
    report = export.export_model(model, tmp_path / "roll.onnx", info={"rotation_frame": "ray"})
    assert report.max_abs_dq <= 1e-4
    assert export.check_parity(model, report.path, n=64, seed=3).passed


def test_roll_must_be_none_or_canonical():
    with pytest.raises(ValueError, match="roll"):
        models.build_refiner("fusion", roll="sideways", **SMALL)


def test_a_network_without_the_roll_goes_on_with_it_with_the_same_weights(tmp_path):
    """data_scaling --init accepts a checkpoint whose config differs only in roll, keeping every weight."""
    from types import SimpleNamespace

    from bench_scripts import load_benchmark

    scaling = load_benchmark("data_scaling")
    torch.manual_seed(0)
    plain = models.build_refiner("fusion", input_size=32, **SMALL)
    ckpt = models.save_checkpoint(plain, tmp_path / "plain.pt", objects=["003_cracker_box"], rotation_frame="ray")
    config = {**plain.config, "roll": "canonical"}
    args = SimpleNamespace(init=ckpt, arch="fusion", config=config, rotation_frame="ray", init_other_set=True)
    with pytest.raises(SystemExit) as exc:  # the checkpoint records no split here: refused after the network check
        scaling._initial_model(args, None, config)
    assert "config" not in str(exc.value)
    assert "records no training data spec" in str(exc.value)
    wider = {**config, "fuse_width": 64}  # any other difference is another network: refused
    with pytest.raises(SystemExit, match="a fusion network with config"):
        scaling._initial_model(SimpleNamespace(**{**vars(args), "config": wider}), None, wider)


def test_refiner_rt_train_init_goes_on_with_the_roll_and_keeps_every_weight(tmp_path):
    from models.recipe import TrainRecipe
    from models.training import load_init

    torch.manual_seed(0)
    plain = models.build_refiner("fusion", input_size=32, **SMALL)
    ckpt = models.save_checkpoint(plain, tmp_path / "plain.pt", objects=["003_cracker_box"], rotation_frame="ray")
    recipe = TrainRecipe.from_dict({"arch": "fusion", "arch_config": {"roll": "canonical"}, "rotation_frame": "ray",
                                    "init": str(ckpt)})
    model = load_init(recipe)
    assert model.config["roll"] == "canonical" and model.training
    for name, value in plain.state_dict().items():
        assert torch.equal(model.state_dict()[name], value), name
    other = TrainRecipe.from_dict({"arch": "fusion", "arch_config": {"roll": "canonical", "fuse_width": 64},
                                   "rotation_frame": "ray", "init": str(ckpt)})
    with pytest.raises(Exception, match="differs from the --init checkpoint's config"):
        load_init(other)
