import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial.distance import cdist

from harness.control.heat import HeatControl
from harness.control.own_estimates import own_velocities, own_velocities_reference
from harness.control.paper import PaperControl, paper_law
from harness.estimators.distributed.consensus import DynamicAverageConsensus, message_counts
from harness.estimators.distributed.density import density_filter_reference
from harness.estimators.distributed.estimator import RobotEstimators
from harness.estimators.distributed.filters import RobotFilters
from harness.estimators.distributed.graph import (
    algebraic_connectivity,
    communication_graph,
    n_components,
)
from harness.estimators.distributed.metrics import central_gap_l2, consensus_l2, estimate_spread
from harness.estimators.distributed.mixing import consensus_weights
from harness.estimators.distributed.robot_kde import robot_kernels
from harness.estimators.filters.common import FilterSettings, MeasurementModel
from harness.estimators.filters.local import LocalFilters
from harness.estimators.kde import KDE
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid, grid_gradient
from harness.plants.agents import Swarm
from harness.targets.densities import DEFAULT_TARGET, Box, Target
from harness.velocity import VelocityField, interpolate

H = 0.04
SIGMA = 5e-5


def _ring(n: int, radius: float = 0.3) -> np.ndarray:
    ang = 2 * np.pi * np.arange(n) / n
    return np.stack([0.5 + radius * np.cos(ang), 0.5 + radius * np.sin(ang)])


# --- graph ------------------------------------------------------------------------------


@pytest.mark.parametrize("radius", [0.0, 0.07, 0.2, 2.0])
def test_radius_graph_is_the_brute_force_one(rng, radius):
    pos = rng.random((2, 150))
    adj = communication_graph(pos, radius=radius)
    expected = (cdist(pos.T, pos.T) <= radius) & ~np.eye(150, dtype=bool)
    np.testing.assert_array_equal(adj.toarray() != 0, expected)
    assert (adj.data == 1).all()


def test_knn_graph_is_the_symmetrised_brute_force_one(rng):
    pos = rng.random((2, 120))
    dist = cdist(pos.T, pos.T)
    np.fill_diagonal(dist, np.inf)
    nearest = np.argsort(dist, axis=1)[:, :4]
    expected = np.zeros((120, 120), dtype=bool)
    expected[np.arange(120)[:, None], nearest] = True
    expected |= expected.T
    np.testing.assert_array_equal(communication_graph(pos, k_nearest=4).toarray() != 0, expected)


def test_knn_within_a_radius_is_the_brute_force_one(rng):
    """Each robot's k nearest among those within r, then symmetrised."""
    pos = rng.random((2, 150))
    dist = cdist(pos.T, pos.T)
    np.fill_diagonal(dist, np.inf)
    expected = np.zeros((150, 150), dtype=bool)
    for i in range(150):
        inside = np.flatnonzero(dist[i] <= 0.08)
        expected[i, inside[np.argsort(dist[i, inside])][:5]] = True
    expected |= expected.T
    adj = communication_graph(pos, radius=0.08, k_nearest=5)
    np.testing.assert_array_equal(adj.toarray() != 0, expected)
    # some robots have fewer than 5 within r (the radius binds), some more (k binds)
    within = (dist <= 0.08).sum(axis=1)
    assert within.min() < 5 < within.max()


def test_ring_spectrum_components_and_messages():
    n = 24
    adj = communication_graph(_ring(n), k_nearest=2)
    assert (np.asarray(adj.sum(axis=1)).ravel() == 2).all()
    lam2 = 2 - 2 * np.cos(2 * np.pi / n)  # analytic: cycle graph
    assert algebraic_connectivity(adj) == pytest.approx(lam2, rel=1e-10)
    assert algebraic_connectivity(adj, dense_max=0) == pytest.approx(lam2, rel=1e-8)
    assert n_components(adj) == 1
    # two separated clusters: two components, lambda_2 = 0
    two = communication_graph(np.hstack([_ring(8, 0.05) - 0.3, _ring(8, 0.05) + 0.3]), radius=0.1)
    assert n_components(two) == 2 and algebraic_connectivity(two) == 0.0
    counts = message_counts(adj, rounds=3, floats_per_round=900)
    assert counts["messages"] == 6 and counts["floats"] == 5400 and counts["bytes"] == 43200


