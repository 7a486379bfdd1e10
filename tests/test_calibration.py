"""The host calibration the benchmarks judge their targets in (benchmarks/calibration.py)."""

import math

from benchmarks import calibration


def walk_reference(steps: int, seed: int) -> float:
    """The calibration's random walk in plain Python integers and floats."""
    state, x = seed, 0.5
    for _ in range(steps):
        state = (6364136223846793005 * state + 1442695040888963407) % 2**64
        x += 0.02 * (state >> 11) * 2.0**-53 - 0.01
        if x < 0.0:
            x = -x
        elif x > 1.0:
            x = 2.0 - x
    return x


def test_the_compiled_walk_is_the_plain_python_walk():
    for seed in (0, 1, 12345):
        assert calibration.reflected_walk(5000, seed) == walk_reference(5000, seed)
    assert 0.0 <= calibration.reflected_walk(100_000, 7) <= 1.0


def test_the_calibration_is_the_geometric_mean_of_its_parts(monkeypatch):
    monkeypatch.setattr(calibration, "parts", lambda repeat=5: {"a": 2.0, "b": 8.0, "c": 4.0})
    assert math.isclose(calibration.measure(), 4.0)


def test_a_real_calibration_is_a_positive_time_of_three_parts():
    times = calibration.parts(repeat=1)
    assert set(times) == {"normals", "copy", "walk"}
    assert all(math.isfinite(t) and t > 0 for t in times.values())


def test_times_scale_with_the_host_rates_against_it_the_rest_not_at_all():
    assert [calibration.exponent(u) for u in ("ms", "s", "us")] == [1, 1, 1]
    assert [calibration.exponent(u) for u in ("steps/s", "robot-steps/s")] == [-1, -1]
    assert [calibration.exponent(u) for u in ("GB", "MiB", "x", "")] == [0, 0, 0, 0]
