"""The runs of a benchmark as options of config group ``point``.

Every run the benchmark makes is one point (a scenario, a law, the law's gains and the
tier's values) on one seed. Each point is written once as a YAML file
``OUT/conf/point/NAME.yaml``::

    # @package _global_
    defaults:
      - override /scenario: ring
      - override /control: paper
    control: {alpha: 0.0071}
    agents: {n: 256}
    point: {scenario: ring, law: paper, stage: tune, trial: 3, roles: []}

and swept by a Hydra multirun, ``+point=NAME,... seed=...`` with
``hydra.searchpath=[file://OUT/conf]``: the runs go through whichever Hydra launcher the
user picks (joblib, submitit, Ray), their directories are named by the point and the
seed, and a re-run of the same multirun skips every run whose log finished with the same
config and code (:mod:`harness.runs.resume`). The ``point`` block is logged with the
config (:data:`harness.runs.checks.LOGGED_BLOCKS`), so the leaderboard reads from the logs
alone what each run was for.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from harness.runs.app import job_dir_name
from harness.runs.status import write_file

GROUP = "point"
"""The config group of the benchmark's points."""

_NAME = re.compile(r"^[A-Za-z0-9_]+$")


def point_name(scenario: str, law: str, tag: str) -> str:
    """The option name of a point: ``SCENARIO--LAW--TAG`` (``ring--paper--t003``).

    Raises:
        ValueError: for a part that is not letters, digits and underscores (a point's
            name is a file name and a Hydra option).
    """
    for part in (scenario, law, tag):
        if not _NAME.match(part):
            raise ValueError(f"{part!r}: a point's parts are letters, digits and underscores")
    return f"{scenario}--{law}--{tag}"


def _yaml_value(value: Any) -> str:
    """``value`` as a YAML flow value (JSON is YAML; floats keep every digit)."""
    return json.dumps(value)


def point_yaml(
    scenario: str,
    law: str,
    gains: Mapping[str, Any],
    values: Mapping[str, Any],
    block: Mapping[str, Any],
) -> str:
    """The text of a point's config file (module docstring)."""
    lines = [
        "# @package _global_",
        "# a benchmark's run (harness/benchmark/points.py); written once, never edited",
        "defaults:",
        f"  - override /scenario: {scenario}",
        f"  - override /control: {law}",
    ]
    merged: dict[str, Any] = {k: v for k, v in values.items() if k != "control"}
    control = dict(values.get("control", {}))
    control.update(gains)
    if control:
        merged["control"] = control
    merged[GROUP] = dict(block)
    for key, value in merged.items():
        lines.append(f"{key}: {_yaml_value(value)}")
    return "\n".join(lines) + "\n"


def write_point(conf_dir: Path, name: str, text: str) -> Path:
    """Write a point's file under ``conf_dir/point/`` (atomically); a point written
    before must have the same text.

    Raises:
        RuntimeError: when a file of that name holds another point (a benchmark
            directory reused by another tier or another version of the laws' configs).
    """
    path = conf_dir / GROUP / f"{name}.yaml"
    if path.exists():
        old = path.read_text()
        if old != text:
            raise RuntimeError(
                f"{path} holds another point than this benchmark would write there "
                "(another tier or other configs used this directory: use a new one)"
            )
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    if not write_file(path, text.encode(), "a benchmark point"):
        raise OSError(f"{path}: could not be written")
    return path


def job_dir(sweep_dir: Path, name: str, seed: int) -> Path:
    """The directory of the run of point ``name`` on ``seed`` in a multirun over
    ``+point=... seed=...`` (Hydra's ``override_dirname``: the overrides sorted).
    """
    return sweep_dir / job_dir_name(f"+{GROUP}={name},seed={seed}")


def multirun_command(
    python: str,
    conf_dirs: Sequence[Path],
    sweep_dir: Path,
    names: Sequence[str],
    seeds: Sequence[int],
    launcher: Sequence[str] = (),
) -> list[str]:
    """The command that runs ``names`` x ``seeds`` as one Hydra multirun.

    Args:
        python: The interpreter.
        conf_dirs: The config directories to search: the one holding ``point/``, and
            those of the user's own laws or scenarios.
        sweep_dir: The multirun's directory.
        names: The points.
        seeds: The seeds.
        launcher: Hydra overrides choosing and setting the launcher
            (``["hydra/launcher=submitit_slurm", "hydra.launcher.partition=debug"]``).
    """
    return [
        python,
        "-m",
        "experiments.closed_loop",
        "--multirun",
        f"hydra.searchpath=[{','.join(f'file://{d.resolve()}' for d in conf_dirs)}]",
        f"hydra.sweep.dir={sweep_dir.resolve()}",
        f"+{GROUP}={','.join(names)}",
        f"seed={','.join(str(s) for s in seeds)}",
        "log.progress=off",
        *launcher,
    ]
