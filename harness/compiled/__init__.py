"""Compiled (numba) loops of the harness, one module per domain they serve.

- :mod:`~harness.compiled.agents`: the robots' Euler-Maruyama step;
- :mod:`~harness.compiled.assignment`: the optimality check of ot's large assignment;
- :mod:`~harness.compiled.binning`: the KDE's linear binning;
- :mod:`~harness.compiled.fokker_planck`: the assembly of ``A(v)``, the implicit
  solvers (Jacobi-split and truncated Neumann series, red-black Gauss-Seidel), the
  density checks of a step;
- :mod:`~harness.compiled.control`: the paper's law;
- :mod:`~harness.compiled.filters`: the filters' variance prediction and the gradient
  update (band Gram matrix, banded Cholesky, conjugate gradients).

Each loop has a numpy, sparse or LAPACK statement, named in its docstring, that tests
compare against. Loops are compiled on first use and cached on disk next to their
module, keyed by the source of the whole package (:func:`stamp_by_package`). A
loop run serially on small inputs and in parallel on large ones has both builds in one
:class:`SerialParallel`.
"""

from __future__ import annotations

import os
import types
from collections.abc import Callable
from inspect import signature
from typing import Any

# Idle OpenMP workers sleep instead of spinning (unless the user chose otherwise):
# on a machine shared with other jobs (sweeps run one job per core) spinning
# workers steal the cores the next parallel region waits for, and a compiled loop of
# a few ms takes hundreds. Read when numba first starts its OpenMP layer.
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import functools
import hashlib
from pathlib import Path

import numba
from numba.core import caching

PARALLEL_MIN_CELLS = 1 << 16
"""Fewer cells (values, for several columns) run the serial build of the Jacobi series,
the red-black sweeps, the assembly of ``A(v)`` and the band transition variance (a
parallel region costs more than it saves on small grids, and much more on a busy
machine)."""


def build(fn: Callable[..., Any], parallel: bool) -> Any:
    """``numba.njit(cache=True, nogil=True, parallel=parallel)`` of a copy of ``fn``
    named ``<fn>_parallel`` or ``<fn>_serial``.

    Why a copy: numba's on-disk cache names an entry by the function's qualified name
    and first line and keys it by signature and bytecode, not by the compile flags, so
    two plain builds of one function with different flags share one entry, and
    whichever is compiled first is loaded by both (measured: the cached "parallel"
    assembly ran at the serial speed). The copies have their own names, so their own
    entries.
    """
    suffix = "_parallel" if parallel else "_serial"
    copy = types.FunctionType(
        fn.__code__, fn.__globals__, fn.__name__ + suffix, fn.__defaults__, fn.__closure__
    )
    copy.__qualname__ = fn.__qualname__ + suffix
    copy.__doc__, copy.__module__ = fn.__doc__, fn.__module__
    return numba.njit(cache=True, nogil=True, parallel=parallel)(copy)


class SerialParallel:
    """The serial and the parallel build of ``fn`` (:func:`build`), called like ``fn``
    (positional arguments).

    A call runs the serial build when ``size`` of ``fn``'s argument named ``argument``
    is below ``min_size``, and the parallel build otherwise; without ``argument``,
    always the parallel build (the serial one is then there for comparisons). Both
    builds run the same arithmetic, so they give the same bits.
    """

    def __init__(
        self,
        fn: Callable[..., Any],
        argument: str | None = None,
        size: Callable[[Any], int] | None = None,
        min_size: int = 0,
    ) -> None:
        if (argument is None) != (size is None):
            raise ValueError("SerialParallel takes both argument and size, or neither")
        self.serial = build(fn, parallel=False)
        self.parallel = build(fn, parallel=True)
        self.min_size = min_size
        self.__doc__ = fn.__doc__
        self._choice: tuple[int, Callable[[Any], int]] | None = None
        if argument is not None and size is not None:
            self._choice = (list(signature(fn).parameters).index(argument), size)

    def __call__(self, *args: Any) -> Any:
        """``fn(*args)`` by the build that the chosen argument's size picks."""
        if self._choice is not None:
            position, size = self._choice
            if size(args[position]) < self.min_size:
                return self.serial(*args)
        return self.parallel(*args)


# --- the disk cache, keyed by the whole package's source --------------------------------
# numba keys a compiled function's cache entry by a hash of the one file that defines it.
# A loop that calls a compiled function of another module (the robots' step calls
# obstacles.avoid) would be loaded with the callee it was compiled with after the callee's
# module changed: numba does not track calls between modules. stamp_by_package keys every
# function of this package by the hash of all its .py files, so an edit of any of them
# recompiles the package's loops once. It relies on numba's cache locators
# (numba.core.caching, numba >= 0.68, whose source stamps are content hashes).


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


stamp_by_package(Path(__file__).parent)
