"""The decentralised loop's consensus designs (``estimator.consensus``, ``share``,
``messages``): PI consensus against the first-order lag formula on a ramp, band
messages against the full-transform projection of grid consensus, every design against
the centralised loop on a complete graph, and the communication counts.
"""

import numpy as np
import pytest
import scipy.fft as sfft
import scipy.sparse as sp

from harness.estimators.distributed.band import BandMessages
from harness.estimators.distributed.consensus import (
    ConsensusForm,
    DynamicAverageConsensus,
    FirstOrder,
    ProportionalIntegral,
)
from harness.estimators.distributed.design import Design
from harness.estimators.distributed.estimator import RobotEstimators
from harness.estimators.distributed.graph import communication_graph
from harness.estimators.distributed.mixing import consensus_weights
from harness.estimators.distributed.robot_kde import kernel_factors, robot_kernels
from harness.estimators.filters.common import FilterSettings
from harness.grid import Grid
from harness.loop import trajectory
from harness.observers.motion import command_disagreement
from harness.records import Command, Estimate, StepRecord
from harness.runs.build import build

H = 0.04
FORMS: dict[str, type[ConsensusForm]] = {"first_order": FirstOrder, "pi": ProportionalIntegral}


def _ring(n: int, radius: float = 0.3) -> np.ndarray:
    ang = 2 * np.pi * np.arange(n) / n
    return np.stack([0.5 + radius * np.cos(ang), 0.5 + radius * np.sin(ang)])


@pytest.mark.parametrize("rounds", [1, 3])
def test_pi_tracks_a_ramp_without_lag_where_first_order_lags_by_its_formula(rng, rounds):
    """Inputs changing by a constant ``c`` per step (a ramp) on a fixed ring: the PI form's
    disagreement goes to zero; the first-order form settles at ``(I - W^m)^+ W^m Pi c``,
    computed here with a dense pseudo-inverse."""
    n, g = 12, Grid(6, 5)
    pos = _ring(n)
    w, _ = consensus_weights(communication_graph(pos, k_nearest=2))
    wd = w.toarray()
    c = rng.normal(size=(n, g.size))
    pi_c = c - c.mean(axis=0)
    wm = np.linalg.matrix_power(wd, rounds)
    lag = np.linalg.pinv(np.eye(n) - wm) @ wm @ pi_c  # on 1^perp: (I - W^m)^+ W^m Pi c
    assert np.linalg.norm(lag) > 0.5 * np.linalg.norm(pi_c)  # a real lag, not a tiny one
    errors = {}
    for form in FORMS:
        dac = DynamicAverageConsensus(g, H, rounds=rounds, form=FORMS[form]())
        dac.initialize(pos, w)
        z0 = rng.normal(size=(n, g.size))
        dac.z = z0.copy()
        if dac.w is not None:
            dac.w[...] = 0.0
        steps = 3000 // rounds
        for _ in range(steps):
            dac._mix(w, rounds, pos, c)
        # the invariant: the mean is the inputs' mean, whatever the form
        np.testing.assert_allclose(dac.z.mean(axis=0), (z0 + steps * c).mean(axis=0),
                                   rtol=1e-9, atol=1e-9)  # fmt: skip
        errors[form] = dac.z - dac.z.mean(axis=0)
    np.testing.assert_allclose(errors["first_order"], lag, atol=1e-9 * np.abs(lag).max())
    assert np.abs(errors["pi"]).max() < 1e-9 * np.abs(pi_c).max()


