"""The decentralised loop through the harness (``estimator=distributed``): the robots'
estimates against the centralised reference run alongside, the per-robot velocities,
the log's fields and metrics, and the refusals.

The building blocks (graph, consensus, per-robot filters) are tested against
brute-force and reference implementations in ``tests/test_distributed.py``.
"""

import numpy as np
import pytest

from analysis.load import load_run
from harness.control.paper import PaperControl
from harness.loop import trajectory
from harness.observers.log import METRIC_KEYS
from harness.records import Command, ControlInput
from harness.runs.build import build
from harness.runs.run import run
from harness.velocity import interpolate

NETWORK_KEYS = METRIC_KEYS[-8:]
assert NETWORK_KEYS[0] == "consensus_l2"

SMALL = ("grid.n=16", "agents.n=600", "sim.dt=0.01", "log.progress=off")  # binned plant KDE


def _loop(compose, overrides):
    parts = build(compose(["estimator=distributed", *SMALL, *overrides]))
    return trajectory(parts), parts


@pytest.mark.parametrize("gradient", ["grid", "fourth_order"])
def test_complete_graph_robots_equal_the_centralised_reference_in_the_loop(compose, gradient):
    """Radius 2 covers the unit square: the graph is complete, one round is exact
    consensus, and every robot's estimate equals the centralised filter's on the plant's
    KDE at every step; each robot then moves exactly as it would on the broadcast field
    (the law of the robots' mean estimate and its central differences of the same
    order)."""
    overrides = ["estimator.radius=2.0", "estimator.initial_rounds=1"]
    steps, parts = _loop(compose, [*overrides, f"estimator.gradient={gradient}"])
    rec, _ = next(steps)
    for step in range(40):
        robots = rec.estimate.robots
        assert robots is not None
        p_central = rec.estimate.fields["p_hat_central"]
        scale = np.abs(p_central).max()
        gap = np.abs(robots.p_hat - p_central.ravel()).max()
        assert gap < 1e-10 * scale, (step, gap)
        assert rec.estimate.metrics["central_gap_l2"] < 1e-10
        assert rec.estimate.metrics["components"] == 1.0
        np.testing.assert_allclose(rec.estimate.p_hat, p_central, atol=1e-10 * scale)
        command = rec.command
        assert command.robots is not None and command.field is not None
        broadcast = interpolate(parts.grid, command.field.centres, rec.positions)
        scale_v = np.abs(broadcast).max()
        np.testing.assert_allclose(command.robots, broadcast, atol=1e-10 * scale_v)
        rec, _ = next(steps)


def test_disconnected_robots_drift_apart_and_away_from_the_reference(compose):
    """Radius 0: no robot hears any other; each filters its own kernel, so the robots
    disagree by about a kernel's norm and the gap to the reference is of that size."""
    steps, _ = _loop(compose, ["estimator.radius=0.0"])
    for _ in range(6):
        rec, _ = next(steps)
    net = rec.estimate.metrics
    assert net["components"] == 600.0 and net["mean_degree"] == 0.0
    assert net["messages"] == 0.0 and net["algebraic_connectivity"] == 0.0
    # one robot's own kernel has L2 norm 1 / (2 sqrt(pi) h) ~ 7 (away from the walls)
    assert net["consensus_l2"] > 2.0 and net["central_gap_l2"] > 2.0


def test_log_holds_the_three_estimates_and_the_network_metrics(tmp_path, compose, smoke):
    cfg = compose(["estimator=distributed", *smoke, "estimator.robot=7"])
    result = run(cfg, tmp_path)
    assert result.state == "completed", result.reason
    log = load_run(tmp_path)
    for topic in ("/fields/p_hat", "/fields/p_hat_central", "/fields/p_hat_robot"):
        assert topic in log.fields
    for key in NETWORK_KEYS:
        values = np.asarray(log.metrics[key], dtype=float)
        assert np.isfinite(values).all(), key
    # the command disagreement from the first step on (the reference's command is there)
    assert np.isfinite(np.asarray(log.metrics["command_disagreement"], dtype=float)).all()
    assert set(log.metrics) == set(METRIC_KEYS)
    # the logged robot's field is robot 7's estimate: it differs from the mean and the
    # reference (graph of radius 0.1 on 200 robots, consensus not exact)
    robot = log.fields["/fields/p_hat_robot"].values[-1]
    mean = log.fields["/fields/p_hat"].values[-1]
    assert np.abs(robot - mean).max() > 1e-3


