"""The decentralised loop's frontier: where the robots are against what they send.

Study ``distributed_frontier`` (``conf/experiment/distributed_frontier.yaml``): the
designs of :mod:`harness.estimators.distributed` (``+design=...``: consensus form, what the robots
agree on, what a message carries) against the communication radius and the consensus
rounds per step, and (``make sweep-distributed_frontier`` adds them to the same sweep
directory) two designs on the graph of each robot's 6 nearest with ten rounds per step
and messages of the band ``band_limit = 2``. Its figure puts each point at

    x = bytes per robot per step            (tail mean of the metric ``bytes``)
    y = swarm_l2 / swarm_l2 of the centralised loop   (tail means, same seed and settings)

and draws the Pareto front (the points no other point beats on both axes). The
centralised loop is the run of ``conf/experiment/distributed_frontier_centralised.yaml``
(``estimator=filters``, the same plant, law and seed), found beside the sweep directory
as ``<sweep dir>_centralised/run.mcap``. A point is drawn filled when it meets the
message budget of the goal (at most :data:`MESSAGES_BUDGET` messages per robot per step,
messages of at most :data:`MESSAGE_BYTES_BUDGET` bytes), hollow otherwise.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np

from analysis.declaration import Study
from analysis.load import load_run
from analysis.plotting import save_figure
from analysis.rows import points, value

MESSAGES_BUDGET = 100.0
"""Messages per robot per step the goal allows."""

MESSAGE_BYTES_BUDGET = 2048.0
"""Bytes per message the goal allows."""

GOAL_RATIO = 1.2
"""``swarm_l2`` over the centralised loop's that the goal asks for."""

DESIGN_KEYS = ("estimator.consensus", "estimator.share", "estimator.messages")
"""The keys a design sets."""

FRONTIER_KEYS = (*DESIGN_KEYS, "estimator.radius", "estimator.rounds")
"""The keys the ``distributed_frontier`` figure draws against."""


def design_name(point: dict[str, Any]) -> str:
    """``consensus/share/messages`` of a point."""
    return "/".join(str(point[k]) for k in DESIGN_KEYS)


def graph_name(point: dict[str, Any]) -> str:
    """The point's graph: ``r = R``, ``k = K`` (its ``K`` nearest) or both."""
    radius, k = point.get("estimator.radius"), point.get("estimator.k_nearest")
    parts = [] if radius is None else [f"r = {float(radius):g}"]
    parts += [] if k is None else [f"k = {int(k)}"]
    return ", ".join(parts)


def centralised_swarm(sweep_dir: Path, tail: float) -> float:
    """The tail mean of ``swarm_l2`` of the centralised run beside ``sweep_dir``
    (``<sweep_dir>_centralised/run.mcap``, else the study's own,
    ``distributed_frontier_centralised/run.mcap`` in the same directory), over the last
    ``tail`` of its time; NaN when neither is there.
    """
    path = sweep_dir.parent / f"{sweep_dir.name}_centralised" / "run.mcap"
    if not path.is_file():
        path = sweep_dir.parent / "distributed_frontier_centralised" / "run.mcap"
    if not path.is_file():
        return math.nan
    run = load_run(path)
    t = np.asarray(run.metrics["t"], dtype=float)
    swarm = np.asarray(run.metrics["swarm_l2"], dtype=float)
    last = (t >= (1.0 - tail) * t.max()) & np.isfinite(swarm)
    return float(np.mean(swarm[last])) if last.any() else math.nan


def knn_reach(path: Path, k: int) -> float:
    """The largest distance from a robot to its ``k``-th nearest over the logged frames
    of ``/swarm/positions`` (length): the radius a graph of the ``k`` nearest needed.
    """
    from scipy.spatial import cKDTree

    run = load_run(path, topics={"/swarm/positions"})
    reach = 0.0
    for frame in run.positions:
        pts = np.asarray(frame, dtype=float)
        pts = pts.T if pts.shape[0] == 2 else pts
        dist, _ = cKDTree(pts).query(pts, k + 1)
        reach = max(reach, float(dist[:, k].max()))
    return reach


