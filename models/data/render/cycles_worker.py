"""Blender Cycles worker: renders the frames of one scene described by a JSON job, under Blender's own Python (``bpy``).

Run as a script by :mod:`models.data.render.cycles` (``BLENDER_PYTHON cycles_worker.py JOB.json``), never imported by
the package: ``bpy`` needs ``numpy < 2`` and lives in an interpreter of its own. It uses only ``bpy`` and the standard
library. The job (all lengths in metres, matrices row-major 4x4, world frame z up):

* ``objects``: ``{"obj": OBJ path, "texture": image path, "matrix": mesh-to-world, "roughness", "specular"}`` (the
  OBJ's material, or the texture where it names none; its coordinates kept as they are: forward ``Y``, up ``Z``),
  optionally ``"gain_rgb"``: a colour multiplied into the base colour (the object's appearance in this scene);
* ``table``: ``{"half": half side, "texture": image path, "roughness"}``, a textured square at z = 0 (or null);
* ``transparent``: objects on a transparent film, written RGBA (to check the images against the ground truth);
* ``world``: ``{"hdr": file name in Blender's studiolights/world, "strength", "rotation"}``: light and background;
* ``lights``: area lights ``{"matrix", "size", "power" (W), "colour"}``;
* ``camera``: ``{"K": 3x3, "width", "height", "scale"}`` (the image is rendered at ``scale`` of the size);
* ``frames``: ``{"cam_to_world"}`` per frame (Blender's camera: looking down its -z, y up), optionally
  ``"regions"``: ``{"percentage", "border": [x0, y0, x1, y1]}`` rendered alone after the frame (the border in the
  pixels of the image at that percentage, top-left origin), written ``NNNNNN_rK.png``;
* ``samples``, ``seed``, ``threads``, ``out`` (folder of ``NNNNNN.png``).
"""

import json
import os
import sys

# This script runs inside Blender's own Python, started with this file's folder first on sys.path; that folder holds
# modules (cycles.py, config.py, ...) that would shadow Blender's own add-ons, so it comes off the path (the one
# sys.path edit in the repository; tests/test_layout_training.py allows it).
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != os.path.dirname(os.path.abspath(__file__))]

import bpy  # noqa: E402
from mathutils import Matrix  # noqa: E402


def _principled(material):
    for node in material.node_tree.nodes if material and material.use_nodes else ():
        if node.type == "BSDF_PRINCIPLED":
            return node
    return None


def _set_input(node, names, value):
    for name in names:  # input names changed between Blender versions
        if name in node.inputs:
            node.inputs[name].default_value = value
            return


def _import_object(spec):
    before = set(bpy.data.objects)
    bpy.ops.wm.obj_import(filepath=spec["obj"], forward_axis="Y", up_axis="Z")
    new = [o for o in bpy.data.objects if o not in before]
    for ob in new:
        ob.matrix_world = Matrix(spec["matrix"])
        if not ob.material_slots:
            ob.data.materials.append(bpy.data.materials.new("surface"))
        for slot in ob.material_slots:
            if slot.material is None:
                slot.material = bpy.data.materials.new("surface")
            slot.material.use_nodes = True
            bsdf = _principled(slot.material)
            if bsdf is None:
                continue
            tree = slot.material.node_tree
            if spec.get("texture") and not any(n.type == "TEX_IMAGE" for n in tree.nodes):
                tex = tree.nodes.new("ShaderNodeTexImage")  # no texture from the OBJ's material: the mesh's own
                tex.image = bpy.data.images.load(spec["texture"])
                tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
            _set_input(bsdf, ("Roughness",), spec["roughness"])
            _set_input(bsdf, ("Specular IOR Level", "Specular"), spec["specular"])
            if spec.get("gain_rgb"):
                _multiply_base_colour(tree, bsdf, spec["gain_rgb"])


def _multiply_base_colour(tree, bsdf, gain):
    """The base colour (the texture's, or the constant) times ``gain`` (r, g, b): a vector multiply between them."""
    mul = tree.nodes.new("ShaderNodeVectorMath")
    mul.operation = "MULTIPLY"
    mul.inputs[1].default_value = tuple(gain)
    base = bsdf.inputs["Base Color"]
    if base.is_linked:
        link = base.links[0]
        tree.links.new(link.from_socket, mul.inputs[0])
        tree.links.remove(link)
    else:
        mul.inputs[0].default_value = tuple(base.default_value)[:3]
    tree.links.new(mul.outputs["Vector"], base)


def _table(spec):
    bpy.ops.mesh.primitive_plane_add(size=2 * spec["half"], location=(0.0, 0.0, 0.0))
    plane = bpy.context.active_object
    mat = bpy.data.materials.new("table")
    mat.use_nodes = True
    bsdf = _principled(mat)
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = bpy.data.images.load(spec["texture"])
    mat.node_tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    _set_input(bsdf, ("Roughness",), spec["roughness"])
    plane.data.materials.append(mat)


