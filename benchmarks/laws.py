"""Speed of every law in the closed loop: `python -m benchmarks.laws` (part of `make bench`).

    python -m benchmarks.laws [--seconds S] [--list] [OVERRIDE ...]

Every law is every option of the config group `control`, as Hydra's config loader lists
them: the project's `conf/control/` and the `control/` of each directory a
`hydra.searchpath=[file://DIR]` override adds (a law of your own, `docs/extending.md`);
`--list` prints them and times nothing. The overrides are also applied to every timed
run. Each law runs the agents plant with the paper's estimator (KDE and both filters) on the
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
from collections.abc import Sequence

from threadpoolctl import threadpool_limits

from benchmarks.ab import cli
from benchmarks.report import record

TARGETS = {1024: 500.0, 65536: 20.0}
"""Steps per second asked for at each swarm size."""

LARGE = ("mmd", "svgd")
"""The laws timed at N = 65536 (when they are options of the group)."""


def laws(overrides: Sequence[str] = ()) -> list[str]:
    """The options of config group ``control`` (alphabetical), with the search path
    ``overrides`` give (``hydra.searchpath=[file:///abs/my_conf]``).
    """
    from harness.api import options

    return options("control", overrides)


def loop_rate(
    law: str, n_robots: int, seconds: float, overrides: Sequence[str] = ()
) -> tuple[float, float]:
    """Closed-loop steps per second of ``control=law`` with ``n_robots`` robots: the
    inverse mean step time over ``seconds`` of simulated time after a warm-up of the
    same length; and the law's own share of a step (mean time of the law's calls over
    the same steps / mean step time).
    """
    from harness.api import compose
    from harness.loop import trajectory
    from harness.runs.build import build

    cfg = compose([*overrides, f"control={law}", f"agents.n={n_robots}"])
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
    loop = trajectory(dataclasses.replace(parts, control=timed), hold=True)  # type: ignore[arg-type]
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
    parser.add_argument("--list", action="store_true", help="print the laws, time nothing")
    parser.add_argument(
        "overrides", nargs="*", help="Hydra overrides, e.g. hydra.searchpath=[file://DIR]"
    )
    args = parser.parse_args(argv)
    every = laws(args.overrides)
    if args.list:
        print("\n".join(every))
        return True
    print("Laws in the closed loop (agents, KDE, both filters, n = 30; steps per second):")
    ok = True
    with threadpool_limits(1):
        for n_robots, target in TARGETS.items():
            timed = every if n_robots == 1024 else [law for law in LARGE if law in every]
            for law in timed:
                rate, share = loop_rate(law, n_robots, args.seconds, args.overrides)
                name = f"N = {n_robots:>6,d}, control={law}"
                ok &= record(name, rate, "steps/s", target, ">=")
                record(f"{name}: the law's share of a step", 100 * share, "%")
    print("all law targets met" if ok else "SOME LAW TARGETS MISSED")
    return ok


if __name__ == "__main__":
    raise SystemExit(cli(main, "benchmarks.laws"))
