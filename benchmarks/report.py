"""One way for every benchmark to report a figure, and the page that collects them.

Each benchmark reports each figure with :func:`record` (name, value, unit, and the target
with the side it must be on): one printed line in a common format, and, when the
environment variable ``DENSITYLOOP_BENCH_FIGURES`` names a file, one JSON line appended
to it. ``make bench`` sets it for every benchmark it runs, then writes
``docs/performance.md`` from the collected figures:

    python -m benchmarks.report FIGURES.jsonl [--out docs/performance.md]
        [--template docs/performance.in.md]

The page holds the command that regenerates it, the machine (CPU model, cores, Python,
numpy and numba versions, the date) and each figure against its target, benchmark by
benchmark, inside the hand-written template (placeholders ``{{machine}}`` and
``{{figures}}``). Without figures (no file, or an empty one) the page says that nothing
was measured.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import shlex
import sys
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

ENV = "DENSITYLOOP_BENCH_FIGURES"
"""The environment variable naming the file :func:`record` appends figures to."""

ROOT = Path(__file__).resolve().parents[1]
COMMAND = "make bench"
"""What regenerates ``docs/performance.md``."""


@dataclass(frozen=True)
class Figure:
    """One measured figure.

    Attributes:
        benchmark: The module that measured it (``benchmarks.suite``).
        command: The command line that ran the module.
        name: What was measured.
        value: The figure.
        unit: Its unit (``ms``, ``steps/s``, ``GB``, ``x`` for a ratio).
        target: The target, or None for a figure shown for reference.
        relation: ``<=`` (the figure must be at most the target) or ``>=``.
    """

    benchmark: str
    command: str
    name: str
    value: float
    unit: str
    target: float | None = None
    relation: str = "<="

    @property
    def met(self) -> bool | None:
        """Whether the target is met (None without a target)."""
        if self.target is None:
            return None
        if self.relation == "<=":
            return self.value <= self.target
        return self.value >= self.target


def _caller() -> tuple[str, str]:
    """The running benchmark's module name and command line."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    module = spec.name if spec is not None else Path(sys.argv[0]).stem
    command = shlex.join(["python", "-m", module, *sys.argv[1:]])
    return module, command


def line(figure: Figure) -> str:
    """The printed line of ``figure``: name, value and unit, target and verdict."""
    text = f"  {figure.name:<52s} {figure.value:10.4g} {figure.unit}"
    if figure.target is not None:
        verdict = "OK" if figure.met else "MISSED"
        text += f"   target {figure.relation} {figure.target:g} {figure.unit}   {verdict}"
    return text


def record(
    name: str, value: float, unit: str, target: float | None = None, relation: str = "<="
) -> bool:
    """Report one figure: print its line, and append it to the file ``$ENV`` names.

    Args:
        name: What was measured (unique within the benchmark).
        value: The figure.
        unit: Its unit.
        target: The target, or None for a figure shown for reference.
        relation: ``<=`` (lower is better) or ``>=``.

    Returns:
        Whether the target is met (True without a target).
    """
    if relation not in ("<=", ">="):
        raise ValueError(f"relation must be '<=' or '>=', got {relation!r}")
    module, command = _caller()
    figure = Figure(module, command, name, float(value), unit, target, relation)
    print(line(figure), flush=True)
    path = os.environ.get(ENV)
    if path:
        with open(path, "a") as f:
            f.write(json.dumps(asdict(figure)) + "\n")
    return figure.met is not False


def read(path: Path) -> list[Figure]:
    """The figures in a file :func:`record` appended to (none when it is missing)."""
    if not path.exists():
        return []
    figures = []
    for number, text in enumerate(path.read_text().splitlines(), 1):
        if not text.strip():
            continue
        try:
            figures.append(Figure(**json.loads(text)))
        except (TypeError, ValueError) as err:
            raise ValueError(f"{path}:{number}: not a figure ({err})") from None
    return figures


def machine(date: datetime.datetime | None = None) -> dict[str, str]:
    """What the figures were measured on: CPU model, cores, Python, numpy, numba, date."""
    import numba
    import numpy

    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for text in cpuinfo.read_text(errors="replace").splitlines():
            if text.startswith("model name"):
                cpu = text.split(":", 1)[1].strip()
                break
    when = date or datetime.datetime.now(datetime.UTC)
    return {
        "CPU": cpu,
        "cores": str(os.cpu_count()),
        "Python": platform.python_version(),
        "numpy": numpy.__version__,
        "numba": numba.__version__,
        "date": when.strftime("%Y-%m-%d %H:%M UTC"),
    }


def _number(value: float) -> str:
    if math.isnan(value):
        return "n/a"
    return f"{value:.4g}"


def figures_section(figures: Iterable[Figure]) -> str:
    """The figures as Markdown: one table per benchmark, with the command that ran it."""
    by_benchmark: dict[str, list[Figure]] = {}
    for figure in figures:
        by_benchmark.setdefault(figure.benchmark, []).append(figure)
    if not by_benchmark:
        return f"No figures: nothing was measured on this checkout. `{COMMAND}` measures them."
    out = []
    for benchmark, group in by_benchmark.items():
        commands = sorted({f.command for f in group})
        module = sys.modules.get(benchmark)
        doc = (getattr(module, "__doc__", None) or "").strip().split("\n\n", 1)[0]
        out.append(f"### `{benchmark}`\n")
        if doc:
            out.append(" ".join(doc.split()) + "\n")
        out.append("Command: " + ", ".join(f"`{c}`" for c in commands) + ".\n")
        out.append("| figure | measured | target | met |")
        out.append("|---|---|---|---|")
        for f in group:
            target = "" if f.target is None else f"{f.relation} {f.target:g} {f.unit}"
            met = {None: "", True: "yes", False: "**no**"}[f.met]
            name = f.name.replace("|", "\\|")
            out.append(f"| {name} | {_number(f.value)} {f.unit} | {target} | {met} |")
        out.append("")
    with_target = [f for group in by_benchmark.values() for f in group if f.target is not None]
    met = sum(bool(f.met) for f in with_target)
    out.append(f"{met} of {len(with_target)} targets met.")
    return "\n".join(out)


def machine_section(info: dict[str, str] | None) -> str:
    """The machine as a Markdown list (or a line saying nothing was measured)."""
    if info is None:
        return "Not measured on this checkout."
    return "\n".join(f"- {key}: {value}" for key, value in info.items())


def page(figures: list[Figure], template: str, info: dict[str, str] | None) -> str:
    """``docs/performance.md``: the template with the machine and the figures filled in."""
    header = (
        f"<!-- Generated by `{COMMAND}` (`python -m benchmarks.report`) from the "
        "benchmarks' figures and `performance.in.md`: edit the template, not this file. -->\n"
    )
    body = template.replace("{{machine}}", machine_section(info if figures else None))
    return header + body.replace("{{figures}}", figures_section(figures))


def main(argv: list[str] | None = None) -> int:
    """Write the performance page from the collected figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("figures", type=Path, help="the file the benchmarks appended to")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "performance.md")
    parser.add_argument("--template", type=Path, default=ROOT / "docs" / "performance.in.md")
    args = parser.parse_args(argv)
    try:
        figures = read(args.figures)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for name in {f.benchmark for f in figures}:  # their docstrings describe the sections
        try:
            __import__(name)
        except ImportError:
            pass
    text = page(figures, args.template.read_text(), machine())
    tmp = args.out.with_name(f".{args.out.name}.tmp")
    tmp.write_text(text)
    tmp.replace(args.out)
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
