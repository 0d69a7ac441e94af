"""The TinyRenderer engine (pybullet, CPU): the objects rendered with their segmentation mask, the table and room
composited behind them with cast shadows and a glossy highlight, then the camera's tone curve, blur, noise and JPEG;
one scene written as a BOP scene folder."""

from __future__ import annotations

import math
import shutil
import time
from pathlib import Path

import cv2
import numpy as np

from .bop_writer import finish_scene, frame_ground_truth
from .camera import camera_path, projection_matrix_gl, view_matrix_gl
from .config import TABLE_HALF, RenderConfig
from .scene import scene_rng, World, build_scene, object_appearance, scene_camera


def random_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
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


class Backdrop:
    """The table top (a textured plane, exact perspective by ray casting) over a random room texture.

    Both are drawn with OpenCV where the renderer drew no object; their brightness follows the
    scene's light (ambient + diffuse for the table's upward normal).
    """

    def __init__(self, rng: np.random.Generator, K: np.ndarray, width: int, height: int, light: dict,
                 gloss: float = 0.0, shininess: float = 20.0):
        self.table = random_texture(rng, 512).astype(np.float32)
        room = random_texture(rng, 256)
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


class ToneCurve:
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


def start_scene(world: World, cfg: RenderConfig, seed: int, scene: int, out_dir: Path):
    """What every engine does first for scene ``scene``: its generator, its final folder and an empty temporary one
    (``rgb/``, ``mask_visib/``), the settled arrangement and the camera's intrinsics: ``(rng, final, tmp, bodies,
    centre, K)``."""
    rng = scene_rng(seed, scene)
    final, tmp = out_dir / f"{scene:06d}", out_dir / f".{scene:06d}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "rgb").mkdir(parents=True)
    (tmp / "mask_visib").mkdir()
    bodies, centre = build_scene(world, cfg, rng)
    return rng, final, tmp, bodies, centre, scene_camera(cfg, rng)


def render_scene(world: World, cfg: RenderConfig, seed: int, scene: int, out_dir: Path) -> dict:
    """Render one BOP scene into ``out_dir/<scene:06d>`` (written to a temporary folder, then renamed).

    Returns:
        ``{"frames": n, "instances": n, "visible_instances": {ycb id: n with visib_fract >= 0.3}, "seconds": s}``.
    """
    pb, c = world.pb, world.client
    t0 = time.perf_counter()
    rng, final, tmp, bodies, centre, K = start_scene(world, cfg, seed, scene, out_dir)
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
    backdrop = Backdrop(rng, K, W, H, light, gloss=rng.uniform(*cfg.table_gloss),
                         shininess=float(np.exp(rng.uniform(np.log(8.0), np.log(80.0)))))
    if cfg.shadows:
        points = []
        for b, obj in bodies.items():
            R_wo, t_wo = world.mesh_pose(b)
            points.append(world.meshes[obj].vertices[::8] @ R_wo.T + t_wo)
        backdrop.cast_shadows(points, softness=rng.uniform(1.0, 6.0))
    tone = ToneCurve(rng, cfg)
    cv2.setRNGSeed(int(rng.integers(1 << 31)))
    noise_std = rng.uniform(*cfg.noise_std)
    blur = rng.uniform(*cfg.blur_sigma)
    poses_w = {b: world.mesh_pose(b) for b in bodies}
    looks = object_appearance(cfg.object_appearance, seed, scene, bodies)
    for b, look in looks.items():
        pb.changeVisualShape(b, -1, specularColor=[look["specular"]] * 3, physicsClientId=c)
    # seg value -> the texture gain of that body (the rendered colour is texture x light: the same as a texture gain)
    gain_lut = {b: np.asarray(look["gain_bgr"], np.float32) for b, look in looks.items()}
    gt, info, cam = {}, {}, {}
    visible = {}
    for im, (R_cw, t_cw) in enumerate(camera_path(cfg, rng, centre, cfg.frames_per_scene)):
        _, _, rgba, _, seg = pb.getCameraImage(
            W, H, view_matrix_gl(R_cw, t_cw), proj, renderer=pb.ER_TINY_RENDERER, physicsClientId=c, **light
        )
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(H, W, 4)[..., :3]
        seg = np.asarray(seg).reshape(H, W)
        obj_px = rgb[..., ::-1].astype(np.float32)
        for b, gain in gain_lut.items():
            hit = seg == b
            obj_px[hit] *= gain
        img = np.where((seg >= 0)[..., None], obj_px, backdrop.draw(R_cw, t_cw))
        img = tone(img)
        if blur > 0.3:
            img = cv2.GaussianBlur(img, (0, 0), blur)
        noise = np.empty(img.shape, np.float32)
        cv2.randn(noise, 0.0, float(noise_std))
        img += noise
        cv2.imwrite(str(tmp / "rgb" / f"{im:06d}.jpg"), np.clip(img, 0, 255).astype(np.uint8),
                    [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])
        gts, infos, seen = frame_ground_truth(world, bodies, poses_w, R_cw, t_cw, seg, K, W, H, tmp / "mask_visib", im)
        for obj in seen:
            visible[obj] = visible.get(obj, 0) + 1
        gt[im], info[im] = gts, infos
        cam[im] = {"cam_K": K.flatten().tolist(), "depth_scale": 1.0}
    meta = {"seed": seed, "scene": scene, "objects": sorted(set(bodies.values())), "light": light, "tone": tone.as_dict(),
            "table_gloss": backdrop.gloss, "shadows": cfg.shadows,
            **({"object_appearance": [{"object": bodies[b], **look} for b, look in looks.items()]} if looks else {}),
            "noise_std": noise_std, "blur_sigma": blur, "meshes": {o: str(m.obj_path) for o, m in world.meshes.items()
                                                                   if o in bodies.values()}}
    finish_scene(tmp, final, gt, info, cam, meta)
    return {"frames": len(gt), "instances": sum(len(v) for v in gt.values()), "visible_instances": visible,
            "seconds": time.perf_counter() - t0}
