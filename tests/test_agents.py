import numpy as np
import pytest

from harness import exact_solutions
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.plants.agents import Swarm
from harness.targets.densities import GaussianMixture
from harness.velocity import VelocityField, interpolate


def test_interpolation_is_exact_for_bilinear_fields(rng):
    g = Grid(12, 9, 0.0, 1.2, 0.0, 0.9)
    x, y = g.mesh
    field = np.stack([2 * x - 3 * y + x * y, 1 + y])
    pts = np.vstack([rng.uniform(g.x[0], g.x[-1], 500), rng.uniform(g.y[0], g.y[-1], 500)])
    values = interpolate(g, field, pts)
    np.testing.assert_allclose(values[0], 2 * pts[0] - 3 * pts[1] + pts[0] * pts[1], atol=1e-12)
    np.testing.assert_allclose(values[1], 1 + pts[1], atol=1e-12)


def test_compiled_step_equals_numpy_reference(rng):
    g = Grid.square(20)
    v = VelocityField.from_centres(rng.normal(scale=0.3, size=(2, *g.shape)))
    start = rng.uniform(0, 1, size=(2, 5000))
    a, b = Swarm(g, start, 1e-3), Swarm(g, start, 1e-3)
    rng_a, rng_b = np.random.default_rng(3), np.random.default_rng(3)
    for _ in range(5):
        a.step(v, 0.05, rng_a)
        b.step_reference(v, 0.05, rng_b)
    np.testing.assert_allclose(a.positions, b.positions, atol=1e-14)


def test_positions_never_leave_the_domain(rng):
    g = Grid(10, 10, -1.0, 2.0, 0.5, 1.0)
    v = VelocityField.from_centres(rng.normal(scale=5.0, size=(2, *g.shape)))
    s = Swarm(g, np.vstack([rng.uniform(-1, 2, 2000), rng.uniform(0.5, 1.0, 2000)]), 0.05)
    for _ in range(20):
        s.step(v, 0.05, rng)
        assert g.contains(s.positions[0], s.positions[1]).all()


def test_free_diffusion_step_statistics(rng):
    # far from the walls one step adds N(v dt, 2 sigma dt) per axis
    g = Grid.square(10)
    sigma, dt, n = 1e-4, 0.01, 200_000
    v = VelocityField.from_centres(np.stack([np.full(g.shape, 0.2), np.full(g.shape, -0.1)]))
    s = Swarm(g, np.full((2, n), 0.5), sigma)
    s.step(v, dt, rng)
    d = s.positions - 0.5
    sd = np.sqrt(2 * sigma * dt)
    assert d[0].mean() == pytest.approx(0.2 * dt, abs=5 * sd / np.sqrt(n))
    assert d[1].mean() == pytest.approx(-0.1 * dt, abs=5 * sd / np.sqrt(n))
    # sample variance: relative standard error sqrt(2/n)
    assert d.var(axis=1) == pytest.approx([sd**2, sd**2], rel=5 * np.sqrt(2 / n))


def test_bad_swarms_are_rejected(rng):
    g = Grid.square(10)
    with pytest.raises(ValueError, match="inside"):
        Swarm(g, np.array([[0.5, 1.5], [0.5, 0.5]]), 1e-3)
    with pytest.raises(ValueError, match="shape"):
        Swarm(g, np.zeros((3, 4)), 1e-3)
    with pytest.raises(ValueError, match="sigma"):
        Swarm(g, np.full((2, 3), 0.5), -1.0)


def swirl(g):
    x, y = g.mesh
    return VelocityField.from_centres(
        np.stack([-0.15 * (y - 0.5) + 0.05 * (0.5 - x), 0.15 * (x - 0.5) + 0.05 * (0.5 - y)])
    )


def fokker_planck_solution(n, dt, p0_density, sigma, t_final):
    g = Grid.square(n)
    p = p0_density.on_grid(g)
    op = FokkerPlanck(g, sigma)
    v = swirl(g)
    for _ in range(round(t_final / dt)):
        p = op.step(p, v, dt)
    return g, p


def coarsen(p):
    return 0.25 * (p[::2, ::2] + p[1::2, ::2] + p[::2, 1::2] + p[1::2, 1::2])


