import math

import numpy as np
import pytest

from analysis.stats import aggregate, geometric_ci, holm, km_median, mean_ci, paired_ratio

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


# ------------------------------------------------ positive quantities: geometric means
def test_geometric_mean_and_its_interval_on_the_logs():
    # logs 0, 1, 2: mean 1, s = 1
    ci = geometric_ci([1.0, math.e, math.e**2])
    assert ci.n == 3 and ci.mean == pytest.approx(math.e)
    half = T2_975 / math.sqrt(3)
    assert ci.low == pytest.approx(math.exp(1 - half)) and ci.high == pytest.approx(
        math.exp(1 + half)
    )
    assert 0 < ci.low < ci.mean < ci.high


def test_geometric_interval_covers_a_lognormal_median_at_its_level():
    rng = np.random.default_rng(7)
    mu, sigma, n, reps = 0.3, 0.8, 4, 4000
    hits = 0
    for _ in range(reps):
        ci = geometric_ci(np.exp(rng.normal(mu, sigma, n)))
        hits += ci.low <= math.exp(mu) <= ci.high
    # binomial standard deviation of the coverage: sqrt(0.95 * 0.05 / 4000) = 0.0034
    assert abs(hits / reps - 0.95) < 0.015


def test_a_non_positive_value_falls_back_to_the_mean():
    assert geometric_ci([0.0, 2.0, 4.0]) == mean_ci([0.0, 2.0, 4.0])
    assert geometric_ci([None, 2.0, 8.0]).mean == pytest.approx(4.0)


# ------------------------------------------------ times with censoring: Kaplan-Meier
def km_by_redistribution(times, ends):
    """Efron's redistribute-to-the-right: each censored run hands its mass in equal
    shares to every run after it; S(t) is 1 less the mass of events up to t."""
    at = [t if math.isfinite(t) else e for t, e in zip(times, ends, strict=True)]
    event = [math.isfinite(t) for t in times]
    # events before censorings at equal times (the Kaplan-Meier convention)
    order = sorted(range(len(at)), key=lambda i: (at[i], not event[i]))
    mass = {i: 1.0 / len(at) for i in order}
    for k, i in enumerate(order):
        if not event[i]:
            later = order[k + 1 :]
            for j in later:
                mass[j] += mass[i] / len(later)
            mass[i] = 0.0
    return lambda t: 1.0 - sum(mass[i] for i in order if event[i] and at[i] <= t)


def test_km_median_without_censoring_is_the_sample_median():
    km = km_median([5.0, 1.0, 3.0, 2.0, 4.0], [10.0] * 5)
    assert (km.median, km.events, km.n) == (3.0, 5, 5)


def test_km_median_counts_the_runs_that_never_reached_it():
    inf = math.inf
    # S(1) = 3/4, S(2) = 1/2: the median is 2; dropping the two censored runs would say 1.5
    assert km_median([1.0, 2.0, inf, inf], [10.0] * 4).median == 2.0
    never = km_median([1.0, inf, inf], [10.0, 10.0, 10.0])
    assert never.median == inf and never.events == 1 and never.n == 3
    assert km_median([inf, inf], [5.0, 5.0]).median == inf
    assert km_median([], []).n == 0
    with pytest.raises(ValueError):
        km_median([1.0], [1.0, 2.0])


def test_km_survival_matches_the_redistribution_to_the_right():
    rng = np.random.default_rng(3)
    for _ in range(50):
        n = int(rng.integers(3, 12))
        times = rng.exponential(1.0, n).round(1)  # ties on purpose
        ends = rng.uniform(0.5, 2.0, n).round(1)
        times = [float(t) if t <= e else math.inf for t, e in zip(times, ends, strict=True)]
        surv = km_by_redistribution(times, list(ends))
        km = km_median(times, ends)
        expected = next((t for t in sorted(set(x for x in times if math.isfinite(x)))
                         if surv(t) <= 0.5 + 1e-12), math.inf)  # fmt: skip
        assert km.median == expected


def test_km_interval_covers_an_exponential_median_at_about_its_level():
    rng = np.random.default_rng(11)
    n, reps, horizon = 25, 1000, 1.5  # exp(-1.5) = 22 % of runs censored
    hits = 0
    for _ in range(reps):
        t = rng.exponential(1.0, n)
        km = km_median(np.where(t <= horizon, t, math.inf), np.full(n, horizon))
        hits += km.low <= math.log(2) <= km.high
    assert 0.90 <= hits / reps <= 0.99


# ------------------------------------------------ paired comparisons and Holm
def test_paired_ratio_is_the_paired_t_test_on_the_log_ratios():
    from scipy import stats

    a = [1.2, 2.5, 0.9, 3.1, 1.7]
    b = [1.0, 2.0, 1.0, 2.0, 1.5]
    got = paired_ratio(a, b)
    logs = np.log(a) - np.log(b)
    assert got.n == 5 and got.ratio == pytest.approx(math.exp(logs.mean()))
    assert got.p == pytest.approx(stats.ttest_rel(np.log(a), np.log(b)).pvalue)
    low, high = stats.t.interval(0.95, 4, loc=logs.mean(), scale=stats.sem(logs))
    assert (got.low, got.high) == pytest.approx((math.exp(low), math.exp(high)))
    same = paired_ratio([2.0, 4.0, 8.0], [1.0, 2.0, 4.0])
    # equal ratios: a zero spread but for round-off
    assert (same.ratio, same.low, same.high) == pytest.approx((2.0, 2.0, 2.0)) and same.p < 1e-12
    assert paired_ratio([1.0, None, 0.0], [1.0, 2.0, 3.0]).n == 1
    with pytest.raises(ValueError):
        paired_ratio([1.0], [1.0, 2.0])


def test_holm_by_hand_and_its_family_wise_error_rate():
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm([0.5, 0.9]) == [1.0, 1.0]
    out = holm([0.01, math.nan])
    assert out[0] == 0.01 and math.isnan(out[1])
    rng = np.random.default_rng(5)
    reps, m = 4000, 6
    falsely = sum(min(holm(rng.uniform(size=m))) <= 0.05 for _ in range(reps))
    assert falsely / reps <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / reps)


def test_aggregate_uses_the_rule_of_each_metric():
    inf = math.inf
    rows = [
        {"law": "a", "err": 1.0, "rate": -1.0, "settle": 2.0, "t_end": 10.0},
        {"law": "a", "err": math.e**2, "rate": 1.0, "settle": inf, "t_end": 10.0},
        {"law": "a", "err": math.e, "rate": 0.0, "settle": inf, "t_end": 10.0},
    ]
    (a,) = aggregate(rows, ["law"], ["err", "rate", "settle"], log_scale={"err"},
                     censored={"settle": "t_end"})  # fmt: skip
    assert a["err_mean"] == pytest.approx(math.e)
    assert a["rate_mean"] == pytest.approx(0.0)
    assert a["settle_mean"] == inf and a["settle_n"] == 1 and a["jobs"] == 3
