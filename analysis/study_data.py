"""A study's inputs for its documentation page (:mod:`analysis.study_pages`): where they
are, and each read and checked before anything is written.

The sweep's ``sweep_aggregated.csv`` and figure, the study's template and its preset are
read through :mod:`harness.files` (regular files only, size capped, text strictly
UTF-8); the CSV must be text without control characters, with the columns of an
aggregated sweep, at least one row and every row whole (:func:`parse_points`), the figure
a whole PNG (:func:`harness.png.png_problem`). Only then are they copied into ``docs``
(:func:`write_inputs`, atomically): a bad input is one line and leaves every file in
``docs`` as it was.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import yaml

from analysis.output import atomic_path
from analysis.safe_yaml import ConfigRecordError, safe_config
from harness.files import UnreadableFile, read_bytes, read_text
from harness.png import png_problem

ROOT = Path(__file__).resolve().parents[1]
"""The repository's root (``conf/`` and ``docs/`` are found from here)."""


class PageError(ValueError):
    """A template that cannot be rendered from its data; the message is one line."""


@dataclass(frozen=True)
class Study:
    """Where a study's inputs and outputs are.

    Attributes:
        name: The study (``conf/experiment/<name>.yaml``).
        figures: The directory ``analysis.sweep`` wrote the study's outputs to.
        docs: The documentation directory.
    """

    name: str
    figures: Path
    docs: Path

    @property
    def template(self) -> Path:
        """``docs/studies/<name>.in.md``."""
        return self.docs / "studies" / f"{self.name}.in.md"

    @property
    def page(self) -> Path:
        """``docs/studies/<name>.md``."""
        return self.docs / "studies" / f"{self.name}.md"

    @property
    def data(self) -> Path:
        """``docs/studies/data/<name>.csv``, the copy of the aggregated CSV."""
        return self.docs / "studies" / "data" / f"{self.name}.csv"

    @property
    def image(self) -> Path:
        """``docs/sweeps/<name>.png``, the copy of the figure."""
        return self.docs / "sweeps" / f"{self.name}.png"


MAX_TEXT_BYTES = 1 << 20
"""Largest template or preset read (bytes; each is a few kB)."""


def read_template(path: Path) -> str:
    """The text of the template ``path`` (:func:`harness.files.read_text`: a regular
    file of at most :data:`MAX_TEXT_BYTES`, strict UTF-8).

    Raises:
        PageError: for a template that cannot be read so, in one line.
    """
    try:
        return read_text(path, MAX_TEXT_BYTES)
    except UnreadableFile as err:
        raise PageError(str(err)) from None


def _analysis(name: str, conf: Path) -> dict[str, object]:
    """The ``analysis`` block of study ``name``'s preset ``conf/experiment/<name>.yaml``
    (empty without a preset or a block), read as :func:`read_template` reads a template
    and parsed within bounds (:func:`analysis.safe_yaml.safe_config`).

    Raises:
        PageError: for a preset that cannot be read or is not a mapping, in one line.
    """
    path = conf / "experiment" / f"{name}.yaml"
    if not present(path):
        return {}
    try:
        preset = safe_config(read_template(path)) or {}
    except (ConfigRecordError, yaml.YAMLError) as err:
        raise PageError(f"{path}: not a YAML preset ({' '.join(str(err).split())})") from None
    block = preset.get("analysis") if isinstance(preset, dict) else None
    if not isinstance(preset, dict) or not isinstance(block or {}, dict):
        raise PageError(f"{path}: not a preset (a mapping with an analysis mapping)")
    return dict(block or {})


def declared_figure(name: str, conf: Path = ROOT / "conf") -> str:
    """The figure study ``name`` declares (``analysis.figure`` of its preset; the
    generic ``convergence`` without one).
    """
    return str(_analysis(name, conf).get("figure", "convergence"))


def declared_primary(name: str, conf: Path = ROOT / "conf") -> list[str]:
    """The keys study ``name`` declares as its points (``analysis.primary``)."""
    primary = _analysis(name, conf).get("primary") or []
    if not isinstance(primary, list):
        raise PageError(f"the preset of {name}: analysis.primary is not a list")
    return [str(k) for k in primary]


MAX_CSV_BYTES = 64 << 20
"""Largest aggregated CSV read (bytes; a study's is tens of kB)."""

MAX_FIGURE_BYTES = 64 << 20
"""Largest figure copied (bytes)."""

CONTROL = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f]")
"""A control character other than tab, line feed and carriage return (C0, DEL, C1)."""

REQUIRED_COLUMNS = ("law", "jobs")
"""Columns every aggregated CSV has (:func:`analysis.rows.points`), beside at least one
statistic ``STAT_mean``."""


