"""One picture of a swarm on its domain, from a run's log: the README's picture.

    python -m analysis.swarm_picture RUN [--at T] [--out docs/rooms.png]

Reads only the run's ``run.mcap`` (``RUN`` is the run directory or the file,
:func:`analysis.load.load_run`) and draws, at the logged time nearest ``T`` (default: the
last positions): the density estimate ``p_hat`` (``/fields/p_hat`` nearest that time,
left out on blocked cells), the target ``p_*`` as contours (``/fields/p_target``), the
obstacles in grey above them (``/domain/obstacles``, the robots' map of them: a wall
thinner than a cell blocks no cell, yet shows; none on the square) and the robots
(``/swarm/positions``) as black dots, into one square PNG written atomically. ``make
picture`` runs the README's run (the paper's law, N = 1024, ``domain=rooms
init=left_room``) and draws it at 15 s, while robots pass the door.

A log that cannot be read, or holds no positions or no ``p_hat``, is one line on
standard error and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from analysis.figures import draw_obstacles, on_free
from analysis.load import LogError, RunLog, load_run
from analysis.output import atomic_path

SIDE_INCHES = 5.0
"""The picture's side (inches; at :data:`DPI`, 600 pixels)."""

DPI = 120
"""Pixels per inch of the picture."""

FIELD_CMAP = matplotlib.colormaps["Blues"].with_extremes(bad=(0.0, 0.0, 0.0, 0.0))
"""The colour map of ``p_hat``: light to dark blue, blocked cells transparent (the
obstacles' grey beneath shows the robots' map of them, finer than the cells)."""

TARGET_COLOUR = "tab:orange"
"""The colour of the target's contours."""


def picture_problem(run: RunLog) -> str | None:
    """What the picture cannot be drawn without, or None."""
    if not run.positions:
        return "no robots' positions (/swarm/positions): a run of the mean-field plant?"
    if "/fields/p_hat" not in run.fields or "/fields/p_target" not in run.fields:
        return "no /fields/p_hat or /fields/p_target"
    return None


def draw_picture(run: RunLog, at: float | None, out: Path) -> tuple[Path, float]:
    """The picture of ``run`` at the positions' time nearest ``at`` (the last when
    None), written to ``out`` (PNG); returns the path and the time drawn (s).
    """
    i = len(run.positions) - 1 if at is None else int(np.argmin(np.abs(run.positions_t - at)))
    t = float(run.positions_t[i])
    robots = run.positions[i]
    p_hat = run.fields["/fields/p_hat"]
    _, field = p_hat.at(t)
    target = run.fields["/fields/p_target"].values[0, 0]
    xc, yc = p_hat.centres()
    extent = p_hat.extent()
    fig, ax = plt.subplots(figsize=(SIDE_INCHES, SIDE_INCHES), constrained_layout=True)
    try:
        ax.set_facecolor(FIELD_CMAP(0.0))  # blocked cells: no estimate, as p_hat = 0
        ax.imshow(
            on_free(run, field[0]),
            origin="lower",
            extent=extent,
            vmin=0,
            cmap=FIELD_CMAP,
            interpolation="bilinear",
        )
        ax.contour(xc, yc, on_free(run, target), levels=6, colors=TARGET_COLOUR, linewidths=0.9)
        draw_obstacles(ax, run, zorder=2)  # above the field: a wall thinner than a cell
        ax.scatter(robots[:, 0], robots[:, 1], s=2.0, c="k", linewidths=0, zorder=3)
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        choices = run.choices
        what = ", ".join(
            f"{k}={choices[k]}" for k in ("control", "domain") if choices.get(k) not in (None, "")
        )
        ax.set_title(f"{robots.shape[0]} robots, {what}, t = {t:.1f} s", fontsize=10)
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(out) as tmp:
            fig.savefig(tmp, dpi=DPI, format="png")
    finally:
        plt.close(fig)
    return out, t


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a run directory or its run.mcap")
    parser.add_argument("--at", type=float, default=None, help="time (s); default the last")
    parser.add_argument("--out", type=Path, default=Path("docs/rooms.png"))
    args = parser.parse_args(argv)
    try:
        run = load_run(args.run, poses=False)
    except LogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    why = picture_problem(run)
    if why is not None:
        print(f"error: {run.path}: {why}", file=sys.stderr)
        return 2
    path, t = draw_picture(run, args.at, args.out)
    print(f"{path} (t = {t:.2f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
