"""What a render draws: :class:`RenderConfig`, the layouts, the cameras of the robot layout."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.data.objects import PAPER_OBJECTS

YCBV_K = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])
LAYOUTS = ("robot", "tabletop")
ENGINES = ("tiny", "cycles")  # pybullet's TinyRenderer; Blender Cycles (models.data.render.cycles)
# Where a robot's camera sees a table from: an arm camera close above it, a head camera further away.
ROBOT_DISTANCE = (0.4, 1.5)  # metres from the arrangement's centre
ROBOT_ELEVATION_DEG = (10.0, 80.0)  # above the table
# Common RGB-D colour cameras at 640x480 (fx, fy, cx, cy in pixels): YCB-Video's Asus Xtion, a RealSense D435/D415
# colour stream, a Kinect v1-like and an Orbbec/Xtion-like default calibration.
COMMON_CAMERAS = tuple(
    ((fx, 0.0, cx), (0.0, fy, cy), (0.0, 0.0, 1.0))
    for fx, fy, cx, cy in ((1066.778, 1067.487, 312.9869, 241.3109), (615.0, 615.0, 320.0, 240.0),
                           (525.0, 525.0, 319.5, 239.5), (570.3, 570.3, 319.5, 239.5))
)
TABLE_HALF = 0.6  # the table top is the square [-0.6, 0.6]^2 m at z = 0 (world frame, z up)


@dataclass
class RenderConfig:
    """What to render.

    Attributes:
        width, height: image size in pixels.
        K: 3x3 intrinsics (OpenCV convention).
        frames_per_scene: frames along each camera path.
        objects_per_scene: (min, max) objects dropped per scene.
        objects: YCB ids to draw from.
        distance: (min, max) camera distance to the arrangement centre, metres.
        elevation_deg: (min, max) camera elevation above the table, degrees.
        sweep_deg: (min, max) azimuth swept along a path, degrees.
        jpeg_quality: JPEG quality of ``rgb/``.
        noise_std: (min, max) std of Gaussian sensor noise, grey levels.
        blur_sigma: (min, max) Gaussian blur sigma, pixels.
        light_tint: probability that a scene's light is strongly tinted (each channel in [0.35, 1]
            instead of [0.75, 1]).
        exposure: (min, max) exposure gain, drawn log-uniformly per scene.
        gamma: (min, max) tone curve exponent per scene (after the gain; a soft shoulder follows it).
        shadows: draw the objects' cast shadows on the table.
        table_gloss: (min, max) strength of the table's specular highlight (0: matte).
        layout: how objects are placed and seen. ``"robot"`` (the default): each object's centre of mass at its
            mesh's centre, so a dropped object comes to rest in one of its stable poses (a box on any face, a drill
            on its side) as often as physics gives it; ``upright`` of the objects are set down standing in their
            scan frame's upright pose; ``stack`` of them dropped onto another (stacked, leaning); cameras where a
            robot's arm or head would be (:data:`ROBOT_DISTANCE`, :data:`ROBOT_ELEVATION_DEG`), each scene through
            one of ``cameras``. ``"tabletop"``: the layout of the data sets before it (``ycb9_v2`` to ``ycb9_v5``,
            benchmarks/DATA.md): every object dropped with its centre of mass at the mesh origin, which for the YCB
            scans sits near the base, so most objects right themselves and stand upright.
        upright: ``"robot"`` layout: share of objects set down upright (the rest are dropped at random).
        stack: ``"robot"`` layout: share of objects (after the first) dropped onto an earlier one.
        cameras: ``"robot"`` layout: intrinsics to draw one of per scene (empty: ``K``); see
            :data:`COMMON_CAMERAS`.
        engine: ``"tiny"`` (pybullet's TinyRenderer, composited backdrop) or ``"cycles"`` (Blender's path tracer,
            :mod:`models.data.render.cycles`); the same scenes and ground truth either way.
        cycles_samples: Cycles samples per pixel (then OpenImageDenoise).
        cycles_scale: Cycles renders at this fraction of ``width`` x ``height``, then resizes.
        cycles_region: Cycles renders each object's region alone, at the refiner's crop scale, over a coarse
            render of the whole frame (:mod:`models.data.render.cycles`): crops as sharp as a full-size render's
            for the pixels a crop needs, whatever the object's distance.
        object_appearance: strength in [0, 1] of a per-scene change of each object's appearance, as a mesh of
            another print run or another light would give (:func:`models.data.render.scene.object_appearance`):
            its texture's gain and colour, and its specularity; 0 (the default) leaves the meshes as they are and
            draws nothing, so the data sets rendered before it stay reproducible.
    """

    width: int = 640
    height: int = 480
    K: tuple = tuple(map(tuple, YCBV_K))
    frames_per_scene: int = 100
    objects_per_scene: tuple[int, int] = (3, 6)
    objects: tuple[str, ...] = PAPER_OBJECTS
    distance: tuple[float, float] = ROBOT_DISTANCE
    elevation_deg: tuple[float, float] = ROBOT_ELEVATION_DEG
    sweep_deg: tuple[float, float] = (60.0, 180.0)
    jpeg_quality: int = 95
    noise_std: tuple[float, float] = (1.0, 4.0)
    blur_sigma: tuple[float, float] = (0.0, 1.0)
    light_tint: float = 0.3
    exposure: tuple[float, float] = (0.6, 1.5)
    gamma: tuple[float, float] = (0.75, 1.35)
    shadows: bool = True
    table_gloss: tuple[float, float] = (0.0, 0.6)
    layout: str = "robot"
    upright: float = 0.35
    stack: float = 0.2
    cameras: tuple = ()
    engine: str = "tiny"
    cycles_samples: int = 16
    cycles_scale: float = 0.5
    cycles_region: bool = False
    object_appearance: float = 0.0

    def __post_init__(self):
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {', '.join(LAYOUTS)}; got {self.layout!r}")
        if self.engine not in ENGINES:
            raise ValueError(f"engine must be one of {', '.join(ENGINES)}; got {self.engine!r}")
        if not (isinstance(self.cycles_samples, int) and self.cycles_samples >= 1):
            raise ValueError(f"cycles_samples must be an integer >= 1; got {self.cycles_samples!r}")
        if not 0.1 <= self.cycles_scale <= 1.0:
            raise ValueError(f"cycles_scale must be in [0.1, 1]; got {self.cycles_scale!r}")
        if not (isinstance(self.object_appearance, (int, float)) and 0.0 <= self.object_appearance <= 1.0):
            raise ValueError(f"object_appearance must be a strength in [0, 1]; got {self.object_appearance!r}")
        if self.cycles_region and self.engine != "cycles":
            raise ValueError("cycles_region needs engine 'cycles'")

    @classmethod
    def for_layout(cls, layout: str, **kw) -> "RenderConfig":
        """The defaults of ``layout``: ``"robot"`` (the dataclass defaults, and :data:`COMMON_CAMERAS` unless ``K`` is
        given) or ``"tabletop"`` (the earlier data sets' config); ``kw`` overrides them."""
        if layout == "robot":
            base = {} if "K" in kw else {"cameras": COMMON_CAMERAS}
        elif layout == "tabletop":
            base = dict(distance=(0.8, 1.6), elevation_deg=(20.0, 70.0))
        else:
            raise ValueError(f"layout must be one of {', '.join(LAYOUTS)}; got {layout!r}")
        return cls(**{**base, "layout": layout, **kw})

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["K"] = [list(r) for r in self.K]
        d["objects"] = list(self.objects)
        d["cameras"] = [[list(r) for r in K] for K in self.cameras]
        if not self.object_appearance:  # as the data sets before it recorded it (they resume with the same record)
            d.pop("object_appearance")
        if not self.cycles_region:
            d.pop("cycles_region")
        if self.engine == "tiny":  # as the data sets before the Cycles engine recorded it
            for key in ("engine", "cycles_samples", "cycles_scale"):
                d.pop(key)
        if self.layout == "tabletop":  # as the earlier data sets recorded it (they resume with the same record)
            for key in ("layout", "upright", "stack") + (() if self.cameras else ("cameras",)):
                d.pop(key)
        return d