# --- kernels and consensus ----------------------------------------------------------------


def test_robot_kernels_average_to_the_kde(rng):
    g = Grid(14, 11)
    pos = rng.random((2, 300))
    phi = robot_kernels(g, pos, H, gradient=True)
    p, grad = KDE(g, H, method="exact").exact(pos)
    m = g.size
    np.testing.assert_allclose(phi[:, :m].mean(axis=0), p.ravel(), atol=1e-12 * p.max())
    np.testing.assert_allclose(phi[:, m:].mean(axis=0), grad.ravel(), atol=1e-12 * abs(grad).max())


def test_compiled_consensus_step_matches_scipy_and_keeps_the_mean_at_the_kde(rng):
    g = Grid.square(12)
    n = 80
    pos = rng.random((2, n))
    dac = DynamicAverageConsensus(g, H, rounds=2, gain=0.7)
    kde = KDE(g, H, method="exact")
    adj = communication_graph(pos, radius=0.15)
    z = dac.initialize(pos, consensus_weights(adj, 0.7)[0]).copy()
    for _ in range(15):
        phi_old = robot_kernels(g, pos, H)
        pos = np.clip(pos + 0.03 * rng.normal(size=pos.shape), 0, 1)  # graph changes
        w, _ = consensus_weights(communication_graph(pos, radius=0.15), 0.7)
        ref, _ = dac.reference_step(z, robot_kernels(g, pos, H), phi_old, w)
        z = dac.step(pos, w).copy()
        np.testing.assert_allclose(z, ref, atol=1e-12 * abs(ref).max())
        p, _ = kde.exact(pos)
        np.testing.assert_allclose(z.mean(axis=0), p.ravel(), atol=1e-12 * p.max())


def test_isolated_robot_tracks_only_its_own_kernel(rng):
    g = Grid.square(30)
    # a cluster near one corner and a loner far from it, moving
    pos = np.hstack([0.2 + 0.05 * rng.random((2, 30)), [[0.8], [0.7]]])
    dac = DynamicAverageConsensus(g, H, rounds=3)
    dac.initialize(pos, consensus_weights(communication_graph(pos, radius=0.1))[0])
    x, y = g.mesh
    for _ in range(10):
        pos = pos + 0.005 * rng.normal(size=pos.shape)
        adj = communication_graph(pos, radius=0.1)
        assert adj[-1].nnz == 0
        z = dac.step(pos, consensus_weights(adj)[0])
        obs = z[-1].reshape(g.shape)
        assert g.integrate(obs) == pytest.approx(1.0, abs=1e-9)
        # its shape: the Gaussian of bandwidth h at X plus wall images, written directly
        xs = [pos[0, -1], -pos[0, -1], 2 - pos[0, -1]]
        ys = [pos[1, -1], -pos[1, -1], 2 - pos[1, -1]]
        kern = sum(
            np.exp(-((x - a) ** 2 + (y - b) ** 2) / (2 * H**2)) / (2 * np.pi * H**2)
            for a in xs
            for b in ys
        )
        np.testing.assert_allclose(obs, kern, atol=1e-12 * kern.max())


