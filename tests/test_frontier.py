"""The frontier figure's arithmetic (:mod:`analysis.frontier`): the Pareto front against
brute force, and the message budget."""

import numpy as np

from analysis.frontier import pareto, within_budget


def test_pareto_front_is_the_brute_force_set_of_undominated_points(rng):
    for _ in range(50):
        n = int(rng.integers(1, 30))
        xs = rng.integers(0, 8, n).astype(float)  # ties on both axes
        ys = rng.integers(0, 8, n).astype(float)
        front = set(pareto(xs, ys).tolist())
        # brute force: i is on the front unless some j is no worse on both axes and
        # better on one, or equal on both with a smaller index (one of equal points)
        expected = set()
        for i in range(n):
            beaten = any(
                (xs[j] <= xs[i] and ys[j] <= ys[i] and (xs[j] < xs[i] or ys[j] < ys[i]))
                or (xs[j] == xs[i] and ys[j] == ys[i] and j < i)
                for j in range(n)
                if j != i
            )
            if not beaten:
                expected.add(i)
        assert front == expected
        order = pareto(xs, ys)
        assert np.all(np.diff(xs[order]) > 0)  # sorted by x, strictly
        assert np.all(np.diff(ys[order]) < 0)  # each point better on y than the last


def test_message_budget():
    assert within_budget({"messages": 100.0, "message_bytes": 2048.0})
    assert not within_budget({"messages": 100.5, "message_bytes": 100.0})
    assert not within_budget({"messages": 10.0, "message_bytes": 2632.0})
