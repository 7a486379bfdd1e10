"""Analyse a sweep from its logs: a tidy CSV and the study's figures.

    python -m analysis.sweep SWEEP_DIR [--out DIR] [--tail 0.25]

Reads every job directory below ``SWEEP_DIR`` that holds a ``run.mcap``, and only the
log: its ``config`` record (the resolved config), its ``status`` and ``theory`` records
and its ``/metrics``. Writes ``sweep.csv`` (one row per job; every config key whose
value differs between the jobs is a column) and figures chosen by what the sweep
varies:

* ``estimator.delta`` (ISS gain curve, ``iss_gain.png/.pdf``): the tail supremum of
  ``||Phi|| = ||p - p_*||`` against the supremum of ``||eps||``, one curve per control
  law (grouped by the logged ``control._target_``), with the fitted linear gain;
* ``agents.n`` (``agents_n.png/.pdf``): tail means of ``||Phi||``, ``||p_hat - p_*||``
  and ``||eps||`` against N;
* otherwise (``convergence.png/.pdf``): ``||Phi||`` curves overlaid and the fitted
  exponential rates next to the theoretical ``(alpha + sigma) lambda``.

Statistics (the CSV's columns; norms in 1/length, rates in 1/s): ``phi_tail_mean``,
``phi_tail_sup``, ``phat_tail_mean``, ``eps_tail_mean``, ``eps_g_tail_mean`` over the
last ``tail`` fraction of the run; ``eps_sup``, ``eps_g_sup`` over the whole run;
``rate_fit``, the least-squares slope of ``-log ||Phi||`` over the second half of the
run; ``rate_theory`` from the log's ``theory`` record; ``wall_s`` (s) from its ``status``
record.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import warnings
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from analysis.configs import component, flatten, logged_config
from analysis.load import LogError, LogWarning, load_run
from analysis.plotting import save_figure

STATS = (
    "phi_tail_mean",
    "phi_tail_sup",
    "phat_tail_mean",
    "eps_tail_mean",
    "eps_g_tail_mean",
    "eps_sup",
    "eps_g_sup",
    "rate_fit",
    "rate_theory",
    "t_end",
)


def decay_rate(t: np.ndarray, phi: np.ndarray) -> float:
    """Least-squares slope of ``-log phi`` over the second half of the run (1 / s)."""
    keep = (t >= t[-1] / 2) & np.isfinite(phi) & (phi > 0)
    if keep.sum() < 3:
        return math.nan
    slope = np.polyfit(t[keep], np.log(phi[keep]), 1)[0]
    return float(-slope)


class SweepWarning(UserWarning):
    """A log whose metadata or metrics are not what this project writes."""


def _stat(fn: Any, values: np.ndarray) -> float:
    """``fn(values)`` over the finite entries; NaN when there are none."""
    finite = values[np.isfinite(values)]
    return float(fn(finite)) if finite.size else math.nan


def job_stats(run, tail: float) -> dict[str, float]:
    """The statistics of one run (see the module docstring); NaN for a statistic whose
    metric the log lacks, and a :class:`SweepWarning` for metadata that is not a number.
    """
    m = run.metrics
    t = m["t"]
    last = t >= t[-1] * (1 - tail)
    missing = np.full(t.shape, np.nan)

    def col(key):
        return m.get(key, missing)

    theory = run.metadata.get("theory", {})
    rate_theory = _float(theory.get("rate_exact", "nan"))
    if "rate_exact" in theory and not math.isfinite(rate_theory):
        warnings.warn(
            f"{run.path}: theory record rate_exact={theory.get('rate_exact')!r} is not a "
            "number; rate_theory is NaN",
            SweepWarning,
            stacklevel=2,
        )
    return {
        "phi_tail_mean": _stat(np.mean, col("phi_l2")[last]),
        "phi_tail_sup": _stat(np.max, col("phi_l2")[last]),
        "phat_tail_mean": _stat(np.mean, col("phat_target_l2")[last]),
        "eps_tail_mean": _stat(np.mean, col("eps_l2")[last]),
        "eps_g_tail_mean": _stat(np.mean, col("eps_g_l2")[last]),
        "eps_sup": _stat(np.max, col("eps_l2")),
        "eps_g_sup": _stat(np.max, col("eps_g_l2")),
        "rate_fit": decay_rate(t, col("phi_l2")),
        "rate_theory": rate_theory,
        "t_end": float(t[-1]),
    }


def mixed(rows: list[dict[str, Any]], primary: list[str]) -> list[str]:
    """Varied config keys that the ``primary`` keys do not explain: keys taking more than
    one value among jobs that agree on every primary key. Non-empty means the directory
    holds more than one sweep.
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(
            repr([value(r, k) if k != "law" else r.get("law") for k in primary]), []
        ).append(r)
    out = []
    for key in varied(rows):
        if key in primary or key == "seed":
            continue
        if any(len({repr(value(r, key)) for r in g}) > 1 for g in groups.values()):
            out.append(key)
    return out


