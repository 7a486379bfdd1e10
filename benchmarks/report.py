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

Every figure carries the calibration of the process that measured it
(:mod:`benchmarks.calibration`), and its target is judged in calibrations: a time ``t``
meets a target ``T`` set on the reference host when ``t / c <= T / c_ref``, which is
``t`` against the target on this host ``T c / c_ref``; rates scale the other way,
memory and ratios not at all. The page shows the figure, the figure in calibrations,
the target in calibrations and on this host, and the verdict.
"""

from __future__ import annotations

import argparse
import atexit
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

from benchmarks import calibration

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
        calibration_ms: The calibration of the process that measured it (ms), or None
            when it was not measured (then the target is taken as absolute).
    """

    benchmark: str
    command: str
    name: str
    value: float
    unit: str
    target: float | None = None
    relation: str = "<="
    calibration_ms: float | None = None

    @property
    def scale(self) -> float:
        """How much slower this host was than the reference, to the power the unit needs.

        ``(c / c_ref)^e`` with ``e`` from :func:`benchmarks.calibration.exponent`: a
        target in the figure's unit on the reference host times this scale is the
        target on the host that measured the figure. 1 without a calibration.
        """
        e = calibration.exponent(self.unit)
        if self.calibration_ms is None or e == 0:
            return 1.0
        return (self.calibration_ms / calibration.REFERENCE_MS) ** e

    @property
    def calibrated(self) -> float | None:
        """The figure in calibrations: ``t / c`` for a time, ``r c / 1000`` for a rate.

        None for a unit that does not scale with the host (memory, ratios) and without a
        calibration.
        """
        e = calibration.exponent(self.unit)
        if e == 0 or self.calibration_ms is None:
            return None
        return (
            self.value / self.calibration_ms if e == 1 else self.value * self.calibration_ms / 1e3
        )

    @property
    def target_calibrated(self) -> float | None:
        """The target in calibrations: the target on the reference host over its calibration.

        None without a target or for a unit that does not scale.
        """
        e = calibration.exponent(self.unit)
        if self.target is None or e == 0:
            return None
        ref = calibration.REFERENCE_MS
        return self.target / ref if e == 1 else self.target * ref / 1e3

    @property
    def target_here(self) -> float | None:
        """The target on the host that measured the figure, in the figure's unit."""
        return None if self.target is None else self.target * self.scale

    @property
    def met(self) -> bool | None:
        """Whether the target is met on this host (None without a target)."""
        target = self.target_here
        if target is None:
            return None
        if self.relation == "<=":
            return self.value <= target
        return self.value >= target


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
    if figure.target_here is not None:
        verdict = "OK" if figure.met else "MISSED"
        text += (
            f"   target here {figure.relation} {figure.target_here:.4g} {figure.unit}"
            f" ({figure.target:g} on the reference)   {verdict}"
        )
    return text


CALIBRATION_UNIT = "ms (calibration)"
"""The unit of the two calibration figures each benchmark process records."""

_STARTED = False


def _host() -> float:
    """This process's calibration; the first call also records it and, at exit, another.

    The figure ``calibration at start`` is measured before the process's first figure,
    ``calibration at end`` when the process exits: far apart, the host's speed drifted
    while the figures were taken.
    """
    global _STARTED
    c = calibration.host_ms()
    if not _STARTED:
        _STARTED = True
        _write(Figure(*_caller(), "calibration at start", c, CALIBRATION_UNIT))
        atexit.register(
            lambda: _write(
                Figure(*_caller(), "calibration at end", calibration.measure(), CALIBRATION_UNIT)
            )
        )
    return c


def _write(figure: Figure) -> None:
    """Print ``figure``'s line and append it to the file ``$ENV`` names."""
    print(line(figure), flush=True)
    path = os.environ.get(ENV)
    if path:
        with open(path, "a") as f:
            f.write(json.dumps(asdict(figure)) + "\n")


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
    if not math.isfinite(value):
        raise ValueError(f"{name}: a figure must be a finite number, got {value!r}")
    module, command = _caller()
    figure = Figure(module, command, name, float(value), unit, target, relation, _host())
    _write(figure)
    return figure.met is not False


FIGURES_LIMIT = 64 * 2**20
"""The largest figures file :func:`read` opens (bytes)."""


def _figure(fields: object) -> Figure:
    """A :class:`Figure` from one decoded JSON line; ValueError naming what is wrong."""
    if not isinstance(fields, dict):
        raise ValueError("not a JSON object")
    known = {f for f in Figure.__dataclass_fields__}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise ValueError(f"unknown fields {unknown}")
    for key in ("benchmark", "command", "name", "unit"):
        if not isinstance(fields.get(key), str):
            raise ValueError(f"{key} must be a string")
    for key in ("value", "target", "calibration_ms"):
        value = fields.get(key)
        if key == "value" or value is not None:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"{key} must be a number, got {value!r}")
    if not math.isfinite(fields["value"]):
        raise ValueError(f"value must be a finite number, got {fields['value']!r}")
    for key in ("target", "calibration_ms"):
        value = fields.get(key)
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"{key} must be a finite positive number, got {value!r}")
    if fields.get("relation", "<=") not in ("<=", ">="):
        raise ValueError(f"relation must be '<=' or '>=', got {fields.get('relation')!r}")
    return Figure(**fields)


def read(path: Path) -> list[Figure]:
    """The figures in a file :func:`record` appended to (none when it is missing).

    Raises:
        ValueError: one line, when the file is not a regular readable UTF-8 file of at
            most :data:`FIGURES_LIMIT` bytes or a line is not a figure.
    """
    from harness.files import UnreadableFile, read_text

    if not path.exists():
        return []
    try:
        text = read_text(path, FIGURES_LIMIT)
    except UnreadableFile as err:
        raise ValueError(str(err)) from None
    figures = []
    for number, line_ in enumerate(text.splitlines(), 1):
        if not line_.strip():
            continue
        try:
            figures.append(_figure(json.loads(line_)))
        except ValueError as err:
            raise ValueError(f"{path}:{number}: not a figure ({err})") from None
    return figures


