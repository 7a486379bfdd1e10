"""Reading a file that a user or another process can replace, without trusting it.

Every file the harness or the analysis opens that it did not just write itself (a floor
cache entry, a log, a sweep's CSV, a status file, a template) is read through
:func:`read_bytes` or :func:`read_text`:

* only a regular file is opened (a FIFO, a device such as ``/dev/zero``, a socket or a
  directory is refused, also behind a symbolic link), and it is opened without blocking,
  then checked again on the open descriptor, so a file swapped between the check and
  the open cannot make the read hang;
* at most ``limit`` bytes are read: a larger file is refused, never loaded;
* text is decoded strictly (UTF-8 by default).

A refusal is an :class:`UnreadableFile` whose message is one line naming the file and
why.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

SMALL_FILE_BYTES = 1 << 20
"""Largest status, run or lock file of a sweep read (bytes): each holds a few hundred."""


class UnreadableFile(OSError):
    """A file that is not a regular file, is larger than allowed, cannot be read or does
    not decode; ``str()`` is one line.
    """


def _kind(mode: int) -> str:
    """What a file that is not a regular file is, in words."""
    for test, name in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def read_bytes(path: str | Path, limit: int) -> bytes:
    """The contents of the regular file ``path``, at most ``limit`` bytes.

    Raises:
        UnreadableFile: for a path that is missing, not a regular file, larger than
            ``limit`` bytes or unreadable.
    """
    path = Path(path)
    try:
        before = os.stat(path)
    except OSError as err:
        raise UnreadableFile(f"{path}: {err.strerror or err}") from None
    if not stat.S_ISREG(before.st_mode):
        raise UnreadableFile(f"{path}: {_kind(before.st_mode)}, not a regular file")
    if before.st_size > limit:
        raise UnreadableFile(f"{path}: {before.st_size} bytes, more than the {limit} allowed")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as err:
        raise UnreadableFile(f"{path}: {err.strerror or err}") from None
    try:
        now = os.fstat(fd)
        if not stat.S_ISREG(now.st_mode):
            raise UnreadableFile(f"{path}: {_kind(now.st_mode)}, not a regular file")
        chunks, total = [], 0
        while True:
            chunk = os.read(fd, min(1 << 20, limit + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
            if total > limit:
                raise UnreadableFile(f"{path}: more than the {limit} bytes allowed")
        return b"".join(chunks)
    except OSError as err:
        if isinstance(err, UnreadableFile):
            raise
        raise UnreadableFile(f"{path}: {err.strerror or err}") from None
    finally:
        os.close(fd)


def read_text(path: str | Path, limit: int, encoding: str = "utf-8") -> str:
    """The text of the regular file ``path`` (:func:`read_bytes`), decoded strictly.

    Raises:
        UnreadableFile: as :func:`read_bytes`, and for bytes that do not decode.
    """
    data = read_bytes(path, limit)
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as err:
        raise UnreadableFile(
            f"{path}: not {encoding} text (byte {err.start}: {err.reason})"
        ) from None
