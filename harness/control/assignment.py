"""Optimal-transport deployment (config group ``control``): every period, the robots are
assigned to ``N`` fixed points of the target by an optimal assignment, and each heads for
its point (:class:`AssignmentControl`, ``control=ot``).

:func:`quantise` gives the target's points; the assignment itself is
:mod:`harness.control.matching` (:func:`~harness.control.matching.assign`).

Reference:
    V. Krishnan and S. Martínez, "Distributed optimal transport for the deployment of
    swarms", IEEE Conference on Decision and Control 2018, arXiv 1804.01572.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from harness.control.free_space import (
    blocked,
    centres,
    points_in_free_cells,
    segments_blocked,
    visible_free_cells,
)
from harness.control.geodesic import Geodesics, Routes, geodesic_costs
from harness.control.guidance import target_masses
from harness.control.matching import (
    DENSE_BYTES_PER_PAIR,
    EXACT_MAX,
    SPARSE_BYTES_PER_ROBOT,
    assign,
    assignment_of_cost,
)
from harness.control.waypoints import PeriodClock, cell_of, steer
from harness.grid import Grid
from harness.parameters import integer, number, speed_cap
from harness.protocols import MemoryEstimate, default_memory
from harness.records import Command, ControlInput
from harness.targets.densities import Target
from harness.velocity import VelocityField

SEED_STREAM = 5
"""The law's random stream: ``np.random.default_rng([seed, 5])``."""


def van_der_corput(k: np.ndarray) -> np.ndarray:
    """The base-2 radical inverse of the integers ``k >= 0`` (bits mirrored about the
    binary point): ``0, 1/2, 1/4, 3/4, 1/8, ...``, any ``2^m`` consecutive ones one in
    each interval ``[l / 2^m, (l + 1) / 2^m)``.
    """
    k = np.asarray(k, dtype=np.uint64).copy()
    out = np.zeros(k.shape)
    scale = 0.5
    while k.any():
        out += scale * (k & np.uint64(1))
        k >>= np.uint64(1)
        scale /= 2
    return out


