"""Estimators (config group ``estimator``): ``filters`` | ``kde`` | ``exact`` | ``smoothed`` |
``injected`` | ``distributed`` (the decentralised loop's,
:class:`harness.decentralised.DistributedEstimator`).

Each step the loop hands an estimator a :class:`~harness.records.StepInput` (the
plant's measurement, the velocity applied over the last interval and its
Fokker-Planck matrix, and the plant's mean-field density) and gets back an
:class:`~harness.records.Estimate` ``(p_hat, q_hat)`` with diagnostics. Only ``exact``
and ``injected`` read the mean-field density; they exist for theory checks and ISS
gain curves. All implement :class:`harness.components.Estimator` and take the run-time
arguments ``grid`` and ``model`` (the run's
:class:`~harness.fokker_planck.FokkerPlanck`).
"""

from __future__ import annotations

import numpy as np

from harness.components import (
    Control,
    MemoryEstimate,
    ParameterError,
    default_memory,
    flag,
    integer,
    number,
    require_field,
)
from harness.filters.common import FilterSettings, MeasurementModel
from harness.filters.engines import FilterEngine
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.records import Estimate, StepInput
from harness.smoothing import Smoother


class KDEEstimator:
    """``p_hat = p_KDE``, ``q_hat = grad p_KDE``: no filter (``estimator=kde``)."""

    uses_kde = True

    def __init__(self, grid: Grid, model: FokkerPlanck) -> None:
        self.grid = grid

    def resolution(self, measured: float | None) -> float | None:
        """The measurement's own resolution (length)."""
        return measured

    def initialize(self, inp: StepInput) -> Estimate:
        """The raw KDE."""
        assert inp.p_kde is not None and inp.grad_kde is not None
        return Estimate(inp.p_kde, inp.grad_kde)

    step = initialize


class ExactEstimator:
    """``p_hat = p``, ``q_hat = G p`` with the mean-field density ``p`` (theory checks,
    ``estimator=exact``).
    """

    uses_kde = False

    def __init__(self, grid: Grid, model: FokkerPlanck) -> None:
        self.grid = grid

    def initialize(self, inp: StepInput) -> Estimate:
        """The mean-field density and its grid gradient."""
        return Estimate(inp.p_true, self.grid.gradient(inp.p_true))

    step = initialize


class SmoothedEstimator:
    """``p_hat = K_h * p``, ``q_hat = grad(K_h * p)``: the noise-free KDE of the plant's
    mean-field density ``p`` (``estimator=smoothed``), what the KDE of infinitely many
    robots distributed as ``p`` would measure (:class:`harness.smoothing.Smoother`).
    On the mean-field plant it is the ``N -> infinity`` limit of the agent loop with the
    raw KDE.

    Args:
        grid, model: Run-time arguments.
        bandwidth: Kernel standard deviation ``h > 0`` (length).
        mirror: Wall images.
    """

    uses_kde = False

    def __init__(
        self, grid: Grid, model: FokkerPlanck, bandwidth: float, mirror: bool = True
    ) -> None:
        self.bandwidth = number("bandwidth", bandwidth, 0.0, strict=True)
        self.smoother = Smoother(grid, self.bandwidth, flag("mirror", mirror))

    def resolution(self, measured: float | None) -> float | None:
        """The kernel's bandwidth ``h`` (length)."""
        return self.bandwidth

    def initialize(self, inp: StepInput) -> Estimate:
        """The smoothed mean-field density and its gradient."""
        return Estimate(*self.smoother(inp.p_true))

    step = initialize


class InjectedEstimator:
    """Truth plus a smooth, seeded error of prescribed L2 size (for ISS gain curves).

        eps(t)   = delta e(t),                e(t) = cos(omega t) e1 + sin(omega t) e2,
        eps_g(t) = delta G e(t) / ||G e(t)||,

    with ``e1, e2`` L2-orthonormal, zero-mean (mass is kept) combinations of the
    Neumann cosine modes up to ``modes`` per axis, with random coefficients from
    ``rng``. So ``||eps|| = ||eps_g|| = delta`` at every step; the error rotates
    between two shapes with angular frequency ``omega`` (rad / s).

    ``estimator=injected``.

    Args:
        grid, model: Run-time arguments.
        delta: Error size ``>= 0`` (1 / length for ``eps``; 1 / length^2 for ``eps_g``,
            the same number).
        seed: Seed of the error shapes (the run's ``seed``; the shapes use the stream
            ``[seed, 1]``, apart from the plant's).
        omega: Angular frequency (rad / s).
        modes: Highest cosine mode per axis in the shapes (``>= 1``).
    """

    uses_kde = False

    def __init__(
        self,
        grid: Grid,
        model: FokkerPlanck,
        delta: float,
        seed: int,
        omega: float = 0.1,
        modes: int = 4,
    ) -> None:
        delta = number("delta", delta, 0.0)
        omega = number("omega", omega)
        modes = integer("modes", modes, 1)
        rng = np.random.default_rng([integer("seed", seed, 0), 1])
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
        """Mean-field density plus the error at ``inp.t``."""
        eps, eps_g = self.error(inp.t)
        return Estimate(inp.p_true + eps, self.grid.gradient(inp.p_true) + eps_g)

    step = initialize


