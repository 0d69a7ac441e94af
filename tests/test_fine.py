"""The cascade measured through the runtime (models/evaluate/cascade.py) and the cascade study: the card's numbers
and the floor curve from error arrays, and the study's table, on arrays whose answers are known."""

import json

import numpy as np

from models.evaluate import cascade as fine
from tests.bench_scripts import load_benchmark


def _errors():
    rng = np.random.default_rng(0)
    n = 300
    inp = rng.uniform(0, 30, n)
    return {"input": inp, "coarse": np.full(n, 3.0), "fine": inp * 0.5, "cascade": np.where(inp < 3, 1.0, 2.0),
            "coarse@0": np.full(100, 2.5), "fine@0": np.full(100, 1.0), "cascade@0": np.full(100, 1.2),
            "cascade_coarse_used": inp >= 3, "cascade@0_coarse_used": np.zeros(100, bool)}


def test_summarise_gives_means_drift_small_inputs_and_the_floor_curve():
    e = _errors()
    s = fine.summarise(e)
    assert s["n"] == 300 and s["input_0_3_n"] == int((e["input"] < 3).sum())
    assert s["coarse"]["mean_deg"] == 3.0 and s["coarse"]["drift_mean_deg"] == 2.5
    assert s["cascade"]["input_0_3_mean_deg"] == 1.0 and s["cascade"]["drift_mean_deg"] == 1.2
    assert abs(s["cascade"]["coarse_used"] - np.mean(e["input"] >= 3)) < 1e-12
    curve = s["fine"]["floor_curve"]
    assert len(curve) == fine.FLOOR_BINS == len(s["floor_curve_n"]) and sum(s["floor_curve_n"]) == 300
    for b, v in enumerate(curve):  # fine = input / 2: each bin's mean lies in [b / 2, (b + 1) / 2)
        if v is not None:
            assert b / 2 <= v < (b + 1) / 2
    json.dumps(s)  # what the JSON stores


def test_summarise_reports_the_cascades_coarse_pass_beside_the_one_pass_coarse_refiner():
    e = {**_errors(), "coarse_cascade": np.full(300, 2.0), "coarse_cascade@0": np.full(100, 1.5)}
    s = fine.summarise(e)
    assert s["coarse"]["mean_deg"] == 3.0 and s["coarse_cascade"]["mean_deg"] == 2.0
    assert s["coarse_cascade"]["drift_mean_deg"] == 1.5
    assert "coarse_cascade" not in fine.summarise(_errors())


def test_the_views_probe_reads_view_pairs_and_names_a_bad_one():
    probe = load_benchmark("studies/cascade/views_probe")
    assert probe.parse_views("1x4, 4x8", _raise) == [(1, 4), (4, 8)]
    for bad in ("4x", "0x4", "4x17", "4*4", "ax4"):
        try:
            probe.parse_views(f"1x4,{bad}", _raise)
        except ValueError as exc:
            assert repr(bad) in str(exc) and "COARSExFINE" in str(exc)
        else:
            raise AssertionError(f"{bad!r} was accepted")


def _raise(message):
    raise ValueError(message)


def test_the_study_table_has_a_row_per_object_and_the_mean():
    cascade = load_benchmark("studies/cascade/cascade")
    s = fine.summarise(_errors())
    doc = {"sets": {"fresh": {"label": "fresh renders, x", "objects": {"a": s, "b": s}, "pooled": s}}}
    text = cascade.table(doc)
    rows = [r for r in text.splitlines() if r.startswith("| fresh")]
    assert len(rows) == 3 and "**mean of 2**" in rows[-1]
    assert f"| 300 | 3.00 | {s['cascade']['mean_deg']:.2f} | 3.00 | 1.00 | 2.50 | 1.00 | 1.20 |" in rows[0]


def test_with_gate_picks_the_path_as_the_cascade_does():
    """The fine result where the fine correction is within gate_deg and the coarse one within coarse_gate_deg, the
    coarse-then-fine result elsewhere; no gate: always coarse then fine (RefinerCascade.refine's rule)."""
    e = {"fine": np.array([1.0, 1.0, 1.0]), "coarse_fine": np.array([2.0, 2.0, 2.0]),
         "fine_move": np.array([0.5, 3.0, 0.5]), "coarse_move": np.array([1.0, 1.0, 20.0]),
         "fine@0": np.array([0.1]), "coarse_fine@0": np.array([0.9]), "fine_move@0": np.array([0.2]),
         "coarse_move@0": np.array([2.0])}
    c = fine.with_gate(e, (2.0, 8.0))
    assert c["cascade"].tolist() == [1.0, 2.0, 2.0] and c["cascade_coarse_used"].tolist() == [False, True, True]
    assert c["cascade@0"].tolist() == [0.1] and c["gate"] == [2.0, 8.0]
    assert fine.with_gate(e, (2.0, None))["cascade"].tolist() == [1.0, 2.0, 1.0]  # no coarse check
    assert fine.with_gate(e, (None, 8.0))["cascade"].tolist() == [2.0, 2.0, 2.0]  # no gate: always the long way


def test_choose_gate_weighs_the_mean_and_the_drift_alike():
    n = 100
    rng = np.random.default_rng(1)
    e = {"fine": np.full(n, 5.0), "coarse_fine": np.full(n, 3.0), "fine_move": rng.uniform(0, 4, n),
         "coarse_move": rng.uniform(0, 10, n), "fine@0": np.full(n, 0.5), "coarse_fine@0": np.full(n, 2.0),
         "fine_move@0": rng.uniform(0, 4, n), "coarse_move@0": rng.uniform(0, 10, n)}
    gate, scores = fine.choose_gate(e)
    assert gate in fine.GATES and set(scores) == set(fine.GATES)
    assert sum(scores[gate]) == min(sum(v) for v in scores.values())
