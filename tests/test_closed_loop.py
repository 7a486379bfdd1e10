import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from analysis.load import load_run
from harness.grid import Grid
from harness.observers.log import METRIC_KEYS
from harness.runs.run import run
from harness.targets.densities import DEFAULT_TARGET

ROOT = Path(__file__).resolve().parents[1]


def test_every_config_option_composes_and_runs(tmp_path, compose, smoke, group_option):
    group, option = group_option
    key = f"+{group}" if group == "experiment" else group
    cfg = compose([f"{key}={option}", *smoke, "sim.t_final=0.06"])
    result = run(cfg, tmp_path)
    assert result.state == "completed", result.reason
    assert load_run(tmp_path).state == "completed"


def test_default_config_is_the_papers(compose):
    cfg = compose([])
    assert (cfg.agents.n, cfg.grid.n, cfg.sim.dt) == (1024, 30, 0.01)
    assert cfg.dynamics.sigma == pytest.approx(5e-5) and cfg.control.alpha == pytest.approx(0.003)
    assert cfg.kde.bandwidth == pytest.approx(0.04)
    assert (cfg.init.x0, cfg.init.x1, cfg.init.y0, cfg.init.y1) == (0.15, 0.85, 0.15, 0.85)
    assert cfg.init._target_ == "harness.targets.densities.Box"
    assert cfg.plant._target_ == "harness.plants.agents.Agents"
    assert cfg.estimator._target_ == "harness.estimators.filters.estimator.FilterEstimator"
    assert cfg.filter.engine == "local"
    assert cfg.control._target_ == "harness.control.paper.PaperControl" and cfg.sim.t_final >= 100


def test_public_keys_reach_the_components(compose):
    from harness.runs.build import build

    cfg = compose(["agents.n=77", "kde.bandwidth=0.05", "dynamics.sigma=1e-4", "grid.n=10"])
    parts = build(cfg)
    assert parts.plant.n == 77 and parts.plant.kde.bandwidth == 0.05
    assert parts.control.sigma == 1e-4 and parts.model.sigma == 1e-4
    measurement = parts.estimator.engine.measurement
    assert (measurement.n_robots, measurement.bandwidth) == (77, 0.05)


@pytest.mark.parametrize("plant", ["agents", "meanfield"])
@pytest.mark.parametrize("estimator", ["filters", "kde", "exact", "injected"])
@pytest.mark.parametrize("control", ["paper", "heat"])
def test_every_combination_runs(tmp_path, compose, smoke, plant, estimator, control):
    cfg = compose([f"plant={plant}", f"estimator={estimator}", f"control={control}", *smoke])
    result = run(cfg, tmp_path)
    assert result.state == "completed", result.reason
    assert result.steps == 10
    log = load_run(tmp_path)
    assert log.state == "completed"
    assert len(log.metrics["t"]) == 11


def topics_of(path):
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    schemas = summary.schemas
    out = {}
    for ch in summary.channels.values():
        count = summary.statistics.channel_message_counts.get(ch.id, 0)
        out[ch.topic] = (
            schemas[ch.schema_id].name,
            schemas[ch.schema_id].encoding,
            ch.message_encoding,
            count,
        )
    return out


