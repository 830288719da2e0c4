"""`python -m train report runs/x [--out DIR] [--svg]`: a Markdown report of a sweep folder, with its figures.

Wired into `python -m train` by `add_parser(subparsers)` and `run(args)`; also runs on its own as
`python -m train.report runs/x`. A missing folder, a folder that is not a sweep, or a sweep with no finished
evaluation yet exits with status 2 and a message, writing nothing.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

PROG = "python -m train report"


DESCRIPTION = (
    "Write report.md, figures/*.png and the results table (CSV) of a finished or partly finished sweep folder."
)


def _add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    parser.add_argument("folder", help="a sweep's output folder (the --out of `python -m train sweep`)")
    parser.add_argument("--out", help="report folder (default: FOLDER/report)")
    parser.add_argument("--svg", action="store_true", help="also save every figure as SVG")
    parser.add_argument(
        "--no-maps",
        action="store_true",
        help="skip the measurement maps of the saved best policies (they run each policy)",
    )
    return parser


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the `report` command to an `argparse` subparsers object; returns its parser."""
    parser = subparsers.add_parser(
        "report", help="write a report (Markdown, figures, tables) of a sweep folder", description=DESCRIPTION
    )
    return _add_arguments(parser)


def run(args: argparse.Namespace) -> int:
    """Write the report described by `args` (from `add_parser`); returns the exit status."""
    from amjax.analysis import NotASweepError, write_report

    try:
        report = write_report(
            args.folder, args.out, formats=("png", "svg") if args.svg else ("png",), maps=not args.no_maps
        )
    except NotASweepError as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 2
    print(f"Report: {report} (figures in {report.parent / 'figures'})")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m train.report FOLDER [--out DIR] [--svg]` (the same command without `python -m train`)."""
    parser = _add_arguments(argparse.ArgumentParser(prog="python -m train.report", description=DESCRIPTION))
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
