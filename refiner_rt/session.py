"""RefinerSession: refine coarse object rotations from an RGB image with an exported ONNX refiner.

This is what robot code embeds. It needs numpy, OpenCV and onnxruntime only (never torch).

Conventions (docs/design.md §2):
    * quaternions are ``wxyz`` (scalar first, Hamilton product), float64, returned with ``w >= 0``;
    * rotations map object coordinates to camera coordinates (``x_cam = R @ x_obj + t``);
    * images are ``H x W x 3`` ``uint8`` **BGR** (what ``cv2.imread`` gives);
    * boxes are ``(x1, y1, x2, y2)`` in pixels, continuous coordinates (pixel ``i`` covers ``[i, i+1)``);
    * the refined rotation is ``q_refined = q_in * q_out`` (the paper's composition).

Speed (``benchmarks/profile_refine.py`` measures it): for up to :data:`SMALL_BATCH` boxes, the
per-box checks and the quaternion maths run on Python floats, since numpy's fixed cost per call would otherwise
exceed the network's time for the small models (``benchmarks/studies/speed``, "Choices in the runtime"). The
operations and their order are those of :mod:`refiner_rt.quaternion`, so results are bit-identical to the
vectorised path used for larger batches. Crops go into a reusable uint8 batch, one ``cv2.warpAffine`` each.

Threads: one session may be shared by any number of threads (a multi-threaded ROS 2 executor, a web server).
``refine()`` and ``refine_crops()`` called concurrently return exactly what the same calls return one after the
other: the reused crop and ``q_in`` buffers are per thread (:class:`threading.local`), and onnxruntime's ``run``
is thread-safe. Each calling thread keeps its own buffers (at most :data:`MAX_BATCH` crops) until it ends.

Limits, each refused with a ``ValueError`` naming the argument: :data:`MAX_BATCH` crops per call (boxes x views),
:data:`MAX_ITERATIONS` iterations, :data:`MAX_VIEWS` views, box coordinates within
:data:`refiner_rt.preprocess.MAX_BOX_COORDINATE` pixels, ``K`` in pinhole form within :data:`K_MAX_ABS`. Any
finite input inside them gives a finite unit rotation. A model that cannot be read or breaks the contract raises
:class:`refiner_rt.ModelError` when it is loaded (never an onnxruntime exception type).
"""

from __future__ import annotations

import logging
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from refiner_rt import quaternion as rq
from refiner_rt.errors import ModelError, ModelNotFoundError
from refiner_rt.metadata import (
    INPUT_IMAGE,
    INPUT_QUATERNION,
    OUTPUT_QUATERNION,
    ModelContract,
    check_graph,
    parse_metadata,
)
from refiner_rt.checks import (  # noqa: F401  (limits re-exported: refiner_rt.session.MAX_BATCH and the like)
    K_MAX_ABS,
    K_MIN_FOCAL,
    MAX_BATCH,
    MAX_ITERATIONS,
    MAX_VIEWS,
    SMALL_BATCH,
    as_wxyz,
    boxes_rows,
    check_batch,
    check_coarse_rows,
    check_principal_point,
    validate_boxes,
    validate_D,
    validate_image,
    validate_iterations,
    validate_K,
    validate_rotations,
    validate_settle,
    validate_threads,
    validate_views,
)
from refiner_rt.geometry import ray_quaternion_rows, ray_quaternions, view_boxes, view_offsets
from refiner_rt.preprocess import ROLL_STEP_DEG, ROLL_TURNS, canonical_roll, crop_to_square, resize_crop
from refiner_rt.distortion import crop_undistorted, undistort_boxes

__all__ = ["RefinerSession", "RefineResult", "ModelError", "DISABLED_OPTIMIZERS", "default_session_options",
           "SMALL_BATCH", "MAX_BATCH", "MAX_ITERATIONS", "MAX_VIEWS", "SETTLE_DEG", "SCORE_SCALE_DEG", "K_MAX_ABS",
           "K_MIN_FOCAL", "available_cores", "settle_keeps", "ray_quaternions", "view_boxes", "view_offsets"]

log = logging.getLogger(__name__)

