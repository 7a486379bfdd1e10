"""Probabilistic swarm guidance (harness/control/guidance.py,
harness/control/waypoints.py): the chains' properties against their definitions, the
robots' observed moves against the chain, and closed loops through the real config."""

import itertools
import math

import numpy as np
import pytest
from scipy import stats

from harness import api
from harness.control.guidance import FeedbackGuidance, MetropolisGuidance, neighbour_table
from harness.control.waypoints import PeriodClock, cell_of
from harness.estimators.smoothing import cell_masses
from harness.grid import Grid
from harness.parameters import ParameterError
from harness.records import ControlInput, Estimate
from harness.targets.densities import DEFAULT_TARGET, GaussianMixture, Target

SMALL = (
    "grid.n=6",
    "agents.n=3000",
    "dynamics.sigma=0.0",
    "estimator=kde",
    "sim.dt=0.05",
    "control.period=0.25",
    "log.progress=off",
)


def brute_force_metropolis(v: np.ndarray, grid: Grid) -> np.ndarray:
    """``M`` as a dense matrix, by loops over cells, from the definitions: ``K_ij = 1 / (1
    + d_j)`` over the cell and its existing neighbours, ``F_ij = min(1, v_i K_ji / (v_j
    K_ij))``, ``M_ij = K_ij F_ij``, rejected mass on the diagonal.
    """
    n = grid.size

    def neighbours(j):
        r, c = divmod(j, grid.nx)
        out = []
        for dr, dc in ((0, -1), (0, 1), (-1, 0), (1, 0)):
            if 0 <= r + dr < grid.ny and 0 <= c + dc < grid.nx:
                out.append((r + dr) * grid.nx + c + dc)
        return out

    m = np.zeros((n, n))
    for j in range(n):
        for i in neighbours(j):
            k_ij = 1 / (1 + len(neighbours(j)))
            k_ji = 1 / (1 + len(neighbours(i)))
            m[i, j] = k_ij * min(1.0, v[i] * k_ji / (v[j] * k_ij))
        m[j, j] = 1 - m[:, j].sum()
    return m


def rough_target(grid: Grid, rng: np.random.Generator) -> Target:
    """A target of random cell values (no closed form): masses spread over 1.5 decades."""
    return Target.from_values(grid, grid.normalise(np.exp(1.7 * rng.random(grid.shape))))


@pytest.mark.parametrize("n", [7, 30])
def test_metropolis_chain_keeps_the_target_and_is_reversible(n, rng):
    grid = Grid.square(n)
    for target in (Target.from_density(grid, DEFAULT_TARGET), rough_target(grid, rng)):
        law = MetropolisGuidance(target)
        m = law.matrix.toarray()
        v = law.masses.ravel()
        assert v.sum() == pytest.approx(1.0, abs=1e-14)
        assert m.min() >= 0
        np.testing.assert_allclose(m.sum(axis=0), 1.0, rtol=0, atol=1e-14)  # column-stochastic
        assert np.abs(m @ v - v).max() <= 1e-12 * v.max()  # v stationary
        flux = m * v[None, :]  # M_ij v_j
        assert np.abs(flux - flux.T).max() <= 1e-15  # detailed balance
        cells, exists = neighbour_table(grid)
        allowed = np.zeros_like(m, dtype=bool)
        allowed[cells[exists], np.nonzero(exists)[0]] = True
        assert not (m[~allowed] != 0).any()  # moves only to the cell and its 4-neighbours
        if n == 7:
            np.testing.assert_allclose(m, brute_force_metropolis(v, grid), rtol=0, atol=1e-15)


def test_metropolis_targets_the_exact_cell_masses():
    grid = Grid.square(30)
    target = Target.from_density(grid, DEFAULT_TARGET)
    law = MetropolisGuidance(target)
    # the masses of the continuous density, not cell values times the cell area
    np.testing.assert_allclose(law.masses, DEFAULT_TARGET.cell_masses(grid), rtol=1e-12)
    assert np.abs(law.masses - target.p * grid.cell_area).max() > 1e-6


