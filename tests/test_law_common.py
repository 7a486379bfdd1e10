"""What every law shares: the speed cap, the robots' mean-velocity field, the motion
metrics, the localisation noise, the open-loop Langevin baseline and the ``hole`` error
of the injected estimator.
"""

import dataclasses

import numpy as np
import pytest
from omegaconf import OmegaConf

from harness import api
from harness.compiled.agents import speed_sums
from harness.estimators.injected import Hole, InjectedEstimator
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.observers.motion import speed_sums_reference
from harness.records import Command
from harness.velocity import VelocityField, cap_vectors, interpolate

FAST = ("grid.n=16", "sim.dt=0.02", "log.progress=off", "log.floor_draws=4")


def test_cap_keeps_directions_and_bounds_every_speed(rng):
    v = rng.normal(size=(2, 500)) * np.array([[1.0], [3.0]])
    capped = cap_vectors(v, 0.5)
    speed = np.hypot(*capped)
    assert speed.max() <= 0.5 * (1 + 1e-15)
    slow = np.hypot(*v) <= 0.5
    np.testing.assert_array_equal(capped[:, slow], v[:, slow])
    # same direction: the cross product vanishes and the dot product is positive
    cross = v[0] * capped[1] - v[1] * capped[0]
    np.testing.assert_allclose(cross, 0, atol=1e-14)
    assert (np.sum(v * capped, axis=0) > 0).all()


def test_capped_command_without_a_cap_is_the_same_object(rng):
    grid = Grid.square(8)
    command = Command(VelocityField.from_centres(rng.normal(size=(2, *grid.shape))))
    assert command.capped(None) is command
    capped = command.capped(0.1)
    assert capped.field is not None
    assert np.hypot(*capped.field.centres).max() <= 0.1 * (1 + 1e-15)
    assert np.abs(capped.field.face_x).max() <= 0.1 and np.abs(capped.field.face_y).max() <= 0.1


def test_robot_field_is_the_mean_velocity_of_each_cell(rng):
    grid = Grid.square(5)
    x = rng.uniform(0, 1, size=(2, 40))
    v = rng.normal(size=(2, 40))
    field = VelocityField.from_robots(grid, x, v)
    for j in range(5):
        for i in range(5):
            inside = (np.floor(x[0] * 5) == i) & (np.floor(x[1] * 5) == j)
            expect = v[:, inside].mean(axis=1) if inside.any() else np.zeros(2)
            np.testing.assert_allclose(field.centres[:, j, i], expect, atol=1e-15)


@pytest.mark.parametrize("n", [300, 70_000])  # the serial and the parallel build
def test_compiled_speed_sums_match_numpy(rng, n):
    grid = Grid.square(12)
    centres = rng.normal(size=(2, *grid.shape))
    x = rng.uniform(0, 1, size=(2, n))
    got = speed_sums(x, centres, grid.x0, grid.x1, grid.y0, grid.y1, grid.nx, grid.ny)
    np.testing.assert_allclose(got, speed_sums_reference(grid, centres, x), rtol=1e-12)
    speed = np.hypot(*interpolate(grid, centres, x))  # independent of both
    assert got[1] == pytest.approx(speed.max(), rel=1e-14)


def test_speed_cap_holds_in_the_log_of_every_step():
    cap = 2e-3
    peaks = [
        m["peak_speed"]
        for _, m in api.simulate([*FAST, "control=heat", f"control.v_max={cap}"], t_final=1.0)
    ]
    assert max(peaks) <= cap * (1 + 1e-12)
    assert max(peaks) > 0.5 * cap  # the heat law's start is faster than the cap: it binds


