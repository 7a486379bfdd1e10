"""The fast density filter's gain against the grid, with the band's correlations in its
variance prediction and with a white per-cell prediction for comparison.

    python -m benchmarks.filter_gain [--steps 300] [--seed 0]

The paper's loop as the app builds it (robots, KDE, both fast filters, the paper's law;
``grid.n`` overridden), run for ``--steps`` steps of 0.01 s; printed per grid size: the
mean over the cells of the density filter's posterior gain ``d+ / r`` (dimensionless;
``d+`` the posterior variance, ``r`` the KDE's variance, both 1 / length^4) and of its
prior ``d- / r``. "band" is the harness's prediction ``diag(F1 S R S F1^T)``; "white"
the same run with ``R = I`` (``LocalFilters.correlations = None``, a white per-cell
prediction), whose gain falls with the grid because a white covariance's
grid-scale modes diffuse away at ``8 dt sigma / dx^2`` per step. Not a speed benchmark.
"""

from __future__ import annotations

import argparse

import numpy as np
from threadpoolctl import threadpool_limits

from harness.api import compose as compose_config
from harness.estimators.filters.engines import LocalEngine
from harness.loop import trajectory
from harness.runs.build import build


def mean_gains(n: int, steps: int, seed: int, white: bool) -> tuple[float, float]:
    """``(mean d+ / r, mean d- / r)`` of the density filter after ``steps`` steps."""
    parts = build(compose_config([f"grid.n={n}", "filter.engine=local", f"seed={seed}"]))
    engine = parts.estimator.engine  # type: ignore[attr-defined]
    assert isinstance(engine, LocalEngine)
    filters = engine.filters
    if white:
        filters.correlations = None
    loop = trajectory(parts, hold=True)
    next(loop)
    for _ in range(steps):
        rec, _ = next(loop)
    assert rec.measurement is not None and filters.d is not None and filters.d_prior is not None
    r = filters.measurement.density_variance(rec.measurement.p)
    return float(np.mean(filters.d / r)), float(np.mean(filters.d_prior / r))


def main() -> None:
    """Print the gains per grid size for both predictions."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"density filter gain after {args.steps} steps (seed {args.seed}), mean over cells:")
    heads = ("band d+/r", "band d-/r", "white d+/r", "white d-/r")
    print(f"  {'n':>4s} " + " ".join(f"{h:>11s}" for h in heads))
    with threadpool_limits(1):
        for n in (32, 64, 128, 256):
            band = mean_gains(n, args.steps, args.seed, white=False)
            white = mean_gains(n, args.steps, args.seed, white=True)
            print(f"  {n:4d} " + " ".join(f"{v:11.4f}" for v in (*band, *white)))


if __name__ == "__main__":
    main()
