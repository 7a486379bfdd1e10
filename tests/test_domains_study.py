"""The start region's metric, its statistics and the figure of the study of every law on
domains with obstacles: against hand counts on small grids, through a real run on the
rooms, and through the real CLI on a tiny sweep with a law the domain refuses."""

import csv
import json
import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from analysis.load import load_run
from analysis.run_stats import START_STATS, STATS, start_stats
from harness.grid import Grid
from harness.observers.swarm import START_KEYS, SwarmTruth, domain_keys
from harness.observers.swarm_metrics import StartRegion
from harness.targets.densities import Box, Target, Uniform
from tests.domain_cases import DOMAINS

ROOT = Path(__file__).parents[1]


def test_start_region_counts_robots_in_the_initial_support_against_the_targets_mass():
    """Rooms on a 20 x 20 grid (wall columns 9 and 10 blocked but for the door's rows
    8-11), the start box [0.3, 0.45] x [0.2, 0.8] over columns 6-8 and rows 4-15: 36
    cells; the uniform target gives each free cell the same mass."""
    grid = Grid.square(20)
    free = DOMAINS["rooms"].resolve(grid)
    assert not free.cells[:8, 9:11].any() and free.cells[8:12, 9:11].all()
    init = Box(0.3, 0.45, 0.2, 0.8).on_grid(grid)
    target = Target.from_density(grid, Uniform(), free)
    region = StartRegion(init, target.p, free)
    expected = np.zeros(grid.shape, dtype=bool)
    expected[4:16, 6:9] = True
    np.testing.assert_array_equal(region.region, expected)
    assert region.target_mass == pytest.approx(36 / free.cells.sum(), rel=1e-13)
    assert free.cells.sum() == 400 - 2 * 16
    # in the box, in its corner cell, in the left room outside it, in the right room;
    # in the wall's blocked cells at (0.46, 0.3), nearest the free centre (0.425, 0.325)
    # of the box, and at (0.46, 0.1), nearest (0.425, 0.125) below the box
    robots = np.array([[0.35, 0.44, 0.05, 0.8, 0.46, 0.46], [0.5, 0.79, 0.5, 0.5, 0.3, 0.1]])
    assert region.fraction(robots) == pytest.approx(3 / 6, abs=1e-15)
    assert region.fraction(np.array([[0.35], [0.5]])) == 1.0


def test_start_region_of_an_initial_density_in_obstacles_only_is_refused():
    grid = Grid.square(20)
    free = DOMAINS["rooms"].resolve(grid)
    init = np.zeros(grid.shape)
    init[:8, 9] = 1.0  # only blocked cells of the wall
    assert not free.cells[:8, 9].any()
    with pytest.raises(ValueError, match="init"):
        StartRegion(init, np.ones(grid.shape), free)


def test_swarm_observer_gives_the_start_metrics_on_obstacles_with_an_initial_density():
    grid = Grid.square(10)
    free = DOMAINS["rooms"].resolve(grid)
    target = Target.from_density(grid, Uniform(), free)
    box = Box(0.1, 0.3, 0.2, 0.8)
    assert domain_keys(free)[-2:] == START_KEYS
    with_init = SwarmTruth(grid, target, 10, 0.1, True, "auto", 1, 1, init=box)
    assert set(START_KEYS) <= set(with_init.gives)
    without = SwarmTruth(grid, target, 10, 0.1, True, "auto", 1, 1)
    assert not set(START_KEYS) & set(without.gives)
    square = Target.from_density(grid, Uniform())
    plain = SwarmTruth(grid, square, 10, 0.1, True, "auto", 1, 1, init=box)
    assert domain_keys(None) == () and not set(START_KEYS) & set(plain.gives)


def _run(tmp_path, *overrides):
    out = tmp_path / "run"
    _write_run(out, *overrides)
    return load_run(out / "run.mcap")