@pytest.mark.parametrize("form", [FirstOrder(), ProportionalIntegral(0.4)])
def test_compiled_rounds_match_the_plain_statement_on_moving_robots(rng, form):
    g = Grid.square(12)
    n = 70
    pos = rng.random((2, n))
    dac = DynamicAverageConsensus(g, H, rounds=2, gain=0.8, form=form)
    dac.initialize(pos, consensus_weights(communication_graph(pos, radius=0.2), 0.8)[0])
    z, acc = dac.z.copy(), None if dac.w is None else dac.w.copy()
    for _ in range(12):
        phi_old = robot_kernels(g, pos, H)
        pos = np.clip(pos + 0.03 * rng.normal(size=pos.shape), 0, 1)  # graph changes
        w, _ = consensus_weights(communication_graph(pos, radius=0.2), 0.8)
        ref, ref_w = dac.reference_step(z, robot_kernels(g, pos, H), phi_old, w, acc)
        z = dac.step(pos, w).copy()
        acc = None if dac.w is None else dac.w.copy()
        np.testing.assert_allclose(z, ref, atol=1e-12 * abs(ref).max())
        if isinstance(form, ProportionalIntegral):
            assert ref_w is not None and acc is not None
            np.testing.assert_allclose(acc, ref_w, atol=1e-12 * abs(ref).max())


def test_pi_form_is_stable_on_every_eigenvalue_the_gain_rule_admits():
    """The Jury conditions of the module docstring: with ``k_P = 1 - k_I^2`` both
    eigenvalues of a round lie inside the unit circle for every ``mu`` in ``(0, 2)``."""
    for k_i in (0.1, 0.5, 0.9):
        k_p = 1 - k_i**2
        for mu in np.linspace(1e-3, 2 - 1e-3, 400):
            a, b = k_p * mu, k_i * mu
            m = np.array([[1 - a, -b], [b * (1 - a), 1 - b * b]])
            assert np.abs(np.linalg.eigvals(m)).max() < 1.0, (k_i, mu)


@pytest.mark.parametrize("k_i", [0.3, 0.5, 0.9])
def test_one_pi_round_acts_on_a_laplacian_mode_as_the_gain_rule_says(k_i):
    """On the complete bipartite graph K_{n,n} the alternating vector is the Laplacian's
    eigenvector of eigenvalue 2 n, so ``mu = eps 2 n = 2 n / (1 + n)`` (near 2, where the
    Jury condition binds). One round from ``(z, w) = (e, 0)`` gives ``z' = (1 - k_P mu)
    e`` and ``w' = k_I mu z'`` with ``k_P = 1 - k_I^2``: the compiled round against the
    formula, so a wrong gain rule fails here."""
    n, g = 6, Grid(5, 4)
    adj = sp.csr_matrix(np.block([[np.zeros((n, n)), np.ones((n, n))],
                                  [np.ones((n, n)), np.zeros((n, n))]]))  # fmt: skip
    adj.sort_indices()
    w, eps = consensus_weights(adj)
    mu = eps * 2 * n
    assert mu == pytest.approx(2 * n / (1 + n))
    pos = np.random.default_rng(0).random((2, 2 * n))
    dac = DynamicAverageConsensus(g, H, rounds=1, form=ProportionalIntegral(k_i))
    dac.initialize(pos, w)
    e = np.repeat(np.r_[np.ones(n), -np.ones(n)][:, None], g.size, axis=1)
    dac.z, dac.w = e.copy(), np.zeros_like(e)
    dac._mix(w, 1, pos, np.zeros_like(e))
    k_p = 1 - k_i**2
    np.testing.assert_allclose(dac.z, (1 - k_p * mu) * e, atol=1e-12)
    np.testing.assert_allclose(dac.w, k_i * mu * (1 - k_p * mu) * e, atol=1e-12)


