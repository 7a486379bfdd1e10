"""Shared figure output and drawing helpers of the analysis scripts."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from analysis.output import atomic_path


def save_figure(fig, out: Path, stem: str, dpi: int = 120) -> list[Path]:
    """Write ``stem.png`` and ``stem.pdf`` into ``out`` atomically (an interrupted write
    leaves the old file), close the figure, return the paths.
    """
    paths = [out / f"{stem}.png", out / f"{stem}.pdf"]
    try:
        for p in paths:
            with atomic_path(p) as tmp:
                fig.savefig(tmp, dpi=dpi, format=p.suffix.lstrip("."))
    finally:
        plt.close(fig)
    return paths


def errorbar(ax: Any, x: Any, agg: list[dict[str, Any]], stat: str, **kwargs: Any) -> None:
    """The means of ``stat`` over the points ``agg`` (``STAT_mean``) against ``x``, with
    their 95 % intervals (``STAT_ci_low``, ``STAT_ci_high``) as error bars; a missing
    bound draws no bar on its side.
    """
    mean = np.array([a[f"{stat}_mean"] for a in agg], dtype=float)
    low = np.array([a[f"{stat}_ci_low"] for a in agg], dtype=float)
    high = np.array([a[f"{stat}_ci_high"] for a in agg], dtype=float)
    err = np.vstack(
        [
            mean - np.where(np.isfinite(low), low, mean),
            np.where(np.isfinite(high), high, mean) - mean,
        ]
    )
    ax.errorbar(x, mean, yerr=np.clip(err, 0, None), capsize=3, marker="o", **kwargs)


def band(ax: Any, x: Any, agg: list[dict[str, Any]], stat: str, color: str, label: str) -> None:
    """A floor ``stat`` (its ``_mean``, ``_lo`` and ``_hi`` as statistics of the points
    ``agg``): the mean line and the 95 % band of N independent robots, against ``x``.
    """
    mean = np.array([a[f"{stat}_mean_mean"] for a in agg], dtype=float)
    lo = np.array([a[f"{stat}_lo_mean"] for a in agg], dtype=float)
    hi = np.array([a[f"{stat}_hi_mean"] for a in agg], dtype=float)
    ax.fill_between(x, lo, hi, color=color, alpha=0.15, lw=0)
    ax.plot(x, mean, ":", color=color, label=label)
