"""Declared settings: a dataclass field with its one-line help and its check.

A section of the configuration (:class:`~eifslam.frontend.config.FrontEndConfig`, the
sections of :class:`~eifslam.system.config.SlamConfig`) declares each field with
:func:`setting`, and calls :func:`check_section` from ``__post_init__``: every value is
checked against what its field declares, once, and a bad one raises
:class:`~eifslam.errors.ConfigError` naming ``section.key``. Pure Python.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from enum import Enum
from typing import Any, Callable, Mapping

from .errors import ConfigError

__all__ = ["Check", "Flag", "Int", "Real", "OneOf", "setting", "check_section", "help_line", "build_section",
           "plain"]


class Check:
    """What a value must be: called with the value, returns it (converted: an enum member
    for a string) or raises ``ValueError`` with the requirement."""

    def __call__(self, value: Any) -> Any:  # pragma: no cover - overridden
        raise NotImplementedError


@dataclass(frozen=True)
class Flag(Check):
    """``true`` or ``false``."""

    def __call__(self, value: Any) -> Any:
        if not isinstance(value, bool):
            raise ValueError("must be true or false")
        return value


@dataclass(frozen=True)
class Int(Check):
    """An integer ``>= lo`` (and ``<= hi`` when given); ``none`` also accepts None."""

    lo: int
    hi: int | None = None
    none: bool = False

    def __call__(self, value: Any) -> Any:
        if value is None and self.none:
            return value
        ok = isinstance(value, int) and not isinstance(value, bool) and value >= self.lo
        if not ok or (self.hi is not None and value > self.hi):
            top = f" and <= {self.hi}" if self.hi is not None else ""
            raise ValueError(f"must be an integer >= {self.lo}{top}" + (" or null" if self.none else ""))
        return value


@dataclass(frozen=True)
class Real(Check):
    """A finite number in the interval from ``lo`` to ``hi``, each end open or closed;
    ``none`` also accepts None."""

    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False
    none: bool = False

    def __call__(self, value: Any) -> Any:
        if value is None and self.none:
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError("must be a finite number" + (" or null" if self.none else ""))
        above = value > self.lo if self.lo_open else value >= self.lo
        below = value < self.hi if self.hi_open else value <= self.hi
        if not (above and below):
            raise ValueError(f"must lie in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}"
                             f"{')' if self.hi_open else ']'}" + (" or be null" if self.none else ""))
        return value


@dataclass(frozen=True)
class OneOf(Check):
    """One of a fixed set of values: the members of an enum (a string is converted to its
    member; see :meth:`parse` of the enum for other accepted spellings) or a tuple."""

    values: Any

    def __call__(self, value: Any) -> Any:
        if isinstance(self.values, type) and issubclass(self.values, Enum):
            parse = getattr(self.values, "parse", None)
            if parse is not None:
                try:
                    return parse(value, "value")
                except ConfigError:
                    pass
            else:
                try:
                    return self.values(value)
                except ValueError:
                    pass
            raise ValueError("must be one of " + ", ".join(str(m.value) for m in self.values))
        if value not in self.values:
            raise ValueError("must be one of " + ", ".join(str(v) for v in self.values))
        return value


def setting(default: Any, help: str, check: Check | Callable[[Any], Any]) -> Any:
    """A dataclass field with its one-line ``help`` (meaning and unit; the default is added
    when printed) and its ``check``, which :func:`check_section` applies."""
    return dataclasses.field(default=default, metadata={"help": help, "check": check})


def check_section(obj: Any, section: str) -> None:
    """Check (and convert) every field of the frozen dataclass ``obj`` with the check its
    :func:`setting` declares.

    Raises
    ------
    ConfigError
        ``section.key`` and what the value must be.
    """
    for f in dataclasses.fields(obj):
        check = f.metadata.get("check")
        if check is None:
            continue
        value = getattr(obj, f.name)
        try:
            converted = check(value)
        except ValueError as exc:
            raise ConfigError(f"{section}.{f.name} {exc}, got {value!r}") from None
        if converted is not value:
            object.__setattr__(obj, f.name, converted)


def plain(value: Any) -> Any:
    """A value as configuration files hold it (an enum as its string)."""
    return value.value if isinstance(value, Enum) else value


def help_line(f: dataclasses.Field) -> str:
    """The one line of help of a field: its help text and its default."""
    default = plain(f.default)
    shown = "null" if default is None else str(default).lower() if isinstance(default, bool) else default
    return f"{f.metadata.get('help', '')} (default {shown})"


def build_section(cls: type, values: Mapping[str, Any], section: str) -> Any:
    """``cls(**values)``, with an unknown key a :class:`ConfigError` naming ``section.key``."""
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ConfigError(f"unknown configuration key {section}.{unknown[0]} (known: {', '.join(names)})")
    return cls(**dict(values))
