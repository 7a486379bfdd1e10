"""Probabilistic swarm guidance (config group ``control``): Markov chains on the grid's
cells that each robot samples on its own, once per period.

Every ``period`` ``T`` (s) each robot in cell ``j`` draws its next cell ``i`` with the
probability ``M_ij`` of a column-stochastic matrix ``M`` (``sum_i M_ij = 1``: column
``j`` is where a robot in ``j`` goes), and heads for a point drawn uniformly in cell
``i``, arriving by the period's end where the speed cap allows
(:mod:`harness.control.waypoints`). The swarm's cell distribution ``m`` (robots per cell over
``N``, sum 1) then evolves in expectation as ``m <- M m``. Moves are to the cell itself or
to its 4-neighbours, so ``M`` has at most 5 entries per column; the robots draw their
next cells all at once from per-cell cumulative rows over those 5 candidates
(:class:`CellChain`).

* :class:`MetropolisGuidance` (``control=psg``): the Metropolis-Hastings chain of
  Açıkmeşe and Bayard, fixed and open loop, with the target's cell masses ``v`` as its
  stationary distribution.
* :class:`FeedbackGuidance` (``control=psg_feedback``): a chain rebuilt every period from
  the run's density estimate, which moves robots only out of cells the estimate says
  hold more than their target mass, and is the identity at the target.

Free space (``target.free``, a domain with obstacles): the chains live on the graph of
free cells joined through open faces (:func:`neighbour_table`): no candidate lies behind
a closed face or in a blocked cell, and the target's masses ``v`` are 0 on blocked
cells (:func:`target_masses`). Every statement below holds on that graph as on the
grid's (the proofs use only the graph's edges and its degrees): ``v`` stays the exact
stationary distribution of ``psg`` and the identity's of ``psg_feedback`` at the
target (``tests/test_guidance_domains.py``). A robot in the free part of a blocked
cell counts in the nearest free cell, and goals are drawn in the free part of a cell
(:mod:`harness.control.free_space`). The way to a goal is a straight segment between
points of neighbouring cells through an open face; where an obstacle clips it (a
partly blocked cell) the robot reflects off it as off a wall (the plant).

Both need robots (``needs_robots``): they have no mean-field form, so the mean-field plant
refuses them and the agents plant carries the robots' histogram in place of an ``N ->
infinity`` limit. Their commands are the robots' own velocities plus the swarm's mean
velocity per cell (:meth:`harness.velocity.VelocityField.from_robots`), which the
filters' transport model uses.

References:
    B. Açıkmeşe and D. S. Bayard, "A Markov chain approach to probabilistic swarm
    guidance", American Control Conference 2012; "Markov chain approach to probabilistic
    guidance for swarms of autonomous agents", Asian Journal of Control 17(4), 2015.
    S. Bandyopadhyay, S.-J. Chung and F. Y. Hadaegh, "Probabilistic and distributed
    control of a large-scale swarm of autonomous agents" (PSG-IMC), IEEE Transactions on
    Robotics 33(5), 2017.
    S. Uzun, N. K. Üre and B. Açıkmeşe, "Decentralized state-dependent Markov chain
    synthesis with an application to swarm guidance" (DSMC), arXiv 2012.02303.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from harness.control.free_space import nearest_free_cells, points_in_free_cells
from harness.control.waypoints import PeriodClock, cell_of, points_in_cells, steer
from harness.domains.base import FreeSpace
from harness.estimators.smoothing import cell_masses, smoothed_target
from harness.grid import Grid
from harness.parameters import flag, integer, number, require, speed_cap
from harness.records import Command, ControlInput
from harness.targets.densities import Target

CANDIDATES = 5
"""Cells a robot may move to: its own, then left, right, below, above."""


ROUND_OFF = 1e-12
"""An excess or deficit ``|m_j - v_j|`` of at most this fraction of ``v_j`` counts as
none (:class:`FeedbackGuidance`): the round-off of an estimate equal to the target."""


SEED_STREAM = 4
"""The guidance laws' random stream: ``np.random.default_rng([seed, 4])`` (streams 1 and
2 are the run's others)."""