def _write_run(out, *overrides):
    cmd = [
        sys.executable, "-m", "experiments.closed_loop", "+experiment=smoke",
        "log.progress=off", "log.floor_draws=2", f"hydra.run.dir={out}", *overrides,
    ]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr


@pytest.fixture(scope="module")
def rooms_run(tmp_path_factory):
    """The directory of a short run on the rooms, the swarm starting in the left room."""
    out = tmp_path_factory.mktemp("rooms") / "run"
    _write_run(out, "domain=rooms", "init=left_room")
    return out


def test_a_run_on_the_rooms_logs_the_start_fraction_against_the_targets_mass(rooms_run):
    """The build hands the initial density to the swarm observer: every robot starts
    in the support of init=left_room, and the target's mass there is the sum of the
    logged target's cells over the box's cells (hand-counted from the log's own mask)."""
    run = load_run(rooms_run / "run.mcap")
    m = run.metrics
    seen = np.isfinite(m["start_fraction"])
    assert seen[0] and seen.sum() >= 3
    assert m["start_fraction"][0] == 1.0
    assert ((m["start_fraction"][seen] >= 0) & (m["start_fraction"][seen] <= 1)).all()
    grid = Grid.square(12)
    box = np.zeros(grid.shape, dtype=bool)  # cells the box [0.08, 0.42] x [0.15, 0.85] overlaps
    box[(grid.y > 0.15 - grid.dy / 2) & (grid.y < 0.85 + grid.dy / 2)] = True
    box[:, (grid.x <= 0.08 - grid.dx / 2) | (grid.x >= 0.42 + grid.dx / 2)] = False
    assert run.domain is not None and run.domain.free is not None
    free = run.domain.free
    p = run.fields["/fields/p_target"].values[0, 0].astype(float)
    expected = p[box & free].sum() / p[free].sum()
    mass = m["start_target_mass"][seen]
    np.testing.assert_allclose(mass, expected, rtol=1e-6)  # the field is float32
    assert 0 < expected < 1


def test_a_square_run_has_no_start_metrics(tmp_path):
    run = _run(tmp_path)
    assert not set(START_KEYS) & set(run.metrics)


def _metrics(**columns):
    return SimpleNamespace(metrics={k: np.asarray(v, dtype=float) for k, v in columns.items()})


def test_start_statistics_against_hand_computed_values():
    """Fraction 1 - t / 20 evaluated every other step for t in [0, 10] s, the target's
    mass 0.4: the excess 0.6 - t / 20 halves (0.3) at t = 6 s; over the tail t >= 7.5 s
    (evaluated at 8 and 10) the fraction's mean is 1 - 9 / 20."""
    t = np.linspace(0.0, 10.0, 11)
    fraction = np.where(np.arange(11) % 2 == 0, 1.0 - t / 20, np.nan)
    mass = np.where(np.isfinite(fraction), 0.4, np.nan)
    out = start_stats(_metrics(t=t, start_fraction=fraction, start_target_mass=mass), t >= 7.5)
    assert out["start_target_mass"] == 0.4
    assert out["start_fraction_tail_mean"] == pytest.approx(1 - 9 / 20, abs=1e-15)
    assert out["start_excess_tail_mean"] == pytest.approx(0.6 - 9 / 20, abs=1e-15)
    assert out["start_half_time"] == 6.0
    stuck = start_stats(
        _metrics(t=t, start_fraction=np.ones(11), start_target_mass=np.full(11, 0.4)), t >= 7.5
    )
    assert stuck["start_half_time"] == math.inf
    square = start_stats(_metrics(t=t), t >= 7.5)
    assert all(math.isnan(square[k]) for k in START_STATS)
    assert set(START_STATS) <= set(STATS)


def test_the_domains_preset_sweeps_every_law_on_rooms_and_obstacles():
    from omegaconf import OmegaConf

    preset = OmegaConf.load(ROOT / "conf" / "experiment" / "domains.yaml")
    params = preset.hydra.sweeper.params
    assert params.control == "glob(*)"
    assert set(str(params.domain).split(",")) == {"rooms", "obstacles"}
    assert set(str(params["agents.n"]).split(",")) == {"1024", "4096"}
    assert len(str(params.seed).split(",")) >= 3
    assert preset.sim.t_final == 60.0
    assert list(preset.analysis.primary) == ["domain", "law", "agents.n"]


