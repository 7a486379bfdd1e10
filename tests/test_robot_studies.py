"""The robot and link studies' tables, boundary and figures: on synthetic rows with a
hand-made answer, and through the real CLI on a tiny sweep."""

import subprocess
import sys
from pathlib import Path

from analysis.robots import link_boundary, robots_table
from analysis.rows import CONFIG_PREFIX, OPTION_PREFIX


def _link_row(period, latency, loss, ratio, seed=0):
    return {
        CONFIG_PREFIX + "link.period": period,
        CONFIG_PREFIX + "link.latency": latency,
        CONFIG_PREFIX + "link.loss": loss,
        CONFIG_PREFIX + "seed": seed,
        "law": "paper",
        "state": "completed",
        "swarm_ratio": ratio,
    }


def test_link_boundary_from_a_known_grid():
    """Ratios 1 + period * latency + period / 10: within 1.5 where that sum is at most
    0.5; the boundary names exactly those cells."""
    rows = [
        _link_row(p, q, loss, 1.0 + p * q + p / 10)
        for p in (0.1, 1.0, 4.0)
        for q in (0.0, 0.2, 1.0)
        for loss in (0.0, 0.5)
    ]
    text = link_boundary(rows)
    line = next(x for x in text.splitlines() if x.startswith("| 0 |"))
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[1] == "4"  # at latency 0: 1 + 0.4 = 1.4 <= 1.5
    assert cells[2] == "1"  # at period 0.1: 1 + 0.1 + 0.01 <= 1.5; latency 1 is the largest
    inside = {(0.1, 0.0), (1.0, 0.0), (4.0, 0.0), (0.1, 0.2), (1.0, 0.2), (0.1, 1.0)}
    assert cells[3].count("(") == len(inside)
    for p, q in inside:
        assert f"({p:g}, {q:g})" in cells[3]
    assert "(4, 0.2)" not in cells[3]  # 1 + 0.8 + 0.4


def test_link_boundary_stops_at_the_first_failure():
    """A period that fails below one that passes ends the boundary there."""
    ratios = {0.1: 1.0, 1.0: 2.0, 4.0: 1.2}
    rows = [_link_row(p, 0.0, 0.0, r) for p, r in ratios.items()]
    rows += [_link_row(p, 1.0, 0.0, 3.0) for p in ratios]
    line = next(x for x in link_boundary(rows).splitlines() if x.startswith("| 0 |"))
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[1] == "0.1" and cells[2] == "0"


def test_robots_table_orders_plants_and_gives_intervals():
    plants = (("unicycles", 2.0), ("agents", 1.0), ("double_integrators", 3.0), ("dropout", 4.0))
    rows = [
        {
            OPTION_PREFIX + "plant": plant,
            CONFIG_PREFIX + "plant._target_": f"somewhere.{plant.title()}",
            CONFIG_PREFIX + "seed": seed,
            "law": "heat",
            "state": "completed",
            "swarm_ratio": ratio + seed,
            "tracking_tail_mean": 0.001,
            "settling_time": 2.0,
        }
        for plant, ratio in plants
        for seed in (0, 1)
    ]
    lines = [x for x in robots_table(rows).splitlines() if x.startswith("| heat")]
    # alphabetical by option; a plant without a label shows its option
    assert [x.split("|")[2].strip() for x in lines] == [
        "ideal integrators", "double integrators", "dropout", "unicycles",
    ]  # fmt: skip
    # the geometric mean of 1 and 2, its interval on the log scale
    assert lines[0].split("|")[3].strip().startswith(f"{2**0.5:.3g} (")


def test_link_figure_from_a_tiny_sweep(tmp_path):
    """Two periods on unicycles through the real CLI and the analysis."""
    sweep = tmp_path / "sweep"
    cmd = [
        sys.executable, "-m", "experiments.closed_loop", "-m", "+experiment=link",
        "link.period=0.02,0.04", "link.latency=0.02", "link.loss=0.5", "agents.n=64",
        "sim.t_final=0.2", "grid.n=12", "log.progress=off", "log.floor_draws=2",
        "log.positions_every=5", f"hydra.sweep.dir={sweep}",
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
    assert (out / "link.png").stat().st_size > 10_000
    assert "| 0.5 |" in (out / "link_boundary.md").read_text()
