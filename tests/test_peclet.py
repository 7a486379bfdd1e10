import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from analysis.peclet import cell_peclet, job_peclet, main, summary

ROOT = Path(__file__).resolve().parents[1]


def test_cell_peclet_of_a_uniform_field():
    v = np.empty((2, 3, 4))
    v[0], v[1] = 0.01, -0.02
    pe = cell_peclet(v, (1 / 32, 1 / 16), 5e-5)
    # max(0.01 / 32, 0.02 / 16) / 5e-5 = 1.25e-3 / 5e-5
    np.testing.assert_allclose(pe, 25.0, rtol=1e-14)
    assert summary(pe) == pytest.approx((25.0, 25.0, 1.0))
    assert summary(np.array([0.0, 1.0, 3.0, 5.0]))[2] == 0.5


@pytest.mark.parametrize("sigma", [0.0, -1.0, float("nan")])
def test_cell_peclet_refuses_a_non_positive_sigma(sigma):
    with pytest.raises(ValueError, match="sigma"):
        cell_peclet(np.zeros((2, 2, 2)), (0.1, 0.1), sigma)


def test_cell_peclet_refuses_a_scalar_field():
    with pytest.raises(ValueError, match="shape"):
        cell_peclet(np.zeros((2, 2)), (0.1, 0.1), 1.0)


def test_peclet_of_a_logged_run_is_the_drift_of_the_target(tmp_path, compose):
    """With alpha = 0 the paper's law is the drift sigma grad p_* / p_* alone, so the
    logged Peclet number is max(|d_x p_*| dx, |d_y p_*| dy) / p_* (sigma cancels),
    computed here from the target the app builds, not from the log."""
    from harness.runs.build import build

    overrides = ["grid.n=12", "agents.n=100", "sim.t_final=0.04", "sim.dt=0.02",
                 "log.progress=off", "control.alpha=0", "log.field_every=1"]  # fmt: skip
    subprocess.run(
        [sys.executable, "-m", "experiments.closed_loop", *overrides,
         f"hydra.run.dir={tmp_path / 'run'}"],
        cwd=ROOT, check=True, capture_output=True, timeout=600,
    )  # fmt: skip
    target = build(compose(overrides)).control.target
    g = target.grid
    expected = np.maximum(np.abs(target.grad[0]) * g.dx, np.abs(target.grad[1]) * g.dy)
    expected /= target.p
    size, pe, t = job_peclet(tmp_path / "run", at=None)
    assert size == 12 and t == pytest.approx(0.04)
    np.testing.assert_allclose(pe, expected, rtol=1e-5)  # the log holds float32
    with pytest.raises(ValueError, match="no velocity field"):
        job_peclet(tmp_path / "run", at=10.0)


def test_peclet_cli_without_logs_exits_2(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    assert "no readable log" in capsys.readouterr().err
