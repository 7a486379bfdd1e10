"""The Fokker-Planck operator on free space (harness/domains): no flux through closed
faces, mass conserved on every component to round-off, the compiled assembly equal bit
for bit to the plain statement, and the steady states known in closed form.
"""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from harness.domains.rooms import Rooms
from harness.domains.square import Square
from harness.fokker_planck import FokkerPlanck, rate
from harness.grid import Grid
from harness.velocity import VelocityField
from tests.domain_cases import DOMAINS

SIGMA = 5e-4


def random_velocity(grid, rng, scale):
    return VelocityField.from_centres(rng.normal(scale=scale, size=(2, *grid.shape)))


def random_free_density(free, rng):
    return free.restrict(rng.random(free.grid.shape) + 1e-3)


@pytest.mark.parametrize("name", DOMAINS)
@pytest.mark.parametrize("n", [16, 30])
def test_the_compiled_operator_equals_the_plain_statement_on_free_space(name, n, rng):
    grid = Grid.square(n)
    free = DOMAINS[name].resolve(grid)
    op = FokkerPlanck(grid, SIGMA, free=free)
    v = random_velocity(grid, rng, 0.02)
    fast, ref = op.matrix(v), op.matrix_reference(v)
    assert np.array_equal(fast.data, ref.data)
    p = random_free_density(free, rng)
    np.testing.assert_allclose(op.rate(p, v), rate(grid, p, v, SIGMA, free), atol=1e-12)


@pytest.mark.parametrize("name", DOMAINS)
def test_no_flux_crosses_a_closed_face_and_blocked_cells_exchange_nothing(name, rng):
    grid = Grid.square(24)
    free = DOMAINS[name].resolve(grid)
    a = FokkerPlanck(grid, SIGMA, free=free).matrix(random_velocity(grid, rng, 0.02)).tocoo()
    idx = np.arange(grid.size).reshape(grid.shape)
    linked = set()  # (row, col) pairs of cells joined by an open face
    for i, j in zip(idx[:, :-1][free.face_x], idx[:, 1:][free.face_x], strict=True):
        linked |= {(i, j), (j, i)}
    for i, j in zip(idx[:-1, :][free.face_y], idx[1:, :][free.face_y], strict=True):
        linked |= {(i, j), (j, i)}
    off = [(r, c) for r, c, x in zip(a.row, a.col, a.data, strict=True) if r != c and x != 0]
    assert set(off) <= linked
    blocked = idx[~free.cells]
    dense = a.toarray()
    assert not dense[blocked].any() and not dense[:, blocked].any()


@pytest.mark.parametrize("name", DOMAINS)
def test_each_component_keeps_its_mass_to_round_off(name, rng):
    grid = Grid.square(24)
    free = DOMAINS[name].resolve(grid)
    op = FokkerPlanck(grid, SIGMA, free=free)
    p = random_free_density(free, rng)
    masses = [grid.integrate(p[free.labels == k]) for k in range(free.n_components)]
    for _ in range(50):
        p = op.step(p, random_velocity(grid, rng, 0.05), 0.05)
    after = [grid.integrate(p[free.labels == k]) for k in range(free.n_components)]
    np.testing.assert_allclose(after, masses, rtol=1e-12)
    assert (p[~free.cells] == 0).all() and (p >= 0).all()


def test_the_shut_rooms_have_two_components_and_keep_their_own_mass():
    free = DOMAINS["shut_rooms"].resolve(Grid.square(24))
    assert free.n_components == 2


@pytest.mark.parametrize("name", ["rooms", "obstacles"])
def test_a_target_is_the_steady_state_of_its_log_gradient_velocity(name, rng):
    """``u = sigma (log p*_R - log p*_L) / h`` on every open face makes every open face's
    flux of ``p*`` vanish: ``A p* = 0``, also next to the obstacles."""
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    target = free.restrict(np.exp(-((grid.mesh[0] - 0.3) ** 2) / 0.05) + 0.1)
    log_p = np.log(np.where(free.cells, target, 1.0))
    face_x = np.where(free.face_x, SIGMA * np.diff(log_p, axis=1) / grid.dx, 0.0)
    face_y = np.where(free.face_y, SIGMA * np.diff(log_p, axis=0) / grid.dy, 0.0)
    v = VelocityField(np.zeros((2, *grid.shape)), face_x, face_y)
    op = FokkerPlanck(grid, SIGMA, free=free)
    scale = np.abs(op.rate(target, VelocityField.zeros(grid))).max()
    assert np.abs(op.rate(target, v)).max() < 1e-10 * scale


def test_diffusion_fills_both_rooms_through_the_door_uniformly():
    """With no drift the steady state of a connected free space is uniform on its free
    cells (the null space of ``A`` restricted to them); a start in the left room reaches
    it through the door."""
    grid = Grid.square(20)
    free = DOMAINS["rooms"].resolve(grid)
    op = FokkerPlanck(grid, 1e-2, free=free)
    left = free.restrict(np.where(grid.mesh[0] < 0.4, 1.0, 0.0))
    p = left
    for _ in range(100):  # backward Euler: each mode shrinks by 1 / (1 + dt |lambda|)
        p = op.step(p, VelocityField.zeros(grid), 20.0)
    uniform = free.restrict(np.ones(grid.shape))
    assert grid.l2(p - uniform) < 1e-3 * grid.l2(left - uniform)


def test_the_implicit_step_matches_sparse_lu_on_free_space(rng):
    grid = Grid.square(30)
    free = DOMAINS["obstacles"].resolve(grid)
    op = FokkerPlanck(grid, SIGMA, free=free)
    v = random_velocity(grid, rng, 0.05)
    p = random_free_density(free, rng)
    system = sp.identity(grid.size, format="csc") - 0.05 * op.matrix(v).tocsc()
    exact = spla.spsolve(system, p.ravel()).reshape(grid.shape)
    np.testing.assert_allclose(op.step(p, v, 0.05), exact, atol=1e-13, rtol=1e-11)


def test_the_square_s_free_space_gives_the_plain_operator_bit_for_bit(rng):
    grid = Grid.square(30)
    v = random_velocity(grid, rng, 0.05)
    plain = FokkerPlanck(grid, SIGMA).matrix(v)
    square = FokkerPlanck(grid, SIGMA, free=Square().resolve(grid)).matrix(v)
    assert np.array_equal(plain.data, square.data)


def test_free_space_of_another_grid_is_refused():
    with pytest.raises(ValueError, match="another grid"):
        FokkerPlanck(Grid.square(30), SIGMA, free=Rooms().resolve(Grid.square(20)))
