"""Write the generated tables of ``benchmarks/RESULTS.md`` and ``README.md`` from their JSON files
(:mod:`models.evaluate.report` renders them).

    python -m benchmarks.report            # rewrite the tables in place
    python -m benchmarks.report --check    # exit 1 if a table differs from what its JSON gives
"""

from __future__ import annotations

import argparse
import sys

from models.evaluate.report import write_docs


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--check", action="store_true", help="report tables that differ from their JSON; change nothing")
    args = p.parse_args(argv)
    try:
        stale = write_docs(check=args.check)
    except ValueError as exc:  # a generated block this script has no table for
        raise SystemExit(str(exc)) from None
    if args.check and stale:
        print(f"generated tables out of date in {', '.join(map(str, stale))}: run python -m benchmarks.report")
        return 1
    print("up to date" if not stale else f"rewrote {', '.join(map(str, stale))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
