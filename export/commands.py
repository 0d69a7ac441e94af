"""The exporter's ``refiner-rt`` subcommands, plugged into the runtime's command line through the entry point group
``refiner_rt.commands`` (``pyproject.toml``) as :class:`refiner_rt.cli.LazyCommand` s: listed by ``refiner-rt --help``
without importing torch. ``bench`` takes the place of the runtime's own where this package is installed: the same
command, with the paper's networks built, PyTorch eager rows and the roofline (:mod:`export.bench`). Torch-free by
design.
"""

from __future__ import annotations

from refiner_rt.cli import LazyCommand

export = LazyCommand("export.cli:export_cmd", "Export a checkpoint to ONNX (parity-checked against PyTorch).")
bench = LazyCommand("export.bench:bench_cmd",
                    "CPU speed of the full refine() path: shallow, fusion and VGG-M, fp32 and INT8.")
