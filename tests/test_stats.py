import math

import numpy as np
import pytest

from analysis.stats import aggregate, mean_ci

# Student quantiles in closed form: 1 degree of freedom (Cauchy) t = tan(pi (u - 1/2));
# 2 degrees of freedom t = (2u - 1) sqrt(2 / (4 u (1 - u))).
T1_975 = math.tan(math.pi * 0.475)
T1_95 = math.tan(math.pi * 0.45)
T2_975 = 0.95 * math.sqrt(2 / (4 * 0.975 * 0.025))


def test_exact_small_case():
    # values 1, 2, 3: mean 2, s = 1
    ci = mean_ci([1.0, 2.0, 3.0])
    assert ci.n == 3 and ci.mean == pytest.approx(2.0)
    half = T2_975 / math.sqrt(3)
    assert ci.low == pytest.approx(2.0 - half, rel=1e-12)
    assert ci.high == pytest.approx(2.0 + half, rel=1e-12)


def test_two_values_and_level():
    # values 0, 2: mean 1, s = sqrt(2), 90 % level
    ci = mean_ci([0.0, 2.0], level=0.90)
    assert ci.high - ci.mean == pytest.approx(T1_95 * math.sqrt(2) / math.sqrt(2))


def test_missing_values_dropped_and_degenerate_cases():
    ci = mean_ci([1.0, None, float("nan"), "oops", 3.0])
    assert ci.n == 2 and ci.mean == pytest.approx(2.0)
    one = mean_ci([5.0])
    assert one.n == 1 and one.mean == 5.0 and math.isnan(one.low) and math.isnan(one.high)
    none = mean_ci([])
    assert none.n == 0 and math.isnan(none.mean)
    with pytest.raises(ValueError):
        mean_ci([1.0, 2.0], level=1.0)


def test_aggregate_groups_by_point_keys():
    rows = [
        {"agents.n": "1024", "seed": "0", "x": 1.0, "y": 10.0},
        {"agents.n": "4096", "seed": "0", "x": 5.0, "y": None},
        {"agents.n": "1024", "seed": "1", "x": 2.0, "y": 20.0},
        {"agents.n": "1024", "seed": "2", "x": 3.0, "y": 30.0},
        {"agents.n": "4096", "seed": "1", "x": 7.0, "y": 4.0},
    ]
    out = aggregate(rows, ["agents.n"], ["x", "y"])
    assert [r["agents.n"] for r in out] == ["1024", "4096"]
    a, b = out
    assert a["jobs"] == 3 and a["x_n"] == 3 and a["x_mean"] == pytest.approx(2.0)
    half = T2_975 / math.sqrt(3)
    assert a["x_ci_low"] == pytest.approx(2.0 - half)
    assert a["y_mean"] == pytest.approx(20.0) and a["y_ci_high"] == pytest.approx(20.0 + 10 * half)
    assert b["jobs"] == 2 and b["x_n"] == 2 and b["y_n"] == 1 and math.isnan(b["y_ci_low"])
    # s = sqrt(2)
    assert b["x_ci_high"] == pytest.approx(6.0 + T1_975 * math.sqrt(2) / math.sqrt(2))


def test_coverage_on_normal_rows():
    # 2000 points of 5 seeds each from N(3, 0.5^2): the 95 % CI must contain 3 in a
    # fraction within the binomial band 0.95 +- 4 sqrt(0.95 * 0.05 / 2000) (= +-0.0195).
    rng = np.random.default_rng(11)
    points, seeds = 2000, 5
    values = rng.normal(3.0, 0.5, size=(points, seeds))
    rows = [
        {"point": p, "seed": s, "metric": values[p, s]} for p in range(points) for s in range(seeds)
    ]
    out = aggregate(rows, ["point"], ["metric"])
    assert len(out) == points
    covered = np.mean([r["metric_ci_low"] <= 3.0 <= r["metric_ci_high"] for r in out])
    band = 4 * math.sqrt(0.95 * 0.05 / points)
    assert abs(covered - 0.95) < band
    # and a z-interval (1.96 s / sqrt(n)) would under-cover with 5 seeds: the t quantile matters
    z_cov = np.mean(
        [
            abs(r["metric_mean"] - 3.0) <= 1.96 * values[i].std(ddof=1) / math.sqrt(seeds)
            for i, r in enumerate(out)
        ]
    )
    assert z_cov < 0.95 - band
