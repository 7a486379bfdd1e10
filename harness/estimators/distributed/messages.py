"""What a message carries: the robots' grid fields, or the band's coefficients of them.

Consensus (:mod:`harness.estimators.distributed.consensus`) and the agreement on the law's
input (:mod:`harness.estimators.distributed.share`) exchange ``C`` float64 values per field:
``C = M`` grid values (:class:`GridMessages`, ``estimator.messages: grid``) or ``C = K``
band coefficients (:class:`harness.estimators.distributed.band.BandMessages`,
``estimator.messages: band``). Both implement :class:`Messages`: the robots' kernels'
change in what the messages carry, the grid fields a robot's state stands for, and the
agreement's rounds on what the messages carry of a field.
"""

from __future__ import annotations

from typing import Protocol

import numba
import numpy as np

from harness.estimators.distributed.mixing import Mixer
from harness.grid import Grid

KernelFactors = tuple[np.ndarray, ...]
"""The robots' kernels as 1-D factors ``(kx, dkx, ky, dky)``
(:func:`harness.estimators.distributed.robot_kde.kernel_factors`)."""


class Messages(Protocol):
    """What a message carries: ``size`` values per field, and the maps between the
    robots' grid fields and them.
    """

    @property
    def size(self) -> int:
        """``C``, the float64 values per field in a message."""
        ...

    def increment(self, factors: KernelFactors, old: KernelFactors | None) -> np.ndarray:
        """``phi(t + 1) - phi(t)`` in what the messages carry, ``(N, C)`` (``phi(0)``
        when ``old`` is None).
        """
        ...

    def add_increment(
        self, z: np.ndarray, factors: KernelFactors, old: KernelFactors | None
    ) -> None:
        """``z += phi(t + 1) - phi(t)`` in place (as :meth:`increment`)."""
        ...

    def fields(self, coef: np.ndarray) -> np.ndarray:
        """``(N, M)`` grid fields that ``(N, C)`` states stand for."""
        ...

    def project(self, fields: np.ndarray) -> np.ndarray:
        """``(N, M)`` fields reduced to what the messages carry of them."""
        ...

    def mixed(self, fields: np.ndarray, mix: Mixer, rounds: int) -> np.ndarray:
        """``rounds`` rounds of ``mix`` on what the messages carry of ``(N, M)``
        fields; the rest stays each robot's own.
        """
        ...


@numba.njit(cache=True, parallel=True, nogil=True)
def _add_kernel_increment(z, ky, kx, ky_old, kx_old, sign_old):  # pragma: no cover
    """``z[i] += outer(ky[i], kx[i]) + sign_old outer(ky_old[i], kx_old[i])`` (flattened
    ``(ny, nx)``), i.e. ``z += phi(t+1) - phi(t)`` for ``sign_old = -1``.
    """
    n, ny = ky.shape
    nx = kx.shape[1]
    for i in numba.prange(n):
        for j in range(ny):
            a = ky[i, j]
            b = sign_old * ky_old[i, j]
            base = j * nx
            for c in range(nx):
                z[i, base + c] += a * kx[i, c] + b * kx_old[i, c]


class GridMessages:
    """Messages of grid fields (``estimator.messages: grid``): ``C = M`` cell values;
    the robots' states are their fields, and the kernels' change is added cell by cell
    from the kernels' 1-D factors (compiled, no ``N M`` temporary when added in place).

    Args:
        grid: The grid.
    """

    def __init__(self, grid: Grid) -> None:
        self.grid = grid

    @property
    def size(self) -> int:
        """``M``, the grid's cells."""
        return self.grid.size

    def increment(self, factors: KernelFactors, old: KernelFactors | None) -> np.ndarray:
        """``phi(t + 1) - phi(t)`` on the grid, ``(N, M)`` (``phi(0)`` when ``old`` is
        None).
        """
        delta = np.zeros((factors[0].shape[0], self.size))
        self.add_increment(delta, factors, old)
        return delta

    def add_increment(
        self, z: np.ndarray, factors: KernelFactors, old: KernelFactors | None
    ) -> None:
        """``z += phi(t + 1) - phi(t)`` cell by cell, in place."""
        kx, _, ky, _ = factors
        if old is None:  # the old kernels' values are unused (sign 0)
            _add_kernel_increment(z, ky, kx, ky, kx, 0.0)
        else:
            okx, _, oky, _ = old
            _add_kernel_increment(z, ky, kx, oky, okx, -1.0)

    def fields(self, coef: np.ndarray) -> np.ndarray:
        """The states themselves."""
        return coef

    def project(self, fields: np.ndarray) -> np.ndarray:
        """The fields themselves: a message carries every cell."""
        return fields

    def mixed(self, fields: np.ndarray, mix: Mixer, rounds: int) -> np.ndarray:
        """``W^rounds F`` on the whole fields."""
        out = fields
        for _ in range(rounds):
            out = mix(out)
        return out
