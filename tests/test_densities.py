import numpy as np
import pytest

from harness.grid import Grid
from harness.parameters import ParameterError
from harness.targets.densities import DEFAULT_TARGET, Box, GaussianMixture, Target, Uniform


@pytest.mark.parametrize("n", [7, 30, 64])
@pytest.mark.parametrize(
    "density", [Uniform(), Box(), Box(0.0, 0.33, 0.5, 1.0), DEFAULT_TARGET], ids=str
)
def test_densities_have_unit_mass_on_the_grid(density, n):
    g = Grid(n, n + 1, 0.0, 1.0, 0.0, 1.0)
    p = density.on_grid(g)
    assert p.shape == g.shape and p.min() >= 0
    assert g.integrate(p) == pytest.approx(1.0, rel=1e-13)


def test_box_cell_fractions_on_cut_cells():
    g = Grid.square(30)  # 0.15 * 30 = 4.5: the box edge cuts cells in half
    p = Box().on_grid(g)
    inside = 1 / 0.49
    assert p[15, 15] == pytest.approx(inside)
    assert p[15, 4] == pytest.approx(0.5 * inside)
    assert p[4, 4] == pytest.approx(0.25 * inside)
    assert p[15, 3] == 0.0


def test_mixture_floor_and_continuous_mass():
    g = Grid.square(200)
    m = GaussianMixture(
        means=((0.2, 0.2), (0.9, 0.5)), stds=(0.05, 0.2), weights=(1, 3), floor=0.25
    )
    p = m.on_grid(g)
    assert p.min() >= 0.25 - 1e-12
    x, y = g.mesh
    # the continuous density integrates to 1 (exact erf normalisation), midpoint rule
    assert g.integrate(m.evaluate(x, y, g)) == pytest.approx(1.0, rel=1e-5)


@pytest.mark.parametrize("density", [Box(0.1, 0.4, 0.2, 0.9), DEFAULT_TARGET], ids=str)
def test_samples_follow_the_density(density, rng):
    g = Grid.square(10)
    n = 200_000
    pts = density.sample(n, g, rng)
    assert pts.shape == (2, n) and g.contains(pts[0], pts[1]).all()
    counts, _, _ = np.histogram2d(pts[1], pts[0], bins=(10, 10), range=((0, 1), (0, 1)))
    prob = density.on_grid(Grid.square(200)).reshape(10, 20, 10, 20).mean(axis=(1, 3)) * 0.01
    # chi-square statistic with 99 degrees of freedom: mean 99, sd 14
    mask = prob > 0
    chi2 = np.sum((counts[mask] - n * prob[mask]) ** 2 / (n * prob[mask]))
    assert chi2 < 99 + 6 * 14
    assert counts[~mask].sum() == 0


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda: Box(0.5, 0.4, 0.0, 1.0), "x1"),
        (lambda: GaussianMixture([[0.5, 0.5]], [0], [1]), "stds"),
        (lambda: GaussianMixture([[0.5, 0.5]], [0.1], [1], floor=0), "floor"),
        (lambda: GaussianMixture([[0.5, 0.5]], [0.1], [1], floor=1.5), "floor"),
        (lambda: GaussianMixture([[0.5]], [0.1], [1]), "pairs"),
        (lambda: GaussianMixture([], [], []), "means"),
        (lambda: GaussianMixture([[0.5, 0.5]], [0.1, 0.2], [1]), "stds"),
        (lambda: GaussianMixture([[0.5, 0.5]], [0.1], ["a"]), "weights"),
    ],
)
def test_bad_densities_give_clear_errors(make, match):
    with pytest.raises(ParameterError, match=match):
        make()


def test_box_outside_the_domain_is_refused_on_the_grid():
    with pytest.raises(ValueError, match="box"):
        Box(-0.1, 0.4, 0.0, 1.0).on_grid(Grid.square(10))


def test_target_must_be_positive():
    g = Grid.square(10)
    with pytest.raises(ValueError, match="strictly positive"):
        Target.from_density(g, Box(0.2, 0.8, 0.2, 0.8))
