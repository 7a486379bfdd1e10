"""The benchmark's parts without runs: tunable declarations, tiers, fronts and choices,
points, scenarios."""

import itertools
import math

import numpy as np
import pytest
from omegaconf import OmegaConf

from harness import api
from harness.benchmark.plan import PlanError, read_plan
from harness.benchmark.points import job_dir, point_name, point_yaml
from harness.benchmark.space import Gain, TunableError, gains
from harness.benchmark.tuning import (
    Candidate,
    choose,
    front,
    grid_values,
    summarise,
    trial_budget,
)
from harness.runs.build import build

LAWS = api.options("control")
SCENARIOS = api.options("scenario")


# -- tunable gains ---------------------------------------------------------------------


@pytest.mark.parametrize("law", LAWS)
def test_every_law_declares_its_gains_within_what_it_accepts(law):
    cfg = api.compose([f"control={law}", "agents.n=64"])
    node = OmegaConf.to_container(cfg.control, resolve=True)
    declared = gains(node)
    for g in declared:
        values = g.grid(3) if g.values is None else list(g.values)
        for v in (values[0], values[-1]):  # each end of the range builds
            build(api.compose([f"control={law}", "agents.n=64", f"control.{g.name}={v}"]))


@pytest.mark.parametrize(
    ("tunable", "words"),
    [
        (None, "missing"),
        ({"nope": {"low": 1, "high": 2}}, "not a parameter"),
        ({"alpha": {"low": 2.0, "high": 1.0}}, "low < high"),
        ({"alpha": {"low": 0.0, "high": 1.0, "log": True}}, "> 0 on a log scale"),
        ({"alpha": {"low": "a", "high": 1.0}}, "a finite number"),
        ({"alpha": {"values": []}}, "non-empty list"),
        ({"alpha": 3}, "{low, high, log} or {values}"),
    ],
)
def test_a_bad_declaration_names_its_key(tunable, words):
    node = {"_target_": "x", "alpha": 0.003}
    if tunable is not None:
        node["tunable"] = tunable
    with pytest.raises(TunableError, match=r"control\.tunable") as err:
        gains(node)
    assert words in str(err.value)


def test_the_gains_never_reach_the_law():
    # the law would refuse an unknown parameter: the run builds, so `tunable` was dropped
    cfg = api.compose(["control=paper", "agents.n=64"])
    assert "tunable" in cfg.control
    exp = build(cfg)
    assert not hasattr(exp.control, "tunable")


def test_grids_are_geometric_on_a_log_scale_and_keep_the_ends_of_a_list():
    g = Gain("alpha", 1e-4, 1e-2, log=True)
    assert np.allclose(grid_values(g, 3), [1e-4, 1e-3, 1e-2])
    assert np.allclose(Gain("a", 0.0, 1.0).grid(3), [0.0, 0.5, 1.0])
    listed = Gain("period", values=(0.2, 0.5, 1.0, 2.0, 5.0))
    assert grid_values(listed, 3) == [0.2, 1.0, 5.0]
    assert grid_values(listed, 9) == [0.2, 0.5, 1.0, 2.0, 5.0]
    assert trial_budget([listed], 3) == 3
    assert trial_budget([], 7) == 0
    assert trial_budget([g, listed], 7) == 7


# -- fronts and the chosen points --------------------------------------------------------


def test_the_front_is_what_no_point_beats_by_brute_force():
    rng = np.random.default_rng(4)
    for _ in range(20):
        pts = [Candidate(f"t{i}", {}, *rng.integers(1, 6, size=2).astype(float)) for i in range(12)]
        found = {c.tag for c in front(pts)}
        for c in pts:
            beaten = any(
                o.error <= c.error
                and o.effort <= c.effort
                and (o.error, o.effort) != (c.error, c.effort)
                for o in pts
            )
            assert (c.tag in found) == (not beaten)


def test_the_chosen_points():
    pts = [
        Candidate("default", {}, 2.0, 1.0),
        Candidate("t000", {"a": 1}, 1.0, 5.0),  # best
        Candidate("t001", {"a": 2}, 1.5, 0.9),  # best within a budget of 1
        Candidate("t002", {"a": 3}, 3.0, 0.1),
    ]
    out = choose(pts, budget=1.0)
    assert out["best"].tag == "t000"
    assert out["matched"].tag == "t001"
    assert out["default"].tag == "default"
    assert "matched" not in choose(pts, budget=0.01)  # nothing spends that little
    assert "matched" not in choose(pts, budget=None)


