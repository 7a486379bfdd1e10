"""The decentralised loop's estimator: graph, consensus and per-robot filters assembled.

:class:`RobotEstimators` runs the robots' side of a step (the communication graph at
their positions, dynamic average consensus, every robot's filter);
:class:`DistributedEstimator` is the harness's ``estimator=distributed``: the robots'
estimates, the centralised reference filters beside them, and the network figures.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from harness.domains.base import FreeSpace
from harness.estimators.diffusion import refinement
from harness.estimators.distributed.consensus import DynamicAverageConsensus, message_counts
from harness.estimators.distributed.design import Design
from harness.estimators.distributed.filters import RobotFilters
from harness.estimators.distributed.free_space import (
    FREE_MESSAGES,
    FreeGradients,
    FreeRobotKernels,
)
from harness.estimators.distributed.graph import algebraic_connectivity, communication_graph
from harness.estimators.distributed.messages import Messages
from harness.estimators.distributed.metrics import FIELD_NAMES, NETWORK_KEYS, network_figures
from harness.estimators.distributed.mixing import Mixer, consensus_weights
from harness.estimators.distributed.walls import line_of_sight
from harness.estimators.filters.common import FilterSettings, MeasurementModel
from harness.estimators.filters.engines import LocalEngine
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid, grid_gradient
from harness.parameters import Incompatible, ParameterError, flag, integer, number, require
from harness.protocols import (
    Control,
    MemoryEstimate,
    Plant,
    command_link,
    default_memory,
    require_field,
)
from harness.records import Estimate, RobotEstimates, StepInput


@dataclass(frozen=True)
class DistributedEstimate:
    """The robots' estimates after a step.

    Attributes:
        p_hat: ``(N, M)`` density estimates (1 / length^2).
        observation: ``(N, M)`` tracked observations ``z_i``.
        adjacency: The step's communication graph.
        eps: The step's consensus gain.
    """

    p_hat: np.ndarray
    observation: np.ndarray
    adjacency: sp.csr_matrix
    eps: float


GRADIENTS = {"grid": 2, "fourth_order": 4}
"""The option ``gradient``: the order of the central differences each robot takes of its
own density estimate (:func:`harness.grid.grid_gradient`)."""


class RobotEstimators:
    """Graph + dynamic average consensus + per-robot fast filters (+ agreement on the
    law's input).

    Per step: the communication graph at the robots' positions; ``rounds`` rounds of
    dynamic average consensus (in the design's form, on what its messages carry,
    :class:`~harness.estimators.distributed.consensus.DynamicAverageConsensus`); every robot's
    filter on what it tracks; then what the robots share of the law's input
    (:mod:`~harness.estimators.distributed.share`: each robot's own estimate, or with
    ``share: command`` the agreed one of eq. ``AGREE``,
    :class:`~harness.estimators.distributed.share.ShareCommand`).

    Args:
        grid: The grid.
        dt: Step (s).
        n_robots: ``N`` (each robot knows it; it sets ``k``, ``k_g``).
        bandwidth: KDE bandwidth ``h`` (length).
        settings: Filter settings.
        radius: Communication radius (length), and/or
        k_nearest: number of nearest neighbours (with both: the ``k`` nearest within
            the radius; :func:`~harness.estimators.distributed.graph.communication_graph`).
        rounds: Consensus rounds per step.
        gain: Consensus gain factor in ``(0, 1]``.
        initial_rounds: Consensus rounds at ``t = 0`` before the first estimate
            (default ``rounds``; see :class:`DynamicAverageConsensus`).
        design: The consensus form, what the robots share, what a message carries
            (:class:`~harness.estimators.distributed.design.Design`; default the
            first-order form, the density, grid fields).
        free: Free space of a domain with obstacles (None: the square). The robots'
            kernels are then the free-space heat kernel's
            (:class:`~harness.estimators.distributed.free_space.FreeRobotKernels`), their
            messages carry free cells only, and their filters' model is the masked
            operator the caller passes.
        through_walls: Whether radio links pass through obstacles (default True); when
            False a link needs a line of sight on the map of obstacles
            (:func:`~harness.estimators.distributed.walls.line_of_sight`).
    """

    def __init__(
        self,
        grid: Grid,
        dt: float,
        n_robots: int,
        bandwidth: float,
        settings: FilterSettings,
        radius: float | None = None,
        k_nearest: int | None = None,
        rounds: int = 1,
        gain: float = 1.0,
        initial_rounds: int | None = None,
        design: Design | None = None,
        free: FreeSpace | None = None,
        through_walls: bool = True,
    ) -> None:
        if radius is None and k_nearest is None:
            raise ValueError("give radius, k_nearest or both")
        design = Design() if design is None else design
        self.grid, self.radius, self.k_nearest = grid, radius, k_nearest
        self.free, self.through_walls = free, bool(through_walls)
        self.share = design.sharing()
        self.filters = RobotFilters(grid, dt, MeasurementModel(n_robots, bandwidth, settings))
        kernels = None if free is None else FreeRobotKernels(free, bandwidth)
        self.messages: Messages
        if kernels is None:
            self.messages = design.carrier(grid, bandwidth)
        else:
            self.messages = FREE_MESSAGES[design.messages](design.band_limit, kernels)
        self.consensus = DynamicAverageConsensus(
            grid, bandwidth, rounds=rounds, gain=gain, initial_rounds=initial_rounds,
            form=design.form(), messages=self.messages, kernels=kernels,
        )  # fmt: skip
        self.adjacency: sp.csr_matrix | None = None
        self._w: sp.csr_matrix | None = None
        self._positions: np.ndarray | None = None

    def _graph(self, positions: np.ndarray) -> sp.csr_matrix:
        self.adjacency = communication_graph(positions, self.radius, self.k_nearest)
        if self.free is not None and not self.through_walls:
            self.adjacency = line_of_sight(self.adjacency, positions, self.free)
        w, self.consensus.eps = consensus_weights(self.adjacency, self.consensus.gain)
        self._w, self._positions = w, positions
        return w

    def _mixer(self) -> Mixer:
        """``x -> W x`` of the step's graph."""
        assert self._w is not None and self._positions is not None
        return self.consensus.mixer(self._w, self._positions)

    def agree(self, p_hat: np.ndarray) -> np.ndarray:
        """The law's input from the robots' filtered estimates: ``p_hat`` itself, or eq.
        ``AGREE`` with ``share: command``
        (:meth:`~harness.estimators.distributed.share.Share.agree`).
        """
        return self.share.agree(p_hat, self._mixer, self.messages)

    def _estimate(self, y: np.ndarray) -> DistributedEstimate:
        f = self.filters
        assert f.x is not None and self.adjacency is not None
        return DistributedEstimate(self.agree(f.x), y, self.adjacency, self.consensus.eps)

    def initialize(self, positions: np.ndarray) -> DistributedEstimate:
        """Graph, ``z(0)`` and the filters' start from it, at ``t = 0``."""
        y = self.consensus.initialize(positions, self._graph(positions))
        self.filters.initialize(np.ascontiguousarray(y))
        return self._estimate(y)

    def step(self, positions: np.ndarray, a: sp.csr_matrix) -> DistributedEstimate:
        """New graph at the new positions, consensus, then every robot's filter step
        under the model ``A`` (the Fokker-Planck matrix of the last interval).
        """
        y = self.consensus.step(positions, self._graph(positions))
        self.filters.step(y, a)
        return self._estimate(y)

    def communication(self, adj: sp.csr_matrix) -> dict[str, float]:
        """Per robot per step (means over robots): ``messages``, ``bytes`` (consensus
        and, with ``share: command``, eq. ``AGREE``), ``message_bytes`` (the largest
        message, bytes) and ``mean_degree``.
        """
        c = self.consensus
        counts = message_counts(adj, c.rounds, c.floats_per_round, c.exchanges)
        counts["message_bytes"] = float(c.message_bytes)
        self.share.count(counts, adj, self.messages)
        return counts

    def memory_bytes(self) -> int:
        """Bytes held in per-robot arrays (consensus states and buffer, filter states)."""
        c = self.consensus
        arrays = [c.z, c.w, c.buffer, self.filters.x, self.filters.d]
        arrays += list(c._factors or ())
        return int(sum(a.nbytes for a in arrays if a is not None))


class DistributedEstimator:
    """Each robot estimates the swarm's density from its own kernel and its neighbours
    (``estimator=distributed``), and moves on its own estimate.

    Per step (:class:`RobotEstimators`; the equations are derived in the modules of
    :mod:`harness.estimators.distributed`): the communication graph of the robots' positions
    (radius ``r`` or ``k`` nearest, :mod:`~harness.estimators.distributed.graph`), the dynamic
    average consensus (eq. ``DAC``: ``rounds`` rounds of ``W = I - eps L`` per step,
    ``initial_rounds`` at ``t = 0``, :mod:`~harness.estimators.distributed.consensus`) tracking
    the mean of the robots' kernels, and per robot the fast density filter
    (:mod:`~harness.estimators.distributed.filters`) on its tracked observation, with the
    gradient the central differences of the robot's own density estimate, of order 2
    (``gradient: grid``, ``G p_hat_i``) or 4 (``gradient: fourth_order``, ``G_4
    p_hat_i``; :func:`harness.grid.grid_gradient`). The control then moves robot
    ``i`` by the law evaluated from its own estimates at its own position (a field law's
    ``at_cells``, :func:`harness.control.own_estimates.own_velocities`).

    The centralised local filters run alongside, with the same parameters, on the exact
    KDE of the robots (the mean of the robots' own kernels, which consensus distributes;
    the plant's KDE may be binned), as the reference: their estimate is logged and
    measured against, never used for control. With a complete graph (``radius >=
    sqrt(2)`` times the domain side) one round is exact consensus and every robot's
    estimate is the centralised one (tested to 1e-10).

    What the estimate returned to the loop holds: ``p_hat`` the robots' mean estimate and
    ``q_hat`` its central differences (the field the log shows, and the velocity field
    whose Fokker-Planck matrix is the shared transport model of every robot's filter and
    of the reference); the traces of the reference; each robot's own estimate
    (:class:`~harness.records.RobotEstimates`); the fields ``p_hat_central`` (the
    reference's estimate) and ``p_hat_robot`` (robot ``robot``'s); and the network
    metrics (:func:`~harness.estimators.distributed.metrics.network_figures`).

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
            :class:`harness.estimators.filters.common.FilterSettings` (``filter.*``).
        radius: Communication radius (length), or None with ``k_nearest``.
        k_nearest: Neighbours per robot (symmetrised), or None with ``radius``; with
            both, each robot talks to its ``k_nearest`` nearest within ``radius``.
        rounds: Consensus rounds per step (``>= 1``).
        gain: Consensus gain factor in ``(0, 1]``: ``eps = gain / (1 + d_max)``.
        gradient: ``grid`` or ``fourth_order`` (see above).
        initial_rounds: Consensus rounds at ``t = 0`` (``>= 0``).
        robot: Index of the robot whose estimate is logged (``/fields/p_hat_robot``).
        connectivity_every: Steps between evaluations of the graph's algebraic
            connectivity (an eigenvalue problem of ``N`` unknowns; held in between).
        consensus: ``first_order`` (eq. ``DAC``) or ``pi`` (eq. ``PI``,
            :mod:`~harness.estimators.distributed.consensus`).
        integral_gain: ``k_I`` of ``pi`` in ``(0, 1)`` (``k_P = 1 - k_I^2``).
        share: ``density`` (consensus on the kernels only) or ``command`` (then
            ``command_rounds`` rounds of agreement on the law's input, eq. ``AGREE`` of
            :class:`~harness.estimators.distributed.share.ShareCommand`).
        messages: ``grid`` (fields of ``M`` cells) or ``band`` (the band's ``K`` cosine
            coefficients, :mod:`~harness.estimators.distributed.band`; the reference then observes
            the band-limited KDE, which is what the robots can agree on).
        band_limit: ``kappa_c h`` of ``band`` messages (finite; 329 modes at the paper's
            grid and ``h``, 2632 bytes a message; 2.0 keeps 214 modes, 1712 bytes).
        command_rounds: Rounds of eq. ``AGREE`` per step (``>= 1``).
        through_walls: On a domain with obstacles, whether radio links pass through them
            (default true, as radio does); false keeps only the links with a line of
            sight on the map of obstacles
            (:func:`~harness.estimators.distributed.walls.line_of_sight`, applied after
            the radius or ``k_nearest`` selection). No effect on the square.

    On a domain with obstacles (``model.free``) the same loop runs on free space: each
    robot's kernel is the free-space heat kernel's column at its position, the same
    kernel as the centralised KDE there, so the robots' mean tracked field is that KDE
    (:mod:`~harness.estimators.distributed.free_space`); messages carry free cells only
    (or the coefficients of the masked Laplacian's band); the filters' model is the
    masked Fokker-Planck operator of the loop, and the reference is the centralised
    ``local`` engine on free space. A robot's gradient is the free-space gradient of
    its own estimate (:meth:`harness.domains.base.FreeSpace.gradient`: the cell itself
    behind a closed face), so ``gradient: fourth_order`` is refused there.

    The last six make the design (:class:`~harness.estimators.distributed.design.Design`,
    which checks them and maps each choice to its class); the designs ``conf/design/*.yaml``
    set ``consensus``, ``share`` and ``messages`` together (``+design=command_band``); the
    metrics ``messages``, ``bytes`` and ``message_bytes`` count what each design sends
    (:meth:`RobotEstimators.communication`).
    """

    uses_kde = False  # the robots' kernels and the reference's exact KDE, from positions
    free_space = True  # free-space kernels, messages, masked filters (test_distributed_free_space)
    publishes = NETWORK_KEYS  # every estimate carries them (network_figures)
    carries = ("traces", "reference")  # the reference filters'; each robot's reference

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
        consensus: str = Design.consensus,
        integral_gain: float = Design.integral_gain,
        share: str = Design.share,
        messages: str = Design.messages,
        band_limit: float = Design.band_limit,
        command_rounds: int = Design.command_rounds,
        through_walls: bool = True,
    ) -> None:
        self.grid = grid
        self.free = model.free
        self.n_robots = integer("robots", robots, 1)
        h = number("bandwidth", bandwidth, 0.0, strict=True)
        dt = number("dt", dt, 0.0, strict=True)
        wall_images = "true (the robots' kernels carry the wall images)"
        require(flag("mirror", mirror), "mirror", mirror, wall_images)
        # the robots' filters keep every grid mode (no band limit)
        checked = FilterSettings.checked(process_noise, r_scale, r_floor, initial_variance)
        settings = dataclasses.replace(checked, band_limit=np.inf)
        require(radius is not None or k_nearest is not None, "radius", radius,
                "a length >= 0, or null with k_nearest set")  # fmt: skip
        if radius is not None:
            radius = number("radius", radius, 0.0)
        if k_nearest is not None:
            k_nearest = integer("k_nearest", k_nearest, 0)
        rounds = integer("rounds", rounds, 1)
        gain = number("gain", gain, 0.0, strict=True)
        require(gain <= 1.0, "gain", gain, "a number in (0, 1]")
        known = isinstance(gradient, str) and gradient in GRADIENTS
        require(known, "gradient", gradient, f"one of {', '.join(GRADIENTS)}")
        self.order = GRADIENTS[gradient]
        if self.free is not None:
            require(self.order == 2, "gradient", gradient,
                    "grid on a domain with obstacles (the free-space gradient)")  # fmt: skip
        through_walls = flag("through_walls", through_walls)
        initial_rounds = integer("initial_rounds", initial_rounds, 0)
        design = Design(
            consensus=consensus, integral_gain=integral_gain, share=share,
            command_rounds=command_rounds, messages=messages, band_limit=band_limit,
        )  # fmt: skip
        self.robot = integer("robot", robot, 0)
        require(self.robot < self.n_robots, "robot", robot, f"an index below robots = {robots}")
        self.connectivity_every = integer("connectivity_every", connectivity_every, 1)
        # the swarm's size and the loop's step, as the run's shared keys must give them
        self.copies = {"robots": ("robots", self.n_robots), "dt": ("dt", dt)}
        self.network = RobotEstimators(
            grid, dt, self.n_robots, h, settings, radius=radius, k_nearest=k_nearest,
            rounds=rounds, gain=gain, initial_rounds=initial_rounds, design=design,
            free=self.free, through_walls=through_walls,
        )  # fmt: skip
        measurement = MeasurementModel(self.n_robots, h, settings)
        if self.free is None:
            self.central = LocalEngine(grid, model.sigma, dt, measurement)
        else:
            self.central = LocalEngine(grid, model.sigma, dt, measurement, free=self.free)
            self._gradients = FreeGradients(self.free)
        self._steps = 0
        self._connectivity = float("nan")

    def resolution(self, measured: float | None) -> float | None:
        """None (the grid's): the robots' filters keep every grid mode."""
        return None

    @classmethod
    def memory_estimate(cls, grid: Grid, robots: int = 1, **params: object) -> MemoryEstimate:
        """Per robot, fields of ``M`` float64 values: consensus state and buffer, kernel
        factors, the filters' states and variances (7), a step's temporaries (the
        kernels' change, the observations, the filters' and the law's work arrays: 4),
        with ``consensus: pi`` six more (the integral state and a round's temporaries),
        with ``share: command`` two more; and the graph: four sparse copies (the
        neighbour lists, the adjacency, ``W``, their construction) of 12 bytes per edge
        end, with ``deg = min(N - 1, 2.5 N pi r^2)`` neighbours per robot for a radius
        ``r`` (2.5: the swarm gathers, at the paper's start box at twice the uniform
        density) and ``deg = 2 k`` for the ``k`` nearest. Calibrated on the peak
        resident memory at N = 16384, r = 0.1 (``python -m benchmarks.distributed
        --app`` checks every design against it). On a domain with obstacles
        (``free_space``, passed by :func:`harness.runs.resources.check_memory`) the
        robots' kernel table (:class:`~harness.estimators.distributed.free_space.FreeRobotKernels`)
        of at most ``(r n)^2 x n^2`` float64 values (``r`` the KDE's refinement), four
        times over while it is built (measured: a 52 MB table raised the peak by 157 MB).
        """
        n = robots if isinstance(robots, int) and robots > 0 else 1
        try:
            design = Design.of(params)
        except ParameterError:  # refused when the estimator is built
            design = Design()
        fields = 11 + design.form().memory_fields + design.sharing().memory_fields
        per_robot = 8 * fields * grid.size + 8 * (grid.nx + grid.ny) * 4
        radius, k = params.get("radius"), params.get("k_nearest")
        degree = float(n - 1)
        if isinstance(k, int) and k >= 0:
            degree = min(degree, 2.0 * k)
        elif isinstance(radius, (int, float)) and radius >= 0:
            degree = min(degree, 2.5 * n * np.pi * float(radius) ** 2)
        graph = 4 * 12 * n * degree
        table = 0
        bandwidth = params.get("bandwidth")
        if params.get("free_space") is True and isinstance(bandwidth, (int, float)):
            try:
                r = refinement(grid, float(bandwidth))
            except ValueError:  # refused when the estimator is built
                r = 1
            table = 4 * 8 * (r * r * grid.size) * grid.size
        return MemoryEstimate(
            default_memory(grid).nbytes + n * per_robot + int(graph) + table, "robots"
        )

    def _estimate(self, est: DistributedEstimate, p_central: np.ndarray) -> Estimate:
        g = self.grid
        adj = est.adjacency
        if self._steps % self.connectivity_every == 0:
            self._connectivity = algebraic_connectivity(adj)
        self._steps += 1
        network = network_figures(g, est.p_hat, p_central, adj,
                                  self.network.communication(adj), self._connectivity)  # fmt: skip
        p_mean = est.p_hat.mean(axis=0).reshape(g.shape)
        central, robot = FIELD_NAMES
        fields = {central: p_central, robot: est.p_hat[self.robot].reshape(g.shape)}
        q_hat = None
        if self.free is None:
            q_mean = grid_gradient(g, p_mean, self.order)  # linear: the robots' mean
        else:  # each robot's free-space gradient of its own estimate, and their mean
            q_mean = self.free.gradient(p_mean)
            q_hat = self._gradients(est.p_hat)
        return Estimate(
            p_mean, q_mean, *self.central.traces,
            robots=RobotEstimates(est.p_hat, q_hat, np.ravel(p_central), self.order),
            fields=fields, metrics=network,
        )  # fmt: skip

    def check(self, plant: Plant, control: Control, **parts: object) -> None:
        """Every robot estimates and moves on its own: refuse a plant without robots, a
        law that does not move each robot by its own estimate, and a command link that is
        not ideal (it models a broadcast from a central law, :mod:`harness.plants.link`).
        """
        if not plant.has_robots:
            raise Incompatible(
                "plant", type(plant).__name__,
                "a plant with robots (plant=agents): every robot of estimator=distributed "
                "estimates and moves on its own",
            )  # fmt: skip
        require_field(control, "for estimator=distributed (its filters' model is A(v) of it)")
        if not control.own_estimates:
            raise Incompatible(
                "control", type(control).__name__,
                "a law that moves each robot by the law of its own estimate (a FieldLaw "
                "with its own at_cells, harness.control) for estimator=distributed",
            )  # fmt: skip
        link = command_link(plant)
        if link is not None and not link.ideal:
            key, value = (
                ("link.loss", link.loss) if link.loss
                else ("link.latency", link.latency_steps * link.dt) if link.latency_steps
                else ("link.period", link.period_steps * link.dt)
            )  # fmt: skip
            raise Incompatible(
                key, value,
                "the ideal link with estimator=distributed: each robot computes its own "
                "command on board, and the link models a broadcast from a central law",
            )  # fmt: skip

    def initialize(self, inp: StepInput) -> Estimate:
        """The graph and consensus at the first positions; every filter's start."""
        if inp.positions is None:
            raise ValueError("estimator=distributed needs robots (plant=agents)")
        robots = self.network.initialize(inp.positions)
        p_central, _ = self.central.initialize(*self._kde())
        return self._estimate(robots, p_central)

    def _kde(self) -> tuple[np.ndarray, np.ndarray]:
        """The reference's observation: the exact KDE the robots' kernels make (band
        limited, ``Pi p``, with band messages: what the robots can agree on), and its
        analytic gradient (not band limited: the reference's gradient filter, whose
        estimate neither the robots nor the metrics use, sees the whole gradient).
        """
        p, grad = self.network.consensus.kde()
        p = self.network.messages.project(p.reshape(1, -1)).reshape(p.shape)
        return p, grad

    def step(self, inp: StepInput) -> Estimate:
        """New graph, consensus, every robot's filter step under the shared model
        ``A`` (of the robots' mean estimate's field), and the reference's step.
        """
        assert inp.positions is not None and inp.a is not None and inp.v_applied is not None
        robots = self.network.step(inp.positions, inp.a)
        p_kde, grad_kde = self._kde()  # the kernels consensus just used
        p_central, _ = self.central.step(p_kde, grad_kde, inp.v_applied, inp.a)
        return self._estimate(robots, p_central)
