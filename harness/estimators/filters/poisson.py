"""The gradient filter's update: the weighted Poisson problem ``(G^T diag(C) G) delta =
b``, solved on the grid or within the band.

The fast gradient filter (:mod:`harness.estimators.filters.local`) keeps information
that is diagonal on the gradient grid, ``Y = G^T diag(C) G``; its update's posterior mean
is the weighted least-squares fit of the innovation by a gradient field,

    (G^T C^+ G) delta = G^T W_g (y_g - G x_g^-),      sum delta = 0,

a variable-coefficient Poisson problem, singular only on the constants (the null space
of the grid gradient ``G``). On grids up to ``lu_max_cells`` cells it is solved on the
grid by preconditioned conjugate gradients (:class:`WeightedPoisson`); on finer grids
with a band limit, within the band's ``K`` cosine modes (:class:`BandPoisson`), at a cost
that does not grow with the grid.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.fft as sfft
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from harness.compiled.filters import (
    band_gram,
    band_rows,
    pinned_band_operator,
    weighted_poisson_pcg,
)
from harness.estimators.filters.common import BandLimit
from harness.fokker_planck import NumericalError
from harness.grid import Grid


class WeightedPoisson:
    """Solves ``(G^T diag(C) G) delta = b`` with ``sum delta = 0`` for ``b`` orthogonal
    to the constants, by preconditioned conjugate gradients.

    ``G^T C G`` is singular only on the constants (the null space of ``G``).
    Two preconditioners:

    * small grids (``M <= lu_max_cells``): a banded Cholesky factor of the operator
      with cell 0 pinned, taken from an earlier ``C`` and refactored when more than
      ``refactor_after`` iterations were needed (the coefficients change slowly). The
      operator couples a cell to its neighbours at distance 1 and 2 along each axis, so
      with the cells numbered along the longer side first its bandwidth is ``2
      min(n_x, n_y)``: a factor costs ``M w^2`` operations (LAPACK ``pbtrf``) and a
      solve ``2 M w``. The whole iteration is one compiled call
      (:func:`harness.compiled.filters.weighted_poisson_pcg`, the operator matrix-free);
      :meth:`solve_reference` is the same iteration in numpy with a sparse LU;
    * larger grids: ``S^{-1/2} (G^T G)^+ S^{-1/2}`` with ``S`` the per-cell mean of
      ``C`` over its two components; ``G^T G`` is diagonal in the orthonormal DCT-II
      basis (:meth:`harness.grid.Grid.gradient` maps cosine modes to sine modes), so
      its pseudo-inverse costs two fast transforms, ``O(M log M)``, against a
      factorisation that grows like ``M^1.5``. When that does not converge in
      ``maxiter`` iterations (very rough ``C``) the LU preconditioner takes over.

    The result is shifted to zero mean.
    """

    def __init__(
        self,
        grid: Grid,
        tol: float = 1e-10,
        refactor_after: int = 8,
        maxiter: int = 60,
        lu_max_cells: int = 1024,
    ) -> None:
        self.grid = grid
        self.g = grid.gradient_matrix.tocsr()
        self.gt = self.g.T.tocsr()
        self.tol = tol
        self.refactor_after = refactor_after
        self.maxiter = maxiter
        self.lu_max_cells = lu_max_cells
        self._lu: Callable[[np.ndarray], np.ndarray] | None = None
        self._factor: np.ndarray | None = None
        self._factor_rows = np.empty((0, 0))  # band_rows(self._factor)
        self._factor_inv = np.empty(0)  # 1 / diagonal of self._factor
        cells = np.arange(grid.size)
        # number the cells along the longer side first: the band is 2 min(nx, ny) wide
        self._order = cells if grid.nx <= grid.ny else cells.reshape(grid.shape).T.ravel()
        self._position = np.empty_like(cells)
        self._position[self._order] = cells
        # the band's width in that ordering: couplings two rows (of the shorter side) apart
        self._width = 2 * min(grid.nx, grid.ny)
        self.iterations = 0
        self.factorizations = 0
        self._inv_laplacian = laplacian_pinv_spectrum(grid)

    def _laplacian_pinv(self, r: np.ndarray) -> np.ndarray:
        g = self.grid
        coef = sfft.dctn(r.reshape(g.shape), type=2, norm="ortho")
        coef *= self._inv_laplacian
        return sfft.idctn(coef, type=2, norm="ortho").ravel()

    def _lu_preconditioner(self, op: sp.csr_matrix):
        pinned = op.tolil()
        pinned[0, :] = 0.0
        pinned[:, 0] = 0.0
        pinned[0, 0] = 1.0
        lu = spla.splu(pinned.tocsc())
        self.factorizations += 1

        def apply(r: np.ndarray) -> np.ndarray:
            r = r.copy()
            r[0] = 0.0
            z = lu.solve(r)
            return z - z.mean()

        return apply

    def _band_factor(self, c: np.ndarray) -> np.ndarray:
        """Banded Cholesky factor of ``G^T diag(c) G`` with cell 0 pinned (its row and
        column replaced by the unit vector), cells in ``self._order``, in the layout of
        :func:`harness.compiled.filters.band_cholesky_solve`: the band assembled by
        :func:`harness.compiled.filters.pinned_band_operator` (:meth:`_band_operator_reference`
        states it with the sparse product), factored by LAPACK ``pbtrf``.
        """
        g, m = self.grid, self.grid.size
        cx, cy = c[:m].reshape(g.shape), c[m:].reshape(g.shape)
        ab = pinned_band_operator(cx, cy, g.dx, g.dy, self._position, self._width)
        try:
            factor = sla.cholesky_banded(ab, lower=True, check_finite=False)
        except np.linalg.LinAlgError as err:
            raise NumericalError(f"gradient update: the operator is not definite ({err})") from err
        self.factorizations += 1
        return np.ascontiguousarray(factor.T)

    def _band_operator_reference(self, c: np.ndarray, width: int | None = None) -> np.ndarray:
        """The pinned operator's lower band storage from the sparse product ``G^T diag(c)
        G`` (numpy; the statement of :func:`harness.compiled.filters.pinned_band_operator`);
        ``width`` defaults to the widest coupling in that ordering.
        """
        op = (self.gt @ sp.diags(c) @ self.g).tocoo()
        rows, cols = self._position[op.row], self._position[op.col]
        keep = (rows >= cols) & (op.row != 0) & (op.col != 0)
        rows, cols, data = rows[keep], cols[keep], op.data[keep]
        if width is None:
            width = int(np.max(rows - cols, initial=0))
        ab = np.zeros((width + 1, self.grid.size))
        np.add.at(ab, (rows - cols, cols), data)
        ab[0, 0] = 1.0
        return ab

    def _refactor(self, c: np.ndarray) -> None:
        """The small grids' preconditioner from ``c``: :meth:`_band_factor`, its rows
        (:func:`harness.compiled.filters.band_rows`) and its diagonal's reciprocals.
        """
        factor = self._band_factor(c)
        self._factor_rows = band_rows(factor)
        self._factor_inv = 1.0 / factor[:, 0]
        self._factor = factor

    def solve(self, c: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The zero-mean solution of ``G^T diag(c) G delta = b``.

        The iteration runs on ``b`` divided by a power of two near its largest entry
        (:func:`power_of_two_scale`; exact, so the result is the same bits), so that its
        inner products do not overflow for right-hand sides above about 1e154.

        Raises:
            NumericalError: ``b`` is not finite, ``c`` not finite and positive, or the
                iteration does not reach the tolerance.
        """
        if not (np.isfinite(c).all() and (c > 0.0).all()):
            raise NumericalError("gradient update: the information is not finite and positive")
        unit = power_of_two_scale(b)
        if unit == 0.0:
            return np.zeros_like(b)
        return unit * self._solve(c, b / unit)

    def _solve(self, c: np.ndarray, b: np.ndarray) -> np.ndarray:
        m, g = self.grid.size, self.grid
        if m <= self.lu_max_cells:
            cx, cy = c[:m].reshape(g.shape), c[m:].reshape(g.shape)
            rhs = b.reshape(g.shape)

            def iterate() -> tuple[np.ndarray, int, bool]:
                assert self._factor is not None
                return weighted_poisson_pcg(
                    cx, cy, rhs, g.dx, g.dy, self._factor, self._factor_rows,
                    self._factor_inv, self._order, self.tol, PCG_MAXITER,
                )  # fmt: skip

            if self._factor is None:
                self._refactor(c)
            delta, its, converged = iterate()
            if not converged:  # the lagged factor may be stale: once more with a fresh one
                self._refactor(c)
                delta, its, converged = iterate()
            elif its > self.refactor_after:
                self._refactor(c)
            self.iterations = its
            if not converged:
                raise NumericalError("gradient update: the weighted Poisson solve did not converge")
            delta = delta.ravel()
            return delta - delta.mean()
        op = (self.gt @ sp.diags(c) @ self.g).tocsr()
        scale = 1.0 / np.sqrt(0.5 * (c[:m] + c[m:]))

        def precondition(r: np.ndarray) -> np.ndarray:
            return scale * self._laplacian_pinv(scale * r)

        delta, its, converged = _pcg(op, precondition, b, self.tol, self.maxiter)
        if not converged:
            delta, its, converged = _pcg(op, self._lu_preconditioner(op), b, self.tol)
        self.iterations = its
        if not converged:
            raise NumericalError("gradient update: the weighted Poisson solve did not converge")
        return delta - delta.mean()

    def solve_reference(self, c: np.ndarray, b: np.ndarray) -> np.ndarray:
        """:meth:`solve` by the numpy iteration :func:`_pcg` preconditioned by a fresh
        sparse LU of the pinned operator (the numpy statement of the small grids' path).
        """
        op = (self.gt @ sp.diags(c) @ self.g).tocsr()
        delta, _, converged = _pcg(op, self._lu_preconditioner(op), b, self.tol)
        if not converged:
            raise NumericalError("gradient update: the weighted Poisson solve did not converge")
        return delta - delta.mean()


