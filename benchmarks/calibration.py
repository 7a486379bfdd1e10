"""The host's speed, measured beside every benchmark's figures.

A figure in milliseconds says as much about the machine as about the code: the same
commit runs tens of per cent apart on two hosts, or on one host on two days. Each
benchmark process therefore times a small fixed workload, the *calibration*, and every
target is judged in units of it:

    c = (t_normals * t_copy * t_walk)^(1/3)                                 (ms)

the geometric mean of three medians, each of the kind of work the harness does:

- ``t_normals``: 2 x 10^6 standard normals from ``numpy.random.Generator`` (PCG64), one
  thread (the robots' noise);
- ``t_copy``: a copy of 64 MiB between two float64 arrays (memory bandwidth);
- ``t_walk``: a compiled loop, 10^7 steps of a random walk on ``[0, 1]`` reflected
  at both walls, one thread (the robots' compiled step).

A time ``t`` is ``t / c`` calibrations; a rate ``r`` (per second) is ``r c / 1000``
per calibration. A target set as an absolute figure on the development machine, whose
calibration is :data:`REFERENCE_MS`, is the same number of calibrations on every host:
``target_here = target * (c / REFERENCE_MS)`` for a time and ``target * (REFERENCE_MS /
c)`` for a rate. Memory and dimensionless ratios are not scaled.

``python -m benchmarks.calibration [--repeat K]`` prints the calibration of this host.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import numba
import numpy as np
from threadpoolctl import threadpool_limits

REFERENCE_MS = 13.8
"""The calibration of the development machine (2 cores, quiet), in ms: the median of
``python -m benchmarks.calibration --repeat 9`` run five times. The targets in the
benchmarks are absolute figures on that machine."""

NORMALS = 2_000_000
COPY_BYTES = 64 * 2**20
WALK_STEPS = 10_000_000

_CACHED: float | None = None


@numba.njit(cache=True, nogil=True)
def reflected_walk(steps: int, seed: int) -> float:
    """A random walk of ``steps`` steps on [0, 1], reflected at both walls.

    The steps are uniform on [-0.01, 0.01), from a 64-bit linear congruential generator
    (Knuth's MMIX constants) started at ``seed``: fixed work and a deterministic result
    (the final position), whatever numba's own generator does.
    """
    state = np.uint64(seed)
    a = np.uint64(6364136223846793005)
    b = np.uint64(1442695040888963407)
    x = 0.5
    for _ in range(steps):
        state = a * state + b
        x += 0.02 * (state >> np.uint64(11)) * 2.0**-53 - 0.01
        if x < 0.0:
            x = -x
        elif x > 1.0:
            x = 2.0 - x
    return x


def _median_ms(fn: Callable[[], object], repeat: int) -> float:
    fn()  # warm-up: compilation, page faults
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def parts(repeat: int = 5) -> dict[str, float]:
    """The three timings (ms, medians over ``repeat``) the calibration is made of."""
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, got {repeat}")
    rng = np.random.default_rng(0)
    src = np.ones(COPY_BYTES // 8)
    dst = np.empty_like(src)
    with threadpool_limits(1):
        return {
            "normals": _median_ms(lambda: rng.standard_normal(NORMALS), repeat),
            "copy": _median_ms(lambda: np.copyto(dst, src), repeat),
            "walk": _median_ms(lambda: reflected_walk(WALK_STEPS, 0), repeat),
        }


def measure(repeat: int = 5) -> float:
    """The calibration ``c`` of this host now (ms): the geometric mean of :func:`parts`."""
    times = parts(repeat)
    return math.exp(sum(math.log(t) for t in times.values()) / len(times))


def host_ms() -> float:
    """The calibration of this process's host, measured once per process (ms)."""
    global _CACHED
    if _CACHED is None:
        _CACHED = measure()
    return _CACHED


def exponent(unit: str) -> int:
    """How a figure in ``unit`` scales with the host's slowness.

    Returns:
        ``1`` for a time (it grows on a slower host), ``-1`` for a rate (``.../s``), ``0``
        for what does not depend on the host's speed (memory, ratios, counts).
    """
    if unit in ("ns", "us", "µs", "ms", "s", "min"):
        return 1
    if unit.endswith("/s"):
        return -1
    return 0


def main(argv: list[str] | None = None) -> int:
    """Print the calibration of this host and its parts."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="medians over this many")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    times = parts(args.repeat)
    c = math.exp(sum(math.log(t) for t in times.values()) / len(times))
    for name, t in times.items():
        print(f"  {name:<8s} {t:8.3f} ms")
    print(f"calibration {c:.3f} ms  ({c / REFERENCE_MS:.3f} x the reference {REFERENCE_MS} ms)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
