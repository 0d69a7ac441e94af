"""Scene sampling: a pybullet world with the meshes loaded once, objects placed by the layout and settled by physics,
the scene's camera intrinsics."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import cv2
import numpy as np

from models.data.meshes import Mesh

from .config import TABLE_HALF, RenderConfig


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


class World:
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


def scene_rng(seed: int, scene: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(scene), 0x5EED])


def object_appearance(strength: float, seed: int, scene: int, bodies: dict[int, str]) -> dict[int, dict]:
    """Per body of scene ``scene``, how its mesh looks in this scene (``RenderConfig.object_appearance``):
    ``{"gain_bgr": [3 floats], "specular": s}``; ``{}`` when ``strength`` is 0.

    The texture's gain is drawn log-uniformly in ``exp(+-0.4 strength)`` (0.67-1.49 at 1), each channel's factor
    in ``exp(+-0.15 strength)`` on top (a colour shift of up to 16%), the specular coefficient in ``[0, strength]``
    (the TinyRenderer engine's; Cycles draws its own roughness and specularity per object). The draws come from a
    generator of their own, so a scene's arrangement, cameras and light do not depend on ``strength``.
    """
    if not strength:
        return {}
    rng = np.random.default_rng([int(seed), int(scene), 0xA99E])
    out = {}
    for body in sorted(bodies):
        gain = np.exp(rng.uniform(-0.4, 0.4) * strength) * np.exp(rng.uniform(-0.15, 0.15, 3) * strength)
        out[body] = {"gain_bgr": [float(g) for g in gain], "specular": float(rng.uniform(0.0, strength))}
    return out


def build_scene(world: World, cfg: RenderConfig, rng: np.random.Generator) -> tuple[dict[int, str], np.ndarray]:
    """Drop objects on a textured table in a textured room and let them settle.

    Returns:
        ``({body id: ycb id}, centre)``: the bodies and the arrangement's centre (world, metres).
    """
    pb, c = world.pb, world.client
    world.clear()
    pb.setGravity(0, 0, -9.81, physicsClientId=c)
    # The table takes part in the physics only: TinyRenderer's cost is per covered pixel, so the table
    # and the room are composited afterwards (see Backdrop), and only the objects are rendered.
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
        bodies = place_robot(world, cfg, rng, [str(o) for o in chosen])
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


def place_robot(world: World, cfg: RenderConfig, rng: np.random.Generator, chosen: list[str]) -> dict[int, str]:
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
