"""The study pages (analysis/study_pages.py): every number from the study's aggregated
CSV, a placeholder that matches no point refused, and the committed pages up to date."""

import csv
import os
import struct
import zlib
from pathlib import Path

import pytest

from analysis import study_pages as sp
from analysis.study_data import declared_figure, read_inputs
from harness.png import PNG_SIGNATURE, png_problem
from tests.test_floor_cache_hostile import Unblocker

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

ROWS = [
    {"law": "paper", "agents.n": "1024", "estimator.delta": "0.1", "jobs": "2",
     "swarm_ratio_mean": "1.07", "swarm_ratio_ci_low": "0.5", "swarm_ratio_ci_high": "1.6",
     "phi_sup_mean": "0.11", "eps_sup_mean": "0.1"},
    {"law": "paper", "agents.n": "4096", "estimator.delta": "0.3", "jobs": "2",
     "swarm_ratio_mean": "2.0", "swarm_ratio_ci_low": "nan", "swarm_ratio_ci_high": "nan",
     "phi_sup_mean": "0.32", "eps_sup_mean": "0.3"},
    {"law": "heat", "agents.n": "1024", "estimator.delta": "0.0", "jobs": "2",
     "swarm_ratio_mean": "0.83", "swarm_ratio_ci_low": "0.7", "swarm_ratio_ci_high": "0.95",
     "phi_sup_mean": "0.001", "eps_sup_mean": "0.0"},
]  # fmt: skip

TEMPLATE = """---
table:
  where: {agents.n: 1024}
  sort: [law]
  columns:
    - law
    - {key: agents.n, label: N}
    - {stat: swarm_ratio, label: "`||swarm||` / floor", ci: true, fmt: .2f}
---
# A study

Paper at N = 1024: {{ci swarm_ratio @ law=paper,
agents.n=1024 : .2f}}; heat {{swarm_ratio @ law=heat}}; largest {{max swarm_ratio @
agents.n=1024|4096}}; gain {{gain phi_sup / eps_sup @ law=paper : .3f}}.

{{table}}

{{figure}}

{{commands}}
"""


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png(width: int = 2, height: int = 2) -> bytes:
    """A whole grey PNG of ``width`` x ``height`` pixels."""
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    pixels = b"".join(b"\0" + b"\x80" * width for _ in range(height))
    return (
        PNG_SIGNATURE
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(pixels))
        + _chunk(b"IEND", b"")
    )