def neighbour_table(grid: Grid, free: FreeSpace | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each cell's candidates: ``(cells, exists)``, both ``(M, 5)`` for the grid's ``M``
    flat cells (C order): column 0 the cell itself, then its left, right, lower and upper
    neighbour; a neighbour beyond a wall, or on free space ``free`` behind a closed face
    (every face of a blocked cell is closed), is the cell itself with ``exists`` false:
    the graph of free cells joined through open faces.
    """
    row, col = np.divmod(np.arange(grid.size), grid.nx)
    steps = ((0, 0), (0, -1), (0, 1), (-1, 0), (1, 0))
    cells = np.empty((grid.size, CANDIDATES), dtype=np.intp)
    exists = np.empty((grid.size, CANDIDATES), dtype=bool)
    for k, (dr, dc) in enumerate(steps):
        r, c = row + dr, col + dc
        ok = (r >= 0) & (r < grid.ny) & (c >= 0) & (c < grid.nx)
        exists[:, k] = ok
        cells[:, k] = np.where(ok, r * grid.nx + c, row * grid.nx + col)
    if free is not None:
        fx, fy = free.face_x.ravel(), free.face_y.ravel()
        right = row * (grid.nx - 1) + col  # face_x between (row, col) and (row, col + 1)
        exists[:, 1] &= fx[np.where(exists[:, 1], right - 1, 0)]
        exists[:, 2] &= fx[np.where(exists[:, 2], right, 0)]
        exists[:, 3] &= fy[np.where(exists[:, 3], (row - 1) * grid.nx + col, 0)]
        exists[:, 4] &= fy[np.where(exists[:, 4], row * grid.nx + col, 0)]
        itself = np.broadcast_to(np.arange(grid.size)[:, None], cells.shape)
        cells = np.where(exists, cells, itself)
    return cells, exists


def target_masses(target: Target) -> np.ndarray:
    """The target's cell masses ``v`` (``(ny, nx)``, dimensionless, sum 1): exact for a
    density with closed-form cell masses (:func:`harness.estimators.smoothing.cell_masses`),
    else cell value times cell area; for a target given by cell values only, those
    times the cell area. On free space (``target.free``) 0 on blocked cells, the free
    cells' masses renormalised to sum 1.
    """
    g = target.grid
    if target.density is None:
        v = target.p * g.cell_area
    else:
        v = cell_masses(target.density, g)
    v = np.clip(v, 0.0, None)
    if target.free is not None:
        v = np.where(target.free.cells, v, 0.0)
    return v / v.sum()


def metropolis_columns(v: np.ndarray, cells: np.ndarray, exists: np.ndarray) -> np.ndarray:
    """The Metropolis-Hastings chain toward ``v`` (flat, sum 1) at each cell's candidates:
    ``P[j, k] = M_{cells[j, k], j}``, shape ``(M, 5)`` (:class:`MetropolisGuidance`).

    Proposal ``K_ij = 1 / (1 + d_j)`` for ``i`` the cell ``j`` or one of its ``d_j``
    existing neighbours; for a neighbour ``i``, ``M_ij = K_ij min(1, v_i K_ji / (v_j
    K_ij)) = min(K_ij, v_i K_ji / v_j)`` (``K_ij`` when ``v_j = 0``); the rest of the
    column on the diagonal.
    """
    degree = exists[:, 1:].sum(axis=1)
    k_out = 1.0 / (1.0 + degree)  # K_ij for every candidate i of j
    k_back = k_out[cells[:, 1:]]  # K_ji
    v_to = v[cells[:, 1:]]
    ratio = np.divide(
        v_to * k_back,
        v[:, None],
        out=np.full(v_to.shape, np.inf),
        where=v[:, None] > 0,
    )
    moves = np.where(exists[:, 1:], np.minimum(k_out[:, None], ratio), 0.0)
    out = np.empty(cells.shape)
    out[:, 1:] = moves
    out[:, 0] = 1.0 - moves.sum(axis=1)  # >= K_jj = 1 / (1 + d_j) > 0
    return out


def chain_matrix(cells: np.ndarray, exists: np.ndarray, columns: np.ndarray) -> sp.csc_matrix:
    """``M`` as a sparse ``(M, M)`` matrix from candidate columns ``P[j, k] = M_{cells[j,
    k], j}`` (entries at missing neighbours dropped).
    """
    m = cells.shape[0]
    source = np.broadcast_to(np.arange(m)[:, None], cells.shape)
    keep = exists & (columns != 0)
    return sp.csc_matrix((columns[keep], (cells[keep], source[keep])), shape=(m, m))


class CellChain:
    """Draws each robot's next cell from its cell's column of ``M``, all robots at once.

    Per cell ``j`` the cumulative sums ``c_jk = sum_{l <= k} P[j, l]`` over its 5
    candidates; a robot in ``j`` with a uniform draw ``u`` takes the candidate ``k = #{l :
    c_jl <= u}``, the first whose cumulative sum exceeds ``u``, so candidate ``k`` has
    probability ``c_jk - c_j(k-1) = P[j, k]`` and a candidate of probability 0 is never
    taken; ``k`` is capped at the last candidate of positive probability (a ``u`` above a
    cumulative sum that round-off left below 1).

    Args:
        cells: ``(M, 5)`` candidate cells (:func:`neighbour_table`).
        columns: ``(M, 5)`` their probabilities, each row summing to 1.
    """

    def __init__(self, cells: np.ndarray, columns: np.ndarray) -> None:
        self.cells = cells
        self.cumulative = np.cumsum(columns, axis=1)
        positive = columns > 0
        self.last = CANDIDATES - 1 - np.argmax(positive[:, ::-1], axis=1)

    def __call__(self, current: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The next cell of robots in flat cells ``current`` (one uniform draw each)."""
        u = rng.random(current.size)
        k = (self.cumulative[current] <= u[:, None]).sum(axis=1)
        k = np.minimum(k, self.last[current])
        return self.cells[current, k]