def test_effort_of_a_constant_field_is_its_squared_speed(rng):
    """A constant field ``c``: every robot is commanded ``c``, so ``effort = |c|^2`` and
    both speeds ``|c|``; on the mean-field plant the same, whatever the density.
    """
    from harness.observers.motion import motion
    from harness.records import Estimate, StepRecord

    grid = Grid.square(9)
    c = np.array([0.3, -0.4])
    field = VelocityField.from_centres(np.broadcast_to(c[:, None, None], (2, *grid.shape)))
    p = rng.uniform(0.5, 1.5, grid.shape)
    est = Estimate(p, np.zeros((2, *grid.shape)))
    for x in (rng.uniform(0, 1, size=(2, 300)), None):
        rec = StepRecord(0, 0.0, p, None, est, Command(field), x)
        m = motion(grid, rec)
        assert m["effort"] == pytest.approx(0.25, rel=1e-12)
        assert m["mean_speed"] == pytest.approx(0.5, rel=1e-12)
        assert m["peak_speed"] == pytest.approx(0.5, rel=1e-12)


def test_localisation_noise_reaches_the_estimator_not_the_robots():
    """The plant's observed positions are the true ones plus noise of the stated
    standard deviation (inside the square); its measurement is the KDE of the observed
    positions, and the robots themselves are where the dynamics put them.
    """
    from harness.runs.build import build

    s = 0.02
    plant = build(api.compose([*FAST, f"agents.localisation_noise={s}", "agents.n=4000"])).plant
    plant.start(np.random.default_rng(3))
    seen, true = plant.observed, plant.positions
    assert seen is not true
    inner = ((true > 0.1) & (true < 0.9)).all(axis=0)
    err = (seen - true)[:, inner]
    assert abs(err.mean()) < 4 * s / np.sqrt(err.size)
    assert err.std() == pytest.approx(s, rel=0.05)
    assert ((seen >= 0) & (seen <= 1)).all()
    measured = plant.measure(np.random.default_rng(4))
    np.testing.assert_array_equal(measured.p, plant.kde(seen)[0])


def test_the_law_sees_the_observed_positions_and_the_records_the_true_ones():
    """Through the loop: the law gets the plant's observed positions, the step records
    (and so the swarm metrics) the true ones.
    """
    from harness.loop import trajectory
    from harness.runs.build import build

    exp = build(api.compose([*FAST, "agents.localisation_noise=0.02"]))
    seen = []

    def spy(inp):
        if inp.positions is not None:  # the robots' law, not the limit's
            seen.append(inp.positions.copy())
        return exp.control(inp)

    steps = trajectory(dataclasses.replace(exp, control=spy))
    next(steps)
    rec, _ = next(steps)
    np.testing.assert_array_equal(seen[-1], exp.plant.observed)
    assert rec.positions is exp.plant.positions
    assert np.abs(seen[-1] - rec.positions).max() > 1e-3


def test_localisation_noise_has_its_own_stream():
    """A law that reads no position moves the robots exactly as without the noise."""
    runs = [
        [m["swarm_l2"] for _, m in api.simulate([*FAST, "control=langevin", *extra], 0.2)]
        for extra in ([], ["agents.localisation_noise=0.05"])
    ]
    assert runs[0] == runs[1]


def test_no_localisation_noise_leaves_the_run_unchanged():
    plain = [m["swarm_l2"] for _, m in api.simulate([*FAST], t_final=0.2)]
    zero = [
        m["swarm_l2"] for _, m in api.simulate([*FAST, "agents.localisation_noise=0"], t_final=0.2)
    ]
    noisy = [
        m["swarm_l2"]
        for _, m in api.simulate([*FAST, "agents.localisation_noise=0.01"], t_final=0.2)
    ]
    assert plain == zero
    assert plain != noisy


def test_meanfield_plant_refuses_localisation_noise(compose):
    from harness.runs.build import build
    from harness.runs.checks import ConfigError

    with pytest.raises(ConfigError, match="localisation_noise"):
        build(compose(["plant=meanfield", "agents.localisation_noise=0.01"]))


def _langevin_from_target(tmp_path, overrides=()):
    cfg = api.compose(
        ["control=langevin", "dynamics.sigma=5e-3", "sim.dt=0.02", "log.progress=off", *overrides]
    )
    cfg.init = OmegaConf.create(OmegaConf.to_container(cfg.target))
    log = api.run(cfg, tmp_path / "run")
    swarm = log.metrics["swarm_l2"]
    values = swarm[np.isfinite(swarm)][1:]
    theory = log.metadata["theory"]
    lo, hi = float(theory["swarm_l2_floor_lo"]), float(theory["swarm_l2_floor_hi"])
    return values, lo, hi, float(theory["swarm_l2_floor_mean"])