def test_mcap_contract_agents_filters(tmp_path, compose, smoke):
    cfg = compose(smoke)
    run(cfg, tmp_path)
    topics = topics_of(tmp_path / "run.mcap")
    grid_topics = [
        "/fields/p_true",
        "/fields/p_kde",
        "/fields/p_hat",
        "/fields/grad_kde",
        "/fields/grad_hat",
        "/fields/velocity",
    ]
    # 10 steps, field_every 3: steps 0, 3, 6, 9 and the last (10)
    for topic in grid_topics:
        assert topics[topic] == ("foxglove.Grid", "protobuf", "protobuf", 5), topic
    assert topics["/fields/p_target"] == ("foxglove.Grid", "protobuf", "protobuf", 1)
    assert topics["/swarm/positions"] == ("foxglove.PointCloud", "protobuf", "protobuf", 4)
    assert topics["/metrics"] == ("densityloop.Metrics", "jsonschema", "json", 11)
    log = load_run(tmp_path)
    assert set(log.metadata) == {"config", "choices", "provenance", "theory", "status"}
    assert log.metadata["choices"]["plant"] == "agents"
    assert log.metadata["choices"]["control"] == "paper"
    assert 5 < float(log.metadata["theory"]["poincare_lambda"]) < 15
    assert "yaml" in log.metadata["config"] and "agents:" in log.metadata["config"]["yaml"]
    prov = log.metadata["provenance"]
    for key in (
        "git_commit",
        "git_dirty",
        "python",
        "seed",
        "host",
        "start_time_utc",
        "version_numpy",
    ):
        assert key in prov
    status = log.metadata["status"]
    assert (status["state"], status["reason"]) == ("completed", "")
    assert float(status["wall_s"]) > 0
    assert set(log.metrics) == set(METRIC_KEYS)
    np.testing.assert_allclose(log.metrics["t"], np.arange(11) * 0.02)
    assert np.all(log.metrics["trace_P"] > 0)
    # Grid layout and round trip: p_target decodes to the target on the grid (float32)
    tgt = log.fields["/fields/p_target"]
    assert tgt.values.shape == (1, 1, 12, 12)
    assert tgt.cell_size == pytest.approx((1 / 12, 1 / 12)) and tgt.origin == (0.0, 0.0)
    expected = DEFAULT_TARGET.on_grid(Grid.square(12)).astype(np.float32)
    np.testing.assert_array_equal(tgt.values[0, 0], expected)
    assert log.fields["/fields/velocity"].names == ("vx", "vy")
    assert log.fields["/fields/grad_hat"].values.shape == (5, 2, 12, 12)
    assert log.positions[0].shape == (200, 2)
    # metrics are plain JSON with null where not applicable
    with open(tmp_path / "run.mcap", "rb") as f:
        _, _, msg = next(iter(make_reader(f).iter_messages(topics=["/metrics"])))
    assert set(json.loads(msg.data)) == set(METRIC_KEYS)


def test_topics_absent_where_not_applicable(tmp_path, compose, smoke):
    cfg = compose(["plant=meanfield", "estimator=exact", *smoke])
    run(cfg, tmp_path)
    topics = topics_of(tmp_path / "run.mcap")
    for absent in ("/swarm/positions", "/fields/p_kde", "/fields/grad_kde"):
        assert absent not in topics
    log = load_run(tmp_path)
    assert np.all(np.isnan(log.metrics["kde_l2"])) and np.all(np.isnan(log.metrics["trace_P"]))


def test_meanfield_exact_run_converges_and_keeps_mass(tmp_path, compose):
    cfg = compose(
        [
            "plant=meanfield",
            "estimator=exact",
            "grid.n=16",
            "sim.t_final=20",
            "sim.dt=0.05",
            "log.field_every=100",
            "log.progress=off",
        ]
    )
    result = run(cfg, tmp_path)
    assert result.state == "completed"
    m = load_run(tmp_path).metrics
    assert np.all(np.diff(m["phi_l2"]) < 0)
    np.testing.assert_allclose(m["mass"], 1.0, rtol=1e-12)
    assert m["phi_l2"][-1] < 0.3 * m["phi_l2"][0]
    assert np.all(np.diff(m["lyapunov"]) <= 1e-14)


def test_figure_script_writes_its_files(tmp_path, compose, smoke):
    run(compose(smoke), tmp_path / "run")
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "analysis.figures",
            str(tmp_path / "run"),
            "--out",
            str(tmp_path / "f"),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    for name in ("fig1.png", "fig1.pdf", "fig2.png", "fig2.pdf", "run.gif"):
        assert (tmp_path / "f" / name).stat().st_size > 1000, name
    bad = subprocess.run(
        [sys.executable, "-m", "analysis.figures", str(tmp_path / "nothing")],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert bad.returncode == 2 and "no run log" in bad.stderr


def test_hydra_entry_point(tmp_path, smoke):
    out = subprocess.run(
        [sys.executable, "-m", "experiments.closed_loop", *smoke, f"hydra.run.dir={tmp_path}"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert "completed after 10 steps" in out.stdout
    assert (tmp_path / "run.mcap").is_file()


@pytest.mark.parametrize(
    "flags,expect",
    [
        (["--cfg", "job"], "agents:"),
        (["-c", "job"], "control:"),
        (["--cfg", "hydra"], "launcher:"),
        (["--info", "searchpath"], "Config search path"),
        (["--help"], "Powered by Hydra"),
        (["--config-name", "closed_loop", "--cfg", "job"], "estimator:"),
        (["-cn", "closed_loop", "-c", "job"], "plant:"),
    ],
)
def test_hydra_flags_work(tmp_path, flags, expect):
    out = subprocess.run(
        [sys.executable, "-m", "experiments.closed_loop", *flags, f"hydra.run.dir={tmp_path}/r"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert expect in out.stdout
    assert not (tmp_path / "r" / "run.mcap").exists()
