"""The ``eifslam`` command line: one sub-command per module of :mod:`eifslam.cli`.

Each module there defines ``add_parser(subparsers) -> argparse.ArgumentParser`` and sets
``func`` (taking the parsed ``argparse.Namespace`` and returning an exit code) as the
parser's default. Known errors (:class:`eifslam.errors.EifslamError`) are printed as one
line and give exit code 1.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .. import __version__
from ..errors import EifslamError

#: sub-command modules, in the order ``--help`` lists them
COMMANDS = ("demo", "run", "render", "eval", "config")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every available sub-command."""
    parser = argparse.ArgumentParser(
        prog="eifslam",
        description="Monocular SLAM with an exactly sparse Extended Information Filter.",
    )
    parser.add_argument("--version", action="version", version=f"eifslam {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"eifslam.cli.{name}")
        except ModuleNotFoundError as exc:  # a command whose module is not there yet
            if exc.name and exc.name.endswith(f"cli.{name}"):
                continue
            raise
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``eifslam`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # report.json records the command
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except EifslamError as exc:
        print(f"eifslam: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("eifslam: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
