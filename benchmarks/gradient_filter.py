"""What the per-robot gradient filter changes in the decentralised loop's command, and
what it costs: `nice -n 10 python -m benchmarks.gradient_filter` (``--help`` for options;
about two minutes on a shared 2-core machine with the defaults).

The setting is the one where the question is clean: a complete graph (``radius = 2``,
``eps = 1/N``, one consensus round is exact), where every robot's estimate is the
centralised filters' on the exact KDE. Then ``estimator.gradient=filter`` gives every
robot the centralised gradient filter's ``q_hat`` (tested to 1e-10 against
:class:`harness.filters.local.LocalFilters`), and ``estimator.gradient=grid`` gives it
``G p_hat``, the grid gradient of the same density estimate. The two options differ in
nothing else. Paper scale (``h``, ``dt``, ``alpha``, ``sigma`` of
:mod:`benchmarks.distributed`), robots from the box ``[0.15, 0.85]^2``, every filter
without the band limit (as in ``estimator=distributed``), BLAS and numba on one thread.

Part 1, along one trajectory (the loop driven by the gradient filter, i.e. the
centralised loop with its gradient filter). Per step, with ``p_hat`` the common density
estimate and ``q_f`` the gradient filter's estimate:

* the gradient estimates' relative L2 errors ``||q - grad p_KDE|| / ||grad p_KDE||``
  against the exact KDE's analytic gradient (what the gradient filter observes) and
  ``||q - grad(K_h p_inf)|| / ||grad(K_h p_inf)||`` against the mean-field limit's
  smoothed gradient (``p_inf`` the ``N -> infinity`` limit of the loop, as the agents
  plant's ``p_true``), for ``q = q_f`` and ``q = G p_hat``;
* the law's command at the robots (eq. ``modified density feedback law using
  estimates``, :func:`harness.robot_law.own_velocities`) with either gradient:
  ``rms_i |v_grid,i - v_filter,i|`` relative to ``rms_i |v_filter,i|`` and to the RMS of
  its feedback part ``-alpha grad(p_hat / p_*)`` (the part the gradient enters);
* wall and process CPU time per step of each option's per-robot estimator step
  (:class:`harness.decentralised.RobotEstimators`: consensus and the robots' filters),
  medians after two steps; ``--per-robot-filter`` also runs ``gradient="filter"`` itself
  and checks it against the centralised gradient filter (available while that option
  exists).

Part 2, closed loops: the loop driven by the grid gradient and the loop driven by the
gradient filter from the same robots with the same noise, ``--seeds`` seeds, ``--seconds``
of simulated time; ``swarm_l2 = ||K_h mu_N - K_h p_*||`` (:mod:`harness.swarm_metrics`)
at the end and its mean over the last fifth.
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np
from threadpoolctl import threadpool_limits

from benchmarks.distributed import ALPHA, DT, SIGMA, H
from harness.agents import Swarm, interpolate
from harness.control import PaperControl, paper_law
from harness.decentralised import RobotEstimators
from harness.densities import DEFAULT_TARGET, Box, Target
from harness.filters.common import FilterSettings, MeasurementModel
from harness.filters.local import LocalFilters
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.kde import KDE
from harness.robot_law import own_velocities
from harness.smoothing import Smoother
from harness.swarm_metrics import smoothed_density

SETTINGS = FilterSettings(band_limit=np.inf)  # estimator=distributed's filters and reference


def _rms(v: np.ndarray) -> float:
    """``sqrt(mean_i |v_i|^2)`` of velocities ``(2, N)``."""
    return float(np.sqrt(np.mean(np.sum(v * v, axis=0))))


def _relative(g: Grid, q: np.ndarray, truth: np.ndarray) -> float:
    """``||q - truth|| / ||truth||`` (grid L2, both components)."""
    q = q.reshape(2, *g.shape)
    err = np.hypot(*(q - truth))
    return g.l2(err) / g.l2(np.hypot(*truth))


def trajectory(
    n_robots: int, n: int, steps: int, per_robot_filter: bool, seed: int = 0
) -> dict[str, np.ndarray]:
    """Part 1 of the module docstring: per-step figures along the gradient filter's loop."""
    g = Grid.square(n)
    rng = np.random.default_rng(seed)
    target = Target.from_density(g, DEFAULT_TARGET)
    fp = FokkerPlanck(g, SIGMA)
    box = Box()
    swarm = Swarm(g, box.sample(n_robots, g, rng), SIGMA)
    pos = swarm.positions  # moved in place by the robot step
    law = PaperControl(target, ALPHA, SIGMA).at_cells
    drift = PaperControl(target, 2 * ALPHA, SIGMA).at_cells  # feedback part by linearity
    model = MeasurementModel(n_robots, H, SETTINGS)
    central = LocalFilters(g, SIGMA, DT, model)
    smoother = Smoother(g, H)
    p_inf = box.on_grid(g)

    def robots(gradient: str) -> RobotEstimators:
        return RobotEstimators(g, DT, n_robots, H, SETTINGS, radius=2.0, gradient=gradient,
                               initial_rounds=1)  # fmt: skip

    options = {"grid": robots("grid")}
    if per_robot_filter:
        options["filter"] = robots("filter")
    est = {name: e.initialize(pos) for name, e in options.items()}
    central.initialize(*options["grid"].consensus.kde())
    out: dict[str, list[float]] = {}

    def record(key: str, value: float) -> None:
        out.setdefault(key, []).append(value)

    for _ in range(steps):
        p_c, q_c = central.estimates
        p_hat = est["grid"].p_hat
        scale = float(np.abs(p_c).max())
        record("density_gap", float(np.abs(p_hat - p_c.ravel()).max()) / scale)
        q_filter = np.repeat(q_c.reshape(1, -1), n_robots, axis=0)
        if per_robot_filter:
            q_robots = est["filter"].q_hat
            assert q_robots is not None
            gap = float(np.abs(q_robots - q_filter).max()) / float(np.abs(q_c).max())
            record("filter_gap", gap)
        # truths: the exact KDE's gradient, the mean-field limit's smoothed gradient
        _, grad_kde = options["grid"].consensus.kde()
        s_inf, grad_inf = smoother(p_inf)
        q_grid = g.gradient(p_c)
        for name, q in (("filter", q_c), ("grid", q_grid)):
            record(f"err_kde_{name}", _relative(g, q, grad_kde))
            record(f"err_inf_{name}", _relative(g, q, grad_inf))
        # the command at the robots with either gradient
        v_filter = own_velocities(g, law, p_hat, pos, q_filter)
        v_grid = own_velocities(g, law, p_hat, pos, None)
        feedback = own_velocities(g, drift, p_hat, pos, q_filter) - v_filter
        diff = _rms(v_grid - v_filter)
        record("cmd_rel", diff / _rms(v_filter))
        record("cmd_rel_feedback", diff / _rms(feedback))
        record("cmd_rms", _rms(v_filter))
        # the loop moves on the gradient filter's command; the shared model A of it
        field = paper_law(p_c, q_c, target, ALPHA, SIGMA)
        a = fp.matrix(field)
        swarm.step_robots(v_filter, DT, rng)
        p_inf = fp.step(p_inf, paper_law(s_inf, grad_inf, target, ALPHA, SIGMA), DT)
        for name, e in options.items():
            w0, c0 = time.perf_counter(), time.process_time()
            est[name] = e.step(pos, a)
            record(f"wall_{name}", time.perf_counter() - w0)
            record(f"cpu_{name}", time.process_time() - c0)
        w0, c0 = time.perf_counter(), time.process_time()
        central.step(*options["grid"].consensus.kde(), field, a)
        record("wall_central", time.perf_counter() - w0)
        record("cpu_central", time.process_time() - c0)
    return {k: np.asarray(v) for k, v in out.items()}


