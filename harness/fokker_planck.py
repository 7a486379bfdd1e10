"""Finite-volume Fokker-Planck operator with reflecting walls (eq. ``FP equation``).

The paper's mean-field model is

    d_t p = -div(v p) + sigma Laplacian(p)     in Omega,
    n . (sigma grad p - v p) = 0               on the walls,

with constant noise intensity ``sigma`` (length^2 / time). On the cell-centred grid
it becomes ``dp/dt = A(v) p`` where ``A(v)`` is an ``M x M`` sparse matrix built
from fluxes through the interior faces; wall faces carry no flux.

Flux through a face (Scharfetter-Gummel, exponential fitting). For the face
between a left cell ``L`` and a right cell ``R`` with normal velocity ``u``,
spacing ``h`` and diffusivity ``D = sigma``, the flux from L to R is

    F = (D / h) [ B(-Pe) p_L - B(Pe) p_R ],   Pe = u h / D,   B(z) = z / (e^z - 1).

Properties the tests check:

* Mass: each face flux leaves one cell and enters its neighbour, so every column
  of ``A`` sums to zero and ``int p`` is conserved to round-off.
* Positivity: ``B > 0``, so ``A`` has non-negative off-diagonal entries for every
  cell Peclet number; ``I - dt A`` is then an M-matrix and the backward-Euler
  step keeps ``p >= 0`` for every ``dt``.
* Equilibrium: if ``u = sigma (log p*_R - log p*_L) / h`` on every face, the flux
  of ``p = p*`` vanishes exactly, so ``p*`` is a discrete steady state.
* Limits: ``D -> 0`` gives first-order upwinding, ``u -> 0`` central diffusion
  ``-D (p_R - p_L) / h``; the scheme is second order in space for smooth data
  (first order where ``|Pe| >> 1``).

The plain reference :func:`rate` computes ``A(v) p`` face by face; the fast path
:meth:`FokkerPlanck.matrix` fills a CSR matrix with a precomputed pattern. A test
checks they agree. The implicit step solves ``(I - dt A) p_next = p`` by red-black
Gauss-Seidel with an exact mass correction (:func:`red_black_solve`, cost ``O(M)`` per
sweep; operators given without the grid's shape take a Neumann series when ``dt ||A||``
is small, else the Jacobi-split series :func:`jacobi_solve`, with twice the sweeps),
with the sparse LU solve (:meth:`FokkerPlanck.step_lu`) as reference and last resort.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from harness.compiled.fokker_planck import (
    assemble_operator,
    density_summary,
    jacobi_series,
    neumann_series,
    red_black,
)
from harness.domains.base import FreeSpace
from harness.grid import Grid
from harness.velocity import VelocityField


class NumericalError(RuntimeError):
    """Raised when a step produces non-finite values, negative density or lost mass."""


def _expm1_scalar(t: float) -> float:
    try:
        return math.expm1(t)
    except OverflowError:  # the C function's result, which math reports as an error
        return math.inf


_expm1_each = np.frompyfunc(_expm1_scalar, 1, 1)


def expm1(x: np.ndarray) -> np.ndarray:
    """``exp(x) - 1`` elementwise by the C library's ``expm1`` (``math.expm1``; ``inf``
    on overflow), the function the compiled assembly calls. Not ``np.expm1``: numpy
    dispatches it to SIMD code of its own on some processors (AVX-512 ones among
    them), which differs from the C library in the last bit for about 5 to 9 % of the
    arguments (measured), so a reference built on it would match the compiled
    assembly bit for bit on some machines only. Slow (one Python call per value): for
    the references.
    """
    return np.asarray(_expm1_each(np.asarray(x, dtype=float)), dtype=float)


def bernoulli(z: np.ndarray) -> np.ndarray:
    """Bernoulli function ``B(z) = z / (exp(z) - 1)`` with ``B(0) = 1``, stable for
    all real ``z`` (``B(z) -> -z`` as ``z -> -inf``, ``-> 0`` as ``z -> +inf``).
    """
    z = np.asarray(z, dtype=float)
    small = np.abs(z) < 1e-6
    safe = np.where(small, 1.0, z)
    with np.errstate(over="ignore"):
        out = safe / expm1(safe)
    return np.where(small, 1.0 - 0.5 * z, out)


def face_coefficients(u: np.ndarray, diffusivity: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients ``(a_L, a_R)`` of the face flux ``F = a_L p_L - a_R p_R``.

    Args:
        u: Normal velocity on the faces (length / time), positive from L to R.
        diffusivity: ``D = sigma >= 0`` (length^2 / time).
        h: Distance between the two cell centres (length).

    Returns:
        ``a_L = (D/h) B(-Pe)`` and ``a_R = (D/h) B(Pe)``, both ``>= 0``, in length /
        time. For ``D = 0`` these are the upwind values ``max(u, 0)``, ``max(-u, 0)``.
    """
    if diffusivity < 0:
        raise ValueError(f"diffusivity must be >= 0, got {diffusivity}")
    if diffusivity == 0.0:
        return np.maximum(u, 0.0), np.maximum(-u, 0.0)
    scale = diffusivity / h
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        pe = u / scale
        # a_R = scale B(Pe) = u / (exp(Pe) - 1): finite for every Pe, also when a
        # tiny diffusivity makes Pe overflow (then the upwind values come out)
        a_r = np.where(np.abs(pe) < 1e-6, scale * (1.0 - 0.5 * pe), u / expm1(pe))
    # B(-z) = B(z) + z, so a_L = a_R + u
    return a_r + u, a_r


