"""Render each study's documentation page from its aggregated sweep.

    python -m analysis.study_pages [STUDY ...] [--figures DIR] [--docs DIR]

For every study (default: every ``docs/studies/<study>.in.md`` template and every
study with a ``sweep_aggregated.csv`` under ``--figures``), this

1. reads ``<figures>/<study>/sweep_aggregated.csv`` (written by ``python -m
   analysis.sweep multirun/<study> --out <figures>/<study>``) and the study's figure
   (``<figures>/<study>/<figure>.png``, the figure its preset declares) when they exist,
   otherwise the copies already in ``docs/`` (so a page renders without its sweep), and
   checks them (:mod:`analysis.study_data`);
2. renders ``docs/studies/<study>.md`` from the template ``docs/studies/<study>.in.md``
   (hand-written prose) with every number taken from the CSV;
3. only then copies the new CSV to ``docs/studies/data/<study>.csv`` and the figure to
   ``docs/sweeps/<study>.png`` and writes the page, each atomically. An input (the
   CSV, the figure, the template, the preset) that is empty, cut short, foreign, not
   UTF-8, holding a control character or not a regular file, or a page that does not
   render, is one line (exit status 2) and nothing in ``docs/`` is written, for any of
   the studies asked for: every page is rendered before the first file is written.

``make sweeps`` and ``make sweep-<study>`` run it after each study.

Template. An optional YAML front matter (between ``---`` lines) declares the table::

    ---
    table:
      where: {agents.n: 1024}            # keep the rows that match (optional)
      sort: [law, agents.n]               # row order (optional)
      columns:
        - law                             # a key, printed as is
        - {key: agents.n, label: N}
        - {stat: swarm_ratio, label: swarm_l2 / floor, ci: true, fmt: .3g, nan: never}
    ---

and the body holds placeholders, each replaced by what the CSV says:

* ``{{table}}``: the table above (a statistic as its mean over the seeds, with its
  95 % interval in brackets when ``ci`` is set and there are several seeds);
  ``{{table NAME}}`` the table ``NAME`` of a front-matter block ``tables:``; a table
  with ``pivot: {rows: KEY, columns: KEY, stat: STAT}`` lays one statistic out with one
  key down and another across;
* ``{{figure}}``: the study's figure; ``{{commands}}``: the commands that regenerate the
  page; ``{{csv}}``: a link to the data;
* ``{{STAT @ key=value, key=value : fmt}}``: the mean of statistic ``STAT`` (column
  ``STAT_mean``, or the column ``STAT`` itself for a key) at the one point whose keys
  match (``key=a|b`` allows either value; ``study=NAME`` reads study ``NAME``'s data);
  ``{{ci STAT @ ...}}`` the same with its interval; ``{{min STAT @ ...}}`` and
  ``{{max STAT @ ...}}`` the least and largest mean over the matching points;
  ``{{gain Y / X @ ...}}`` the least-squares slope through the origin of the means of
  ``Y`` against those of ``X`` over the matching points with ``X > 0`` (an ISS gain,
  as :mod:`analysis.laws` fits it; at least two points).

The data names the control law in column ``law`` and the option of any other config group
that the study varies in a column named after the group (``plant``), by the option
names the logs record (``law=paper``, ``plant=unicycles``; :mod:`analysis.rows`). A
placeholder
that matches no point, or several where one is meant, stops the rendering with one line
naming the template and the placeholder (exit status 2): a page never shows a number
that is not in its data. A study without a template gets a page of its primary keys,
its main statistics and its figure.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from analysis.output import write_text
from analysis.safe_yaml import ConfigRecordError, safe_config
from analysis.stats import BEYOND
from analysis.study_data import (
    ROOT,
    PageError,
    Study,
    declared_primary,
    present,
    read_inputs,
    read_points,
    read_template,
    write_inputs,
)

DEFAULT_STATS = ("phat_tail_mean", "swarm_tail_mean", "swarm_ratio", "rate_fit", "rate_theory")
"""The statistics of a page without a template (those the CSV has)."""


GAIN_MIN_X = 1e-12
"""``X`` at or below this counts as no error in a gain (as in :mod:`analysis.laws`)."""


def _number(text: Any) -> float | None:
    try:
        return float(text)
    except (TypeError, ValueError):
        return None


def _same(cell: str, wanted: str) -> bool:
    a, b = _number(cell), _number(wanted)
    if a is not None and b is not None:
        return a == b or (math.isnan(a) and math.isnan(b))
    return cell.strip().lower() == wanted.strip().lower()


class Points:
    """The aggregated rows of one study, looked up by key values.

    Args:
        rows: The rows of ``sweep_aggregated.csv``.
    """

    def __init__(self, rows: list[dict[str, str]]):
        self.rows = rows

    def column(self, stat: str) -> str:
        """The CSV column of a statistic's mean (``STAT_mean``) or of a key (``STAT``)."""
        columns = self.rows[0].keys() if self.rows else ()
        for name in (f"{stat}_mean", stat):
            if name in columns:
                return name
        raise PageError(f"no column {stat!r} (or {stat}_mean) in the data")

    def select(self, where: Mapping[str, Any]) -> list[dict[str, str]]:
        """The rows whose keys have the given values (``a|b``: either)."""
        rows = self.rows
        for key, wanted in where.items():
            if rows and key not in rows[0]:
                raise PageError(f"no key {key!r} in the data")
            allowed = wanted if isinstance(wanted, list) else [wanted]
            rows = [r for r in rows if any(_same(r[key], str(w)) for w in allowed)]
        return rows

    def one(self, where: Mapping[str, Any]) -> dict[str, str]:
        """The single row that matches ``where``."""
        rows = self.select(where)
        if len(rows) != 1:
            raise PageError(f"{len(rows)} points match {dict(where)}, not one")
        return rows[0]


