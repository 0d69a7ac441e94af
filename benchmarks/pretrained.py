"""The coarse refiners' build, kept under its old name for the commands recorded before it moved: the same as
``python -m export.release.coarse`` (its docstring has the commands; ``export/release/README.md`` one per version)."""

import sys

from export.release.coarse import main

if __name__ == "__main__":
    sys.exit(main())
