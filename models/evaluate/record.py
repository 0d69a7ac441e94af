"""What the benchmarks and studies share: their common options and the record each JSON carries.

``benchmarks.averaging``, ``benchmarks.cross_split`` and ``benchmarks.error_breakdown`` take checkpoints and rebuild
their recorded test crops; every study writes the command that produced it and the machine it ran on beside its
numbers (:func:`provenance`, :func:`machine`), so a row of
``RESULTS.md`` or of a study's README can be traced and rerun. :func:`write_json` also stamps each new file with
the version of these common fields (:data:`SCHEMA_VERSION`) and the git commit of the code that wrote it; files
written before that carry neither and are left as they are.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

# Version of the fields every result JSON carries (schema_version, git_commit, command, machine): 1 = the first
# stamped files. Bump it when one of them changes meaning.
SCHEMA_VERSION = 1
REPO = Path(__file__).resolve().parents[2]


def checkpoint_parser(description: str, *, data: bool = True, checkpoints_help: str | None = None,
                      json_help: str = "write the results and the command here") -> argparse.ArgumentParser:
    """A parser with the studies' common options: ``CKPT...``, ``--data`` (optional), ``--cache``, ``--threads``,
    ``--json``; the caller adds its own."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("checkpoints", type=Path, nargs="+", metavar="CKPT", help=checkpoints_help)
    if data:
        p.add_argument("--data", type=Path,
                       help="the dataset folder if it moved since training (default: the recorded one)")
    p.add_argument("--cache", type=Path, help="crop cache folder (default: DATA/.crops)")
    p.add_argument("--threads", type=int, default=0, help="torch threads (default 0: torch's own choice)")
    p.add_argument("--json", type=Path, help=json_help)
    return p


def parse_checkpoint_args(p: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """``p.parse_args(argv)``, refusing checkpoint paths that are not files (before any slow import)."""
    args = p.parse_args(argv)
    missing = [str(c) for c in args.checkpoints if not c.is_file()]
    if missing:
        p.error(f"no such checkpoint file(s): {', '.join(missing)}")
    return args


def provenance(module: str, argv: list[str] | None, threads: int | None = None, **machine) -> dict:
    """``{"command", "machine"}`` of a study run: the command line as typed (``python -m <module>`` and ``argv``,
    default ``sys.argv[1:]``) and the Python and processor it ran with; with ``threads`` (a torch study) also its torch
    threads and torch version, and ``machine``'s entries after those (e.g. ``processes=1``). Without ``threads`` torch
    is not imported.

    ``module``: the script's module, e.g. ``"benchmarks.data_scaling"`` (scripts run as ``python -m`` from the
    repository root).
    """
    record = {"python": platform.python_version(), "processor": platform.processor() or platform.machine()}
    if threads is not None:
        import torch

        record.update(threads=threads, torch=torch.__version__)
    record.update(machine)
    return {"command": shlex.join(["python", "-m", module, *(sys.argv[1:] if argv is None else argv)]),
            "machine": record}


RESULTS_DIR = "benchmarks/results"


def current_command(command: str) -> str:
    """A recorded ``command`` as the generated documents print it, so that it can be rerun today: a script run by
    its path, as the records before the ``python -m`` layout wrote it (``python benchmarks/NAME.py``, ``python
    benchmarks/studies/STUDY/SCRIPT.py``), as its module (``python -m benchmarks.NAME``); a result file written
    straight into ``benchmarks/results/`` (where every script wrote before the folder was split) in the sub-folder of
    the script that wrote it, named after the script (``--json benchmarks/results/tracking.json`` of
    ``benchmarks.tracking`` -> ``benchmarks/results/tracking/tracking.json``) or the ``refiner-rt`` command
    (``refiner-rt bench`` -> ``benchmarks/results/bench/``), the rule of ``benchmarks/results/README.md``. Everything
    else is kept as recorded; commands joined by ``&&`` are rewritten one by one. Idempotent.
    """
    if " && " in command:
        return " && ".join(current_command(c) for c in command.split(" && "))
    args = shlex.split(command)
    if args[:1] == ["python"] and len(args) > 1 and args[1].endswith(".py") and not args[1].startswith(("/", "..")):
        args = ["python", "-m", args[1][: -len(".py")].replace("/", "."), *args[2:]]
    if args[:2] == ["python", "-m"] and len(args) > 2:
        folder = args[2].rsplit(".", 1)[-1]
    elif args[:1] == ["refiner-rt"] and len(args) > 1:
        folder = args[1]
    else:
        return command
    out = []
    root = Path(__file__).resolve().parents[2]
    for arg in args:
        flag, eq, value = arg.partition("=") if arg.startswith("--") else ("", "", arg)
        head, _, name = value.rpartition("/")
        if head == RESULTS_DIR and Path(name).suffix:  # a file (a folder argument stays as recorded)
            # where the file is now (the rule's exceptions: a script writing into another's folder), else the rule
            found = sorted(p.parent.name for p in (root / RESULTS_DIR).glob(f"*/{name}"))
            arg = f"{flag}{eq}{RESULTS_DIR}/{found[0] if len(found) == 1 else folder}/{name}"
        out.append(arg)
    return shlex.join(out)


def machine() -> dict:
    """CPU model, instruction-set flags that matter for speed, and core count."""
    model, flags = platform.processor() or "unknown", []
    try:
        text = Path("/proc/cpuinfo").read_text()
        model = next((ln.split(":", 1)[1].strip() for ln in text.splitlines() if ln.startswith("model name")), model)
        line = next((ln for ln in text.splitlines() if ln.startswith("flags")), "")
        flags = sorted(f for f in line.split(":", 1)[-1].split() if f.startswith(("avx", "amx", "fma")) or "vnni" in f)
    except OSError:
        pass
    return {"cpu": model, "isa_flags": flags, "cores": os.cpu_count()}


def data_name(data: Path) -> str:
    """A dataset folder's name as records print it: a BOP split folder by its dataset's name
    (``real_ycbv_dev/test``), so that no record names a folder of the machine it ran on."""
    data = Path(data).resolve()
    return f"{data.parent.name}/{data.name}" if data.name in ("test", "val", "train") else data.name


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1; got {text}")
    return value


def git_commit(repo: Path = REPO) -> str | None:
    """The commit checked out in ``repo`` (40 hex digits), with ``-dirty`` when tracked files differ from it; None
    outside a git checkout or without git."""
    try:
        head = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("-dirty" if dirty else "")


def stamp(doc: dict) -> dict:
    """``doc`` with ``schema_version`` and ``git_commit`` first (values already in ``doc`` are kept)."""
    return {"schema_version": SCHEMA_VERSION, "git_commit": git_commit(), **doc}


def write_json(path: Path, doc: dict) -> None:
    """Write a study's document, stamped (:func:`stamp`), indented, one trailing newline, creating its folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(stamp(doc), indent=1) + "\n")
