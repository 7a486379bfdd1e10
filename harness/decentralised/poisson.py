"""The per-robot gradient filters' weighted Poisson solve, batched over robots.

Each robot's gradient update solves ``(G^T diag(c_i) G) delta_i = b_i`` (the
weighted-Poisson mean update of :class:`harness.filters.local.LocalFilters`, derived in
:mod:`harness.filters.local`) with its own information ``c_i``. What is shared with the
centralised solver (:class:`harness.filters.local.WeightedPoisson`) and what is not:

* shared: the pseudo-inverse of ``G^T G`` in the orthonormal DCT-II basis, its
  eigenvalue table (:func:`harness.filters.local.laplacian_pinv_spectrum`);
* not shared, the preconditioner's transforms: the centralised solver transforms one
  field by fast DCTs, the robots' solve transforms all robots at once by dense products
  with the ``n x n`` DCT matrices (one large matrix product instead of ``N`` small
  transforms; the two round differently);
* not shared, the iteration: the centralised conjugate gradients solve one system
  (a compiled call with a banded Cholesky preconditioner on small grids, a scalar
  iteration with fast transforms on larger ones); here every robot's step length,
  stopping test and breakdown test is a vector over robots, with cells in rows and
  robots in columns so that each product runs along contiguous robots. A loop of the
  scalar solver over robots would cost ``N`` Python-level solves per step and sum its
  inner products in another order;
* not shared, the operator: :func:`_weighted_laplacian_columns` applies ``G^T diag(c_i)
  G`` to all robots in one pass (a gather along contiguous robots), the centralised
  one to one field.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.fft as sfft

from harness.filters.local import laplacian_pinv_spectrum
from harness.fokker_planck import NumericalError
from harness.grid import Grid


@numba.njit(cache=True, parallel=True, nogil=True)
def _weighted_laplacian_columns(d, c, nx, ny, dx, dy, g, out):  # pragma: no cover
    """``out[:, k] = G^T diag(c[:, k]) G d[:, k]`` for every robot ``k`` (columns), cells
    in rows (robots last, so the inner loops run along contiguous robots). ``g`` is a
    ``(2M, N)`` work array. ``G`` is :meth:`harness.grid.Grid.gradient` (central
    differences, reflecting ghosts: the neighbour beyond a wall is the cell itself);
    ``G^T`` is applied as a gather, so rows run in parallel without races and every
    value is summed in a fixed order.
    """
    m = nx * ny
    n = d.shape[1]
    for j in numba.prange(ny):
        jm = max(j - 1, 0)
        jp = min(j + 1, ny - 1)
        for i in range(nx):
            im = max(i - 1, 0)
            ip = min(i + 1, nx - 1)
            cell = j * nx + i
            for k in range(n):
                g[cell, k] = c[cell, k] * (d[j * nx + ip, k] - d[j * nx + im, k]) / (2.0 * dx)
                g[m + cell, k] = (
                    c[m + cell, k] * (d[jp * nx + i, k] - d[jm * nx + i, k]) / (2.0 * dy)
                )
    for j in numba.prange(ny):
        for i in range(nx):
            cell = j * nx + i
            for k in range(n):
                out[cell, k] = 0.0
            # x: cell i is the right neighbour of i - 1 (and of itself at the right
            # wall), the left neighbour of i + 1 (and of itself at the left wall)
            if i >= 1:
                for k in range(n):
                    out[cell, k] += g[cell - 1, k] / (2.0 * dx)
            if i == nx - 1:
                for k in range(n):
                    out[cell, k] += g[cell, k] / (2.0 * dx)
            if i <= nx - 2:
                for k in range(n):
                    out[cell, k] -= g[cell + 1, k] / (2.0 * dx)
            if i == 0:
                for k in range(n):
                    out[cell, k] -= g[cell, k] / (2.0 * dx)
            if j >= 1:
                for k in range(n):
                    out[cell, k] += g[m + cell - nx, k] / (2.0 * dy)
            if j == ny - 1:
                for k in range(n):
                    out[cell, k] += g[m + cell, k] / (2.0 * dy)
            if j <= ny - 2:
                for k in range(n):
                    out[cell, k] -= g[m + cell + nx, k] / (2.0 * dy)
            if j == 0:
                for k in range(n):
                    out[cell, k] -= g[m + cell, k] / (2.0 * dy)


class BatchedPoisson:
    """Solves ``(G^T diag(c_i) G) delta_i = b_i``, ``sum delta_i = 0``, for every robot
    ``i`` by conjugate gradients, each robot preconditioned with ``S_i^{-1/2} (G^T G)^+
    S_i^{-1/2}``, ``S_i`` the local mean of ``c_i`` that scales the operator's diagonal
    (:meth:`diagonal_weights`).

    ``G^T G`` is diagonal in the orthonormal DCT-II basis, so its pseudo-inverse is two
    transforms; for ``N`` robots on a small grid they are dense products with the
    ``n x n`` DCT matrices over all robots at once. The iteration keeps cells in rows and
    robots in columns, so each product is one large matrix product and the operator a
    compiled pass along contiguous robots (:func:`_weighted_laplacian_columns`). The
    scaling takes out each robot's own range of information (a factor of about 25
    across the domain mid-run); what is left sets the iteration count (about 35 for a
    relative residual of ``1e-10`` mid-run at paper scale, ``python -m
    benchmarks.distributed --gradient-filter``). A robot stops when its residual is
    below ``tol`` relative to ``b_i``; a robot that has not, or whose iteration broke
    down above it, stops the run (:class:`~harness.fokker_planck.NumericalError`). The
    result is reproducible for the same robots; a robot's bits may differ at round-off
    with the batch it is solved in (the blocking of the batched matrix products).
    """

    def __init__(self, grid: Grid, tol: float = 1e-10) -> None:
        self.grid, self.tol = grid, tol
        self.g = grid.gradient_matrix.tocsr()
        self.gt = self.g.T.tocsr()
        self._inv = laplacian_pinv_spectrum(grid)[:, :, None]
        self._cx = sfft.dct(np.eye(grid.nx), type=2, norm="ortho", axis=0)
        self._cy = sfft.dct(np.eye(grid.ny), type=2, norm="ortho", axis=0)
        # contiguous transposes: the batched products fall back to slow loops otherwise
        self._cx_t = np.ascontiguousarray(self._cx.T)
        self._cy_t = np.ascontiguousarray(self._cy.T)
        self._work: tuple[np.ndarray, ...] | None = None
        self.iterations = 0

    def diagonal_weights(self, c: np.ndarray) -> np.ndarray:
        """``S_i`` ``(N, M)``: per cell, the mean of the four gradient-grid weights that
        enter its diagonal entry of ``G^T diag(c_i) G`` (central differences: ``c_x`` of
        the left and right neighbours, ``c_y`` of the lower and upper ones; a wall cell
        uses itself for the missing one), so that on square cells (``dx = dy``) ``S_i``
        times the unweighted diagonal is the weighted one in the interior. (The plain
        per-cell mean of ``c_i`` needs about 50 rather than 35 iterations mid-run at
        paper scale.) Rows are robots.
        """
        g = self.grid
        n = c.shape[0]
        cx = c[:, : g.size].reshape(n, g.ny, g.nx)
        cy = c[:, g.size :].reshape(n, g.ny, g.nx)
        s = np.empty((n, g.ny, g.nx))
        s[:, :, 1:-1] = cx[:, :, :-2] + cx[:, :, 2:]
        s[:, :, 0] = cx[:, :, 0] + cx[:, :, 1]
        s[:, :, -1] = cx[:, :, -2] + cx[:, :, -1]
        s[:, 1:-1, :] += cy[:, :-2, :] + cy[:, 2:, :]
        s[:, 0, :] += cy[:, 0, :] + cy[:, 1, :]
        s[:, -1, :] += cy[:, -2, :] + cy[:, -1, :]
        return 0.25 * s.reshape(n, g.size)

    def _buffers(self, n: int) -> tuple[np.ndarray, ...]:
        """Work arrays for ``n`` robots (cells by robots), kept between calls."""
        m = self.grid.size
        if self._work is None or self._work[0].shape[1] != n:
            self._work = (np.empty((m, n)), np.empty((m, n)), np.empty((2 * m, n)))
        return self._work

    def pinv_columns(self, r: np.ndarray, out: np.ndarray) -> np.ndarray:
        """``out[:, k] = (G^T G)^+ r[:, k]`` for cells by robots ``(M, N)`` (four dense
        products with the DCT matrices; ``out`` may be ``r``).
        """
        g = self.grid
        n = r.shape[1]
        _, b, _ = self._buffers(n)
        np.matmul(self._cy, r.reshape(g.ny, g.nx * n), out=b.reshape(g.ny, g.nx * n))  # y
        coef = out.reshape(g.ny, g.nx, n)
        np.matmul(self._cx, b.reshape(g.ny, g.nx, n), out=coef)  # x, per row of modes
        coef *= self._inv
        np.matmul(self._cx_t, coef, out=b.reshape(g.ny, g.nx, n))
        np.matmul(self._cy_t, b.reshape(g.ny, g.nx * n), out=out.reshape(g.ny, g.nx * n))
        return out

    def laplacian_pinv(self, r: np.ndarray) -> np.ndarray:
        """``(G^T G)^+ r_i`` for every row of ``r`` ``(N, M)`` (robots in rows)."""
        cols = np.array(r.T, dtype=float, order="C")  # a copy: never a view of r
        return np.ascontiguousarray(self.pinv_columns(cols, cols).T)

    def solve(self, c: np.ndarray, b: np.ndarray, maxiter: int = 500) -> np.ndarray:
        """Zero-mean solutions ``(N, M)`` for information ``c`` ``(N, 2M)``, ``b`` ``(N, M)``
        (robots in rows; the iteration runs on the transposes).

        Raises:
            NumericalError: A robot's residual is not below ``tol`` after ``maxiter``
                iterations (the estimate would not be the filter's).
        """
        g = self.grid
        n = b.shape[0]
        top = np.max(np.abs(b), axis=1)
        if not np.isfinite(top).all():
            raise NumericalError("gradient update: a robot's right-hand side is not finite")
        if not (np.isfinite(c).all() and (c > 0.0).all()):
            raise NumericalError(
                "gradient update: a robot's information is not finite and positive"
            )
        # each robot's right-hand side divided by a power of two near its largest entry
        # (the largest entry scaled into [1, 2)): exact, and its inner products cannot
        # overflow
        unit = np.where(top > 0.0, np.ldexp(1.0, np.frexp(top)[1] - 1), 1.0)
        ct = np.ascontiguousarray(c.T)
        scale = np.ascontiguousarray((1.0 / np.sqrt(self.diagonal_weights(c))).T)
        r = np.array(b.T / unit, dtype=float, order="C")
        _, _, work = self._buffers(n)
        z, ad = np.empty_like(r), np.empty_like(r)

        def precondition() -> None:
            np.multiply(scale, r, out=z)
            self.pinv_columns(z, z)
            np.multiply(z, scale, out=z)

        x = np.zeros_like(r)
        b_norm = np.sqrt(np.einsum("ij,ij->j", r, r))
        active = b_norm > 0.0
        precondition()
        d = z.copy()
        rz = np.einsum("ij,ij->j", r, z)
        its = 0
        while active.any() and its < maxiter:
            its += 1
            _weighted_laplacian_columns(d, ct, g.nx, g.ny, g.dx, g.dy, work, ad)
            curv = np.einsum("ij,ij->j", d, ad)
            # a robot whose preconditioned residual vanished has converged to round-off
            active &= (rz > 0.0) & (curv > 0.0)
            step = np.where(active, rz / np.where(active, curv, 1.0), 0.0)
            x += step * d
            r -= step * ad
            active &= np.sqrt(np.einsum("ij,ij->j", r, r)) > self.tol * b_norm
            if not active.any():
                break
            precondition()
            rz_new = np.einsum("ij,ij->j", r, z)
            beta = np.where(active, rz_new / np.where(rz > 0, rz, 1.0), 0.0)
            d *= beta
            d += z
            rz = rz_new
        self.iterations = its
        # every robot, also one whose iteration stopped on a vanishing r^T z or d^T A d:
        # its residual off the constants (the part of b along them cannot be reduced)
        r -= r.mean(axis=0)
        off = np.sqrt(np.einsum("ij,ij->j", r, r))
        failed = ~(off <= self.tol * b_norm)
        if failed.any():
            raise NumericalError(
                f"gradient update: {int(failed.sum())} robots' Poisson solves did not "
                f"reach the tolerance in {its} iterations"
            )
        x -= x.mean(axis=0)
        x *= unit
        return np.ascontiguousarray(x.T)
