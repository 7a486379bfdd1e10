"""The KDE and the smoother on free space (harness/estimators/diffusion.py): the kernel is
diffusion for h^2/2 with no flux through closed faces; no mass in obstacles, unit mass on
free space, no leak through thin walls, E[KDE] = K_h p exactly, bias falling with h and
noise with N, and on the open square the reflected-Gaussian KDE up to the discretisation.
"""

import numpy as np
import pytest
import scipy.fft as sfft
import scipy.linalg as sla

from harness.compiled.binning import free_binning
from harness.domains.base import FreeSpace, components
from harness.domains.obstacles import Obstacles
from harness.domains.rooms import Rooms
from harness.estimators.diffusion import (
    FreeKernel,
    HeatKernel,
    bin_reference,
    gradient_matrix,
    refine,
)
from harness.estimators.kde import KDE
from harness.estimators.smoothing import Smoother, smoothed_target
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.targets.densities import GaussianMixture, Target
from harness.velocity import VelocityField

H = 0.04

DOMAINS = {
    "rooms": Rooms(),
    "obstacles": Obstacles(
        discs=[{"center": [0.5, 0.5], "radius": 0.15}],
        polygons=[[[0.1, 0.7], [0.3, 0.7], [0.3, 0.8], [0.1, 0.8]]],
    ),
}


def open_square(grid):
    """The square expressed as free space: every cell free and every face open."""
    cells = np.ones(grid.shape, bool)
    fx, fy = np.ones((grid.ny, grid.nx - 1), bool), np.ones((grid.ny - 1, grid.nx), bool)
    return FreeSpace(grid, cells, fx, fy, components(cells, fx, fy), np.zeros((16, 16), np.uint8))


def sample_cells(free, p, n, rng):
    """``n`` robots from the density ``p`` constant on each cell (uniform inside it)."""
    g = free.grid
    mass = (np.where(free.cells, p, 0.0) * g.cell_area).ravel()
    cell = rng.choice(g.size, size=n, p=mass / mass.sum())
    j, i = np.divmod(cell, g.nx)
    return np.stack([g.x0 + (i + rng.random(n)) * g.dx, g.y0 + (j + rng.random(n)) * g.dy])


@pytest.mark.parametrize("name", DOMAINS)
def test_the_free_space_kde_has_no_mass_in_obstacles_and_unit_mass_on_free_space(name, rng):
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    kde = KDE(grid, H, free=free)
    positions = sample_cells(free, np.ones(grid.shape), 2000, rng)
    positions[:, :50] = rng.uniform(0, 1, size=(2, 50))  # some in obstacles too
    p, grad = kde(positions)
    assert (p[~free.cells] == 0).all() and (grad[:, ~free.cells] == 0).all()
    assert p.min() >= 0
    # point values at the centres: unit mass up to the midpoint rule on a smooth field
    assert grid.integrate(p) == pytest.approx(1.0, abs=1e-8)
    # the diffused fine field itself carries the robots' mass to round-off
    k = kde.diffusion
    w = free_binning(
        positions, 0.0, 1.0, 0.0, 1.0, k.fine.grid.nx, k.fine.grid.ny, k.targets, k.home
    )
    assert k.heat(w.ravel()).sum() == pytest.approx(1.0, abs=1e-13)


def test_the_kernel_does_not_leak_through_a_thin_wall(rng):
    # a wall of a quarter bandwidth with no door: the Gaussian with images puts
    # exp(-(0.01)^2 / (2 h^2)) ~ 97 % of a peak across it; diffusion puts nothing
    grid = Grid.square(64)
    free = Obstacles(polygons=[[[0.49, 0.0], [0.51, 0.0], [0.51, 1.0], [0.49, 1.0]]]).resolve(grid)
    assert free.n_components == 2
    left = rng.uniform([0.40, 0.2], [0.485, 0.8], size=(400, 2)).T
    p, _ = KDE(grid, H, free=free)(left)
    assert (p[free.labels == 1] == 0).all()
    assert grid.integrate(np.where(free.labels == 0, p, 0.0)) == pytest.approx(1.0, abs=1e-8)
    p_plain, _ = KDE(grid, H)(left)
    assert grid.integrate(np.where(free.labels == 1, p_plain, 0.0)) > 0.05