def test_agents_match_fokker_planck_within_statistical_bound():
    """Histogram of N = 1e5 robots vs the Fokker-Planck solution, same fixed v.

    Bound: ||h - p|| <= sqrt(E + 5 sd) + b, with E and sd the mean and standard
    deviation of ||h - p_bar||^2 for multinomial counts (exact_solutions.histogram_noise)
    and b the discretisation error of p, estimated by Richardson: twice the
    distance to the solution on a grid twice as fine (second order in space),
    plus the distance to the solution with half the time step (first order).
    """
    rng = np.random.default_rng(11)
    n, dt, sigma, t_final, n_robots = 20, 0.01, 1e-3, 3.0, 100_000
    p0 = GaussianMixture(means=((0.35, 0.4), (0.7, 0.65)), stds=(0.1, 0.08), weights=(0.6, 0.4))
    g, p = fokker_planck_solution(n, dt, p0, sigma, t_final)
    _, p_fine = fokker_planck_solution(2 * n, dt, p0, sigma, t_final)
    _, p_half = fokker_planck_solution(n, dt / 2, p0, sigma, t_final)
    b = 4 / 3 * g.l2(p - coarsen(p_fine)) + 2 * g.l2(p - p_half)

    swarm = Swarm(g, p0.sample(n_robots, g, rng), sigma)
    v = swirl(g)
    for _ in range(round(t_final / dt)):
        swarm.step(v, dt, rng)
    h = swarm.histogram()
    mean, sd = exact_solutions.histogram_noise(g, p, n_robots)
    distance = g.l2(h - p)
    assert distance <= np.sqrt(mean + 5 * sd) + b, (distance, np.sqrt(mean), b)
    # the bound is tight enough to matter: the initial density is far outside it
    assert g.l2(h - p0.on_grid(g)) > 3 * (np.sqrt(mean + 5 * sd) + b)


def _with_threads(threads, fn):
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        return fn()
    finally:
        numba.set_num_threads(before)


@pytest.mark.parametrize("n_robots", [1000, 300_000])
def test_parallel_step_equals_reference_and_is_independent_of_thread_count(n_robots, rng):
    """1 and 2 numba threads give the same bits; both equal the numpy reference to
    round-off. 300 000 robots take the chunked parallel draw of the increments.
    """
    g = Grid.square(25)
    v = VelocityField.from_centres(rng.normal(scale=0.3, size=(2, *g.shape)))
    start = rng.uniform(0, 1, size=(2, n_robots))
    results = []
    for threads in (1, 2):
        s = Swarm(g, start, 1e-3)
        r = np.random.default_rng(5)
        results.append(
            _with_threads(threads, lambda s=s, r=r: [s.step(v, 0.05, r) for _ in range(3)])[
                -1
            ].copy()
        )
    assert np.array_equal(results[0], results[1])
    ref = Swarm(g, start, 1e-3)
    r = np.random.default_rng(5)
    for _ in range(3):
        ref.step_reference(v, 0.05, r)
    np.testing.assert_allclose(results[0], ref.positions, atol=1e-14)


def test_parallel_draw_gives_standard_normals():
    from harness.plants.agents import PARALLEL_DRAW_MIN, draw_normals

    out = np.empty((2, PARALLEL_DRAW_MIN))
    draw_normals(np.random.default_rng(9), out)
    z = out.ravel()
    n = z.size
    # mean, variance and the fourth moment of N(0, 1), each within 5 standard errors
    assert abs(z.mean()) < 5 / np.sqrt(n)
    assert abs(z.var() - 1.0) < 5 * np.sqrt(2 / n)
    assert abs(np.mean(z**4) - 3.0) < 5 * np.sqrt(96 / n)
    # the whole distribution, and each chunk's (SFC64 generators on spawned seeds)
    from scipy import stats

    assert stats.kstest(z, "norm").pvalue > 1e-3
    from harness.plants.agents import DRAW_CHUNK as chunk

    for c in range(z.size // chunk):
        assert stats.kstest(z[c * chunk : (c + 1) * chunk], "norm").pvalue > 1e-4
    # chunks are independent streams: no two chunks repeat each other
    from harness.plants.agents import DRAW_CHUNK

    assert not np.array_equal(z[:DRAW_CHUNK], z[DRAW_CHUNK : 2 * DRAW_CHUNK])
    # and the same generator state gives the same numbers
    again = draw_normals(np.random.default_rng(9), np.empty_like(out))
    assert np.array_equal(out, again)
