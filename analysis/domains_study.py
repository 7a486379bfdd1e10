"""The figure of the study of every law on domains with obstacles (``analysis.figure:
domains``; primary keys ``domain``, ``law``, ``agents.n``), drawn from a sweep's rows and
metrics by :mod:`analysis.sweep`.

``domains.png/.pdf``: one row of panels per domain (the option of config group
``domain``, in alphabetical order), each law in its own colour (laws in alphabetical
order, :func:`analysis.laws.by_law`) and each swarm size in its own line style:

* ``swarm_l2`` over the mean of its finite-N floor against time (the mean over the
  seeds of each job's ratio; 1: where N robots drawn independently from ``p_*`` sit);
* ``start_fraction``, the robots' fraction in the support of the initial density,
  against time (mean over the seeds), with ``start_target_mass``, the target's mass
  there (black, dotted): where a swarm distributed as ``p_*`` levels off;
* the integrated effort ``int effort dt`` (length^2 / s) per law, one bar per swarm
  size, means over the seeds with 95 % confidence intervals.
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
from analysis.laws import by_law
from analysis.plotting import save_figure
from analysis.rows import LAW, points_with, value

DOMAIN = "domain"
"""The key of the domain: the option of config group ``domain`` (:mod:`analysis.rows`)."""

SIZE = "agents.n"
"""The key of the swarm's size."""

STYLES = ("-", "--", ":", "-.")
"""Line styles of the swarm sizes, smallest first."""


