"""benchmarks/error_breakdown.py and the swing-twist split it uses, on the tiny cube dataset."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from models.evaluate.metrics import swing_twist_deg
from tests.bench_scripts import load_benchmark
from tests.cube_dataset import make_cube_dataset


def _wxyz(r: Rotation) -> np.ndarray:
    xyzw = r.as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)


@pytest.mark.parametrize("axis", [(0.0, 0.0, 1.0), (1.0, 2.0, -0.5)])
def test_swing_twist_recovers_the_angles_scipy_composed(axis):
    rng = np.random.default_rng(0)
    n = 500
    a = np.asarray(axis) / np.linalg.norm(axis)
    twist = rng.uniform(-179.0, 179.0, n)
    swing = np.concatenate([[1e-7, 0.0, 179.9], rng.uniform(0.0, 179.0, n - 3)])
    perp = np.cross(a, rng.normal(size=(n, 3)))  # swing axes perpendicular to the twist axis
    perp /= np.linalg.norm(perp, axis=1, keepdims=True)
    r = Rotation.from_rotvec(perp * np.radians(swing)[:, None]) * Rotation.from_rotvec(a * np.radians(twist)[:, None])
    q = _wxyz(r)
    for sign in (1.0, -1.0):  # q and -q are one rotation
        s, t = swing_twist_deg(sign * q, axis)
        np.testing.assert_allclose(s, swing, atol=1e-9)
        np.testing.assert_allclose(t, np.abs(twist), atol=1e-9)


def test_swing_twist_refuses_a_zero_axis():
    with pytest.raises(ValueError, match="axis must be 3 finite numbers, not all zero"):
        swing_twist_deg(np.array([1.0, 0, 0, 0]), (0, 0, 0))


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A tiny model kept by data_scaling.py --save, with the JSON that measured it."""
    tmp = tmp_path_factory.mktemp("breakdown")
    data = tmp / "cubes"
    make_cube_dataset(data, scenes=6, frames=20)
    out = tmp / "study.json"
    argv = ["--data", str(data), "--object", "003_cracker_box", "--modes", "scenes", "--sizes", "30", "--val", "10",
            "--test", "20", "--samples", "64", "--epoch-samples", "32", "--cache", str(tmp / "cache"),
            "--threads", "1", "--save", str(tmp / "models"), "--json", str(out), "--quiet"]
    assert load_benchmark("data_scaling").main(argv) == 0
    return tmp, json.loads(out.read_text())["rows"][0]


def test_breakdown_measures_each_part_and_splits_the_test_error(saved, capsys):
    tmp, row = saved
    out = tmp / "breakdown.json"
    argv = [row["checkpoint"], "--cache", str(tmp / "cache"), "--threads", "1", "--json", str(out)]
    assert load_benchmark("error_breakdown").main(argv) == 0
    doc = json.loads(out.read_text())
    assert doc["command"] == "python -m benchmarks.error_breakdown " + " ".join(argv)
    assert doc["machine"]["threads"] == 1 and doc["machine"]["torch"]  # a torch study records torch's threads and version
    r = doc["results"][0]
    parts = r["parts"]
    assert [parts[p]["n"] for p in ("train_base", "val", "test")] == [row["train_crops"], 10, 20]
    assert parts["test"]["mean_deg"] == pytest.approx(row["mean_deg"], abs=1e-6)  # data_scaling's own evaluation
    assert r["twist_axis"] == "viewing ray" and r["rotation_frame"] == "ray"
    for name in ("refined", "input"):
        s = r[f"test_{name}"]
        assert 0 <= s["in_plane_mean_deg"] and 0 <= s["out_of_plane_mean_deg"]
    # Inputs are at most 30 degrees off; each part of an error rotation is at most the whole, and together they
    # make it up (the angles of swing and twist sum to at least the total angle).
    assert r["test_input"]["in_plane_mean_deg"] <= parts["test"]["input_mean_deg"] + 1e-9
    assert r["test_input"]["out_of_plane_mean_deg"] <= parts["test"]["input_mean_deg"] + 1e-9
    assert (r["test_input"]["in_plane_mean_deg"] + r["test_input"]["out_of_plane_mean_deg"]
            >= parts["test"]["input_mean_deg"] - 1e-9)
    printed = capsys.readouterr().out
    assert f"| {r['checkpoint'].split('/')[-1]} | scenes | {parts['train_base']['mean_deg']:.2f} |" in printed


def test_breakdown_names_a_missing_checkpoint(tmp_path, capsys):
    with pytest.raises(SystemExit):
        load_benchmark("error_breakdown").main([str(tmp_path / "none.pt")])
    assert "no such checkpoint file(s)" in capsys.readouterr().err
