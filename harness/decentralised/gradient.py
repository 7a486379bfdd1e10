"""The robots' gradient estimates: the option ``gradient``, resolved once.

:data:`GRADIENTS` maps the option's name to the class that carries it out, so the
per-robot filters (:class:`harness.decentralised.filters.RobotFilters`) choose their code
path by construction:

* ``"grid"`` (default, :class:`GridGradient`): ``q_hat_i = G p_hat_i``, the grid
  gradient of the robot's own density estimate; only the density kernel is tracked
  (``F = 1``);
* ``"filter"`` (:class:`FilteredGradient`): the fast gradient filter of
  :mod:`harness.filters.local` per robot on the tracked analytic kernel gradient (``F =
  3``): the auxiliary density ``x_g`` predicted by the transition, the gradient-grid
  information ``C`` by ``1/C^- = (F1 o F1)(1/C) + q dt k_g``, and the weighted-Poisson
  mean update solved by batched conjugate gradients, each robot preconditioned by the
  grid Laplacian's pseudo-inverse scaled by its own information
  (:class:`~harness.decentralised.poisson.BatchedPoisson`); a robot that does not reach
  the tolerance stops the run.

Shared with the centralised filter: the state predict ``x_g^- = F x_g`` is the truncated
Neumann series of :func:`harness.fokker_planck.implicit_solve` on all robots at once
(robots as columns, the same bits as one robot at a time), and one sparse LU over rows
(:class:`~harness.decentralised.row_solver.RowSolver`) where the series would take more
than ``_MAX_SERIES_TERMS`` terms. Not shared: the variance product (compiled per robot,
the diagonal of ``F1 o F1`` as ``1 + 2 dt a_rr`` plus ``(dt a_rr)^2``, where
:func:`harness.filters.local.squared_transition` adds ``(dt a_rr)^2 + 2 dt a_rr`` to the
identity: another rounding) and the innovation's right-hand side ``G^T (w o (y_g - G
x_g))`` (compiled per robot with the differences divided by ``2 dx``, where the
centralised filter multiplies by the sparse ``G``).
"""

from __future__ import annotations

from typing import Protocol

import numba
import numpy as np
import scipy.sparse as sp

from harness.decentralised.poisson import BatchedPoisson
from harness.decentralised.row_solver import RowSolver
from harness.filters.common import MeasurementModel
from harness.fokker_planck import _MAX_SERIES_TERMS, _series_terms, implicit_solve
from harness.grid import Grid


@numba.njit(cache=True, nogil=True)
def _sq_apply(indptr, indices, sq, boost, v, out):  # pragma: no cover
    """``out = sq @ v + boost v``: ``(F1 o F1) v`` of ``squared_transition``."""
    for r in range(v.size):
        s = boost[r] * v[r]
        for k in range(indptr[r], indptr[r + 1]):
            s += sq[k] * v[indices[k]]
        out[r] = s


@numba.njit(cache=True, parallel=True, nogil=True)
def _gradient_variance_predict(cg, indptr, indices, sq, boost, qkg):  # pragma: no cover
    """Per robot, in place, per gradient component: ``1/C^- = (F1 o F1)(1/C) + q dt
    k_g`` (``cg`` rows hold both components, ``(N, 2M)``).
    """
    n = cg.shape[0]
    m = cg.shape[1] // 2
    for i in numba.prange(n):
        tmp = np.empty(m)
        inv = np.empty(m)
        for comp in range(2):
            for c in range(m):
                inv[c] = 1.0 / cg[i, comp * m + c]
            _sq_apply(indptr, indices, sq, boost, inv, tmp)
            for c in range(m):
                cg[i, comp * m + c] = 1.0 / (tmp[c] + qkg)


@numba.njit(cache=True, nogil=True)
def _grad_row(f, nx, ny, dx, dy, out):  # pragma: no cover
    """``out = G f`` for one flattened field (``Grid.gradient``: central differences,
    reflecting ghosts), ``out`` of length ``2M``.
    """
    m = nx * ny
    for j in range(ny):
        jm = max(j - 1, 0)
        jp = min(j + 1, ny - 1)
        for i in range(nx):
            im = max(i - 1, 0)
            ip = min(i + 1, nx - 1)
            out[j * nx + i] = (f[j * nx + ip] - f[j * nx + im]) / (2.0 * dx)
            out[m + j * nx + i] = (f[jp * nx + i] - f[jm * nx + i]) / (2.0 * dy)


