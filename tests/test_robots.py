"""Robots that are not ideal integrators (unicycles, double integrators): the compiled
steps against their numpy statements, the limits from the logged poses, the exact hold
against the single integrator, and closed runs that follow the ideal integrators of the
same seed as the look-ahead shrinks and the gain grows.
"""

import numpy as np
import pytest

from harness.api import compose, run, simulate
from harness.grid import Grid
from harness.plants.agents import Swarm
from harness.plants.double_integrators import (
    DoubleIntegratorSwarm,
    double_integrator_step_reference,
)
from harness.plants.unicycles import UnicycleSwarm, unicycle_step_reference
from harness.runs.build import build

GRID = Grid(16, 16)
BASE = ("grid.n=20", "agents.n=300", "estimator=exact", "log.progress=off", "log.floor_draws=2")
"""Short closed runs: with the exact estimator the commands are the limit's, the same
for every plant of a seed, so two plants differ only by their robots."""


def _uni(rng: np.random.Generator, n: int, v_max=0.3, omega_max=4.0, ell=0.02) -> UnicycleSwarm:
    pos = rng.uniform(0.1, 0.9, (2, n))
    return UnicycleSwarm(
        GRID, pos, 5e-5, rng.uniform(-np.pi, np.pi, n),
        np.full(n, v_max), np.full(n, omega_max), np.full(n, ell),
    )  # fmt: skip


def _di(rng: np.random.Generator, n: int, a_max=0.5, gain=5.0) -> DoubleIntegratorSwarm:
    pos = rng.uniform(0.1, 0.9, (2, n))
    return DoubleIntegratorSwarm(GRID, pos, 5e-5, np.full(n, a_max), np.full(n, gain))


@pytest.mark.parametrize("make", [_uni, _di], ids=["unicycles", "double_integrators"])
def test_compiled_step_matches_numpy_statement(make) -> None:
    """Compiled and numpy steps from the same state and draws agree (limits binding for
    part of the robots: commanded speeds up to 1 length/s against limits of 0.3 and
    0.5)."""
    rng = np.random.default_rng(1)
    a, b = make(rng, 500), make(np.random.default_rng(1), 500)
    reference = (
        unicycle_step_reference
        if isinstance(a, UnicycleSwarm)
        else double_integrator_step_reference
    )
    for step in range(20):
        v = np.random.default_rng(100 + step).uniform(-1, 1, (2, 500))
        fast = a.move(v, 0.01, np.random.default_rng(step)).copy()
        slow = reference(b, v, 0.01, np.random.default_rng(step))
        np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.positions, b.positions, rtol=0, atol=1e-12)
    if isinstance(a, UnicycleSwarm):
        np.testing.assert_allclose(a.headings, b.headings, rtol=0, atol=1e-12)
    else:
        np.testing.assert_allclose(a.velocities, b.velocities, rtol=0, atol=1e-12)


def test_unicycle_exact_hold_stays_within_twice_the_lookahead() -> None:
    """Within the limits, the point ahead moves by v dt each hold, so without noise the
    axle stays within 2 l of the single integrator fed the same velocities, however
    many holds (the deviation telescopes), and comes back to exactly l once aligned."""
    rng = np.random.default_rng(2)
    n, ell = 400, 0.01
    uni = _uni(rng, n, v_max=10.0, omega_max=1e4, ell=ell)
    uni.sigma = 0.0
    si = Swarm(GRID, uni.positions.copy(), 0.0)
    worst = 0.0
    for step in range(300):
        # a smoothly turning velocity per robot, 0.05 length/s, away from the walls
        angle = 0.02 * step + np.linspace(0, 2 * np.pi, n)
        v = 0.05 * np.array([np.cos(angle), np.sin(angle)])
        g = np.random.default_rng(step)
        uni.move(v, 0.01, g)
        si.move(v, 0.01, np.random.default_rng(step))
        worst = max(worst, float(np.max(np.hypot(*(uni.positions - si.positions)))))
    assert worst <= 2 * ell * (1 + 1e-9)
    assert worst > 0.5 * ell  # random initial headings: the offset is really there


