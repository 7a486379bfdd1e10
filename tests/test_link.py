"""The command link: the ideal link is the run without one (bit for bit), latency
shifts the applied commands by whole steps, broadcasts are held for their period,
losses follow their probability, ages their formula, and bad values are refused."""

import numpy as np
import pytest
from scipy.stats import binomtest

from harness.api import simulate
from harness.grid import Grid
from harness.plants.agents import Agents, Swarm
from harness.plants.link import Link
from harness.records import Command

SMALL = ("grid.n=12", "agents.n=200", "sim.dt=0.02", "log.progress=off", "log.floor_draws=2")


def _robot_commands(n_robots: int, steps: int) -> list[Command]:
    """Distinct per-robot velocities at every step (step k: robot i moves at (k, i))."""
    return [
        Command(None, np.array([np.full(n_robots, float(k)), np.arange(n_robots, dtype=float)]))
        for k in range(steps)
    ]


@pytest.mark.parametrize("latency_steps", [0, 1, 3, 7])
def test_latency_shifts_applied_commands_by_whole_steps(latency_steps) -> None:
    """Noise-free robots behind a link of latency k dt: the displacement over step n is
    the command of step n - k (zero before the first arrival)."""
    dt, n = 0.01, 5
    link = Link(dt, latency_steps * dt, 0.0, dt)
    link.start(n)
    swarm = Swarm(Grid(8, 8, x1=1e6, y1=1e6), np.full((2, n), 10.0), 0.0)
    commands = _robot_commands(n, 20)
    for step, command in enumerate(commands):
        before = swarm.positions.copy()
        link.transmit(command, step)
        swarm.move(link.velocities(swarm.positions, swarm.grid), dt, np.random.default_rng(0))
        moved = (swarm.positions - before) / dt
        expected = commands[step - latency_steps].robots if step >= latency_steps else 0.0
        np.testing.assert_allclose(moved, expected, rtol=1e-9, atol=1e-9)