def _world(spec):
    world = bpy.data.worlds.new("world")
    bpy.context.scene.world = world
    world.use_nodes = True
    nodes, links = world.node_tree.nodes, world.node_tree.links
    background = next(n for n in nodes if n.type == "BACKGROUND")
    env = nodes.new("ShaderNodeTexEnvironment")
    folder = bpy.utils.system_resource("DATAFILES", path="studiolights/world")
    env.image = bpy.data.images.load(os.path.join(folder, spec["hdr"]))
    mapping = nodes.new("ShaderNodeMapping")
    coords = nodes.new("ShaderNodeTexCoord")
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, spec["rotation"])
    links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
    links.new(mapping.outputs["Vector"], env.inputs["Vector"])
    links.new(env.outputs["Color"], background.inputs["Color"])
    background.inputs["Strength"].default_value = spec["strength"]


def _light(spec, index):
    data = bpy.data.lights.new(f"area{index}", type="AREA")
    data.size = spec["size"]
    data.energy = spec["power"]
    data.color = spec["colour"]
    ob = bpy.data.objects.new(f"area{index}", data)
    bpy.context.scene.collection.objects.link(ob)
    ob.matrix_world = Matrix(spec["matrix"])


def _camera(spec):
    scene = bpy.context.scene
    K, w, h = spec["K"], spec["width"], spec["height"]
    data = bpy.data.cameras.new("camera")
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = 36.0
    data.lens = K[0][0] * data.sensor_width / w
    # OpenCV puts pixel centres at integers, Blender at half-integers; shifts are in units of the image width.
    data.shift_x = (w / 2.0 - (K[0][2] + 0.5)) / w
    data.shift_y = ((K[1][2] + 0.5) - h / 2.0) / w
    data.clip_start, data.clip_end = 0.02, 20.0
    ob = bpy.data.objects.new("camera", data)
    scene.collection.objects.link(ob)
    scene.camera = ob
    scene.render.resolution_x, scene.render.resolution_y = w, h
    scene.render.resolution_percentage = max(1, int(round(100 * spec["scale"])))
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0  # square pixels (the engine checks fx = fy)
    return ob


def _render_region(scene, region, path):
    """One region alone: the border (pixels of the image at the region's percentage, top-left origin) as Blender's
    fractions (bottom-left origin), nudged inside so that its integer pixel bounds are the ones given."""
    r = scene.render
    r.resolution_percentage = region["percentage"]
    w, h = r.resolution_x * region["percentage"] // 100, r.resolution_y * region["percentage"] // 100
    x0, y0, x1, y1 = region["border"]
    eps = 1e-4
    r.border_min_x, r.border_max_x = (x0 + eps) / w, (x1 + eps) / w
    r.border_min_y, r.border_max_y = (h - y1 + eps) / h, (h - y0 + eps) / h
    r.use_border = r.use_crop_to_border = True
    r.filepath = path
    bpy.ops.render.render(write_still=True)


def main(path):
    job = json.loads(open(path).read())
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.preferences.addon_enable(module="cycles")  # the factory settings leave the Cycles add-on off
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = job["samples"]
    scene.cycles.use_adaptive_sampling = True
    scene.cycles.use_denoising = True
    scene.cycles.denoiser = "OPENIMAGEDENOISE"
    scene.cycles.seed = job["seed"]
    scene.cycles.max_bounces = 4
    scene.render.threads_mode = "FIXED"
    scene.render.threads = max(1, job["threads"])
    scene.render.use_persistent_data = True  # the scene's BVH and textures kept between a frame's renders
    scene.render.image_settings.file_format = "PNG"
    transparent = bool(job.get("transparent"))  # objects only, on a transparent film (alignment checks)
    scene.render.image_settings.color_mode = "RGBA" if transparent else "RGB"
    scene.view_settings.view_transform = "Standard"
    scene.render.film_transparent = transparent
    for spec in job["objects"]:
        _import_object(spec)
    if job.get("table"):
        _table(job["table"])
    _world(job["world"])
    for i, spec in enumerate(job["lights"]):
        _light(spec, i)
    cam = _camera(job["camera"])
    os.makedirs(job["out"], exist_ok=True)
    full = scene.render.resolution_percentage
    for i, frame in enumerate(job["frames"]):
        cam.matrix_world = Matrix(frame["cam_to_world"])
        scene.render.use_border = scene.render.use_crop_to_border = False
        scene.render.resolution_percentage = full
        scene.render.filepath = os.path.join(job["out"], f"{i:06d}.png")
        bpy.ops.render.render(write_still=True)
        for k, region in enumerate(frame.get("regions", ())):
            _render_region(scene, region, os.path.join(job["out"], f"{i:06d}_r{k}.png"))
    print(json.dumps({"frames": len(job["frames"]), "blender": bpy.app.version_string}))


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: cycles_worker.py JOB.json")
    main(sys.argv[1])
    sys.stdout.flush()
    os._exit(0)  # bpy's atexit handlers can take seconds; nothing is left to write
