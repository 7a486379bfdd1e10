"""Did a change make a benchmark slower? Two commits timed alternately in one run.

``python -m benchmarks.<name> --vs COMMIT [--rounds K] [args ...]`` runs the benchmark
``K`` times on this checkout (A) and ``K`` times on ``COMMIT`` (B, exported with ``git
archive`` into ``build/bench/vs/<sha>``), alternating A B, B A, A B, ... so that a drift
of the host hits both alike. Before each run the calibration of the host
(:mod:`benchmarks.calibration`) is measured in this process, and every figure is
divided by it (times) or multiplied by it (rates) before A and B are compared.

For each figure that both commits report, round ``k`` gives the paired ratio

    q_k = (cost of A) / (cost of B)

where a cost is a calibrated time, or the inverse of a calibrated rate: ``q > 1`` means
this checkout is slower. The summary is the geometric mean ``q = exp(mean(log q_k))``
with a 95 % interval from Student's t on the ``log q_k`` (``K - 1`` degrees of freedom;
none for ``K = 1``). The verdict is ``slower`` when the interval lies above 1 and ``q``
exceeds ``1 + THRESHOLD``, ``faster`` the other way round, and ``no change detected``
otherwise. The exit status is 1 when a figure is slower, 2 when a run failed.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from benchmarks import calibration
from benchmarks.report import CALIBRATION_UNIT, ENV, ROOT, Figure, read

THRESHOLD = 0.03
"""A change smaller than this fraction is not called slower or faster."""


@dataclass(frozen=True)
class Comparison:
    """One figure of the two commits over the rounds.

    Attributes:
        name: The figure.
        unit: Its unit.
        ratios: ``q_k`` per round (A's cost over B's, calibrated).
    """

    name: str
    unit: str
    ratios: tuple[float, ...]

    @property
    def ratio(self) -> float:
        """The geometric mean of the ratios."""
        return math.exp(sum(math.log(q) for q in self.ratios) / len(self.ratios))

    @property
    def interval(self) -> tuple[float, float]:
        """The 95 % interval of the geometric mean (t on the log ratios); (0, inf) for K = 1."""
        k = len(self.ratios)
        if k < 2:
            return (0.0, math.inf)
        from scipy import stats

        logs = [math.log(q) for q in self.ratios]
        mean = sum(logs) / k
        sd = math.sqrt(sum((x - mean) ** 2 for x in logs) / (k - 1))
        half = float(stats.t.ppf(0.975, k - 1)) * sd / math.sqrt(k)
        return (math.exp(mean - half), math.exp(mean + half))

    @property
    def verdict(self) -> str:
        """``slower``, ``faster`` or ``no change detected`` (see the module's docstring)."""
        low, high = self.interval
        if low > 1.0 and self.ratio > 1.0 + THRESHOLD:
            return "slower"
        if high < 1.0 and self.ratio < 1.0 / (1.0 + THRESHOLD):
            return "faster"
        return "no change detected"


RANGE = re.compile(r"\s*\[[^\[\]]*\bto\b[^\[\]]*\]")
"""A measured range in a figure's name (``rooms [286 to 416]``): it differs between runs."""


def key(figure: Figure) -> tuple[str, str]:
    """What pairs a figure of A with one of B: its name without measured ranges, and its
    unit."""
    return RANGE.sub("", figure.name).strip(), figure.unit


def cost(figure: Figure, c: float) -> float | None:
    """The calibrated cost of ``figure`` measured at calibration ``c``: ``t / c`` for a
    time, ``1 / (r c)`` for a rate; a ratio of two speeds measured together (``x``,
    already free of the host) as itself when its target is an upper bound and its
    inverse when a lower one; None for what does not depend on speed (memory) and a
    ratio without a target."""
    if not (math.isfinite(figure.value) and figure.value > 0):
        return None
    e = calibration.exponent(figure.unit)
    if e == 0:
        if figure.unit != "x" or figure.target is None:
            return None
        return figure.value if figure.relation == "<=" else 1.0 / figure.value
    return figure.value / c if e == 1 else 1.0 / (figure.value * c)


def compare(
    a_runs: Sequence[tuple[float, list[Figure]]], b_runs: Sequence[tuple[float, list[Figure]]]
) -> list[Comparison]:
    """Pair the figures of A and B round by round (calibration, figures per run)."""
    out: dict[tuple[str, str], list[float]] = {}
    order: list[tuple[str, str]] = []
    for (ca, fa), (cb, fb) in zip(a_runs, b_runs, strict=True):
        b_by_key = {key(f): f for f in fb}
        for f in fa:
            k = key(f)
            other = b_by_key.get(k)
            if f.unit == CALIBRATION_UNIT or other is None:
                continue
            qa, qb = cost(f, ca), cost(other, cb)
            if qa is None or qb is None:
                continue
            if k not in out:
                out[k] = []
                order.append(k)
            out[k].append(qa / qb)
    return [Comparison(name, unit, tuple(out[(name, unit)])) for name, unit in order]


def export(commit: str) -> Path:
    """``commit`` of this repository as a plain tree under ``build/bench/vs/`` (reused)."""
    sha = subprocess.run(
        ["git", "rev-parse", "--verify", f"{commit}^{{commit}}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    if sha.returncode != 0:
        raise ValueError(f"--vs {commit}: not a commit of {ROOT}")
    full = sha.stdout.strip()
    where = ROOT / "build" / "bench" / "vs" / full[:12]
    if (where / ".complete").exists():
        return where
    where.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "archive", full], cwd=ROOT, capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(where)], input=archive.stdout, check=True)
    (where / ".complete").write_text(full + "\n")
    return where


