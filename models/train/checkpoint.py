"""Checkpoint files: save a refiner with its config and training info, load it back safely (docs/design.md §5).

A checkpoint is a ``torch.save`` dict::

    {"format": "refiner-rt/1", "arch": str, "config": dict, "state_dict": {name: tensor}, "info": dict}

``config`` rebuilds the network through the registry (``build_refiner(arch, **config)``); ``info`` holds
JSON-able training facts that the exporter copies into the ONNX metadata (``objects``: list of YCB ids,
``train_noise``: e.g. ``"uniform:0:30"``, ``rotation_frame``: ``"camera"`` or ``"ray"``) and anything else.
A checkpoint is untrusted input: it is loaded with ``torch.load(..., weights_only=True)``, never unpickled freely.
"""

from __future__ import annotations

import json
import logging
import os
import re
import secrets
from pathlib import Path

import torch

from refiner_rt.metadata import file_sha256  # re-exported: the checkpoint's hash in exported models
from models.nets.blocks import Refiner
from models.nets.registry import get_refiner_class

__all__ = ["CHECKPOINT_FORMAT", "file_sha256", "load_checkpoint", "new_temp_file_beside", "save_checkpoint"]

logger = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "refiner-rt/1"
_KEYS = ("format", "arch", "config", "state_dict", "info")


def _require_json(value, what: str) -> None:
    try:
        json.dumps(value, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be JSON-serialisable (str, number, bool, None, list, dict); {exc}") from None


def new_temp_file_beside(path) -> Path:
    """A new, empty hidden file in ``path``'s folder for an atomic write: fill it, then ``os.replace`` it onto ``path``.

    Created like any new file (``open(..., "x")``), so it gets the user's umask, typically 0644; a
    ``tempfile.mkstemp`` file is 0600, and ``os.replace`` would carry that mode over to the written model.

    Raises:
        OSError: the folder does not exist or is not writable (e.g. ``PermissionError``).
    """
    path = Path(path)
    while True:
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
        try:
            with open(tmp, "xb"):
                return tmp
        except FileExistsError:  # a 32-bit random name taken: draw another
            continue


def save_checkpoint(model: Refiner, path, **info) -> Path:
    """Write ``model`` (weights, arch, config) and ``info`` to ``path`` atomically.

    Args:
        model: a registered refiner (has ``arch`` and ``config``).
        path: destination file (conventionally ``*.pt``); parent directories must exist.
        **info: JSON-able training facts, e.g. ``objects=["003_cracker_box"]``, ``train_noise="uniform:0:30"``,
            ``rotation_frame="camera"``, ``epoch=15``.

    Returns:
        The path written.

    Raises:
        ValueError: ``model`` is not a registered refiner, or ``config`` / ``info`` is not JSON-able.
    """
    arch = getattr(model, "arch", None)
    config = getattr(model, "config", None)
    if not isinstance(model, Refiner) or not arch or not isinstance(config, dict):
        raise ValueError(f"model must be a registered refiner (models.build_refiner); got {type(model).__name__}")
    get_refiner_class(arch)
    _require_json(config, "model.config")
    _require_json(info, "checkpoint info")
    payload = {
        "format": CHECKPOINT_FORMAT,
        "arch": arch,
        "config": config,
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "info": info,
    }
    path = Path(path)
    tmp = new_temp_file_beside(path)
    try:
        torch.save(payload, tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    logger.info("saved %s checkpoint to %s", arch, path)
    return path


def load_checkpoint(path) -> tuple[Refiner, dict]:
    """Load a checkpoint written by :func:`save_checkpoint`.

    Args:
        path: checkpoint file.

    Returns:
        ``(model, info)``: the rebuilt refiner on the CPU in eval mode with the saved weights (move it with
        ``model.to(device)``), and the saved info dict.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: not a weights-only torch file, wrong ``format``, unknown ``arch``, invalid ``config``, or a
            ``state_dict`` that does not fit the architecture; the message names the file and the field.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError... for non-checkpoints
        # Keep torch's reason (e.g. "Unsupported global: ...") but not its advice to retry with weights_only=False.
        found = re.search(r"Unsupported global: GLOBAL [\w.]+", str(exc))
        reason = found.group(0) if found else ""
        raise ValueError(
            f"{path}: not a refiner-rt checkpoint: torch.load(weights_only=True) cannot read it "
            f"({type(exc).__name__}{': ' + reason if reason else ''}); a checkpoint holds only tensors and plain values"
        ) from None
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path}: a checkpoint must be a dict with keys {list(_KEYS)}; got {type(ckpt).__name__}")
    fmt = ckpt.get("format")
    if fmt != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: field 'format' is {fmt!r}; expected {CHECKPOINT_FORMAT!r}")
    missing = [k for k in _KEYS if k not in ckpt]
    if missing:
        raise ValueError(f"{path}: missing field(s) {missing}; a checkpoint has {list(_KEYS)}")
    arch, config, info = ckpt["arch"], ckpt["config"], ckpt["info"]
    try:
        cls = get_refiner_class(arch)
    except ValueError as exc:
        raise ValueError(f"{path}: field 'arch': {exc}") from None
    if not isinstance(config, dict):
        raise ValueError(f"{path}: field 'config' must be a dict; got {type(config).__name__}")
    if not isinstance(info, dict):
        raise ValueError(f"{path}: field 'info' must be a dict; got {type(info).__name__}")
    # Init-only keys (e.g. VGG-M's init_state_dict path) are skipped: the checkpoint's weights replace them.
    build_config = {k: (None if k in cls.INIT_ONLY_KEYS else v) for k, v in config.items()}
    try:
        model = cls(**build_config)
    except ValueError as exc:
        raise ValueError(f"{path}: field 'config': {exc}") from None
    model.config = {**model.config, **{k: config[k] for k in cls.INIT_ONLY_KEYS if k in config}}
    state = ckpt["state_dict"]
    if not isinstance(state, dict):
        raise ValueError(f"{path}: field 'state_dict' must be a dict of tensors; got {type(state).__name__}")
    try:
        result = model.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # shape mismatches
        raise ValueError(f"{path}: field 'state_dict' does not fit arch {arch!r} with this config: {exc}") from None
    if result.missing_keys or result.unexpected_keys:
        raise ValueError(
            f"{path}: field 'state_dict' does not fit arch {arch!r} with this config: "
            f"missing {result.missing_keys[:5]}{'...' if len(result.missing_keys) > 5 else ''}, "
            f"unexpected {result.unexpected_keys[:5]}{'...' if len(result.unexpected_keys) > 5 else ''}"
        )
    model.eval()
    return model, info

