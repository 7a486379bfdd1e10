"""The gradient filter's update on free space (a domain with obstacles): the weighted
Poisson problem ``(G^T diag(C) G) delta = b`` with ``G`` the free-space gradient, solved
by conjugate gradients preconditioned with a lagged banded Cholesky factor
(:class:`FreePoisson`); the rectangle's solvers are in
:mod:`harness.estimators.filters.poisson`.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from harness.compiled.filters import (
    band_rows,
)
from harness.compiled.free_poisson import free_pinned_band_operator, free_poisson_pcg
from harness.domains.base import FreeSpace
from harness.estimators.diffusion import gradient_matrix
from harness.estimators.filters.poisson import PCG_MAXITER, power_of_two_scale
from harness.fokker_planck import NumericalError


class FreePoisson:
    """Solves ``(G^T diag(C) G) delta = b`` on free space, ``G`` the free-space gradient
    (:func:`harness.estimators.diffusion.gradient_matrix`: central differences, the cell
    itself behind a closed face), with zero mean on every component of free space.

    Neither of the rectangle's solvers applies: the DCT preconditioner and the band's
    cosine Gram matrix assume every cell and face of the rectangle. The operator is
    singular on each component's constants (the null space of ``G``), which are pinned
    (the first cell of each component: its row and column replaced by the unit vector);
    blocked cells are not unknowns (0 in the result; the pinned band holds the unit
    vector on their rows). Conjugate gradients are preconditioned by the banded Cholesky
    factor of the pinned operator for an earlier ``C``, refactored when more than
    ``refactor_after`` iterations were needed or the iteration failed: the coefficients
    change slowly, so one factor serves many steps, and with a fresh factor the iteration
    converges in one or two steps. As on the rectangle
    (:class:`WeightedPoisson`), the operator couples cells at distance 1 and 2 along an
    axis, so with the cells numbered along the longer side first the band is ``w = 2
    min(n_x, n_y)`` wide: a factor costs ``M w^2`` operations (LAPACK ``pbtrf``), a
    solve ``2 M w``. The whole iteration is one compiled call
    (:func:`harness.compiled.free_poisson.free_poisson_pcg`, the operator matrix-free);
    :meth:`solve_reference` is the same iteration in numpy on the free cells, with the
    sparse product and a sparse LU of the same pinned operator.

    Args:
        free: Free space.
        tol: Relative residual (off the components' constants) at which it stops.
        refactor_after: Iterations above which the next solve refactors.
    """

    def __init__(self, free: FreeSpace, tol: float = 1e-10, refactor_after: int = 8) -> None:
        self.free, self.grid = free, free.grid
        g = self.grid
        self.g = gradient_matrix(free)
        self.gt = self.g.T.tocsr()
        self.cells = np.flatnonzero(free.cells.ravel())
        self._g_free = self.g[:, self.cells].tocsc()
        labels = free.labels.ravel()[self.cells]
        self._labels = labels
        self._counts = np.bincount(labels, minlength=free.n_components).astype(float)
        self._pins = np.array([int(np.argmax(labels == c)) for c in range(free.n_components)])
        self.tol, self.refactor_after = tol, refactor_after
        self._lu: spla.SuperLU | None = None
        self.iterations = 0
        self.factorizations = 0
        # the compiled path: whole-grid fields, the gradient's two cells per gradient cell
        self._lo, self._hi = gradient_neighbours(free)
        self._hx, self._hy = 0.5 / g.dx, 0.5 / g.dy
        self._grid_labels = np.ascontiguousarray(free.labels.ravel(), dtype=np.int64)
        pinned = ~free.cells.ravel()
        pinned[self.cells[self._pins]] = True
        self._pinned = pinned
        cells = np.arange(g.size)
        self._order = cells if g.nx <= g.ny else cells.reshape(g.shape).T.ravel()
        self._position = np.empty_like(cells)
        self._position[self._order] = cells
        self._width = 2 * min(g.nx, g.ny)
        self._factor: np.ndarray | None = None
        self._factor_rows = np.empty((0, 0))
        self._factor_inv = np.empty(0)

    def _off_constants(self, r: np.ndarray) -> np.ndarray:
        """``r`` (on the free cells) less its mean on every component."""
        means = np.bincount(self._labels, r, self._counts.size) / self._counts
        return r - means[self._labels]

    def _operator(self, c: np.ndarray) -> sp.csr_matrix:
        return (self._g_free.T @ sp.diags(c) @ self._g_free).tocsr()

    def _factor_lu(self, op: sp.csr_matrix) -> None:
        pinned = op.tolil()
        for i in self._pins:
            pinned[i, :] = 0.0
            pinned[:, i] = 0.0
            pinned[i, i] = 1.0
        try:
            self._lu = spla.splu(pinned.tocsc())
        except RuntimeError as err:  # singular: a null mode of G besides the constants
            raise NumericalError(f"gradient update: the operator is singular ({err})") from err

    def _precondition(self, r: np.ndarray) -> np.ndarray:
        assert self._lu is not None
        r = r.copy()
        r[self._pins] = 0.0
        return self._off_constants(self._lu.solve(r))

    def _pcg(self, op: sp.csr_matrix, b: np.ndarray) -> tuple[np.ndarray, int, bool]:
        x = np.zeros_like(b)
        r = b.copy()
        b_norm = float(np.linalg.norm(b))
        if b_norm == 0.0:
            return x, 0, True
        z = self._precondition(r)
        d = z.copy()
        rz = float(r @ z)
        for it in range(1, PCG_MAXITER + 1):
            if np.linalg.norm(self._off_constants(r)) <= self.tol * b_norm:
                return x, it - 1, True
            ad = op @ d
            curvature = float(d @ ad)
            if rz <= 0.0 or curvature <= 0.0:
                break
            step = rz / curvature
            x += step * d
            r -= step * ad
            z = self._precondition(r)
            rz_new = float(r @ z)
            d = z + (rz_new / rz) * d
            rz = rz_new
        return x, PCG_MAXITER, bool(np.linalg.norm(self._off_constants(r)) <= self.tol * b_norm)

    def band_operator(self, c: np.ndarray) -> np.ndarray:
        """The pinned operator for weights ``c`` in LAPACK's lower band storage, cells in
        the band's order (:func:`harness.compiled.free_poisson.free_pinned_band_operator`).
        """
        return free_pinned_band_operator(
            np.ascontiguousarray(c, dtype=float), self._hx, self._hy, self._lo, self._hi,
            self._position, self._width, self._pinned,
        )  # fmt: skip

    def _refactor(self, c: np.ndarray) -> None:
        """The preconditioner from ``c``: the banded Cholesky factor of the pinned
        operator, its rows (:func:`harness.compiled.filters.band_rows`) and its
        diagonal's reciprocals.
        """
        try:
            factor = sla.cholesky_banded(self.band_operator(c), lower=True, check_finite=False)
        except np.linalg.LinAlgError as err:  # a null mode of G besides the constants
            raise NumericalError(f"gradient update: the operator is singular ({err})") from err
        factor = np.ascontiguousarray(factor.T)
        self._factor_rows = band_rows(factor)
        self._factor_inv = 1.0 / factor[:, 0]
        self._factor = factor
        self.factorizations += 1

    def _iterate(self, c: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int, bool]:
        assert self._factor is not None
        return free_poisson_pcg(
            c, rhs, self._hx, self._hy, self._lo, self._hi, self._factor, self._factor_rows,
            self._factor_inv, self._order, self._pinned, self._grid_labels, self._counts,
            self.tol, PCG_MAXITER,
        )  # fmt: skip

    def _check(self, c: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray]:
        """The power of two ``b`` is divided by and the scaled right-hand side on the free
        cells, off the components' constants.

        Raises:
            NumericalError: ``b`` or ``c`` not finite (``c`` not positive).
        """
        if not (np.isfinite(c).all() and (c > 0.0).all()):
            raise NumericalError("gradient update: the information is not finite and positive")
        unit = power_of_two_scale(b)
        if unit == 0.0:
            return unit, np.zeros(self.cells.size)
        return unit, self._off_constants(b[self.cells] / unit)

    def solve(self, c: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The solution ``(M,)`` with zero mean on every component (0 on blocked cells).

        Raises:
            NumericalError: ``b`` or ``c`` not finite (``c`` not positive), or the
                iteration does not converge with a fresh factor.
        """
        unit, rhs_free = self._check(c, b)
        out = np.zeros(self.grid.size)
        if unit == 0.0:
            return out
        c = np.ascontiguousarray(c, dtype=float)
        rhs = np.zeros(self.grid.size)
        rhs[self.cells] = rhs_free
        if self._factor is None:
            self._refactor(c)
        x, its, converged = self._iterate(c, rhs)
        if not converged:
            self._refactor(c)
            x, its, converged = self._iterate(c, rhs)
        elif its > self.refactor_after:
            self._refactor(c)
        self.iterations = its
        if not converged:
            raise NumericalError("gradient update: the weighted Poisson solve did not converge")
        out[self.cells] = unit * self._off_constants(x[self.cells])
        return out

    def solve_reference(self, c: np.ndarray, b: np.ndarray) -> np.ndarray:
        """:meth:`solve` in numpy with a fresh preconditioner: the iteration on the free
        cells with the sparse operator, preconditioned by a sparse LU of the pinned
        operator for ``c``.

        Raises:
            NumericalError: as :meth:`solve`.
        """
        unit, rhs = self._check(c, b)
        out = np.zeros(self.grid.size)
        if unit == 0.0:
            return out
        op = self._operator(c)
        self._factor_lu(op)
        x, _, converged = self._pcg(op, rhs)
        if not converged:
            raise NumericalError("gradient update: the weighted Poisson solve did not converge")
        out[self.cells] = unit * self._off_constants(x)
        return out


def gradient_neighbours(free: FreeSpace) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` ``(2M,)`` int: the two cells the free-space gradient
    (:func:`harness.estimators.diffusion.gradient_matrix`) differences at each gradient
    cell (x cells, then y cells): the neighbour across the open face, else the cell
    itself; both the cell itself for blocked cells.
    """
    g = free.grid
    idx = np.arange(g.size).reshape(g.shape)
    east, west, north, south = free.neighbours(idx)
    blocked = ~free.cells
    for a in (east, west, north, south):
        a[blocked] = idx[blocked]
    lo = np.concatenate([west.ravel(), south.ravel()]).astype(np.int64)
    hi = np.concatenate([east.ravel(), north.ravel()]).astype(np.int64)
    return lo, hi
