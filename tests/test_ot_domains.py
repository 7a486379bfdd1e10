"""``control=ot`` on free space: geodesic costs equal to a brute-force Dijkstra on the
cell graph, and robots that follow their shortest paths, never through an obstacle.
"""

import heapq

import numpy as np
import pytest

from harness.control.assignment import AssignmentControl
from harness.control.free_space import centres
from harness.control.geodesic import Geodesics, cell_graph, geodesic_costs
from harness.domains.rooms import Rooms
from harness.grid import Grid
from harness.protocols import on_free_space
from harness.records import ControlInput, Estimate
from harness.targets.densities import DEFAULT_TARGET, Target
from tests.domain_cases import DOMAINS


def brute_force_distances(free, graph, source):
    """Dijkstra by a heap over the neighbours the graph lists (its edge weights checked
    against the centres' distance and the free space's faces)."""
    g = free.grid
    nx = g.nx
    dist = {source: 0.0}
    heap = [(0.0, source)]
    done = set()
    graph = graph.tocsr()
    while heap:
        d, c = heapq.heappop(heap)
        if c in done:
            continue
        done.add(c)
        r, k = divmod(c, nx)
        for j, w in zip(
            graph.indices[graph.indptr[c] : graph.indptr[c + 1]],
            graph.data[graph.indptr[c] : graph.indptr[c + 1]],
            strict=True,
        ):
            rr, kk = divmod(int(j), nx)
            assert abs(rr - r) <= 1 and abs(kk - k) <= 1 and free.cells[rr, kk]
            if rr == r:  # an x face
                assert free.face_x[r, min(k, kk)] and w == g.dx
            elif kk == k:
                assert free.face_y[min(r, rr), k] and w == g.dy
            else:  # a diagonal: the 2 x 2 block's four faces open
                r0, k0 = min(r, rr), min(k, kk)
                assert free.face_x[r0, k0] and free.face_x[r0 + 1, k0]
                assert free.face_y[r0, k0] and free.face_y[r0, k0 + 1]
                assert w == pytest.approx(np.hypot(g.dx, g.dy), rel=1e-15)
            if d + w < dist.get(int(j), np.inf):
                dist[int(j)] = d + w
                heapq.heappush(heap, (d + w, int(j)))
    out = np.full(g.size, np.inf)
    for c, d in dist.items():
        out[c] = d
    return out


@pytest.mark.parametrize("name", DOMAINS)
@pytest.mark.parametrize("n", [10, 16])
def test_geodesic_costs_match_a_brute_force_dijkstra_on_small_grids(name, n, rng):
    grid = Grid.square(n)
    free = DOMAINS[name].resolve(grid)
    graph = cell_graph(free)
    cells = np.flatnonzero(free.cells.ravel())
    sources = rng.choice(cells, size=6, replace=False)
    geo = Geodesics(free, sources)
    for s in sources:
        np.testing.assert_allclose(
            geo.distance[geo.row(np.array([s]))[0]],
            brute_force_distances(free, graph, int(s)),
            rtol=1e-14,
        )
    # the costs of positions in those cells: max(D, straight)^2, finite only within a component
    here = rng.choice(cells, size=9)
    x = centres(grid, here) + rng.uniform(-0.4, 0.4, size=(2, 9)) * grid.dx
    there = np.repeat(sources, 2)
    y = centres(grid, there) + rng.uniform(-0.4, 0.4, size=(2, 12)) * grid.dx
    cost = geodesic_costs(geo, x, here, y, there)
    for i in range(9):
        for j in range(12):
            d = brute_force_distances(free, graph, int(there[j]))[here[i]]
            if np.isfinite(d):
                assert cost[i, j] == pytest.approx(
                    max(d, float(np.hypot(*(x[:, i] - y[:, j])))) ** 2, rel=1e-14
                )
            else:
                assert free.labels.ravel()[here[i]] != free.labels.ravel()[there[j]]


def test_geodesic_distance_is_within_8_percent_of_the_straight_one_without_obstacles():
    grid = Grid.square(20)
    free = Rooms(door=(0.0, 1.0)).resolve(grid)  # the whole wall a door: nothing in the way
    assert free.everywhere
    geo = Geodesics(free, np.arange(grid.size))
    c = centres(grid, np.arange(grid.size))
    straight = np.sqrt(((c[:, :, None] - c[:, None, :]) ** 2).sum(axis=0))
    assert (geo.distance >= straight - 1e-12).all()
    assert (geo.distance <= straight * (2 / np.sqrt(2 + np.sqrt(2))) + 1e-12).all()


def deep_in_obstacle(domain, points, side):
    """Blocked in the exact geometry, with every point within one raster square too."""
    out = np.ones(points.shape[1], dtype=bool)
    for ox in (-side, 0.0, side):
        for oy in (-side, 0.0, side):
            out &= domain.blocked(points[0] + ox, points[1] + oy, 1.0)
    return out


@pytest.mark.parametrize("name", ["rooms", "obstacles"])
def test_no_robot_path_crosses_an_obstacle_and_robots_reach_their_points(name, rng):
    domain = DOMAINS[name]
    grid = Grid.square(30)
    free = domain.resolve(grid)
    target = Target.from_density(grid, DEFAULT_TARGET, free)
    n, dt, period = 300, 0.01, 1.0
    x = rng.random((2, 20 * n))
    if name == "rooms":  # start in the left room, so that robots must pass the door
        x[0] *= 0.45
    x = x[:, ~domain.blocked(x[0], x[1], 1.0)][:, :n]
    law = AssignmentControl(target, robots=n, period=period, seed=1)
    side = 1.0 / free.raster.shape[0]  # the robots' map resolves obstacles to its squares
    assert not deep_in_obstacle(domain, law.points, side).any()
    est = Estimate(p_hat=target.p, q_hat=target.grad)
    start = x.copy()
    for step in range(2 * round(period / dt)):
        t = step * dt
        u = law(ControlInput(t=t, estimate=est, positions=x)).robots
        new = x + dt * u
        for s in np.linspace(0.0, 1.0, 41):  # each step's segment, finely
            assert not deep_in_obstacle(domain, x + s * (new - x), side).any()
        x = new
        if step + 1 == round(period / dt):  # the period's end
            goals = law.points[:, law.assignment]
            np.testing.assert_allclose(x, goals, atol=1e-9)
    if name == "rooms":
        assert (x[0] > 0.55).sum() >= 0.3 * n and (start[0] > 0.55).sum() == 0
    assert on_free_space(law)