def analyse(sweep_dir: Path, tail: float = 0.25) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Rows of the CSV and the decoded metrics per job directory.

    Each row holds the job's directory, state, statistics, wall time, the short name
    of its control law (``law``) and its whole flattened config; :func:`varied` then
    picks the config keys that differ between jobs.
    """
    rows, series = [], {}
    for log_path in sorted(sweep_dir.glob("*/run.mcap")):
        job_dir = log_path.parent
        row: dict[str, Any] = {"dir": job_dir.name}
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", LogWarning)
                run = load_run(log_path, topics={"/metrics"})
        except LogError as err:
            row["state"] = f"unreadable: {err}"
            rows.append(row)
            continue
        if run.recovery is not None:  # damaged or cut short: say so, whatever its status says
            row["recovery"] = run.recovery
            warnings.warn(f"{log_path}: {run.recovery}", SweepWarning, stacklevel=2)
        flat = flatten(logged_config(run))
        row.update({CONFIG_PREFIX + k: v for k, v in flat.items()})
        row["law"] = component(flat, "control")
        row["state"] = run.state if run.recovery is None else f"damaged ({run.state})"
        row["wall_s"] = _float(run.metadata.get("status", {}).get("wall_s"))
        if "t" in run.metrics and len(run.metrics["t"]) > 2:
            row.update(job_stats(run, tail))
            series[job_dir.name] = run.metrics
        rows.append(row)
    return rows, series


def _float(text: Any) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


CONFIG_PREFIX = "cfg:"
"""Prefix of the config columns in the rows (dropped in the CSV header)."""


def varied(rows: list[dict[str, Any]]) -> list[str]:
    """Config keys (without the prefix) whose values differ between the rows, leaving
    out the logging and progress keys.
    """
    keys = sorted({k for r in rows for k in r if k.startswith(CONFIG_PREFIX)})
    out = []
    for k in keys:
        key = k[len(CONFIG_PREFIX) :]
        if key.startswith("log."):
            continue
        if len({repr(r.get(k)) for r in rows}) > 1:
            out.append(key)
    return out


def value(row: dict[str, Any], key: str) -> Any:
    """The row's config value at ``key``."""
    return row.get(CONFIG_PREFIX + key)


def write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    """Tidy CSV: the varied config keys, the law, then the fixed columns."""
    keys = varied(rows)
    fixed = ["dir", "state", *STATS, "wall_s", "recovery"]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[*keys, "law", *fixed], restval="")
        writer.writeheader()
        for r in rows:
            out = {k: value(r, k) for k in keys}
            out["law"] = r.get("law", "")
            out.update({k: r.get(k, "") for k in fixed})
            writer.writerow(out)


def iss_figure(rows, out: Path) -> tuple[list[Path], dict[str, float]]:
    """Tail sup ||Phi|| against sup ||eps||, per control law, with fitted gains."""
    fig, ax = plt.subplots(figsize=(6, 4.5), constrained_layout=True)
    gains: dict[str, float] = {}
    groups: dict[str, list] = {}
    for r in rows:
        if "phi_tail_sup" in r:
            groups.setdefault(r.get("law") or "law", []).append(r)
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


