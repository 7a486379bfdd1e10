"""The law studies' figures and comparison table (figures of :mod:`analysis.sweep`).

* ``laws_n`` (``law``, ``agents.n``; ``laws_n.png/.pdf``, ``laws_table.md``): per law
  against N, means over the seeds with 95 % confidence intervals: ``swarm_l2`` and
  ``swarm_w2`` over their finite-N floors, the integrated effort, the tail mean speed,
  the settling time and the run's steps per second; and the comparison table.
* ``laws_iss`` (``law``, ``estimator.shape``, ``estimator.delta``; ``laws_iss.png/.pdf``):
  mean-field plant with injected errors, per error shape, the supremum of ``||Phi||``
  over the run against the supremum of ``||eps||``, per law, with the fitted linear gain.
* ``heat_floor`` (``control.density_floor``, ``estimator.shape``, ``estimator.delta``;
  ``heat_floor.png/.pdf``): the same for the heat law at several floors ``c``, and the
  fitted gain against ``c``.
* ``laws_noise`` (``law``, ``agents.localisation_noise``; ``laws_noise.png/.pdf``): the tail
  mean of ``swarm_l2`` over its floor against the localisation noise, per law.

Each law is shown under its option name (the ``law`` column, :mod:`analysis.rows`; a
log written before logs recorded Hydra's choices gives the class name instead), the laws
in alphabetical order (:func:`by_law`), the order in which ``control=glob(*)`` runs them.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from analysis.declaration import Study
from analysis.output import write_text
from analysis.plotting import errorbar, save_figure
from analysis.rows import LAW, points_with, value
from analysis.stats import BEYOND


def by_law(rows: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """The rows (or points) grouped by their law (:data:`analysis.rows.LAW`), the laws
    in alphabetical order.
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for a in rows:
        groups.setdefault(str(a.get(LAW, "")), []).append(a)
    return dict(sorted(groups.items()))


