"""A real benchmark, tiny: a law and a scenario of the user's own enter it through the
search path, a killed benchmark resumes without repeating finished trials or runs, and
the leaderboard is written from the logs."""

import json
import math
from pathlib import Path

import numpy as np
import optuna
import pytest
from optuna.trial import TrialState

from analysis import leaderboard
from analysis.stats import geometric_ci, holm, paired_ratio
from harness import api
from harness.benchmark.driver import Benchmark, Settings
from harness.benchmark.plan import read_plan

MY_LAW = """\
_target_: harness.control.heat.HeatControl
alpha: 0.003
sigma: ${dynamics.sigma}
density_floor: 0.1
noise_compensation: true
debias: ${kde.debias}
bandwidth: ${kde.bandwidth}
mirror: ${kde.mirror}
v_max: null
tunable:
  alpha: {low: 1.0e-3, high: 1.0e-2, log: true}
"""

MY_SCENARIO = """\
# @package _global_
defaults:
  - override /target: two_groups
  - override /init: between
scenario:
  description: two groups, from between them
  why: a user's own scenario
"""

TIER = """\
scenarios: [mine]
laws: [my_law, langevin]
trials: 2
tuning_seeds: [0]
verdict_seeds: [5, 6]
budget_law: my_law
values:
  grid: {n: 12}
  agents: {n: 32}
  sim: {t_final: 0.2}
  log: {field_every: 1000, positions_every: 5, w2_every: 1000, floor_draws: 2}
"""


@pytest.fixture
def plugin(tmp_path):
    conf = tmp_path / "my_conf"
    (conf / "control").mkdir(parents=True)
    (conf / "scenario").mkdir()
    (conf / "control" / "my_law.yaml").write_text(MY_LAW)
    (conf / "scenario" / "mine.yaml").write_text(MY_SCENARIO)
    tier = tmp_path / "tiny.yaml"
    tier.write_text(TIER)
    return conf, tier


def _plan(conf, tier, laws=None):
    sp = [f"hydra.searchpath=[file://{conf}]"]
    return read_plan(tier, api.options("scenario", sp), api.options("control", sp))


def test_a_law_and_a_scenario_of_ones_own_are_options_of_every_tier(plugin, tmp_path):
    conf, _ = plugin
    every = tmp_path / "every.yaml"
    every.write_text(TIER.replace("[mine]", "all").replace("[my_law, langevin]", "all"))
    plan = _plan(conf, every)
    assert "my_law" in plan.laws and "paper" in plan.laws
    assert "mine" in plan.scenarios and "ring" in plan.scenarios