def test_domains_figure_from_a_tiny_sweep_with_a_refused_law(tmp_path):
    """The study's preset, shortened: two laws and mmd (refused on obstacles until it
    honours them, or run), both domains, two sizes. A refused job is `invalid` in the
    sweep's status table and the others run; the analysis writes the figure and the
    start statistics of every completed point."""
    sweep = tmp_path / "sweep"
    cmd = [
        sys.executable, "-m", "experiments.closed_loop", "-m", "+experiment=domains",
        "control=paper,heat,mmd", "agents.n=64,128", "seed=0", "sim.t_final=0.5",
        "sim.dt=0.05", "grid.n=12", "log.progress=off", "log.floor_draws=2",
        "log.positions_every=2", "log.w2_every=10", f"hydra.sweep.dir={sweep}",
        "hydra.callbacks.sweep_status.progress=off",
    ]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    with open(sweep / "sweep_status.csv", newline="") as f:
        status = list(csv.DictReader(f))
    assert len(status) == 12
    by_law = {}
    for row in status:
        law = next(o.split("=")[1] for o in row["overrides"].split() if o.startswith("control="))
        by_law.setdefault(law, set()).add(row["state"])
    assert by_law["paper"] == by_law["heat"] == {"completed"}
    assert by_law["mmd"] in ({"completed"}, {"invalid"})
    assert done.returncode == (0 if by_law["mmd"] == {"completed"} else 1), done.stderr
    out = tmp_path / "out"
    analysed = subprocess.run(
        [sys.executable, "-m", "analysis.sweep", str(sweep), "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert analysed.returncode == 0, analysed.stderr
    assert (out / "domains.png").stat().st_size > 10_000
    with open(out / "sweep_aggregated.csv", newline="") as f:
        points = list(csv.DictReader(f))
    completed = [law for law, states in by_law.items() if states == {"completed"}]
    assert len(points) == 2 * 2 * len(completed)
    for a in points:
        assert a["domain"] in ("rooms", "obstacles") and a["law"] in completed
        assert 0 < float(a["start_target_mass_mean"]) < 1
        assert 0 <= float(a["start_fraction_tail_mean_mean"]) <= 1
    assert "start region" in analysed.stdout
    json.dumps(points)  # plain values


def test_the_picture_draws_the_robots_and_obstacles_of_a_rooms_log(rooms_run, tmp_path):
    """The README's picture from a log alone: a PNG of the declared size whose pixels
    hold the obstacles' grey and the robots' black."""
    import matplotlib.image

    from analysis.figures import OBSTACLE_GREY
    from analysis.swarm_picture import DPI, SIDE_INCHES, main

    out = tmp_path / "rooms.png"
    assert main([str(rooms_run), "--at", "0.1", "--out", str(out)]) == 0
    image = matplotlib.image.imread(out)
    side = round(SIDE_INCHES * DPI)
    assert image.shape[:2] == (side, side)
    rgb = image[..., :3]
    grey = float(OBSTACLE_GREY)
    assert (np.abs(rgb - grey).max(axis=-1) < 0.02).sum() > 100  # the wall
    assert (rgb.max(axis=-1) < 0.1).sum() > 100  # the robots


def test_the_picture_refuses_a_log_without_robots_in_one_line(tmp_path, capsys):
    from analysis.swarm_picture import main

    run_dir = tmp_path / "meanfield"
    _write_run(run_dir, "plant=meanfield", "estimator=exact")
    assert main([str(run_dir), "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no robots' positions" in err
    assert not (tmp_path / "x.png").exists()
    assert main([str(tmp_path / "nothing"), "--out", str(tmp_path / "x.png")]) == 2