class _Guidance:
    """What the two guidance laws share: parameters, the period clock and the robots'
    goals (a ``NaN`` goal holds the robot).

    Attributes:
        uses: What the law reads, as a phrase (logged in the ``theory`` record).
        divides_by_density: Whether a density estimate sits in a denominator.
    """

    gives_field: ClassVar[bool] = True
    # precomputed from the static target: refused with target=moving (harness.runs.build)
    follows_moving_target: ClassVar[bool] = False
    own_estimates: ClassVar[bool] = False
    needs_robots: ClassVar[bool] = True
    uses: ClassVar[str] = "positions, target cell masses"
    divides_by_density: ClassVar[bool] = False
    # chains on the graph of free cells (tests/test_guidance_domains.py)
    free_space: ClassVar[bool] = True

    def __init__(self, target: Target, period: float, seed: int, v_max: float | None) -> None:
        self.target = target
        self.grid = target.grid
        self.period = number("period", period, 0.0, strict=True)
        self.seed = integer("seed", seed, 0)
        self.v_max = speed_cap(v_max)
        self.free = target.free
        self.cells, self.exists = neighbour_table(self.grid, self.free)
        self._nearest = None if self.free is None else nearest_free_cells(self.free)
        self.clock = PeriodClock(self.period)
        self.rng = np.random.default_rng([self.seed, SEED_STREAM])
        self.goals: np.ndarray | None = None

    def chain(self, inp: ControlInput) -> CellChain:
        """The chain the robots sample at the start of the period containing ``inp.t``."""
        raise NotImplementedError

    def __call__(self, inp: ControlInput) -> Command:
        """The command at ``inp.t``: at a period's start each robot draws its next cell
        and a goal in it (a robot that stays holds under :class:`FeedbackGuidance`);
        then every robot heads for its goal (:func:`harness.control.waypoints.steer`).

        Raises:
            ValueError: without robots (``inp.positions`` None).
        """
        positions = inp.positions
        if positions is None:
            raise ValueError(f"{type(self).__name__} moves robots: it needs their positions")
        starts = self.clock.tick(inp.t)
        if self.clock.restarted:
            self.rng = np.random.default_rng([self.seed, SEED_STREAM])
        if starts or self.goals is None or self.goals.shape != positions.shape:
            here = self.cell_of(positions)
            there = self.chain(inp)(here, self.rng)
            self.goals = self.goal_points(here, there)
        return steer(self.grid, positions, self.goals, self.clock.time_left(inp.t), self.v_max)

    def cell_of(self, positions: np.ndarray) -> np.ndarray:
        """The cell each robot counts in: its own, or on free space the nearest free
        cell to its own when that is blocked
        (:func:`harness.control.free_space.nearest_free_cells`).
        """
        here = cell_of(self.grid, positions)
        return here if self._nearest is None else self._nearest[here]

    def points(self, cells: np.ndarray) -> np.ndarray:
        """A point drawn uniformly in each of ``cells``, ``(2, n)``; on free space in
        the free part of the cell (:func:`harness.control.free_space.points_in_free_cells`).
        """
        if self.free is None:
            return points_in_cells(self.grid, cells, self.rng)
        return points_in_free_cells(self.free, cells, self.rng)

    def goal_points(self, here: np.ndarray, there: np.ndarray) -> np.ndarray:
        """A point drawn uniformly in each robot's next cell ``there``, ``(2, N)``."""
        return self.points(there)

    def feedback_diffusivity(self, p0: np.ndarray) -> None:
        """None: the law is no held velocity field of the estimate, so the sampled-data
        bound of :func:`harness.control.field.sampled_data_dt_bound` does not apply (the run
        says it is not checked).
        """
        return None


