import numpy as np
import pytest

from harness.control.heat import heat_law
from harness.control.paper import paper_law, paper_law_reference
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.targets.densities import Box, Uniform


def test_paper_law_formula_at_centres(grid30, target30, rng):
    p_hat = rng.random(grid30.shape)
    q_hat = rng.normal(size=(2, *grid30.shape))
    alpha, sigma = 0.003, 5e-5
    v = paper_law(p_hat, q_hat, target30, alpha, sigma)
    ps, gps = target30.p, target30.grad
    expected = -alpha * (ps * q_hat - p_hat * gps) / ps**2 + sigma * gps / ps
    np.testing.assert_allclose(v.centres, expected, rtol=1e-13)


@pytest.mark.parametrize("debias", [False, True])
def test_compiled_paper_law_equals_the_numpy_statement_bit_for_bit(debias, rng):
    from harness.estimators.smoothing import smoothed_target
    from harness.targets.densities import DEFAULT_TARGET, GaussianMixture, Target

    g = Grid(37, 23, 0.0, 1.0, 0.0, 0.6)  # rectangular, dx != dy
    d = DEFAULT_TARGET  # its bumps moved into the rectangle (y scaled by 0.6)
    means = [[x, 0.6 * y] for x, y in d.means]
    target = Target.from_density(g, GaussianMixture(means, d.stds, d.weights, d.floor))
    feedback = smoothed_target(target, 0.04) if debias else None
    p_hat = rng.normal(size=g.shape)  # estimates may be negative
    q_hat = rng.normal(scale=10.0, size=(2, *g.shape))
    fast = paper_law(p_hat, q_hat, target, 0.003, 5e-5, feedback)
    ref = paper_law_reference(p_hat, q_hat, target, 0.003, 5e-5, feedback)
    for a, b in ((fast.centres, ref.centres), (fast.face_x, ref.face_x), (fast.face_y, ref.face_y)):
        assert a.shape == b.shape and np.array_equal(a, b)


def test_paper_law_refuses_estimates_off_the_grid(grid30, target30):
    with pytest.raises(ValueError, match="do not fit the grid"):
        paper_law(np.ones((30, 29)), np.zeros((2, 30, 30)), target30, 0.003, 5e-5)
    with pytest.raises(ValueError, match="do not fit the grid"):
        paper_law(np.ones((30, 30)), np.zeros((30, 30)), target30, 0.003, 5e-5)


def test_paper_law_vanishes_at_target_with_exact_estimates(grid30, target30):
    v = paper_law(target30.p, grid30.gradient(target30.p), target30, 0.05, 0.0)
    assert np.abs(v.centres).max() < 1e-12
    assert np.abs(v.face_x).max() < 1e-12 and np.abs(v.face_y).max() < 1e-12


def test_paper_law_faces_carry_the_log_drift(grid30, target30):
    sigma = 2e-3
    v = paper_law(np.zeros(grid30.shape), np.zeros((2, *grid30.shape)), target30, 0.0, sigma)
    lp = np.log(target30.p)
    np.testing.assert_allclose(v.face_x, sigma * np.diff(lp, axis=1) / grid30.dx)


def test_face_drift_converges_to_centre_drift_at_second_order():
    from harness.targets.densities import DEFAULT_TARGET, Target

    gaps = []
    for n in (30, 60, 120):
        g = Grid.square(n)
        t = Target.from_density(g, DEFAULT_TARGET)
        v = paper_law(np.zeros(g.shape), np.zeros((2, *g.shape)), t, 0.0, 1.0)
        avg = 0.5 * (v.centres[0, :, 1:] + v.centres[0, :, :-1])
        gaps.append(np.abs(v.face_x - avg)[:, 1:-1].max())  # away from one-sided wall stencils
    orders = np.log2(np.array(gaps[:-1]) / np.array(gaps[1:]))
    assert np.all(orders > 1.7), orders


def test_paper_law_is_linear_in_the_estimates(grid30, target30, rng):
    a, b = rng.random(grid30.shape), rng.random(grid30.shape)
    qa, qb = rng.normal(size=(2, 2, *grid30.shape))
    v = lambda p, q: paper_law(p, q, target30, 0.01, 0.0).centres  # noqa: E731
    np.testing.assert_allclose(v(a + 2 * b, qa + 2 * qb), v(a, qa) + 2 * v(b, qb), atol=1e-12)