@pytest.mark.parametrize(("gain", "rounds"), [(1.0, 1), (0.5, 1), (1.0, 3)])
def test_consensus_error_decays_at_the_rate_of_the_algebraic_connectivity(gain, rounds):
    n = 12
    g = Grid(6, 5)
    pos = _ring(n)
    adj = communication_graph(pos, k_nearest=2)
    w, eps = consensus_weights(adj, gain)
    lap = np.diag(np.asarray(adj.sum(axis=1)).ravel()) - adj.toarray()
    lam = np.linalg.eigvalsh(lap)  # independent of the code under test
    assert lam[1] == pytest.approx(2 - 2 * np.cos(2 * np.pi / n), rel=1e-12)
    rate = max(abs(1 - eps * lam[1]), abs(1 - eps * lam[-1])) ** rounds
    assert rate == pytest.approx((1 - eps * lam[1]) ** rounds)
    dac = DynamicAverageConsensus(g, H, rounds=rounds, gain=gain)
    z = dac.initialize(pos, w)
    errs = []
    for _ in range(200 // rounds):  # robots at rest: e(t+1) = W^m e(t)
        errs.append(np.linalg.norm(z - z.mean(axis=0)))
        z = dac.step(pos, w)
    errs = np.array(errs)
    measured = errs[-1] / errs[-2]
    assert measured == pytest.approx(rate, rel=1e-6)
    # and the whole history is bounded by the rate: ||e(t)|| <= rate^t ||e(0)||
    t = np.arange(errs.size)
    assert (errs <= errs[0] * rate**t * (1 + 1e-9)).all()


# --- filters ------------------------------------------------------------------------------


def _swarm_and_velocity(g, rng, n):
    target = Target.from_density(g, DEFAULT_TARGET)
    return target, Box().sample(n, g, rng)


def test_vectorised_filters_equal_one_local_filter_per_robot(rng):
    """Each robot's density filter is the centralised local filter's on its own
    observation (its gradient filter runs beside it and does not touch it)."""
    g = Grid(10, 9)
    n = 6
    # the per-robot filters do not carry the band limit yet: the centralised reference is
    # the same local filter without it (every cosine mode kept)
    settings = FilterSettings(band_limit=np.inf)
    model = MeasurementModel(400, H, settings)
    dt = 0.01
    fp = FokkerPlanck(g, SIGMA)
    ys = [1.0 + 0.3 * rng.random((n, g.size))]
    yg = [5.0 * rng.normal(size=(n, 2 * g.size))]
    batch = RobotFilters(g, dt, model)
    batch.initialize(ys[0])
    refs = [LocalFilters(g, SIGMA, dt, model) for _ in range(n)]
    for i, f in enumerate(refs):
        f.initialize(ys[0][i].reshape(g.shape), yg[0][i].reshape(2, *g.shape))
    for step in range(12):
        # strong and weak transport: both the Neumann series and the sparse-LU branch
        scale = 3.0 if step % 3 == 0 else 0.05
        v = VelocityField.from_centres(scale * rng.normal(size=(2, *g.shape)))
        a = fp.matrix(v)
        y = 1.0 + 0.3 * rng.random((n, g.size))
        y_g = 5.0 * rng.normal(size=(n, 2 * g.size))
        x0, d0 = batch.x.copy(), batch.d.copy()
        batch.step(y, a)
        x_ref, d_ref = density_filter_reference(x0, d0, y, a, dt, model)
        np.testing.assert_allclose(batch.x, x_ref, atol=1e-12 * abs(x_ref).max())
        np.testing.assert_allclose(batch.d, d_ref, rtol=1e-12)
        for i, f in enumerate(refs):
            p_i, _ = f.step(y[i].reshape(g.shape), y_g[i].reshape(2, *g.shape), v, a)
            np.testing.assert_allclose(batch.x[i], p_i.ravel(), atol=1e-11 * abs(p_i).max())
            np.testing.assert_allclose(batch.d[i], f.d, rtol=1e-11)


@pytest.mark.parametrize("order", [2, 4])
def test_complete_graph_equals_the_centralised_filter(order):
    """Complete graph: eps = 1/N and W = 1 1^T / N, one round is exact consensus; every
    robot then runs the centralised density filter on the centralised KDE, moves on the
    law of the centralised estimate and its central differences (order 2 or 4), and the
    two closed loops coincide."""
    rng = np.random.default_rng(5)
    g = Grid.square(16)
    n, dt, alpha = 60, 0.01, 0.003
    target, pos = _swarm_and_velocity(g, rng, n)
    swarm = Swarm(g, pos, SIGMA)  # the robots' step, each robot with its own velocity
    pos = swarm.positions
    # the per-robot filters do not carry the band limit yet: the centralised reference is
    # the same local filter without it (every cosine mode kept)
    settings = FilterSettings(band_limit=np.inf)
    kde = KDE(g, H, method="exact")
    est = RobotEstimators(g, dt, n, H, settings, radius=2.0)
    central = LocalFilters(g, SIGMA, dt, MeasurementModel(n, H, settings))
    fp = FokkerPlanck(g, SIGMA)
    e = est.initialize(pos)
    central.initialize(*kde.exact(pos))
    for step in range(30):
        assert e.eps == pytest.approx(1.0 / n)
        p_c, _ = central.estimates
        np.testing.assert_allclose(e.p_hat, np.broadcast_to(p_c.ravel(), e.p_hat.shape),
                                   atol=1e-10 * abs(p_c).max())  # fmt: skip
        q_c = grid_gradient(g, p_c, order)
        # time-varying gain: a time-varying velocity field
        a_t = alpha * (1.0 + 10.0 * np.sin(0.3 * step) ** 2)
        v_field = paper_law(p_c, q_c, target, a_t, SIGMA)
        law = PaperControl(target, a_t, SIGMA).at_cells
        v_robots = own_velocities(g, law, e.p_hat, pos, order=order)
        expected = interpolate(g, v_field.centres, pos)
        np.testing.assert_allclose(v_robots, expected, atol=1e-9 * abs(expected).max())
        pos = swarm.step_robots(v_robots, dt, rng)
        a = fp.matrix(v_field)
        e = est.step(pos, a)
        central.step(*kde.exact(pos), v_field, a)
    assert consensus_l2(g, e.p_hat) < 1e-12


def test_own_velocities_match_the_per_robot_field(rng, grid30, target30):
    n = 40
    pos = rng.random((2, n))
    pos[:, :4] = [[0.0, 1.0, 0.01, 0.995], [0.0, 1.0, 0.99, 0.003]]  # near the walls
    p_hat = 1.0 + 0.5 * rng.random((n, grid30.size))
    q_hat = rng.normal(size=(n, 2 * grid30.size))
    controls = [
        PaperControl(target30, 0.003, SIGMA),
        PaperControl(target30, 0.003, SIGMA, debias=True, bandwidth=H),
        HeatControl(target30, 0.01, SIGMA, density_floor=1.2),
        HeatControl(target30, 0.01, SIGMA, noise_compensation=False),
    ]
    for control in controls:
        for q, order in ((None, 2), (None, 4), (q_hat, 2)):
            fast = own_velocities(grid30, control.at_cells, p_hat, pos, q, order)
            ref = own_velocities_reference(grid30, control.field, p_hat, pos, q, order)
            np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match="order"):
        own_velocities(grid30, controls[0].at_cells, p_hat, pos, order=3)


