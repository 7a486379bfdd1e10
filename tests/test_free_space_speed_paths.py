"""The compiled paths of the loop on free space against their plain statements: the heat
kernel's Chebyshev series (harness/compiled/diffusion.py) and the gradient update's
conjugate gradients with a banded Cholesky factor (harness/compiled/free_poisson.py),
both equal to their sparse references to round-off; and the local filters' single
product with the free band equal to two.
"""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from harness.compiled.diffusion import chebyshev_heat
from harness.estimators.diffusion import FreeKernel, HeatKernel, five_point_stencil, refine
from harness.estimators.filters.common import FilterSettings, MeasurementModel
from harness.estimators.filters.free_poisson import FreePoisson
from harness.estimators.filters.local import LocalFilters
from harness.estimators.smoothing import Smoother
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.velocity import VelocityField
from tests.domain_cases import DOMAINS

H = 0.04


@pytest.mark.parametrize("name", DOMAINS)
def test_the_five_point_stencil_holds_the_operators_rows(name, rng):
    free = refine(DOMAINS[name].resolve(Grid(12, 9, 0.0, 1.0, 0.0, 0.8)), 2)
    g = free.grid
    a = FokkerPlanck(g, 1.0, free=free).matrix(VelocityField.zeros(g))
    st = five_point_stencil(a, g.nx)
    f = rng.random(g.size)
    pad = np.concatenate([np.zeros(g.nx), f, np.zeros(g.nx)])
    shifts = [pad[: g.size], pad[g.nx - 1 : g.nx - 1 + g.size], f,
              pad[g.nx + 1 : g.nx + 1 + g.size], pad[2 * g.nx :]]  # fmt: skip
    got = sum(st[k] * shifts[k] for k in range(5))
    np.testing.assert_allclose(got, a @ f, rtol=0, atol=1e-12 * np.abs(a).max())


@pytest.mark.parametrize("name", DOMAINS)
@pytest.mark.parametrize("r", [1, 2, 3])
def test_the_compiled_heat_kernel_equals_its_sparse_statement(name, r, rng):
    free = refine(DOMAINS[name].resolve(Grid.square(20)), r)
    heat = HeatKernel(free, 0.5 * H**2)
    f = np.where(free.cells, rng.random(free.grid.shape), 0.0).ravel()
    fast, ref = heat(f), heat.reference(f)
    assert np.abs(fast - ref).max() <= 1e-15 * heat.terms * np.abs(f).max()
    cols = np.column_stack([f, 2.0 * f[::-1] * free.cells.ravel()])
    np.testing.assert_allclose(heat(cols), heat.reference(cols), rtol=0, atol=1e-13)
    # mass kept to round-off on the fast path as on the reference
    assert fast.sum() == pytest.approx(f.sum(), rel=1e-13)


@pytest.mark.parametrize("n", [20, 30, 45])
def test_a_float32_stencil_is_used_only_where_exact_and_gives_the_same_bits(n, rng):
    free = refine(DOMAINS["rooms"].resolve(Grid.square(n)), 3)
    heat = HeatKernel(free, 0.5 * H**2)
    g = free.grid
    wide = five_point_stencil(heat.matrix, g.nx)
    assert heat.stencil is not None
    np.testing.assert_array_equal(heat.stencil.astype(np.float64), wide)
    f = np.where(free.cells, rng.random(g.shape), 0.0).ravel()
    s, c = heat.scale, heat.coefficients
    np.testing.assert_array_equal(heat(f), chebyshev_heat(f, wide, g.nx, s, c))


def test_a_stencil_float32_cannot_hold_stays_float64():
    free = refine(DOMAINS["rooms"].resolve(Grid(31, 29, 0.0, 1.0, 0.0, 0.93)), 3)
    heat = HeatKernel(free, 0.5 * H**2)
    assert heat.stencil is not None
    if heat.stencil.dtype == np.float32:  # exact on this grid after all: nothing to test
        pytest.skip("float32 holds this grid's weights")
    assert heat.stencil.dtype == np.float64


@pytest.mark.parametrize("name", DOMAINS)
def test_the_free_kde_through_the_compiled_kernel_equals_the_sparse_one(name, rng, monkeypatch):
    grid = Grid.square(30)
    kernel = FreeKernel(DOMAINS[name].resolve(grid), H)
    positions = rng.uniform(0, 1, size=(2, 1024))
    p, grad = kernel.kde(positions)
    monkeypatch.setattr(HeatKernel, "__call__", HeatKernel.reference)  # the sparse recurrence
    p_ref, grad_ref = kernel.kde(positions)
    np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-13 * p.max())
    np.testing.assert_allclose(grad, grad_ref, rtol=0, atol=1e-13 * np.abs(grad).max())


