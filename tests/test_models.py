"""models: the registry (every arch: shape, unit norm, finite, gradients), configs, inputs, checkpoints."""

import json

import numpy as np
import pytest
from torch import nn
import torch

import models
from models.nets import registry
from models.nets.blocks import IMAGENET_MEAN_RGB, IMAGENET_STD_RGB, InputNormalization, Refiner
from models.nets.vggm import MIN_INPUT_SIZE
import models.train.losses

# Small hidden widths keep the tests fast; the default sizes are tested once in test_default_*.
SMALL_COMMON = {"pose_widths": [8, 16], "head_widths": [16, 8]}
SMALL_CONFIGS = {
    "shallow": {**SMALL_COMMON, "input_size": 32, "conv_channels": [4, 4]},
    "vggm": {**SMALL_COMMON, "input_size": 64, "fc_widths": [32, 32]},
}


def small_config(arch: str) -> dict:
    """A fast config for ``arch``; an architecture without an entry in SMALL_CONFIGS is tested at its defaults."""
    return dict(SMALL_CONFIGS.get(arch, {}))


def random_inputs(model, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` random uint8 NHWC crops and unit quaternions (wxyz) for ``model``."""
    g = torch.Generator().manual_seed(seed)
    s = model.input_size
    image = torch.randint(0, 256, (n, s, s, 3), dtype=torch.uint8, generator=g)
    q = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1)
    return image, q


ARCHS = models.list_refiners()


def test_registry_has_paper_archs():
    assert {"shallow", "vggm"} <= set(ARCHS)
    assert models.get_refiner_class("shallow").arch == "shallow"


@pytest.mark.parametrize("arch", ARCHS)
def test_forward_shape_unit_norm_finite(arch):
    torch.manual_seed(0)
    model = models.build_refiner(arch, **small_config(arch)).eval()
    image, q = random_inputs(model, 5)
    with torch.no_grad():
        out = model(image, q)
    assert out.shape == (5, 4) and out.dtype == torch.float32
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out.norm(dim=1), torch.ones(5))
    assert model.arch == arch and model.channel_order == "BGR"
    assert model.input_size == small_config(arch).get("input_size", model.default_config()["input_size"])


@pytest.mark.parametrize("arch", ARCHS)
def test_gradient_flows_to_every_parameter(arch):
    torch.manual_seed(0)
    model = models.build_refiner(arch, **small_config(arch)).train()
    image, q = random_inputs(model, 4)
    label = torch.nn.functional.normalize(torch.randn(4, 4), dim=1)
    models.train.losses.geodesic_loss(model(image, q), label).backward()
    for name, p in model.named_parameters():
        assert p.grad is not None, f"no gradient reached {name}"
        assert torch.isfinite(p.grad).all(), f"non-finite gradient in {name}"
    assert sum(p.grad.abs().sum() for p in model.parameters()) > 0


@pytest.mark.parametrize("arch", ARCHS)
def test_config_is_json_and_rebuilds(arch):
    model = models.build_refiner(arch, **small_config(arch))
    config = json.loads(json.dumps(model.config))
    assert config == model.config
    rebuilt = models.build_refiner(arch, **config)
    assert rebuilt.config == model.config
    assert rebuilt.state_dict().keys() == model.state_dict().keys()


def test_default_shallow_is_the_paper_network():
    model = models.build_refiner("shallow").eval()
    assert model.input_size == 64 and model.channel_order == "BGR"
    convs = [m for m in model.features if isinstance(m, nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size, c.padding) for c in convs] == [
        (3, 16, (5, 5), (2, 2)),
        (16, 16, (5, 5), (2, 2)),
    ]
    assert sum(isinstance(m, nn.BatchNorm2d) for m in model.features) == 2
    assert sum(isinstance(m, nn.MaxPool2d) for m in model.features) == 2
    pose = [(m.in_features, m.out_features) for m in model.pose.modules() if isinstance(m, nn.Linear)]
    head = [(m.in_features, m.out_features) for m in model.head.modules() if isinstance(m, nn.Linear)]
    assert pose == [(4, 64), (64, 512), (512, 4096)]
    assert head == [(8192, 1024), (1024, 256), (256, 64), (64, 4)]
    image, q = random_inputs(model, 1)
    with torch.no_grad():
        assert model.features(model.normalize(image)).shape == (1, 4096)
        assert model(image, q).shape == (1, 4)


def test_default_vggm_is_vggm_conv1_to_fc7():
    model = models.build_refiner("vggm").eval()
    f = model.features
    assert model.input_size == 224
    assert (f.conv1.out_channels, f.conv1.kernel_size, f.conv1.stride) == (96, (7, 7), (2, 2))
    assert (f.conv2.out_channels, f.conv2.kernel_size, f.conv2.stride, f.conv2.padding) == (256, (5, 5), (2, 2), (1, 1))
    assert [getattr(f, f"conv{i}").out_channels for i in (3, 4, 5)] == [512, 512, 512]
    assert (f.norm1.size, f.norm1.alpha, f.norm1.beta, f.norm1.k) == (5, 5e-4, 0.75, 2.0)
    assert (f.fc6.in_features, f.fc6.out_features, f.fc7.out_features) == (6 * 6 * 512, 4096, 4096)
    assert model.head.layers[0].in_features == 8192
    image, q = random_inputs(model, 1)
    with torch.no_grad():
        assert f[:15](model.normalize(image)).shape == (1, 512, 6, 6)
        assert model(image, q).shape == (1, 4)


def test_vggm_lrn_matches_torch_reference():
    x = torch.randn(2, 96, 7, 7)
    lrn = models.nets.vggm.LocalResponseNorm(5, 5e-4, 0.75, 2.0)
    torch.testing.assert_close(lrn(x), nn.LocalResponseNorm(5, 5e-4, 0.75, 2.0)(x))


def test_input_normalisation_known_value_and_channel_order():
    image = torch.tensor([10, 128, 250], dtype=torch.uint8).view(1, 1, 1, 3).expand(1, 2, 2, 3)
    mean, std = np.array(IMAGENET_MEAN_RGB), np.array(IMAGENET_STD_RGB)
    bgr = InputNormalization("BGR", IMAGENET_MEAN_RGB, IMAGENET_STD_RGB)(image)
    rgb = InputNormalization("RGB", IMAGENET_MEAN_RGB, IMAGENET_STD_RGB)(image)
    assert bgr.shape == (1, 3, 2, 2)  # NCHW
    np.testing.assert_allclose(bgr[0, :, 0, 0], (np.array([10, 128, 250]) / 255 - mean[::-1]) / std[::-1], rtol=1e-5)
    np.testing.assert_allclose(rgb[0, :, 0, 0], (np.array([10, 128, 250]) / 255 - mean) / std, rtol=1e-5)


def test_rgb_model_on_rgb_image_equals_bgr_model_on_bgr_image():
    torch.manual_seed(0)
    bgr_model = models.build_refiner("shallow", **small_config("shallow")).eval()
    rgb_model = models.build_refiner("shallow", **small_config("shallow"), channel_order="RGB").eval()
    rgb_model.load_state_dict(bgr_model.state_dict())
    # The first conv sees channels in its own order: reorder its input weights to match.
    with torch.no_grad():
        rgb_model.features[0].weight.copy_(bgr_model.features[0].weight.flip(1))
    image_bgr, q = random_inputs(bgr_model, 3)
    with torch.no_grad():
        torch.testing.assert_close(rgb_model(image_bgr.flip(-1), q), bgr_model(image_bgr, q))


@pytest.mark.parametrize(
    ("arch", "config", "match"),
    [
        ("shallow", {"hidden": 3}, r"unknown config key\(s\) \['hidden'\].*known keys"),
        ("shallow", {"channel_order": "bgr"}, "channel_order"),
        ("shallow", {"input_size": 30}, "multiple of 4"),
        ("shallow", {"pose_widths": [8, 0]}, "pose_widths"),
        ("shallow", {"std_rgb": [0.2, 0.0, 0.2]}, "std_rgb"),
        ("shallow", {"crop_context": 0.5}, "crop_context"),
        ("vggm", {"input_size": MIN_INPUT_SIZE - 1}, f"at least {MIN_INPUT_SIZE}"),
        ("vggm", {"dropout": 1.0}, "dropout"),
        ("vggm", {"fc_widths": [32]}, "fc_widths"),
    ],
)
def test_invalid_config_raises_value_error(arch, config, match):
    with pytest.raises(ValueError, match=match):
        models.build_refiner(arch, **config)


def test_unknown_arch_lists_registered():
    with pytest.raises(ValueError, match=r"unknown refiner arch 'resnet'.*shallow"):
        models.build_refiner("resnet")


def test_new_arch_is_a_few_lines():
    try:

        @models.register_refiner("tiny_test")
        class TinyRefiner(Refiner):
            DEFAULT_CONFIG = {"input_size": 16}

            def build_feature_stage(self, config):
                return nn.Sequential(nn.Conv2d(3, 2, 4, stride=4), nn.Flatten()), 2 * 4 * 4

        assert "tiny_test" in models.list_refiners()
        model = models.build_refiner("tiny_test", **SMALL_COMMON).eval()
        assert model.arch == "tiny_test"
        image, q = random_inputs(model, 2)
        assert model(image, q).shape == (2, 4)
        with pytest.raises(ValueError, match="already registered"):
            models.register_refiner("tiny_test")(TinyRefiner)
    finally:
        registry._REGISTRY.pop("tiny_test", None)


def test_bad_inputs_raise_value_error():
    model = models.build_refiner("shallow", **small_config("shallow")).eval()
    image, q = random_inputs(model, 2)
    with pytest.raises(ValueError, match="uint8"):
        model(image.float(), q)
    with pytest.raises(ValueError, match=r"\(N, 32, 32, 3\).*got \(2, 3, 32, 32\)"):
        model(image.permute(0, 3, 1, 2).contiguous(), q)
    with pytest.raises(ValueError, match=r"q_in must be a float tensor \(N, 4\)"):
        model(image, q[:, :3])
    with pytest.raises(ValueError, match="same N"):
        model(image, q[:1])


# ---------------------------------------------------------------- checkpoints
@pytest.mark.parametrize("arch", ARCHS)
def test_checkpoint_round_trip(arch, tmp_path):
    torch.manual_seed(0)
    model = models.build_refiner(arch, **small_config(arch)).eval()
    path = models.save_checkpoint(model, tmp_path / "ckpt.pt", objects=["003_cracker_box"], train_noise="uniform:0:30")
    loaded, info = models.load_checkpoint(path)
    assert info == {"objects": ["003_cracker_box"], "train_noise": "uniform:0:30"}
    assert loaded.arch == arch and loaded.config == model.config and not loaded.training
    image, q = random_inputs(model, 3)
    with torch.no_grad():
        torch.testing.assert_close(loaded(image, q), model(image, q), rtol=0, atol=0)
    raw = torch.load(path, weights_only=True)
    assert set(raw) == {"format", "arch", "config", "state_dict", "info"} and raw["format"] == "refiner-rt/1"


def _write(path, payload):
    torch.save(payload, path)
    return path


def _valid_payload():
    model = models.build_refiner("shallow", **small_config("shallow"))
    return {"format": "refiner-rt/1", "arch": "shallow", "config": model.config, "state_dict": model.state_dict(), "info": {}}


class _NotAllowed:
    pass


@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda p: {**p, "format": "other/2"}, r"field 'format' is 'other/2'; expected 'refiner-rt/1'"),
        (lambda p: {**p, "arch": "resnet"}, r"field 'arch': unknown refiner arch 'resnet'"),
        (lambda p: {k: v for k, v in p.items() if k != "info"}, r"missing field\(s\) \['info'\]"),
        (lambda p: {**p, "config": {**p["config"], "conv_channels": [8, 8]}}, r"field 'state_dict' does not fit"),
        (lambda p: {**p, "state_dict": {}}, r"field 'state_dict' does not fit.*missing"),
        (lambda p: {**p, "config": {**p["config"], "wat": 1}}, r"field 'config': unknown config key"),
        (lambda p: [1, 2], "must be a dict"),
        (lambda p: {**p, "info": _NotAllowed()}, r"weights_only"),
    ],
)
def test_bad_checkpoint_raises_value_error_naming_file_and_field(tmp_path, mutate, match):
    path = _write(tmp_path / "bad.pt", mutate(_valid_payload()))
    with pytest.raises(ValueError, match=match) as err:
        models.load_checkpoint(path)
    assert str(path) in str(err.value)


def test_not_a_torch_file_and_missing_file(tmp_path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint at all")
    with pytest.raises(ValueError, match="not a refiner-rt checkpoint") as err:
        models.load_checkpoint(junk)
    assert str(junk) in str(err.value)
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        models.load_checkpoint(tmp_path / "nope.pt")


def test_save_checkpoint_rejects_non_json_info_and_non_refiners(tmp_path):
    model = models.build_refiner("shallow", **small_config("shallow"))
    with pytest.raises(ValueError, match="JSON"):
        models.save_checkpoint(model, tmp_path / "a.pt", objects={1, 2})
    with pytest.raises(ValueError, match="registered refiner"):
        models.save_checkpoint(nn.Linear(2, 2), tmp_path / "b.pt")
    assert list(tmp_path.iterdir()) == []


def test_vggm_init_state_dict_and_checkpoint_independence(tmp_path):
    torch.manual_seed(0)
    cfg = small_config("vggm")
    donor = models.build_refiner("vggm", **cfg)
    conv_only = {k: v for k, v in donor.features.state_dict().items() if k.startswith("conv")}
    init_file = tmp_path / "vggm_conv.pt"
    torch.save(conv_only, init_file)
    model = models.build_refiner("vggm", **cfg, init_state_dict=str(init_file))
    for k, v in conv_only.items():
        torch.testing.assert_close(model.features.state_dict()[k], v)
    ckpt = models.save_checkpoint(model, tmp_path / "ckpt.pt")
    init_file.unlink()  # the checkpoint must not need the init file any more
    loaded, _ = models.load_checkpoint(ckpt)
    assert loaded.config["init_state_dict"] == str(init_file)
    torch.testing.assert_close(loaded.features.conv1.weight, conv_only["conv1.weight"])


def test_vggm_init_state_dict_rejects_bad_files(tmp_path):
    cfg = small_config("vggm")
    with pytest.raises(ValueError, match="file not found"):
        models.build_refiner("vggm", **cfg, init_state_dict=str(tmp_path / "missing.pt"))
    bad_key = tmp_path / "bad_key.pt"
    torch.save({"conv9.weight": torch.zeros(1)}, bad_key)
    with pytest.raises(ValueError, match=r"unexpected key\(s\) \['conv9.weight'\]"):
        models.build_refiner("vggm", **cfg, init_state_dict=str(bad_key))
    bad_shape = tmp_path / "bad_shape.pt"
    torch.save({"conv1.weight": torch.zeros(96, 3, 5, 5)}, bad_shape)
    with pytest.raises(ValueError, match=r"'conv1.weight' has shape \(96, 3, 5, 5\); expected \(96, 3, 7, 7\)"):
        models.build_refiner("vggm", **cfg, init_state_dict=str(bad_shape))


def test_fusion_quaternion_to_matrix_matches_scipy():
    from scipy.spatial.transform import Rotation

    from models.nets.fusion import quaternion_to_matrix_flat

    rot = Rotation.random(200, random_state=3)
    q_wxyz = np.roll(rot.as_quat(), 1, axis=1)  # scipy is xyzw
    got = quaternion_to_matrix_flat(torch.tensor(q_wxyz, dtype=torch.float64)).numpy().reshape(-1, 3, 3)
    np.testing.assert_allclose(got, rot.as_matrix(), atol=1e-12)
    # q and -q are the same rotation, and give the same matrix.
    got_neg = quaternion_to_matrix_flat(torch.tensor(-q_wxyz, dtype=torch.float64)).numpy().reshape(-1, 3, 3)
    np.testing.assert_allclose(got_neg, got, atol=1e-12)


def test_fusion_absolute_output_is_the_exact_correction():
    from scipy.spatial.transform import Rotation

    from models.nets.fusion import correction_from_matrices, matrix_from_6d, quaternion_to_matrix_flat

    r_in, r_abs = Rotation.random(100, random_state=4), Rotation.random(100, random_state=5)
    q = correction_from_matrices(torch.tensor(r_in.as_matrix()), torch.tensor(r_abs.as_matrix())).numpy()
    ref = np.roll((r_in.inv() * r_abs).as_quat(), 1, axis=1)
    ref *= np.sign(ref[:, :1])
    np.testing.assert_allclose(q, ref, atol=1e-9)
    # Gram-Schmidt of 6 numbers gives a proper rotation; of a rotation's first two columns, that rotation.
    m = matrix_from_6d(torch.randn(50, 6, dtype=torch.float64))
    np.testing.assert_allclose((m.transpose(1, 2) @ m).numpy(), np.broadcast_to(np.eye(3), (50, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(torch.linalg.det(m).numpy(), 1.0, atol=1e-12)
    cols = torch.tensor(r_abs.as_matrix())[:, :, :2].transpose(1, 2).reshape(100, 6)
    np.testing.assert_allclose(matrix_from_6d(cols).numpy(), r_abs.as_matrix(), atol=1e-12)
    # In the model: q_in * q_out equals the rotation the head estimated.
    model = models.build_refiner("fusion", output="absolute", input_size=16, conv_channels=[4], fuse_width=16,
                                 pose_widths=[16], head_widths=[8]).eval()
    image = torch.randint(0, 256, (5, 16, 16, 3), dtype=torch.uint8)
    q_in = torch.tensor(np.roll(Rotation.random(5, random_state=6).as_quat(), 1, axis=1), dtype=torch.float32)
    with torch.no_grad():
        q_out = model(image, q_in).double().numpy()
        a = model.features(model.normalize(image))
        b = model.pose(quaternion_to_matrix_flat(q_in))
        r_est = matrix_from_6d(model.head(torch.cat([a, b, a * b], dim=1))).double().numpy()
    assert (q_out[:, 0] >= 0).all()
    q_refined = Rotation.from_quat(np.roll(q_in.double().numpy(), -1, axis=1)) * Rotation.from_quat(np.roll(q_out, -1, axis=1))
    np.testing.assert_allclose(q_refined.as_matrix(), r_est, atol=1e-4)


def test_per_crop_normalisation_equals_numpy_reference_and_ignores_gain_and_offset():
    rng = np.random.default_rng(3)
    image = rng.integers(40, 160, size=(2, 16, 16, 3)).astype(np.uint8)
    norm = InputNormalization("BGR", IMAGENET_MEAN_RGB, IMAGENET_STD_RGB, per_crop=True)
    got = norm(torch.from_numpy(image)).numpy()
    x = image.transpose(0, 3, 1, 2) / 255.0  # the reference: per crop and channel, population std
    want = (x - x.mean(axis=(2, 3), keepdims=True)) / (x.std(axis=(2, 3), keepdims=True) + 0.02)
    np.testing.assert_allclose(got, want, atol=1e-5)
    # a per-channel gain and offset (exposure, white balance, contrast) that stays inside 0..255: same input to the
    # network up to the eps (std / (std + eps) moves by about 4% here) and the uint8 rounding; the dataset
    # normalisation moves by more than 0.3
    gain, offset = np.array([1.4, 1.0, 0.8]), np.array([-20.0, 5.0, 10.0])
    shifted = np.clip(np.rint(image * gain + offset), 0, 255).astype(np.uint8)
    assert shifted.min() > 0 and shifted.max() < 255
    moved = norm(torch.from_numpy(shifted)).numpy()
    assert np.abs(moved - got).max() < 0.1
    plain = InputNormalization("BGR", IMAGENET_MEAN_RGB, IMAGENET_STD_RGB)
    assert np.abs(plain(torch.from_numpy(shifted)).numpy() - plain(torch.from_numpy(image)).numpy()).max() > 0.3


def test_fusion_input_norm_config():
    model = models.build_refiner("fusion", input_norm="per_crop", **small_config("fusion"))
    assert model.config["input_norm"] == "per_crop" and model.normalize.per_crop
    assert models.build_refiner("fusion").config["input_norm"] == "dataset"
    with pytest.raises(ValueError, match="input_norm"):
        models.build_refiner("fusion", input_norm="gray")
    image, q = random_inputs(model, 3)
    out = model.eval()(image, q)
    assert out.shape == (3, 4) and torch.isfinite(out).all()
    flat = torch.full_like(image, 77)  # a flat crop: zero spread, finite by the eps
    assert torch.isfinite(model(flat, q)).all()
