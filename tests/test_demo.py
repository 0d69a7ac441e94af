"""`refiner-rt demo`: the sample frames and their ground truth, the coarse rotations, the table and picture (with
constant-output stand-in models, and with the shipped models when any ship), the user-image mode and bad options."""

import re

from click.testing import CliRunner
import cv2
import numpy as np
import pytest

from refiner_rt import demo
from refiner_rt import pretrained as pt
from refiner_rt import quaternion as rq
from refiner_rt.cli import main
from refiner_rt.draw import project
from tests.test_pretrained import weights  # noqa: F401  (fixture: two constant-output models in place of the shipped ones)

PAPER_OBJECTS = ("002_master_chef_can", "003_cracker_box", "004_sugar_box", "006_mustard_bottle", "009_gelatin_box",
                 "011_banana", "021_bleach_cleanser", "035_power_drill", "037_scissors")
SHIPPED = pt.pretrained_models()
FRAMES = demo.load_samples()


def _table(output: str) -> dict[str, list[str]]:
    """The demo's table rows by object: [n, input deg, refined deg, ms]."""
    rows = {}
    for line in output.splitlines():
        cells = line.split()
        if len(cells) == 5 and re.fullmatch(r"\d+", cells[1]):
            rows[cells[0]] = cells[1:]
    return rows


# ------------------------------------------------------------------------------------------------- sample data
def test_samples_show_all_nine_objects_and_stay_small():
    shown = {o.object_id for f in FRAMES for o in f.objects if o.visib_fract >= 0.5}
    assert shown == set(PAPER_OBJECTS)
    files = [f.path for f in FRAMES]
    assert all(p.suffix == ".jpg" for p in files) and sum(p.stat().st_size for p in files) < 3e6
    for f in FRAMES:
        image = f.image()
        h, w = image.shape[:2]
        assert f.K[2].tolist() == [0, 0, 1] and f.K[0, 0] > 0 and f.K[1, 1] > 0
        for o in f.objects:
            x1, y1, x2, y2 = o.box_xyxy
            assert 0 <= x1 < x2 <= w and 0 <= y1 < y2 <= h
            assert abs(np.linalg.norm(o.q_gt) - 1) < 1e-6 and o.q_gt[0] >= 0


def test_ground_truth_puts_each_outline_on_its_box():
    """The samples' rotations and translations (object to camera, scan frame) project each object's outline points
    onto its visible box: the conversions from BOP (row-major cam_R_m2c, mm, [x, y, w, h]) are right."""
    outlines = demo.load_outlines()
    assert set(outlines) == set(PAPER_OBJECTS)
    for f in FRAMES:
        for o in f.objects:
            uv, z = project(outlines[o.object_id].points_m, rq.to_matrix(o.q_gt), o.t_m, f.K)
            assert (z > 0.2).all()
            lo, hi = uv.min(axis=0) + 0.5, uv.max(axis=0) + 0.5  # OpenCV pixel centres -> continuous coordinates
            ix = np.clip(np.minimum(hi, o.box_xyxy[2:]) - np.maximum(lo, o.box_xyxy[:2]), 0, None)
            inter = ix[0] * ix[1]
            box_area = np.prod(o.box_xyxy[2:] - o.box_xyxy[:2])
            assert inter / box_area > 0.9, (f.path.name, o.object_id)  # the visible box lies inside the projection


def test_coarse_rotations_are_u0_30_around_the_truth_and_fixed_by_the_seed():
    a, b, c = (demo.coarse_rotations(FRAMES, seed) for seed in (0, 0, 1))
    for f, qa, qb, qc in zip(FRAMES, a, b, c):
        q_gt = np.array([o.q_gt for o in f.objects])
        angles = rq.geodesic_angle(qa, q_gt)
        assert np.all(angles <= 30 + 1e-9) and np.array_equal(qa, qb) and not np.allclose(qa, qc)


