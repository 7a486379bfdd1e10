"""The leaderboard of a benchmark, from its runs' logs: data, figure and page.

    python -m analysis.leaderboard OUT [--page docs/benchmark.md] [--command "make ..."]
    python -m analysis.leaderboard --render docs/benchmark.md   # the page from its data

``OUT`` is a benchmark's directory (:mod:`harness.benchmark.driver`). Every number comes
from the logs of its runs (``OUT/tune/*/run.mcap``, ``OUT/verdict/*/run.mcap``: their
statistics by :mod:`analysis.run_stats`, what each run was for from the ``point`` block
of its logged config); ``OUT/benchmark.json`` adds what has no log: the tier, the
machine, and the scenario and law pairs that cannot run. Three files are written,
each atomically: the data ``PAGE_DIR/PAGE_STEM/data.json``, the figure of the fronts
``PAGE_DIR/PAGE_STEM/fronts.png`` and the page, rendered from the data alone
(:func:`render`), so the committed page can be checked against its committed data.

Per scenario and law, over the tier's fresh seeds (the same seeds for every law):

* ``swarm_ratio`` (tail ``swarm_l2`` over its finite-N floor, dimensionless) and
  ``effort_integral`` (length^2 / s) as geometric means with 95 % intervals on the log
  scale (:func:`analysis.stats.geometric_ci`);
* ``settling_time`` (s) as the Kaplan-Meier median with runs that never settled censored
  at the run's end (:func:`analysis.stats.km_median`);
* ``ms_per_step``, wall time per step (ms), geometric mean;
* against the tier's ``budget_law`` at the matched effort budget: the geometric mean of
  the per-seed ratios of ``swarm_ratio`` with its interval, the paired t-test on the log
  ratios and Holm's correction over the laws of the scenario
  (:func:`analysis.stats.paired_ratio`, :func:`analysis.stats.holm`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from analysis.output import atomic_path, write_text
from analysis.rows import analyse, value
from analysis.stats import BEYOND, geometric_ci, holm, km_median, paired_ratio

ROLES = ("matched", "best", "default")
"""The points of a law the verdict re-runs (:mod:`harness.benchmark.tuning`)."""


def _f(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _json_number(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _summary(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """A role's statistics over its seeds (module docstring)."""
    err = geometric_ci([r.get("swarm_ratio") for r in rows])
    eff = geometric_ci([r.get("effort_integral") for r in rows])
    ms = geometric_ci([r.get("ms_per_step") for r in rows])
    settle = km_median([r.get("settling_time") for r in rows], [r.get("t_end") for r in rows])
    return {
        "seeds": sorted(int(_f(value(r, "seed"))) for r in rows),
        "completed": sum(r.get("state") == "completed" for r in rows),
        "error": [_json_number(err.mean), _json_number(err.low), _json_number(err.high)],
        "effort": [_json_number(eff.mean), _json_number(eff.low), _json_number(eff.high)],
        "ms_per_step": _json_number(ms.mean),
        "settling": [
            _json_number(settle.median),
            _json_number(settle.low),
            _json_number(settle.high),
        ],
        "t_end": _json_number(max((_f(r.get("t_end")) for r in rows), default=math.nan)),
    }


def _gains(row: Mapping[str, Any]) -> dict[str, Any]:
    """The tunable gains of a run's law, as the run used them."""
    out = {}
    prefix = "cfg:control.tunable."
    names = {k[len(prefix) :].split(".")[0] for k in row if k.startswith(prefix)}
    for name in sorted(names):
        out[name] = value(row, f"control.{name}")
    return out


def _tuning(rows: Iterable[Mapping[str, Any]]) -> dict[tuple[str, str], list[dict[str, Any]]]:
    """Every tuning point per scenario and law, its objectives the geometric means over
    the tuning seeds (None when a run failed).
    """
    by_point: dict[tuple[str, str, str], list[Mapping[str, Any]]] = {}
    for r in rows:
        key = (value(r, "point.scenario"), value(r, "point.law"), value(r, "point.trial"))
        by_point.setdefault(key, []).append(r)
    out: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for (scenario, law, tag), members in sorted(by_point.items()):
        ok = all(m.get("state") == "completed" for m in members)
        err = geometric_ci([m.get("swarm_ratio") for m in members])
        eff = geometric_ci([m.get("effort_integral") for m in members])
        good = ok and err.n == len(members) and eff.n == len(members)
        out.setdefault((scenario, law), []).append(
            {
                "trial": tag,
                "gains": _gains(members[0]),
                "error": _json_number(err.mean) if good else None,
                "effort": _json_number(eff.mean) if good else None,
            }
        )
    return out