def rate(
    grid: Grid, p: np.ndarray, v: VelocityField, sigma: float, free: FreeSpace | None = None
) -> np.ndarray:
    """Reference right-hand side ``dp/dt = -div(v p) + sigma Laplacian(p)`` (eq.
    ``FP equation``) as face fluxes, plain numpy, for testing the fast path.

    Args:
        grid: The grid.
        p: Density, shape ``(ny, nx)`` (1 / length^2).
        v: Velocity field; only the face values are used.
        sigma: Noise intensity ``sigma >= 0`` (length^2 / time).
        free: Free space on the grid; no flux crosses its closed faces (None: every
            interior face is open).

    Returns:
        ``dp/dt``, shape ``(ny, nx)``, in 1 / (length^2 time).
    """
    out = np.zeros_like(p, dtype=float)
    a_l, a_r = face_coefficients(v.face_x, sigma, grid.dx)
    flux_x = a_l * p[:, :-1] - a_r * p[:, 1:]
    if free is not None:
        flux_x = np.where(free.face_x, flux_x, 0.0)
    out[:, :-1] -= flux_x / grid.dx
    out[:, 1:] += flux_x / grid.dx
    a_l, a_r = face_coefficients(v.face_y, sigma, grid.dy)
    flux_y = a_l * p[:-1, :] - a_r * p[1:, :]
    if free is not None:
        flux_y = np.where(free.face_y, flux_y, 0.0)
    out[:-1, :] -= flux_y / grid.dy
    out[1:, :] += flux_y / grid.dy
    return out


@dataclass(frozen=True)
class _Pattern:
    """CSR sparsity pattern of ``A`` and where each face coefficient lands in it."""

    indptr: np.ndarray
    indices: np.ndarray
    slot: np.ndarray  # position in csr data of each (row, col) entry listed below
    diag_slot: np.ndarray  # position in csr data of each diagonal entry
    nnz: int


def _build_pattern(grid: Grid) -> _Pattern:
    idx = np.arange(grid.size).reshape(grid.shape)
    left_x, right_x = idx[:, :-1].ravel(), idx[:, 1:].ravel()
    left_y, right_y = idx[:-1, :].ravel(), idx[1:, :].ravel()
    left = np.concatenate([left_x, left_y])
    right = np.concatenate([right_x, right_y])
    diag = np.arange(grid.size)
    # Entries: (L,L), (L,R), (R,L), (R,R) for each face, then the diagonal.
    rows = np.concatenate([left, left, right, right, diag])
    cols = np.concatenate([left, right, left, right, diag])
    order = np.lexsort((cols, rows))
    keys = rows[order] * grid.size + cols[order]
    unique_keys = np.unique(keys)
    slot_sorted = np.searchsorted(unique_keys, keys)
    slot = np.empty_like(slot_sorted)
    slot[order] = slot_sorted
    u_rows = unique_keys // grid.size
    u_cols = unique_keys % grid.size
    indptr = np.searchsorted(u_rows, np.arange(grid.size + 1)).astype(np.int32)
    nfaces = left.size
    return _Pattern(
        indptr=indptr,
        indices=u_cols.astype(np.int32),
        slot=slot[: 4 * nfaces],
        diag_slot=slot[4 * nfaces :],
        nnz=unique_keys.size,
    )