def fmt_number(value: float, fmt: str = ".3g", nan: str = "n/a") -> str:
    """``value`` formatted, ``nan`` for a missing value, ``inf`` as ``never``."""
    if math.isnan(value):
        return nan
    if math.isinf(value):
        return "never"
    return format(value, fmt)


def with_ci(points: Points, row: Mapping[str, str], stat: str, fmt: str, nan: str) -> str:
    """Summary of ``stat`` at ``row``, with its 95 % interval in brackets when it has
    one; an infinite median of a censored time that some seeds reached, or an infinite
    interval end, reads :data:`analysis.stats.BEYOND`.
    """
    mean = _number(row.get(points.column(stat)))
    reached = _number(row.get(f"{stat}_n"))
    if mean is not None and math.isinf(mean) and reached is not None and reached > 0:
        text = BEYOND
    else:
        text = fmt_number(math.nan if mean is None else mean, fmt, nan)
    low, high = _number(row.get(f"{stat}_ci_low")), _number(row.get(f"{stat}_ci_high"))
    if mean is None or math.isnan(mean) or low is None or high is None:
        return text
    if math.isnan(low) or math.isnan(high) or (math.isinf(low) and math.isinf(high)):
        return text  # no interval, or one wholly beyond the run: the summary alone

    def end(v: float) -> str:
        return BEYOND if math.isinf(v) else format(v, fmt)

    return f"{text} ({end(low)} to {end(high)})"


def parse_where(text: str) -> dict[str, Any]:
    """``key=value, key=a|b`` as a dict (a value with ``|`` is a list of alternatives)."""
    where: dict[str, Any] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, eq, value = part.partition("=")
        if not eq:
            raise PageError(f"filter {part!r} is not key=value")
        alternatives = [v.strip() for v in value.split("|")]
        where[key.strip()] = alternatives if len(alternatives) > 1 else alternatives[0]
    return where


