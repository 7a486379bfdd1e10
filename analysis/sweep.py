"""Analyse a sweep from its logs: a tidy CSV and the study's figures.

    python -m analysis.sweep SWEEP_DIR [--out DIR] [--tail 0.25] [--mixed-code]

Reads every job directory below ``SWEEP_DIR`` (one holding a ``run.mcap``, a
``job_status.json`` or a ``.hydra/``; a job without a readable log counts as not
completed, with its reason), and only the log: its ``config`` record (the resolved
config), its ``choices`` record (the option of each config group), its ``status`` and
``theory`` records and its ``/metrics``
(:mod:`analysis.rows`). Writes ``sweep.csv`` (one row per job; every config key whose
value differs between the jobs is a column, ``law`` holds the option of the control
law and ``plant``, ``estimator``, ... the options of the other config groups when they
differ) and ``sweep_aggregated.csv`` (one row per point: jobs that differ only in
``seed``, with the mean over the seeds and the 95 % Student-t interval of every
statistic; :func:`analysis.rows.points`), and the figure the study declares. The
statistics and their units: :mod:`analysis.run_stats`.

Declaration (:mod:`analysis.declaration`). A study preset (``conf/experiment/*.yaml``)
declares its analysis in a top-level ``analysis`` block, which every job logs with its
config::

    analysis:
      figure: iss_gain                    # a name of FIGURES
      primary: [law, estimator.delta]     # the keys the study varies (besides seed)
      tail: 0.25                          # tail fraction of each run

``primary`` (default: every varied key but ``seed``) lists the keys that make the
study's points: config keys, ``law`` (the option of group ``control``) or the name of
another config group (``plant``: its option); jobs that differ in any other key (but
``seed``) are more than one sweep, and the analysis refuses them. ``tail`` (default
0.25) is the fraction of each run the tail statistics use; ``--tail`` overrides it. An
unknown figure name or declaration key, or jobs that declare different analyses, stop
the analysis with one line (exit status 2).

The figures (:data:`FIGURES`), each drawing against the primary keys it names:

* ``convergence`` (:mod:`analysis.convergence`), the generic figure (a sweep without a
  declaration, typed on the command line, gets it), and ``iss_gain`` (``law``,
  ``estimator.delta``);
* ``agents_n`` (``agents.n``), ``debias_n`` (``agents.n``, ``kde.debias``),
  ``conv_grid_agents`` (``grid.n``) and ``distributed_r`` (``estimator.radius``):
  the agent-level studies (:mod:`analysis.agent_figures`);
* ``laws_n``, ``laws_iss``, ``heat_floor``, ``laws_noise``: the law studies
  (:mod:`analysis.laws`);
* ``robots`` (``plant``, ``law``) and ``link`` (``link.period``, ``link.latency``,
  ``link.loss``): the robot and link studies (:mod:`analysis.robots`);
* ``distributed_frontier``: the decentralised loop's frontier
  (:mod:`analysis.frontier`);
* ``domains`` (``domain``, ``law``, ``agents.n``): every law on domains with obstacles
  (:mod:`analysis.domains_study`).

Law order. Figures and tables show the laws in alphabetical order of their options (the
order in which ``control=glob(*)`` runs them), each under its option name.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path
from typing import Any

from analysis.agent_figures import (
    draw_agents_n,
    draw_conv_grid_agents,
    draw_debias_n,
    draw_distributed_r,
)
from analysis.convergence import draw_convergence, draw_iss_gain
from analysis.declaration import (
    DEFAULT_TAIL,
    Declaration,
    DeclarationError,
    Figure,
    Study,
    study_declaration,
)
from analysis.domains_study import draw_domains
from analysis.frontier import FRONTIER_KEYS, draw_frontier
from analysis.laws import draw_heat_floor, draw_laws_iss, draw_laws_n, draw_laws_noise
from analysis.robots import LINK_KEYS, draw_link, draw_robots
from analysis.rows import (
    analyse,
    config_of,
    mixed,
    mixed_code,
    points,
    varied,
    write_csv,
    write_points,
)
from analysis.run_stats import SweepWarning

FIGURES: dict[str, Figure] = {
    "iss_gain": Figure(draw_iss_gain, ("law", "estimator.delta")),
    "laws_n": Figure(draw_laws_n, ("law", "agents.n")),
    "laws_iss": Figure(draw_laws_iss, ("law", "estimator.shape", "estimator.delta")),
    "heat_floor": Figure(
        draw_heat_floor, ("control.density_floor", "estimator.shape", "estimator.delta")
    ),
    "laws_noise": Figure(draw_laws_noise, ("law", "agents.localisation_noise")),
    "robots": Figure(draw_robots, ("plant", "law")),
    "link": Figure(draw_link, LINK_KEYS),
    "debias_n": Figure(draw_debias_n, ("agents.n", "kde.debias")),
    "agents_n": Figure(draw_agents_n, ("agents.n",)),
    "distributed_r": Figure(draw_distributed_r, ("estimator.radius",)),
    "distributed_frontier": Figure(
        draw_frontier, FRONTIER_KEYS, ("estimator.k_nearest", "estimator.band_limit")
    ),
    "conv_grid_agents": Figure(draw_conv_grid_agents, ("grid.n",)),
    "domains": Figure(draw_domains, ("domain", "law", "agents.n")),
    "convergence": Figure(draw_convergence),
}
"""The figures a study can declare (``analysis.figure``), by name."""


def sweep_declaration(rows: list[dict[str, Any]]) -> Declaration:
    """The one declaration of the jobs whose config was read, its figure one of
    :data:`FIGURES` (:func:`analysis.declaration.study_declaration`).
    """
    return study_declaration(((r["dir"], config_of(r)) for r in rows), FIGURES)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    parser = argparse.ArgumentParser(description="CSV and figures of a sweep, from its logs.")
    parser.add_argument("sweep_dir", type=Path)
    parser.add_argument("--out", type=Path, default=None, help="default: SWEEP_DIR/analysis")
    parser.add_argument(
        "--tail",
        type=float,
        default=None,
        help=f"tail fraction of each run (default: the declared one, else {DEFAULT_TAIL})",
    )
    parser.add_argument(
        "--mixed-code",
        action="store_true",
        help="pool logs made by different code (commit, local changes, package versions)",
    )
    args = parser.parse_args(argv)
    if not args.sweep_dir.is_dir():
        print(f"error: no sweep directory at {args.sweep_dir}", file=sys.stderr)
        return 2
    if args.tail is not None and not 0 < args.tail <= 1:
        print(f"error: --tail must be in (0, 1], got {args.tail}", file=sys.stderr)
        return 2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SweepWarning)
        try:
            rows, series = analyse(args.sweep_dir, args.tail)
            study = sweep_declaration(rows)
        except DeclarationError as err:
            problem: DeclarationError | None = err
        else:
            problem = None
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    if problem is not None:
        print(f"error: {args.sweep_dir}: {problem}", file=sys.stderr)
        return 2
    if not rows:
        print(f"error: no job directory below {args.sweep_dir}", file=sys.stderr)
        return 2
    codes = mixed_code(rows)
    if codes and not args.mixed_code:
        print(
            f"error: {args.sweep_dir}: the logs were made by different code ("
            + ", ".join(f"{c}: {n} jobs" for c, n in sorted(codes.items()))
            + "; rerun the sweep into the same directory to bring every job to the same "
            "code, or pass --mixed-code)",
            file=sys.stderr,
        )
        return 2
    keys = varied(rows)
    usable = [r for r in rows if "phi_tail_sup" in r]
    figure = FIGURES[study.figure]
    if study.primary is None:  # a sweep of its own axes: every varied key but the seed
        primary = [k for k in keys if k != "seed"]
    else:
        primary = list(study.primary)
    missing = [k for k in figure.needs if k not in primary]
    if missing:
        print(
            f"error: {args.sweep_dir}: analysis.primary={primary!r}: the figure "
            f"{study.figure} draws against {', '.join(missing)} (list it)",
            file=sys.stderr,
        )
        return 2
    extra = mixed(rows, [*primary, *figure.also])
    if extra:
        print(
            f"error: {args.sweep_dir} holds more than one sweep: besides "
            f"{', '.join(primary)} the jobs differ in {', '.join(extra)} "
            "(analyse each sweep from a directory of its own)",
            file=sys.stderr,
        )
        return 2
    out = args.out or args.sweep_dir / "analysis"
    out.mkdir(parents=True, exist_ok=True)
    write_csv(rows, out / "sweep.csv")
    write_points(points(rows), out / "sweep_aggregated.csv")
    written = [out / "sweep.csv", out / "sweep_aggregated.csv"]
    if usable:
        tail = args.tail if args.tail is not None else study.tail
        written += figure.draw(Study(usable, series, keys, out, args.sweep_dir, tail))
    bad = [r for r in rows if r.get("state") != "completed"]
    print(f"{len(rows)} jobs, {len(bad)} not completed")
    for p in written:
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