@dataclass
class FokkerPlanck:
    """The Fokker-Planck operator ``A(v)`` on a grid and its implicit time stepper.

    Args:
        grid: The grid.
        sigma: Noise intensity ``sigma >= 0`` (length^2 / time); the robots'
            Brownian term is ``sqrt(2 sigma) dB``.
        mass_tolerance: Largest relative change of ``int p`` allowed in one step
            before :meth:`step` raises :class:`NumericalError`.
        free: Free space on the grid (:class:`harness.domains.base.FreeSpace`): no flux
            through its closed faces, so a blocked cell exchanges nothing and the mass
            on each component of free space is conserved. None: the whole rectangle.
    """

    grid: Grid
    sigma: float
    mass_tolerance: float = 1e-9
    free: FreeSpace | None = None
    _pattern: _Pattern = field(init=False, repr=False)
    _template: sp.csr_matrix = field(init=False, repr=False)
    _open: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not np.isfinite(self.sigma) or self.sigma < 0:
            raise ValueError(f"sigma must be finite and >= 0, got {self.sigma}")
        if self.free is not None and self.free.grid != self.grid:
            raise ValueError("free space resolved on another grid")
        g = self.grid
        if self.free is None:
            self._open = (np.ones((g.ny, g.nx - 1), bool), np.ones((g.ny - 1, g.nx), bool))
        else:
            self._open = (self.free.face_x.copy(), self.free.face_y.copy())
        for flags in self._open:
            flags.flags.writeable = False
        self._pattern = _build_pattern(self.grid)
        pat, size = self._pattern, self.grid.size
        # every A(v) shares the pattern's index arrays, read-only so that no consumer
        # can change them under the others
        pat.indptr.flags.writeable = False
        pat.indices.flags.writeable = False
        self._template = sp.csr_matrix(
            (np.zeros(pat.nnz), pat.indices, pat.indptr), shape=(size, size)
        )

    def _face_rates(self, v: VelocityField) -> tuple[np.ndarray, np.ndarray]:
        """Face rates ``(a_L / h, a_R / h)`` (1 / time), x faces then y faces."""
        g = self.grid
        ax_l, ax_r = face_coefficients(v.face_x.ravel(), self.sigma, g.dx)
        ay_l, ay_r = face_coefficients(v.face_y.ravel(), self.sigma, g.dy)
        a_l = np.concatenate([ax_l / g.dx, ay_l / g.dy])
        a_r = np.concatenate([ax_r / g.dx, ay_r / g.dy])
        open_faces = np.concatenate([f.ravel() for f in self._open])
        return np.where(open_faces, a_l, 0.0), np.where(open_faces, a_r, 0.0)

    def matrix(self, v: VelocityField) -> sp.csr_matrix:
        """Sparse ``A(v)`` with ``dp/dt = A(v) p`` on flattened fields (eq. ``FP
        equation``); columns sum to zero, off-diagonals are ``>= 0``.

        Filled by the compiled :func:`harness.compiled.fokker_planck.assemble_operator`
        (the face rates, then the rows, in one call), equal bit for bit to
        :meth:`matrix_reference`.
        """
        g, pat = self.grid, self._pattern
        a = copy.copy(self._template)  # scipy's constructor re-checks the pattern: 40 us
        face_x = np.ascontiguousarray(v.face_x, dtype=float)
        face_y = np.ascontiguousarray(v.face_y, dtype=float)
        a.data = assemble_operator(
            face_x, face_y, *self._open, float(self.sigma), float(g.dx), float(g.dy), pat.indptr
        )
        return a

    def matrix_reference(self, v: VelocityField) -> sp.csr_matrix:
        """Plain-numpy statement of :meth:`matrix` (``np.bincount`` over the entries)."""
        g = self.grid
        a_l, a_r = self._face_rates(v)
        # dp_L -= F/h, dp_R += F/h with F = a_L p_L - a_R p_R.
        values = np.concatenate([-a_l, a_r, a_l, -a_r, np.zeros(g.size)])
        slots = np.concatenate([self._pattern.slot, self._pattern.diag_slot])
        data = np.bincount(slots, weights=values, minlength=self._pattern.nnz)
        return sp.csr_matrix(
            (data, self._pattern.indices, self._pattern.indptr), shape=(g.size, g.size)
        )

    def rate(self, p: np.ndarray, v: VelocityField) -> np.ndarray:
        """``A(v) p`` through the sparse matrix, shape ``(ny, nx)``."""
        return (self.matrix(v) @ p.ravel()).reshape(self.grid.shape)

    def step(
        self, p: np.ndarray, v: VelocityField, dt: float, a: sp.csr_matrix | None = None
    ) -> np.ndarray:
        """One backward-Euler step ``(I - dt A(v)) p_next = p`` (``a`` may pass a
        precomputed ``A(v)``).

        Unconditionally stable, positivity preserving (M-matrix) and mass
        conserving for every ``dt > 0``; first order in time.

        Solver (:func:`implicit_solve`): red-black Gauss-Seidel
        (:func:`red_black_solve`), whose cost is ``O(M)`` per sweep and whose sweep
        count depends on ``dt`` times the largest outflow rate only; it is positive
        and mass-conserving by construction. The sparse LU solve (:meth:`step_lu`) is
        the last resort when it would need more than ``_MAX_JACOBI_TERMS`` sweeps.
        Callers without the grid's shape get the truncated Neumann series ``sum_k (dt
        A)^k p`` from :func:`implicit_solve`: after ``K`` terms the remainder is at most
        ``rho^(K+1) / (1 - rho) ||p||_1`` (``rho = dt ||A||_1``), and each term with
        ``k >= 1`` has zero mass.

        Raises:
            NumericalError: if ``v`` or the result is not finite, the result has a
                negative value below round-off, or the mass changed by more than
                ``mass_tolerance`` (relative).
        """
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        if not v.is_finite():
            raise NumericalError("velocity field has non-finite values")
        if not np.isfinite(p).all():
            raise NumericalError("density has non-finite values before the step")
        a = self.matrix(v) if a is None else a
        p_next = implicit_solve(a, dt, p.ravel().astype(float), self.grid.nx)
        p_next = p_next.reshape(self.grid.shape)
        check_density(self.grid, p, p_next, self.mass_tolerance)
        return p_next

    def step_lu(self, p: np.ndarray, v: VelocityField, dt: float) -> np.ndarray:
        """Reference backward-Euler step by sparse LU, without checks."""
        system = (sp.identity(self.grid.size, format="csr") - dt * self.matrix(v)).tocsc()
        return spla.splu(system).solve(p.ravel().astype(float)).reshape(self.grid.shape)


