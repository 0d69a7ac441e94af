"""Cameras: look-at poses, the OpenGL matrices that reproduce a pinhole ``K``, projected silhouettes and boxes,
and the smooth camera path of a scene."""

from __future__ import annotations

import math

import cv2
import numpy as np

from models.data.meshes import Mesh

from .config import RenderConfig


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
    front &= (cam[f, 2] > 0.01).all(axis=1)  # triangles reaching behind a close camera would not project: left out
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
