"""Atomic writes of the analysis outputs: a file is either its old content or its new
one, never a part (an interrupted or failed write leaves the old file in place).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """A temporary path beside ``path`` (same suffix, so writers that choose the format
    by suffix choose the same) that replaces ``path`` when the block ends without an
    exception; removed otherwise.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def write_text(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (:func:`atomic_path`); the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)