def test_a_killed_benchmark_resumes_without_repeating_what_finished(plugin, tmp_path, monkeypatch):
    conf, tier = plugin
    plan = _plan(conf, tier)
    out = tmp_path / "out"
    settings = Settings(out=out, searchpath=[conf])
    said: list[str] = []
    launches: list[list[str]] = []
    real_launch = Benchmark._launch

    def killed_after_the_second_round(self, sweep_dir, names, seeds):
        launches.append(list(names))
        real_launch(self, sweep_dir, names, seeds)
        if len(launches) == 2:  # its runs are done, the trial not yet told
            raise KeyboardInterrupt("killed by the test")

    monkeypatch.setattr(Benchmark, "_launch", killed_after_the_second_round)
    with pytest.raises(KeyboardInterrupt):
        Benchmark(plan, settings, echo=said.append).run()
    storage = f"sqlite:///{out / 'tuning.db'}"
    study = optuna.load_study(study_name="mine/my_law", storage=storage)
    assert [t.state for t in study.trials] == [TrialState.COMPLETE, TrialState.RUNNING]
    before = {t.number: t.params for t in study.trials}
    logs = {p: p.stat().st_mtime_ns for p in (out / "tune").glob("*/run.mcap")}
    assert len(logs) == 4  # two defaults, two trials, one seed
    monkeypatch.undo()

    Benchmark(plan, settings, echo=said.append).run()
    study = optuna.load_study(study_name="mine/my_law", storage=storage)
    assert [t.state for t in study.trials] == [TrialState.COMPLETE] * 2
    assert {t.number: t.params for t in study.trials} == before  # nothing asked again
    assert sorted(v["alpha"] for v in before.values()) == pytest.approx([1e-3, 1e-2])
    for path, mtime in logs.items():  # no finished run made again
        assert path.stat().st_mtime_ns == mtime, path
    relaunched = [p for p in logs if "t000" not in p.parent.name]  # trial 0 was told
    statuses = [json.loads((p.parent / "job_status.json").read_text()) for p in relaunched]
    assert len(statuses) == 3 and all(s["skipped"] for s in statuses)
    verdicts = sorted(p.parent.name for p in (out / "verdict").glob("*/run.mcap"))
    assert verdicts and all(n.endswith(("seed=5", "seed=6")) for n in verdicts)
    assert any("tuning: 2 of 2 trials done" in line for line in said)

    page = tmp_path / "docs" / "benchmark.md"
    assert leaderboard.main([str(out), "--page", str(page), "--command", "the test"]) == 0
    data = json.loads((page.parent / "benchmark" / "data.json").read_text())
    text = page.read_text()
    assert text == leaderboard.render(data, "benchmark/fronts.png")
    assert "`mine`" in text and "my_law" in text and "the test" in text
    (scenario,) = data["scenarios"]
    laws = {e["law"]: e for e in scenario["laws"]}
    assert laws["my_law"]["roles"]["best"]["seeds"] == [5, 6]
    assert laws["langevin"]["roles"]["default"]["completed"] == 2
    assert (page.parent / "benchmark" / "fronts.png").read_bytes().startswith(b"\x89PNG")


def test_the_leaderboard_summarises_by_the_rules_of_the_statistics():
    rng = np.random.default_rng(7)
    seeds = list(range(8))
    ref = np.exp(rng.normal(0.0, 0.3, 8))
    ratio = np.exp(rng.normal(np.log(0.5), 0.1, 8))
    mine = ref * ratio

    def rows(values, law):
        return [
            {
                "cfg:seed": s,
                "cfg:point.scenario": "s",
                "cfg:point.law": law,
                "state": "completed",
                "swarm_ratio": v,
                "effort_integral": 1e-3 * v,
                "ms_per_step": 1.0,
                "settling_time": math.inf if s == 0 else 3.0 + s,
                "t_end": 20.0,
            }
            for s, v in zip(seeds, values, strict=True)
        ]

    summary = leaderboard._summary(rows(mine, "a"))
    gm = geometric_ci(mine)
    assert summary["error"] == pytest.approx([gm.mean, gm.low, gm.high])
    assert summary["settling"][0] == pytest.approx(7.0)  # seed 0 never settled: counted
    by_role = {("s", "a", "matched"): rows(mine, "a"), ("s", "b", "matched"): rows(ref, "b")}
    laws = [{"law": "a", "roles": {"matched": {}}}, {"law": "b", "roles": {"matched": {}}}]
    leaderboard._versus(laws, by_role, "s", "b")
    expected = paired_ratio(mine, ref)
    assert laws[0]["versus"]["ratio"] == pytest.approx(expected.ratio)
    assert laws[0]["versus"]["p_holm"] == pytest.approx(holm([expected.p])[0])
    assert laws[0]["versus"]["high"] < 1  # a halving on 8 seeds is found
    assert laws[1]["versus"] is None


def test_the_committed_page_is_its_data_rendered():
    page = Path(__file__).resolve().parents[1] / "docs" / "benchmark.md"
    data = json.loads((page.parent / "benchmark" / "data.json").read_text())
    assert page.read_text() == leaderboard.render(data, "benchmark/fronts.png")
