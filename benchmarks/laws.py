"""Speed of every law in the closed loop: `python -m benchmarks.laws` (part of `make bench`).

Each law runs the agents plant with the paper's estimator (KDE and both filters) on the
paper's 30 x 30 grid; the rate is steps per second, the inverse of the *mean* wall time
of a step over whole periods of the periodic laws (``psg``, ``psg_feedback``, ``ot``
solve once per ``control.period``, and the mean counts that solve once per period),
after one warm-up period. Targets: at least 500 steps/s at N = 1024 for every law, and
at least 20 steps/s for ``mmd`` and ``svgd`` at N = 65536. One process, BLAS on one
thread as in a run; run with nothing else on the machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

from threadpoolctl import threadpool_limits

from benchmarks.report import record

LAWS = ("paper", "heat", "langevin", "mmd", "svgd", "psg", "psg_feedback", "ot")
"""Every law (``control=<law>``)."""

TARGETS = {1024: 500.0, 65536: 20.0}
"""Steps per second asked for at each swarm size."""

LARGE = ("mmd", "svgd")
"""The laws timed at N = 65536."""


def loop_rate(law: str, n_robots: int, seconds: float) -> tuple[float, float]:
    """Closed-loop steps per second of ``control=law`` with ``n_robots`` robots: the
    inverse mean step time over ``seconds`` of simulated time after a warm-up of the
    same length; and the law's own share of a step (mean time of the law's calls over
    the same steps / mean step time).
    """
    from harness.api import compose
    from harness.loop import trajectory
    from harness.runs.build import build

    cfg = compose([f"control={law}", f"agents.n={n_robots}"])
    parts = build(cfg)
    spent = [0.0]
    control = parts.control

    def timed(inp):
        t0 = time.perf_counter()
        out = control(inp)
        spent[0] += time.perf_counter() - t0
        return out

    timed.gives_field = control.gives_field  # type: ignore[attr-defined]
    timed.own_estimates = control.own_estimates  # type: ignore[attr-defined]
    loop = trajectory(dataclasses.replace(parts, control=timed))  # type: ignore[arg-type]
    steps = max(1, round(seconds / parts.dt))
    next(loop)
    for _ in range(steps):
        next(loop)
    spent[0] = 0.0
    t0 = time.perf_counter()
    for _ in range(steps):
        next(loop)
    wall = time.perf_counter() - t0
    return steps / wall, spent[0] / wall


def main(argv: list[str] | None = None) -> bool:
    """Time every law; print each rate against its target; return whether all are met."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="simulated s per timing")
    args = parser.parse_args(argv)
    print("Laws in the closed loop (agents, KDE, both filters, n = 30; steps per second):")
    ok = True
    with threadpool_limits(1):
        for n_robots, target in TARGETS.items():
            for law in LAWS if n_robots == 1024 else LARGE:
                rate, share = loop_rate(law, n_robots, args.seconds)
                name = f"N = {n_robots:>6,d}, control={law}"
                ok &= record(name, rate, "steps/s", target, ">=")
                record(f"{name}: the law's share of a step", 100 * share, "%")
    print("all law targets met" if ok else "SOME LAW TARGETS MISSED")
    return ok


if __name__ == "__main__":
    main()
