"""The benchmark of the field's laws: tune every law per scenario, re-run the chosen
points on fresh seeds, and write the leaderboard.

    python -m experiments.benchmark --tier quick                # make benchmark-quick
    python -m experiments.benchmark --tier full --launcher hydra/launcher=submitit_slurm
    python -m experiments.benchmark --tier quick --searchpath my_conf  # your own laws too

A tier is ``conf/benchmark/NAME.yaml`` or a YAML file of your own
(:mod:`harness.benchmark.plan`). Runs go through the Hydra launcher the ``--launcher``
overrides choose (joblib on every core by default). Run the same command again to
resume a killed benchmark: finished runs and trials are not repeated. The leaderboard
(:mod:`analysis.leaderboard`) is written at the end unless ``--no-page``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    """Run a benchmark tier; the exit status is 0 when it finished, 2 for a tier or
    argument that cannot run, 130 when interrupted (run again to resume).
    """
    parser = argparse.ArgumentParser(
        prog="python -m experiments.benchmark", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--tier", default="quick", help="a tier of conf/benchmark/ or a YAML path")
    parser.add_argument(
        "--out", type=Path, help="the benchmark's directory (outputs/benchmark/TIER)"
    )
    parser.add_argument(
        "--launcher",
        action="append",
        default=[],
        metavar="OVERRIDE",
        help="a Hydra override choosing or setting the launcher (repeatable)",
    )
    parser.add_argument(
        "--searchpath",
        action="append",
        default=[],
        type=Path,
        metavar="DIR",
        help="a config directory of your own laws or scenarios (repeatable)",
    )
    parser.add_argument("--page", type=Path, help="write the leaderboard page here")
    parser.add_argument("--no-page", action="store_true", help="do not write the leaderboard")
    parser.add_argument("--command", help="the command to name on the page (default: this one)")
    args = parser.parse_args(argv)

    from harness.api import options
    from harness.benchmark.driver import Benchmark, LaunchError, Settings
    from harness.benchmark.plan import PlanError, read_plan

    for d in args.searchpath:
        if not d.is_dir():
            print(f"--searchpath {d}: not a directory", file=sys.stderr)
            return 2
    extra = [f"hydra.searchpath=[{','.join(f'file://{d.resolve()}' for d in args.searchpath)}]"]
    extra = extra if args.searchpath else []
    try:
        plan = read_plan(args.tier, options("scenario", extra), options("control", extra))
    except PlanError as err:
        print(f"invalid tier: {err}", file=sys.stderr)
        return 2
    out = args.out or Path("outputs") / "benchmark" / plan.name
    settings = Settings(out=out, launcher=list(args.launcher), searchpath=list(args.searchpath))
    try:
        Benchmark(plan, settings).run()
    except KeyboardInterrupt as err:
        print(f"interrupted ({err or 'Ctrl-C'}): run the same command to resume", file=sys.stderr)
        return 130
    except (LaunchError, RuntimeError, OSError) as err:
        print(f"benchmark stopped: {err}", file=sys.stderr)
        return 1
    if not args.no_page:
        from analysis.leaderboard import main as leaderboard

        page = ["--page", str(args.page)] if args.page else []
        command = args.command or " ".join(["python -m experiments.benchmark", *sys.argv[1:]])
        return leaderboard([str(out), *page, "--command", command])
    return 0


if __name__ == "__main__":
    sys.exit(main())
