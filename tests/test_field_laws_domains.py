"""The field laws (paper, heat, langevin) on free space: no velocity through an
obstacle's face, finite everywhere, and ``p_*`` the paper's law's exact discrete fixed
point on the masked grid.
"""

import numpy as np
import pytest

from harness.control.heat import HeatControl, LangevinControl
from harness.control.paper import PaperControl, paper_law, paper_law_reference
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.protocols import on_free_space
from harness.targets.densities import DEFAULT_TARGET, Target
from tests.domain_cases import DOMAINS

ALPHA, SIGMA = 5e-3, 5e-4


def laws(target):
    return {
        "paper": PaperControl(target, ALPHA, SIGMA),
        "heat": HeatControl(target, ALPHA, SIGMA),
        "langevin": LangevinControl(target, SIGMA),
    }


@pytest.mark.parametrize("name", DOMAINS)
@pytest.mark.parametrize("n", [24, 30])
def test_p_star_is_the_paper_laws_exact_discrete_fixed_point_on_free_space(name, n):
    grid = Grid.square(n)
    free = DOMAINS[name].resolve(grid)
    target = Target.from_density(grid, DEFAULT_TARGET, free)
    q = free.gradient(target.p)
    v = paper_law(target.p, q, target, ALPHA, SIGMA)
    assert v.is_finite()
    rate = FokkerPlanck(grid, SIGMA, free=free).rate(target.p, v)
    scale = SIGMA / grid.dx**2 * float(target.p.max())  # one face's diffusive flux rate
    assert np.abs(rate).max() <= 1e-10 * scale
    # not a property of the target alone: a disturbed estimate moves mass
    disturbed = paper_law(target.p * (1 + 0.1 * grid.mesh[0]), q, target, ALPHA, SIGMA)
    moved = FokkerPlanck(grid, SIGMA, free=free).rate(target.p, disturbed)
    assert np.abs(moved).max() > 1e-3 * scale


@pytest.mark.parametrize("name", DOMAINS)
@pytest.mark.parametrize("law", ["paper", "heat", "langevin"])
def test_field_laws_give_no_velocity_through_an_obstacle_and_are_finite(name, law, rng):
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    target = Target.from_density(grid, DEFAULT_TARGET, free)
    p_hat = free.restrict(rng.random(grid.shape) + 0.05)
    q_hat = free.gradient(p_hat) + rng.normal(scale=0.1, size=(2, *grid.shape))
    v = laws(target)[law].field(p_hat, q_hat)
    assert v.is_finite()
    assert not v.centres[:, ~free.cells].any()
    assert not v.face_x[~free.face_x].any() and not v.face_y[~free.face_y].any()
    assert np.abs(v.face_x[free.face_x]).max() > 0  # the open faces do carry the law


@pytest.mark.parametrize("name", DOMAINS)
def test_the_compiled_paper_law_equals_its_plain_statement_on_free_space(name, rng):
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    target = Target.from_density(grid, DEFAULT_TARGET, free)
    p_hat = free.restrict(rng.random(grid.shape) + 0.05)
    q_hat = free.gradient(p_hat)
    fast = paper_law(p_hat, q_hat, target, ALPHA, SIGMA)
    ref = paper_law_reference(p_hat, q_hat, target, ALPHA, SIGMA)
    for a, b in zip(
        (fast.centres, fast.face_x, fast.face_y), (ref.centres, ref.face_x, ref.face_y), strict=True
    ):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("name", DOMAINS)
def test_the_paper_laws_feedback_diffusivity_reads_free_cells_only(name):
    grid = Grid.square(30)
    free = DOMAINS[name].resolve(grid)
    target = Target.from_density(grid, DEFAULT_TARGET, free)
    law = PaperControl(target, ALPHA, SIGMA)
    assert law.feedback_diffusivity(target.p) == pytest.approx(ALPHA, rel=1e-15)
    assert HeatControl(target, ALPHA, SIGMA).feedback_diffusivity(target.p) <= ALPHA


@pytest.mark.parametrize("law", ["paper", "heat", "langevin"])
def test_field_laws_say_they_honour_free_space(law):
    grid = Grid.square(16)
    target = Target.from_density(grid, DEFAULT_TARGET)
    assert on_free_space(laws(target)[law])
