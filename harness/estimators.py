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

from collections.abc import Sequence

import numpy as np

from harness.components import (
    Control,
    MemoryEstimate,
    ParameterError,
    default_memory,
    flag,
    integer,
    number,
    require,
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
    """Truth plus a seeded error of prescribed L2 size (for ISS gain curves).

    Two shapes (``estimator.shape``):

    ``smooth`` (a rotating combination of low cosine modes):

        eps(t)   = delta e(t),                e(t) = cos(omega t) e1 + sin(omega t) e2,
        eps_g(t) = delta G e(t) / ||G e(t)||,

    with ``e1, e2`` L2-orthonormal, zero-mean (mass is kept) combinations of the
    Neumann cosine modes up to ``modes`` per axis, with random coefficients from
    ``rng``. So ``||eps|| = ||eps_g|| = delta`` at every step; the error rotates
    between two shapes with angular frequency ``omega`` (rad / s).

    ``hole`` (small in L2, but the estimate of a region the robots must reach drops
    towards zero): with the Gaussian well ``w(x) = exp(-|x - c|^2 / (2 r^2))`` at
    ``c = hole_centre`` of width ``r = hole_radius`` and the plant's density ``p``,

        b = p w - (1 / |Omega|) int p w,          eps = -delta b / ||b||,
        eps_g = G eps,

    so ``||eps|| = delta`` exactly, mass is kept, and ``p_hat = p + eps = p (1 - d w)
    + d <p w>`` with depth ``d = delta / ||b||``: at ``d = 1`` the estimate at ``c``
    falls to the small offset ``d <p w>`` (the mean of ``p w`` over the domain), and
    for ``d > 1`` it turns negative there. Everywhere within ``r / 2`` of ``c``,
    ``p_hat <= p (1 - d exp(-1/8)) + d <p w>`` (:meth:`hole_level` gives the bound).
    The gradient error is the gradient of the hole itself (an estimate with a hole has
    its slopes), so ``||eps_g||`` is not ``delta`` (it is logged as ``eps_g_l2``).

    ``estimator=injected``.

    Args:
        grid, model: Run-time arguments.
        delta: Error size ``>= 0`` (1 / length for ``eps``; 1 / length^2 for ``eps_g``,
            the same number, for ``smooth``).
        seed: Seed of the error shapes (the run's ``seed``; the shapes use the stream
            ``[seed, 1]``, apart from the plant's).
        omega: Angular frequency (rad / s), ``smooth``.
        modes: Highest cosine mode per axis in the shapes (``>= 1``), ``smooth``.
        shape: ``smooth`` | ``hole``.
        hole_centre: ``c`` (length), inside the domain, ``hole``.
        hole_radius: ``r > 0`` (length), ``hole``.
    """

    uses_kde = False
    SHAPES = ("smooth", "hole")

    def __init__(
        self,
        grid: Grid,
        model: FokkerPlanck,
        delta: float,
        seed: int,
        omega: float = 0.1,
        modes: int = 4,
        shape: str = "smooth",
        hole_centre: Sequence[float] = (0.45, 0.74),
        hole_radius: float = 0.08,
    ) -> None:
        delta = number("delta", delta, 0.0)
        omega = number("omega", omega)
        modes = integer("modes", modes, 1)
        require(shape in self.SHAPES, "shape", shape, f"one of {', '.join(self.SHAPES)}")
        centre = [number("hole_centre", c) for c in _pair("hole_centre", hole_centre)]
        require(
            bool(grid.contains(np.array([centre[0]]), np.array([centre[1]])).all()),
            "hole_centre", list(hole_centre), "a point inside the domain",
        )  # fmt: skip
        radius = number("hole_radius", hole_radius, 0.0, strict=True)
        rng = np.random.default_rng([integer("seed", seed, 0), 1])
        self.grid, self.delta, self.omega, self.shape = grid, delta, omega, shape
        x, y = grid.mesh
        self.well = np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * radius**2))
        self.hole_centre, self.hole_radius = (centre[0], centre[1]), radius
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

    def error(self, t: float, p: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(eps, eps_g)`` at time ``t`` (``p``: the plant's density, for ``hole``)."""
        g = self.grid
        if self.shape == "hole":
            assert p is not None
            pw = np.maximum(p, 0.0) * self.well
            b = pw - g.integrate(pw) / g.area
            norm = g.l2(b)
            eps = -self.delta * b / norm if norm > 0 else np.zeros_like(b)
            return eps, g.gradient(eps)
        e = np.cos(self.omega * t) * self.e1 + np.sin(self.omega * t) * self.e2
        ge = g.gradient(e)
        return self.delta * e, self.delta * ge / g.l2(ge)

    def hole_level(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The ``hole`` shape's guarantee for density ``p``: the cells within
        ``hole_radius / 2`` of the centre (a boolean mask) and the bound ``p (1 - d
        exp(-1/8)) + d <p w>`` that ``p_hat`` stays at or below there.
        """
        g = self.grid
        x, y = g.mesh
        cx, cy = self.hole_centre
        inside = (x - cx) ** 2 + (y - cy) ** 2 <= (self.hole_radius / 2) ** 2
        pw = np.maximum(p, 0.0) * self.well
        mean = g.integrate(pw) / g.area
        norm = g.l2(pw - mean)
        depth = self.delta / norm if norm > 0 else 0.0
        return inside, p * (1 - depth * np.exp(-1 / 8)) + depth * mean

    def initialize(self, inp: StepInput) -> Estimate:
        """Mean-field density plus the error at ``inp.t``."""
        eps, eps_g = self.error(inp.t, inp.p_true)
        return Estimate(inp.p_true + eps, self.grid.gradient(inp.p_true) + eps_g)

    step = initialize


def _pair(name: str, value: object) -> tuple[object, object]:
    """Two coordinates, or :class:`~harness.components.ParameterError` naming ``name``."""
    ok = isinstance(value, Sequence) and not isinstance(value, str) and len(value) == 2
    require(ok, name, value, "two coordinates [x, y]")
    assert isinstance(value, Sequence)
    return value[0], value[1]


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