class MetropolisGuidance(_Guidance):
    """Probabilistic swarm guidance by a Metropolis-Hastings chain (``control=psg``).

    Source: Açıkmeşe and Bayard (ACC 2012; Asian J. Control 17(4), 2015): the bins are
    the grid's cells, the target distribution is the target's cell masses

        v_j = int_{cell j} p_*   (exact where the target has closed forms,
                                  :func:`target_masses`; dimensionless, sum 1),

    the proposal is uniform over the cell and its existing 4-neighbours (``d_j`` of them:
    4 inside, 3 on a wall, 2 in a corner),

        K_ij = 1 / (1 + d_j)   for i = j or i a neighbour of j,   else 0,

    (so a robot at a wall proposes each cell it can reach with the same probability; the
    asymmetry ``K_ij != K_ji`` between cells of different degree is what the acceptance
    corrects), and

        F_ij = min(1, v_i K_ji / (v_j K_ij)),   M_ij = K_ij F_ij  (i != j),
        M_jj = 1 - sum_{i != j} M_ij = K_jj + sum_{i != j} K_ij (1 - F_ij).

    Each period a robot in cell ``j`` draws ``i`` from column ``j`` of ``M`` and heads for
    a uniform point of cell ``i`` (a fresh point of its own cell when ``i = j``),
    arriving by the period's end when ``v_max`` allows (:mod:`harness.control.waypoints`). Open
    loop: neither the estimate nor the other robots enter.

    Properties (each checked in ``tests/test_guidance.py``). ``M_ij v_j = min(K_ij v_j,
    K_ji v_i)`` is symmetric in ``i, j``: detailed balance ``M_ij v_j = M_ji v_i``, hence
    ``(M v)_i = sum_j M_ji v_i = v_i``, ``v`` stationary. ``M`` is column-stochastic,
    ``M_jj >= K_jj > 0`` (aperiodic) and ``M_ij > 0`` between neighbours where ``v > 0``
    (irreducible on a connected grid), so ``M^k m -> v`` from every start ``m``,
    geometrically at the rate of ``M``'s second eigenvalue (real, as ``M`` is reversible).
    For the default target on the 30 x 30 grid that eigenvalue is 0.99812: a relaxation
    time ``1 / (1 - lambda_2)`` of 531 periods, about what a nearest-neighbour random
    walk needs to cross 30 cells (at ``T`` = 1 s, 8.9 min, against the 34 s time
    constant of the paper's loop; a shorter period shortens it in proportion and speeds
    the robots up in proportion). Where the robots end up beside the other laws: the
    study ``laws_n`` (``make sweep-laws_n``).

    Inputs: the robots' positions at the start of each period (their cells) and the
    time. A density in a denominator: ``v_j`` of the target in ``F``, never an
    estimate; ``v_j = 0`` (a cell without target mass) accepts every move out and none
    in.

    Stability and steady state. Open loop: the cell distribution follows the linear,
    convergent ``m_{k+1} = M m_k`` whatever the estimates do (their gain is zero). The
    robots draw independently, so at stationarity their cells are ``N`` independent
    draws from ``v``: the histogram fluctuates multinomially about ``v`` (the finite-N
    floor of independent samples), and the robots never stop: a robot leaves its cell
    with probability ``1 - M_jj`` every period (at the default target on 30 x 30, 71 %
    of the swarm per period). Where the robots are: at the period boundaries, in cell
    ``i`` uniformly (the target's cell masses spread uniformly over each cell, the
    target at the grid's resolution); in between, on straight paths between points of
    neighbouring cells, which smooths that piecewise-constant density over about a cell
    along the grid's axes. The noise ``sigma`` does not shift the stationary
    distribution: each robot ends the period at its goal plus one step's noise
    (standard deviation ``sqrt(2 sigma dt)`` per axis, 0.001 at the paper's ``sigma``
    and ``dt``, 3 % of a 30 x 30 cell), so near its edges a cell lends and borrows a
    little mass, and within the period the Brownian bridge spreads a robot about its
    path by at most ``sqrt(2 sigma T) / 2`` (0.005 at ``T`` = 1 s). With a speed cap a
    robot that cannot reach its goal in the period draws again from wherever it is:
    the chain on the cells is then no longer ``M`` and ``v`` no longer exactly
    stationary.

    Args:
        target: The target on the grid (run-time argument).
        period: ``T > 0`` (s) between draws.
        seed: The run's seed; the law draws from ``np.random.default_rng([seed, 4])``.
        v_max: Speed cap (length / s), or None.

    Attributes:
        masses: ``v``, ``(ny, nx)``.
        matrix: ``M``, sparse ``(M, M)`` over flat cells (C order; column = from).
    """

    def __init__(
        self, target: Target, period: float = 1.0, seed: int = 0, v_max: float | None = None
    ) -> None:
        super().__init__(target, period, seed, v_max)
        self.masses = target_masses(target)
        self.columns = metropolis_columns(self.masses.ravel(), self.cells, self.exists)
        self.matrix = chain_matrix(self.cells, self.exists, self.columns)
        self._chain = CellChain(self.cells, self.columns)

    def chain(self, inp: ControlInput) -> CellChain:
        """The fixed chain ``M``."""
        return self._chain


