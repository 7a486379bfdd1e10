"""The decentralised loop on domains with obstacles (harness/estimators/distributed/):
each robot's kernel is the free-space heat kernel's column at its position, so the robots'
mean is the centralised free-space KDE; with a complete graph every robot's filter is the
centralised free-space filter; no estimate mass on blocked cells or across a wall; unit
mass on free space; radio through walls or by line of sight; the loop end to end on rooms.
"""

import numpy as np
import pytest

from harness import api
from harness.control.paper import PaperControl, paper_law
from harness.estimators.distributed.estimator import RobotEstimators
from harness.estimators.distributed.free_space import (
    FreeBandMessages,
    FreeGradients,
    FreeGridMessages,
    FreeRobotKernels,
)
from harness.estimators.distributed.graph import communication_graph
from harness.estimators.distributed.metrics import NETWORK_KEYS, consensus_l2
from harness.estimators.distributed.mixing import consensus_weights, mixer
from harness.estimators.distributed.walls import line_of_sight
from harness.estimators.filters.common import FilterSettings, FreeBand, MeasurementModel
from harness.estimators.filters.local import LocalFilters
from harness.estimators.kde import KDE
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.plants.agents import Swarm
from harness.plants.obstacles import RobotMap
from harness.records import ControlInput, Estimate, RobotEstimates
from harness.targets.densities import DEFAULT_TARGET, Target
from harness.velocity import interpolate
from tests.domain_cases import DOMAINS

H = 0.04
SIGMA = 5e-5


def free_positions(free, n, rng, box=(0.0, 1.0, 0.0, 1.0)):
    """``n`` robots uniform over the free squares of ``free``'s raster inside ``box``."""
    raster = free.raster
    side = 1.0 / raster.shape[0]
    out = np.empty((2, 0))
    while out.shape[1] < n:
        p = rng.uniform(box[::2], box[1::2], size=(4 * n, 2)).T
        ok = raster[(p[1] / side).astype(int), (p[0] / side).astype(int)] == 0
        out = np.concatenate([out, p[:, ok]], axis=1)
    return out[:, :n]


@pytest.mark.parametrize("name", DOMAINS)
def test_the_robots_kernels_average_to_the_centralised_free_space_kde(name, rng):
    g = Grid.square(30)
    free = DOMAINS[name].resolve(g)
    kernels = FreeRobotKernels(free, H)
    pos = free_positions(free, 1500, rng)
    pos[:, :20] = rng.uniform(0, 1, size=(2, 20))  # some in obstacles: counted at their home
    factors = kernels(pos)
    phi = kernels.kernels(factors)
    mean = np.zeros(g.size)
    mean[kernels.cells] = phi.mean(axis=0)
    p_kde, grad_kde = KDE(g, H, free=free)(pos)
    np.testing.assert_allclose(mean, p_kde.ravel(), rtol=0, atol=1e-12 * p_kde.max())
    p, grad = kernels.kde(factors)  # the reference's observation
    np.testing.assert_allclose(p, p_kde, rtol=0, atol=1e-12 * p_kde.max())
    np.testing.assert_allclose(grad, grad_kde, rtol=0, atol=1e-12 * abs(grad_kde).max())


@pytest.mark.parametrize("name", DOMAINS)
def test_a_robots_kernel_has_unit_mass_on_free_space_and_none_on_blocked_cells(name, rng):
    g = Grid.square(30)
    free = DOMAINS[name].resolve(g)
    kernels = FreeRobotKernels(free, H)
    pos = free_positions(free, 400, rng)
    fields = FreeGridMessages(kernels).fields(kernels.kernels(kernels(pos)))
    assert (fields[:, ~free.cells.ravel()] == 0).all()
    assert fields.min() >= 0
    # point values at the centres: unit mass up to the midpoint rule, as the KDE's
    np.testing.assert_allclose(fields.sum(axis=1) * g.cell_area, 1.0, atol=1e-7)


def test_a_robots_kernel_does_not_reach_through_a_wall(rng):
    g = Grid.square(30)
    free = DOMAINS["shut_rooms"].resolve(g)
    assert free.n_components == 2
    kernels = FreeRobotKernels(free, H)
    # robots within a bandwidth of the wall, on its left
    pos = free_positions(free, 200, rng, box=(0.43, 0.47, 0.1, 0.9))
    fields = FreeGridMessages(kernels).fields(kernels.kernels(kernels(pos)))
    right = (free.labels == 1).ravel()
    assert (fields[:, right] == 0).all()
    np.testing.assert_allclose(fields.sum(axis=1) * g.cell_area, 1.0, atol=1e-7)