@pytest.mark.parametrize("order", [2, 4])
def test_central_differences_scale_each_cosine_mode_by_their_factor(order):
    """``G`` and ``G_4`` map a Neumann cosine mode onto its derivative times
    ``sin(k dx) / (k dx)`` and ``(8 sin(k dx) - sin(2 k dx)) / (6 k dx)`` (the ghost
    cells reflected about the walls: exact for cosine modes, wall cells included), on a
    rectangular grid; ``G`` is :meth:`Grid.gradient`."""
    g = Grid(13, 11, 0.0, 1.3, 0.0, 0.9)
    x, y = g.mesh
    lx, ly = g.x1 - g.x0, g.y1 - g.y0

    def factor(k: float, d: float) -> float:
        t = k * d
        return np.sin(t) / t if order == 2 else (8 * np.sin(t) - np.sin(2 * t)) / (6 * t)

    for a, b in ((1, 0), (2, 3), (5, 4), (12, 10)):
        kx, ky = a * np.pi / lx, b * np.pi / ly
        f = np.cos(kx * x) * np.cos(ky * y)
        exact = np.stack([
            -kx * np.sin(kx * x) * np.cos(ky * y) * (factor(kx, g.dx) if a else 0.0),
            -ky * np.cos(kx * x) * np.sin(ky * y) * (factor(ky, g.dy) if b else 0.0),
        ])  # fmt: skip
        got = grid_gradient(g, f, order)
        np.testing.assert_allclose(got, exact, atol=1e-12 * max(kx, ky))
    if order == 2:
        np.testing.assert_array_equal(grid_gradient(g, f, 2), g.gradient(f))


