"""Optimal-transport deployment (config group ``control``): every period, the robots are
assigned to ``N`` fixed points of the target by an optimal assignment, and each heads for
its point (:class:`AssignmentControl`, ``control=ot``).

The functions hold the pieces: :func:`quantise` (the target's points),
:func:`exact_assignment` (the dense network simplex, up to :data:`EXACT_MAX` robots),
:func:`large_assignment` (above: a sparse network simplex with column generation,
certified optimal when it converges) and :func:`assign`, which picks between them.

Reference:
    V. Krishnan and S. Martínez, "Distributed optimal transport for the deployment of
    swarms", IEEE Conference on Decision and Control 2018, arXiv 1804.01572.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import ot
import scipy.sparse as sp
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from harness.compiled.assignment import violations as compiled_violations
from harness.control.guidance import target_masses
from harness.control.waypoints import PeriodClock, steer
from harness.grid import Grid
from harness.parameters import integer, number, speed_cap
from harness.protocols import MemoryEstimate, default_memory
from harness.records import Command, ControlInput
from harness.targets.densities import Target

EXACT_MAX = 4096
"""Most robots assigned by the dense network simplex (:func:`exact_assignment`); above,
:func:`large_assignment`."""


SEED_STREAM = 5
"""The law's random stream: ``np.random.default_rng([seed, 5])``."""


COARSE_SIDE = 32
"""Cells per side of the coarse grid of :func:`coarse_assignment`."""


NEIGHBOURS = 8
"""Nearest points of each robot, and nearest robots of each point, among the first edges of
:func:`large_assignment`."""


ROUNDS = 4
"""Most sparse solves of :func:`large_assignment` (each after a column-generation check)."""


QUICK_ROUNDS = 2
"""Rounds :func:`assign` gives :func:`large_assignment` from the last period's assignment
before the dense simplex, up to :data:`EXACT_MAX` robots."""


PER_ROW = 8
"""Most violating edges a robot adds per round of :func:`large_assignment`."""


DENSE_BYTES_PER_PAIR = 48
"""Peak memory of :func:`exact_assignment` per robot-point pair (bytes): the cost matrix,
the plan and the network simplex's arcs (measured: 655 MB above the interpreter at
4096 robots, 40 bytes per pair, rounded up)."""


SPARSE_BYTES_PER_ROBOT = 16384
"""Peak memory of :func:`large_assignment` per robot (bytes; its edges, trees and the
solver's arcs; measured: 250 MB above the interpreter for 16384 robots crossing the
domain, 4 rounds, 15 kB per robot)."""


CHECK_BLOCK = 1 << 22
"""Reduced costs evaluated at once by :func:`violations_reference` (32 MB of float64)."""


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


