"""The fusion network's canonical roll: the turn's geometry against SciPy and a pinhole projection, its agreement
with the training's in-plane turns, the unchanged contract, ONNX export parity, and a network going on from one
trained without it."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
import torch

import export
import models
from models.data.augment import rotate_in_plane
from models.nets.fusion import canonical_roll, roll_angle

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
    the pixels and the pose q_z(phi) * q that rotate_in_plane gives for the same phi (it rounds to uint8)."""
    crops = torch.randint(0, 256, (6, 32, 32, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
    gen_seed, max_deg = 1, 170.0
    images, _, q_turn = rotate_in_plane(crops, None, max_deg, torch.Generator().manual_seed(gen_seed))
    phi = ((torch.rand(6, generator=torch.Generator().manual_seed(gen_seed), dtype=torch.float64) * 2 - 1)
           * np.radians(max_deg)).numpy()  # the angles rotate_in_plane drew
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


def _smooth_crops(n: int, size: int, seed: int) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    return np.stack([cv2.GaussianBlur(c, (7, 7), 2) for c in rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8)])


def test_the_runtime_turn_is_the_training_turn():
    """refiner_rt.preprocess.canonical_roll (OpenCV, uint8, plain floats) against models.nets.fusion.canonical_roll
    (PyTorch GridSample, float): the same angle, the same rotation, pixels within a grey level (its rounding)."""
    from refiner_rt.preprocess import canonical_roll as runtime_roll
    from refiner_rt.preprocess import roll_angles

    q = _wxyz(Rotation.random(64, random_state=5))
    crops = _smooth_crops(64, 48, 0)
    np.testing.assert_allclose(roll_angles(q.double().numpy()), roll_angle(q.double()).numpy(), atol=1e-9)
    turned, q_turned = runtime_roll(crops, q.numpy(), step_deg=0)  # the exact angle, as the training
    ref, q_ref = canonical_roll(torch.tensor(crops).permute(0, 3, 1, 2).float(), q)
    assert turned.dtype == np.uint8 and turned.shape == crops.shape
    diff = np.abs(turned.astype(np.float32) - ref.permute(0, 2, 3, 1).numpy())
    assert diff.max() <= 1.0 + 1e-3 and diff.mean() < 0.3  # rounding, and OpenCV's fixed-point weights
    np.testing.assert_allclose(q_turned, q_ref.numpy(), atol=1e-6)


def test_canonical_roll_network_keeps_the_contract_and_exports_the_turn_for_the_runtime(tmp_path):
    """The file holds the network without the turn (no GridSample), says format 2 with ``roll = canonical``, and the
    runtime, which makes the turn, gives what the PyTorch network with the roll gives."""
    import onnx

    from refiner_rt import RefinerSession
    from refiner_rt.metadata import FORMAT_ROLL

    torch.manual_seed(0)
    model = models.build_refiner("fusion", input_size=32, roll="canonical", **SMALL).eval()
    assert model.config["roll"] == "canonical"
    image = torch.randint(0, 256, (5, 32, 32, 3), dtype=torch.uint8)
    q = torch.nn.functional.normalize(torch.randn(5, 4), dim=1)
    out = model(image, q)
    assert out.shape == (5, 4) and torch.allclose(out.norm(dim=1), torch.ones(5), atol=1e-5)
    report = export.export_model(model, tmp_path / "roll.onnx", info={"rotation_frame": "ray"})
    assert report.max_abs_dq <= 1e-4
    proto = onnx.load(str(report.path))
    assert "GridSample" not in {node.op_type for node in proto.graph.node}
    sess = RefinerSession(report.path, roll_step_deg=0)  # the exact turn, as the PyTorch network makes it
    assert sess.contract.roll == "canonical" and sess.metadata["refiner_rt.format"] == FORMAT_ROLL
    crops = _smooth_crops(40, 32, 1)
    q_in = _wxyz(Rotation.random(40, random_state=2))
    with torch.no_grad():
        ref = model(torch.tensor(crops), q_in).double().numpy()  # the network takes BGR, as the runtime
    got = sess.refine_crops(crops, q_in.numpy().astype(np.float64)).q_out
    angle = np.degrees(2 * np.arccos(np.clip(np.abs((got * ref).sum(axis=1)) / np.linalg.norm(ref, axis=1), 0, 1)))
    assert angle.max() < 0.05  # the uint8 turn's rounding only
    # one crop at a time (the runtime's plain-float path without the roll) gives the same
    one = sess.refine_crops(crops[:1], q_in[:1].numpy().astype(np.float64)).q_out
    np.testing.assert_allclose(one, got[:1], atol=1e-6)


def test_a_roll_model_needs_format_2_and_the_ray_frame():
    from refiner_rt.metadata import FORMAT, FORMAT_ROLL, build_metadata, parse_metadata

    common = dict(arch="fusion", input_size=64, channel_order="RGB", crop_context=1.2, objects=["x"],
                  train_noise="uniform:0:30", checkpoint_sha256="none", version="0")
    props = build_metadata(rotation_frame="ray", roll="canonical", **common)
    assert props["refiner_rt.format"] == FORMAT_ROLL and parse_metadata(props).roll == "canonical"
    assert build_metadata(rotation_frame="ray", **common)["refiner_rt.format"] == FORMAT
    with pytest.raises(ValueError, match="'roll'.*belongs to format"):
        parse_metadata({**props, "refiner_rt.format": FORMAT})
    with pytest.raises(ValueError, match="'roll' must be one of"):
        parse_metadata({**props, "roll": "sideways"})
    with pytest.raises(ValueError, match="'roll' must be one of"):
        parse_metadata({k: v for k, v in props.items() if k != "roll"})
    with pytest.raises(ValueError, match="needs rotation_frame 'ray'"):
        build_metadata(rotation_frame="camera", roll="canonical", **common)


def test_a_roll_export_recovers_and_quantises_with_the_turn(tmp_path):
    """export.recover gives back the network with the roll from the file (on crops as the graph takes them), and the
    INT8 file keeps format 2 and the roll."""
    from export.quantize import quantize_model
    from export.recover import checkpoint_from_onnx
    from refiner_rt import RefinerSession
    from refiner_rt.preprocess import canonical_roll as runtime_roll

    torch.manual_seed(1)
    model = models.build_refiner("fusion", input_size=32, roll="canonical", **SMALL).eval()
    fp32 = export.export_model(model, tmp_path / "roll.onnx", info={"rotation_frame": "ray"}).path
    crops = _smooth_crops(32, 32, 3)
    q_in = _wxyz(Rotation.random(32, random_state=4)).numpy()
    turned, q_turned = runtime_roll(crops, q_in)
    ckpt = checkpoint_from_onnx(fp32, tmp_path / "back.pt", turned, q_turned.astype(np.float32), tol=1e-3)
    back, _ = models.load_checkpoint(ckpt)
    assert back.config["roll"] == "canonical"
    with torch.no_grad():
        a = back.eval()(torch.tensor(crops), torch.tensor(q_in)).numpy()
        b = model(torch.tensor(crops), torch.tensor(q_in)).numpy()
    np.testing.assert_allclose(np.abs((a * b).sum(axis=1)), 1.0, atol=1e-4)
    int8 = quantize_model(fp32, tmp_path / "roll.int8.onnx", enforce=False).path
    assert RefinerSession(int8).contract.roll == "canonical"


def test_the_quarter_roll_turns_by_the_nearest_quarter_and_the_runtime_moves_the_same_pixels(tmp_path):
    """models.nets.fusion.quarter_roll turns each crop by the multiple of 90 degrees nearest the canonical turn (so the
    axis then points within 45 degrees of up; views already there are left alone), as the continuous turn would at
    those angles; refiner_rt.preprocess.quarter_roll gives the same pixels and rotations, and a quarter-roll network
    runs through the runtime as in PyTorch."""
    from models.nets.fusion import quarter_roll, turn_grid
    from refiner_rt import RefinerSession
    from refiner_rt.preprocess import quarter_roll as runtime_quarter

    q = _wxyz(Rotation.random(200, random_state=7)).double()
    crops = _smooth_crops(200, 16, 4)
    images = torch.tensor(crops).permute(0, 3, 1, 2).double()
    turned, q_turned = quarter_roll(images, q)
    assert np.degrees(roll_angle(q_turned).abs().max().item()) <= 45.0 + 1e-6
    k = torch.round(roll_angle(q) / (np.pi / 2)).remainder(4)
    assert set(k.tolist()) == {0.0, 1.0, 2.0, 3.0}
    assert torch.equal(turned[k == 0], images[k == 0])  # no turn, no resampling
    ref = torch.nn.functional.grid_sample(images, turn_grid(-k * np.pi / 2, 16), mode="bilinear",
                                          padding_mode="reflection", align_corners=False)
    assert (turned - ref).abs().max() < 1e-5
    turn = Rotation.from_quat(np.c_[q_turned[:, 1:], q_turned[:, :1]]) * Rotation.from_quat(np.c_[q[:, 1:], q[:, :1]]).inv()
    expected = Rotation.from_rotvec(np.c_[np.zeros((200, 2)), -k.numpy() * np.pi / 2])  # about the ray
    assert (turn * expected.inv()).magnitude().max() < 1e-9
    got, q_got = runtime_quarter(crops, q.numpy())
    assert np.array_equal(got, turned.permute(0, 2, 3, 1).numpy().astype(np.uint8))
    np.testing.assert_allclose(q_got, q_turned.numpy(), atol=1e-12)

    torch.manual_seed(2)
    model = models.build_refiner("fusion", input_size=32, roll="quarter", **SMALL).eval()
    path = export.export_model(model, tmp_path / "quarter.onnx", info={"rotation_frame": "ray"}).path
    sess = RefinerSession(path)
    assert sess.contract.roll == "quarter"
    crops32, q_in = _smooth_crops(40, 32, 5), _wxyz(Rotation.random(40, random_state=6))
    with torch.no_grad():
        ref_out = model(torch.tensor(crops32), q_in).double().numpy()
    out = sess.refine_crops(crops32, q_in.numpy().astype(np.float64)).q_out
    assert np.abs(np.abs((out * ref_out).sum(axis=1)) / np.linalg.norm(ref_out, axis=1) - 1).max() < 1e-6


def test_training_and_runtime_know_the_same_rolls():
    from models.nets.fusion import ROLLS
    from refiner_rt.metadata import ROLLS as CONTRACT_ROLLS
    from refiner_rt.preprocess import ROLL_TURNS

    assert set(ROLLS) == set(ROLL_TURNS) and CONTRACT_ROLLS == ("none", *ROLL_TURNS)


def test_roll_must_be_none_or_canonical():
    with pytest.raises(ValueError, match="roll"):
        models.build_refiner("fusion", roll="sideways", **SMALL)


def test_a_network_without_the_roll_goes_on_with_it_with_the_same_weights(tmp_path):
    """data_scaling --init accepts a checkpoint whose config differs only in roll, keeping every weight."""
    from types import SimpleNamespace

    from tests.bench_scripts import load_benchmark

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
    from models.train.recipe import TrainRecipe
    from models.train.run import load_init

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


def test_roll_bins_measures_the_roll_and_the_axis_to_the_ray_as_scipy_does():
    """benchmarks/studies/real_levers/roll_bins.py's bins: the angle of the object's z axis to the viewing ray (from
    SciPy's matrix) and the magnitude of the turn's roll angle."""
    from tests.bench_scripts import load_benchmark

    study = load_benchmark("studies/real_levers/roll_bins")
    r = Rotation.random(100, random_state=8)
    got = study.bins(_wxyz(r).double().numpy())
    z = r.as_matrix()[:, :, 2]
    np.testing.assert_allclose(got["axis"], np.degrees(np.arccos(np.abs(z[:, 2]))), atol=1e-3)  # float32 rows
    np.testing.assert_allclose(got["roll"], np.degrees(roll_angle(_wxyz(r).double()).abs().numpy()), atol=1e-4)


def test_the_runtime_turn_rounds_the_roll_so_a_small_change_of_the_pose_keeps_the_crop():
    """With ``step_deg`` the crop is turned by the roll angle rounded to that step, its rotation by the same angle:
    the turned axis points within half a step of up, and a 1e-4-degree change of the pose leaves the crop unchanged
    (unless the angle crosses a step) while the rotation moves by exactly that change."""
    import math

    from refiner_rt import quaternion as rq
    from refiner_rt.preprocess import ROLL_STEP_DEG, roll_angles
    from refiner_rt.preprocess import canonical_roll as runtime_roll

    q = _wxyz(Rotation.random(64, random_state=7)).double().numpy()
    crops = _smooth_crops(64, 48, 3)
    rng = np.random.default_rng(0)
    axes = rng.standard_normal((64, 3))
    q2 = rq.multiply(q, rq.from_axis_angle(axes / np.linalg.norm(axes, axis=1, keepdims=True), 1e-4))
    for step in (0.5, ROLL_STEP_DEG, 2.0):
        turned, q_turned = runtime_roll(crops, q, step_deg=step)
        turned2, q_turned2 = runtime_roll(crops, q2, step_deg=step)
        psi = np.degrees(roll_angles(q))
        residual = np.degrees(roll_angles(q_turned))
        np.testing.assert_allclose(residual, psi - step * np.round(psi / step), atol=1e-5)  # the rounded turn
        assert np.abs(residual).max() <= step / 2 + 1e-5
        crossing = np.floor(psi / step + 0.5) != np.floor(np.degrees(roll_angles(q2)) / step + 0.5)
        assert crossing.sum() == 0, step  # none of these 64 lies within 1e-4 degree of a step's edge
        np.testing.assert_array_equal(turned, turned2)
        moved = rq.geodesic_angle(q_turned, q_turned2)
        np.testing.assert_allclose(moved, 1e-4, rtol=1e-3)
    # step 0 is the exact turn: the axis up, and the crop resampled at the smallest change
    turned, q_turned = runtime_roll(crops, q, step_deg=0)
    assert np.abs(np.degrees(roll_angles(q_turned))).max() < 1e-5
    assert not np.array_equal(turned, runtime_roll(crops, q2, step_deg=0)[0])
    assert math.isclose(ROLL_STEP_DEG, 1.0)


def test_the_session_refuses_a_bad_roll_step():
    from refiner_rt import RefinerSession
    from tests.onnx_fixtures import constant_model

    for bad in (-1, 90, float("nan"), "1", True):
        with pytest.raises(ValueError, match="roll_step_deg must be a number of degrees in \\[0, 90\\)"):
            RefinerSession(constant_model([1, 0, 0, 0]), roll_step_deg=bad)


def test_a_network_goes_on_with_per_crop_input_norm_and_the_roll_at_once_with_the_same_weights():
    from models.nets.fusion import with_roll

    torch.manual_seed(0)
    plain = models.build_refiner("fusion", input_size=32, **SMALL)
    changed = with_roll(plain, {**plain.config, "roll": "canonical", "input_norm": "per_crop",
                                "crop_filter": "antialias"})
    assert changed.config["roll"] == "canonical" and changed.config["input_norm"] == "per_crop"
    assert changed.config["crop_filter"] == "antialias"
    assert changed.normalize.per_crop
    for name, value in plain.state_dict().items():
        assert torch.equal(changed.state_dict()[name], value), name
    wider = with_roll(plain, {**plain.config, "input_norm": "per_crop", "fuse_width": 64})
    assert wider is plain  # another network as well: left to the caller's checks, which refuse it