class BandPoisson:
    """The weighted Poisson problem of the gradient update within the band: the
    posterior mean of a band-limited state, solved in the cosine modes.

    The gradient filter's state lives in ``range(Pi)`` (:class:`BandLimit`), spanned by
    the orthonormal DCT-II modes ``phi_ab`` with ``|kappa_ab| <= kappa_c``. For a prior
    of information ``G^T diag(C^-) G`` and the measurement ``y_g = G x_g + v`` (``v`` of
    information ``W_g``), the posterior mean of that state is ``x_g^- + B a`` with

        (B^T G^T diag(C^+) G B) a = B^T G^T W_g (y_g - G x_g^-),      C^+ = C^- + W_g,

    ``B`` the band's modes without the constant (``G`` does not see it, so ``delta`` has
    zero mean): a ``K x K`` system, ``K`` the modes in the band (about 330 for ``h =
    0.04`` and ``band_limit = 2.5``, on every grid finer than 40 x 40), solved by
    Cholesky. The grid-wide solve of :class:`WeightedPoisson` followed by ``Pi`` is the
    same for constant ``C`` (``G^T G`` is diagonal in the modes) and an approximation of
    it otherwise; its cost grows with the cells, this one's does not (two fast
    transforms aside).

    The Gram matrix from the transforms of ``C``. The grid gradient maps the modes
    exactly (:meth:`harness.grid.Grid.gradient`): ``G_x phi_ab = -s_a psi_a(x)
    phi_b(y)`` with ``s_a = sin(pi a / n_x) / dx`` and ``psi_a`` the sine companion of
    ``phi_a`` (same normalisation ``c_a``), likewise along ``y``. Products of two cosines
    or two sines are sums of cosines of the sum and difference frequencies, so

        [B^T G_x^T diag(C_x) G_x B]_(ab),(a'b') = s_a s_a' c_a c_a' c_b c_b' / 4
            (E(|a-a'|, |b-b'|) + E(|a-a'|, b+b') - E(a+a', |b-b'|) - E(a+a', b+b')),

    with ``E(alpha, beta) = sum_ij C_x(i, j) cos(pi alpha (i + 1/2) / n_x) cos(pi beta
    (j + 1/2) / n_y)``, a quarter of the unnormalised DCT-II of ``C_x`` for ``alpha <
    n_x``, ``beta < n_y``, extended beyond by ``E(2 n - m) = -E(m)`` and ``E(n) = 0`` per
    axis (the cosines alias with a sign); the ``y`` part has the signs of the sine
    products on the ``y`` frequencies. A test compares with the dense product.

    Args:
        grid: The grid.
        band: The band (its ``mask`` of kept modes).
    """

    def __init__(self, grid: Grid, band: BandLimit) -> None:
        self.grid = grid
        self.bases = band.bases
        rows, cols = np.nonzero(band.mask)
        varying = (rows > 0) | (cols > 0)
        self.a, self.b = cols[varying], rows[varying]  # x and y mode numbers
        nx, ny = grid.nx, grid.ny
        ca = np.sqrt(np.where(self.a == 0, 1.0, 2.0) / nx)  # orthonormal DCT-II scaling
        cb = np.sqrt(np.where(self.b == 0, 1.0, 2.0) / ny)
        s_a = np.sin(np.pi * self.a / nx) / grid.dx
        s_b = np.sin(np.pi * self.b / ny) / grid.dy
        # gram = wx wx^T o (E_x combination) + wy wy^T o (E_y combination)
        self._wx, self._wy = s_a * ca * cb / 2.0, s_b * ca * cb / 2.0
        norm = np.outer(ca * cb, ca * cb) / 4.0
        self._fx = (norm * np.outer(s_a, s_a)).ravel()
        self._fy = (norm * np.outer(s_b, s_b)).ravel()
        a0, a1 = self.a[:, None], self.a[None, :]
        b0, b1 = self.b[:, None], self.b[None, :]
        # flat indices into E (2 n_y x 2 n_x) of (|b-b'|, |a-a'|), (b+b', |a-a'|),
        # (|b-b'|, a+a'), (b+b', a+a')
        width = 2 * nx
        pairs = [(np.abs(b0 - b1), np.abs(a0 - a1)), (b0 + b1, np.abs(a0 - a1)),
                 (np.abs(b0 - b1), a0 + a1), (b0 + b1, a0 + a1)]  # fmt: skip
        self._take = [(y * width + x).ravel() for y, x in pairs]
        self._quarter_suffices = 2 * int(self.a.max()) < nx and 2 * int(self.b.max()) < ny
        self._work = tuple(np.empty(self.a.size**2) for _ in range(5))

    @property
    def modes(self) -> int:
        """``K``, the band's non-constant modes."""
        return int(self.a.size)

    def _extended(self, c: np.ndarray) -> np.ndarray:
        """``E(beta, alpha)`` for ``beta < 2 n_y``, ``alpha < 2 n_x`` (see above); on
        grids where the band's sum frequencies ``a + a'``, ``b + b'`` stay below ``n_x``,
        ``n_y`` (every grid from ``n`` of about 2 kappa_c / pi on) only the quarter
        ``beta < n_y``, ``alpha < n_x`` is read, and only the quarter is returned.
        """
        quarter = sfft.dctn(c.reshape(self.grid.shape), type=2)
        quarter *= 0.25
        if self._quarter_suffices:
            return quarter
        return self._extend(quarter)

    def _extend(self, quarter: np.ndarray) -> np.ndarray:
        """The quarter extended by the sign rules (see the class docstring)."""
        g = self.grid
        e = np.zeros((2 * g.ny, 2 * g.nx))
        e[: g.ny, : g.nx] = quarter
        e[: g.ny, g.nx + 1 :] = -quarter[:, :0:-1]
        e[g.ny + 1 :, :] = -e[g.ny - 1 : 0 : -1, :]
        return e

    def _full(self, c: np.ndarray) -> np.ndarray:
        """``E`` on the whole ``2 n_y x 2 n_x`` range (the reference's flat indices)."""
        return self._extend(0.25 * sfft.dctn(c.reshape(self.grid.shape), type=2))

    def _upper(self, c: np.ndarray) -> np.ndarray:
        """The upper triangle of :meth:`gram` (strict lower triangle undefined)."""
        m, k = self.grid.size, self.modes
        out = np.empty((k, k))
        ex, ey = self._extended(c[:m]), self._extended(c[m:])
        band_gram(ex, ey, self.a, self.b, self._wx, self._wy, out)
        return out

    def gram(self, c: np.ndarray) -> np.ndarray:
        """``B^T G^T diag(c) G B`` (``K x K``) for gradient-grid weights ``c`` (2M),
        compiled (:func:`harness.compiled.filters.band_gram`, upper triangle, mirrored here;
        :meth:`gram_reference` is the numpy statement).
        """
        upper = np.triu(self._upper(c))
        return upper + np.triu(upper, 1).T

    def gram_reference(self, c: np.ndarray) -> np.ndarray:
        """:meth:`gram` by gathers of the extended transforms (numpy)."""
        m, k = self.grid.size, self.modes
        # preallocated work: fresh K x K temporaries cost page faults that dominate
        dd, sd, ds, ss, part = self._work
        gram = np.empty(k * k)
        flat = self._full(c[:m]).ravel()
        for i, out in zip(self._take, (dd, sd, ds, ss), strict=True):
            np.take(flat, i, out=out)
        np.add(dd, sd, out=part)  # x part: (dd + sd) - (ds + ss)
        part -= ds
        part -= ss
        np.multiply(self._fx, part, out=gram)
        flat = self._full(c[m:]).ravel()
        for i, out in zip(self._take, (dd, sd, ds, ss), strict=True):
            np.take(flat, i, out=out)
        np.subtract(dd, sd, out=part)  # y part: (dd - sd) + (ds - ss)
        part += ds
        part -= ss
        part *= self._fy
        gram += part
        return gram.reshape(k, k)

    def solve(self, c: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``B a`` with ``(B^T G^T diag(c) G B) a = B^T b``: zero mean, in the band."""
        g = self.grid
        c_y, c_x = self.bases  # the band's rows of the orthonormal DCT-II matrices
        rhs = (c_y @ b.reshape(g.shape) @ c_x.T)[self.b, self.a]
        # The row-major upper triangle is the column-major lower one: LAPACK's Cholesky
        # (potrf) and its solve (potrs) read it in place, without a copy or mirroring.
        lower = self._upper(c).T
        factor, info = sla.lapack.dpotrf(lower, lower=1, clean=0, overwrite_a=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"band Gram matrix not positive definite ({info})")
        coef, info = sla.lapack.dpotrs(factor, rhs, lower=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"band solve failed ({info})")
        full = np.zeros((c_y.shape[0], c_x.shape[0]))
        full[self.b, self.a] = coef
        return (c_y.T @ full @ c_x).ravel()


def power_of_two_scale(b: np.ndarray) -> float:
    """``2^e`` with ``max |b| / 2^e`` in ``[1, 2)`` (0 for ``b = 0``): dividing by it is
    exact (the scale itself is finite up to the largest float), and the scaled vector's
    squared norm cannot overflow.

    Raises:
        NumericalError: ``b`` holds a NaN or an infinity.
    """
    top = float(np.max(np.abs(b), initial=0.0))
    if not np.isfinite(top):
        raise NumericalError("gradient update: the right-hand side is not finite")
    if top == 0.0:
        return 0.0
    return float(np.ldexp(1.0, int(np.frexp(top)[1]) - 1))


def _gradient_eigenvalues(n: int, h: float) -> np.ndarray:
    """Eigenvalues ``|D phi_a|^2`` of ``D^T D`` for the 1-D grid gradient ``D`` (central
    differences, reflecting ghosts) on the orthonormal DCT-II vectors ``phi_a``.
    """
    from harness.grid import gradient_1d

    basis = sfft.idct(np.eye(n), type=2, norm="ortho", axis=0)
    return np.sum((gradient_1d(n, h) @ basis) ** 2, axis=0)


def laplacian_pinv_spectrum(grid: Grid) -> np.ndarray:
    """The pseudo-inverse of ``G^T G`` in the orthonormal DCT-II basis, ``(ny, nx)``:
    ``1 / lambda`` on the modes with ``lambda > 1e-12 max lambda`` and 0 on the
    constants (``lambda = |D_y phi_b|^2 + |D_x phi_a|^2``, :func:`_gradient_eigenvalues`
    per axis); :class:`WeightedPoisson` preconditions with it.
    """
    eig_x = _gradient_eigenvalues(grid.nx, grid.dx)
    eig_y = _gradient_eigenvalues(grid.ny, grid.dy)
    lam = eig_y[:, None] + eig_x[None, :]
    inv = np.zeros_like(lam)
    inv[lam > 1e-12 * lam.max()] = 1.0 / lam[lam > 1e-12 * lam.max()]
    return inv


PCG_MAXITER = 200
"""Iterations after which conjugate gradients give up."""


def _pcg(
    op: sp.csr_matrix, precond, b: np.ndarray, tol: float, maxiter: int = PCG_MAXITER
) -> tuple[np.ndarray, int, bool]:
    """Preconditioned conjugate gradients from zero for the operator ``G^T diag(c) G``,
    singular on the constants; returns ``(x, iterations, converged)``, converged when
    the residual off the constants is at most ``tol ||b||`` (the part of ``b`` along
    the constants, zero up to round-off for ``b = G^T v``, cannot be reduced and is
    ignored). An iteration that breaks down (``r^T z <= 0`` or ``d^T A d <= 0``) stops
    and reports that test.
    """
    x = np.zeros_like(b)
    r = b.copy()
    b_norm = float(np.linalg.norm(b))
    if b_norm == 0.0:
        return x, 0, True

    def done() -> bool:
        return bool(np.linalg.norm(r - r.mean()) <= tol * b_norm)

    z = precond(r)
    d = z.copy()
    rz = float(r @ z)
    for it in range(1, maxiter + 1):
        ad = op @ d
        curvature = float(d @ ad)
        if rz <= 0.0 or curvature <= 0.0:
            # the preconditioned residual vanished: converged to round-off, or broke down
            return x, it - 1, done()
        step = rz / curvature
        x += step * d
        r -= step * ad
        if np.linalg.norm(r) <= tol * b_norm:
            return x, it, True
        z = precond(r)
        rz_new = float(r @ z)
        d = z + (rz_new / rz) * d
        rz = rz_new
    return x, maxiter, done()
