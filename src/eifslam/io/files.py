"""Reading a text file with a one-line error that names it."""

from __future__ import annotations

from pathlib import Path

from ..errors import DatasetError, EifslamError


def read_text(path: Path, what: str = "", error: type[EifslamError] = DatasetError,
              missing: str | None = None) -> str:
    """The text of ``path``; a missing or unreadable file raises ``error`` naming it.

    Parameters
    ----------
    path : file to read.
    what : what the file is, for the message ("poses file", ...); "" for plain "file".
    error : the exception type to raise.
    missing : the message for a missing file (default "<what> not found").
    """
    missing = missing or f"{what or 'file'} not found"
    try:
        return path.read_text()
    except FileNotFoundError:
        raise error(f"{path}: {missing}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{path}: cannot read {what + ' ' if what else ''}({exc})") from None
