"""The figures of the mean-field studies: convergence curves with their decay rates,
and the ISS gain (figures of :mod:`analysis.sweep`).

* ``convergence`` (``convergence.png/.pdf``), the generic figure (a sweep without a
  declaration gets it): ``||Phi||`` curves overlaid, labelled by the first varied key,
  and the fitted exponential rates next to the theoretical ``(alpha + sigma) lambda``;
* ``iss_gain`` (``law``, ``estimator.delta``; ``iss_gain.png/.pdf``): the tail supremum
  of ``||Phi|| = ||p - p_*||`` against the supremum of ``||eps||``, one curve per
  control law (in alphabetical order of the laws' options), with the fitted linear gain.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from analysis.declaration import Study
from analysis.plotting import save_figure
from analysis.rows import LAW, value


def iss_figure(rows: list[dict[str, Any]], out: Path) -> tuple[list[Path], dict[str, float]]:
    """Tail sup ||Phi|| against sup ||eps||, per control law (alphabetical), with the
    gains fitted through the origin over the runs with an error; dashed, a law's run
    without error.
    """
    fig, ax = plt.subplots(figsize=(6, 4.5), constrained_layout=True)
    gains: dict[str, float] = {}
    groups: dict[str, list] = {}
    for r in rows:
        if "phi_tail_sup" in r:
            groups.setdefault(r.get(LAW) or LAW, []).append(r)
    for law, group in sorted(groups.items()):
        group.sort(key=lambda r: float(value(r, "estimator.delta") or 0))
        x = np.array([r["eps_sup"] for r in group])
        y = np.array([r["phi_tail_sup"] for r in group])
        pos = x > 1e-12
        (line,) = ax.loglog(x[pos], y[pos], "o-", label=law)
        if pos.sum() >= 2:
            gains[law] = float(np.linalg.lstsq(x[pos, None], y[pos], rcond=None)[0][0])
            xs = np.geomspace(x[pos].min(), x[pos].max(), 20)
            ax.loglog(
                xs,
                gains[law] * xs,
                ":",
                color=line.get_color(),
                label=rf"fit $\gamma$ = {gains[law]:.3g}",
            )
        if (~pos).any():
            ax.axhline(
                y[~pos].max(), color=line.get_color(), ls="--", lw=0.8, label=f"{law}, no error"
            )
    ax.set_xlabel(r"$\sup_t \|\epsilon\|_{L^2}$ (1/length)")
    ax.set_ylabel(r"tail $\sup \|\Phi\|_{L^2}$ (1/length)")
    ax.set_title("ISS gain: tracking error against estimation error")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, out, "iss_gain"), gains


def _label(row: dict[str, Any], key: str) -> str:
    """The row's value at ``key`` as a label (its directory when it has none)."""
    v = value(row, key)
    return row["dir"] if v is None else str(v)


def convergence_figure(
    rows: list[dict[str, Any]], series: dict[str, Any], varied: list[str], out: Path
) -> list[Path]:
    """``||Phi||`` curves overlaid, labelled by the first varied key, and each run's
    fitted decay rate beside the theoretical ``(alpha + sigma) lambda`` (1/s).
    """
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    label_key = varied[0] if varied else "dir"
    done = [r for r in rows if r["dir"] in series]
    for r in done:
        m = series[r["dir"]]
        ax0.semilogy(m["t"], m["phi_l2"], label=f"{label_key}={_label(r, label_key)}")
    ax0.set_xlabel("t (s)")
    ax0.set_ylabel(r"$\|p - p_*\|_{L^2}$ (1/length)")
    ax0.grid(True, which="both", alpha=0.3)
    ax0.legend(fontsize=8)
    ax0.set_title("convergence curves")
    x = np.arange(len(done))
    ax1.bar(x - 0.2, [r["rate_fit"] for r in done], 0.4, label="measured (fit, second half)")
    ax1.bar(x + 0.2, [r["rate_theory"] for r in done], 0.4, label=r"$(\alpha+\sigma)\lambda$")
    ax1.set_xticks(x, [_label(r, label_key) for r in done])
    ax1.set_xlabel(label_key)
    ax1.set_ylabel("exponential rate (1/s)")
    ax1.legend(fontsize=8)
    ax1.set_title("decay rates")
    return save_figure(fig, out, "convergence")


def draw_iss_gain(study: Study) -> list[Path]:
    """:func:`iss_figure`, and the fitted gain of each law."""
    paths, gains = iss_figure(study.usable, study.out)
    for law, g in gains.items():
        print(f"fitted ISS gain ({law}): {g:.4g} (tail sup ||Phi|| per unit sup ||eps||)")
    return paths


def draw_convergence(study: Study) -> list[Path]:
    """:func:`convergence_figure`, and each job's measured and theoretical rates."""
    paths = convergence_figure(study.usable, study.series, study.varied, study.out)
    for r in study.usable:
        print(
            f"{r['dir']}: rate {r['rate_fit']:.4g} 1/s measured, {r['rate_theory']:.4g} 1/s theory"
        )
    return paths