# ------------------------------------------------------------------------------------------------- the command
def test_demo_prints_the_table_and_writes_the_picture(weights, tmp_path):  # noqa: F811
    out = tmp_path / "new" / "folder" / "demo.png"  # missing folders are made (refiner_rt.cli.prepare_output)
    res = CliRunner().invoke(main, ["demo", "--out", str(out)])
    assert res.exit_code == 0, res.output
    rows = _table(res.output)
    assert set(rows) == {"003_cracker_box", "011_banana", "all"}
    n = sum(1 for f in FRAMES for o in f.objects if o.object_id in ("003_cracker_box", "011_banana"))
    assert int(rows["all"][0]) == n
    for cells in rows.values():  # the stand-in models output the identity: refined = coarse
        assert cells[1] == cells[2] and 0 < float(cells[1]) <= 30 and float(cells[3]) > 0
    assert "No shipped model for these, skipped: 002_master_chef_can" in res.output
    picture = cv2.imread(str(out))
    assert picture is not None and picture.shape[1] > 2 * demo.PANEL and picture.shape[0] > demo.PANEL


def test_demo_without_models_says_so(tmp_path, monkeypatch):
    monkeypatch.setattr(pt, "WEIGHTS_DIR", tmp_path)
    res = CliRunner().invoke(main, ["demo", "--out", str(tmp_path / "d.png")])
    assert res.exit_code == 1 and "no pretrained models ship" in res.output and "Traceback" not in res.output


