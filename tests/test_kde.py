import numpy as np
import pytest

from harness.estimators.kde import KDE, noise_constants
from harness.grid import Grid
from harness.targets.densities import Box, GaussianMixture, Target


def test_noise_constants_paper_values():
    k, k_g = noise_constants(1024, 0.04)
    assert k == pytest.approx(0.0486, rel=1e-2)
    assert k_g == pytest.approx(15.18, rel=1e-2)
    with pytest.raises(ValueError):
        noise_constants(0, 0.04)


@pytest.mark.parametrize("method", ["exact", "binned"])
def test_mirrored_kde_integrates_to_one_even_near_walls(method, rng):
    g = Grid.square(30)
    positions = rng.uniform(0.0, 0.05, size=(2, 300))  # crowded into a corner
    p, _ = getattr(KDE(g, 0.04, mirror=True), method)(positions)
    assert g.integrate(p) == pytest.approx(1.0, abs=1e-9)
    p_plain, _ = getattr(KDE(g, 0.04, mirror=False), method)(positions)
    assert g.integrate(p_plain) < 0.6  # without mirroring about half the mass is lost


def test_gradient_matches_finite_difference_of_density(rng):
    # fourth-order central differences on a fine grid: error ~ (dx/h)^4 / 30 ~ 2e-6
    g = Grid.square(300)
    positions = rng.uniform(0.0, 1.0, size=(2, 200))
    p, grad = KDE(g, 0.04, method="exact")(positions)

    def d4(f, axis, h):
        f = np.moveaxis(f, axis, 0)
        d = (-f[4:] + 8 * f[3:-1] - 8 * f[1:-3] + f[:-4]) / (12 * h)
        return np.moveaxis(d, 0, axis)

    scale = np.abs(grad).max()
    assert np.abs(d4(p, 1, g.dx) - grad[0][:, 2:-2]).max() < 1e-4 * scale
    assert np.abs(d4(p, 0, g.dy) - grad[1][2:-2, :]).max() < 1e-4 * scale


def test_mirrored_gradient_normal_to_wall_vanishes(rng):
    g = Grid.square(200)
    positions = rng.uniform(0.0, 1.0, size=(2, 400))
    _, grad = KDE(g, 0.04)(positions)
    # half a cell from the wall the normal derivative is O(dx/h) of its interior size
    assert np.abs(grad[0][:, 0]).max() < 0.1 * np.abs(grad[0]).max()
    assert np.abs(grad[1][-1, :]).max() < 0.1 * np.abs(grad[1]).max()


@pytest.mark.parametrize("n_robots", [50, 3000, 20000])
def test_binned_agrees_with_exact(n_robots, rng):
    g = Grid.square(30)
    kde = KDE(g, 0.04)
    positions = Box(0.1, 0.9, 0.0, 0.6).sample(n_robots, g, rng)
    p_e, g_e = kde.exact(positions)
    p_b, g_b = kde.binned(positions)
    # linear binning moves each robot's kernel by at most its curvature times
    # dx_fine^2 / 8: relative (dx_fine / h)^2 / 8 = 5.4e-3 of a kernel peak here
    assert np.abs(p_b - p_e).max() < 6e-3 * p_e.max()
    assert np.abs(g_b - g_e).max() < 1e-2 * np.abs(g_e).max()
    # the compiled binning equals its numpy reference
    from harness.compiled.binning import linear_binning

    np.testing.assert_allclose(
        linear_binning(positions, 0.0, 1.0, 0.0, 1.0, 120, 120),
        kde.bin_weights(positions),
        atol=1e-15,
    )


@pytest.mark.parametrize("n_robots", [5000, 200_000])
def test_parallel_binning_equals_reference_and_is_independent_of_thread_count(n_robots, rng):
    """Chunked parallel binning: 1 and 2 numba threads give the same bits, and both
    equal the numpy reference (np.bincount) to round-off. 200 000 robots make
    several chunks (and more than one batch of chunks).
    """
    import numba

    from harness.compiled.binning import BIN_BATCH, bin_chunk_size, linear_binning_chunked

    g = Grid.square(30)
    kde = KDE(g, 0.04)
    positions = Box(0.1, 0.9, 0.0, 0.6).sample(n_robots, g, rng)
    chunk = min(bin_chunk_size(n_robots, 121 * 121), 12_000)
    results = []
    before = numba.get_num_threads()
    try:
        for threads in (1, 2):
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            results.append(linear_binning_chunked(positions, 0.0, 1.0, 0.0, 1.0, 120, 120, chunk))
    finally:
        numba.set_num_threads(before)
    assert n_robots < chunk or n_robots > BIN_BATCH * chunk
    assert np.array_equal(results[0], results[1])
    ref = kde.bin_weights(positions)
    np.testing.assert_allclose(results[0], ref, rtol=1e-12, atol=1e-300)
    assert results[0].sum() == pytest.approx(1.0, rel=1e-12)


