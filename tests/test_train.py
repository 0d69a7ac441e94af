"""Training loop, noise specs, CropSet and metrics: behaviour on small synthetic data."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import models
from models.data.cropset import CropSet
from models.data.noise import NoiseSpec, perturb
from models.evaluate.metrics import format_markdown, format_table, summarize_errors
from models.train.config import TrainConfig
from models.train.loop import train_refiner, validation_errors
from refiner_rt import quaternion as rq

TESTS = Path(__file__).parent


def tiny_model():
    return models.build_refiner("fusion", input_size=16, conv_channels=[4], fuse_width=16, pose_widths=[16], head_widths=[8])


def tiny_data(n=48, seed=0):
    rng = np.random.default_rng(seed)
    q = rq.sample_rotation_noise(n, "uniform", 0, 90, rng)
    crops = np.zeros((n, 16, 16, 3), np.uint8)
    crops[:, :8] = (q[:, None, None, 1:] * 120 + 128).astype(np.uint8)  # the image shows the rotation
    return CropSet(crops, q, np.array(["003_cracker_box", "011_banana"] * (n // 2)))


def test_noise_spec_parse_and_perturb_labels():
    spec = NoiseSpec.parse("uniform:0:30")
    assert str(spec) == "uniform:0:30" and str(NoiseSpec.parse("normal:10:5")) == "normal:10:5"
    for bad in ("uniform:0", "gauss:1:2", "uniform:a:b", "uniform:30:0"):
        with pytest.raises(ValueError):
            NoiseSpec.parse(bad)
    q_gt = rq.sample_rotation_noise(500, "uniform", 0, 180, np.random.default_rng(0))
    q_in, label = perturb(q_gt, spec, np.random.default_rng(1))
    # q_in * label = q_gt, and the input error is the noise angle
    np.testing.assert_allclose(rq.geodesic_angle(rq.multiply(q_in, label), q_gt), 0, atol=1e-6)
    err = rq.geodesic_angle(q_in, q_gt)
    assert err.max() <= 30 + 1e-9 and abs(err.mean() - 15) < 1.5


def test_twist_noise_turns_about_the_object_z_axis_only():
    from scipy.spatial.transform import Rotation

    spec = NoiseSpec.parse("twist:5:30")
    assert str(spec) == "twist:5:30"
    for bad in ("twist:30:5", "twist:-1:30", "twist:0:181"):
        with pytest.raises(ValueError, match="twist"):
            NoiseSpec.parse(bad)
    q_gt = rq.sample_rotation_noise(400, "uniform", 0, 180, np.random.default_rng(0))
    q_in, label = perturb(q_gt, spec, np.random.default_rng(1))
    np.testing.assert_allclose(rq.geodesic_angle(rq.multiply(q_in, label), q_gt), 0, atol=1e-6)
    # The error in the object's frame (q_gt^-1 q_in), by SciPy: a rotation vector along z, 5 to 30 degrees, both signs.
    w, x, y, z = rq.multiply(rq.inverse(q_gt), q_in).T
    rotvec = np.degrees(Rotation.from_quat(np.column_stack([x, y, z, w])).as_rotvec())
    np.testing.assert_allclose(rotvec[:, :2], 0, atol=1e-6)
    assert 5 - 1e-6 <= np.abs(rotvec[:, 2]).min() and np.abs(rotvec[:, 2]).max() <= 30 + 1e-6
    assert (rotvec[:, 2] > 0).mean() == pytest.approx(0.5, abs=0.1)


def test_cropset_validation_and_frames():
    data = tiny_data()
    assert data.objects == ["003_cracker_box", "011_banana"] and data.input_size == 16
    assert len(data.for_object("011_banana")) == 24
    with pytest.raises(ValueError, match="no crops of object"):
        data.for_object("035_power_drill")
    with pytest.raises(ValueError, match="uint8"):
        CropSet(np.zeros((2, 4, 4, 3), np.float32), np.zeros((2, 4)), ["a", "b"])
    with pytest.raises(ValueError, match="q_gt must be"):
        CropSet(np.zeros((2, 4, 4, 3), np.uint8), np.zeros((3, 4)), ["a", "b"])
    with pytest.raises(ValueError, match="needs the intrinsics"):
        data.q_gt_in("ray")
    q_ray = rq.sample_rotation_noise(len(data), "uniform", 0, 20, np.random.default_rng(3))
    with_ray = CropSet(data.crops, data.q_gt, data.obj_ids, q_ray=q_ray)
    np.testing.assert_allclose(rq.geodesic_angle(rq.multiply(q_ray, with_ray.q_gt_in("ray")), data.q_gt), 0, atol=1e-6)


def test_metrics_summary_matches_direct_computation():
    ids = np.array(["a"] * 3 + ["b"] * 2)
    out = np.array([1.0, 2.0, 6.0, 4.0, 12.0])
    inp = np.array([10.0, 10.0, 10.0, 20.0, 20.0])
    s = summarize_errors(ids, out, inp)
    assert s["objects"]["a"]["mean_deg"] == pytest.approx(3.0)
    assert s["objects"]["a"]["std_deg"] == pytest.approx(np.std([1, 2, 6]))
    assert s["objects"]["b"]["under_5_deg"] == pytest.approx(0.5)
    assert s["objects"]["b"]["under_10_deg"] == pytest.approx(0.5)
    assert s["average"]["mean_deg"] == pytest.approx((3.0 + 8.0) / 2)  # mean over objects, as the paper
    assert s["pooled"]["mean_deg"] == pytest.approx(out.mean())
    assert s["average"]["input_mean_deg"] == pytest.approx(15.0)
    assert "average" in format_table(s) and "| a |" in format_markdown(s)
    with pytest.raises(ValueError, match="equal lengths"):
        summarize_errors(ids, out[:2], inp)


def test_training_reduces_loss_and_keeps_best_epoch(tmp_path):
    torch.manual_seed(0)
    data = tiny_data(96)
    cfg = TrainConfig(epochs_mse=2, epochs_geodesic=6, batch_size=16, lr=3e-3, lr_schedule="cosine", warmup_epochs=0.5)
    res = train_refiner(tiny_model(), data, data.subset(np.arange(32)), cfg, progress=False, log_path=tmp_path / "log.jsonl")
    assert len(res.history) == 8
    vals = [r["val_mean_deg"] for r in res.history]
    assert res.best_val_deg == pytest.approx(min(vals)) and res.history[res.best_epoch - 1]["val_mean_deg"] == min(vals)
    assert min(vals) < vals[0]
    assert [r["loss_kind"] for r in res.history] == ["mse"] * 2 + ["geodesic"] * 6
    assert len((tmp_path / "log.jsonl").read_text().splitlines()) == 8


def test_bf16_training_learns_like_float32_and_keeps_float32_weights():
    """Mixed precision changes the arithmetic of the training forward pass only: the weights stay float32 and the
    run learns as the float32 one does (the same recipe, within a quarter of its error on this toy problem)."""
    data = tiny_data(96)
    val = data.subset(np.arange(32))
    runs = {}
    for bf16 in (False, True):
        torch.manual_seed(0)
        cfg = TrainConfig(epochs_mse=2, epochs_geodesic=6, batch_size=16, lr=3e-3, lr_schedule="cosine",
                          warmup_epochs=0.5, bf16=bf16)
        runs[bf16] = train_refiner(tiny_model(), data, val, cfg, progress=False)
    fp32, bf16 = runs[False], runs[True]
    assert all(v.dtype == torch.float32 for v in bf16.model.state_dict().values() if v.is_floating_point())
    assert any(not torch.equal(a, b) for a, b in zip(fp32.model.state_dict().values(), bf16.model.state_dict().values()))
    vals = [r["val_mean_deg"] for r in bf16.history]
    assert min(vals) < vals[0] - 5  # it learns
    assert abs(bf16.best_val_deg - fp32.best_val_deg) < 0.25 * fp32.best_val_deg
    with pytest.raises(ValueError, match="bf16 must be True or False"):
        TrainConfig(bf16="yes")


def test_weight_average_follows_the_ema_recurrence():
    """The average is ``a <- d * a + (1 - d) * w`` with ``d = min(decay, (1 + t) / (10 + t))``, written out here in
    float64 numpy; integer buffers (batch-norm's step counter) are copied, not averaged."""
    from models.train.loop import _WeightAverage

    torch.manual_seed(0)
    model = models.build_refiner("fusion", input_size=16, conv_channels=[4], fuse_width=16, pose_widths=[16],
                                 head_widths=[8])
    avg = _WeightAverage(model, 0.9)
    ref = {k: v.detach().double().numpy().copy() for k, v in model.state_dict().items() if v.is_floating_point()}
    rng = np.random.default_rng(1)
    for t in range(30):
        with torch.no_grad():
            for v in model.state_dict().values():
                if v.is_floating_point():
                    v.add_(torch.from_numpy(rng.normal(size=v.shape)).to(v.dtype))
                else:
                    v.add_(1)
        avg.update(model)
        d = min(0.9, (1 + t) / (10 + t))
        for k in ref:
            ref[k] = d * ref[k] + (1 - d) * model.state_dict()[k].double().numpy()
    assert avg.steps == 30
    for k, v in avg.state.items():
        if v.is_floating_point():
            np.testing.assert_allclose(v.double().numpy(), ref[k], rtol=1e-5, atol=1e-5)
        else:
            assert torch.equal(v, model.state_dict()[k])


def test_ema_training_validates_and_keeps_the_averaged_weights(tmp_path):
    data = tiny_data(96)
    val = data.subset(np.arange(32))
    cfg = TrainConfig(epochs_mse=2, epochs_geodesic=4, batch_size=16, lr=3e-3, ema=0.9)  # constant rate: resumable
    torch.manual_seed(0)
    res = train_refiner(tiny_model(), data, val, cfg, progress=False)
    assert all("val_raw_mean_deg" in r for r in res.history)
    assert any(r["val_raw_mean_deg"] != r["val_mean_deg"] for r in res.history)
    # the returned model is the averaged weights of the kept epoch: they score that epoch's validation error
    assert validation_errors(res.model, val, cfg).mean() == pytest.approx(res.best_val_deg, abs=1e-4)
    assert res.best_val_deg == min(r["val_mean_deg"] for r in res.history)
    # interrupted after 3 epochs and resumed: the same average as one uninterrupted run
    state = tmp_path / "state.pt"
    torch.manual_seed(0)
    train_refiner(tiny_model(), data, val, TrainConfig(**{**cfg.__dict__, "epochs_geodesic": 1}), state_path=state,
                  progress=False)
    resumed = train_refiner(tiny_model(), data, val, cfg, state_path=state, progress=False)
    for a, b in zip(res.history, resumed.history):
        assert a["val_mean_deg"] == pytest.approx(b["val_mean_deg"], abs=1e-3)
    for a, b in zip(res.model.state_dict().values(), resumed.model.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    for bad in (1.0, -0.1):
        with pytest.raises(ValueError, match="ema must be a decay in"):
            TrainConfig(ema=bad)


def test_decoupled_weight_decay_shrinks_the_weights():
    data = tiny_data(96)
    norms = {}
    for wd in (0.0, 5.0):
        torch.manual_seed(0)
        cfg = TrainConfig(epochs_mse=1, epochs_geodesic=2, batch_size=16, lr=3e-3, weight_decay=wd,
                          decoupled_weight_decay=True)
        res = train_refiner(tiny_model(), data, None, cfg, progress=False)
        norms[wd] = sum(float(p.detach().norm() ** 2) for p in res.model.parameters()) ** 0.5
    assert norms[5.0] < 0.9 * norms[0.0]
    with pytest.raises(ValueError, match="weight_decay must be >= 0"):
        TrainConfig(weight_decay=-1.0)
    with pytest.raises(ValueError, match="decoupled_weight_decay must be True or False"):
        TrainConfig(decoupled_weight_decay=1)


def test_in_plane_turn_matches_a_rotation_about_the_viewing_ray():
    """A crop centred on the principal point, turned by ``rotate_in_plane``, shows what the camera sees of the
    scene rotated by the returned ``q_z`` (checked with SciPy and a pinhole projection); masks turn with it."""
    from scipy.spatial.transform import Rotation

    from models.data.augment import rotate_in_plane

    size, f = 64, 80.0
    points = np.array([[0.12, -0.05, 1.0], [-0.08, 0.1, 1.2], [0.02, 0.15, 0.9]])

    def project(p):
        return f * p[:, :2] / p[:, 2:3] + size / 2  # pixel centres at +0.5: continuous coordinates

    images = np.zeros((len(points), size, size, 3), np.uint8)
    masks = np.zeros((len(points), size, size), np.uint8)
    for i, (u, v) in enumerate(project(points)):
        yy, xx = np.mgrid[:size, :size] + 0.5
        blob = (xx - u) ** 2 + (yy - v) ** 2 <= 2.0**2
        images[i][blob] = 255
        masks[i][blob] = 1
    gen = torch.Generator().manual_seed(3)
    out, out_masks, q_turn = rotate_in_plane(torch.from_numpy(images), torch.from_numpy(masks), 90.0, gen)
    assert out.dtype == torch.uint8 and out.shape == images.shape and q_turn.shape == (len(points), 4)
    angles = rq.geodesic_angle(q_turn, np.tile([1.0, 0, 0, 0], (len(points), 1)))  # degrees
    assert angles.max() <= 90 + 1e-9 and angles.max() > 10  # real turns, within the range asked for
    for i in range(len(points)):
        turned = Rotation.from_quat(rq.to_xyzw(q_turn[i])).apply(points[i : i + 1])
        u, v = project(turned)[0]
        w = out[i, :, :, 0].double().numpy()
        yy, xx = np.mgrid[:size, :size] + 0.5
        assert abs((w * xx).sum() / w.sum() - u) < 0.5 and abs((w * yy).sum() / w.sum() - v) < 0.5
        m = out_masks[i].numpy()
        assert m.sum() > 0 and abs(xx[m > 0].mean() - u) < 0.7 and abs(yy[m > 0].mean() - v) < 0.7


def test_in_plane_training_needs_the_ray_frame_and_learns():
    data = tiny_data(96)
    q_ray = rq.sample_rotation_noise(len(data), "uniform", 0, 20, np.random.default_rng(3))
    data = CropSet(data.crops, data.q_gt, data.obj_ids, q_ray=q_ray)
    with pytest.raises(ValueError, match="inplane needs rotation_frame='ray'"):
        TrainConfig(inplane=30.0)
    with pytest.raises(ValueError, match="inplane must be an angle"):
        TrainConfig(inplane=200.0, rotation_frame="ray")
    torch.manual_seed(0)
    cfg = TrainConfig(epochs_mse=2, epochs_geodesic=6, batch_size=16, lr=3e-3, lr_schedule="cosine",
                      warmup_epochs=0.5, rotation_frame="ray", inplane=30.0)
    res = train_refiner(tiny_model(), data, data.subset(np.arange(32)), cfg, progress=False)
    vals = [r["val_mean_deg"] for r in res.history]
    assert min(vals) < vals[0]


def test_resume_continues_where_it_stopped(tmp_path):
    data = tiny_data()
    state = tmp_path / "state.pt"
    torch.manual_seed(0)
    full = train_refiner(tiny_model(), data, data, TrainConfig(epochs_mse=1, epochs_geodesic=3, batch_size=16, lr=1e-3), progress=False)
    torch.manual_seed(0)
    train_refiner(tiny_model(), data, data, TrainConfig(epochs_mse=1, epochs_geodesic=1, batch_size=16, lr=1e-3),
                  state_path=state, progress=False)
    # "interrupted" after 2 of 4 epochs: resume with the full schedule
    torch.manual_seed(123)  # a different init must not matter: the state holds the weights
    resumed = train_refiner(tiny_model(), data, data, TrainConfig(epochs_mse=1, epochs_geodesic=3, batch_size=16, lr=1e-3),
                            state_path=state, progress=False)
    assert [r["epoch"] for r in resumed.history] == [1, 2, 3, 4]
    for a, b in zip(full.history, resumed.history):
        assert a["train_loss"] == pytest.approx(b["train_loss"], rel=1e-5)
    for k, v in full.model.state_dict().items():
        torch.testing.assert_close(v, resumed.model.state_dict()[k])


def test_train_config_rejects_bad_values():
    with pytest.raises(ValueError, match="noise"):
        TrainConfig(noise="uniform")
    with pytest.raises(ValueError, match="lr_schedule"):
        TrainConfig(lr_schedule="step")
    with pytest.raises(ValueError, match="epochs"):
        TrainConfig(epochs_mse=0, epochs_geodesic=0)
    with pytest.raises(ValueError, match="crops are 16 px"):
        train_refiner(models.build_refiner("fusion", input_size=32, conv_channels=[4], fuse_width=16, pose_widths=[16]),
                      tiny_data(), None, TrainConfig(), progress=False)


def test_ddp_two_processes_keep_identical_weights(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), str(TESTS.parent), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1"}
    # --standalone: the launcher binds its rendezvous store to a free port itself; a port picked here and passed
    # on could be taken by another process before the launcher binds it (seen once, beside another test run).
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           str(TESTS / "ddp_worker.py"), str(tmp_path)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    a = torch.load(tmp_path / "rank0.pt", weights_only=True)
    b = torch.load(tmp_path / "rank1.pt", weights_only=True)
    init = tiny_model().state_dict()
    changed = False
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)
        changed |= not torch.equal(a[k], init[k]) if k in init and a[k].is_floating_point() else False
    assert changed, "training did not change the weights"
