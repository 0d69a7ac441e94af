"""Choose how :class:`refiner_rt.RefinerTracker` re-initialises a track the loss-of-track check flags
(``reinit=True``) on rendered video: tracks started within 30 degrees (the benchmark's draws, ``compare``) must not
get worse than without it, and of the variants that do not, the one with the least error on tracks started 45-90
degrees off (a track already lost) is chosen.

Each variant is ``RefinerTracker(lost_deg=LOST_DEG, reinit=True)`` with the module constants of
:mod:`refiner_rt.tracker` it names set while it updates (``REINIT_PASSES``, ``REINIT_GATE_DEG``,
``REINIT_HYPOTHESES``: 0 refines the track's own rotation alone, ``REINIT_MARGIN_DEG``); ``track_lost`` is the check
without re-initialisation. Per variant and start: the mean error over frames, videos and seeds, the sequences ending
above 30 degrees, and the searches and re-initialisations per object and frame, with the CPU time of the updates.

Usage (from the repository root)::

    python -m benchmarks.studies.tracking_real.choose_reinit --data data/tracking_robot_s561 --seeds 4 \\
        --json benchmarks/studies/tracking_real/choose_reinit_s561.json
"""

from __future__ import annotations

import argparse
import json
import time
from contextlib import contextmanager
from pathlib import Path

import refiner_rt.tracker as tracker_module
from models.evaluate.tracking import cpu_record
from models.evaluate.tracking_video import run
from refiner_rt.tracker import LOST_DEG, RefinerTracker

STARTS = {"near": (0.0, 30.0), "far": (45.0, 90.0)}
# name -> the module constants set while the variant searches ({} with reinit=False: the check alone)
VARIANTS = {
    "track_lost": None,
    "own_p3_g10": {"REINIT_HYPOTHESES": 0, "REINIT_PASSES": 3, "REINIT_GATE_DEG": 10.0},
    "search_p3_g15_m20": {"REINIT_HYPOTHESES": 8, "REINIT_PASSES": 3, "REINIT_GATE_DEG": 15.0,
                          "REINIT_MARGIN_DEG": 20.0},
    "search_p5_g15_m10": {"REINIT_HYPOTHESES": 8, "REINIT_PASSES": 5, "REINIT_GATE_DEG": 15.0,
                          "REINIT_MARGIN_DEG": 10.0},
    "search_p5_g15_m20": {"REINIT_HYPOTHESES": 8, "REINIT_PASSES": 5, "REINIT_GATE_DEG": 15.0,
                          "REINIT_MARGIN_DEG": 20.0},
}


@contextmanager
def constants(values: dict):
    saved = {k: getattr(tracker_module, k) for k in values}
    for k, v in values.items():
        setattr(tracker_module, k, v)
    try:
        yield
    finally:
        for k, v in saved.items():
            setattr(tracker_module, k, v)


class Variant(RefinerTracker):
    """A :class:`RefinerTracker` that searches with the module constants ``constants`` and adds its updated objects,
    CPU seconds, flagged objects and re-initialisations to ``STATS[name]``."""

    def __init__(self, *args, name: str, constants: dict | None, **kwargs):
        super().__init__(*args, reinit=constants is not None, **kwargs)
        self.constants = constants or {}
        self.stats = STATS.setdefault(name, {"cpu_s": 0.0, "object_updates": 0, "flagged": 0, "reinits": 0})

    def update(self, image, boxes, detector=None):
        t0, before = time.process_time(), self.reinits
        with constants(self.constants):
            out = super().update(image, boxes, detector)
        self.stats["cpu_s"] += time.process_time() - t0
        self.stats["object_updates"] += len(out)
        self.stats["flagged"] += len(self.lost) + self.reinits - before
        self.stats["reinits"] += self.reinits - before
        return out


STATS: dict[str, dict] = {}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--max-frames", type=int, default=100)
    p.add_argument("--seeds", type=int, default=4, help="coarse-pose draws per video (default 4)")
    p.add_argument("--variants", help="comma-separated names of VARIANTS (default: all)")
    p.add_argument("--starts", default="near,far", help="comma-separated starts of STARTS (default: near,far)")
    p.add_argument("--json", type=Path)
    a = p.parse_args(argv)
    names = a.variants.split(",") if a.variants else list(VARIANTS)
    for given, known, option in ((names, VARIANTS, "--variants"), (a.starts.split(","), STARTS, "--starts")):
        bad = [x for x in given if x not in known]
        if bad:
            p.error(f"{option}: unknown {', '.join(bad)}; expected of {', '.join(known)}")
    doc = {"data": a.data.resolve().name, "starts": {k: STARTS[k] for k in a.starts.split(",")}, "seeds": a.seeds,
           "max_frames": a.max_frames, "lost_deg": LOST_DEG, "variants": {n: VARIANTS[n] for n in names},
           "results": {}}
    t0 = time.time()
    for start in a.starts.split(","):
        STATS.clear()
        trackers = {n: {"lost_deg": LOST_DEG, "name": n, "constants": VARIANTS[n]} for n in names}
        res = run(a.data, a.max_frames, a.seeds, None, trackers, STARTS[start], Variant)
        out = doc["results"][start] = {"per_frame": res["summary"]["per_frame"],
                                       "per_frame_per_video": {v: r["summary"]["per_frame"]["mean_deg"]
                                                               for v, r in res["videos"].items()}}
        for name in names:
            st = STATS[name]
            n = max(st["object_updates"], 1)
            r = out[name] = {
                "summary": res["summary"][name],
                "per_video": {v: r["summary"][name]["mean_deg"] for v, r in res["videos"].items()},
                "flagged_per_object_update": round(st["flagged"] / n, 4),
                "reinits_per_object_update": round(st["reinits"] / n, 4),
                "cpu_ms_per_object_update": round(1000 * st["cpu_s"] / n, 2)}
            print(f"{start:4s} {name:20s} mean {r['summary']['mean_deg']:6.2f} (per-frame "
                  f"{out['per_frame']['mean_deg']:.2f}) last {r['summary']['last_frame_mean_deg']:6.2f} ended>30 "
                  f"{r['summary']['ended_above_30']} ({r['summary']['ended_above_30_flagged_lost']}) flagged/update "
                  f"{r['flagged_per_object_update']:.4f} re-init/update {r['reinits_per_object_update']:.4f} cpu "
                  f"{r['cpu_ms_per_object_update']:.2f} ms", flush=True)
    doc["wall_s"] = round(time.time() - t0, 1)
    doc["machine"] = cpu_record()
    if a.json:
        a.json.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
