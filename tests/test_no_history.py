"""No line of the repository narrates the history of the work.

Docs, docstrings and comments speak of the code as it is; how it got there is in version
control. This test scans the README, ``docs/*.md``, ``src/``, ``tests/`` and
``benchmarks/`` for the marks such narration leaves (a numbered work session, an issue
number, a numbered stop, a machine path, a date of work) and lists every ``file:line``.
A date is allowed in the provenance header of a generated results page (``- Date: ...``,
written by :func:`benchmarks._common.markdown_header`).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: What a line that narrates the work's history looks like (case-insensitive).
PATTERNS: dict[str, re.Pattern[str]] = {
    "numbered session": re.compile(r"\bsessions? #?[0-9]+", re.I),
    "issue number": re.compile(r"\bissues? #?[0-9]+", re.I),
    "numbered stop": re.compile(r"\bstops? #?[0-9]+", re.I),
    "machine path": re.compile(r"(?<![\w.])/(?:work|tmp)/", re.I),
    "date": re.compile(r"\b20[0-9]{2}-[0-9]{2}-[0-9]{2}\b"),
}

#: Lines where a date is part of the content, not a date of work: the provenance header of
#: a generated page.
ALLOWED_DATE_LINE = re.compile(r"^\s*[-*]\s*Date:", re.I)

#: Files this test itself needs to name the patterns in.
SELF = Path(__file__).resolve()

SUFFIXES = {".py", ".md", ".txt", ".toml", ".cfg", ".yaml", ".yml", ".j2", ".html", ".rst"}

def _files(group: str) -> list[Path]:
    if group == "docs":
        return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    files = sorted(p for p in (ROOT / group).rglob("*")
                   if p.is_file() and p.suffix in SUFFIXES and "__pycache__" not in p.parts)
    return files


def history_lines(paths: list[Path]) -> list[str]:
    """``file:line: kind: text`` of every line in ``paths`` that matches a history pattern.

    Parameters
    ----------
    paths : list of Path
        Text files to scan (missing files are skipped).

    Returns
    -------
    list of str
        One entry per matching line, paths relative to the repository's root.
    """
    found = []
    for path in paths:
        if path.resolve() == SELF or not path.is_file():
            continue
        for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            for kind, pattern in PATTERNS.items():
                if not pattern.search(line):
                    continue
                if kind == "date" and ALLOWED_DATE_LINE.match(line):
                    continue
                found.append(f"{path.relative_to(ROOT)}:{n}: {kind}: {line.strip()[:120]}")
    return found


def test_the_patterns_catch_history_and_spare_the_code():
    # the samples are assembled, so that this file itself holds no line of the kinds it rejects
    n, day = "12", "-".join(["2024", "05", "01"])
    lines = [f"Speed, {'session'} {n}", f"as {'issue'} #{n} asks", f"at {'stop'} {n} the gate",
             "see " + "/".join(["", "work", "main", "docs"]), "written to " + "/".join(["", "tmp", "x"]),
             f"run on {day}", f"- Date: {day} 10:00 UTC"]
    hits = [k for line in lines for k, p in PATTERNS.items()
            if p.search(line) and not (k == "date" and ALLOWED_DATE_LINE.match(line))]
    assert hits == ["numbered session", "issue number", "numbered stop", "machine path", "machine path", "date"]
    clean = ["a saved session is reloaded", "the issue is the scale", "src/eifslam/io/files.py",
             "tempfile.gettempdir()", "stop the run"]
    assert not [line for line in clean for p in PATTERNS.values() if p.search(line)]


@pytest.mark.parametrize("group", ["src", "benchmarks", "tests", "docs"])
def test_no_history(group):
    found = history_lines(_files(group))
    assert not found, f"history in {group}:\n" + "\n".join(found)
