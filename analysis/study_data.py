"""A study's inputs for its documentation page (:mod:`analysis.study_pages`): where they
are, and each read and checked before anything is written.

The sweep's ``sweep_aggregated.csv`` and figure, the study's template and its preset are
read through :mod:`harness.files` (regular files only, size capped, text strictly
UTF-8); the CSV must be text without control characters, with the columns of an
aggregated sweep, at least one row and every row whole (:func:`parse_points`), the figure
a whole PNG (:func:`png_problem`). Only then are they copied into ``docs``
(:func:`write_inputs`, atomically): a bad input is one line and leaves every file in
``docs`` as it was.
"""

from __future__ import annotations

import csv
import re
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import yaml

from analysis.output import atomic_path
from analysis.safe_yaml import ConfigRecordError, safe_config
from harness.files import UnreadableFile, read_bytes, read_text

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

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
"""The first bytes of every PNG file."""

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


def png_problem(data: bytes) -> str:
    """What makes ``data`` other than a whole PNG file a viewer can show, in words (empty
    when nothing does).

    In order: the signature; at most :data:`MAX_CHUNKS` chunks, each of a length that
    fits in the file and a matching CRC-32; ``IHDR`` first (13 bytes: a width and height
    from 1 to :data:`MAX_SIDE`, a colour type with one of its allowed bit depths,
    compression and filter methods 0, interlace 0 or 1); every later chunk one libpng
    reads (:func:`chunk_problem`); ``PLTE`` before the pixels of a palette image; the
    ``IDAT`` chunks consecutive; ``IEND`` last with nothing after it. Then the ``IDAT``
    data must inflate (:func:`pixels_problem`) to exactly the scanlines ``IHDR``
    declares, each with a known filter type, so a damaged stream under recomputed CRCs
    is found too. Last, Pillow (matplotlib's reader of PNG files) must decode it.
    Nothing is inflated or decoded before the declared image is known to be within the
    pixel budget.
    """
    if not data.startswith(PNG_SIGNATURE):
        return "no PNG signature"
    at, header = len(PNG_SIGNATURE), b""
    stream: list[bytes] = []
    kinds: list[bytes] = []
    while True:
        if len(kinds) >= MAX_CHUNKS:
            return f"more than {MAX_CHUNKS} chunks"
        if at + 12 > len(data):
            return f"cut short at byte {at} (no IEND chunk)"
        length, kind = struct.unpack(">I4s", data[at : at + 8])
        end = at + 12 + length
        if length > 0x7FFFFFFF or end > len(data):
            return f"a chunk at byte {at} runs past the end of the file (cut short)"
        body = data[at + 8 : end - 4]
        if zlib.crc32(data[at + 4 : end - 4]) != struct.unpack(">I", data[end - 4 : end])[0]:
            return f"the {kind[:4]!r} chunk at byte {at} fails its CRC (damaged)"
        if not kinds:
            if kind != b"IHDR" or length != 13:
                return "its first chunk is not a 13-byte IHDR"
            problem = header_problem(body)
            if problem:
                return problem
            header = body
        else:
            problem = chunk_problem(kind, body, header, kinds)
            if problem:
                return f"{problem} (chunk at byte {at})"
        if kind == b"IDAT":
            if stream and kinds[-1] != b"IDAT":
                return "its IDAT chunks are not consecutive"
            stream.append(body)
        kinds.append(kind)
        at = end
        if kind == b"IEND":
            break
    if not stream:
        return "no IDAT chunk (no pixels)"
    if at != len(data):
        return f"{len(data) - at} bytes after its IEND chunk"
    if header[9] == 3 and (b"PLTE" not in kinds or kinds.index(b"PLTE") > kinds.index(b"IDAT")):
        return "a palette image without a PLTE chunk before its pixels"
    return pixels_problem(header, b"".join(stream)) or decoder_problem(data)


def chunk_problem(kind: bytes, body: bytes, header: bytes, before: list[bytes]) -> str:
    """What libpng would refuse in a chunk after ``IHDR``, in words (empty when nothing).

    The chunk type is four ASCII letters; a critical chunk (first letter upper case) is
    one of ``IHDR``, ``PLTE``, ``IDAT``, ``IEND``, and ``IHDR`` comes only first; ``PLTE``
    comes at most once, before the pixels, never in a grey image, with 1 to
    ``2^depth`` (at most 256) entries of 3 bytes.

    Args:
        kind: The chunk's type (4 bytes).
        body: The chunk's data.
        header: The 13-byte ``IHDR`` body, already checked.
        before: The types of the chunks before it, in order.
    """
    if not all(65 <= c <= 90 or 97 <= c <= 122 for c in kind):
        return f"a chunk type {kind!r} that is not four ASCII letters"
    if kind[0] <= 90 and kind not in CRITICAL:
        return f"an unknown critical chunk {kind.decode()}"
    if kind == b"IHDR":
        return "a second IHDR"
    if kind == b"PLTE":
        depth, colour = header[8], header[9]
        entries = min(256, 1 << depth) if colour == 3 else 256
        if b"PLTE" in before:
            return "a second PLTE"
        if b"IDAT" in before:
            return "a PLTE after the pixels"
        if colour in (0, 4):
            return "a PLTE in a grey image"
        if not body or len(body) % 3 or len(body) // 3 > entries:
            return f"a PLTE of {len(body)} bytes (PNG allows 3 to {3 * entries} in steps of 3)"
    return ""


