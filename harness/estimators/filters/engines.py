"""Filter engines: one interface for the fast and the reference filters.

An engine runs the paper's two filters (eqs. ``density filter``, ``density Riccati``,
``gradient filter``, ``gradient Riccati``) on the KDE and reports the traces of their
covariances and process noises. Engines register themselves by name when subclassed
(``class Mine(FilterEngine, name="mine")``), and ``filter.engine`` picks one by that
name (:meth:`FilterEngine.named`), so the estimator never branches on it.

* ``local``: :class:`harness.estimators.filters.local.LocalFilters` (fast, the default);
* ``reference``: the dense grid filters of :mod:`harness.estimators.filters.reference`;
* ``filterpy``: the same dense filters with filterpy's ``KalmanFilter`` doing the
  algebra.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import scipy.sparse as sp

from harness.domains.base import FreeSpace
from harness.estimators.filters.common import Integrator, MeasurementModel
from harness.estimators.filters.local import LocalFilters
from harness.estimators.filters.reference import (
    FilterpyDensityFilter,
    FilterpyGradientFilter,
    ReferenceDensityFilter,
    ReferenceGradientFilter,
)
from harness.grid import Grid
from harness.protocols import sparse_lu_bytes
from harness.velocity import VelocityField


class FilterEngine:
    """Base class and registry of filter engines.

    Args:
        grid: The grid.
        sigma: Noise intensity (length^2 / s).
        dt: Measurement period (s).
        measurement: KDE measurement model (``k``, ``k_g`` and the filter settings).
    """

    registry: ClassVar[dict[str, type[FilterEngine]]] = {}

    def __init_subclass__(cls, name: str = "", **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        if name:
            FilterEngine.registry[name] = cls

    @classmethod
    def named(cls, name: str) -> type[FilterEngine]:
        """The engine registered as ``name`` (KeyError when there is none)."""
        return cls.registry[name]

    def __init__(self, grid: Grid, sigma: float, dt: float, measurement: MeasurementModel):
        self.grid, self.sigma, self.dt, self.measurement = grid, sigma, dt, measurement

    @classmethod
    def memory_bytes(cls, grid: Grid) -> int:
        """Up-front estimate of the bytes the engine holds on ``grid`` (an upper
        estimate; an engine that does not say is assumed to hold 64 grid fields).
        """
        return 64 * 8 * 3 * grid.size

    def initialize(self, p_kde: np.ndarray, grad_kde: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Start both filters from the first KDE; returns ``(p_hat, q_hat)``."""
        raise NotImplementedError

    def step(
        self, p_kde: np.ndarray, grad_kde: np.ndarray, v: VelocityField, a: sp.csr_matrix | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Predict under the applied velocity ``v`` (``a = A(v)`` when known), update with
        the KDE; returns ``(p_hat, q_hat)``.
        """
        raise NotImplementedError

    @property
    def traces(self) -> tuple[float, float, float, float]:
        """``(trace P, trace Q, trace P_grad, trace Q_grad)`` (1 / length^2 for the density
        filter, 1 / length^4 for the gradient filter; see :class:`harness.records.Estimate`).
        """
        raise NotImplementedError


class LocalEngine(FilterEngine, name="local"):
    """The fast filters with local covariances (:mod:`harness.estimators.filters.local`),
    on the rectangle and on free space (``free``; the only engine that runs there).
    """

    free_space = True

    def __init__(
        self,
        grid: Grid,
        sigma: float,
        dt: float,
        measurement: MeasurementModel,
        free: FreeSpace | None = None,
    ):
        super().__init__(grid, sigma, dt, measurement)
        self.filters = LocalFilters(grid, sigma, dt, measurement, free)

    @classmethod
    def memory_bytes(cls, grid: Grid) -> int:
        """Local covariances and the gradient update's preconditioner: 64 grid fields,
        the band's correlations (18 fields), the lagged banded Cholesky factor and its
        rows (``2 M (2 min(n_x, n_y) + 1)`` float64, small grids) and two sparse LU
        factorisations (:func:`sparse_lu_bytes`, the fallback of the fine grids'
        iteration).
        """
        band = 2 * 8 * grid.size * (2 * min(grid.nx, grid.ny) + 1)
        correlations = 18 * 8 * (grid.size + 1)
        return 64 * 8 * 3 * grid.size + correlations + band + 2 * sparse_lu_bytes(grid.size)

    def initialize(self, p_kde: np.ndarray, grad_kde: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`LocalFilters.initialize`."""
        return self.filters.initialize(p_kde, grad_kde)

    def step(
        self, p_kde: np.ndarray, grad_kde: np.ndarray, v: VelocityField, a: sp.csr_matrix | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`LocalFilters.step`."""
        return self.filters.step(p_kde, grad_kde, v, a)

    @property
    def traces(self) -> tuple[float, float, float, float]:
        """Traces of the local covariance models."""
        (tp, tg), (qp, qg) = self.filters.trace_P, self.filters.trace_Q
        return tp, qp, tg, qg


class ReferenceEngine(FilterEngine, name="reference"):
    """The dense grid filters with numpy doing the algebra
    (:mod:`harness.estimators.filters.reference`); ``density_filter`` and ``gradient_filter`` are
    their classes.
    """

    density_filter: type[ReferenceDensityFilter] = ReferenceDensityFilter
    gradient_filter: type[ReferenceGradientFilter] = ReferenceGradientFilter
    dense_copies = 20
    """Dense ``M x M`` float64 arrays held at once: density filter ``P``, ``F``, ``Q`` and
    temporaries (3), gradient filter (``2M`` states: 4 each for ``P``, ``F`` and a
    temporary, 12), the integration operator's pseudo-inverse (``2M x M``, 2), and
    the dense solve of the transition (3)."""

    @classmethod
    def memory_bytes(cls, grid: Grid) -> int:
        """``dense_copies`` dense ``M x M`` float64 arrays (``O(M^2)``, ``M`` cells)."""
        return cls.dense_copies * 8 * grid.size**2 + 64 * 8 * 3 * grid.size

    def __init__(self, grid: Grid, sigma: float, dt: float, measurement: MeasurementModel):
        super().__init__(grid, sigma, dt, measurement)
        self.density = self.density_filter(grid, sigma, dt, measurement)
        self.gradient = self.gradient_filter(
            grid, sigma, dt, measurement, integrator=Integrator.build(grid)
        )

    def initialize(self, p_kde: np.ndarray, grad_kde: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Both dense filters from the first KDE."""
        return self.density.initialize(p_kde), self.gradient.initialize(grad_kde)

    def step(
        self, p_kde: np.ndarray, grad_kde: np.ndarray, v: VelocityField, a: sp.csr_matrix | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Both dense filters (they assemble their own dense transitions from ``v``)."""
        return self.density.step(p_kde, v), self.gradient.step(grad_kde, p_kde, v)

    @property
    def traces(self) -> tuple[float, float, float, float]:
        """Traces of the dense covariances."""
        d, g = self.density, self.gradient
        return d.trace_P, d.trace_Q, g.trace_P, g.trace_Q


class FilterpyEngine(ReferenceEngine, name="filterpy"):
    """The dense grid filters with filterpy's ``KalmanFilter`` doing the algebra."""

    density_filter = FilterpyDensityFilter
    gradient_filter = FilterpyGradientFilter
    dense_copies = 40  # filterpy keeps its own F, Q, H, B, K, S and prior/post copies
