"""What a robot's gradient estimate changes in the decentralised loop, against the
gradient filter: `nice -n 10 python -m benchmarks.gradient_filter` (``--help`` for
options; about three minutes on a shared 2-core machine with the defaults).

The setting is the one where the question is clean: a complete graph (``radius = 2``,
``eps = 1/N``, one consensus round is exact), where every robot's density estimate is
the centralised density filter's on the exact KDE (tested to 1e-10,
``tests/test_distributed.py``), so one :class:`harness.estimators.filters.local.LocalFilters`
stands for every robot. The gradient a robot's law may use:

* ``filter``: the centralised gradient filter's ``q_hat`` (on the complete graph, what a
  gradient filter per robot on the tracked analytic kernel gradient computes);
* ``grid``: ``G p_hat``, ``estimator.gradient=grid``;
* ``fourth_order``: ``G_4 p_hat``, ``estimator.gradient=fourth_order``
  (:func:`harness.grid.grid_gradient`).

Paper scale (``h``, ``dt``, ``alpha``, ``sigma`` of :mod:`benchmarks.distributed`), ``n x
n`` grid, robots from the box ``[0.15, 0.85]^2``, every filter without the band limit (as
in ``estimator=distributed``), BLAS and numba on one thread.

Closed loops: for each seed, one loop driven by each gradient from the same robots
with the same noise; ``swarm_l2 = ||K_h mu_N - K_h p_*||`` (:mod:`harness.observers.swarm_metrics`,
exact KDE) at the end and its mean over the last fifth. Along the loop driven by the
gradient filter, every 10 steps, for each gradient ``q``:

* the law's command at the robots (eq. ``modified density feedback law using
  estimates``), ``rms_i |v_i(q) - v_i(q_filter)| / rms_i |v_i(q_filter)|``;
* ``||q - grad p_KDE|| / ||grad p_KDE||`` against the exact KDE's analytic gradient
  (what the gradient filter observes) and ``||q - grad(K_h p_inf)|| / ||grad(K_h
  p_inf)||`` against the mean-field limit's (``p_inf`` the loop's ``N -> infinity``
  limit, as the agents plant's ``p_true``).

Cost: wall and process CPU time of the law at the robots with ``G`` and with ``G_4``
(:func:`harness.control.own_estimates.own_velocities`, the only part of the decentralised loop the
option changes), and of one step of the centralised filters, medians of ``--repeats``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numba
import numpy as np
from threadpoolctl import threadpool_limits

from benchmarks.distributed import ALPHA, DT, SIGMA, H
from harness.control.own_estimates import own_velocities
from harness.control.paper import PaperControl, paper_law
from harness.estimators.filters.common import FilterSettings, MeasurementModel
from harness.estimators.filters.local import LocalFilters
from harness.estimators.kde import KDE
from harness.estimators.smoothing import Smoother, smoothed_density
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid, grid_gradient
from harness.plants.agents import Swarm
from harness.targets.densities import DEFAULT_TARGET, Box, Target
from harness.velocity import interpolate

SETTINGS = FilterSettings(band_limit=np.inf)  # estimator=distributed's filters and reference

GRADIENTS: dict[str, Callable[[Grid, np.ndarray, np.ndarray], np.ndarray]] = {
    "filter": lambda g, p, q: q,
    "grid": lambda g, p, q: grid_gradient(g, p, 2),
    "fourth_order": lambda g, p, q: grid_gradient(g, p, 4),
}
"""``(grid, p_hat, q_filter) -> q``: the gradient each loop's law uses."""


def _rms(v: np.ndarray) -> float:
    """``sqrt(mean_i |v_i|^2)`` of velocities ``(2, N)``."""
    return float(np.sqrt(np.mean(np.sum(v * v, axis=0))))


def _relative(g: Grid, q: np.ndarray, truth: np.ndarray) -> float:
    """``||q - truth|| / ||truth||`` (grid L2 of the vector's length)."""
    return g.l2(np.hypot(*(q - truth))) / g.l2(np.hypot(*truth))


