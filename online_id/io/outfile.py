"""Output files: checked before the work starts, written under a temporary name, renamed on success.

A command that fails (full disk, a bad value half-way, Ctrl-C) leaves no
half-written output behind: the temporary file is removed and an older file
of the same name, if any, is untouched.  The temporary file lies in the same
directory (so the rename is atomic) and keeps the suffix (writers that pick
the format by suffix, such as python-can's, still work).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from online_id.errors import InputDataError


def check_output(path: str | Path, what: str = "output", directory: bool = False) -> Path:
    """Raise :class:`InputDataError` (one line) when ``path`` cannot be written; returns it as a Path.

    ``directory``: the output is a directory that may be created (its nearest
    existing ancestor must be a writable directory).
    """
    path = Path(path)
    if directory:
        if path.exists() and not path.is_dir():
            raise InputDataError(f"{path}: cannot create the {what} directory: it exists and is not a directory")
        parent = path
        while not parent.exists():
            parent = parent.parent
    else:
        if path.is_dir():
            raise InputDataError(f"{path}: cannot write the {what} here: it is a directory")
        parent = path.parent
    if not parent.exists():
        raise InputDataError(f"{path}: cannot write the {what}: the directory {parent} does not exist")
    if not parent.is_dir():
        raise InputDataError(f"{path}: cannot write the {what}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputDataError(f"{path}: cannot write the {what}: the directory {parent} is not writable")
    return path


_hold_depth = 0
_held: list[BaseException] = []


def holding() -> bool:
    """True within a step that must not be cut half-way (a temporary file made but not yet guarded)."""
    return _hold_depth > 0


def hold(exc: BaseException) -> None:
    """Raise ``exc`` (a signal's, from its handler) at the end of the step :func:`holding` says runs."""
    if not _held:
        _held.append(exc)


@contextmanager
def _whole() -> Iterator[None]:
    """A step that a signal's handler does not cut (it asks :func:`holding` and calls :func:`hold`)."""
    global _hold_depth
    _hold_depth += 1
    try:
        yield
    finally:
        _hold_depth -= 1
    if not _hold_depth and _held:
        raise _held.pop()


@contextmanager
def atomic_output(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on a clean exit it is renamed to ``path``, else removed.

    A signal (SIGINT, SIGTERM: :mod:`online_id.interrupt`) while the temporary file is made is held
    until the removal guards it: it never outlives its command.
    """
    path = check_output(path)
    done = False
    tmp_path = None
    try:
        with _whole():
            fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".partial{path.suffix}", dir=path.parent)
            os.close(fd)
            tmp_path = Path(tmp)
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, path)
        done = True
    except OSError as err:
        raise InputDataError(f"{path}: cannot write: {err.strerror or err}") from err
    finally:
        if not done and tmp_path is not None:
            tmp_path.unlink(missing_ok=True)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
