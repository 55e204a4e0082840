"""Atomic file writing: a reader never sees a half-written file.

Data goes to a temporary file in the target's folder, is flushed and fsynced,
then renamed over the target (``os.replace`` is atomic on POSIX and Windows).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from cdma_lidar.errors import ConfigError

__all__ = ["atomic_open", "atomic_write_bytes", "atomic_write_text", "check_writable"]


def _read_umask() -> int:
    """The process umask (read once; os.umask can only be read by setting it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: Files get the permissions ``open()`` would give them (mkstemp alone makes them 0600).
_FILE_MODE = 0o666 & ~_read_umask()


def check_writable(path: str | os.PathLike[str], option: str = "--out") -> Path:
    """Return ``path`` as a Path after proving a file can be created beside it.

    Creates and removes a probe file in the target's folder: ``os.access`` says yes
    to root everywhere and to pseudo file systems such as ``/proc``, a probe cannot
    lie. Raises ConfigError naming ``option`` (the CLI option or field that gave the
    path), so the CLI can say what to do before any work is spent on a scan whose
    result could not be saved.
    """
    p = Path(path)
    field = option.lstrip("-")
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise ConfigError(f"{option}: folder {str(folder)!r} does not exist; create it first",
                          field)
    if p.is_dir():
        raise ConfigError(f"{option}: {str(p)!r} is a folder; give a file name", field)
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".probe", dir=folder)
    except OSError as exc:
        raise ConfigError(f"{option} {str(p)!r}: cannot write in folder {str(folder)!r} "
                          f"({exc.strerror}); choose a writable folder", field) from None
    os.close(fd)
    os.unlink(probe)
    return p


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside ``path``; on clean exit it replaces ``path`` atomically.

    On an exception the temporary file is removed and ``path`` is left untouched.
    """
    if mode not in ("w", "wb"):
        raise ConfigError(f"mode must be 'w' or 'wb', not {mode!r}", "mode")
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent or ".")
    try:
        os.fchmod(fd, _FILE_MODE)
        with os.fdopen(fd, mode, **({"encoding": "utf-8"} if mode == "w" else {})) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_open(path, "wb") as fh:
        fh.write(data)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_open(path, "w") as fh:
        fh.write(text)