def squared_distances(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``|x_i - y_j|^2`` for ``x`` ``(n, 2)`` and ``y`` ``(m, 2)``: ``(n, m)`` (length^2),
    from the coordinate differences (no cancellation, never negative).
    """
    out = np.subtract.outer(x[:, 0], y[:, 0])
    out *= out
    dy = np.subtract.outer(x[:, 1], y[:, 1])
    dy *= dy
    out += dy
    return out


def transport_cost(x: np.ndarray, y: np.ndarray, perm: np.ndarray) -> float:
    """``sum_i |x_i - y_{perm_i}|^2`` (length^2) of an assignment."""
    d = x - y[perm]
    return float(np.einsum("ij,ij->", d, d))


def _is_permutation(perm: np.ndarray, n: int) -> bool:
    return perm.shape == (n,) and bool(np.bincount(perm, minlength=n).max(initial=0) <= 1)


def exact_assignment(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The optimal assignment of robots ``x`` to points ``y`` (both ``(n, 2)``) for the
    squared Euclidean cost: ``perm`` with robot ``i`` at point ``perm[i]`` minimising
    ``sum_i |x_i - y_{perm_i}|^2``.

    By POT's dense network simplex (``ot.emd``) with unit masses on both sides. The
    assignment polytope's vertices are the permutation matrices (Birkhoff), and the
    simplex returns a vertex, so the plan holds one entry 1 per row; it is read as each
    row's largest entry and accepted when that is a permutation with entries above 1/2
    and the solver reports optimality. Otherwise (not seen in testing) the assignment
    comes from ``scipy.optimize.linear_sum_assignment``, exact too. Why the simplex
    first: both are exact, and on transport-like problems (a swarm moving across the
    domain) ``linear_sum_assignment`` took 0.36 s at ``n = 1024`` and 28.5 s at 4096
    against the simplex's 0.13 s and 3.0 s, while near the assignment's fixed point (each
    robot near its point) it took 7 ms against 74 ms at 1024 (0.30 s against 1.3 s at
    4096); the simplex's worst case is the one that bounds a run.
    """
    n = x.shape[0]
    if n <= 1:
        return np.zeros(n, dtype=np.intp)
    cost = squared_distances(x, y)
    ones = np.ones(n)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # non-optimal exit: checked below
        plan, log = ot.emd(ones, ones, cost, numItermax=100_000_000, log=True)
    perm = np.argmax(plan, axis=1)
    ok = log["result_code"] == 1 and _is_permutation(perm, n)
    if ok and plan[np.arange(n), perm].min() > 0.5:
        return perm
    _, perm = linear_sum_assignment(cost)
    return np.asarray(perm, dtype=np.intp)


def coarse_assignment(
    grid: Grid, x: np.ndarray, y: np.ndarray, side: int = COARSE_SIDE
) -> np.ndarray:
    """An assignment from an exact transport between cells of a coarse grid: a cheap,
    good start for :func:`large_assignment`.

    1. The robots and the points are counted in the cells of a ``side x side`` grid
       over the domain, and the counts are transported exactly (network simplex) for the
       squared distance between the cells' centroids; with integer counts the optimal
       plan is integral (the transport polytope's vertices are), ``T_AB`` robots from
       cell ``A`` to cell ``B``.
    2. The robots of each cell ``A`` are split among its plan's cells ``B`` (``T_AB``
       each) by an exact transport to those cells' centroids.
    3. In each cell ``B`` the robots routed there are assigned exactly to its points
       (:func:`exact_assignment`).

    Against the exact assignment at 4096 robots (``python -m benchmarks.law_costs
    --solve``): close to its cost for a swarm crossing the domain, but far above it near
    the fixed point, where the exact cost is tiny and the cells' centroids too coarse;
    the sparse stage of :func:`large_assignment` removes that.
    """
    n = x.shape[0]
    m = side * side

    def cell(z: np.ndarray) -> np.ndarray:
        cx = np.clip(
            ((z[:, 0] - grid.x0) / (grid.x1 - grid.x0) * side).astype(np.intp), 0, side - 1
        )
        cy = np.clip(
            ((z[:, 1] - grid.y0) / (grid.y1 - grid.y0) * side).astype(np.intp), 0, side - 1
        )
        return cy * side + cx

    a_cell, b_cell = cell(x), cell(y)
    a = np.bincount(a_cell, minlength=m).astype(float)
    b = np.bincount(b_cell, minlength=m).astype(float)
    centre_a = (
        np.stack([np.bincount(a_cell, x[:, c], m) for c in range(2)], 1) / np.maximum(a, 1)[:, None]
    )
    centre_b = (
        np.stack([np.bincount(b_cell, y[:, c], m) for c in range(2)], 1) / np.maximum(b, 1)[:, None]
    )
    ia, ib = np.flatnonzero(a), np.flatnonzero(b)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        plan = ot.emd(
            a[ia], b[ib], squared_distances(centre_a[ia], centre_b[ib]), numItermax=100_000_000
        )
    flows = np.rint(plan).astype(np.intp)
    if not (
        np.array_equal(flows.sum(1), a[ia].astype(np.intp))
        and np.array_equal(flows.sum(0), b[ib].astype(np.intp))
    ):
        return np.arange(n)  # not integral (not seen): any permutation is a valid start
    by_a = np.argsort(a_cell, kind="stable")
    start_a = np.concatenate([[0], np.cumsum(a).astype(np.intp)])
    by_b = np.argsort(b_cell, kind="stable")
    start_b = np.concatenate([[0], np.cumsum(b).astype(np.intp)])
    routed = np.empty(n, dtype=np.intp)
    for row, ca in enumerate(ia):
        robots = by_a[start_a[ca] : start_a[ca + 1]]
        to = np.flatnonzero(flows[row])
        if to.size == 1:
            routed[robots] = ib[to[0]]
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            split = ot.emd(
                np.ones(robots.size),
                flows[row, to].astype(float),
                squared_distances(x[robots], centre_b[ib[to]]),
            )
        routed[robots] = ib[to[np.argmax(split, axis=1)]]
    if not np.array_equal(np.bincount(routed, minlength=m), b.astype(np.intp)):
        return np.arange(n)
    perm = np.empty(n, dtype=np.intp)
    by_route = np.argsort(routed, kind="stable")
    for cb in ib:
        robots = by_route[start_b[cb] : start_b[cb + 1]]
        points = by_b[start_b[cb] : start_b[cb + 1]]
        perm[robots] = points[exact_assignment(x[robots], y[points])]
    return perm


@dataclass(frozen=True)
class LargeAssignment:
    """What :func:`large_assignment` found.

    Attributes:
        perm: The assignment (robot ``i`` to point ``perm[i]``).
        certified: Whether the dual check over all pairs proved it optimal.
        rounds: Sparse solves made.
        edges: Robot-point pairs in the last sparse problem.
    """

    perm: np.ndarray
    certified: bool
    rounds: int
    edges: int


def violations(
    x: np.ndarray, y: np.ndarray, u: np.ndarray, w: np.ndarray, tol: float, per_row: int
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(i, j)`` of negative reduced cost ``|x_i - y_j|^2 - u_i - w_j < -tol``,
    at most ``per_row`` per robot (the most negative), as ``(rows, cols)``, over all
    pairs in one compiled pass (:func:`harness.compiled.assignment.violations`; 0.65 s
    at 16384 robots on two cores, against 5.9 s for :func:`violations_reference`).
    """
    n = x.shape[0]
    cols = np.empty((n, per_row), dtype=np.intp)
    vals = np.empty((n, per_row))
    compiled_violations(
        np.ascontiguousarray(x, dtype=float),
        np.ascontiguousarray(y, dtype=float),
        np.ascontiguousarray(u, dtype=float),
        np.ascontiguousarray(w, dtype=float),
        float(tol),
        cols,
        vals,
    )
    rows = np.broadcast_to(np.arange(n)[:, None], cols.shape)
    keep = cols >= 0
    return rows[keep], cols[keep]


def violations_reference(
    x: np.ndarray, y: np.ndarray, u: np.ndarray, w: np.ndarray, tol: float, per_row: int
) -> tuple[np.ndarray, np.ndarray]:
    """Numpy statement of :func:`violations` (the same pairs), in row blocks of
    :data:`CHECK_BLOCK` values.
    """
    n = x.shape[0]
    block = max(1, CHECK_BLOCK // max(n, 1))
    rows, cols = [], []
    for s in range(0, n, block):
        r = squared_distances(x[s : s + block], y)
        r -= u[s : s + block, None]
        r -= w[None, :]
        bad = np.flatnonzero((r < -tol).any(axis=1))
        if bad.size == 0:
            continue
        r = r[bad]
        k = min(per_row, n)
        idx = np.argpartition(r, k - 1, axis=1)[:, :k]
        take = np.take_along_axis(r, idx, axis=1) < -tol
        rows.append(np.broadcast_to((s + bad)[:, None], idx.shape)[take])
        cols.append(idx[take])
    if not rows:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    return np.concatenate(rows), np.concatenate(cols)


def large_assignment(
    grid: Grid,
    x: np.ndarray,
    y: np.ndarray,
    start: np.ndarray | None = None,
    rounds: int = ROUNDS,
) -> LargeAssignment:
    """An assignment of robots ``x`` to points ``y`` (both ``(n, 2)``) without the dense
    cost matrix; optimal when ``certified``.

    Column generation on the assignment's network simplex:

    1. Edges: each robot to its :data:`NEIGHBOURS` nearest points, each point to its
       nearest robots, and the pairs of a start assignment, which makes the sparse
       problem feasible and its optimum at most the start's cost: ``start`` when given
       (the last period's), else :func:`coarse_assignment`.
    2. The sparse problem is solved exactly by POT's sparse network simplex, which also
       gives dual potentials ``u`` (robots) and ``w`` (points), ``u_i + w_j <= c_ij`` on
       the edges with equality on the assignment.
    3. Over all ``n^2`` pairs (:func:`violations`, one compiled pass), the reduced costs
       ``c_ij - u_i - w_j``: if none is below ``-2e-9 L^2`` (``L`` the domain's side),
       ``(u, w)`` is feasible for the full dual and the assignment is optimal for the
       full problem (LP duality: certified). Otherwise each robot's :data:`PER_ROW` most
       negative pairs join the edges (and, after a first round from ``start``, the pairs
       of :func:`coarse_assignment`), and step 2 repeats, up to ``rounds`` solves.

    Accuracy against :func:`exact_assignment`, on the default target's points
    (``python -m benchmarks.law_costs --solve``): a settled swarm (each robot within
    0.005 of its point) is certified optimal in 1 round at ``n = 1024`` and 2 at 4096; a
    swarm crossing the domain (uniform on ``[0.15, 0.85]^2``) stops uncertified after 4
    rounds at 1.0004 times the optimal cost at 1024 and 1.0022 times at 4096 (the coarse
    start alone: 1.016). Time at 16384 robots (two shared cores): 1.5 s settled
    (certified in 2 rounds), 16 s crossing (4 rounds, most of it in the sparse
    simplex).

    Args:
        grid: The grid (its rectangle, for :func:`coarse_assignment`).
        x: Robots ``(n, 2)`` (length).
        y: Points ``(n, 2)`` (length).
        start: A previous assignment to start from, or None.
        rounds: Most sparse solves.
    """
    n = x.shape[0]
    coarse_added = start is None or not _is_permutation(start, n)
    first = coarse_assignment(grid, x, y) if coarse_added else start
    assert first is not None
    k = min(NEIGHBOURS, n)
    _, near_points = cKDTree(y).query(x, k)
    _, near_robots = cKDTree(x).query(y, k)
    robots = np.arange(n)
    r = np.concatenate([np.repeat(robots, k), np.asarray(near_robots).ravel(), robots])
    c = np.concatenate([np.asarray(near_points).ravel(), np.repeat(robots, k), first])
    keys = np.unique(r * n + c)
    ones = np.ones(n)
    side = max(grid.x1 - grid.x0, grid.y1 - grid.y0)
    tol = 2e-9 * side * side
    perm, certified, done = first, False, 0
    while done < rounds:
        done += 1
        rr, cc = np.divmod(keys, n)
        d = x[rr] - y[cc]
        cost = sp.coo_matrix((np.einsum("ij,ij->i", d, d), (rr, cc)), shape=(n, n))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            plan, log = ot.emd(ones, ones, cost, numItermax=100_000_000, log=True)
        plan = sp.coo_matrix(plan)
        take = plan.data > 0.5
        candidate = np.full(n, -1, dtype=np.intp)
        candidate[plan.row[take]] = plan.col[take]
        if log["result_code"] != 1 or take.sum() != n or not _is_permutation(candidate, n):
            break  # keep the last assignment (not seen)
        perm = candidate
        u, w = np.asarray(log["u"], dtype=float), np.asarray(log["v"], dtype=float)
        bad_r, bad_c = violations(x, y, u, w, tol, PER_ROW)
        if bad_r.size == 0:
            certified = True
            break
        new = [bad_r * n + bad_c]
        if not coarse_added:
            new.append(robots * n + coarse_assignment(grid, x, y))
            coarse_added = True
        keys = np.union1d(keys, np.concatenate(new))
    return LargeAssignment(perm, certified, done, int(keys.size))


def assign(
    grid: Grid, x: np.ndarray, y: np.ndarray, previous: np.ndarray | None = None
) -> np.ndarray:
    """Robots ``x`` to points ``y`` (both ``(n, 2)``), optimal up to :data:`EXACT_MAX`
    robots.

    Up to :data:`EXACT_MAX`: when the robots are still near the points of a previous
    assignment (root mean square distance below the points' spacing ``sqrt(|Omega| /
    n)``: a settled swarm), first :func:`large_assignment` from it with
    :data:`QUICK_ROUNDS` rounds, kept when certified optimal (10 ms against the dense
    simplex's 90 ms for a settled swarm at ``n = 1024``); else, and when not certified,
    :func:`exact_assignment`. Above: :func:`large_assignment` (from ``previous`` when
    given). Either way the result is optimal up to :data:`EXACT_MAX`; the test of
    settledness only picks the faster route.
    """
    n = x.shape[0]
    if n <= EXACT_MAX:
        spacing2 = (grid.x1 - grid.x0) * (grid.y1 - grid.y0) / n
        if (
            previous is not None
            and previous.shape == (n,)
            and transport_cost(x, y, previous) < n * spacing2
        ):
            quick = large_assignment(grid, x, y, previous, QUICK_ROUNDS)
            if quick.certified:
                return quick.perm
        return exact_assignment(x, y)
    return large_assignment(grid, x, y, previous).perm


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

    (:func:`assign`: exact up to :data:`EXACT_MAX` robots, above it certified-optimal
    when the column generation of :func:`large_assignment` converges within its rounds),
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
        self.period = number("period", period, 0.0, strict=True)
        self.seed = integer("seed", seed, 0)
        self.v_max = speed_cap(v_max)
        rng = np.random.default_rng([self.seed, SEED_STREAM])
        self.points = quantise(self.grid, target_masses(target), self.robots, rng)
        self.clock = PeriodClock(self.period)
        self.assignment: np.ndarray | None = None

    @classmethod
    def memory_estimate(cls, grid: Grid, robots: Any = 1, **params: Any) -> MemoryEstimate:
        """The assignment's peak: :data:`DENSE_BYTES_PER_PAIR` per pair up to
        :data:`EXACT_MAX` robots, :data:`SPARSE_BYTES_PER_ROBOT` per robot above; plus
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
        if starts or self.assignment is None:
            x = np.ascontiguousarray(positions.T)
            y = np.ascontiguousarray(self.points.T)
            self.assignment = assign(self.grid, x, y, self.assignment)
        goals = self.points[:, self.assignment]
        return steer(self.grid, positions, goals, self.clock.time_left(inp.t), self.v_max)

    def feedback_diffusivity(self, p0: np.ndarray) -> None:
        """None: the law is no held velocity field of the estimate, so the sampled-data
        bound of :func:`harness.control.field.sampled_data_dt_bound` does not apply (the run
        says it is not checked).
        """
        return None
