"""``eifslam config [FILE]``: every setting as YAML with one comment line of help each (the
defaults, or a file's effective configuration), and the reading of ``--config FILE.yaml``.

A configuration file holds any subset of the sections of
:class:`~eifslam.system.config.SlamConfig` (``frontend``, ``tracking``, ``mapping``,
``keyframes``, ``loops``, ``smoothing``, ``runtime``, ``experimental``) and of their keys;
what it leaves out keeps its default, and every value is checked as
:meth:`SlamConfig.from_dict` checks it. The file is read with a safe YAML loader (plain
data only, no Python objects).
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import yaml

from ..errors import ConfigError
from ..system.config import SECTIONS, SlamConfig


class _Loader(yaml.SafeLoader):
    """YAML's safe loader that also reads ``1e-6`` as a number (YAML 1.1 wants ``1.0e-6``)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def read_config(path: str | Path) -> SlamConfig:
    """The configuration of a YAML file: ``SlamConfig()`` with the file's settings.

    Raises
    ------
    ConfigError
        One line naming the file: missing, unreadable, not YAML, not a mapping of
        sections, an unknown key or a value out of range.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read configuration file ({exc.__class__.__name__}: {exc})") from None
    try:
        values = yaml.load(text, Loader=_Loader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or "syntax error"
        raise ConfigError(f"{path}: not valid YAML{where}: {problem}") from None
    if values is None:
        values = {}
    if not isinstance(values, dict) or not all(isinstance(v, dict) for v in values.values()):
        raise ConfigError(f"{path}: a configuration file maps sections ({', '.join(SECTIONS)}) to settings")
    try:
        return SlamConfig.from_dict(values)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def config_yaml(config: SlamConfig, comments: bool = True) -> str:
    """Every setting of ``config`` as YAML, which :func:`read_config` reads back; with
    ``comments``, each setting follows a comment line of help (meaning, unit, default)."""
    values = config.to_dict()
    if not comments:
        return yaml.safe_dump(values, sort_keys=False, default_flow_style=False)
    helps = config.help_lines()
    lines: list[str] = []
    for section, settings in values.items():
        lines.append(f"{section}:")
        for key, value in settings.items():
            lines.append(f"  # {helps[section][key]}")
            lines.append("  " + yaml.safe_dump({key: value}, default_flow_style=False, width=10**6).rstrip("\n"))
    return "\n".join(lines) + "\n"


def main(args: argparse.Namespace) -> int:
    config = read_config(args.file) if args.file is not None else SlamConfig()
    print(config_yaml(config), end="")
    return 0


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("config", help="print every setting as YAML with its help (the defaults, or a file's)",
                       description="Print every setting of the configuration as YAML, each after a comment line "
                                   "of help (meaning, unit, default): the defaults, or with FILE the "
                                   "configuration it gives (defaults for what it leaves out), checked. "
                                   "Save the output, edit it, and pass it to 'eifslam run --config FILE'.")
    p.add_argument("file", nargs="?", type=Path, default=None, metavar="FILE", help="a configuration file to check")
    p.set_defaults(func=main)
    return p
