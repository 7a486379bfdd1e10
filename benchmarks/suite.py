"""Speed benchmarks: `make bench`. Each figure is printed next to its target.

Medians over repeats (per call, milliseconds) or rates over a run (steps per
second), wall-clock, one process, BLAS pinned to one thread as in the run loop;
run with nothing else on the machine.
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable
from pathlib import Path as Path_

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

from benchmarks.ab import cli
from benchmarks.report import record
from harness.control.paper import paper_law
from harness.estimators.kde import KDE
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.plants.agents import Swarm
from harness.targets.densities import DEFAULT_TARGET, Box, Target


def median_ms(fn: Callable[[], object], repeats: int, warmup: int = 2) -> float:
    """Median wall time of ``fn`` in ms."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def report(name: str, value_ms: float, target_ms: float | None) -> bool:
    """Report one time in ms (:func:`benchmarks.report.record`); whether its target is met."""
    return record(name, value_ms, "ms", target_ms, "<=")


def bench_kde_agents() -> bool:
    """KDE + agent step."""
    print("KDE (density + gradient) and agent step, n = 30, h = 0.04:")
    g = Grid.square(30)
    rng = np.random.default_rng(0)
    target = Target.from_density(g, DEFAULT_TARGET)
    p0 = Box().on_grid(g)
    v = paper_law(p0, g.gradient(p0), target, 0.003, 5e-5)
    ok = True
    for n_robots, repeats, target_ms in ((1024, 400, 0.5), (1_000_000, 15, 80.0)):
        swarm = Swarm(g, Box().sample(n_robots, g, rng), 5e-5)
        kde = KDE(g, 0.04)

        def loop(swarm=swarm, kde=kde) -> None:
            swarm.step(v, 0.01, rng)
            kde(swarm.positions)

        t_kde = median_ms(lambda swarm=swarm, kde=kde: kde(swarm.positions), repeats)
        t_agent = median_ms(lambda swarm=swarm: swarm.step(v, 0.01, rng), repeats)
        t_both = median_ms(loop, repeats)
        method = "exact" if n_robots <= kde.exact_max_robots else "binned"
        report(f"N = {n_robots:>9,d}: KDE ({method})", t_kde, None)
        report(f"N = {n_robots:>9,d}: agent step", t_agent, None)
        ok &= report(f"N = {n_robots:>9,d}: KDE + agent step", t_both, target_ms)
        if n_robots <= 4096:
            report(
                f"N = {n_robots:>9,d}: KDE exact path (for reference)",
                median_ms(lambda swarm=swarm, kde=kde: kde.exact(swarm.positions), repeats),
                None,
            )
    return ok


def bench_fokker_planck() -> bool:
    """Fokker-Planck operator assembly and step."""
    print("Fokker-Planck (backward Euler) under the paper's law, mid-run state p = 0.7 p* + 0.3:")
    ok = True
    for n in (30, 64, 128):
        g = Grid.square(n)
        target = Target.from_density(g, DEFAULT_TARGET)
        p = 0.7 * target.p + 0.3 / g.area
        v = paper_law(p, g.gradient(p), target, 0.003, 5e-5)
        op = FokkerPlanck(g, 5e-5)
        report(f"n = {n:>3d}: assemble A(v)", median_ms(lambda op=op, v=v: op.matrix(v), 50), None)
        report(
            f"n = {n:>3d}: step dt = 0.01",
            median_ms(lambda op=op, p=p, v=v: op.step(p, v, 0.01), 50),
            None,
        )
        report(
            f"n = {n:>3d}: step dt = 0.01 by sparse LU",
            median_ms(lambda op=op, p=p, v=v: op.step_lu(p, v, 0.01), 20),
            None,
        )
    return ok


def closed_loop_rate(n: int, engine: str, steps: int) -> float:
    """Closed-loop steps per second: agents, KDE, both filters, paper's law, reference;
    the inverse of the median wall time of a step over ``steps`` steps after the first
    (the median: a step that the host delays does not move it)."""
    from harness.api import compose
    from harness.loop import trajectory
    from harness.runs.build import build

    loop = trajectory(build(compose([f"grid.n={n}", f"filter.engine={engine}"])), hold=True)
    next(loop)
    next(loop)
    times = np.empty(steps)
    for i in range(steps):
        t0 = time.perf_counter()
        next(loop)
        times[i] = time.perf_counter() - t0
    return 1.0 / float(np.median(times))


def bench_filters() -> bool:
    """Closed loop with the paper's filters."""
    print("Closed loop, N = 1024, both filters (steps per second = 1 / median step time):")
    fast30 = closed_loop_rate(30, "local", 2000)
    slow30 = closed_loop_rate(30, "filterpy", 3)
    fast64 = closed_loop_rate(64, "local", 300)
    ratio = fast30 / slow30
    rows = [
        ("n = 30, fast (local) filters", fast30, 300.0),
        ("n = 30, filterpy KalmanFilter as the engine", slow30, None),
        ("n = 64, fast (local) filters", fast64, 30.0),
    ]
    ok = True
    for name, value, target in rows:
        ok &= record(name, value, "steps/s", target, ">=")
    met = record("speed-up of fast over filterpy engine, n = 30", ratio, "x", 100.0, ">=")
    return ok and met


def bench_sweeps() -> bool:
    """Parallel efficiency of a two-job sweep and the cost of logging."""
    import subprocess
    import sys
    import tempfile

    print("Sweeps (paper-scale agent loop, 20 s of simulated time per job):")
    # both through the joblib launcher, so start-up costs are alike
    base = [
        sys.executable,
        "-m",
        "experiments.closed_loop",
        "-m",
        "sim.t_final=20",
        "log.progress=off",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        subprocess.run(
            [*base, "seed=1", f"hydra.sweep.dir={tmp}/one"], check=True, capture_output=True
        )
        one = time.perf_counter() - t0
        t0 = time.perf_counter()
        subprocess.run(
            [*base, "seed=1,2", f"hydra.sweep.dir={tmp}/two"], check=True, capture_output=True
        )
        two = time.perf_counter() - t0
    record("one-job sweep (process wall time)", one, "s")
    record("two jobs on two cores (joblib launcher)", two, "s")
    met = record("ratio two jobs / one job", two / one, "x", 1.15, "<=")
    # logging share of a run's wall time, default rates
    from harness.api import compose
    from harness.runs.run import run

    cfg = compose(["sim.t_final=20", "log.progress=off"])
    with tempfile.TemporaryDirectory() as tmp:
        result = run(cfg, Path_(tmp))
    share = 100 * result.log_s / result.wall_s
    met_log = record("logging share of run wall time (default rates)", share, "%", 10.0, "<=")
    return met and met_log


def main(argv: list[str] | None = None) -> bool:
    """Run every benchmark and summarise; whether every target was met."""
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args(argv)
    print(
        f"densityloop benchmarks on {platform.processor() or platform.machine()}, "
        f"Python {platform.python_version()}"
    )
    blas = {(i.get("internal_api"), i.get("num_threads")) for i in threadpool_info()}
    print(f"BLAS: {sorted(blas)}")
    # the sweep benchmark runs first: after the dense filterpy products the idle
    # BLAS threads of this process measurably slow its child processes
    results = [bench_sweeps()]
    with threadpool_limits(1):
        results += [bench_kde_agents(), bench_fokker_planck(), bench_filters()]
    print("all targets met" if all(results) else "SOME TARGETS MISSED")
    return all(results)


if __name__ == "__main__":
    raise SystemExit(cli(main, "benchmarks.suite"))