def test_agreement_is_w_to_the_rounds_on_grids_and_on_the_band_part(rng):
    """Eq. AGREE on a ring: ``W^m p_hat`` with grid messages; with band messages the part
    outside the band stays each robot's own: ``p - Pi p + W^m Pi p`` (dense reference,
    full-transform projector)."""
    g = Grid.square(30)
    pos = _ring(12)
    settings = FilterSettings(band_limit=np.inf)
    p_hat = rng.random((12, g.size))
    for messages in ("grid", "band"):
        design = Design(share="command", command_rounds=3, messages=messages, band_limit=2.0)
        est = RobotEstimators(g, 0.01, 12, H, settings, k_nearest=2, design=design)
        est._graph(pos)
        wm = np.linalg.matrix_power(est._w.toarray(), 3)
        agreed = est.agree(p_hat)
        if messages == "grid":
            expected = wm @ p_hat
        else:
            assert isinstance(est.messages, BandMessages)
            mask = est.messages.band.mask
            coef = sfft.dctn(p_hat.reshape(12, 30, 30), type=2, norm="ortho", axes=(1, 2)) * mask
            inside = sfft.idctn(coef, type=2, norm="ortho", axes=(1, 2)).reshape(12, -1)
            expected = p_hat - inside + wm @ inside
        np.testing.assert_allclose(agreed, expected, atol=1e-12)
    assert not np.allclose(agreed, p_hat)  # the agreement did something


def test_band_coefficients_of_the_kernels_are_their_transforms(rng):
    g = Grid.square(30)
    band = BandMessages(g, 2.5 / H)
    # the band's size, counted directly: modes (a, b) with pi^2 (a^2 + b^2) <= (2.5 / h)^2
    count = sum(
        1 for a in range(30) for b in range(30) if np.pi**2 * (a * a + b * b) <= (2.5 / H) ** 2
    )
    assert band.size == count == 329 and band.message_bytes == 8 * 329
    pos = rng.random((2, 25))
    phi = robot_kernels(g, pos, H).reshape(-1, 30, 30)
    full = sfft.dctn(phi, type=2, norm="ortho", axes=(1, 2))
    kx, _, ky, _ = kernel_factors(g, pos, H)
    coef = band.kernels(kx, ky)
    np.testing.assert_allclose(coef, full[:, band.rows, band.cols], atol=1e-12 * abs(full).max())


@pytest.mark.parametrize("form", ["first_order", "pi"])
def test_band_messages_reconstruct_the_band_projected_grid_consensus(rng, form):
    """Consensus on the band's coefficients and on grid fields, same robots and graphs:
    each robot's reconstructed field is the band projection of its grid state, by the
    full inverse transform, to 1e-12."""
    g = Grid.square(30)
    n = 60
    pos = rng.random((2, n))
    band = BandMessages(g, 2.0 / H)
    on_grid = DynamicAverageConsensus(g, H, rounds=2, form=FORMS[form]())
    on_band = DynamicAverageConsensus(g, H, rounds=2, form=FORMS[form](), messages=band)
    adj = communication_graph(pos, radius=0.25)
    w, _ = consensus_weights(adj)
    on_grid.initialize(pos, w)
    on_band.initialize(pos, w)
    mask = band.band.mask
    for _ in range(10):
        pos = np.clip(pos + 0.01 * rng.normal(size=pos.shape), 0, 1)
        w, _ = consensus_weights(communication_graph(pos, radius=0.25))
        grid_fields = on_grid.step(pos, w).reshape(n, 30, 30)
        robot_fields = on_band.step(pos, w)
        coef = sfft.dctn(grid_fields, type=2, norm="ortho", axes=(1, 2)) * mask
        projected = sfft.idctn(coef, type=2, norm="ortho", axes=(1, 2)).reshape(n, -1)
        scale = abs(projected).max()
        np.testing.assert_allclose(robot_fields, projected, atol=1e-12 * scale)
        assert on_band.z.shape == (n, band.size)


SLOW = pytest.mark.slow
SMALL = ("grid.n=16", "agents.n=300", "sim.dt=0.01", "log.progress=off")


