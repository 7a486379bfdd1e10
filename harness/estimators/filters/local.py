"""Fast filters: exact state propagation, local covariance structure.

The paper's density filter (eqs. ``density filter``, ``density Riccati``) and gradient
filter (eqs. ``gradient filter``, ``gradient Riccati``) in the sampled-data form of
:mod:`harness.estimators.filters.common`, with the covariance kept in a structure that costs
``O(M)`` per step instead of ``O(M^3)``.

Why. The reference grid filters carry dense covariances at ``O(M^3)`` per step.
Their state is cheap to propagate (one sparse Fokker-Planck solve); only the
covariance is expensive. In this problem ``P0``, ``Q``, ``R`` and the measurement
matrix ``H = I`` are all diagonal on the grid, and the transition ``F = (I - dt
A)^{-1} = I + O(dt)`` couples a cell only to its neighbours and only weakly
(``dt |A_ij| ~ 1e-3`` at paper scale). The covariance therefore stays nearly
diagonal in the variables where the information arrives, and that is the
structure kept here.

Density filter (variance form: the local variances ``d`` of the state):

    predict:  x^- = F x^+                        (exact, as in the reference)
              d^- = diag(F1 S R S F1^T) + q dt k  (F1 = I + dt A, S = diag(sqrt(d^+)))
    update:   d^+ = 1 / (1 / d^- + 1 / r),        x^+ = x^- + (d^+ / r) (y - x^-),

``r`` the diagonal of ``R``; ``F1`` is ``F`` to first order. The prior behind the
prediction is ``P = S R S``: local variances ``d`` with the correlations ``R`` of the
state space. With every cosine mode kept (no band limit) ``R = I``, ``P`` is diagonal
and ``d^- = (F1 o F1) d^+`` (``o`` the entrywise product), exact for that ``P``: only
the off-diagonal covariance that transport creates in one step is dropped. With the
band limit (below) the state is a band-limited field, and so is its error: ``R`` is
the correlation of the band-limited white field ``Pi w``, ``R_ij = Pi_ij / sqrt(Pi_ii
Pi_jj)``, needed only between a cell's 5-point neighbours
(:meth:`harness.estimators.filters.common.BandLimit.correlations`; the prediction
:func:`transition_variance`). Why not ``R = I`` there: a white ``P`` holds grid-scale
modes that diffusion damps at the rate ``sigma |kappa|^2`` of the grid's highest
modes, so ``(F1 o F1)`` drains a cell's variance by about ``8 dt sigma / dx^2`` per
step, 0.26 at ``n = 256`` at the paper's settings, and the filter's gain fell with
the grid (mean density gain 0.047, 0.042, 0.030, 0.015 at ``n`` = 32, 64, 128, 256
after 3 s of the paper's loop, ``python -m benchmarks.filter_gain``): on fine grids the
filter trusted its model more and the KDE less for modes outside the state space.
(``8 dt sigma / dx^2`` is the mean of the variance decay ``2 dt sigma |kappa|^2`` over
all grid modes.) Over the band's disc the same mean is ``dt sigma kappa_c^2 = 0.002``
per step, on every grid (a test checks both rates). The update stays per cell, as if
``P^-`` were diagonal: the correlations enter the prediction only. With ``A = 0`` the
filter *is* the reference (a test checks it).

Gradient filter (information form). Its state is an auxiliary unit-mass density
``x_g`` with ``q_hat = G x_g`` (the integration operator ``I`` carried along: ``q``
stays in the range of the grid gradient ``G`` and ``q_{n+1} = G F I(q_n)`` becomes
``x_g^- = F x_g^+``). The reference's covariance, pulled back to ``x_g``, starts as
``P0 = c0^{-1} (G^T G)^+`` and every update adds ``G^T W_g G`` to its inverse
(``W_g = R_g^{-1}`` diagonal per gradient component). Both are of the form
``Y = G^T diag(C) G``: information that is diagonal on the *gradient* grid. So

    predict:  x_g^- = F x_g^+,   1/C^- = diag(F1 S R_c S F1^T) + q dt k_g   (per component c,
                                  S = diag(sqrt(1/C^+)), R_c that of G_c Pi w; R_c = I without band)
    update:   C^+ = C^- + w_g,
              x_g^+ = x_g^- + delta,   (G^T C^+ G) delta = G^T W_g (y_g - G x_g^-),  sum delta = 0,

the last being the exact posterior mean for that prior: a weighted least-squares fit of the
innovation by a gradient field, i.e. a variable-coefficient Poisson problem
(:mod:`harness.estimators.filters.poisson`). On grids up to ``lu_max_cells`` (1024) cells it
is solved by conjugate gradients preconditioned with a banded Cholesky factor of the same
operator from an earlier step (the coefficients change slowly), refactored when the
iteration count grows, in one compiled call
(:class:`~harness.estimators.filters.poisson.WeightedPoisson`), and the result is projected
on the band (below). On finer grids with a band limit it is solved within the band
(:class:`~harness.estimators.filters.poisson.BandPoisson`): the exact posterior mean of the
band-limited state, a dense system of the band's ``K`` modes (about 330 at the paper's
``h``) whose cost does not grow with the grid (an iteration on the grid takes 50 to 100
preconditioned iterations at ``n = 256``). With ``A = 0`` and ``q = 0`` the filter is the
reference.

Band limit (why the filters are stable at every grid size). The KDE measures the
cosine mode of wavenumber ``kappa`` with gain ``exp(-(kappa h)^2 / 2)`` and noise
spectrum ``exp(-(kappa h)^2)``: above ``kappa ~ 1/h`` it carries neither signal nor
noise. A grid filter with white ``P0``, ``Q`` and per-cell gains keeps those modes as
states and propagates them by its model alone, and its model is the closed loop
under the held feedback: an explicit diffusion of coefficient up to ``alpha max(p /
p_*)`` that amplifies the mode ``kappa`` by ``|1 - dt alpha r kappa^2|`` per step.
On fine grids (``n >~ 40`` at the paper's ``dt``) the grid's own modes grow faster
than a measurement update with gain ``~ 0.03`` can hold them, which made the paper's
loop diverge at ``n = 128`` while the raw-KDE loop stayed stable. So both filters
estimate the band the KDE resolves: after every update (and at the start) the
states are projected onto the Neumann cosine modes with ``|kappa| <= band_limit /
h`` (:class:`harness.estimators.filters.common.BandLimit`, a DCT; mass kept), i.e. the model
is ``x_{n+1} = Pi F_n x_n`` with measurement ``Pi y``. The band does not depend on
the grid, so estimates and errors converge as the grid is refined; on the paper's
30 x 30 grid it removes the modes with ``|kappa| h > 2.5`` only. The reference
filters carry the same projected model (``F' = Pi F``, ``Q' = q Pi``, ``R' = Pi R Pi
+ (I - Pi)``).

Free space (a domain with obstacles, ``free`` given). The transition is the
Fokker-Planck operator on free space (no flux through closed faces: every component
keeps its mass in the prediction); the band is :class:`~harness.estimators.filters.common.FreeBand`
(the masked Laplacian's modes below the cut, each component's constant among them, 0 on
blocked cells), its correlations computed from those modes; the gradient is the
free-space gradient and the gradient update's Poisson problem is solved by
:class:`~harness.estimators.filters.free_poisson.FreePoisson` (conjugate gradients with a
lagged banded Cholesky factor, the components' constants pinned) on every grid, then
projected on the band (both states in one product with the band's modes). The
auxiliary density ``x_g`` starts with the KDE's mass on each component (the gradient
does not see it). The rectangle's fast paths (cosine transforms,
:class:`~harness.estimators.filters.poisson.BandPoisson`) are not used there.

Process noise ``Q = q dt k I`` (density) and ``q dt k_g I`` (gradient), as in the
reference. The approximation error is measured, not assumed:
``benchmarks.filter_accuracy.compare_filters`` runs both forms in one closed loop.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from harness.compiled.filters import band_transition_variance
from harness.compiled.filters import squared_transition as compiled_squared_transition
from harness.domains.base import FreeSpace
from harness.estimators.filters.common import (
    BandLimit,
    FilterSettings,
    FreeBand,
    MeasurementModel,
)
from harness.estimators.filters.free_poisson import FreePoisson
from harness.estimators.filters.poisson import BandPoisson, WeightedPoisson
from harness.fokker_planck import FokkerPlanck, implicit_solve
from harness.grid import Grid
from harness.velocity import VelocityField


def squared_transition(a: sp.csr_matrix, dt: float, d: np.ndarray) -> np.ndarray:
    """``(F1 o F1) d`` with ``F1 = I + dt A``: the diagonal of ``F1 diag(d) F1^T``.

    ``d`` may hold several columns. Compiled, one pass over ``A``
    (:func:`harness.compiled.filters.squared_transition`); :func:`squared_transition_reference`
    is the numpy statement.
    """
    a = a.tocsr()
    if not a.has_canonical_format:  # duplicates summed first, as the diagonal() is
        a = a.copy()
        a.sum_duplicates()
    cols = np.ascontiguousarray(d, dtype=float).reshape(d.shape[0], -1)
    out = compiled_squared_transition(a.indptr, a.indices, a.data, float(dt), cols)
    return out.reshape(d.shape)


def squared_transition_reference(a: sp.csr_matrix, dt: float, d: np.ndarray) -> np.ndarray:
    """Numpy statement of :func:`squared_transition`."""
    sq = a.copy()
    sq.data = (dt * sq.data) ** 2
    diag = a.diagonal()
    # (1 + dt a_ii)^2 on the diagonal instead of (dt a_ii)^2
    boost = 1.0 + 2.0 * dt * diag
    return sq @ d + (boost[:, None] * d if d.ndim == 2 else boost * d)


def transition_variance(
    a: sp.csr_matrix, dt: float, d: np.ndarray, rho: np.ndarray | None, nx: int
) -> np.ndarray:
    """The prediction of the filters' variances, the covariance-propagation half of eqs.
    ``density Riccati`` and ``gradient Riccati`` in the sampled-data form of
    :mod:`harness.estimators.filters.common` (``P^- = F P^+ F^T + Q``) for the local model ``P =
    S R S``: ``diag(F1 S R S F1^T)`` for each column
    of ``d`` (``S = diag(sqrt(d))``, ``F1 = I + dt A``, ``A`` 5-point on a grid of
    ``nx`` columns), ``R`` the band's correlations ``rho`` (``(1 or c, 6, M + 1)``, as
    :meth:`harness.estimators.filters.common.BandLimit.correlations` gives them; compiled,
    :func:`harness.compiled.filters.band_transition_variance`), or ``R = I`` when ``rho`` is
    None (every mode kept): then it is :func:`squared_transition`. Derivation in the
    module docstring; :func:`transition_variance_reference` is the dense statement.
    """
    if rho is None:
        return squared_transition(a, dt, d)
    a = a.tocsr()
    if not a.has_canonical_format:
        a = a.copy()
        a.sum_duplicates()
    cols = np.ascontiguousarray(d, dtype=float).reshape(d.shape[0], -1)
    out = band_transition_variance(a.indptr, a.indices, a.data, float(dt), cols, rho, int(nx))
    return out.reshape(d.shape)


def transition_variance_reference(
    a: sp.csr_matrix, dt: float, d: np.ndarray, correlations: list[np.ndarray]
) -> np.ndarray:
    """Dense statement of :func:`transition_variance`: column ``k`` of ``d`` ``(M, c)``
    gives ``diag(F1 S R_k S F1^T)`` with the dense correlation matrices ``R_k``
    (``correlations[k]``, or ``correlations[0]`` for every column).
    """
    f1 = np.eye(a.shape[0]) + dt * a.toarray()
    cols = d.reshape(d.shape[0], -1)
    out = np.empty_like(cols)
    for k in range(cols.shape[1]):
        r = correlations[k if len(correlations) > 1 else 0]
        s = np.sqrt(cols[:, k])
        out[:, k] = np.einsum("ij,jl,il->i", f1 * s, r, f1 * s)
    return out.reshape(d.shape)


class LocalFilters:
    """Density and gradient filters with local covariances (see the module docstring).

    Args:
        grid: The grid.
        sigma: Noise intensity (length^2 / s).
        dt: Measurement period (s).
        measurement: KDE measurement model (``k``, ``k_g``, settings).
        free: Free space of a domain with obstacles (module docstring); None for the
            rectangle.
    """

    def __init__(
        self,
        grid: Grid,
        sigma: float,
        dt: float,
        measurement: MeasurementModel,
        free: FreeSpace | None = None,
    ) -> None:
        self.grid, self.dt, self.measurement = grid, dt, measurement
        self.free = free
        self.settings: FilterSettings = measurement.settings
        self.operator = FokkerPlanck(grid, sigma, free=free)
        cutoff = self.settings.band_limit / measurement.bandwidth
        self.band: BandLimit | FreeBand
        self.poisson: WeightedPoisson | FreePoisson
        self.band_poisson: BandPoisson | None = None
        if free is None:
            self.poisson = WeightedPoisson(grid)
            self.band = BandLimit(grid, cutoff)
            # above the LU preconditioner's grids, the gradient update is solved in the band
            fine = grid.size > self.poisson.lu_max_cells and not self.band.is_identity
            self.band_poisson = BandPoisson(grid, self.band) if fine else None
            self.area = grid.area
        else:
            self.poisson = FreePoisson(free)
            self.band = FreeBand(free, cutoff)
            self.area = free.free_area
        # the band's correlations between neighbouring cells, for the variance prediction
        self.correlations = None if self.band.is_identity else self.band.correlations()
        self.x: np.ndarray | None = None  # p_hat, flattened
        self.d: np.ndarray | None = None  # density variances
        self.x_g: np.ndarray | None = None  # auxiliary density, q_hat = G x_g
        self.c_g: np.ndarray | None = None  # gradient-grid information (2M)
        # priors (after predict) of the states and of the covariance diagonals
        self.x_prior: np.ndarray | None = None
        self.x_g_prior: np.ndarray | None = None
        self.d_prior: np.ndarray | None = None
        self.c_g_prior: np.ndarray | None = None

    def initialize(self, p_kde: np.ndarray, grad_kde: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``x0 = p_KDE``, ``P0 = initial_variance k I``; ``x_g0`` the unit-mass density
        whose grid gradient best fits ``grad p_KDE``, ``C0 = 1 / (initial_variance k_g)``.
        """
        s, g = self.settings, self.grid
        k, k_g = self.measurement.constants
        self.x = self.band(np.array(p_kde, dtype=float).ravel())
        self.d = np.full(g.size, s.initial_variance * k)
        self.c_g = np.full(2 * g.size, 1.0 / (s.initial_variance * k_g))
        fit = self._gradient_solve(
            np.ones(2 * g.size), self.poisson.gt @ np.asarray(grad_kde).ravel()
        )
        self.x_g = self.band(fit) + self._constants(p_kde)
        self.x_prior, self.x_g_prior = self.x.copy(), self.x_g.copy()
        self.d_prior, self.c_g_prior = self.d.copy(), self.c_g.copy()
        return self.estimates

    def step(
        self,
        p_kde: np.ndarray,
        grad_kde: np.ndarray,
        v_applied: VelocityField,
        a: sp.csr_matrix | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Predict both filters under ``v_applied``, then update with the KDE.

        ``a`` may pass ``A(v_applied)`` when the caller has it already.
        """
        assert self.x is not None and self.d is not None, "call initialize first"
        assert self.x_g is not None and self.c_g is not None
        g, s, dt = self.grid, self.settings, self.dt
        k, k_g = self.measurement.constants
        a = self.operator.matrix(v_applied) if a is None else a
        # predict: states by the grid transition, variances by F1 S R S F1^T
        states = implicit_solve(a, dt, np.column_stack([self.x, self.x_g]), g.nx)
        x, x_g = states[:, 0], states[:, 1]
        q = s.process_noise * dt
        # one product for the density variances and both gradient components
        var = transition_variance(
            a,
            dt,
            np.column_stack([self.d, (1.0 / self.c_g).reshape(2, g.size).T]),
            self.correlations,
            g.nx,
        )
        d = var[:, 0] + q * k
        c_g = 1.0 / (var[:, 1:].T.ravel() + q * k_g)
        self.x_prior, self.x_g_prior = x, x_g
        self.d_prior, self.c_g_prior = d, c_g
        # density update, per cell (exact for a diagonal prior; the prediction's
        # correlations are not carried into it)
        r = self.measurement.density_variance(p_kde)
        self.d = 1.0 / (1.0 / d + 1.0 / r)
        x_post = x + self.d / r * (np.asarray(p_kde).ravel() - x)
        if self.free is None:
            self.x = self.band(x_post)
        # gradient update: information adds, mean by the weighted Poisson solve
        w_g = 1.0 / self.measurement.gradient_variance(p_kde)
        self.c_g = c_g + w_g
        innovation = np.asarray(grad_kde).ravel() - self.poisson.g @ x_g
        x_g_post = x_g + self._gradient_solve(self.c_g, self.poisson.gt @ (w_g * innovation))
        if self.free is None:
            self.x_g = self.band(x_g_post)
        else:  # both states through the free band's modes in one product
            both = self.band(np.column_stack([x_post, x_g_post]))
            self.x, self.x_g = both[:, 0].copy(), both[:, 1].copy()
        return self.estimates

    def _constants(self, p_kde: np.ndarray) -> np.ndarray | float:
        """The part of ``x_g`` its gradient does not see: ``1 / |Omega|`` on the
        rectangle; on free space, on each component the KDE's mass there over its area.
        """
        if self.free is None:
            return 1.0 / self.grid.area
        labels = self.free.labels.ravel()
        on = labels >= 0
        n = self.free.n_components
        p = np.asarray(p_kde, dtype=float).ravel()
        mass = np.bincount(labels[on], p[on], n)
        count = np.bincount(labels[on], minlength=n)
        out = np.zeros(self.grid.size)
        out[on] = (mass / count)[labels[on]]
        return out

    def _gradient_solve(self, c: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The gradient update's weighted Poisson solve: in the band on grids above the
        LU preconditioner's size (:class:`~harness.estimators.filters.poisson.BandPoisson`),
        on the grid below (:class:`~harness.estimators.filters.poisson.WeightedPoisson`,
        then projected by the caller).
        """
        if self.band_poisson is not None:
            return self.band_poisson.solve(c, b)
        return self.poisson.solve(c, b)

    @property
    def estimates(self) -> tuple[np.ndarray, np.ndarray]:
        """``(p_hat, q_hat)`` on the grid, ``q_hat = G x_g``."""
        assert self.x is not None and self.x_g is not None
        g = self.grid
        return self.x.reshape(g.shape), (self.poisson.g @ self.x_g).reshape(2, *g.shape)

    @property
    def trace_P(self) -> tuple[float, float]:
        """L2 traces of the diagonal covariance models, ``sum(d) a`` and ``sum(1/C) a``
        (``a`` the cell area; the gradient's is its local variance per gradient cell).
        """
        assert self.d is not None and self.c_g is not None
        a = self.grid.cell_area
        if self.free is not None:  # the states on free cells only
            on = self.free.cells.ravel()
            both = np.concatenate([on, on])
            return float(self.d[on].sum()) * a, float((1.0 / self.c_g[both]).sum()) * a
        return float(self.d.sum()) * a, float((1.0 / self.c_g).sum()) * a

    @property
    def trace_Q(self) -> tuple[float, float]:
        """L2 traces of ``Q`` per step, ``q dt k M a`` and ``q dt k_g 2M a`` (``M`` the
        free cells on free space).
        """
        k, k_g = self.measurement.constants
        q = self.settings.process_noise * self.dt * self.area
        return q * k, 2 * q * k_g
