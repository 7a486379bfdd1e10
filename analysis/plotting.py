"""Shared figure output for the analysis scripts."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

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
