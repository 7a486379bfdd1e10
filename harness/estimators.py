"""The estimator interface of the run loop: ``filters`` | ``kde`` | ``exact`` | ``injected``.

Each step the run loop hands an estimator a :class:`StepInput` (the KDE of the
swarm, the velocity applied over the last interval and its Fokker-Planck matrix,
and the mean-field truth) and gets back an :class:`Estimate` ``(p_hat, q_hat)``
with diagnostics. Only ``exact`` and ``injected`` read the truth; they exist for
theory checks and ISS gain curves.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import scipy.sparse as sp

from harness.filters.common import FilterSettings, Integrator, MeasurementModel
from harness.filters.local import LocalFilters
from harness.filters.reference import ReferenceDensityFilter, ReferenceGradientFilter
from harness.grid import Grid
from harness.velocity import VelocityField


@dataclass(frozen=True)
class StepInput:
    """What an estimator may use at time ``t`` (s).

    Attributes:
        t: Time (s).
        p_kde: KDE of the swarm ``(ny, nx)`` (1 / length^2).
        grad_kde: Its gradient ``(2, ny, nx)`` (1 / length^3).
        v_applied: Velocity applied over the last interval (None at ``t = 0``).
        a: ``A(v_applied)``, the Fokker-Planck matrix (None at ``t = 0``).
        p_true: Mean-field truth ``(ny, nx)``; only ``exact`` and ``injected`` read it.
    """

    t: float
    p_kde: np.ndarray
    grad_kde: np.ndarray
    v_applied: VelocityField | None
    a: sp.csr_matrix | None
    p_true: np.ndarray | None


@dataclass(frozen=True)
class Estimate:
    """Estimates and diagnostics.

    Attributes:
        p_hat: Density estimate ``(ny, nx)`` (1 / length^2).
        q_hat: Gradient estimate ``(2, ny, nx)`` (1 / length^3).
        trace_P: L2 trace of the density filter's covariance (1 / length^2), or None.
        trace_Q: L2 trace of its process noise per step (1 / length^2), or None.
        trace_P_grad: Same for the gradient filter (1 / length^4), or None.
        trace_Q_grad: Same for the gradient filter (1 / length^4), or None.
    """

    p_hat: np.ndarray
    q_hat: np.ndarray
    trace_P: float | None = None
    trace_Q: float | None = None
    trace_P_grad: float | None = None
    trace_Q_grad: float | None = None


class Estimator(Protocol):
    """Turns measurements into ``(p_hat, q_hat)``."""

    name: str
    uses_kde: bool

    def initialize(self, inp: StepInput) -> Estimate:
        """First estimate, at ``t = 0``."""
        ...

    def step(self, inp: StepInput) -> Estimate:
        """Estimate at a later step."""
        ...


class KDEEstimator:
    """``p_hat = p_KDE``, ``q_hat = grad p_KDE``: no filter."""

    name = "kde"
    uses_kde = True

    def initialize(self, inp: StepInput) -> Estimate:
        """The raw KDE."""
        return Estimate(inp.p_kde, inp.grad_kde)

    step = initialize


class ExactEstimator:
    """``p_hat = p``, ``q_hat = G p`` with the mean-field truth ``p`` (theory checks)."""

    name = "exact"
    uses_kde = False

    def __init__(self, grid: Grid) -> None:
        self.grid = grid

    def initialize(self, inp: StepInput) -> Estimate:
        """The truth and its grid gradient."""
        assert inp.p_true is not None
        return Estimate(inp.p_true, self.grid.gradient(inp.p_true))

    step = initialize


class InjectedEstimator:
    """Truth plus a smooth, seeded error of prescribed L2 size (for ISS gain curves).

        eps(t)   = delta e(t),                e(t) = cos(omega t) e1 + sin(omega t) e2,
        eps_g(t) = delta G e(t) / ||G e(t)||,

    with ``e1, e2`` L2-orthonormal, zero-mean (mass is kept) combinations of the
    Neumann cosine modes up to ``modes`` per axis, with random coefficients from
    ``rng``. So ``||eps|| = ||eps_g|| = delta`` at every step; the error rotates
    between two shapes with angular frequency ``omega`` (rad / s).

    Args:
        grid: The grid.
        delta: Error size ``>= 0`` (1 / length for ``eps``; 1 / length^2 for ``eps_g``,
            the same number).
        rng: Generator for the error shapes.
        omega: Angular frequency (rad / s).
        modes: Highest cosine mode per axis in the shapes.
    """

    name = "injected"
    uses_kde = False

    def __init__(
        self, grid: Grid, delta: float, rng: np.random.Generator, omega: float = 0.1, modes: int = 4
    ) -> None:
        if not (np.isfinite(delta) and delta >= 0):
            raise ValueError(f"estimator.delta must be >= 0, got {delta}")
        self.grid, self.delta, self.omega = grid, delta, omega
        x, y = grid.mesh
        lx, ly = grid.x1 - grid.x0, grid.y1 - grid.y0
        shapes = []
        for _ in range(2):
            f = np.zeros(grid.shape)
            for a in range(modes + 1):
                for b in range(modes + 1):
                    if a == b == 0:
                        continue
                    f += (
                        rng.normal()
                        / (1 + a * a + b * b)
                        * np.cos(a * np.pi * (x - grid.x0) / lx)
                        * np.cos(b * np.pi * (y - grid.y0) / ly)
                    )
            shapes.append(f - grid.integrate(f) / grid.area)
        e1 = shapes[0] / grid.l2(shapes[0])
        e2 = shapes[1] - grid.inner(shapes[1], e1) * e1
        self.e1, self.e2 = e1, e2 / grid.l2(e2)

    def error(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """``(eps, eps_g)`` at time ``t``."""
        e = np.cos(self.omega * t) * self.e1 + np.sin(self.omega * t) * self.e2
        ge = self.grid.gradient(e)
        return self.delta * e, self.delta * ge / self.grid.l2(ge)

    def initialize(self, inp: StepInput) -> Estimate:
        """Truth plus the error at ``inp.t``."""
        assert inp.p_true is not None
        eps, eps_g = self.error(inp.t)
        return Estimate(inp.p_true + eps, self.grid.gradient(inp.p_true) + eps_g)

    step = initialize


class FilterEstimator:
    """The paper's two filters, fast (``local``) or reference (``reference``, or the
    reference with filterpy as the engine, ``filterpy``).
    """

    name = "filters"
    uses_kde = True

    def __init__(
        self,
        grid: Grid,
        sigma: float,
        dt: float,
        n_robots: int,
        bandwidth: float,
        settings: FilterSettings,
        method: str = "local",
    ) -> None:
        if method not in ("local", "reference", "filterpy"):
            raise ValueError(f"filter.method must be local, reference or filterpy, got {method!r}")
        self.method = method
        model = MeasurementModel(n_robots, bandwidth, settings)
        if method == "local":
            self.fast = LocalFilters(grid, sigma, dt, model)
        else:
            engine = "numpy" if method == "reference" else "filterpy"
            self.density = ReferenceDensityFilter(grid, sigma, dt, model, engine=engine)
            self.gradient = ReferenceGradientFilter(
                grid, sigma, dt, model, engine=engine, integrator=Integrator.build(grid)
            )

    def _estimate(self, p_hat: np.ndarray, q_hat: np.ndarray) -> Estimate:
        if self.method == "local":
            (tp, tg), (qp, qg) = self.fast.trace_P, self.fast.trace_Q
        else:
            tp, tg = self.density.trace_P, self.gradient.trace_P
            qp, qg = self.density.trace_Q, self.gradient.trace_Q
        return Estimate(p_hat, q_hat, tp, qp, tg, qg)

    def initialize(self, inp: StepInput) -> Estimate:
        """Start both filters from the first KDE."""
        if self.method == "local":
            return self._estimate(*self.fast.initialize(inp.p_kde, inp.grad_kde))
        return self._estimate(
            self.density.initialize(inp.p_kde), self.gradient.initialize(inp.grad_kde)
        )

    def step(self, inp: StepInput) -> Estimate:
        """Predict under the applied velocity, update with the KDE."""
        assert inp.v_applied is not None
        if self.method == "local":
            return self._estimate(*self.fast.step(inp.p_kde, inp.grad_kde, inp.v_applied, inp.a))
        return self._estimate(
            self.density.step(inp.p_kde, inp.v_applied),
            self.gradient.step(inp.grad_kde, inp.p_kde, inp.v_applied),
        )