def test_robots_draw_their_next_cell_from_their_cells_column():
    grid = Grid.square(5)
    law = MetropolisGuidance(rough_target(grid, np.random.default_rng(3)))
    gen = np.random.default_rng(11)
    here = np.repeat(np.arange(grid.size), 4000)
    there = law.chain(None)(here, gen)
    m = law.matrix.toarray()
    counts = np.zeros_like(m)
    np.add.at(counts, (there, here), 1)
    observed, expected = counts[m > 0], (m * 4000)[m > 0]
    assert not counts[m == 0].any()  # never a cell of probability 0
    stat = ((observed - expected) ** 2 / expected).sum()
    dof = int((m > 0).sum()) - grid.size
    assert stats.chi2.sf(stat, dof) > 1e-3


def test_observed_transitions_through_the_loop_match_the_chain(compose):
    """The robots' cells at successive period starts, in the real loop (agents plant,
    no noise, so each robot is at its goal when the period ends), against M."""
    cfg = compose(["control=psg", *SMALL, "sim.t_final=10.0"])
    steps_per_period = 5
    cells = []
    for rec, _ in api.simulate(cfg):
        if rec.step % steps_per_period == 0:
            cells.append(cell_of(Grid.square(6), rec.positions))
    from harness.runs.build import build

    law = build(compose(["control=psg", *SMALL])).control
    m = law.matrix.toarray()
    counts = np.zeros_like(m)
    for before, after in itertools.pairwise(cells):
        np.add.at(counts, (after, before), 1)
    assert not counts[m == 0].any()
    stat, dof = 0.0, 0
    for j in range(m.shape[1]):
        expected = m[:, j] * counts[:, j].sum()
        used = m[:, j] > 0
        if expected[used].min() < 5:
            continue  # too few robots left this cell to test it
        stat += (((counts[used, j] - expected[used]) ** 2) / expected[used]).sum()
        dof += int(used.sum()) - 1
    assert dof > 100  # nearly every cell tested
    assert stats.chi2.sf(stat, dof) > 1e-3


@pytest.mark.parametrize("law", ["psg", "psg_feedback"])
def test_robots_never_leave_the_square(law, compose):
    cfg = compose(
        [
            f"control={law}",
            "grid.n=8",
            "agents.n=500",
            "dynamics.sigma=0.002",  # strong noise: robots hit the walls often
            "agents.localisation_noise=0.02",
            "estimator=kde",
            "sim.dt=0.02",
            "control.period=0.1",
            "sim.t_final=3.0",
            "log.progress=off",
        ]
    )
    for rec, _ in api.simulate(cfg, copy=False):
        x, y = rec.positions
        assert x.min() >= 0 and x.max() <= 1 and y.min() >= 0 and y.max() <= 1


def test_robots_reach_their_goal_cells_within_the_period_and_keep_speed_caps():
    grid = Grid.square(10)
    target = Target.from_density(grid, DEFAULT_TARGET)
    gen = np.random.default_rng(5)
    x = gen.uniform(0, 1, (2, 400))
    law = MetropolisGuidance(target, period=0.5, seed=3)
    dt, est = 0.05, Estimate(target.p, target.grad)
    for n in range(10):
        cmd = law(ControlInput(n * dt, est, x))
        if n == 0:
            goals = law.goals.copy()
        x = x + dt * cmd.robots
    np.testing.assert_allclose(x, goals, rtol=0, atol=1e-13)
    capped = MetropolisGuidance(target, period=0.5, seed=3, v_max=0.01)
    cmd = capped(ControlInput(0.0, est, gen.uniform(0, 1, (2, 400))))
    assert np.hypot(*cmd.robots).max() <= 0.01 * (1 + 1e-12)
    assert np.hypot(*cmd.field.centres).max() <= 0.01 * (1 + 1e-12)


def feedback_law(n=10, **kwargs):
    grid = Grid.square(n)
    return FeedbackGuidance(Target.from_density(grid, DEFAULT_TARGET), **kwargs)


def test_feedback_chain_is_the_identity_at_the_target():
    law = feedback_law(gain=1.0)
    grid = law.grid
    p_star = law.masses / grid.cell_area  # the estimate of the target's own cell masses
    m = law.matrix(p_star)
    np.testing.assert_array_equal(m.toarray(), np.eye(grid.size))  # exactly I, so M v = v
    v = law.masses.ravel()
    np.testing.assert_array_equal(m @ v, v)
    # the robots hold: zero velocity, over a whole period and the next
    x = np.random.default_rng(1).uniform(0, 1, (2, 300))
    est = Estimate(p_star, grid.gradient(p_star))
    for n in range(0, 250, 10):
        cmd = law(ControlInput(n * 0.01, est, x))
        assert not cmd.robots.any() and not cmd.field.centres.any()


