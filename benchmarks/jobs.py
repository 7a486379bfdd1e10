"""What a sweep job costs beyond its loop: `python -m benchmarks.jobs` (part of `make bench`).

    python -m benchmarks.jobs [--n N] [--seconds S]

A job of the ``laws_n`` kind (``+experiment=laws_n``, the paper's law, N = 1024, 25 s,
the default observers) in a sweep of four jobs, two at a time on two cores (the joblib
launcher, seeds 0 to 3), against the loop alone: the same built experiment stepped by
``harness.loop.trajectory`` with no observer. The launcher's two workers each run two
jobs: a worker's first job also pays for loading the harness into the worker, the
second finds it loaded, as all but the first two of a study's jobs do. Figures:

- the loop alone (s for the whole run), in one process with the machine otherwise idle,
  and in two processes at once (one per core, as the sweep's two jobs run): what sharing
  the machine costs the loop by itself; numba on one thread, as in a sweep's job;
- the cost of a job: ``ended_at - started_at`` of its ``job_status.json`` (build in the
  launcher's worker, fork, run with every observer, finalised log), the mean of the two
  jobs that started first (each its worker's first) and of the two that started last;
  once with an empty floor cache (each job computes its finite-N floors) and once with
  the floors cached (what most jobs of a study find: the floors depend on the target, N
  and the seed, not on the law);
- the sweep's wall time, from the command's start to its exit;
- the target: a job costs at most ``1.3`` times the loop alone plus 1.5 s, judged as the
  cost of the later jobs with the floors cached minus 1.3 times the loop, at most 1.5 s
  (a time: in calibrations).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

from benchmarks.ab import cli
from benchmarks.report import ROOT, record

LOOP_FACTOR = 1.3
"""A job may cost this many times the loop alone, plus :data:`FIXED_TARGET_S`."""

FIXED_TARGET_S = 1.5
"""A job's cost beyond ``LOOP_FACTOR`` times the loop alone, at most (s)."""


def overrides(n_robots: int, seconds: float) -> list[str]:
    """The job's config: ``laws_n`` with the paper's law, ``n_robots`` robots."""
    return [
        "+experiment=laws_n",
        f"agents.n={n_robots}",
        "control=paper",
        f"sim.t_final={seconds}",
        "log.progress=off",
    ]


def loop_alone_s(n_robots: int, seconds: float) -> float:
    """Wall time (s) of the whole run's steps, the experiment built as the job builds it
    and stepped with no observer (after building, before the first step: the first
    steps' compiled-code loading is counted, as in a job)."""
    from harness.api import compose
    from harness.loop import trajectory
    from harness.runs.build import build

    cfg = compose(overrides(n_robots, seconds))
    exp = build(cfg)
    steps = round(seconds / exp.dt)
    loop = trajectory(exp, hold=True)
    t0 = time.perf_counter()
    for _ in range(steps + 1):
        next(loop)
    return time.perf_counter() - t0


def loop_alone_twice_s(n_robots: int, seconds: float) -> float:
    """The mean of :func:`loop_alone_s` in two processes started together (s)."""
    cmd = [sys.executable, "-m", "benchmarks.jobs", "--loop-only", f"--n={n_robots}"]
    cmd.append(f"--seconds={seconds}")
    procs = [subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [proc.communicate()[0] for proc in procs]
    if any(proc.returncode != 0 for proc in procs):
        raise RuntimeError("a loop-alone process failed")
    return sum(float(out.split()[-1]) for out in outs) / 2


def sweep(n_robots: int, seconds: float, where: Path, floors: Path) -> tuple[float, list[float]]:
    """Run the four-job sweep into ``where``; its wall time and each job's cost (s), in
    the order the jobs started."""
    cmd = [
        sys.executable,
        "-m",
        "experiments.closed_loop",
        "-m",
        *overrides(n_robots, seconds),
        "seed=0,1,2,3",
        f"hydra.sweep.dir={where}",
        f"log.floor_cache={floors}",
    ]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"the sweep failed ({done.returncode}): {done.stderr[-2000:]}")
    jobs = []
    for status in sorted(where.glob("*/job_status.json")):
        data = json.loads(status.read_text())
        if data.get("state") != "completed":
            raise RuntimeError(f"{status}: {data.get('state')} {data.get('reason')}")
        jobs.append((float(data["started_at"]), float(data["ended_at"])))
    if len(jobs) != 4:
        raise RuntimeError(f"{where}: {len(jobs)} jobs, expected 4")
    return wall, [end - start for start, end in sorted(jobs)]


def main(argv: list[str] | None = None) -> bool:
    """Time the loop alone and the two-job sweep; whether the target is met."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=1024, help="robots")
    parser.add_argument("--seconds", type=float, default=25.0, help="simulated s per job")
    parser.add_argument("--loop-only", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.n < 1 or not args.seconds > 0:
        parser.error("--n and --seconds must be positive")
    import numba

    numba.set_num_threads(1)  # as a sweep's job: one core each
    if args.loop_only:  # one of the two processes of loop_alone_twice_s
        with threadpool_limits(1):
            print(f"{loop_alone_s(args.n, args.seconds):.6f}")
        return True
    print(f"A sweep job of the laws_n kind (N = {args.n}, {args.seconds:g} s) against its loop:")
    with threadpool_limits(1):
        loop = loop_alone_s(args.n, args.seconds)
    record("loop alone (no observer), whole run", loop, "s")
    twice = loop_alone_twice_s(args.n, args.seconds)
    record("loop alone, two processes at once", twice, "s")
    record("loop alone, two at once / one", twice / loop, "x")
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        floors = Path(tmp) / "floors"
        for label in ("floors computed", "floors cached"):
            where = Path(tmp) / label.replace(" ", "_")
            wall, costs = sweep(args.n, args.seconds, where, floors)
            record(f"{label}: four-job sweep, wall time", wall, "s")
            for which, pair in (("first", costs[:2]), ("later", costs[2:])):
                cost = sum(pair) / 2
                name = f"{label}: a {which} job's cost (mean of 2)"
                record(name, cost, "s")
                record(f"{label}: a {which} job's cost / loop alone", cost / loop, "x")
                target = FIXED_TARGET_S if (label, which) == ("floors cached", "later") else None
                ok &= record(
                    f"{label}: a {which} job's cost - {LOOP_FACTOR} x loop alone",
                    cost - LOOP_FACTOR * loop,
                    "s",
                    target,
                )
    return ok


if __name__ == "__main__":
    raise SystemExit(cli(main, "benchmarks.jobs"))
