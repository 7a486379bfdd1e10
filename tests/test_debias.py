"""The debiased loop puts the robots on p_*; the paper's loop sharpens them."""

import numpy as np
import pytest

from analysis.load import load_run
from harness.runs.build import build
from harness.runs.run import run


def test_debiased_law_vanishes_at_the_smoothed_target(compose):
    # p_hat = K_h p_*, q_hat = G K_h p_*: the feedback term is zero, only the drift is left
    parts = build(compose(["kde.debias=true", "grid.n=20"]))
    ft = parts.control.feedback_target
    v = parts.control.field(ft.p, ft.grad)
    undebiased = build(compose(["grid.n=20"])).control
    drift = undebiased.field(parts.target.p, parts.target.grad)
    np.testing.assert_allclose(v.centres, drift.centres, atol=1e-15)
    # and the smoothed target is K_h p_*: smaller peaks, same mass
    assert ft.p.max() < parts.target.p.max()
    assert parts.grid.integrate(ft.p) == pytest.approx(1.0, abs=2e-3)


@pytest.mark.slow
def test_debiased_loop_reaches_the_floor_and_the_papers_does_not(tmp_path, compose):
    """N = 16384, paper's settings, 60 s: swarm_l2 within 1.3 x its floor (mean) for the
    debiased loop, above 2 x for the paper's loop."""
    ratios = {}
    for debias in (True, False):
        cfg = compose(
            [
                "agents.n=16384",
                "sim.t_final=60",
                f"kde.debias={str(debias).lower()}",
                "log.field_every=1000",
                "log.positions_every=500",
                "log.w2_every=6000",
                "log.floor_draws=20",
                "log.progress=off",
            ]
        )
        out = tmp_path / str(debias)
        assert run(cfg, out).state == "completed"
        log = load_run(out)
        floor = float(log.metadata["theory"]["swarm_l2_floor_mean"])
        ratios[debias] = log.metrics["swarm_l2"][-1] / floor
    assert ratios[True] < 1.3, ratios
    assert ratios[False] > 2.0, ratios