def laws_n_figure(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """Per law against N: the swarm metrics over their floors, effort, tail speed,
    settling time and steps per second (means over the seeds, 95 % CIs).
    """
    agg = points_with(rows, ("agents.n",))
    panels = (
        ("swarm_ratio", r"tail $\mathrm{swarm\_l2}$ / floor", "log"),
        ("swarm_w2_ratio", r"tail $\mathrm{swarm\_w2}$ / floor", "log"),
        ("effort_integral", r"$\int$ effort dt (length$^2$/s)", "log"),
        ("speed_tail_mean", "tail mean speed (length/s)", "log"),
        ("settling_time", "settling time (s; settled seeds)", "linear"),
        ("ms_per_step", "wall time per step (ms, with metrics and log)", "log"),
    )
    fig, axes = plt.subplots(2, 3, figsize=(15, 8.5), constrained_layout=True)
    for i, (law, group) in enumerate(by_law(agg).items()):
        group.sort(key=lambda a: a["agents.n"])
        n = np.array([a["agents.n"] for a in group], dtype=float)
        for ax, (stat, _, _) in zip(axes.flat, panels, strict=True):
            if np.isfinite([a[f"{stat}_mean"] for a in group]).any():
                errorbar(ax, n, group, stat, label=law, color=f"C{i}")
    for ax, (_, label, scale) in zip(axes.flat, panels, strict=True):
        ax.set_xscale("log")
        ax.set_yscale(scale)
        ax.set_xlabel("robots N")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes.flat[:2]:
        ax.axhline(1.0, color="0.4", ls=":", lw=0.8, label="floor: N robots drawn from $p_*$")
    axes.flat[0].legend(fontsize=8)
    fig.suptitle("Laws side by side on the same seeds")
    return save_figure(fig, out, "laws_n")


def cell(a: dict[str, Any] | None, stat: str, fmt: str = "{:.3g}") -> str:
    """A table cell: ``summary (low to high)`` of a point's statistic over the seeds
    with its 95 % interval (:func:`analysis.rows.points`), ``never`` for a settling time
    no seed reached and ``beyond the run`` for a median (or interval end) the seeds did
    not reach, ``-`` for no value; a settling time reached by some seeds says how many.
    """
    if a is None:
        return "-"
    mean = a.get(f"{stat}_mean", math.nan)
    n = a.get(f"{stat}_n", 0)
    jobs = a.get("jobs", 0)
    if isinstance(mean, float) and math.isinf(mean) and n:
        return f"{BEYOND}, {n} of {jobs} seeds"
    if not (isinstance(mean, float) and math.isfinite(mean)):
        return "never" if stat == "settling_time" and jobs else "-"
    text = fmt.format(mean)
    low, high = a.get(f"{stat}_ci_low", math.nan), a.get(f"{stat}_ci_high", math.nan)
    if not (math.isnan(low) or math.isnan(high)):
        ends = [BEYOND if math.isinf(v) else fmt.format(v) for v in (low, high)]
        text += f" ({ends[0]} to {ends[1]})"
    if stat == "settling_time" and n < jobs:
        text += f", {n} of {jobs} seeds"
    return text


def laws_table(rows: list[dict[str, Any]], sizes: tuple[int, int] = (1024, 16384)) -> str:
    """The comparison table (Markdown): per law, what it uses, whether a density
    estimate sits in a denominator, ``swarm_l2`` and ``swarm_w2`` over their floors at
    the two sizes, and at the first size the integrated effort (length^2 / s), the tail
    mean speed (length / s), the settling time (s) and the steps per second of the
    sweep's runs (with metrics and log). Means over the seeds, 95 % CIs in brackets.
    """
    agg = points_with(rows, ("agents.n",))
    facts: dict[str, tuple[str, str]] = {}
    for r in rows:
        facts.setdefault(
            str(r.get(LAW, "")),
            (r.get("law_uses", "") or "-", r.get("law_divides_by_density", "") or "-"),
        )
    small, large = sizes
    head = (
        f"| law | uses | density in a denominator | swarm_l2/floor N={small} | "
        f"swarm_l2/floor N={large} | swarm_w2/floor N={small} | effort (length^2/s) | "
        f"tail speed (length/s) | settling time (s) | steps/s |"
    )
    lines = [head, "|" + "---|" * 10]
    for law, group in by_law(agg).items():
        at = {int(a["agents.n"]): a for a in group}
        a, b = at.get(small), at.get(large)
        steps = "-"
        if a is not None and math.isfinite(a.get("ms_per_step_mean", math.nan)):
            steps = f"{1e3 / a['ms_per_step_mean']:.0f}"
        uses, divides = facts.get(law, ("-", "-"))
        lines.append(
            f"| {law} | {uses} | {divides} | {cell(a, 'swarm_ratio')} | "
            f"{cell(b, 'swarm_ratio')} | {cell(a, 'swarm_w2_ratio')} | "
            f"{cell(a, 'effort_integral')} | {cell(a, 'speed_tail_mean')} | "
            f"{cell(a, 'settling_time', '{:.1f}')} | {steps} |"
        )
    return "\n".join(lines) + "\n"


def draw_laws_n(study: Study) -> list[Path]:
    """:func:`laws_n_figure` and :func:`laws_table` (printed and written)."""
    paths = laws_n_figure(study.usable, study.out)
    table = laws_table(study.usable)
    path = write_text(study.out / "laws_table.md", table)
    print(table)
    return [*paths, path]


def _gain(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope through the origin of ``y`` against ``x`` (``x > 0``)."""
    pos = x > 1e-12
    if pos.sum() < 2:
        return math.nan
    return float(np.linalg.lstsq(x[pos, None], y[pos], rcond=None)[0][0])


FLOOR_PHI = 1e-4
"""``sup ||Phi||`` (1 / length) below which an ISS panel draws a law at this value: a
law that reads no estimate stays at ``p_*`` to round-off (about 1e-14)."""


def _iss_panel(ax, groups: dict[str, list[dict[str, Any]]], gains: dict[str, float]) -> None:
    """``sup ||Phi||`` against ``sup ||eps||`` per group (log-log), with fitted gains;
    dashed, the same law without error.
    """
    for i, (name, group) in enumerate(groups.items()):
        group.sort(key=lambda r: float(value(r, "estimator.delta") or 0))
        x = np.array([r["eps_sup"] for r in group], dtype=float)
        y = np.array([r["phi_sup"] for r in group], dtype=float)
        pos = x > 1e-12
        gains[name] = _gain(x, y)
        note = "" if (y[pos] >= FLOOR_PHI).any() else f", drawn at {FLOOR_PHI:g}"
        label = f"{name} ($\\gamma$ = {gains[name]:.3g}{note})"
        ax.loglog(x[pos], np.maximum(y[pos], FLOOR_PHI), "o-", color=f"C{i}", label=label)
        if (~pos).any() and y[~pos].max() >= FLOOR_PHI:
            ax.axhline(y[~pos].max(), color=f"C{i}", ls="--", lw=0.8)
    ax.set_xlabel(r"$\sup_t \|\epsilon\|_{L^2}$ (1/length)")
    ax.set_ylabel(r"$\sup_t \|\Phi\|_{L^2}$ (1/length)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)


def _shapes(rows: list[dict[str, Any]]) -> list[str]:
    return sorted({str(value(r, "estimator.shape")) for r in rows})


def laws_iss_figure(rows: list[dict[str, Any]], out: Path) -> tuple[list[Path], dict]:
    """Per error shape, ``sup ||Phi||`` against ``sup ||eps||`` per law; the gains."""
    shapes = _shapes(rows)
    fig, axes = plt.subplots(1, len(shapes), figsize=(6.5 * len(shapes), 4.8), squeeze=False)
    gains: dict[str, dict[str, float]] = {}
    for ax, shape in zip(axes[0], shapes, strict=True):
        groups: dict[str, list[dict[str, Any]]] = {}
        for r in rows:
            if str(value(r, "estimator.shape")) == shape:
                groups.setdefault(str(r.get(LAW, "")), []).append(r)
        gains[shape] = {}
        _iss_panel(ax, dict(sorted(groups.items())), gains[shape])
        ax.set_title(f"injected error: {shape}")
    fig.suptitle("Mean-field plant, injected estimation errors, start at $p_*$")
    fig.set_layout_engine("constrained")
    return save_figure(fig, out, "laws_iss"), gains


def heat_floor_figure(rows: list[dict[str, Any]], out: Path) -> tuple[list[Path], dict]:
    """The heat law at several floors ``c``: per error shape, ``sup ||Phi||`` against
    ``sup ||eps||`` per floor, and the fitted gain against ``c``.
    """
    shapes = _shapes(rows)
    fig, axes = plt.subplots(
        1, len(shapes) + 1, figsize=(6 * (len(shapes) + 1), 4.8), squeeze=False
    )
    gains: dict[str, dict[str, float]] = {}
    for ax, shape in zip(axes[0], shapes, strict=False):
        groups: dict[str, list[dict[str, Any]]] = {}
        for r in rows:
            if str(value(r, "estimator.shape")) == shape:
                c = float(value(r, "control.density_floor"))
                groups.setdefault(f"c = {c:g}", []).append(r)
        gains[shape] = {}
        ordered = dict(sorted(groups.items(), key=lambda kv: -float(kv[0][4:])))
        _iss_panel(ax, ordered, gains[shape])
        ax.set_title(f"heat law, injected error: {shape}")
    ax = axes[0][-1]
    for i, shape in enumerate(shapes):
        floors = np.array([float(k[4:]) for k in gains[shape]])
        fitted = np.array(list(gains[shape].values()))
        order = np.argsort(floors)
        ax.loglog(floors[order], fitted[order], "o-", color=f"C{i}", label=shape)
    ax.set_xlabel("density floor c (1/length$^2$)")
    ax.set_ylabel(r"fitted gain $\gamma$")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("gain against the floor")
    fig.set_layout_engine("constrained")
    return save_figure(fig, out, "heat_floor"), gains


def laws_noise_figure(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """Tail ``swarm_l2`` over its floor against the localisation noise, per law."""
    agg = points_with(rows, ("agents.localisation_noise",))
    fig, ax = plt.subplots(figsize=(7, 4.8), constrained_layout=True)
    for i, (law, group) in enumerate(by_law(agg).items()):
        group.sort(key=lambda a: a["agents.localisation_noise"])
        s = np.array([a["agents.localisation_noise"] for a in group], dtype=float)
        errorbar(ax, s, group, "swarm_ratio", label=law, color=f"C{i}")
    ax.set_yscale("log")
    ax.set_xlabel("localisation noise (length, standard deviation)")
    ax.set_ylabel(r"tail $\mathrm{swarm\_l2}$ / floor")
    ax.axhline(1.0, color="0.4", ls=":", lw=0.8, label="floor")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Every law against localisation error (true positions measured)")
    return save_figure(fig, out, "laws_noise")


def _print_gains(gains: dict[str, dict[str, float]]) -> None:
    for shape, by in gains.items():
        for name, g in by.items():
            print(f"fitted ISS gain ({shape}, {name}): {g:.4g} (sup ||Phi|| per unit sup ||eps||)")


def draw_laws_iss(study: Study) -> list[Path]:
    """:func:`laws_iss_figure`, and each law's gain per shape."""
    paths, gains = laws_iss_figure(study.usable, study.out)
    _print_gains(gains)
    return paths


def draw_heat_floor(study: Study) -> list[Path]:
    """:func:`heat_floor_figure`, and each floor's gain per shape."""
    paths, gains = heat_floor_figure(study.usable, study.out)
    _print_gains(gains)
    return paths


def draw_laws_noise(study: Study) -> list[Path]:
    """:func:`laws_noise_figure`, and each law's ratio at each noise."""
    paths = laws_noise_figure(study.usable, study.out)
    for a in sorted(
        points_with(study.usable, ("agents.localisation_noise",)),
        key=lambda a: (str(a[LAW]), a["agents.localisation_noise"]),
    ):
        print(
            f"{a[LAW]}, localisation noise {a['agents.localisation_noise']}: "
            f"swarm_l2 / floor = {cell(a, 'swarm_ratio')}"
        )
    return paths