@dataclass(frozen=True)
class Inputs:
    """A study's inputs, read and checked before anything is written.

    Attributes:
        rows: The aggregated rows the page is rendered from.
        csv: The new aggregated CSV's bytes, to copy to :attr:`Study.data` (None: the
            copy in ``docs`` is used).
        figure: The new figure's bytes, to copy to :attr:`Study.image` (None: the copy in
            ``docs`` is used).
    """

    rows: list[dict[str, str]]
    csv: bytes | None
    figure: bytes | None


def parse_points(data: bytes, path: Path) -> list[dict[str, str]]:
    """The rows of the aggregated CSV ``data`` (the bytes of ``path``), checked: UTF-8
    text without control characters other than tab and line ends (:data:`CONTROL`), a
    header with :data:`REQUIRED_COLUMNS` and a ``STAT_mean`` column, at least
    one row, every row as long as the header and the last one ended by a line break
    (a file cut short is refused, not read as fewer points).

    Raises:
        PageError: naming ``path`` and what is wrong, in one line.
    """
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise PageError(f"{path}: not UTF-8 text (byte {err.start}: {err.reason})") from None
    if not text.strip():
        raise PageError(f"{path}: empty, not an aggregated sweep CSV")
    control = CONTROL.search(text)
    if control:
        line = text.count("\n", 0, control.start()) + 1
        code = f"U+{ord(control.group()):04X}"
        raise PageError(f"{path}: a control character ({code}) on line {line}, not a CSV cell")
    try:
        table = list(csv.reader(text.splitlines(keepends=True), strict=True))
    except csv.Error as err:
        raise PageError(f"{path}: cut short or not a CSV file ({err})") from None
    header, rows = table[0], [r for r in table[1:] if r]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing or not any(c.endswith("_mean") for c in header):
        what = ", ".join(missing) if missing else "a STAT_mean column"
        raise PageError(f"{path}: not an aggregated sweep CSV (no {what} in its header)")
    if len(set(header)) != len(header):
        raise PageError(f"{path}: a column name appears twice in its header")
    if not rows:
        raise PageError(f"{path}: a header without rows (no point of the sweep)")
    for number, row in enumerate(rows, start=2):
        if len(row) != len(header):
            raise PageError(
                f"{path}: row {number} has {len(row)} cells, the header {len(header)} "
                "(cut short or damaged)"
            )
    if not text.endswith(("\n", "\r")):
        raise PageError(f"{path}: its last row has no line end (cut short)")
    return [dict(zip(header, row, strict=True)) for row in rows]


def read_inputs(study: Study) -> Inputs:
    """The study's inputs: the sweep's aggregated CSV and figure when they exist (read
    through :mod:`harness.files`: regular files only, size capped), else the copies in
    ``docs``; each CSV checked (:func:`parse_points`), each figure a whole PNG
    (:func:`harness.png.png_problem`).

    Raises:
        PageError: for an input that cannot be read or is not what it should be (one
            line); nothing has been written then.
    """
    source = study.figures / study.name / "sweep_aggregated.csv"
    new_csv = _read(source, MAX_CSV_BYTES) if present(source) else None
    if new_csv is not None:
        rows = parse_points(new_csv, source)
    elif present(study.data):
        rows = parse_points(_read(study.data, MAX_CSV_BYTES), study.data)
    else:
        rows = []
    figure = study.figures / study.name / f"{declared_figure(study.name)}.png"
    new_figure = _read(figure, MAX_FIGURE_BYTES) if present(figure) else None
    problem = None if new_figure is None else png_problem(new_figure)
    if problem:
        raise PageError(f"{figure}: not a PNG image ({problem})")
    return Inputs(rows, new_csv, new_figure)


def present(path: Path) -> bool:
    """Whether anything (a file, a FIFO, a broken link, ...) is at ``path``."""
    return path.exists() or path.is_symlink()


def _read(path: Path, limit: int) -> bytes:
    """The bytes of ``path`` (:func:`harness.files.read_bytes`), a refusal as a
    :class:`PageError`.
    """
    try:
        return read_bytes(path, limit)
    except UnreadableFile as err:
        raise PageError(str(err)) from None


def write_inputs(study: Study, inputs: Inputs) -> list[Path]:
    """Copy the checked new inputs into ``docs``, each atomically; the paths written."""
    written = []
    for data, path in ((inputs.csv, study.data), (inputs.figure, study.image)):
        if data is None:
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
        written.append(path)
    return written


def read_points(path: Path) -> list[dict[str, str]]:
    """The checked rows of an aggregated CSV (:func:`parse_points`; empty when there is
    none).
    """
    if not present(path):
        return []
    return parse_points(_read(path, MAX_CSV_BYTES), path)