@pytest.mark.parametrize(
    "design",
    [
        pytest.param(
            ["estimator.consensus=pi", "estimator.rounds=70", "estimator.initial_rounds=70"],
            marks=SLOW,
        ),
        pytest.param(["estimator.messages=band", "estimator.band_limit=1.5"], marks=SLOW),
        pytest.param(["estimator.share=command", "estimator.command_rounds=2"], marks=SLOW),
        # all three together (in make test; each alone with make test-slow)
        ["estimator.consensus=pi", "estimator.rounds=70", "estimator.initial_rounds=70",
         "estimator.messages=band", "estimator.band_limit=1.5", "estimator.share=command"],
    ],
)  # fmt: skip
def test_every_design_equals_the_centralised_loop_on_a_complete_graph(compose, design):
    """Radius 2: the graph is complete; with exact consensus (one first-order round, or
    enough PI rounds) every robot's estimate is the reference's, and its command is the
    law of the reference's estimate at its position, to 1e-10, along a closed-loop run."""
    parts = build(compose(["estimator=distributed", *SMALL, "estimator.radius=2.0", *design]))
    steps = trajectory(parts)
    rec, _ = next(steps)
    for step in range(25):
        robots = rec.estimate.robots
        assert robots is not None and robots.reference is not None
        scale = np.abs(robots.reference).max()
        gap = np.abs(robots.p_hat - robots.reference).max()
        assert gap < 1e-10 * scale, (step, gap)
        command = rec.command
        assert command.robots is not None and command.reference is not None
        scale_v = np.abs(command.reference).max()
        np.testing.assert_allclose(command.robots, command.reference, atol=1e-10 * scale_v)
        rec, _ = next(steps)


def test_messages_and_bytes_per_design():
    """Counts on a ring where every robot has two neighbours: first order sends ``m``
    messages of ``C`` values per neighbour, PI ``2 m`` messages carrying ``3 C`` values,
    the agreement ``m_c`` more of ``C``."""
    g = Grid.square(30)
    pos = _ring(10)
    adj = communication_graph(pos, k_nearest=2)
    settings = FilterSettings(band_limit=np.inf)
    cases = [
        ({}, 3 * 2, 3 * 2 * 900 * 8, 900 * 8),
        ({"consensus": "pi"}, 2 * 3 * 2, 3 * 2 * 3 * 900 * 8, 2 * 900 * 8),
        ({"messages": "band"}, 3 * 2, 3 * 2 * 329 * 8, 329 * 8),
        ({"messages": "band", "share": "command", "command_rounds": 2},
         3 * 2 + 2 * 2, (3 * 2 + 2 * 2) * 329 * 8, 329 * 8),
    ]  # fmt: skip
    for kwargs, messages, total, largest in cases:
        est = RobotEstimators(g, 0.01, 10, H, settings, k_nearest=2, rounds=3,
                              design=Design(**kwargs))  # fmt: skip
        counts = est.communication(adj)
        assert counts["messages"] == messages, kwargs
        assert counts["bytes"] == total, kwargs
        assert counts["message_bytes"] == largest, kwargs


def test_command_disagreement_on_known_velocities():
    robots = np.array([[0.0, 3.0], [0.0, 0.0]])
    reference = np.array([[0.0, 0.0], [1.0, 4.0]])
    est = Estimate(np.zeros((4, 4)), np.zeros((2, 4, 4)))

    def record(command: Command) -> StepRecord:
        return StepRecord(0, 0.0, np.zeros((4, 4)), None, est, command, np.zeros((2, 2)))

    assert command_disagreement(record(Command(None, robots, reference))) == pytest.approx(3.0)
    assert command_disagreement(record(Command(None, robots))) is None


@pytest.mark.parametrize(
    ("key", "value"),
    [("consensus", "second_order"), ("integral_gain", 1.0), ("share", "velocity"),
     ("command_rounds", 0), ("messages", "wavelets"), ("band_limit", "inf")],
)  # fmt: skip
def test_a_design_value_not_allowed_is_refused_in_one_line_naming_its_key(refusal, key, value):
    message = refusal(["estimator=distributed", *SMALL, f"estimator.{key}={value}"])
    assert message is not None and message.startswith("invalid config:"), message
    assert f"estimator.{key}" in message and "\n" not in message, message