def test_a_point_fails_when_any_seed_fails_and_averages_geometrically():
    ok = {"state": "completed", "swarm_ratio": 2.0, "effort_integral": 1e-3}
    ok2 = {"state": "completed", "swarm_ratio": 8.0, "effort_integral": 1e-1}
    out = summarise({0: ok, 1: ok2})
    assert out.values is not None
    assert math.isclose(out.values[0], 4.0) and math.isclose(out.values[1], 1e-2)
    failed = summarise({0: ok, 1: {"state": "diverged", "reason": "blew up"}})
    assert failed.values is None and "seed 1" in failed.reason and "blew up" in failed.reason
    zero = summarise({0: {**ok, "effort_integral": 0.0}})
    assert zero.values is None and "effort_integral" in zero.reason


# -- tiers -------------------------------------------------------------------------------


def _tier(tmp_path, **over):
    base = {
        "scenarios": ["paper"],
        "laws": ["paper", "heat"],
        "trials": 2,
        "tuning_seeds": [0],
        "verdict_seeds": [5, 6],
        "budget_law": "paper",
    }
    base.update(over)
    path = tmp_path / "t.yaml"
    path.write_text(OmegaConf.to_yaml(OmegaConf.create(base)))
    return path


def test_the_shipped_tiers_read():
    for tier in ("quick", "full"):
        plan = read_plan(tier, SCENARIOS, LAWS)
        assert not set(plan.tuning_seeds) & set(plan.verdict_seeds)
        assert len(plan.verdict_seeds) >= 8
    assert read_plan("full", SCENARIOS, LAWS).scenarios == tuple(SCENARIOS)


@pytest.mark.parametrize(
    ("over", "words"),
    [
        ({"verdict_seeds": [0, 1]}, "fresh seeds"),
        ({"laws": ["nope"]}, "not among the options"),
        ({"trials": 0}, "trials"),
        ({"budget_law": "svgd"}, "budget_law"),
        ({"tuning_seeds": [0, 0]}, "each seed once"),
        ({"extra": 1}, "not keys of a tier"),
        ({"values": [1]}, "values"),
    ],
)
def test_a_bad_tier_is_one_line_naming_the_key(tmp_path, over, words):
    with pytest.raises(PlanError) as err:
        read_plan(_tier(tmp_path, **over), SCENARIOS, LAWS)
    assert words in str(err.value) and "\n" not in str(err.value)


def test_an_unknown_tier_name_lists_the_shipped_ones():
    with pytest.raises(PlanError, match="quick"):
        read_plan("nope", SCENARIOS, LAWS)


# -- points and scenarios ----------------------------------------------------------------


def test_a_point_composes_to_its_scenario_law_gains_and_values(tmp_path):
    name = point_name("ring", "heat", "t003")
    text = point_yaml(
        "ring", "heat", {"alpha": 0.0071}, {"agents": {"n": 64}}, {"stage": "tune", "trial": "t003"}
    )
    (tmp_path / "point").mkdir()
    (tmp_path / "point" / f"{name}.yaml").write_text(text)
    cfg = api.compose([f"hydra.searchpath=[file://{tmp_path}]", f"+point={name}"])
    assert cfg.hydra.runtime.choices.scenario == "ring"
    assert cfg.hydra.runtime.choices.control == "heat"
    assert cfg.control.alpha == 0.0071 and cfg.agents.n == 64
    assert cfg.point.trial == "t003"
    assert job_dir(tmp_path, name, 3).name == f"+point={name},seed=3"
    with pytest.raises(ValueError, match="letters"):
        point_name("a b", "heat", "t0")


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_every_scenario_builds_and_says_what_it_is_for(scenario):
    cfg = api.compose([f"scenario={scenario}", "agents.n=64"])
    assert cfg.scenario.description and cfg.scenario.why
    build(cfg)


def test_a_command_line_override_beats_the_scenario():
    cfg = api.compose(["scenario=large", "agents.n=128", "domain=rooms"])
    assert cfg.agents.n == 128 and cfg.hydra.runtime.choices.domain == "rooms"
    assert api.compose([]).hydra.runtime.choices.get("scenario") is None


def test_every_pair_of_scenario_and_law_either_builds_or_is_refused_in_one_line():
    from harness.runs.checks import ConfigError

    refused = []
    for scenario, law in itertools.product(SCENARIOS, LAWS):
        if scenario == "large":
            continue  # as paper at another N
        try:
            build(api.compose([f"scenario={scenario}", f"control={law}", "agents.n=64"]))
        except ConfigError as err:
            assert "\n" not in str(err)
            refused.append((scenario, law, str(err)))
    # the only refusals: a law that cannot follow a moving target, or run among obstacles
    for scenario, law, line in refused:
        if scenario != "moving":
            assert f"control={law} runs on (no obstacles)" in line, (scenario, law, line)


def test_the_method_page_lists_every_scenario_and_shipped_tier():
    from pathlib import Path

    page = (Path(__file__).resolve().parents[1] / "docs" / "benchmark-method.md").read_text()
    for scenario in SCENARIOS:
        assert f"| `{scenario}` |" in page, scenario
    for tier in ("quick", "full"):
        assert f"`{tier}`" in page