def make_study(tmp_path: Path, template: str | None = TEMPLATE, name: str = "mine"):
    figures, docs = tmp_path / "figures", tmp_path / "docs"
    (figures / name).mkdir(parents=True)
    with (figures / name / "sweep_aggregated.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(ROWS[0]))
        writer.writeheader()
        writer.writerows(ROWS)
    (figures / name / "convergence.png").write_bytes(png())
    (docs / "studies").mkdir(parents=True)
    if template is not None:
        (docs / "studies" / f"{name}.in.md").write_text(template)
    return sp.Study(name, figures, docs)


def test_a_page_takes_every_number_from_its_data(tmp_path):
    study = make_study(tmp_path)
    assert sp.main([study.name, "--figures", str(study.figures), "--docs", str(study.docs)]) == 0
    page = study.page.read_text()
    assert "Paper at N = 1024: 1.07 (0.50 to 1.60); heat 0.83; largest 2;" in page
    gain = (0.1 * 0.11 + 0.3 * 0.32) / (0.1**2 + 0.3**2)
    assert f"gain {gain:.3f}." in page
    table = [line for line in page.splitlines() if line.startswith("|")]
    assert table[0] == r"| law | N | `\|\|swarm\|\|` / floor |"
    assert table[2:] == ["| `heat` | `1024` | 0.83 (0.70 to 0.95) |",
                         "| `paper` | `1024` | 1.07 (0.50 to 1.60) |"]  # fmt: skip
    assert "![mine](../sweeps/mine.png)" in page
    assert "python -m analysis.study_pages mine" in page and "data/mine.csv" in page
    assert "{{" not in page
    assert study.data.read_text() == (study.figures / "mine" / "sweep_aggregated.csv").read_text()
    assert study.image.read_bytes() == png()


@pytest.mark.parametrize(
    "placeholder, why",
    [
        ("{{swarm_ratio @ law=paper}}", "2 points match"),
        ("{{swarm_ratio @ law=ot}}", "0 points match"),
        ("{{nosuch @ law=heat}}", "no column 'nosuch'"),
        ("{{swarm_ratio @ nokey=1}}", "no key 'nokey'"),
        ("{{gain phi_sup / eps_sup @ law=heat}}", "fewer than two points"),
        ("{{swarm_ratio @ law=heat", "unclosed placeholder"),
    ],
)
def test_a_placeholder_that_does_not_fit_the_data_stops_the_page(
    tmp_path, capsys, placeholder, why
):
    study = make_study(tmp_path, f"# A study\n\n{placeholder}\n")
    code = sp.main([study.name, "--figures", str(study.figures), "--docs", str(study.docs)])
    assert code == 2
    err = capsys.readouterr().err
    assert why in err and len(err.strip().splitlines()) == 1
    assert not study.page.exists()


def test_a_pivot_table_lays_a_statistic_out_by_two_keys(tmp_path):
    template = TEMPLATE.replace(
        "  where: {agents.n: 1024}\n  sort: [law]\n  columns:\n    - law\n"
        "    - {key: agents.n, label: N}\n"
        '    - {stat: swarm_ratio, label: "`||swarm||` / floor", ci: true, fmt: .2f}\n',
        "  pivot: {rows: law, columns: agents.n, stat: swarm_ratio, fmt: .2g}\n",
    )
    study = make_study(tmp_path, template)
    page = sp.render(study, read_inputs(study).rows)
    table = [line for line in page.splitlines() if line.startswith("|")]
    assert table[0] == r"| law \ agents.n | `1024` | `4096` |"
    assert table[2:] == ["| `heat` | 0.83 |  |", "| `paper` | 1.1 | 2 |"]


def test_a_study_without_a_template_gets_a_page_of_its_keys(tmp_path):
    study = make_study(tmp_path, template=None, name="smoke")
    page = sp.render(study, read_inputs(study).rows)
    assert "# Study `smoke`" in page and "swarm_ratio" in page and "{{" not in page


def test_a_page_without_data_renders_its_prose_and_says_where_the_numbers_come_from(tmp_path):
    docs = tmp_path / "docs"
    (docs / "studies").mkdir(parents=True)
    (docs / "studies" / "later.in.md").write_text("# Later\n\nQuoted.\n\n{{commands}}\n")
    study = sp.Study("later", tmp_path / "none", docs)
    page = sp.render(study)
    assert "No copy of the sweep's `sweep_aggregated.csv`" in page
    bad = docs / "studies" / "later.in.md"
    bad.write_text("# Later\n\n{{swarm_ratio @ law=paper}}\n")
    with pytest.raises(sp.PageError, match="no data"):
        sp.render(study)


@pytest.mark.parametrize("name", sp.studies(DOCS, ROOT / "no-figures"))
def test_the_committed_study_pages_are_rendered_from_their_templates_and_data(name):
    study = sp.Study(name, ROOT / "no-figures", DOCS)
    assert study.page.read_text() == sp.render(study), (
        f"docs/studies/{name}.md is not what its template and data give: "
        f"python -m analysis.study_pages {name}"
    )


GOOD_DATA = b"law,jobs,swarm_ratio_mean\r\npaper,2,1.07\r\n"


@pytest.mark.parametrize(
    "data, why",
    [
        (b"", "empty"),
        (b"law,agents.n,jobs,swarm_ratio_mean\r\npaper,1024,2,1.0", "cut short"),
        (b"law,agents.n,jobs,swarm_ratio_mean\r\npaper,1024\r\n", "cut short"),
        (b"law,agents.n,jo", "not an aggregated sweep CSV"),
        (b"name,price\r\nwidget,3\r\n", "not an aggregated sweep CSV"),
        (b"law,jobs,swarm_ratio_mean\r\n", "without rows"),
        (b"law,jobs,swarm_ratio_mean\r\npaper,2,\xff\xfe1.0\r\n", "not UTF-8"),
        (b'law,jobs,swarm_ratio_mean\r\n"paper,2,1.0\r\n', "cut short"),
        (b"law,jobs,swarm_ratio_mean\r\npaper,2,\x001.1\r\n", "control character (U+0000)"),
        (b"law,jobs,swarm_ratio_mean\r\npaper\x1b,2,1.1\r\n", "control character (U+001B)"),
        (b"law,jobs,swarm_ratio_mean\r\npaper,2,1.1\x7f\r\n", "control character (U+007F)"),
        ("law,jobs,swarm_ratio_mean\npaper,2,1.1\x85\n".encode(), "control character (U+0085)"),
    ],
    ids=["empty", "cut-mid-row", "short-row", "cut-header", "foreign", "header-only",
         "not-utf8", "open-quote", "nul", "escape", "delete", "c1-next-line"],
)  # fmt: skip
def test_a_bad_aggregated_csv_is_refused_in_one_line_before_anything_is_written(
    tmp_path, capsys, data, why
):
    study = make_study(tmp_path)
    study.data.parent.mkdir(parents=True)
    study.data.write_bytes(GOOD_DATA)
    study.page.write_text("the old page\n")
    (study.figures / study.name / "sweep_aggregated.csv").write_bytes(data)
    code = sp.main([study.name, "--figures", str(study.figures), "--docs", str(study.docs)])
    err = capsys.readouterr().err
    assert code == 2 and why in err and len(err.strip().splitlines()) == 1, err
    assert "sweep_aggregated.csv" in err
    assert study.data.read_bytes() == GOOD_DATA  # the committed data is kept
    assert study.page.read_text() == "the old page\n"
    assert not study.image.exists()  # nothing copied
    assert sorted(p.name for p in study.data.parent.iterdir()) == [f"{study.name}.csv"]


def test_a_fifo_or_a_non_png_in_place_of_an_input_is_refused_without_writing(tmp_path, capsys):
    import os

    study = make_study(tmp_path)
    source = study.figures / study.name / "sweep_aggregated.csv"
    source.unlink()
    os.mkfifo(source)  # would block an open() for reading
    args = [study.name, "--figures", str(study.figures), "--docs", str(study.docs)]
    assert sp.main(args) == 2
    assert "a FIFO" in capsys.readouterr().err
    assert not study.data.exists() and not study.page.exists()
    source.unlink()
    make_study(tmp_path / "again")  # a good CSV, beside a figure that is not a PNG
    study = sp.Study(study.name, tmp_path / "again" / "figures", tmp_path / "again" / "docs")
    (study.figures / study.name / "convergence.png").write_text("<html>")
    assert sp.main([*args[:1], "--figures", str(study.figures), "--docs", str(study.docs)]) == 2
    assert "not a PNG image" in capsys.readouterr().err
    assert not study.data.exists() and not study.page.exists()


def test_a_new_csv_is_written_only_when_its_page_renders(tmp_path, capsys):
    study = make_study(tmp_path, "# A study\n\n{{swarm_ratio @ law=nosuch}}\n")
    study.data.parent.mkdir(parents=True)
    study.data.write_bytes(GOOD_DATA)
    args = [study.name, "--figures", str(study.figures), "--docs", str(study.docs)]
    assert sp.main(args) == 2
    assert study.data.read_bytes() == GOOD_DATA and not study.page.exists()


def test_the_committed_figures_are_whole_pngs():
    figures = sorted((DOCS / "sweeps").glob("*.png"))
    assert figures
    assert {f.name: png_problem(f.read_bytes()) for f in figures} == {f.name: "" for f in figures}


def _cut(data: bytes) -> bytes:
    return data[:100]


def _signature_only(data: bytes) -> bytes:
    return PNG_SIGNATURE


def _no_iend(data: bytes) -> bytes:
    return data[:-12]


def _flipped(data: bytes) -> bytes:
    at = len(data) // 2  # inside the IDAT chunk: its CRC no longer matches
    return data[:at] + bytes([data[at] ^ 1]) + data[at + 1 :]


def _trailing(data: bytes) -> bytes:
    return data + b"<html>"


def _no_ihdr(data: bytes) -> bytes:
    return PNG_SIGNATURE + data[len(PNG_SIGNATURE) + 25 :]  # the IHDR chunk (25 bytes) left out


def _long_chunk(data: bytes) -> bytes:
    start = len(PNG_SIGNATURE) + 25  # the IDAT's length: past the end of the file
    return data[:start] + struct.pack(">I", 1 << 30) + data[start + 4 :]


def _with_idat(data: bytes, pixels: bytes) -> bytes:
    """``data`` with its ``IDAT`` chunks replaced by one holding ``pixels``, CRC made to
    match, so only the pixel data itself is wrong."""
    at, chunks = len(PNG_SIGNATURE), []
    while at < len(data):
        (length,) = struct.unpack(">I", data[at : at + 4])
        chunks.append(data[at : at + 12 + length])
        at += 12 + length
    idat = b"IDAT" + pixels
    new = struct.pack(">I", len(pixels)) + idat + struct.pack(">I", zlib.crc32(idat))
    kept = [c for c in chunks if c[4:8] != b"IDAT"]
    return PNG_SIGNATURE + b"".join(kept[:-1]) + new + kept[-1]


def _idat(data: bytes) -> bytes:
    at, parts = len(PNG_SIGNATURE), []
    while at < len(data):
        (length,) = struct.unpack(">I", data[at : at + 4])
        if data[at + 4 : at + 8] == b"IDAT":
            parts.append(data[at + 8 : at + 8 + length])
        at += 12 + length
    return b"".join(parts)


def _stream_damaged_crc_recomputed(data: bytes) -> bytes:
    stream = bytearray(_idat(data))
    middle = len(stream) // 2
    stream[middle : middle + 64] = bytes(b ^ 0x5A for b in stream[middle : middle + 64])
    return _with_idat(data, bytes(stream))


def _too_few_pixels(data: bytes) -> bytes:
    pixels = zlib.decompress(_idat(data))
    return _with_idat(data, zlib.compress(pixels[: len(pixels) // 2]))


def _too_many_pixels(data: bytes) -> bytes:
    pixels = zlib.decompress(_idat(data))
    return _with_idat(data, zlib.compress(pixels + bytes(1 << 20)))


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _png(ihdr: tuple, pixels: bytes, between: bytes = b"", split: bool = False) -> bytes:
    """A PNG from its IHDR fields ``(w, h, depth, colour, compression, filter, interlace)``
    and its raw scanlines ``pixels`` (zlib-compressed here); ``between`` goes between two
    halves of the IDAT data when ``split``."""
    head = _chunk(b"IHDR", struct.pack(">IIBBBBB", *ihdr))
    data = zlib.compress(pixels)
    if split:
        idat = _chunk(b"IDAT", data[: len(data) // 2]) + between
        idat += _chunk(b"IDAT", data[len(data) // 2 :])
    else:
        idat = _chunk(b"IDAT", data)
    palette = _chunk(b"PLTE", bytes(range(48))) if ihdr[3] == 3 else b""
    return PNG_SIGNATURE + head + palette + idat + _chunk(b"IEND", b"")


ADAM7_8X8 = [(1, 1), (1, 1), (1, 2), (2, 2), (2, 4), (4, 4), (4, 8)]
"""(rows, columns) of the seven Adam7 passes of an 8 x 8 image (the PNG specification)."""


def _interlaced(filter_of_pass_4: int) -> bytes:
    rows = []
    for k, (n_rows, cols) in enumerate(ADAM7_8X8):
        for _ in range(n_rows):
            rows.append(bytes([filter_of_pass_4 if k == 3 else 0]) + bytes(range(cols)))
    return _png((8, 8, 8, 0, 0, 0, 1), b"".join(rows))


def _plain(width: int, height: int, depth: int, colour: int, row: int, **kw) -> bytes:
    method = kw.pop("method", 0)
    return _png((width, height, depth, colour, 0, method, 0), (b"\0" + bytes(row)) * height, **kw)


def test_a_valid_interlaced_png_is_accepted():
    assert png_problem(_interlaced(0)) == ""


@pytest.mark.parametrize(
    "data, why",
    [
        (_interlaced(7), "unknown filter type"),
        (_plain(4, 4, 16, 3, 8), "bit depth 16"),  # a palette of 16 bits
        (_plain(4, 4, 4, 2, 6), "bit depth 4"),  # RGB of 4 bits
        (_plain(4, 4, 8, 0, 4, method=1), "filter method 1"),
        (_plain(4, 4, 8, 0, 4, split=True, between=_chunk(b"tEXt", b"a\0b")), "not consecutive"),
        (_png((0x7FFFFFFF, 0x7FFFFFFF, 16, 6, 0, 0, 0), b"\0" * 100), "each side"),
        (_png((0xFFFFFFFF, 0xFFFFFFFF, 8, 0, 0, 0, 0), b"\0" * 100), "pixels"),
        (_png((65536, 81920, 8, 0, 0, 0, 0), b"\0" * 1000), "each side"),
    ],
    ids=["interlaced-bad-filter", "palette-depth-16", "rgb-depth-4", "filter-method-1",
         "idat-not-consecutive", "huge-dimensions", "dimensions-beyond-png", "bomb"],
)  # fmt: skip
def test_a_png_no_decoder_shows_is_refused_before_anything_is_inflated(data, why):
    import tracemalloc

    tracemalloc.start()
    try:
        problem = png_problem(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert why in problem, problem
    assert peak < 20e6, f"{peak / 1e6:.0f} MB to check a PNG of {len(data)} bytes"


def _with_chunk(chunk: bytes, data: bytes | None = None, at: int = 33) -> bytes:
    """``data`` (a 4 x 4 grey PNG by default) with ``chunk`` inserted at byte ``at``
    (33: right after IHDR)."""
    data = _plain(4, 4, 8, 0, 4) if data is None else data
    return data[:at] + chunk + data[at:]


PALETTE_4X4 = _plain(4, 4, 8, 3, 4)
"""A 4 x 4 palette image whose PLTE (16 entries) follows IHDR."""


def _libpng_problem(data: bytes) -> str | None:
    """What libpng 1.6's simplified reader says of ``data`` (empty when it reads the whole
    image), or None when the system has no libpng16."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("png16")
    if name is None:
        return None

    class Image(ctypes.Structure):  # png_image of png.h, version 1
        _fields_ = [
            ("opaque", ctypes.c_void_p),
            ("version", ctypes.c_uint32),
            ("width", ctypes.c_uint32),
            ("height", ctypes.c_uint32),
            ("format", ctypes.c_uint32),
            ("flags", ctypes.c_uint32),
            ("colormap_entries", ctypes.c_uint32),
            ("warning_or_error", ctypes.c_uint32),
            ("message", ctypes.c_char * 64),
        ]

    lib = ctypes.CDLL(name)
    image = Image(version=1)
    buffer = ctypes.create_string_buffer(data, len(data))
    pointer = ctypes.byref(image)
    if not lib.png_image_begin_read_from_memory(pointer, buffer, ctypes.c_size_t(len(data))):
        return image.message.decode(errors="replace") or "refused"
    image.format = 3  # RGBA, 8 bits a sample
    out = ctypes.create_string_buffer(4 * image.width * image.height)
    ok = lib.png_image_finish_read(pointer, None, out, 0, None)
    message = image.message.decode(errors="replace")
    lib.png_image_free(pointer)
    return "" if ok and not image.warning_or_error & 2 else message or "refused"


LIBPNG_REFUSES = [
    (_with_chunk(_chunk(b"ABCD", b"x")), "unknown critical chunk ABCD"),
    (_with_chunk(_chunk(b"a1b2", b"x")), "not four ASCII letters"),
    (_with_chunk(_chunk(b"ab d", b"x")), "not four ASCII letters"),
    (_with_chunk(_chunk(b"IHDR", struct.pack(">IIBBBBB", 4, 4, 8, 0, 0, 0, 0))), "a second IHDR"),
    (_with_chunk(_chunk(b"PLTE", bytes(48)), PALETTE_4X4), "a second PLTE"),
    (PALETTE_4X4[:33] + _chunk(b"PLTE", bytes(47)) + PALETTE_4X4[33 + 60 :], "47 bytes"),
    (PALETTE_4X4[:33] + _chunk(b"PLTE", b"") + PALETTE_4X4[33 + 60 :], "0 bytes"),
    (PALETTE_4X4[:33] + _chunk(b"PLTE", bytes(900)) + PALETTE_4X4[33 + 60 :], "900 bytes"),
    (_png((1000001, 1, 8, 0, 0, 0, 0), b"\0" * 100), "each side"),
    (_png((1, 1000001, 8, 0, 0, 0, 0), b"\0" * 100), "each side"),
]
"""PNG files Pillow decodes but libpng, the reader of most viewers, refuses, with what
:func:`png_problem` says of each."""


@pytest.mark.parametrize("data, why", LIBPNG_REFUSES, ids=[
    "critical-unknown", "name-digits", "name-space", "ihdr-twice", "plte-twice",
    "plte-not-3", "plte-empty", "plte-over-256", "wide", "tall",
])  # fmt: skip
def test_a_png_libpng_refuses_is_refused_though_pillow_shows_it(data, why):
    assert why in png_problem(data), png_problem(data)


def test_libpng_refuses_the_forged_pngs_and_reads_the_good_ones():
    """The witness for the cases above: libpng itself (skipped without libpng16)."""
    if _libpng_problem(_plain(4, 4, 8, 0, 4)) is None:
        pytest.skip("no libpng16 on this system")
    assert _libpng_problem(_plain(4, 4, 8, 0, 4)) == ""
    assert _libpng_problem(PALETTE_4X4) == ""
    assert _libpng_problem((DOCS / "sweeps" / "link.png").read_bytes()) == ""
    for data, why in LIBPNG_REFUSES:
        assert _libpng_problem(data), why


def test_a_png_of_many_tiny_chunks_is_refused_quickly():
    data = _plain(4, 4, 8, 0, 4)
    many = data[:33] + _chunk(b"tEXt", b"a\0b") * 20000 + data[33:]
    assert "more than 16384 chunks" in png_problem(many)


def test_the_idat_rebuilder_keeps_a_good_png_good():
    good = (DOCS / "sweeps" / "link.png").read_bytes()
    assert png_problem(_with_idat(good, _idat(good))) == ""


@pytest.mark.parametrize(
    "damage, why",
    [
        (_cut, "cut short"),
        (_signature_only, "cut short"),
        (_no_iend, "no IEND"),
        (_flipped, "fails its CRC"),
        (_trailing, "after its IEND"),
        (_no_ihdr, "not a 13-byte IHDR"),
        (_long_chunk, "runs past the end"),
        (_stream_damaged_crc_recomputed, "pixel data"),
        (_too_few_pixels, "pixel data is not the"),
        (_too_many_pixels, "pixel data is not the"),
    ],
    ids=["cut-at-100-bytes", "signature-only", "no-iend", "flipped-byte", "trailing-bytes",
         "no-ihdr", "chunk-longer-than-file", "stream-damaged-crc-recomputed",
         "too-few-pixels", "too-many-pixels"],
)  # fmt: skip
def test_a_png_cut_short_or_damaged_is_refused_and_the_old_figure_kept(
    tmp_path, capsys, damage, why
):
    study = make_study(tmp_path)
    good = (DOCS / "sweeps" / "link.png").read_bytes()  # a figure matplotlib wrote
    assert png_problem(good) == ""
    study.image.parent.mkdir(parents=True)
    study.image.write_bytes(good)
    (study.figures / study.name / "convergence.png").write_bytes(damage(good))
    args = [study.name, "--figures", str(study.figures), "--docs", str(study.docs)]
    assert sp.main(args) == 2
    err = capsys.readouterr().err
    assert "not a PNG image" in err and why in err and len(err.strip().splitlines()) == 1, err
    assert study.image.read_bytes() == good
    assert not study.page.exists() and not study.data.exists()


@pytest.mark.parametrize(
    "kind, why",
    [
        ("fifo", "a FIFO"),
        ("device", "a character device"),
        ("not-utf8", "not utf-8 text"),
        ("huge", "more than the"),
        ("bad-front-matter", "front matter is not YAML"),
    ],
)
def test_a_template_that_is_not_a_readable_utf8_file_is_refused_in_one_line(
    tmp_path, capsys, kind, why
):
    study = make_study(tmp_path)
    template = study.template
    if kind == "fifo":
        template.unlink()
        os.mkfifo(template)  # an open() for reading would wait for a writer
    elif kind == "device":
        template.unlink()
        template.symlink_to("/dev/zero")  # endless
    elif kind == "not-utf8":
        template.write_bytes(TEMPLATE.encode() + b"\xff\xfe")
    elif kind == "huge":
        template.write_text(TEMPLATE + "x" * (2 << 20))
    else:
        template.write_text("---\ntable: [unclosed\n---\n# A study\n")
    args = [study.name, "--figures", str(study.figures), "--docs", str(study.docs)]
    with Unblocker(template, after_s=5.0) as watchdog:
        code = sp.main(args)
    assert not watchdog.used, "the template was opened as a FIFO and waited on"
    err = capsys.readouterr().err
    assert code == 2 and why in err and len(err.strip().splitlines()) == 1, err
    assert str(template) in err
    assert not study.page.exists() and not study.data.exists() and not study.image.exists()


@pytest.mark.parametrize(
    "preset, why",
    [
        ("fifo", "a FIFO"),
        (b"analysis: {figure: [unclosed\n", "not a YAML preset"),
        (b"- a list\n", "not a preset"),
        (b"analysis: \xff\n", "not utf-8 text"),
    ],
    ids=["fifo", "bad-yaml", "not-a-mapping", "not-utf8"],
)
def test_a_preset_that_is_not_a_readable_yaml_mapping_is_refused_in_one_line(tmp_path, preset, why):
    path = tmp_path / "conf" / "experiment" / "mine.yaml"
    path.parent.mkdir(parents=True)
    if preset == "fifo":
        os.mkfifo(path)
    else:
        path.write_bytes(preset)
    with Unblocker(path, after_s=5.0) as watchdog:
        with pytest.raises(sp.PageError) as refused:
            declared_figure("mine", tmp_path / "conf")
    assert not watchdog.used
    assert why in str(refused.value) and "\n" not in str(refused.value)


def test_nothing_is_written_when_any_study_asked_for_is_refused(tmp_path, capsys):
    good = make_study(tmp_path, name="first")  # renders alone
    (good.figures / "second").mkdir()
    (good.figures / "second" / "sweep_aggregated.csv").write_bytes(b"law,jobs\r\n")  # refused
    (good.docs / "studies" / "second.in.md").write_text(TEMPLATE)
    args = ["first", "second", "--figures", str(good.figures), "--docs", str(good.docs)]
    assert sp.main(args) == 2
    assert "second" in capsys.readouterr().err
    assert not good.page.exists() and not good.data.exists() and not good.image.exists()
    assert sp.main(args[:1] + args[2:]) == 0 and good.page.exists()


def test_censored_times_read_never_beyond_the_run_or_their_interval():
    row = {"law": "a", "t_mean": "inf", "t_ci_low": "inf", "t_ci_high": "inf", "t_n": "0"}
    points = sp.Points([row])
    assert sp.with_ci(points, row, "t", ".2g", "n/a") == "never"  # no seed reached it
    some = {**row, "t_n": "1"}  # one of several seeds: the median lies beyond the run
    assert sp.with_ci(points, some, "t", ".2g", "n/a") == "beyond the run"
    half = {"law": "a", "t_mean": "3", "t_ci_low": "3", "t_ci_high": "inf", "t_n": "1"}
    assert sp.with_ci(points, half, "t", ".2g", "n/a") == "3 (3 to beyond the run)"
    finite = {"law": "a", "t_mean": "2", "t_ci_low": "1", "t_ci_high": "4", "t_n": "2"}
    assert sp.with_ci(points, finite, "t", ".2g", "n/a") == "2 (1 to 4)"
