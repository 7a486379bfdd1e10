"""The figures of the agent-level studies: errors against the swarm size N, the grid
size n and the communication radius r (figures of :mod:`analysis.sweep`).

* ``agents_n`` (``agents.n``; ``agents_n.png/.pdf``): tail means of ``||p_hat -
  p_*||``, ``swarm_l2`` (with its floor) and the decomposition terms against N;
* ``debias_n`` (``agents.n``, ``kde.debias``; ``debias_n.png/.pdf``): ``swarm_l2`` and
  ``swarm_w2`` with their finite-N floors against N, the paper's loop against the
  debiased loop, and ``||p_hat - p_*||`` beside them;
* ``conv_grid_agents`` (``grid.n``; ``conv_grid_agents.png/.pdf``): tail ``||p_hat -
  p_*||``, ``swarm_l2`` and the decomposition terms against n, and the wall time per
  step;
* ``distributed_r`` (``estimator.radius``; ``distributed_r.png/.pdf``): the
  decentralised loop's ``central_gap_l2`` and ``consensus_l2``, ``swarm_l2`` with its
  floor and the mean estimate's ``||p_hat - p_*||``, and the messages and components,
  against the radius.

Means over the seeds with their 95 % confidence intervals as error bars
(:func:`analysis.rows.points`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from analysis.declaration import Study
from analysis.plotting import band, errorbar, save_figure
from analysis.rows import points

DECOMPOSITION = {
    "phat_tail_mean": r"$\|\hat p - p_*\|$",
    "swarm_tail_mean": r"$\|K_h\mu_N - K_h p_*\|$ (robots)",
    "est_swarm_tail_mean": r"$\|\hat p - K_h\mu_N\|$ (estimator)",
    "limit_swarm_tail_mean": r"$\|K_h\mu_N - K_h p_\infty\|$ (finite N)",
    "limit_target_tail_mean": r"$\|K_h p_\infty - K_h p_*\|$ (limit loop)",
}
"""The statistics the agent-level figures draw against N or n, with their labels."""


def agents_figure(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """Tail errors against the number of robots: means over the seeds with 95 % CIs."""
    agg = sorted(points(rows), key=lambda a: a["agents.n"])
    n = np.array([a["agents.n"] for a in agg], dtype=float)
    fig, ax = plt.subplots(figsize=(6.5, 4.8), constrained_layout=True)
    for stat, label in DECOMPOSITION.items():
        errorbar(ax, n, agg, stat, label=label)
    band(ax, n, agg, "swarm_floor", "0.4", "floor: N robots drawn from $p_*$")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("robots N")
    ax.set_ylabel("tail mean (1/length)")
    ax.set_title("errors against swarm size (mean over seeds, 95 % CI)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return save_figure(fig, out, "agents_n")


def debias_figure(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """``swarm_l2``, ``swarm_w2`` (with floors) and ``||p_hat - p_*||`` against N, for
    the paper's loop and the debiased loop, means over the seeds with 95 % CIs.
    """
    agg = points(rows)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4), constrained_layout=True)
    colors = {False: "C3", True: "C0"}
    for debias in (False, True):
        group = sorted(
            (a for a in agg if bool(a.get("kde.debias")) is debias), key=lambda a: a["agents.n"]
        )
        if not group:
            continue
        n = np.array([a["agents.n"] for a in group], dtype=float)
        name = "debiased" if debias else "paper"
        c = colors[debias]
        errorbar(axes[0], n, group, "swarm_tail_mean", color=c, label=f"{name} loop")
        if not debias:
            band(axes[0], n, group, "swarm_floor", "0.4", "floor: N robots drawn from $p_*$")
            band(axes[1], n, group, "swarm_w2_floor", "0.4", "floor: N robots drawn from $p_*$")
        errorbar(axes[1], n, group, "swarm_w2_last", color=c, label=f"{name} loop")
        errorbar(axes[2], n, group, "phat_tail_mean", color=c, label=f"{name} loop")
    titles = (
        r"where the robots are: $\|K_h\mu_N - K_h p_*\|$",
        r"transport $W_2(\mu_N, p_*)$: exact to N = 4096, sliced above",
        r"the paper's Fig. 2 quantity $\|\hat p - p_*\|$",
    )
    units = ("1/length", "length", "1/length")
    for ax, title, unit in zip(axes, titles, units, strict=True):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("robots N")
        ax.set_ylabel(f"tail mean ({unit})")
        ax.set_title(title, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    return save_figure(fig, out, "debias_n")


def grid_figure(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """Agent loop against grid size: tail errors and wall time per step, means over the
    seeds with 95 % CIs.
    """
    agg = sorted(points(rows), key=lambda a: a["grid.n"])
    n = np.array([a["grid.n"] for a in agg], dtype=float)
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11.5, 4.4), constrained_layout=True)
    for stat, label in DECOMPOSITION.items():
        errorbar(ax0, n, agg, stat, label=label)
    band(ax0, n, agg, "swarm_floor", "0.4", "floor: N robots drawn from $p_*$")
    ax0.set_yscale("log")
    ax0.set_ylabel("tail mean (1/length)")
    ax0.set_title("tail errors against grid size")
    errorbar(ax1, n, agg, "ms_per_step", color="k", label="wall time per step")
    ax1.set_yscale("log")
    ax1.set_ylabel("ms per step")
    ax1.set_title("cost against grid size")
    for ax in (ax0, ax1):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("cells per side n")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    return save_figure(fig, out, "conv_grid_agents")


def network_figure(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """Decentralised loop against the communication radius: the robots' gap to the
    centralised filter and their disagreement; where the robots are (with the finite-N
    floor) and the mean estimate's error; the communication each robot pays. Means over
    the seeds with 95 % CIs; the radius axis is linear below 0.01 (``r = 0``: no
    neighbours) and logarithmic above.
    """
    agg = sorted(points(rows), key=lambda a: a["estimator.radius"])
    r = np.array([a["estimator.radius"] for a in agg], dtype=float)
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.4), constrained_layout=True)
    errorbar(axes[0], r, agg, "central_gap_tail_mean", color="C3",
              label=r"$\mathrm{mean}_i\,\|\hat p_i - \hat p_{\mathrm{central}}\|$")  # fmt: skip
    errorbar(axes[0], r, agg, "consensus_tail_mean", color="C0",
              label=r"$\mathrm{mean}_i\,\|\hat p_i - \bar{\hat p}\|$ (disagreement)")  # fmt: skip
    axes[0].set_title("robots' estimates against the centralised filter")
    axes[0].set_ylabel("tail mean (1/length)")
    errorbar(axes[1], r, agg, "swarm_tail_mean", color="k",
              label=r"$\|K_h\mu_N - K_h p_*\|$ (robots)")  # fmt: skip
    errorbar(axes[1], r, agg, "phat_tail_mean", color="C2",
              label=r"$\|\bar{\hat p} - p_*\|$ (mean estimate)")  # fmt: skip
    band(axes[1], r, agg, "swarm_floor", "0.4", "floor: N robots drawn from $p_*$")
    axes[1].set_title("where the robots are (complete graph = centralised loop)")
    axes[1].set_ylabel("tail mean (1/length)")
    errorbar(axes[2], r, agg, "messages_tail_mean", color="C1",
              label="messages per robot per step")  # fmt: skip
    errorbar(axes[2], r, agg, "components_tail_mean", color="C4",
              label="connected components")  # fmt: skip
    axes[2].set_title("communication")
    axes[2].set_ylabel("tail mean (1)")
    for ax in axes:
        ax.set_xscale("symlog", linthresh=0.01)
        ax.set_yscale("log")
        ax.set_xlabel("communication radius r (length)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    axes[2].set_yscale("symlog", linthresh=1.0)  # r = 0 sends no messages
    return save_figure(fig, out, "distributed_r")


def draw_agents_n(study: Study) -> list[Path]:
    """:func:`agents_figure`."""
    return agents_figure(study.usable, study.out)


def draw_debias_n(study: Study) -> list[Path]:
    """:func:`debias_figure`, and ``swarm_l2`` over its floor at each point."""
    paths = debias_figure(study.usable, study.out)
    for a in sorted(points(study.usable), key=lambda a: (a["kde.debias"], a["agents.n"])):
        print(
            f"N = {a['agents.n']}, debias = {a['kde.debias']}: swarm_l2 / floor = "
            f"{a['swarm_ratio_mean']:.3g} (95 % CI {a['swarm_ratio_ci_low']:.3g} to "
            f"{a['swarm_ratio_ci_high']:.3g}, {a['jobs']} seeds)"
        )
    return paths


def draw_conv_grid_agents(study: Study) -> list[Path]:
    """:func:`grid_figure`, and the tail error and cost at each grid size."""
    paths = grid_figure(study.usable, study.out)
    for a in sorted(points(study.usable), key=lambda a: a["grid.n"]):
        print(
            f"n = {a['grid.n']}: ||p_hat - p*|| tail {a['phat_tail_mean_mean']:.4g} "
            f"1/length, {a['ms_per_step_mean']:.3g} ms per step ({a['jobs']} seeds)"
        )
    return paths


def draw_distributed_r(study: Study) -> list[Path]:
    """:func:`network_figure`, and the gap, ``swarm_l2`` and messages at each radius."""
    paths = network_figure(study.usable, study.out)
    for a in sorted(points(study.usable), key=lambda a: a["estimator.radius"]):
        print(
            f"r = {a['estimator.radius']}: central_gap_l2 "
            f"{a['central_gap_tail_mean_mean']:.3g} "
            f"(95 % CI {a['central_gap_tail_mean_ci_low']:.3g} to "
            f"{a['central_gap_tail_mean_ci_high']:.3g}) 1/length, swarm_l2 "
            f"{a['swarm_tail_mean_mean']:.3g} 1/length (floor "
            f"{a['swarm_floor_mean_mean']:.3g}), {a['messages_tail_mean_mean']:.3g} "
            f"messages per robot per step ({a['jobs']} seeds)"
        )
    return paths