def closed_loop(n_robots: int, n: int, steps: int, gradient: str, seed: int) -> np.ndarray:
    """Part 2: ``swarm_l2`` per step of the complete-graph loop that moves on the
    ``gradient`` option's command (the robots' estimate is the centralised filters' on
    the complete graph, so one :class:`LocalFilters` stands for all of them).
    """
    g = Grid.square(n)
    rng = np.random.default_rng(seed)
    target = Target.from_density(g, DEFAULT_TARGET)
    fp = FokkerPlanck(g, SIGMA)
    swarm = Swarm(g, Box().sample(n_robots, g, rng), SIGMA)
    pos = swarm.positions
    kde = KDE(g, H, method="exact")
    smoothed = smoothed_density(DEFAULT_TARGET, g, H)
    central = LocalFilters(g, SIGMA, DT, MeasurementModel(n_robots, H, SETTINGS))
    p_c, q_c = central.initialize(*kde.exact(pos))
    out = []
    for _ in range(steps):
        q = q_c if gradient == "filter" else g.gradient(p_c)
        field = paper_law(p_c, q, target, ALPHA, SIGMA)
        # every robot's own command is the common field's interpolant (complete graph)
        swarm.step_robots(interpolate(g, field.centres, pos), DT, rng)
        p_kde, grad_kde = kde.exact(pos)
        p_c, q_c = central.step(p_kde, grad_kde, field, fp.matrix(field))
        out.append(g.l2(p_kde - smoothed))  # swarm_l2 of the exact KDE
    return np.asarray(out)