def _positions(overrides, t_final=2.0):
    return [rec.positions.copy() for rec, _ in simulate([*BASE, *overrides], t_final=t_final)]


def test_unicycles_follow_ideal_integrators_as_the_lookahead_shrinks() -> None:
    """Same seed, large limits: the largest distance between a unicycle and its ideal
    integrator over 2 s shrinks in proportion to the look-ahead (the offset), where an
    error of the discretisation (of order |v| dt per hold) would not."""
    ideal = _positions(["plant=agents"])
    worst = {}
    for ell in (1e-3, 1e-4):
        uni = _positions(
            ["plant=unicycles", f"plant.lookahead={ell}", "plant.v_max=100", "plant.omega_max=1e7"]
        )
        worst[ell] = max(float(np.max(np.hypot(*(a - b)))) for a, b in zip(ideal, uni, strict=True))
    assert worst[1e-4] < 20 * 1e-4
    assert 7 < worst[1e-3] / worst[1e-4] < 13


def test_double_integrators_follow_ideal_integrators_as_the_gain_grows() -> None:
    """Same seed, large limit: the distance to the ideal integrators falls like 1 / g
    and stays below twice the peak commanded speed over g (the velocity loop's lag)."""
    ideal = [rec for rec, _ in simulate(["plant=agents", *BASE], t_final=2.0)]
    peak = max(float(np.max(np.hypot(*r.command.field.centres))) for r in ideal)
    worst = {}
    for gain in (1e3, 1e4):
        di = _positions(["plant=double_integrators", f"plant.gain={gain}", "plant.a_max=1e7"])
        worst[gain] = max(
            float(np.max(np.hypot(*(a.positions - b)))) for a, b in zip(ideal, di, strict=True)
        )
        assert worst[gain] < 2 * peak / gain
    assert 7 < worst[1e3] / worst[1e4] < 13


def test_unicycle_limits_hold_at_every_step_in_the_logged_poses(tmp_path) -> None:
    """Without noise, between two logged poses a unicycle turns by at most omega_max dt
    and travels at most v_max dt, with limits that bind (the start's commands reach
    0.37 length/s against v_max = 0.05)."""
    dt, v_max, omega_max = 0.01, 0.05, 2.0
    log = run(
        [*BASE, "plant=unicycles", f"plant.v_max={v_max}", f"plant.omega_max={omega_max}",
         "dynamics.sigma=0", "sim.t_final=1.0", "log.positions_every=1"],
        tmp_path / "run",
    )  # fmt: skip
    assert len(log.poses) == 101
    poses = np.stack(log.poses)  # (steps, N, 3)
    np.testing.assert_allclose(poses[:, :, :2], np.stack(log.positions), atol=1e-6)
    turn = np.angle(np.exp(1j * np.diff(poses[:, :, 2], axis=0)))
    travel = np.hypot(*np.moveaxis(np.diff(poses[:, :, :2], axis=0), -1, 0))
    assert np.abs(turn).max() <= omega_max * dt * (1 + 1e-9)
    assert travel.max() <= v_max * dt * (1 + 1e-9)
    assert np.abs(turn).max() > 0.9 * omega_max * dt  # the turn limit binds
    assert travel.max() > 0.9 * v_max * dt  # the speed limit binds
    assert np.nanmax(log.metrics["tracking_error"]) > 0.01  # and the robots lag


def test_double_integrator_acceleration_limit_holds(tmp_path) -> None:
    """Without noise, the second difference of the positions over two steps (a
    weighted mean of the acceleration) never exceeds a_max, which binds."""
    dt, a_max = 0.01, 0.2
    positions = np.stack(
        _positions(["plant=double_integrators", f"plant.a_max={a_max}", "dynamics.sigma=0"], 1.0)
    )
    inside = np.all((positions > 0.01) & (positions < 0.99), axis=(0, 1))  # no wall contact
    accel = np.diff(positions[:, :, inside], 2, axis=0) / dt**2
    size = np.hypot(accel[:, 0], accel[:, 1])
    assert size.max() <= a_max * (1 + 1e-6)
    assert size.max() > 0.9 * a_max