class FilterEstimator:
    """The paper's two filters on the KDE (``estimator=filters``): eqs. ``density
    filter``, ``density Riccati``, ``gradient filter``, ``gradient Riccati``.

    The engine is chosen by name from :class:`harness.filters.engines.FilterEngine`'s
    registry: ``local`` (fast, default), ``reference`` (dense) or ``filterpy`` (dense,
    filterpy's ``KalmanFilter`` doing the algebra).

    Args:
        grid, model: Run-time arguments (the model gives ``sigma``).
        engine: Engine name (``filter.engine``).
        robots: Swarm size ``N`` of the KDE noise constants ``k``, ``k_g``.
        bandwidth: KDE bandwidth ``h`` (length).
        dt: Measurement period (s).
        process_noise, r_scale, r_floor, initial_variance, band_limit: As
            :class:`harness.filters.common.FilterSettings` (``filter.*``), checked by
            :meth:`~harness.filters.common.FilterSettings.checked`.
    """

    uses_kde = True

    def resolution(self, measured: float | None) -> float | None:
        """The measurement's resolution: the filters estimate only the cosine modes of
        ``|k| <= band_limit / h`` that the KDE resolves
        (:class:`~harness.filters.common.BandLimit`), so their estimates carry no finer
        content than the measurement.
        """
        return measured

    def __init__(
        self,
        grid: Grid,
        model: FokkerPlanck,
        engine: str,
        robots: int,
        bandwidth: float,
        dt: float,
        process_noise: float = 0.1,
        r_scale: float = 1.0,
        r_floor: float = 0.05,
        initial_variance: float = 10.0,
        band_limit: float = 2.5,
    ) -> None:
        engines = sorted(FilterEngine.registry)
        if engine not in FilterEngine.registry:
            raise ParameterError("engine", engine, f"one of {', '.join(engines)}")
        settings = FilterSettings.checked(
            process_noise, r_scale, r_floor, initial_variance, band_limit
        )
        measurement = MeasurementModel(
            integer("robots", robots, 1), number("bandwidth", bandwidth, 0.0, strict=True), settings
        )
        dt = number("dt", dt, 0.0, strict=True)
        self.engine = FilterEngine.named(engine)(grid, model.sigma, dt, measurement)

    @classmethod
    def memory_estimate(cls, grid: Grid, engine: str = "local", **params: object) -> MemoryEstimate:
        """The engine's (:meth:`FilterEngine.memory_bytes`; dense engines are ``O(M^2)``)
        plus the grid arrays; the default estimate for an unknown engine name.
        """
        chosen = FilterEngine.registry.get(engine) if isinstance(engine, str) else None
        extra = chosen.memory_bytes(grid) if chosen is not None else 0
        return MemoryEstimate(default_memory(grid).nbytes + extra, "engine")

    def check(self, control: Control, **parts: object) -> None:
        """The filters' transport model is ``A(v)`` of the law's field: refuse a law
        without one.
        """
        require_field(control, "for estimator=filters (their transport model is A(v) of it)")

    def _estimate(self, p_hat: np.ndarray, q_hat: np.ndarray) -> Estimate:
        return Estimate(p_hat, q_hat, *self.engine.traces)

    def initialize(self, inp: StepInput) -> Estimate:
        """Start both filters from the first KDE."""
        assert inp.p_kde is not None and inp.grad_kde is not None
        return self._estimate(*self.engine.initialize(inp.p_kde, inp.grad_kde))

    def step(self, inp: StepInput) -> Estimate:
        """Predict under the applied velocity, update with the KDE."""
        assert inp.v_applied is not None
        assert inp.p_kde is not None and inp.grad_kde is not None
        return self._estimate(*self.engine.step(inp.p_kde, inp.grad_kde, inp.v_applied, inp.a))
