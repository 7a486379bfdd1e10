"""On-disk caching of compiled loops keyed by the whole package's source.

numba's cache keys a compiled function by a hash of the one file that defines it. A loop
that calls a compiled function of another module (the robots' step calls
:func:`harness.compiled.obstacles.avoid`) is then loaded from the cache with the callee
it was compiled with, after the callee's module has changed: numba does not track
calls between modules. :func:`stamp_by_package` makes every function of a package's
directory keyed by the hash of all the package's ``.py`` files, so an edit of any of
them recompiles the package's loops once, and a cached loop always runs the current
code. Other packages' caches are untouched.

Relies on numba's cache locators (``numba.core.caching``, numba >= 0.68, whose source
stamps are content hashes).
"""

from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path
from typing import Any

from numba.core import caching


def package_stamp(directory: Path) -> bytes:
    """The SHA-256 of the names and bytes of every ``.py`` file in ``directory`` (not
    its subdirectories), in name order; re-read when a file's size or time changes.
    """
    files = sorted(directory.glob("*.py"))
    stats = tuple((f.name, f.stat().st_mtime_ns, f.stat().st_size) for f in files)
    return _stamp(str(directory), stats)


@functools.lru_cache(maxsize=64)
def _stamp(directory: str, stats: tuple[tuple[str, int, int], ...]) -> bytes:
    digest = hashlib.sha256()
    for name, _, _ in stats:
        digest.update(name.encode() + b"\0")
        digest.update((Path(directory) / name).read_bytes() + b"\0")
    return digest.digest()


def _locator(base: type, directory: Path) -> type:
    """A subclass of the numba locator ``base`` that answers only for functions defined
    in ``directory`` and stamps them with :func:`package_stamp`.
    """

    class PackageStamped(base):
        @classmethod
        def from_function(cls, py_func: Any, py_file: str) -> Any:
            if Path(os.path.abspath(py_file)).parent != directory:
                return None
            return super().from_function(py_func, py_file)

        def get_source_stamp(self) -> Any:
            return package_stamp(directory)

    PackageStamped.__name__ = PackageStamped.__qualname__ = f"PackageStamped{base.__name__}"
    return PackageStamped


def stamp_by_package(directory: Path) -> None:
    """Key the on-disk cache of every compiled function defined in ``directory`` by
    :func:`package_stamp` of it, wherever numba would put it (``NUMBA_CACHE_DIR`` when
    set, else the directory's ``__pycache__``). Idempotent.
    """
    directory = Path(os.path.abspath(directory))
    classes = caching.CacheImpl._locator_classes
    if any(getattr(c, "directory", None) == directory for c in classes):
        return
    ours: list[Any] = [
        _locator(caching.UserProvidedCacheLocator, directory),
        _locator(caching.InTreeCacheLocator, directory),
    ]
    for cls in ours:
        cls.directory = directory
    classes[:0] = ours