def test_messages_carry_free_cells_only_and_band_consensus_is_the_band_projection(rng):
    g = Grid.square(30)
    free = DOMAINS["rooms"].resolve(g)
    kernels = FreeRobotKernels(free, H)
    grid_msgs = FreeGridMessages(kernels)
    assert grid_msgs.size == int(free.cells.sum()) < g.size
    band = FreeBandMessages(kernels, 2.5 / H)
    pi = FreeBand(free, 2.5 / H)
    assert band.size == pi.modes.shape[1] < grid_msgs.size
    pos = free_positions(free, 60, rng)
    factors = kernels(pos)
    fields = grid_msgs.fields(kernels.kernels(factors))
    # a kernel's coefficients are those of its field
    np.testing.assert_allclose(
        band.increment(factors, None), band.coefficients(fields), atol=1e-12 * abs(fields).max()
    )
    w, _ = consensus_weights(communication_graph(pos, 0.3))
    mix = mixer(w, pos)
    on_coef = band.fields(mix(band.coefficients(fields)))
    on_fields = pi((w @ fields).T).T  # consensus on the fields, then the band's projector
    np.testing.assert_allclose(on_coef, on_fields, atol=1e-12 * abs(fields).max())


@pytest.mark.parametrize("name", DOMAINS)
def test_each_robots_gradient_is_the_free_space_gradient_of_its_estimate(name, rng):
    g = Grid.square(30)
    free = DOMAINS[name].resolve(g)
    p_hat = np.where(free.cells.ravel(), rng.random((7, g.size)), 0.0)
    got = FreeGradients(free)(p_hat)
    expected = np.stack([free.gradient(p.reshape(g.shape)).ravel() for p in p_hat])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * abs(expected).max())


def _brute_line_of_sight(free, a, b, samples=4000):
    """Whether dense samples of the segment ``a b`` all fall on free raster squares."""
    raster = free.raster
    r = raster.shape[0]
    t = np.linspace(0.0, 1.0, samples)
    x = a[0] + t * (b[0] - a[0])
    y = a[1] + t * (b[1] - a[1])
    ix = np.clip((x * r).astype(int), 0, r - 1)
    iy = np.clip((y * r).astype(int), 0, r - 1)
    return not raster[iy, ix].any()


