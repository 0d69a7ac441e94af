"""Putting a finished temporary file in place with the permissions a plain ``open(path, "w")`` would have given.

The exporter writes a model to a ``tempfile.mkstemp`` file beside its destination and renames it there only once it
has passed its checks. ``mkstemp`` creates files readable by their owner only (0600); without the ``chmod`` below
an exported model would keep that mode, unlike every other file the user writes.
"""

from __future__ import annotations

import os
from pathlib import Path


def current_umask() -> int:
    """The process's file-creation mask (``os.umask`` can only be read by setting it, so it is set back at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def replace_with_umask(tmp: Path, dest: Path) -> None:
    """Give ``tmp`` mode ``0o666 & ~umask`` (0644 with the usual umask 022), then rename it to ``dest`` atomically."""
    os.chmod(tmp, 0o666 & ~current_umask())
    os.replace(tmp, dest)