# refine(settle_deg=...): a later pass is kept only where it turns a result by more than this. Chosen on rendered
# scenes the model card does not score (ycb9_calib_s22) among 1, 1.5, 2, 3, 5 and 8 degrees, for the smallest mean of
# the errors from U(0, 30) inputs, from U(30, 60) inputs and from the true pose: the coarse refiner's minimum; the
# cascade's criterion is flat from 1 to 3 degrees (benchmarks/studies/far_inputs).
SETTLE_DEG = 2.0
# RefineResult.score = exp(-(degrees moved) / SCORE_SCALE_DEG): 0.97 for a pass that moves 1 degree, 0.72 for 10.
# Calibrated on rendered scenes the model card does not score (ycb9_calib_s22; benchmarks/studies/score_calibration):
# with two passes the score is then the share of refined rotations within SCORE_WITHIN_DEG of the truth (the least
# Brier score among scales 5-60 degrees, inputs U(0, 30) and U(30, 90) degrees off).
SCORE_SCALE_DEG = 30.0
SCORE_WITHIN_DEG = 10.0
# onnxruntime graph transformers every session turns off. QDQPropagationTransformer moves the first QuantizeLinear
# of a static-qdq-int8-conv model above the first block's max-pool, which then runs on uint8 in NCHW, much slower
# than the fp32 max-pool it replaces (benchmarks/studies/int8_convs). Max-pooling and reshapes commute with
# quantisation, so the outputs are the same bit for bit (tests/test_quantize_conv.py checks both static schemes);
# fp32 and dynamic-int8 models have no QuantizeLinear to move.
DISABLED_OPTIMIZERS = ("QDQPropagationTransformer",)
def default_session_options(threads: int, **config_entries: str) -> ort.SessionOptions:
    """The ``onnxruntime.SessionOptions`` a :class:`RefinerSession` on ``threads`` threads uses (the class docstring
    says why each is chosen), plus extra ``add_session_config_entry`` settings, e.g.
    ``default_session_options(2, **{"session.intra_op.allow_spinning": "0"})``: for callers who change one option
    and keep the rest."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3
    for key, value in config_entries.items():
        options.add_session_config_entry(key, value)
    return options


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, which cgroups and ``taskset`` restrict)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@dataclass(frozen=True)
class RefineResult:
    """Output of :meth:`RefinerSession.refine`.

    Attributes:
        q_refined: ``(N, 4)`` float64, ``wxyz``, ``w >= 0``: refined object-to-camera rotations.
        q_out: ``(N, 4)`` float64, ``wxyz``, ``w >= 0``: the correction predicted at the last
            iteration (in the model's rotation frame; ``q_refined = q_prev * q_out``); with ``settle_deg``, at
            the last pass kept for that object.
        q_in: ``(N, 4)`` float64, ``wxyz``, ``w >= 0``: the input rotations as used (unit-normalised).
        views_spread_deg: ``(N,)`` float64 degrees with ``views > 1``: the mean angle between each view's correction
            and their average, at the last pass kept; None with one view.

    Confidence: :attr:`score`, from the last pass's correction (:attr:`correction_deg`) and the views' spread.
    """

    q_refined: np.ndarray
    q_out: np.ndarray
    q_in: np.ndarray
    views_spread_deg: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.q_refined)

    @property
    def correction_deg(self) -> np.ndarray:
        """``(N,)`` float64 degrees: the angle of :attr:`q_out`, how far the last pass kept turned each rotation."""
        q = np.asarray(self.q_out, dtype=np.float64).reshape(-1, 4)
        return np.degrees(2.0 * np.arctan2(np.linalg.norm(q[:, 1:], axis=1), np.abs(q[:, 0])))

    @property
    def score(self) -> np.ndarray:
        """``(N,)`` float64 in ``(0, 1]``: a confidence per refined rotation, higher for a smaller error:
        ``exp(-(correction_deg + views_spread_deg) / SCORE_SCALE_DEG)`` (the spread 0 with one view).

        From what the refinement computed anyway: a refiner that has reached its answer turns the rotation little
        on a further pass, and views of one object that agree give corrections that agree. With ``iterations >= 2``
        the correction is the last pass's movement, the signal to use, and the score is calibrated: on rendered
        scenes (shipped INT8 refiners, two passes, one view, inputs U(0, 30) and U(30, 90) degrees off) it is the
        probability that the refined rotation is within :data:`SCORE_WITHIN_DEG` (10) degrees of the truth: of the
        results scoring 0.9-1 (mean 0.95) 97% were, of those scoring 0.2-0.4 (mean 0.35) 35%
        (``benchmarks/studies/score_calibration``; ``tests/test_session.py`` checks the order on the sample frames).
        With one pass the correction is the distance the refiner moved the coarse pose, so it mostly says how far the
        input was: a good refinement from 25 degrees off scores low. In :class:`refiner_rt.RefinerTracker` each
        update starts from the last rotation, so its one pass is such a second opinion (:attr:`RefinerTracker.scores`).
        """
        moved = self.correction_deg
        if self.views_spread_deg is not None:
            moved = moved + self.views_spread_deg
        return np.exp(-moved / SCORE_SCALE_DEG)

    @property
    def R(self) -> np.ndarray:
        """``(N, 3, 3)`` float64: the refined rotations as matrices, object to camera (``x_cam = R @ x_obj + t``)."""
        return rq.to_matrix(self.q_refined)


def settle_keeps(q_before, q_after, settle_deg: float) -> np.ndarray:
    """``(N,)`` bools: which objects keep a later refinement pass under ``settle_deg`` (the one definition the
    session, :class:`refiner_rt.RefinerCascade`, ``refiner-rt eval`` and the far-inputs study use): those the pass
    turns by more than ``settle_deg`` degrees (``(N, 4)`` wxyz rotations before and after the pass)."""
    return rq.geodesic_angle(q_before, q_after) > settle_deg


def _ort_message(exc: Exception) -> str:
    """onnxruntime's error text on one line, without its ``[ONNXRuntimeError] : 7 :`` prefix."""
    text = re.sub(r"^\[ONNXRuntimeError\] : \d+ : ", "", str(exc).strip())
    text = " ".join(text.split())
    return text if len(text) <= 400 else text[:400] + "..."


class RefinerSession:
    """An onnxruntime session for a refiner-rt ONNX model, with the crop rule and composition built in.

    Thread safety: one session may be called from many threads at once. Concurrent :meth:`refine` and
    :meth:`refine_crops` calls give bit for bit the results of the same calls made one after the other: the reused
    crop and ``q_in`` buffers are per calling thread and onnxruntime's ``run`` is thread-safe. There is no need for
    a session per thread (each would hold its own copy of the weights).

    Args:
        model: path to a ``.onnx`` file, or the model's bytes.
        threads: threads the network runs on (``>= 1``), the calling thread included; ``0`` means every
            core this process may run on (:func:`available_cores`, its CPU affinity). Cropping and the
            quaternion maths run on the calling thread. With 1 thread onnxruntime creates no thread pool.
            With more, its workers spin briefly after each call (faster at batch 1), which takes CPU from other
            processes on those cores: on a machine shared with a renderer, prefer ``threads=1``.
        providers: onnxruntime execution providers, default ``["CPUExecutionProvider"]``. Each must
            be available: there is no silent fallback to another provider.
        session_options: an ``onnxruntime.SessionOptions`` to use instead of the defaults (then
            ``threads`` is ignored and :attr:`threads` reports the options' intra-op thread count).
        object_id: the YCB id (or object name) the caller will refine. When given, the model must have been
            trained for it (metadata ``objects``), so one object is never refined with another's model.
        roll_step_deg: for a model with the canonical roll (metadata ``roll = "canonical"``): the crop is turned by
            the roll angle rounded to a multiple of this many degrees (:data:`refiner_rt.preprocess.ROLL_STEP_DEG`,
            1), so that a small change of ``q_in`` leaves the crop as it was and the output moves smoothly with it;
            ``0`` turns it by the exact angle, as the training does (:func:`refiner_rt.preprocess.canonical_roll`).
            In ``[0, 90)``; other models ignore it.

    Loading checks the whole contract before the first call: the metadata (:func:`refiner_rt.metadata.parse_metadata`:
    known values in sane ranges), the graph's inputs and outputs (:func:`refiner_rt.metadata.check_graph`: names,
    element types, shapes, a dynamic batch axis), and one trial run on a batch of two black crops, which checks
    that the batch axis really is free and that ``q_out`` comes back ``(2, 4)``.

    Default session options, each chosen by measurement (``benchmarks/profile_refine.py``; the numbers are in
    ``benchmarks/studies/speed``, "Choices in the runtime"): graph optimisation ``ORT_ENABLE_ALL`` (it adds layout
    transformations such as NCHWc convolutions), CPU memory arena and memory pattern on, sequential execution with
    one inter-op thread (the graph is a chain), intra-op spinning left at onnxruntime's default (on), the plain
    ``run`` (no IOBinding). onnxruntime's ``QDQPropagationTransformer`` is always off (:data:`DISABLED_OPTIMIZERS`;
    also with ``session_options``): it slows the static INT8 conv models and changes nothing else.

    Raises:
        ModelNotFoundError: ``model`` is a path that does not exist (a :class:`ModelError`, so a ``ValueError``,
            and a ``FileNotFoundError``).
        ModelError: (a ``ValueError``) the file is unreadable, empty, truncated or not ONNX; the model lacks the
            refiner-rt metadata contract, declares one this runtime does not understand or with values out of
            range, breaks the graph contract, or fails its trial run. The message names the file and the cause.
        ValueError: an unknown or unavailable provider; a bad ``threads`` value; ``object_id`` not among the
            model's objects.

    Example:
        >>> sess = RefinerSession("refiner.onnx", threads=1)
        >>> res = sess.refine(image_bgr, boxes_xyxy, q_in_wxyz)
        >>> res.q_refined  # (N, 4) wxyz, object-to-camera
    """

    #: :class:`refiner_rt.Refiner`'s capability: ``iterations``, ``views`` and ``settle_deg`` are :meth:`refine`'s.
    per_call_passes = True

    def __init__(self, model, threads: int = 1, providers=None, session_options: ort.SessionOptions | None = None,
                 object_id: str | None = None, roll_step_deg: float = ROLL_STEP_DEG):
        if isinstance(model, (bytes, bytearray)):
            source, self.model_path = bytes(model), None
            self._label = "<model bytes>"
            if not source:
                raise ModelError("<model bytes>: empty (0 bytes), not an ONNX model")
        elif isinstance(model, (str, os.PathLike)):
            path = Path(model)
            if not path.is_file():
                raise ModelNotFoundError(f"model file not found: {path}")
            source, self.model_path = str(path), path
            self._label = str(path)
            try:
                size = path.stat().st_size
                with open(path, "rb"):  # readable? (onnxruntime's own message for this is less clear)
                    pass
            except OSError as exc:
                raise ModelError(f"{path}: cannot read the model file ({exc.strerror or exc})") from exc
            if size == 0:
                raise ModelError(f"{path}: the file is empty (0 bytes), not an ONNX model")
        else:
            raise TypeError(f"model must be a path or the ONNX model's bytes; got {type(model).__name__}")
        if (isinstance(roll_step_deg, bool) or not isinstance(roll_step_deg, (int, float, np.integer, np.floating))
                or not 0 <= roll_step_deg < 90):
            raise ValueError(f"roll_step_deg must be a number of degrees in [0, 90); got {roll_step_deg!r}")
        # 0 is resolved here: onnxruntime's own default counts physical cores and ignores the CPU affinity, so
        # under `taskset -c 0` it would start 2 threads on 1 core.
        self.threads = validate_threads(threads) or available_cores()

        available = ort.get_available_providers()
        providers = list(providers) if providers is not None else ["CPUExecutionProvider"]
        for p in providers:
            name = p[0] if isinstance(p, tuple) else p
            if name not in available:
                raise ValueError(f"provider {name!r} is not available in this onnxruntime; available: {available}")

        if session_options is None:
            session_options = default_session_options(self.threads)
        else:
            self.threads = session_options.intra_op_num_threads
        try:
            self._session = ort.InferenceSession(source, sess_options=session_options, providers=providers,
                                                 disabled_optimizers=list(DISABLED_OPTIMIZERS))
        except Exception as exc:  # onnxruntime's InvalidProtobuf, InvalidArgument, Fail, ... (all plain Exceptions)
            raise ModelError(f"{self._label}: onnxruntime cannot load it as an ONNX model: {_ort_message(exc)}") from exc

        try:
            self.contract: ModelContract = parse_metadata(self._session.get_modelmeta().custom_metadata_map)
            check_graph(self._session.get_inputs(), self._session.get_outputs(), self.contract.input_size)
        except ValueError as exc:
            raise ModelError(f"{self._label}: {exc}") from None
        self._output_names = [OUTPUT_QUATERNION]
        self._rgb = self.contract.channel_order == "RGB"
        self._ray = self.contract.rotation_frame == "ray"
        self._roll = ROLL_TURNS.get(self.contract.roll)  # the turn of each crop before each pass, or None
        self.roll_step_deg = float(roll_step_deg)
        if self._roll is canonical_roll:
            step = self.roll_step_deg
            self._roll = lambda crops, q, out=None: canonical_roll(crops, q, out, step_deg=step)
        self._trial_run()
        self._local = threading.local()  # per-thread reusable buffers (see _buffers)
        if object_id is not None:
            if not isinstance(object_id, str):
                raise TypeError(f"object_id must be a string such as '003_cracker_box'; got {type(object_id).__name__}")
            if object_id not in self.contract.objects:
                raise ValueError(f"object_id {object_id!r} is not an object this model was trained for "
                                 f"(metadata objects: {list(self.contract.objects)}); use that object's model")

    @classmethod
    def pretrained(cls, object_id: str, int8: bool = True, threads: int = 1, stage: str = "coarse",
                   **kwargs) -> "RefinerSession":
        """A session on the refiner shipped for ``object_id`` (package data; nothing is downloaded).

        Args:
            object_id: YCB id, e.g. ``"003_cracker_box"`` (``refiner_rt.pretrained_models()`` lists them).
            int8: the INT8 model (default, fastest) or the fp32 one.
            stage: ``"coarse"`` (default: inputs up to 30 degrees off) or ``"fine"``: the object's fine refiner, for
                inputs a few degrees off (the coarse refiner's output, the previous video frame's); a
                :class:`refiner_rt.RefinerCascade` runs the two in turn.
            threads: as for the constructor.
            **kwargs: ``providers`` / ``session_options`` / ``roll_step_deg``, as for the constructor.

        The shipped models were trained in the viewing-ray frame: pass the camera intrinsics ``K`` to
        :meth:`refine`. Their object frame is the YCB google_16k scan frame (see :mod:`refiner_rt.pretrained`).

        Raises:
            ValueError: no model ships for ``object_id`` (the message lists those that do).
        """
        from refiner_rt.pretrained import pretrained_model

        path = pretrained_model(object_id).path(int8=int8, stage=stage)
        return cls(path, threads=threads, object_id=object_id, **kwargs)

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
    def refine(self, image_bgr, boxes_xyxy, q_in_wxyz, *, K=None, D=None, q_order: str = "wxyz", coarse=None,
               iterations: int = 1, views: int = 1, settle_deg: float | None = None) -> RefineResult:
        """Refine the rotations of ``N`` objects seen in one image.

        Safe to call from several threads at once on one session (see the class docstring). Everything after
        ``q_in_wxyz`` is keyword-only, as in every :class:`refiner_rt.Refiner` (:class:`refiner_rt.RefinerCascade`
        takes the same first keywords).

        Args:
            image_bgr: ``H x W x 3`` ``uint8`` image, **BGR** channel order.
            boxes_xyxy: ``(N, 4)`` boxes ``(x1, y1, x2, y2)`` in pixels (float, continuous
                coordinates), not normalised to 0..1; each at least ``MIN_BOX_SIDE`` (2) pixels wide and high,
                with at least ``MIN_INSIDE_FRACTION`` (25%) of its area inside the image and coordinates within
                ``+-MAX_BOX_COORDINATE`` (1e6) pixels (:func:`refiner_rt.checks.validate_boxes`: the errors
                name the box). ``N * views`` at most :data:`MAX_BATCH` (1024).
            q_in_wxyz: ``(N, 4)`` coarse object-to-camera rotations, ``wxyz`` (or in ``q_order``). Finite and
                non-zero; non-unit quaternions are normalised (their norm carries no rotation; huge
                components are scaled down first, so any finite non-zero quaternion works). Or ``(N, 3, 3)``
                rotation matrices (object to camera, ``x_cam = R @ x_obj + t``; orthonormal within 1e-3, det +1;
                a single ``(3, 3)`` matrix is refused with a message saying how to pass it).
            iterations: feed the refined rotation back this many times (``1`` to :data:`MAX_ITERATIONS`;
                the paper does 1).
            K: ``(3, 3)`` camera intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels, finite,
                ``fx, fy`` in ``[K_MIN_FOCAL, K_MAX_ABS]``, ``|s|, |cx|, |cy| <= K_MAX_ABS``, for this image's
                resolution: a principal point outside the image's central half is logged as a warning (the sign of
                a ``K`` for another resolution; a cropped image's ``K`` may put it there). Required by models
                trained in the viewing-ray frame (metadata ``rotation_frame == "ray"``), checked but unused by
                ``"camera"`` models.
            views: refine each object from this many crops and average the corrections (chordal mean,
                :func:`refiner_rt.quaternion.mean`): the box itself and ``views - 1`` fixed jitters of it (window
                centre shifted and side scaled by up to 5%, as the training's ``--augment`` box jitter), in one
                batch of ``N * views`` crops. Costs ``views`` network passes per object; it suits models trained
                with ``--augment`` (``benchmarks/averaging.py`` measures it). ``1`` to :data:`MAX_VIEWS`.
            q_order: ``"wxyz"`` (the default) or ``"xyzw"`` (ROS ``geometry_msgs/Quaternion``, SciPy): the order of
                ``q_in_wxyz``'s quaternions. Results are ``wxyz`` always (``res.R`` gives matrices).
            D: the camera's lens distortion coefficients, OpenCV's model (``k1, k2, p1, p2[, k3[, k4, k5, k6]]``,
                ``sensor_msgs/CameraInfo``'s ``d`` for ``plumb_bob`` and ``rational_polynomial``), with ``K`` its
                intrinsics; ``image_bgr`` and the boxes are then the raw (distorted) image's. Each crop is sampled
                through the distortion as the pinhole camera of ``K`` would see it, the view the network trained
                on (:mod:`refiner_rt.distortion`). None or all zeros: a pinhole camera.
            coarse: ``(N,)`` bools or None, as :meth:`refiner_rt.RefinerCascade.refine` takes it (rows known to be
                coarse); checked, and without effect here: a session refines every row with its one network.
            settle_deg: with ``iterations > 1``, a later pass is kept only for the objects it turns by more than
                this many degrees, and an object whose pass is not kept stops there (it has settled: a pass that
                turns a result by less is the refiner's floor, not a correction). From inputs within the refiner's
                range the first pass then stands nearly everywhere; from coarse poses 30-60 degrees off, beyond the
                range it trained on, the later passes go on (docs/cascade.md, "Coarse poses far off").
                :data:`SETTLE_DEG` is the value measured there. A number in ``(0, 180)`` with ``iterations >= 2``,
                or None (default): every pass is kept. Later passes run only for the objects still going on.

        Raises:
            ValueError / TypeError: a bad argument, named with what was expected and what was given.
            ModelError: the network failed or returned a non-finite or zero ``q_out``.
        """
        image = validate_image(image_bgr, "image_bgr")
        D = validate_D(D)
        small = boxes_rows(boxes_xyxy, image.shape) if D is None else None
        if small is None:
            boxes = validate_boxes(boxes_xyxy, image.shape, "boxes_xyxy")
            rows = boxes
        else:
            boxes, rows = small
        if type(iterations) is not int or not 1 <= iterations <= MAX_ITERATIONS:
            iterations = validate_iterations(iterations)
        if type(views) is not int or views != 1:
            views = validate_views(views)
        if settle_deg is not None:
            settle_deg = validate_settle(settle_deg, iterations)
        n = len(boxes)
        if coarse is not None:
            check_coarse_rows(coarse, n)
        if small is None or views > 1:
            check_batch(n, views, "boxes_xyxy")
        q_in, q_rows = self._q_in(as_wxyz(q_in_wxyz, q_order), n, "boxes_xyxy")
        if views > 1 or settle_deg is not None:
            q_rows, small = None, None  # the averaged and the settling paths run on numpy arrays
        q_frame = None
        if K is not None:
            K = validate_K(K)
            check_principal_point(K, image.shape)
        if D is not None:
            if K is None:
                raise ValueError("K is required with D: the distortion coefficients are in the pixels of the "
                                 "(3, 3) camera intrinsics K")
            boxes = rows = undistort_boxes(boxes, K, D)  # the boxes in the pinhole image of K
        if self._ray:
            if K is None:
                raise ValueError(
                    "K is required: this model was trained in the viewing-ray frame (metadata rotation_frame='ray'); "
                    "pass the (3, 3) camera intrinsics"
                )
            q_frame = ray_quaternion_rows(K, rows) if small is not None else ray_quaternions(K, boxes)
        size, context = self.contract.input_size, self.contract.crop_context
        if views > 1:
            rows = view_boxes(boxes, views, context)
        crops, q_net = self._buffers(len(rows))
        for i, box in enumerate(rows):
            if D is None:
                crop_to_square(image, box, size, context, out=crops[i], crop_filter=self.contract.crop_filter)
            else:
                crop_undistorted(image, box, size, context, K, D, out=crops[i], crop_filter=self.contract.crop_filter)
        return self._run(crops, q_net, q_in, q_rows, iterations, q_frame, views, settle_deg)

    def refine_crops(self, crops_bgr, q_in_wxyz, iterations: int = 1, *, q_order: str = "wxyz") -> RefineResult:
        """Refine rotations from crops that are already cut out (the crop window, any size).

        Each crop is resampled to ``S x S`` with the crop rule's warp (``context = 1``: the crop is
        taken to be the whole window; a non-square crop is zero-padded on its short side).
        Safe to call from several threads at once on one session (see the class docstring).

        Args:
            crops_bgr: a sequence of ``h x w x 3`` ``uint8`` BGR crops, or an ``(N, h, w, 3)`` array;
                ``N`` at most :data:`MAX_BATCH`.
            q_in_wxyz: ``(N, 4)`` coarse rotations, ``wxyz`` (or in ``q_order``), or ``(N, 3, 3)`` rotation
                matrices, in the model's rotation frame (for a ``"ray"`` model: relative to each crop's viewing
                ray; use :meth:`refine` with ``K`` to have that done for you).
            iterations: refinement iterations (``1`` to :data:`MAX_ITERATIONS`).
            q_order: ``"wxyz"`` (the default) or ``"xyzw"``, as in :meth:`refine`.

        Returns:
            :class:`RefineResult`.

        Raises:
            ValueError / TypeError: a bad argument, named with what was expected and what was given.
            ModelError: the network failed or returned a non-finite or zero ``q_out``.
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
        check_batch(len(crops_list), 1, "crops_bgr")
        for i, c in enumerate(crops_list):
            validate_image(c, f"crops_bgr[{i}]")
        q_in, q_rows = self._q_in(as_wxyz(q_in_wxyz, q_order), len(crops_list), "crops_bgr")
        iterations = validate_iterations(iterations)
        crops, q_net = self._buffers(len(crops_list))
        for i, c in enumerate(crops_list):
            if c.shape[0] == self.input_size and c.shape[1] == self.input_size:
                crops[i] = c
            else:
                resize_crop(np.ascontiguousarray(c), self.input_size, out=crops[i],
                            crop_filter=self.contract.crop_filter)
        return self._run(crops, q_net, q_in, q_rows, iterations, None)

    # ------------------------------------------------------------------ internals
    def _q_in(self, q, n: int, other: str) -> tuple[np.ndarray, list | None]:
        """Validated, unit, canonical ``q_in`` as ``(float64 (n, 4) array, rows)``; rows (Python floats) only for
        ``0 < n <= SMALL_BATCH`` well-formed input, else None. Anything unusual takes
        :func:`refiner_rt.checks.validate_rotations`, which raises the detailed errors."""
        if 0 < n <= SMALL_BATCH:
            arr = q
            if not isinstance(q, np.ndarray):
                try:
                    arr = np.asarray(q)
                except (ValueError, TypeError):  # ragged: validate_rotations names it
                    return validate_rotations(q, n, other), None
            if arr.dtype.kind in "fiu" and arr.shape == (n, 4):
                rows = rq.normalize_rows(arr.astype(np.float64, copy=False).tolist())
                if rows is not None:
                    return np.array(rows), rows
        return validate_rotations(q, n, other), None

    def _buffers(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Views of ``n`` crops and ``n`` float32 ``q_in`` rows in this thread's reusable buffers (grown when
        needed). Per thread, so that concurrent calls never share them."""
        try:
            crops, q32 = self._local.buffers
        except AttributeError:  # this thread's first call
            crops = q32 = ()
        if len(crops) < n:
            s = self.input_size
            crops = np.zeros((max(n, 2 * len(crops)), s, s, 3), dtype=np.uint8)
            q32 = np.zeros((len(crops), 4), dtype=np.float32)
            self._local.buffers = crops, q32
        return crops[:n], q32[:n]

    def _trial_run(self) -> None:
        """Run the network once on two black crops: the batch axis must be free and ``q_out`` ``(2, 4)`` float32."""
        s = self.input_size
        feed = {INPUT_IMAGE: np.zeros((2, s, s, 3), dtype=np.uint8), INPUT_QUATERNION: np.tile(
            np.array([[1.0, 0.0, 0.0, 0.0]], dtype=np.float32), (2, 1))}
        try:
            out = self._session.run(self._output_names, feed)[0]
        except Exception as exc:  # onnxruntime's own types
            raise ModelError(
                f"{self._label}: the network fails on a trial batch of 2 black {s}x{s} crops: {_ort_message(exc)}"
            ) from exc
        if not isinstance(out, np.ndarray) or out.shape != (2, 4) or out.dtype != np.float32:
            got = f"shape {out.shape}, dtype {out.dtype}" if isinstance(out, np.ndarray) else type(out).__name__
            raise ModelError(
                f"{self._label}: output {OUTPUT_QUATERNION!r} must be (batch, 4) float32; a trial batch of 2 gave {got}"
            )

    def _bad_output(self, out: np.ndarray) -> ModelError:
        """The error for a ``q_out`` batch with a non-finite or zero row (found by the fast or numpy path)."""
        out64 = out.astype(np.float64)
        with np.errstate(invalid="ignore", over="ignore"):
            bad = ~np.isfinite(out64).all(axis=1) | ~(np.linalg.norm(out64, axis=1) >= rq.MIN_NORM)
        i = int(np.argmax(bad))
        return ModelError(
            f"{self._label}: the network returned q_out[{i}] = {out[i].tolist()}: expected a finite, non-zero "
            "quaternion (wxyz)"
        )

    def _run(self, crops: np.ndarray, q_net: np.ndarray, q_in: np.ndarray, q_rows: list | None, iterations: int,
             q_frame, views: int = 1, settle_deg: float | None = None) -> RefineResult:
        """Run the network ``iterations`` times and compose; Python floats when ``q_rows`` is given, else numpy.
        With ``views > 1`` (numpy only) ``crops`` holds ``views`` crops per object, object-major, and each pass
        averages their corrections. With ``settle_deg`` (numpy only) a pass after the first is kept for the objects
        it turns by more than that, and the others stop (:meth:`refine`). ``crops`` and ``q_net`` are this thread's
        buffers (see :meth:`_buffers`)."""
        if settle_deg is not None and iterations > 1:
            return self._settle(crops, q_in, iterations, q_frame, views, settle_deg)
        n = len(q_in)
        if n == 0:
            empty = np.zeros((0, 4))
            return RefineResult(q_refined=empty, q_out=empty.copy(), q_in=empty.copy())
        if self._rgb:
            crops = np.ascontiguousarray(crops[..., ::-1])
        turned = np.empty_like(crops) if self._roll is not None else None  # each pass turns them by their roll
        feed = {INPUT_IMAGE: crops if turned is None else turned, INPUT_QUATERNION: q_net}
        # The network sees rotations in its own frame; for "ray" models q_net = q_ray^-1 * q.
        # q_refined = q_prev * q_out holds in either frame (q_ray * (q_ray^-1 q) * q_out = q * q_out).
        q = q_in if q_rows is None else q_rows
        q_out = None
        spread = None
        frame_inv = None
        if q_frame is not None:
            if q_rows is None:
                frame_inv = rq.inverse(np.asarray(q_frame))
            else:
                frame_inv = rq.inverse_rows(q_frame if isinstance(q_frame, list) else q_frame.tolist())
        for _ in range(iterations):
            if frame_inv is None:
                q_cur = q
            else:
                q_cur = rq.multiply(frame_inv, q) if q_rows is None else rq.multiply_rows(frame_inv, q)
            q_net[...] = q_cur if views == 1 else np.repeat(q_cur, views, axis=0)
            if turned is not None:
                q_net[...] = self._roll(crops, q_net, out=turned)[1]
            try:
                out = self._session.run(self._output_names, feed)[0]
            except Exception as exc:  # onnxruntime's own types: the inputs were checked, so the model failed
                raise ModelError(
                    f"{self._label}: the network failed on a batch of {len(q_net)}: {_ort_message(exc)}"
                ) from exc
            if out.shape != q_net.shape:
                raise ModelError(
                    f"{self._label}: output {OUTPUT_QUATERNION!r} has shape {out.shape} for a batch of {len(q_net)}; "
                    f"expected {q_net.shape}"
                )
            if q_rows is not None:
                q_out = rq.normalize_rows(out.tolist())
                if q_out is None:
                    raise self._bad_output(out)
                q = rq.normalize_rows(rq.multiply_rows(q, q_out))  # unit * unit: always finite and unit
                continue
            try:
                q_out = rq.normalize(out.astype(np.float64))
            except ValueError:
                raise self._bad_output(out) from None
            if views > 1:
                per_view = q_out.reshape(n, views, 4)
                q_out = rq.mean(per_view, axis=1)
                spread = rq.geodesic_angle(per_view, q_out[:, None, :]).mean(axis=1)
            q = rq.normalize(rq.multiply(q, q_out))
        if q_rows is not None:
            q, q_out = np.array(q), np.array(q_out)
        return RefineResult(q_refined=q, q_out=q_out, q_in=q_in, views_spread_deg=spread)

    def _settle(self, crops: np.ndarray, q_in: np.ndarray, iterations: int, q_frame, views: int,
                settle_deg: float) -> RefineResult:
        """:meth:`_run` with ``settle_deg``: each pass after the first runs on the objects still going on (their crops
        only) and is kept where it turns the rotation by more than ``settle_deg``."""
        q_frame = None if q_frame is None else np.asarray(q_frame, dtype=np.float64)
        q, q_out, spread = np.array(q_in, dtype=np.float64), None, None
        going = np.arange(len(q_in))
        for k in range(iterations):
            rows = (going[:, None] * views + np.arange(views)).ravel()  # the crops of the objects going on
            frame = None if q_frame is None else q_frame[going]
            step = self._run(crops[rows], np.empty((len(rows), 4), dtype=np.float32), q[going], None, 1, frame, views)
            if k == 0:
                q, q_out, spread = step.q_refined, step.q_out, step.views_spread_deg
            else:
                moved = settle_keeps(q[going], step.q_refined, settle_deg)
                going = going[moved]
                q[going], q_out[going] = step.q_refined[moved], step.q_out[moved]
                if spread is not None:
                    spread[going] = step.views_spread_deg[moved]
            if not len(going):
                break
        return RefineResult(q_refined=q, q_out=q_out, q_in=q_in, views_spread_deg=spread)

    def __repr__(self) -> str:
        src = str(self.model_path) if self.model_path else "<bytes>"
        c = self.contract
        return (
            f"RefinerSession({src!r}, arch={c.arch!r}, input_size={c.input_size}, "
            f"rotation_frame={c.rotation_frame!r}, threads={self.threads}, providers={self.providers})"
        )
