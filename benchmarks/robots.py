"""Speed of the robots that are not ideal integrators: `python -m benchmarks.robots`
(part of `make bench`).

Two figures against their targets:

* the unicycles' step at N = 1024 (the held field through the link, interpolated at
  the robots, the move with its noise draws) over the ideal integrators' (their
  compiled Euler-Maruyama step): at most 1.3; the double integrators' beside it, and the
  whole closed-loop step (paper's law and estimator, 30 x 30 grid) with each plant, for
  what the robots weigh in a run;
* the unicycles' step at N = 1e6 under the paper's start-time field: at most 30 ms,
  beside the ideal integrators' and, for each, the whole plant step
  (:meth:`harness.plants.agents.Agents.advance`, with the limit ``p_inf``);
* the ideal integrators' step on the rooms (``domain=rooms``: every move checked
  against the robots' map of obstacles) over the same step on the square, at N = 1024
  and N = 1e6, under the square's start-time field (no target: what the map costs).

Times are medians over repeats of the mean over a block of steps, after a warm-up (the
compiled loops are built then). One process, BLAS on one thread as in a run; run with
nothing else on the machine.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from threadpoolctl import threadpool_limits

from benchmarks.ab import cli
from benchmarks.report import record

PLANTS = ("agents", "unicycles", "double_integrators")
"""The plants compared (``plant=<option>``)."""

ROBOT_RATIO_TARGET = 1.3
"""Largest robots' step time of the unicycles over the ideal integrators' at N = 1024."""

LARGE_STEP_TARGET_MS = 30.0
"""Largest unicycle plant step at N = 1e6 (ms)."""


def loop_step_ms(plant: str, n_robots: int, steps: int, repeats: int) -> float:
    """Median over ``repeats`` blocks of the mean closed-loop step time (ms)."""
    from harness.api import compose
    from harness.loop import trajectory
    from harness.runs.build import build

    parts = build(compose([f"plant={plant}", f"agents.n={n_robots}"]))
    loop = trajectory(parts, hold=True)
    next(loop)
    for _ in range(steps):  # warm-up: compile, fill caches
        next(loop)
    blocks = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            next(loop)
        blocks.append((time.perf_counter() - t0) / steps * 1e3)
    return float(np.median(blocks))


def _started(plant: str, n_robots: int):
    """A built loop at its start (exact estimates) and the command it computed there."""
    from harness.api import compose
    from harness.loop import trajectory
    from harness.runs.build import build

    parts = build(compose([f"plant={plant}", f"agents.n={n_robots}", "estimator=exact"]))
    rec, _ = next(trajectory(parts))
    assert rec.command.field is not None
    return parts, rec.command, np.random.default_rng(0)


WARM_UP = 150
"""Steps before timing: the compiled loops are built, and the unicycles, which start
with uniform headings, turn onto their commands (1.5 s at omega_max = 3 rad/s), so the
timed steps are the loop's usual ones rather than its first."""


def _median_ms(step, steps: int, repeats: int) -> float:
    for _ in range(WARM_UP):
        step()
    blocks = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        blocks.append((time.perf_counter() - t0) / steps * 1e3)
    return float(np.median(blocks))


def robot_step_ms(plant: str, n_robots: int, steps: int, repeats: int) -> float:
    """Median over ``repeats`` blocks of the mean robots' step (ms) under the start's
    field (:meth:`harness.plants.agents.Agents.advance`: the command through the link and
    the robots' move with the noise's draws; for the ideal integrators the compiled
    Euler-Maruyama step they take by default).
    """
    parts, command, rng = _started(plant, n_robots)

    def step() -> None:
        parts.plant.advance(command, None, parts.dt, rng)

    return _median_ms(step, steps, repeats)


def plant_step_ms(plant: str, n_robots: int, steps: int, repeats: int) -> float:
    """Median over ``repeats`` blocks of the mean plant step (ms: the link and the robots,
    :meth:`harness.plants.agents.Agents.advance`, and the loop's limit ``p_inf``,
    :meth:`harness.plants.limit.Limit.advance`) under the start's command, held fixed."""
    parts, command, rng = _started(plant, n_robots)
    a = parts.model.matrix(command.field)
    limit = parts.limit
    assert limit is not None

    def step() -> None:
        parts.plant.advance(command, a, parts.dt, rng)
        limit.advance(parts.dt)

    return _median_ms(step, steps, repeats)


