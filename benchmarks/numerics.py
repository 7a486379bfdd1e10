"""Numerics benchmarks of the fine grids: each figure against its target.

    python -m benchmarks.numerics [--quick]

Medians of wall-clock times (ms per call) or rates over a run (steps per second), BLAS
pinned to one thread (threadpoolctl) as in the run loop; numba uses its default
thread count (all cores). Run with nothing else on the machine: on a busy machine
the parallel compiled loops wait for descheduled threads and every figure is pessimistic.

Figures (each against its target):

* Fokker-Planck step (``FokkerPlanck.step`` with matrix assembly), mid-run paper
  settings (sigma = 5e-5, dt = 0.01, the paper's law with alpha = 0.003 evaluated
  halfway between a KDE of the initial box and p_*): n = 128 <= 5 ms, n = 256 <=
  20 ms; the sparse-LU reference step for comparison;
* KDE (binned, n = 30, h = 0.04) + agent step: N = 1e6 <= 20 ms; N = 1e7 <= 250 ms
  with peak resident memory <= 1.5 GB (measured in child processes, ``ru_maxrss``,
  which includes the interpreter and numba, about 0.2 GB); the median of three child
  processes, with the range;
* closed loop with both fast filters, N = 1024, dt = 0.01 (robots, KDE, filters,
  paper's law, Fokker-Planck truth): n = 30 >= 1000 steps/s, n = 64 >= 200,
  n = 128 >= 100, n = 256 >= 25; inverse median step time, median of three runs with
  their range;
* the same loop on the rooms (``domain=rooms init=left_room``: the KDE and the
  filters on free space) against the square, n = 30, N = 1024: the rooms' steps per
  second at least half the square's. The two loops run in turn in one process (square,
  rooms, rooms, square, ...), so that a host that slows down during the benchmark slows
  both alike; the figure is the median over rounds of each round's ratio, with the
  range.
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import time
from functools import partial

import numpy as np
from threadpoolctl import threadpool_limits

from benchmarks.ab import cli
from benchmarks.report import record
from benchmarks.suite import closed_loop_rate, median_ms
from harness.control.paper import paper_law
from harness.estimators.kde import KDE
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.plants.agents import Swarm
from harness.targets.densities import DEFAULT_TARGET, Box, Target
from harness.velocity import VelocityField


def line(name: str, value: float, unit: str, target: float | None, lower_is_better: bool) -> bool:
    """Report one figure against its target (:func:`benchmarks.report.record`); whether
    it is met."""
    return record(name, value, unit, target, "<=" if lower_is_better else ">=")


def mid_run(g: Grid) -> tuple[np.ndarray, VelocityField]:
    """Density halfway between a KDE of the initial box and ``p_*`` and the paper's
    velocity for it (alpha = 0.003, sigma = 5e-5)."""
    target = Target.from_density(g, DEFAULT_TARGET)
    y, _ = KDE(g, 0.04)(Box().sample(1024, g, np.random.default_rng(0)))
    p = 0.5 * (y + target.p)
    return p, paper_law(p, g.gradient(p), target, 0.003, 5e-5)


def bench_fokker_planck(quick: bool) -> bool:
    """Fokker-Planck step at n = 128 and 256."""
    print("Fokker-Planck step, mid-run paper settings (ms per step, assembly included):")
    ok = True
    for n, target_ms in ((30, None), (64, None), (128, 5.0), (256, 20.0)):
        g = Grid.square(n)
        p, v = mid_run(g)
        op = FokkerPlanck(g, 5e-5)
        repeats = 10 if quick else 40
        t_step = median_ms(partial(op.step, p, v, 0.01), repeats)
        ok &= line(f"n = {n}: step", t_step, "ms", target_ms, True)
        if n >= 128:
            t_lu = median_ms(partial(op.step_lu, p, v, 0.01), 3)
            line(f"n = {n}: sparse-LU reference step", t_lu, "ms", None, True)
    return ok


def kde_agents_child(n_robots: int, repeats: int) -> None:
    """In a child process: print the median ms of one agent step plus one KDE."""
    g = Grid.square(30)
    rng = np.random.default_rng(0)
    _, v = mid_run(g)
    swarm = Swarm(g, Box().sample(n_robots, g, rng), 5e-5)
    kde = KDE(g, 0.04)

    def both() -> None:
        swarm.step(v, 0.01, rng)
        kde(swarm.positions)

    with threadpool_limits(1):
        print(median_ms(both, repeats, warmup=1))


def bench_kde_agents(quick: bool, runs: int = 3) -> bool:
    """KDE + agent step at N = 1e6 and 1e7: the median over ``runs`` child processes of
    each one's median step time, with the range (as the closed-loop rates: the host's
    speed moves between runs), and the peak memory of the children."""
    print(
        f"KDE (binned, n = 30) + agent step (ms per step: median of {runs} processes, "
        "range in brackets; peak RSS of the processes):"
    )
    ok = True
    for n_robots, target_ms, target_gb in ((10**6, 20.0, None), (10**7, 250.0, 1.5)):
        repeats = 5 if quick else 15
        times = []
        for _ in range(runs):
            out = subprocess.run(
                [sys.executable, "-m", "benchmarks.numerics", "--child", str(n_robots),
                 str(repeats)],
                capture_output=True,
                text=True,
                check=True,
            )  # fmt: skip
            times.append(float(out.stdout.strip().splitlines()[-1]))
        peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 2**20  # kB -> GB
        ms = float(np.median(times))
        name = f"N = {n_robots:>10,d} [{min(times):.1f} to {max(times):.1f}]: KDE + agent step"
        ok &= line(name, ms, "ms", target_ms, True)
        if target_gb is not None:  # children so far: this one is the largest
            ok &= line(f"N = {n_robots:>10,d}: peak memory", peak_gb, "GB", target_gb, True)
    return ok


def bench_closed_loop(quick: bool, repeats: int = 3) -> bool:
    """Closed-loop rates at n = 30 .. 256: the loop the app builds from its config
    (:func:`benchmarks.suite.closed_loop_rate`: robots with the loop's N -> infinity limit,
    KDE, both fast filters, the paper's law; the inverse median step time). Each rate is
    measured ``repeats`` times (fresh loops, in turn over the grids) and the median is
    set against the target, with the range: on a shared host the same benchmark moves by
    tens of per cent between runs minutes apart.
    """
    print(
        f"Closed loop, both fast filters, N = 1024, dt = 0.01 (steps per second = 1 / median "
        f"step time; median of {repeats} runs, range in brackets):"
    )
    cases = ((30, 1000, 1000), (64, 200, 400), (128, 100, 200), (256, 25, 60))
    rates: dict[int, list[float]] = {n: [] for n, _, _ in cases}
    for _ in range(repeats):
        for n, _, steps in cases:
            rates[n].append(closed_loop_rate(n, "local", steps // 4 if quick else steps))
    ok = True
    for n, target, _ in cases:
        r = rates[n]
        ok &= line(f"n = {n} [{min(r):.0f} to {max(r):.0f}]", float(np.median(r)), "steps/s",
                   target, False)  # fmt: skip
    return ok


ROOMS_RATIO_TARGET = 0.5
"""Least steps per second of the paper's loop on the rooms over the square's."""


def loop_rate(overrides: list[str], steps: int, warmup: int = 20) -> float:
    """Steps per second of the loop the app builds from ``overrides``: the inverse of the
    median wall time of a step over ``steps`` steps after ``warmup`` (the compiled loops
    are built and the filters' factors made then)."""
    from harness.api import compose
    from harness.loop import trajectory
    from harness.runs.build import build

    loop = trajectory(build(compose(overrides)), hold=True)
    for _ in range(warmup):
        next(loop)
    times = np.empty(steps)
    for i in range(steps):
        t0 = time.perf_counter()
        next(loop)
        times[i] = time.perf_counter() - t0
    return 1.0 / float(np.median(times))


ROOMS = ["grid.n=30", "agents.n=1024", "domain=rooms", "init=left_room"]
"""The paper's loop on the rooms, the swarm starting in the left room."""

SQUARE = ["grid.n=30", "agents.n=1024"]
"""The paper's loop on the square."""


def bench_rooms(quick: bool, rounds: int = 4) -> bool:
    """The paper's loop on the rooms against the square (module docstring): ``rounds``
    rounds, each a square run and a rooms run in alternating order; the median of the
    rounds' ratios against :data:`ROOMS_RATIO_TARGET`, each loop's median rate beside it.
    """
    print(
        "Paper's loop on the rooms against the square, n = 30, N = 1024 (steps per second; "
        f"{rounds} rounds alternating the two, range in brackets):"
    )
    steps = 150 if quick else 600
    square, rooms = [], []
    for k in range(rounds):
        pair = (SQUARE, ROOMS) if k % 2 == 0 else (ROOMS, SQUARE)
        rates = {id(o): loop_rate(o, steps) for o in pair}
        square.append(rates[id(SQUARE)])
        rooms.append(rates[id(ROOMS)])
    ratio = np.array(rooms) / np.array(square)
    for name, r in (("square", square), ("rooms", rooms)):
        line(f"n = 30, N = 1024, {name} [{min(r):.0f} to {max(r):.0f}]", float(np.median(r)),
             "steps/s", None, False)  # fmt: skip
    name = f"rooms over square [{ratio.min():.2f} to {ratio.max():.2f}]"
    return line(name, float(np.median(ratio)), "x", ROOMS_RATIO_TARGET, False)


def main(argv: list[str] | None = None) -> bool:
    """Run every benchmark and print the figures against their targets."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    parser.add_argument("--child", nargs=2, type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        kde_agents_child(*args.child)
        return True
    import numba

    print(f"numba threads: {numba.get_num_threads()}, layer on first use")
    results = []
    with threadpool_limits(1):
        results.append(bench_fokker_planck(args.quick))
    results.append(bench_kde_agents(args.quick))
    with threadpool_limits(1):
        results.append(bench_closed_loop(args.quick))
        results.append(bench_rooms(args.quick))
    print("all targets met" if all(results) else "some targets MISSED")
    return all(results)


if __name__ == "__main__":
    raise SystemExit(cli(main, "benchmarks.numerics"))