@numba.njit(cache=True, nogil=True)
def _grad_t_row(g, nx, ny, dx, dy, out):  # pragma: no cover
    """``out = G^T g`` for one stacked gradient ``g`` (length ``2M``)."""
    m = nx * ny
    for r in range(m):
        out[r] = 0.0
    for j in range(ny):
        jm = max(j - 1, 0)
        jp = min(j + 1, ny - 1)
        for i in range(nx):
            im = max(i - 1, 0)
            ip = min(i + 1, nx - 1)
            a = g[j * nx + i] / (2.0 * dx)
            out[j * nx + ip] += a
            out[j * nx + im] -= a
            b = g[m + j * nx + i] / (2.0 * dy)
            out[jp * nx + i] += b
            out[jm * nx + i] -= b


@numba.njit(cache=True, parallel=True, nogil=True)
def _gradient_rhs(xg, yg, w, nx, ny, dx, dy, out):  # pragma: no cover
    """``out_i = G^T (w_i o (y_g,i - G x_g,i))``: the weighted-Poisson right-hand side."""
    n, m = xg.shape
    for i in numba.prange(n):
        g = np.empty(2 * m)
        _grad_row(xg[i], nx, ny, dx, dy, g)
        for r in range(2 * m):
            g[r] = w[i, r] * (yg[i, r] - g[r])
        _grad_t_row(g, nx, ny, dx, dy, out[i])


class RobotGradient(Protocol):
    """One value of the option ``gradient``: how every robot estimates the gradient."""

    tracks_kernel_gradient: bool
    """Whether consensus also tracks the kernels' analytic gradients (``F = 3``)."""

    memory_fields: int
    """Per-robot fields of ``M`` cells the option adds to the estimator's state."""

    def __init__(
        self, grid: Grid, dt: float, measurement: MeasurementModel, poisson: BatchedPoisson
    ) -> None: ...

    def initialize(self, y_g: np.ndarray | None) -> None:
        """Start from the first tracked gradient observations ``(N, 2M)``, if tracked."""
        ...

    def step(self, y: np.ndarray, a: sp.csr_matrix, y_g: np.ndarray | None) -> None:
        """Predict under ``A`` and update with the observations (in place)."""
        ...

    def q_hat(self, x: np.ndarray) -> np.ndarray:
        """Every robot's gradient estimate ``(N, 2M)`` from the density estimates ``x``."""
        ...

    def estimate(self, x: np.ndarray) -> np.ndarray | None:
        """The gradient estimates handed on with ``x``, or None when the law evaluates
        ``G p_hat_i`` itself at the cells it needs
        (:func:`harness.robot_law.own_velocities`).
        """
        ...

    def arrays(self) -> tuple[np.ndarray, ...]:
        """The per-robot arrays the option holds."""
        ...


class GridGradient:
    """``q_hat_i = G p_hat_i``: no state of its own (``gradient="grid"``).

    Args:
        grid, dt, measurement: As :class:`~harness.decentralised.filters.RobotFilters`.
        poisson: The robots' Poisson solver (its ``G^T`` is used).
    """

    tracks_kernel_gradient = False
    memory_fields = 0

    def __init__(
        self, grid: Grid, dt: float, measurement: MeasurementModel, poisson: BatchedPoisson
    ) -> None:
        self.poisson = poisson

    def initialize(self, y_g: np.ndarray | None) -> None:
        """Nothing to start."""

    def step(self, y: np.ndarray, a: sp.csr_matrix, y_g: np.ndarray | None) -> None:
        """Nothing to propagate."""

    def q_hat(self, x: np.ndarray) -> np.ndarray:
        """``G p_hat_i`` for every robot ``(N, 2M)``."""
        return np.asarray(x @ self.poisson.gt)

    def estimate(self, x: np.ndarray) -> np.ndarray | None:
        """None: the law takes ``G p_hat_i`` at the four cells around each robot."""
        return None

    def arrays(self) -> tuple[np.ndarray, ...]:
        """None."""
        return ()


