"""The sampled-data step bound against the held loop itself, and the KDE smoothing it
relies on against the analytic action of a mirrored Gaussian on cosine modes."""

import numpy as np
import pytest

from harness.control.field import grid_modes, sampled_data_dt_bound
from harness.control.paper import PaperControl
from harness.estimators.smoothing import Smoother, transfer
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.runs.build import build
from harness.runs.checks import ConfigError
from harness.targets.densities import Target, Uniform

ALPHA, SIGMA = 0.003, 1e-9


def cosine(grid, i, j):
    x, y = grid.mesh
    return np.cos(i * np.pi * x) * np.cos(j * np.pi * y)


@pytest.mark.parametrize("n,h,i,j", [(30, 0.04, 3, 5), (32, 0.1, 6, 2), (64, 0.04, 10, 0)])
def test_smoother_multiplies_cosine_modes_by_the_gaussian_transfer(n, h, i, j):
    g = Grid.square(n)
    mode = cosine(g, i, j)
    smooth, grad = Smoother(g, h)(mode)
    k = np.pi * np.hypot(i, j)
    factor = transfer(np.array(k), h)
    np.testing.assert_allclose(smooth, factor * mode, atol=1e-9)
    x, y = g.mesh
    gx = -i * np.pi * np.sin(i * np.pi * x) * np.cos(j * np.pi * y)
    gy = -j * np.pi * np.cos(i * np.pi * x) * np.sin(j * np.pi * y)
    np.testing.assert_allclose(grad, factor * np.stack([gx, gy]), atol=1e-7 * max(k, 1))


@pytest.mark.parametrize(
    "nx,ny,lx,ly",
    [(64, 64, 1, 1), (128, 128, 1, 1), (100, 80, 1, 0.8), (256, 256, 1, 1), (200, 150, 1, 1)],
)
def test_smoother_transform_form_equals_the_kernel_matrices_on_fine_grids(nx, ny, lx, ly, rng):
    """Where the aliasing factor is below round-off the transforms and the kernel
    matrices give the same field and gradient for a rough density, also with dx != dy
    (the transforms are used from TRANSFORM_MIN_SIDE cells per side on, where they are
    the faster form)."""
    from harness.estimators.smoothing import ALIAS_TOLERANCE, TRANSFORM_MIN_SIDE

    g = Grid(nx, ny, 0.0, lx, 0.0, ly)
    sm = Smoother(g, 0.04)
    assert np.exp(-0.5 * (np.pi * 0.04 / max(g.dx, g.dy)) ** 2) <= ALIAS_TOLERANCE
    assert sm.spectral == (min(nx, ny) >= TRANSFORM_MIN_SIDE)
    p = rng.random(g.shape)
    (a, ga), (b, gb) = sm.matrices(p), sm.transformed(p)
    np.testing.assert_allclose(b, a, atol=1e-13 * np.abs(a).max())
    np.testing.assert_allclose(gb, ga, atol=1e-12 * np.abs(ga).max())


def test_smoother_keeps_the_matrices_for_kernels_wide_enough_to_see_further_images():
    """The matrices hold one image per wall, the transforms all: for h = 0.25 on the
    unit square the two differ by per cents, and the transforms are not used."""
    g = Grid.square(256)
    sm = Smoother(g, 0.25)
    assert not sm.spectral
    p = np.random.default_rng(0).random(g.shape)
    ga, gb = sm.matrices(p)[1], sm.transformed(p)[1]
    assert np.abs(gb - ga).max() > 1e-3 * np.abs(ga).max()