_PLACEHOLDER = re.compile(r"\{\{\s*(.+?)\s*\}\}", re.DOTALL)
"""A placeholder; it may run over several lines of the template."""
_EXPRESSION = re.compile(
    r"^(?:(?P<op>ci|min|max|gain)\s+)?(?P<stat>[\w.]+)(?:\s*/\s*(?P<x>[\w.]+))?"
    r"(?:\s*@\s*(?P<where>[^:]*?))?(?:\s*:\s*(?P<fmt>[^:]+))?$"
)


def evaluate(points: Points, expression: str, other: Callable[[str], Points] | None = None) -> str:
    """The text of one number placeholder (``{{ci swarm_ratio @ law=paper}}``); the
    filter ``study=NAME`` reads another study's points, through ``other``.
    """
    match = _EXPRESSION.match(expression)
    if not match:
        raise PageError(f"cannot read placeholder {{{{{expression}}}}}")
    op, stat, x = match["op"], match["stat"], match["x"]
    where = parse_where(match["where"] or "")
    if "study" in where:
        if other is None:
            raise PageError("study=... is not available here")
        points = other(str(where.pop("study")))
    fmt = (match["fmt"] or ".3g").strip()
    if (op == "gain") != (x is not None):
        raise PageError(f"'Y / X' goes with gain, in {{{{{expression}}}}}")
    if op == "gain":
        rows = points.select(where)
        xs = np.array([_number(r[points.column(str(x))]) for r in rows], dtype=float)
        ys = np.array([_number(r[points.column(stat)]) for r in rows], dtype=float)
        keep = np.isfinite(xs) & np.isfinite(ys) & (xs > GAIN_MIN_X)
        if keep.sum() < 2:
            raise PageError(f"fewer than two points with {x} > 0 match {where}")
        gain = float(xs[keep] @ ys[keep] / (xs[keep] @ xs[keep]))
        return fmt_number(gain, fmt)
    if op in ("min", "max"):
        rows = points.select(where)
        values = [_number(r[points.column(stat)]) for r in rows]
        finite = [v for v in values if v is not None and math.isfinite(v)]
        if not finite:
            raise PageError(f"no finite {stat} matches {where}")
        return fmt_number(min(finite) if op == "min" else max(finite), fmt)
    row = points.one(where)
    if op == "ci":
        return with_ci(points, row, stat, fmt, "n/a")
    cell = row[points.column(stat)]
    value = _number(cell)
    if value is None:
        return cell
    return fmt_number(value, fmt)


def _sort_key(keys: Sequence[str]) -> Any:
    """Rows in the order of their values at ``keys``: numbers first, by value, then text."""

    def key(row: Mapping[str, str]) -> tuple:
        out: list[tuple[int, float, str]] = []
        for k in keys:
            value = _number(row.get(k))
            if value is None:
                out.append((1, 0.0, row.get(k, "")))
            else:
                out.append((0, value, ""))
        return tuple(out)

    return key


def _row(cells: Iterable[str]) -> str:
    """A Markdown table row (``|`` within a cell escaped, as tables need)."""
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def _cell(points: Points, row: Mapping[str, str], column: Mapping[str, Any]) -> str:
    """One table cell: a statistic's mean (with its interval when ``ci``), or a key."""
    if "stat" in column:
        fmt, nan = str(column.get("fmt", ".3g")), str(column.get("nan", "n/a"))
        if column.get("ci"):
            return with_ci(points, row, str(column["stat"]), fmt, nan)
        value = _number(row.get(points.column(str(column["stat"]))))
        return fmt_number(math.nan if value is None else value, fmt, nan)
    key = str(column["key"])
    if key not in row:
        raise PageError(f"no key {key!r} in the data")
    return f"`{row[key]}`"