class FilteredGradient:
    """A fast gradient filter per robot (``gradient="filter"``, see the module
    docstring): auxiliary densities ``x_g`` ``(N, M)``, ``q_hat_i = G x_g,i``, and
    gradient-grid information ``c_g`` ``(N, 2M)``.

    Args:
        grid: The grid.
        dt: Step (s).
        measurement: The swarm's KDE measurement model (``k_g``, settings).
        poisson: The robots' Poisson solver.
    """

    tracks_kernel_gradient = True
    memory_fields = 4

    def __init__(
        self, grid: Grid, dt: float, measurement: MeasurementModel, poisson: BatchedPoisson
    ) -> None:
        self.grid, self.dt, self.measurement, self.poisson = grid, dt, measurement, poisson
        self.x_g: np.ndarray | None = None
        self.c_g: np.ndarray | None = None

    def initialize(self, y_g: np.ndarray | None) -> None:
        """``C0 = 1 / (initial_variance k_g)``; ``x_g0`` the unit-mass density whose grid
        gradient best fits ``y_g`` (as ``LocalFilters.initialize``).
        """
        assert y_g is not None
        s, g = self.measurement.settings, self.grid
        _, k_g = self.measurement.constants
        n = y_g.shape[0]
        self.c_g = np.full((n, 2 * g.size), 1.0 / (s.initial_variance * k_g))
        rhs = np.asarray(y_g) @ self.poisson.g  # rows: G^T y_g,i
        fit = self.poisson.solve(np.ones((n, 2 * g.size)), np.ascontiguousarray(rhs))
        self.x_g = fit + 1.0 / g.area

    def step(self, y: np.ndarray, a: sp.csr_matrix, y_g: np.ndarray | None) -> None:
        """Predict under ``A`` (CSR, sorted indices), update with the tracked density
        ``y`` (its variances) and gradient ``y_g`` ``(N, 2M)``.
        """
        assert self.x_g is not None and self.c_g is not None and y_g is not None
        s, dt, g = self.measurement.settings, self.dt, self.grid
        _, k_g = self.measurement.constants
        q = s.process_noise * dt
        terms = _series_terms(dt * 2.0 * float(np.max(np.abs(a.diagonal()), initial=0.0)))
        if terms > _MAX_SERIES_TERMS:  # one sparse LU for every robot
            solver = RowSolver(sp.identity(g.size, format="csr") - dt * a)
            self.x_g = solver.solve_rows(self.x_g)
        else:  # implicit_solve's truncated series (the same test), robots as columns
            self.x_g = np.ascontiguousarray(implicit_solve(a, dt, self.x_g.T).T)
        _gradient_variance_predict(
            self.c_g, a.indptr, a.indices, (dt * a.data) ** 2,
            1.0 + 2.0 * dt * a.diagonal(), q * k_g,
        )  # fmt: skip
        one = 1.0 / (s.r_scale * k_g * np.maximum(y, s.r_floor))
        w_g = np.concatenate([one, one], axis=1)
        self.c_g += w_g
        rhs = np.empty_like(self.x_g)
        yg = np.ascontiguousarray(y_g, dtype=float)
        _gradient_rhs(self.x_g, yg, w_g, g.nx, g.ny, g.dx, g.dy, rhs)
        self.x_g += self.poisson.solve(self.c_g, rhs)

    def q_hat(self, x: np.ndarray) -> np.ndarray:
        """``G x_g,i`` for every robot ``(N, 2M)``."""
        assert self.x_g is not None
        return np.asarray(self.x_g @ self.poisson.gt)

    def estimate(self, x: np.ndarray) -> np.ndarray | None:
        """:meth:`q_hat`."""
        return self.q_hat(x)

    def arrays(self) -> tuple[np.ndarray, ...]:
        """``x_g`` and ``c_g``."""
        return tuple(a for a in (self.x_g, self.c_g) if a is not None)


GRADIENTS: dict[str, type[RobotGradient]] = {"grid": GridGradient, "filter": FilteredGradient}
"""The option ``gradient``: name -> how the robots estimate the gradient."""
