"""The examples of docs/extending.md, copied verbatim and run from outside the project."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from analysis.load import load_run

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"```(?:python|yaml)\n# file: (\S+)\n(.*?)```", re.DOTALL)


def example_files() -> dict[str, str]:
    text = (ROOT / "docs" / "extending.md").read_text()
    return {name: f"# file: {name}\n{body}" for name, body in BLOCK.findall(text)}


def test_the_page_has_one_module_and_one_yaml_per_component():
    names = sorted(example_files())
    assert names == [
        "my_components/dropout.py",
        "my_components/ewma.py",
        "my_components/ring.py",
        "my_components/saturated.py",
        "my_conf/control/saturated.yaml",
        "my_conf/estimator/ewma.yaml",
        "my_conf/plant/dropout.yaml",
        "my_conf/target/ring.yaml",
    ]


@pytest.mark.parametrize(
    "override",
    ["control=saturated", "estimator=ewma", "plant=dropout", "target=ring"],
)
def test_each_example_runs_out_of_tree(tmp_path, smoke, override):
    for name, text in example_files().items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(tmp_path / "my_components"), str(ROOT)]),
    }
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
    assert load_run(run_dir).state == "completed"


def test_an_example_parameter_is_checked_by_its_component(tmp_path):
    for name, text in example_files().items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(tmp_path / "my_components"), str(ROOT)]),
    }
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
