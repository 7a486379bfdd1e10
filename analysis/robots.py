"""Figures of the robot and link studies (``analysis.figure: robots | link``), drawn
from a sweep's rows by :mod:`analysis.sweep`.

* ``robots`` (``plant``, ``law``; ``robots.png/.pdf``): per law, one bar per plant
  (in alphabetical order of the plants' options: ideal integrators ``agents``, double
  integrators, unicycles, and any plant of your own under its option name): the tail
  ``swarm_l2`` over its finite-N floor, the tail mean tracking error (length / s) and
  the settling time (s), means over the seeds with 95 % confidence intervals; a table
  ``robots_table.md`` with the same numbers.
* ``link`` (``link.png/.pdf``): per loss probability, the tail ``swarm_l2`` over its
  floor on the grid of broadcast period against latency (colour, log scale, value in
  each cell), the cells within :data:`REACHES` times the floor outlined; the boundary
  (:func:`link_boundary`) printed and written to ``link_boundary.md``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import LogNorm

from analysis.declaration import Study
from analysis.laws import by_law, cell
from analysis.output import write_text
from analysis.plotting import save_figure
from analysis.rows import points_with

PLANT = "plant"
"""The key of the plant: the option of config group ``plant`` (:mod:`analysis.rows`)."""

PLANT_LABELS = {"agents": "ideal integrators", "double_integrators": "double integrators"}
"""How the figure and table name the project's plants whose option name does not read
as words; any other plant is shown under its option name."""

REACHES = 1.5
"""A loop reaches its floor when its tail ``swarm_l2`` is at most this many times the
floor's mean (the settling criterion of :data:`analysis.run_stats.SETTLING_FACTOR`)."""

LINK_KEYS = ("link.period", "link.latency", "link.loss")
"""The link study's axes."""


def plant_label(a: dict[str, Any]) -> str:
    """The point's plant as the figure and table name it (:data:`PLANT_LABELS`, else its
    option name).
    """
    option = str(a.get(PLANT, ""))
    return PLANT_LABELS.get(option, option)


def _plants(agg: list[dict[str, Any]]) -> list[str]:
    """The points' plants, in alphabetical order of their options."""
    return [plant_label({PLANT: p}) for p in sorted({str(a.get(PLANT, "")) for a in agg})]


def robots_figure(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """Bars per law and plant: ``swarm_ratio``, ``tracking_tail_mean``,
    ``settling_time`` (module docstring).
    """
    agg = points_with(rows, (PLANT,))
    laws = by_law(agg)
    plants = _plants(agg)
    panels = (
        ("swarm_ratio", r"tail $\mathrm{swarm\_l2}$ / floor", "log"),
        ("tracking_tail_mean", "tail tracking error (length/s)", "linear"),
        ("settling_time", "settling time (s; settled seeds)", "linear"),
    )
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8), constrained_layout=True)
    width = 0.8 / max(len(plants), 1)
    x = np.arange(len(laws))
    for j, plant in enumerate(plants):
        for ax, (stat, _, _) in zip(axes, panels, strict=True):
            mean, err = [], []
            for group in laws.values():
                a = next((a for a in group if plant_label(a) == plant), None)
                m = a.get(f"{stat}_mean", math.nan) if a else math.nan
                lo = a.get(f"{stat}_ci_low", math.nan) if a else math.nan
                hi = a.get(f"{stat}_ci_high", math.nan) if a else math.nan
                mean.append(m)
                err.append(
                    (m - lo if math.isfinite(lo) else 0.0, hi - m if math.isfinite(hi) else 0.0)
                )
            heights = np.array(mean, dtype=float)
            ax.bar(
                x + (j - (len(plants) - 1) / 2) * width,
                np.where(np.isfinite(heights), heights, 0.0),
                width,
                yerr=np.clip(np.array(err).T, 0, None),
                capsize=2,
                color=f"C{j}",
                label=plant,
            )
    for ax, (_, label, scale) in zip(axes, panels, strict=True):
        ax.set_xticks(x, list(laws))
        ax.set_yscale(scale)
        ax.set_ylabel(label)
        ax.grid(True, axis="y", which="both", alpha=0.3)
    axes[0].axhline(1.0, color="0.4", ls=":", lw=0.8, label="floor: N robots drawn from $p_*$")
    axes[0].axhline(REACHES, color="0.4", ls="--", lw=0.8, label=f"{REACHES} x floor")
    axes[0].legend(fontsize=8)
    fig.suptitle("Laws on robots that are not ideal integrators (N = 1024, same seeds)")
    return save_figure(fig, out, "robots")


def robots_table(rows: list[dict[str, Any]]) -> str:
    """Markdown: per law and plant, ``swarm_l2`` over its floor, the tail tracking
    error (length / s) and the settling time (s); means with 95 % CIs.
    """
    agg = points_with(rows, (PLANT,))
    lines = [
        "| law | plant | swarm_l2/floor | tracking error (length/s) | settling time (s) |",
        "|---|---|---|---|---|",
    ]
    for law, group in by_law(agg).items():
        for a in sorted(group, key=lambda a: str(a.get(PLANT, ""))):
            lines.append(
                f"| {law} | {plant_label(a)} | {cell(a, 'swarm_ratio')} | "
                f"{cell(a, 'tracking_tail_mean')} | {cell(a, 'settling_time', '{:.1f}')} |"
            )
    return "\n".join(lines) + "\n"


