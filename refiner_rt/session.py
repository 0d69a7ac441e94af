"""RefinerSession: refine coarse object rotations from an RGB image with an exported ONNX refiner.

This is what robot code embeds. It needs numpy, OpenCV and onnxruntime only (never torch).

Conventions (design.md section 2):
    * quaternions are ``wxyz`` (scalar first, Hamilton product), float64, returned with ``w >= 0``;
    * rotations map object coordinates to camera coordinates (``x_cam = R @ x_obj + t``);
    * images are ``H x W x 3`` ``uint8`` **BGR** (what ``cv2.imread`` gives);
    * boxes are ``(x1, y1, x2, y2)`` in pixels, continuous coordinates (pixel ``i`` covers ``[i, i+1)``);
    * the refined rotation is ``q_refined = q_in * q_out`` (the paper's composition).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from refiner_rt import quaternion as rq
from refiner_rt.metadata import (
    INPUT_IMAGE,
    INPUT_QUATERNION,
    OUTPUT_QUATERNION,
    ModelContract,
    parse_metadata,
)
from refiner_rt.preprocess import crop_to_square, resize_crop, validate_boxes, validate_image

__all__ = ["RefinerSession", "RefineResult", "ray_quaternions"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RefineResult:
    """Output of :meth:`RefinerSession.refine`.

    Attributes:
        q_refined: ``(N, 4)`` float64, ``wxyz``, ``w >= 0``: refined object-to-camera rotations.
        q_out: ``(N, 4)`` float64, ``wxyz``, ``w >= 0``: the correction predicted at the last
            iteration (in the model's rotation frame; ``q_refined = q_prev * q_out``).
        q_in: ``(N, 4)`` float64, ``wxyz``, ``w >= 0``: the input rotations as used (unit-normalised).
    """

    q_refined: np.ndarray
    q_out: np.ndarray
    q_in: np.ndarray

    def __len__(self) -> int:
        return len(self.q_refined)


def ray_quaternions(K, boxes_xyxy) -> np.ndarray:
    """Rotations from the camera frame to the viewing-ray frame of each box centre.

    The ray frame is the camera frame rotated by the smallest rotation that takes the optical
    axis ``(0, 0, 1)`` onto the ray through the box centre, ``d = K^-1 (cx, cy, 1)``. A crop shows
    the object's rotation relative to that ray: ``q_ray_frame = q_ray^-1 * q_camera``.

    Args:
        K: ``(3, 3)`` camera intrinsics (pixels), ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, or
            ``(N, 3, 3)``, one per box.
        boxes_xyxy: ``(N, 4)`` boxes ``(x1, y1, x2, y2)`` in pixels.

    Returns:
        ``(N, 4)`` float64 ``wxyz`` unit quaternions ``q_ray`` (``R(q_ray) @ (0, 0, 1) = d / |d|``).
    """
    K = np.asarray(K, dtype=np.float64)
    boxes = np.asarray(boxes_xyxy, dtype=np.float64)
    # Continuous pixel centre -> the projection model's coordinates (pixel i centred at i + 0.5 in
    # continuous coordinates; K follows OpenCV's convention of pixel centres at integers).
    u = 0.5 * (boxes[:, 0] + boxes[:, 2]) - 0.5
    v = 0.5 * (boxes[:, 1] + boxes[:, 3]) - 0.5
    pts = np.stack([u, v, np.ones_like(u)], axis=-1)
    d = np.einsum("...ij,...j->...i", np.linalg.inv(K), pts)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    # Half-way quaternion: q = normalize(1 + z.d, z x d) rotates z onto d (d never opposite z here).
    z = np.array([0.0, 0.0, 1.0])
    q = np.concatenate([1.0 + d[:, 2:3], np.cross(z, d)], axis=-1)
    return rq.canonical(q / np.linalg.norm(q, axis=-1, keepdims=True))


def _validate_K(K) -> np.ndarray:
    arr = np.asarray(K)
    if arr.dtype.kind not in "fiu" or arr.shape != (3, 3):
        raise ValueError(f"K must be a (3, 3) numeric intrinsics matrix; got shape {arr.shape}, dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)) or arr[0, 0] <= 0 or arr[1, 1] <= 0:
        raise ValueError(f"K must be finite with fx > 0 and fy > 0; got {arr.tolist()}")
    return arr


class RefinerSession:
    """An onnxruntime session for a refiner-rt ONNX model, with the crop rule and composition built in.

    Args:
        model: path to a ``.onnx`` file, or the model's bytes.
        threads: intra-op threads for onnxruntime (``>= 1``); ``0`` lets onnxruntime pick (all cores).
        providers: onnxruntime execution providers, default ``["CPUExecutionProvider"]``. Each must
            be available: there is no silent fallback to another provider.
        session_options: an ``onnxruntime.SessionOptions`` to use instead of the defaults (then
            ``threads`` is ignored).

    Raises:
        FileNotFoundError: ``model`` is a path that does not exist.
        ValueError: the model lacks the refiner-rt metadata contract, declares one this runtime does
            not understand, or lacks the ``image`` / ``q_in`` inputs or ``q_out`` output; an unknown
            or unavailable provider; a bad ``threads`` value.

    Example:
        >>> sess = RefinerSession("refiner.onnx", threads=1)
        >>> res = sess.refine(image_bgr, boxes_xyxy, q_in_wxyz)
        >>> res.q_refined  # (N, 4) wxyz, object-to-camera
    """

    def __init__(self, model, threads: int = 1, providers=None, session_options: ort.SessionOptions | None = None):
        if isinstance(model, (bytes, bytearray)):
            source, self.model_path = bytes(model), None
        elif isinstance(model, (str, os.PathLike)):
            path = Path(model)
            if not path.is_file():
                raise FileNotFoundError(f"model file not found: {path}")
            source, self.model_path = str(path), path
        else:
            raise TypeError(f"model must be a path or the ONNX model's bytes; got {type(model).__name__}")
        if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 0:
            raise ValueError(f"threads must be an integer >= 0 (0 = all cores); got {threads!r}")
        self.threads = int(threads)

        available = ort.get_available_providers()
        providers = list(providers) if providers is not None else ["CPUExecutionProvider"]
        for p in providers:
            name = p[0] if isinstance(p, tuple) else p
            if name not in available:
                raise ValueError(f"provider {name!r} is not available in this onnxruntime; available: {available}")

        if session_options is None:
            session_options = ort.SessionOptions()
            session_options.intra_op_num_threads = self.threads
            session_options.inter_op_num_threads = 1
            session_options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
            session_options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
            session_options.log_severity_level = 3
        self._session = ort.InferenceSession(source, sess_options=session_options, providers=providers)

        self.contract: ModelContract = parse_metadata(self._session.get_modelmeta().custom_metadata_map)
        inputs = {i.name: i for i in self._session.get_inputs()}
        outputs = {o.name: o for o in self._session.get_outputs()}
        missing = [n for n in (INPUT_IMAGE, INPUT_QUATERNION) if n not in inputs]
        missing += [n for n in (OUTPUT_QUATERNION,) if n not in outputs]
        if missing:
            raise ValueError(
                f"model graph lacks {missing}: expected inputs {[INPUT_IMAGE, INPUT_QUATERNION]} and output "
                f"{OUTPUT_QUATERNION!r}; got inputs {sorted(inputs)} and outputs {sorted(outputs)}"
            )
        img = inputs[INPUT_IMAGE]
        if img.type != "tensor(uint8)":
            raise ValueError(f"model input {INPUT_IMAGE!r} must be uint8 (batch, S, S, 3); the graph declares {img.type}")
        s = self.contract.input_size
        declared = list(img.shape)
        if len(declared) != 4 or any(isinstance(d, int) and d != e for d, e in zip(declared[1:], (s, s, 3))):
            raise ValueError(
                f"model input {INPUT_IMAGE!r} has shape {declared}; the metadata's input_size={s} expects (batch, {s}, {s}, 3)"
            )
        self._buffer = np.zeros((0, s, s, 3), dtype=np.uint8)

    # ------------------------------------------------------------------ properties
    @property
    def metadata(self) -> dict:
        """The model's metadata contract as a dict (``arch``, ``input_size``, ``channel_order``, ...)."""
        return self.contract.as_dict()

    @property
    def input_size(self) -> int:
        """Side ``S`` of the square crop the network takes."""
        return self.contract.input_size

    @property
    def providers(self) -> list[str]:
        """The execution providers this session runs on."""
        return self._session.get_providers()

    def get_inputs(self):
        """The graph inputs (onnxruntime ``NodeArg``s)."""
        return self._session.get_inputs()

    def get_outputs(self):
        """The graph outputs (onnxruntime ``NodeArg``s)."""
        return self._session.get_outputs()

    # ------------------------------------------------------------------ public API
    def refine(self, image_bgr, boxes_xyxy, q_in_wxyz, iterations: int = 1, K=None) -> RefineResult:
        """Refine the rotations of ``N`` objects seen in one image.

        Args:
            image_bgr: ``H x W x 3`` ``uint8`` image, **BGR** channel order.
            boxes_xyxy: ``(N, 4)`` boxes ``(x1, y1, x2, y2)`` in pixels (float, continuous
                coordinates); each must be non-empty and overlap the image.
            q_in_wxyz: ``(N, 4)`` coarse object-to-camera rotations, ``wxyz``. Finite and
                non-zero; non-unit quaternions are normalised (their norm carries no rotation).
            iterations: feed the refined rotation back this many times (``>= 1``; the paper does 1).
            K: ``(3, 3)`` camera intrinsics. Required by models trained in the viewing-ray frame
                (metadata ``rotation_frame == "ray"``), unused by ``"camera"`` models.

        Returns:
            :class:`RefineResult` with ``q_refined`` ``(N, 4)`` float64 ``wxyz``, ``w >= 0``.

        Raises:
            ValueError / TypeError: a bad argument, named with what was expected and what was given.
        """
        image = validate_image(image_bgr, "image_bgr")
        boxes = validate_boxes(boxes_xyxy, image.shape, "boxes_xyxy")
        q_in = self._validate_q(q_in_wxyz, len(boxes), "boxes_xyxy")
        iterations = self._validate_iterations(iterations)
        q_frame = None
        if self.contract.rotation_frame == "ray":
            if K is None:
                raise ValueError(
                    "K is required: this model was trained in the viewing-ray frame (metadata rotation_frame='ray'); "
                    "pass the (3, 3) camera intrinsics"
                )
            q_frame = ray_quaternions(_validate_K(K), boxes)
        elif K is not None:
            _validate_K(K)
        crops = self._crops(len(boxes))
        ctx = self.contract.crop_context
        for i in range(len(boxes)):
            crop_to_square(image, boxes[i], self.input_size, ctx, out=crops[i])
        return self._run(crops, q_in, iterations, q_frame)

    def refine_crops(self, crops_bgr, q_in_wxyz, iterations: int = 1) -> RefineResult:
        """Refine rotations from crops that are already cut out (the crop window, any size).

        Each crop is resampled to ``S x S`` with the crop rule's warp (``context = 1``: the crop is
        taken to be the whole window; a non-square crop is zero-padded on its short side).

        Args:
            crops_bgr: a sequence of ``h x w x 3`` ``uint8`` BGR crops, or an ``(N, h, w, 3)`` array.
            q_in_wxyz: ``(N, 4)`` coarse rotations, ``wxyz``, in the model's rotation frame (for a
                ``"ray"`` model: relative to each crop's viewing ray; use :meth:`refine` with ``K``
                to have that done for you).
            iterations: refinement iterations (``>= 1``).

        Returns:
            :class:`RefineResult`.
        """
        if isinstance(crops_bgr, np.ndarray) and crops_bgr.ndim == 4:
            crops_list = list(crops_bgr)
        elif isinstance(crops_bgr, (list, tuple)):
            crops_list = list(crops_bgr)
        else:
            raise TypeError(
                "crops_bgr must be a list of (h, w, 3) uint8 BGR arrays or an (N, h, w, 3) uint8 array; "
                f"got {type(crops_bgr).__name__}"
                + (f" of shape {crops_bgr.shape}" if isinstance(crops_bgr, np.ndarray) else "")
            )
        for i, c in enumerate(crops_list):
            validate_image(c, f"crops_bgr[{i}]")
        q_in = self._validate_q(q_in_wxyz, len(crops_list), "crops_bgr")
        iterations = self._validate_iterations(iterations)
        crops = self._crops(len(crops_list))
        for i, c in enumerate(crops_list):
            if c.shape[0] == self.input_size and c.shape[1] == self.input_size:
                crops[i] = c
            else:
                resize_crop(np.ascontiguousarray(c), self.input_size, out=crops[i])
        return self._run(crops, q_in, iterations, None)

    # ------------------------------------------------------------------ internals
    def _validate_q(self, q, n: int, other: str) -> np.ndarray:
        q = rq.as_quaternion(q, "q_in_wxyz")
        if q.ndim == 1:
            q = q[None]
        if q.ndim != 2:
            raise ValueError(f"q_in_wxyz must have shape (N, 4), wxyz; got shape {q.shape}")
        if len(q) != n:
            raise ValueError(f"q_in_wxyz has {len(q)} rotations but {other} has {n}: expected one rotation per box")
        return rq.normalize(q)

    @staticmethod
    def _validate_iterations(iterations) -> int:
        if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 1:
            raise ValueError(f"iterations must be an integer >= 1; got {iterations!r}")
        return int(iterations)

    def _crops(self, n: int) -> np.ndarray:
        """A view of ``n`` crops in the reusable uint8 batch buffer (grown when needed)."""
        if len(self._buffer) < n:
            s = self.input_size
            self._buffer = np.zeros((max(n, 2 * len(self._buffer)), s, s, 3), dtype=np.uint8)
        return self._buffer[:n]

    def _run(self, crops: np.ndarray, q_in: np.ndarray, iterations: int, q_frame) -> RefineResult:
        n = len(q_in)
        if n == 0:
            empty = np.zeros((0, 4))
            return RefineResult(q_refined=empty, q_out=empty.copy(), q_in=empty.copy())
        if self.contract.channel_order == "RGB":
            crops = crops[..., ::-1]
        crops = np.ascontiguousarray(crops)
        # The network sees rotations in its own frame; for "ray" models q_net = q_ray^-1 * q.
        # q_refined = q_prev * q_out holds in either frame (q_ray * (q_ray^-1 q) * q_out = q * q_out).
        q = q_in
        q_out = None
        for _ in range(iterations):
            q_net = q if q_frame is None else rq.multiply(rq.inverse(q_frame), q)
            out = self._session.run(
                [OUTPUT_QUATERNION],
                {INPUT_IMAGE: crops, INPUT_QUATERNION: q_net.astype(np.float32)},
            )[0]
            q_out = rq.normalize(out.astype(np.float64))
            q = rq.normalize(rq.multiply(q, q_out))
        return RefineResult(q_refined=q, q_out=q_out, q_in=q_in)

    def __repr__(self) -> str:
        src = str(self.model_path) if self.model_path else "<bytes>"
        c = self.contract
        return (
            f"RefinerSession({src!r}, arch={c.arch!r}, input_size={c.input_size}, "
            f"rotation_frame={c.rotation_frame!r}, threads={self.threads}, providers={self.providers})"
        )