def test_feedback_moves_robots_only_out_of_the_cell_above_its_target():
    law = feedback_law(gain=1.0)
    grid = law.grid
    hot = 4 * grid.nx + 6
    p_hat = law.masses / grid.cell_area
    p_hat.ravel()[hot] *= 3.0  # three times its target; every other cell now below its own
    m = law.matrix(p_hat).toarray()
    others = np.arange(grid.size) != hot
    np.testing.assert_array_equal(m[:, others], np.eye(grid.size)[:, others])
    v_hot = law.masses.ravel()[hot]
    # g (m - v) / m with m = 3 v / (1 + 2 v) after renormalising
    assert 1 - m[hot, hot] == pytest.approx(1 - (1 + 2 * v_hot) / 3, rel=1e-12)
    # through the law: only robots in that cell move, and only to its neighbours
    gen = np.random.default_rng(2)
    x = gen.uniform(0, 1, (2, 20000))
    cmd = law(ControlInput(0.0, Estimate(p_hat, grid.gradient(p_hat)), x))
    moving = np.hypot(*cmd.robots) > 0
    inside = cell_of(grid, x) == hot
    assert not moving[~inside].any()
    assert 0.55 < moving[inside].mean() < 0.8
    goal_cells = cell_of(grid, law.goals[:, moving])
    assert set(goal_cells) == {hot - 1, hot + 1, hot - grid.nx, hot + grid.nx}


def test_feedback_relays_excess_toward_the_nearest_deficit():
    grid = Grid.square(10)
    law = FeedbackGuidance(Target.from_values(grid, np.ones(grid.shape)), gain=1.0)
    mass = law.masses.copy()
    mass[4:7, 4:7] *= 2.0  # an over-full block
    mass[:, :2] -= 9 * law.masses[0, 0] / 20  # its excess missing from the two left columns
    m = law.matrix(mass / grid.cell_area).toarray()
    centre = 5 * grid.nx + 5  # its neighbours all have an excess: it relays to the left
    moves = np.flatnonzero(m[:, centre])
    assert set(moves) == {centre, centre - 1}
    assert m[centre - 1, centre] == pytest.approx(0.5)  # g (2 v - v) / 2 v
    edge = 5 * grid.nx + 6  # right edge of the block: its right neighbour is at target
    assert set(np.flatnonzero(m[:, edge])) == {edge, edge - 1}
    at_target = 5 * grid.nx + 8
    assert m[at_target, at_target] == 1.0


def test_feedback_chain_properties_on_random_estimates():
    """Column-stochastic, moves only out of cells with an excess and only to neighbours,
    and the expected distance to the target never grows (exact estimates, gain <= 1)."""
    gen = np.random.default_rng(7)
    grid = Grid.square(9)
    cells, exists = neighbour_table(grid)
    for trial in range(200):
        target = rough_target(grid, gen)
        law = FeedbackGuidance(target, gain=gen.uniform(0.05, 1.0))
        mass = gen.random(grid.size) ** (1 + 3 * gen.random())
        if trial % 4 == 0:
            mass[gen.random(grid.size) < 0.3] = 0.0  # empty cells
        mass /= mass.sum()
        m = law.matrix(mass.reshape(grid.shape) / grid.cell_area).toarray()
        v = law.masses.ravel()
        assert m.min() >= 0
        np.testing.assert_allclose(m.sum(axis=0), 1.0, rtol=0, atol=1e-14)
        excess = mass > v
        np.testing.assert_array_equal(m[:, ~excess], np.eye(grid.size)[:, ~excess])
        allowed = np.zeros_like(m, dtype=bool)
        allowed[cells[exists], np.nonzero(exists)[0]] = True
        assert not (m[~allowed] != 0).any()
        before = np.abs(mass - v).sum()
        after = np.abs(m @ mass - v).sum()
        assert after <= before + 1e-14
        borders = (
            allowed & ~np.eye(grid.size, dtype=bool) & (v > mass)[:, None] & excess[None, :]
        ).any()
        if borders:
            assert after < before - 1e-12


