"""The ONNX model contract: graph input/output names and the ``metadata_props`` keys (docs/design.md §4).

The exporter writes this contract with :func:`build_metadata`; the runtime reads it back with
:func:`parse_metadata` and refuses any model whose contract it does not understand, naming the key.
Names of graph inputs and outputs live here only, so the exporter and the runtime cannot drift apart.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field

from refiner_rt.preprocess import CROP_FILTERS, ROLL_TURNS

__all__ = [
    "file_sha256",
    "FORMAT",
    "FORMAT_ROLL",
    "ROLLS",
    "INPUT_IMAGE",
    "INPUT_QUATERNION",
    "OUTPUT_QUATERNION",
    "MAX_CROP_CONTEXT",
    "MAX_INPUT_SIZE",
    "REQUIRED_KEYS",
    "ModelContract",
    "build_metadata",
    "check_graph",
    "parse_metadata",
]

FORMAT = "refiner-rt/onnx/1"
# Format 2 is format 1 plus the key ``roll``: a turn of every crop and its coarse rotation that the runtime makes
# before the graph (refiner_rt.preprocess.canonical_roll). A file that needs it says format 2, so that a runtime
# which knows only format 1 refuses it instead of feeding it unturned crops.
FORMAT_ROLL = "refiner-rt/onnx/2"
ROLLS = ("none", *ROLL_TURNS)
INPUT_IMAGE = "image"          # (batch, S, S, 3) uint8, channel order from the metadata
INPUT_QUATERNION = "q_in"      # (batch, 4) float32, wxyz, object-to-camera (or ray frame, see rotation_frame)
OUTPUT_QUATERNION = "q_out"    # (batch, 4) float32, wxyz, unit norm: correction, q_refined = q_in * q_out

REQUIRED_KEYS = (
    "refiner_rt.format",
    "refiner_rt.version",
    "arch",
    "input_size",
    "channel_order",
    "crop_context",
    "quaternion_order",
    "rotation_frame",
    "objects",
    "train_noise",
    "checkpoint_sha256",
)

CHANNEL_ORDERS = ("BGR", "RGB")
ROTATION_FRAMES = ("camera", "ray")
QUANTIZATIONS = ("none", "dynamic-int8", "static-qdq-int8", "static-qdq-int8-conv", "static-qdq-int8-conv-float-pose")
# Sane ranges, refused outside them on load (and by the training config). input_size: the paper's networks take 64
# (shallow) and 224 (VGG-M); a 1024 crop is 3 MB per box. crop_context: the window is max(w, h) * context; past 4
# the object fills under a quarter of the crop, and a huge or infinite value makes every crop black.
MAX_INPUT_SIZE = 1024
MAX_CROP_CONTEXT = 4.0


@dataclass(frozen=True)
class ModelContract:
    """The parsed, validated metadata of a refiner ONNX model.

    Attributes:
        arch: architecture name from the model registry (e.g. ``"shallow"``).
        input_size: side ``S`` of the square ``S x S x 3`` uint8 crop the graph takes.
        channel_order: ``"BGR"`` or ``"RGB"``: the order the graph's ``image`` input expects.
        crop_context: crop-rule context factor (window side = ``max(w, h) * context``).
        rotation_frame: ``"camera"`` (q_in in the camera frame, K unused) or ``"ray"`` (q_in in the
            frame aligned with the viewing ray through the box centre; needs K at run time).
        objects: YCB ids the weights were trained for.
        train_noise: the coarse-pose noise used in training, e.g. ``"uniform:0:30"``.
        quantization: ``"none"``, ``"dynamic-int8"``, ``"static-qdq-int8"``, ``"static-qdq-int8-conv"`` or
            ``"static-qdq-int8-conv-float-pose"`` (the scheme of :mod:`export.quantize` that made the model).
        checkpoint_sha256: SHA-256 of the checkpoint the model was exported from.
        version: refiner-rt version that exported the model.
        extra: every other metadata key, as written.
        roll: ``"none"``, ``"canonical"`` or ``"quarter"``: before each pass the runtime turns every crop about its
            centre, and its coarse rotation about the viewing ray, so that the coarse pose's object z axis points up
            (:func:`refiner_rt.preprocess.canonical_roll`), or within 45 degrees of up in quarter turns
            (:func:`refiner_rt.preprocess.quarter_roll`); format 2, ray frame only.
        crop_filter: ``"none"`` or ``"antialias"``: how the crop rule filters the window's pixels before its warp
            (:func:`refiner_rt.preprocess.crop_to_square`); ``"none"`` when the key is absent (every model made
            before it).
    """

    arch: str
    input_size: int
    channel_order: str
    crop_context: float
    rotation_frame: str
    objects: tuple[str, ...]
    train_noise: str
    quantization: str
    checkpoint_sha256: str
    version: str
    extra: dict = field(default_factory=dict)
    roll: str = "none"
    crop_filter: str = "none"

    def as_dict(self) -> dict:
        """The contract as plain Python values (what ``RefinerSession.metadata`` returns)."""
        return {
            "refiner_rt.format": FORMAT if self.roll == "none" else FORMAT_ROLL,
            "refiner_rt.version": self.version,
            "arch": self.arch,
            "input_size": self.input_size,
            "channel_order": self.channel_order,
            "crop_context": self.crop_context,
            "quaternion_order": "wxyz",
            "rotation_frame": self.rotation_frame,
            "objects": list(self.objects),
            "train_noise": self.train_noise,
            "quantization": self.quantization,
            "checkpoint_sha256": self.checkpoint_sha256,
            **({"roll": self.roll} if self.roll != "none" else {}),
            **({"crop_filter": self.crop_filter} if self.crop_filter != "none" else {}),
            **self.extra,
        }


def build_metadata(
    *,
    arch: str,
    input_size: int,
    channel_order: str,
    crop_context: float,
    rotation_frame: str,
    objects,
    train_noise: str,
    checkpoint_sha256: str,
    version: str,
    quantization: str = "none",
    extra: dict | None = None,
    roll: str = "none",
    crop_filter: str = "none",
) -> dict[str, str]:
    """The ``metadata_props`` of a refiner model as ``{key: str}``, validated by :func:`parse_metadata` (format 2 with
    its ``roll`` key when ``roll`` is not ``"none"``)."""
    props = {
        "refiner_rt.format": FORMAT if roll == "none" else FORMAT_ROLL,
        "refiner_rt.version": str(version),
        "arch": str(arch),
        "input_size": str(int(input_size)),
        "channel_order": str(channel_order),
        "crop_context": repr(float(crop_context)),
        "quaternion_order": "wxyz",
        "rotation_frame": str(rotation_frame),
        "objects": json.dumps(list(objects)),
        "train_noise": str(train_noise),
        "checkpoint_sha256": str(checkpoint_sha256),
        "quantization": str(quantization),
        **({"roll": str(roll)} if roll != "none" else {}),
        **({"crop_filter": str(crop_filter)} if crop_filter != "none" else {}),
    }
    for k, v in (extra or {}).items():
        props[str(k)] = v if isinstance(v, str) else json.dumps(v)
    parse_metadata(props)
    return props


def parse_metadata(props: dict[str, str]) -> ModelContract:
    """Validate ``metadata_props`` and return the :class:`ModelContract`.

    Raises:
        ValueError: a required key is missing, or a key holds a value this runtime does not
            understand; the message names the key, what was expected and what was found.
    """
    missing = [k for k in REQUIRED_KEYS if k not in props]
    if missing:
        raise ValueError(
            f"model metadata is missing required key(s) {missing}: not a refiner-rt model, or exported by "
            f"an incompatible tool (expected keys {list(REQUIRED_KEYS)})"
        )
    if props["refiner_rt.format"] not in (FORMAT, FORMAT_ROLL):
        raise ValueError(
            f"model metadata key 'refiner_rt.format' is {props['refiner_rt.format']!r}; this runtime understands "
            f"{FORMAT!r} and {FORMAT_ROLL!r}"
        )
    roll = props.get("roll", "none")
    if props["refiner_rt.format"] == FORMAT_ROLL:
        if "roll" not in props or roll not in ROLLS or roll == "none":
            raise ValueError(f"model metadata key 'roll' must be one of {ROLLS[1:]} in a {FORMAT_ROLL!r} model; got "
                             f"{props.get('roll', 'no such key')!r}")
        if props["rotation_frame"] != "ray":
            raise ValueError(f"model metadata key 'roll' is {roll!r}, a turn about the viewing ray: it needs "
                             f"rotation_frame 'ray'; got {props['rotation_frame']!r}")
    elif "roll" in props:
        raise ValueError(f"model metadata key 'roll' ({roll!r}) belongs to format {FORMAT_ROLL!r}; this model says "
                         f"{FORMAT!r}")
    if props["quaternion_order"] != "wxyz":
        raise ValueError(f"model metadata key 'quaternion_order' is {props['quaternion_order']!r}; expected 'wxyz'")
    try:
        input_size = int(props["input_size"])
    except ValueError:
        raise ValueError(f"model metadata key 'input_size' must be a positive integer; got {props['input_size']!r}") from None
    if not 1 <= input_size <= MAX_INPUT_SIZE:
        raise ValueError(f"model metadata key 'input_size' must be an integer from 1 to {MAX_INPUT_SIZE}; got {input_size}")
    if props["channel_order"] not in CHANNEL_ORDERS:
        raise ValueError(f"model metadata key 'channel_order' must be one of {CHANNEL_ORDERS}; got {props['channel_order']!r}")
    try:
        context = float(props["crop_context"])
    except ValueError:
        raise ValueError(
            f"model metadata key 'crop_context' must be a number from 1 to {MAX_CROP_CONTEXT:g}; got {props['crop_context']!r}"
        ) from None
    if not (math.isfinite(context) and 1.0 <= context <= MAX_CROP_CONTEXT):
        raise ValueError(f"model metadata key 'crop_context' must be a number from 1 to {MAX_CROP_CONTEXT:g}; got {context}")
    if props["rotation_frame"] not in ROTATION_FRAMES:
        raise ValueError(f"model metadata key 'rotation_frame' must be one of {ROTATION_FRAMES}; got {props['rotation_frame']!r}")
    try:
        objects = json.loads(props["objects"])
    except (json.JSONDecodeError, RecursionError):
        objects = None
    if not isinstance(objects, list) or not all(isinstance(o, str) for o in objects):
        raise ValueError(f"model metadata key 'objects' must be a JSON list of YCB id strings; got {props['objects']!r}")
    quantization = props.get("quantization", "none")
    if quantization not in QUANTIZATIONS:
        raise ValueError(f"model metadata key 'quantization' must be one of {QUANTIZATIONS}; got {quantization!r}")
    crop_filter = props.get("crop_filter", "none")
    if crop_filter not in CROP_FILTERS:
        raise ValueError(f"model metadata key 'crop_filter' must be one of {CROP_FILTERS}; got {crop_filter!r}")
    known = set(REQUIRED_KEYS) | {"quantization", "roll", "crop_filter"}
    extra = {k: v for k, v in props.items() if k not in known}
    return ModelContract(
        arch=props["arch"],
        input_size=input_size,
        channel_order=props["channel_order"],
        crop_context=context,
        rotation_frame=props["rotation_frame"],
        objects=tuple(objects),
        train_noise=props["train_noise"],
        quantization=quantization,
        checkpoint_sha256=props["checkpoint_sha256"],
        version=props["refiner_rt.version"],
        extra=extra,
        roll=roll,
        crop_filter=crop_filter,
    )


def _is_dynamic(dim) -> bool:
    """Whether a graph dimension (onnxruntime: an int, a symbolic name or None) is left free."""
    return not isinstance(dim, int)


def check_graph(inputs, outputs, input_size: int) -> None:
    """Check a refiner graph's inputs and outputs against the contract (docs/design.md §4.1).

    Expected: exactly the inputs ``image`` ``(batch, S, S, 3)`` ``tensor(uint8)`` and ``q_in`` ``(batch, 4)``
    ``tensor(float)``, and an output ``q_out`` ``(batch, 4)`` ``tensor(float)`` (other outputs are ignored), with the
    batch axis dynamic (a symbolic name, not a number) and ``S`` = the metadata's ``input_size``. A dimension left
    symbolic where a number is expected is accepted here (the runtime's trial run on load checks it).

    Args:
        inputs, outputs: the graph's inputs and outputs, each with ``.name``, ``.type`` (e.g. ``"tensor(uint8)"``)
            and ``.shape`` (a list of ints, names or None), as onnxruntime's ``NodeArg``.
        input_size: ``S`` from the metadata.

    Raises:
        ValueError: the first violation, naming the input or output, what was expected and what the graph declares.
    """
    s = input_size
    expected_in = {INPUT_IMAGE: ("tensor(uint8)", (None, s, s, 3)), INPUT_QUATERNION: ("tensor(float)", (None, 4))}
    expected_out = {OUTPUT_QUATERNION: ("tensor(float)", (None, 4))}
    by_name_in = {i.name: i for i in inputs}
    by_name_out = {o.name: o for o in outputs}
    missing = [n for n in expected_in if n not in by_name_in] + [n for n in expected_out if n not in by_name_out]
    if missing:
        raise ValueError(
            f"model graph lacks {missing}: expected inputs {list(expected_in)} and output {OUTPUT_QUATERNION!r}; "
            f"got inputs {sorted(by_name_in)} and outputs {sorted(by_name_out)}"
        )
    extra = sorted(set(by_name_in) - set(expected_in))
    if extra:
        raise ValueError(
            f"model graph has inputs {extra} that the runtime does not feed: expected exactly {list(expected_in)}"
        )
    for kind, expected, declared in (("input", expected_in, by_name_in), ("output", expected_out, by_name_out)):
        for name, (dtype, shape) in expected.items():
            arg = declared[name]
            want = "(batch, " + ", ".join(str(d) for d in shape[1:]) + ")"
            if arg.type != dtype:
                raise ValueError(f"model {kind} {name!r} must be {dtype} {want}; the graph declares {arg.type}")
            got = list(arg.shape)
            if len(got) != len(shape) or any(isinstance(g, int) and g != w for g, w in zip(got[1:], shape[1:])):
                hint = f" (the metadata's input_size={s} expects {want})" if name == INPUT_IMAGE else ""
                raise ValueError(f"model {kind} {name!r} must have shape {want}{hint}; the graph declares {got}")
            if not _is_dynamic(got[0]):
                raise ValueError(
                    f"model {kind} {name!r} must have a dynamic batch axis {want}; the graph fixes it to {got[0]} "
                    "(export with a dynamic batch dimension)"
                )


def file_sha256(path) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MB blocks: what models record of the files they came from
    (``checkpoint_sha256``, a mesh's ``sha256``)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