def quantise(grid: Grid, masses: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points of the piecewise-uniform density with cell masses ``masses`` (``(ny,
    nx)``, sum 1), stratified: shape ``(2, n)`` (length).

    Systematic sampling along a serpentine path through the cells (row 0 left to right,
    row 1 right to left, ...): with the cumulative masses ``S_c`` along the path and one
    uniform draw ``U``, point ``k`` lies at the path's mass coordinate ``s_k = (k + U) /
    n``, in the cell ``c`` with ``S_{c-1} <= s_k < S_c``, at the fraction ``(s_k -
    S_{c-1}) / m_c`` of that cell along the path's direction; across it, at ``(r(k) +
    U') mod 1``, ``r`` the base-2 radical inverse (:func:`van_der_corput`) and ``U'`` a
    second draw, so that the points sharing a cell spread across it too. The points are
    ``1 / n`` apart in mass, so cell ``c`` holds ``floor(n m_c)`` or ``ceil(n m_c)`` of
    them, and so does any run of cells along the path (``|count - n m| < 1``); cells of
    zero mass get none.
    """
    masses = np.asarray(masses, dtype=float)
    ny, nx = masses.shape
    serpentine = np.arange(ny * nx).reshape(ny, nx)
    serpentine[1::2] = serpentine[1::2, ::-1]
    path = serpentine.ravel()
    along = masses.ravel()[path]
    cumulative = np.cumsum(along)
    last = int(np.flatnonzero(along > 0)[-1])
    shift, across_shift = rng.random(2)
    s = (np.arange(n) + shift) / n * cumulative[-1]
    step = np.minimum(np.searchsorted(cumulative, s, side="right"), last)
    frac = np.clip((s - (cumulative[step] - along[step])) / along[step], 0.0, 1.0 - 1e-12)
    row, col = np.divmod(path[step], nx)
    fx = np.where(row % 2 == 0, frac, 1.0 - 1e-12 - frac)
    fy = (van_der_corput(np.arange(n)) + across_shift) % 1.0
    return np.stack([grid.x0 + (col + fx) * grid.dx, grid.y0 + (row + fy) * grid.dy])


class AssignmentControl:
    """Optimal-transport deployment by periodic assignment (``control=ot``).

    Source: Krishnan and Martínez (CDC 2018, arXiv 1804.01572) deploy a swarm by
    descending a Kantorovich potential between the swarm and the target that the
    robots estimate in a distributed way. This is the centralised stand-in: the exact
    discrete optimal transport between the robots and a fixed quantisation of ``p_*``
    with ``N`` points, recomputed every period.

    Quantisation (drawn once per run, when the law is built, from
    ``np.random.default_rng([seed, 5])``): ``N`` points stratified over the target's cell
    masses ``v`` (:func:`quantise`: systematic sampling of the density that spreads each
    ``v_j`` uniformly over its cell, along a serpentine path through the cells, ``v``
    exact where the target has closed forms, :func:`harness.control.guidance.target_masses`).
    Why: every cell then holds ``floor(N v_j)`` or ``ceil(N v_j)`` points, so the robots,
    once on their points, match the target's cell masses to within one robot per cell,
    which independent samples miss by ``sqrt(N v_j)`` (largest cell deviation 6.4
    robots at ``N = 1024`` on 30 x 30, 26 at 16384, means of 10 draws), and so did the
    other candidate, scrambled Sobol points mapped through the cells' masses by the
    Rosenblatt transform (2.7 and 3.6: low discrepancy over boxes bounds a cell's count
    only to a few points). What it gives up: below the grid's scale the points are
    spread evenly in each cell, not by ``p_*`` itself.

    The law. At the start of each period ``[k T, (k + 1) T)``, with the robots'
    positions ``x_i`` (as the law sees them) and the points ``y_j``, the assignment

        pi = argmin_{pi permutation} sum_i |x_i - y_{pi(i)}|^2

    (:func:`~harness.control.matching.assign`: exact up to
    :data:`~harness.control.matching.EXACT_MAX` robots, above it certified-optimal
    when the column generation of
    :func:`~harness.control.matching.large_assignment` converges within its rounds),
    and every step ``u_i = (y_{pi(i)} - x_i) / (time left in the period)``, capped at
    ``v_max`` (:mod:`harness.control.waypoints`): robot ``i`` reaches ``y_{pi(i)}`` by the
    period's end when ``v_max >= |y_{pi(i)} - x_i| / T`` and ``sigma = 0``, exactly up to
    round-off. Without cap and noise the robots then move along the displacement
    interpolation of the discrete optimal transport, ``x_i + (s / T) (y_{pi(i)} -
    x_i)``, on which no two robots are at one place at one time ``0 < s < T``: two that
    were would have ``(T - s) (x_1 - x_2) = -s (y_1 - y_2)``, so ``<x_1 - x_2, y_1 -
    y_2> < 0``, and exchanging their points would lower the cost (the cyclical
    monotonicity of an optimal assignment for the squared cost).

    Inputs: the robots' positions at the start of each period and the time; no
    estimate, no density in a denominator.

    Free space (``target.free``, a domain with obstacles). The points are drawn in the
    free part of their cells (a point the quantisation puts in an obstacle, or cut off
    from its cell's centre, is drawn again there,
    :func:`harness.control.free_space.points_in_free_cells`); the cost is geodesic,

        c_ij = max(D(cell of x_i, cell of y_j), |x_i - y_j|)^2,

    ``D`` the shortest path between the cells' centres on the graph of free cells
    joined through open faces and free diagonals (:mod:`harness.control.geodesic`, at
    most 8.2 % above the straight distance where nothing is in the way), exact by the
    dense simplex (:func:`~harness.control.matching.assignment_of_cost`; at most
    :data:`~harness.control.matching.EXACT_MAX` robots); and each robot follows its
    shortest path, a polyline through the cells' centres, by the period's end
    (:class:`harness.control.geodesic.Routes`), never the straight line through an
    obstacle. A robot starts its way from the nearest free cell whose centre it sees
    (:func:`harness.control.free_space.visible_free_cells`). What changes at the fixed
    point: nothing in the points; the assignment is optimal for the geodesic cost, so
    the displacement interpolation's no-collision argument above (which needs the
    squared Euclidean cost) does not carry over.

    Stability and steady state. Without noise and with a cap that allows it, the
    robots sit on their points from the end of the first period on, and the assignment
    of the next period is the identity (the robots already at the points: cost 0), so
    they stay: a fixed point reached in one period (with a binding cap, in about ``max
    |y - x| / v_max``, each period's assignment being optimal from where the robots
    are). With the noise ``sigma``, each period's recomputation of the velocity pulls
    each robot back toward its point (a Brownian bridge, :mod:`harness.control.waypoints`): a
    robot strays from its point by ``sqrt(2 sigma s (T - s) / T)`` per axis at time ``s``
    into the period (at most ``sqrt(2 sigma T) / 2``, 0.005 at ``T`` = 1 s and ``sigma``
    = 5e-5; the period-average variance ``2 sigma T / 6``) and ends it within one step's
    noise ``sqrt(2 sigma dt)`` (0.001). The swarm's distribution is then the ``N``
    points, each blurred by a Gaussian of that scale: ``p_*`` at the points' spacing
    (``1 / sqrt(N)`` per unit area, 0.031 at ``N`` = 1024), much smoother in its cell
    masses than independent samples, but a point cloud below the spacing whenever
    ``sqrt(2 sigma T) / 2`` is smaller than it (at the paper's values, 6 times smaller: a
    KDE of bandwidth ``h`` = 0.04 smooths it out). The next period's assignment may
    exchange points between robots whose strays cross (only when two points are within
    the noise's scale of each other); nothing else moves. Where the robots end up beside
    the other laws: the study ``laws_n`` (``make sweep-laws_n``); ``swarm_w2`` cannot go
    below the metric's own cell-centre quantisation of ``p_*``.

    Args:
        target: The target on the grid (run-time argument).
        robots: ``N``, the swarm size (``${agents.n}``): the number of points.
        period: ``T > 0`` (s) between assignments.
        seed: The run's seed; the law draws from ``np.random.default_rng([seed, 5])``.
        v_max: Speed cap (length / s), or None.

    Attributes:
        points: The quantisation ``(2, N)`` (length).
        assignment: The current period's ``pi`` (None before the first call).
        uses: What the law reads, as a phrase (logged in the ``theory`` record).
        divides_by_density: False: no density in a denominator.
    """

    gives_field: ClassVar[bool] = True
    # precomputed from the static target: refused with target=moving (harness.runs.build)
    follows_moving_target: ClassVar[bool] = False
    own_estimates: ClassVar[bool] = False
    needs_robots: ClassVar[bool] = True
    uses: ClassVar[str] = "positions, target cell masses"
    divides_by_density: ClassVar[bool] = False
    # geodesic costs and paths (tests/test_ot_domains.py)
    free_space: ClassVar[bool] = True

    def __init__(
        self,
        target: Target,
        robots: int,
        period: float = 1.0,
        seed: int = 0,
        v_max: float | None = None,
    ) -> None:
        self.target = target
        self.grid = target.grid
        self.robots = integer("robots", robots, 1)
        self.copies = {"robots": ("robots", self.robots)}  # one point per robot of the swarm
        self.period = number("period", period, 0.0, strict=True)
        self.seed = integer("seed", seed, 0)
        self.v_max = speed_cap(v_max)
        rng = np.random.default_rng([self.seed, SEED_STREAM])
        self.points = quantise(self.grid, target_masses(target), self.robots, rng)
        self.clock = PeriodClock(self.period)
        self.assignment: np.ndarray | None = None
        self.free = target.free
        if self.free is not None:
            if self.robots > EXACT_MAX:
                raise ValueError(
                    f"control=ot on a domain with obstacles assigns at most {EXACT_MAX} "
                    f"robots (dense geodesic costs), got {self.robots}"
                )
            cells = cell_of(self.grid, self.points)
            # points in an obstacle's part of a free cell, or cut off from its centre
            bad = blocked(self.free, self.points) | segments_blocked(
                self.free, centres(self.grid, cells), self.points
            )
            self.points[:, bad] = points_in_free_cells(self.free, cells[bad], rng)
            self.point_cells = cells
            self.geodesics = Geodesics(self.free, cells)
            self.routes: Routes | None = None

    @classmethod
    def memory_estimate(cls, grid: Grid, robots: Any = 1, **params: Any) -> MemoryEstimate:
        """The assignment's peak: :data:`DENSE_BYTES_PER_PAIR` per pair up to
        :data:`~harness.control.matching.EXACT_MAX` robots,
        :data:`~harness.control.matching.SPARSE_BYTES_PER_ROBOT` per robot above; plus
        the grid arrays.
        """
        n = robots if isinstance(robots, int) and robots > 0 else 1
        if n <= EXACT_MAX:
            solver = DENSE_BYTES_PER_PAIR * n * n
        else:
            solver = SPARSE_BYTES_PER_ROBOT * n
        return MemoryEstimate(solver + default_memory(grid).nbytes, "robots")

    def __call__(self, inp: ControlInput) -> Command:
        """At a period's start, the assignment of the robots to the points; every step,
        each robot toward its point (the class docstring).

        Raises:
            ValueError: without robots, or with a number of robots other than ``robots``.
        """
        positions = inp.positions
        if positions is None:
            raise ValueError("AssignmentControl moves robots: it needs their positions")
        if positions.shape[1] != self.robots:
            raise ValueError(
                f"AssignmentControl has {self.robots} points (control.robots) for "
                f"{positions.shape[1]} robots"
            )
        starts = self.clock.tick(inp.t)
        if self.clock.restarted:
            self.assignment = None
        if self.free is not None:
            return self.on_free_space(positions, starts, inp.t)
        if starts or self.assignment is None:
            x = np.ascontiguousarray(positions.T)
            y = np.ascontiguousarray(self.points.T)
            self.assignment = assign(self.grid, x, y, self.assignment)
        goals = self.points[:, self.assignment]
        return steer(self.grid, positions, goals, self.clock.time_left(inp.t), self.v_max)

    def on_free_space(self, positions: np.ndarray, starts: bool, t: float) -> Command:
        """The command on a domain with obstacles (the class docstring): at a period's
        start the assignment for the geodesic costs
        (:func:`harness.control.geodesic.geodesic_costs`) and each robot's way along its
        shortest path (:class:`harness.control.geodesic.Routes`); every step the
        velocity along it.
        """
        assert self.free is not None
        if starts or self.assignment is None or self.routes is None:
            here = visible_free_cells(self.free, positions)
            cost = geodesic_costs(self.geodesics, positions, here, self.points, self.point_cells)
            self.assignment = assignment_of_cost(cost)
            self.routes = Routes(
                self.geodesics,
                positions,
                here,
                self.points[:, self.assignment],
                self.point_cells[self.assignment],
            )
        u = self.routes.velocity(positions, self.clock.time_left(t), self.clock.step, self.v_max)
        return Command(VelocityField.from_robots(self.grid, positions, u), u)

    def feedback_diffusivity(self, p0: np.ndarray) -> None:
        """None: the law is no held velocity field of the estimate, so the sampled-data
        bound of :func:`harness.control.field.sampled_data_dt_bound` does not apply (the run
        says it is not checked).
        """
        return None
