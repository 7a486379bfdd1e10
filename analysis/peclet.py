"""Cell Peclet numbers of the applied velocity, from a sweep's logs.

    python -m analysis.peclet SWEEP_DIR [--at T]

For every job below ``SWEEP_DIR`` (a directory holding ``run.mcap``): the logged
velocity field ``/fields/velocity`` (cell centres, length / s) at the last logged time,
or at the first logged time at or after ``--at`` seconds, and its cell Peclet number

    Pe = max(|v_x| dx, |v_y| dy) / sigma        (dimensionless, per cell),

``dx``, ``dy`` the logged cell size (length) and ``sigma`` the logged
``dynamics.sigma`` (length^2 / s). Where ``Pe > 2`` the Scharfetter-Gummel fluxes of
:mod:`harness.fokker_planck` are upwind-dominated: their numerical diffusion, about
``|v| dx / 2``, exceeds ``sigma``. Prints, per grid size (the logged ``grid.n``, or
``grid.nx``), the median and the 90th percentile of ``Pe`` over the cells of all its
jobs, the fraction of cells above 2, and the number of jobs. Reads only the logs.
Exit status 2 when there is no readable log with a velocity field.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from analysis.configs import flatten, logged_config
from analysis.load import LogError, load_run

UPWIND_PECLET = 2.0
"""Cell Peclet number above which the Scharfetter-Gummel flux is upwind-dominated."""


def cell_peclet(velocity: np.ndarray, cell_size: tuple[float, float], sigma: float) -> np.ndarray:
    """``max(|v_x| dx, |v_y| dy) / sigma`` per cell for cell-centred ``velocity`` of shape
    ``(2, ny, nx)`` (length / s), ``cell_size = (dx, dy)`` (length), ``sigma > 0``
    (length^2 / s).

    Raises:
        ValueError: ``sigma`` is not positive and finite, or ``velocity`` has another shape.
    """
    if not (np.isfinite(sigma) and sigma > 0.0):
        raise ValueError(f"sigma must be positive and finite, got {sigma}")
    v = np.asarray(velocity, dtype=float)
    if v.ndim != 3 or v.shape[0] != 2:
        raise ValueError(f"velocity must have shape (2, ny, nx), got {v.shape}")
    dx, dy = cell_size
    return np.maximum(np.abs(v[0]) * dx, np.abs(v[1]) * dy) / sigma


def summary(pe: np.ndarray) -> tuple[float, float, float]:
    """Median, 90th percentile and fraction above :data:`UPWIND_PECLET` of ``pe``."""
    flat = np.asarray(pe, dtype=float).ravel()
    return (
        float(np.median(flat)),
        float(np.percentile(flat, 90)),
        float(np.mean(flat > UPWIND_PECLET)),
    )


def job_peclet(path: Path, at: float | None) -> tuple[object, np.ndarray, float]:
    """``(grid size, Pe per cell, time of the field in s)`` of the job logged at ``path``.

    Raises:
        LogError: the log cannot be read.
        KeyError: it has no velocity field or no ``dynamics.sigma``.
        ValueError: no field was logged at or after ``at``.
    """
    run = load_run(path, topics={"/fields/velocity"})
    flat = flatten(logged_config(run))
    raw = flat["dynamics.sigma"]
    if isinstance(raw, bool) or not isinstance(raw, (int, float, str)):
        raise ValueError(f"dynamics.sigma={raw!r} is not a number")
    sigma = float(raw)
    series = run.fields["/fields/velocity"]
    times = np.asarray(series.t, dtype=float)
    if at is None:
        index = times.size - 1
    else:
        later = np.nonzero(times >= at)[0]
        if later.size == 0:
            raise ValueError(f"no velocity field at or after t = {at} s (last {times[-1]} s)")
        index = int(later[0])
    dx, dy = series.cell_size
    size = flat.get("grid.n", flat.get("grid.nx", "?"))
    if not isinstance(size, (int, float, str)):
        size = repr(size)  # a foreign value: shown as it is
    pe = cell_peclet(series.values[index], (float(dx), float(dy)), sigma)
    return size, pe, float(times[index])


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    parser = argparse.ArgumentParser(description="Cell Peclet numbers from a sweep's logs.")
    parser.add_argument("sweep_dir", type=Path)
    parser.add_argument("--at", type=float, default=None, help="time (s); default: last field")
    args = parser.parse_args(argv)
    logs = sorted(args.sweep_dir.rglob("run.mcap")) if args.sweep_dir.is_dir() else []
    groups: dict[object, list[np.ndarray]] = defaultdict(list)
    times: dict[object, set[float]] = defaultdict(set)
    for log in logs:
        try:
            size, pe, t = job_peclet(log, args.at)
        except (LogError, KeyError, ValueError) as err:
            print(f"warning: {log}: {err}", file=sys.stderr)
            continue
        groups[size].append(pe.ravel())
        times[size].add(t)
    if not groups:
        print(f"error: no readable log with a velocity field below {args.sweep_dir}",
              file=sys.stderr)  # fmt: skip
        return 2
    print("cell Peclet number max(|v_x| dx, |v_y| dy) / sigma of the logged velocity:")
    for size in sorted(groups, key=lambda s: (str(type(s)), s)):
        median, p90, upwind = summary(np.concatenate(groups[size]))
        print(f"  n = {size}: median {median:.3g}, 90th percentile {p90:.3g}, "
              f"above {UPWIND_PECLET:g} on {100 * upwind:.1f} % of cells "
              f"({len(groups[size])} jobs, t = "
              f"{', '.join(f'{t:g}' for t in sorted(times[size]))} s)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