_MAX_SERIES_TERMS = 12
"""Most Neumann-series terms :func:`implicit_solve` takes for an operator given without
the grid's shape; above, the Jacobi-split series (chosen when the series was the small
grids' step: a sparse LU was cheaper above it, `make bench` at n = 30 to 128)."""


def series_terms(rho: float) -> int:
    """Terms ``K`` with ``rho^(K+1) / (1 - rho) <= 1e-15`` (``K = 0`` when ``rho = 0``;
    a large number when ``rho >= 1``).
    """
    if rho == 0.0:
        return 0
    if rho >= 1.0:
        return 10**9
    return max(int(np.ceil(np.log(1e-15 * (1.0 - rho)) / np.log(rho))) - 1, 1)


_MAX_JACOBI_TERMS = 400
"""Above this many Jacobi-series terms (bound of :func:`jacobi_solve`) a sparse LU
solve is used; one term costs about ``1 / 1000`` of a factorisation at n = 128."""

JACOBI_TOLERANCE = 1e-15
"""Relative L1 residual ``||r||_1 / ||rhs||_1`` at which :func:`jacobi_solve` stops."""


def jacobi_solve(
    a: sp.csr_matrix, dt: float, rhs: np.ndarray, tol: float = JACOBI_TOLERANCE
) -> np.ndarray | None:
    """Solve ``(I - dt A) x = rhs`` (one column ``(M,)``) by the Jacobi-split Neumann
    series with a mass-exact, positive final correction; ``None`` if the series
    would need more than ``_MAX_JACOBI_TERMS`` terms.

    Derivation. Write ``I - dt A = D - N`` with ``D = diag(1 + dt o)`` (``o_j = -a_jj
    >= 0`` the outflow rate of cell ``j``, 1 / time) and ``N = dt (A - diag A) >= 0``
    (entrywise). Columns of ``A`` sum to zero, so column ``j`` of ``N`` sums to
    ``dt o_j`` and ``||N D^{-1}||_1 = q = max_j dt o_j / (1 + dt o_j) < 1`` for every
    ``dt``: the series

        x = sum_k (D^{-1} N)^k D^{-1} rhs,   delta_0 = D^{-1} rhs,  delta_{k+1} = D^{-1} N delta_k,

    converges geometrically with ratio ``q`` in the norm ``||D y||_1``. After ``K``
    terms ``x_K = sum_{k <= K} delta_k`` has the residual ``r_K = rhs - (D - N) x_K =
    N delta_K`` *exactly* (telescoping), with ``||r_K||_1 <= q^(K+1) ||rhs||_1``.
    ``(I - dt A)^{-1}`` is entrywise non-negative with unit column sums (M-matrix),
    so ``||x - x_K||_1 <= ||r_K||_1`` (with equality when ``rhs >= 0``).

    Mass correction. ``1^T (I - dt A) = 1^T``, hence ``1^T x_K = 1^T rhs - 1^T r_K``:
    the truncated series loses exactly the residual's mass. The returned value is
    ``x_K + r_K`` (one Richardson step, ``= rhs + dt A x_K``), whose mass is
    ``1^T rhs`` to round-off and whose error is ``-dt A (x - x_K)``, at most
    ``2 rho ||r_K||_1`` (``rho = dt max_j 2 o_j``). For ``rhs >= 0`` every ``delta_k``
    and ``r_K`` is ``>= 0`` (``D^{-1}``, ``N >= 0``), so the corrected value is
    non-negative: positivity without clipping.

    Cost. ``K = log(tol) / log(q)`` terms of one sparse product each, ``O(M)``;
    ``q`` depends on ``dt`` times the largest outflow rate (``4 sigma / dx^2 +
    2 |u| / dx``), about 0.25 at n = 128 and 0.4 at n = 256 at the paper's
    settings (25 to 40 terms). Warm starts buy nothing here: ``I - dt A`` is
    within ``q`` of its diagonal, so the first term already carries all but a
    fraction ``q`` of the answer. The compiled loop is
    :func:`harness.compiled.fokker_planck.jacobi_series`; the reference is the sparse LU.
    """
    o_max = float(np.max(-a.diagonal(), initial=0.0))
    q = dt * o_max / (1.0 + dt * o_max)
    if q > 0.0:
        bound = int(np.ceil(np.log(tol) / np.log(q)))
        if bound > _MAX_JACOBI_TERMS:
            return None
    else:
        bound = 1
    x, _, res = jacobi_series(
        a.indptr,
        a.indices,
        a.data,
        float(dt),
        np.ascontiguousarray(rhs, dtype=float),
        tol,
        bound + 2,
    )
    return x if res <= tol else None


