"""Figures shared by the experiment entry points."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from harness.densities import Target
from harness.grid import Grid
from harness.meanfield import MeanFieldResult


def plot_meanfield_convergence(
    result: MeanFieldResult,
    grid: Grid,
    target: Target,
    p0: np.ndarray,
    rate: float,
    out_dir: Path,
    name: str = "meanfield_convergence",
) -> list[Path]:
    """Initial density, final density, target, and ``||p - p_*||`` and ``V`` over
    time on a log scale with the theoretical rate ``(alpha + sigma) lambda``.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    fig = plt.figure(figsize=(13, 3.6), constrained_layout=True)
    axes = fig.subplots(1, 4, gridspec_kw={"width_ratios": [1, 1, 1, 1.6]})
    vmax = max(p0.max(), target.p.max(), result.p_final.max())
    extent = (grid.x0, grid.x1, grid.y0, grid.y1)
    for ax, field, title in zip(
        axes[:3],
        (p0, result.p_final, target.p),
        ("$p_0$", f"$p$ at t = {result.t[-1]:.0f} s", "target $p_*$"),
        strict=True,
    ):
        im = ax.imshow(field, origin="lower", extent=extent, vmin=0, vmax=vmax, cmap="viridis")
        ax.set_title(title)
        ax.set_xlabel("x")
        ax.set_ylabel("y")
    fig.colorbar(im, ax=axes[:3], shrink=0.8, label="density (1/length$^2$)")
    ax = axes[3]
    ax.semilogy(result.t, result.phi_l2, label=r"$\|p - p_*\|_{L^2}$")
    ax.semilogy(result.t, np.sqrt(2 * result.lyapunov), label=r"$\sqrt{2V}$", ls="--")
    t_ref = result.t[len(result.t) // 2 :]
    anchor = result.phi_l2[len(result.t) // 2]
    ax.semilogy(
        t_ref,
        anchor * np.exp(-rate * (t_ref - t_ref[0])),
        color="k",
        ls=":",
        label=rf"rate $(\alpha+\sigma)\lambda$ = {rate:.3g} 1/s",
    )
    ax.set_xlabel("t (s)")
    ax.set_title("convergence, exact estimates")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    paths = [out_dir / f"{name}.png", out_dir / f"{name}.pdf"]
    for p in paths:
        fig.savefig(p, dpi=130)
    plt.close(fig)
    return paths
