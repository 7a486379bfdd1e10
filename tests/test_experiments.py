import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from harness.config import register_configs

CONF = Path(__file__).resolve().parents[1] / "conf"


@pytest.mark.parametrize("target", ["three_bumps", "uniform"])
@pytest.mark.parametrize("init", ["paper_box", "uniform"])
def test_meanfield_config_composes(target, init):
    register_configs()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("meanfield", overrides=[f"target={target}", f"init={init}"])
    assert cfg.grid.n == 30 and cfg.dynamics.sigma == pytest.approx(5e-5)
    assert OmegaConf.select(cfg, "target.kind") in ("gaussian_mixture", "uniform")


def test_bad_type_fails_at_composition():
    register_configs()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        with pytest.raises(Exception, match=r"grid\.n"):
            compose("meanfield", overrides=["grid.n=abc"])


def test_meanfield_experiment_runs_and_writes_figure(tmp_path):
    cmd = [
        sys.executable,
        "-m",
        "experiments.meanfield_convergence",
        "grid.n=12",
        "sim.t_final=1.0",
        "sim.dt=0.05",
        f"hydra.run.dir={tmp_path / 'run'}",
        f"figures_dir={tmp_path / 'fig'}",
    ]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=CONF.parent, timeout=300)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "fig" / "meanfield_convergence.png").stat().st_size > 10_000
    rows = (tmp_path / "run" / "meanfield.csv").read_text().splitlines()
    assert rows[0].startswith("t_s,") and len(rows) == 1 + 21
