"""export.recover: a float32 ONNX refiner turned back into a trainable checkpoint computes what the exported network
computed (reference: the PyTorch network before export, with non-trivial BatchNorm statistics)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from export import export_model
from export.recover import RecoverError, checkpoint_from_onnx
import models

CONFIG = {"conv_channels": [8, 16], "fuse_width": 32, "pose_widths": [16, 32], "head_widths": [16, 8],
          "input_size": 32}


def _inputs(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    images = rng.integers(0, 256, (n, 32, 32, 3), dtype=np.uint8)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    return images, q / np.linalg.norm(q, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A small fusion network with BatchNorm statistics and affine terms far from the identity, exported to fp32."""
    torch.manual_seed(0)
    net = models.build_refiner("fusion", **CONFIG)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            c = m.num_features
            m.running_mean.copy_(torch.randn(c) * 0.5)
            m.running_var.copy_(torch.rand(c) * 2 + 0.1)
            m.weight.data.copy_(torch.randn(c))  # some negative scales: the unfolding must keep their sign
            m.bias.data.copy_(torch.randn(c) * 0.3)
    net.eval()
    path = tmp_path_factory.mktemp("recover") / "net.onnx"
    export_model(net, path, info={"objects": ["003_cracker_box"], "train_noise": "uniform:0:30",
                                  "rotation_frame": "ray"})
    return net, path


def test_recovered_network_matches_the_network_before_export(exported, tmp_path):
    net, path = exported
    images, q = _inputs(64)
    out = checkpoint_from_onnx(path, tmp_path / "rec.pt", images, q)
    rec, info = models.load_checkpoint(out)
    assert rec.arch == "fusion" and rec.config == net.config
    assert info["objects"] == ["003_cracker_box"] and info["rotation_frame"] == "ray"
    assert info["recovered_from"]["file"] == "net.onnx" and info["recover_max_abs_dq"] <= 1e-4
    test_images, test_q = _inputs(64, seed=1)  # other inputs than the ones the statistics came from
    rec.eval()
    with torch.no_grad():
        want = net(torch.from_numpy(test_images), torch.from_numpy(test_q))
        got = rec(torch.from_numpy(test_images), torch.from_numpy(test_q))
    assert torch.allclose(got, want, atol=1e-4)
    # In train mode each BatchNorm normalises by the batch: on the batch the statistics came from, the same function.
    rec.train()
    with torch.no_grad():
        got_train = rec(torch.from_numpy(images), torch.from_numpy(q))
        want_stats_batch = net(torch.from_numpy(images), torch.from_numpy(q))
    assert torch.allclose(got_train, want_stats_batch, atol=1e-4)


def test_recovered_checkpoint_trains(exported, tmp_path):
    """The checkpoint is an ordinary one: its network takes optimisation steps and exports again."""
    _, path = exported
    images, q = _inputs(32)
    rec, _ = models.load_checkpoint(checkpoint_from_onnx(path, tmp_path / "rec.pt", images, q))
    rec.train()
    opt = torch.optim.Adam(rec.parameters(), lr=1e-3)
    before = [p.detach().clone() for p in rec.parameters()]
    loss = rec(torch.from_numpy(images), torch.from_numpy(q))[:, 0].mean()
    loss.backward()
    opt.step()
    assert any(not torch.equal(a, b) for a, b in zip(before, rec.parameters()))
    export_model(rec, tmp_path / "again.onnx")


def test_refuses_quantised_files_and_bad_inputs(exported, tmp_path):
    from export.quantize import quantize_model

    _, path = exported
    images, q = _inputs(32)
    int8 = tmp_path / "net.int8.onnx"
    quantize_model(path, int8)
    with pytest.raises(RecoverError, match="dynamic-int8 model; recover from the float32 file"):
        checkpoint_from_onnx(int8, tmp_path / "x.pt", images, q)
    with pytest.raises(RecoverError, match=r"images must be \(N >= 16, S, S, 3\) uint8"):
        checkpoint_from_onnx(path, tmp_path / "x.pt", images[:8], q[:8])
    with pytest.raises(RecoverError, match=r"q_in must be \(32, 4\)"):
        checkpoint_from_onnx(path, tmp_path / "x.pt", images, q[:, :3])
    assert not (tmp_path / "x.pt").exists()


def test_a_file_without_a_weight_the_network_has_is_named(exported, tmp_path):
    import onnx

    _, path = exported
    proto = onnx.load(str(path))
    kept = [t for t in proto.graph.initializer if t.name != "head.layers.0.weight"]
    del proto.graph.initializer[:]
    proto.graph.initializer.extend(kept)
    broken = tmp_path / "broken.onnx"
    onnx.save(proto, str(broken))
    images, q = _inputs(16)
    with pytest.raises(RecoverError, match=r"weights \['head.layers.0.weight'\] not in the file"):
        checkpoint_from_onnx(broken, tmp_path / "x.pt", images, q)
    assert not (tmp_path / "x.pt").exists()