def test_period_holds_each_broadcast_and_age_follows_its_formula() -> None:
    """Period P steps and latency L: the command held at step n is the one of the last
    broadcast step at or before n - L, and the mean age over many periods is
    (L + (P - 1) / 2) dt."""
    dt, p, lat, n = 0.01, 4, 3, 6
    link = Link(p * dt, lat * dt, 0.0, dt)
    link.start(n)
    ages = []
    for step, command in enumerate(_robot_commands(n, 400)):
        link.transmit(command, step)
        held = link.velocities(np.zeros((2, n)), Grid(4, 4))
        if step >= lat:
            assert held[0, 0] == ((step - lat) // p) * p
            ages.append(link.age)
    assert np.mean(ages[100:]) == pytest.approx((lat + (p - 1) / 2) * dt, rel=1e-2)


@pytest.mark.parametrize("loss", [0.1, 0.5])
def test_missed_fraction_matches_the_loss_probability(loss) -> None:
    """Over 200 broadcasts to 500 robots the missed fraction is binomial(loss): the exact
    two-sided test does not reject it, and rejects a loss 0.05 away (power)."""
    link = Link(0.01, 0.0, loss, 0.01, seed=7)
    link.start(500)
    for step, command in enumerate(_robot_commands(500, 200)):
        link.transmit(command, step)
    assert link.delivered == 200 * 500
    assert binomtest(link.missed, link.delivered, loss).pvalue > 1e-3
    assert binomtest(link.missed, link.delivered, loss + 0.05).pvalue < 1e-6


def test_a_robot_that_misses_keeps_its_last_command() -> None:
    link = Link(0.01, 0.0, 0.5, 0.01, seed=1)
    link.start(300)
    previous = np.zeros((2, 300))
    for step, command in enumerate(_robot_commands(300, 30)):
        link.transmit(command, step)
        held = link.velocities(np.zeros((2, 300)), Grid(4, 4))
        got = held[0] == step
        assert np.all(held[:, ~got] == previous[:, ~got])  # missed: unchanged
        if step > 0:  # (at step 0 the command (0, i) and "none" look alike)
            assert 0.3 < got.mean() < 0.7
        previous = held


def _advance_without_link(self, command, a, dt, rng) -> None:
    """The agents plant's step as it reads without a link (the reference)."""
    if command.robots is not None:
        self.swarm.step_robots(command.robots, dt, rng)
    else:
        self.swarm.step(command.field, dt, rng)
    self.tracking_error = 0.0
    self.command_age = 0.0
    self._observe()


@pytest.mark.parametrize("control", ["paper", "ot"])
def test_ideal_link_is_bit_for_bit_the_run_without_a_link(monkeypatch, control) -> None:
    """Default link: every record (positions, fields, estimates, commands) and every
    metric equal, to the bit, those of the plant stepped without a link; the link's
    own metrics say ideal (no lag, no age)."""
    overrides = [*SMALL, f"control={control}", "sim.t_final=0.2"]
    linked = list(simulate(overrides))
    with monkeypatch.context() as m:
        m.setattr(Agents, "advance", _advance_without_link)
        plain = list(simulate(overrides))
    assert len(linked) == len(plain) == 11
    for (a, ma), (b, mb) in zip(linked, plain, strict=True):
        np.testing.assert_array_equal(a.positions, b.positions)
        np.testing.assert_array_equal(a.estimate.p_hat, b.estimate.p_hat)
        np.testing.assert_array_equal(a.p_true, b.p_true)
        if a.command.field is not None:
            np.testing.assert_array_equal(a.command.field.centres, b.command.field.centres)
        for key, value in ma.items():
            if key in ("tracking_error", "command_age"):
                assert value == (None if a.step == 0 else 0.0)
            else:
                assert repr(value) == repr(mb[key]), key


def test_explicit_ideal_link_logs_the_same_bytes(tmp_path) -> None:
    """link.period = sim.dt given explicitly: the same message bytes as the default."""
    from mcap.reader import make_reader

    from harness.api import run

    def messages(path):
        with open(path / "run.mcap", "rb") as f:
            return [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f).iter_messages()]

    run([*SMALL, "sim.t_final=0.1"], tmp_path / "a")
    run([*SMALL, "sim.t_final=0.1", "link.period=0.02", "link.latency=0"], tmp_path / "b")
    a, b = messages(tmp_path / "a"), messages(tmp_path / "b")
    assert a == b
    assert "/swarm/poses" not in {topic for topic, _, _ in a}  # no headings, no channel


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        (["link.period=0.03"], "link.period"),  # not a whole number of 0.02 s steps
        (["link.latency=-0.02"], "link.latency"),
        (["link.loss=1"], "link.loss"),
        (["link.loss=nan"], "link.loss"),
        (["plant=meanfield", "link.latency=0.02"], "link.latency"),
        (["plant=meanfield", "link.loss=0.1"], "link.loss"),
    ],
)
def test_bad_link_values_are_refused_in_one_line(refusal, overrides, key) -> None:
    message = refusal([*SMALL, *overrides])
    assert message is not None and "\n" not in message
    assert key in message


def test_link_metrics_in_a_lossy_run() -> None:
    """Period 0.1 s, latency 0.2 s, loss 0.3 on unicycles: nothing arrives before 0.2 s
    (ages grow from 0), then the logged age is at least L dt and exceeds (L + P - 1) dt
    at some step (robots that missed a broadcast hold older commands), and the robots
    lag."""
    records = list(
        simulate(
            [
                *SMALL,
                "plant=unicycles",
                "link.period=0.1",
                "link.latency=0.2",
                "link.loss=0.3",
                "sim.t_final=1.0",
            ]
        )
    )
    ages = np.array([m["command_age"] for _, m in records[1:]])
    assert np.all(ages[:10] == pytest.approx(np.arange(10) * 0.02))  # nothing arrived yet
    assert np.all(ages[10:] >= 0.2 - 1e-12)
    assert ages[10:].max() > 0.28 + 1e-9
    assert max(m["tracking_error"] for _, m in records[1:]) > 0