def _q(x: np.ndarray) -> str:
    """Median and 10th-90th percentiles."""
    lo, med, hi = np.percentile(x, [10, 50, 90])
    return f"{med:.3g} ({lo:.3g} to {hi:.3g})"


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--robots", type=int, default=256)
    parser.add_argument("--grid", type=int, default=30, help="cells per side")
    parser.add_argument("--steps", type=int, default=300, help="steps of part 1")
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated time of part 2")
    parser.add_argument("--seeds", type=int, default=3, help="seeds of part 2")
    parser.add_argument(
        "--per-robot-filter", action="store_true", help="also run gradient='filter' (slow)"
    )
    args = parser.parse_args()
    numba.set_num_threads(1)
    with threadpool_limits(1):
        t0 = time.perf_counter()
        r = trajectory(args.robots, args.grid, args.steps, args.per_robot_filter)
        print(
            f"Part 1: N = {args.robots}, n = {args.grid}, complete graph, {args.steps} steps "
            f"({args.steps * DT:g} s) along the gradient filter's loop; median (10th to "
            f"90th percentile) over steps"
        )
        print(f"  robots' p_hat against the centralised filter (max rel): "
              f"{r['density_gap'].max():.1e}")  # fmt: skip
        if "filter_gap" in r:
            print(f"  gradient='filter' q_hat against the centralised gradient filter (max "
                  f"rel): {r['filter_gap'].max():.1e}")  # fmt: skip
        for truth, label in (("kde", "grad p_KDE (exact KDE)"), ("inf", "grad K_h p_inf (limit)")):
            for name in ("filter", "grid"):
                print(f"  ||q_{name} - {label}|| / ||.||: {_q(r[f'err_{truth}_{name}'])}")
        print(f"  command rms |v_filter| (length/s): {_q(r['cmd_rms'])}")
        print(f"  rms |v_grid - v_filter| / rms |v_filter|: {_q(r['cmd_rel'])}")
        print(f"  rms |v_grid - v_filter| / rms |feedback part|: {_q(r['cmd_rel_feedback'])}")
        times = ["grid", "filter"] if "wall_filter" in r else ["grid"]
        for name in [*times, "central"]:
            what = "centralised filters (one robot's work)" if name == "central" else (
                f"per-robot estimators, gradient={name}")  # fmt: skip
            wall = 1e3 * float(np.median(r[f"wall_{name}"][2:]))
            cpu = 1e3 * float(np.median(r[f"cpu_{name}"][2:]))
            print(f"  {what:<40s} wall {wall:9.2f} ms   cpu {cpu:9.2f} ms per step")
        print(f"  ({time.perf_counter() - t0:.0f} s)")
        t0 = time.perf_counter()
        steps = round(args.seconds / DT)
        tail = max(1, steps // 5)
        floor = 1.0 / np.sqrt(4 * np.pi * args.robots * H**2)  # large-N mean, floors()
        print(f"Part 2: closed loops, {args.seconds:g} s, seeds 0..{args.seeds - 1}: "
              f"swarm_l2 at the end, mean over the last {tail * DT:g} s (finite-N floor "
              f"of independent samples about {floor:.3f})")  # fmt: skip
        for seed in range(args.seeds):
            res = {grad: closed_loop(args.robots, args.grid, steps, grad, seed)
                   for grad in ("filter", "grid")}  # fmt: skip
            line = ", ".join(
                f"{grad}: {x[-1]:.4f}, {x[-tail:].mean():.4f}" for grad, x in res.items()
            )
            gap = np.abs(res["grid"] - res["filter"]).max()
            print(f"  seed {seed}: {line}; max |difference| over time {gap:.4f}")
        print(f"  ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