@pytest.mark.parametrize("name", DOMAINS)
def test_the_compiled_binning_equals_the_plain_statement(name, rng):
    grid = Grid.square(30)
    k = FreeKernel(DOMAINS[name].resolve(grid), H)
    positions = rng.uniform(-0.01, 1.01, size=(2, 5000))
    fg = k.fine.grid
    fast = free_binning(positions, fg.x0, fg.x1, fg.y0, fg.y1, fg.nx, fg.ny, k.targets, k.home)
    ref = bin_reference(k.fine, k.targets, k.home, positions)
    np.testing.assert_allclose(fast, ref, atol=1e-15)
    assert fast.sum() == pytest.approx(1.0, abs=1e-13)
    assert (fast[~k.fine.cells] == 0).all()


@pytest.mark.parametrize("name", DOMAINS)
def test_binning_sends_no_share_through_a_closed_face(name, rng):
    grid = Grid.square(20)
    free = refine(DOMAINS[name].resolve(grid), 2)
    k_targets = FreeKernel(DOMAINS[name].resolve(grid), H, refine_by=2).targets
    g = free.grid
    idx = np.arange(g.size).reshape(g.shape)
    linked = {(int(c), int(c)) for c in idx[free.cells]}
    for a, b in zip(idx[:, :-1][free.face_x], idx[:, 1:][free.face_x], strict=True):
        linked |= {(int(a), int(b)), (int(b), int(a))}
    for a, b in zip(idx[:-1, :][free.face_y], idx[1:, :][free.face_y], strict=True):
        linked |= {(int(a), int(b)), (int(b), int(a))}
    for c in idx[free.cells]:
        for q in range(4):
            own, xn, yn, diag = k_targets[c, q]
            assert own == c and (c, xn) in linked and (c, yn) in linked
            # the diagonal share reaches its cell through an open neighbour
            assert diag == xn or diag == yn or (xn, diag) in linked or (yn, diag) in linked


@pytest.mark.parametrize("name", DOMAINS)
def test_the_free_space_gradient_matrix_is_the_free_space_gradient(name, rng):
    grid = Grid.square(24)
    free = DOMAINS[name].resolve(grid)
    f = rng.random(grid.shape)
    got = (gradient_matrix(free) @ f.ravel()).reshape(2, *grid.shape)
    np.testing.assert_allclose(got, free.gradient(f), atol=1e-12)


@pytest.mark.parametrize("name", DOMAINS)
def test_the_heat_kernel_is_the_matrix_exponential_and_keeps_component_masses(name, rng):
    grid = Grid.square(16)
    free = DOMAINS[name].resolve(grid)
    t = 0.5 * 0.08**2
    a = FokkerPlanck(grid, 1.0, free=free).matrix(VelocityField.zeros(grid)).toarray()
    exact = sla.expm(t * a)
    f = np.where(free.cells, rng.random(grid.shape), 0.0).ravel()
    # a tight tail: the series is the exponential to round-off
    tight = HeatKernel(free, t, tol=1e-14)(f)
    assert np.abs(tight - exact @ f).max() < 1e-12 * np.abs(f).max() * grid.size
    # the default tail: within its documented bound, 2 tol in the 2-norm
    heat = HeatKernel(free, t)
    got = heat(f)
    assert np.linalg.norm(got - exact @ f) <= 2 * heat.tol * np.linalg.norm(f) + 1e-13
    for c in range(free.n_components):
        on = (free.labels == c).ravel()
        assert got[on].sum() == pytest.approx(f[on].sum(), rel=1e-14)
    assert (got[~free.cells.ravel()] == 0).all()


