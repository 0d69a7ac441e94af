"""The exporter's ``refiner-rt export`` subcommand, plugged into the runtime's command line through the entry point
group ``refiner_rt.commands`` (``pyproject.toml``) as a :class:`refiner_rt.cli.LazyCommand`: listed by
``refiner-rt --help`` without importing torch. Torch-free by design.
"""

from __future__ import annotations

from refiner_rt.cli import LazyCommand

export = LazyCommand("export.cli:export_cmd", "Export a checkpoint to ONNX (parity-checked against PyTorch).")