def render_pivot(points: Points, rows: list[dict[str, str]], spec: Mapping[str, Any]) -> str:
    """A statistic laid out with one key down and another across (``pivot:`` with
    ``rows``, ``columns``, ``stat`` and optionally ``ci``, ``fmt``, ``nan``, ``label``).
    """
    down, across = str(spec["rows"]), str(spec["columns"])
    for key in (down, across):
        if key not in rows[0]:
            raise PageError(f"no key {key!r} in the data")
    order = _sort_key([down]), _sort_key([across])
    ys = list(dict.fromkeys(r[down] for r in sorted(rows, key=order[0])))
    xs = list(dict.fromkeys(r[across] for r in sorted(rows, key=order[1])))
    corner = str(spec.get("label") or f"{down} \\ {across}")
    header = [corner, *(f"`{x}`" for x in xs)]
    lines = [_row(header), "|" + "---|" * len(header)]
    for y in ys:
        cells = [f"`{y}`"]
        for x in xs:
            match = [r for r in rows if r[down] == y and r[across] == x]
            if len(match) > 1:
                raise PageError(f"{len(match)} points at {down}={y}, {across}={x}, not one")
            cells.append(_cell(points, match[0], spec) if match else "")
        lines.append(_row(cells))
    return "\n".join(lines)


def render_table(points: Points, spec: Mapping[str, Any]) -> str:
    """A Markdown table of the rows ``spec`` selects: in its ``columns``, or laid out
    by its ``pivot``.
    """
    rows = points.select(spec.get("where") or {})
    if not rows:
        raise PageError(f"the table's filter {spec.get('where')} matches no point")
    if "pivot" in spec:
        return render_pivot(points, rows, spec["pivot"])
    rows = sorted(rows, key=_sort_key(list(spec.get("sort") or [])))
    columns = [c if isinstance(c, dict) else {"key": c} for c in spec.get("columns") or []]
    if not columns:
        raise PageError("the table lists no columns")
    header = [str(c.get("label") or c.get("key") or c.get("stat")) for c in columns]
    lines = [_row(header), "|" + "---|" * len(columns)]
    for row in rows:
        lines.append(_row(_cell(points, row, c) for c in columns))
    return "\n".join(lines)


def split_front_matter(text: str) -> tuple[dict[str, Any], str]:
    """The template's YAML front matter (empty without one) and its body."""
    if text.startswith("---\n"):
        end = text.find("\n---\n", 4)
        if end < 0:
            raise PageError("front matter without its closing '---'")
        try:
            meta = safe_config(text[4:end]) or {}
        except (ConfigRecordError, yaml.YAMLError) as err:
            raise PageError(f"front matter is not YAML ({' '.join(str(err).split())})") from None
        if not isinstance(meta, dict):
            raise PageError("front matter is not a mapping")
        return meta, text[end + 5 :]
    return {}, text


def default_template(study: Study, points: Points) -> str:
    """The template of a study without one: its keys, main statistics and figure."""
    keys = [k for k in declared_primary(study.name) if not points.rows or k in points.rows[0]]
    stats = [s for s in DEFAULT_STATS if points.rows and f"{s}_mean" in points.rows[0]]
    columns = [*keys, *({"stat": s, "ci": True} for s in stats)]
    meta = yaml.safe_dump({"table": {"sort": keys, "columns": columns}}, sort_keys=False)
    return (
        f"---\n{meta}---\n# Study `{study.name}`\n\n"
        f"The study preset `conf/experiment/{study.name}.yaml` says what it varies.\n\n"
        "{{table}}\n\n{{figure}}\n\n{{commands}}\n"
    )


