"""The examples of docs/extending.md, copied verbatim and run from outside the project."""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from analysis.load import load_run

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"```(?:python|yaml)\n# file: (\S+)\n(.*?)```", re.DOTALL)


def example_files() -> dict[str, str]:
    text = (ROOT / "docs" / "extending.md").read_text()
    return {name: f"# file: {name}\n{body}" for name, body in BLOCK.findall(text)}


def example_env(tmp_path):
    """The environment of a run: the examples' modules, and this checkout's code (not
    another copy of the project that may be installed)."""
    path = os.pathsep.join([str(tmp_path / "my_components"), str(ROOT)])
    return {**os.environ, "PYTHONPATH": path}


def test_the_page_has_one_module_and_one_yaml_per_component():
    names = sorted(example_files())
    assert names == [
        "my_components/capped.py",
        "my_components/csv_metrics.py",
        "my_components/dropout.py",
        "my_components/ewma.py",
        "my_components/halo.py",
        "my_components/saturated.py",
        "my_conf/control/capped.yaml",
        "my_conf/control/saturated.yaml",
        "my_conf/estimator/ewma.yaml",
        "my_conf/observers/csv.yaml",
        "my_conf/plant/dropout.yaml",
        "my_conf/target/halo.yaml",
    ]


@pytest.mark.parametrize(
    "override",
    [
        "control=saturated",
        "control=capped",
        "estimator=ewma",
        "plant=dropout",
        "target=halo",
        "observers=[default,csv]",
    ],
)
def test_each_example_runs_out_of_tree(tmp_path, smoke, override):
    for name, text in example_files().items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    env = example_env(tmp_path)
    run_dir = tmp_path / "run"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "experiments.closed_loop",
            f"hydra.searchpath=[file://{tmp_path / 'my_conf'}]",
            override,
            *smoke,
            f"hydra.run.dir={run_dir}",
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    log = load_run(run_dir)
    assert log.state == "completed"
    if override.startswith("observers"):
        rows = (run_dir / "metrics.csv").read_text().splitlines()
        assert rows[0] == "t,phat_target_l2,swarm_l2"
        steps = len(log.metrics["t"]) - 1
        assert len(rows) == 1 + steps // 10 + 1  # every 10 steps from t = 0
        t, err, _ = rows[-1].split(",")
        i = int(np.argmin(np.abs(log.metrics["t"] - float(t))))
        assert float(err) == pytest.approx(log.metrics["phat_target_l2"][i], rel=1e-12)


def test_an_example_parameter_is_checked_by_its_component(tmp_path):
    for name, text in example_files().items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    env = example_env(tmp_path)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "experiments.closed_loop",
            f"hydra.searchpath=[file://{tmp_path / 'my_conf'}]",
            "control=saturated",
            "control.v_max=-1",
            f"hydra.run.dir={tmp_path / 'run'}",
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == "invalid config: control.v_max=-1: a finite number > 0"


def test_a_new_law_is_two_files(tmp_path):
    """The page's law from a temporary directory on Hydra's search path: a two-law sweep
    with it, and the analysis' law table and the benchmark's list of laws name it by its
    option, with no edit to this project."""
    for name, text in example_files().items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    env = example_env(tmp_path)
    searchpath = f"hydra.searchpath=[file://{tmp_path / 'my_conf'}]"
    sweep = tmp_path / "sweep"

    def python(*args):
        proc = subprocess.run(
            [sys.executable, "-m", *args],
            capture_output=True,
            text=True,
            cwd=tmp_path,
            env=env,
            timeout=600,
        )
        assert proc.returncode == 0, proc.stderr
        return proc

    python(
        "experiments.closed_loop", "-m", searchpath, "+experiment=smoke",
        "control=paper,saturated", "+analysis.figure=laws_n",
        "+analysis.primary=[law,agents.n]", "log.progress=off", f"hydra.sweep.dir={sweep}",
        "hydra/launcher=basic",  # in one process: no workers to start
    )  # fmt: skip
    out = tmp_path / "analysis"
    analysed = python("analysis.sweep", str(sweep), "--out", str(out))
    assert "warning" not in analysed.stderr  # every log names its law
    table = (out / "laws_table.md").read_text()
    assert [line.split("|")[1].strip() for line in table.splitlines()[2:]] == [
        "paper",
        "saturated",
    ]
    assert "| saturated |" in analysed.stdout
    with_mine = python("benchmarks.laws", "--list", searchpath).stdout.split()
    assert "saturated" in with_mine and "paper" in with_mine
    assert with_mine == sorted(with_mine)
    assert "saturated" not in python("benchmarks.laws", "--list").stdout.split()
