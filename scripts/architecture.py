"""Draw ``docs/architecture.png``: the packages in their layers with the imports between
them (read from the source, so the picture is the code's), and one step of the loop.

    python scripts/architecture.py [--out docs/architecture.png]

The layers are those ``tests/test_layout.py`` checks (:data:`LAYERS` there); an arrow
from package A to package B says that some module of A imports some module of B.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch

ROOT = Path(__file__).resolve().parents[1]


def layout_test():
    """``tests/test_layout.py`` as a module (its layers and import graph)."""
    spec = importlib.util.spec_from_file_location("test_layout", ROOT / "tests" / "test_layout.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def package(module: str, layers: tuple[tuple[str, ...], ...]) -> str:
    """The box a module is drawn in: its layer's entry that holds it."""
    best = ""
    for members in layers:
        for prefix in members:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > len(best):
                best = prefix
    return best


LABELS = {
    "harness.compiled": "compiled\n(numba loops)",
    "harness.grid": "grid",
    "harness.velocity": "velocity",
    "harness.parameters": "parameters",
    "harness.fokker_planck": "fokker_planck",
    "harness.exact_solutions": "exact_solutions",
    "harness.targets": "targets/\n(target, init)",
    "harness.records": "records",
    "harness.protocols": "protocols",
    "harness.estimators": "estimators/\n(estimator, filter)",
    "harness.control": "control/\n(control)",
    "harness.plants": "plants/\n(plant, link, limit)",
    "harness.observers": "observers/\n(observers)",
    "harness.loop": "loop\n(trajectory)",
    "harness.runs": "runs/\n(build, run, sweeps)",
    "analysis": "analysis/\n(reads logs)",
    "harness.api": "api",
    "experiments": "experiments/\n(the Hydra app)",
}


def reduced(edges: set[tuple[str, str]]) -> set[tuple[str, str]]:
    """The transitive reduction of an acyclic graph: an edge is left out when a longer
    path joins its ends.
    """

    def reach(start: str, skip: tuple[str, str]) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            node = todo.pop()
            for a, b in edges:
                if a == node and (a, b) != skip and b not in seen:
                    seen.add(b)
                    todo.append(b)
        return seen

    return {(a, b) for a, b in edges if b not in reach(a, (a, b))}


def draw_layers(ax, test) -> None:
    """The layers bottom-up, one row each, each package with its modules, and the
    package-level imports that no longer path implies.
    """
    layers = test.LAYERS
    graph = test.graph()
    edges = set()
    for module, deps in graph.items():
        a = package(module, layers)
        for dep in deps:
            b = package(dep, layers)
            if a != b:
                edges.add((a, b))
    members_of: dict[str, list[str]] = {}
    for module in graph:
        name = package(module, layers)
        leaf = module[len(name) + 1 :] if module != name else ""
        if leaf:
            members_of.setdefault(name, []).append(leaf)
    where: dict[str, tuple[float, float]] = {}
    for row, members in enumerate(layers):
        y = row * 1.0
        width = 9.0 / max(len(members), 1)
        for k, name in enumerate(members):
            x = (k + 0.5) * width - 4.5
            where[name] = (x, y)
            w = min(width - 0.15, 8.6)
            box = FancyBboxPatch(
                (x - w / 2, y - 0.36), w, 0.72, boxstyle="round,pad=0.02",
                facecolor="#e8f0fb" if name.startswith("harness") else "#fbeee8",
                edgecolor="#35528a", linewidth=0.8,
            )  # fmt: skip
            ax.add_patch(box)
            label = LABELS.get(name, name).replace("\n", "  ")
            ax.text(x, y + 0.14, label, ha="center", va="center", fontsize=6.8, weight="bold")
            leaves = sorted({m.split(".")[0] for m in members_of.get(name, [])})
            if leaves and len(members) == 1:
                text = ", ".join(leaves)
                size = 5.6 if len(text) < 100 else 5.6 * 100 / len(text)
                ax.text(x, y - 0.17, text, ha="center", va="center", fontsize=size, color="#333333")
    for a, b in sorted(reduced(edges)):
        (xa, ya), (xb, yb) = where[a], where[b]
        ax.add_patch(
            FancyArrowPatch(
                (xa + 3.6 if xa == xb else xa, ya - 0.36),
                (xb + 3.6 if xa == xb else xb, yb + 0.36),
                arrowstyle="-|>",
                mutation_scale=6,
                color="#8796b5",
                linewidth=0.6,
            )
        )
    ax.set_xlim(-4.7, 4.7)
    ax.set_ylim(-0.6, len(layers) - 0.4)
    ax.set_title("Packages in their layers, lowest first (a module imports only from\n"
                 "its own layer or a lower one; arrows: imports no other path implies)",
                 fontsize=8.5)  # fmt: skip
    ax.axis("off")


def draw_step(ax) -> None:
    """One step of the loop (harness.loop) and who watches it."""
    nodes = {
        "plant": (0.0, 2.6, "plant\nrobots move under u_n\n(through the link)"),
        "estimator": (2.6, 2.6, "estimator\npredict under v_n,\nupdate"),
        "control": (5.2, 2.6, "control\nu_{n+1} from\nthe estimate"),
        "limit": (0.0, 1.1, "limit\np_inf under the law's\nfield of K_h p_inf"),
        "observers": (
            2.6,
            -0.3,
            "observers (each step's StepRecord)\nmetrics, swarm, motion,\n"
            "estimator, guard, live, log, progress",
        ),
    }
    for x, y, text in nodes.values():
        box = FancyBboxPatch(
            (x - 1.0, y - 0.42), 2.0, 0.84, boxstyle="round,pad=0.03",
            facecolor="#eef6ea", edgecolor="#3d7a35", linewidth=0.8,
        )  # fmt: skip
        ax.add_patch(box)
        ax.text(x, y, text, ha="center", va="center", fontsize=6.5)
    arrows = [
        ((1.0, 2.75), (1.6, 2.75), "measurement\n(KDE)", (1.3, 3.15), 0.0),
        ((3.6, 2.75), (4.2, 2.75), "estimate\n(p_hat, q_hat)", (3.9, 3.15), 0.0),
        (
            (5.2, 2.18),
            (0.4, 2.18),
            "command u, held over the step\n(a field, robots' velocities)",
            (2.6, 1.62),
            -0.25,
        ),
        ((0.0, 2.18), (0.0, 1.52), "", None, 0.0),
        ((0.6, 0.68), (1.8, 0.12), "", None, 0.0),
        ((5.0, 2.18), (3.4, 0.12), "", None, 0.0),
    ]
    for start, end, label, at, rad in arrows:
        ax.add_patch(
            FancyArrowPatch(
                start,
                end,
                arrowstyle="-|>",
                mutation_scale=9,
                color="#3d7a35",
                linewidth=1.0,
                connectionstyle=f"arc3,rad={rad}",
            )
        )
        if label:
            ax.text(*at, label, ha="center", va="center", fontsize=5.8, color="#2b5425")
    ax.set_xlim(-1.2, 6.4)
    ax.set_ylim(-1.0, 3.5)
    ax.set_aspect("equal")
    ax.set_title("One step n -> n + 1 (harness.loop.trajectory)", fontsize=9)
    ax.axis("off")


def main() -> None:
    """Draw and save the picture."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "architecture.png")
    args = parser.parse_args()
    test = layout_test()
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 6.4), width_ratios=[1.3, 1])
    draw_layers(left, test)
    draw_step(right)
    fig.tight_layout()
    fig.savefig(args.out, dpi=150)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