def test_the_heat_kernel_on_the_open_square_is_the_neumann_cosine_transfer(rng):
    # the drift-free operator on the open square is diagonal in the DCT-II modes, with
    # eigenvalues -(4 / dx^2) sin^2(pi a / 2n) per axis: exp(t A) in closed form
    grid = Grid.square(40)
    t = 0.5 * H**2
    f = rng.random(grid.shape)
    got = HeatKernel(open_square(grid), t)(f.ravel()).reshape(grid.shape)
    lam = 4.0 / grid.dx**2 * np.sin(np.pi * np.arange(40) / 80) ** 2
    transfer = np.exp(-t * (lam[:, None] + lam[None, :]))
    exact = sfft.idctn(sfft.dctn(f, norm="ortho") * transfer, norm="ortho")
    np.testing.assert_allclose(got, exact, atol=1e-12)


@pytest.mark.parametrize("cells_per_h", [3, 5, 10])
def test_the_grid_heat_kernel_departs_from_the_gaussian_by_the_stated_leading_term(cells_per_h):
    # per axis, max_kappa |exp(-t 4 sin^2(kappa s / 2) / s^2) - exp(-t kappa^2)| is
    # 4 e^-2 / 12 (s^2 / t) to leading order in s^2 / t (module docstring): 2 % above
    # it at s = h / 3, converging to it
    t, s = 0.5 * H**2, H / cells_per_h
    kappa = np.linspace(0.0, np.pi / s, 20000)  # up to the grid's Nyquist
    lam = 4.0 / s**2 * np.sin(kappa * s / 2) ** 2
    gap = np.abs(np.exp(-t * lam) - np.exp(-t * kappa**2)).max()
    lead = 4 * np.exp(-2) / 12 * s**2 / t
    assert lead <= gap <= lead * (1 + 0.12 * s**2 / t)


@pytest.mark.parametrize("r", [3, 5])
def test_on_the_open_square_the_diffusion_kde_is_the_reflected_gaussian_kde(r, rng):
    # Leading errors against the Gaussian with wall images, both O((s / h)^2) of a kernel
    # peak for the fine spacing s = dx / r (module docstring): bilinear binning at most
    # (s^2 / 8)(|K_xx| + |K_yy|) <= (s / h)^2 / 4 of a peak, and the grid's heat kernel
    # 0.090 (s / h)^2 per axis, 0.18 (s / h)^2 in 2-D; the gradient, read by a central
    # difference over 2 s, adds s^2 / 6 |p'''| ~ (s / h)^2 / 2 of its own peak.
    grid = Grid.square(30)
    s_h = grid.dx / r / H
    positions = rng.uniform(0, 1, size=(2, 4000))
    p_d, g_d = FreeKernel(open_square(grid), H, refine_by=r).kde(positions)
    p_g, g_g = KDE(grid, H, method="exact")(positions)
    value_tol = s_h**2 * (1 / 4 + 0.18)
    assert grid.l2(p_d - p_g) <= value_tol * grid.l2(p_g)
    assert grid.l2(g_d - g_g) <= (value_tol + 0.5 * s_h**2) * grid.l2(g_g)


def test_on_the_open_square_the_diffusion_kde_converges_like_the_fine_spacing_squared(rng):
    grid = Grid.square(30)
    positions = rng.uniform(0, 1, size=(2, 4000))
    p_g, _ = KDE(grid, H, method="exact")(positions)
    free = open_square(grid)
    err = [grid.l2(FreeKernel(free, H, refine_by=r).kde(positions)[0] - p_g) for r in (2, 4)]
    assert 4 / 1.6 < err[0] / err[1] < 4 * 1.6  # halving s divides the error by 4


