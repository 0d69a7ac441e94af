"""benchmarks/averaging.py: corrections averaged over box-jittered views and over models, on the tiny cube dataset."""

import json
from pathlib import Path

import numpy as np
import pytest

from models.evaluate.errors import evaluate_errors, torch_predictor
from tests.bench_scripts import load_benchmark
from tests.cube_dataset import make_cube_dataset


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """Two tiny models of one split (seeds 0 and 1) and one of another split, kept by data_scaling.py --save."""
    tmp = tmp_path_factory.mktemp("averaging")
    data = tmp / "cubes"
    make_cube_dataset(data, scenes=6, frames=20)
    study = load_benchmark("data_scaling")
    paths = []
    for seed, split_seed in ((0, 0), (1, 0), (0, 1)):
        out = tmp / f"s{seed}_{split_seed}.json"
        argv = ["--data", str(data), "--object", "003_cracker_box", "--modes", "scenes", "--sizes", "30", "--val",
                "10", "--test", "20", "--samples", "64", "--epoch-samples", "32", "--cache", str(tmp / "cache"),
                "--threads", "1", "--seed", str(seed), "--split-seed", str(split_seed),
                "--save", str(tmp / f"models_{seed}_{split_seed}"), "--json", str(out), "--quiet"]
        assert study.main(argv) == 0
        paths.append(json.loads(out.read_text())["rows"][0]["checkpoint"])
    return tmp, paths


