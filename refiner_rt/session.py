"""RefinerSession: refine coarse object rotations from an RGB image with an exported ONNX refiner.

This is what robot code embeds. It needs numpy, OpenCV and onnxruntime only (never torch).

Conventions (design.md section 2):
    * quaternions are ``wxyz`` (scalar first, Hamilton product), float64, returned with ``w >= 0``;
    * rotations map object coordinates to camera coordinates (``x_cam = R @ x_obj + t``);
    * images are ``H x W x 3`` ``uint8`` **BGR** (what ``cv2.imread`` gives);
    * boxes are ``(x1, y1, x2, y2)`` in pixels, continuous coordinates (pixel ``i`` covers ``[i, i+1)``);
    * the refined rotation is ``q_refined = q_in * q_out`` (the paper's composition).

Speed (issue 6; ``benchmarks/profile_refine.py`` measures it): for up to :data:`SMALL_BATCH` boxes, the
per-box checks and the quaternion maths run on Python floats, since numpy's fixed cost per call (about a
microsecond per ufunc on a 4-vector) would otherwise exceed the network's time for the small models. The
operations and their order are those of :mod:`refiner_rt.quaternion`, so results are bit-identical to the
vectorised path used for larger batches. Crops go into a reusable uint8 batch, one ``cv2.warpAffine`` each.
A session is not meant to be called from several threads at once (it reuses its buffers): use one per thread.
"""

from __future__ import annotations

import logging
import math
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
from refiner_rt.geometry import (  # noqa: F401  (re-exported under their old names)
    MAX_VIEWS,
    VIEW_JITTER,
    _is_pinhole,
    _ray_rows,
    ray_quaternions,
    view_boxes,
    view_offsets,
)
from refiner_rt.preprocess import crop_to_square, resize_crop, validate_boxes, validate_image

__all__ = ["RefinerSession", "RefineResult", "SMALL_BATCH", "MAX_VIEWS", "available_cores", "ray_quaternions",
           "view_boxes", "view_offsets"]

log = logging.getLogger(__name__)

# Up to this many boxes, refine() validates and composes on Python floats (see the module docstring). Measured on
# the project's EPYC (checks + composition, warm caches): about 1.8 us per box on Python floats against about
# 90 us for the numpy path at any N up to 64, so the crossover is near 50 boxes.
SMALL_BATCH = 32
_MIN_NORM = 1e-12  # as refiner_rt.quaternion.as_quaternion: a smaller norm is a zero quaternion
def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, which cgroups and ``taskset`` restrict)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _unit_rows(rows: list) -> list | None:
    """:func:`refiner_rt.quaternion.normalize` on Python floats: unit norm, canonical sign ``w >= 0``.

    Same IEEE operations in the same order as the numpy version (sequential sum of squares, ``sqrt``,
    division, sign key ``w``, then ``x``, ``y``, ``z`` when ``w == 0``), so the results are identical.

    Args:
        rows: ``N`` lists ``[w, x, y, z]`` of floats.

    Returns:
        ``N`` lists ``[w, x, y, z]``, or None when a row is non-finite or has a norm below 1e-12 (the caller
        then takes the numpy path, which raises the detailed error).
    """
    isfinite = math.isfinite
    out = []
    for w, x, y, z in rows:
        if not (isfinite(w) and isfinite(x) and isfinite(y) and isfinite(z)):
            return None
        norm = math.sqrt(w * w + x * x + y * y + z * z)
        if norm < _MIN_NORM:
            return None
        w, x, y, z = w / norm, x / norm, y / norm, z / norm
        key = w if w != 0.0 else x if x != 0.0 else y if y != 0.0 else z
        out.append([-w, -x, -y, -z] if key < 0.0 else [w, x, y, z])
    return out


def _multiply_rows(a: list, b: list) -> list:
    """:func:`refiner_rt.quaternion.multiply` (Hamilton product ``a * b``, ``wxyz``) on Python floats, row by row."""
    out = []
    for (aw, ax, ay, az), (bw, bx, by, bz) in zip(a, b):
        out.append([
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ])
    return out


def _conjugate_rows(rows: list) -> list:
    """:func:`refiner_rt.quaternion.inverse` on Python floats: ``(w, -x, -y, -z)`` with canonical sign (same sign
    key as the numpy version; negation is exact, so the results are identical)."""
    out = []
    for w, x, y, z in rows:
        x, y, z = -x, -y, -z
        key = w if w != 0.0 else x if x != 0.0 else y if y != 0.0 else z
        out.append([-w, -x, -y, -z] if key < 0.0 else [w, x, y, z])
    return out


