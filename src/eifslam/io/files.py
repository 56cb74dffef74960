"""Files in and out with one-line errors that name them.

* :func:`read_text` reads a text file (optionally refusing one over a size limit);
* :func:`ensure_output_dir` checks, before any work, that a folder can take the outputs;
* :func:`atomic_write` / :func:`atomic_path` write a file so that a reader (or a run
  killed half way) only ever sees the old file or the whole new one: the bytes go to a
  temporary file in the same folder, which :func:`os.replace` then renames over the
  target (atomic on POSIX and Windows within one file system).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator

from ..errors import DatasetError, EifslamError, OutputError

__all__ = ["read_text", "ensure_output_dir", "atomic_write", "atomic_path"]

_UMASK = os.umask(0o022)  # read the process umask (the only way) and put it back
os.umask(_UMASK)


def read_text(path: Path, what: str = "", error: type[EifslamError] = DatasetError,
              missing: str | None = None, max_bytes: int | None = None) -> str:
    """The text of ``path``; a missing or unreadable file raises ``error`` naming it.

    Parameters
    ----------
    path : file to read.
    what : what the file is, for the message ("poses file", ...); "" for plain "file".
    error : the exception type to raise.
    missing : the message for a missing file (default "<what> not found").
    max_bytes : refuse, before reading it, a file larger than this (bytes).

    Anything but a regular file (a folder, a FIFO that would block, a device) is refused.
    """
    missing = missing or f"{what or 'file'} not found"
    try:
        if path.exists() and not path.is_file():  # a folder, a FIFO (would block), /dev/zero
            raise error(f"{path}: {what or 'file'} is not a regular file")
        if max_bytes is not None and path.stat().st_size > max_bytes:
            raise error(f"{path}: {what or 'file'} is {path.stat().st_size} bytes, "
                        f"more than the {max_bytes} allowed")
        return path.read_text()
    except FileNotFoundError:
        raise error(f"{path}: {missing}") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise error(f"{path}: cannot read {what + ' ' if what else ''}({_reason(exc)})") from None


def _reason(exc: BaseException) -> str:
    """The short reason of an OS error (``strerror``), else its one-line text."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def ensure_output_dir(path: str | Path) -> Path:
    """Create ``path`` (and its parents) if needed and check that files can be written in it.

    Called before any work, so that a run never computes for an hour and then fails to
    save: the folder is created, then a temporary file is created in it and removed.

    Raises
    ------
    OutputError
        ``path`` is a file, a parent is a file, the folder cannot be created or written
        (permissions, a read-only or pseudo file system such as ``/proc``), or the path
        is longer than the operating system allows; the message names the path.
    """
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: output path is a file, not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".eifslam-probe-", dir=out)
        os.close(fd)
        os.unlink(probe)
    except (OSError, ValueError) as exc:
        raise OutputError(f"{out}: cannot write outputs in this folder ({_reason(exc)})") from None
    return out


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Context manager giving a temporary path to write instead of ``path``.

    The temporary file lies in the same folder and ends with the same suffix (libraries
    that pick a format by extension still work). On a clean exit it replaces ``path``
    (:func:`os.replace`); on an exception it is removed and ``path`` is left as it was.

    Raises
    ------
    OutputError
        The file cannot be written or renamed (names ``path``).
    """
    target = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=f".tmp{target.suffix}",
                                   dir=target.parent)
        os.close(fd)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give what open() would
    except (OSError, ValueError) as exc:
        raise OutputError(f"{target}: cannot write ({_reason(exc)})") from None
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, target)
    except OSError as exc:
        raise OutputError(f"{target}: cannot write ({_reason(exc)})") from None
    finally:
        if tmp_path.exists():
            with contextlib.suppress(OSError):
                tmp_path.unlink()


def atomic_write(path: str | Path, data: str | bytes) -> None:
    """Write ``data`` (text as UTF-8, or bytes) to ``path`` atomically (:func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data.encode("utf-8") if isinstance(data, str) else data)
            fh.flush()
            os.fsync(fh.fileno())