def test_auto_method_switches_on_robot_count(rng):
    g = Grid.square(10)
    kde = KDE(g, 0.1, exact_max_robots=100)
    small = rng.uniform(size=(2, 100))
    np.testing.assert_array_equal(kde(small)[0], kde.exact(small)[0])
    large = rng.uniform(size=(2, 101))
    np.testing.assert_array_equal(kde(large)[0], kde.binned(large)[0])


def test_bad_inputs_are_rejected(grid30):
    with pytest.raises(ValueError, match="bandwidth"):
        KDE(grid30, 0.0)
    with pytest.raises(ValueError, match="method"):
        KDE(grid30, 0.04, method="fft")
    with pytest.raises(ValueError, match="shape"):
        KDE(grid30, 0.04)(np.zeros((3, 10)))


def test_monte_carlo_variance_matches_k_p_in_interior():
    """Var[p_KDE] ~ k p - p^2/N and Var[d_x p_KDE] ~ k_g p (notes section 3)."""
    rng = np.random.default_rng(7)
    g = Grid.square(30)
    n_robots, h, reps = 1024, 0.04, 400
    # a smooth, broad, non-uniform density: the kernel smoothing of p is then negligible
    density = GaussianMixture(means=((0.4, 0.6),), stds=(0.3,), weights=(1.0,), floor=0.3)
    p_true = density.on_grid(g)
    kde = KDE(g, h, method="exact")
    samples = np.empty((reps, *g.shape))
    grads = np.empty((reps, 2, *g.shape))
    for r in range(reps):
        samples[r], grads[r] = kde(density.sample(n_robots, g, rng))
    k, k_g = noise_constants(n_robots, h)
    interior = np.ix_((g.y > 0.2) & (g.y < 0.8), (g.x > 0.2) & (g.x < 0.8))
    var = samples.var(axis=0, ddof=1)[interior]
    expected = (k * p_true - p_true**2 / n_robots)[interior]
    assert np.mean(var / expected) == pytest.approx(1.0, abs=0.1)
    var_g = grads[:, 0].var(axis=0, ddof=1)[interior]
    assert np.mean(var_g / (k_g * p_true[interior])) == pytest.approx(1.0, abs=0.1)
    # and the KDE is unbiased up to O(h^2) in the interior
    bias = samples.mean(axis=0)[interior] - p_true[interior]
    assert np.abs(bias).max() < 0.05 * p_true.max()


def test_target_from_density_is_normalised_and_positive(grid30):
    from harness.targets.densities import DEFAULT_TARGET

    t = Target.from_density(grid30, DEFAULT_TARGET)
    assert grid30.integrate(t.p) == pytest.approx(1.0, rel=1e-13)
    assert t.p.min() >= 0.2 - 1e-12


@pytest.mark.parametrize("n", [64, 128, 256])
def test_binned_accuracy_on_fine_grids_is_the_papers(n, rng):
    """On grids finer than the kernel needs the binning spacing stays at the paper's
    ``h / 4.8`` (120 nodes per axis at ``h = 0.04``), and the binned estimate stays
    within the paper grid's binning error of the exact one."""
    g = Grid.square(n)
    kde = KDE(g, 0.04)
    assert kde.bins == (120, 120)
    positions = Box(0.1, 0.9, 0.0, 0.6).sample(3000, g, rng)
    p_e, g_e = kde.exact(positions)
    p_b, g_b = kde.binned(positions)
    assert np.abs(p_b - p_e).max() < 6e-3 * p_e.max()
    assert np.abs(g_b - g_e).max() < 1e-2 * np.abs(g_e).max()


def test_binning_follows_the_grid_where_it_is_coarser_than_the_kernel():
    assert KDE(Grid.square(30), 0.04).bins == (120, 120)
    assert KDE(Grid.square(16), 0.04).bins == (64, 64)
    assert KDE(Grid.square(64), 0.2).bins == (24, 24)
