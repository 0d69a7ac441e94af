"""benchmarks/pose_coverage.py: nearest-training-rotation angles against SciPy, hand-built splits, a BOP folder."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from models.data import Sample, SplitSizes, make_splits
from tests.bench_scripts import load_benchmark
from tests.cube_dataset import make_cube_dataset

K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])


def _load():
    return load_benchmark("pose_coverage")


def _wxyz(r: Rotation) -> np.ndarray:
    xyzw = np.atleast_2d(r.as_quat())
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)


def _sample(R, box, scene=0, frame=0, obj="003_cracker_box") -> Sample:
    return Sample(image_path=f"/d/{scene:06d}/rgb/{frame:06d}.png", obj_id=obj, R=R, t=[0.0, 0.0, 1.0],
                  box_xyxy=box, K=K, image_size=(640, 480), scene_id=f"{scene:06d}", frame_id=frame,
                  visib_fract=1.0, dataset="/d")


def test_nearest_angles_match_scipy_brute_force_and_ignore_quaternion_sign():
    cov = _load()
    query, ref = Rotation.random(40, random_state=1), Rotation.random(25, random_state=2)
    expected = np.array([np.degrees((ref.inv() * query[i]).magnitude()).min() for i in range(len(query))])
    q, r = _wxyz(query), _wxyz(ref)
    r[::2] *= -1  # q and -q are the same rotation
    np.testing.assert_allclose(cov.nearest_angles(q, r, chunk=7), expected, atol=1e-6)
    assert cov.nearest_angles(r, r).max() < 1e-4


def test_nearest_angles_reject_bad_shapes_and_an_empty_reference():
    cov = _load()
    with pytest.raises(ValueError, match=r"reference must be \(N, 4\)"):
        cov.nearest_angles(np.zeros((3, 4)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="nothing to be near"):
        cov.nearest_angles(np.zeros((3, 4)), np.zeros((0, 4)))


def test_ray_frame_rotation_removes_the_smallest_rotation_onto_the_box_ray():
    cov = _load()
    R = Rotation.from_euler("xyz", [20, -35, 50], degrees=True)
    centred = _sample(R.as_matrix(), [300.0, 220.0, 340.0, 260.0])   # centre (320, 240): on the optical axis
    off = _sample(R.as_matrix(), [500.0, 50.0, 560.0, 110.0])
    got = cov.ray_frame_rotations([centred, off])
    u, v = 530.0 - 0.5, 80.0 - 0.5
    d = np.linalg.solve(K, [u, v, 1.0])
    d /= np.linalg.norm(d)
    axis = np.cross([0.0, 0.0, 1.0], d)
    ray = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.arccos(d[2]))
    for q, expected in zip(got, [R, ray.inv() * R]):
        assert np.degrees((Rotation.from_quat(np.r_[q[1:], q[0]]).inv() * expected).magnitude()) < 1e-6


def test_frames_split_finds_twins_that_the_scenes_split_holds_out():
    """Static scenes: every frame of a scene shows one rotation, so frames-split test crops have exact twins in
    training, and scenes-split ones are as far as the nearest other scene's rotation."""
    cov = _load()
    scene_rot = Rotation.random(12, random_state=3)
    box = [300.0, 220.0, 340.0, 260.0]
    samples = [_sample(scene_rot[s].as_matrix(), box, scene=s, frame=f) for s in range(12) for f in range(10)]
    sizes = SplitSizes(train_base=40, train_finetune=20, val=20, test=20)
    frames = cov.split_coverage(make_splits(samples, mode="frames", sizes=sizes, seed=0))
    assert frames["003_cracker_box"]["mean_deg"] < 1e-4 and frames["003_cracker_box"]["under_2_deg"] == 1.0

    splits = make_splits(samples, mode="scenes", sizes=sizes, seed=0)
    row = cov.split_coverage(splits)["003_cracker_box"]
    train_scenes = sorted({int(s.scene_id) for s in splits.train})
    expected = [np.degrees((scene_rot[train_scenes].inv() * scene_rot[int(s.scene_id)]).magnitude()).min()
                for s in splits.test]
    assert row["n"] == len(splits.test) and row["train"] == len(splits.train)
    assert row["train_scenes"] == len(train_scenes) and row["test_scenes"] == len({s.scene_id for s in splits.test})
    assert row["mean_deg"] == pytest.approx(np.mean(expected), abs=1e-5) and row["mean_deg"] > 1.0
    assert row["median_deg"] == pytest.approx(np.median(expected), abs=1e-5)