def agents_figure(rows, out: Path) -> list[Path]:
    """Tail errors against the number of robots."""
    rows = sorted((r for r in rows if "phi_tail_mean" in r), key=lambda r: value(r, "agents.n"))
    n = np.array([int(value(r, "agents.n")) for r in rows])
    fig, ax = plt.subplots(figsize=(6, 4.5), constrained_layout=True)
    for key, label in (
        ("phi_tail_mean", r"$\|p - p_*\|$ (mean-field)"),
        ("phat_tail_mean", r"$\|\hat p - p_*\|$"),
        ("eps_tail_mean", r"$\|\hat p - p\|$"),
    ):
        ax.loglog(n, [r[key] for r in rows], "o-", label=label)
    ax.loglog(n, rows[0]["phat_tail_mean"] * np.sqrt(n[0] / n), "k:", label=r"$\propto N^{-1/2}$")
    ax.set_xlabel("robots N")
    ax.set_ylabel("tail mean (1/length)")
    ax.set_title("tracking and estimation errors against swarm size")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, out, "agents_n")


def _label(row: dict[str, Any], key: str) -> str:
    v = value(row, key)
    return row["dir"] if v is None else str(v)


def convergence_figure(rows, series, varied: list[str], out: Path) -> list[Path]:
    """||Phi|| curves overlaid and fitted against theoretical rates."""
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


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    parser = argparse.ArgumentParser(description="CSV and figures of a sweep, from its logs.")
    parser.add_argument("sweep_dir", type=Path)
    parser.add_argument("--out", type=Path, default=None, help="default: SWEEP_DIR/analysis")
    parser.add_argument("--tail", type=float, default=0.25, help="tail fraction of each run")
    args = parser.parse_args(argv)
    if not args.sweep_dir.is_dir():
        print(f"error: no sweep directory at {args.sweep_dir}", file=sys.stderr)
        return 2
    if not 0 < args.tail <= 1:
        print(f"error: --tail must be in (0, 1], got {args.tail}", file=sys.stderr)
        return 2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SweepWarning)
        rows, series = analyse(args.sweep_dir, args.tail)
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    if not rows:
        print(f"error: no run.mcap below {args.sweep_dir}", file=sys.stderr)
        return 2
    keys = varied(rows)
    usable = [r for r in rows if "phi_tail_sup" in r]
    if "estimator.delta" in keys:
        primary = ["law", "estimator.delta"]
    elif "agents.n" in keys:
        primary = ["agents.n"]
    else:
        counts = {k: len({repr(value(r, k)) for r in rows}) for k in keys}
        primary = [max(keys, key=lambda k: (counts[k], k != "seed"))] if keys else []
    extra = mixed(rows, primary)
    if extra:
        print(
            f"error: {args.sweep_dir} holds more than one sweep: besides "
            f"{', '.join(primary)} the jobs differ in {', '.join(extra)} "
            "(analyse each sweep from a directory of its own)",
            file=sys.stderr,
        )
        return 2
    out = args.out or args.sweep_dir / "analysis"
    out.mkdir(parents=True, exist_ok=True)
    write_csv(rows, out / "sweep.csv")
    written = [out / "sweep.csv"]
    if usable and "estimator.delta" in keys:
        paths, gains = iss_figure(usable, out)
        written += paths
        for law, g in gains.items():
            print(f"fitted ISS gain ({law}): {g:.4g} (tail sup ||Phi|| per unit sup ||eps||)")
    elif usable and "agents.n" in keys:
        written += agents_figure(usable, out)
    elif usable:
        written += convergence_figure(usable, series, keys, out)
        for r in usable:
            print(
                f"{r['dir']}: rate {r['rate_fit']:.4g} 1/s measured, "
                f"{r['rate_theory']:.4g} 1/s theory"
            )
    bad = [r for r in rows if r.get("state") != "completed"]
    print(f"{len(rows)} jobs, {len(bad)} not completed")
    for p in written:
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
