"""Write the regression logs of a checkout, or compare two sets of them.

    python scripts/regression_logs.py run OUT [--repo DIR] [--only NAME ...]
    python scripts/regression_logs.py diff OLD NEW

``run`` writes ``OUT/NAME/run.mcap`` for: the two runs of ``make reproduce`` (the
paper's experiment and the mean-field check), a decentralised smoke run, a short run of
unicycles behind a lossy, late link, and the first
job of every study preset in ``conf/experiment/`` (the first value of each sweep axis,
as Hydra's basic sweeper orders them: Hydra's own parser reads each axis, so
``glob(*)`` gives the first of the group's options in alphabetical order, as the sweep
does), each run once from the checkout ``--repo``
(default: this one) with the Python running this script. ``diff`` compares every log of
``OLD`` with the one of the same name in ``NEW`` by ``python -m analysis.diff``
(messages byte for byte; metadata may differ) and exits 1 when one differs or is
missing. A refactoring that must not change results runs ``run`` on the commit before
it and on the change, then ``diff``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPRODUCE = {
    "reproduce": [],
    "reproduce_meanfield": ["plant=meanfield", "estimator=exact", "log.field_every=100"],
    "distributed_smoke": ["+experiment=smoke", "estimator=distributed"],
    "unicycles_link": [
        "+experiment=smoke",
        "plant=unicycles",
        "link.period=0.04",
        "link.latency=0.02",
        "link.loss=0.3",
        "sim.t_final=1",
    ],
}


def axes(repo: Path, params: dict[str, object]) -> list[list[str]]:
    """The sweep axes of ``params`` (a preset's ``hydra.sweeper.params``) as Hydra's
    basic sweeper expands them: per key, the overrides ``key=value`` in its order (a
    choice sweep in the order written, ``glob(...)`` over the options of the group in
    ``repo/conf`` in alphabetical order, a range in its order).
    """
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(repo / "conf"), version_base="1.3"):
            loader = GlobalHydra.instance().config_loader()
            parser = OverridesParser.create(config_loader=loader)
            out = []
            for override in parser.parse_overrides([f"{k}={v}" for k, v in params.items()]):
                key = override.get_key_element()
                if override.is_sweep_override():
                    out.append([f"{key}={v}" for v in override.sweep_string_iterator()])
                else:
                    out.append([f"{key}={override.get_value_element_as_str()}"])
            return out
    finally:
        GlobalHydra.instance().clear()


def first_jobs(repo: Path) -> dict[str, list[str]]:
    """``{study: overrides}`` of the first job of every study preset: the first value of
    each of its sweep axes (:func:`axes`).
    """
    jobs = {}
    for path in sorted((repo / "conf" / "experiment").glob("*.yaml")):
        preset = yaml.safe_load(path.read_text()) or {}
        params = (((preset.get("hydra") or {}).get("sweeper") or {}).get("params")) or {}
        if not params:
            continue
        first = [axis[0] for axis in axes(repo, params)]
        jobs[path.stem] = [f"+experiment={path.stem}", *first, "hydra.mode=RUN"]
    return jobs


def run(out: Path, repo: Path, only: list[str]) -> int:
    """Run every regression job of ``repo`` into ``out``; the number that failed."""
    jobs = {**REPRODUCE, **first_jobs(repo)}
    failed = 0
    for name, overrides in jobs.items():
        if only and name not in only:
            continue
        run_dir = (out / name).absolute()
        if (run_dir / "run.mcap").exists():
            print(f"{name}: exists, skipped", flush=True)
            continue
        cmd = [sys.executable, "-m", "experiments.closed_loop", *overrides]
        cmd += [f"hydra.run.dir={run_dir}", "log.progress=off"]
        t0 = time.perf_counter()
        code = subprocess.run(cmd, cwd=repo).returncode
        print(f"{name}: exit {code} in {time.perf_counter() - t0:.0f} s", flush=True)
        failed += code != 0
    return failed


def diff(old: Path, new: Path) -> int:
    """Compare the logs of ``old`` with those of ``new``; 1 when one differs."""
    status = 0
    for log in sorted(old.glob("*/run.mcap")):
        other = new / log.parent.name / "run.mcap"
        if not other.exists():
            print(f"{log.parent.name}: missing in {new}")
            status = 1
            continue
        res = subprocess.run(
            [sys.executable, "-m", "analysis.diff", str(log), str(other)],
            capture_output=True,
            text=True,
        )
        print(f"{log.parent.name}: {res.stdout.strip() or res.stderr.strip()}")
        status |= res.returncode != 0
    return status


def main() -> int:
    """Entry point."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_run = sub.add_parser("run")
    p_run.add_argument("out", type=Path)
    p_run.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[1])
    p_run.add_argument("--only", nargs="*", default=[])
    p_diff = sub.add_parser("diff")
    p_diff.add_argument("old", type=Path)
    p_diff.add_argument("new", type=Path)
    args = parser.parse_args()
    if args.command == "run":
        return 1 if run(args.out, args.repo.resolve(), args.only) else 0
    return diff(args.old, args.new)


if __name__ == "__main__":
    sys.exit(main())
