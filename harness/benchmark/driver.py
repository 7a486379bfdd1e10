"""A whole benchmark in order: check, tune, choose, verdicts.

``OUT`` (the benchmark's directory) holds:

* ``conf/point/*.yaml``: every point run (:mod:`harness.benchmark.points`);
* ``tune/``: the tuning runs (a Hydra multirun directory, one job per point and seed);
* ``verdict/``: the chosen points on the fresh seeds;
* ``tuning.db``: Optuna's SQLite storage of the trials;
* ``benchmark.json``: the tier, the scenario and law pairs that cannot run (with the
  one-line reason), the effort budget per scenario, each law's chosen points, the
  machine and the wall time (s) of the tuning and of the verdicts in the process that
  finished them (a resumed benchmark counts only its last process).

1. **Check.** Every scenario and law pair is composed and built (nothing run); a pair
   that cannot combine (a law that cannot follow a moving target, a plant a law cannot
   drive) is reported in one line and kept in ``benchmark.json``, not dropped silently.
2. **Tune** (:mod:`harness.benchmark.tuning`): in rounds, each round one trial of every
   study that has budget left, all of the round's runs as one multirun, then told.
   Each law's default gains run in the first round. A line per round says the trials
   done and the best ``swarm_ratio`` so far per law.
3. **Choose** each law's ``best``, ``matched`` and ``default`` points.
4. **Verdicts**: the chosen points, each once, on the tier's fresh seeds, as one
   multirun.

Every step skips what a killed benchmark finished: the multiruns skip finished runs and
the tuning resumes from the storage.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from harness.benchmark.plan import Plan
from harness.benchmark.points import (
    job_dir,
    multirun_command,
    point_name,
    point_yaml,
    write_point,
)
from harness.benchmark.space import Gain, TunableError, gains
from harness.benchmark.tuning import (
    DEFAULT,
    Candidate,
    Outcome,
    ask,
    candidates,
    choose,
    done,
    open_study,
    summarise,
    tell,
    trial_budget,
)
from harness.runs.status import read_status, write_file


class LaunchError(RuntimeError):
    """A multirun that started none of its runs (a launcher that cannot start)."""


Pair = tuple[str, str]
"""A scenario and a law."""


def flat_overrides(values: Mapping[str, Any], prefix: str = "") -> list[str]:
    """Nested config values as Hydra overrides (``{"agents": {"n": 256}}`` gives
    ``["agents.n=256"]``), values in JSON (which Hydra's override grammar reads).
    """
    out = []
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.extend(flat_overrides(value, name + "."))
        else:
            out.append(f"{name}={json.dumps(value)}")
    return out


@dataclass
class Settings:
    """Where and how a benchmark runs.

    Attributes:
        out: The benchmark's directory.
        launcher: Hydra overrides choosing the launcher and its settings.
        searchpath: Config directories of the user's own laws or scenarios (each added
            with ``hydra.searchpath``).
        python: The interpreter the multiruns start.
    """

    out: Path
    launcher: list[str] = field(default_factory=list)
    searchpath: list[Path] = field(default_factory=list)
    python: str = sys.executable


class Benchmark:
    """A benchmark tier run into a directory (module docstring)."""

    def __init__(self, plan: Plan, settings: Settings, echo: Callable[[str], None] = print):
        self.plan, self.settings, self.echo = plan, settings, echo
        out = settings.out
        self.conf_dir, self.tune_dir, self.verdict_dir = out / "conf", out / "tune", out / "verdict"
        self.storage = f"sqlite:///{(out / 'tuning.db').resolve()}"
        self.refused: dict[Pair, str] = {}
        self.gains: dict[Pair, list[Gain]] = {}
        self.defaults: dict[Pair, Outcome] = {}
        self.chosen: dict[Pair, dict[str, Candidate]] = {}
        self.started = time.monotonic()
        self.stage_s: dict[str, float] = {}  # wall time of each stage in this process (s)

    # -- helpers -----------------------------------------------------------------------

    def _searchpath(self) -> list[str]:
        dirs = [f"file://{p.resolve()}" for p in self.settings.searchpath]
        return [f"hydra.searchpath=[{','.join(dirs)}]"] if dirs else []

    def _say(self, text: str) -> None:
        self.echo(f"[{time.monotonic() - self.started:7.0f} s] {text}")

    def _write_point(self, pair: Pair, tag: str, gains_: Mapping[str, Any], block: dict) -> str:
        scenario, law = pair
        name = point_name(scenario, law, tag)
        text = point_yaml(scenario, law, gains_, self.plan.values, block)
        write_point(self.conf_dir, name, text)
        return name

    def _launch(self, sweep_dir: Path, names: Sequence[str], seeds: Sequence[int]) -> None:
        """One multirun over ``names`` x ``seeds``; Ctrl-C reaches the jobs too (same
        process group): wait for them to close their logs, then stop.
        """
        dirs = [self.conf_dir, *self.settings.searchpath]
        cmd = multirun_command(
            self.settings.python, dirs, sweep_dir, names, seeds, self.settings.launcher
        )
        proc = subprocess.Popen(cmd)
        try:
            code = proc.wait()
        except KeyboardInterrupt:
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
            raise
        if code in (130, -signal.SIGINT, -signal.SIGTERM):
            raise KeyboardInterrupt(f"the multirun in {sweep_dir} was interrupted")
        started = any(job_dir(sweep_dir, n, s).is_dir() for n in names for s in seeds)
        if code != 0 and not started:
            raise LaunchError(
                f"the multirun into {sweep_dir} exited with status {code} before any run "
                "started (its output above says why; a launcher override?)"
            )

    def _outcome(self, sweep_dir: Path, name: str, seeds: Sequence[int]) -> Outcome:
        from analysis.rows import LOG_FILE, job_row

        rows: dict[int, Mapping[str, Any]] = {}
        for seed in seeds:
            jd = job_dir(sweep_dir, name, seed)
            status = read_status(jd)
            if (jd / LOG_FILE).exists():
                row, _, _ = job_row(jd)
                if row.get("state") != "completed" and status.get("reason"):
                    row["reason"] = status["reason"]
                rows[seed] = row
            else:
                rows[seed] = {
                    "state": status.get("state", "missing"),
                    "reason": status.get("reason", f"no log in {jd}"),
                }
        return summarise(rows)

    # -- steps ---------------------------------------------------------------------------

    def check(self) -> list[Pair]:
        """The pairs that can run; the others kept in ``refused`` (step 1)."""
        from hydra.errors import HydraException
        from omegaconf.errors import OmegaConfBaseException

        from harness.api import compose
        from harness.runs.build import build
        from harness.runs.checks import ConfigError

        pairs = []
        for scenario in self.plan.scenarios:
            for law in self.plan.laws:
                pair = (scenario, law)
                overrides = [
                    *self._searchpath(),
                    f"scenario={scenario}",
                    f"control={law}",
                    *flat_overrides(self.plan.values),
                ]
                try:
                    cfg = compose(overrides)
                    node = OmegaConf.to_container(cfg.control, resolve=True)
                    assert isinstance(node, dict)
                    self.gains[pair] = gains({str(k): v for k, v in node.items()}, "control")
                    build(cfg)
                except (ConfigError, TunableError, HydraException, OmegaConfBaseException) as err:
                    self.refused[pair] = (str(err).strip().splitlines() or [type(err).__name__])[0]
                    self._say(f"cannot run {scenario} / {law}: {self.refused[pair]}")
                    continue
                pairs.append(pair)
        self._say(f"{len(pairs)} scenario and law pairs to run, {len(self.refused)} cannot run")
        return pairs

    def tune(self, pairs: Sequence[Pair]) -> None:
        """Step 2 (module docstring)."""
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        self.tune_dir.mkdir(parents=True, exist_ok=True)
        studies = {
            p: open_study(self.storage, *p, self.gains[p], self.plan)
            for p in pairs
            if self.gains[p]
        }
        budget = {p: trial_budget(self.gains[p], self.plan.trials) for p in studies}
        total = sum(budget.values())
        seeds = self.plan.tuning_seeds
        first, round_ = True, 0
        while True:
            batch: list[tuple[Pair, Any, str]] = []
            if first:
                for p in pairs:
                    block = {"scenario": p[0], "law": p[1], "stage": "tune", "trial": DEFAULT}
                    batch.append((p, None, self._write_point(p, DEFAULT, {}, block)))
            for p, study in studies.items():
                if done(study) >= budget[p]:
                    continue
                trial, params, _ = ask(study, self.gains[p])
                tag = f"t{trial.number:03d}"
                block = {"scenario": p[0], "law": p[1], "stage": "tune", "trial": tag}
                batch.append((p, trial, self._write_point(p, tag, params, block)))
            if not batch:
                break
            round_ += 1
            self._say(f"tuning round {round_}: {len(batch)} points x {len(seeds)} seeds")
            self._launch(self.tune_dir, [name for _, _, name in batch], seeds)
            for p, trial, name in batch:
                outcome = self._outcome(self.tune_dir, name, seeds)
                if trial is None:
                    self.defaults[p] = outcome
                else:
                    tell(studies[p], trial, outcome)
            first = False
            told = sum(done(s) for s in studies.values())
            self._say(f"tuning: {told} of {total} trials done; {self._leaders(studies)}")

    def _leaders(self, studies: Mapping[Pair, Any]) -> str:
        """The best ``swarm_ratio`` so far per scenario and law, in one line."""
        parts = []
        for scenario in self.plan.scenarios:
            best = []
            for law in self.plan.laws:
                pair = (scenario, law)
                if pair in self.refused:
                    continue
                pool = (
                    candidates(studies[pair], self.defaults.get(pair))
                    if pair in studies
                    else (candidates_default(self.defaults.get(pair)))
                )
                if pool:
                    best.append(f"{law} {min(c.error for c in pool):.3g}")
            parts.append(f"{scenario}: " + ", ".join(best))
        return "best swarm_l2 / floor so far: " + "; ".join(parts)

    def choose_points(self, pairs: Sequence[Pair]) -> dict[str, float]:
        """Step 3: every law's chosen points; returns the effort budget per scenario
        (length^2 / s).
        """
        import optuna

        budgets: dict[str, float] = {}
        for scenario in self.plan.scenarios:
            base = self.defaults.get((scenario, self.plan.budget_law))
            if base is not None and base.values is not None:
                budgets[scenario] = base.values[1]
        for p in pairs:
            if self.gains[p]:
                study = optuna.load_study(study_name=f"{p[0]}/{p[1]}", storage=self.storage)
                pool = candidates(study, self.defaults.get(p))
            else:
                pool = candidates_default(self.defaults.get(p))
            self.chosen[p] = choose(pool, budgets.get(p[0]))
            if not self.chosen[p]:
                self._say(f"{p[0]} / {p[1]}: no point completed; no verdict")
        return budgets

    def verdicts(self, pairs: Sequence[Pair]) -> None:
        """Step 4: the chosen points on the fresh seeds."""
        names = []
        for p in pairs:
            by_tag: dict[str, list[str]] = {}
            picked: dict[str, Candidate] = {}
            for role, c in self.chosen.get(p, {}).items():
                by_tag.setdefault(c.tag, []).append(role)
                picked[c.tag] = c
            for tag, roles in sorted(by_tag.items()):
                block = {
                    "scenario": p[0],
                    "law": p[1],
                    "stage": "verdict",
                    "trial": tag,
                    "roles": sorted(roles),
                }
                names.append(self._write_point(p, f"v_{tag}", picked[tag].gains, block))
        if not names:
            return
        self.verdict_dir.mkdir(parents=True, exist_ok=True)
        self._say(f"verdicts: {len(names)} points x {len(self.plan.verdict_seeds)} fresh seeds")
        self._launch(self.verdict_dir, names, self.plan.verdict_seeds)

    def record(self, budgets: Mapping[str, float]) -> Path:
        """Write ``benchmark.json`` (module docstring)."""
        path = self.settings.out / "benchmark.json"
        data = {
            "tier": asdict(self.plan),
            "refused": [
                {"scenario": s, "law": law, "reason": why}
                for (s, law), why in sorted(self.refused.items())
            ],
            "budgets": dict(budgets),
            "machine": machine(),
            "stage_s": dict(self.stage_s),
            "chosen": [
                {"scenario": s, "law": law, "role": role, **asdict(c)}
                for (s, law), roles in sorted(self.chosen.items())
                for role, c in sorted(roles.items())
            ],
        }
        text = json.dumps(data, indent=1, sort_keys=True, default=_jsonable) + "\n"
        if not write_file(path, text.encode(), "the benchmark's record"):
            raise OSError(f"{path}: could not be written")
        return path

    def run(self) -> Path:
        """The whole benchmark; returns the path of ``benchmark.json``."""
        self.settings.out.mkdir(parents=True, exist_ok=True)
        pairs = self.check()
        self.tune(pairs)
        self.stage_s["tuning"] = time.monotonic() - self.started
        budgets = self.choose_points(pairs)
        path = self.record(budgets)
        self.verdicts(pairs)
        self.stage_s["verdicts"] = time.monotonic() - self.started - self.stage_s["tuning"]
        path = self.record(budgets)
        self._say(f"done: {path}")
        return path


def machine() -> dict[str, Any]:
    """The machine the benchmark ran on: its CPU model, logical cores and system."""
    import platform

    from harness.runs.identity import cpu_model

    return {"cpu": cpu_model(), "cores": os.cpu_count(), "system": platform.platform()}


def candidates_default(default: Outcome | None) -> list[Candidate]:
    """A law without gains: its default gains as its only candidate."""
    if default is None or default.values is None:
        return []
    return [Candidate(DEFAULT, {}, *default.values)]


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return str(value)