def _small_boxes(boxes, image_shape) -> tuple[np.ndarray, list] | None:
    """Fast path of :func:`validate_boxes` for up to :data:`SMALL_BATCH` well-formed ``(N, 4)`` numeric boxes.

    Returns:
        ``(float64 (N, 4) array, N lists [x1, y1, x2, y2])`` when every box is finite, non-empty and overlaps
        the image; None otherwise (the caller then runs :func:`validate_boxes`, which raises or converts).
    """
    arr = boxes if isinstance(boxes, np.ndarray) else np.asarray(boxes)
    if arr.dtype.kind not in "fiu" or arr.ndim != 2 or arr.shape[1] != 4 or len(arr) > SMALL_BATCH:
        return None
    arr = arr.astype(np.float64, copy=False)
    rows = arr.tolist()
    h, w = image_shape[0], image_shape[1]
    isfinite = math.isfinite
    for x1, y1, x2, y2 in rows:
        if not (isfinite(x1) and isfinite(y1) and isfinite(x2) and isfinite(y2)):
            return None
        if not (x1 < x2 and y1 < y2 and x2 > 0 and y2 > 0 and x1 < w and y1 < h):
            return None
    return arr, rows


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


def _validate_K(K) -> np.ndarray:
    arr = np.asarray(K)
    if arr.dtype.kind not in "fiu" or arr.shape != (3, 3):
        raise ValueError(f"K must be a (3, 3) numeric intrinsics matrix; got shape {arr.shape}, dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)  # read only from here on
    values = arr.ravel().tolist()  # checked on Python floats: a few times cheaper than numpy at 9 values
    if not all(map(math.isfinite, values)) or values[0] <= 0 or values[4] <= 0:
        raise ValueError(f"K must be finite with fx > 0 and fy > 0; got {arr.tolist()}")
    return arr


class RefinerSession:
    """An onnxruntime session for a refiner-rt ONNX model, with the crop rule and composition built in.

    Args:
        model: path to a ``.onnx`` file, or the model's bytes.
        threads: threads the network runs on (``>= 1``), the calling thread included; ``0`` means every
            core this process may run on (:func:`available_cores`, its CPU affinity). Cropping and the
            quaternion maths run on the calling thread. With 1 thread onnxruntime creates no thread pool.
            With more, its workers spin briefly after each call (measured up to 1.5x faster at batch 1 than
            without spinning on a 2-core EPYC), which takes CPU from other processes on those cores: on a
            machine shared with a renderer, prefer ``threads=1``.
        providers: onnxruntime execution providers, default ``["CPUExecutionProvider"]``. Each must
            be available: there is no silent fallback to another provider.
        session_options: an ``onnxruntime.SessionOptions`` to use instead of the defaults (then
            ``threads`` is ignored and :attr:`threads` reports the options' intra-op thread count).
        object_id: the YCB id (or object name) the caller will refine. When given, the model must have been
            trained for it (metadata ``objects``), so one object is never refined with another's model.

    Default session options, each chosen by measurement (``benchmarks/profile_refine.py`` and the notes in
    issue 6): graph optimisation ``ORT_ENABLE_ALL`` (``EXTENDED``/``BASIC`` ran 1.2-1.5x slower at batch 1;
    ALL adds layout transformations such as NCHWc convolutions), CPU memory arena and memory pattern on
    (turning them off never helped), sequential execution with one inter-op thread (the graph is a chain),
    intra-op spinning left at onnxruntime's default (on). IOBinding saved 0.5-3.5 us per call, within the
    noise of the whole call, so the plain ``run`` stays.

    Raises:
        FileNotFoundError: ``model`` is a path that does not exist.
        ValueError: the model lacks the refiner-rt metadata contract, declares one this runtime does
            not understand, or lacks the ``image`` / ``q_in`` inputs or ``q_out`` output; an unknown
            or unavailable provider; a bad ``threads`` value; ``object_id`` not among the model's objects.

    Example:
        >>> sess = RefinerSession("refiner.onnx", threads=1)
        >>> res = sess.refine(image_bgr, boxes_xyxy, q_in_wxyz)
        >>> res.q_refined  # (N, 4) wxyz, object-to-camera
    """

    def __init__(self, model, threads: int = 1, providers=None, session_options: ort.SessionOptions | None = None,
                 object_id: str | None = None):
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
        # 0 is resolved here: onnxruntime's own default counts physical cores and ignores the CPU affinity, so
        # under `taskset -c 0` it would start 2 threads on 1 core.
        self.threads = int(threads) or available_cores()

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
        else:
            self.threads = session_options.intra_op_num_threads
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
        self._q32 = np.zeros((0, 4), dtype=np.float32)
        self._output_names = [OUTPUT_QUATERNION]
        self._rgb = self.contract.channel_order == "RGB"
        self._ray = self.contract.rotation_frame == "ray"
        if object_id is not None:
            if not isinstance(object_id, str):
                raise TypeError(f"object_id must be a string such as '003_cracker_box'; got {type(object_id).__name__}")
            if object_id not in self.contract.objects:
                raise ValueError(f"object_id {object_id!r} is not an object this model was trained for "
                                 f"(metadata objects: {list(self.contract.objects)}); use that object's model")

    @classmethod
    def pretrained(cls, object_id: str, int8: bool = True, threads: int = 1, **kwargs) -> "RefinerSession":
        """A session on the refiner shipped for ``object_id`` (package data; nothing is downloaded).

        Args:
            object_id: YCB id, e.g. ``"003_cracker_box"`` (``refiner_rt.pretrained_models()`` lists them).
            int8: the INT8 model (default, fastest) or the fp32 one.
            threads: as for the constructor.
            **kwargs: ``providers`` / ``session_options``, as for the constructor.

        The shipped models were trained in the viewing-ray frame: pass the camera intrinsics ``K`` to
        :meth:`refine`. Their object frame is the YCB google_16k scan frame (see :mod:`refiner_rt.pretrained`).

        Raises:
            ValueError: no model ships for ``object_id`` (the message lists those that do).
        """
        from refiner_rt.pretrained import pretrained_model

        return cls(pretrained_model(object_id).path(int8=int8), threads=threads, object_id=object_id, **kwargs)

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
    def refine(self, image_bgr, boxes_xyxy, q_in_wxyz, iterations: int = 1, K=None, views: int = 1) -> RefineResult:
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
            views: refine each object from this many crops and average the corrections (chordal mean,
                :func:`refiner_rt.quaternion.mean`): the box itself and ``views - 1`` fixed jitters of it (window
                centre shifted and side scaled by up to 5%, as the training's ``--augment`` box jitter), in one
                batch of ``N * views`` crops. Costs ``views`` network passes per object; it suits models trained
                with ``--augment`` (``benchmarks/averaging.py`` measures it). ``1`` to :data:`MAX_VIEWS`.

        Returns:
            :class:`RefineResult` with ``q_refined`` ``(N, 4)`` float64 ``wxyz``, ``w >= 0``.

        Raises:
            ValueError / TypeError: a bad argument, named with what was expected and what was given.
        """
        image = validate_image(image_bgr, "image_bgr")
        small = _small_boxes(boxes_xyxy, image.shape)
        if small is None:
            boxes = validate_boxes(boxes_xyxy, image.shape, "boxes_xyxy")
            rows = boxes
        else:
            boxes, rows = small
        q_in, q_rows = self._q_in(q_in_wxyz, len(boxes), "boxes_xyxy")
        if type(iterations) is not int or iterations < 1:
            iterations = self._validate_iterations(iterations)
        if type(views) is not int or views != 1:
            views = self._validate_views(views)
            q_rows, small = None, None  # the averaged path runs on numpy arrays
        q_frame = None
        if self._ray:
            if K is None:
                raise ValueError(
                    "K is required: this model was trained in the viewing-ray frame (metadata rotation_frame='ray'); "
                    "pass the (3, 3) camera intrinsics"
                )
            K = _validate_K(K)
            if small is not None and _is_pinhole(K):
                q_frame = _ray_rows(K, rows)
            else:
                q_frame = ray_quaternions(K, boxes)
        elif K is not None:
            _validate_K(K)
        size, context = self.contract.input_size, self.contract.crop_context
        if views > 1:
            rows = view_boxes(boxes, views, context)
        crops = self._crops(len(rows))
        for i, box in enumerate(rows):
            crop_to_square(image, box, size, context, out=crops[i])
        return self._run(crops, q_in, q_rows, iterations, q_frame, views)

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
        q_in, q_rows = self._q_in(q_in_wxyz, len(crops_list), "crops_bgr")
        iterations = self._validate_iterations(iterations)
        crops = self._crops(len(crops_list))
        for i, c in enumerate(crops_list):
            if c.shape[0] == self.input_size and c.shape[1] == self.input_size:
                crops[i] = c
            else:
                resize_crop(np.ascontiguousarray(c), self.input_size, out=crops[i])
        return self._run(crops, q_in, q_rows, iterations, None)

    # ------------------------------------------------------------------ internals
    def _q_in(self, q, n: int, other: str) -> tuple[np.ndarray, list | None]:
        """Validated, unit, canonical ``q_in`` as ``(float64 (n, 4) array, rows)``; rows (Python floats) only for
        ``0 < n <= SMALL_BATCH`` well-formed input, else None. Anything unusual takes :meth:`_validate_q`, which
        raises the detailed errors."""
        if 0 < n <= SMALL_BATCH:
            arr = q if isinstance(q, np.ndarray) else np.asarray(q)
            if arr.dtype.kind in "fiu" and arr.shape == (n, 4):
                rows = _unit_rows(arr.astype(np.float64, copy=False).tolist())
                if rows is not None:
                    return np.array(rows), rows
        return self._validate_q(q, n, other), None

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

    @staticmethod
    def _validate_views(views) -> int:
        if isinstance(views, bool) or not isinstance(views, (int, np.integer)) or not 1 <= views <= MAX_VIEWS:
            raise ValueError(f"views must be an integer from 1 to {MAX_VIEWS}; got {views!r}")
        return int(views)

    def _crops(self, n: int) -> np.ndarray:
        """A view of ``n`` crops in the reusable uint8 batch buffer (grown when needed)."""
        if len(self._buffer) < n:
            s = self.input_size
            self._buffer = np.zeros((max(n, 2 * len(self._buffer)), s, s, 3), dtype=np.uint8)
        return self._buffer[:n]

    def _q_net(self, n: int) -> np.ndarray:
        """A view of ``n`` rows of the reusable float32 ``q_in`` input buffer (grown when needed)."""
        if len(self._q32) < n:
            self._q32 = np.zeros((max(n, 2 * len(self._q32)), 4), dtype=np.float32)
        return self._q32[:n]

    def _run(self, crops: np.ndarray, q_in: np.ndarray, q_rows: list | None, iterations: int, q_frame,
             views: int = 1) -> RefineResult:
        """Run the network ``iterations`` times and compose; Python floats when ``q_rows`` is given, else numpy.
        With ``views > 1`` (numpy only) ``crops`` holds ``views`` crops per object, object-major, and each pass
        averages their corrections."""
        n = len(q_in)
        if n == 0:
            empty = np.zeros((0, 4))
            return RefineResult(q_refined=empty, q_out=empty.copy(), q_in=empty.copy())
        if self._rgb:
            crops = np.ascontiguousarray(crops[..., ::-1])
        q_net = self._q_net(n * views)
        feed = {INPUT_IMAGE: crops, INPUT_QUATERNION: q_net}
        # The network sees rotations in its own frame; for "ray" models q_net = q_ray^-1 * q.
        # q_refined = q_prev * q_out holds in either frame (q_ray * (q_ray^-1 q) * q_out = q * q_out).
        q = q_in if q_rows is None else q_rows
        q_out = None
        frame_inv = None
        if q_frame is not None:
            if q_rows is None:
                frame_inv = rq.inverse(np.asarray(q_frame))
            else:
                frame_inv = _conjugate_rows(q_frame if isinstance(q_frame, list) else q_frame.tolist())
        for _ in range(iterations):
            if frame_inv is None:
                q_cur = q
            else:
                q_cur = rq.multiply(frame_inv, q) if q_rows is None else _multiply_rows(frame_inv, q)
            q_net[...] = q_cur if views == 1 else np.repeat(q_cur, views, axis=0)
            out = self._session.run(self._output_names, feed)[0]
            if views > 1:
                q_out = rq.mean(rq.normalize(out.astype(np.float64)).reshape(n, views, 4), axis=1)
                q = rq.normalize(rq.multiply(q, q_out))
            elif q_rows is not None:
                q_out = _unit_rows(out.tolist())
                if q_out is None:  # a non-finite or zero model output: rq.normalize raises the detailed error
                    rq.normalize(out.astype(np.float64))
                q = _unit_rows(_multiply_rows(q, q_out))  # unit * unit: always finite and unit
            else:
                q_out = rq.normalize(out.astype(np.float64))
                q = rq.normalize(rq.multiply(q, q_out))
        if q_rows is not None:
            q, q_out = np.array(q), np.array(q_out)
        return RefineResult(q_refined=q, q_out=q_out, q_in=q_in)

    def __repr__(self) -> str:
        src = str(self.model_path) if self.model_path else "<bytes>"
        c = self.contract
        return (
            f"RefinerSession({src!r}, arch={c.arch!r}, input_size={c.input_size}, "
            f"rotation_frame={c.rotation_frame!r}, threads={self.threads}, providers={self.providers})"
        )
