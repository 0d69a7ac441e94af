"""The release gate of a new coarse model version against the shipped one (the study's README, "The release gate"):
two records of :mod:`benchmarks.appearance` (the shipped INT8 models and the candidate's, the same sets, draws and
seed) and, optionally, the two versions' card evaluations on the held-out tabletop renders (the build records of
``benchmarks/results/pretrained/``). Prints one table and the verdict; decides nothing on real frames (reported).

    python -m benchmarks.studies.appearance.gate --shipped benchmarks/results/appearance/card.json \\
        --shipped-fresh benchmarks/results/appearance/v6_int8.json --candidate V7.json \\
        --shipped-cards benchmarks/results/pretrained --candidate-cards CHECKOUT/benchmarks/results/pretrained

(``--shipped-fresh``: a second record of the shipped models holding the fresh robot renders, where the first lacks
them.) Exit status 0 when the gate holds, 1 when it does not.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

FRESH = "robot_fresh_s41"  # the fresh robot-layout renders, as benchmarks.appearance names the set
MAX_RENDER_COST_DEG = 0.10  # (a), (b): how much worse than the shipped models a candidate may be on fresh renders
STRESS_BAR_DEG = 1.0  # (c): a stress case that costs an object more than this is one the bar counts


def per_object_worst(stress: dict) -> dict[str, tuple[str, float]]:
    """Per object: its worst stress case and that case's cost against its clean frames (degrees)."""
    out = {}
    for obj, clean in stress["clean_objects"].items():
        worst = max(stress["cases"], key=lambda c: c["objects"][obj] - clean)
        out[obj] = (worst["case"], worst["objects"][obj] - clean)
    return out


def fresh_mean(*records: dict) -> float | None:
    for r in records:
        if r and FRESH in r.get("rendered", {}).get("sets", {}):
            return r["rendered"]["sets"][FRESH]["mean_deg"]
    return None


def card_mean(folder: Path | None) -> tuple[float, dict] | None:
    """The nine-object mean of the card's held-out INT8 error, and per object, from the build records."""
    if folder is None:
        return None
    per = {}
    for p in sorted(folder.glob("0*.json")):
        d = json.loads(p.read_text())
        per[d["object_id"]] = d["heldout"]["mean_deg"]
    return (sum(per.values()) / len(per), per) if per else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shipped", type=Path, required=True, help="benchmarks.appearance record of the shipped models")
    ap.add_argument("--shipped-fresh", type=Path, help="another record of them holding the fresh robot renders")
    ap.add_argument("--candidate", type=Path, required=True, help="the same record of the candidate models")
    ap.add_argument("--shipped-cards", type=Path, help="folder of the shipped models' build records")
    ap.add_argument("--candidate-cards", type=Path, help="folder of the candidate's build records")
    ap.add_argument("--json", type=Path, help="write the verdict and its numbers here")
    args = ap.parse_args(argv)
    a = json.loads(args.shipped.read_text())
    a2 = json.loads(args.shipped_fresh.read_text()) if args.shipped_fresh else None
    b = json.loads(args.candidate.read_text())
    rows, checks = [], {}

    fa, fb = fresh_mean(a, a2), fresh_mean(b)
    if fa is None or fb is None:
        ap.error(f"both versions need the fresh robot renders ({FRESH}) in a record: (a) cannot be checked")
    checks["a_fresh_renders"] = fb <= fa + MAX_RENDER_COST_DEG
    rows.append(("fresh robot renders (robot_fresh_s41), mean", fa, fb))
    ca, cb = card_mean(args.shipped_cards), card_mean(args.candidate_cards)
    if not (ca and cb):
        ap.error("--shipped-cards and --candidate-cards: folders of build records, both: (b) cannot be checked")
    checks["b_card_heldout"] = cb[0] <= ca[0] + MAX_RENDER_COST_DEG
    rows.append(("card held-out tabletop renders (ycb9_fresh_s21), mean", ca[0], cb[0]))
    wa, wb = per_object_worst(a["stress"]), per_object_worst(b["stress"])
    over_a = sum(c > STRESS_BAR_DEG for _, c in wa.values())
    over_b = sum(c > STRESS_BAR_DEG for _, c in wb.values())
    checks["c_stress"] = b["stress"]["worst_cost_deg"] < a["stress"]["worst_cost_deg"] and over_b < over_a
    rows.append(("stress test: worst case of the nine-object mean", a["stress"]["worst_cost_deg"],
                 b["stress"]["worst_cost_deg"]))
    rows.append((f"stress test: objects with a case above {STRESS_BAR_DEG:g} deg", over_a, over_b))
    for part in ("cycles", "tiny"):
        sa, sb = a["rendered"]["sets"].get(part), b["rendered"]["sets"].get(part)
        if sa and sb:
            rows.append((f"{part} validation set, mean (reported)", sa["mean_deg"], sb["mean_deg"]))
    rows.append(("real dev frames, mean (reported)", a["gap"]["real_deg"], b["gap"]["real_deg"]))
    rows.append(("real dev frames, drift (reported)", a["gap"]["real_drift_deg"], b["gap"]["real_drift_deg"]))
    rows.append(("appearance gap: real - re-drawn (reported)", a["gap"]["gap_deg"], b["gap"]["gap_deg"]))

    print("| measure | shipped | candidate |\n|---|---:|---:|")
    for name, x, y in rows:
        fmt = (lambda v: f"{v:d}") if isinstance(x, int) else (lambda v: f"{v:.2f}")
        print(f"| {name} | {fmt(x)} | {fmt(y)} |")
    print("\nper object, worst stress case (shipped -> candidate):")
    for obj in wa:
        print(f"  {obj}: {wa[obj][0]} {wa[obj][1]:+.2f} -> {wb[obj][0]} {wb[obj][1]:+.2f}")
    print("per object, card held-out mean (shipped -> candidate):")
    for obj in ca[1]:
        print(f"  {obj}: {ca[1][obj]:.2f} -> {cb[1].get(obj, float('nan')):.2f}")
    held = all(checks.values())
    print(f"\ngate: {', '.join(f'{k} {v}' for k, v in checks.items())} -> {'HOLDS' if held else 'FAILS'}")
    if args.json:
        args.json.write_text(json.dumps({"checks": checks, "held": held,
                                         "rows": [{"measure": n, "shipped": x, "candidate": y} for n, x, y in rows],
                                         "stress_worst": {"shipped": wa, "candidate": wb},
                                         "card_heldout": {"shipped": ca[1], "candidate": cb[1]}},
                                        indent=1) + "\n")
    return 0 if held else 1


if __name__ == "__main__":
    raise SystemExit(main())