def test_period_starts_survive_round_off():
    clock = PeriodClock(0.3)
    starts = [n for n in range(31) if clock.tick(n * 0.1)]  # 3 * 0.1 = 0.30000000000000004
    assert starts == [0, 3, 6, 9, 12, 15, 18, 21, 24, 27, 30]
    clock = PeriodClock(1.0)
    for n in range(100):
        clock.tick(n * 0.01)
        assert clock.time_left(n * 0.01) == pytest.approx(1.0 - n * 0.01 if n else 1.0)
    clock.tick(0.0)  # a new run
    assert clock.restarted and clock.index == 0
    coarse = PeriodClock(1.0)  # a period that is no multiple of the step: no overshoot
    for t in (0.0, 0.3, 0.6, 0.9):
        coarse.tick(t)
    assert coarse.time_left(0.9) == pytest.approx(0.3)


@pytest.mark.parametrize(
    ("law", "override", "name"),
    [
        ("psg", "control.period=0", "control.period"),
        ("psg", "control.period=-1.0", "control.period"),
        ("psg", "control.v_max=0", "control.v_max"),
        ("psg", "seed=-1", "seed"),
        ("psg_feedback", "control.gain=0", "control.gain"),
        ("psg_feedback", "control.gain=1.5", "control.gain"),
        ("psg_feedback", "control.period=nan", "control.period"),
    ],
)
def test_bad_parameters_are_refused_by_name(law, override, name, refusal, smoke):
    message = refusal([f"control={law}", *smoke, override])
    assert message is not None and f"{name}=" in message, message


def test_bad_gain_is_a_parameter_error():
    with pytest.raises(ParameterError, match="gain"):
        feedback_law(gain=2.0)
    with pytest.raises(ParameterError, match="period"):
        feedback_law(period=0.0)


@pytest.mark.parametrize("law", ["psg", "psg_feedback"])
@pytest.mark.parametrize("estimator", ["filters", "kde"])
def test_closed_loop_runs(law, estimator, compose, smoke):
    cfg = compose([f"control={law}", f"estimator={estimator}", *smoke, "sim.t_final=0.5"])
    records = list(api.simulate(cfg))
    assert len(records) == 26
    for rec, metrics in records:
        assert np.isfinite(rec.estimate.p_hat).all() and rec.command.is_finite()
        assert all(v is None or math.isfinite(v) for v in metrics.values())
    first, last = records[0][0].positions, records[-1][0].positions
    assert not np.array_equal(first, last)  # the robots moved
    assert max(m["peak_speed"] for _, m in records) > 0  # the motion metrics see them


@pytest.mark.parametrize(("law", "divides"), [("psg", "no"), ("psg_feedback", "yes"), ("ot", "no")])
def test_the_laws_say_what_they_use(law, divides, compose, smoke, tmp_path):
    from analysis.load import load_run
    from harness.runs.run import run

    result = run(compose([f"control={law}", *smoke, "sim.t_final=0.04"]), tmp_path)
    assert result.state == "completed", result.reason
    theory = load_run(tmp_path).metadata["theory"]
    assert "positions" in theory["law_uses"] and "target cell masses" in theory["law_uses"]
    assert theory["law_divides_by_density"] == divides


@pytest.mark.parametrize("law", ["psg", "psg_feedback"])
def test_the_mean_field_plant_refuses_them(law, refusal, smoke):
    message = refusal([f"control={law}", "plant=meanfield", *smoke])
    assert message is not None
    assert "control=" in message and "mean-field form" in message, message


def test_debiased_feedback_compares_with_the_smoothed_target():
    grid = Grid.square(12)
    bumpy = GaussianMixture(means=((0.5, 0.5),), stds=(0.08,), weights=(1.0,), floor=0.2)
    target = Target.from_density(grid, bumpy)
    plain = FeedbackGuidance(target)
    debiased = FeedbackGuidance(target, debias=True, bandwidth=0.04)
    np.testing.assert_allclose(plain.masses, cell_masses(bumpy, grid), rtol=1e-12)
    assert debiased.masses.max() < plain.masses.max()  # smoothing lowers the peak
    assert debiased.masses.sum() == pytest.approx(1.0)