def test_metrics_on_known_deviations(rng):
    g = Grid.square(12)
    base = rng.random(g.size)
    e = rng.normal(size=g.size)
    e /= np.sqrt(e @ e * g.cell_area)  # unit L2 norm
    c = np.array([0.5, -1.0, 2.0, 0.25])
    p_hat = base + c[:, None] * e
    assert central_gap_l2(g, p_hat, base) == pytest.approx(np.mean(np.abs(c)), rel=1e-12)
    assert consensus_l2(g, p_hat) == pytest.approx(np.mean(np.abs(c - c.mean())), rel=1e-12)
    spread, gap = estimate_spread(g, p_hat, base.reshape(g.shape))
    assert spread == pytest.approx(np.mean(np.abs(c - c.mean())), rel=1e-12)
    assert gap == pytest.approx(np.mean(np.abs(c)), rel=1e-12)


def _iss_gap(delta: float, settings: FilterSettings) -> float:
    """Largest gap ``max_{t, i} ||p_hat_i - p_hat_central||`` when robot ``i`` observes the
    KDE plus ``delta e_i(t)``, ``e_i`` unit-L2, zero-mean, smooth and rotating."""
    rng = np.random.default_rng(11)
    g = Grid.square(16)
    n, dt = 500, 0.01
    target, pos = _swarm_and_velocity(g, rng, n)
    swarm = Swarm(g, pos, SIGMA)  # the robots' step, each robot with its own velocity
    pos = swarm.positions
    kde = KDE(g, H, method="exact")
    model = MeasurementModel(n, H, settings)
    central = LocalFilters(g, SIGMA, dt, model)
    robots = RobotFilters(g, dt, model)
    x, y = g.mesh
    shapes = []
    for a, b in ((1, 0), (0, 2), (2, 1), (1, 3), (3, 3), (4, 1)):
        s = np.cos(a * np.pi * x) * np.cos(b * np.pi * y)
        shapes.append((s / g.l2(s)).ravel())
    shapes = np.array(shapes)

    def err(t: int) -> np.ndarray:  # three robots, unit-norm errors rotating in time
        c, s = np.cos(0.1 * t), np.sin(0.1 * t)
        return np.array([c * shapes[2 * i] + s * shapes[2 * i + 1] for i in range(3)])

    p, gr = kde.exact(pos)
    central.initialize(p, gr)
    robots.initialize(np.repeat(p.ravel()[None], 3, axis=0))  # error injected from t = 1
    fp = FokkerPlanck(g, SIGMA)
    gap = 0.0
    for t in range(1, 80):
        p_c, q_c = central.estimates
        v = paper_law(p_c, q_c, target, 0.01, SIGMA)
        pos = swarm.step_robots(interpolate(g, v.centres, pos), dt, rng)
        a = fp.matrix(v)
        p, gr = kde.exact(pos)
        central.step(p, gr, v, a)
        robots.step(p.ravel() + delta * err(t), a)
        gap = max(gap, max(g.l2(robots.x[i] - central.x) for i in range(3)))
    return gap


def test_local_filter_gap_is_linear_in_an_injected_consensus_error():
    """ISS with respect to the consensus error: the gap to the centralised filter is at
    most proportional to the injected error's size. With ``R`` independent of the
    observation (large ``r_floor``) the filter is linear in it, so the gap is exactly
    proportional; with the default ``R = k max(y, r_floor)`` the gain depends on ``y``
    and the proportionality holds to first order (the ratio may not grow by more than the
    relative size of the error, 10 % at delta = 0.1 against densities of order 1)."""
    deltas = (1e-3, 1e-2, 1e-1)
    linear = FilterSettings(r_floor=50.0, band_limit=np.inf)
    gaps = np.array([_iss_gap(d, linear) for d in deltas])
    ratios = gaps / np.array(deltas)
    assert ratios[0] > 0
    np.testing.assert_allclose(ratios, ratios[0], rtol=1e-6)
    gaps = np.array([_iss_gap(d, FilterSettings(band_limit=np.inf)) for d in deltas])
    ratios = gaps / np.array(deltas)
    assert ratios[0] > 0
    assert (ratios <= ratios[0] * (1 + np.array(deltas) * 1.0 + 1e-6)).all(), ratios


