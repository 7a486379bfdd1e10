"""Shared figure output for the analysis scripts."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def save_figure(fig, out: Path, stem: str, dpi: int = 120) -> list[Path]:
    """Write ``stem.png`` and ``stem.pdf`` into ``out``, close the figure, return the paths."""
    paths = [out / f"{stem}.png", out / f"{stem}.pdf"]
    for p in paths:
        fig.savefig(p, dpi=dpi)
    plt.close(fig)
    return paths
