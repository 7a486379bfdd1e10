"""The sampled-data step bound on free space (harness/control/field.py
free_space_dt_bound): never above the masked operator's true threshold (dense
eigen-solves on random layouts), tight on the rooms, and real: a dt above it grows an
error on a masked grid in the closed loop while one below does not.
"""

import numpy as np
import pytest

from harness.control.field import sampled_data_dt_bound
from harness.control.paper import paper_law
from harness.domains.base import FreeSpace, components
from harness.estimators.diffusion import FreeKernel, gradient_matrix
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.targets.densities import Target
from harness.velocity import VelocityField
from tests.domain_cases import DOMAINS

H = 0.04


def operators(free):
    """Dense ``F = G^T G`` (the held feedback with exact estimates) and the five-point
    diffusion ``L`` on the free cells."""
    cells = free.cells.ravel()
    g = gradient_matrix(free)[:, cells]
    lap = -FokkerPlanck(free.grid, 1.0, free=free).matrix(VelocityField.zeros(free.grid))
    return (g.T @ g).toarray(), lap.toarray()[np.ix_(cells, cells)]


def random_layout(rng):
    g = Grid(int(rng.integers(4, 13)), int(rng.integers(4, 13)), 0.0, 1.0, 0.0, 1.3)
    cells = rng.random(g.shape) < rng.uniform(0.4, 1.0)
    cells[0, 0] = True
    fx = cells[:, 1:] & cells[:, :-1] & (rng.random((g.ny, g.nx - 1)) < rng.uniform(0.5, 1))
    fy = cells[1:, :] & cells[:-1, :] & (rng.random((g.ny - 1, g.nx)) < rng.uniform(0.5, 1))
    return FreeSpace(g, cells, fx, fy, components(cells, fx, fy), np.zeros((4, 4), np.uint8))


def test_the_free_space_bound_never_exceeds_the_masked_operators_threshold(rng):
    # the step is stable exactly for dt lambda_max(D F - sigma L) <= 2 (both symmetric)
    for _ in range(150):
        free = random_layout(rng)
        f, lap = operators(free)
        for d, sigma in ((1.0, 0.0), (1.0, 0.05), (1.0, 0.7), (1.0, 1.0), (1.0, 2.0)):
            top = np.linalg.eigvalsh(d * f - sigma * lap).max()
            bound = sampled_data_dt_bound(free.grid, d, None, sigma, free)
            if sigma >= d:  # F <= L: no mode grows, the robots' diffusion wins
                assert bound == np.inf and top <= 1e-12 * (np.abs(lap).max() + 1.0)
            elif top > 1e-12 * np.abs(f).max():  # else the threshold is infinite too
                assert bound * top <= 2.0 * (1 + 1e-12)


@pytest.mark.parametrize("name", DOMAINS)
@pytest.mark.parametrize("n", [20, 25])
def test_the_free_space_bound_is_within_five_percent_of_the_threshold(name, n):
    free = DOMAINS[name].resolve(Grid.square(n))
    f, lap = operators(free)
    d, sigma = 0.003, 5e-5
    threshold = 2.0 / np.linalg.eigvalsh(d * f - sigma * lap).max()
    bound = sampled_data_dt_bound(free.grid, d, None, sigma, free)
    assert 0.95 * threshold <= bound <= threshold * (1 + 1e-12)


def perturbation_growth(free, alpha, sigma, dt, steps, rng):
    """``max |p - p_*|`` after ``steps`` closed-loop steps over its start, for the paper's
    law with exact estimates about a uniform target on free space (where the
    linearised step is ``(I + dt sigma L)^-1 (I - dt alpha F)`` exactly)."""
    g = free.grid
    target = Target.from_values(g, np.ones(g.shape), free)
    op = FokkerPlanck(g, sigma, free=free)
    p = free.restrict(target.p * (1.0 + 1e-8 * rng.standard_normal(g.shape)))
    start = np.abs(p - target.p).max()
    for _ in range(steps):
        v = paper_law(p, free.gradient(p), target, alpha, sigma)
        p = op.step(p, v, dt)
    return np.abs(p - target.p).max() / start


@pytest.mark.parametrize("name", DOMAINS)
def test_a_dt_above_the_bound_grows_an_error_on_a_masked_grid_and_one_below_does_not(name, rng):
    free = DOMAINS[name].resolve(Grid.square(20))
    alpha, sigma = 0.1, 5e-5
    bound = sampled_data_dt_bound(free.grid, alpha, None, sigma, free)
    assert perturbation_growth(free, alpha, sigma, 0.95 * bound, 150, rng) < 1.0
    assert perturbation_growth(free, alpha, sigma, 1.2 * bound, 150, rng) > 1e3


@pytest.mark.parametrize("name", DOMAINS)
def test_the_smoothed_feedbacks_eigenvalues_stay_within_the_bounds_scale(name):
    # the held feedback through estimates smoothed by the free-space kernel: G^T times
    # the smoothed gradient. At dt = 2 / (D top), top = 2 / (e h^2), every mode's
    # multiplier 1 - dt D mu stays in the unit disc (no credit taken for sigma)
    grid = Grid.square(16)
    free = DOMAINS[name].resolve(grid)
    kernel = FreeKernel(free, H)
    gt = gradient_matrix(free).T.tocsr()
    idx = np.flatnonzero(free.cells.ravel())
    f = np.empty((idx.size, idx.size))
    for j, c in enumerate(idx):
        e = np.zeros(grid.size)
        e[c] = 1.0
        f[:, j] = (gt @ kernel.smooth(e.reshape(grid.shape))[1].ravel())[idx]
    ev = np.linalg.eigvals(f)
    top = 2.0 / (np.e * H**2)
    assert np.abs(1.0 - 2.0 * ev / top).max() <= 1.0 + 1e-9
    d = 0.003
    bound = sampled_data_dt_bound(grid, d, H, 5e-5, free)
    assert bound == pytest.approx(2.0 / (d * top), rel=1e-12)


def test_on_the_square_the_bound_is_the_cosine_modes_bound():
    grid = Grid.square(30)
    assert sampled_data_dt_bound(grid, 0.003, H, 5e-5) == sampled_data_dt_bound(
        grid, 0.003, H, 5e-5, None
    )
