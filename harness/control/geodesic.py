"""Shortest paths in free space on the cell graph (``control=ot`` on a domain with
obstacles, :class:`harness.control.assignment.AssignmentControl`).

The graph: the free cells (:class:`harness.domains.base.FreeSpace`), joined to their
4-neighbours through open faces (edge length ``dx`` or ``dy``: the segment between the
two centres is free, :mod:`harness.domains.base`), and to their diagonal neighbours
(length ``sqrt(dx^2 + dy^2)``) where the four faces of the ``2 x 2`` block are open and
the diagonal segment meets no blocked square of the robots' raster
(:func:`harness.control.free_space.segments_blocked`). The geodesic distance ``D(a, b)``
between cells is the length of the shortest path between their centres on this graph
(Dijkstra, :func:`scipy.sparse.csgraph.dijkstra`): with the diagonals, at most
``2 / sqrt(2 + sqrt(2)) - 1 = 8.2 %`` above the straight distance where nothing is in the
way, and every path a polyline of free segments between cell centres.

What it costs: one Dijkstra from each cell that holds a point of the target's
quantisation, made once when the law is built: ``O(S M log M)`` time and ``12 S M``
bytes for ``S`` such cells of ``M`` (distances in float64, predecessors in int32).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from harness.control.free_space import centres, segments_blocked
from harness.domains.base import FreeSpace
from harness.velocity import cap_vectors


def cell_graph(free: FreeSpace) -> sp.csr_matrix:
    """The symmetric ``(M, M)`` graph of free cells (the module docstring), edge weights
    the distances between centres (length).
    """
    g = free.grid
    idx = np.arange(g.size).reshape(g.shape)
    rows = [idx[:, :-1][free.face_x], idx[:-1, :][free.face_y]]
    cols = [idx[:, 1:][free.face_x], idx[1:, :][free.face_y]]
    weights = [np.full(int(free.face_x.sum()), g.dx), np.full(int(free.face_y.sum()), g.dy)]
    # 2 x 2 blocks with their four faces open: bottom, top (x faces), left, right (y faces)
    block = free.face_x[:-1, :] & free.face_x[1:, :] & free.face_y[:, :-1] & free.face_y[:, 1:]
    diagonal = float(np.hypot(g.dx, g.dy))
    for a, b in (
        (idx[:-1, :-1][block], idx[1:, 1:][block]),
        (idx[:-1, 1:][block], idx[1:, :-1][block]),
    ):
        ok = ~segments_blocked(free, centres(g, a), centres(g, b)) if a.size else a.astype(bool)
        rows.append(a[ok])
        cols.append(b[ok])
        weights.append(np.full(int(ok.sum()), diagonal))
    r, c, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(weights)
    graph = sp.coo_matrix(
        (np.concatenate([w, w]), (np.concatenate([r, c]), np.concatenate([c, r]))),
        shape=(g.size, g.size),
    )
    return graph.tocsr()


class Geodesics:
    """Shortest paths on the cell graph from a set of source cells.

    Args:
        free: Free space.
        sources: Flat free cells to measure from (repeats allowed).

    Attributes:
        sources: The distinct source cells, sorted.
        distance: ``(S, M)`` ``D(source, cell)`` (length; ``inf`` in another component
            or at a blocked cell).
        predecessor: ``(S, M)`` int32: the next cell from each cell toward the source
            (the source itself at the source; -9999 where unreachable).
    """

    def __init__(self, free: FreeSpace, sources: np.ndarray) -> None:
        self.free = free
        self.sources = np.unique(np.asarray(sources, dtype=np.intp))
        graph = cell_graph(free)
        dist, pred = dijkstra(graph, directed=False, indices=self.sources, return_predecessors=True)
        self.distance = dist
        self.predecessor = pred.astype(np.int32)
        rows = np.arange(self.sources.size)
        self.predecessor[rows, self.sources] = self.sources

    def row(self, cells: np.ndarray) -> np.ndarray:
        """The row of :attr:`distance` of each source cell in ``cells``."""
        return np.searchsorted(self.sources, cells)

    def paths(self, start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The cells of the shortest path from each ``start`` to its ``end`` (a source),
        both included: ``(cells, count)``, ``cells`` ``(n, K)`` padded with ``end``
        (``count`` cells each, 0 where ``end`` cannot be reached).
        """
        row = self.row(end)
        reachable = np.isfinite(self.distance[row, start])
        cur = np.where(reachable, start, end)
        seq = [cur]
        while (cur != end).any():
            cur = np.where(cur == end, end, self.predecessor[row, cur])
            seq.append(cur)
        cells = np.stack(seq, axis=1)
        count = np.where(reachable, 1 + (cells[:, 1:] != cells[:, :-1]).sum(axis=1), 0)
        return cells, count


