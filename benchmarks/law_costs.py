"""Costs of the robot laws (psg, psg_feedback, ot) and the accuracy of ot's large-N
assignment.

    python -m benchmarks.law_costs --calls [--n 1024] [--grid 30] [--repeat 50]
    python -m benchmarks.law_costs --solve [--sizes 1024 4096 16384]
    python -m benchmarks.law_costs --loop [--n 1024] [--steps 500] [--rounds 6] [--laws paper ...]

``--calls`` times one call of each law (median over ``repeat``; BLAS on one thread as in
the run): a step inside a period (velocities toward the goals) and a step that starts a
period (the chain's draws, or the assignment), at the default target, the paper's start
box and the default estimate (the target itself); for ot also a period's start with a
fresh swarm on the start box every period (a transport across the domain each time) and
with the swarm settled on its points and moved by 0.005 (the noise of a period).

``--solve`` times ot's assignment per size for two swarms, one crossing the domain
(uniform on the paper's start box) and one settled (each robot within 0.005 of its
point), and up to :data:`harness.control.matching.EXACT_MAX` robots compares
:func:`harness.control.matching.large_assignment` with the exact assignment (cost ratio,
certified or not, rounds).

``--loop`` steps the closed loop (the agents plant, the run's estimator, the law; no
observers) and prints steps per second, counting each period's solve (500 steps are 5
periods of the default 1 s); the laws take turns, round after round, so that load from
elsewhere slows them alike.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from threadpoolctl import threadpool_limits

from harness.api import compose
from harness.control.assignment import AssignmentControl, quantise
from harness.control.guidance import FeedbackGuidance, MetropolisGuidance, target_masses
from harness.control.matching import EXACT_MAX, exact_assignment, large_assignment, transport_cost
from harness.control.paper import PaperControl
from harness.grid import Grid
from harness.loop import trajectory
from harness.records import ControlInput, Estimate
from harness.runs.build import build
from harness.targets.densities import DEFAULT_TARGET, Target


def median_time(f, repeat: int) -> float:
    """Median wall time of ``f()`` (s) over ``repeat`` calls."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def calls(n: int, side: int, repeat: int) -> None:
    """Per-call costs of each law (``--calls``)."""
    grid = Grid.square(side)
    target = Target.from_density(grid, DEFAULT_TARGET)
    est = Estimate(target.p, target.grad)
    gen = np.random.default_rng(0)
    x = gen.uniform(0.15, 0.85, (2, n))
    laws = {
        "paper": PaperControl(target, alpha=0.003, sigma=5e-5),
        "psg": MetropolisGuidance(target),
        "psg_feedback": FeedbackGuidance(target),
        "ot": AssignmentControl(target, robots=n),
    }
    print(f"N = {n}, {side} x {side} grid, median of {repeat} (ms)")
    for name, law in laws.items():
        law(ControlInput(0.0, est, x))  # the first period's solve
        inside = median_time(lambda law=law: law(ControlInput(0.5, est, x)), repeat)
        starts = []
        for k in range(1, repeat + 1):
            t0 = time.perf_counter()
            law(ControlInput(float(k), est, x))  # a period's start
            starts.append(time.perf_counter() - t0)
        print(
            f"  {name:13s} step {1e3 * inside:8.3f}   period start {1e3 * np.median(starts):8.3f}"
        )
    ot_law = laws["ot"]
    assert isinstance(ot_law, AssignmentControl)
    for swarm in ("crossing", "settled"):
        starts = []
        for k in range(1, repeat + 1):
            if swarm == "crossing":  # a fresh swarm on the start box: a transport every period
                x = gen.uniform(0.15, 0.85, (2, n))
            else:  # on the points, moved by the noise of a period
                assert ot_law.assignment is not None
                x = np.clip(
                    ot_law.points[:, ot_law.assignment] + 0.005 * gen.standard_normal((2, n)), 0, 1
                )
            t0 = time.perf_counter()
            ot_law(ControlInput(float(repeat + 2 * k), est, x))
            starts.append(time.perf_counter() - t0)
        print(f"  ot, {swarm:9s} period start {1e3 * np.median(starts):8.3f}")


