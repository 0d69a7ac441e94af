"""The appearance benchmark (models/evaluate/appearance.py, run by benchmarks/appearance.py): the stressed copies are the frames through the training
augmentation's own operations, reused when unchanged; a model that ignores the pixels pays nothing for any case, one
that reads them pays for a change of its input; the gap and the rendered sets' ratio add up."""

import json

import cv2
import numpy as np
import pytest

from tests.data_fixtures import make_bop
from tests.onnx_fixtures import channel_mean_model, constant_model, contract


@pytest.fixture(scope="module")
def real_folder(tmp_path_factory):
    split = tmp_path_factory.mktemp("real") / "test"
    make_bop(split)
    return split


@pytest.fixture(scope="module")
def appearance():
    from models.evaluate import appearance

    return appearance


def test_every_stress_case_is_an_operation_of_the_augmentation(appearance):
    from models.data.augment import PHOTOMETRIC_OPS

    assert {op for _, op, _ in appearance.STRESS_CASES} <= set(PHOTOMETRIC_OPS)
    assert len({name for name, _, _ in appearance.STRESS_CASES}) == len(appearance.STRESS_CASES)


def test_stressed_copy_is_the_operation_on_every_frame_and_is_reused(appearance, real_folder, tmp_path):
    out = appearance.stressed_copy(real_folder, tmp_path / "dark", "brightness", 0.6)
    originals = sorted(real_folder.glob("*/rgb/*"))
    copies = sorted(out.glob("*/rgb/*"))
    assert [p.stem for p in copies] == [p.stem for p in originals] and all(p.suffix == ".png" for p in copies)
    for a, b in zip(originals, copies):
        image = cv2.imread(str(a), cv2.IMREAD_COLOR).astype(np.float32)
        np.testing.assert_array_equal(cv2.imread(str(b), cv2.IMREAD_COLOR),
                                      np.clip(image * np.float32(0.6), 0, 255).round().astype(np.uint8))
    for gt in real_folder.glob("*/scene_gt*.json"):
        assert (out / gt.parent.name / gt.name).read_text() == gt.read_text()
    stamp = copies[0].stat().st_mtime_ns
    appearance.stressed_copy(real_folder, tmp_path / "dark", "brightness", 0.6)
    assert copies[0].stat().st_mtime_ns == stamp  # the same case: reused
    appearance.stressed_copy(real_folder, tmp_path / "dark", "brightness", 0.5)
    assert json.loads((out / "stress.json").read_text())["strength"] == 0.5  # another strength: rebuilt


def _write(tmp_path, name, data: bytes):
    path = tmp_path / name
    path.write_bytes(data)
    return path


def test_a_model_blind_to_pixels_pays_nothing_and_one_that_reads_them_pays(appearance, real_folder, tmp_path):
    cases = (("exposure -0.7 EV", "brightness", 0.6), ("unchanged", "brightness", 1.0))
    blind = {"003_cracker_box": _write(tmp_path, "blind.onnx",
                                       constant_model([0.98, 0.2, 0.0, 0.0], props=contract()))}
    s = appearance.run_stress(blind, real_folder, tmp_path / "work", draws=3, seed=0, cases=cases, progress=False)
    assert [r["cost_deg"] for r in s["cases"]] == pytest.approx([0.0, 0.0], abs=1e-9)
    reader = {"003_cracker_box": _write(tmp_path, "reader.onnx", channel_mean_model(props=contract()))}
    s = appearance.run_stress(reader, real_folder, tmp_path / "work", draws=3, seed=0, cases=cases, progress=False)
    dark, same = s["cases"]
    assert abs(dark["cost_deg"]) > 0.1  # the crops' means changed, so did the output
    assert same["cost_deg"] == pytest.approx(0.0, abs=1e-9)
    worst = max(s["cases"], key=lambda r: r["cost_deg"])
    assert s["worst_case"] == worst["case"] and s["worst_cost_deg"] == worst["cost_deg"]
    text = appearance.table({"stress": s})
    assert "exposure -0.7 EV" in text and "clean" in text


