"""The ``eifslam`` command line: argument parsing, one module per sub-command.

The entry point is :func:`eifslam.cli.main.main`.
"""

from .main import build_parser, main

__all__ = ["build_parser", "main"]
