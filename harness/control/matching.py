"""The assignment problem of optimal-transport deployment (:mod:`harness.control.assignment`):
which robot goes to which of ``N`` points so that the sum of squared distances is least.

:func:`exact_assignment` solves it by the dense network simplex up to :data:`EXACT_MAX`
robots; :func:`large_assignment` above, by a sparse network simplex on a few nearest
edges per robot with column generation (certified optimal when no reduced cost is
negative, :func:`violations`, :func:`violations_reference` the plain statement);
:func:`assign` picks between them.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import ot
import scipy.sparse as sp
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from harness.compiled.assignment import violations as compiled_violations
from harness.grid import Grid

EXACT_MAX = 4096
"""Most robots assigned by the dense network simplex (:func:`exact_assignment`); above,
:func:`large_assignment`."""


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
    return assignment_of_cost(squared_distances(x, y))


def assignment_of_cost(cost: np.ndarray) -> np.ndarray:
    """The optimal assignment for the cost matrix ``cost`` ``(n, n)`` (robot ``i`` at
    point ``perm[i]`` minimising ``sum_i cost[i, perm_i]``), by the dense network simplex
    with the exact fallback of :func:`exact_assignment`.
    """
    n = cost.shape[0]
    if n <= 1:
        return np.zeros(n, dtype=np.intp)
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