def test_rendered_sets_give_the_ratio_of_the_first_to_the_second(appearance, real_folder, tmp_path):
    reader = {"003_cracker_box": _write(tmp_path, "reader.onnx", channel_mean_model(props=contract()))}
    dark = appearance.stressed_copy(real_folder, tmp_path / "dark", "brightness", 0.5)
    r = appearance.run_rendered(reader, {"a": dark, "b": real_folder}, draws=2, seed=0)
    assert r["ratio"]["of"] == "a" and r["ratio"]["to"] == "b"
    assert r["ratio"]["value"] == pytest.approx(r["sets"]["a"]["mean_deg"] / r["sets"]["b"]["mean_deg"])


def test_the_command_line_refuses_nothing_to_measure(capsys):
    from benchmarks import appearance as script

    with pytest.raises(SystemExit):
        script.main([])
    assert "nothing to measure" in capsys.readouterr().err


def test_per_object_columns_are_each_objects_worst_case_gap_and_cycles_ratio(appearance, real_folder, tmp_path):
    """The card's columns from a record: per object the case costing it most over its own clean frames (not the
    nine-object worst case), its gap, and Cycles over the twin."""
    reader = {"003_cracker_box": _write(tmp_path, "reader.onnx", channel_mean_model(props=contract()))}
    cases = (("exposure -0.7 EV", "brightness", 0.6), ("exposure +0.5 EV", "brightness", 1.4))
    s = appearance.run_stress(reader, real_folder, tmp_path / "work", draws=2, seed=0, cases=cases, progress=False)
    dark = appearance.stressed_copy(real_folder, tmp_path / "dark", "brightness", 0.5)
    doc = {"stress": s, "rendered": appearance.run_rendered(reader, {"cycles": dark, "tiny": real_folder}, 2, 0),
           "gap": {"objects": {"003_cracker_box": {"gap_deg": 0.5, "instances": 7}}}}
    cols = appearance.per_object(doc)["003_cracker_box"]
    clean = s["clean_objects"]["003_cracker_box"]
    costs = {c["case"]: c["objects"]["003_cracker_box"] - clean for c in s["cases"]}
    worst = max(costs, key=costs.get)
    assert cols["stress_worst"] == {"case": worst, "cost_deg": pytest.approx(costs[worst], abs=1e-3)}
    assert cols["gap_deg"] == 0.5 and cols["real_instances"] == 7
    sets = doc["rendered"]["sets"]
    assert cols["cycles"]["ratio"] == pytest.approx(sets["cycles"]["objects"]["003_cracker_box"]["mean_deg"]
                                                    / sets["tiny"]["objects"]["003_cracker_box"]["mean_deg"], abs=1e-3)
    assert appearance.per_object({"stress": {k: v for k, v in s.items() if k != "clean_objects"}}) == {}


def test_the_card_shows_appearance_only_for_the_files_that_ship(tmp_path):
    """A record of the shipped INT8 file fills the card's appearance section; one of another file is left out."""
    from export.release import card
    from refiner_rt.metadata import file_sha256
    from refiner_rt.pretrained import WEIGHTS_DIR, model_file_name

    shipped = file_sha256(WEIGHTS_DIR / model_file_name("011_banana", int8=True))
    cases = [{"case": "JPEG 30", "objects": {"011_banana": 9.0, "004_sugar_box": 4.0}},
             {"case": "contrast 1.3", "objects": {"011_banana": 8.0, "004_sugar_box": 5.0}}]
    doc = {"draws": 10, "real": "real_ycbv_dev/test", "model_sha256": {"011_banana": shipped, "004_sugar_box": "0" * 64},
           "stress": {"clean_objects": {"011_banana": 7.0, "004_sugar_box": 3.0}, "cases": cases}}
    path = tmp_path / "card.json"
    path.write_text(json.dumps(doc))
    got = card._appearance(path)
    assert set(got) == {"011_banana"}
    assert got["011_banana"]["stress_worst"] == {"case": "JPEG 30", "cost_deg": 2.0}
    text = card.appearance_markdown(got)
    assert "| 011_banana | JPEG 30 (+2.00) | - | - | - | - |" in text
    assert card.appearance_markdown({}) == ""


def test_the_card_option_needs_the_real_frames_and_both_rendered_sets(tmp_path, capsys):
    from benchmarks import appearance as script

    with pytest.raises(SystemExit):
        script.main(["--real", str(tmp_path), "--rendered", f"cycles={tmp_path}", "--card"])
    assert "--card needs" in capsys.readouterr().err
