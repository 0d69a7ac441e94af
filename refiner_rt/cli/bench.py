"""``refiner-rt bench``: CPU speed of the full ``refine()`` path (the timer and its options: :mod:`refiner_rt.bench`)."""

from __future__ import annotations

from refiner_rt.bench import bench_command

__all__ = ["bench_cmd"]

bench_cmd = bench_command()  # the random-weight networks come from the training package, when installed