def test_langevin_from_the_target_with_large_noise_stays_in_the_floor_band(tmp_path):
    """Robots drawn from ``p_*`` under ``v = sigma grad log p_*`` with 100 times the
    paper's noise stay distributed as ``p_*`` for 10 s (the noise alone would spread
    them over ``sqrt(2 sigma t)`` = 0.3): ``swarm_l2`` inside the finite-N floor's band.
    The same robots under the drift of another target (uniform: no drift) leave it.
    """
    values, lo, hi, mean = _langevin_from_target(tmp_path, ["sim.t_final=10"])
    assert np.mean((values >= lo) & (values <= hi)) >= 0.8
    assert values.mean() <= mean * 1.15
    wrong, lo, hi, _ = _langevin_from_target(
        tmp_path / "wrong", ["sim.t_final=10", "control.v_max=1e-12"]
    )
    assert np.mean(wrong[-20:] > hi) == 1.0


def _injected(grid: Grid, delta: float) -> InjectedEstimator:
    return InjectedEstimator(grid, FokkerPlanck(grid, 5e-5), delta, seed=0, shape="hole")


def test_hole_error_has_the_size_asked_for_and_keeps_mass(target30):
    grid, p = target30.grid, target30.p
    est = _injected(grid, 0.2)
    eps, eps_g = est.error(0.0, p)
    assert grid.l2(eps) == pytest.approx(0.2, rel=1e-12)
    assert abs(grid.integrate(eps)) < 1e-13
    np.testing.assert_allclose(eps_g, grid.gradient(eps), atol=1e-15)


def test_hole_drives_the_estimate_towards_zero_on_its_region(target30):
    """With the depth ``d = 1`` (``delta = ||p w - <p w>||``), ``p_hat`` within ``r / 2``
    of the centre is at most ``p (1 - exp(-1/8)) + <p w>``, computed here from the
    definition of the well, and far below ``p`` there.
    """
    grid, p = target30.grid, target30.p
    x, y = grid.mesh
    r, (cx, cy) = 0.08, (0.45, 0.74)
    well = np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * r**2))
    mean = grid.integrate(p * well) / grid.area
    delta = grid.l2(p * well - mean)
    est = _injected(grid, delta)
    p_hat = p + est.error(0.0, p)[0]
    inside = (x - cx) ** 2 + (y - cy) ** 2 <= (r / 2) ** 2
    assert inside.sum() >= 3
    level = p * (1 - np.exp(-1 / 8)) + mean
    assert (p_hat[inside] <= level[inside] + 1e-12).all()
    assert (p_hat[inside] <= 0.2 * p[inside]).all()
    assert isinstance(est.shape, Hole)
    mask, bound = est.shape.level(p)
    np.testing.assert_array_equal(mask, inside)
    np.testing.assert_allclose(bound, level, rtol=1e-12)
    assert delta < 0.5 * grid.l2(p)  # small in L2 against the density itself


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("estimator.shape=ring", "estimator.shape"),
        ("estimator.hole_radius=0", "estimator.hole_radius"),
        ("estimator.hole_centre=[2.0,0.5]", "estimator.hole_centre"),
    ],
)
def test_hole_parameters_are_checked(compose, override, key):
    from harness.runs.build import build
    from harness.runs.checks import ConfigError

    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        build(compose(["plant=meanfield", "estimator=injected", override]))


def test_swarm_histogram_counts_as_numpy_histogram2d(rng):
    from harness.plants.agents import Swarm

    grid = Grid.square(7)
    x = rng.uniform(0, 1, size=(2, 3000))
    x[:, :3] = [[0.0, 1.0, 1.0], [1.0, 0.0, 1.0]]  # robots on the walls and corners
    counts, _, _ = np.histogram2d(x[1], x[0], bins=(7, 7), range=((0, 1), (0, 1)))
    expect = counts / (3000 * grid.cell_area)
    np.testing.assert_array_equal(Swarm(grid, x, 0.0).histogram(), expect)