def mean_curve(
    rows: list[dict[str, Any]], series: dict[str, Any], key: str, scale: str | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The mean over ``rows`` (jobs of one point: the same times) of metric ``key``
    divided by each job's statistic ``scale`` when given, at the times where every job
    evaluated it: ``(t, mean)`` (empty arrays when none did).
    """
    curves = []
    t: np.ndarray | None = None
    for r in rows:
        m = series.get(r["dir"])
        if m is None:
            continue
        y = np.asarray(m[key], dtype=float)
        if scale is not None:
            y = y / float(r.get(scale, math.nan))
        if t is None:
            t = np.asarray(m["t"], dtype=float)
        if y.shape != t.shape:
            continue  # a job cut short: its times are not the point's
        curves.append(y)
    if t is None or not curves:
        return np.array([]), np.array([])
    stack = np.vstack(curves)
    keep = np.isfinite(stack).all(axis=0)
    return t[keep], stack[:, keep].mean(axis=0)


def _jobs(rows: list[dict[str, Any]], domain: str, law: str, n: int) -> list[dict[str, Any]]:
    """The jobs of one point."""
    return [
        r
        for r in rows
        if str(value(r, DOMAIN)) == domain
        and str(r.get(LAW, "")) == law
        and int(value(r, SIZE)) == n
    ]


def domains_figure(rows: list[dict[str, Any]], series: dict[str, Any], out: Path) -> list[Path]:
    """The study's figure (module docstring) from its completed jobs ``rows`` and their
    metrics ``series``.
    """
    agg = points_with(rows, (DOMAIN, SIZE))
    domains = sorted({str(a[DOMAIN]) for a in agg})
    sizes = sorted({int(a[SIZE]) for a in agg})
    laws = list(by_law(agg))
    fig, axes = plt.subplots(
        len(domains), 3, figsize=(16, 4.6 * len(domains)), squeeze=False, constrained_layout=True
    )
    for d, domain in enumerate(domains):
        ax_l2, ax_start, ax_effort = axes[d]
        masses = []
        for i, law in enumerate(laws):
            for j, n in enumerate(sizes):
                jobs = _jobs(rows, domain, law, n)
                style = {"color": f"C{i}", "ls": STYLES[j % len(STYLES)], "lw": 1.2}
                label = f"{law}, N = {n}"
                t, ratio = mean_curve(jobs, series, "swarm_l2", "swarm_floor_mean")
                if t.size:
                    ax_l2.plot(t, ratio, label=label, **style)
                t, fraction = mean_curve(jobs, series, "start_fraction")
                if t.size:
                    ax_start.plot(t, fraction, label=label, **style)
                masses += [r.get("start_target_mass", math.nan) for r in jobs]
        finite = [m for m in masses if math.isfinite(m)]
        if finite:
            ax_start.axhline(
                float(np.mean(finite)), color="k", ls=":", lw=1.0, label=r"$p_*$'s mass there"
            )
        ax_l2.axhline(1.0, color="0.4", ls=":", lw=0.8, label="floor: N robots drawn from $p_*$")
        ax_l2.set_yscale("log")
        ax_l2.set_ylabel(r"$\mathrm{swarm\_l2}$ / floor")
        ax_start.set_ylabel("robots in the start region (fraction)")
        ax_start.set_ylim(0, 1.05)
        for ax in (ax_l2, ax_start):
            ax.set_xlabel("t (s)")
            ax.grid(True, which="both", alpha=0.3)
        ax_l2.set_title(f"{domain}: where the robots are")
        ax_start.set_title(f"{domain}: the swarm leaving its start region")
        _effort_bars(ax_effort, [a for a in agg if str(a[DOMAIN]) == domain], laws, sizes)
        ax_effort.set_title(f"{domain}: effort")
    axes[0][1].legend(fontsize=7, ncol=2)
    axes[0][2].legend(fontsize=8)
    fig.suptitle("Every law on domains with obstacles")
    return save_figure(fig, out, "domains")


def _effort_bars(ax: Any, agg: list[dict[str, Any]], laws: list[str], sizes: list[int]) -> None:
    """``effort_integral`` per law (x) and swarm size (bars), with 95 % intervals."""
    width = 0.8 / max(len(sizes), 1)
    x = np.arange(len(laws))
    for j, n in enumerate(sizes):
        mean, low, high = [], [], []
        for law in laws:
            a = next((a for a in agg if a.get(LAW) == law and int(a[SIZE]) == n), None)
            m = a.get("effort_integral_mean", math.nan) if a else math.nan
            lo = a.get("effort_integral_ci_low", math.nan) if a else math.nan
            hi = a.get("effort_integral_ci_high", math.nan) if a else math.nan
            mean.append(m)
            low.append(m - lo if math.isfinite(lo) else 0.0)
            high.append(hi - m if math.isfinite(hi) else 0.0)
        err = np.clip(np.array([low, high], dtype=float), 0, None)
        offset = (j - (len(sizes) - 1) / 2) * width
        shade = f"{0.3 + 0.3 * j / max(len(sizes) - 1, 1):.2f}"
        ax.bar(x + offset, mean, width, yerr=err, capsize=2, label=f"N = {n}", color=shade)
    ax.set_xticks(x, laws, rotation=30, ha="right")
    ax.set_yscale("log")
    ax.set_ylabel(r"$\int$ effort dt (length$^2$/s)")
    ax.grid(True, axis="y", which="both", alpha=0.3)


def draw_domains(study: Study) -> list[Path]:
    """:func:`domains_figure`, and per domain, law and size the tail ``swarm_l2`` over
    its floor and the start region's excess (printed).
    """
    paths = domains_figure(study.usable, study.series, study.out)
    for a in sorted(
        points_with(study.usable, (DOMAIN, SIZE)),
        key=lambda a: (str(a[DOMAIN]), str(a.get(LAW)), int(a[SIZE])),
    ):
        print(
            f"{a[DOMAIN]} {a.get(LAW)} N={a[SIZE]}: swarm_l2/floor "
            f"{a.get('swarm_ratio_mean', math.nan):.3g}, start region "
            f"{a.get('start_fraction_tail_mean_mean', math.nan):.3g} against "
            f"{a.get('start_target_mass_mean', math.nan):.3g}"
        )
    return paths