class Routes:
    """Each robot's way to its goal along a shortest path of the cell graph, and the
    velocity that follows it (``control=ot`` on free space).

    The way: the polyline from the robot's position through the centres of the cells
    of its path (:meth:`Geodesics.paths`) to its goal; the first centre is left out when
    the segment from the robot to the second is free on the raster, and the last when
    the segment from the one before it to the goal is (so a robot does not turn back to
    its own cell's centre). Segments between centres are free (the graph's edges); the
    segments to and from the end points are free when checked so, else they go through
    the end cells' centres, and a robot in the free part of a blocked cell, or one whose
    first segment to its cell's centre an obstacle clips, reflects off it (the plant).

    The velocity (:meth:`velocity`): toward the current waypoint ``w`` at the speed
    ``(|x - w| + rest) / tau``, ``rest`` the length of the way beyond ``w`` and ``tau`` the
    time left in the period, so the robot covers its whole way by the period's end; a
    step that would pass ``w`` ends on it instead (``(w - x) / h``, ``h`` the step) and
    the robot heads for the next waypoint from the next call on. So without noise and
    without a binding cap the robot moves along its polyline and never cuts a corner
    (the polyline is its path up to round-off), at the last waypoint, its goal, exactly
    as :func:`harness.control.waypoints.steer` (``(g - x) / tau``). At a run's first call
    the step is not known yet (0): no step ends on a waypoint there. Unreachable goals
    (another component of free space) hold the robot (velocity 0).
    """

    def __init__(
        self,
        geodesics: Geodesics,
        positions: np.ndarray,
        here: np.ndarray,
        goals: np.ndarray,
        goal_cells: np.ndarray,
    ) -> None:
        g = geodesics.free.grid
        free = geodesics.free
        cells, count = geodesics.paths(here, goal_cells)
        n, k = cells.shape
        ways = np.full((n, k + 2, 2), np.nan)
        ways[:, 0] = positions.T
        ways[:, 1 : k + 1] = np.moveaxis(centres(g, cells.ravel()).reshape(2, n, k), 0, 2)
        robots = np.arange(n)
        last = np.maximum(count, 1) + 1  # index of the goal
        ways[robots, last] = goals.T
        skip = np.zeros((n, k + 2), dtype=bool)
        skip[:, 0] = True  # the start is where the robot is
        # leave out the first centre when the way past it is free
        second = np.minimum(2, last)
        ok = ~segments_blocked(free, positions, ways[robots, second].T)
        skip[robots[ok], 1] = True
        # and the last centre when the way to the goal from the point before it is free
        final = last - 1  # index of the last centre
        before = np.where((final - 1 == 1) & skip[:, 1], 0, final - 1)
        ok = (final >= 2) & ~segments_blocked(free, ways[robots, before].T, goals)
        skip[robots[ok], final[ok]] = True
        skip[np.arange(k + 2)[None, :] > last[:, None]] = True
        self.ways, self.skip, self.last = ways, skip, last
        self.reachable = count > 0
        # rest[i, j]: length of the way from waypoint j (kept) to the goal
        rest = np.zeros((n, k + 2))
        following = ways[robots, last]
        length = np.zeros(n)
        for j in range(k + 1, -1, -1):
            kept = ~skip[:, j] | (j == 0)
            here_j = ways[:, j]
            step = np.sqrt(((following - here_j) ** 2).sum(axis=1))
            live = kept & (j < last)
            length = np.where(live, length + np.nan_to_num(step), length)
            following = np.where(live[:, None], here_j, following)
            rest[:, j] = length
        self.rest = rest
        self.current = self.next_kept(np.zeros(n, dtype=np.intp))
        self.landing = np.zeros(n, dtype=bool)

    def next_kept(self, index: np.ndarray) -> np.ndarray:
        """The first waypoint kept after ``index`` (the goal at most)."""
        out = np.minimum(index + 1, self.last)
        while True:
            move = self.skip[np.arange(out.size), out] & (out < self.last)
            if not move.any():
                return out
            out = np.where(move, out + 1, out)

    def velocity(
        self, positions: np.ndarray, time_left: float, step: float, v_max: float | None
    ) -> np.ndarray:
        """The velocity ``(2, N)`` (length / s) of each robot at ``positions`` (the class
        docstring), with ``time_left`` in the period, the step ``step`` (0: unknown) and
        the speed cap ``v_max``.
        """
        robots = np.arange(positions.shape[1])
        self.current = np.where(self.landing, self.next_kept(self.current), self.current)
        w = self.ways[robots, self.current].T
        to_goal = self.current == self.last
        gap = w - positions
        distance = np.sqrt((gap**2).sum(axis=0))
        speed = (distance + self.rest[robots, self.current]) / time_left
        with np.errstate(invalid="ignore", divide="ignore"):
            u = np.where(distance > 0, gap / distance * speed, 0.0)
        if step > 0:
            lands = ~to_goal & (speed * step >= distance)
            u = np.where(lands, gap / step, u)
        else:
            lands = np.zeros_like(to_goal)
        u = np.where(to_goal, gap / time_left, u)
        if v_max is not None:
            capped = cap_vectors(u, v_max)
            lands &= np.all(capped == u, axis=0)
            u = capped
        u = np.where(self.reachable, u, 0.0)
        self.landing = lands & self.reachable
        return u


def geodesic_costs(
    geodesics: Geodesics, x: np.ndarray, here: np.ndarray, y: np.ndarray, there: np.ndarray
) -> np.ndarray:
    """The cost ``(n, m)`` (length^2) of moving robot ``i`` at ``x[:, i]`` (in free cell
    ``here[i]``) to point ``j`` at ``y[:, j]`` (in source cell ``there[j]``):

        c_ij = max(D(here_i, there_j), |x_i - y_j|)^2,

    the geodesic distance between the cells' centres (:class:`Geodesics`), or the
    straight one where that is longer (within a cell, and between points of
    neighbouring cells). Between components of free space, where ``D`` is infinite:
    a finite cost larger than any path's, ``(4 (max finite D + L))^2`` (the assignment
    then holds such a robot, :class:`Routes`).
    """
    rows = geodesics.row(there)
    d = geodesics.distance[np.ix_(rows, here)].T
    dx = np.subtract.outer(x[0], y[0])
    dy = np.subtract.outer(x[1], y[1])
    straight = np.sqrt(dx * dx + dy * dy)
    finite = np.isfinite(d)
    if not finite.all():
        g = geodesics.free.grid
        worst = float(d[finite].max(initial=0.0)) + (g.x1 - g.x0) + (g.y1 - g.y0)
        d = np.where(finite, d, 4.0 * worst)
    return np.maximum(d, straight) ** 2
