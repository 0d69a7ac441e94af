"""The runtime's own exception type for model files: one type to catch, whatever onnxruntime raised underneath."""

from __future__ import annotations

__all__ = ["ModelError", "ModelNotFoundError", "TRAINING_INSTALL"]

# What to do when a command of the training package (train, render, export, eval) runs where only the runtime is
# installed: the wheel carries refiner_rt alone; training lives in the source checkout.
TRAINING_INSTALL = ("it ships in the source checkout, not in the wheel: in a clone of refiner-rt, "
                    "pip install torch==2.13.0 && pip install -e '.[train]'")


class ModelError(ValueError):
    """A model that cannot be used: the file is unreadable, empty, not ONNX, or breaks the refiner-rt contract
    (metadata values, graph input/output names, element types, shapes, a dynamic batch axis), or the network
    fails or returns a non-finite rotation when it runs.

    The message names the model (its path, or ``<model bytes>``) and the cause. A ``ValueError`` subclass, so
    code that catches ``ValueError`` for bad input keeps working; onnxruntime's own exception types never escape
    :class:`refiner_rt.RefinerSession` (the original is kept as ``__cause__`` for debugging).
    """


class ModelNotFoundError(ModelError, FileNotFoundError):
    """The model path names no file: a :class:`ModelError` (so a ``ValueError``, as the README promises for bad
    input) and a ``FileNotFoundError`` (what code written for a missing file catches)."""
