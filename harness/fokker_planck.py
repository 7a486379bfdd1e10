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
checks they agree.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from harness.grid import Grid
from harness.velocity import VelocityField


class NumericalError(RuntimeError):
    """Raised when a step produces non-finite values, negative density or lost mass."""


def bernoulli(z: np.ndarray) -> np.ndarray:
    """Bernoulli function ``B(z) = z / (exp(z) - 1)`` with ``B(0) = 1``, stable for
    all real ``z`` (``B(z) -> -z`` as ``z -> -inf``, ``-> 0`` as ``z -> +inf``).
    """
    z = np.asarray(z, dtype=float)
    small = np.abs(z) < 1e-6
    safe = np.where(small, 1.0, z)
    with np.errstate(over="ignore"):
        out = safe / np.expm1(safe)
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
        a_r = np.where(np.abs(pe) < 1e-6, scale * (1.0 - 0.5 * pe), u / np.expm1(pe))
    # B(-z) = B(z) + z, so a_L = a_R + u
    return a_r + u, a_r


def rate(grid: Grid, p: np.ndarray, v: VelocityField, sigma: float) -> np.ndarray:
    """Reference right-hand side ``dp/dt = -div(v p) + sigma Laplacian(p)`` (eq.
    ``FP equation``) as face fluxes, plain numpy, for testing the fast path.

    Args:
        grid: The grid.
        p: Density, shape ``(ny, nx)`` (1 / length^2).
        v: Velocity field; only the face values are used.
        sigma: Noise intensity ``sigma >= 0`` (length^2 / time).

    Returns:
        ``dp/dt``, shape ``(ny, nx)``, in 1 / (length^2 time).
    """
    out = np.zeros_like(p, dtype=float)
    a_l, a_r = face_coefficients(v.face_x, sigma, grid.dx)
    flux_x = a_l * p[:, :-1] - a_r * p[:, 1:]
    out[:, :-1] -= flux_x / grid.dx
    out[:, 1:] += flux_x / grid.dx
    a_l, a_r = face_coefficients(v.face_y, sigma, grid.dy)
    flux_y = a_l * p[:-1, :] - a_r * p[1:, :]
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
    """

    grid: Grid
    sigma: float
    mass_tolerance: float = 1e-9
    _pattern: _Pattern = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not np.isfinite(self.sigma) or self.sigma < 0:
            raise ValueError(f"sigma must be finite and >= 0, got {self.sigma}")
        self._pattern = _build_pattern(self.grid)

    def matrix(self, v: VelocityField) -> sp.csr_matrix:
        """Sparse ``A(v)`` with ``dp/dt = A(v) p`` on flattened fields (eq. ``FP
        equation``); columns sum to zero, off-diagonals are ``>= 0``.
        """
        g = self.grid
        ax_l, ax_r = face_coefficients(v.face_x.ravel(), self.sigma, g.dx)
        ay_l, ay_r = face_coefficients(v.face_y.ravel(), self.sigma, g.dy)
        a_l = np.concatenate([ax_l / g.dx, ay_l / g.dy])
        a_r = np.concatenate([ax_r / g.dx, ay_r / g.dy])
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

        Solver. Let ``rho = dt ||A||_1`` (``||A||_1`` = largest absolute column
        sum = twice the largest outflow rate). When ``rho < 1`` the solution is
        the Neumann series ``p_next = sum_k (dt A)^k p``; after ``K`` terms the
        remainder is at most ``rho^(K+1) / (1 - rho) ||p||_1``, so ``K`` is chosen
        to make it below ``1e-15 ||p||_1``. Each term ``(dt A)^k p`` with ``k >= 1``
        has zero mass (columns of ``A`` sum to zero), so the truncated series
        conserves mass to round-off as well. At paper scale ``rho ~ 2e-3`` and
        ``K = 5`` sparse products replace a sparse LU factorisation (about 20 times
        faster). When more than ``_MAX_SERIES_TERMS`` terms would be needed (``rho``
        above about 0.05) the step uses a sparse LU solve instead.

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
        p_next = implicit_solve(a, dt, p.ravel().astype(float)).reshape(self.grid.shape)
        check_density(self.grid, p, p_next, self.mass_tolerance)
        return p_next

    def step_lu(self, p: np.ndarray, v: VelocityField, dt: float) -> np.ndarray:
        """Reference backward-Euler step by sparse LU, without checks."""
        system = (sp.identity(self.grid.size, format="csr") - dt * self.matrix(v)).tocsc()
        return spla.splu(system).solve(p.ravel().astype(float)).reshape(self.grid.shape)


_MAX_SERIES_TERMS = 12
"""Above this many Neumann-series terms a sparse LU solve is cheaper (measured
with `make bench` at n = 30 to 128)."""


def _series_terms(rho: float) -> int:
    """Terms ``K`` with ``rho^(K+1) / (1 - rho) <= 1e-15`` (``K = 0`` when ``rho = 0``;
    a large number when ``rho >= 1``).
    """
    if rho == 0.0:
        return 0
    if rho >= 1.0:
        return 10**9
    return max(int(np.ceil(np.log(1e-15 * (1.0 - rho)) / np.log(rho))) - 1, 1)


def implicit_solve(a: sp.csr_matrix, dt: float, rhs: np.ndarray) -> np.ndarray:
    """Solve ``(I - dt A) x = rhs`` for one right-hand side ``(M,)`` or several ``(M, c)``.

    Truncated Neumann series ``sum_k (dt A)^k rhs`` when ``rho = dt ||A||_1`` allows
    at most ``_MAX_SERIES_TERMS`` terms for a remainder below ``1e-15 ||rhs||_1``
    (see :meth:`FokkerPlanck.step`), sparse LU otherwise. No checks: estimates
    propagated by the filters may be negative.
    """
    rho = dt * 2.0 * float(np.max(np.abs(a.diagonal()), initial=0.0))
    terms = _series_terms(rho)
    if terms <= _MAX_SERIES_TERMS:
        term, total = rhs, rhs.copy()
        a_dt = a * dt
        for _ in range(terms):
            term = a_dt @ term
            total += term
        return total
    system = (sp.identity(a.shape[0], format="csr") - dt * a).tocsc()
    return spla.splu(system).solve(rhs)


def check_density(grid: Grid, before: np.ndarray, after: np.ndarray, tolerance: float) -> None:
    """Raise :class:`NumericalError` unless ``after`` is finite, non-negative (to
    round-off) and has the mass of ``before`` to relative ``tolerance``.
    """
    if not np.isfinite(after).all():
        raise NumericalError("density became non-finite (NaN or inf)")
    m0, m1 = grid.integrate(before), grid.integrate(after)
    scale = max(abs(m0), np.finfo(float).tiny)
    if abs(m1 - m0) > tolerance * scale:
        raise NumericalError(f"mass changed from {m0:.15g} to {m1:.15g} in one step")
    floor = -1e-12 * float(np.max(np.abs(before)))
    if after.min() < floor:
        raise NumericalError(f"density became negative (min {after.min():.3g})")