def draw_robots(study: Study) -> list[Path]:
    """:func:`robots_figure` and :func:`robots_table` (printed and written)."""
    paths = robots_figure(study.usable, study.out)
    table = robots_table(study.usable)
    path = write_text(study.out / "robots_table.md", table)
    print(table)
    return [*paths, path]


def _link_grid(agg: list[dict[str, Any]], loss: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Periods, latencies and the ``swarm_ratio`` means (latency x period) at ``loss``."""
    at = [a for a in agg if a["link.loss"] == loss]
    periods = np.array(sorted({float(a["link.period"]) for a in at}))
    latencies = np.array(sorted({float(a["link.latency"]) for a in at}))
    ratio = np.full((latencies.size, periods.size), np.nan)
    for a in at:
        i = int(np.searchsorted(latencies, float(a["link.latency"])))
        j = int(np.searchsorted(periods, float(a["link.period"])))
        ratio[i, j] = a["swarm_ratio_mean"]
    return periods, latencies, ratio


def _last_passing(axis: np.ndarray, ok: np.ndarray) -> float:
    """The largest value of the ascending ``axis`` up to which every value passes
    (``ok``); NaN when the first does not.
    """
    failing = np.flatnonzero(~ok)
    last = (failing[0] if failing.size else axis.size) - 1
    return float(axis[last]) if last >= 0 else math.nan


def link_boundary(rows: list[dict[str, Any]]) -> str:
    """Per loss probability: the largest period at latency 0 up to which every period
    passes, the largest latency at the smallest period up to which every latency passes,
    and the cells (period, latency) where the loop stays within :data:`REACHES` times its
    floor (Markdown).
    """
    agg = points_with(rows, LINK_KEYS)
    lines = [
        f"Loop within {REACHES} x its floor (tail swarm_l2 / floor), per loss:",
        "",
        "| loss | largest period at no latency (s) | largest latency at the shortest period (s) "
        "| cells within (period s, latency s) |",
        "|---|---|---|---|",
    ]
    for loss in sorted({float(a["link.loss"]) for a in agg}):
        periods, latencies, ratio = _link_grid(agg, loss)
        ok = ratio <= REACHES
        period = _last_passing(periods, ok[0]) if latencies[0] == 0 else math.nan
        latency = _last_passing(latencies, ok[:, 0])
        cells = ", ".join(
            f"({periods[j]:g}, {latencies[i]:g})" for i, j in zip(*np.nonzero(ok), strict=True)
        )
        lines.append(f"| {loss:g} | {period:g} | {latency:g} | {cells or 'none'} |")
    return "\n".join(lines) + "\n"


def link_figure(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """One panel per loss: ``swarm_ratio`` over period x latency (module docstring)."""
    agg = points_with(rows, LINK_KEYS)
    losses = sorted({float(a["link.loss"]) for a in agg})
    values = np.array([a["swarm_ratio_mean"] for a in agg], dtype=float)
    finite = values[np.isfinite(values) & (values > 0)]
    norm = (
        LogNorm(vmin=max(finite.min(), 0.5), vmax=max(finite.max(), 2.0)) if finite.size else None
    )
    fig, axes = plt.subplots(
        1, len(losses), figsize=(4.8 * len(losses), 4.4), constrained_layout=True, squeeze=False
    )
    image = None
    for ax, loss in zip(axes[0], losses, strict=True):
        periods, latencies, ratio = _link_grid(agg, loss)
        image = ax.imshow(ratio, origin="lower", cmap="viridis", norm=norm, aspect="auto")
        for i in range(latencies.size):
            for j in range(periods.size):
                if math.isfinite(ratio[i, j]):
                    inside = ratio[i, j] <= REACHES
                    ax.text(j, i, f"{ratio[i, j]:.2g}", ha="center", va="center", fontsize=8,
                            color="w" if not inside else "k",
                            bbox={"fc": "w", "ec": "k", "lw": 1} if inside else None)  # fmt: skip
        ax.set_xticks(range(periods.size), [f"{p:g}" for p in periods])
        ax.set_yticks(range(latencies.size), [f"{q:g}" for q in latencies])
        ax.set_xlabel("broadcast period (s)")
        ax.set_ylabel("latency (s)")
        ax.set_title(f"loss {loss:g}")
    if image is not None:
        fig.colorbar(image, ax=axes[0].tolist(), label=r"tail $\mathrm{swarm\_l2}$ / floor")
    fig.suptitle(
        f"The paper's loop on unicycles behind a command link (boxed: within {REACHES} x floor)"
    )
    return save_figure(fig, out, "link")


def draw_link(study: Study) -> list[Path]:
    """:func:`link_figure` and :func:`link_boundary` (printed and written)."""
    paths = link_figure(study.usable, study.out)
    text = link_boundary(study.usable)
    path = write_text(study.out / "link_boundary.md", text)
    print(text)
    return [*paths, path]