def closed_loop(
    n_robots: int, n: int, steps: int, drive: str, seed: int, every: int = 10
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The complete-graph loop whose law uses the gradient ``drive``: ``swarm_l2`` per
    step and, every ``every`` steps, the figures of the module docstring for each
    gradient (keys ``cmd_<name>``, ``kde_<name>``, ``inf_<name>``).
    """
    g = Grid.square(n)
    rng = np.random.default_rng(seed)
    target = Target.from_density(g, DEFAULT_TARGET)
    fp = FokkerPlanck(g, SIGMA)
    box = Box()
    swarm = Swarm(g, box.sample(n_robots, g, rng), SIGMA)
    pos = swarm.positions  # moved in place by the robot step
    kde = KDE(g, H, method="exact")
    smoothed = smoothed_density(DEFAULT_TARGET, g, H)
    smoother = Smoother(g, H)
    central = LocalFilters(g, SIGMA, DT, MeasurementModel(n_robots, H, SETTINGS))
    p_kde, grad_kde = kde.exact(pos)
    p_c, q_c = central.initialize(p_kde, grad_kde)
    p_inf = box.on_grid(g)
    l2 = np.empty(steps)
    figures: dict[str, list[float]] = {}

    def command(q: np.ndarray) -> np.ndarray:
        # every robot's own command is the common field's interpolant (complete graph)
        return interpolate(g, paper_law(p_c, q, target, ALPHA, SIGMA).centres, pos)

    for step in range(steps):
        qs = {name: gradient(g, p_c, q_c) for name, gradient in GRADIENTS.items()}
        s_inf, grad_inf = smoother(p_inf)
        if step % every == 0:
            v_filter = command(q_c)
            for name, q in qs.items():
                diff = _rms(command(q) - v_filter) / _rms(v_filter)
                figures.setdefault(f"cmd_{name}", []).append(diff)
                figures.setdefault(f"kde_{name}", []).append(_relative(g, q, grad_kde))
                figures.setdefault(f"inf_{name}", []).append(_relative(g, q, grad_inf))
        field = paper_law(p_c, qs[drive], target, ALPHA, SIGMA)
        swarm.step_robots(interpolate(g, field.centres, pos), DT, rng)
        p_inf = fp.step(p_inf, paper_law(s_inf, grad_inf, target, ALPHA, SIGMA), DT)
        p_kde, grad_kde = kde.exact(pos)
        p_c, q_c = central.step(p_kde, grad_kde, field, fp.matrix(field))
        l2[step] = g.l2(p_kde - smoothed)  # swarm_l2 of the exact KDE
    return l2, {k: np.asarray(v) for k, v in figures.items()}


def costs(n_robots: int, n: int, repeats: int) -> dict[str, tuple[float, float]]:
    """Milliseconds ``(wall, cpu)``, medians over ``repeats``: the law at the robots with
    ``G`` and ``G_4`` (every robot holding its own ``(N, M)`` estimate), one step of the
    centralised filters.
    """
    g = Grid.square(n)
    rng = np.random.default_rng(0)
    target = Target.from_density(g, DEFAULT_TARGET)
    pos = Box().sample(n_robots, g, rng)
    kde = KDE(g, H, method="exact")
    p, grad = kde.exact(pos)
    p_hat = p.ravel() * (1.0 + 0.01 * rng.random((n_robots, g.size)))
    law = PaperControl(target, ALPHA, SIGMA).at_cells
    central = LocalFilters(g, SIGMA, DT, MeasurementModel(n_robots, H, SETTINGS))
    p_c, q_c = central.initialize(p, grad)
    field = paper_law(p_c, q_c, target, ALPHA, SIGMA)
    a = FokkerPlanck(g, SIGMA).matrix(field)
    parts: dict[str, Callable[[], object]] = {
        "law at the robots, G (grid)": lambda: own_velocities(g, law, p_hat, pos, order=2),
        "law at the robots, G_4 (fourth_order)": lambda: own_velocities(
            g, law, p_hat, pos, order=4
        ),
        "centralised filters, one step": lambda: central.step(p, grad, field, a),
    }
    out = {}
    for name, part in parts.items():
        part()  # compiled or cached on the first call
        wall, cpu = [], []
        for _ in range(repeats):
            w0, c0 = time.perf_counter(), time.process_time()
            part()
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
        out[name] = (1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu)))
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--robots", type=int, default=1024)
    parser.add_argument("--grid", type=int, default=30, help="cells per side")
    parser.add_argument("--seconds", type=float, default=40.0, help="simulated time per loop")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=50, help="timed calls per part")
    args = parser.parse_args()
    numba.set_num_threads(1)
    steps = round(args.seconds / DT)
    tail = max(1, steps // 5)
    floor = 1.0 / np.sqrt(4 * np.pi * args.robots * H**2)  # large-N mean, swarm_metrics.floors
    with threadpool_limits(1):
        t0 = time.perf_counter()
        print(
            f"N = {args.robots}, n = {args.grid}, complete graph, {args.seconds:g} s "
            f"({steps} steps), seeds 0..{args.seeds - 1}"
        )
        print(
            f"swarm_l2 at the end, mean over the last {tail * DT:g} s (finite-N floor of "
            f"independent samples about {floor:.3f}):"
        )
        tails: dict[str, list[float]] = {name: [] for name in GRADIENTS}
        figures: dict[str, list[np.ndarray]] = {}
        for seed in range(args.seeds):
            line = []
            for drive in GRADIENTS:
                l2, fig = closed_loop(args.robots, args.grid, steps, drive, seed)
                tails[drive].append(float(l2[-tail:].mean()))
                line.append(f"{drive} {l2[-1]:.4f}, {tails[drive][-1]:.4f}")
                if drive == "filter":
                    for key, values in fig.items():
                        figures.setdefault(key, []).append(values)
            print(f"  seed {seed}: " + ";  ".join(line))
        means = ", ".join(f"{name} {np.mean(v):.4f}" for name, v in tails.items())
        print(f"  tail means over seeds: {means}")
        print("Along the gradient filter's loop (every 10 steps, seeds pooled): median (10th "
              "to 90th percentile)")  # fmt: skip
        rows = (
            ("cmd", "rms |v(q) - v(q_filter)| / rms |v(q_filter)|"),
            ("kde", "||q - grad p_KDE|| / ||grad p_KDE||"),
            ("inf", "||q - grad K_h p_inf|| / ||grad K_h p_inf||"),
        )
        for key, label in rows:
            print(f"  {label}:")
            for name in GRADIENTS:
                x = np.concatenate(figures[f"{key}_{name}"])
                lo, med, hi = np.percentile(x, [10, 50, 90])
                print(f"    {name:<13s} {med:.3f} ({lo:.3f} to {hi:.3f})")
        print(f"Cost per step (N = {args.robots}, medians of {args.repeats}):")
        for name, (wall, cpu) in costs(args.robots, args.grid, args.repeats).items():
            print(f"  {name:<40s} wall {wall:8.2f} ms   cpu {cpu:8.2f} ms")
        print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