def machine(date: datetime.datetime | None = None) -> dict[str, str]:
    """What the figures were measured on: CPU model, cores, Python, numpy, numba, date."""
    import numba
    import numpy

    from harness.runs.identity import cpu_model

    when = date or datetime.datetime.now(datetime.UTC)
    return {
        "CPU": cpu_model(),
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


def _calibration_of(group: list[Figure]) -> str:
    """The line saying what the benchmark's processes measured of the host."""
    starts = [f.value for f in group if f.name == "calibration at start"]
    ends = [f.value for f in group if f.name == "calibration at end"]
    if not starts:
        return "Calibration: not measured (targets taken as absolute)."
    ref = calibration.REFERENCE_MS
    text = ", ".join(f"{c:.3g} ms ({c / ref:.2f} x the reference)" for c in starts)
    if ends:
        text += "; at the end " + ", ".join(f"{c:.3g} ms" for c in ends)
    return f"Calibration at the start: {text}."


def summary(benchmark: str) -> str:
    """The first paragraph of the docstring of benchmark module ``benchmark``, read from
    its source with ``ast`` (never imported: the name comes from a file); empty unless
    the name is ``benchmarks.<identifier>`` of a module in this project's ``benchmarks/``.
    """
    import ast

    from harness.files import UnreadableFile, read_text

    prefix, _, name = benchmark.partition(".")
    if prefix != "benchmarks" or not name.isidentifier():
        return ""
    path = ROOT / "benchmarks" / f"{name}.py"
    if not path.exists():
        return ""
    try:
        doc = ast.get_docstring(ast.parse(read_text(path, 2**20))) or ""
    except (UnreadableFile, SyntaxError, ValueError):
        return ""
    return " ".join(doc.strip().split("\n\n", 1)[0].split())


def figures_section(figures: Iterable[Figure]) -> str:
    """The figures as Markdown: one table per benchmark, with the command that ran it.

    Columns: the figure as measured; in calibrations (times over ``c``, rates times
    ``c``); the target in calibrations; the target on the host that measured it, in the
    figure's unit; whether it is met.
    """
    by_benchmark: dict[str, list[Figure]] = {}
    for figure in figures:
        by_benchmark.setdefault(figure.benchmark, []).append(figure)
    if not by_benchmark:
        return f"No figures: nothing was measured on this checkout. `{COMMAND}` measures them."
    out = []
    for benchmark, group in by_benchmark.items():
        commands = sorted({f.command for f in group})
        doc = summary(benchmark)
        out.append(f"### `{_cell(benchmark)}`\n")
        if doc:
            out.append(doc + "\n")
        out.append("Command: " + ", ".join(f"`{_cell(c)}`" for c in commands) + ".\n")
        out.append(_calibration_of(group) + "\n")
        out.append("| figure | measured | in calibrations | target | target on this host | met |")
        out.append("|---|---|---|---|---|---|")
        for f in group:
            if f.unit == CALIBRATION_UNIT:
                continue
            cal = "" if f.calibrated is None else _number(f.calibrated)
            if f.target is None:
                target = here = ""
            elif f.target_calibrated is None:
                target = f"{f.relation} {f.target:g} {_cell(f.unit)}"
                here = target
            else:
                target = f"{f.relation} {f.target_calibrated:.3g}"
                here = f"{f.relation} {_number(f.target_here or math.nan)} {_cell(f.unit)}"
            met = {None: "", True: "yes", False: "**no**"}[f.met]
            out.append(
                f"| {_cell(f.name)} | {_number(f.value)} {_cell(f.unit)} | {cal} | {target}"
                f" | {here} | {met} |"
            )
        out.append("")
    with_target = [f for group in by_benchmark.values() for f in group if f.target is not None]
    n_met = sum(bool(f.met) for f in with_target)
    out.append(f"{n_met} of {len(with_target)} targets met, judged in calibrations.")
    return "\n".join(out)


def _cell(text: str) -> str:
    """``text`` safe inside a Markdown table cell: one line, no bare ``|``."""
    return " ".join(str(text).split()).replace("|", "\\|")


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


TEMPLATE_LIMIT = 2**20
"""The largest template :func:`main` opens (bytes)."""


def main(argv: list[str] | None = None) -> int:
    """Write the performance page from the collected figures.

    Returns:
        0 when written; 2, with one line on stderr, when the figures, the template or the
        output folder are not usable (nothing is written then).
    """
    from harness.files import UnreadableFile, read_text

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("figures", type=Path, help="the file the benchmarks appended to")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "performance.md")
    parser.add_argument("--template", type=Path, default=ROOT / "docs" / "performance.in.md")
    args = parser.parse_args(argv)
    try:
        figures = read(args.figures)
        template = read_text(args.template, TEMPLATE_LIMIT)
    except (ValueError, UnreadableFile) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    missing = [mark for mark in ("{{machine}}", "{{figures}}") if mark not in template]
    if missing:
        print(f"error: {args.template}: no {' or '.join(missing)} in the template", file=sys.stderr)
        return 2
    if not args.out.parent.is_dir():
        print(f"error: {args.out.parent}: no such folder for --out", file=sys.stderr)
        return 2
    text = page(figures, template, machine())
    tmp = args.out.with_name(f".{args.out.name}.tmp")
    try:
        tmp.write_text(text)
        tmp.replace(args.out)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        print(f"error: {args.out}: {err.strerror or err}", file=sys.stderr)
        return 2
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