def test_centralised_runs_log_the_network_metrics_as_null(tmp_path, compose, smoke):
    result = run(compose(list(smoke)), tmp_path)
    assert result.state == "completed"
    log = load_run(tmp_path)
    for key in (*NETWORK_KEYS, "command_disagreement"):
        assert np.isnan(np.asarray(log.metrics[key], dtype=float)).all(), key
    assert "/fields/p_hat_central" not in log.fields


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        (["plant=meanfield"], "plant"),
        (["estimator.radius=null"], "estimator.radius"),
        (["estimator.radius=null", "estimator.k_nearest=-1"], "estimator.k_nearest"),
        (["estimator.radius=-0.1"], "estimator.radius"),
        (["estimator.robot=600"], "estimator.robot"),
        (["estimator.gradient=filter"], "estimator.gradient"),
        (["estimator.gain=1.5"], "estimator.gain"),
        (["estimator.rounds=0"], "estimator.rounds"),
        (["kde.mirror=false"], "kde.mirror"),
    ],
)
def test_bad_decentralised_configs_are_refused_naming_the_key(refusal, overrides, key):
    message = refusal(["estimator=distributed", *SMALL, *overrides])
    assert message is not None and message.startswith(f"invalid config: {key}="), message


def test_k_nearest_graph_runs(compose):
    steps, _ = _loop(compose, ["estimator.radius=null", "estimator.k_nearest=6"])
    next(steps)
    rec, _ = next(steps)
    assert rec.estimate.metrics["mean_degree"] >= 6.0


def test_a_law_without_cell_values_is_refused(refusal, tmp_path):
    """A control without ``at_cells`` cannot be evaluated by each robot."""
    message = refusal(
        ["estimator=distributed", *SMALL, "control._target_=tests.test_decentralised.FieldOnly"]
    )
    assert message is not None and message.startswith("invalid config: control="), message


class FieldOnly:
    """A law on fields only (it does not evaluate the robots' own estimates)."""

    gives_field = True
    own_estimates = False

    def __init__(self, target, alpha, sigma, **debias):
        self.inner = PaperControl(target, alpha, sigma, **debias)

    def __call__(self, inp: ControlInput) -> Command:
        return Command(self.inner.field(inp.estimate.p_hat, inp.estimate.q_hat))

    def feedback_diffusivity(self, p0):
        return self.inner.feedback_diffusivity(p0)


class CappedPaper(PaperControl):
    """A law that changes ``field`` but inherits ``at_cells``: refused."""

    def field(self, p_hat, q_hat):
        return super().field(p_hat, q_hat)


class SamePaper(PaperControl):
    """A subclass that changes neither: the parent's cell values are its own."""


def test_a_law_that_inherits_another_laws_cell_values_is_refused(refusal):
    assert PaperControl.own_estimates and SamePaper.own_estimates
    assert not CappedPaper.own_estimates
    message = refusal(
        ["estimator=distributed", *SMALL, "control._target_=tests.test_decentralised.CappedPaper"]
    )
    assert message is not None and message.startswith("invalid config: control="), message
    assert "own at_cells" in message


def test_a_law_without_a_field_is_refused_where_a_field_is_needed(refusal):
    """The mean-field plant, the agents plant's limit and the filters need the field."""
    law = "control._target_=tests.test_decentralised.RobotsOnly"
    for overrides in (["plant=meanfield", "estimator=exact"], ["estimator=kde"], []):
        message = refusal([*SMALL, law, *overrides])
        assert message is not None and message.startswith("invalid config: control="), message
        assert "velocity field" in message


class RobotsOnly(FieldOnly):
    """A law that moves robots only."""

    gives_field = False
