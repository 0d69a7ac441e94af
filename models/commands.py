"""The training package's ``refiner-rt`` subcommands, plugged into the runtime's command line through the entry point
group ``refiner_rt.commands`` (``pyproject.toml``): each is a :class:`refiner_rt.cli.LazyCommand`, its module and its
one-line help, so that ``refiner-rt --help`` lists them without importing torch. Torch-free by design.
"""

from __future__ import annotations

from refiner_rt.cli import LazyCommand

render = LazyCommand("models.data.render:render_cmd", "Render BOP-format training scenes of YCB objects on the CPU.")
train = LazyCommand("models.train.cli:train_cmd", "Train a refiner (paper recipe: base, then per-object fine-tuning).")
evaluate = LazyCommand("models.evaluate.cli:eval_cmd", "Evaluate a checkpoint or ONNX model on a dataset's test split.")
