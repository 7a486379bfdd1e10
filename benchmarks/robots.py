"""Speed of the robots that are not ideal integrators: `python -m benchmarks.robots`
(part of `make bench`).

Two figures against their targets:

* the closed-loop step (paper's law, paper's estimator, 30 x 30 grid, N = 1024) with
  ``plant=unicycles`` and ``plant=double_integrators`` over the step with
  ``plant=agents`` (ideal integrators): at most 1.3;
* the unicycles' plant step (:meth:`harness.plants.Agents.advance`: the command through
  the link, the robots' move, the limit ``p_inf``) at N = 1e6 under the paper's
  start-time field: at most 30 ms, beside the ideal integrators' for comparison.

Times are medians over repeats of the mean over a block of steps, after a warm-up (the
compiled loops are built then). One process, BLAS on one thread as in a run; run with
nothing else on the machine.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from threadpoolctl import threadpool_limits

PLANTS = ("agents", "unicycles", "double_integrators")
"""The plants compared (``plant=<option>``)."""

LOOP_RATIO_TARGET = 1.3
"""Largest closed-loop step time of a robot plant over the ideal integrators' at N = 1024."""

LARGE_STEP_TARGET_MS = 30.0
"""Largest unicycle plant step at N = 1e6 (ms)."""


def loop_step_ms(plant: str, n_robots: int, steps: int, repeats: int) -> float:
    """Median over ``repeats`` blocks of the mean closed-loop step time (ms)."""
    from harness.api import compose
    from harness.build import build
    from harness.loop import ClosedLoop

    parts = build(compose([f"plant={plant}", f"agents.n={n_robots}"]))
    loop = ClosedLoop(
        parts.plant, parts.estimator, parts.control, parts.model, parts.dt,
        np.random.default_rng(0),
    )  # fmt: skip
    loop.start()
    for _ in range(steps):  # warm-up: compile, fill caches
        loop.step()
    blocks = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            loop.step()
        blocks.append((time.perf_counter() - t0) / steps * 1e3)
    return float(np.median(blocks))


def plant_step_ms(plant: str, n_robots: int, steps: int, repeats: int) -> float:
    """Median over ``repeats`` blocks of the mean plant step (ms) under the command the
    loop computes at its start (held fixed, so only the plant is timed)."""
    from harness.api import compose
    from harness.build import build
    from harness.loop import ClosedLoop

    parts = build(compose([f"plant={plant}", f"agents.n={n_robots}", "estimator=exact"]))
    rng = np.random.default_rng(0)
    loop = ClosedLoop(parts.plant, parts.estimator, parts.control, parts.model, parts.dt, rng)
    loop.start()
    command = loop.command
    assert command is not None and command.field is not None
    a = parts.model.matrix(command.field)
    for _ in range(3):
        parts.plant.advance(command, a, parts.dt, rng)
    blocks = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            parts.plant.advance(command, a, parts.dt, rng)
        blocks.append((time.perf_counter() - t0) / steps * 1e3)
    return float(np.median(blocks))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200, help="steps per block at N = 1024")
    parser.add_argument("--repeats", type=int, default=5, help="blocks (median reported)")
    parser.add_argument("--large", type=int, default=1_000_000, help="robots of the large case")
    args = parser.parse_args(argv)
    with threadpool_limits(limits=1, user_api="blas"):
        base = loop_step_ms("agents", 1024, args.steps, args.repeats)
        print("closed-loop step, N = 1024, paper's law and estimator, 30 x 30 grid:")
        print(f"  agents             {base:7.3f} ms")
        ok = True
        for plant in PLANTS[1:]:
            ms = loop_step_ms(plant, 1024, args.steps, args.repeats)
            ratio = ms / base
            good = ratio <= LOOP_RATIO_TARGET
            ok &= good
            print(
                f"  {plant:<18} {ms:7.3f} ms  ratio {ratio:.2f} "
                f"(target <= {LOOP_RATIO_TARGET}) {'ok' if good else 'MISSED'}"
            )
        print(f"plant step at N = {args.large:.0e} (command through the link, move, limit):")
        for plant in ("agents", "unicycles"):
            ms = plant_step_ms(plant, args.large, 10, args.repeats)
            line = f"  {plant:<18} {ms:7.2f} ms"
            if plant == "unicycles":
                ok &= ms <= LARGE_STEP_TARGET_MS
                good = "ok" if ms <= LARGE_STEP_TARGET_MS else "MISSED"
                line += f"  (target <= {LARGE_STEP_TARGET_MS:g} ms) {good}"
            print(line)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