def test_cli_writes_both_modes_for_a_bop_folder(tmp_path, capsys):
    cov = _load()
    make_cube_dataset(tmp_path / "cubes", scenes=6, frames=10)
    out = tmp_path / "coverage.json"
    assert cov.main(["--data", str(tmp_path / "cubes"), "--sizes", "20,10,5,10", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert set(doc["modes"]) == {"frames", "scenes"} and doc["sizes"] == [20, 10, 5, 10]
    for block in doc["modes"].values():
        rows = block["per_object"].values()
        assert len(rows) == 2 and all(r["n"] > 0 and r["mean_deg"] >= 0 for r in rows)
        assert block["average"]["mean_deg"] == pytest.approx(np.mean([r["mean_deg"] for r in rows]))
    assert "| scenes | **average** |" in capsys.readouterr().out
    assert doc["command"].startswith("python ")


@pytest.mark.parametrize("sizes", ["3000,5000", "a,b,c,d", "3000,5000,3000,0", "0,0,10,10"])
def test_cli_names_bad_sizes(tmp_path, sizes):
    cov = _load()
    with pytest.raises(SystemExit, match="--sizes: expected train_base,train_finetune,val,test"):
        cov.main(["--data", str(tmp_path), "--sizes", sizes])


def test_cli_names_an_unknown_split_mode(tmp_path):
    cov = _load()
    make_cube_dataset(tmp_path / "cubes", scenes=2, frames=4)
    with pytest.raises(SystemExit, match="--modes sideways: .*mode must be one of"):
        cov.main(["--data", str(tmp_path / "cubes"), "--sizes", "4,0,0,2", "--modes", "sideways"])


def test_cli_names_a_missing_dataset_folder(tmp_path):
    cov = _load()
    with pytest.raises(SystemExit, match=r"--data .*nowhere: dataset folder not found"):
        cov.main(["--data", str(tmp_path / "nowhere")])


def test_a_turn_about_the_ray_moves_the_rotation_but_not_the_viewing_direction():
    """A query rotated about the viewing ray by 40 deg from its only reference is 40 deg away in rotation and 0 in
    viewing direction; one tilted about the image x axis by 25 deg is 25 deg away in both (SciPy's rotations)."""
    cov = _load()
    R = Rotation.from_euler("xyz", [30, -20, 75], degrees=True)
    box = [300.0, 220.0, 340.0, 260.0]  # on the optical axis: the ray frame is the camera frame
    rolled = Rotation.from_euler("z", 40, degrees=True) * R
    tilted = Rotation.from_euler("x", 25, degrees=True) * R
    query = [_sample(rolled.as_matrix(), box), _sample(tilted.as_matrix(), box)]
    out = cov.query_coverage(query, {"train": [_sample(R.as_matrix(), box)]})["train"]["003_cracker_box"]
    assert out["n"] == 2 and out["reference"] == 1
    assert out["rotation"]["max_deg"] == pytest.approx(40.0, abs=1e-4)
    assert out["rotation"]["mean_deg"] == pytest.approx(32.5, abs=1e-4)
    assert out["direction"]["mean_deg"] == pytest.approx(12.5, abs=1e-4)  # 0 and 25
    # The direction is the camera's, seen from the object: R^T (0, 0, -1), against SciPy.
    d = cov.viewing_directions(_wxyz(R))[0]
    np.testing.assert_allclose(d, R.inv().apply([0.0, 0.0, -1.0]), atol=1e-12)


def test_query_cli_measures_one_folder_against_another(tmp_path, capsys):
    cov = _load()
    make_cube_dataset(tmp_path / "train", scenes=4, frames=6)
    make_cube_dataset(tmp_path / "query", scenes=2, frames=3, seed=7)
    out = tmp_path / "q.json"
    assert cov.main(["--data", str(tmp_path / "train"), "--query", str(tmp_path / "query"), "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["query"] == "query" and "--query REAL" in doc["command"]  # no machine path recorded
    rows = doc["coverage"]["train"]
    assert rows and all(r["n"] > 0 and 0 <= r["direction"]["max_deg"] <= r["rotation"]["max_deg"] + 1e-6
                        for r in rows.values())
    assert "| train |" in capsys.readouterr().out
    # Itself as the training set: every query instance has a twin.
    assert cov.main(["--data", str(tmp_path / "query"), "--query", str(tmp_path / "query")]) == 0
    assert "| query | " in capsys.readouterr().out


def test_several_data_folders_need_a_query(tmp_path):
    cov = _load()
    with pytest.raises(SystemExit):
        cov.main(["--data", str(tmp_path / "a"), "--data", str(tmp_path / "b")])


def test_neighbours_count_the_reference_instances_within_ten_degrees():
    cov = _load()
    box = [300.0, 220.0, 340.0, 260.0]
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)
    refs = [Rotation.from_euler("z", a, degrees=True) * R for a in (3, 8, 12, 40)]  # 2 within 10 deg in rotation
    out = cov.query_coverage([_sample(R.as_matrix(), box)], {"t": [_sample(r.as_matrix(), box) for r in refs]})
    row = out["t"]["003_cracker_box"]
    assert row["rotation"]["neighbours_median"] == 2 and row["direction"]["neighbours_median"] == 4