def _on_front(points: list[dict[str, Any]]) -> None:
    """Mark each completed tuning point on or off the Pareto front (in place)."""
    done = [p for p in points if p["error"] is not None and p["effort"] is not None]
    for p in points:
        p["front"] = p in done and not any(
            o["error"] <= p["error"]
            and o["effort"] <= p["effort"]
            and (o["error"] < p["error"] or o["effort"] < p["effort"])
            for o in done
        )


def collect(out: Path) -> dict[str, Any]:
    """The leaderboard's data from a benchmark's directory (module docstring).

    Raises:
        FileNotFoundError: without ``OUT/benchmark.json`` (not a finished benchmark).
    """
    record = json.loads((out / "benchmark.json").read_text())
    tier = record["tier"]
    tune_rows = analyse(out / "tune")[0] if (out / "tune").is_dir() else []
    verdict_rows = analyse(out / "verdict")[0] if (out / "verdict").is_dir() else []
    tuning = _tuning(tune_rows)
    refused = {(r["scenario"], r["law"]): r["reason"] for r in record.get("refused", [])}
    by_role: dict[tuple[str, str, str], list[Mapping[str, Any]]] = {}
    meta: dict[str, Mapping[str, Any]] = {}
    for r in verdict_rows:
        s, law = value(r, "point.scenario"), value(r, "point.law")
        meta.setdefault(s, r)
        roles = value(r, "point.roles") or []
        roles = json.loads(roles) if isinstance(roles, str) else roles
        for role in roles:
            by_role.setdefault((s, law, role), []).append(r)
    commits = sorted({str(r.get("code", "")) for r in verdict_rows + tune_rows} - {""})
    wall = sum(
        _f(r.get("wall_s")) for r in verdict_rows + tune_rows if math.isfinite(_f(r.get("wall_s")))
    )
    scenarios = []
    for s in tier["scenarios"]:
        m = meta.get(s, {})
        laws = []
        for law in tier["laws"]:
            entry: dict[str, Any] = {"law": law, "refused": refused.get((s, law))}
            roles = {}
            for role in ROLES:
                rows = sorted(by_role.get((s, law, role), []), key=lambda r: _f(value(r, "seed")))
                if rows:
                    roles[role] = {
                        **_summary(rows),
                        "gains": _gains(rows[0]),
                        "trial": value(rows[0], "point.trial"),
                    }
                    entry["uses"] = rows[0].get("law_uses", "")
            entry["roles"] = roles
            points = tuning.get((s, law), [])
            _on_front(points)
            entry["tuning"] = points
            laws.append(entry)
        _versus(laws, by_role, s, tier["budget_law"])
        scenarios.append(
            {
                "name": s,
                "description": value(m, "scenario.description") or "",
                "why": value(m, "scenario.why") or "",
                "n": value(m, "agents.n"),
                "t_final": value(m, "sim.t_final"),
                "plant": value(m, "plant"),
                "domain": value(m, "domain"),
                "budget": record.get("budgets", {}).get(s),
                "laws": laws,
            }
        )
    return {
        "tier": tier,
        "machine": record.get("machine", {}),
        "stage_s": record.get("stage_s", {}),
        "code": commits,
        "runs": len(tune_rows) + len(verdict_rows),
        "run_wall_s": wall,
        "scenarios": scenarios,
    }


