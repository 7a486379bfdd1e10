"""Per-step cost of the distributed estimator and decentralised loop: `python -m
benchmarks.distributed` (``--help`` for options).

One closed-loop step at n = 30, paper scale (h = 0.04, dt = 0.01, alpha = 0.003, sigma =
5e-5, robots from the box [0.15, 0.85]^2, ``initial_rounds`` consensus rounds before the
robots move): communication graph (with the consensus weights), consensus (the robots'
kernels, their increments and the mixing rounds), per-robot filters (model ``A`` from the
law applied to the robots' mean estimate, which is the benchmark's stand-in for the
filters' model), per-robot law, robot step; then the logged graph metrics on their own.
Medians over steps of wall time and of process CPU time (the machine may be shared: CPU
time is the work done; with numba's threads it sums the threads), BLAS pinned to one
thread, numba to ``--threads`` (default 1).

``--app`` times the loop the app builds instead (:func:`app_loop`, what ``make bench``
runs): the figure its target is about, with the centralised reference filters,
the plant's KDE and limit loop and the logged network metrics included.

Targets: the closed loop -- graph + consensus + per-robot filters + per-robot
law (+ model and robot step) -- <= 20 ms per step (>= 50 steps/s) at N = 1024, n = 30,
radius 0.05 to 0.2 and k-nearest; N = 4096 must run. Each line
prints its figure against the target; memory is the bytes held per robot.
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np
from threadpoolctl import threadpool_limits

from benchmarks.ab import cli
from benchmarks.report import record
from harness.control.own_estimates import own_velocities
from harness.control.paper import PaperControl, paper_law
from harness.estimators.distributed.density import jacobi_sweeps, stencil_coefficients
from harness.estimators.distributed.estimator import RobotEstimators
from harness.estimators.distributed.graph import algebraic_connectivity, n_components
from harness.estimators.filters.common import FilterSettings
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.plants.agents import Swarm
from harness.targets.densities import DEFAULT_TARGET, Box, Target

SIGMA, ALPHA, H, DT = 5e-5, 0.003, 0.04, 0.01
TARGET_MS = 20.0


class Clock:
    """Wall and CPU time per named part."""

    def __init__(self) -> None:
        self.wall: dict[str, list[float]] = {}
        self.cpu: dict[str, list[float]] = {}

    def __call__(self, name, fn):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        self.wall.setdefault(name, []).append(time.perf_counter() - w0)
        self.cpu.setdefault(name, []).append(time.process_time() - c0)
        return out

    def report(self, skip: int, target: float | None) -> tuple[float, float]:
        total_w = total_c = 0.0
        for name in [n for n in self.wall if len(self.wall[n]) > skip]:
            w = 1e3 * float(np.median(self.wall[name][skip:]))
            c = 1e3 * float(np.median(self.cpu[name][skip:]))
            if not name.startswith("("):
                total_w, total_c = total_w + w, total_c + c
            print(f"    {name:<34s} wall {w:8.2f} ms   cpu {c:8.2f} ms")
        verdict = ""
        if target is not None:
            ok = "meets" if total_c <= target else "MISSES"
            verdict = f"   target <= {target:.0f} ms (>= {1e3 / target:.0f} steps/s): {ok} (cpu)"
        print(
            f"    {'closed-loop step (sum)':<34s} wall {total_w:8.2f} ms   cpu {total_c:8.2f} ms"
            f"{verdict}"
        )
        print(f"    {'steps/s':<34s} wall {1e3 / total_w:8.1f}      cpu {1e3 / total_c:8.1f}")
        return total_w, total_c


def run(
    n_robots: int,
    radius: float | None,
    k: int | None,
    steps: int,
    initial_rounds: int,
    target: float | None,
    warmup: int = 0,
) -> None:
    g = Grid.square(30)
    rng = np.random.default_rng(0)
    target_density = Target.from_density(g, DEFAULT_TARGET)
    fp = FokkerPlanck(g, SIGMA)
    swarm = Swarm(g, Box().sample(n_robots, g, rng), SIGMA)
    pos = swarm.positions  # moved in place by the robot step
    est = RobotEstimators(
        g, DT, n_robots, H, FilterSettings(), radius=radius, k_nearest=k,
        initial_rounds=initial_rounds,
    )  # fmt: skip
    law = PaperControl(target_density, ALPHA, SIGMA).at_cells
    clock = Clock()
    e = clock("(initialize)", lambda: est.initialize(pos))
    sweeps = []
    for step in range(warmup + steps):
        if warmup and step == warmup:  # time from here on
            clock = Clock()
        p_mean = e.p_hat.mean(axis=0).reshape(g.shape)

        def model(p_mean=p_mean):
            q = g.gradient(p_mean)
            return fp.matrix(paper_law(p_mean, q, target_density, ALPHA, SIGMA))

        a = clock("filter model A (mean estimate)", model)
        sweeps.append(jacobi_sweeps(stencil_coefficients(g, a, DT)[0]))
        v = clock(
            "per-robot law",
            lambda e=e: own_velocities(g, law, e.p_hat, pos),
        )
        clock("robot step", lambda v=v: swarm.step_robots(v, DT, rng))
        w = clock("graph", lambda: est._graph(pos))
        y = clock("consensus", lambda w=w: est.consensus.step(pos, w))
        clock("per-robot filters", lambda y=y, a=a: est.filters.step(y, a))
        e = est._estimate(y)
        clock("(components, logged)", lambda e=e: n_components(e.adjacency))
        clock("(algebraic connectivity, logged)", lambda e=e: algebraic_connectivity(e.adjacency))
    graph = f"radius {radius}" if radius is not None else f"k = {k}"
    counts = est.communication(est.adjacency)
    print(
        f"  N = {n_robots}, {graph}: mean degree "
        f"{counts['mean_degree']:.1f}, {counts['messages']:.1f} messages "
        f"({counts['bytes'] / 1e3:.0f} kB) per robot per step, Jacobi sweeps "
        f"{min(sweeps[warmup:])}..{max(sweeps[warmup:])} (a priori)"
    )
    print(
        f"    memory {est.memory_bytes() / n_robots / 1e3:.1f} kB per robot "
        f"({est.memory_bytes() / 1e6:.1f} MB for the swarm)"
    )
    clock.report(skip=2 if warmup == 0 else 0, target=target)


def app_loop(n_robots: int, radius: float, steps: int, design: str = "grid") -> float:
    """Milliseconds per step of the loop the app builds with ``estimator=distributed``
    and ``+design=design`` (robots, plant's KDE and ``N -> infinity`` limit, graph,
    consensus, per-robot filters, the centralised reference filters, network metrics,
    per-robot law), median over ``steps`` steps after two untimed ones.
    """
    from harness.api import compose as compose_config
    from harness.loop import trajectory
    from harness.runs.build import build

    cfg = compose_config(
        [
            "estimator=distributed",
            f"agents.n={n_robots}",
            f"estimator.radius={radius}",
            f"+design={design}",
        ]
    )
    loop = trajectory(build(cfg), hold=True)
    for _ in range(3):
        next(loop)
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        next(loop)
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


DESIGNS = ("grid", "band", "pi_band", "command_band")
"""The designs of ``conf/design/`` (the ``distributed_frontier`` study's)."""


def bench_app(quick: bool) -> bool:
    """The app-built decentralised loop against its targets: N = 1024 with the baseline
    design, and N = 4096 at r = 0.1 with every design (the target is for the fastest).
    """
    print("Decentralised loop as the app builds it (n = 30, estimator=distributed):")
    ok = True
    cases: list[tuple[int, float, int, float | None, str]] = [(1024, 0.1, 200, TARGET_MS, "grid")]
    cases += [(4096, 0.1, 20, None, d) for d in DESIGNS]
    fastest = np.inf
    for n_robots, radius, steps, target, design in cases:
        if quick:
            steps = max(1, steps // 4)
        ms = app_loop(n_robots, radius, steps, design)
        if n_robots == 4096:
            fastest = min(fastest, ms)
        name = f"N = {n_robots}, r = {radius}, {design}"
        ok &= record(name, 1e3 / ms, "steps/s", None if target is None else 1e3 / target, ">=")
    name = "N = 4096, r = 0.1, fastest design"
    ok &= record(name, 1e3 / fastest, "steps/s", 1e3 / TARGET_MS, ">=")
    return ok


def memory_case(n_robots: int, radius: float, design: str, steps: int = 3) -> None:
    """Build the app's loop, take ``steps`` steps, print the peak resident memory against
    the estimate the harness prints and checks before a run
    (:func:`harness.runs.resources.check_memory`); run in a process of its own.
    """
    import resource

    from harness.api import compose as compose_config
    from harness.grid import Grid as GridType
    from harness.loop import trajectory
    from harness.runs.build import build
    from harness.runs.resources import check_memory

    # two rounds before the start: the memory does not depend on them, the time does
    overrides = ["estimator=distributed", f"agents.n={n_robots}", f"estimator.radius={radius}",
                 "estimator.initial_rounds=2",
                 f"+design={design}"]  # fmt: skip
    cfg = compose_config(overrides)
    estimate = check_memory(cfg, GridType.square(int(cfg.grid.n), float(cfg.grid.length)))
    loop = trajectory(build(cfg), hold=True)
    next(loop)
    t0 = time.perf_counter()
    for _ in range(steps):
        next(loop)
    ms = 1e3 * (time.perf_counter() - t0) / steps
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # kB on Linux
    name = f"N = {n_robots}, r = {radius}, {design}"
    record(f"{name}: peak memory (target: the estimate)", peak / 2**20, "MiB", estimate / 2**20)
    record(f"{name}: step time, the memory case", ms, "ms")


def bench_memory() -> bool:
    """N = 16384 runs within the memory estimate (a process per design)."""
    import subprocess
    import sys

    print("Memory at N = 16384, r = 0.1 (peak resident set over 3 steps):")
    ok = True
    for design in DESIGNS:
        cmd = [sys.executable, "-m", "benchmarks.distributed", "--memory", "16384", design]
        out = subprocess.run(cmd, capture_output=True, text=True, check=False)
        print(out.stdout.rstrip() or f"  {design}: failed: {out.stderr.strip()[-300:]}")
        ok &= out.returncode == 0 and "OK" in out.stdout
    return ok


def main(argv: list[str] | None = None) -> bool:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--threads", type=int, default=1, help="numba threads")
    parser.add_argument("--initial-rounds", type=int, default=30)
    parser.add_argument(
        "--warmup", type=int, default=0, help="untimed steps first (0: skip 2 timed steps)"
    )
    parser.add_argument("--only", type=int, default=None, help="run only this case (index)")
    parser.add_argument(
        "--app", action="store_true", help="only the app-built loop (what make bench runs)"
    )
    parser.add_argument("--quick", action="store_true", help="fewer steps (with --app)")
    parser.add_argument(
        "--memory", nargs=2, metavar=("N", "DESIGN"), help="one memory case (in its own process)"
    )
    args = parser.parse_args(argv)
    if args.memory:
        with threadpool_limits(1):
            memory_case(int(args.memory[0]), 0.1, args.memory[1])
        return True
    if args.app:
        with threadpool_limits(1):
            ok = bench_app(args.quick)
            ok &= bench_memory()
        print("all targets met" if ok else "some targets MISSED")
        return ok
    numba.set_num_threads(args.threads)
    print(
        f"numba threads {args.threads}; BLAS pinned to 1 thread; n = 30; "
        f"initial_rounds {args.initial_rounds}; warmup {args.warmup} steps"
    )
    cases: list[tuple[int, float | None, int | None, float | None]] = [
        (1024, 0.05, None, TARGET_MS),
        (1024, 0.1, None, TARGET_MS),
        (1024, 0.2, None, TARGET_MS),
        (1024, None, 8, TARGET_MS),
        (4096, 0.05, None, None),
    ]
    if args.only is not None:
        cases = [cases[args.only]]
    with threadpool_limits(1):
        for n_robots, radius, k, target in cases:
            run(n_robots, radius, k, args.steps, args.initial_rounds, target, args.warmup)
    return True


if __name__ == "__main__":
    raise SystemExit(cli(main, "benchmarks.distributed"))
