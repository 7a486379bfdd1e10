"""The guidance chains (psg, psg_feedback) on free space: the graph of free cells joined
through open faces, with ``p_*``'s cell masses the exact stationary distribution.
"""

import numpy as np
import pytest

from harness.control.free_space import blocked
from harness.control.guidance import FeedbackGuidance, MetropolisGuidance
from harness.grid import Grid
from harness.protocols import on_free_space
from harness.records import ControlInput, Estimate
from harness.targets.densities import DEFAULT_TARGET, Target
from tests.domain_cases import DOMAINS


def open_pairs(free):
    """Brute force: the set of (i, j) flat cells joined by an open face, both ways."""
    g = free.grid
    pairs = set()
    for r in range(g.ny):
        for c in range(g.nx):
            if c + 1 < g.nx and free.face_x[r, c]:
                pairs |= {(r * g.nx + c, r * g.nx + c + 1), (r * g.nx + c + 1, r * g.nx + c)}
            if r + 1 < g.ny and free.face_y[r, c]:
                pairs |= {(r * g.nx + c, (r + 1) * g.nx + c), ((r + 1) * g.nx + c, r * g.nx + c)}
    return pairs


def setting(name, n=24):
    grid = Grid.square(n)
    free = DOMAINS[name].resolve(grid)
    return grid, free, Target.from_density(grid, DEFAULT_TARGET, free)


def moves_only_through_open_faces(matrix, free):
    m = matrix.tocoo()
    off = m.row != m.col
    pairs = open_pairs(free)
    assert all((int(i), int(j)) in pairs for i, j in zip(m.row[off], m.col[off], strict=True))
    blocked_cells = np.flatnonzero(~free.cells.ravel())
    dense = matrix.toarray()
    np.testing.assert_array_equal(dense[:, blocked_cells], np.eye(dense.shape[0])[:, blocked_cells])
    np.testing.assert_allclose(dense.sum(axis=0), 1.0, rtol=0, atol=1e-15)
    assert dense.min() >= 0


@pytest.mark.parametrize("name", DOMAINS)
def test_psg_keeps_the_targets_cell_masses_exactly_stationary_on_free_space(name):
    _, free, target = setting(name)
    law = MetropolisGuidance(target)
    v = law.masses.ravel()
    assert not v[~free.cells.ravel()].any() and v.sum() == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(law.matrix @ v, v, rtol=0, atol=1e-17)
    flow = law.matrix.toarray() * v[None, :]  # M_ij v_j, detailed balance: symmetric
    np.testing.assert_allclose(flow, flow.T, rtol=0, atol=1e-18)


@pytest.mark.parametrize("name", DOMAINS)
def test_psg_moves_no_robot_into_a_blocked_cell_or_across_a_closed_face(name):
    _, free, target = setting(name)
    moves_only_through_open_faces(MetropolisGuidance(target).matrix, free)


@pytest.mark.parametrize("name", DOMAINS)
def test_psg_feedback_moves_only_through_open_faces_and_holds_at_the_target(name, rng):
    grid, free, target = setting(name)
    law = FeedbackGuidance(target)
    p_hat = free.restrict(rng.random(grid.shape) + 0.05)
    moves_only_through_open_faces(law.matrix(p_hat), free)
    at_target = law.masses / grid.cell_area
    np.testing.assert_array_equal(law.matrix(at_target).toarray(), np.eye(grid.size))


@pytest.mark.parametrize("name", DOMAINS)
@pytest.mark.parametrize("cls", [MetropolisGuidance, FeedbackGuidance])
def test_guidance_goals_lie_in_free_space_and_every_robot_counts_in_a_free_cell(name, cls, rng):
    grid, free, target = setting(name, n=30)
    law = cls(target, seed=3)
    # robots anywhere in free space on the raster, blocked cells' free parts included
    x = rng.random((2, 20000))
    x = x[:, ~blocked(free, x)][:, :4000]
    assert free.cells.ravel()[law.cell_of(x)].all()
    est = Estimate(
        p_hat=free.restrict(rng.random(grid.shape) + 0.05), q_hat=np.zeros((2, *grid.shape))
    )
    law(ControlInput(t=0.0, estimate=est, positions=x))
    goals = law.goals[:, ~np.isnan(law.goals[0])]
    assert goals.shape[1] > 0 and not blocked(free, goals).any()
    assert on_free_space(law)