def red_black_solve(
    a: sp.csr_matrix,
    dt: float,
    rhs: np.ndarray,
    nx: int,
    tol: float = JACOBI_TOLERANCE,
    diag: np.ndarray | None = None,
) -> np.ndarray | None:
    """Solve ``(I - dt A) x = rhs`` (one column ``(M,)`` or several ``(M, c)``, swept
    together; ``A`` a 5-point operator on a grid of ``nx`` columns) by red-black
    Gauss-Seidel with the same final correction as :func:`jacobi_solve`; ``None`` if it
    would need more than ``_MAX_JACOBI_TERMS`` sweeps. ``diag`` may pass ``A``'s
    diagonal when the caller has it.

    Derivation. With ``I - dt A = D - N`` as in :func:`jacobi_solve` (``D > 0``
    diagonal, ``N >= 0``), a red-black sweep is the Gauss-Seidel step of the regular
    splitting ``D - N = (D - N_rb) - N_br`` (``N_rb`` the couplings of red cells to black
    ones, updated first). For an M-matrix its iteration matrix is entrywise non-negative
    with spectral radius at most the Jacobi ratio ``q`` (Stein-Rosenberg), and for the
    5-point (consistently ordered) operator about ``q^2``: half the sweeps of the
    Jacobi series' terms, each one pass over the matrix
    (:func:`harness.compiled.fokker_planck.red_black`). From ``x_0 = 0`` and ``rhs >= 0``
    the iterates are non-negative and increase; the residual ``r_K = rhs - (D - N) x_K``
    is ``>= 0``, zero on black cells, and ``x_K + r_K`` has the mass of ``rhs`` (``1^T
    (I - dt A) = 1^T``) and is non-negative, with error ``-dt A (x - x_K)`` as there.
    Measured at the paper's settings mid-run: 9 sweeps against 17 terms at n = 128, 14
    against 26 at n = 256 (``python -m benchmarks.numerics``). The reference is the
    sparse LU.
    """
    o_max = float(np.max(-(a.diagonal() if diag is None else diag), initial=0.0))
    q = dt * o_max / (1.0 + dt * o_max)
    bound = int(np.ceil(np.log(tol) / np.log(q))) if q > 0.0 else 1
    if bound > _MAX_JACOBI_TERMS:
        return None
    rhs = np.ascontiguousarray(rhs, dtype=float)
    x, sweeps, res = red_black(
        a.indptr, a.indices, a.data, float(dt), rhs.reshape(rhs.shape[0], -1), int(nx), tol,
        bound + 2,
    )  # fmt: skip
    if sweeps < 0:
        raise ValueError(f"not a 5-point operator on a grid of {nx} columns ({a.shape[0]} rows)")
    return x.reshape(rhs.shape) if res <= tol else None