def test_consensus_weights_are_doubly_stochastic_and_nonnegative(rng):
    adj = communication_graph(rng.random((2, 200)), radius=0.12)
    for gain in (1.0, 0.3):
        w, eps = consensus_weights(adj, gain)
        dense = w.toarray()
        assert (dense >= 0).all()
        np.testing.assert_allclose(dense.sum(axis=0), 1.0, atol=1e-14)
        np.testing.assert_allclose(dense, dense.T)
        deg = np.asarray(adj.sum(axis=1)).ravel()
        assert eps == pytest.approx(gain / (1 + deg.max()))
    assert isinstance(w, sp.csr_matrix)


def test_row_solver_matches_superlu(rng):
    from harness.estimators.distributed.row_solver import RowSolver

    g = Grid(9, 8)
    a = FokkerPlanck(g, 1e-3).matrix(VelocityField.from_centres(rng.normal(size=(2, *g.shape))))
    system = sp.identity(g.size, format="csr") - 0.3 * a
    x = rng.normal(size=(37, g.size))
    expected = spla.splu(system.tocsc()).solve(x.T).T
    for chunks in (1, 3, 8):
        got = RowSolver(system, chunks=chunks).solve_rows(x)
        np.testing.assert_allclose(got, expected, atol=1e-13 * abs(expected).max())


# --- initial rounds, graph ties, thread independence -----------------------------------


@pytest.mark.parametrize("initial_rounds", [0, 1, 7, 60])
def test_initial_rounds_mix_the_first_kernels_by_the_matrix_power(initial_rounds):
    """``z(0) = W^{m_0} phi(0)``: against a dense matrix power (numpy), and the
    disagreement is bounded by ``rho^{m_0}`` times the kernels' (ring graph, analytic
    spectrum)."""
    n = 16
    g = Grid(7, 6)
    pos = _ring(n)
    adj = communication_graph(pos, k_nearest=2)
    _, eps = consensus_weights(adj, 0.8)
    phi = robot_kernels(g, pos, H)
    dense = np.eye(n) - eps * (2 * np.eye(n) - adj.toarray())
    expected = np.linalg.matrix_power(dense, initial_rounds) @ phi
    est = RobotEstimators(
        g, 0.01, n, H, FilterSettings(), k_nearest=2, gain=0.8, initial_rounds=initial_rounds
    )
    z = est.initialize(pos).observation
    np.testing.assert_allclose(z, expected, atol=1e-12 * abs(phi).max())
    if initial_rounds == 0:
        np.testing.assert_array_equal(z, phi)
    lam = 2 - 2 * np.cos(2 * np.pi * np.arange(n) / n)  # cycle graph eigenvalues
    rho = np.max(np.abs(1 - eps * lam[1:]))
    dev = np.linalg.norm(z - phi.mean(axis=0))
    assert dev <= rho**initial_rounds * np.linalg.norm(phi - phi.mean(axis=0)) * (1 + 1e-9)
    assert est.consensus.rounds == 1  # the per-step rounds are unchanged


def test_radius_graph_on_a_lattice_keeps_exact_ties():
    """Lattice spacing 0.05: distances equal to the radius (to round-off) decide as
    ``cdist`` does."""
    pts = np.stack(np.meshgrid(np.arange(20) * 0.05, np.arange(20) * 0.05)).reshape(2, -1)
    for radius in (0.05, 0.1, np.hypot(0.05, 0.05), 0.15):
        expected = (cdist(pts.T, pts.T) <= radius) & ~np.eye(400, dtype=bool)
        adj = communication_graph(pts, radius=radius)
        np.testing.assert_array_equal(adj.toarray() != 0, expected)
        rows = np.split(adj.indices, adj.indptr[1:-1])
        assert all((np.diff(r) > 0).all() for r in rows)  # canonical CSR


def test_results_do_not_depend_on_the_thread_count(rng):
    import numba

    g = Grid.square(14)
    n = 90
    pos = Box().sample(n, g, rng)
    fp = FokkerPlanck(g, SIGMA)
    a = fp.matrix(VelocityField.from_centres(0.05 * rng.normal(size=(2, *g.shape))))
    moved = np.clip(pos + 0.01 * rng.normal(size=pos.shape), 0, 1)
    outs = []
    before = numba.get_num_threads()
    try:
        for threads in (1, numba.config.NUMBA_NUM_THREADS):
            numba.set_num_threads(threads)
            est = RobotEstimators(g, 0.01, n, H, FilterSettings(), radius=0.2, rounds=2)
            est.initialize(pos)
            outs.append(est.step(moved, a).p_hat.copy())
    finally:
        numba.set_num_threads(before)
    np.testing.assert_array_equal(outs[0], outs[1])


