"""The Python API (harness/api.py): the command line's config and log, the in-memory
loop, the example notebook, and an installed (non-editable) package."""

import os
import re
import runpy
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest
import yaml
from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from harness import api
from harness.runs.checks import ConfigError

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "explore.py"
README = ROOT / "README.md"


def cli(*args: str, cwd: Path, python: str = sys.executable, env=None, timeout=300):
    """``python -m experiments.closed_loop ARGS`` from ``cwd``, this checkout's code."""
    env = env if env is not None else {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [python, "-m", "experiments.closed_loop", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_compose_is_the_config_of_the_command_line(tmp_path):
    overrides = ["+experiment=smoke", "control=heat", "grid.n=14"]
    proc = cli("--cfg", "job", *overrides, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    cfg = api.compose(overrides)
    composed = OmegaConf.to_container(cfg)
    # of Hydra's node only the choices and the overrides, which --cfg job leaves out
    hydra = composed.pop("hydra")
    assert hydra == {
        "runtime": {"choices": hydra["runtime"]["choices"]},
        "overrides": {"task": overrides},
    }
    assert hydra["runtime"]["choices"]["control"] == "heat"
    assert hydra["runtime"]["choices"]["experiment"] == "smoke"
    assert composed == yaml.safe_load(proc.stdout)


def test_compose_repeatedly_from_any_directory_and_inside_hydra(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert api.compose(["grid.n=12"]).grid.n == 12
    assert api.compose(["grid.n=13"]).grid.n == 13
    assert api.compose().control._target_ == "harness.control.paper.PaperControl"
    assert not GlobalHydra.instance().is_initialized()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "app.yaml").write_text("answer: 42\n")
    with initialize_config_dir(config_dir=str(mine), version_base="1.3"):
        assert api.compose(["control=heat"]).control._target_ == "harness.control.heat.HeatControl"
        assert hydra_compose("app").answer == 42  # the caller's Hydra is back as it was
    assert not GlobalHydra.instance().is_initialized()


def test_compose_takes_a_search_path_of_ones_own(tmp_path):
    (tmp_path / "control").mkdir()
    (tmp_path / "control" / "mine.yaml").write_text(
        "_target_: harness.control.paper.PaperControl\nalpha: 0.01\nsigma: ${dynamics.sigma}\n"
    )
    cfg = api.compose([f"hydra.searchpath=[file://{tmp_path}]", "control=mine"])
    assert cfg.control.alpha == 0.01


def test_a_single_string_is_not_taken_for_overrides():
    with pytest.raises(TypeError):
        api.run("grid.n=12", "unused")  # type: ignore[arg-type]


def test_run_writes_and_returns_the_command_lines_log(tmp_path, smoke):
    proc = cli(*smoke, f"hydra.run.dir={tmp_path / 'cli'}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    log = api.run(list(smoke), tmp_path / "api")
    assert isinstance(log, api.RunLog)
    assert log.path == tmp_path / "api" / "run.mcap"
    assert log.state == "completed"
    by_cli = api.load_run(tmp_path / "cli")
    digest = by_cli.metadata["provenance"]["config_sha256"]
    assert log.metadata["provenance"]["config_sha256"] == digest
    assert log.metrics.keys() == by_cli.metrics.keys()
    for key, values in log.metrics.items():
        np.testing.assert_array_equal(values, by_cli.metrics[key], err_msg=key)
    with pytest.raises(ConfigError):  # an existing log is never overwritten
        api.run(list(smoke), tmp_path / "api")


def test_simulate_yields_the_logged_metrics_and_writes_nothing(tmp_path, monkeypatch, smoke):
    log = api.run(list(smoke), tmp_path / "run")
    monkeypatch.chdir(tmp_path / "run")
    steps = list(api.simulate(api.compose(smoke)))
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["run.mcap"]
    assert [rec.step for rec, _ in steps] == list(range(len(log.metrics["t"])))
    for key, values in log.metrics.items():
        simulated = [np.nan if m[key] is None else m[key] for _, m in steps]
        np.testing.assert_array_equal(simulated, values, err_msg=key)


def test_simulate_copies_records_unless_told_not_to(smoke):
    kept = list(api.simulate(list(smoke), t_final=0.1))
    assert [rec.t for rec, _ in kept] == pytest.approx([0.0, 0.02, 0.04, 0.06, 0.08, 0.1])
    seen = [rec.positions.copy() for rec, _ in api.simulate(list(smoke), 0.1, copy=False)]
    for (rec, _), positions in zip(kept, seen, strict=True):
        np.testing.assert_array_equal(rec.positions, positions)
    assert not np.array_equal(seen[0], seen[-1])


def test_simulate_checks_the_config_when_called():
    with pytest.raises(ConfigError, match=r"agents\.n=0"):
        api.simulate(["agents.n=0"])


def check_example_outputs(figure: Path, final: dict[str, float], curves: dict) -> None:
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert set(final) == {"paper", "heat"}
    for law, (t, err) in curves.items():
        assert t[0] == 0.0 and t[-1] == pytest.approx(20.0)
        assert np.isfinite(err).all()
        # both laws at least halve the estimation error of the start over 20 s
        assert 0 < final[law] == err[-1] < 0.5 * err[0], law


def test_the_example_runs_from_another_directory_and_makes_its_figure_s_folder(
    tmp_path, monkeypatch
):
    figure = tmp_path / "new" / "figures" / "figure.png"
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("EXPLORE_FIGURE", str(figure))
    import matplotlib.pyplot as plt

    try:
        out = runpy.run_path(str(EXAMPLE), run_name="__main__")
    finally:
        plt.close("all")
    check_example_outputs(figure, out["final"], out["curves"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new"]


def test_the_example_stops_before_simulating_when_its_figure_has_no_folder(
    tmp_path, monkeypatch, capsys
):
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv("EXPLORE_FIGURE", str(tmp_path / "a-file" / "figure.png"))

    def no_simulation(*args, **kwargs):
        raise AssertionError("simulated before the figure's folder was checked")

    monkeypatch.setattr(api, "simulate", no_simulation)
    with pytest.raises(SystemExit) as stop:
        runpy.run_path(str(EXAMPLE), run_name="__main__")
    message = capsys.readouterr().err
    assert stop.value.code == 2
    assert message.startswith("error: EXPLORE_FIGURE=") and "a-file" in message
    assert len(message.strip().splitlines()) == 1, message


@pytest.mark.parametrize("kind", ["directory", "fifo", "no suffix"])
def test_the_example_refuses_a_figure_it_could_not_write_where_it_says(
    tmp_path, monkeypatch, capsys, kind
):
    """A directory, a FIFO or a name matplotlib would extend (``x`` -> ``x.png``): refused
    before the simulations, so the printed path is always the written one."""
    target = tmp_path / "figure"
    if kind == "directory":
        target.mkdir()
    elif kind == "fifo":
        target = tmp_path / "figure.png"
        os.mkfifo(target)
    monkeypatch.setenv("EXPLORE_FIGURE", str(target))

    def no_simulation(*args, **kwargs):
        raise AssertionError("simulated before the figure's path was checked")

    monkeypatch.setattr(api, "simulate", no_simulation)
    with pytest.raises(SystemExit) as stop:
        runpy.run_path(str(EXAMPLE), run_name="__main__")
    message = capsys.readouterr().err
    assert stop.value.code == 2
    assert message.startswith(f"error: EXPLORE_FIGURE={target}:"), message
    assert len(message.strip().splitlines()) == 1, message


def readme_example() -> str:
    """The Python block of the README's section "From Python"."""
    text = README.read_text()
    section = text[text.index("## From Python") :]
    match = re.search(r"```python\n(.*?)```", section, re.DOTALL)
    assert match, "no Python block under 'From Python' in README.md"
    return match[1]


def test_the_readme_example_runs_from_another_directory(tmp_path, monkeypatch, capsys):
    code = readme_example()
    assert len([line for line in code.splitlines() if line.strip()]) <= 10
    here, scratch = tmp_path / "here", tmp_path / "tmp"
    here.mkdir()
    scratch.mkdir()
    monkeypatch.chdir(here)
    monkeypatch.setattr("tempfile.tempdir", str(scratch))
    exec(compile(code, str(README), "exec"), {"__name__": "__main__"})
    out = capsys.readouterr().out
    errors = [float(v) for v in re.findall(r"\|\|p_hat - p_\*\|\| = (\S+) 1/length", out)]
    assert len(errors) >= 3 and 0 < errors[-1] < errors[0], out
    assert re.search(r"^completed swarm_l2 = \d", out, re.MULTILINE), out
    assert list(here.iterdir()) == []  # the run's log went where the example put it
    assert [p.name for p in scratch.glob("*/run.mcap")] == ["run.mcap"]


@pytest.mark.slow
def test_install_the_package_and_run_the_example_and_the_cli_elsewhere(tmp_path):
    """``pip install --no-deps .`` (a wheel, not editable) into a fresh virtual
    environment whose dependencies are those of the environment running the tests
    (through a ``.pth`` file, so nothing is downloaded but the build backend); then the
    example and the command line from a directory outside the repository, with
    ``PYTHONPATH`` unset: the configs are found in the installed package.
    """
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", venv], check=True)
    python = str(venv / "bin" / "python")
    site = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (Path(site) / "densityloop_test_deps.pth").write_text("\n".join(sorted(deps)) + "\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    # a copy of the project, so that the build leaves nothing in the checkout
    source = tmp_path / "source"
    shutil.copytree(
        ROOT,
        source,
        symlinks=True,
        ignore=shutil.ignore_patterns(
            ".git",
            ".venv",
            "__pycache__",
            ".*_cache",
            ".hypothesis",
            "*.egg-info",
            "build",
            "outputs",
            "multirun",
            "figures",
            "*.mcap",
        ),
    )
    install = subprocess.run(
        [sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps", source],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert install.returncode == 0, install.stderr
    shutil.rmtree(source)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    modules = (
        "import harness.api as a, experiments as e; print(a.__file__, a.CONFIG_DIR, e.__file__)"
    )
    where = subprocess.run(
        [python, "-c", modules],
        cwd=elsewhere,
        env=env,
        capture_output=True,
        text=True,
    )
    assert where.returncode == 0, where.stderr
    for line in where.stdout.split():
        assert Path(line).is_relative_to(site) and not Path(line).is_relative_to(ROOT), line
    assert (Path(site) / "harness" / "conf" / "closed_loop.yaml").is_file()
    assert not (Path(site) / "harness" / "conf").is_symlink()
    for data in ("domains/data/warehouse.png", "targets/data/letters.png"):  # package data
        assert (Path(site) / "harness" / data).is_file(), data

    shutil.copy(EXAMPLE, elsewhere / "explore.py")
    figure = elsewhere / "figure.png"
    example = subprocess.run(
        [python, "explore.py"],
        cwd=elsewhere,
        env={**env, "EXPLORE_FIGURE": str(figure)},
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert example.returncode == 0, example.stderr
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    final = dict(re.findall(r"(\w+): \|\|p_hat - p_\*\|\| = (\S+) 1/length", example.stdout))
    assert set(final) == {"paper", "heat"}, example.stdout
    assert all(0 < float(value) < 0.5 for value in final.values()), final

    run_dir = tmp_path / "run"
    proc = cli(
        "+experiment=smoke", f"hydra.run.dir={run_dir}", cwd=elsewhere, python=python, env=env
    )
    assert proc.returncode == 0, proc.stderr
    assert f"log: {run_dir / 'run.mcap'}" in proc.stdout
    log = api.load_run(run_dir)
    assert log.state == "completed"
    assert yaml.safe_load(log.metadata["config"]["yaml"])["grid"]["n"] == 12