def crossing_and_settled(n: int, seed: int = 4) -> tuple[Grid, np.ndarray, dict[str, np.ndarray]]:
    """Points of the default target and two swarms: crossing from the paper's start box,
    and settled within 0.005 of the points."""
    gen = np.random.default_rng(seed)
    grid = Grid.square(30)
    y = quantise(grid, target_masses(Target.from_density(grid, DEFAULT_TARGET)), n, gen).T
    crossing = gen.uniform(0.15, 0.85, (n, 2))
    settled = np.clip(y + 0.005 * gen.standard_normal((n, 2)), 0, 1)
    return grid, y, {"crossing": crossing, "settled": settled}


def solve(sizes: list[int]) -> None:
    """Assignment times and the large method's accuracy (``--solve``)."""
    for n in sizes:
        grid, y, cases = crossing_and_settled(n)
        for name, x in cases.items():
            line = f"N = {n:6d} {name:9s}"
            exact_cost = None
            if n <= EXACT_MAX:
                t0 = time.perf_counter()
                exact_cost = transport_cost(x, y, exact_assignment(x, y))
                line += f" exact {time.perf_counter() - t0:7.2f} s"
            t0 = time.perf_counter()
            found = large_assignment(grid, x, y)
            spent = time.perf_counter() - t0
            line += f" | large {spent:7.2f} s, rounds {found.rounds}, certified {found.certified}"
            if exact_cost is not None:
                ratio = transport_cost(x, y, found.perm) / exact_cost
                line += f", cost / exact {ratio:.6f}"
            print(line, flush=True)


def loop(n: int, steps: int, laws: list[str], estimator: str, rounds: int) -> None:
    """Closed-loop steps per second (``--loop``): the laws' loops are stepped in turn,
    ``steps`` at a time, ``rounds`` times (so that a busy machine slows them alike); the
    best and the median round per law.
    """
    loops = {}
    for law in laws:
        cfg = compose(
            [f"control={law}", f"agents.n={n}", f"estimator={estimator}", "log.progress=off"]
        )
        run = trajectory(build(cfg))
        next(run)
        next(run)  # warm up (compilation)
        loops[law] = run
    spent: dict[str, list[float]] = {law: [] for law in laws}
    for _ in range(rounds):
        for law, run in loops.items():
            t0 = time.perf_counter()
            for _ in range(steps):
                next(run)
            spent[law].append((time.perf_counter() - t0) / steps)
    for law, times in spent.items():
        best, median = min(times), float(np.median(times))
        print(
            f"  {law:13s} best {1 / best:7.1f} steps/s ({1e3 * best:.3f} ms/step), "
            f"median {1 / median:7.1f} steps/s ({1e3 * median:.3f} ms/step)",
            flush=True,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", action="store_true")
    parser.add_argument("--solve", action="store_true")
    parser.add_argument("--loop", action="store_true")
    parser.add_argument("--n", type=int, default=1024)
    parser.add_argument("--grid", type=int, default=30)
    parser.add_argument("--repeat", type=int, default=50)
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096, 16384])
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--estimator", default="filters")
    parser.add_argument(
        "--laws", nargs="+", default=["paper", "langevin", "psg", "psg_feedback", "ot"]
    )
    args = parser.parse_args()
    with threadpool_limits(1):
        if args.calls:
            calls(args.n, args.grid, args.repeat)
        if args.solve:
            solve(args.sizes)
        if args.loop:
            print(f"N = {args.n}, estimator={args.estimator}, {args.rounds} x {args.steps} steps")
            loop(args.n, args.steps, args.laws, args.estimator, args.rounds)


if __name__ == "__main__":
    main()
