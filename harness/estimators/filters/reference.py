"""Reference grid filters: the paper's density and gradient filters, dense.

Every grid cell is a state (``M = nx ny`` states for the density, ``2M`` for the
gradient) and the covariance is a dense matrix, so a step costs ``O(M^3)``. They
implement the sampled-data form derived in :mod:`harness.estimators.filters.common`
faithfully, are cross-checked against filterpy's ``KalmanFilter`` in the tests,
and are the yardstick for the fast filters (:mod:`.local`). Use them on small grids.

Symbols (filterpy's): ``x`` state, ``P`` covariance, ``F`` transition, ``Q``
process noise, ``H = I`` measurement matrix, ``R`` measurement covariance,
``K`` gain, ``S`` innovation covariance; ``x_prior, P_prior`` after predict and
``x_post, P_post`` after update.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg as sla

from harness.estimators.filters.common import (
    BandLimit,
    FilterSettings,
    Integrator,
    MeasurementModel,
    transition_dense,
)
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.velocity import VelocityField

if TYPE_CHECKING:
    from filterpy.kalman import KalmanFilter


@dataclass
class DenseKalman:
    """Discrete Kalman filter with ``H = I`` and diagonal ``R`` (dense ``P``), the
    equations below computed directly with numpy. :class:`FilterpyKalman` hands the
    same ``F, Q, R`` to filterpy's ``KalmanFilter`` instead.
    """

    x: np.ndarray
    P: np.ndarray
    x_prior: np.ndarray = field(init=False)
    P_prior: np.ndarray = field(init=False)
    x_post: np.ndarray = field(init=False)
    P_post: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.x = np.asarray(self.x, dtype=float).copy()
        self.P = np.asarray(self.P, dtype=float).copy()
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()
        self.x_post, self.P_post = self.x.copy(), self.P.copy()

    def predict(self, F: np.ndarray, q: float | np.ndarray, u: np.ndarray | None = None) -> None:
        """``x^- = F x^+ + u``, ``P^- = F P^+ F^T + Q`` with ``Q = q I`` (``q`` a number)
        or ``Q = q`` (a matrix).
        """
        self.x = F @ self.x
        if u is not None:
            self.x = self.x + u
        self.P = F @ self.P @ F.T
        if np.ndim(q) == 0:
            self.P[np.diag_indices_from(self.P)] += q
        else:
            self.P = self.P + q
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()

    def update(self, y: np.ndarray, r: np.ndarray) -> None:
        """Measurement update with ``H = I`` and ``R = diag(r)`` (``r`` a vector) or
        ``R = r`` (a matrix):

            S = P^- + R,  K = P^- S^{-1},  x^+ = x^- + K (y - x^-),
            P^+ = (I - K) P^- (I - K)^T + K R K^T = P^- - P^- S^{-1} P^-.

        filterpy evaluates the Joseph form (first line, :class:`FilterpyKalman`); this
        class the equal symmetric form with ``S = L L^T``, ``V = L^{-1} P^-``: ``P^+ =
        P^- - V^T V`` and ``K (y - x^-) = V^T L^{-1} (y - x^-)`` (a third of the flops).
        """
        y = np.asarray(y, dtype=float).ravel()
        if np.ndim(r) == 1:
            s = self.P.copy()
            s[np.diag_indices_from(s)] += r
        else:
            s = self.P + r
        low = sla.cholesky(s, lower=True, check_finite=False)
        v = sla.solve_triangular(low, self.P, lower=True, check_finite=False)
        innovation = sla.solve_triangular(low, y - self.x, lower=True, check_finite=False)
        self.x = self.x + v.T @ innovation
        self.P = self.P - v.T @ v
        self.x_post, self.P_post = self.x.copy(), self.P.copy()


@dataclass
class FilterpyKalman(DenseKalman):
    """:class:`DenseKalman` with filterpy's ``KalmanFilter`` doing the algebra (slower;
    the reference in tests and the baseline in benchmarks). ``_kf`` is filterpy's filter.
    """

    _kf: KalmanFilter = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # filterpy loads scipy.stats (about a second): only this engine pays for it
        from filterpy.kalman import KalmanFilter

        super().__post_init__()
        m = self.x.size
        kf = KalmanFilter(dim_x=m, dim_z=m)
        kf.x = self.x.reshape(m, 1).copy()
        kf.P = self.P.copy()
        kf.H = np.eye(m)
        self._kf = kf

    def predict(self, F: np.ndarray, q: float | np.ndarray, u: np.ndarray | None = None) -> None:
        """:meth:`DenseKalman.predict` by ``KalmanFilter.predict`` (``B = I`` for ``u``)."""
        m = self.x.size
        self._kf.F = F
        self._kf.Q = q * np.eye(m) if np.ndim(q) == 0 else np.asarray(q)
        if u is None:
            self._kf.predict()
        else:
            self._kf.B = np.eye(m)
            self._kf.predict(u=u.reshape(m, 1))
        self.x, self.P = self._kf.x.ravel().copy(), self._kf.P.copy()
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()

    def update(self, y: np.ndarray, r: np.ndarray) -> None:
        """:meth:`DenseKalman.update` by ``KalmanFilter.update`` (the Joseph form)."""
        y = np.asarray(y, dtype=float).ravel()
        self._kf.update(y.reshape(-1, 1), R=np.diag(r) if np.ndim(r) == 1 else r)
        self.x, self.P = self._kf.x.ravel().copy(), self._kf.P.copy()
        self.x_post, self.P_post = self.x.copy(), self.P.copy()


class _DenseGridFilter:
    """What the two reference filters share: set-up, the start from a first KDE, and
    the L2 traces of ``P`` and ``Q``. ``_kind`` selects ``k`` (0) or ``k_g`` (1),
    ``_states`` is the number of states per cell (1 or 2) and ``kalman`` the class
    doing the Kalman algebra.
    """

    _kind = 0
    _states = 1
    kalman: type[DenseKalman] = DenseKalman

    def __init__(
        self,
        grid: Grid,
        sigma: float,
        dt: float,
        measurement: MeasurementModel,
    ) -> None:
        self.grid, self.dt, self.measurement = grid, dt, measurement
        self.settings: FilterSettings = measurement.settings
        self.operator = FokkerPlanck(grid, sigma)
        self.kf: DenseKalman | None = None
        band = BandLimit(grid, self.settings.band_limit / measurement.bandwidth)
        self.projector: np.ndarray | None = None if band.is_identity else band.matrix()

    def _project_model(
        self, f: np.ndarray, y: np.ndarray, r: np.ndarray, u: np.ndarray | None = None
    ) -> tuple[np.ndarray, float | np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """The band-limited model of :class:`~harness.estimators.filters.common.BandLimit` with
        projector ``Pi`` (``Pi_g = G Pi G^+`` for the gradient): ``F' = Pi F``, ``u' =
        Pi u``, ``Q' = Pi Q Pi = q Pi``, ``y' = Pi y`` and ``R' = Pi R Pi + (I - Pi)``
        (any positive block outside the band: the prior has no variance there, so the
        gain vanishes on it). Unchanged when every grid mode is kept.
        """
        if self.projector is None:
            return f, self.q, y, r, u
        pi = self.projector
        r_full = pi @ (r[:, None] * pi) + (np.eye(pi.shape[0]) - pi)
        return (
            pi @ f,
            self.q * pi,
            pi @ np.asarray(y).ravel(),
            r_full,
            None if u is None else pi @ u,
        )

    @property
    def q(self) -> float:
        """Per-step process-noise variance ``q dt k`` (density, 1 / length^4) or
        ``q dt k_g`` (gradient, 1 / length^6).
        """
        return self.settings.process_noise * self.dt * self.measurement.constants[self._kind]

    def _start(self, y0: np.ndarray) -> None:
        """``x0 = Pi y0``, ``P0 = initial_variance k Pi`` (or ``k_g``; ``Pi = I`` when
        every grid mode is kept).
        """
        m = self._states * self.grid.size
        var = self.settings.initial_variance * self.measurement.constants[self._kind]
        x0 = np.asarray(y0, dtype=float).ravel()
        p0 = var * np.eye(m)
        if self.projector is not None:
            x0, p0 = self.projector @ x0, var * self.projector
        self.kf = self.kalman(x0, p0)

    @property
    def trace_P(self) -> float:
        """``trace(P)`` after the last update, times the cell area (the L2 trace)."""
        assert self.kf is not None
        return float(np.trace(self.kf.P)) * self.grid.cell_area

    @property
    def trace_Q(self) -> float:
        """``trace(Q)`` per step, times the cell area."""
        return self.q * self._states * self.grid.size * self.grid.cell_area


class ReferenceDensityFilter(_DenseGridFilter):
    """The density filter (eqs. ``density filter``, ``density Riccati``) on the grid.

    State ``p`` (``M`` cells), ``F_n = (I - dt A(v_n))^{-1}``, ``Q = q dt k I``,
    ``y = p_KDE``, ``R = r_scale k diag(max(p_KDE, r_floor))``; see
    :mod:`harness.estimators.filters.common` for the derivation.
    """

    def initialize(self, p_kde: np.ndarray) -> np.ndarray:
        """Start at ``x0 = p_KDE(0)``, ``P0 = initial_variance k I``."""
        self._start(p_kde)
        return self.estimate

    def step(self, p_kde: np.ndarray, v_applied: VelocityField) -> np.ndarray:
        """Predict over the last interval under ``v_applied``, then update with ``p_kde``."""
        assert self.kf is not None, "call initialize first"
        f = transition_dense(self.operator.matrix(v_applied), self.dt)
        f, q, y, r, _ = self._project_model(f, p_kde, self.measurement.density_variance(p_kde))
        self.kf.predict(f, q)
        self.kf.update(y, r)
        return self.estimate

    @property
    def estimate(self) -> np.ndarray:
        """``p_hat``, shape ``(ny, nx)``."""
        assert self.kf is not None
        return self.kf.x.reshape(self.grid.shape)


class ReferenceGradientFilter(_DenseGridFilter):
    """The gradient filter (eqs. ``gradient filter``, ``gradient Riccati``) on the grid.

    State ``q`` (``2M``: x then y components), ``F_g = G F_n G^+``, known input
    ``u_n = G F_n 1/|Omega|`` (mass constraint,
    :class:`~harness.estimators.filters.common.Integrator`),
    ``Q = q dt k_g I``, ``y_g = grad p_KDE``, ``R_g = r_scale k_g diag(max(p_KDE, r_floor))``.
    """

    def __init__(
        self,
        grid: Grid,
        sigma: float,
        dt: float,
        measurement: MeasurementModel,
        integrator: Integrator | None = None,
    ) -> None:
        super().__init__(grid, sigma, dt, measurement)
        self.integrator = integrator or Integrator.build(grid)
        self.G = grid.gradient_matrix.tocsr()
        if self.projector is not None:
            # Pi_g = G Pi G^+: Pi commutes with G^T G (both diagonal in the DCT basis),
            # so Pi_g is the orthogonal projector onto gradients of band-limited fields
            self.projector = self.G @ (self.projector @ self.integrator.pinv)

    _kind = 1
    _states = 2

    def initialize(self, grad_kde: np.ndarray) -> np.ndarray:
        """Start at ``x0 = grad p_KDE(0)``, ``P0 = initial_variance k_g I``."""
        self._start(grad_kde)
        return self.estimate

    def transition(self, v_applied: VelocityField) -> tuple[np.ndarray, np.ndarray]:
        """``(F_g, u)`` for the interval under ``v_applied``."""
        f = transition_dense(self.operator.matrix(v_applied), self.dt)
        gf = self.G @ f
        return gf @ self.integrator.pinv, np.asarray(gf.sum(axis=1)).ravel() / self.grid.area

    def step(self, grad_kde: np.ndarray, p_kde: np.ndarray, v_applied: VelocityField) -> np.ndarray:
        """Predict under ``v_applied``, then update with ``grad p_KDE`` (its variance
        from ``p_KDE``).
        """
        assert self.kf is not None, "call initialize first"
        y, r = self._predict(grad_kde, self.measurement.gradient_variance(p_kde), v_applied)
        self.kf.update(y, r)
        return self.estimate

    def _predict(
        self, grad_kde: np.ndarray, r: np.ndarray, v_applied: VelocityField
    ) -> tuple[np.ndarray, np.ndarray]:
        """The prediction under ``v_applied``; returns the measurement and its covariance
        for the update (projected when the band is limited).

        The equations of :meth:`transition` grouped to avoid forming ``F_g``: with ``Z =
        G^+ P G^+T``, ``F_g P F_g^T = G (F Z F^T) G^T`` and ``F_g x = G F (G^+ x)``.
        """
        kf = self.kf
        assert kf is not None
        f = transition_dense(self.operator.matrix(v_applied), self.dt)
        pinv = self.integrator.pinv
        z = pinv @ kf.P @ pinv.T
        fz = f @ z @ f.T
        kf.P = self.G @ (self.G @ fz).T
        kf.P[np.diag_indices_from(kf.P)] += self.q
        kf.x = self.G @ (f @ (pinv @ kf.x + 1.0 / self.grid.area))
        y = grad_kde
        if self.projector is not None:
            pi = self.projector
            kf.P = pi @ kf.P @ pi.T
            kf.x = pi @ kf.x
            _, _, y, r, _ = self._project_model(pi, grad_kde, r)
        kf.x_prior, kf.P_prior = kf.x.copy(), kf.P.copy()
        return y, r

    @property
    def estimate(self) -> np.ndarray:
        """``q_hat``, shape ``(2, ny, nx)``."""
        assert self.kf is not None
        return self.kf.x.reshape(2, *self.grid.shape)


class FilterpyDensityFilter(ReferenceDensityFilter):
    """:class:`ReferenceDensityFilter` with filterpy's ``KalmanFilter`` doing the algebra."""

    kalman = FilterpyKalman


class FilterpyGradientFilter(ReferenceGradientFilter):
    """:class:`ReferenceGradientFilter` with filterpy's ``KalmanFilter`` doing the
    algebra; its prediction forms ``F_g`` and ``u`` (:meth:`transition`) and hands them
    to filterpy.
    """

    kalman = FilterpyKalman

    def _predict(
        self, grad_kde: np.ndarray, r: np.ndarray, v_applied: VelocityField
    ) -> tuple[np.ndarray, np.ndarray]:
        """``F_g``, ``u`` and the band-limited model of :meth:`_project_model`, then
        filterpy's prediction.
        """
        assert self.kf is not None
        fg, u0 = self.transition(v_applied)
        fg, q, y, r, u = self._project_model(fg, grad_kde, r, u0)
        self.kf.predict(fg, q, u)
        return y, r
