"""The paper's filters on free space (estimator=filters, engine local): the band of the
masked Laplacian, the gradient update's Poisson solve without the rectangle's transforms,
no estimate mass in obstacles, the prediction's mass kept per component, convergence to
exact measurements; the dense engines refused there.
"""

import numpy as np
import pytest
import scipy.fft as sfft

from harness.domains.base import FreeSpace, components
from harness.domains.rooms import Rooms
from harness.estimators.diffusion import gradient_matrix
from harness.estimators.filters.common import (
    BandLimit,
    FilterSettings,
    FreeBand,
    MeasurementModel,
    correlations_from_factors,
)
from harness.estimators.filters.estimator import FilterEstimator
from harness.estimators.filters.free_poisson import FreePoisson
from harness.estimators.filters.local import LocalFilters
from harness.estimators.smoothing import Smoother
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.parameters import ParameterError
from harness.velocity import VelocityField
from tests.domain_cases import DOMAINS

H = 0.04
SIGMA = 5e-4


def open_square(grid):
    cells = np.ones(grid.shape, bool)
    fx, fy = np.ones((grid.ny, grid.nx - 1), bool), np.ones((grid.ny - 1, grid.nx), bool)
    return FreeSpace(grid, cells, fx, fy, components(cells, fx, fy), np.zeros((16, 16), np.uint8))


def component_masses(free, p):
    labels = free.labels.ravel()
    on = labels >= 0
    return np.bincount(labels[on], np.asarray(p).ravel()[on], free.n_components)


@pytest.mark.parametrize("name", DOMAINS)
def test_the_free_band_is_an_orthogonal_projector_keeping_component_masses(name, rng):
    grid = Grid.square(24)
    free = DOMAINS[name].resolve(grid)
    band = FreeBand(free, 2.5 / 0.06)
    pi = band.matrix()
    np.testing.assert_allclose(pi, pi.T, atol=1e-12)
    np.testing.assert_allclose(pi @ pi, pi, atol=1e-10)
    f = rng.random(grid.size)
    out = band(f)
    assert (out[~free.cells.ravel()] == 0).all()
    np.testing.assert_allclose(component_masses(free, out), component_masses(free, f), rtol=1e-12)


def test_on_the_open_square_the_free_band_lies_in_the_rectangles_band(rng):
    grid = Grid.square(30)
    free_band, band = FreeBand(open_square(grid), 2.5 / H), BandLimit(grid, 2.5 / H)
    f = rng.random(grid.size)
    inside = free_band(f)
    np.testing.assert_allclose(band(inside), inside, atol=1e-11)
    assert 0.8 * band.mask.sum() < free_band.modes.shape[1] <= band.mask.sum()


def test_correlations_from_factors_are_the_rectangles_band_correlations():
    grid = Grid.square(20)
    band = BandLimit(grid, 2.5 / 0.08)
    c_y = sfft.dct(np.eye(grid.ny), type=2, norm="ortho", axis=0)
    c_x = sfft.dct(np.eye(grid.nx), type=2, norm="ortho", axis=0)
    rows, cols = np.nonzero(band.mask)
    modes = np.stack([np.outer(c_y[b], c_x[a]).ravel() for b, a in zip(rows, cols, strict=True)], 1)
    grad = grid.gradient_matrix @ modes
    m = grid.size
    got = correlations_from_factors([modes, grad[:m], grad[m:]], grid)
    np.testing.assert_allclose(got, band.correlations(), atol=1e-10)


