"""The paper's Figures 1 and 2 and an animation, from run logs only.

    python -m analysis.figures RUN_DIR [RUN_DIR ...] [--out figures] [--no-gif]

* ``fig1_<run>.png/.pdf`` (paper's Fig. 1): rows swarm, ``p_hat`` and velocity field,
  columns four logged times (0, about T/10, T/3 and T).
* ``fig2.png/.pdf`` (paper's Fig. 2): the target ``p_*`` and ``||p_hat - p_*||`` over
  time on a log scale (every run overlaid; ``||p - p_*||`` of the plant's mean-field
  density dashed, the limit ``N -> infinity`` for robots; with robots also
  ``swarm_l2`` = ``||K_h mu_N - K_h p_*||``, dash-dotted, and its finite-N floor as a
  95 % band from the ``theory`` record; for runs whose estimates are exact, ``||p_hat -
  p|| = 0`` at every step, the theoretical rate ``(alpha + sigma) lambda``, dotted).
* ``run_<run>.gif``: the swarm over ``p_*`` and ``p_hat`` through the run.

A run with obstacles (its log's ``/domain/mask`` and ``/domain/obstacles``) has its
obstacles filled grey beneath the fields, which are left out on blocked cells, and the
robots (:func:`draw_obstacles`, :func:`on_free`).
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.animation import FuncAnimation, PillowWriter
from matplotlib.collections import PatchCollection
from matplotlib.patches import Rectangle

from analysis.load import LogError, RunLog, load_run
from analysis.output import atomic_path
from analysis.plotting import save_figure


def _exact_estimates(run: RunLog) -> bool:
    """Whether the run's estimates are the plant's mean-field density and its gradient
    at every step (``eps_l2 = eps_g_l2 = 0`` throughout, as with ``estimator=exact``):
    the loop whose decay rate the theory gives.
    """
    m = run.metrics
    return all(k in m and len(m[k]) > 0 and not np.any(m[k]) for k in ("eps_l2", "eps_g_l2"))


def _float(text: object) -> float:
    """``text`` as a number, NaN when it is not one."""
    try:
        return float(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return float("nan")


_NAMES: dict[Path, str] = {}
"""Names of the runs in the figures, made distinct by :func:`name_runs`."""


def _name(run: RunLog) -> str:
    return _NAMES.get(run.path, run.path.parent.name or "run")


def name_runs(runs: list[RunLog]) -> list[str]:
    """A distinct name per run for file names and legends: its directory's name, with
    8 hex digits of its full path's SHA-256 where two runs' directories share a name.
    """
    plain = [r.path.parent.name or "run" for r in runs]
    names = [
        n
        if plain.count(n) == 1
        else f"{n}-{hashlib.sha256(str(r.path.resolve()).encode()).hexdigest()[:8]}"
        for n, r in zip(plain, runs, strict=True)
    ]
    _NAMES.update({r.path: n for r, n in zip(runs, names, strict=True)})
    return names


SHAPES = {"/fields/p_hat": 1, "/fields/p_target": 1, "/fields/velocity": 2}
"""The field topics the figures draw, with their number of components."""


def problem(run: RunLog) -> str | None:
    """Why the figures cannot be drawn from ``run`` (a topic or metric missing, a field
    of another shape than the log contract's, or no finite value to draw), or None.
    """
    missing = set(SHAPES) - set(run.fields)
    m = run.metrics
    if missing or "phat_target_l2" not in m or "phi_l2" not in m or len(m.get("t", ())) == 0:
        return f"lacks {sorted(missing) or ['/metrics']}"
    shape = run.fields["/fields/p_hat"].values.shape[-2:]
    for topic, components in SHAPES.items():
        series = run.fields[topic]
        cell = np.asarray(series.cell_size, dtype=float)
        if series.values.shape[1] != components or series.values.shape[-2:] != shape:
            return (
                f"{topic} holds {series.values.shape[1]} component(s) on "
                f"{series.values.shape[-2]} x {series.values.shape[-1]} cells; the figures "
                f"draw {components} on the grid of /fields/p_hat ({shape[0]} x {shape[1]})"
            )
        if min(shape) < 2 or not (np.isfinite(cell).all() and (cell > 0).all()):
            return f"{topic}: a grid of at least 2 x 2 cells of positive size is drawn"
        if not np.isfinite(series.values).any():
            return f"{topic} holds no finite value"
    if not np.isfinite(m["t"]).all():
        return "the metrics' times are not all finite"
    return None


OBSTACLE_GREY = "0.6"
"""Fill colour of the obstacles in every panel of a run with obstacles."""


def draw_obstacles(ax, run: RunLog, zorder: float = -1) -> None:
    """The run's obstacles (``/domain/obstacles``, :class:`analysis.load.DomainShapes`),
    filled grey, by default beneath everything else on ``ax`` (``zorder`` -1; images
    are drawn at 0, points at 1); nothing for a run on the square.
    """
    if run.domain is None or not len(run.domain.rectangles):
        return
    boxes = [Rectangle((x0, y0), x1 - x0, y1 - y0) for x0, y0, x1, y1 in run.domain.rectangles]
    patches = PatchCollection(boxes, facecolor=OBSTACLE_GREY, edgecolor="none", zorder=zorder)
    ax.add_collection(patches)


def on_free(run: RunLog, values: np.ndarray) -> np.ndarray:
    """``values`` ``(ny, nx)`` masked on the run's blocked cells (``/domain/mask``), so
    an image of them shows the obstacles beneath; unchanged on the square.
    """
    free = None if run.domain is None else run.domain.free
    if free is None or free.shape != values.shape:
        return values
    return np.ma.masked_where(~free, values)


def field_cmap(run: RunLog):
    """The colour map of a field's image: matplotlib's default (None) on the square;
    with obstacles the default with its blocked (masked) cells grey, like the obstacles.
    """
    if run.domain is None or run.domain.free is None:
        return None
    return matplotlib.colormaps[plt.rcParams["image.cmap"]].with_extremes(bad=OBSTACLE_GREY)


def figure1(run: RunLog, out: Path, stem: str) -> list[Path]:
    """Swarm, ``p_hat`` and ``v`` at four times."""
    p_hat = run.fields["/fields/p_hat"]
    vel = run.fields["/fields/velocity"]
    target = run.fields["/fields/p_target"].values[0, 0]
    t_end = float(p_hat.t[-1])
    times = [0.0, t_end / 10, t_end / 3, t_end]
    fig, axes = plt.subplots(3, 4, figsize=(13, 9.6), constrained_layout=True)
    vmax = float(np.nanmax(p_hat.values))
    extent = p_hat.extent()
    xc, yc = p_hat.centres()
    step = max(1, len(xc) // 20)
    for col, t in enumerate(times):
        ax = axes[0, col]
        if run.positions:
            i = int(np.argmin(np.abs(run.positions_t - t)))
            pts = run.positions[i]
            draw_obstacles(ax, run)
            ax.contour(xc, yc, on_free(run, target), levels=6, colors="0.75", linewidths=0.6)
            ax.scatter(pts[:, 0], pts[:, 1], s=1.5, c="k", alpha=0.7, linewidths=0)
            ax.set_title(f"swarm, t = {run.positions_t[i]:.1f} s")
        else:
            ax.text(0.5, 0.5, "mean-field plant\n(no robots)", ha="center", va="center")
            ax.set_title(f"t = {t:.1f} s")
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_aspect("equal")
        ts, field = p_hat.at(t)
        draw_obstacles(axes[1, col], run)
        im = axes[1, col].imshow(
            on_free(run, field[0]),
            origin="lower",
            extent=extent,
            vmin=0,
            vmax=vmax,
            cmap=field_cmap(run),
        )
        axes[1, col].set_title(rf"$\hat p$, t = {ts:.1f} s")
        tv, v = vel.at(t)
        speed = np.hypot(v[0], v[1])
        draw_obstacles(axes[2, col], run)
        q = axes[2, col].quiver(
            xc[::step],
            yc[::step],
            v[0][::step, ::step],
            v[1][::step, ::step],
            speed[::step, ::step],
            cmap="magma",
        )
        axes[2, col].set_aspect("equal")
        axes[2, col].set_xlim(extent[0], extent[1])
        axes[2, col].set_ylim(extent[2], extent[3])
        axes[2, col].set_title(f"v, t = {tv:.1f} s (max {speed.max():.2g})")
        fig.colorbar(q, ax=axes[2, col], shrink=0.7, label="speed (length/s)")
    fig.colorbar(im, ax=axes[1, :], shrink=0.8, label=r"$\hat p$ (1/length$^2$)")
    fig.suptitle("Swarm (top), density estimate (middle), velocity field (bottom)")
    return save_figure(fig, out, stem)


def figure2(runs: list[RunLog], out: Path) -> list[Path]:
    """Target and convergence error of every run."""
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    tgt = runs[0].fields["/fields/p_target"]
    draw_obstacles(ax0, runs[0])
    im = ax0.imshow(
        on_free(runs[0], tgt.values[0, 0]),
        origin="lower",
        extent=tgt.extent(),
        cmap=field_cmap(runs[0]),
    )
    ax0.set_title(r"target $p_*$")
    fig.colorbar(im, ax=ax0, label="1/length$^2$")
    for run in runs:
        m = run.metrics
        (line,) = ax1.semilogy(
            m["t"], m["phat_target_l2"], label=rf"$\|\hat p - p_*\|$ {_name(run)}"
        )
        robots = "swarm_l2" in m and np.isfinite(m["swarm_l2"]).any()
        ax1.semilogy(
            m["t"],
            m["phi_l2"],
            ls="--",
            lw=0.9,
            color=line.get_color(),
            label=(
                rf"$\|p_\infty - p_*\|$ (limit $N\to\infty$) {_name(run)}"
                if robots
                else rf"$\|p - p_*\|$ (mean-field) {_name(run)}"
            ),
        )
        if robots:
            swarm_band(ax1, run, line.get_color())
        rate = _float(run.metadata.get("theory", {}).get("rate_exact"))
        if _exact_estimates(run) and np.isfinite(rate):
            # with exact estimates the theory gives the rate: draw it over the second half
            half = m["t"] >= m["t"][-1] / 2
            t_ref = m["t"][half]
            ax1.semilogy(
                t_ref,
                m["phi_l2"][half][0] * np.exp(-rate * (t_ref - t_ref[0])),
                "k:",
                label=rf"theory $(\alpha+\sigma)\lambda$ = {rate:.3g} 1/s",
            )
    ax1.set_xlabel("t (s)")
    ax1.set_ylabel("L2 norm (1/length)")
    ax1.set_title("convergence error")
    ax1.grid(True, which="both", alpha=0.3)
    ax1.legend(fontsize=7)
    return save_figure(fig, out, "fig2")


def swarm_band(ax, run: RunLog, color: str) -> None:
    """``swarm_l2`` (where the robots are, against ``K_h p_*``) and its finite-N floor:
    the mean and 95 % band of the same distance for N robots drawn from ``p_*``.
    """
    m = run.metrics
    ok = np.isfinite(m["swarm_l2"])
    ax.semilogy(
        m["t"][ok],
        m["swarm_l2"][ok],
        ls="-.",
        lw=1.0,
        color=color,
        label=rf"$\|K_h\mu_N - K_h p_*\|$ (robots) {_name(run)}",
    )
    theory = run.metadata.get("theory", {})
    try:
        mean, lo, hi = (float(theory[f"swarm_l2_floor_{k}"]) for k in ("mean", "lo", "hi"))
    except (KeyError, ValueError):
        return
    t = m["t"]
    ax.fill_between([t[0], t[-1]], lo, hi, color=color, alpha=0.15, lw=0)
    ax.axhline(mean, color=color, lw=0.6, ls=":", label=f"finite-N floor (95 % band) {_name(run)}")


def animation(run: RunLog, out: Path, stem: str, max_frames: int = 80) -> Path:
    """GIF of the swarm over the target and of ``p_hat``."""
    p_hat = run.fields["/fields/p_hat"]
    target = run.fields["/fields/p_target"].values[0, 0]
    frames = np.unique(np.linspace(0, len(p_hat.t) - 1, min(max_frames, len(p_hat.t))).astype(int))
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(8, 4), constrained_layout=True)
    extent = p_hat.extent()
    xc, yc = p_hat.centres()
    draw_obstacles(ax0, run)
    draw_obstacles(ax1, run)
    ax0.contour(xc, yc, on_free(run, target), levels=6, colors="0.7", linewidths=0.6)
    scat = ax0.scatter([], [], s=1.5, c="k", linewidths=0)
    ax0.set_xlim(extent[0], extent[1])
    ax0.set_ylim(extent[2], extent[3])
    ax0.set_aspect("equal")
    im = ax1.imshow(
        on_free(run, p_hat.values[0, 0]),
        origin="lower",
        extent=extent,
        vmin=0,
        vmax=float(np.nanmax(p_hat.values)),
        cmap=field_cmap(run),
    )
    title = fig.suptitle("")

    def draw(k: int):
        t = p_hat.t[frames[k]]
        if run.positions:
            i = int(np.argmin(np.abs(run.positions_t - t)))
            scat.set_offsets(run.positions[i])
        im.set_data(on_free(run, p_hat.values[frames[k], 0]))
        title.set_text(f"t = {t:.1f} s: swarm over p* contours (left), p_hat (right)")
        return scat, im, title

    anim = FuncAnimation(fig, draw, frames=len(frames), blit=False)
    path = out / f"{stem}.gif"
    try:
        with atomic_path(path) as tmp:
            anim.save(tmp, writer=PillowWriter(fps=10))
    finally:
        plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    """Write the figures of the given runs; print their paths."""
    parser = argparse.ArgumentParser(description="Figures 1 and 2 and a GIF from run logs.")
    parser.add_argument("runs", nargs="+", type=Path, help="run directories or run.mcap files")
    parser.add_argument("--out", type=Path, default=Path("figures"), help="output directory")
    parser.add_argument("--no-gif", action="store_true", help="skip the animation")
    args = parser.parse_args(argv)
    try:
        runs = [load_run(p, poses=False) for p in args.runs]  # the figures use no poses
    except LogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for run in runs:
        why = problem(run)
        if why is not None:
            print(f"error: {run.path}: {why}", file=sys.stderr)
            return 2
    args.out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    single = len(runs) == 1
    name_runs(runs)
    for run in runs:
        stem = "fig1" if single else f"fig1_{_name(run)}"
        written += figure1(run, args.out, stem)
        if not args.no_gif:
            written.append(animation(run, args.out, "run" if single else f"run_{_name(run)}"))
    written += figure2(runs, args.out)
    for p in written:
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
