"""Swarm-level metrics from robot positions, independent of every estimator.

Three quantities say where the robots are, whatever the filters believe:

* the smoothed target ``K_h * p_*`` on the grid
  (:func:`harness.estimators.smoothing.smoothed_density`), with the KDE's own kernel,
  wall images included (exact for a density with a closed form);
* ``swarm_l2 = ||K_h * mu_N - K_h * p_*||`` (:func:`swarm_l2`, 1 / length), with
  ``mu_N = (1/N) sum_k delta_{X_k}`` the robots' empirical measure and ``K_h * mu_N``
  the KDE of :mod:`harness.estimators.kde`;
* ``swarm_w2``, an optimal-transport distance between the robots and ``p_*``
  (:func:`swarm_w2`, length);

and :func:`floors` gives the finite-N floor of both: their distribution when the N
robots are drawn independently from ``p_*`` (Monte Carlo, seeded).

The kernel. :class:`harness.estimators.kde.KDE` evaluates, at a cell centre ``c = (c_x, c_y)``,

    K(c, X) = k_x(c_x, X_x) k_y(c_y, X_y),
    k(c, X) = g_h(c - X) + g_h(c - (2 lo - X)) + g_h(c - (2 hi - X)),

with ``g_h(z) = exp(-z^2 / 2h^2) / (sqrt(2 pi) h)`` and the two images per axis
(the corner images come from the product). It skips the image of a robot farther
than ``9 h`` from a wall, which changes ``k`` by less than ``3e-18 / (sqrt(2 pi) h)``;
the closed forms of :mod:`harness.targets.densities` keep every image. The expectation of the
KDE of N independent samples of ``p`` is then ``(K_h * p)(c) = int_Omega p(x) K(c, x)
dx``.

``K_h * p`` of a density and its cell masses are
:func:`harness.estimators.smoothing.smoothed_density` and
:func:`harness.estimators.smoothing.cell_masses`.

Which K_h * p the loop sees. With more than ``exact_max_robots`` robots the KDE
bins them linearly onto a grid ``bin_factor`` times finer (at most the kernel's
resolution needs, :func:`harness.estimators.kde.binning_nodes`) before smoothing; its expectation is
then ``K_h * p`` plus the binning bias, ``O((s / h)^2)`` for node spacing ``s``
relative (about 1e-3 for the paper's settings, ``~1e-3`` in ``swarm_l2`` against a
floor of 0.03 at ``N = 65536``). The floors use the same KDE, so they include it.

Cost per call on the 30 x 30 grid (2 shared cores, BLAS on one thread; indicative,
the host was loaded 4x while measuring: ``python -m benchmarks.debias_check --costs``):
``swarm_l2`` 0.2-0.5 ms for N = 1024 to 65536; ``swarm_w2`` exact EMD 0.12 s
(N = 1024) and 0.55 s (N = 4096) on a quiet host, 0.56 s and 2.6 s loaded; sliced
(64 directions, target on the 4x refined grid) 0.16, 0.19, 0.38, 0.82 s loaded at
N = 1024, 4096, 16384, 65536. ``swarm_l2`` fits every ``log.positions_every = 10``
steps; ``swarm_w2`` does not (a 10^4-step run would spend 10^3 calls): log it every
100 steps (1 s of simulated time, far below the loop's 34 s time constant).
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits

from harness.domains.base import FreeSpace
from harness.estimators.kde import KDE
from harness.estimators.smoothing import cell_masses
from harness.grid import Grid
from harness.targets.densities import Density

EMD_MAX_ROBOTS = 4096
"""``swarm_w2`` uses the exact EMD up to this many robots and the sliced distance above
(see :func:`swarm_w2`)."""


N_PROJECTIONS = 64
"""Directions of the sliced distance (equispaced on the half circle)."""


@dataclass(frozen=True)
class TargetMeasure:
    """``p_*`` as a discrete measure for transport: the exact mass of each cell of a
    quantisation grid, placed at the cell's centre.

    Moving each cell's mass to its centre costs at most ``W2 <= (dx^2 + dy^2)^(1/2) /
    sqrt(12)`` (0.0136 for a 30 x 30 grid on the unit square): ``swarm_w2`` of robots
    drawn from ``p_*`` includes it, and so does its floor.

    Attributes:
        points: ``(M, 2)`` cell centres (length).
        weights: ``(M,)`` cell masses, summing to 1 (cells of zero mass dropped).
    """

    points: np.ndarray
    weights: np.ndarray

    @classmethod
    def from_density(cls, density: Density, grid: Grid, refine: int = 1) -> TargetMeasure:
        """Cell masses of ``density`` on ``grid`` refined ``refine`` times per axis."""
        if refine < 1:
            raise ValueError(f"refine must be >= 1, got {refine}")
        q = Grid(grid.nx * refine, grid.ny * refine, grid.x0, grid.x1, grid.y0, grid.y1)
        m = cell_masses(density, q).ravel()
        x, y = q.mesh
        keep = m > 0
        pts = np.column_stack([x.ravel()[keep], y.ravel()[keep]])
        return cls(pts, m[keep] / m[keep].sum())


def swarm_l2(positions: np.ndarray, kde: KDE, smoothed_target: np.ndarray, grid: Grid) -> float:
    """``||K_h * mu_N - K_h * p_*||`` (1 / length), the discrete L2 norm of :meth:`Grid.l2`.

    Args:
        positions: Robots, shape ``(2, N)`` (length).
        kde: The loop's KDE (its bandwidth, images and evaluation method).
        smoothed_target: ``K_h * p_*`` on the grid, from :func:`smoothed_density`.
        grid: The grid.
    """
    p, _ = kde(positions)
    return grid.l2(p - smoothed_target)


def w2_method(n_robots: int, emd_max: int = EMD_MAX_ROBOTS) -> str:
    """``"emd"`` up to ``emd_max`` robots, ``"sliced"`` above."""
    return "emd" if n_robots <= emd_max else "sliced"


def _projections(n: int) -> np.ndarray:
    """``(2, n)`` unit directions at angles ``pi (j + 1/2) / n``, ``j < n``."""
    theta = np.pi * (np.arange(n) + 0.5) / n
    return np.vstack([np.cos(theta), np.sin(theta)])


def swarm_w2(
    positions: np.ndarray,
    target: TargetMeasure,
    method: str = "auto",
    n_projections: int = N_PROJECTIONS,
    emd_max: int = EMD_MAX_ROBOTS,
) -> float:
    """Optimal-transport distance between the robots and ``p_*`` (length).

    Compares the empirical measure ``mu_N`` (weight ``1/N`` at each robot) with the
    discrete target ``nu = sum_j m_j delta_{c_j}`` of :class:`TargetMeasure` (exact cell
    masses at cell centres), for the squared Euclidean cost:

    * ``emd``: ``W2(mu_N, nu) = (min_pi sum pi_kj |X_k - c_j|^2)^(1/2)`` by the network
      simplex (``ot.emd2``); memory ``8 N M`` bytes, so for ``N <= emd_max``;
    * ``sliced``: ``SW2(mu_N, nu) = ((1/P) sum_j W2^2(theta_j . mu_N, theta_j . nu))^(1/2)``
      over ``P = n_projections`` directions ``theta_j`` equispaced on the half circle
      (deterministic, no random projections), each a sorted 1-D transport
      (:func:`sliced_w2`; ``sliced_pot`` is the same through
      ``ot.sliced_wasserstein_distance``, the reference). ``SW2 <= W2``; for a
      translation by ``d`` it is ``|d| / sqrt(2)`` (``W2 = |d|``). ``O(P (N + M) log)``.
    * ``auto``: :func:`w2_method`.

    The two are different distances: compare values (and their floors, which use the
    same method) only within one method.

    On a domain with obstacles the ground cost stays the squared *Euclidean* distance,
    not the geodesic one: the target measure is ``p_*`` on free space
    (:func:`free_target_measure`) and the robots are in free space, but a transport
    plan may move mass through an obstacle at the straight-line price. So ``swarm_w2``
    is a distance between the two measures on the plane (0 exactly when the robots
    match the target's atoms) that under-prices a swarm on the wrong side of a wall: a
    robot in the wrong room costs its straight-line distance to the target's mass, not
    the way round through the door. The component metric
    (:class:`Components`) catches mass in the wrong component, which no Euclidean
    cost can.

    Args:
        positions: Robots, shape ``(2, N)`` (length).
        target: The discrete target measure.
        method: ``auto``, ``emd``, ``sliced`` (:func:`sliced_w2`) or ``sliced_pot`` (the
            same distance by ``ot.sliced_wasserstein_distance``, the reference).
        n_projections: ``P`` for ``sliced``.
        emd_max: Threshold of ``auto``.
    """
    if method not in W2_METHODS:
        raise ValueError(f"swarm_w2 method must be auto, emd, sliced or sliced_pot, got {method!r}")
    positions = np.asarray(positions, dtype=float)
    return W2_METHODS[method](positions, target, n_projections, emd_max)


def _w2_auto(
    positions: np.ndarray, target: TargetMeasure, n_projections: int, emd_max: int
) -> float:
    """The method of :func:`w2_method` for this many robots."""
    chosen = W2_METHODS[w2_method(positions.shape[1], emd_max)]
    return chosen(positions, target, n_projections, emd_max)


def _w2_emd(
    positions: np.ndarray, target: TargetMeasure, n_projections: int, emd_max: int
) -> float:
    """Exact ``W2`` by the network simplex (``ot.emd2``)."""
    import ot  # loaded by SwarmTruth where the run is built (harness.observers.swarm)

    n = positions.shape[1]
    xs = np.ascontiguousarray(positions.T)
    a = np.full(n, 1.0 / n)
    cost = ot.dist(xs, target.points, metric="sqeuclidean")
    value = ot.emd2(a, target.weights, cost, numItermax=10_000_000, check_marginals=False)
    return float(np.sqrt(max(float(value), 0.0)))


def _w2_sliced(
    positions: np.ndarray, target: TargetMeasure, n_projections: int, emd_max: int
) -> float:
    """:func:`sliced_w2`."""
    return sliced_w2(positions, target, n_projections)


def _w2_sliced_pot(
    positions: np.ndarray, target: TargetMeasure, n_projections: int, emd_max: int
) -> float:
    """The sliced distance by ``ot.sliced_wasserstein_distance`` (the reference)."""
    import ot  # as in _w2_emd

    n = positions.shape[1]
    xs = np.ascontiguousarray(positions.T)
    a = np.full(n, 1.0 / n)
    return float(
        ot.sliced_wasserstein_distance(
            xs, target.points, a, target.weights, p=2, projections=_projections(n_projections)
        )
    )


W2_METHODS: dict[str, Callable[[np.ndarray, TargetMeasure, int, int], float]] = {
    "auto": _w2_auto,
    "emd": _w2_emd,
    "sliced": _w2_sliced,
    "sliced_pot": _w2_sliced_pot,
}
"""The transport methods of :func:`swarm_w2` by name; each takes ``(positions, target,
n_projections, emd_max)``."""


def sliced_w2(
    positions: np.ndarray, target: TargetMeasure, n_projections: int = N_PROJECTIONS
) -> float:
    """Sliced ``SW2(mu_N, nu)`` (length) by prefix integrals of the target's quantile function.

    For a direction ``theta`` let ``x_(1) <= ... <= x_(N)`` be the sorted projections of
    the robots and ``G^-1`` the quantile function of the projected target (atoms
    ``y_j = theta . c_j`` of mass ``m_j``). The monotone coupling gives

        W2^2 = (1/N) sum_k x_(k)^2 + sum_j m_j y_j^2 - 2 sum_k x_(k) [I(k/N) - I((k-1)/N)],

    with ``I(t) = int_0^t G^-1``, piecewise linear between the target's cumulative
    masses (``np.interp``). Cost ``O(P N log N)`` for the sorts, against the merge of
    ``N + M`` breakpoints per direction in ``ot.wasserstein_1d``.
    """
    x = np.asarray(positions, dtype=float)
    n = x.shape[1]
    dirs = _projections(n_projections)
    # elementwise products, not BLAS: a threaded GEMM of this shape stalls on a busy host
    xp = np.sort(np.outer(dirs[0], x[0]) + np.outer(dirs[1], x[1]), axis=1)
    yp = np.outer(dirs[0], target.points[:, 0]) + np.outer(dirs[1], target.points[:, 1])
    t_grid = np.arange(n + 1) / n
    total = 0.0
    for j in range(n_projections):
        order = np.argsort(yp[j], kind="stable")
        y = yp[j, order]
        m = target.weights[order]
        cum = np.concatenate([[0.0], np.cumsum(m)])
        cum /= cum[-1]
        prefix = np.concatenate([[0.0], np.cumsum(m * y)])
        dint = np.diff(np.interp(t_grid, cum, prefix))
        w2sq = np.mean(xp[j] ** 2) + np.dot(m, y**2) - 2.0 * np.dot(xp[j], dint)
        total += max(w2sq, 0.0)
    return float(np.sqrt(total / n_projections))


@dataclass(frozen=True)
class Band:
    """Monte-Carlo distribution of a distance: mean, 2.5 and 97.5 percentiles, draws."""

    mean: float
    lo: float
    hi: float
    draws: int

    def as_dict(self) -> dict[str, float | int]:
        """Plain mapping for the log's metadata."""
        return {"mean": self.mean, "lo": self.lo, "hi": self.hi, "draws": self.draws}


def _band(values: np.ndarray) -> Band:
    lo, hi = np.percentile(values, [2.5, 97.5])
    return Band(float(values.mean()), float(lo), float(hi), int(values.size))


def floors(
    density: Density | FreeSampler,
    grid: Grid,
    kde: KDE,
    smoothed_target: np.ndarray,
    target: TargetMeasure,
    n_robots: int,
    rng: np.random.Generator,
    draws: int = 100,
    w2: str = "auto",
    n_projections: int = N_PROJECTIONS,
    window: Callable[[], AbstractContextManager[object]] = nullcontext,
) -> dict[str, Band]:
    """Finite-N floors: ``swarm_l2`` and ``swarm_w2`` of N robots drawn from ``p_*``.

    Each of ``draws`` Monte-Carlo draws places ``n_robots`` independent samples of
    ``density`` (``density.sample`` with ``rng``; on free space :class:`FreeSampler`)
    and evaluates both distances exactly as for the swarm (same KDE, same target
    measure, same transport method for this N). A swarm distributed as ``p_*`` lands
    inside ``[lo, hi]`` with probability 0.95.
    For large N, ``E swarm_l2^2 ~ int k K_h * p_* = 1 / (4 pi N h^2)`` (notes section 3).

    Args:
        density: ``p_*``.
        grid, kde, smoothed_target, target: As for :func:`swarm_l2` and :func:`swarm_w2`.
        n_robots: N.
        rng: Seeded generator (the only randomness).
        draws: Monte-Carlo count.
        w2: Transport method (``auto``: :func:`w2_method` of ``n_robots``).
        n_projections: For the sliced method.
        window: Entered around each draw: a run's stop window
            (:attr:`harness.observers.base.RunContext.window`), which raises to stop
            between draws when a stop was requested.

    Returns:
        ``{"swarm_l2": Band, "swarm_w2": Band}``.
    """
    if draws < 2:
        raise ValueError(f"floors need at least 2 draws, got {draws}")
    l2 = np.empty(draws)
    w = np.empty(draws)
    with threadpool_limits(1):  # small BLAS calls on many threads stall on a busy host
        for i in range(draws):
            with window():
                x = density.sample(n_robots, grid, rng)
                l2[i] = swarm_l2(x, kde, smoothed_target, grid)
                w[i] = swarm_w2(x, target, w2, n_projections)
    return {"swarm_l2": _band(l2), "swarm_w2": _band(w)}


# --- free space (a domain with obstacles) ---------------------------------------------

SAMPLE_TRIES = 64
"""Rounds of rejection against the robots' raster when drawing a robot in a free cell
(:class:`FreeSampler`); one still blocked after them is put at its cell's centre."""


def _raster_blocked(x: np.ndarray, y: np.ndarray, free: FreeSpace) -> np.ndarray:
    """Whether each point ``(x, y)`` lies in a blocked square of the robots' raster
    (``free.raster``: row along y, side ``L / r`` from the grid's origin).
    """
    g = free.grid
    r = free.raster.shape[0]
    col = np.clip(((x - g.x0) / (g.x1 - g.x0) * r).astype(np.intp), 0, r - 1)
    row = np.clip(((y - g.y0) / (g.y1 - g.y0) * r).astype(np.intp), 0, r - 1)
    return free.raster[row, col].astype(bool)


@dataclass(frozen=True)
class FreeSampler:
    """``p_*`` on free space as the law of one robot, for the finite-N floors.

    A robot falls in free cell ``c`` with probability ``p_*(c) dx dy`` (the target's
    cell values, 0 on blocked cells and of unit mass on free ones,
    :meth:`harness.domains.base.FreeSpace.restrict`) and is uniform on the part of the
    cell that the robots' raster marks free (rejection, :data:`SAMPLE_TRIES` rounds; a
    robot still blocked after them sits at the cell's centre, which is free space by the
    definition of a free cell). So no robot is drawn inside an obstacle, and the cell
    masses of the law are exactly the target's.

    Attributes:
        p: The target's cell values ``(ny, nx)`` (1 / length^2).
        free: Free space.
    """

    p: np.ndarray
    free: FreeSpace

    def sample(self, n: int, grid: Grid, rng: np.random.Generator) -> np.ndarray:
        """``n`` positions, shape ``(2, n)`` (row 0: x, row 1: y)."""
        masses = np.where(self.free.cells, self.p, 0.0).ravel() * grid.cell_area
        cells = rng.choice(masses.size, size=n, p=masses / masses.sum())
        row, col = np.divmod(cells, grid.nx)
        x = np.empty(n)
        y = np.empty(n)
        todo = np.arange(n)
        for _ in range(SAMPLE_TRIES):
            u = rng.random((2, todo.size))
            x[todo] = grid.x0 + (col[todo] + u[0]) * grid.dx
            y[todo] = grid.y0 + (row[todo] + u[1]) * grid.dy
            todo = todo[_raster_blocked(x[todo], y[todo], self.free)]
            if todo.size == 0:
                break
        x[todo] = grid.x[col[todo]]
        y[todo] = grid.y[row[todo]]
        return np.vstack([x, y])


def free_target_measure(
    p: np.ndarray, free: FreeSpace, grid: Grid, refine: int = 1
) -> TargetMeasure:
    """``p_*`` on free space as a discrete measure for transport.

    Each free cell of the simulation grid (``free.grid``) carries its mass ``p_*(c) dx
    dy``, split evenly over the centres of its ``refine x refine`` sub-squares that the
    robots' raster marks free (all of them when none is; with ``refine = 1`` the cell's
    centre, free by the definition of a free cell): the law :class:`FreeSampler` draws
    from, with the mass of each sub-square moved to its centre. When ``grid`` (the
    measure's grid, :func:`harness.observers.swarm.measure_grid`) is coarser than the
    simulation grid refined ``refine`` times, the atoms are merged per cell of ``grid``
    refined ``refine`` times, at their mass-weighted centroid (inside the convex hull of
    free points, where a cell's centre could lie in an obstacle).
    """
    fine = free.grid
    masses = np.where(free.cells, p, 0.0) * fine.cell_area
    row, col = np.nonzero(free.cells & (masses > 0))
    mass = masses[row, col]
    offsets = (np.arange(refine) + 0.5) / refine
    ox, oy = np.meshgrid(offsets, offsets, indexing="xy")
    x = fine.x0 + (col[:, None] + ox.ravel()[None, :]) * fine.dx  # (cells, refine^2)
    y = fine.y0 + (row[:, None] + oy.ravel()[None, :]) * fine.dy
    if refine > 1:
        open_ = ~_raster_blocked(x, y, free)
        open_[~open_.any(axis=1)] = True  # a cell whose sub-centres are all blocked keeps them
    else:
        open_ = np.ones(x.shape, dtype=bool)
    share = open_ / open_.sum(axis=1, keepdims=True)
    w = (mass[:, None] * share)[open_]
    px, py = x[open_], y[open_]
    nx, ny = grid.nx * refine, grid.ny * refine
    if nx < fine.nx * refine or ny < fine.ny * refine:
        bx = np.minimum(((px - grid.x0) / (grid.x1 - grid.x0) * nx).astype(np.intp), nx - 1)
        by = np.minimum(((py - grid.y0) / (grid.y1 - grid.y0) * ny).astype(np.intp), ny - 1)
        key = by * nx + bx
        total = np.bincount(key, w, nx * ny)
        keep = total > 0
        cx = np.bincount(key, w * px, nx * ny)[keep] / total[keep]
        cy = np.bincount(key, w * py, nx * ny)[keep] / total[keep]
        px, py, w = cx, cy, total[keep]
    return TargetMeasure(np.column_stack([px, py]), w / w.sum())


class FreeCells:
    """The free cell of the control grid that holds each robot.

    A robot belongs to the cell that holds it; a robot in a blocked cell (a cell less
    than half free still has free space the robots' raster lets them reach) to the free
    cell whose centre is nearest to it.

    Args:
        free: Free space.
    """

    def __init__(self, free: FreeSpace) -> None:
        from scipy.spatial import cKDTree

        self.free = free
        g = free.grid
        self._rows, self._cols = np.nonzero(free.cells)
        self._tree = cKDTree(np.column_stack([g.x[self._cols], g.y[self._rows]]))

    def cells_of(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The row and column of each robot's free cell, each of shape ``(N,)``."""
        g = self.free.grid
        x, y = np.asarray(positions[0], dtype=float), np.asarray(positions[1], dtype=float)
        col = np.clip(((x - g.x0) / g.dx).astype(np.intp), 0, g.nx - 1)
        row = np.clip(((y - g.y0) / g.dy).astype(np.intp), 0, g.ny - 1)
        lost = np.flatnonzero(~self.free.cells[row, col])
        if lost.size:
            _, nearest = self._tree.query(np.column_stack([x[lost], y[lost]]))
            row[lost], col[lost] = self._rows[nearest], self._cols[nearest]
        return row, col


class Components(FreeCells):
    """The robots in each connected component of free space against the target's mass
    there.

    A robot belongs to the component of its free cell (:class:`FreeCells`: the cell
    that holds it, or for a robot in a blocked cell the free cell whose centre is
    nearest). ``gap`` is ``max_c |robots' fraction in c - p_*'s mass in c|``
    (dimensionless, in ``[0, 1]``): 0 when every component holds its share of the swarm,
    1 when the whole swarm sits in a component the target gives no mass.

    Args:
        p: The target's cell values (1 / length^2; 0 on blocked cells).
        free: Free space.
    """

    def __init__(self, p: np.ndarray, free: FreeSpace) -> None:
        super().__init__(free)
        g = free.grid
        labels = free.labels
        self.n = free.n_components
        total = np.bincount(labels[free.cells], np.asarray(p)[free.cells] * g.cell_area, self.n)
        self.masses = total / total.sum()

    def of(self, positions: np.ndarray) -> np.ndarray:
        """The component of each robot, shape ``(N,)``."""
        return self.free.labels[self.cells_of(positions)]

    def fractions(self, positions: np.ndarray) -> np.ndarray:
        """The fraction of the robots in each component, shape ``(n_components,)``."""
        n = positions.shape[1]
        return np.bincount(self.of(positions), minlength=self.n)[: self.n] / n

    def gap(self, fractions: np.ndarray) -> float:
        """``max_c |fractions[c] - masses[c]|`` (dimensionless)."""
        return float(np.max(np.abs(np.asarray(fractions) - self.masses)))


SUPPORT_MASS = 1e-12
"""The least mass of the initial density a cell holds to be in its support
(:class:`StartRegion`): above the round-off of a cell that only touches the edge of a
box."""


class StartRegion(FreeCells):
    """The robots still in the region where the swarm started, against the target's
    mass there.

    The region ``S`` is the support of the initial density on the control grid: the
    free cells that hold more than :data:`SUPPORT_MASS` of its mass (for
    ``init=left_room`` the cells that the box ``[0.08, 0.42] x [0.15, 0.85]`` overlaps;
    a cell that only touches a box's edge holds round-off, not mass). A robot is in
    ``S`` when its free cell is (:class:`FreeCells`).

    * :meth:`fraction`: ``#{k : X_k in S} / N`` (dimensionless, in ``[0, 1]``), 1 at the
      start;
    * ``target_mass``: ``sum_{c in S} p_*(c) dx dy`` over the target on free space
      (unit mass there; dimensionless): the fraction a swarm distributed as ``p_*``
      keeps in ``S``.

    Args:
        init: The initial density's cell values on the control grid (1 / length^2).
        p: The target's cell values (1 / length^2; 0 on blocked cells).
        free: Free space.

    Attributes:
        region: ``(ny, nx)`` booleans, the cells of ``S``.
        target_mass: ``p_*``'s mass in ``S`` (dimensionless).

    Raises:
        ValueError: when the initial density has no mass on a free cell.
    """

    def __init__(self, init: np.ndarray, p: np.ndarray, free: FreeSpace) -> None:
        super().__init__(free)
        mass = np.asarray(init, dtype=float) * free.grid.cell_area
        self.region = free.cells & (mass > SUPPORT_MASS)
        if not self.region.any():
            raise ValueError("init: an initial density with mass on a free cell")
        self.target_mass = self.mass_of(p)

    def mass_of(self, p: np.ndarray) -> float:
        """``p``'s mass in the region over its mass on free space (dimensionless)."""
        p = np.asarray(p)
        return float(p[self.region].sum() / p[self.free.cells].sum())

    def fraction(self, positions: np.ndarray) -> float:
        """The fraction of the robots in the region (dimensionless)."""
        return float(self.region[self.cells_of(positions)].mean())
