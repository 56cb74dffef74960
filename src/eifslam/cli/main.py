"""The ``eifslam`` command line: one sub-command per module of :mod:`eifslam.cli`.

Each module there defines ``add_parser(subparsers) -> argparse.ArgumentParser`` and sets
``func`` (taking the parsed ``argparse.Namespace`` and returning an exit code) as the
parser's default. Known errors (:class:`eifslam.errors.EifslamError`) are printed as one
line and give exit code 1.

Ctrl-C, SIGTERM and SIGHUP are handled alike: a run stops its loop (after the frame being
tracked, :func:`eifslam.system.runner.request_stop`) and writes what it estimated; outside
a run, or at a second signal, they raise :class:`KeyboardInterrupt` at once.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import signal
import sys
import threading
from typing import Iterator

from .. import __version__
from ..errors import EifslamError

#: sub-command modules, in the order ``--help`` lists them
COMMANDS = ("demo", "run", "batch", "render", "eval", "config")


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


def _one_line(text: str) -> str:
    return " ".join(text.split("\n")).strip()


def _interrupt(signum: int, frame) -> None:
    """Ctrl-C, SIGTERM, SIGHUP: a run in progress stops after the frame being tracked and
    writes its outputs; otherwise (or at a second signal) interrupt at once."""
    name = signal.Signals(signum).name
    runner = sys.modules.get("eifslam.system.runner")  # not imported: no run in progress
    if runner is None or not runner.request_stop(name):
        raise KeyboardInterrupt(name)
    print(f"\neifslam: {name}: stopping after this frame and writing the outputs "
          "(again to abort)", file=sys.stderr)


@contextlib.contextmanager
def _signals_as_interrupt() -> Iterator[None]:
    """Handle Ctrl-C (SIGINT), SIGTERM and SIGHUP by :func:`_interrupt` while inside
    (main thread only: Python delivers signals there); the previous handlers are put
    back after."""
    names = ("SIGINT", "SIGTERM", "SIGHUP")
    sigs = [getattr(signal, n) for n in names if hasattr(signal, n)]
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _interrupt) for s in sigs}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``eifslam`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # report.json records the command
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        with _signals_as_interrupt():
            return int(args.func(args) or 0)
    except EifslamError as exc:
        print(f"eifslam: error: {_one_line(str(exc))}", file=sys.stderr)
        return 1
    except OSError as exc:  # a file operation no check foresaw: still one line naming it
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"eifslam: error: {where}{_one_line(exc.strerror or str(exc))}", file=sys.stderr)
        return 1
    except MemoryError:
        print("eifslam: error: out of memory", file=sys.stderr)
        return 1
    except KeyboardInterrupt as exc:
        name = str(exc)
        print(f"eifslam: interrupted{f' ({name})' if name else ''}", file=sys.stderr)
        return 128 + (int(getattr(signal, name)) if name.startswith("SIG") and hasattr(signal, name) else 2)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
