"""Recover a trainable checkpoint from a float32 refiner ONNX file: the reverse of export, for training on from it.

Why: the checkpoints behind the shipped refiners do not survive from one build to the next (only the ONNX files ship),
and training on from a trained model is cheaper than training anew (``benchmarks/studies/scene_count``: starting a
larger run from a trained model was worth about 0.3 degrees at the same wall time). The fp32 file holds every weight
under its PyTorch name, except that the exporter folded each eval-mode BatchNorm into the convolution before it
(``export.onnx_export``: ``W' = W * g / s``, ``b' = (b - m) * g / s + beta``). Folding loses ``g``, ``s``, ``m`` and
``beta`` apart, so they are rebuilt ("unfolded") such that the network computes the same function:

    conv weight ``W'``, conv bias 0; per channel, over a batch of real crops, ``mu`` and ``var`` of ``conv(x; W')``;
    BatchNorm ``running_mean = mu``, ``running_var = var``, ``weight = sqrt(var + eps)``, ``bias = mu + b'``.

In eval mode that BatchNorm gives ``conv(x; W') + b'`` exactly, for any ``mu`` and ``var``; in train mode it normalises
by the batch's statistics, which are close to ``mu`` and ``var`` when the crops are like the training crops, so
training goes on from (nearly) the same function instead of from a network whose layers suddenly see other scales.
The recovered network is checked against the ONNX file with onnxruntime (max ``|dq|`` over the given crops) before
the checkpoint is written.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper

__all__ = ["RecoverError", "RECOVER_TOL", "checkpoint_from_onnx"]

RECOVER_TOL = 1e-4  # max |dq| between the recovered network (eval mode) and the ONNX file, as export's fp32 bound


class RecoverError(ValueError):
    """The ONNX file cannot be turned back into a checkpoint (quantised, unknown weights, or no parity)."""


def _load(onnx_path: Path) -> tuple[dict, dict]:
    model = onnx.load(str(onnx_path))
    props = {p.key: p.value for p in model.metadata_props}
    weights = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    return props, weights


def checkpoint_from_onnx(onnx_path, out, images: np.ndarray, q_in: np.ndarray, *, tol: float = RECOVER_TOL) -> Path:
    """Write a ``refiner-rt/1`` checkpoint (``models.save_checkpoint``) that computes what ``onnx_path`` computes.

    Args:
        onnx_path: a float32 refiner ONNX file exported by this project (metadata ``quantization`` "none").
        out: the checkpoint to write (``*.pt``).
        images: ``(N, S, S, 3)`` uint8 NHWC crops in the model's channel order, like its training crops (N >= 16),
            as the graph takes them (for a model with the canonical roll, turned: ``export.quantize.dataset_calibration``
            gives them so): the batch whose per-channel statistics rebuild the BatchNorm layers, then the parity
            inputs.
        q_in: ``(N, 4)`` float32 coarse rotations, ``wxyz``, in the model's rotation frame.
        tol: largest ``max |dq|`` allowed between the recovered network and the file.

    Returns:
        ``out``. The checkpoint's ``info`` holds the file's ``objects``, ``train_noise``, ``rotation_frame``, its
        ``data`` spec (the split it was trained on), ``recovered_from`` (file name and sha256) and ``recover_max_abs_dq``.

    Raises:
        RecoverError: a quantised or foreign file, a weight the network does not have (or lacks), or parity above
            ``tol`` (nothing is written then).
    """
    import onnxruntime as ort

    import models
    from refiner_rt.metadata import file_sha256

    onnx_path, out = Path(onnx_path), Path(out)
    props, weights = _load(onnx_path)
    if props.get("quantization", "none") != "none":
        raise RecoverError(f"{onnx_path}: a {props['quantization']} model; recover from the float32 file")
    if "arch" not in props or "model_config" not in props:
        raise RecoverError(f"{onnx_path}: no 'arch'/'model_config' metadata; not a refiner-rt export")
    images = np.ascontiguousarray(images)
    q_in = np.ascontiguousarray(q_in, dtype=np.float32)
    if images.dtype != np.uint8 or images.ndim != 4 or images.shape[3] != 3 or len(images) < 16:
        raise RecoverError(f"images must be (N >= 16, S, S, 3) uint8; got {images.shape} {images.dtype}")
    if q_in.shape != (len(images), 4):
        raise RecoverError(f"q_in must be ({len(images)}, 4) wxyz; got {q_in.shape}")

    config = json.loads(props["model_config"])
    # The file holds the network without the canonical roll (the runtime turns the crops before the graph): the
    # weights are recovered on that network, from crops as the graph takes them, and the roll is put back at the end.
    model = models.build_refiner(props["arch"], **{**config, **({"roll": "none"} if "roll" in config else {})})
    state = model.state_dict()
    bns = {name: m for name, m in model.named_modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)}
    modules = dict(model.named_modules())
    folded = {}  # BatchNorm name -> the conv before it
    for bn_name in bns:
        parent, _, idx = bn_name.rpartition(".")
        if not idx.isdigit():
            raise RecoverError(f"{onnx_path}: BatchNorm {bn_name} is not in a Sequential; cannot find its convolution")
        conv_name = f"{parent}.{int(idx) - 1}" if parent else str(int(idx) - 1)
        if not isinstance(modules.get(conv_name), torch.nn.Conv2d):
            raise RecoverError(f"{onnx_path}: BatchNorm {bn_name} does not follow a convolution; cannot unfold it")
        folded[bn_name] = conv_name
    bn_keys = {f"{bn}.{k}" for bn in bns for k in ("weight", "bias", "running_mean", "running_var",
                                                   "num_batches_tracked")}
    wanted = [k for k in state if k not in bn_keys]
    missing = [k for k in wanted if k not in weights]
    if missing:
        raise RecoverError(f"{onnx_path}: weights {missing} not in the file (an export by another version?)")
    new_state = {k: torch.from_numpy(np.array(weights[k])).to(state[k].dtype) for k in wanted}
    for k, v in new_state.items():
        if v.shape != state[k].shape:
            raise RecoverError(f"{onnx_path}: weight {k} has shape {tuple(v.shape)}; the network has {tuple(state[k].shape)}")
    conv_bias = {conv: new_state[f"{conv}.bias"].clone() for conv in folded.values()}
    for conv in folded.values():
        new_state[f"{conv}.bias"] = torch.zeros_like(conv_bias[conv])
    model.load_state_dict({**state, **new_state})
    model.eval()

    def set_stats(bn_name):
        def hook(module, args):
            x = args[0].detach().double()
            mu, var = x.mean(dim=(0, 2, 3)), x.var(dim=(0, 2, 3), unbiased=False)
            module.running_mean.copy_(mu.float())
            module.running_var.copy_(var.float())
            module.weight.data.copy_(torch.sqrt(var + module.eps).float())
            module.bias.data.copy_((mu + conv_bias[folded[bn_name]].double()).float())
            module.num_batches_tracked.zero_()
        return hook

    handles = [bns[name].register_forward_pre_hook(set_stats(name)) for name in folded]
    with torch.no_grad():
        model(torch.from_numpy(images), torch.from_numpy(q_in))
    for h in handles:
        h.remove()

    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    ref = sess.run(["q_out"], {"image": images, "q_in": q_in})[0]
    with torch.no_grad():
        got = model(torch.from_numpy(images), torch.from_numpy(q_in)).numpy()
    # q and -q are one rotation: compare up to sign per row.
    dq = np.minimum(np.abs(got - ref).max(axis=1), np.abs(got + ref).max(axis=1)).max()
    if not dq <= tol:
        raise RecoverError(f"{onnx_path}: the recovered network differs from the file by max |dq| {dq:.3g} > {tol:g}")
    info = {
        "objects": json.loads(props.get("objects", "[]")),
        "train_noise": props.get("train_noise", "uniform:0:30"),
        "rotation_frame": props.get("rotation_frame", "camera"),
        "recovered_from": {"file": onnx_path.name, "sha256": file_sha256(onnx_path),
                           "model_version": props.get("model_version"), "recipe": props.get("recipe")},
        "recover_max_abs_dq": float(dq),
    }
    if props.get("data"):
        info["data"] = json.loads(props["data"])
    from models.nets.fusion import with_roll

    return models.save_checkpoint(with_roll(model, config).train(), out, **info)
