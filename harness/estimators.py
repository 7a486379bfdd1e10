"""Estimators (config group ``estimator``): ``filters`` | ``kde`` | ``exact`` | ``smoothed`` |
``injected`` | ``distributed``.

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
    MemoryEstimate,
    ParameterError,
    default_memory,
    flag,
    integer,
    number,
    require,
)
from harness.distributed import (
    DistributedEstimate,
    RobotEstimators,
    algebraic_connectivity,
    estimate_spread,
    message_counts,
    n_components,
)
from harness.filters.common import FilterSettings, MeasurementModel
from harness.filters.engines import FilterEngine
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.records import Estimate, RobotEstimates, StepInput
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


class DistributedEstimator:
    """Each robot estimates the swarm's density from its own kernel and its neighbours
    (``estimator=distributed``), and moves on its own estimate.

    Per step (:mod:`harness.distributed`, where the equations are derived): the
    communication graph of the robots' positions (radius ``r`` or ``k`` nearest), the
    dynamic average consensus (eq. ``DAC``: ``rounds`` rounds of ``W = I - eps L``
    per step, ``initial_rounds`` at ``t = 0``) tracking the mean of the robots'
    kernels, and per robot the fast density filter (:mod:`harness.filters.local`) on
    its tracked observation, with the gradient either the grid gradient of the robot's
    own density estimate (``gradient: grid``) or its own gradient filter (``gradient:
    filter``, slow: one weighted Poisson solve per robot and step). The loop then moves
    robot ``i`` with the law evaluated from its own estimates at its own position
    (:func:`harness.distributed.decentralised_velocities`, the control's ``at_cells``).

    The centralised local filters run alongside, with the same parameters, on the exact
    KDE of the robots (the mean of the robots' own kernels, which consensus distributes;
    the plant's KDE may be binned), as the reference: their estimate is logged and
    measured against, never used for control. With a complete graph (``radius >=
    sqrt(2)`` times the domain side) one round is exact consensus and every robot's
    estimate is the centralised one (tested to 1e-10).

    What the estimate returned to the loop holds: ``p_hat``, ``q_hat`` the robots' mean
    estimate (the field the log shows, and the velocity field whose Fokker-Planck matrix
    is the shared transport model of every robot's filter and of the reference); the
    traces of the reference; and :class:`~harness.records.RobotEstimates`.

    The plant's ``p_true`` stays the centralised loop's ``N -> infinity`` limit (the
    decentralised loop's own limit depends on the graph and is not modelled).

    The robots' filters keep every grid mode (no band limit; a per-robot DCT would
    cost ``O(N M log M)`` per step), and so does the reference, so that the two differ
    only by what consensus does; the step bound is therefore the grid's
    (:meth:`resolution`).

    Args:
        grid, model: Run-time arguments.
        robots: ``N`` (``agents.n``): every robot knows the swarm size (it sets the
            kernel weights' noise constants ``k``, ``k_g``).
        bandwidth: Kernel bandwidth ``h`` (length, ``kde.bandwidth``).
        dt: Step (s).
        mirror: Must be true: the robots' kernels carry the wall images.
        process_noise, r_scale, r_floor, initial_variance: As
            :class:`harness.filters.common.FilterSettings` (``filter.*``).
        radius: Communication radius (length), or None with ``k_nearest``.
        k_nearest: Neighbours per robot (symmetrised), or None with ``radius``.
        rounds: Consensus rounds per step (``>= 1``).
        gain: Consensus gain factor in ``(0, 1]``: ``eps = gain / (1 + d_max)``.
        gradient: ``grid`` or ``filter`` (see above).
        initial_rounds: Consensus rounds at ``t = 0`` (``>= 0``).
        robot: Index of the robot whose estimate is logged (``/fields/p_hat_robot``).
        connectivity_every: Steps between evaluations of the graph's algebraic
            connectivity (an eigenvalue problem of ``N`` unknowns; held in between).
    """

    uses_kde = False  # the robots' kernels and the reference's exact KDE, from positions
    decentralised = True
    GRADIENTS = ("grid", "filter")

    def __init__(
        self,
        grid: Grid,
        model: FokkerPlanck,
        robots: int,
        bandwidth: float,
        dt: float,
        mirror: bool = True,
        process_noise: float = 0.1,
        r_scale: float = 1.0,
        r_floor: float = 0.05,
        initial_variance: float = 10.0,
        radius: float | None = 0.1,
        k_nearest: int | None = None,
        rounds: int = 1,
        gain: float = 1.0,
        gradient: str = "grid",
        initial_rounds: int = 30,
        robot: int = 0,
        connectivity_every: int = 100,
    ) -> None:
        self.grid = grid
        self.n_robots = integer("robots", robots, 1)
        h = number("bandwidth", bandwidth, 0.0, strict=True)
        dt = number("dt", dt, 0.0, strict=True)
        wall_images = "true (the robots' kernels carry the wall images)"
        require(flag("mirror", mirror), "mirror", mirror, wall_images)
        settings = FilterSettings(
            process_noise=number("process_noise", process_noise, 0.0),
            r_scale=number("r_scale", r_scale, 0.0, strict=True),
            r_floor=number("r_floor", r_floor, 0.0, strict=True),
            initial_variance=number("initial_variance", initial_variance, 0.0, strict=True),
            band_limit=np.inf,
        )
        require((radius is None) != (k_nearest is None), "radius", radius,
                "a length >= 0, or null with k_nearest set (exactly one of the two)")  # fmt: skip
        if radius is not None:
            radius = number("radius", radius, 0.0)
        if k_nearest is not None:
            k_nearest = integer("k_nearest", k_nearest, 0)
        rounds = integer("rounds", rounds, 1)
        gain = number("gain", gain, 0.0, strict=True)
        require(gain <= 1.0, "gain", gain, "a number in (0, 1]")
        require(gradient in self.GRADIENTS, "gradient", gradient, "one of grid, filter")
        initial_rounds = integer("initial_rounds", initial_rounds, 0)
        self.robot = integer("robot", robot, 0)
        require(self.robot < self.n_robots, "robot", robot, f"an index below robots = {robots}")
        self.connectivity_every = integer("connectivity_every", connectivity_every, 1)
        self.network = RobotEstimators(
            grid, dt, self.n_robots, h, settings, radius=radius, k_nearest=k_nearest,
            rounds=rounds, gain=gain, gradient=gradient, initial_rounds=initial_rounds,
        )  # fmt: skip
        measurement = MeasurementModel(self.n_robots, h, settings)
        self.central = FilterEngine.named("local")(grid, model.sigma, dt, measurement)
        self._steps = 0
        self._connectivity = float("nan")

    def resolution(self, measured: float | None) -> float | None:
        """None (the grid's): the robots' filters keep every grid mode."""
        return None

    @classmethod
    def memory_estimate(cls, grid: Grid, robots: int = 1, **params: object) -> MemoryEstimate:
        """Per robot: consensus state and buffer, kernel factors, the filters' states
        and variances (with ``gradient: filter`` three more fields), about ``8 (4 + 3 +
        (4 if filter)) M`` bytes, plus the grid arrays; the graph is ``O(N deg)``.
        """
        n = robots if isinstance(robots, int) and robots > 0 else 1
        fields = 11 if params.get("gradient") == "filter" else 7
        per_robot = 8 * fields * grid.size + 8 * (grid.nx + grid.ny) * 4
        return MemoryEstimate(default_memory(grid).nbytes + n * per_robot, "robots")

    def _estimate(self, est: DistributedEstimate, p_central: np.ndarray) -> Estimate:
        g = self.grid
        adj = est.adjacency
        if self._steps % self.connectivity_every == 0:
            self._connectivity = algebraic_connectivity(adj)
        self._steps += 1
        counts = message_counts(adj, self.network.consensus.rounds,
                                self.network.consensus.fields * g.size)  # fmt: skip
        spread, gap = estimate_spread(g, est.p_hat, p_central)
        network = {
            "consensus_l2": spread,
            "central_gap_l2": gap,
            "messages": counts["messages"],
            "mean_degree": counts["mean_degree"],
            "components": float(n_components(adj)),
            "algebraic_connectivity": self._connectivity,
        }
        p_mean = est.p_hat.mean(axis=0).reshape(g.shape)
        if est.q_hat is None:
            q_mean = g.gradient(p_mean)  # G is linear: the mean of G p_hat_i
        else:
            q_mean = est.q_hat.mean(axis=0).reshape(2, *g.shape)
        robots = RobotEstimates(est.p_hat, est.q_hat, p_central, self.robot, network)
        return Estimate(p_mean, q_mean, *self.central.traces, robots=robots)

    def initialize(self, inp: StepInput) -> Estimate:
        """The graph and consensus at the first positions; every filter's start."""
        if inp.positions is None:
            raise ValueError("estimator=distributed needs robots (plant=agents)")
        robots = self.network.initialize(inp.positions)
        p_central, _ = self.central.initialize(*self.network.consensus.kde())
        return self._estimate(robots, p_central)

    def step(self, inp: StepInput) -> Estimate:
        """New graph, consensus, every robot's filter step under the shared model
        ``A`` (of the robots' mean estimate's field), and the reference's step.
        """
        assert inp.positions is not None and inp.a is not None and inp.v_applied is not None
        robots = self.network.step(inp.positions, inp.a)
        p_kde, grad_kde = self.network.consensus.kde()  # the kernels consensus just used
        p_central, _ = self.central.step(p_kde, grad_kde, inp.v_applied, inp.a)
        return self._estimate(robots, p_central)