def test_spread_draws_per_robot_values_around_the_nominal() -> None:
    """plant.spread: per-robot limits uniform on nominal (1 +- s), seeded, positions
    untouched (the draws come from the plant's own stream)."""

    def started(spread: float):
        parts = build(compose([*BASE, "plant=unicycles", f"plant.spread={spread}", "seed=3"]))
        parts.plant.start(np.random.default_rng(3))
        return parts.plant.swarm

    plain, spread, again = started(0.0), started(0.5), started(0.5)
    np.testing.assert_array_equal(plain.positions, spread.positions)
    np.testing.assert_array_equal(plain.v_max, 0.1)
    assert spread.v_max.min() >= 0.05 and spread.v_max.max() <= 0.15
    assert spread.v_max.std() > 0.02 and spread.lookahead.std() > 0.002
    np.testing.assert_array_equal(spread.v_max, again.v_max)


@pytest.mark.parametrize(
    "override",
    ["plant.v_max=0", "plant.omega_max=-1", "plant.lookahead=nan", "plant.spread=1"],
)
def test_bad_robot_parameters_are_refused_in_one_line(refusal, override) -> None:
    message = refusal([*BASE, "plant=unicycles", override])
    assert message is not None and "\n" not in message
    assert override.split("=")[0] in message


def _rk4_unicycle(swarm: UnicycleSwarm, v: np.ndarray, dt: float, substeps: int = 4000):
    """The feedback-linearising law under a held ``v`` integrated by RK4 (no limits, no
    noise), with the largest ``|u|`` and ``|omega|`` met on the way."""
    ell = swarm.lookahead
    x = swarm.positions.copy()
    th = np.arctan2(swarm.headings[1], swarm.headings[0])
    h = dt / substeps

    def f(x, th):
        c, s = np.cos(th), np.sin(th)
        u = c * v[0] + s * v[1]
        w = (c * v[1] - s * v[0]) / ell
        return np.array([u * c, u * s]), w, u

    top_u, top_w = np.zeros(x.shape[1]), np.zeros(x.shape[1])
    for _ in range(substeps):
        k1, m1, u = f(x, th)
        top_u, top_w = np.maximum(top_u, np.abs(u)), np.maximum(top_w, np.abs(m1))
        k2, m2, _ = f(x + 0.5 * h * k1, th + 0.5 * h * m1)
        k3, m3, _ = f(x + 0.5 * h * k2, th + 0.5 * h * m2)
        k4, m4, _ = f(x + h * k3, th + h * m3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        th = th + h / 6 * (m1 + 2 * m2 + 2 * m3 + m4)
    _, w_end, u_end = f(x, th)
    top_u, top_w = np.maximum(top_u, np.abs(u_end)), np.maximum(top_w, np.abs(w_end))
    return x, th, top_u, top_w


def test_unicycle_hold_against_an_independent_integration():
    """Against RK4 of the continuous law: robots whose law stays within the limits over
    the hold end where RK4 puts them (1e-9); robots whose law exceeds a limit take the
    clipped arc instead, turning at most omega_max dt and travelling at most v_max dt."""
    rng = np.random.default_rng(5)
    n, dt, v_max, omega_max = 600, 0.01, 0.2, 8.0
    swarm = _uni(rng, n, v_max=v_max, omega_max=omega_max, ell=0.02)
    swarm.sigma = 0.0
    # look-aheads from slow turning to swinging from behind to ahead within the hold
    swarm.lookahead[:] = 10 ** rng.uniform(-5, -1, n)
    speed = rng.uniform(0.0, 0.3, n)
    angle = rng.uniform(-np.pi, np.pi, n)
    # a third start almost opposite their command with a look-ahead that swings them
    # round within the hold: small turn rates at both ends, |v| / l in between
    behind = np.arange(n) % 3 == 0
    th = np.arctan2(swarm.headings[1], swarm.headings[0])
    angle[behind] = th[behind] + np.pi - rng.uniform(1e-4, 5e-3, behind.sum())
    swarm.lookahead[behind] = speed[behind] * dt / rng.uniform(10, 40, behind.sum())
    v = speed * np.array([np.cos(angle), np.sin(angle)])
    x_ref, th_ref, top_u, top_w = _rk4_unicycle(swarm, v, dt)
    before = swarm.positions.copy()
    th0 = np.arctan2(swarm.headings[1], swarm.headings[0])
    swarm.move(v, dt, np.random.default_rng(0))
    th1 = np.arctan2(swarm.headings[1], swarm.headings[0])
    within = (top_u < 0.99 * v_max) & (top_w < 0.99 * omega_max)
    beyond = (top_u > 1.01 * v_max) | (top_w > 1.01 * omega_max)
    assert within.sum() > 50 and beyond.sum() > 50  # both branches are exercised
    np.testing.assert_allclose(swarm.positions[:, within], x_ref[:, within], atol=1e-9)
    turn_ref = np.angle(np.exp(1j * (th_ref - th0)))
    turn = np.angle(np.exp(1j * (th1 - th0)))
    np.testing.assert_allclose(turn[within], turn_ref[within], atol=1e-9)
    assert np.all(np.abs(turn[beyond]) <= omega_max * dt * (1 + 1e-12))
    travel = np.hypot(*(swarm.positions - before))
    assert np.all(travel[beyond] <= v_max * dt * (1 + 1e-12))
    assert np.all(np.abs(turn[beyond] - turn_ref[beyond]) + np.hypot(
        *(swarm.positions - x_ref))[beyond] > 1e-9)  # fmt: skip


def test_unicycle_step_edge_cases_are_finite_and_match_the_reference():
    """Zero command, a command exactly behind the robot, a look-ahead so small that the
    heading's decay underflows, and a huge command: compiled and numpy agree, all
    finite."""
    heading = np.array([0.0, np.pi, 0.3, 2.0, 0.0])
    v = np.array([[0.0, 0.05, 0.05, 1e200, 0.05], [0.0, 0.0, 1e-300, 1e200, 1e-310]])
    ell = np.array([0.01, 0.01, 1e-300, 0.01, 1e-9])

    def make():
        pos = np.full((2, 5), 0.5)
        return UnicycleSwarm(GRID, pos, 0.0, heading, np.full(5, 1e300), np.full(5, 1e300), ell)

    a, b = make(), make()
    fast = a.move(v, 0.01, np.random.default_rng(0)).copy()
    slow = unicycle_step_reference(b, v, 0.01, np.random.default_rng(0))
    assert np.isfinite(fast).all() and np.isfinite(a.headings).all()
    np.testing.assert_allclose(fast, slow, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.headings, b.headings, atol=1e-12)
    np.testing.assert_array_equal(fast[:, 0], 0.0)  # no command: no motion
    np.testing.assert_allclose(a.headings[:, 1], [-1.0, 0.0], atol=1e-15)  # backs up


def test_unicycles_under_a_shared_field_take_one_pass_with_the_same_result():
    """move_field (interpolation inside the kernel) equals move under the field's
    interpolant at the robots, and returns the mean tracking error."""
    from harness.velocity import VelocityField, interpolate

    rng = np.random.default_rng(8)
    field = VelocityField.from_centres(rng.uniform(-0.2, 0.2, (2, *GRID.shape)))
    a, b = _uni(np.random.default_rng(3), 700), _uni(np.random.default_rng(3), 700)
    for step in range(10):
        v = interpolate(GRID, field.centres, b.positions)
        error = a.move_field(field, 0.01, np.random.default_rng(step))
        applied = b.move(v, 0.01, np.random.default_rng(step))
        np.testing.assert_array_equal(a.positions, b.positions)
        np.testing.assert_array_equal(a.headings, b.headings)
        assert error == pytest.approx(np.mean(np.hypot(*(applied - v))), rel=1e-12)
        assert error > 0
