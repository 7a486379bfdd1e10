import dataclasses

import numpy as np
import pytest

from harness.grid import Grid


def test_geometry_of_rectangle():
    g = Grid(8, 4, 0.0, 2.0, 1.0, 2.0)
    assert g.shape == (4, 8)
    assert g.dx == pytest.approx(0.25) and g.dy == pytest.approx(0.25)
    assert g.cell_area == pytest.approx(0.0625)
    assert g.x[0] == pytest.approx(0.125) and g.x[-1] == pytest.approx(1.875)
    assert g.y[0] == pytest.approx(1.125)
    x, y = g.mesh
    assert x.shape == g.shape and y[2, 0] == pytest.approx(g.y[2])


def test_grid_is_immutable():
    g = Grid.square(10)
    with pytest.raises(dataclasses.FrozenInstanceError):
        g.nx = 5


@pytest.mark.parametrize(
    "args", [(3, 10), (10, 2), (10.5, 10), (10, 10, 1.0, 0.0), (10, 10, 0.0, 1.0, 1.0, 1.0)]
)
def test_bad_grids_are_rejected(args):
    with pytest.raises(ValueError):
        Grid(*args)


def test_integral_and_norm_of_known_functions():
    g = Grid(40, 20, 0.0, 2.0, 0.0, 1.0)
    x, y = g.mesh
    assert g.integrate(np.ones(g.shape)) == pytest.approx(2.0)
    # midpoint rule on a bilinear function is exact
    assert g.integrate(x * y) == pytest.approx(2.0 * 0.5, rel=1e-12)
    assert g.l2(np.full(g.shape, 3.0)) == pytest.approx(3.0 * np.sqrt(2.0))
    assert g.inner(x, np.ones(g.shape)) == pytest.approx(2.0)


def test_gradient_is_exact_for_quadratics_inside_and_matches_matrix():
    g = Grid(12, 9, 0.0, 1.5, -1.0, 1.0)
    x, y = g.mesh
    f = 3 * x**2 - 2 * x * y + y**2 + x
    grad = g.gradient(f)
    np.testing.assert_allclose(grad[0][:, 1:-1], (6 * x - 2 * y + 1)[:, 1:-1], atol=1e-11)
    np.testing.assert_allclose(grad[1][1:-1, :], (-2 * x + 2 * y)[1:-1, :], atol=1e-11)
    np.testing.assert_allclose(
        (g.gradient_matrix @ f.ravel()).reshape(2, *g.shape), grad, atol=1e-12
    )


@pytest.mark.parametrize("a,b", [(1, 0), (3, 2), (7, 5), (11, 8)])
def test_gradient_maps_cosine_modes_to_sine_modes(a, b):
    """Reflecting ghost cells: exact DCT-to-DST map, also in the wall cells."""
    g = Grid(12, 9, 0.0, 1.5, -1.0, 1.0)
    lx, ly = 1.5, 2.0
    x, y = g.mesh
    cx, cy = np.cos(a * np.pi * x / lx), np.cos(b * np.pi * (y + 1) / ly)
    sx, sy = np.sin(a * np.pi * x / lx), np.sin(b * np.pi * (y + 1) / ly)
    grad = g.gradient(cx * cy)
    kx = np.sin(a * np.pi * g.dx / lx) / g.dx
    ky = np.sin(b * np.pi * g.dy / ly) / g.dy
    np.testing.assert_allclose(grad[0], -kx * sx * cy, atol=1e-12)
    np.testing.assert_allclose(grad[1], -ky * cx * sy, atol=1e-12)


def test_gradient_converges_at_second_order_for_neumann_fields():
    errors = []
    for n in (16, 32, 64):
        g = Grid.square(n)
        x, y = g.mesh
        f = np.exp(np.cos(np.pi * x)) * np.cos(2 * np.pi * y)  # zero normal derivative
        exact = np.stack(
            [
                -np.pi * np.sin(np.pi * x) * np.exp(np.cos(np.pi * x)) * np.cos(2 * np.pi * y),
                -2 * np.pi * np.exp(np.cos(np.pi * x)) * np.sin(2 * np.pi * y),
            ]
        )
        errors.append(g.l2(g.gradient(f) - exact))
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(rates > 1.8), rates