def _versus(
    laws: list[dict[str, Any]],
    by_role: Mapping[tuple[str, str, str], list[Mapping[str, Any]]],
    scenario: str,
    base: str,
) -> None:
    """Each law's ``swarm_ratio`` at the matched budget against ``base``'s, paired by
    seed, with Holm's correction over the scenario's laws (in place: ``versus``).
    """
    ref = {
        int(_f(value(r, "seed"))): r.get("swarm_ratio")
        for r in by_role.get((scenario, base, "matched"), [])
    }
    tests = []
    for entry in laws:
        if entry["law"] == base or "matched" not in entry["roles"]:
            entry["versus"] = None
            continue
        mine = {
            int(_f(value(r, "seed"))): r.get("swarm_ratio")
            for r in by_role.get((scenario, entry["law"], "matched"), [])
        }
        seeds = sorted(set(ref) & set(mine))
        if not seeds:
            entry["versus"] = None
            continue
        pr = paired_ratio([mine[k] for k in seeds], [ref[k] for k in seeds])
        entry["versus"] = {
            "ratio": _json_number(pr.ratio),
            "low": _json_number(pr.low),
            "high": _json_number(pr.high),
            "p": _json_number(pr.p),
            "n": pr.n,
        }
        tests.append(entry)
    adjusted = holm([_f(e["versus"]["p"]) for e in tests])
    for entry, p in zip(tests, adjusted, strict=True):
        entry["versus"]["p_holm"] = _json_number(p)


# -- the page ------------------------------------------------------------------------


def _g(x: Any, fmt: str = ".3g") -> str:
    return "n/a" if x is None or not math.isfinite(_f(x)) else format(_f(x), fmt)


def _ci(triple: Sequence[Any] | None, fmt: str = ".3g") -> str:
    if not triple or triple[0] is None:
        return "n/a"
    mean, low, high = triple
    if low is None or high is None:
        return _g(mean, fmt)
    return f"{_g(mean, fmt)} [{_g(low, fmt)}, {_g(high, fmt)}]"


def _settling(role: Mapping[str, Any] | None) -> str:
    if role is None:
        return "n/a"
    median, low, high = role["settling"]
    if median is None:
        return BEYOND
    hi = BEYOND if high is None else _g(high, ".3g")
    lo = _g(low, ".3g")
    return f"{_g(median, '.3g')} [{lo}, {hi}]"


def _gain_text(gains: Mapping[str, Any]) -> str:
    """The gains in words (a gain left at null, such as no speed cap, reads "none")."""
    return ", ".join(f"{k} {'none' if v is None else _g(v)}" for k, v in gains.items()) or "none"


def _versus_text(v: Mapping[str, Any] | None) -> str:
    if not v:
        return "n/a"
    return f"{_ci([v['ratio'], v['low'], v['high']])}, p = {_g(v.get('p_holm'), '.2g')}"


def scenario_table(scenario: Mapping[str, Any], base: str) -> str:
    """The table of one scenario (module docstring), Markdown."""
    head = (
        "| law | swarm_l2 / floor at matched effort | its effort (length^2/s) | "
        f"against {base} (ratio, Holm p) | best swarm_l2 / floor | its effort | best gains | "
        "default swarm_l2 / floor | settling at best (s) | ms per step | uses |"
    )
    lines = [head, "|" + "---|" * 11]
    for e in scenario["laws"]:
        if e.get("refused"):
            lines.append(f"| {e['law']} | cannot run: {e['refused']} |" + " |" * 9)
            continue
        r = e["roles"]
        m, b, d = r.get("matched"), r.get("best"), r.get("default")
        lines.append(
            "| "
            + " | ".join(
                [
                    e["law"],
                    _ci(m["error"]) if m else "no point within the budget",
                    _ci(m["effort"]) if m else "n/a",
                    _versus_text(e.get("versus")) if e["law"] != base else "(reference)",
                    _ci(b["error"]) if b else "n/a",
                    _ci(b["effort"]) if b else "n/a",
                    _gain_text(b["gains"]) if b else "n/a",
                    _ci(d["error"]) if d else "n/a",
                    _settling(b),
                    _g(b["ms_per_step"]) if b else "n/a",
                    str(e.get("uses", "")) or "n/a",
                ]
            )
            + " |"
        )
    return "\n".join(lines)


