"""The demo's sample frames, kept under its old name: the same as ``python -m export.release.samples`` (its
docstring has the commands)."""

import sys

from export.release.samples import main

if __name__ == "__main__":
    sys.exit(main())