def test_radio_links_pass_through_walls_and_line_of_sight_keeps_the_visible_ones(rng):
    g = Grid.square(30)
    free = DOMAINS["rooms"].resolve(g)
    # across the wall far from the door, and through the door
    pos = np.array([[0.45, 0.55, 0.45, 0.55], [0.2, 0.2, 0.5, 0.5]])
    through = communication_graph(pos, 0.2)
    assert through[0, 1] == 1 and through[2, 3] == 1
    seen = line_of_sight(through, pos, free)
    assert seen[0, 1] == 0 and seen[2, 3] == 1
    pos = free_positions(free, 300, rng, box=(0.35, 0.65, 0.0, 1.0))
    adj = communication_graph(pos, 0.15)
    seen = line_of_sight(adj, pos, free)
    assert (seen != seen.T).nnz == 0
    rows, cols = adj.nonzero()
    upper = rows < cols
    expected = [_brute_line_of_sight(free, pos[:, i], pos[:, j])
                for i, j in zip(rows[upper], cols[upper], strict=True)]  # fmt: skip
    got = np.asarray(seen[rows[upper], cols[upper]]).ravel() == 1
    assert 0 < np.sum(expected) < len(expected)  # some links cross the wall, some do not
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("name", ["rooms", "obstacles"])
def test_complete_graph_equals_the_centralised_free_space_filter_and_law(name):
    """Complete graph: one round is exact consensus; every robot runs the centralised
    free-space density filter on the centralised free-space KDE and moves by the law of
    the centralised estimate with its free-space gradient, and the loops coincide."""
    rng = np.random.default_rng(7)
    g = Grid.square(20)
    free = DOMAINS[name].resolve(g)
    target = Target.from_density(g, DEFAULT_TARGET, free)
    n, dt, alpha = 80, 0.01, 0.003
    swarm = Swarm(g, free_positions(free, n, rng), SIGMA, RobotMap.of(free))
    pos = swarm.positions
    settings = FilterSettings(band_limit=np.inf)  # the robots' filters keep every mode
    kde = KDE(g, H, free=free)
    est = RobotEstimators(g, dt, n, H, settings, radius=2.0, free=free)
    central = LocalFilters(g, SIGMA, dt, MeasurementModel(n, H, settings), free=free)
    fp = FokkerPlanck(g, SIGMA, free=free)
    law = PaperControl(target, alpha, SIGMA)
    e = est.initialize(pos)
    central.initialize(*kde(pos))
    for _ in range(25):
        p_c, _ = central.estimates
        np.testing.assert_allclose(e.p_hat, np.broadcast_to(p_c.ravel(), e.p_hat.shape),
                                   rtol=0, atol=1e-10 * abs(p_c).max())  # fmt: skip
        assert (e.p_hat[:, ~free.cells.ravel()] == 0).all()
        q_c = free.gradient(p_c)
        v_field = paper_law(p_c, q_c, target, alpha, SIGMA)
        q_own = np.stack([free.gradient(p.reshape(g.shape)).ravel() for p in e.p_hat])
        robots = RobotEstimates(e.p_hat, q_own, p_c.ravel())
        cmd = law(ControlInput(0.0, Estimate(p_c, q_c, robots=robots), positions=pos))
        expected = interpolate(g, v_field.centres, pos)
        scale = abs(expected).max()
        np.testing.assert_allclose(cmd.robots, expected, rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(cmd.reference, expected, rtol=0, atol=1e-12 * scale)
        pos = swarm.step_robots(cmd.robots, dt, rng)
        a = fp.matrix(v_field)
        e = est.step(pos, a)
        central.step(*kde(pos), v_field, a)
    assert consensus_l2(g, e.p_hat) < 1e-12


def test_robots_own_estimates_without_their_gradients_are_refused_on_free_space():
    g = Grid.square(20)
    free = DOMAINS["rooms"].resolve(g)
    target = Target.from_density(g, DEFAULT_TARGET, free)
    p = target.p
    robots = RobotEstimates(np.broadcast_to(p.ravel(), (3, g.size)), None)
    inp = ControlInput(0.0, Estimate(p, free.gradient(p), robots=robots),
                       positions=np.array([[0.2, 0.3, 0.8], [0.5, 0.5, 0.5]]))  # fmt: skip
    with pytest.raises(ValueError, match="own gradients"):
        PaperControl(target, 0.003, SIGMA)(inp)


def test_the_decentralised_loop_runs_on_rooms_end_to_end(smoke):
    overrides = [*smoke, "domain=rooms", "init=left_room", "estimator=distributed"]
    steps = list(api.simulate(overrides))
    assert len(steps) > 2
    cfg = api.compose(overrides)
    free = DOMAINS["rooms"].resolve(Grid.square(cfg.grid.n))
    for rec, metrics in steps:
        for key in NETWORK_KEYS:
            assert np.isfinite(metrics[key]), (key, metrics[key])
        p_hat = rec.estimate.robots.p_hat
        assert (p_hat[:, ~free.cells.ravel()] == 0).all()
        assert (rec.estimate.p_hat[~free.cells] == 0).all()
        q_hat = rec.estimate.robots.q_hat.reshape(p_hat.shape[0], 2, -1)
        assert (q_hat[:, :, ~free.cells.ravel()] == 0).all()
    # at t = 0 each filter starts at its tracked field, whose mean over robots is the
    # centralised free-space KDE (unit mass up to the midpoint rule)
    first = steps[0][0]
    p_kde, _ = KDE(free.grid, cfg.kde.bandwidth, free=free)(first.positions)
    np.testing.assert_allclose(first.estimate.p_hat, p_kde, rtol=0, atol=1e-12 * p_kde.max())


def test_line_of_sight_changes_the_graph_on_rooms_and_not_the_square(smoke):
    base = [*smoke, "init=uniform", "estimator=distributed", "estimator.radius=0.3"]
    for domain, changes in (("rooms", True), ("square", False)):
        degrees = []
        for through in ("true", "false"):
            over = [*base, f"domain={domain}", f"estimator.through_walls={through}"]
            _, metrics = next(iter(api.simulate(over)))
            degrees.append(metrics["mean_degree"])
        assert (degrees[1] < degrees[0]) == changes, (domain, degrees)


@pytest.mark.parametrize(
    ("override", "key", "allowed"),
    [("estimator.gradient=fourth_order", "estimator.gradient=", "grid on a domain with obstacles"),
     ("estimator.through_walls=3", "estimator.through_walls=", "true or false")],
)  # fmt: skip
def test_a_decentralised_option_that_does_not_hold_on_free_space_is_refused(
    refusal, override, key, allowed
):
    line = refusal(["domain=rooms", "init=left_room", "grid.n=12", "agents.n=40",
                    "estimator=distributed", override])  # fmt: skip
    assert line is not None and line.startswith(f"invalid config: {key}"), line
    assert allowed in line, line


def test_the_memory_estimate_on_free_space_bounds_the_kernel_tables_build():
    """tracemalloc sees numpy's allocations: the estimate's share for the table bounds the
    peak of building it (rooms, n = 24), and the check counts it only off the square."""
    import tracemalloc

    from harness.domains.rooms import Rooms
    from harness.estimators.distributed.estimator import DistributedEstimator
    from harness.estimators.distributed.free_space import FreeRobotKernels
    from harness.grid import Grid

    grid = Grid.square(24)
    free = Rooms().resolve(grid)
    FreeRobotKernels(free, 0.04)  # compile first: only the arrays are measured
    tracemalloc.start()
    kernels = FreeRobotKernels(free, 0.04)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    square = DistributedEstimator.memory_estimate(grid, robots=64, bandwidth=0.04)
    rooms = DistributedEstimator.memory_estimate(grid, robots=64, bandwidth=0.04, free_space=True)
    extra = rooms.nbytes - square.nbytes
    assert extra >= peak, (extra, peak)
    assert extra <= 6 * peak, (extra, peak)  # not far above
    assert kernels.table.nbytes <= extra / 4


def test_the_memory_check_passes_free_space_only_off_the_square(compose):
    from harness.grid import Grid
    from harness.runs import resources

    grid = Grid.square(30)
    square = resources.check_memory(compose(["estimator=distributed"]), grid, (1 << 50, "t"))
    rooms = resources.check_memory(
        compose(["estimator=distributed", "domain=rooms"]), grid, (1 << 50, "t")
    )
    assert rooms - square >= 4 * 8 * (3 * 3 * 900) * 900  # the table, r = 3 at n = 30