def neumann_series_reference(
    a: sp.csr_matrix, dt: float, rhs: np.ndarray, terms: int
) -> np.ndarray:
    """``sum_{k <= terms} (dt A)^k rhs`` by sparse products: the numpy statement of
    :func:`harness.compiled.fokker_planck.neumann_series` (same bits).
    """
    term, total = rhs, rhs.copy()
    a_dt = a * dt
    for _ in range(terms):
        term = a_dt @ term
        total += term
    return total


def implicit_solve(
    a: sp.csr_matrix, dt: float, rhs: np.ndarray, nx: int | None = None
) -> np.ndarray:
    """Solve ``(I - dt A) x = rhs`` for one right-hand side ``(M,)`` or several ``(M, c)``.

    With the grid's ``nx`` given: red-black Gauss-Seidel on all columns at once
    (:func:`red_black_solve`; 5, 9 and 14 sweeps at n = 30, 128 and 256 on the
    benchmarks' mid-run state, and at n = 30 two to three times faster than the series
    below, measured).
    Without it: the truncated Neumann series ``sum_k (dt A)^k rhs`` (compiled,
    :func:`harness.compiled.fokker_planck.neumann_series`) when ``rho = dt ||A||_1`` allows at most
    ``_MAX_SERIES_TERMS`` terms for a remainder below ``1e-15 ||rhs||_1`` (see
    :meth:`FokkerPlanck.step`), else the Jacobi-split series (:func:`jacobi_solve`)
    column by column. Sparse LU when the sweeps or terms would exceed
    ``_MAX_JACOBI_TERMS``. No checks: estimates propagated by the filters may be
    negative.
    """
    a = a.tocsr()
    diag = a.diagonal()
    if nx is not None:  # all columns in one set of sweeps
        x = red_black_solve(a, dt, rhs, nx, diag=diag)
        if x is not None:
            return x
    else:
        rho = dt * 2.0 * float(np.max(np.abs(diag), initial=0.0))
        terms = series_terms(rho)
        if terms <= _MAX_SERIES_TERMS:
            block = np.ascontiguousarray(rhs, dtype=float).reshape(rhs.shape[0], -1)
            total = neumann_series(a.indptr, a.indices, a.data, float(dt), block, terms)
            return total.reshape(rhs.shape)
        cols = [rhs] if rhs.ndim == 1 else [rhs[:, c] for c in range(rhs.shape[1])]
        solved: list[np.ndarray] = []
        for col in cols:
            x = jacobi_solve(a, dt, col)
            if x is None:
                break
            solved.append(x)
        else:
            return solved[0] if rhs.ndim == 1 else np.column_stack(solved)
    system = (sp.identity(a.shape[0], format="csr") - dt * a).tocsc()
    return spla.splu(system).solve(rhs)


def check_density(grid: Grid, before: np.ndarray, after: np.ndarray, tolerance: float) -> None:
    """Raise :class:`NumericalError` unless ``after`` is finite, non-negative (to
    round-off: ``min after >= -1e-12 max |before|``) and has the mass of ``before`` to
    relative ``tolerance`` (masses as grid integrals, the sums in one compiled pass,
    :func:`harness.compiled.fokker_planck.density_summary`).
    """
    finite, s0, s1, low, top = density_summary(before.reshape(-1), after.reshape(-1))
    if not finite:
        raise NumericalError("density became non-finite (NaN or inf)")
    m0, m1 = s0 * grid.cell_area, s1 * grid.cell_area
    scale = max(abs(m0), np.finfo(float).tiny)
    if abs(m1 - m0) > tolerance * scale:
        raise NumericalError(f"mass changed from {m0:.15g} to {m1:.15g} in one step")
    if low < -1e-12 * top:
        raise NumericalError(f"density became negative (min {low:.3g})")
