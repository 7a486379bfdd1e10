"""The robots' kernels and messages on free space (a domain with obstacles).

On the square each robot's kernel is the Gaussian with its wall images
(:mod:`harness.estimators.distributed.robot_kde`). On free space
(:class:`harness.domains.base.FreeSpace`) the centralised KDE is diffusion of the robots'
histogram on the masked domain (:class:`harness.estimators.diffusion.FreeKernel`): each
robot's ``1 / N`` is split bilinearly over at most four subcells of a grid ``r`` times
finer (``b_i``, shares summing to 1, none across a closed face), diffused for ``h^2 /
2`` with no flux through closed faces and read at the control cells' centres,

    p_KDE = R exp(t A) (1/N) sum_i b_i / s^2 = (1/N) sum_i phi_i,
    phi_i = R exp(t A) b_i / s^2 = sum_k b_ik T[c_ik],     T = (R exp(t A))^T / s^2,  (FREE)

with ``R`` the read-out, ``A`` the drift-free Fokker-Planck operator of unit diffusivity
on the fine free space and ``s^2`` a fine cell's area. The map is linear, so robot ``i``'s
own kernel ``phi_i`` is the combination of at most four rows of the table ``T`` (the
free-space heat kernel's columns at its subcells, read at the control cells), and the
mean of the robots' kernels is the centralised free-space KDE (to round-off: the table
and the KDE apply the same series in two orders). ``A`` is symmetric, so ``T`` is the
heat kernel applied once to the read-out's rows (``M_free`` columns of the fine grid,
made when the estimator is built). A kernel never reaches through a wall: ``phi_i`` is
0 on every cell that no path in free space of the series' length joins to the robot,
and exactly 0 on blocked cells and on the other components.

A robot knows its kernel from its position and the map of free space alone (it could run
the series on board for its own subcells, ``O(K M_fine)`` operations); the simulation
shares one table. Its size is ``M_fine_free x M_free`` float64: about 47 MB on the
paper's 30 x 30 grid at ``h = 0.04`` (``r = 3``, rooms).

Messages carry only free cells: grid messages ``M_free`` values
(:class:`FreeGridMessages`), band messages the coefficients of the modes of
:class:`harness.estimators.filters.common.FreeBand` (the masked Laplacian's lowest
modes, 0 on blocked cells; :class:`FreeBandMessages`), the band the centralised filters
keep on free space.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np

from harness.domains.base import FreeSpace
from harness.estimators.diffusion import FreeKernel, bilinear_shares
from harness.estimators.distributed.messages import KernelFactors
from harness.estimators.distributed.mixing import Mixer
from harness.estimators.filters.common import FreeBand


@numba.njit(cache=True, parallel=True, nogil=True)
def _add_kernels(z, table, rows, shares, sign):  # pragma: no cover - compiled
    """``z[i] += sign sum_k shares[i, k] table[rows[i, k]]`` for every robot ``i``
    (rows of ``z`` in parallel; a zero share is skipped).
    """
    n, c = z.shape
    for i in numba.prange(n):
        zi = z[i]
        for k in range(rows.shape[1]):
            s = sign * shares[i, k]
            if s != 0.0:
                t = table[rows[i, k]]
                for j in range(c):
                    zi[j] += s * t[j]


class FreeRobotKernels:
    """Each robot's own kernel on free space (eq. ``FREE`` of the module docstring).

    Args:
        free: Free space on the control grid.
        bandwidth: ``h`` (length).
    """

    def __init__(self, free: FreeSpace, bandwidth: float) -> None:
        self.free, self.bandwidth = free, float(bandwidth)
        self.kernel = k = FreeKernel(free, bandwidth)
        fine = k.fine
        self.cells = np.flatnonzero(free.cells.ravel())  # the control grid's free cells
        self.fine_cells = np.flatnonzero(fine.cells.ravel())
        self.row = np.full(fine.grid.size, -1, dtype=np.int64)  # fine cell -> table row
        self.row[self.fine_cells] = np.arange(self.fine_cells.size)
        # T = (R exp(tA))^T / s^2 = exp(tA) R^T / s^2 (A symmetric), free rows and columns
        read_t = k.read[self.cells].T.toarray()  # (M_fine, M_free)
        heat = k.heat(read_t)[self.fine_cells]
        self.table = np.ascontiguousarray(np.maximum(heat, 0.0) / fine.grid.cell_area)

    def shares(self, positions: np.ndarray) -> KernelFactors:
        """The robots' bilinear shares ``b_i`` on the fine grid: ``(rows, shares)``,
        ``(N, 4)`` table rows (``table``) and shares summing to 1 per robot, as
        :func:`harness.compiled.binning.free_binning` splits a robot (a robot found in a
        blocked subcell counts whole at its nearest free one).
        """
        k = self.kernel
        pos = np.asarray(positions, dtype=float)
        targets, shares = bilinear_shares(k.fine, k.targets, k.home, pos)
        return np.ascontiguousarray(self.row[targets]), np.ascontiguousarray(shares)

    def __call__(self, positions: np.ndarray) -> KernelFactors:
        """:meth:`shares` (the robots' kernels as the consensus keeps them)."""
        return self.shares(positions)

    def kernels(self, factors: KernelFactors) -> np.ndarray:
        """``(N, M_free)`` the robots' kernels ``phi_i`` on the free cells."""
        rows, shares = factors
        out = np.zeros((rows.shape[0], self.table.shape[1]))
        _add_kernels(out, self.table, rows, shares, 1.0)
        return out

    def kde(self, factors: KernelFactors) -> tuple[np.ndarray, np.ndarray]:
        """The centralised free-space KDE of the robots, ``(p, grad p)`` of shapes
        ``(ny, nx)`` and ``(2, ny, nx)``: their shares binned, diffused and read out
        (:meth:`harness.estimators.diffusion.FreeKernel.density`).
        """
        rows, shares = factors
        fg = self.kernel.fine.grid
        w = np.bincount(self.fine_cells[rows.ravel()], shares.ravel(), fg.size)
        return self.kernel.density(w / (rows.shape[0] * fg.cell_area))


@numba.njit(cache=True, parallel=True, nogil=True)
def _free_gradients(p, cells, east, west, north, south, dx, dy, out):  # pragma: no cover
    """``out[i, c] = (p[i, east] - p[i, west]) / (2 dx)`` and ``out[i, M + c] = (p[i,
    north] - p[i, south]) / (2 dy)`` at every free cell ``c`` (``cells``), rows in
    parallel; entries of blocked cells are left as they are.
    """
    n, m = p.shape
    for i in numba.prange(n):
        pi, oi = p[i], out[i]
        for k in range(cells.size):
            c = cells[k]
            oi[c] = (pi[east[k]] - pi[west[k]]) / (2.0 * dx)
            oi[m + c] = (pi[north[k]] - pi[south[k]]) / (2.0 * dy)


class FreeGradients:
    """Every robot's free-space gradient of its own density estimate,
    :meth:`harness.domains.base.FreeSpace.gradient` row by row (central differences, the
    cell itself behind a closed face, 0 on blocked cells), compiled over robots, into
    ``(N, 2M)`` (``x`` block then ``y`` block, the layout of
    :class:`harness.records.RobotEstimates`), an array reused from step to step.

    Args:
        free: Free space.
    """

    def __init__(self, free: FreeSpace) -> None:
        g = free.grid
        self.grid = g
        idx = np.arange(g.size).reshape(g.shape)
        east, west, north, south = free.neighbours(idx)
        on = free.cells
        self._cells, self._east, self._west, self._north, self._south = (
            np.ascontiguousarray(a[on], dtype=np.int64) for a in (idx, east, west, north, south)
        )
        self._out: np.ndarray | None = None

    def __call__(self, p_hat: np.ndarray) -> np.ndarray:
        """``(N, 2M)`` gradients of ``(N, M)`` estimates (valid until the next call)."""
        p = np.ascontiguousarray(p_hat, dtype=float)
        shape = (p.shape[0], 2 * self.grid.size)
        if self._out is None or self._out.shape != shape:
            self._out = np.zeros(shape)
        _free_gradients(p, self._cells, self._east, self._west, self._north, self._south,
                        self.grid.dx, self.grid.dy, self._out)  # fmt: skip
        return self._out


class FreeGridMessages:
    """Messages of the free cells' values (``estimator.messages: grid`` on free space):
    ``C = M_free`` values; blocked cells are 0 in every robot's field and are not sent
    (:class:`harness.estimators.distributed.messages.Messages`).

    Args:
        kernels: The robots' kernels on free space.
    """

    def __init__(self, kernels: FreeRobotKernels) -> None:
        self.kernels = kernels
        self.grid = kernels.free.grid
        self.cells = kernels.cells
        self.table = kernels.table

    @property
    def size(self) -> int:
        """``C``, values per field in a message."""
        return int(self.table.shape[1])

    def add_increment(
        self, z: np.ndarray, factors: KernelFactors, old: KernelFactors | None
    ) -> None:
        """``z += phi(t + 1) - phi(t)`` in what the messages carry, in place."""
        rows, shares = factors
        _add_kernels(z, self.table, rows, shares, 1.0)
        if old is not None:
            _add_kernels(z, self.table, old[0], old[1], -1.0)

    def increment(self, factors: KernelFactors, old: KernelFactors | None) -> np.ndarray:
        """``phi(t + 1) - phi(t)`` ``(N, C)`` (``phi(0)`` when ``old`` is None)."""
        out = np.zeros((factors[0].shape[0], self.size))
        self.add_increment(out, factors, old)
        return out

    def coefficients(self, fields: np.ndarray) -> np.ndarray:
        """``(N, C)`` what the messages carry of ``(N, M)`` fields: the free cells."""
        return np.ascontiguousarray(np.asarray(fields, dtype=float)[:, self.cells])

    def fields(self, coef: np.ndarray) -> np.ndarray:
        """``(N, M)`` fields of ``(N, C)`` states, 0 on blocked cells."""
        coef = np.asarray(coef, dtype=float)
        out = np.zeros((coef.shape[0], self.grid.size))
        out[:, self.cells] = coef
        return out

    def project(self, fields: np.ndarray) -> np.ndarray:
        """The fields as the messages carry them (blocked cells set to 0)."""
        return self.fields(self.coefficients(fields))

    def mixed(self, fields: np.ndarray, mix: Mixer, rounds: int) -> np.ndarray:
        """``rounds`` rounds of ``mix`` on what the messages carry of ``(N, M)`` fields;
        the rest stays each robot's own.
        """
        coef = self.coefficients(fields)
        outside = fields - self.fields(coef)
        for _ in range(rounds):
            coef = mix(coef)
        return outside + self.fields(coef)


class FreeBandMessages(FreeGridMessages):
    """Band messages on free space (``estimator.messages: band``): the coefficients of
    the robots' fields on the modes ``V`` ``(M_free, K)`` of
    :class:`~harness.estimators.filters.common.FreeBand` (orthonormal, 0 on blocked
    cells), ``c = F V`` and ``Pi F = c V^T``; a robot's kernel's coefficients are rows
    of ``T V`` (eq. ``FREE``). Consensus on the coefficients is consensus on the fields
    followed by ``Pi``, as on the square.

    Args:
        kernels: The robots' kernels on free space.
        cutoff: ``kappa_c`` (1 / length), finite: ``band_limit / h``.
    """

    def __init__(self, kernels: FreeRobotKernels, cutoff: float) -> None:
        if not np.isfinite(cutoff) or cutoff <= 0:
            raise ValueError(f"the band's cutoff must be a finite number > 0, got {cutoff}")
        super().__init__(kernels)
        self.band = FreeBand(kernels.free, float(cutoff))
        self.modes = self.band.modes
        self.table = np.ascontiguousarray(kernels.table @ self.modes)

    def coefficients(self, fields: np.ndarray) -> np.ndarray:
        """``(N, K)`` coefficients of ``(N, M)`` fields on the band's modes."""
        return np.asarray(fields, dtype=float)[:, self.cells] @ self.modes

    def fields(self, coef: np.ndarray) -> np.ndarray:
        """``(N, M)`` fields ``Pi F_i`` of ``(N, K)`` coefficients."""
        return super().fields(np.asarray(coef, dtype=float) @ self.modes.T)


FREE_MESSAGES: dict[str, Callable[[float, FreeRobotKernels], FreeGridMessages]] = {
    "grid": lambda band_limit, kernels: FreeGridMessages(kernels),
    "band": lambda band_limit, kernels: FreeBandMessages(kernels, band_limit / kernels.bandwidth),
}
"""``estimator.messages`` on free space (the keys of
:data:`harness.estimators.distributed.design.MESSAGES`), from the design's ``band_limit``
(``kappa_c h``) and the robots' kernels.

:meta hide-value:
"""
