"""The A/B mode of the benchmarks (benchmarks/ab.py) on made-up figures with known ratios."""

import math

import pytest

from benchmarks import ab
from benchmarks.report import Figure


def fig(
    name: str, value: float, unit: str, target: float | None = None, relation: str = "<="
) -> Figure:
    return Figure("b", "python -m b", name, value, unit, target, relation)


def test_costs_are_calibrated_times_and_inverse_calibrated_rates():
    assert ab.cost(fig("t", 6.0, "ms"), 2.0) == 3.0
    assert ab.cost(fig("r", 50.0, "steps/s"), 2.0) == 0.01
    assert ab.cost(fig("m", 1.0, "GB"), 2.0) is None  # memory does not scale with the host
    assert ab.cost(fig("nan", math.nan, "ms"), 2.0) is None


def test_a_change_hidden_by_a_slower_host_is_found_after_calibration():
    # A is 20 % slower per calibration; the host ran B's rounds twice as slow
    a_runs = [
        (1.0, [fig("step", 1.2 * x, "ms"), fig("rate", 100 / (1.2 * x), "steps/s")])
        for x in (1.0, 1.01, 0.99)
    ]
    b_runs = [(2.0, [fig("step", 2.0 * x, "ms"), fig("rate", 100 / (2.0 * x), "steps/s")])
              for x in (1.0, 0.99, 1.01)]  # fmt: skip
    comps = {c.name: c for c in ab.compare(a_runs, b_runs)}
    for name in ("step", "rate"):
        assert comps[name].ratio == pytest.approx(1.2, rel=0.01)
        low, high = comps[name].interval
        assert 1.0 < low < 1.2 < high
        assert comps[name].verdict == "slower"


def test_the_verdict_needs_both_the_threshold_and_the_interval():
    assert ab.Comparison("x", "ms", (0.8, 0.81, 0.79)).verdict == "faster"
    assert ab.Comparison("x", "ms", (1.01, 1.02, 1.015)).verdict == "no change detected"
    assert ab.Comparison("x", "ms", (1.5, 0.7, 1.4)).verdict == "no change detected"
    one = ab.Comparison("x", "ms", (2.0,))
    assert one.interval == (0.0, math.inf) and one.verdict == "no change detected"


def test_the_interval_is_students_t_on_the_log_ratios():
    from scipy import stats

    ratios = (1.1, 1.3, 1.2, 1.25)
    logs = [math.log(q) for q in ratios]
    mean, sem = sum(logs) / 4, stats.sem(logs)
    low, high = stats.t.interval(0.95, 3, loc=mean, scale=sem)
    got = ab.Comparison("x", "ms", ratios).interval
    assert got == pytest.approx((math.exp(low), math.exp(high)))


def test_figures_only_one_commit_reports_are_left_out():
    a_runs = [(1.0, [fig("both", 1.0, "ms"), fig("new", 1.0, "ms")])]
    b_runs = [(1.0, [fig("both", 2.0, "ms"), fig("old", 1.0, "ms")])]
    assert [c.name for c in ab.compare(a_runs, b_runs)] == ["both"]


def test_an_unknown_commit_is_one_line(monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["b", "--vs", "no-such-commit-xyz"])
    assert ab.cli(lambda argv: True, "benchmarks.robots") == 2
    assert "not a commit" in capsys.readouterr().err


def test_figures_are_paired_by_name_without_their_measured_ranges():
    a_runs = [(1.0, [fig("n = 30, rooms [286 to 416]", 300.0, "steps/s")])]
    b_runs = [(1.0, [fig("n = 30, rooms [250 to 260]", 250.0, "steps/s")])]
    (comp,) = ab.compare(a_runs, b_runs)
    assert comp.name == "n = 30, rooms" and comp.ratio == pytest.approx(250.0 / 300.0)


def test_a_ratio_of_speeds_is_compared_by_the_sense_of_its_target():
    # a ratio of two speeds measured together needs no calibration; higher is better
    # under a lower bound (rooms over square), lower is better under an upper bound
    assert ab.cost(fig("rooms over square", 0.5, "x", 0.5, ">="), 2.0) == 2.0
    assert ab.cost(fig("unicycles / agents", 1.8, "x", 1.3, "<="), 2.0) == 1.8
    assert ab.cost(fig("shown only", 1.8, "x"), 2.0) is None
    a_runs = [(1.0, [fig("rooms over square [0.4 to 0.6]", 0.55, "x", 0.5, ">=")])]
    b_runs = [(3.0, [fig("rooms over square [0.3 to 0.5]", 0.44, "x", 0.5, ">=")])]
    (comp,) = ab.compare(a_runs, b_runs)
    assert comp.ratio == pytest.approx(0.44 / 0.55)  # A faster: q < 1