def test_smoother_forms_differ_on_coarse_grids_by_the_alias_of_the_sampling():
    """On the paper's grid the matrices see the mode next to Nyquist through its alias
    about the sampling wavenumber 2 pi / dx (Poisson summation); the transforms do not:
    the difference is the alias's Gaussian factor, which is why the matrices stay there."""
    g = Grid.square(30)
    sm = Smoother(g, 0.04)
    assert not sm.spectral
    a = g.nx - 1
    mode = cosine(g, a, 0)
    (m, _), (t, _) = sm.matrices(mode), sm.transformed(mode)
    alias = transfer(np.array(2 * np.pi / g.dx - a * np.pi), 0.04)
    np.testing.assert_allclose(t, transfer(np.array(a * np.pi), 0.04) * mode, atol=1e-12)
    np.testing.assert_allclose(m - t, alias * mode, rtol=1e-3, atol=1e-9)


def held_loop(grid, estimate, dt, mode, steps=30, eps=1e-6):
    """Amplitudes of ``mode`` in the paper's held loop about the uniform target."""
    target = Target.from_density(grid, Uniform())
    model = FokkerPlanck(grid, SIGMA)
    control = PaperControl(target, ALPHA, SIGMA)
    p = 1.0 + eps * mode
    amplitudes = []
    for _ in range(steps):
        v = control.field(*estimate(p))
        p = model.step(p, v, dt)
        amplitudes.append(grid.inner(p - 1.0, mode) / grid.inner(mode, mode))
    return np.array(amplitudes)


@pytest.mark.parametrize("smoothed", [False, True])
def test_bound_separates_decay_from_growth_of_the_worst_mode(smoothed):
    g = Grid.square(32)
    h = 0.1 if smoothed else None
    feedback, diffusion = grid_modes(g, h)
    j, i = np.unravel_index(np.argmax(ALPHA * feedback - SIGMA * diffusion), feedback.shape)
    mode = cosine(g, i, j)
    if smoothed:
        smoother = Smoother(g, h)
        estimate = smoother
    else:
        estimate = lambda p: (p, g.gradient(p))  # noqa: E731  (exact estimates)
    bound = sampled_data_dt_bound(g, ALPHA, h, SIGMA)
    below = held_loop(g, estimate, 0.97 * bound, mode)
    above = held_loop(g, estimate, 1.03 * bound, mode)
    assert abs(below[-1]) < abs(below[0]) and abs(above[-1]) > 2 * abs(above[0])
    # the per-step factor is the one the derivation predicts
    for dt, amps in ((0.97 * bound, below), (1.03 * bound, above)):
        predicted = (1 - dt * ALPHA * feedback[j, i]) / (1 + dt * SIGMA * diffusion[j, i])
        np.testing.assert_allclose(amps[1:] / amps[:-1], predicted, rtol=1e-3)


def test_the_kde_bound_does_not_shrink_with_the_grid():
    bounds = [sampled_data_dt_bound(Grid.square(n), ALPHA, 0.04, 5e-5) for n in (30, 64, 128, 256)]
    exact = [sampled_data_dt_bound(Grid.square(n), ALPHA, None, 5e-5) for n in (30, 64, 128, 256)]
    assert min(bounds) > 1.0 and max(bounds) / min(bounds) < 1.2
    # exact estimates: the grid sets it, ~ dx^2
    assert exact[-1] < exact[0] / 50
    # and the peak of k^2 exp(-k^2 h^2 / 2) is 2 / (e h^2)
    peak = 2 / (np.e * 0.04**2)
    assert 2 / (ALPHA * bounds[-1]) == pytest.approx(peak, rel=0.15)


def test_validation_follows_the_estimates_resolution(compose):
    # the agent loop on the raw KDE is stable at n = 256 with the paper's dt ...
    build(compose(["grid.n=256", "estimator=kde", "agents.n=10"]))
    # ... the mean-field loop with exact estimates is not
    with pytest.raises(ConfigError, match=r"sim\.dt=0\.01.*grid resolution"):
        build(compose(["grid.n=256", "plant=meanfield", "estimator=exact"]))
    build(compose(["grid.n=256", "plant=meanfield", "estimator=exact", "sim.dt=0.004"]))