class FeedbackGuidance(_Guidance):
    """Density-feedback guidance (``control=psg_feedback``): a chain rebuilt each period
    from the run's estimate that moves robots only out of cells holding more than their
    target mass, and is the identity at the target.

    Sources: the idea (a time-varying, state-dependent column-stochastic ``M`` built from
    the current swarm distribution, with transitions only along the grid's edges, that
    tends to the identity as the swarm reaches the target, so that the robots settle) is
    that of Uzun, Üre and Açıkmeşe's DSMC (arXiv 2012.02303) and of Bandyopadhyay, Chung
    and Hadaegh's PSG-IMC (IEEE T-RO 33(5), 2017). The matrix below is this project's
    own construction in that spirit, not the matrices of either paper.

    The chain. At the start of each period, with the estimate ``p_hat`` (1 / length^2),
    the estimated cell masses ``m_j = max(p_hat_j, 0) |cell| / sum_l max(p_hat_l, 0)
    |cell|`` and the target's ``v_j`` (:func:`target_masses`; with ``debias``, those of
    ``K_h * p_*``, which is what a KDE-based estimate estimates), cell ``j`` has the
    excess ``e_j = max(0, m_j - v_j)`` and the deficit ``d_j = max(0, v_j - m_j)`` (each
    0 at round-off level, ``|m_j - v_j| <= 1e-12 v_j``). A
    robot in cell ``j`` leaves with probability

        a_j = g e_j / m_j          (0 where e_j = 0; 0 <= a_j <= g <= 1),

    ``g`` the ``gain``, and goes to the neighbour ``i`` with probability ``w_ij``:
    proportional to the neighbours' deficits, ``w_ij = d_i / sum_{l ~ j} d_l``, or, when
    no neighbour has a deficit, uniformly over the neighbours one step closer (on the
    grid's graph) to the nearest cell with a deficit, so that excess inside an
    over-full region is relayed toward the deficits, one cell per period (Uzun, Üre and
    Açıkmeşe add shortest paths to their DSMC for states that do not border a deficit;
    this is the same idea in its simplest form, the hop count). So

        M_ij = a_j w_ij  (i ~ j),     M_jj = 1 - a_j.

    Properties (each checked in ``tests/test_guidance.py``):

    * ``M`` is column-stochastic, nonnegative, with moves only to 4-neighbours.
    * Robots leave only cells with an excess: column ``j`` is ``e_j`` (cell ``j`` of the
      identity) unless ``m_j > v_j``.
    * At the target, ``m = v``: every ``e_j = 0``, so ``M = I``; hence ``M v = v`` (``v``
      is stationary) and the robots stop moving (they hold; only the noise moves them).
      Conversely ``M = I`` only at ``m = v`` (masses of sum 1 without an excess have no
      deficit either).
    * Descent of the expected distribution (``N -> infinity``, exact estimates ``m_hat =
      m``, ``g <= 1``): ``||M m - v||_1 <= ||m - v||_1``. Proof: a cell with an excess
      sends ``a_j m_j = g e_j <= e_j``, so it stays at or above its target and its
      ``|m_j - v_j|`` falls by what it sends and rises by what it receives; cells
      without an excess send nothing. Adding up, with ``r_i`` what cell ``i`` receives,
      ``||M m - v||_1 - ||m - v||_1 = sum_{d_i > 0} (|r_i - d_i| - d_i - r_i) = -2
      sum_{d_i > 0} min(r_i, d_i) <= 0``, strictly negative whenever a cell with an
      excess borders one with a deficit (the deficit cell then receives). It is a
      descent, not a proof of convergence: an excess that does not border a deficit
      is relayed along shortest paths toward one, which does not decrease the distance
      until it arrives.

    Inputs: the estimate ``p_hat`` at the start of each period and the robots' cells.
    A density in a denominator: the estimate's ``m_j`` in ``a_j``, but only where ``m_j >
    v_j > 0`` (elsewhere ``a_j = 0``), and ``e_j / m_j <= 1`` there, so ``a_j`` stays
    in ``[0, g]`` however small or noisy the estimate; deficits are normalised only by a
    positive sum. An estimate with no positive mass holds every robot.

    Stability and steady state. With exact estimates the descent above holds each
    period; with estimates, ``M`` acts on ``m_hat``'s excesses, so estimation errors
    move robots out of cells that are in fact at target (a robot in cell ``j`` leaves
    with probability ``g (m_hat_j - v_j)_+ / m_hat_j``, of the order of the estimate's
    relative error): the swarm churns at that rate. What the loop settles to is ``m_hat
    = v``, not ``m = v``: a KDE-based estimate (``kde``, ``filters``) estimates ``K_h *
    p``, so without ``debias`` the robots' distribution sharpens toward ``K_h^{-1}`` of
    the target, as for the paper's law. The chain works on cell masses, so it needs an
    estimate that averages over several robots per cell: with the robots' histogram
    itself (``estimator=exact``) at about one robot per cell (1024 robots, 900 cells),
    every occupied cell of low target mass has an excess and its empty neighbours a
    deficit, and robots shuffle locally instead of leaving the low regions. With the noise
    ``sigma`` there is no fixed point of the robots themselves: holding robots diffuse
    (``sqrt(2 sigma T)`` per period, 0.01 at ``T`` = 1 s and the paper's ``sigma``, a
    third of a 30 x 30 cell), which every period moves about ``sigma T |Laplacian v|``
    of mass per unit area into the target's valleys, and the chain sends back ``g``
    times the excess it sees: a balance at a bias of order ``sigma T |Laplacian v| / g``
    (a percent of ``v`` for the default target, derived as an order of magnitude, not
    measured). Where the robots end up beside the other laws: the study ``laws_n``
    (``make sweep-laws_n``).

    Args:
        target: The target on the grid (run-time argument).
        gain: ``g`` in ``(0, 1]``: the expected fraction of a cell's estimated excess
            that leaves per period. The default 1 sends the whole estimated excess each
            period (the chain's L1 descent above holds for every ``g <= 1``).
        period: ``T > 0`` (s) between decisions.
        seed: The run's seed; the law draws from ``np.random.default_rng([seed, 4])``.
        v_max: Speed cap (length / s), or None.
        debias: Compare the estimate with the cell masses of ``K_h * p_*``.
        bandwidth: The KDE's bandwidth ``h`` (length), for ``debias``.
        mirror: The KDE's wall images, for ``debias``.

    Attributes:
        masses: The target masses ``v`` the estimate is compared with, ``(ny, nx)``.
    """

    uses: ClassVar[str] = "positions, estimate, target cell masses"
    divides_by_density: ClassVar[bool] = True  # m_hat_j in a_j, bounded (class docstring)

    def __init__(
        self,
        target: Target,
        gain: float = 1.0,
        period: float = 1.0,
        seed: int = 0,
        v_max: float | None = None,
        debias: bool = False,
        bandwidth: float | None = None,
        mirror: bool = True,
    ) -> None:
        super().__init__(target, period, seed, v_max)
        self.gain = number("gain", gain, 0.0, strict=True)
        require(self.gain <= 1, "gain", gain, "a number in (0, 1]")
        if flag("debias", debias):
            h = number("bandwidth", bandwidth, 0.0, strict=True)
            compared = smoothed_target(target, h, flag("mirror", mirror))
            self.masses = target_masses(compared)
        else:
            self.masses = target_masses(target)
        source = np.broadcast_to(np.arange(self.grid.size)[:, None], self.cells.shape)
        edges = self.exists.copy()
        edges[:, 0] = False
        self._graph = sp.csr_matrix(
            (np.ones(int(edges.sum())), (source[edges], self.cells[edges])),
            shape=(self.grid.size, self.grid.size),
        )
        degree = self.exists[:, 1:].sum(axis=1, keepdims=True)  # 0: a cell shut in
        self._uniform = self.exists[:, 1:] / np.maximum(degree, 1)

    def toward_deficits(self, deficit: np.ndarray) -> np.ndarray:
        """Per cell, ``(M, 4)`` weights over its neighbours: uniform over those one hop
        closer to the nearest cell with ``deficit > 0`` (uniform over all neighbours
        when no cell has a deficit).
        """
        sources = np.flatnonzero(deficit > 0)
        if sources.size == 0:
            return self._uniform
        hops = dijkstra(self._graph, directed=False, indices=sources, min_only=True)
        closer = self.exists[:, 1:] & (hops[self.cells[:, 1:]] < hops[:, None])
        count = closer.sum(axis=1, keepdims=True)
        return np.where(count > 0, closer / np.maximum(count, 1), self._uniform)

    def estimated_masses(self, p_hat: np.ndarray) -> np.ndarray | None:
        """``m_hat`` (flat, sum 1) from ``p_hat`` (1 / length^2), or None when it has no
        positive mass.
        """
        m = np.clip(np.asarray(p_hat, dtype=float).ravel(), 0.0, None) * self.grid.cell_area
        total = float(m.sum())
        if not (np.isfinite(total) and total > 0):
            return None
        return m / total

    def columns(self, p_hat: np.ndarray) -> np.ndarray:
        """The chain at the candidates, ``P[j, k] = M_{cells[j, k], j}``, ``(M, 5)``, for
        the estimate ``p_hat`` (the class docstring).
        """
        out = np.zeros(self.cells.shape)
        out[:, 0] = 1.0
        m = self.estimated_masses(p_hat)
        if m is None:
            return out
        v = self.masses.ravel()
        excess = np.where(m - v > ROUND_OFF * v, m - v, 0.0)
        deficit = np.where(v - m > ROUND_OFF * v, v - m, 0.0)
        leave = np.zeros_like(m)
        np.divide(self.gain * excess, m, out=leave, where=excess > 0)
        leave = np.minimum(leave, 1.0)
        if self.free is not None:  # a free cell with no open face keeps its robots
            leave = np.where(self.exists[:, 1:].any(axis=1), leave, 0.0)
        wanting = np.where(self.exists[:, 1:], deficit[self.cells[:, 1:]], 0.0)
        total = wanting.sum(axis=1, keepdims=True)
        has = total[:, 0] > 0
        weights = np.where(has[:, None], wanting / np.where(has, total[:, 0], 1.0)[:, None], 0.0)
        if (excess[~has] > 0).any():
            weights[~has] = self.toward_deficits(deficit)[~has]
        out[:, 1:] = leave[:, None] * weights
        out[:, 0] = 1.0 - leave
        return out

    def matrix(self, p_hat: np.ndarray) -> sp.csc_matrix:
        """``M`` for the estimate ``p_hat``, sparse ``(M, M)`` over flat cells."""
        return chain_matrix(self.cells, self.exists, self.columns(p_hat))

    def chain(self, inp: ControlInput) -> CellChain:
        """The chain of the current estimate ``inp.estimate.p_hat``."""
        return CellChain(self.cells, self.columns(inp.estimate.p_hat))

    def goal_points(self, here: np.ndarray, there: np.ndarray) -> np.ndarray:
        """A uniform point of the next cell for a robot that moves; ``NaN`` (hold) for
        one that stays.
        """
        goals = self.points(there)
        goals[:, there == here] = np.nan
        return goals
