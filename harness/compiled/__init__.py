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
module, keyed by the source of the whole package (:mod:`~harness.compiled.caching`). A
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

from pathlib import Path

import numba

from harness.compiled.caching import stamp_by_package

# a loop's cache entry is keyed by every module of this package, not only its own: the
# robots' steps call obstacles.avoid, which numba would not see change
stamp_by_package(Path(__file__).parent)

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
