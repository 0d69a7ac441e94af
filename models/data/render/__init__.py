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

from models.data.meshes import MODEL_FILES, TEXTURE_FILE, Mesh, find_models, list_models, load_obj  # noqa: F401

from .bop_writer import may_be_occluded  # noqa: F401
from .builtin import builtin_models_dir  # noqa: F401
from .camera import camera_path, look_at, projected_bbox, projection_matrix_gl, silhouette, view_matrix_gl  # noqa: F401
from .cli import YCB_MODELS_DIR, default_models_dir, render_cmd  # noqa: F401
from .config import (COMMON_CAMERAS, ENGINES, LAYOUTS, ROBOT_DISTANCE, ROBOT_ELEVATION_DEG, TABLE_HALF,  # noqa: F401
                     YCBV_K, RenderConfig)
from .dataset import render_dataset  # noqa: F401
from .scene import World, build_scene, import_pybullet, place_robot, scene_camera, scene_rng  # noqa: F401
from .tiny import Backdrop, ToneCurve, random_texture, render_scene  # noqa: F401

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
