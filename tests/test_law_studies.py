"""The law studies' statistics, table and figures, on synthetic logs and on a tiny sweep."""

import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from analysis.laws import laws_table
from analysis.rows import CONFIG_PREFIX, varied
from analysis.run_stats import motion_stats


def _run(metrics):
    return SimpleNamespace(metrics={k: np.asarray(v, dtype=float) for k, v in metrics.items()})


def test_motion_statistics_against_hand_computed_values():
    t = np.linspace(0.0, 10.0, 101)
    effort = np.full_like(t, 0.04)  # constant: the integral is 0.04 * 10
    speed = np.where(t >= 7.5, 0.3, 1.0)
    swarm = np.full_like(t, np.nan)
    swarm[::10] = np.linspace(1.0, 0.1, 11)  # evaluated every 10 steps
    out = motion_stats(
        _run({"t": t, "effort": effort, "mean_speed": speed, "swarm_l2": swarm}),
        t >= 7.5,
        floor_mean=0.2,
    )
    assert math.isclose(out["effort_integral"], 0.4, rel_tol=1e-12)
    assert math.isclose(out["speed_tail_mean"], 0.3, rel_tol=1e-12)
    # first evaluated swarm_l2 <= 1.5 * 0.2 = 0.3: 1.0 - 0.09 k <= 0.3 at k = 8, t = 8 s
    assert out["settling_time"] == 8.0


def test_settling_never_is_inf_and_without_robots_nan():
    t = np.linspace(0.0, 1.0, 11)
    far = motion_stats(_run({"t": t, "swarm_l2": np.ones_like(t)}), t >= 0.75, floor_mean=0.1)
    assert far["settling_time"] == math.inf
    none = motion_stats(_run({"t": t}), t >= 0.75, floor_mean=0.1)
    assert math.isnan(none["settling_time"]) and math.isnan(none["effort_integral"])


def test_a_components_copy_of_the_seed_is_not_an_axis():
    rows = [
        {CONFIG_PREFIX + "seed": s, CONFIG_PREFIX + "control.seed": s, CONFIG_PREFIX + "n": n}
        for s in (0, 1)
        for n in (4, 8)
    ]
    rows.append({CONFIG_PREFIX + "seed": 0, CONFIG_PREFIX + "n": 4})  # a law without one
    assert varied(rows) == ["n", "seed"]
    rows[0][CONFIG_PREFIX + "control.seed"] = 7  # no longer a copy: an axis
    assert "control.seed" in varied(rows)


def _row(law, n, seed, ratio, settle):
    return {
        CONFIG_PREFIX + "agents.n": n,
        CONFIG_PREFIX + "seed": seed,
        "law": law,
        "law_uses": "estimate",
        "law_divides_by_density": "no",
        "state": "completed",
        "swarm_ratio": ratio,
        "settling_time": settle,
        "t_end": 25.0,
        "ms_per_step": 2.0,
    }


def test_the_table_gives_geometric_means_intervals_and_unsettled_seeds():
    rows = [
        _row("paper", 1024, 0, 1.0, 3.0),
        _row("paper", 1024, 1, 3.0, math.inf),
        _row("paper", 16384, 0, 2.0, math.inf),
        _row("paper", 16384, 1, 2.0, math.inf),
        _row("my_law", 1024, 0, 1.5, 2.0),  # a law of one's own, under its option name
    ]
    table = laws_table(rows)
    laws = [line.split("|")[1].strip() for line in table.splitlines()[2:]]
    assert laws == ["my_law", "paper"]  # alphabetical
    line = next(x for x in table.splitlines() if x.startswith("| paper"))
    cells = [c.strip() for c in line.split("|")[1:-1]]
    # ratios 1 and 3: geometric mean sqrt(3), 95 % t interval on the logs, above zero
    logs = [0.0, math.log(3.0)]
    half = 12.706 * (math.log(3.0) / math.sqrt(2)) / math.sqrt(2)
    low, high = math.exp(sum(logs) / 2 - half), math.exp(sum(logs) / 2 + half)
    assert cells[3] == f"{math.sqrt(3):.3g} ({low:.3g} to {high:.3g})"
    assert cells[4] == "2 (2 to 2)"  # no spread
    # settled at 3 s on one seed of two (the other censored at 25 s): S(3) = 1/2, the
    # Kaplan-Meier median is 3 s, and no time bounds its interval from above
    assert cells[8] == "3.0 (3.0 to beyond the run), 1 of 2 seeds"
    assert cells[9] == "500"


def test_law_figures_from_a_tiny_sweep(tmp_path):
    """Two laws, two swarm sizes, through the real CLI and the analysis."""
    sweep = tmp_path / "sweep"
    cmd = [
        sys.executable, "-m", "experiments.closed_loop", "-m", "+experiment=laws_n",
        "agents.n=64,128", "control=paper,mmd", "seed=0", "sim.t_final=0.4",
        "grid.n=12", "log.progress=off", "log.floor_draws=2", "log.positions_every=5",
        f"hydra.sweep.dir={sweep}",
    ]  # fmt: skip
    subprocess.run(cmd, check=True, capture_output=True, cwd=Path(__file__).parents[1])
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-m", "analysis.sweep", str(sweep), "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=Path(__file__).parents[1],
    )
    assert done.returncode == 0, done.stderr
    assert (out / "laws_n.png").stat().st_size > 10_000
    table = (out / "laws_table.md").read_text()
    assert "| paper | estimate, gradient estimate | no |" in table
    assert "| mmd | positions, target smoothed by the kernel | no |" in table