def findings(data: Mapping[str, Any], alpha: float = 0.05) -> list[str]:
    """One bullet per scenario, from the data alone: the law with the least
    ``swarm_ratio`` at the matched budget and at its best point, and the laws that the
    paired tests (Holm-adjusted, at level ``alpha``) find better or worse than the
    budget law at the matched budget.
    """
    base = data["tier"]["budget_law"]
    lines = []
    for s in data["scenarios"]:
        ran = [e for e in s["laws"] if not e.get("refused")]

        def least(role: str, pool: list[dict[str, Any]] = ran) -> tuple[str, Any] | None:
            have = [
                (e["roles"][role]["error"][0], e["law"])
                for e in pool
                if role in e["roles"] and e["roles"][role]["error"][0] is not None
            ]
            return (min(have)[1], min(have)[0]) if have else None

        matched, best = least("matched"), least("best")
        better = [
            e["law"]
            for e in ran
            if e.get("versus")
            and _f(e["versus"].get("p_holm")) <= alpha
            and _f(e["versus"]["ratio"]) < 1
        ]
        worse = [
            e["law"]
            for e in ran
            if e.get("versus")
            and _f(e["versus"].get("p_holm")) <= alpha
            and _f(e["versus"]["ratio"]) > 1
        ]
        none = [e["law"] for e in ran if "matched" not in e["roles"]]
        refused = [e["law"] for e in s["laws"] if e.get("refused")]
        text = f"- `{s['name']}`: "
        text += (
            f"least swarm_l2 / floor at the matched effort: {matched[0]} ({_g(matched[1])}); "
            if matched
            else "no law within the matched effort; "
        )
        text += f"at any effort: {best[0]} ({_g(best[1])}). " if best else ""
        text += (
            f"Against {base} at the matched effort (paired, Holm, level {alpha:g}): "
            f"better: {', '.join(better) or 'none'}; worse: {', '.join(worse) or 'none'}."
        )
        if none:
            text += f" No point within the budget: {', '.join(none)}."
        if refused:
            text += f" Cannot run here: {', '.join(refused)}."
        lines.append(text)
    return lines


def _stages(stage_s: Mapping[str, float]) -> str:
    """The benchmark's wall time per stage, as words (empty when unrecorded)."""
    if not stage_s:
        return ""
    parts = [f"{name} {_g(seconds / 60, '.2g')} min" for name, seconds in stage_s.items()]
    return "; wall time " + ", ".join(parts)


def render(data: Mapping[str, Any], figure: str = "benchmark/fronts.png") -> str:
    """The leaderboard page from its data alone."""
    tier = data["tier"]
    machine = data.get("machine", {})
    out = [
        "# Benchmark: the field's laws, each tuned, on fresh seeds",
        "",
        "<!-- generated by python -m analysis.leaderboard from benchmark/data.json; "
        "do not edit -->",
        "",
        f"Tier `{tier['name']}`: {len(tier['scenarios'])} scenarios, {len(tier['laws'])} laws, "
        f"{tier['trials']} tuning trials per law and scenario besides the default gains, on "
        f"tuning seeds {tier['tuning_seeds']}; verdicts on the fresh seeds "
        f"{tier['verdict_seeds']}, the same for every law. Matched effort: the effort of "
        f"`{tier['budget_law']}` at its default gains. {data['runs']} runs, "
        f"{_g(data['run_wall_s'] / 3600, '.2g')} h of run time summed over the runs"
        + _stages(data.get("stage_s", {}))
        + ".",
        "",
        f"Made with `{data.get('command', 'python -m experiments.benchmark')}` on "
        f"{machine.get('cpu', 'an unrecorded CPU')} ({machine.get('cores', '?')} cores), "
        "code SHA-256 (harness, analysis, experiments, conf) "
        f"{', '.join(c[:12] for c in data['code']) or 'unrecorded'}.",
        "",
        "How to read it (definitions in [the metrics page](metrics.md) and "
        "[the statistics](benchmark-method.md)): `swarm_l2 / floor` is the tail mean of the "
        "robots' KDE distance to `K_h * p_*` over what N independent draws from `p_*` "
        "give (1: as good as independent draws); effort is the integrated mean squared "
        "commanded speed (length^2 / s). Intervals are 95 %, on the log scale for "
        "positive quantities; settling times are Kaplan-Meier medians with runs that "
        "never settled counted at the run's end.",
        "",
        f"![fronts]({figure})",
        "",
        "Per scenario, error against effort (both on log axes): small dots every tuning "
        "point (tuning seeds), lines each law's front among them; large circles each law's "
        "best point and squares its point at the matched effort, re-run on the fresh seeds "
        "with 95 % intervals; the dotted line the effort budget.",
        "",
    ]
    out += ["## What it shows", "", *findings(data), ""]
    for s in data["scenarios"]:
        out += [
            f"## `{s['name']}`: {s['description']}",
            "",
            f"Why: {s['why']}. N = {s['n']}, {s['t_final']} s, plant `{s['plant']}`, "
            f"domain `{s['domain']}`; effort budget {_g(s['budget'])} length^2 / s.",
            "",
            scenario_table(s, tier["budget_law"]),
            "",
        ]
    return "\n".join(out)