def test_demo_on_your_own_image(weights, tmp_path):  # noqa: F811
    frame = next(f for f in FRAMES if any(o.object_id == "003_cracker_box" for o in f.objects))
    obj = next(o for o in frame.objects if o.object_id == "003_cracker_box")
    fx, fy, cx, cy = frame.K[0, 0], frame.K[1, 1], frame.K[0, 2], frame.K[1, 2]
    out = tmp_path / "mine.png"
    res = CliRunner().invoke(main, ["demo", "--image", str(frame.path), "--box", ",".join(map(str, obj.box_xyxy)),
                                    "--q", ",".join(map(str, obj.q_gt)), "--K", f"{fx},{fy},{cx},{cy}",
                                    "--object", "003_cracker_box", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "refined q (wxyz)" in res.output and "0.0 deg from the coarse one" in res.output
    picture = cv2.imread(str(out))
    image = frame.image()
    h, w = image.shape[:2]
    # the image under a legend band naming the colours
    assert picture.shape == (h + 34, max(w, 560), 3) and not np.array_equal(picture[34:, :w], image)
    band = picture[:34]
    assert (np.abs(band.astype(int) - demo.COLOURS["coarse"]).sum(axis=2) < 40).any()
    assert (np.abs(band.astype(int) - demo.COLOURS["refined"]).sum(axis=2) < 40).any()


@pytest.mark.parametrize("args, message", [
    (["--box", "1,2,3,4"], "--box: only with --image FILE (these options describe your own image)"),
    (["--image", "IMG"], "--image needs --box, --q, --K, --object"),
    (["--image", "IMG", "--box", "1,2,3", "--q", "1,0,0,0", "--K", "1,1,1,1", "--object", "003_cracker_box"],
     "expected 4 comma-separated numbers x1,y1,x2,y2; got '1,2,3'"),
    (["--image", "IMG", "--box", "10,10,50,50", "--q", "1,0,0,zero", "--K", "1,1,1,1", "--object", "003_cracker_box"],
     "expected 4 comma-separated numbers w,x,y,z"),
    (["--image", "IMG", "--box", "10,10,50,50", "--q", "1,0,0,0", "--K", "0,500,320,240", "--object", "003_cracker_box"],
     "fx, fy must be > 0"),
    (["--image", "IMG", "--box", "10,10,50,50", "--q", "0,0,0,0", "--K", "500,500,320,240", "--object", "003_cracker_box"],
     "expected a non-zero quaternion"),
    (["--image", "IMG", "--box", "50,10,10,50", "--q", "1,0,0,0", "--K", "500,500,320,240", "--object", "003_cracker_box"],
     "expected x1 < x2 and y1 < y2"),
    (["--image", "IMG", "--box", "900,10,950,50", "--q", "1,0,0,0", "--K", "500,500,320,240", "--object", "003_cracker_box"],
     "lies outside the 640x480 image"),
    (["--image", "IMG", "--box", "10,10,50,50", "--q", "1,0,0,0", "--K", "500,500,320,240", "--object", "024_bowl"],
     "no shipped model for '024_bowl'; shipped: 003_cracker_box, 011_banana"),
    (["--image", "NOTIMG", "--box", "10,10,50,50", "--q", "1,0,0,0", "--K", "500,500,320,240", "--object", "011_banana"],
     "is not an image OpenCV can read"),
    (["--out", "NOTIMG/d.png"], "cannot create the folder"),  # a file where the folder would be
])
def test_bad_options_are_one_line_errors(weights, tmp_path, args, message):  # noqa: F811
    notimg = tmp_path / "notes.png"
    notimg.write_text("not an image")
    args = [str(FRAMES[0].path) if a == "IMG" else str(notimg) + a[len("NOTIMG"):] if a.startswith("NOTIMG") else a
            for a in args]
    res = CliRunner().invoke(main, ["demo", *args])
    assert res.exit_code == 2, res.output
    assert message in res.output and "Traceback" not in res.output


# ------------------------------------------------------------------------------------------------- shipped models
@pytest.mark.skipif(not SHIPPED, reason="no pretrained model ships in this checkout")
def test_demo_with_the_shipped_models_refines(tmp_path):
    """The shipped models bring the sample frames' coarse rotations closer to the truth, on average."""
    res = CliRunner().invoke(main, ["demo", "--out", str(tmp_path / "demo.png")])
    assert res.exit_code == 0, res.output
    rows = _table(res.output)
    assert set(rows) - {"all"} == {m.object_id for m in SHIPPED}
    assert float(rows["all"][2]) < float(rows["all"][1])


@pytest.mark.skipif(not any("fine" in m.stages for m in SHIPPED), reason="no fine refiner ships in this checkout")
def test_demo_with_the_cascade_refines_as_the_shipped_cascades_do(tmp_path):
    """--cascade: each object's RefinerCascade.pretrained where a fine refiner ships, the same numbers as refining the
    samples with those cascades; on your own image too."""
    from refiner_rt import RefinerCascade

    res = CliRunner().invoke(main, ["demo", "--cascade", "--out", str(tmp_path / "demo.png")])
    assert res.exit_code == 0, res.output
    assert "the shipped INT8 cascades (coarse and fine refiners)" in res.output
    rows = _table(res.output)
    fine = {m.object_id for m in SHIPPED if "fine" in m.stages}
    cascades = {o: RefinerCascade.pretrained(o) for o in fine}
    want = demo.refine_samples(FRAMES, cascades, seed=0, timed_calls=1)
    for obj in fine & set(rows):
        errors = [r.refined_error_deg for r in want if r.object_id == obj]
        assert rows[obj][2] == f"{np.mean(errors):.1f}"
    frame = next(f for f in FRAMES if any(o.object_id in fine for o in f.objects))
    obj = next(o for o in frame.objects if o.object_id in fine)
    fx, fy, cx, cy = frame.K[0, 0], frame.K[1, 1], frame.K[0, 2], frame.K[1, 2]
    res = CliRunner().invoke(main, ["demo", "--cascade", "--image", str(frame.path), "--box",
                                    ",".join(map(str, obj.box_xyxy)), "--q", ",".join(map(str, obj.q_gt)),
                                    "--K", f"{fx},{fy},{cx},{cy}", "--object", obj.object_id,
                                    "--out", str(tmp_path / "mine.png")])
    assert res.exit_code == 0, res.output
    q_ref = cascades[obj.object_id].refine(frame.image(), obj.box_xyxy[None], obj.q_gt[None], K=frame.K).q_refined[0]
    assert f"refined q (wxyz) {np.array2string(q_ref, precision=4, separator=', ')}" in res.output