@pytest.mark.parametrize("name", DOMAINS)
def test_the_free_space_poisson_solve_is_the_least_squares_gradient_fit(name, rng):
    grid = Grid.square(20)
    free = DOMAINS[name].resolve(grid)
    poisson = FreePoisson(free)
    g = gradient_matrix(free)
    cells = free.cells.ravel()
    c = rng.uniform(0.5, 2.0, size=2 * grid.size)
    v = rng.normal(size=2 * grid.size)
    b = g.T @ (c * v)
    got = poisson.solve(c, b)
    # brute force: the dense weighted least-squares fit on the free cells
    gf = g[:, cells].toarray() * np.sqrt(c)[:, None]
    ref = np.zeros(grid.size)
    ref[cells] = np.linalg.lstsq(gf, np.sqrt(c) * v, rcond=None)[0]
    labels = free.labels.ravel()[cells]
    for comp in range(free.n_components):  # zero mean per component
        sel = np.flatnonzero(cells)[labels == comp]
        ref[sel] -= ref[sel].mean()
        assert abs(got[sel].mean()) < 1e-12 * np.abs(got).max()
    np.testing.assert_allclose(got, ref, atol=1e-8 * np.abs(ref).max())
    assert (got[~cells] == 0).all()


def filters_on(free, band_limit=2.5):
    meas = MeasurementModel(1024, H, FilterSettings(band_limit=band_limit))
    return LocalFilters(free.grid, SIGMA, 0.01, meas, free)


@pytest.mark.parametrize("name", DOMAINS)
def test_the_filters_estimate_has_no_mass_in_obstacles(name, rng):
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    f = filters_on(free)
    smooth = Smoother(grid, H, free=free)
    y, gy = smooth(free.restrict(0.2 + rng.random(grid.shape)))
    f.initialize(y, gy)
    op = FokkerPlanck(grid, SIGMA, free=free)
    for _ in range(5):
        v = VelocityField.from_centres(rng.normal(scale=0.02, size=(2, *grid.shape)))
        p_hat, q_hat = f.step(y, gy, v, op.matrix(v))
        assert (p_hat[~free.cells] == 0).all() and (q_hat[:, ~free.cells] == 0).all()


@pytest.mark.parametrize("name", DOMAINS)
def test_the_density_filters_prediction_keeps_the_mass_of_every_component(name, rng):
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    f = filters_on(free)
    y, gy = Smoother(grid, H, free=free)(free.restrict(0.2 + rng.random(grid.shape)))
    f.initialize(y, gy)
    for _ in range(4):
        before = component_masses(free, f.x)
        before_g = component_masses(free, f.x_g)
        v = VelocityField.from_centres(rng.normal(scale=0.05, size=(2, *grid.shape)))
        f.step(y, gy, v)
        np.testing.assert_allclose(component_masses(free, f.x_prior), before, rtol=1e-12)
        np.testing.assert_allclose(component_masses(free, f.x_g_prior), before_g, rtol=1e-12)


@pytest.mark.parametrize("name", DOMAINS)
def test_with_exact_measurements_the_filters_converge_to_the_measured_density(name, rng):
    # the truth is a steady state of the model (constant on each component, v = 0), with
    # its own mass on each component; the filters start from another density
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    share = rng.uniform(0.2, 1.0, free.n_components)
    truth = np.where(free.cells, share[np.maximum(free.labels, 0)], 0.0)
    truth = free.restrict(truth)
    f = filters_on(free)
    start, g_start = Smoother(grid, H, free=free)(free.restrict(0.2 + rng.random(grid.shape)))
    f.initialize(start, g_start)
    v = VelocityField.zeros(grid)
    zero = np.zeros((2, *grid.shape))
    first = None
    for _ in range(400):
        p_hat, q_hat = f.step(truth, zero, v)
        first = grid.l2(p_hat - truth) if first is None else first
    assert grid.l2(p_hat - truth) < 1e-3 * first
    assert np.abs(q_hat).max() < 1e-3 * np.abs(g_start).max()


def test_the_dense_engines_are_refused_on_free_space():
    grid = Grid.square(16)
    model = FokkerPlanck(grid, SIGMA, free=Rooms().resolve(grid))
    with pytest.raises(ParameterError, match="engine"):
        FilterEstimator(grid, model, "reference", 1024, H, 0.01)
    assert FilterEstimator(grid, model, "local", 1024, H, 0.01).engine.filters.free is model.free