def pareto(xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Indices of the points that no other point beats on both axes (lower is better),
    sorted by ``x``.
    """
    order = np.lexsort((ys, xs))
    front, best = [], math.inf
    for i in order:
        if ys[i] < best:
            front.append(int(i))
            best = float(ys[i])
    return np.array(front, dtype=int)


def frontier_rows(rows: list[dict[str, Any]], central: float) -> list[dict[str, Any]]:
    """One row per point (design, radius, rounds): its bytes, messages, largest message,
    ``swarm_l2`` and ratio to ``central``, the gap to the centralised filter and the
    command disagreement (tail means, averaged over seeds).
    """
    out = []
    for a in points(rows):
        a = {**_constants(rows), **a}  # the keys no job varies are the same for every point
        out.append({
            "design": design_name(a),
            "graph": graph_name(a),
            "band_limit": a.get("estimator.band_limit"),
            "rounds": int(a["estimator.rounds"]),
            "bytes": float(a["bytes_tail_mean_mean"]),
            "messages": float(a["messages_tail_mean_mean"]),
            "message_bytes": float(a["message_bytes_tail_mean_mean"]),
            "swarm_l2": float(a["swarm_tail_mean_mean"]),
            "ratio": float(a["swarm_tail_mean_mean"]) / central,
            "central_gap": float(a["central_gap_tail_mean_mean"]),
            "disagreement": float(a["disagreement_tail_mean_mean"]),
            "seeds": int(a["jobs"]),
        })  # fmt: skip
    return sorted(out, key=lambda r: (r["design"], r["graph"], r["rounds"]))


def _constants(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The estimator keys of the first job (their values where no job varies them)."""
    prefix = "cfg:"
    keys = (*DESIGN_KEYS, "estimator.radius", "estimator.k_nearest", "estimator.band_limit",
            "estimator.rounds")  # fmt: skip
    return {k: value(rows[0], k) for k in keys if f"{prefix}{k}" in rows[0]} if rows else {}


def within_budget(row: dict[str, Any]) -> bool:
    """Whether a point meets the goal's message budget."""
    return row["messages"] <= MESSAGES_BUDGET and row["message_bytes"] <= MESSAGE_BYTES_BUDGET


def frontier_figure(table: list[dict[str, Any]], central: float, out: Path) -> list[Path]:
    """Ratio against bytes, one marker per design, one colour per graph, the rounds
    written beside each point, the Pareto front and the goal's ratio.
    """
    designs = sorted({r["design"] for r in table})
    radii = sorted({r["graph"] for r in table})
    markers = "osD^v<>p*h"
    fig, ax = plt.subplots(figsize=(9.5, 5.6), constrained_layout=True)
    for r in table:
        colour = f"C{radii.index(r['graph'])}"
        marker = markers[designs.index(r["design"]) % len(markers)]
        face = colour if within_budget(r) else "none"
        ax.scatter(r["bytes"], r["ratio"], marker=marker, s=60, edgecolors=colour,
                   facecolors=face, zorder=3)  # fmt: skip
        ax.annotate(f"m={r['rounds']}", (r["bytes"], r["ratio"]), textcoords="offset points",
                    xytext=(5, 3), fontsize=7)  # fmt: skip
    xs = np.array([r["bytes"] for r in table])
    ys = np.array([r["ratio"] for r in table])
    front = pareto(xs, ys)
    if front.size:
        ax.step(xs[front], ys[front], where="post", color="k", lw=1, alpha=0.6,
                label="Pareto front")  # fmt: skip
    ax.axhline(GOAL_RATIO, color="C3", ls="--", lw=1, label=f"goal: {GOAL_RATIO} x centralised")
    ax.axhline(1.0, color="0.5", ls=":", lw=1, label="centralised loop")
    for d in designs:
        ax.scatter([], [], marker=markers[designs.index(d) % len(markers)], color="0.3", label=d)
    for r_ in radii:
        ax.scatter([], [], marker="s", color=f"C{radii.index(r_)}", label=r_)
    ax.set_xscale("log")
    ax.set_xlabel("bytes per robot per step (tail mean)")
    ax.set_ylabel(r"swarm_l2 / centralised loop's (tail means)")
    ax.set_yscale("log")
    ax.set_title(
        f"decentralised designs against what they send (centralised swarm_l2 = {central:.3g} "
        f"1/length)\nfilled: within the budget of {MESSAGES_BUDGET:.0f} messages per robot per "
        f"step of at most {MESSAGE_BYTES_BUDGET:.0f} B each",
        fontsize=10,
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    return save_figure(fig, out, "distributed_frontier")


def draw_frontier(study: Study) -> list[Path]:
    """The study's figure (:data:`analysis.sweep.FIGURES`), and one line per point."""
    sweep_dir = study.sweep_dir
    central = centralised_swarm(sweep_dir, study.tail) if sweep_dir is not None else math.nan
    if sweep_dir is None or not math.isfinite(central):
        where = Path("SWEEP_DIR") if sweep_dir is None else sweep_dir
        raise SystemExit(
            f"error: no centralised run at {where}_centralised/run.mcap nor "
            f"{where.parent}/distributed_frontier_centralised/run.mcap: run "
            "python -m experiments.closed_loop +experiment=distributed_frontier_centralised"
        )
    table = frontier_rows(study.usable, central)
    print(f"centralised loop: swarm_l2 tail mean {central:.4g} 1/length")
    for row in study.usable:
        k = value(row, "estimator.k_nearest")
        if k not in (None, "", "None"):
            reach = knn_reach(sweep_dir / row["dir"] / "run.mcap", int(float(k)))
            print(
                f"{row['dir']}: a robot's {int(float(k))}th nearest at most {reach:.4g} "
                "length away at the logged frames"
            )
    for r in table:
        print(
            f"{r['design']}, {r['graph']}, band_limit {r['band_limit']}, rounds {r['rounds']}: "
            f"swarm_l2 "
            f"{r['swarm_l2']:.3g} 1/length = {r['ratio']:.3g} x centralised, "
            f"{r['bytes'] / 1e3:.4g} kB per robot per step in {r['messages']:.4g} messages "
            f"(largest {r['message_bytes']:.0f} B), central_gap_l2 {r['central_gap']:.3g} "
            f"1/length, command disagreement {r['disagreement']:.3g} length/s"
            + ("" if within_budget(r) else " [over the message budget]")
        )
    return frontier_figure(table, central, study.out)
