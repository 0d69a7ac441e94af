"""Your own objects: a mesh the test writes (not a YCB id) renders, trains, exports and evaluates through the CLI
under its own name, with its mesh's SHA-256 in the model; BOP models/ folders (PLY in mm, vertex colours,
symmetries) load under their obj_id."""

import hashlib
import json

from click.testing import CliRunner
import numpy as np

from refiner_rt.cli import main
from tests.test_render import write_box_mesh

TINY = json.dumps({"input_size": 32, "conv_channels": [8, 8], "fuse_width": 64, "pose_widths": [32, 64],
                   "head_widths": [32, 16]})


def test_a_users_textured_mesh_renders_trains_and_evaluates_under_its_name(tmp_path):
    models = tmp_path / "meshes"
    write_box_mesh(models / "my_widget", size=(0.07, 0.04, 0.1), seed=3)
    runner = CliRunner()
    data = tmp_path / "widget"
    res = runner.invoke(main, ["render", "--out", str(data), "--models", str(models), "--frames", "24",
                               "--frames-per-scene", "8", "--width", "160", "--height", "120",
                               "--K", "200,200,79.5,59.5", "--quiet"], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    record = json.loads((data / "objects.json").read_text())
    sha = hashlib.sha256((models / "my_widget" / "textured.obj").read_bytes()).hexdigest()
    assert record == {"my_widget": {"obj_id": 1000, "mesh": {"file": "textured.obj", "sha256": sha, "unit": "m"}}}
    cam = json.loads((data / "000000" / "scene_camera.json").read_text())["0"]["cam_K"]
    assert cam == [200.0, 0.0, 79.5, 0.0, 200.0, 59.5, 0.0, 0.0, 1.0]

    out = tmp_path / "run" / "widget.pt"
    res = runner.invoke(main, ["train", "--data", str(data), "--objects", "my_widget", "--arch", "fusion", "--config",
                               TINY, "--base-per-object", "8", "--per-object", "4", "--val-per-object", "2",
                               "--test-per-object", "2", "--epochs-mse", "1", "--epochs-geodesic", "1",
                               "--batch-size", "8", "--device", "cpu", "--threads", "1", "--quiet", "--cache",
                               str(tmp_path / "cache"), "--out", str(out)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert out.with_name("widget.my_widget.pt").is_file()
    res = runner.invoke(main, ["export", str(out)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    from refiner_rt import RefinerSession

    for onnx in (out.with_suffix(".onnx"), out.with_name("widget.my_widget.onnx")):
        meta = RefinerSession(onnx).metadata
        assert meta["objects"] == ["my_widget"]
        assert json.loads(meta["meshes"])["my_widget"]["sha256"] == sha
    js = tmp_path / "eval.json"
    res = runner.invoke(main, ["eval", str(out.with_suffix(".onnx")), "--data", str(data), "--json", str(js),
                               "--cache", str(tmp_path / "cache"), "--threads", "1", "--quiet"],
                        catch_exceptions=False)
    assert res.exit_code == 0, res.output
    result = json.loads(js.read_text())
    assert set(result["objects"]) == {"my_widget"} and result["objects"]["my_widget"]["n"] == 2
    assert set(result["per_object_models"]) == {"my_widget"}


def test_a_bop_models_folder_in_mm_with_vertex_colours_and_symmetries(tmp_path):
    import trimesh

    from models.data import load_bop
    from models.data.meshes import find_models, list_models
    from models.data.render import RenderConfig, render_dataset

    write_box_mesh(tmp_path / "box", size=(0.06, 0.04, 0.1), n=2)
    from models.data.meshes import load_obj

    v, f = load_obj(tmp_path / "box" / "textured.obj")
    colours = np.random.default_rng(0).integers(0, 256, (len(v), 4), dtype=np.uint8)
    colours[:, 3] = 255
    bop = tmp_path / "models"
    bop.mkdir()
    trimesh.Trimesh(v * 1000.0, f, vertex_colors=colours, process=False).export(bop / "obj_000007.ply")
    flip = [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]  # a half turn about x
    (bop / "models_info.json").write_text(json.dumps({"7": {"diameter": 120.0, "symmetries_discrete": [flip]}}))
    assert list_models(bop) == ["obj_000007"]
    meshes = find_models(bop, ["obj_000007"], cache_dir=tmp_path / "cache")
    m = meshes["obj_000007"]
    assert m.number == 7 and m.unit == "mm" and m.symmetry == {"symmetries_discrete": [flip]}
    np.testing.assert_allclose(m.vertices, v, atol=1e-6)  # converted to metres
    K = ((200.0, 0.0, 79.5), (0.0, 200.0, 59.5), (0.0, 0.0, 1.0))
    out = tmp_path / "ds"
    cfg = RenderConfig(width=160, height=120, K=K, frames_per_scene=2, objects=("obj_000007",), objects_per_scene=(1, 1))
    render_dataset(out, 2, bop, cfg, seed=1, progress=False)
    record = json.loads((out / "objects.json").read_text())["obj_000007"]
    assert record["obj_id"] == 7 and record["mesh"]["unit"] == "mm" and record["symmetry"]["symmetries_discrete"]
    samples = load_bop(out)
    assert samples and {s.obj_id for s in samples} == {"obj_000007"}
    gt = json.loads((out / "000000" / "scene_gt.json").read_text())
    assert {g["obj_id"] for frame in gt.values() for g in frame} == {7}


def test_bad_camera_and_names_are_refused(tmp_path):
    res = CliRunner().invoke(main, ["render", "--out", str(tmp_path / "o"), "--K", "1,2,3"])
    assert res.exit_code == 2 and "fx,fy,cx,cy" in res.output
    res = CliRunner().invoke(main, ["render", "--out", str(tmp_path / "o"), "--objects", "a b"])
    assert res.exit_code == 2 and "object names" in res.output
    res = CliRunner().invoke(main, ["render", "--out", str(tmp_path / "o"), "--models", str(tmp_path), "--objects",
                                    "nothing_here", "--frames", "1", "--quiet"])
    assert res.exit_code == 1 and "no mesh for object 'nothing_here'" in res.output
