"""``python -m refiner_rt.cli``: the ``refiner-rt`` command."""

from refiner_rt.cli import main

main()
