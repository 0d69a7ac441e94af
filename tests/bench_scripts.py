"""The scripts of ``benchmarks/`` imported as modules by their tests: ``benchmarks/<name>.py`` (``name`` may be
``studies/<study>/<script>``) as the module ``benchmarks.<name>``, the same module ``python -m`` runs."""

import importlib


def load_benchmark(name: str):
    """The script ``benchmarks/<name>.py`` as its module (``"studies/cascade/cascade"`` -> ``benchmarks.studies.cascade.cascade``)."""
    return importlib.import_module("benchmarks." + name.replace("/", "."))
