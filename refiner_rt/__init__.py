"""refiner-rt runtime: refine a coarse object rotation from an RGB crop with an ONNX refiner.

Runtime dependencies are numpy, OpenCV, onnxruntime and click only; this package never imports torch.
Conventions: quaternions ``wxyz`` (Hamilton), rotations object-to-camera, images ``H x W x 3`` uint8 BGR,
boxes ``(x1, y1, x2, y2)`` pixels, angles in degrees.
"""

from __future__ import annotations

__version__ = "0.1.0"

from refiner_rt.errors import ModelError, ModelNotFoundError

__all__ = ["ModelError", "ModelNotFoundError", "Refiner", "load", "RefinerSession", "RefineResult", "RefinerCascade",
           "RefinerTracker", "SETTLE_DEG", "PoseEstimator", "PoseEstimate", "quaternion", "pretrained_models",
           "__version__"]


def __getattr__(name):
    # Lazy: `import refiner_rt.quaternion` (used by training code) need not load onnxruntime.
    if name in ("RefinerSession", "RefineResult", "SETTLE_DEG"):
        from refiner_rt import session

        return getattr(session, name)
    if name in ("Refiner", "load"):
        from refiner_rt import refiner

        return getattr(refiner, name)
    if name == "RefinerCascade":
        from refiner_rt.cascade import RefinerCascade

        return RefinerCascade
    if name == "RefinerTracker":
        from refiner_rt.tracker import RefinerTracker

        return RefinerTracker
    if name in ("PoseEstimator", "PoseEstimate"):
        from refiner_rt import estimate

        return getattr(estimate, name)
    if name == "pretrained_models":
        from refiner_rt.pretrained import pretrained_models

        return pretrained_models
    if name == "quaternion":
        import importlib

        return importlib.import_module("refiner_rt.quaternion")
    raise AttributeError(f"module 'refiner_rt' has no attribute {name!r}")