def pinned_dense(poisson, c):
    """The pinned operator on the whole grid from the sparse product (dense)."""
    op = (poisson.gt @ (c[:, None] * poisson.g.toarray())).copy()
    for i in np.flatnonzero(poisson._pinned):
        op[i, :] = 0.0
        op[:, i] = 0.0
        op[i, i] = 1.0
    return op


@pytest.mark.parametrize("name", DOMAINS)
@pytest.mark.parametrize("shape", [(20, 20), (24, 17), (15, 22)])
def test_the_free_poissons_pinned_band_is_the_pinned_sparse_operator(name, shape, rng):
    # cells of another aspect where the rectangle is shorter than the unit square, so that
    # every obstacle of the shared domains lies in it
    grid = Grid(shape[1], shape[0], 0.0, 1.0, 0.0, max(1.0, shape[0] / shape[1]))
    poisson = FreePoisson(DOMAINS[name].resolve(grid))
    c = rng.uniform(0.5, 2.0, size=2 * grid.size)
    ab = poisson.band_operator(c)
    dense = pinned_dense(poisson, c)[np.ix_(poisson._order, poisson._order)]
    band = np.zeros_like(dense)
    for t in range(ab.shape[0]):
        idx = np.arange(grid.size - t)
        band[idx + t, idx] = ab[t, : grid.size - t]
    np.testing.assert_allclose(band, np.tril(dense), rtol=0, atol=1e-10 * np.abs(dense).max())
    assert np.abs(np.tril(dense, -ab.shape[0])).max() == 0.0  # nothing outside the band


@pytest.mark.parametrize("name", DOMAINS)
def test_the_compiled_free_poisson_equals_its_sparse_statement(name, rng):
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    poisson = FreePoisson(free)
    for _ in range(6):  # the lagged factor serves several coefficient fields
        c = rng.uniform(0.5, 2.0, size=2 * grid.size)
        b = poisson.gt @ (c * rng.normal(size=2 * grid.size))
        fast = poisson.solve(c, b)
        ref = poisson.solve_reference(c, b)
        np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-9 * np.abs(ref).max())
        # and both solve the pinned system (a direct sparse solve) to the tolerance
        cells = free.cells.ravel()
        op = (poisson.gt @ (c[:, None] * poisson.g.toarray()))[np.ix_(cells, cells)]
        residual = op @ fast[cells] - b[cells]
        labels = free.labels.ravel()[cells]
        for comp in range(free.n_components):
            residual[labels == comp] -= residual[labels == comp].mean()
        assert np.linalg.norm(residual) <= 1e-9 * np.linalg.norm(b)
    # with a fresh factor: one iteration to the tolerance, equal to round-off
    poisson._refactor(c)
    fast = poisson.solve(c, b)
    assert poisson.iterations <= 2
    np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-11 * np.abs(ref).max())
    rhs = np.where(poisson._pinned, 0.0, b)
    direct = spla.spsolve(sp.csc_matrix(pinned_dense(poisson, c)), rhs)
    for comp in range(free.n_components):
        on = free.labels.ravel() == comp
        direct[on] -= direct[on].mean()
    direct[~cells] = 0.0
    np.testing.assert_allclose(fast, direct, rtol=0, atol=1e-8 * np.abs(direct).max())


@pytest.mark.parametrize("name", DOMAINS)
def test_the_local_filters_one_band_product_equals_two(name, rng):
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    meas = MeasurementModel(1024, H, FilterSettings())
    f = LocalFilters(grid, 5e-4, 0.01, meas, free)
    y, gy = Smoother(grid, H, free=free)(free.restrict(0.2 + rng.random(grid.shape)))
    f.initialize(y, gy)
    v = VelocityField.from_centres(rng.normal(scale=0.02, size=(2, *grid.shape)))
    band = f.band
    both = np.column_stack([f.x, f.x_g])
    np.testing.assert_allclose(
        band(both), np.column_stack([band(f.x), band(f.x_g)]), rtol=0, atol=1e-13
    )
    p_hat, q_hat = f.step(y, gy, v)
    assert (p_hat[~free.cells] == 0).all() and (q_hat[:, ~free.cells] == 0).all()
    np.testing.assert_allclose(band(f.x), f.x, rtol=0, atol=1e-12 * np.abs(f.x).max())
    np.testing.assert_allclose(band(f.x_g), f.x_g, rtol=0, atol=1e-12 * np.abs(f.x_g).max())
