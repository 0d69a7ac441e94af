"""Evaluation: a refiner's errors on a dataset's crops (PyTorch or ONNX), their summaries and tables, scoring every
instance of a folder of (real) frames, and the ``refiner-rt eval`` command."""