def test_heat_law_formula_and_floor(grid30, target30, rng):
    p_hat = rng.normal(size=grid30.shape)  # negative values hit the floor
    q_hat = rng.normal(size=(2, *grid30.shape))
    v = heat_law(p_hat, q_hat, target30, 0.01, 1e-3, density_floor=0.2)
    d = np.maximum(p_hat, 0.2)
    np.testing.assert_allclose(v.centres, -0.01 * (q_hat - target30.grad) / d + 1e-3 * q_hat / d)
    v0 = heat_law(p_hat, q_hat, target30, 0.01, 1e-3, noise_compensation=False)
    np.testing.assert_allclose(v0.centres, -0.01 * (q_hat - target30.grad) / np.maximum(p_hat, 0.1))


@pytest.mark.parametrize("law", [paper_law, heat_law])
def test_bad_gains_are_rejected(law, grid30, target30):
    p = Uniform().on_grid(grid30)
    with pytest.raises(ValueError, match="alpha"):
        law(p, grid30.gradient(p), target30, -1.0, 0.0)
    with pytest.raises(ValueError, match="sigma"):
        law(p, grid30.gradient(p), target30, 0.0, float("nan"))


@pytest.mark.parametrize("law,alpha", [(paper_law, 0.003), (heat_law, 0.003)])
def test_meanfield_closed_loop_reaches_target_from_paper_start(grid30, target30, law, alpha):
    """Paper's setting (sigma 5e-5, dt 0.01) with exact estimates, 60 s."""
    sigma, dt = 5e-5, 0.01
    op = FokkerPlanck(grid30, sigma)
    p = Box().on_grid(grid30)
    start = grid30.l2(p - target30.p)
    for _ in range(6000):
        p = op.step(p, law(p, grid30.gradient(p), target30, alpha, sigma), dt)
    final = grid30.l2(p - target30.p)
    assert final < 0.05 * start
    assert grid30.integrate(p) == pytest.approx(1.0, rel=1e-10)


def test_heat_law_compensation_removes_the_noise_bias():
    """With exact estimates the compensated heat law settles at p_* (up to the face
    averaging, O(dx^2)); without compensation at (alpha p_* + sigma c) / (alpha + sigma),
    a bias of order sigma / alpha."""
    from harness.targets.densities import DEFAULT_TARGET, Target

    g = Grid.square(16)
    target = Target.from_density(g, DEFAULT_TARGET)
    sigma, alpha, dt = 2e-3, 0.01, 0.05
    op = FokkerPlanck(g, sigma)
    finals = {}
    for comp in (True, False):
        p = Uniform().on_grid(g)
        for _ in range(2500):
            v = heat_law(p, g.gradient(p), target, alpha, sigma, noise_compensation=comp)
            p = op.step(p, v, dt)
        finals[comp] = g.l2(p - target.p)
    bias = sigma / (alpha + sigma) * g.l2(target.p - 1.0)
    assert finals[False] > 0.5 * bias
    assert finals[True] < 0.2 * finals[False]


def test_larger_gain_converges_faster(target30, grid30):
    sigma, dt = 5e-5, 0.01
    op = FokkerPlanck(grid30, sigma)
    finals = []
    for alpha in (0.0, 0.001, 0.003):
        p = Box().on_grid(grid30)
        for _ in range(1000):
            p = op.step(p, paper_law(p, grid30.gradient(p), target30, alpha, sigma), dt)
        finals.append(grid30.l2(p - target30.p))
    assert finals[0] > finals[1] > finals[2]


def test_grid_independent_of_orientation():
    # a target symmetric under x <-> y gives a velocity field with the same symmetry
    from harness.targets.densities import GaussianMixture, Target

    g = Grid.square(16)
    t = Target.from_density(g, GaussianMixture(means=((0.3, 0.3),), stds=(0.1,), weights=(1,)))
    p = Box(0.1, 0.7, 0.1, 0.7).on_grid(g)
    v = paper_law(p, g.gradient(p), t, 0.01, 1e-3)
    np.testing.assert_allclose(v.centres[0], v.centres[1].T, atol=1e-12)
    np.testing.assert_allclose(v.face_x, v.face_y.T, atol=1e-12)