@pytest.mark.parametrize("radius", [0.08, 0.3, 2.0])
def test_mixing_by_neighbour_sums_equals_the_sparse_product(rng, radius):
    """The consensus product by sliding neighbour sums (uniform off-diagonal weights)
    and the general one (non-uniform weights) against scipy's ``W @ z``."""
    g = Grid(8, 7)
    n = 300
    pos = rng.random((2, n))
    w, _ = consensus_weights(communication_graph(pos, radius=radius), 0.9)
    # non-uniform off-diagonal weights: symmetric, rows still summing to one
    off = sp.triu(w, k=1)
    off.data *= rng.uniform(0.5, 1.0, off.nnz)
    w_var = (off + off.T).tocsr()
    w_var = (w_var + sp.diags(1.0 - np.asarray(w_var.sum(axis=1)).ravel())).tocsr()
    w_var.sort_indices()
    for weights in (w, w_var):
        dac = DynamicAverageConsensus(g, H, rounds=2, initial_rounds=0)
        phi = dac.initialize(pos, weights).copy()
        z = dac.step(pos, weights)  # the kernels did not move: z = W^2 phi
        np.testing.assert_allclose(z, weights @ (weights @ phi), atol=1e-12 * abs(phi).max())


@pytest.mark.parametrize(("shape", "h"), [((30, 30), 0.04), ((17, 11), 0.1), ((64, 64), 0.01)])
def test_compiled_kernel_factors_equal_the_kde_kernel(rng, shape, h):
    """Products of exponentials (two per robot, axis and image) against
    :func:`harness.estimators.kde.kernel_1d` (one exponential per value), robots on the
    walls too."""
    from harness.estimators.distributed.robot_kde import kernel_factors
    from harness.estimators.kde import kernel_1d

    g = Grid(*shape)
    pos = rng.random((2, 400))
    pos[:, :3] = [[0.0, 1.0, 0.5], [1.0, 0.0, 1e-9]]
    got = kernel_factors(g, pos, h)
    ref = (
        *kernel_1d(pos[0], g.x, h, g.x0, g.x1, True),
        *kernel_1d(pos[1], g.y, h, g.y0, g.y1, True),
    )
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13 * abs(b).max())


def test_consensus_kde_is_the_exact_kde_of_the_positions(rng):
    """The reference's measurement, from the kernel factors consensus computed, equals
    the KDE's exact path on the same positions."""
    g = Grid(14, 11, 0.0, 1.0, 0.0, 0.8)
    pos = rng.random((2, 90)) * np.array([[1.0], [0.8]])
    dac = DynamicAverageConsensus(g, H)
    dac.initialize(pos, sp.identity(90, format="csr"))
    p, grad = dac.kde()
    p_ref, grad_ref = KDE(g, H, method="exact").exact(pos)
    np.testing.assert_allclose(p, p_ref, rtol=1e-12, atol=1e-12 * p_ref.max())
    np.testing.assert_allclose(grad, grad_ref, rtol=1e-12, atol=1e-12 * np.abs(grad_ref).max())


def test_the_algebraic_connectivity_of_a_large_graph_is_the_same_bits_every_time():
    """ARPACK (above 400 robots) starts from a fixed vector: the logged metric is
    reproducible to the last bit, and equals the dense eigenvalue to round-off."""
    from harness.estimators.distributed.graph import algebraic_connectivity, communication_graph

    rng = np.random.default_rng(3)
    positions = rng.uniform(0.0, 1.0, (2, 900))
    adj = communication_graph(positions, radius=0.12)
    first = algebraic_connectivity(adj)
    again = [algebraic_connectivity(adj) for _ in range(5)]
    assert all(value == first for value in again), [v - first for v in again]
    dense = algebraic_connectivity(adj, dense_max=10_000)
    assert first == pytest.approx(dense, rel=1e-9)