def test_on_the_square_without_free_space_the_kde_is_unchanged(rng):
    grid = Grid.square(30)
    positions = rng.uniform(0, 1, size=(2, 700))
    p0, g0 = KDE(grid, H)(positions)
    p1, g1 = KDE(grid, H, free=None)(positions)
    assert np.array_equal(p0, p1) and np.array_equal(g0, g1)
    smooth = Smoother(grid, H)
    assert smooth.diffusion is None


@pytest.mark.parametrize("name", DOMAINS)
def test_the_kde_expectation_is_the_smoother_of_the_density(name, rng):
    # E[KDE] = K_h p exactly for robots drawn from p constant on cells: the mean of
    # many KDEs approaches the smoother like 1 / sqrt(repeats)
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    p = free.restrict(0.2 + rng.random(grid.shape))
    kernel = FreeKernel(free, H)
    expected, _ = kernel.smooth(p)
    total = np.zeros(grid.shape)
    repeats, n = 40, 5000
    sq_err = []
    for _ in range(repeats):
        est, _ = kernel.kde(sample_cells(free, p, n, rng))
        total += est
        sq_err.append(grid.l2(est - expected) ** 2)
    # the mean of R KDEs has mean squared error E||KDE - K_h p||^2 / R
    assert grid.l2(total / repeats - expected) ** 2 < 3 * np.mean(sq_err) / repeats


@pytest.mark.parametrize("name", DOMAINS)
def test_the_kde_noise_falls_like_one_over_n(name, rng):
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    p = free.restrict(0.2 + rng.random(grid.shape))
    kernel = FreeKernel(free, H)
    expected, _ = kernel.smooth(p)

    def mse(n):
        return np.mean(
            [
                grid.l2(kernel.kde(sample_cells(free, p, n, rng))[0] - expected) ** 2
                for _ in range(30)
            ]
        )

    small, large = mse(1000), mse(16000)
    assert 16 / 1.5 < small / large < 16 * 1.5
    # and matches the KDE's noise constant k = 1 / (4 pi N h^2) per unit density, up
    # to the walls' reflection (which raises it near them) and the discretisation
    k = 1 / (4 * np.pi * 16000 * H**2)
    assert 0.7 * k < large < 2.0 * k


@pytest.mark.parametrize("name", DOMAINS)
def test_the_smoothing_bias_vanishes_as_h_shrinks(name):
    # Bias of K_h p against p: O(h^2) inside, O(h) in a layer of width h at walls where
    # p's normal derivative does not vanish: O(h^{3/2}) in L2 (smoothing module
    # docstring). Measured on a fine grid (cells below h / 3 for every h here).
    grid = Grid.square(120)
    free = DOMAINS[name].resolve(grid)
    target = Target.from_density(
        grid,
        GaussianMixture(means=((0.3, 0.35), (0.7, 0.6)), stds=(0.1, 0.08), weights=(0.6, 0.4)),
        free,
    )
    errors = []
    hs = [0.08, 0.04, 0.02]
    for h in hs:
        smoothed, _ = Smoother(grid, h, free=free)(target.p)
        errors.append(grid.l2(smoothed - target.p))
    rates = np.log(np.array(errors[:-1]) / np.array(errors[1:])) / np.log(2)
    assert (rates > 1.3).all(), rates
    assert (rates < 2.2).all(), rates


@pytest.mark.parametrize("name", DOMAINS)
def test_the_smoothed_target_is_the_free_space_kernel_of_the_target(name):
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    target = Target.from_density(
        grid,
        GaussianMixture(means=((0.3, 0.35), (0.7, 0.6)), stds=(0.1, 0.08), weights=(0.6, 0.4)),
        free,
    )
    smooth = smoothed_target(target, H)
    assert smooth.free is free
    np.testing.assert_allclose(smooth.p, free.restrict(Smoother(grid, H, free=free)(target.p)[0]))
    assert (smooth.p[~free.cells] == 0).all()
    assert grid.integrate(smooth.p) == pytest.approx(1.0, abs=1e-12)