def figure(data: Mapping[str, Any], path: Path) -> None:
    """The fronts: per scenario, error against effort of every tuning point (small), the
    front (line) and the verdicts at the chosen points (large, with intervals).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenarios = data["scenarios"]
    cols = min(3, len(scenarios))
    rows = math.ceil(len(scenarios) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.8 * rows), squeeze=False)
    laws = data["tier"]["laws"]
    colours = plt.get_cmap("tab10")
    for ax, s in zip(axes.flat, scenarios, strict=False):
        for k, e in enumerate(s["laws"]):
            c = colours(k % 10)
            done = [p for p in e["tuning"] if p["error"] is not None]
            if done:
                ax.scatter(
                    [p["effort"] for p in done],
                    [p["error"] for p in done],
                    s=8,
                    color=c,
                    alpha=0.35,
                )
                fr = sorted((p for p in done if p["front"]), key=lambda p: p["effort"])
                ax.plot([p["effort"] for p in fr], [p["error"] for p in fr], color=c, lw=1)
            for role, marker in (("best", "o"), ("matched", "s")):
                r = e["roles"].get(role)
                if r and r["error"][0] is not None and r["effort"][0] is not None:
                    y, lo, hi = r["error"]
                    ax.errorbar(
                        [r["effort"][0]],
                        [y],
                        yerr=[[y - (lo or y)], [(hi or y) - y]],
                        fmt=marker,
                        color=c,
                        ms=6,
                        label=e["law"] if role == "best" else None,
                    )
        if s.get("budget"):
            ax.axvline(s["budget"], color="0.5", ls=":", lw=1)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(s["name"])
        ax.set_xlabel("effort (length$^2$/s)")
        ax.set_ylabel("swarm_l2 / floor")
    for ax in list(axes.flat)[len(scenarios) :]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(laws), 8), fontsize=8)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def paths(page: Path) -> tuple[Path, Path]:
    """The data and figure that go with ``page``."""
    folder = page.parent / page.stem
    return folder / "data.json", folder / "fronts.png"


def main(argv: Iterable[str] | None = None) -> int:
    """Write the leaderboard (module docstring); exit status 2 for a directory that holds
    no finished benchmark.
    """
    parser = argparse.ArgumentParser(prog="python -m analysis.leaderboard")
    parser.add_argument("out", nargs="?", type=Path, help="a benchmark's directory")
    parser.add_argument("--page", type=Path, help="the page (default OUT/leaderboard.md)")
    parser.add_argument("--command", help="the command that made the benchmark, for the page")
    parser.add_argument("--render", type=Path, help="re-render PAGE from its data only")
    args = parser.parse_args(list(argv) if argv is not None else None)
    if args.render is not None:
        data_path, _ = paths(args.render)
        data = json.loads(data_path.read_text())
        write_text(args.render, render(data, f"{args.render.stem}/fronts.png"))
        print(args.render)
        return 0
    if args.out is None:
        parser.error("give a benchmark's directory or --render PAGE")
    if not (args.out / "benchmark.json").is_file():
        print(f"{args.out}: no benchmark.json (not a finished benchmark)", file=sys.stderr)
        return 2
    page = args.page or args.out / "leaderboard.md"
    data = collect(args.out)
    data["command"] = (
        args.command or f"python -m experiments.benchmark --tier {data['tier']['name']}"
    )
    data_path, figure_path = paths(page)
    data_path.parent.mkdir(parents=True, exist_ok=True)
    write_text(data_path, json.dumps(data, indent=1, sort_keys=True) + "\n")
    figure(data, figure_path)
    write_text(page, render(data, f"{page.stem}/fronts.png"))
    print(page)
    print(figure_path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