def run_once(module: str, args: Sequence[str], tree: Path) -> list[Figure]:
    """Run ``python -m module args`` with ``tree`` first on the path; its figures."""
    with tempfile.TemporaryDirectory() as tmp:
        figures = Path(tmp) / "figures.jsonl"
        env = {**os.environ, ENV: str(figures), "PYTHONPATH": str(tree)}
        done = subprocess.run([sys.executable, "-m", module, *args], cwd=tree, env=env)
        if done.returncode not in (0, 1):  # 1: a target missed, the figures are there
            raise RuntimeError(f"{module} in {tree} exited {done.returncode}")
        return read(figures)


def ab(module: str, args: Sequence[str], vs: str, rounds: int) -> int:
    """Time ``module`` on this checkout against ``vs``, alternating; print the verdicts."""
    other = export(vs)
    a_runs: list[tuple[float, list[Figure]]] = []
    b_runs: list[tuple[float, list[Figure]]] = []
    for k in range(rounds):
        sides = [("A", ROOT, a_runs), ("B", other, b_runs)]
        for label, tree, runs in sides if k % 2 == 0 else sides[::-1]:
            c = calibration.measure()
            print(
                f"== round {k + 1}/{rounds}, {label} ({tree}), calibration {c:.3f} ms", flush=True
            )
            runs.append((c, run_once(module, args, tree)))
    comparisons = compare(a_runs, b_runs)
    print(f"\nA = this checkout, B = {vs}; q = A's cost / B's cost (> 1: A is slower)")
    print(f"{'figure':<56s} {'q':>7s} {'95 % interval':>17s}  verdict")
    for comp in comparisons:
        low, high = comp.interval
        print(f"{comp.name[:56]:<56s} {comp.ratio:7.3f} {low:8.3f} {high:8.3f}  {comp.verdict}")
    if not comparisons:
        print("no figure measured by both commits")
    return 1 if any(c.verdict == "slower" for c in comparisons) else 0


def cli(main: Callable[[list[str]], object], module: str) -> int:
    """A benchmark's command line: ``--vs COMMIT [--rounds K]`` runs :func:`ab`, anything
    else goes to the benchmark's own ``main``.

    Returns:
        The exit status: the benchmark's (``True``/``None`` as 0, ``False`` as 1), or the
        A/B verdict's.
    """
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--vs", default=None)
    parser.add_argument("--rounds", type=int, default=None)
    known, rest = parser.parse_known_args(sys.argv[1:])
    if known.vs is None and known.rounds is not None:
        print("error: --rounds goes with --vs COMMIT", file=sys.stderr)
        return 2
    if known.vs is None:
        result = main(rest)
        if isinstance(result, bool) or result is None:
            return 0 if result is not False else 1
        return int(result)  # type: ignore[call-overload]
    rounds = 3 if known.rounds is None else known.rounds
    if rounds < 1:
        print("error: --rounds must be at least 1", file=sys.stderr)
        return 2
    try:
        return ab(module, rest, known.vs, rounds)
    except (ValueError, RuntimeError, subprocess.CalledProcessError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