def commands(study: Study, has_data: bool) -> str:
    """The commands that regenerate the page's data and the page; ``has_data``: the
    page's numbers are read from the study's aggregated CSV.
    """
    s = study.name
    sweep = f"python -m analysis.sweep multirun/{s} --out figures/sweeps/{s}"
    text = (
        f"Regenerate: `make sweep-{s}` (the sweep, then `{sweep}` and "
        f"`python -m analysis.study_pages {s}`); from existing logs, the last two alone."
    )
    if has_data:
        text += (
            f" Every number on this page is read from [`data/{s}.csv`](data/{s}.csv), the "
            "sweep's `sweep_aggregated.csv`."
        )
    else:
        text += (
            f" No copy of the sweep's `sweep_aggregated.csv` is in `docs/studies/data/` yet: "
            f"the numbers on this page are quoted from a run of the sweep, and `{sweep}` "
            "prints them."
        )
    return text


def render(study: Study, rows: list[dict[str, str]] | None = None) -> str:
    """The page of ``study``: its template with every placeholder filled from its data
    (``rows``, default the checked copy in ``docs``, :func:`read_points`); a study named
    by ``study=NAME`` is read as :func:`read_inputs` reads it.
    """
    points = Points(read_points(study.data) if rows is None else rows)
    source = read_template(study.template) if present(study.template) else None
    text = source if source is not None else default_template(study, points)
    where = study.template if source is not None else "default template"
    try:
        meta, body = split_front_matter(text)
    except PageError as err:
        raise PageError(f"{where}: {err}") from None

    def other(name: str) -> Points:
        rows = read_inputs(Study(name, study.figures, study.docs)).rows
        if not rows:
            raise PageError(f"no data for study {name!r}")
        return Points(rows)

    def fill(match: re.Match[str]) -> str:
        expression = " ".join(match[1].split())
        try:
            if expression == "figure":
                return f"![{study.name}](../sweeps/{study.name}.png)"
            if expression == "commands":
                return commands(study, bool(points.rows))
            if expression == "csv":
                return f"[`data/{study.name}.csv`](data/{study.name}.csv)"
            if not points.rows:
                raise PageError(f"no data ({study.data} is missing)")
            if expression == "table" or expression.startswith("table "):
                name = expression.removeprefix("table").strip()
                spec = (meta.get("tables") or {}).get(name) if name else meta.get("table")
                if not spec:
                    raise PageError(f"no table {name or 'table'!r} in the front matter")
                return render_table(points, spec)
            return evaluate(points, expression, other)
        except PageError as err:
            raise PageError(f"{where}: {{{{{expression}}}}}: {err}") from None

    header = (
        f"<!-- Generated by `python -m analysis.study_pages {study.name}` from "
        f"{'`studies/' + study.name + '.in.md`' if source is not None else 'its default template'}"
        f" and `studies/data/{study.name}.csv`: edit the template, not this file. -->\n"
    )
    page = _PLACEHOLDER.sub(fill, body)
    if "{{" in page or "}}" in page:
        raise PageError(f"{where}: an unclosed placeholder")
    return header + page


def studies(docs: Path, figures: Path) -> list[str]:
    """Every study with a template or with an aggregated CSV under ``figures``."""
    names = {p.name.removesuffix(".in.md") for p in (docs / "studies").glob("*.in.md")}
    names |= {p.parent.name for p in figures.glob("*/sweep_aggregated.csv")}
    return sorted(names)


def main(argv: Iterable[str] | None = None) -> int:
    """Render the pages; exit status 2 with one line when an input is refused or a
    template does not render, before any file is written.
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", nargs="*", help="studies (default: all)")
    parser.add_argument("--figures", type=Path, default=Path("figures/sweeps"))
    parser.add_argument("--docs", type=Path, default=ROOT / "docs")
    args = parser.parse_args(None if argv is None else list(argv))
    done = []
    for name in args.study or studies(args.docs, args.figures):
        study = Study(name, args.figures, args.docs)
        try:  # every input checked and every page rendered before anything is written
            inputs = read_inputs(study)
            done.append((study, inputs, render(study, inputs.rows)))
        except PageError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
    for study, inputs, page in done:
        write_inputs(study, inputs)
        write_text(study.page, page)
        print(study.page)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