CRITICAL = (b"IHDR", b"PLTE", b"IDAT", b"IEND")
"""The critical chunk types PNG defines; a viewer refuses any other critical chunk."""

MAX_CHUNKS = 1 << 14
"""Most chunks read from one PNG: a 64 MiB figure in 8 KiB IDATs has 8192; bounds the
time spent on a file of millions of tiny chunks."""

MAX_SIDE = 4096
"""Largest width or height accepted (pixels; libpng's own default limit is 10^6)."""

MAX_FIGURE_PIXELS = MAX_SIDE * MAX_SIDE
"""Largest figure accepted (pixels): about 16.8 million, 4096 x 4096; a study's figure
has about 1.5 million. Bounds what inflating and decoding one may allocate."""

CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
"""Samples per pixel of each PNG colour type (grey, RGB, palette, grey + alpha, RGBA)."""

DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
"""The bit depths the PNG specification allows for each colour type."""

ADAM7 = (
    (0, 0, 8, 8),
    (4, 0, 8, 8),
    (0, 4, 4, 8),
    (2, 0, 4, 4),
    (0, 2, 2, 4),
    (1, 0, 2, 2),
    (0, 1, 1, 2),
)
"""The seven passes of an interlaced PNG: first column, first row, column step, row step."""


def header_problem(header: bytes) -> str:
    """What is wrong with a 13-byte ``IHDR`` body (empty when nothing is)."""
    width, height, depth, colour, compression, method, interlace = struct.unpack(">IIBBBBB", header)
    if not (0 < width <= MAX_SIDE and 0 < height <= MAX_SIDE):
        return f"an image of {width} x {height} pixels (each side 1 to {MAX_SIDE} allowed)"
    if depth not in DEPTHS.get(colour, ()):
        return (
            f"IHDR declares colour type {colour} with bit depth {depth}, which PNG does not allow"
        )
    if compression != 0 or method != 0 or interlace not in (0, 1):
        return (
            f"IHDR declares compression method {compression}, filter method {method}, "
            f"interlace {interlace} (PNG allows 0, 0 and 0 or 1)"
        )
    return ""


def scanlines(header: bytes) -> list[tuple[int, int]]:
    """``(rows, bytes per row including the filter byte)`` of each pass of the image
    ``header`` declares (one pass for a plain image, the seven Adam7 passes for an
    interlaced one; passes without pixels left out).
    """
    width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", header)
    bits = CHANNELS[colour] * depth
    out = []
    for x0, y0, dx, dy in ADAM7 if interlace else ((0, 0, 1, 1),):
        columns, rows = -(-(width - x0) // dx), -(-(height - y0) // dy)
        if columns > 0 and rows > 0:
            out.append((rows, 1 + -(-columns * bits // 8)))
    return out


def pixels_problem(header: bytes, stream: bytes) -> str:
    """What is wrong with a PNG's concatenated ``IDAT`` data, in words (empty when
    nothing is).

    The data must be one zlib stream (its Adler-32 checked by ``zlib``) that inflates to
    exactly the bytes of :func:`scanlines` (``rows * (1 + ceil(columns * bits per pixel
    / 8))`` summed over the passes), every scanline starting with a filter type 0 to 4.
    Inflation stops one byte past the declared size, which ``IHDR``'s checks
    (:func:`header_problem`) keep within :data:`MAX_FIGURE_PIXELS` pixels.

    Args:
        header: The 13-byte ``IHDR`` body, already checked.
        stream: The ``IDAT`` chunks' data, joined in order.
    """
    passes = scanlines(header)
    size = sum(rows * row for rows, row in passes)
    inflater = zlib.decompressobj()
    try:
        pixels = inflater.decompress(stream, size + 1)
    except zlib.error as error:
        return f"its pixel data does not inflate ({error}; damaged)"
    if len(pixels) != size or not inflater.eof or inflater.unused_data:
        return f"its pixel data is not the {size} bytes IHDR declares (damaged)"
    at = 0
    for rows, row in passes:
        if any(pixels[at + k * row] > 4 for k in range(rows)):
            return "a scanline with an unknown filter type (damaged)"
        at += rows * row
    return ""


def decoder_problem(data: bytes) -> str:
    """What Pillow, the decoder matplotlib reads PNG files with, says of ``data`` (empty
    when it decodes the whole image). Called only on a file whose pixel count is
    within :data:`MAX_FIGURE_PIXELS`.
    """
    import io

    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as image:
            image.load()
    except Exception as err:  # any refusal of the decoder: the figure could not be shown
        return f"Pillow cannot decode it ({type(err).__name__}: {str(err)[:120]})"
    return ""


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
    (:func:`png_problem`).

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