def domain_step_ms(domain: str, n_robots: int, steps: int, repeats: int) -> float:
    """Median over ``repeats`` blocks of the mean robots' step (ms) of ``N`` ideal
    integrators on ``domain`` (``square`` or ``rooms``) under the square's start-time
    field (:meth:`harness.plants.agents.Agents.advance`); the plant is made with the
    run's grid, ``p_0`` and bandwidth and the domain's free space.
    """
    from harness.domains.rooms import Rooms
    from harness.fokker_planck import FokkerPlanck
    from harness.plants.agents import Agents

    parts, command, rng = _started("agents", n_robots)
    grid = parts.grid
    free = Rooms().resolve(grid) if domain == "rooms" else None
    model = FokkerPlanck(grid, parts.model.sigma, free=free)
    plant = Agents(
        grid=grid, model=model, init=parts.init, n=n_robots,
        bandwidth=parts.plant.kde.bandwidth, dt=parts.dt,
    )  # fmt: skip
    plant.start(rng)

    def step() -> None:
        plant.advance(command, None, parts.dt, rng)

    return _median_ms(step, steps, repeats)


def main(argv: list[str] | None = None) -> bool:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200, help="steps per block at N = 1024")
    parser.add_argument("--repeats", type=int, default=5, help="blocks (median reported)")
    parser.add_argument("--large", type=int, default=1_000_000, help="robots of the large case")
    args = parser.parse_args(argv)
    with threadpool_limits(limits=1, user_api="blas"):
        ok = True
        print("robots' step, N = 1024 (command through the link, move, draws):")
        base = robot_step_ms("agents", 1024, 20 * args.steps, args.repeats)
        record("N = 1024: agents, robots' step", base * 1e3, "us")
        for plant in PLANTS[1:]:
            ms = robot_step_ms(plant, 1024, 20 * args.steps, args.repeats)
            record(f"N = 1024: {plant}, robots' step", ms * 1e3, "us")
            target = ROBOT_RATIO_TARGET if plant == "unicycles" else None
            ok &= record(f"N = 1024: {plant} / agents, robots' step", ms / base, "x", target)
        print("closed-loop step, N = 1024, paper's law and estimator, 30 x 30 grid:")
        base = loop_step_ms("agents", 1024, args.steps, args.repeats)
        record("N = 1024: agents, closed-loop step", base, "ms")
        for plant in PLANTS[1:]:
            ms = loop_step_ms(plant, 1024, args.steps, args.repeats)
            record(f"N = 1024: {plant}, closed-loop step", ms, "ms")
            record(f"N = 1024: {plant} / agents, closed-loop step", ms / base, "x")
        print(f"N = {args.large:,d}: robots' step, and the plant step (with the limit p_inf):")
        for plant in ("agents", "unicycles"):
            ms = robot_step_ms(plant, args.large, 10, args.repeats)
            whole = plant_step_ms(plant, args.large, 10, args.repeats)
            target = LARGE_STEP_TARGET_MS if plant == "unicycles" else None
            ok &= record(f"N = {args.large:,d}: {plant}, robots' step", ms, "ms", target)
            record(f"N = {args.large:,d}: {plant}, plant step", whole, "ms")
        print("ideal integrators' step on the rooms (robots' map of obstacles) and the square:")
        for n_robots, steps in ((1024, 20 * args.steps), (args.large, 10)):
            square = domain_step_ms("square", n_robots, steps, args.repeats)
            rooms = domain_step_ms("rooms", n_robots, steps, args.repeats)
            unit, scale = ("us", 1e3) if n_robots < 100_000 else ("ms", 1.0)
            record(f"N = {n_robots:,d}: agents on the square, robots' step", square * scale, unit)
            record(f"N = {n_robots:,d}: agents on the rooms, robots' step", rooms * scale, unit)
            record(f"N = {n_robots:,d}: rooms / square, robots' step", rooms / square, "x")
    return ok


if __name__ == "__main__":
    raise SystemExit(cli(main, "benchmarks.robots"))