def test_views_and_ensembles_on_the_same_test_crops(saved, capsys):
    tmp, (a, b, _) = saved
    out = tmp / "avg.json"
    bench = load_benchmark("averaging")
    assert bench.main([a, b, "--views", "3", "--cache", str(tmp / "cache"), "--threads", "1", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    rows = {(tuple(r["models"]), r["views"]): r for r in doc["rows"]}
    name_a, name_b = (f"{Path(x).parent.name}/{Path(x).name}" for x in (a, b))  # one file name in two folders
    assert set(rows) == {((name_a,), 1), ((name_a,), 3), ((name_b,), 1), ((name_b,), 3),
                         ((name_a, name_b), 1), ((name_a, name_b), 3)}
    assert rows[((name_a, name_b), 3)]["passes"] == 6
    # One view of one model is that model's own error, as data_scaling.py measured it on the same test crops.
    own = json.loads((tmp / "s0_0.json").read_text())["rows"][0]
    assert rows[((name_a,), 1)]["mean_deg"] == pytest.approx(own["mean_deg"], abs=1e-9)
    # Averages of a model with itself change nothing: the mean of identical rotations is that rotation.
    nets, test, frame, _ = bench.load_models([Path(a)] * 2, None, tmp / "cache")
    one = evaluate_errors(torch_predictor(nets[0]), test, rotation_frame=frame)
    twice = evaluate_errors(bench.averaged_predictor(nets, 1), test, rotation_frame=frame)
    np.testing.assert_allclose(twice.err_out_deg, one.err_out_deg, atol=1e-3)
    # Jittered views are the crop itself first, then changed copies of the same size.
    views = bench.jittered_views(test.crops[:4], 3)
    assert len(views) == 3 and np.array_equal(views[0], test.crops[:4])
    assert all(v.shape == test.crops[:4].shape and v.dtype == np.uint8 and not np.array_equal(v, views[0])
               for v in views[1:])
    assert "| " + name_a + " + " + name_b + " | 3 | 6 |" in capsys.readouterr().out


def test_models_of_other_splits_and_bad_views_are_refused(saved, capsys):
    tmp, (a, _, other) = saved
    bench = load_benchmark("averaging")
    with pytest.raises(SystemExit, match="its split .* is not that of"):
        bench.main([a, other, "--cache", str(tmp / "cache"), "--threads", "1"])
    with pytest.raises(SystemExit):
        bench.main([a, "--views", "1"])
    assert "expected view counts >= 2" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        bench.main([str(tmp / "missing.pt")])
    assert "no such checkpoint file(s)" in capsys.readouterr().err


def test_a_model_trained_on_more_scenes_of_the_same_split_joins_an_ensemble(saved, tmp_path):
    import shutil

    tmp, (a, _, _) = saved
    make_cube_dataset(tmp_path / "next", scenes=8, frames=20)
    (tmp_path / "more").mkdir()
    for s in ("000006", "000007"):  # new scene ids: the set's next scenes
        shutil.move(tmp_path / "next" / s, tmp_path / "more" / s)
    out = tmp_path / "grown.json"
    argv = ["--data", str(tmp / "cubes"), "--object", "003_cracker_box", "--modes", "scenes", "--sizes", "30", "--val",
            "10", "--test", "20", "--samples", "64", "--epoch-samples", "32", "--cache", str(tmp / "cache"),
            "--threads", "1", "--extra-train", str(tmp_path / "more"), "--save", str(tmp_path / "models"),
            "--json", str(out), "--quiet"]
    assert load_benchmark("data_scaling").main(argv) == 0
    grown = json.loads(out.read_text())["rows"][0]["checkpoint"]
    bench = load_benchmark("averaging")
    _, alone, _, _ = bench.load_models([Path(a)], None, tmp / "cache")
    _, together, _, _ = bench.load_models([Path(a), Path(grown)], None, tmp / "cache")
    np.testing.assert_array_equal(together.crops, alone.crops)


def test_runtime_views_run_the_exported_model_on_the_full_frames(saved, capsys):
    """--runtime: the checkpoint exported to ONNX and run by RefinerSession.refine(views=K) on the frames, with the
    coarse poses of the crop rows; one view there is the same model on the runtime's own crops of the same boxes."""
    tmp, (a, _, _) = saved
    out = tmp / "runtime.json"
    bench = load_benchmark("averaging")
    argv = [a, "--views", "3", "--runtime", "--cache", str(tmp / "cache"), "--threads", "1", "--json", str(out)]
    assert bench.main(argv) == 0
    rows = json.loads(out.read_text())["rows"]
    crops = {r["views"]: r for r in rows if r.get("path", "crops") == "crops"}
    runtime = {r["views"]: r for r in rows if r.get("path") == "runtime"}
    assert set(crops) == set(runtime) == {1, 3}
    # The same network (ONNX parity), crops and inputs: the same errors up to float32 and resampling rounding.
    assert runtime[1]["mean_deg"] == pytest.approx(crops[1]["mean_deg"], abs=0.05)
    assert runtime[1]["input_mean_deg"] == pytest.approx(crops[1]["input_mean_deg"], abs=1e-9)
    assert runtime[3]["passes"] == 3 and runtime[3]["mean_deg"] != runtime[1]["mean_deg"]
    assert "| runtime |" in capsys.readouterr().out


def test_evaluate_errors_settle_deg_stops_the_samples_a_later_iteration_barely_turns():
    """A predictor that halves each sample's error: iteration k turns it by e / 2^k. With settle_deg 3 the second
    iteration is kept where e / 4 > 3, the third where e / 8 > 3 (refiner_rt.session.settle_keeps), against the
    plain iterations (SciPy's composition gives the errors: halving along the same axis)."""
    from scipy.spatial.transform import Rotation

    from models.data.cropset import CropSet
    from refiner_rt import quaternion as rq

    n = 40
    q_gt = rq.from_xyzw(Rotation.random(n, random_state=4).as_quat())
    crops = np.zeros((n, 8, 8, 3), np.uint8)
    crops[:, 0, 0, 0] = np.arange(n)  # the row, for the predictor
    data = CropSet(crops, rq.canonical(q_gt), np.array(["003_cracker_box"] * n))

    def halve(c, q):
        rows = c[:, 0, 0, 0].astype(int)
        step = rq.multiply(rq.inverse(q), data.q_gt[rows])
        axis, angle = rq.to_axis_angle(step)
        return rq.from_axis_angle(axis, angle / 2)

    plain = evaluate_errors(halve, data, "uniform:10:30", seed=5, iterations=3)
    e = plain.err_in_deg
    np.testing.assert_allclose(plain.err_out_deg, e / 8, atol=1e-6)
    settled = evaluate_errors(halve, data, "uniform:10:30", seed=5, iterations=3, settle_deg=3.0)
    want = np.where(e / 8 > 3, e / 8, np.where(e / 4 > 3, e / 4, e / 2))
    np.testing.assert_allclose(settled.err_out_deg, want, atol=1e-6)
    assert ((e / 4 > 3) & (e / 8 <= 3)).any() and (e / 4 <= 3).any()  # every branch is taken
    with pytest.raises(ValueError, match="give iterations=2 or more"):
        evaluate_errors(halve, data, iterations=1, settle_deg=3.0)
